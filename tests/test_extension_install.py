"""The extension as Blender sees it: built, validated and installed with Blender's own tools.

Build and validation run bpy's extension CLI (`blender --command extension build|validate`
without a `blender` binary); installation runs `bpy.ops.extensions.package_install_files`.
See extension_harness.py for how, and for why BLENDER_USER_RESOURCES must be set before bpy is
imported. The fresh-process tests work however the session is set up; the in-session tests need
`extension_harness.isolate_user_resources()` at the top of conftest.py and skip without it.
"""
import fnmatch
import os
import shutil
import zipfile

import pytest

from . import extension_harness as eh

pytestmark = pytest.mark.blender

try:
    eh.blender_ext_cli()
except FileNotFoundError as exc:  # no bpy in this interpreter
    pytest.skip(f"Blender's extension CLI not available: {exc}", allow_module_level=True)

ROOT = eh.REPO_ROOT
MODULE = "bl_ext.user_default.vpffd"


def _repo_py_files(folder):
    return sorted(f"{folder}/{name}" for name in os.listdir(os.path.join(ROOT, folder))
                  if name.endswith(".py"))


@pytest.fixture(scope="module")
def built_zip(tmp_path_factory):
    return eh.build_extension_zip(ROOT, str(tmp_path_factory.mktemp("ext_build")))


@pytest.fixture(scope="module")
def zip_names(built_zip):
    with zipfile.ZipFile(built_zip) as zf:
        return zf.namelist()


@pytest.fixture(scope="module")
def fresh(built_zip, tmp_path_factory):
    """Report from installing the zip in a fresh interpreter with its own user resources."""
    user = tmp_path_factory.mktemp("fresh_blender_user")
    report = eh.probe_in_fresh_process(built_zip, str(user))
    report["_user"] = os.path.realpath(str(user))
    return report


# ------------------------------------------------------------------------------ build

def test_zip_is_built_by_blenders_builder(built_zip):
    cli = eh.blender_ext_cli()
    assert cli.startswith(eh.bpy_package_dir())
    assert cli.endswith(os.path.join("bl_pkg", "cli", "blender_ext.py"))
    manifest = eh.read_manifest(ROOT)
    assert os.path.basename(built_zip) == f"{manifest['id']}-{manifest['version']}.zip"
    assert zipfile.is_zipfile(built_zip)


def test_zip_has_extension_at_its_root(zip_names):
    names = set(zip_names)
    assert {"blender_manifest.toml", "__init__.py"} <= names
    for folder in ("vpffd_addon", "operators"):
        expected = _repo_py_files(folder)
        assert expected and "/".join((folder, "__init__.py")) in expected
        missing = sorted(set(expected) - names)
        assert not missing, f"missing from the zip: {missing}"


def test_zip_excludes_development_paths(zip_names):
    banned_prefixes = ("tests/", "benchmarks/", "examples/", ".venv/", ".git/", ".ci/", "requirements/")
    banned_names = ("dev",)
    bad = [n for n in zip_names
           if n.startswith(banned_prefixes) or n in banned_names
           or "__pycache__/" in n or n.endswith((".pyc", ".zip"))]
    assert not bad, f"development files in the zip: {bad}"


def test_zip_holds_only_extension_files(zip_names):
    """Allow-list: whatever else lies in the working tree (tool caches such as .hypothesis/ and
    .pytest_cache/, pytest.ini, .gitignore) must be excluded by the manifest."""
    allowed = ("blender_manifest.toml", "__init__.py", "README.md", "LICENSE*",
               "vpffd_addon/*.py", "operators/*.py")
    extra = [n for n in zip_names if not any(fnmatch.fnmatchcase(n, p) for p in allowed)]
    assert not extra, ("files outside the extension in the zip; add them to "
                       f"[build] paths_exclude_pattern in blender_manifest.toml: {extra}")


def test_build_plan_matches_blenders_zip(zip_names):
    """The harness's pre-build plan (Blender's matcher and walk) lists exactly what was zipped."""
    assert sorted(n for n in zip_names if n != "blender_manifest.toml") == eh.planned_files(ROOT)


def test_build_refuses_oversized_tree(tmp_path):
    src = tmp_path / "ext"
    (src / "junk").mkdir(parents=True)
    shutil.copy(os.path.join(ROOT, "__init__.py"), src / "__init__.py")
    text = open(os.path.join(ROOT, "blender_manifest.toml"), encoding="utf-8").read()
    (src / "blender_manifest.toml").write_text(text)
    (src / "junk" / "blob.bin").write_bytes(b"\0" * 4096)  # not excluded by the manifest
    with pytest.raises(eh.ExtensionBuildError, match="PREFLIGHT"):
        eh.build_extension_zip(str(src), str(tmp_path / "out"), max_bytes=2048)
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------ validate

