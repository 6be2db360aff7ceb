"""The distance and the profile behind the lattice's Outside modes (`outside.py` holds the table
of modes): what the deformation does outside the lattice's rest box (docs/design.md, "Outside the
lattice") is a per-vertex factor on the influence, computed from the positions as they enter the
deformer, never from deformed ones, so the deformation stays affine in the control points and the
closed-form volume correction applies unchanged.

- FOLLOW: 1 everywhere (Blender's Lattice modifier: outside vertices follow the clamped
  extrapolation of the boundary).
- FALLOFF: w(d / distance), d the distance to the box in lattice-size units per side (each axis's
  excess over the box divided by the box's size along it; Euclidean over the axes), with the
  profile w(t) = 1 - t^2 (3 - 2 t) on [0, 1]: w = 1 and w' = 0 at the box, w = 0 and w' = 0 at the
  falloff distance. The displacement w F (F Blender's extrapolation) then has a continuous slope
  across the box's faces (w' = 0 there) and vanishes smoothly at the distance.
- STAY (earlier INSIDE): 1 inside the box, 0 outside it (beyond a millionth of its size per axis).
"""
import numpy as np

#: Excess over the box (in lattice-size units) below which a vertex counts as inside.
INSIDE_SLACK = 1e-6


def box_distance(lattice, verts):
    """(V,) float64 distance of `verts` (V, 3) (lattice space) to the lattice's rest box, in
    lattice-size units per side. An axis with a single point has no extent and adds nothing."""
    v = np.asarray(verts, dtype=np.float64)
    d2 = np.zeros(len(v))
    for a in range(3):
        width = lattice.hi[a] - lattice.lo[a]
        if lattice.shape[a] == 1 or not width > 0:
            continue
        excess = np.maximum(np.maximum(lattice.lo[a] - v[:, a], v[:, a] - lattice.hi[a]), 0.0) / width
        d2 += excess * excess
    return np.sqrt(d2)


def profile(t):
    """(V,) the falloff profile at t (V,) >= 0: 1 - t^2 (3 - 2 t) on [0, 1], 0 beyond."""
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)
