"""The project's own imports form no circle (read with `ast`, imports inside functions included):
every module of `vpffd_addon/` and `operators/` is a node; `from . import x`, `from .x import y`,
`from .. import vpffd_addon` and `from ..vpffd_addon.x import y` are edges. `operators/__init__.py`
only registers its submodules, so it is left out."""
import ast
import os

import pytest

pytestmark = pytest.mark.core

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGES = ("vpffd_addon", "operators")
LEFT_OUT = {"operators"}       # the package __init__ that only registers the submodules


def _modules():
    """{module name ("vpffd_addon.binding", "vpffd_addon" for an __init__): path}."""
    out = {}
    for pkg in PACKAGES:
        for fn in sorted(os.listdir(os.path.join(ROOT, pkg))):
            if fn.endswith(".py"):
                name = pkg if fn == "__init__.py" else f"{pkg}.{fn[:-3]}"
                out[name] = os.path.join(ROOT, pkg, fn)
    return out


def _edges(name, path, modules):
    package = name if path.endswith("__init__.py") else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(open(path, encoding="utf-8").read(), path)):
        if not isinstance(node, ast.ImportFrom) or node.level == 0:
            continue
        base = package.split(".")
        base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
        if node.level > len(package.split(".")):
            base = []                                   # above our packages: the repository root
        target = ".".join(base + ([node.module] if node.module else []))
        for alias in node.names:
            sub = f"{target}.{alias.name}" if target else alias.name
            # `from . import x` names module x; any other name comes from the module `target`.
            found.add(sub if sub in modules else target)
    found &= set(modules)
    return found - {name}


def _graph():
    modules = _modules()
    return {name: _edges(name, path, modules) for name, path in modules.items() if name not in LEFT_OUT}


def _cycle(graph):
    """One import circle as a list of modules, or None."""
    state = {}

    def visit(node, stack):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt, stack)
                if found:
                    return found
        state[node] = "done"
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node, [])
            if found:
                return found
    return None


def test_the_project_has_no_import_circle():
    graph = _graph()
    assert len(graph) > 20 and graph["operators.update"], "the walk found the modules and their imports"
    cycle = _cycle(graph)
    assert cycle is None, "import circle: " + " -> ".join(cycle)


def test_the_walk_sees_imports_inside_functions(tmp_path):
    """The checker itself: a circle closed only by an import inside a function is found."""
    graph = {"a": {"b"}, "b": set()}
    assert _cycle(graph) is None
    src = "def f():\n    from .a import x\n"
    path = tmp_path / "b.py"
    path.write_text(src)
    graph["b"] = _edges("pkg.b", str(path), {"pkg.a", "pkg.b"})
    assert graph["b"] == {"pkg.a"}
    assert _cycle({"pkg.a": {"pkg.b"}, "pkg.b": graph["b"]}) is not None


def test_the_core_never_imports_blender():
    for name, path in _modules().items():
        if name.startswith("vpffd_addon"):
            tree = ast.parse(open(path, encoding="utf-8").read(), path)
            for node in ast.walk(tree):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
                assert not any(n.split(".")[0] in ("bpy", "gpu", "mathutils", "bmesh") for n in names), name


def test_the_layout_table_names_every_module():
    """Every module is named in docs/development.md's *Repository layout* or in
    docs/architecture.md's table of modules (the flow of a frame module by module)."""
    text = open(os.path.join(ROOT, "docs", "development.md"), encoding="utf-8").read()
    table = text[text.index("## Repository layout"):]
    doc = open(os.path.join(ROOT, "docs", "architecture.md"), encoding="utf-8").read()
    table += doc[doc.index("## Modules"):]
    import re
    missing = [name for name in _modules() if name not in PACKAGES
               and not re.search(r"[`/]" + re.escape(name.split(".")[1]) + r"\.py`", table)]
    assert not missing, missing
