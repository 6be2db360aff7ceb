"""Application handlers, managed in one place. All are @persistent (they survive file loads) and
none lets an exception reach Blender: `update.update` records problems for the panel instead."""
import logging

import bpy
from bpy.app.handlers import persistent

from . import deformers, modifier, tracked_objects
from .bound import forget, invalidate, relink_after_undo
from .update import update_scene

log = logging.getLogger(__name__)

_updating = False  # our own writes trigger depsgraph updates: do not recurse into them


def _guarded(scene, depsgraph):
    global _updating
    if _updating or depsgraph is None:
        return
    _updating = True
    try:
        update_scene(scene, depsgraph)
    except Exception as exc:  # never raise into Blender
        log.error("update failed: %s", exc)
    finally:
        _updating = False


@persistent
def on_frame_change(scene: bpy.types.Scene, depsgraph: "bpy.types.Depsgraph | None" = None) -> None:
    """Every frame (viewport, playback, F12 and command-line renders, which pass their depsgraph)."""
    _guarded(scene, depsgraph)


@persistent
def on_depsgraph_update(scene: bpy.types.Scene, depsgraph: "bpy.types.Depsgraph | None" = None) -> None:
    """Live edits: lattice points, shape keys, transforms, settings. Objects whose inputs did not
    change are skipped by their input signature, so our own attribute writes end the loop."""
    _guarded(scene, depsgraph)


@persistent
def on_load(*_args) -> None:
    """A loaded file brings bound objects but no cached bindings: drop stale ones, lock the
    interface during renders (handlers change data), and solve the current frame."""
    forget()
    tracked_objects.forget()
    try:
        for ob in tracked_objects.local_bound():
            # Files bound by older versions have an older node group and no solver helper,
            # and settings that do not name their modifier yet.
            for d in deformers.bound(ob):
                if d.mod is not None:
                    modifier.prepare(ob, d.mod, deformers.claim(ob, d.mod))
            for scene in ob.users_scene:
                scene.render.use_lock_interface = True
        context = bpy.context
        if context.scene is not None:
            _guarded(context.scene, context.evaluated_depsgraph_get())
    except Exception as exc:
        log.error("after loading: %s", exc)


@persistent
def on_undo(*_args) -> None:
    """Undo and Redo restore the settings and the solver helpers' offsets but not the panel
    figures: solve the restored state again, so that the panel describes what is shown. The
    pipelines' caches stay: their keys hold every input, so a binding is reused exactly when the
    restored inputs are the ones it was built from (no stall after an undo). A lattice that undo
    brings back after Delete is linked again (`bound.relink_after_undo`)."""
    invalidate()
    tracked_objects.forget()
    try:
        for ob in tracked_objects.local_bound():
            for d in deformers.bound(ob):
                relink_after_undo(d, bpy.data.objects)
        context = bpy.context
        if context.scene is not None:
            _guarded(context.scene, context.evaluated_depsgraph_get())
    except Exception as exc:
        log.error("after undo: %s", exc)


_HANDLERS = (
    (bpy.app.handlers.frame_change_post, on_frame_change),
    (bpy.app.handlers.depsgraph_update_post, on_depsgraph_update),
    (bpy.app.handlers.load_post, on_load),
    (bpy.app.handlers.undo_post, on_undo),
    (bpy.app.handlers.redo_post, on_undo),
)


def register():
    for handlers, fn in _HANDLERS:
        if fn not in handlers:
            handlers.append(fn)


def unregister():
    for handlers, fn in _HANDLERS:
        while fn in handlers:
            handlers.remove(fn)
    forget()
