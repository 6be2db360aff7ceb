"""Build, validate and install the VP-FFD extension with Blender's own tools, headless (no `blender`).

Everything here works from the bpy wheel alone:

* Building and validating run the extension CLI that bpy ships,
  ``bpy/<X.Y>/scripts/addons_core/bl_pkg/cli/blender_ext.py``, with the test interpreter (it needs
  only the standard library). ``blender --command extension build|validate`` is this same script
  run with ``--valid-tags`` set to Blender's ``_bpy_internal/extensions/tags.py``; without that
  argument the CLI does not check tags, so it is always passed here::

      python <bpy>/<X.Y>/scripts/addons_core/bl_pkg/cli/blender_ext.py build \\
          --source-dir REPO --output-dir OUT \\
          --valid-tags <bpy>/<X.Y>/scripts/modules/_bpy_internal/extensions/tags.py
      python .../blender_ext.py validate --valid-tags .../tags.py REPO_OR_ZIP

  The builder honours the manifest's ``[build] paths_exclude_pattern`` (gitignore-style patterns).

* Installing uses Blender's own installer in the running bpy:
  ``bpy.ops.extensions.package_install_files(filepath=zip, repo='user_default',
  enable_on_install=True)``; the add-on's module is then ``bl_ext.user_default.<id>``.

BLENDER_USER_RESOURCES must be set before the first ``import bpy`` of the process. Blender reads
it at start-up to build the ``bl_ext.<repo>`` packages' ``__path__``. Set later, it still changes
``bpy.utils.user_resource()`` and the repositories' ``directory`` (which are computed on every call),
so the installer unpacks into the new folder, but enabling then fails with
``No module named 'bl_ext.user_default.vpffd'`` (bpy 4.2.23 and 5.0.1). Left unset, installs
land in ``~/.config/blender/<X.Y>/extensions``. Therefore:

* A pytest session that wants the extension in-process calls `isolate_user_resources()` from
  ``tests/conftest.py`` at import time, before any test module imports bpy. The session-scoped
  `installed_extension` fixture then installs once into that temporary folder.
* `probe_in_fresh_process` installs into a fresh interpreter with its own temporary
  BLENDER_USER_RESOURCES and reports what it found, so it works however the session was set up.

Resetting the scene between tests. ``bpy.ops.wm.read_factory_settings(use_empty=True)`` also resets
the preferences: it disables and unregisters every add-on that was enabled after start-up, this
extension included (its operators and ``Object`` properties disappear; ``addon_utils.check``
returns ``(False, False)``), in bpy 4.2.23 and 5.0.1. Use `reset_scene()`, which runs
``bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)``: it loads the factory
startup file with no objects, keeps the preferences, so the extension stays enabled and is not
re-registered. Non-``@persistent`` handlers are cleared by it as by any file load. After a
``read_factory_settings``, `ensure_enabled(module)` enables the extension again.

Note that the installed extension's core, ``bl_ext.user_default.vpffd.vpffd_addon``, is a different
module object from the repository's ``vpffd_addon`` that the core tests import; do not mix their
classes in ``isinstance`` checks.
"""
import atexit
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from typing import NamedTuple

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_REPO = "user_default"
ENV = "BLENDER_USER_RESOURCES"

# What the next milestone registers; `probe` reports which of them exist.
EXPECTED_OPERATORS = ("object.vpffd_bind", "object.vpffd_unbind", "object.vpffd_apply")
EXPECTED_OBJECT_POINTERS = ("vpffd",)


class ExtensionToolError(RuntimeError):
    """Blender's extension CLI failed; `messages` holds its (type, text) messages."""

    def __init__(self, what, messages, returncode):
        self.messages = list(messages)
        self.returncode = returncode
        text = "\n".join(f"  {kind}: {msg}" for kind, msg in self.messages) or "  (no output)"
        status = "" if returncode is None else f" (exit status {returncode})"
        super().__init__(f"{what} failed{status}:\n{text}")


class ExtensionBuildError(ExtensionToolError):
    pass


class ExtensionValidationError(ExtensionToolError):
    pass


# --------------------------------------------------------------------------------------------
# Blender's extension CLI, found inside the bpy package without importing bpy.

