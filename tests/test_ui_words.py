"""Every menu path that VP-FFD's words give a user ("Bake > Use Live Solve", "Add > VP-FFD Cage")
names panels, menus and buttons that exist: each step is a label VP-FFD draws (a panel's or
operator's `bl_label`, a `text=` of a layout call, a property's name) or one of Blender's own menus.
Read from the sources (no Blender needed); docstrings are for developers and are left out."""
import ast
import os
import re

import pytest

pytestmark = pytest.mark.core

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SOURCES = sorted(os.path.join(ROOT, "operators", n) for n in os.listdir(os.path.join(ROOT, "operators"))
                 if n.endswith(".py"))
#: Blender's own menus and panels that VP-FFD's words lead through.
BLENDER = {"Add", "Lattice", "Preferences", "File Paths", "Temporary Files", "Object", "Apply"}
PATH = re.compile(r"[^()>]+?(?: > [A-Z][^()>.,:;]*)+")   # steps after the first are capitalised


def _docstrings(tree):
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                out.add(id(body[0].value))
    return out


def _labels_and_words():
    labels, words = set(BLENDER), []
    for path in SOURCES:
        with open(path) as fh:
            tree = ast.parse(fh.read())
        skip = _docstrings(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "bl_label" for t in node.targets) \
                    and isinstance(node.value, ast.Constant):
                labels.add(node.value.value)
            if isinstance(node, ast.Call):
                for kw in node.keywords:
                    if kw.arg in ("text", "name") and isinstance(kw.value, ast.Constant) \
                            and isinstance(kw.value.value, str) and kw.value.value:
                        labels.add(kw.value.value)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
                words.append((os.path.basename(path), node.lineno, node.value))
    return labels, words


def _steps(text):
    """The menu paths in `text`, each as its list of steps."""
    return [[s.strip() for s in m.group(0).split(" > ")] for m in PATH.finditer(text)]


def _named(step, labels, first):
    """Whether `step` (a path's first step: its end; a later one: its start) is a label."""
    words = step.split()
    pieces = [" ".join(words[k:]) for k in range(len(words))] if first else \
        [" ".join(words[:k]) for k in range(len(words), 0, -1)]
    return any(p in labels for p in pieces)


def test_the_check_reads_paths_as_a_user_does():
    labels = {"Bake", "Use Live Solve", "Add", "VP-FFD Cage"}
    assert _steps("h > 0u and weight > 0") == []
    for good in ("Bake > Use Live Solve switches back", "a cage (Add > VP-FFD Cage)"):
        (steps,) = _steps(good)
        assert all(_named(s, labels, k == 0) for k, s in enumerate(steps)), good
    for bad in ("Bake > Use Live switches back", "Baking > Use Live Solve"):
        (steps,) = _steps(bad)
        assert not all(_named(s, labels, k == 0) for k, s in enumerate(steps)), bad


def test_every_menu_path_in_the_panel_and_messages_names_what_exists():
    labels, words = _labels_and_words()
    assert {"Bake", "Use Live Solve", "Re-bind", "Unbind", "VP-FFD Cage"} <= labels
    wrong = []
    seen = 0
    for where, line, text in words:
        for steps in _steps(text):
            seen += 1
            if not all(_named(s, labels, k == 0) for k, s in enumerate(steps)):
                wrong.append(f"{where}:{line}: {' > '.join(steps)}")
    assert seen >= 3, "the sources name menu paths; none was found"
    assert not wrong, wrong


def _tooltips():
    """(file, line, text) of every tooltip VP-FFD gives: properties' and enum items'
    descriptions, and operators' docstrings (Blender shows them on hover)."""
    out = []
    for path in SOURCES:
        with open(path) as fh:
            tree = ast.parse(fh.read())
        name = os.path.basename(path)
        for node in ast.walk(tree):
            if isinstance(node, ast.Call):
                for kw in node.keywords:
                    if kw.arg == "description" and isinstance(kw.value, ast.Constant):
                        out.append((name, node.lineno, kw.value.value))
                    if kw.arg == "items" and isinstance(kw.value, (ast.List, ast.Tuple)):
                        out.extend((name, el.lineno, el.elts[2].value) for el in kw.value.elts
                                   if isinstance(el, ast.Tuple) and len(el.elts) >= 3
                                   and isinstance(el.elts[2], ast.Constant))
            if isinstance(node, ast.ClassDef) and any(getattr(b, "attr", "") == "Operator" for b in node.bases):
                doc = ast.get_docstring(node)
                if doc:
                    out.append((name, node.lineno, doc))
    return out


def test_tooltips_are_one_or_two_plain_sentences():
    """A tooltip is read while hovering: at most two sentences and 35 words (the details belong
    in docs/user-guide.md)."""
    tips = _tooltips()
    assert len(tips) >= 30, "the sources hold tooltips; too few were found"
    long = [f"{where}:{line}: {len(text.split())} words" for where, line, text in tips
            if len(text.split()) > 35 or len(re.findall(r"[.!?](?:\s|$)", text.strip())) > 2]
    assert not long, long


def _compared_with_a_constant(tree):
    """Lines of f-strings that show a comparison with a value filled in ("(< {LIMIT})"): a
    developer's notation, not a user's words."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            parts = node.values
            for a, b in zip(parts, parts[1:]):
                if isinstance(a, ast.Constant) and isinstance(b, ast.FormattedValue) \
                        and a.value.rstrip().endswith(("<", ">", "<=", ">=")):
                    found.append(node.lineno)
    return found


def test_messages_use_words_not_comparisons():
    assert _compared_with_a_constant(ast.parse('f"Auto: {n} vertices (< {LIMIT}) are faster"'))
    assert not _compared_with_a_constant(ast.parse('f"a mesh of {n} vertices solves faster there"'))
    wrong = []
    for path in SOURCES:
        with open(path) as fh:
            wrong += [f"{os.path.basename(path)}:{line}" for line in _compared_with_a_constant(ast.parse(fh.read()))]
    assert not wrong, wrong