def test_blender_validation_passes(built_zip):
    for path in (ROOT, built_zip):
        messages = eh.validate_manifest(path)
        assert any("Success" in m for m in messages), messages


def test_blender_validation_rejects_bad_manifest(tmp_path):
    """Guards the harness: it must run the same checks as `blender --command extension validate`,
    including Blender's tag list."""
    src = tmp_path / "ext"
    src.mkdir()
    shutil.copy(os.path.join(ROOT, "__init__.py"), src / "__init__.py")
    text = open(os.path.join(ROOT, "blender_manifest.toml"), encoding="utf-8").read()
    assert 'tags = ["Animation", "Modeling"]' in text
    (src / "blender_manifest.toml").write_text(
        text.replace('tags = ["Animation", "Modeling"]', 'tags = ["Animation", "NotABlenderTag"]'))
    with pytest.raises(eh.ExtensionValidationError, match="NotABlenderTag"):
        eh.validate_manifest(str(src))
    with pytest.raises(eh.ExtensionBuildError, match="NotABlenderTag"):
        eh.build_extension_zip(str(src), str(tmp_path / "out"))


# ------------------------------------------------------------------------------ install (fresh process)

def test_installs_and_enables_in_fresh_blender(fresh):
    assert fresh["errors"] == []
    assert fresh["module"] == MODULE
    assert fresh["enabled"] is True
    installed = os.path.join(fresh["_user"], "extensions", "user_default", "vpffd")
    assert os.path.realpath(fresh["module_file"]) == os.path.join(installed, "__init__.py")
    assert os.path.realpath(fresh["core_file"]) == os.path.join(installed, "vpffd_addon", "__init__.py")
    assert fresh["repo_vpffd_addon_importable"] is False  # only the installed copy was used


def test_installed_core_works_in_fresh_blender(fresh):
    core = fresh["core"]
    assert core["deform_identity_err"] < 1e-12
    assert core["solve_identity_err"] < 1e-12
    assert core["squash_volume"] == pytest.approx(core["rest_volume"], rel=1e-9)
    assert abs(core["squash_plain_volume"] - core["rest_volume"]) > 1e-3 * core["rest_volume"]


def test_scene_reset_and_disable_in_fresh_blender(fresh):
    assert fresh["errors"] == []
    assert fresh["enabled_after_read_homefile"] is True          # eh.reset_scene keeps it
    assert fresh["registration_after_read_homefile"] == fresh["registration"]
    assert fresh["enabled_after_read_factory_settings"] is False  # resets preferences
    assert fresh["enabled_after_ensure_enabled"] is True
    assert fresh["enabled_after_disable"] is False
    reg = fresh["registration_after_disable"]
    assert not any(reg["operators"].values()) and not any(reg["object_properties"].values())
    assert fresh["enabled_after_reenable"] is True


def test_operators_and_properties_registered(fresh):
    reg = fresh["registration"]
    assert reg["operators"] == {op: True for op in eh.EXPECTED_OPERATORS}
    assert reg["object_properties"] == {"vpffd": "POINTER"}


# ------------------------------------------------------------------------------ install (this session)

@pytest.fixture(scope="module")
def ext(tmp_path_factory):
    return eh.installed_extension(tmp_path_factory)


def test_session_extension_enabled_and_core_works(ext):
    import importlib
    assert ext.module_name == MODULE
    assert eh.is_enabled(MODULE)
    assert os.path.realpath(ext.module.__file__).startswith(os.path.realpath(ext.user_resources) + os.sep)
    core = eh.core_smoke(importlib.import_module(MODULE + ".vpffd_addon"))
    assert core["deform_identity_err"] < 1e-12
    assert core["squash_volume"] == pytest.approx(core["rest_volume"], rel=1e-9)


def test_session_reset_scene_keeps_extension(ext):
    import bpy
    bpy.data.objects.new("vpffd_probe_empty", None)
    eh.reset_scene()
    assert len(bpy.data.objects) == 0
    assert eh.is_enabled(MODULE)
    try:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        assert not eh.is_enabled(MODULE)
    finally:
        eh.ensure_enabled(MODULE)
    assert eh.is_enabled(MODULE)
