"""The edges and boxes the viewport overlay draws (operators/overlay.py draws them): a lattice's
grid, a cage's cells, the box where a lattice's falloff ends. Index pairs and corners only; the
Blender layer moves them into world space and draws them."""
import functools

import numpy as np

#: (12, 2) the edges of a box whose corner k sits at (k & 1, k >> 1 & 1, k >> 2 & 1) (`box_corners`).
BOX_EDGES = np.array([(k, k | 1 << a) for k in range(8) for a in range(3) if not k >> a & 1])


def lattice_edges(shape):
    """(E, 2) int64 index pairs of neighbouring points of a lattice of `shape` (nu, nv, nw), u
    fastest (Blender's point order); read-only, made once per shape (the overlay asks for them
    on every frame)."""
    return _lattice_edges(tuple(int(n) for n in shape))


@functools.lru_cache(maxsize=32)
def _lattice_edges(shape):
    nu, nv, nw = shape
    index = np.arange(nu * nv * nw).reshape(nw, nv, nu)
    pairs = []
    for axis in range(3):
        if index.shape[axis] > 1:
            a = np.take(index, range(index.shape[axis] - 1), axis=axis).ravel()
            b = np.take(index, range(1, index.shape[axis]), axis=axis).ravel()
            pairs.append(np.stack([a, b], 1))
    edges = np.concatenate(pairs) if pairs else np.zeros((0, 2), np.int64)
    edges.flags.writeable = False
    return edges


def cage_edges(cells):
    """(E, 2) int64 distinct edges of the cells' faces (cells: tuples of face loops), sorted."""
    edges = {tuple(sorted((a, b))) for faces in cells for f in faces for a, b in zip(f, f[1:] + f[:1])}
    return np.array(sorted(edges), np.int64).reshape(-1, 2)


def box_corners(lo, hi):
    """(8, 3) float64 corners of the box [lo, hi] ((3,) each), corner k at (k & 1, k >> 1 & 1,
    k >> 2 & 1) (the order of `BOX_EDGES`)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return np.array([[(hi if k >> a & 1 else lo)[a] for a in range(3)] for k in range(8)])


def falloff_box(lattice, distance):
    """(8, 3) corners, in lattice space, of the box where a `Lattice`'s falloff ends: its rest box
    grown by `distance` of its sizes on every side."""
    grow = float(distance) * (lattice.hi - lattice.lo)
    return box_corners(lattice.lo - grow, lattice.hi + grow)
