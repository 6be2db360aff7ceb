"""An update's result, published: the offsets written to the solver helper (Blender then evaluates
the object again with them), what the overlay and the next update need kept, the panel's figures."""
import time

import numpy as np

from .. import vpffd_addon as vp
from ..vpffd_addon import outside as outside_modes
from ..vpffd_addon import backends, wireframe
from . import compiled_backend, meshio, node_group, solver_helper
from .saved_data import JACOBIAN_ATTRIBUTE, float_attribute
from .status import set_status


FOLD_CHECK_MAX_VERTS = 5000         # above this, folds are counted on request only (Check Folds)


def zero_offsets(d, state=None):
    """Show deformer `d`'s slot input undeformed (a defined result for a frame that cannot be
    solved)."""
    mod = d.mod
    helper = node_group.get_input(mod, node_group.SOLVER_INPUT) if mod is not None else None
    if helper is None or helper.get(solver_helper.HELPER_TAG) is None:
        return
    if len(helper.data.vertices):
        solver_helper.write_offsets(helper, np.zeros((0, 3), np.float32))
        if state is not None:
            state.wrote = True
    if state is not None:
        state.written = None


def _write(state, helper, offsets32, changed):
    """Write the float32 offsets to the helper unless it already holds exactly these (every write
    makes Blender evaluate the object again, and the handler runs again after it)."""
    if not changed and len(helper.data.vertices) == len(offsets32):
        return
    solver_helper.write_offsets(helper, offsets32)
    state.written = offsets32
    state.wrote = True


def publish(d, state, frame, result, t0):
    """Write deformer `d`'s offsets to its solver helper, keep what the overlay and the next
    update need, and give the panel its figures."""
    obj = d.obj
    X = frame.inputs.positions
    lattice = frame.inputs.lattice
    core_seconds = time.perf_counter() - t0
    # The offsets in float32, the output as Blender will compute it, whether they differ from
    # those written and the largest, in one pass (ValueError, nothing written, for non-finite
    # or float32-overflowing ones).
    offsets32, output, changed, moved = result.float32_offsets(state.written)
    _write(state, frame.helper, offsets32, changed)
    seconds = time.perf_counter() - t0
    # Weights read before the vertex-group input changed are the old group's: solve again
    # after the evaluation that the change brings.
    state.signature, state.result = (None if frame.stale_weights else frame.signature), result
    state.output = output          # float32, the very sum the modifier's Set Position makes
    state.moved = moved
    edges = (wireframe.lattice_edges(lattice.shape) if isinstance(lattice, vp.Lattice)
             else wireframe.cage_edges(lattice.cells))
    state.overlay = (meshio.transform(result.points, frame.lattice_matrix), edges)
    state.matrix = frame.inputs.matrix      # object -> lattice space of this solve
    state.falloff_box = None
    mode = outside_modes.mode(frame.inputs.outside)
    if isinstance(lattice, vp.Lattice) and mode.has_distance:
        state.falloff_box = meshio.transform(wireframe.falloff_box(lattice, frame.inputs.falloff),
                                             frame.lattice_matrix)
    binding = result.binding
    backend, backend_reason = state.backend
    s = state.settings
    info = dict(error=None, seconds=seconds, core_seconds=core_seconds,
                warnings=tuple(frame.warnings) + tuple(result.warnings) + _lattice_notes(lattice),
                backend=backend,
                backend_reason=backend_reason, n_verts=len(X), folds=None,
                closed=None if binding is None else binding.is_closed,
                input_volume=result.input_volume, rebound=result.rebound, outside=result.outside,
                outside_follow=(mode if isinstance(lattice, vp.Lattice)
                                else outside_modes.mode(s.cage_outside, "cage")).follows,
                outside_mode=frame.inputs.outside, falloff=_fading(frame.inputs, result),
                still=result.still, beyond=result.beyond, editing=frame.editing,
                encloses_nothing=encloses_nothing(result))
    if backend == "CPU" and result.backend is not None:
        compiled = result.backend == "COMPILED"     # the solve says which steps ran
        info["kernels"] = "compiled" if compiled else "NumPy"
        if not compiled:
            # Why the compiled entry was passed over: the registry's words for the binding, or
            # the compile's own state (compiling, numba missing) while it is not available.
            refused = backends.usable(backends.COMPILED, "CPU", binding, {})[1] if binding is not None else None
            info["kernels_why"] = ("Backend is CPU (NumPy): the reference path" if s.backend == "NUMPY"
                                   else refused if vp.compiled.ready() or isinstance(lattice, vp.Cage)
                                   else compiled_backend.status()[1])
            info["awaits_kernels"] = (s.backend != "NUMPY" and isinstance(lattice, vp.Lattice)
                                      and compiled_backend.status()[0] == "compiling")
    reference = result.reference_volume
    # A mirror turns every vertex inside out alike: folds are the vertices turned against it.
    mirrored = bool(reference and result.plain_volume and result.plain_volume / reference < 0)
    info["mirrored"], state.orientation = mirrored, -1.0 if mirrored else 1.0
    if reference:
        # Sizes: a lattice that mirrors space turns the volume's sign with the shape.
        info["volume_percent"] = 100.0 * abs(result.volume / reference)
        info["plain_percent"] = 100.0 * abs(result.plain_volume / reference)
        if result.target_given:
            info["target_from"] = "bind"
            info["input_percent"] = 100.0 * abs(result.input_volume / reference)
    if binding is not None:
        if s.use_fold_attribute and frame.faces_from == "mesh" and obj.data.library is None:
            det = vp.jacobian_det(binding, result.points)
            float_attribute(obj.data, JACOBIAN_ATTRIBUTE, det)
            info["folds"] = int((det * state.orientation <= 0).sum())
        elif binding.n_verts <= FOLD_CHECK_MAX_VERTS:
            info["folds"] = count_folds(binding, result.points, state.orientation)
    set_status(d, **info)


def encloses_nothing(result):
    """Whether the frame's input is an open surface whose volume about the lattice's centre is
    zero to within the rounding of its terms: there is no volume to keep."""
    b = result.binding
    return (b is not None and not b.is_closed and result.reference_volume is not None
            and abs(result.reference_volume) <= float(np.sum(b.rest_volume_noise)))


def count_folds(binding, points, orientation=1.0):
    """Vertices where the deformation's Jacobian determinant is <= 0 (the lattice folds there),
    or >= 0 under a lattice that mirrors space (`orientation` -1): a mirror alone folds nothing."""
    return int((vp.jacobian_det(binding, points) * orientation <= 0).sum())


def _lattice_notes(lattice):
    """What the user should know about the lattice itself, shown with the solve's warnings."""
    if isinstance(lattice, vp.Lattice) and 1 in lattice.shape:
        return ("the lattice has a single point on an axis: it only moves along that axis",)
    return ()


def _fading(inputs, result):
    """Vertices outside the lattice that Falloff moves partly: those outside (one definition of
    outside for every count: a vertex on the lattice's face is inside) and not beyond the
    falloff distance."""
    if not outside_modes.mode(inputs.outside).has_distance or not isinstance(inputs.lattice, vp.Lattice):
        return result.falloff
    return max(result.outside - result.beyond, 0)
