"""Jacobian determinant of the FFD map at the vertices: where it is <= 0 the lattice folds space."""
import numpy as np

from .bases import axis_taps
from .linalg3 import det3


def jacobian_det(binding, points):
    """det(d x' / d x) at every bound vertex's rest position, for control points `points` (N, 3),
    for a lattice or a cage binding: (V,) float64 in the mesh's vertex order."""
    return binding.jacobian_det(points)


def lattice_jacobian_det(binding, points):
    """`jacobian_det` of a lattice `Binding`.

    The map is x' = x + s (S B (P - P0)), s the vertex's influence held fixed. Column a of the
    Jacobian is the same product as the deformation with axis a's weights replaced by their
    derivatives, so it runs through the binding's block products. Returns (V,) float64 in the mesh's
    vertex order.
    """
    b = binding
    lat = b.lattice
    D = b.displacements(points)
    rest = b.to_verts(b.x0)
    taps = [axis_taps(rest[:, a], lat.shape[a], lat.lo[a], lat.hi[a], lat.interpolation[a], derivative=True)
            for a in range(3)]
    (_, wu, du), (_, wv, dv), (_, ww, dw) = taps
    s = b.influence.astype(np.float64)[:, None]
    V = b.n_verts

    def outer(a, c):  # (V, Ka) x (V, Kc) -> (V, Ka * Kc), a slowest
        return (a[:, :, None] * c[:, None, :]).reshape(V, -1)

    factors = [(b.block_layout(outer(wv, du)), None),              # d/du: (v x du), w
               (b.block_layout(outer(dv, wu)), None),              # d/dv: (dv x u), w
               (None, b.block_layout(dw * s))]                     # d/dw: (v x u), dw
    J = np.empty((V, 3, 3))
    for col, (wuv, wwd) in enumerate(factors):
        for comp in range(3):
            slots = b.forward(D[:, comp], wuv=wuv, ww=wwd)
            J[:, comp, col] = slots[b.slot]
    J[:, [0, 1, 2], [0, 1, 2]] += 1.0
    det = det3(J)
    if not np.isfinite(det).all():
        raise ValueError("the Jacobian overflows: the displacements are too large for the lattice's cells")
    return det
