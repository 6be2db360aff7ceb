"""The README's pictures stay small enough to load quickly on a repository's front page: together
under 3 MB, each one present, and the window screenshots saved with the palette that
`./dev screenshots` gives them (tests/e2e/screenshots.py)."""
import os
import re

import pytest

from tests.e2e import screenshots

# With the Blender environments (they have Pillow, which Debian's core-only Python lacks).
pytestmark = pytest.mark.blender

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LIMIT = 3_000_000        # bytes, all the README's pictures together
PICTURE = re.compile(r"""!\[[^\]]*\]\(([^)\s]+)|<img\s[^>]*src=["']([^"']+)""")


def readme_pictures(readme=os.path.join(ROOT, "README.md")):
    """Paths (relative to the repository) of the local pictures the README shows, in order."""
    with open(readme, encoding="utf-8") as fh:
        text = fh.read()
    found = [a or b for a, b in PICTURE.findall(text)]
    return [p for p in dict.fromkeys(found) if "://" not in p]


def test_the_readme_shows_its_pictures_from_the_repository():
    pictures = readme_pictures()
    assert any(p.startswith("docs/window_") for p in pictures), pictures
    missing = [p for p in pictures if not os.path.isfile(os.path.join(ROOT, p))]
    assert not missing


def test_the_readme_pictures_stay_under_3_mb():
    sizes = {p: os.path.getsize(os.path.join(ROOT, p)) for p in readme_pictures()}
    largest = sorted(sizes.items(), key=lambda kv: -kv[1])[:5]
    assert sum(sizes.values()) < LIMIT, f"{sum(sizes.values())} bytes; largest: {largest}"


def test_window_screenshots_are_saved_with_a_palette():
    from PIL import Image
    for path in readme_pictures():
        if os.path.basename(path).startswith("window_"):
            with Image.open(os.path.join(ROOT, path)) as im:
                assert im.mode == "P", f"{path}: save it with screenshots.save_for_readme"


def test_saving_for_the_readme_keeps_the_picture_within_its_palette(tmp_path):
    """What ./dev screenshots does to a full-colour picture (here a demo's rendered contact sheet,
    thousands of colours): a palette of at most COLOURS colours, pixels within a few levels of
    their colours on average (the screenshots measured 2.9 to 3.1 of 255), a smaller file; and
    saving it again changes nothing."""
    from PIL import Image
    import numpy as np
    full = tmp_path / "full.png"
    with Image.open(os.path.join(ROOT, "docs", "cube_contact_sheet.jpg")) as im:
        im.convert("RGB").save(full)
    shot = screenshots.save_for_readme(str(full), str(tmp_path / "shot.png"))
    with Image.open(full) as a, Image.open(shot) as b:
        assert len(a.getcolors(1 << 24)) > 10 * screenshots.COLOURS
        assert b.mode == "P" and len(b.getcolors(screenshots.COLOURS + 1)) <= screenshots.COLOURS
        diff = np.abs(np.asarray(a, np.int16) - np.asarray(b.convert("RGB"), np.int16))
    assert diff.mean() < 4
    assert os.path.getsize(shot) < os.path.getsize(full)
    before = open(shot, "rb").read()
    screenshots.save_for_readme(shot, shot)
    assert open(shot, "rb").read() == before
