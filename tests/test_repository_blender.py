"""`./dev package` makes its output folder an extensions repository (Blender's own index.json and
index.html over the packages), and Blender installs VP-FFD from it and updates it when a newer
version is published there: through what Preferences > Get Extensions runs (add the remote
repository, check for updates, Install, Update) and through `blender --command extension`'s own
handler (repo-add, sync, install, list, update), each step in a fresh bpy process of one user.

The packages here are NumPy-only, built for this machine's platform, so that nothing is
downloaded: the same builder, validation and index as the numba packages (their wheels are
tested in test_package_blender.py)."""
import json
import os
import shutil
import subprocess
import sys
import zipfile

import pytest

bpy = pytest.importorskip("bpy")

from release import package  # noqa: E402
from . import extension_harness as eh  # noqa: E402

pytestmark = pytest.mark.blender

SESSION = os.path.join(os.path.dirname(os.path.abspath(__file__)), "repository_session.py")
EXT_ID = eh.read_manifest()["id"]
OLD = eh.read_manifest()["version"]


def this_platform():
    """This machine's platform as Blender names it (what its repositories filter on)."""
    return eh._blender_ext_module().platform_from_this_system()


def bumped_source(folder, version):
    """A copy of the extension's files as the builder packs them, with `version` in its
    manifest: the next release, as a developer would publish it."""
    for rel in eh.planned_files():
        os.makedirs(os.path.join(folder, os.path.dirname(rel)), exist_ok=True)
        shutil.copy2(os.path.join(eh.REPO_ROOT, rel), os.path.join(folder, rel))
    with open(os.path.join(eh.REPO_ROOT, "blender_manifest.toml")) as fh:
        text = fh.read()
    line = f'version = "{OLD}"'
    assert text.count(line) == 1
    with open(os.path.join(folder, "blender_manifest.toml"), "w") as fh:
        fh.write(text.replace(line, f'version = "{version}"'))
    return str(folder)


def publish(repo, root=eh.REPO_ROOT):
    """`./dev package` into `repo` with a NumPy-only package for this platform."""
    return package.build([], out=str(repo), universal=False, numpy_only=(this_platform(),),
                         root=root)


#: Why bpy 4.2 runs only a user's first step: its module crashes (SIGSEGV) in wm.read_userpref,
#: which every later step needs to find what the earlier ones saved.
PREFS_CRASH = "bpy 4.2's module crashes reading saved preferences (wm.read_userpref)"


def step(user, *args):
    """One step of repository_session.py in a fresh interpreter with `user` as its
    BLENDER_USER_RESOURCES; its report, with its output under "log"."""
    if bpy.app.version < (4, 3, 0) and os.path.isfile(os.path.join(str(user), "config", "userpref.blend")):
        pytest.skip(PREFS_CRASH)
    env = dict(os.environ)
    env[eh.ENV] = str(user)
    env.pop("PYTHONPATH", None)
    env.pop("NUMBA_CACHE_DIR", None)
    proc = subprocess.run([sys.executable, SESSION, *args], capture_output=True, text=True,
                          timeout=300, env=env, cwd=str(user))
    marker = "VPFFD-REPO-REPORT "
    line = next((l for l in proc.stdout.splitlines() if l.startswith(marker)), None)
    assert line is not None, f"{args}: no report (exit {proc.returncode})\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    report = json.loads(line[len(marker):])
    report["log"] = proc.stdout + proc.stderr
    return report


def url_of(repo):
    return "file://" + os.path.join(os.path.abspath(str(repo)), "index.json")


def read_index(repo):
    with open(os.path.join(str(repo), "index.json")) as fh:
        return json.load(fh)


