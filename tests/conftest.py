"""Test session set-up. `tests` is a package: pytest puts the repository root (the first folder
above it without an `__init__.py`) on sys.path, so `import vpffd_addon` and `from . import
_meshes` work however pytest is started, with no path edits.

- Blender's user resources point at a private temporary folder before anything imports bpy, so
  the extension installs through Blender's own installer without touching a real configuration.
- `vpffd`: the extension, built into a zip and installed once per session (skips without bpy).
- Hypothesis runs derandomized (the same examples on every run, printed on failure with the
  blob to reproduce it); VPFFD_HYPOTHESIS_RANDOM=1 draws new ones.
- Skips are accounted for: every pass prints how many tests were skipped and why, and with
  VPFFD_STRICT_SKIPS=1 (set by `./dev test`) a skip whose reason is not on ALLOWED_SKIPS fails the
  run: a broken bpy, a GPU kernel that does not compile or a missing chroot must turn the run red,
  not shrink it.
"""
import os
import re
import sys

import pytest
from hypothesis import settings as _hypothesis_settings

from . import extension_harness as eh

eh.isolate_user_resources()

_hypothesis_settings.register_profile("vpffd-derandomized", derandomize=True, print_blob=True)
_hypothesis_settings.register_profile("vpffd-random", print_blob=True)
_hypothesis_settings.load_profile("vpffd-random" if os.environ.get("VPFFD_HYPOTHESIS_RANDOM") == "1"
                                  else "vpffd-derandomized")

# (pattern of the skip reason, why it is allowed, when: a function of nothing, True where allowed).
ALLOWED_SKIPS = (
    (r"could not import 'bpy'|bpy is not installed",
     "the core-only pass on Debian's Python has no bpy (the bpy passes must import it)",
     lambda: os.environ.get("VPFFD_CORE_ONLY") == "1"),
    (r"numba is not installed in this environment",
     "only the 5.3 and 4.2 passes install numba (the others test the NumPy path Blender takes "
     "without it)",
     lambda: os.environ.get("VPFFD_PASS") not in ("5.3", "4.2")),
    (r"bpy 4.2's module crashes at interpreter exit",
     "bpy 4.2 prints no exit report (the newer passes read it)",
     lambda: os.environ.get("VPFFD_PASS") == "4.2"),
    (r"bpy 4.2's module crashes reading saved preferences",
     "bpy 4.2 runs only the first step of a user's life with an extensions repository; the "
     "newer passes run them all, Debian's blender the command lines",
     lambda: os.environ.get("VPFFD_PASS") == "4.2"),
    (r"bpy 4.5 leaves a 16-byte block per evaluation",
     "a bpy 4.5 leak in Geometry Nodes evaluation (docs/testing.md); 5.0 and newer are read",
     lambda: os.environ.get("VPFFD_PASS") == "4.5"),
    (r"Vulkan backend needs Blender 4.5 or newer",
     "the fallback chroot (Debian trixie, Blender 4.3) has no Vulkan backend to test",
     lambda: True),
)
_skips = []


def _record_skip(report):
    if report.skipped and not hasattr(report, "wasxfail"):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        _skips.append((report.nodeid, reason.removeprefix("Skipped: ")))


def pytest_runtest_logreport(report):
    _record_skip(report)


def pytest_collectreport(report):
    _record_skip(report)


def _why_allowed(reason):
    for pattern, why, when in ALLOWED_SKIPS:
        if re.search(pattern, reason) and when():
            return why
    return None


def pytest_terminal_summary(terminalreporter):
    allowed = [(n, r, _why_allowed(r)) for n, r in _skips]
    bad = [(n, r) for n, r, why in allowed if why is None]
    name = os.environ.get("VPFFD_PASS", "this run")
    terminalreporter.write_line(f"VP-FFD skips in {name}: {len(_skips)} ({len(bad)} not on the allow-list)")
    for n, r, why in allowed:
        terminalreporter.write_line(f"  {'ALLOWED' if why else 'NOT ALLOWED'}: {n}: {r}"
                                    + (f" [{why}]" if why else ""))
    if bad and os.environ.get("VPFFD_STRICT_SKIPS") == "1":
        terminalreporter.write_line("VP-FFD: skips not on the allow-list (tests/conftest.py "
                                    "ALLOWED_SKIPS) fail the run", red=True)


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
    if (os.environ.get("VPFFD_STRICT_SKIPS") == "1" and int(exitstatus) in (0, 5)
            and any(_why_allowed(r) is None for _, r in _skips)):
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
    _exit_status["code"] = int(session.exitstatus)


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