def bpy_package_dir():
    """The installed bpy package folder (``.../site-packages/bpy``); bpy is not imported."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("bpy is not installed in this interpreter")
    return list(spec.submodule_search_locations)[0]


def bpy_version_dir():
    """``.../bpy/<X.Y>``, the folder with Blender's scripts and data files."""
    root = bpy_package_dir()
    found = [d for d in os.listdir(root)
             if re.fullmatch(r"\d+\.\d+", d) and os.path.isdir(os.path.join(root, d))]
    if len(found) != 1:
        raise FileNotFoundError(f"expected one <major>.<minor> folder in {root}, found {found}")
    return os.path.join(root, found[0])


def blender_ext_cli():
    """Path of ``blender_ext.py``, the script behind ``blender --command extension``."""
    path = os.path.join(bpy_version_dir(), "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py")
    if not os.path.isfile(path):
        raise FileNotFoundError(path)
    return path


def blender_tags_file():
    """The tag list ``blender --command extension`` validates tags against."""
    path = os.path.join(bpy_version_dir(), "scripts", "modules", "_bpy_internal", "extensions", "tags.py")
    if not os.path.isfile(path):
        raise FileNotFoundError(path)
    return path


def run_extension_cli(*args, timeout=300):
    """Run ``blender_ext.py ARGS --output-type JSON`` with this interpreter.

    Returns ``(returncode, messages)`` where messages are ``(type, text)`` pairs such as
    ``("STATUS", "...")`` or ``("FATAL_ERROR", "...")``."""
    cmd = [sys.executable, blender_ext_cli(), *args, "--output-type", "JSON"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    messages = []
    for line in proc.stdout.splitlines():
        line = line.strip()
        if not line:
            continue
        try:
            kind, msg = json.loads(line)
        except (ValueError, TypeError):
            kind, msg = "OUTPUT", line
        messages.append((str(kind), msg if isinstance(msg, str) else json.dumps(msg)))
    if proc.stderr.strip():
        messages.append(("STDERR", proc.stderr.strip()))
    return proc.returncode, messages


def _failed(returncode, messages):
    return returncode != 0 or any(kind in ("ERROR", "FATAL_ERROR") for kind, _ in messages)


def read_manifest(repo_root=REPO_ROOT):
    with open(os.path.join(repo_root, "blender_manifest.toml"), "rb") as fh:
        return tomllib.load(fh)


# The builder's own exclusions when a manifest has no [build] table (blender_ext.py, both 4.2 and
# 5.0). A manifest that declares paths_exclude_pattern replaces this list, dot-files rule included.
BLENDER_DEFAULT_EXCLUDES = ("__pycache__/", ".*", "/*.zip", "*.blend[1-9]")


def _blender_ext_module():
    """bpy's blender_ext.py imported as a module (for its PathPatternMatch and directory walk)."""
    name = "_vpffd_blender_ext"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, blender_ext_cli())
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def planned_files(repo_root=REPO_ROOT):
    """Relative paths the builder will pack from `repo_root` (besides blender_manifest.toml),
    found with the builder's own pattern matcher and directory walk, without building.

    Mirrors the ``paths_exclude_pattern`` branch of blender_ext.py's build (symlinks are skipped
    there too); manifests with ``[build] paths`` are not handled."""
    ext = _blender_ext_module()
    build = read_manifest(repo_root).get("build", {})
    if "paths" in build:
        raise NotImplementedError("planned_files() does not handle [build] paths")
    matcher = ext.PathPatternMatch(list(build.get("paths_exclude_pattern", BLENDER_DEFAULT_EXCLUDES)))

    def keep(rel, is_dir):
        rel = rel.replace(os.sep, "/")
        if matcher.test_path(rel + "/" if is_dir else rel):
            return False
        return is_dir or rel.lower() != "blender_manifest.toml"

    return sorted(rel.replace(os.sep, "/") for _, rel in ext.scandir_recursive(repo_root, keep))


