"""One step of a user's life with a studio's extensions repository, run in a fresh bpy process by
tests/test_repository_blender.py (``python repository_session.py STEP [ARGS...]``), with
BLENDER_USER_RESOURCES set by the test before bpy is imported. Successive steps share that
folder, as successive Blender sessions of one user share their preferences. Each prints one line,
``VPFFD-REPO-REPORT {json}``: the state at its start and what the step saw.

Steps:

* ``ui-install URL``: what Preferences > Get Extensions does: Repositories > Add Remote
  Repository with URL, its sync (which the window runs on adding; background Blender leaves it
  to the caller), then Install on VP-FFD's row; saves the preferences.
* ``ui-update``: the refresh button of the repository; when VP-FFD's row shows the newer
  version, its Update button (the same operator as Install, enabling what was enabled); saves
  the preferences.
* ``cli [--online] ARGS...``: ``blender [--online-mode] --command extension ARGS...``: the handler
  of Blender's command (bl_pkg's bl_extension_cli) with these arguments; ``--online`` allows online
  access for this run only, as ``--online-mode`` does.
* ``report``: only the state.

The bpy module, unlike the blender program, does not read the saved preferences when it starts,
so every step reads them first (``wm.read_userpref``, once there are any), as Blender does at
start-up.
"""
import json
import os
import sys
import tomllib

EXT_ID = "vpffd"
REPO_MODULE = "studio"        # what the command-line steps call the repository


def _repos():
    import bpy
    return list(bpy.context.preferences.extensions.repos)


def _repo_index(url):
    """Index of the repository whose remote URL is `url`; None if none is."""
    found = [i for i, repo in enumerate(_repos()) if repo.remote_url == url]
    return found[0] if found else None


def state():
    """Every repository with VP-FFD installed: its installed version, whether Blender has it
    enabled, and whether its operators are registered."""
    import addon_utils
    import bpy
    out = {"repos": {r.module: r.remote_url for r in _repos()}, "installed": {},
           "online_access": bpy.app.online_access}
    for repo in _repos():
        manifest = os.path.join(repo.directory, EXT_ID, "blender_manifest.toml")
        if not os.path.isfile(manifest):
            continue
        with open(manifest, "rb") as fh:
            version = tomllib.load(fh)["version"]
        module = f"bl_ext.{repo.module}.{EXT_ID}"
        out["installed"][repo.module] = {
            "version": version, "module": module,
            "enabled": addon_utils.check(module) == (True, True)
            and module in bpy.context.preferences.addons,
            "bind_registered": hasattr(bpy.types, "OBJECT_OT_vpffd_bind")}
    return out


def remote_version(repo_index):
    """The version of VP-FFD in the repository's listing from the last sync (what Blender draws
    in the row), or None."""
    from bl_pkg import repo_cache_store_ensure
    listings = list(repo_cache_store_ensure().pkg_manifest_from_remote_ensure(error_fn=print))
    listing = listings[repo_index] or {}
    item = listing.get(EXT_ID)
    return None if item is None else item.version


def _run(op, **kwargs):
    """Run an operator; its result, or the error it raised (a refused poll included)."""
    try:
        return sorted(op(**kwargs))
    except RuntimeError as exc:
        return f"error: {exc}"


def ui_install(url):
    import bpy
    prefs = bpy.context.preferences
    report = {"add": _run(bpy.ops.preferences.extension_repo_add, name="Studio",
                          remote_url=url, type='REMOTE')}
    index = report["repo_index"] = _repo_index(url)
    report["sync"] = _run(bpy.ops.extensions.repo_sync, repo_index=index)
    report["remote_version"] = remote_version(index)
    # Installing asks for online access, also from a file:// repository.
    prefs.system.use_online_access = False
    report["install_poll_offline"] = bpy.ops.extensions.package_install.poll()
    prefs.system.use_online_access = True
    report["install"] = _run(bpy.ops.extensions.package_install, repo_index=index,
                             pkg_id=EXT_ID, enable_on_install=True)
    report["save"] = _run(bpy.ops.wm.save_userpref)
    return report


def ui_update():
    import bpy
    url = next(r.remote_url for r in _repos() if r.name == "Studio")
    index = _repo_index(url)
    # The refresh button beside the active repository in the Repositories list.
    bpy.context.preferences.extensions.active_repo = index
    report = {"sync": _run(bpy.ops.extensions.repo_sync_all, use_active_only=True),
              "remote_version": remote_version(index)}
    module = next(r.module for r in _repos() if r.name == "Studio")
    import addon_utils
    enabled = addon_utils.check(f"bl_ext.{module}.{EXT_ID}") == (True, True)
    # The Update button: extensions.package_install on the row, keeping it enabled if it was.
    report["update"] = _run(bpy.ops.extensions.package_install, repo_index=index,
                            pkg_id=EXT_ID, enable_on_install=enabled)
    report["save"] = _run(bpy.ops.wm.save_userpref)
    return report


def cli(args):
    import bpy
    from bl_pkg.bl_extension_cli import cli_extension_handler
    if args and args[0] == "--online":
        args = args[1:]
        bpy.context.preferences.system.use_online_access = True
    return {"args": args, "returncode": cli_extension_handler(args)}


def main(argv):
    import bpy
    if os.path.isfile(os.path.join(os.environ["BLENDER_USER_RESOURCES"], "config", "userpref.blend")):
        bpy.ops.wm.read_userpref()
    step, args = argv[0], argv[1:]
    report = {"before": state()}
    if step == "ui-install":
        report["step"] = ui_install(*args)
    elif step == "ui-update":
        report["step"] = ui_update()
    elif step == "cli":
        report["step"] = cli(args)
    elif step != "report":
        raise SystemExit(f"unknown step {step!r}")
    report["after"] = state()
    print("VPFFD-REPO-REPORT " + json.dumps(report), flush=True)


if __name__ == "__main__":
    # Run as a script: sys.path[0] is tests/; the repository root must not be importable, so that
    # the installed copy is the only VP-FFD.
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    sys.path[:] = [p for p in sys.path if os.path.realpath(p or ".") != os.path.realpath(root)]
    main(sys.argv[1:])
