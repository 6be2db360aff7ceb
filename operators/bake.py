"""Bake: the volume-preserved deformation of a frame range written to a point cache (PC2, or MDD)
that Blender's own Mesh Cache modifier reads, and a switch between that cache and the live solve.

A baked frame is what the VP-FFD slot gives on that frame (the positions that reach it plus the
offsets VP-FFD writes, `update.slot_output`), so the cache reproduces the live result. Modifiers
before VP-FFD are baked in. `switch_to_cache` puts a Mesh Cache modifier where the VP-FFD modifier
is in the stack and disables (does not delete) the VP-FFD modifier: a file saved that way renders on a machine
without the extension. `switch_to_live` goes back; the cache modifier stays, disabled, remembering
its file for `switch_to_cache` again.

Frame mapping, from Blender's MOD_meshcache.cc: with Play Mode *Scene* and Time Mode *Frame* the
modifier reads cache frame ``frame_scale * scene_time - frame_start``; so ``frame_start`` = the
bake's first frame and ``frame_scale`` = 1 make scene frame f read the frame baked at f (with Time
Stretching, scene time is frame * old/new, and ``frame_scale`` = new/old undoes it). Frames
outside the baked range show the first or last baked frame; between frames (motion blur
sub-frames) the modifier interpolates linearly.

Paths: only a file the user named is written, resolved with `bpy.path.abspath` (symbolic links
followed). Refused: an empty name, a `//` path while the .blend is unsaved, any other relative path
(it would land in Blender's working folder), a name without the format's extension, a folder, an
existing file that is not a cache of that format, a missing folder (unless "Create Folder" is on:
then that one folder is made, inside an existing one, and nothing more). Writing is atomic
(`vpffd_addon.pointcache`): a cancelled or failed bake leaves nothing under the final name.
"""
import logging
import os
import tempfile
import time
from typing import NamedTuple

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty

from ..vpffd_addon import pointcache
from . import modifier
from .cache_modifier import CACHE_MODIFIER_NAME, find_cache, using_cache
from .text import report
from .status import status
from .update import slot_output, update

log = logging.getLogger(__name__)

FORMATS = {"PC2": ".pc2", "MDD": ".mdd"}
FORMAT_ITEMS = [
    ("PC2", "PC2", "Point Cache 2 (little-endian float32; start frame and rate in the header)"),
    ("MDD", "MDD", "LightWave MDD (big-endian float32 with a time stamp per frame)"),
]
# Path properties that accept '//' without a warning (the option is in 5.0, not in 4.2).
_PATH_OPTIONS = ({"SKIP_SAVE", "PATH_SUPPORTS_BLEND_RELATIVE"}
                 if "is_path_supports_blend_relative" in bpy.types.Property.bl_rna.properties
                 else {"SKIP_SAVE"})
# Frames baked per timer event: as many as fit in this time (at least one). The window redraws
# after each event, so a short budget ties the bake's speed to redrawing the viewport.
_MODAL_BUDGET_S = 0.5


class BakeError(ValueError):
    """A bake or switch that cannot be done; the message says what to change."""


class BakeCancelled(Exception):
    """The bake was cancelled; nothing was written under the final name."""


class BakeResult(NamedTuple):
    filepath: str        # absolute path written
    format: str          # 'PC2' or 'MDD'
    frame_start: int
    frame_end: int
    n_verts: int
    seconds: float


# ------------------------------------------------------------------------------------- paths

def _why(exc):
    """The readable part of an OSError (its strerror), else the exception's text."""
    return getattr(exc, "strerror", None) or str(exc)


def _check_format(fmt):
    f = str(fmt).upper()
    if f not in FORMATS:
        raise BakeError(f"unknown cache format {fmt!r}; expected one of {', '.join(FORMATS)}")
    return f