def build_extension_zip(repo_root, out_dir, max_bytes=64 * 2 ** 20):
    """Build the extension zip with Blender's own builder; returns the zip's path.

    Same as ``blender --command extension build --source-dir REPO_ROOT --output-filepath
    OUT_DIR/<id>-<version>.zip``: the manifest is validated (tags included) and
    ``[build] paths_exclude_pattern`` applied. First refuses (ExtensionBuildError, message kind
    PREFLIGHT) when the files the builder would pack exceed `max_bytes` (None: no limit): a
    working tree can hold caches, virtual environments or chroots that a too-narrow exclude list
    would otherwise zip."""
    repo_root = os.path.abspath(repo_root)
    out_dir = os.path.abspath(out_dir)
    if max_bytes is not None:
        sizes = {}
        for rel in planned_files(repo_root):
            top = rel.split("/")[0]
            sizes[top] = sizes.get(top, 0) + os.path.getsize(os.path.join(repo_root, rel))
        total = sum(sizes.values())
        if total > max_bytes:
            worst = sorted(sizes.items(), key=lambda kv: -kv[1])[:8]
            raise ExtensionBuildError(f"building {repo_root}", [(
                "PREFLIGHT", f"would pack {total} bytes (limit {max_bytes}); largest top-level "
                f"entries: {worst}; extend [build] paths_exclude_pattern in blender_manifest.toml")],
                None)
    os.makedirs(out_dir, exist_ok=True)
    manifest = read_manifest(repo_root)
    path = os.path.join(out_dir, f"{manifest['id']}-{manifest['version']}.zip")
    rc, messages = run_extension_cli(
        "build", "--source-dir", repo_root, "--output-filepath", path,
        "--valid-tags", blender_tags_file())
    if _failed(rc, messages) or not os.path.isfile(path):
        raise ExtensionBuildError(f"building {repo_root}", messages, rc)
    return path


def validate_manifest(path=REPO_ROOT):
    """Blender's own extension validation of a source folder or a built zip.

    Same as ``blender --command extension validate PATH``. Returns the CLI's message texts on
    success; raises `ExtensionValidationError` (with all messages) on failure."""
    rc, messages = run_extension_cli("validate", "--valid-tags", blender_tags_file(),
                                     os.path.abspath(path))
    if _failed(rc, messages):
        raise ExtensionValidationError(f"validating {path}", messages, rc)
    return [msg for _, msg in messages]


# --------------------------------------------------------------------------------------------
# Installing into a running bpy.

_ISOLATED = None  # the folder isolate_user_resources() set, if it did


def isolate_user_resources(path=None):
    """Point BLENDER_USER_RESOURCES at a private temporary folder for this process.

    Must run before the process's first ``import bpy`` (call it at import time of
    tests/conftest.py). Always overrides an inherited value, so tests never touch a real Blender
    configuration. The folder is removed at exit. Returns its path."""
    global _ISOLATED
    if _ISOLATED is not None and path is None:
        return _ISOLATED
    if "bpy" in sys.modules:
        raise RuntimeError(
            "isolate_user_resources() was called after bpy was imported; Blender reads "
            f"{ENV} only at start-up. Call it at the top of tests/conftest.py.")
    if path is None:
        path = tempfile.mkdtemp(prefix="vpffd-blender-user-")
        atexit.register(shutil.rmtree, path, True)
    os.makedirs(path, exist_ok=True)
    os.environ[ENV] = path
    _ISOLATED = path
    return path


def _repo(bpy, repo):
    for r in bpy.context.preferences.extensions.repos:
        if r.module == repo:
            return r
    raise KeyError(f"no extension repository with module name {repo!r}")


def user_resources_problem(repo=DEFAULT_REPO):
    """None when installing into `repo` in this process is safe and will work, else the reason."""
    value = os.environ.get(ENV)
    if not value:
        return (f"{ENV} is not set: installing would write into the real Blender configuration "
                "(~/.config/blender). Call extension_harness.isolate_user_resources() at the top "
                "of tests/conftest.py.")
    import bpy
    import importlib
    directory = os.path.realpath(_repo(bpy, repo).directory)
    package = importlib.import_module(f"bl_ext.{repo}")
    paths = [os.path.realpath(p) for p in package.__path__]
    if directory not in paths or not directory.startswith(os.path.realpath(value) + os.sep):
        return (f"bpy was imported before {ENV} was set to {value!r} (bl_ext.{repo} points at "
                f"{paths}, the repository at {directory!r}); the installed extension could not be "
                "imported. Call extension_harness.isolate_user_resources() at the top of "
                "tests/conftest.py, before anything imports bpy.")
    return None


def module_name(repo=DEFAULT_REPO, ext_id=None):
    return f"bl_ext.{repo}.{ext_id or read_manifest()['id']}"


def is_enabled(module):
    import bpy
    import addon_utils  # only importable once bpy is
    return addon_utils.check(module) == (True, True) and module in bpy.context.preferences.addons


