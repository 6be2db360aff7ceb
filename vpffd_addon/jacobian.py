"""Jacobian determinant of the FFD map at the vertices: where it is <= 0 the lattice folds space."""
import numpy as np

from .bases import axis_taps

_CHUNK = 8192  # vertices per pass: bounds the (chunk, Kw, Kv, Ku, 3) gather


def jacobian_det(binding, points):
    """det(d x' / d x) at every bound vertex's rest position, for control points `points` (N, 3).

    The map is x' = x + s (S B (P - P0)), s the vertex's influence held fixed. Returns (V,) float64
    in the mesh's vertex order.
    """
    b = binding
    lat = b.lattice
    D = b._displacements(points)
    rest = b._to_verts(b.x0)
    influence = b.influence
    out = np.empty(b.n_verts)
    for start in range(0, b.n_verts, _CHUNK):
        x = rest[start:start + _CHUNK]
        taps = [axis_taps(x[:, a], lat.shape[a], lat.lo[a], lat.hi[a], lat.interpolation[a], derivative=True)
                for a in range(3)]
        grid = [np.clip(first[:, None] + np.arange(w.shape[1]), 0, lat.shape[a] - 1)
                for a, (first, w, _) in enumerate(taps)]
        nu, nv, _ = lat.shape
        idx = (grid[2][:, :, None, None] * nv + grid[1][:, None, :, None]) * nu + grid[0][:, None, None, :]
        Dg = D[idx]                                        # (c, Kw, Kv, Ku, 3)
        (_, wu, du), (_, wv, dv), (_, ww, dw) = taps
        cols = [np.einsum("cw,cv,cu,cwvux->cx", ww, wv, du, Dg, optimize=True),
                np.einsum("cw,cv,cu,cwvux->cx", ww, dv, wu, Dg, optimize=True),
                np.einsum("cw,cv,cu,cwvux->cx", dw, wv, wu, Dg, optimize=True)]
        J = np.stack(cols, 2) * influence[start:start + _CHUNK, None, None] + np.eye(3)
        out[start:start + len(x)] = np.linalg.det(J)
    return out
