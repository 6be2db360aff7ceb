"""3x3 and 4x4 linear algebra written out elementwise, for stacks of small matrices.

NumPy hands `linalg.inv`, `linalg.solve` and `@` to LAPACK/BLAS. For 3x3 or 4x4 matrices that
costs more than the arithmetic, and an OpenBLAS build runs even a 4x4 solve on its worker threads,
which then spin for a while after the call and take a core from the per-frame kernels (measured in
Blender: most of a frame's system time on two cores; docs/performance.md). Every function here is
a few whole-array ufunc operations: shapes in, shapes out, no threads.
"""
import numpy as np


def det3(A):
    """Determinants of (..., 3, 3) matrices: (...) float64."""
    A = np.asarray(A, dtype=np.float64)
    return (A[..., 0, 0] * (A[..., 1, 1] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 1])
            - A[..., 0, 1] * (A[..., 1, 0] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 0])
            + A[..., 0, 2] * (A[..., 1, 0] * A[..., 2, 1] - A[..., 1, 1] * A[..., 2, 0]))


def _adjugate3(A):
    """Adjugates (..., 3, 3) of (..., 3, 3) matrices (the transposed cofactors)."""
    adj = np.empty(A.shape)
    for i in range(3):
        for j in range(3):
            r0, r1 = (j + 1) % 3, (j + 2) % 3       # rows of the cofactor of entry (j, i)
            c0, c1 = (i + 1) % 3, (i + 2) % 3
            adj[..., i, j] = A[..., r0, c0] * A[..., r1, c1] - A[..., r0, c1] * A[..., r1, c0]
    return adj


def inv3(A):
    """Inverses of (..., 3, 3) matrices: (..., 3, 3) float64 (inf/nan where a determinant is 0:
    callers test `det3` first)."""
    A = np.asarray(A, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return _adjugate3(A) / det3(A)[..., None, None]


def solve3(A, b):
    """x with A x = b for (..., 3, 3) matrices A and (..., 3) or (..., 3, k) right-hand sides b."""
    b = np.asarray(b, dtype=np.float64)
    Ainv = inv3(A)
    if b.ndim == Ainv.ndim - 1:
        return np.einsum("...ij,...j->...i", Ainv, b)
    return np.einsum("...ij,...jk->...ik", Ainv, b)


def affine(points, mat):
    """(V, 3) float64: `points` (V, 3) mapped by the (4, 4) affine matrix `mat`."""
    p = np.asarray(points, dtype=np.float64)
    m = np.asarray(mat, dtype=np.float64)
    out = np.empty((len(p), 3))
    for r in range(3):
        col = out[:, r]
        np.multiply(p[:, 0], m[r, 0], out=col)
        col += p[:, 1] * m[r, 1]
        col += p[:, 2] * m[r, 2]
        col += m[r, 3]
    return out


def affine_inverse(mat):
    """Inverse (4, 4) of an affine (4, 4) matrix (last row 0, 0, 0, 1) with an invertible 3x3 part."""
    m = np.asarray(mat, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = inv3(m[:3, :3])
    out[:3, 3] = -np.einsum("ij,j->i", out[:3, :3], m[:3, 3])
    return out


def matmul4(*mats):
    """Product of (4, 4) matrices, left to right."""
    out = np.asarray(mats[0], dtype=np.float64)
    for m in mats[1:]:
        out = np.einsum("ij,jk->ik", out, np.asarray(m, dtype=np.float64))
    return out
