"""Test session set-up. `tests` is a package: pytest puts the repository root (the first folder
above it without an `__init__.py`) on sys.path, so `import vpffd_addon` and `from . import
_meshes` work however pytest is started, with no path edits.

- Blender's user resources point at a private temporary folder before anything imports bpy, so
  the extension installs through Blender's own installer without touching a real configuration.
- `vpffd`: the extension, built into a zip and installed once per session (skips without bpy).
"""
import os
import sys

import pytest

from . import extension_harness as eh

eh.isolate_user_resources()


@pytest.fixture(scope="session")
def vpffd(tmp_path_factory):
    """InstalledExtension(module_name, module, zip_path, user_resources) of the enabled extension."""
    return eh.installed_extension(tmp_path_factory)


@pytest.fixture
def ext(vpffd):
    """The installed extension in an empty scene at frame 1, emptied again afterwards. A module
    that needs another set-up defines its own `ext`."""
    import bpy                     # installed by `vpffd`, never before `isolate_user_resources`
    eh.reset_scene()
    bpy.context.scene.frame_set(1)
    yield vpffd
    eh.reset_scene()


# The bpy 4.2 module crashes while the interpreter shuts down once any property with a Python
# update callback has been registered, after every test has run and been reported (checked with a
# ten-line script registering one FloatProperty(update=...); bpy 5.0 does not). Leave such a
# session right after pytest's own last words, with pytest's exit status.
_exit_status = {}


def pytest_collection_modifyitems(config, items):
    """VPFFD_NO_E2E=1 (`./dev test`'s second pass) deselects the tests that run Debian's Blender
    from the chroot (e2e, gui): they do not depend on the bpy of the pass."""
    if os.environ.get("VPFFD_NO_E2E", "") in ("", "0"):
        return
    chroot = [item for item in items if item.get_closest_marker("e2e")]
    if chroot:
        config.hook.pytest_deselected(items=chroot)
        items[:] = [item for item in items if not item.get_closest_marker("e2e")]


def pytest_sessionfinish(session, exitstatus):
    _exit_status["code"] = int(exitstatus)


def pytest_unconfigure(config):
    bpy = sys.modules.get("bpy")
    if bpy is None or "code" not in _exit_status or tuple(bpy.app.version) >= (4, 3, 0):
        return
    import shutil
    sys.stdout.flush()
    sys.stderr.flush()
    if eh._ISOLATED:
        shutil.rmtree(eh._ISOLATED, ignore_errors=True)
    os._exit(_exit_status["code"])
