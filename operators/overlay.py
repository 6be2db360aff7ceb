"""Viewport overlay: the corrected lattice or cage (the control points the solver used), the box
where a lattice's falloff ends (Outside: Falloff), and the volume percentage next to each bound
object whose "Show Corrected Lattice" is on.

Only the draw callbacks touch `gpu`/`blf`, and only when Blender draws a 3D viewport; nothing runs
at import or registration, and nothing is drawn in background mode.
"""
import logging

import bpy
import numpy as np

from ..vpffd_addon import wireframe
from . import deformers, tracked_objects
from .bound import state_of
from .status import status
from .text import percent

log = logging.getLogger(__name__)

LATTICE_COLOUR = (0.15, 0.85, 0.95, 0.9)
FALLOFF_COLOUR = (1.0, 0.6, 0.2, 0.6)
TEXT_COLOUR = (1.0, 1.0, 1.0, 0.95)

_handles = []


def lines(points, edges):
    """(2 * E, 3) segment end points for points (N, 3) joined by edges (E, 2)."""
    return np.asarray(points, float)[np.asarray(edges, np.int64)].reshape(-1, 3)


def overlay_geometry(target):
    """(corrected lattice or cage points in world space (N, 3), edges (E, 2), label) of the last
    solve of deformer `target` (or of a mesh object's first), or None before the first one."""
    state = state_of(target)
    if state is None or getattr(state, "overlay", None) is None:
        return None
    info = status(target)
    if info.error or info.paused or info.switched_off:
        return None     # the mesh shows no correction now: drawing the last one would be false
    label = f"{percent(info.volume_percent)} volume" if info.volume_percent is not None else ""
    return state.overlay + (label,)


def falloff_geometry(target):
    """(corners in world space (8, 3), edges (12, 2)) of the box where the falloff of the last
    solve ends, or None (no falloff, or nothing shown now)."""
    state = state_of(target)
    if overlay_geometry(target) is None or getattr(state, "falloff_box", None) is None:
        return None
    return state.falloff_box, wireframe.BOX_EDGES


def _visible(context):
    """(object, deformer, drawn) of every bound deformer whose overlay is on and shown."""
    for ob in tracked_objects.shown(context.view_layer):
        for d in deformers.bound(ob):
            if d.settings.show_overlay:
                drawn = overlay_geometry(d)
                if drawn is not None:
                    yield ob, d, drawn


def _draw_lattices():
    try:
        import gpu
        from gpu_extras.batch import batch_for_shader
        context = bpy.context
        shader = gpu.shader.from_builtin("UNIFORM_COLOR")
        gpu.state.blend_set("ALPHA")
        gpu.state.line_width_set(1.5)
        gpu.state.point_size_set(5.0)
        for _ob, d, (points, edges, _) in _visible(context):
            shader.uniform_float("color", LATTICE_COLOUR)
            batch_for_shader(shader, "LINES", {"pos": lines(points, edges).astype(np.float32)}).draw(shader)
            batch_for_shader(shader, "POINTS", {"pos": points.astype(np.float32)}).draw(shader)
            box = falloff_geometry(d)
            if box is not None:
                shader.uniform_float("color", FALLOFF_COLOUR)
                batch_for_shader(shader, "LINES", {"pos": lines(*box).astype(np.float32)}).draw(shader)
        gpu.state.blend_set("NONE")
    except Exception as exc:  # drawing must never raise into Blender
        log.error("overlay: %s", exc)


def _draw_labels():
    try:
        import blf
        from bpy_extras.view3d_utils import location_3d_to_region_2d
        context = bpy.context
        region, rv3d = context.region, context.region_data
        if region is None or rv3d is None:
            return
        for ob, _d, (_, _, text) in _visible(context):
            at = location_3d_to_region_2d(region, rv3d, ob.matrix_world.translation)
            if at is None:
                continue
            blf.size(0, 14)
            blf.color(0, *TEXT_COLOUR)
            blf.position(0, at.x + 12, at.y + 12, 0)
            blf.draw(0, text)
    except Exception as exc:
        log.error("overlay: %s", exc)


def register():
    if not _handles:
        space = bpy.types.SpaceView3D
        _handles.append(space.draw_handler_add(_draw_lattices, (), "WINDOW", "POST_VIEW"))
        _handles.append(space.draw_handler_add(_draw_labels, (), "WINDOW", "POST_PIXEL"))


def unregister():
    space = bpy.types.SpaceView3D
    while _handles:
        handle = _handles.pop()
        try:
            space.draw_handler_remove(handle, "WINDOW")
        except ValueError:
            pass
