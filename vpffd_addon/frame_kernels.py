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
    # (slices, indexed from 0: numba checks an index from a start known only at run time for a
    # negative value, which keeps LLVM from vectorising; docs/performance.md, "Indices numba
    # can trust")
    P = points[v0:v1]
    O = out[v0:v1]
    for v in range(P.shape[0]):
        p0 = P[v, 0] * 1.0
        p1 = P[v, 1] * 1.0
        p2 = P[v, 2] * 1.0
        for r in range(3):
            O[v, r] = p0 * mat[r, 0] + p1 * mat[r, 1] + p2 * mat[r, 2] + mat[r, 3]


def float32_offsets(positions, mat, inputs, still, written, offsets, output, v0, v1):
    # Vertices v0..v1-1: offsets = float32(p - inputs) (the difference in float64, rounded once),
    # output = inputs + offsets in the inputs' precision (float32 inputs: the sum Blender's Set
    # Position makes), against `written` (empty: none) whether any offset differs. p is the slot's
    # output: positions[v], or mapped by `mat` (4, 4) where it is given (not empty) exactly as
    # `affine` maps it, or inputs[v] itself where still[v] (`still` not empty): the frame's output
    # made and written in one pass (`frame.SlotOutput`). Returns (0, or 1 when a difference is not
    # finite, or 2 when one overflows float32; whether any differs from `written`; the largest
    # |offset|), as `offsets._numpy`. (A vertex's three components written out one after another:
    # 11-28% faster than a loop over them with the choice of p inside.)
    compare = written.shape[0] > 0
    mapped = mat.shape[0] > 0
    keep = still.shape[0] > 0
    changed = not compare
    moved = 0.0
    m00 = m01 = m02 = m03 = m10 = m11 = m12 = m13 = m20 = m21 = m22 = m23 = 0.0
    if mapped:
        m00, m01, m02, m03 = mat[0, 0], mat[0, 1], mat[0, 2], mat[0, 3]
        m10, m11, m12, m13 = mat[1, 0], mat[1, 1], mat[1, 2], mat[1, 3]
        m20, m21, m22, m23 = mat[2, 0], mat[2, 1], mat[2, 2], mat[2, 3]
    # (every array sliced to the part, as in `affine`)
    positions, inputs, offsets, output = positions[v0:v1], inputs[v0:v1], offsets[v0:v1], output[v0:v1]
    still = still[v0:v1] if keep else still
    written = written[v0:v1] if compare else written
    for v in range(inputs.shape[0]):
        i0 = inputs[v, 0] * 1.0
        i1 = inputs[v, 1] * 1.0
        i2 = inputs[v, 2] * 1.0
        if keep and still[v]:
            q0, q1, q2 = i0, i1, i2
        elif mapped:
            p0 = positions[v, 0] * 1.0
            p1 = positions[v, 1] * 1.0
            p2 = positions[v, 2] * 1.0
            q0 = p0 * m00 + p1 * m01 + p2 * m02 + m03
            q1 = p0 * m10 + p1 * m11 + p2 * m12 + m13
            q2 = p0 * m20 + p1 * m21 + p2 * m22 + m23
        else:
            q0 = positions[v, 0] * 1.0
            q1 = positions[v, 1] * 1.0
            q2 = positions[v, 2] * 1.0
        d0 = q0 - i0
        d1 = q1 - i1
        d2 = q2 - i2
        if not (np.isfinite(d0) and np.isfinite(d1) and np.isfinite(d2)):
            return 1, True, 0.0
        o0 = np.float32(d0)
        o1 = np.float32(d1)
        o2 = np.float32(d2)
        if not (np.isfinite(o0) and np.isfinite(o1) and np.isfinite(o2)):
            return 2, True, 0.0
        offsets[v, 0] = o0
        offsets[v, 1] = o1
        offsets[v, 2] = o2
        output[v, 0] = inputs[v, 0] + o0
        output[v, 1] = inputs[v, 1] + o1
        output[v, 2] = inputs[v, 2] + o2
        if compare and not changed:
            changed = o0 != written[v, 0] or o1 != written[v, 1] or o2 != written[v, 2]
        moved = max(moved, abs(o0 * 1.0), abs(o1 * 1.0), abs(o2 * 1.0))
    return 0, changed, moved


# Every part at once on numba's own worker threads (`compiled.over`, as in `solve_kernels`):
# part k covers edges[k]..edges[k + 1] - 1, the same call `parallel.run` makes for it.
prange = range


def affine_team(edges, points, mat, out):
    for k in prange(edges.shape[0] - 1):
        _k_affine(points, mat, out, edges[k], edges[k + 1])  # noqa: F821


def float32_offsets_team(edges, got, positions, mat, inputs, still, written, offsets, output):
    # got (parts, 3) float64: each part's (flag, changed, largest |offset|).
    for k in prange(edges.shape[0] - 1):
        flag, changed, moved = _k_float32_offsets(positions, mat, inputs, still, written,  # noqa: F821
                                                  offsets, output, edges[k], edges[k + 1])
        got[k, 0] = flag
        got[k, 1] = 1.0 if changed else 0.0
        got[k, 2] = moved


_KERNELS = {"affine": affine, "float32_offsets": float32_offsets}
_TEAMS = tuple(_KERNELS)