@pytest.fixture(scope="module")
def life(tmp_path_factory):
    """Version OLD published, installed by a user through Preferences and by a farm worker through
    the command line; then NEW published into the same folder, and both update."""
    base = tmp_path_factory.mktemp("studio")
    repo, ui, cli = base / "repo", base / "ui_user", base / "cli_user"
    for folder in (ui, cli):
        folder.mkdir()
    url = url_of(repo)
    out = {"published_old": publish(repo), "index_old": read_index(repo)}
    out["ui_install"] = step(ui, "ui-install", url)
    # Hermetic: sync refreshes every remote repository, extensions.blender.org's too.
    out["cli_remove_blender_org"] = step(cli, "cli", "repo-remove", "blender_org")
    out["cli_add"] = step(cli, "cli", "repo-add", "studio", "--url", url)
    out["cli_sync_offline"] = step(cli, "cli", "sync")
    out["cli_sync"] = step(cli, "cli", "--online", "sync")
    out["cli_install"] = step(cli, "cli", "install", EXT_ID, "--enable")
    out["new"] = new = _next_patch(OLD)
    out["published_new"] = publish(repo, bumped_source(base / "next", new))
    out["index_new"] = read_index(repo)
    out["ui_update"] = step(ui, "ui-update")
    out["ui_after"] = step(ui, "report")
    out["cli_sync_again"] = step(cli, "cli", "--online", "sync")
    out["cli_list"] = step(cli, "cli", "list")
    out["cli_update"] = step(cli, "cli", "--online", "update")
    out["cli_after"] = step(cli, "report")
    return out


def _next_patch(version):
    major, minor, patch = version.split(".")[:3]
    return f"{major}.{minor}.{int(patch.split('-')[0]) + 1}"


# ------------------------------------------------------------------------------ the repository

def test_package_writes_blenders_index_over_one_package_per_platform(tmp_path):
    """The default layout: a NumPy-only package per platform numba has no wheels for, each
    validated, listed in index.json with its size and hash; the any-platform package lies in
    universal/, outside the index, since it would match every platform's entry."""
    made = package.build([], out=str(tmp_path))
    universal = os.path.join(str(tmp_path), package.UNIVERSAL, f"{EXT_ID}-{OLD}.zip")
    assert made[0] == universal
    index = read_index(tmp_path)
    entries = {e["archive_url"]: e for e in index["data"]}
    expected = {f"./{EXT_ID}-{OLD}-{p.replace('-', '_')}.zip": p for p in package.NUMPY_ONLY}
    assert set(entries) == set(expected)
    for url, platform in expected.items():
        entry = entries[url]
        path = os.path.join(str(tmp_path), url[2:])
        assert entry["id"] == EXT_ID and entry["version"] == OLD
        assert entry["platforms"] == [platform]
        assert entry["archive_size"] == os.path.getsize(path)
        assert entry["archive_hash"] == "sha256:" + package.sha256(path)
        eh.validate_manifest(path)
    with zipfile.ZipFile(universal) as zf:
        assert "platforms" not in zf.read("blender_manifest.toml").decode()
    with open(tmp_path / "index.html") as fh:
        assert f"{EXT_ID}-{OLD}-macos_x64.zip" in fh.read()


def test_an_index_with_two_packages_for_one_system_is_refused(tmp_path):
    """Blender would list one and install the other: server-generate's warning stops the build."""
    package.build([], out=str(tmp_path))
    shutil.copy2(tmp_path / package.UNIVERSAL / f"{EXT_ID}-{OLD}.zip", tmp_path)
    with pytest.raises(package.PackageError, match="duplicates"):
        package.write_index(str(tmp_path))


def test_publishing_replaces_the_older_version_and_keeps_other_extensions(tmp_path):
    publish(tmp_path)
    other = tmp_path / "another_extension-1.0.0.zip"
    with zipfile.ZipFile(other, "w") as zf:
        zf.writestr("blender_manifest.toml", 'id = "another_extension"\nversion = "1.0.0"\n')
    new = _next_patch(OLD)
    package.remove_stale(str(tmp_path), {"id": EXT_ID, "version": new})
    assert sorted(os.listdir(tmp_path)) == ["another_extension-1.0.0.zip", "index.html", "index.json"]


def test_a_package_for_any_platform_left_beside_the_platform_ones_goes(tmp_path):
    """Where an earlier `./dev package` left the universal package in the repository's folder,
    the next one moves it to universal/ instead of refusing the index."""
    made = package.build([], out=str(tmp_path))
    shutil.copy2(made[0], tmp_path)
    again = package.build([], out=str(tmp_path))
    assert again == made
    entries = read_index(tmp_path)["data"]
    assert entries and all(e.get("platforms") for e in entries)
    assert not (tmp_path / os.path.basename(made[0])).exists()