def default_filepath(obj, fmt="PC2"):
    """``//vpffd_<object name><.pc2|.mdd>`` next to the .blend file; for a file not saved yet, the
    same name in Blender's temporary folder (Preferences > File Paths), else the system's."""
    name = f"vpffd_{bpy.path.clean_name(obj.name)}{FORMATS[_check_format(fmt)]}"
    if bpy.data.filepath:
        return "//" + name
    return os.path.join(temporary_folder(), name)


def temporary_folder():
    """Blender's temporary folder (Preferences > File Paths > Temporary Files) when it is set and
    exists, else the system's."""
    folder = bpy.path.abspath(bpy.context.preferences.filepaths.temporary_directory or "")
    return folder if folder and os.path.isdir(folder) else tempfile.gettempdir()


def _absolute(filepath):
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
    fmt = _check_format(fmt)
    path = os.path.realpath(_absolute(filepath))
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
            raise BakeError(f"cannot read the existing {path}: {_why(exc)}") from None
    folder = os.path.dirname(path)
    if not os.path.isdir(folder):
        if not (make_folder and os.path.isdir(os.path.dirname(folder))):
            hint = (" (Create Folder makes only the file's own folder, inside an existing one)"
                    if make_folder else "; create it, or turn on Create Folder")
            raise BakeError(f"folder {folder} does not exist{hint}")
    elif not os.access(folder, os.W_OK):
        raise BakeError(f"cannot write in folder {folder}")
    return path


def _prepare_folder(path, make_folder):
    folder = os.path.dirname(path)
    if os.path.isdir(folder):
        return
    if not make_folder:
        raise BakeError(f"folder {folder} does not exist")
    try:
        os.mkdir(folder)  # one level only: its parent was checked to exist
    except OSError as exc:
        raise BakeError(f"cannot create folder {folder}: {_why(exc)}") from None


# ------------------------------------------------------------------------------- the modifier

def check_bakeable(obj, scene=None):
    """Raise BakeError naming what stops `obj` from being baked (in `scene`)."""
    if obj is None or obj.type != "MESH":
        raise BakeError("select a mesh object bound with VP-FFD")
    if not obj.vpffd.is_bound:
        raise BakeError(f"'{obj.name}' is not bound to a lattice: Bind it first")
    vp_mod = modifier.find(obj)
    if vp_mod is None:
        raise BakeError("the VP-FFD modifier was removed: Bind again")
    if obj.mode == "EDIT":
        raise BakeError("leave Edit Mode before baking")
    if scene is not None and scene.objects.get(obj.name) != obj:
        raise BakeError(f"'{obj.name}' is not in scene '{scene.name}'")
    return vp_mod


def _move_before(obj, mod, target):
    """Move modifier `mod` directly above `target` in obj's stack."""
    names = [m.name for m in obj.modifiers]
    cur, want = names.index(mod.name), names.index(target.name)
    if cur == want - 1:
        return
    index = want - 1 if cur < want else want
    if hasattr(obj.modifiers, "move"):
        obj.modifiers.move(cur, index)
    else:
        with bpy.context.temp_override(object=obj, active_object=obj):
            bpy.ops.object.modifier_move_to_index(modifier=mod.name, index=index)
    names = [m.name for m in obj.modifiers]
    if names.index(mod.name) != names.index(target.name) - 1:
        raise BakeError(f"could not move '{mod.name}' above '{target.name}': move it by hand")


def _cache_path_for_reading(filepath):
    try:
        return _absolute(filepath)
    except BakeError as exc:
        raise BakeError(f"cache file: {exc}") from None


