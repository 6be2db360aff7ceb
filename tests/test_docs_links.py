"""Every link of the documentation leads somewhere: in README.md and docs/*.md, each relative link
and picture names a file of the repository, and each `#anchor` (on the same page or
`page.md#anchor`) names a heading of its page, slugged as GitHub does (lower case, spaces to `-`,
punctuation dropped but `-` and `_`, a repeated heading numbered `-1`, `-2`, ...). External
http(s) links are not fetched (the tests have no network), only checked to be well formed. Code
(fenced blocks and `inline`) holds no links."""
import glob
import os
import re
from urllib.parse import unquote, urlparse

import pytest

pytestmark = pytest.mark.core

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
INLINE_CODE = re.compile(r"(`+)(.+?)\1")
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
HTML_LINK = re.compile(r"""<(?:img|a)\s[^>]*?(?:src|href)=["']([^"']+)["']""", re.IGNORECASE)
COMMENT = re.compile(r"<!--.*?-->", re.DOTALL)


def pages(root=ROOT):
    """The README and every page in docs/, as absolute paths."""
    return [os.path.join(root, "README.md")] + sorted(glob.glob(os.path.join(root, "docs", "*.md")))


def _prose_lines(text):
    """(line number, line) of `text` outside fenced code blocks and HTML comments."""
    text = COMMENT.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    fenced = False
    for n, line in enumerate(text.split("\n"), 1):
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            yield n, line


def slug(heading):
    """GitHub's anchor for a heading's markdown text."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)     # a link or picture: its text
    text = INLINE_CODE.sub(lambda m: m.group(2), text)
    text = re.sub(r"<[^>]+>", "", text).replace("*", "")
    text = re.sub(r"[^\w\- ]", "", text.strip().lower())
    return text.replace(" ", "-")


def anchors(path):
    """The anchors of the headings of the page at `path`."""
    seen, out = {}, set()
    with open(path, encoding="utf-8") as fh:
        for _, line in _prose_lines(fh.read()):
            m = HEADING.match(line)
            if m:
                base = slug(m.group(2))
                k = seen.get(base, 0)
                seen[base] = k + 1
                out.add(base if k == 0 else f"{base}-{k}")
    return out


def links(path):
    """(line number, target) of every link and picture of the page at `path`, code left out."""
    with open(path, encoding="utf-8") as fh:
        text = fh.read()
    for n, line in _prose_lines(text):
        line = INLINE_CODE.sub("", line)
        for m in LINK.finditer(line):
            yield n, m.group(1)
        for m in HTML_LINK.finditer(line):
            yield n, m.group(1)


def broken(path, root=ROOT):
    """Words for every link of the page at `path` that leads nowhere."""
    out, where = [], os.path.relpath(path, root)
    for n, target in links(path):
        if not target:
            out.append(f"{where}:{n}: an empty link")
            continue
        url = urlparse(target)
        if url.scheme in ("http", "https"):
            if not url.netloc or " " in target:
                out.append(f"{where}:{n}: {target}: not a well-formed URL")
            continue
        if url.scheme or target.startswith("//"):
            out.append(f"{where}:{n}: {target}: only http(s) and relative links are expected")
            continue
        file_part, _, anchor = target.partition("#")
        dest = os.path.normpath(os.path.join(os.path.dirname(path), unquote(file_part))) if file_part else path
        if not os.path.exists(dest):
            out.append(f"{where}:{n}: {target}: no such file")
            continue
        if not os.path.abspath(dest).startswith(os.path.abspath(root) + os.sep):
            out.append(f"{where}:{n}: {target}: outside the repository")
            continue
        if anchor:
            if not dest.endswith(".md"):
                out.append(f"{where}:{n}: {target}: an anchor into a file that is not a page")
            elif unquote(anchor) not in anchors(dest):
                out.append(f"{where}:{n}: {target}: no heading '#{anchor}' on "
                           f"{os.path.relpath(dest, root)}")
    return out


def test_every_page_is_checked():
    names = {os.path.relpath(p, ROOT) for p in pages()}
    assert {"README.md", "docs/user-guide.md", "docs/render-farms.md", "docs/library.md",
            "docs/development.md", "docs/testing.md", "docs/design.md"} <= names, names
    assert len(list(links(pages()[0]))) > 20          # the README's links are read


@pytest.mark.parametrize("page", pages(), ids=lambda p: os.path.relpath(p, ROOT))
def test_every_link_leads_somewhere(page):
    assert not broken(page)


def test_slugs_are_githubs():
    assert slug("Render farms (Flamenco, Deadline)") == "render-farms-flamenco-deadline"
    assert slug("A studio's extensions repository") == "a-studios-extensions-repository"
    assert slug("A. Install the extension on every worker") == "a-install-the-extension-on-every-worker"
    assert slug("`./dev mutate`") == "dev-mutate"
    assert slug("Bent arm (Armature, Target: Bind)") == "bent-arm-armature-target-bind"
    assert slug("snake_case and x-y") == "snake_case-and-x-y"


def test_a_broken_link_is_found(tmp_path):
    """The check goes red: a missing file, a missing heading on the same page and on another, a
    malformed URL; while code, a good anchor and a repeated heading's anchor pass."""
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "other.md").write_text("# Other\n\n## Same\n\n## Same\n")
    (tmp_path / "README.md").write_text(
        "# Top\n\n## Part one\n\n[ok](#part-one) [ok](docs/other.md#same-1) ![pic](docs/gone.png)\n"
        "[bad](#part-two) [bad](docs/other.md#nowhere) [bad](https:///x)\n"
        "`[in code](missing.md)`\n\n```\n[in a block](missing.md)\n```\n")
    found = broken(str(tmp_path / "README.md"), root=str(tmp_path))
    assert len(found) == 4, found
    assert any("gone.png" in f for f in found) and any("#part-two" in f for f in found)
    assert any("#nowhere" in f for f in found) and any("https:///x" in f for f in found)
