"""Bake: the volume-preserved deformation of a frame range written to a point cache (PC2, or MDD)
that Blender's own Mesh Cache modifier reads, and a switch between that cache and the live solve.

A baked frame is what the (last) VP-FFD slot gives on that frame (the positions that reach it plus
the offsets VP-FFD writes, `update.slot_output`), so the cache reproduces the live result. Modifiers
before it, other VP-FFD modifiers included, are baked in. `switch_to_cache` puts a Mesh Cache modifier where the VP-FFD modifier
is in the stack and disables (does not delete) the VP-FFD modifier: a file saved that way renders on a machine
without the extension. `switch_to_live` goes back; the cache modifier stays, disabled, remembering
its file for `switch_to_cache` again.

Frame mapping, from Blender's MOD_meshcache.cc: with Play Mode *Scene* and Time Mode *Frame* the
modifier reads cache frame ``frame_scale * scene_time - frame_start``; so ``frame_start`` = the
bake's first frame and ``frame_scale`` = 1 make scene frame f read the frame baked at f (with Time
Stretching, scene time is frame * old/new, and ``frame_scale`` = new/old undoes it). Frames
outside the baked range show the first or last baked frame; between frames (motion blur
sub-frames) the modifier interpolates linearly.

The files and their paths: `bake_files.py`; the switch between cache and live solve:
`cache_switch.py`; the operators and the Bake sub-panel: `bake_ops.py`.
"""
import logging
import time
from typing import NamedTuple

import bpy
import numpy as np

from ..vpffd_addon import pointcache
from . import deformers
from .bake_files import BakeError, check_format, os_error_words, prepare_folder, resolve_path
from .cache_modifier import find_cache
from .cache_switch import check_bakeable, live_modifiers, switch_to_cache
from .status import status
from .update import slot_output, update_object

log = logging.getLogger(__name__)


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


class Baker:
    """One bake, a frame at a time (the modal operator steps it from a timer):
    ``b = Baker(...); b.start(); while not b.step(): ...; result = b.finish()``, or `b.abort()`.

    Validates everything in the constructor (BakeError), writes nothing before `start()`, and
    writes the final file only in `finish()`. While it runs, the VP-FFD modifiers are on and the
    cache modifier off; `finish`/`abort` restore them and the scene's frame."""

    def __init__(self, obj, scene, filepath, frame_start, frame_end, fmt="PC2", make_folder=False):
        self.fmt = check_format(fmt)
        self.deformer = check_bakeable(obj, scene)
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
        prepare_folder(self.path, self.make_folder)
        self._t0 = time.perf_counter()
        cache = find_cache(obj)
        mods = live_modifiers(obj)
        self._saved = (scene.frame_current, scene.frame_subframe,
                       [(m, m.show_viewport, m.show_render) for m in mods],
                       None if cache is None else (cache.show_viewport, cache.show_render))
        for m in mods:
            m.show_viewport = True
        if cache is not None:
            cache.show_viewport = False
        # The cache holds what the VP-FFD slot gives, so its point count is the slot's.
        self.scene.frame_set(self.frame_start)
        update_object(obj, self._depsgraph(), force=True)
        first = slot_output(self.deformer)
        error = self._error()
        if error or first is None:
            self._restore()
            raise BakeError(f"frame {self.frame_start}: {error or 'no result'}")
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
            raise BakeError(f"cannot write {self.path}: {os_error_words(exc)}") from None

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

    def _error(self):
        """The first error of the object's deformers on this frame, or None."""
        for d in deformers.bound(self.obj):
            error = status(d).error if d.mod is not None else None
            if error:
                return error
        return None

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
        update_object(self.obj, depsgraph)
        error = self._error()
        if error:
            raise BakeError(f"frame {f}: {error}")
        coords = slot_output(self.deformer)
        if coords is None or len(coords) != self.n_points:
            raise BakeError(f"frame {f}: the number of points reaching VP-FFD changed "
                            f"({self.n_points} at the first frame)")
        try:
            self._writer.write_frame(coords)
        except ValueError as exc:
            raise BakeError(f"frame {f}: {exc}") from None
        except OSError as exc:
            raise BakeError(f"cannot write {self.path}: {os_error_words(exc)}") from None
        self.done += 1
        return self.done == self.total

    def finish(self):
        """Move the complete file into place and restore the scene; returns a BakeResult."""
        try:
            path = self._writer.commit()
        except (OSError, ValueError) as exc:
            self._restore()
            raise BakeError(f"cannot write {self.path}: {os_error_words(exc)}") from None
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
        present = set(live_modifiers(self.obj))
        for m, viewport, render in vp_flags:
            if m in present:
                m.show_viewport, m.show_render = viewport, render
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