def switch_to_cache(obj, filepath, fmt="PC2", frame_start=None, scene=None):
    """Play the baked cache `filepath` through a Mesh Cache modifier (placed where the VP-FFD
    modifier is) and disable the VP-FFD modifier, so the object needs no extension.

    `frame_start`: scene frame of the cache's first frame (the bake's first frame); None reads it
    from the file (PC2 header start frame, or the first MDD time stamp times the scene's fps).
    The path is stored as given (a `//` path stays relative to the .blend). Raises BakeError when
    the file is missing, not a cache of format `fmt`, or holds a different number of points than
    the mesh has vertices. `scene` (default: the context's) gives the fps for MDD and the time
    stretching to undo. Returns the Mesh Cache modifier."""
    fmt = _check_format(fmt)
    if obj is None or obj.type != "MESH":
        raise BakeError("select a mesh object")
    vp_mod = modifier.find(obj)
    if vp_mod is None:
        raise BakeError(f"'{obj.name}' has no VP-FFD modifier to replace")
    path = _cache_path_for_reading(filepath)
    try:
        info = pointcache.cache_info(path, fmt)
    except FileNotFoundError:
        raise BakeError(f"cache file {path} does not exist: Bake first") from None
    except ValueError as exc:
        raise BakeError(str(exc)) from None
    except OSError as exc:
        raise BakeError(f"cannot read {path}: {_why(exc)}") from None
    # The cache replaces what reaches the VP-FFD slot: its point count is the slot's.
    live = slot_output(obj)
    n = len(obj.data.vertices) if live is None else len(live)
    if info["points"] != n:
        raise BakeError(f"{path} holds {info['points']} points but {n} reach the VP-FFD modifier "
                        f"of '{obj.name}': bake again")
    if frame_start is None:
        if fmt == "PC2":
            frame_start = info["start_frame"]
        else:
            render = (scene or bpy.context.scene).render
            fps = render.fps / render.fps_base
            frame_start = round(info["start_time"] * fps, 3)

    cache = find_cache(obj)
    if cache is None:
        cache = obj.modifiers.new(CACHE_MODIFIER_NAME, "MESH_CACHE")
    cache.cache_format = fmt
    cache.filepath = filepath
    cache.play_mode = "SCENE"
    cache.time_mode = "FRAME"
    cache.frame_start = float(frame_start)
    # Scene time = frame * frame_map_old / frame_map_new (Time Stretching; 1 by default): scale
    # it back so scene frame f reads the frame baked at f (checked: exact with 100 -> 150).
    render = (scene or bpy.context.scene).render
    cache.frame_scale = render.frame_map_new / render.frame_map_old
    cache.interpolation = "LINEAR"
    cache.deform_mode = "OVERWRITE"
    cache.factor = 1.0
    cache.vertex_group = ""
    cache.forward_axis, cache.up_axis = "POS_Y", "POS_Z"
    try:
        cache.flip_axis = (False, False, False)   # Blender 5: a boolean array
    except TypeError:
        cache.flip_axis = set()                   # Blender 4.2: an enum set
    _move_before(obj, cache, vp_mod)
    cache.show_viewport = cache.show_render = True
    vp_mod.show_viewport = vp_mod.show_render = False
    obj.update_tag()
    return cache


def switch_to_live(obj):
    """Solve live again: enable the VP-FFD modifier and disable the cache modifier (kept, with its
    file, for `switch_to_cache`). Raises BakeError when the VP-FFD modifier is gone."""
    if obj is None or obj.type != "MESH":
        raise BakeError("select a mesh object")
    vp_mod = modifier.find(obj)
    if vp_mod is None:
        raise BakeError(f"'{obj.name}' has no VP-FFD modifier to switch back to: Bind again")
    cache = find_cache(obj)
    if cache is not None:
        cache.show_viewport = cache.show_render = False
    vp_mod.show_viewport = vp_mod.show_render = True
    if obj.vpffd.is_bound:
        update(obj, bpy.context.evaluated_depsgraph_get(), force=True)  # never raises
    obj.update_tag()


# -------------------------------------------------------------------------------------- bake

