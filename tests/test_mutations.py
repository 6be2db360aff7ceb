"""`./dev mutate` breaks the product by replacing an exact piece of source text (tests/mutate.py);
a mutation whose text the code no longer holds would stop with an error when run, long after the
change that moved the text. Here every mutation's text is found in its file exactly once, and each
is named in docs/testing.md's table, on every run of the core layer."""
import os

import pytest

from tests.mutate import MUTATIONS

pytestmark = pytest.mark.core

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.parametrize("name", sorted(MUTATIONS))
def test_the_mutation_finds_its_text_once(name):
    path, old, new, _, _ = MUTATIONS[name]
    if path is None:
        return              # not a text edit (bpy missing)
    with open(os.path.join(ROOT, path), encoding="utf-8") as fh:
        text = fh.read()
    assert text.count(old) == 1, f"{name}: its text is in {path} {text.count(old)} times"
    assert new != old


def test_every_mutation_is_in_the_testing_page():
    with open(os.path.join(ROOT, "docs", "testing.md"), encoding="utf-8") as fh:
        page = fh.read()
    missing = [name for name in MUTATIONS if f"`{name}`" not in page]
    assert not missing, missing
