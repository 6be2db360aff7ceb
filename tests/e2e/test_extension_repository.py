"""A farm worker's command lines against a studio's extensions repository served over HTTP, with
Debian's real `blender`: `./dev package` publishes into a folder (here a NumPy-only package for
this platform, so nothing is downloaded) that a plain static-file server serves; the worker adds
it with `blender --command extension repo-add`, syncs and installs; a newer version is published
into the same folder, and `list` shows it outdated and `update` installs it, enabled. Every
command is its own Blender process, sharing one user's preferences, as on a worker. These are the
commands the README and docs/render-farms.md give studios (test_repository_blender.py takes a file:// URL)."""
import functools
import http.server
import os
import re
import threading

import pytest

from . import blender_chroot as bc
from .. import extension_harness as eh
from .. import test_repository_blender as trb

pytestmark = pytest.mark.e2e

pytest.importorskip("bpy")     # ./dev package builds with the extension CLI that bpy ships

EXT_ID = trb.EXT_ID
OLD = trb.OLD
ENABLED = r'''
import addon_utils, bpy, os, tomllib
module = "bl_ext.studio.%s"
path = os.path.join(bpy.utils.user_resource("EXTENSIONS"), "studio", "%s", "blender_manifest.toml")
version = tomllib.load(open(path, "rb"))["version"] if os.path.isfile(path) else None
print("VPFFD-INSTALLED", version, addon_utils.check(module) == (True, True),
      hasattr(bpy.types, "OBJECT_OT_vpffd_bind"))
''' % (EXT_ID, EXT_ID)


def blender(work, *args):
    """`blender ARGS` in the chroot with the work folder's user resources; (rc, output)."""
    rc, out, err, _ = bc.run_blender(list(args), workdir=work, timeout=300)
    return rc, out + err


def installed(work):
    """(version, enabled, operators registered) in a fresh `blender -b` of this user."""
    with open(os.path.join(work, "enabled.py"), "w") as fh:
        fh.write(ENABLED)
    rc, out = blender(work, "-b", "--python-exit-code", "1", "--python", "{work}/enabled.py")
    found = re.search(r"^VPFFD-INSTALLED (\S+) (True|False) (True|False)$", out, re.M)
    assert rc == 0 and found, out[-3000:]
    return found.group(1), found.group(2) == "True", found.group(3) == "True"


@pytest.fixture
def served(tmp_path):
    """(folder, URL of its index.json) served by Python's static-file server on this machine,
    which the chroot shares the network with."""
    folder = tmp_path / "repo"
    folder.mkdir()
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield str(folder), f"http://127.0.0.1:{server.server_address[1]}/index.json"
    server.shutdown()
    server.server_close()


@pytest.fixture(scope="module")
def worker(chroot):
    work = bc.new_workdir()
    yield work
    if os.environ.get("VPFFD_E2E_KEEP") != "1":
        bc.remove_workdir(work)


def test_a_worker_installs_from_the_repository_and_updates(worker, served, tmp_path):
    repo, url = served
    trb.publish(repo)

    # Offline workers: sync would also try extensions.blender.org, which is not wanted here.
    assert blender(worker, "--command", "extension", "repo-remove", "blender_org")[0] == 0
    rc, out = blender(worker, "--command", "extension", "repo-add", "studio", "--url", url)
    assert rc == 0, out[-3000:]
    rc, out = blender(worker, "--command", "extension", "sync")
    assert "Online access required" in out, "without --online-mode, sync refuses"
    rc, out = blender(worker, "--online-mode", "--command", "extension", "sync")
    assert rc == 0 and "Error" not in out, out[-3000:]
    rc, out = blender(worker, "--command", "extension", "install", EXT_ID, "--enable")
    assert rc == 0 and f'Installed "{EXT_ID}"' in out, out[-3000:]
    assert installed(worker) == (OLD, True, True)

    new = trb._next_patch(OLD)
    trb.publish(repo, trb.bumped_source(tmp_path / "next", new))
    rc, out = blender(worker, "--online-mode", "--command", "extension", "sync")
    assert rc == 0, out[-3000:]
    rc, out = blender(worker, "--command", "extension", "list")
    assert f"{EXT_ID} [outdated: {OLD} -> {new}]" in out, out[-3000:]
    rc, out = blender(worker, "--command", "extension", "update")
    assert rc != 0 and installed(worker)[0] == OLD, "without --online-mode, update refuses"
    rc, out = blender(worker, "--online-mode", "--command", "extension", "update")
    assert rc == 0, out[-3000:]
    assert installed(worker) == (new, True, True)