class Baker:
    """One bake, a frame at a time (the modal operator steps it from a timer):
    ``b = Baker(...); b.start(); while not b.step(): ...; result = b.finish()``, or `b.abort()`.

    Validates everything in the constructor (BakeError), writes nothing before `start()`, and
    writes the final file only in `finish()`. While it runs, the VP-FFD modifier is on and the
    cache modifier off; `finish`/`abort` restore them and the scene's frame."""

    def __init__(self, obj, scene, filepath, frame_start, frame_end, fmt="PC2", make_folder=False):
        self.fmt = _check_format(fmt)
        self.vp_mod = check_bakeable(obj, scene)
        self.obj, self.scene = obj, scene
        try:
            self.frame_start, self.frame_end = int(frame_start), int(frame_end)
        except (TypeError, ValueError):
            raise BakeError(f"frames must be integers, got {frame_start!r} and {frame_end!r}") \
                from None
        if self.frame_end < self.frame_start:
            raise BakeError(f"the end frame ({self.frame_end}) is before the start frame "
                            f"({self.frame_start})")
        self.filepath = filepath
        self.make_folder = bool(make_folder)
        self.path = resolve_path(filepath, self.fmt, self.make_folder)
        self.frames = range(self.frame_start, self.frame_end + 1)
        self.done = 0
        self._writer = None
        self._saved = None
        self._t0 = None

    @property
    def total(self):
        return len(self.frames)

    @property
    def current_frame(self):
        return self.frames[min(self.done, self.total - 1)]

    def start(self):
        obj, scene = self.obj, self.scene
        check_bakeable(obj, scene)
        _prepare_folder(self.path, self.make_folder)
        self._t0 = time.perf_counter()
        cache = find_cache(obj)
        self._saved = (scene.frame_current, scene.frame_subframe,
                       (self.vp_mod.show_viewport, self.vp_mod.show_render),
                       None if cache is None else (cache.show_viewport, cache.show_render))
        self.vp_mod.show_viewport = True
        if cache is not None:
            cache.show_viewport = False
        # The cache holds what the VP-FFD slot gives, so its point count is the slot's.
        self.scene.frame_set(self.frame_start)
        update(obj, self._depsgraph(), force=True)
        first = slot_output(obj)
        if status(obj).error or first is None:
            self._restore()
            raise BakeError(f"frame {self.frame_start}: {status(obj).error or 'no result'}")
        n = self.n_points = len(first)
        try:
            if self.fmt == "PC2":
                self._writer = pointcache.PC2Writer(self.path, n, self.total, self.frame_start, 1.0)
            else:
                fps = scene.render.fps / scene.render.fps_base
                times = np.arange(self.frame_start, self.frame_end + 1, dtype=np.float64) / fps
                self._writer = pointcache.MDDWriter(self.path, n, times)
        except (OSError, ValueError) as exc:
            self._restore()
            raise BakeError(f"cannot write {self.path}: {_why(exc)}") from None

    def _depsgraph(self):
        ctx = bpy.context
        if ctx.scene == self.scene and ctx.view_layer is not None:
            return ctx.evaluated_depsgraph_get()
        for layer in self.scene.view_layers:
            if layer.objects.get(self.obj.name) == self.obj:
                depsgraph = layer.depsgraph
                depsgraph.update()
                return depsgraph
        raise BakeError(f"'{self.obj.name}' is in no view layer of scene '{self.scene.name}'")

    def step(self):
        """Bake the next frame. Returns True once every frame is baked."""
        if self._writer is None or self._writer.closed:
            raise BakeError("the bake is not running")
        f = self.frames[self.done]
        self.scene.frame_set(f)
        depsgraph = self._depsgraph()
        # The frame handler has already solved this frame; a non-forced update re-solves exactly
        # when the inputs differ from that solve. `start` forced the first frame's solve, so no
        # stale state (e.g. an undo) can slip in.
        update(self.obj, depsgraph)
        error = status(self.obj).error
        if error:
            raise BakeError(f"frame {f}: {error}")
        coords = slot_output(self.obj)
        if coords is None or len(coords) != self.n_points:
            raise BakeError(f"frame {f}: the number of points reaching VP-FFD changed "
                            f"({self.n_points} at the first frame)")
        try:
            self._writer.write_frame(coords)
        except ValueError as exc:
            raise BakeError(f"frame {f}: {exc}") from None
        except OSError as exc:
            raise BakeError(f"cannot write {self.path}: {_why(exc)}") from None
        self.done += 1
        return self.done == self.total

    def finish(self):
        """Move the complete file into place and restore the scene; returns a BakeResult."""
        try:
            path = self._writer.commit()
        except (OSError, ValueError) as exc:
            self._restore()
            raise BakeError(f"cannot write {self.path}: {_why(exc)}") from None
        self._restore()
        return BakeResult(path, self.fmt, self.frame_start, self.frame_end, self.n_points,
                          time.perf_counter() - self._t0)

    def abort(self):
        """Discard what was written (nothing appears under the final name); restore the scene."""
        if self._writer is not None:
            self._writer.abort()
        self._restore()

    def _restore(self):
        if self._saved is None:
            return
        frame, subframe, vp_flags, cache_flags = self._saved
        self._saved = None
        if modifier.find(self.obj) == self.vp_mod:
            self.vp_mod.show_viewport, self.vp_mod.show_render = vp_flags
        cache = find_cache(self.obj)
        if cache is not None and cache_flags is not None:
            cache.show_viewport, cache.show_render = cache_flags
        self.scene.frame_set(frame, subframe=subframe)


