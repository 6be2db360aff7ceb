"""Compiled kernels of a frame's own passes (`frame.py`), as plain functions that `compiled.py`
compiles (nothing here imports numba). Each computes every value with the same operations, in the
same order and precision, as the NumPy code it stands in for: its results are bit for bit NumPy's."""
import numpy as np


def define(njit):
    """The kernels, compiled by `njit` (no fast-math: no fused multiply-adds): {name: function}."""
    return {name: njit(fn) for name, fn in _KERNELS.items()}


def affine(points, mat, out, v0, v1):
    # out[v] = mat (4, 4) applied to points[v] (V, 3) in float64 for v0..v1-1, as
    # `linalg3.affine` (((p0 m0 + p1 m1) + p2 m2) + m3 per row, no fused multiply-adds): the map
    # into lattice space and back, twice a frame.
    for v in range(v0, v1):
        p0 = points[v, 0] * 1.0
        p1 = points[v, 1] * 1.0
        p2 = points[v, 2] * 1.0
        for r in range(3):
            out[v, r] = p0 * mat[r, 0] + p1 * mat[r, 1] + p2 * mat[r, 2] + mat[r, 3]


def float32_offsets(positions, inputs, written, offsets, output, v0, v1):
    # Vertices v0..v1-1: offsets = float32(positions - inputs) (the difference in float64, rounded
    # once), output = inputs + offsets in the inputs' precision (float32 inputs: the sum Blender's
    # Set Position makes), against `written` (empty: none) whether any offset differs. Returns
    # (0, or 1 when a difference is not finite, or 2 when one overflows float32; whether any
    # differs from `written`; the largest |offset|), as `offsets._numpy`.
    compare = written.shape[0] > 0
    changed = not compare
    moved = 0.0
    for v in range(v0, v1):
        for c in range(3):
            d = positions[v, c] - inputs[v, c] * 1.0
            if not np.isfinite(d):
                return 1, True, 0.0
            o = np.float32(d)
            if not np.isfinite(o):
                return 2, True, 0.0
            offsets[v, c] = o
            output[v, c] = inputs[v, c] + o
            if compare and not changed and o != written[v, c]:
                changed = True
            m = abs(o * 1.0)
            if m > moved:
                moved = m
    return 0, changed, moved


# Every part at once on numba's own worker threads (`compiled.over`, as in `solve_kernels`):
# part k covers edges[k]..edges[k + 1] - 1, the same call `parallel.run` makes for it.
prange = range


def affine_team(edges, points, mat, out):
    for k in prange(edges.shape[0] - 1):
        _k_affine(points, mat, out, edges[k], edges[k + 1])  # noqa: F821


def float32_offsets_team(edges, got, positions, inputs, written, offsets, output):
    # got (parts, 3) float64: each part's (flag, changed, largest |offset|).
    for k in prange(edges.shape[0] - 1):
        flag, changed, moved = _k_float32_offsets(positions, inputs, written, offsets, output,  # noqa: F821
                                                  edges[k], edges[k + 1])
        got[k, 0] = flag
        got[k, 1] = 1.0 if changed else 0.0
        got[k, 2] = moved


_KERNELS = {"affine": affine, "float32_offsets": float32_offsets}
_TEAMS = tuple(_KERNELS)