def install_extension(zip_path, repo=DEFAULT_REPO):
    """Install and enable `zip_path` through Blender's installer in this bpy process.

    Requires BLENDER_USER_RESOURCES set before bpy was imported (see `isolate_user_resources`).
    Returns the add-on's module name, e.g. ``bl_ext.user_default.vpffd``, after checking that
    Blender reports it loaded and enabled."""
    problem = user_resources_problem(repo)
    if problem:
        raise RuntimeError(problem)
    import bpy
    ext_id = _zip_manifest(zip_path)["id"]
    result = bpy.ops.extensions.package_install_files(
        filepath=os.path.abspath(zip_path), repo=repo, enable_on_install=True)
    if result != {"FINISHED"}:
        raise RuntimeError(f"package_install_files returned {result}")
    module = module_name(repo, ext_id)
    if not is_enabled(module):
        raise RuntimeError(f"{module} was installed but is not enabled")
    return module


def ensure_enabled(module):
    """Enable `module` again if something (read_factory_settings) disabled it."""
    if is_enabled(module):
        return
    import bpy  # noqa: F401
    import addon_utils
    errors = []
    addon_utils.enable(module, default_set=True, handle_error=errors.append)
    if errors or not is_enabled(module):
        raise RuntimeError(f"could not enable {module}: {errors}")


def reset_scene():
    """Empty factory scene that keeps the preferences, so installed extensions stay enabled."""
    import bpy
    bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)


def _zip_manifest(zip_path):
    import zipfile
    with zipfile.ZipFile(zip_path) as zf:
        return tomllib.loads(zf.read("blender_manifest.toml").decode("utf-8"))


class InstalledExtension(NamedTuple):
    module_name: str       # "bl_ext.user_default.vpffd"
    module: object         # the enabled add-on module
    zip_path: str
    user_resources: str    # BLENDER_USER_RESOURCES of this process


_SESSION = {}


def installed_extension(tmp_path_factory, repo=DEFAULT_REPO):
    """Body of a session-scoped fixture: build the zip and install it into this process, once.

    Wire it in tests/conftest.py::

        from . import extension_harness as eh   # in tests/conftest.py (tests is a package)
        eh.isolate_user_resources()      # at import time, before anything imports bpy

        @pytest.fixture(scope="session")
        def installed_extension(tmp_path_factory):
            return eh.installed_extension(tmp_path_factory)

    Skips (with the reason) when bpy is missing or the session was not isolated. Re-enables the
    extension if a test disabled it (e.g. with read_factory_settings)."""
    import pytest
    pytest.importorskip("bpy")
    import importlib
    if repo in _SESSION:
        ext = _SESSION[repo]
        ensure_enabled(ext.module_name)
        return ext
    problem = user_resources_problem(repo)
    if problem:
        pytest.skip(problem)
    zip_path = build_extension_zip(REPO_ROOT, str(tmp_path_factory.mktemp("extension_zip")))
    module = install_extension(zip_path, repo=repo)
    ext = InstalledExtension(module, importlib.import_module(module), zip_path, os.environ[ENV])
    _SESSION[repo] = ext
    return ext


# --------------------------------------------------------------------------------------------
# Checks shared by the in-process tests and the fresh-process probe.

def core_smoke(vp):
    """Bind a small icosphere to a 3x3x3 lattice through the module `vp` (an installed
    ``...vpffd.vpffd_addon``); returns errors of the identity deformation and volumes."""
    import numpy as np
    verts, tris = vp.icosphere(1, radius=0.4)
    lat = vp.Lattice((3, 3, 3))
    binding = vp.bind(lat, verts, tris)
    rest = lat.rest_points
    identity = binding.solve(rest)
    squash = binding.solve(rest * np.array([1.3, 1.0, 0.7]))
    return {
        "n_verts": int(len(verts)),
        "deform_identity_err": float(np.abs(binding.deform(rest) - verts).max()),
        "solve_identity_err": float(np.abs(identity.verts - verts).max()),
        "rest_volume": float(binding.rest_volume),
        "squash_volume": float(squash.volume),
        "squash_plain_volume": float(squash.plain_volume),
    }


def registration_report(operators=EXPECTED_OPERATORS, pointers=EXPECTED_OBJECT_POINTERS):
    """Which of the expected operators and ``Object`` pointer properties are registered."""
    import bpy
    ops = {}
    for idname in operators:
        category, name = idname.split(".")
        ops[idname] = hasattr(bpy.types, f"{category.upper()}_OT_{name}")
    props = {}
    for name in pointers:
        prop = bpy.types.Object.bl_rna.properties.get(name)
        props[name] = None if prop is None else prop.type
    return {"operators": ops, "object_properties": props}