def bake(obj, scene, filepath, frame_start, frame_end, fmt="PC2", progress=None, cancelled=None,
         make_folder=False, switch=False):
    """Bake `obj`'s deformation for scene frames frame_start..frame_end (inclusive) to the point
    cache `filepath` (format 'PC2' or 'MDD'); returns a BakeResult.

    progress(done, total) is called after each frame; cancelled() before each frame: when it
    returns True the bake stops, nothing is written under `filepath`, and BakeCancelled is
    raised. With `switch`, the object then plays the cache (`switch_to_cache`). Raises BakeError
    (a ValueError) for anything the user must change. The scene's frame is restored."""
    baker = Baker(obj, scene, filepath, frame_start, frame_end, fmt, make_folder)
    baker.start()
    try:
        finished = False
        while not finished:
            if cancelled is not None and cancelled():
                raise BakeCancelled(f"bake cancelled after {baker.done} of {baker.total} frames; "
                                    f"nothing was written to {baker.path}")
            finished = baker.step()
            if progress is not None:
                progress(baker.done, baker.total)
    except BaseException:
        baker.abort()
        raise
    result = baker.finish()
    if switch:
        switch_to_cache(obj, filepath, result.format, result.frame_start, scene)
    return result


# --------------------------------------------------------------------------------- operators

def _format_changed(self, _context):
    """Keep the file name's extension in step with the chosen format."""
    root, ext = os.path.splitext(self.filepath)
    new = FORMATS[self.format]
    if ext.lower() in FORMATS.values() and ext.lower() != new:
        self.filepath = root + new


def _bound_mesh(context):
    ob = context.object
    return ob is not None and ob.type == "MESH" and ob.vpffd.is_bound


