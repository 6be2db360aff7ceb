"""The switch between a baked cache and the live solve: `switch_to_cache` puts a Mesh Cache
modifier where the (last) VP-FFD modifier is in the stack and disables (does not delete) the
VP-FFD modifiers; `switch_to_live` goes back (bake.py says how frames map)."""
import bpy

from ..vpffd_addon import pointcache
from . import deformers
from .bake_files import BakeError, absolute_path, check_format, os_error_words
from .cache_modifier import CACHE_MODIFIER_NAME, find_cache
from .update import slot_output, update_object


def baked_deformer(obj):
    """The deformer whose slot output a bake writes: the last bound VP-FFD modifier in the stack,
    whose slot gives the result of every VP-FFD deformer before it; None when there is none."""
    found = [d for d in deformers.bound(obj) if d.mod is not None]
    return found[-1] if found else None


def live_modifiers(obj):
    """The VP-FFD modifiers of the bound deformers of `obj` (what the cache stands in for)."""
    return [d.mod for d in deformers.bound(obj) if d.mod is not None]


def check_bakeable(obj, scene=None):
    """Raise BakeError naming what stops `obj` from being baked (in `scene`); else the deformer
    whose slot output the bake writes (`baked_deformer`)."""
    if obj is None or obj.type != "MESH":
        raise BakeError("select a mesh object bound with VP-FFD")
    if not deformers.is_bound(obj):
        raise BakeError(f"'{obj.name}' is not bound to a lattice: Bind it first")
    d = baked_deformer(obj)
    if d is None:
        raise BakeError("the VP-FFD modifier was removed: Bind again")
    if obj.mode == "EDIT":
        raise BakeError("leave Edit Mode before baking")
    if scene is not None and scene.objects.get(obj.name) != obj:
        raise BakeError(f"'{obj.name}' is not in scene '{scene.name}'")
    return d


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
        return absolute_path(filepath)
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
    fmt = check_format(fmt)
    if obj is None or obj.type != "MESH":
        raise BakeError("select a mesh object")
    d = baked_deformer(obj)
    if d is None:
        raise BakeError(f"'{obj.name}' has no VP-FFD modifier to replace")
    vp_mod = d.mod
    path = _cache_path_for_reading(filepath)
    try:
        info = pointcache.cache_info(path, fmt)
    except FileNotFoundError:
        raise BakeError(f"cache file {path} does not exist: Bake first") from None
    except ValueError as exc:
        raise BakeError(str(exc)) from None
    except OSError as exc:
        raise BakeError(f"cannot read {path}: {os_error_words(exc)}") from None
    # The cache replaces what reaches the VP-FFD slot: its point count is the slot's.
    live = slot_output(d)
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
    for m in live_modifiers(obj):
        m.show_viewport = m.show_render = False
    obj.update_tag()
    return cache


def switch_to_live(obj):
    """Solve live again: enable the VP-FFD modifier and disable the cache modifier (kept, with its
    file, for `switch_to_cache`). Raises BakeError when the VP-FFD modifier is gone."""
    if obj is None or obj.type != "MESH":
        raise BakeError("select a mesh object")
    mods = live_modifiers(obj)
    if not mods:
        raise BakeError(f"'{obj.name}' has no VP-FFD modifier to switch back to: Bind again")
    cache = find_cache(obj)
    if cache is not None:
        cache.show_viewport = cache.show_render = False
    for m in mods:
        m.show_viewport = m.show_render = True
    update_object(obj, bpy.context.evaluated_depsgraph_get(), force=True)  # never raises
    obj.update_tag()


# -------------------------------------------------------------------------------------- bake
