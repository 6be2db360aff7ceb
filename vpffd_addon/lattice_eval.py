"""Evaluating a field given on a lattice's control points at arbitrary positions, with the
lattice's own basis: ``f(x) = sum_ijk w_i(u) w_j(v) w_k(w) F_ijk``. Used where no binding exists
or is needed: the lattice vertex group's weight at each position, and the plain deformation of
positions whose faces are unknown."""
import numpy as np

from .bases import axis_taps
from .lattice import Lattice


def interpolate(lattice, verts, values):
    """The field `values` ((N,) or (N, C), one row per control point, Blender's point order)
    interpolated at `verts` (V, 3) in lattice space: (V,) or (V, C) float64."""
    if not isinstance(lattice, Lattice):
        raise ValueError(f"interpolate needs a vpffd_addon.Lattice, got {type(lattice).__name__}")
    verts = np.asarray(verts, dtype=np.float64)
    F = np.asarray(values, dtype=np.float64)
    if F.shape[0] != lattice.n_points:
        raise ValueError(f"values must have {lattice.n_points} rows, got {F.shape}")
    flat = F.reshape(lattice.n_points, -1)
    nu, nv, nw = lattice.shape
    taps = [axis_taps(verts[:, a], lattice.shape[a], lattice.lo[a], lattice.hi[a], lattice.interpolation[a])
            for a in range(3)]
    out = np.zeros((len(verts), flat.shape[1]))
    (fu, wu), (fv, wv), (fw, ww) = taps
    for k in range(ww.shape[1]):
        iw = np.clip(fw + k, 0, nw - 1)
        for j in range(wv.shape[1]):
            iv = np.clip(fv + j, 0, nv - 1)
            wjk = ww[:, k] * wv[:, j]
            base = (iw * nv + iv) * nu
            for i in range(wu.shape[1]):
                idx = base + np.clip(fu + i, 0, nu - 1)
                out += (wjk * wu[:, i])[:, None] * flat[idx]
    return out.reshape((len(verts),) + F.shape[1:])