class OBJECT_OT_vpffd_bake(bpy.types.Operator):
    """Bake the volume-preserved deformation of a frame range to a point cache (PC2 or MDD) that
    Blender's Mesh Cache modifier plays without this extension"""
    bl_idname = "object.vpffd_bake"
    bl_label = "Bake to Point Cache"
    bl_options = {"REGISTER"}  # no redo panel: changing a setting must not silently re-bake
    _baker = None
    _timer = None

    filepath: StringProperty(
        name="File", subtype="FILE_PATH", default="", options=_PATH_OPTIONS,
        description="Cache file to write; empty: vpffd_<object>.pc2 next to the .blend file (in the "
                    "temporary folder while the file is not saved)")
    format: EnumProperty(
        name="Format", items=FORMAT_ITEMS, default="PC2", update=_format_changed,
        description="Point cache format (both are read by Blender's Mesh Cache modifier)")
    frame_start: IntProperty(
        name="Start", options={"SKIP_SAVE"},
        description="First frame to bake (default: the scene's start frame)")
    frame_end: IntProperty(
        name="End", options={"SKIP_SAVE"},
        description="Last frame to bake (default: the scene's end frame)")
    use_switch: BoolProperty(
        name="Switch to Cache", default=True,
        description="Afterwards, play the cache through a Mesh Cache modifier and disable the "
                    "VP-FFD modifier (switch back any time)")
    make_folder: BoolProperty(
        name="Create Folder", default=False, options={"SKIP_SAVE"},
        description="Create the file's folder if it does not exist (that one folder only)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _bound_mesh(context)

    def _fill_defaults(self, context):
        scene = context.scene
        if not self.filepath:
            self.filepath = default_filepath(context.object, self.format)
        if not self.properties.is_property_set("frame_start"):
            self.frame_start = scene.frame_start
        if not self.properties.is_property_set("frame_end"):
            self.frame_end = scene.frame_end

    def invoke(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        self._fill_defaults(context)
        return context.window_manager.invoke_props_dialog(self, width=420)

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        layout.use_property_split = True
        layout.prop(self, "filepath")
        if not bpy.data.filepath:
            col = layout.column(align=True)
            if self.filepath.startswith("//"):
                texts = ("The .blend file is not saved: a path starting with // has no folder.",
                         "Save the file first, or choose a folder.")
            else:
                texts = ("The .blend file is not saved: the cache goes to the temporary folder.",
                         "Save the file first to keep the cache next to it.")
            for k, text in enumerate(texts):
                col.label(text=text, icon="INFO" if k == 0 else "BLANK1")
        layout.prop(self, "make_folder")
        layout.prop(self, "format")
        col = layout.column(align=True)
        col.prop(self, "frame_start")
        col.prop(self, "frame_end")
        layout.prop(self, "use_switch")

    def execute(self, context: bpy.types.Context) -> set[str]:
        self._fill_defaults(context)
        try:
            baker = Baker(context.object, context.scene, self.filepath, self.frame_start,
                          self.frame_end, self.format, self.make_folder)
            baker.start()
        except BakeError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        self._baker = baker
        if bpy.app.background or context.window is None:
            return self._run_blocking()
        wm = context.window_manager
        wm.progress_begin(0, baker.total)
        self._timer = wm.event_timer_add(0.001, window=context.window)
        wm.modal_handler_add(self)
        self._status(context)
        return {"RUNNING_MODAL"}

    def _run_blocking(self):
        baker = self._baker
        step = max(1, baker.total // 10)
        try:
            while not baker.step():
                if baker.done % step == 0:
                    log.info("baked %d/%d frames", baker.done, baker.total)
        except BakeError as exc:
            baker.abort()
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        except BaseException:
            baker.abort()
            raise
        return self._finish()

    def _finish(self):
        try:
            result = self._baker.finish()
            if self.use_switch:
                switch_to_cache(self._baker.obj, self.filepath, result.format, result.frame_start,
                                self._baker.scene)
        except BakeError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        report(self, "INFO", f"baked frames {result.frame_start}-{result.frame_end} "
                              f"({result.n_verts:,} vertices) to {result.filepath} "
                              f"in {result.seconds:.1f} s")
        return {"FINISHED"}

    def _status(self, context, text=None):
        workspace = getattr(context, "workspace", None)
        if workspace is None:
            return
        if text is None and self._baker is not None:
            b = self._baker
            text = (f"VP-FFD: baking '{b.obj.name}' frame {b.current_frame} "
                    f"({b.done}/{b.total}); Esc to cancel")
        workspace.status_text_set(text)

    def _stop(self, context):
        wm = context.window_manager
        if getattr(self, "_timer", None) is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        workspace = getattr(context, "workspace", None)
        if workspace is not None:
            workspace.status_text_set(None)

    def modal(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        try:
            return self._modal(context, event)
        except BaseException as exc:  # never leave a running bake (or its temporary file) behind
            self._stop(context)
            self._baker.abort()
            report(self, "ERROR", f"bake failed: {type(exc).__name__}: {exc}")
            return {"CANCELLED"}

    def _modal(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        baker = self._baker
        if event.type == "ESC" and event.value == "PRESS":
            self._stop(context)
            baker.abort()
            report(self, "WARNING", f"bake cancelled after {baker.done} of {baker.total} "
                                     f"frames; nothing was written to {baker.path}")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"RUNNING_MODAL"}  # the scene changes frame under the user: keep input out
        deadline = time.perf_counter() + _MODAL_BUDGET_S
        try:
            finished = baker.step()
            while not finished and time.perf_counter() < deadline:
                finished = baker.step()
        except BakeError as exc:
            self._stop(context)
            baker.abort()
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        context.window_manager.progress_update(baker.done)
        if not finished:
            self._status(context)
            return {"RUNNING_MODAL"}
        self._stop(context)
        status = self._finish()
        if status == {"FINISHED"} and self.use_switch:
            try:
                bpy.ops.ed.undo_push(message="VP-FFD: Switch to Cache")
            except RuntimeError:
                pass
        return status

    def cancel(self, context: bpy.types.Context) -> None:
        """Blender ended the modal operator (e.g. a file was loaded): discard the bake."""
        self._stop(context)
        if getattr(self, "_baker", None) is not None:
            self._baker.abort()


class OBJECT_OT_vpffd_use_cache(bpy.types.Operator):
    """Play the baked point cache through Blender's Mesh Cache modifier and disable the VP-FFD
    modifier (kept, to switch back): the file then needs no extension to render"""
    bl_idname = "object.vpffd_use_cache"
    bl_label = "Use Baked Cache"
    bl_options = {"REGISTER", "UNDO"}

    filepath: StringProperty(
        name="File", subtype="FILE_PATH", default="", options=_PATH_OPTIONS,
        description="Cache file; empty: the one the cache modifier already names")
    format: EnumProperty(name="Format", items=FORMAT_ITEMS, default="PC2", options={"SKIP_SAVE"})
    frame_start: IntProperty(
        name="Start", options={"SKIP_SAVE"},
        description="Scene frame of the cache's first frame (default: read from the file)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        ob = context.object
        return ob is not None and ob.type == "MESH" and modifier.find(ob) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        ob = context.object
        try:
            if self.filepath:
                start = self.frame_start if self.properties.is_property_set("frame_start") else None
                switch_to_cache(ob, self.filepath, self.format, start, context.scene)
            else:
                cache = find_cache(ob)
                if cache is None or not cache.filepath:
                    raise BakeError("nothing baked yet: Bake first")
                switch_to_cache(ob, cache.filepath, cache.cache_format, cache.frame_start,
                                context.scene)
        except BakeError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class OBJECT_OT_vpffd_use_live(bpy.types.Operator):
    """Solve live again: enable the VP-FFD modifier and disable the cache modifier"""
    bl_idname = "object.vpffd_use_live"
    bl_label = "Use Live Solve"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        ob = context.object
        return ob is not None and ob.type == "MESH" and modifier.find(ob) is not None

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            switch_to_live(context.object)
        except BakeError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


classes = (OBJECT_OT_vpffd_bake, OBJECT_OT_vpffd_use_cache, OBJECT_OT_vpffd_use_live)


def draw_bake(layout, obj):
    """The Bake sub-panel of the VP-FFD panel for `obj`."""
    col = layout.column()
    cache = find_cache(obj)
    if cache is not None and using_cache(obj):
        col.label(text=f"Playing the {cache.cache_format} cache {cache.filepath}.", icon="FILE_CACHE")
        if modifier.find(obj) is not None and modifier.find(obj).show_viewport:
            col.label(text="The VP-FFD modifier is on too: its offsets add to the cache.",
                      icon="ERROR")
    row = col.row(align=True)
    row.operator("object.vpffd_bake", icon="EXPORT")
    if cache is not None:
        if using_cache(obj):
            row.operator("object.vpffd_use_live", icon="MOD_LATTICE")
        else:
            row.operator("object.vpffd_use_cache", icon="FILE_CACHE")
