"""Test session set-up.

- The repository root is importable (`import vpffd_addon`) however pytest is started.
- Blender's user resources point at a private temporary folder before anything imports bpy, so
  the extension installs through Blender's own installer without touching a real configuration.
- `vpffd`: the extension, built into a zip and installed once per session (skips without bpy).
"""
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
for path in (ROOT, os.path.dirname(os.path.abspath(__file__))):
    if path not in sys.path:
        sys.path.insert(0, path)

import extension_harness as eh  # noqa: E402

eh.isolate_user_resources()


@pytest.fixture(scope="session")
def vpffd(tmp_path_factory):
    """InstalledExtension(module_name, module, zip_path, user_resources) of the enabled extension."""
    return eh.installed_extension(tmp_path_factory)
