"""A lattice fitted around points: where it goes, how large it is and how many points it has.

Array in, numbers out; used by "VP-FFD Lattice Deform Selected" (operators/fit.py), which fits
one lattice around what reaches the selected meshes' VP-FFD slots and binds each of them to it.
"""
import numpy as np


def fit_lattice(points, margin=0.05, resolution=4, min_size=1e-3):
    """(centre (3,), size (3,), shape (3,) ints) of an axis-aligned lattice around `points`.

    points: (V, 3) positions (world space), V >= 1, finite.
    margin: added on each side, as a fraction of the largest extent (so a flat or thin mesh gets a
        box, not a sheet, and no vertex sits on the lattice's boundary).
    resolution: points along the longest axis; the others get as many as keep the cells about
        square, at least 2 (a B-spline lattice needs 2 to bend along an axis).
    min_size: the smallest extent, relative to the largest (a flat mesh still gets a box).
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if len(p) == 0:
        raise ValueError("no points to fit a lattice around")
    if not np.isfinite(p).all():
        raise ValueError("the points to fit a lattice around are not all finite")
    if int(resolution) < 2:
        raise ValueError(f"resolution must be at least 2, not {resolution}")
    lo, hi = p.min(0), p.max(0)
    extent = hi - lo
    largest = float(extent.max())
    if largest <= 0.0:
        largest = 1.0                      # a single point: a unit box around it
    size = np.maximum(extent, min_size * largest) + 2.0 * margin * largest
    shape = np.clip(np.rint(1 + (int(resolution) - 1) * size / size.max()), 2, int(resolution)).astype(int)
    return 0.5 * (lo + hi), size, shape
