"""Letting go of a binding: `unbind` (the user's Unbind: the modifier and what Bind saved go) and
`release` (the modifier is already gone: removed, or applied by Blender)."""
import numpy as np

from . import meshio, modifier, solver_helper
from .bound import forget, states
from .cache_modifier import find_cache, using_cache
from .saved_data import CAGE_REST_PROPERTY, JACOBIAN_ATTRIBUTE, LEGACY_ATTRIBUTES, PIN_ATTRIBUTE, remove_attribute


def release(obj):
    """Forget the binding of an object whose VP-FFD modifier is gone (X on it, or Blender's
    Apply), leaving its settings, its other modifiers and its coordinates as they are. What was
    VP-FFD's goes with it: a baked cache switched off (a playing one stays: it is what is shown)
    and the solver helper nothing uses any more."""
    mesh = obj.data
    cache = find_cache(obj)
    if cache is not None and not using_cache(obj):
        obj.modifiers.remove(cache)
    solver_helper.free_unused_helpers(obj)
    if mesh.library is None:
        for name in (PIN_ATTRIBUTE, JACOBIAN_ATTRIBUTE, CAGE_REST_PROPERTY) + LEGACY_ATTRIBUTES:
            remove_attribute(mesh, name)
    if _shows_last_solve(obj):
        note_applied(obj)              # Blender's Apply: the mesh keeps the deformed shape
    obj.vpffd.is_bound = False
    forget(obj)


def _shows_last_solve(obj):
    """Whether the mesh's own coordinates are now the last solve's deformed output (Blender's
    Apply wrote it), rather than the undeformed input (the modifier was removed)."""
    state = states.get(obj.session_uid)
    out = None if state is None else state.output
    if out is None or len(out) != len(obj.data.vertices) or not len(out):
        return False
    size = float(np.ptp(out, 0).max()) or 1.0
    return state.moved > 1e-5 * size and np.abs(meshio.mesh_coords(obj.data) - out).max() <= 1e-6 * size


def note_applied(obj):
    """Remember which lattice's deformation is now the mesh's own shape (the panel warns that
    Bind would deform it again)."""
    lat = obj.vpffd.lattice
    obj.vpffd.applied_lattice = lat.name if lat is not None else ""


def unbind(obj):
    """Remove the VP-FFD modifier (with its solver helper; and a baked cache's Mesh Cache
    modifier) and the attributes; the mesh's coordinates were never changed."""
    mesh = obj.data
    modifier.remove(obj)
    cache = find_cache(obj)
    if cache is not None:
        obj.modifiers.remove(cache)
    if mesh.library is None:
        for name in (PIN_ATTRIBUTE, JACOBIAN_ATTRIBUTE, CAGE_REST_PROPERTY) + LEGACY_ATTRIBUTES:
            remove_attribute(mesh, name)
    obj.vpffd.is_bound = False
    forget(obj)
    mesh.update_tag()
