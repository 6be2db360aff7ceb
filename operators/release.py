"""Letting go of a binding: `unbind` (the user's Unbind: the deformer's modifier and what Bind
saved go) and `release` (the modifier is already gone: removed, or applied by Blender)."""
import numpy as np

from . import deformers, meshio, modifier, solver_helper
from .bound import forget, states
from .cache_modifier import find_cache, using_cache
from .saved_data import CAGE_REST_PROPERTY, JACOBIAN_ATTRIBUTE, LEGACY_ATTRIBUTES, PIN_ATTRIBUTE, remove_attribute
from .status import deformer_of


def _others_bound(d):
    """Whether another deformer of the object stays bound."""
    return any(e.settings != d.settings for e in deformers.bound(d.obj))


def _let_go(d):
    """What every way of letting go does: the settings are no longer bound (a further deformer's
    are removed with its modifier), the cached state goes; when no deformer of the mesh stays
    bound, what was VP-FFD's on the mesh goes too."""
    obj, mesh = d.obj, d.obj.data
    last = not _others_bound(d)
    if last and mesh.library is None:
        for name in (PIN_ATTRIBUTE, JACOBIAN_ATTRIBUTE, CAGE_REST_PROPERTY) + LEGACY_ATTRIBUTES:
            remove_attribute(mesh, name)
    d.settings.is_bound = False
    forget(d=d)
    deformers.drop(d)
    return last


def release(d):
    """Forget the binding of deformer `d` whose VP-FFD modifier is gone (X on it, or Blender's
    Apply), leaving its settings (those of the first deformer), the other modifiers and the
    coordinates as they are. What was VP-FFD's goes with it: when it was the mesh's last bound
    deformer, a baked cache switched off (a playing one stays: it is what is shown); the solver
    helper nothing uses any more."""
    obj = d.obj
    cache = find_cache(obj)
    if cache is not None and not using_cache(obj) and not _others_bound(d):
        obj.modifiers.remove(cache)
    solver_helper.free_unused_helpers(obj)
    if _shows_last_solve(d):
        note_applied(d)                # Blender's Apply: the mesh keeps the deformed shape
    _let_go(d)


def _shows_last_solve(d):
    """Whether the mesh's own coordinates are now the last solve's deformed output (Blender's
    Apply wrote it), rather than the undeformed input (the modifier was removed)."""
    state = states.get(d.key)
    out = None if state is None else state.output
    if out is None or len(out) != len(d.obj.data.vertices) or not len(out):
        return False
    size = float(np.ptp(out, 0).max()) or 1.0
    return state.moved > 1e-5 * size and np.abs(meshio.mesh_coords(d.obj.data) - out).max() <= 1e-6 * size


def note_applied(d):
    """Remember which lattice's deformation is now the mesh's own shape (the panel warns that
    Bind would deform it again)."""
    lat = d.settings.lattice
    d.settings.applied_lattice = lat.name if lat is not None else ""


def unbind(target):
    """Remove deformer `target`'s VP-FFD modifier (with its solver helper; and, when it was the
    last bound one, a baked cache's Mesh Cache modifier) and what Bind saved; the mesh's
    coordinates were never changed. `target`: a `deformers.Deformer`, or a mesh object for its
    first deformer."""
    d = deformer_of(target)
    obj = d.obj
    modifier.remove(obj, d.mod)
    if not _others_bound(d):
        cache = find_cache(obj)
        if cache is not None:
            obj.modifiers.remove(cache)
    _let_go(d)
    obj.data.update_tag()