def probe(zip_path, repo=DEFAULT_REPO):
    """Run in a fresh interpreter (see `probe_in_fresh_process`): install, enable, exercise."""
    import importlib
    import traceback
    out = {"errors": []}
    try:
        import bpy
        import addon_utils  # only importable once bpy is
        out["bpy_version"] = bpy.app.version_string
        out["user_resources"] = os.environ.get(ENV)
        module = install_extension(zip_path, repo)
        mod = importlib.import_module(module)
        out["module"] = module
        out["module_file"] = mod.__file__
        out["enabled"] = is_enabled(module)
        vp = importlib.import_module(module + ".vpffd_addon")
        out["core_file"] = vp.__file__
        out["core"] = core_smoke(vp)
        out["registration"] = registration_report()
        out["repo_vpffd_addon_importable"] = importlib.util.find_spec("vpffd_addon") is not None

        reset_scene()
        out["enabled_after_read_homefile"] = is_enabled(module)
        out["registration_after_read_homefile"] = registration_report()
        bpy.ops.wm.read_factory_settings(use_empty=True)
        out["enabled_after_read_factory_settings"] = is_enabled(module)
        ensure_enabled(module)
        out["enabled_after_ensure_enabled"] = is_enabled(module)

        errors = []
        addon_utils.disable(module, default_set=True, handle_error=errors.append)
        out["enabled_after_disable"] = is_enabled(module)
        out["registration_after_disable"] = registration_report()
        addon_utils.enable(module, default_set=True, handle_error=errors.append)
        out["enabled_after_reenable"] = is_enabled(module)
        out["errors"] += [repr(e) for e in errors]
    except Exception:
        out["errors"].append(traceback.format_exc())
    return out


def probe_in_fresh_process(zip_path, user_resources, timeout=300):
    """Install `zip_path` in a new interpreter whose BLENDER_USER_RESOURCES is `user_resources`
    (set before it imports bpy) and return `probe`'s report (a dict)."""
    env = dict(os.environ)
    env[ENV] = os.path.abspath(user_resources)
    env.pop("PYTHONPATH", None)  # the installed copy must be the only vpffd importable
    proc = subprocess.run(
        [sys.executable, os.path.abspath(__file__), "probe", os.path.abspath(zip_path)],
        capture_output=True, text=True, timeout=timeout, env=env,
        cwd=os.path.abspath(user_resources))
    marker = "VPFFD-PROBE-REPORT "
    for line in proc.stdout.splitlines():
        if line.startswith(marker):
            return json.loads(line[len(marker):])
    raise RuntimeError(f"probe produced no report (exit {proc.returncode})\n"
                       f"stdout:\n{proc.stdout[-4000:]}\nstderr:\n{proc.stderr[-4000:]}")


def run_in_fresh_process(zip_path, user_resources, script, timeout=600):
    """Install and enable `zip_path` in a new interpreter (as `probe_in_fresh_process`), run the
    Python file `script` there with `module` (the extension's module name) defined, and let the
    interpreter end as Blender's does. Returns the CompletedProcess (text stdout and stderr:
    Blender's own words at exit included)."""
    env = dict(os.environ)
    env[ENV] = os.path.abspath(user_resources)
    env.pop("PYTHONPATH", None)
    env.pop("NUMBA_CACHE_DIR", None)     # set by this process's extension: the new one sets its own
    return subprocess.run(
        [sys.executable, os.path.abspath(__file__), "run", os.path.abspath(zip_path),
         os.path.abspath(script)], capture_output=True, text=True, timeout=timeout, env=env,
        cwd=os.path.abspath(user_resources))


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "run":
        sys.path[:] = [p for p in sys.path
                       if os.path.realpath(p or ".") != os.path.realpath(REPO_ROOT)]
        module = install_extension(sys.argv[2])
        with open(sys.argv[3]) as fh:
            exec(compile(fh.read(), sys.argv[3], "exec"), {"module": module, "__name__": "__vpffd_run__"})
    elif len(sys.argv) == 3 and sys.argv[1] == "probe":
        # Run as a script: sys.path[0] is tests/, the repository root is not importable.
        sys.path[:] = [p for p in sys.path
                       if os.path.realpath(p or ".") != os.path.realpath(REPO_ROOT)]
        report = probe(sys.argv[2])
        print("VPFFD-PROBE-REPORT " + json.dumps(report), flush=True)
    else:
        sys.exit(f"usage: {sys.argv[0]} probe ZIP | run ZIP SCRIPT")
