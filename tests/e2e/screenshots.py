"""`./dev screenshots`: run the window session (gui_session.py) and keep its screenshots of the
real Blender window in docs/ (window_panel.png, window_overlay.png, window_editmode.png,
window_bake.png, window_fit.png, window_arm.png), for the README. Exits non-zero when a check of the session fails."""
import os
import shutil
import sys

from . import blender_chroot as bc
from . import gui_window as gw

DOCS = os.path.join(bc.REPO_ROOT, "docs")


def main():
    results, shots, work = gw.run_session()
    try:
        failed = [c for c in results["checks"] if not c[1]]
        for name, path in sorted(shots.items()):
            target = os.path.join(DOCS, f"window_{name}.png")
            shutil.copyfile(path, target)
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
