"""`./dev screenshots`: run the window session (gui_session.py) and keep its screenshots of the
real Blender window in docs/ (window_panel.png, window_overlay.png, window_editmode.png,
window_bake.png, window_fit.png, window_arm.png), for the README and docs/user-guide.md. Exits non-zero when a check of the session fails.

    ./dev screenshots              # the window session, then its screenshots into docs/
    ./dev screenshots --existing   # only save docs/window_*.png again as the session's are saved

The screenshots are saved with an adaptive palette (see `save_for_readme`), so that the pictures
stay small enough to load quickly (tests/test_readme_pictures.py checks the README's total)."""
import glob
import os
import sys

from . import blender_chroot as bc
from . import gui_window as gw

DOCS = os.path.join(bc.REPO_ROOT, "docs")
#: Colours of the palette. Blender's interface is flat greys and text; the viewport's shading is
#: what needs colours. Pillow's fast octree keeps that shading smoother than its median cut (which
#: bands highlights) and gives a PNG about a quarter of the full-colour one's size.
COLOURS = 256


def save_for_readme(src, target):
    """Write the screenshot `src` to `target` (which may be `src`) as a PNG with an adaptive
    palette of COLOURS colours; returns `target`."""
    from PIL import Image
    with Image.open(src) as im:
        im.load()
        # A palette picture keeps its palette: quantising it again would merge a few more
        # colours on every run.
        reduced = im if im.mode == "P" else \
            im.convert("RGB").quantize(colors=COLOURS, method=Image.Quantize.FASTOCTREE)
    part = target + ".part.png"
    reduced.save(part, optimize=True)
    os.replace(part, target)
    return target


def save_existing():
    """Save the screenshots already in docs/ again with `save_for_readme` (without Blender)."""
    for path in sorted(glob.glob(os.path.join(DOCS, "window_*.png"))):
        before = os.path.getsize(path)
        save_for_readme(path, path)
        print(f"screenshots: {os.path.relpath(path, bc.REPO_ROOT)}  {before} -> "
              f"{os.path.getsize(path)} bytes")
    return 0


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv == ["--existing"]:
        return save_existing()
    if argv:
        print(__doc__, file=sys.stderr)
        return 2
    results, shots, work = gw.run_session()
    try:
        failed = [c for c in results["checks"] if not c[1]]
        for name, path in sorted(shots.items()):
            target = save_for_readme(path, os.path.join(DOCS, f"window_{name}.png"))
            print(f"screenshots: {os.path.relpath(target, bc.REPO_ROOT)}")
        for name, _, detail in failed:
            print(f"screenshots: check failed: {name}: {detail}", file=sys.stderr)
        if results["error"]:
            print(results["error"], file=sys.stderr)
        return 1 if failed or results["error"] else 0
    finally:
        bc.remove_workdir(work)


if __name__ == "__main__":
    sys.exit(main())
