"""The README's pictures stay small enough to load quickly on a repository's front page: together
under 3 MB, each one present, and the window screenshots, wherever a page shows them (the README,
docs/*.md), saved with the palette that `./dev screenshots` gives them (tests/e2e/screenshots.py)."""
import glob
import os
import re

import pytest

from tests.e2e import screenshots

# With the Blender environments (they have Pillow, which Debian's core-only Python lacks).
pytestmark = pytest.mark.blender

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README = os.path.join(ROOT, "README.md")
LIMIT = 3_000_000        # bytes, all the README's pictures together
PICTURE = re.compile(r"""!\[[^\]]*\]\(([^)\s]+)|<img\s[^>]*src=["']([^"']+)""")


def readme_pictures(readme=README):
    """Paths (relative to the repository) of the local pictures a page shows, in order."""
    with open(readme, encoding="utf-8") as fh:
        text = fh.read()
    found = [a or b for a, b in PICTURE.findall(text)]
    here = os.path.relpath(os.path.dirname(os.path.abspath(readme)), ROOT)
    return [os.path.normpath(os.path.join(here, p)).replace(os.sep, "/")
            for p in dict.fromkeys(found) if "://" not in p]


def every_page_picture():
    """The local pictures of the README and of every page in docs/."""
    pages = [README] + sorted(glob.glob(os.path.join(ROOT, "docs", "*.md")))
    return list(dict.fromkeys(p for page in pages for p in readme_pictures(page)))


def test_the_readme_shows_its_pictures_from_the_repository():
    pictures = readme_pictures()
    assert any(p.startswith("docs/window_") for p in pictures), pictures
    assert any(p.endswith(".gif") for p in pictures), pictures      # something moves on the front page
    missing = [p for p in pictures if not os.path.isfile(os.path.join(ROOT, p))]
    assert not missing


def test_a_page_in_docs_names_its_pictures_relative_to_itself():
    pictures = readme_pictures(os.path.join(ROOT, "docs", "user-guide.md"))
    assert "docs/window_panel.png" in pictures, pictures


def test_the_readme_pictures_stay_under_3_mb():
    sizes = {p: os.path.getsize(os.path.join(ROOT, p)) for p in readme_pictures()}
    largest = sorted(sizes.items(), key=lambda kv: -kv[1])[:5]
    assert sum(sizes.values()) < LIMIT, f"{sum(sizes.values())} bytes; largest: {largest}"


def test_window_screenshots_are_saved_with_a_palette():
    from PIL import Image
    shots = [p for p in every_page_picture() if os.path.basename(p).startswith("window_")]
    assert len(shots) >= 6, shots
    for path in shots:
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
