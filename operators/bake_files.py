"""The cache files a bake writes: their formats, their paths, and the error a bake or a switch
raises.

Paths: only a file the user named is written, resolved with `bpy.path.abspath` (symbolic links
followed). Refused: an empty name, a `//` path while the .blend is unsaved, any other relative path
(it would land in Blender's working folder), a name without the format's extension, a folder, an
existing file that is not a cache of that format, a missing folder (unless "Create Folder" is on:
then that one folder is made, inside an existing one, and nothing more). Writing is atomic
(`vpffd_addon.pointcache`): a cancelled or failed bake leaves nothing under the final name.
"""
import os
import tempfile

import bpy

from ..vpffd_addon import pointcache


FORMATS = {"PC2": ".pc2", "MDD": ".mdd"}


FORMAT_ITEMS = [
    ("PC2", "PC2", "Point Cache 2 (little-endian float32; start frame and rate in the header)"),
    ("MDD", "MDD", "LightWave MDD (big-endian float32 with a time stamp per frame)"),
]


class BakeError(ValueError):
    """A bake or switch that cannot be done; the message says what to change."""


def os_error_words(exc):
    """The readable part of an OSError (its strerror), else the exception's text."""
    return getattr(exc, "strerror", None) or str(exc)


def check_format(fmt):
    f = str(fmt).upper()
    if f not in FORMATS:
        raise BakeError(f"unknown cache format {fmt!r}; expected one of {', '.join(FORMATS)}")
    return f


def default_filepath(obj, fmt="PC2"):
    """``//vpffd_<object name><.pc2|.mdd>`` next to the .blend file; for a file not saved yet, the
    same name in Blender's temporary folder (Preferences > File Paths), else the system's."""
    name = f"vpffd_{bpy.path.clean_name(obj.name)}{FORMATS[check_format(fmt)]}"
    if bpy.data.filepath:
        return "//" + name
    return os.path.join(temporary_folder(), name)


def temporary_folder():
    """Blender's temporary folder (Preferences > File Paths > Temporary Files) when it is set and
    exists, else the system's."""
    folder = bpy.path.abspath(bpy.context.preferences.filepaths.temporary_directory or "")
    return folder if folder and os.path.isdir(folder) else tempfile.gettempdir()


def absolute_path(filepath):
    """The absolute, normalised path for a user's `filepath`, or BakeError (no file access)."""
    if not isinstance(filepath, str) or not filepath.strip():
        raise BakeError("choose a file for the cache")
    if "\0" in filepath:
        raise BakeError("the cache path contains a NUL character")
    if filepath.startswith("//"):
        if not bpy.data.filepath:
            raise BakeError(f"'{filepath}' is relative to the .blend file, which is not saved yet: "
                            "save the file first, or give an absolute path")
        path = bpy.path.abspath(filepath)
    else:
        path = filepath
    if not os.path.isabs(path):
        raise BakeError(f"'{filepath}' is a relative path, which would land in Blender's working "
                        "folder: give an absolute path, or one relative to the .blend file ('//')")
    return os.path.normpath(path)


def resolve_path(filepath, fmt="PC2", make_folder=False):
    """The absolute path a bake of format `fmt` would write for the user's `filepath`
    (symbolic links resolved), or BakeError saying why it is refused. Touches nothing."""
    fmt = check_format(fmt)
    path = os.path.realpath(absolute_path(filepath))
    ext = FORMATS[fmt]
    if not path.lower().endswith(ext):
        raise BakeError(f"a {fmt} cache file name must end in '{ext}': {path}")
    if os.path.isdir(path):
        raise BakeError(f"{path} is a folder: name a file")
    if os.path.lexists(path):
        if not os.path.isfile(path):
            raise BakeError(f"{path} exists and is not a regular file: not overwriting it")
        try:
            pointcache.cache_info(path, fmt)
        except ValueError:
            raise BakeError(f"{path} exists and is not a {fmt} cache: not overwriting it") from None
        except OSError as exc:
            raise BakeError(f"cannot read the existing {path}: {os_error_words(exc)}") from None
    folder = os.path.dirname(path)
    if not os.path.isdir(folder):
        if not (make_folder and os.path.isdir(os.path.dirname(folder))):
            hint = (" (Create Folder makes only the file's own folder, inside an existing one)"
                    if make_folder else "; create it, or turn on Create Folder")
            raise BakeError(f"folder {folder} does not exist{hint}")
    elif not os.access(folder, os.W_OK):
        raise BakeError(f"cannot write in folder {folder}")
    return path


def prepare_folder(path, make_folder):
    folder = os.path.dirname(path)
    if os.path.isdir(folder):
        return
    if not make_folder:
        raise BakeError(f"folder {folder} does not exist")
    try:
        os.mkdir(folder)  # one level only: its parent was checked to exist
    except OSError as exc:
        raise BakeError(f"cannot create folder {folder}: {os_error_words(exc)}") from None


# ------------------------------------------------------------------------------- the modifier
