"""What a frame writes: the offsets from a slot's input to its output in float32 (what Blender
stores), and what the next frame and the panel keep of them. One pass over the vertices by the
compiled kernel where it is loaded (`frame_kernels.float32_offsets`), NumPy's passes otherwise,
with the same results bit for bit. The pass also makes the output itself from the solve's
vertices (the map back to the object's space, the positions no influence moves), so that with the
kernel a frame never writes the object-space positions to memory only to read them again
(docs/performance.md, "A frame's own passes")."""
import numpy as np

from . import compiled, parallel
from .linalg3 import affine

_NOT_FINITE = "the solve produced non-finite offsets; nothing was written"
_TOO_BIG = ("the offsets exceed what Blender can store (float32): the lattice points or the object "
            "scales are extreme; nothing was written")
_NONE = np.zeros((0, 3), np.float32)
_NO_MATRIX = np.zeros((0, 4))
_NO_STILL = np.zeros(0, np.bool_)


def float32_offsets(positions, inputs, written=None, matrix=None, still=None):
    """(offsets (V, 3) float32, output (V, 3), changed, moved) for a slot's output `positions`
    (V, 3) float64 and its input `inputs` (V, 3) float32 or float64. Where `matrix` (4, 4) is
    given, the slot's output is `positions` mapped by it (`linalg3.affine`); where `still` (V,)
    bool is given, the output of the positions it marks is exactly their input.

    offsets: positions - inputs, computed in float64 and rounded to float32 once; output:
    inputs + offsets in the inputs' precision (for float32 inputs exactly the sum Blender's Set
    Position node makes with the written offsets); changed: whether the offsets differ from
    `written` (V, 3) float32, the offsets written before (None: nothing was written: True); moved:
    the largest |offset|. Raises ValueError when an offset is not finite or overflows float32
    (nothing is to be written then)."""
    positions = np.asarray(positions)
    inputs = np.asarray(inputs)
    if positions.shape != inputs.shape or positions.ndim != 2 or positions.shape[1:] != (3,):
        raise ValueError(f"positions {positions.shape} and inputs {inputs.shape} must both be (V, 3)")
    if still is not None:
        still = np.ascontiguousarray(still)
        if still.shape != (len(inputs),) or still.dtype != np.bool_:
            raise ValueError(f"still must be ({len(inputs)},) bool, got {still.shape} {still.dtype}")
    if matrix is not None:
        matrix = np.ascontiguousarray(matrix, dtype=np.float64)
        if matrix.shape != (4, 4):
            raise ValueError(f"matrix must be (4, 4), got {matrix.shape}")
    K = compiled.kernels()
    if (K is None or positions.dtype != np.float64 or inputs.dtype not in (np.float32, np.float64)
            or not (positions.flags.c_contiguous and inputs.flags.c_contiguous)):
        return _numpy(_output(positions, inputs, matrix, still), inputs, written)
    V = len(positions)
    same = (written is not None and written.shape == (V, 3) and written.dtype == np.float32
            and written.flags.c_contiguous)
    offsets = np.empty((V, 3), np.float32)
    output = np.empty((V, 3), np.result_type(inputs.dtype, np.float32))
    parts = parallel.split(V, V) if V else [slice(0, 0)]
    got = compiled.over("float32_offsets", parts, positions, _NO_MATRIX if matrix is None else matrix,
                        inputs, _NO_STILL if still is None else still,
                        written if same else _NONE, offsets, output, returns=3, kernels=K)
    for flag, _, _ in got:
        if flag:
            raise ValueError(_NOT_FINITE if flag == 1 else _TOO_BIG)
    changed = (not same) or any(part[1] for part in got)
    return offsets, output, changed, max((part[2] for part in got), default=0.0)


def _output(positions, inputs, matrix=None, still=None):
    """(V, 3) float64: the slot's output as `float32_offsets` defines it, with NumPy."""
    out = np.asarray(positions, dtype=np.float64) if matrix is None else affine(positions, matrix)
    if still is not None and still.any():
        out = out.copy() if matrix is None else out
        out[still] = np.asarray(inputs, dtype=np.float64)[still]
    return out


def _numpy(positions, inputs, written):
    """The NumPy reference of `float32_offsets`."""
    offsets64 = positions - inputs
    if not np.isfinite(offsets64).all():
        raise ValueError(_NOT_FINITE)
    with np.errstate(over="ignore"):            # (said below, in words)
        offsets = np.ascontiguousarray(offsets64, dtype=np.float32)
    if not np.isfinite(offsets).all():
        raise ValueError(_TOO_BIG)
    changed = written is None or written.shape != offsets.shape or not np.array_equal(written, offsets)
    moved = float(np.abs(offsets).max()) if len(offsets) else 0.0
    return offsets, inputs + offsets, changed, moved
