"""`./dev package`: the linux-x64 package with numba's wheels, built by Blender's own builder from
pinned, hash-checked wheels, installs through Blender's own installer into a fresh bpy (the
newest and 4.2 LTS in the matrix), which puts the wheels for its own Python on its path: numba
imports from the extension's wheels and compiles a function. The universal package has none."""
import json
import os
import sys
import zipfile

import pytest

bpy = pytest.importorskip("bpy")

from release import package  # noqa: E402
from . import extension_harness as eh  # noqa: E402

pytestmark = pytest.mark.blender

PY = f"{sys.version_info.major}.{sys.version_info.minor}"

SESSION = r'''
import json, os, sys
# Blender put the package's wheels in the extensions' own site folder; this test's interpreter also
# has numba of its own (the test environment), which a user's Blender has not: look there first.
user = os.environ["BLENDER_USER_RESOURCES"]
ours = [p for p in sys.path if os.path.realpath(p).startswith(os.path.realpath(user))]
sys.path[:0] = ours
import numba
from numba import njit


@njit(cache=False)
def dot(a, b):
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


import numpy as np
x = np.arange(5.0)
import llvmlite
print("VPFFD-NUMBA " + json.dumps({"version": numba.__version__, "file": numba.__file__,
                                   "llvmlite": llvmlite.__file__, "site": ours,
                                   "dot": dot(x, x), "python": sys.version}), flush=True)
'''


@pytest.fixture(scope="module")
def linux_package(tmp_path_factory):
    """The universal package, the linux-x64 one, then the NumPy-only ones (package.NUMPY_ONLY)."""
    out = tmp_path_factory.mktemp("dist")
    return package.build(["linux-x64"], [PY], out=str(out), universal=True)


def test_the_platform_package_holds_only_its_locked_wheels(linux_package):
    universal, linux = linux_package[:2]
    lock = package.read_lock()
    locked = {name for name, _ in lock[("linux-x64", PY)]}
    with zipfile.ZipFile(linux) as zf:
        wheels = {n.split("/", 1)[1] for n in zf.namelist() if n.startswith("wheels/")}
        manifest = zf.read("blender_manifest.toml").decode()
    assert wheels == locked
    assert 'platforms = ["linux-x64"]' in manifest
    with zipfile.ZipFile(universal) as zf:
        assert not [n for n in zf.namelist() if n.startswith("wheels/")]
    eh.validate_manifest(linux)
    with open(os.path.join(os.path.dirname(linux), "index.json")) as fh:
        index = json.load(fh)
    entry, = [e for e in index["data"] if e["archive_url"] == "./" + os.path.basename(linux)]
    assert entry["platforms"] == ["linux-x64"] and entry["python_versions"] == [PY]
    assert os.path.basename(universal) not in json.dumps(index), "the universal one stays out"


def test_a_wheel_that_differs_from_the_lock_is_refused(tmp_path, monkeypatch):
    lock = package.read_lock()
    name, _ = lock[("linux-x64", PY)][0]
    bad = {k: [(n, "0" * 64 if n == name else d) for n, d in v] for k, v in lock.items()}
    monkeypatch.setattr(package, "read_lock", lambda path=None: bad)
    with pytest.raises(package.PackageError, match="SHA-256"):
        package.build(["linux-x64"], [PY], out=str(tmp_path), universal=False)
    assert not os.listdir(tmp_path)


def test_numba_from_the_package_runs_in_blender(linux_package, tmp_path):
    linux = linux_package[1]
    script = tmp_path / "numba_session.py"
    script.write_text(SESSION)
    user = tmp_path / "user"
    user.mkdir()
    proc = eh.run_in_fresh_process(linux, str(user), str(script))
    out = proc.stdout + proc.stderr
    line = next((l for l in proc.stdout.splitlines() if l.startswith("VPFFD-NUMBA ")), None)
    assert line is not None, out[-4000:]
    report = json.loads(line[len("VPFFD-NUMBA "):])
    assert report["version"] == "0.68.1"
    assert report["dot"] == 30.0
    assert report["site"], "Blender added the extensions' site folder to the path"
    for module in ("file", "llvmlite"):
        assert os.path.realpath(report[module]).startswith(os.path.realpath(str(user))), \
            (module, "comes from the wheels Blender installed for the extension", report)


#: Official Blender builds and the Python each embeds (Debian's 5.2 embeds 3.14).
OFFICIAL = (((4, 2, 0), (3, 11, 0)), ((4, 5, 0), (3, 11, 0)), ((5, 0, 0), (3, 11, 0)),
            ((5, 1, 0), (3, 13, 0)), ((5, 3, 0), (3, 13, 0)))


def test_every_blender_on_arm_windows_and_the_numpy_platforms_finds_one_package(tmp_path):
    """numba has only Python 3.13 wheels for Windows on ARM: its package serves Blender from 5.1
    on, a NumPy-only one the Blender versions before; Blender's own filter finds exactly one
    package in the index for each official Blender there and on the NumPy-only platforms."""
    package.build(["windows-arm64"], out=str(tmp_path), universal=False)
    with open(tmp_path / "index.json") as fh:
        entries = json.load(fh)["data"]
    ext = eh._blender_ext_module()
    for platform in ("windows-arm64", *package.NUMPY_ONLY):
        for blender, python in OFFICIAL:
            found = [e["archive_url"] for e in entries if not ext.repository_filter_skip(
                e, filter_blender_version=blender, filter_platform=platform,
                filter_python_version=python, skip_message_fn=None, error_fn=print)]
            assert len(found) == 1, (platform, blender, found)
            if platform == "windows-arm64":
                with zipfile.ZipFile(tmp_path / found[0][2:]) as zf:
                    wheels = [n for n in zf.namelist() if n.startswith("wheels/")]
                assert bool(wheels) == (python[:2] == (3, 13)), (blender, found)