# ------------------------------------------------------------------------------ Preferences

def test_preferences_add_the_repository_and_install_vpffd(life):
    old = life["published_old"]
    assert [e["version"] for e in life["index_old"]["data"]] == [OLD]
    assert [os.path.basename(p) for p in old] == [f"{EXT_ID}-{OLD}-{this_platform().replace('-', '_')}.zip"]
    step_ = life["ui_install"]["step"]
    assert step_["add"] == ["FINISHED"] and step_["sync"] == ["FINISHED"]
    assert step_["remote_version"] == OLD
    assert step_["install_poll_offline"] is False, "Install asks for Allow Online Access"
    assert step_["install"] == ["FINISHED"], life["ui_install"]["log"][-3000:]
    (repo, installed), = life["ui_install"]["after"]["installed"].items()
    assert installed == {"version": OLD, "module": f"bl_ext.{repo}.{EXT_ID}", "enabled": True,
                         "bind_registered": True}


def test_preferences_see_the_new_version_and_update(life):
    new = life["new"]
    assert [e["version"] for e in life["index_new"]["data"]] == [new]
    before = life["ui_update"]["before"]["installed"]
    assert [v["version"] for v in before.values()] == [OLD]
    assert all(v["enabled"] for v in before.values()), "still enabled in the next session"
    step_ = life["ui_update"]["step"]
    assert step_["sync"] == ["FINISHED"]
    assert step_["remote_version"] == new, "the row shows the new version: Update"
    assert step_["update"] == ["FINISHED"], life["ui_update"]["log"][-3000:]
    after = life["ui_after"]["before"]["installed"]
    assert [(v["version"], v["enabled"], v["bind_registered"]) for v in after.values()] == \
        [(new, True, True)], "the new version, enabled, in the next session"


# ------------------------------------------------------------------------------ command line

def test_command_line_adds_syncs_and_installs(life):
    assert life["cli_remove_blender_org"]["step"]["returncode"] == 0
    assert "blender_org" not in life["cli_add"]["before"]["repos"]
    assert life["cli_add"]["step"]["returncode"] == 0
    assert life["cli_add"]["after"]["repos"]["studio"] == url_of(os.path.dirname(
        life["published_old"][0]))
    offline = life["cli_sync_offline"]
    assert "Online access required" in offline["log"], "sync needs --online-mode"
    assert life["cli_sync"]["step"]["returncode"] == 0
    install = life["cli_install"]
    assert install["step"]["returncode"] == 0, install["log"][-3000:]
    assert install["after"]["installed"]["studio"] == {
        "version": OLD, "module": f"bl_ext.studio.{EXT_ID}", "enabled": True,
        "bind_registered": True}


def test_command_line_lists_the_update_and_installs_it(life):
    new = life["new"]
    assert life["cli_sync_again"]["step"]["returncode"] == 0
    assert f"{EXT_ID} [outdated: {OLD} -> {new}]" in life["cli_list"]["log"]
    update = life["cli_update"]
    assert update["step"]["returncode"] == 0, update["log"][-3000:]
    assert life["cli_after"]["before"]["installed"]["studio"] == {
        "version": new, "module": f"bl_ext.studio.{EXT_ID}", "enabled": True,
        "bind_registered": True}


def test_blender_refuses_a_package_whose_index_hash_is_wrong(tmp_path):
    """Blender checks each download against the index: a broken index installs nothing."""
    repo, user = tmp_path / "repo", tmp_path / "user"
    user.mkdir()
    publish(repo)
    index = read_index(repo)
    index["data"][0]["archive_hash"] = "sha256:" + "0" * 64
    with open(repo / "index.json", "w") as fh:
        json.dump(index, fh)
    report = step(user, "ui-install", url_of(repo))
    assert report["step"]["sync"] == ["FINISHED"] and report["step"]["remote_version"] == OLD
    assert "Archive checksum mismatch" in report["log"], report["log"][-3000:]
    assert not report["after"]["installed"]
