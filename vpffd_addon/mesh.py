"""Triangle-mesh checks and topology: validation, closedness, connected components."""
import numpy as np

from . import parallel


def check_verts(verts, name="verts"):
    """Return `verts` as a finite (V, 3) float64 array or raise ValueError naming the problem."""
    v = np.asarray(verts, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{name} must have shape (V, 3), got {v.shape}")
    if len(v) == 0:
        raise ValueError(f"{name} is empty")
    if not np.isfinite(v).all():    # (per vertex only then: a reduction along rows of 3 is slow)
        bad = ~np.isfinite(v).all(1)
        raise ValueError(f"{name} has non-finite coordinates at {int(bad.sum())} vertices "
                         f"(first: index {int(np.argmax(bad))})")
    return v


def check_tris(tris, n_verts):
    """Return `tris` as an (F, 3) int64 array of indices into n_verts vertices, or raise ValueError."""
    t = np.asarray(tris)
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"tris must have shape (F, 3), got {t.shape}")
    if len(t) == 0:
        raise ValueError("tris is empty: a mesh needs faces to enclose a volume")
    if t.dtype.kind not in "iu":
        if t.dtype.kind != "f" or not np.isfinite(t).all() or not (t == np.round(t)).all():
            raise ValueError(f"tris must hold integer vertex indices, got dtype {t.dtype}")
    t = t.astype(np.int64)
    out = (t < 0) | (t >= n_verts)
    if out.any():
        f = int(np.argmax(out.any(1)))
        raise ValueError(f"tris index out of range [0, {n_verts}) in {int(out.any(1).sum())} faces "
                         f"(first: face {f} = {t[f].tolist()})")
    return t


def is_closed(tris, n_verts):
    """True when every edge of the non-degenerate faces of `tris` (F, 3) is used exactly twice, in
    opposite directions: a closed, consistently oriented surface whose volume is well defined."""
    t = tris[(tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 2] != tris[:, 0])]
    if len(t) == 0:
        return False
    a = t.ravel()
    b = t[:, [1, 2, 0]].ravel()
    # One sort of the undirected edges, each tagged with its direction in the lowest bit: a closed,
    # consistently oriented surface has every edge exactly twice, once in each direction, so the
    # sorted keys come in pairs (2e, 2e + 1) with e strictly increasing from pair to pair.
    n = np.int64(n_verts)
    keys = np.sort((np.minimum(a, b) * n + np.maximum(a, b)) * 2 + (a > b))
    if len(keys) % 2:
        return False
    first, second = keys[0::2], keys[1::2]
    if not ((first & 1) == 0).all() or not np.array_equal(second, first + 1):
        return False
    return bool((first[1:] > second[:-1]).all())


def connected_components(tris, n_verts):
    """Label the connected components of the vertices of `tris` (F, 3).

    Returns (labels (n_verts,) int64 in 0..k-1, numbered by lowest vertex; k). Vertices that no face
    uses are their own components. Hooks every edge to the smaller label, then halves pointer chains;
    O(E log V) with NumPy passes only.
    """
    a = np.concatenate([tris[:, 0], tris[:, 1], tris[:, 2]])
    b = np.concatenate([tris[:, 1], tris[:, 2], tris[:, 0]])
    parent = np.arange(n_verts, dtype=np.int64)
    while True:
        pa, pb = parent[a], parent[b]
        differ = pa != pb
        if not differ.any():
            break
        lo = np.minimum(pa, pb)[differ]
        hi = np.maximum(pa, pb)[differ]
        np.minimum.at(parent, hi, lo)
        while True:  # pointer jumping until every vertex points at a root
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand
        a, b = a[differ], b[differ]
    roots, labels = np.unique(parent, return_inverse=True)
    return labels.astype(np.int64), len(roots)


class Topology:
    """What a bind needs to know about a triangle mesh that does not depend on where its vertices
    are: validated faces, closedness and islands. It is computed once and handed to every later
    bind of the same faces (a mesh moving through a lattice re-embeds on every frame, but its
    topology stays), which then only re-embeds the new positions.

    tris: (F, 3) vertex indices; n_verts: number of vertices V.
    Attributes: `tris` (F, 3) int64 (and `tris_t`, its (3, F) copy), `n_verts`, `is_closed`, `labels` (V,) island of each vertex,
    `n_islands`, `face_island` (F,), and `island_order` (V,) / `island_start` (n_islands,): the
    vertices grouped by island, for per-island reductions without scattered writes.
    """

    def __init__(self, tris, n_verts, kernels=None):
        self.n_verts = int(n_verts)
        self.tris = check_tris(tris, self.n_verts)
        self.tris_t = np.ascontiguousarray(self.tris.T)     # (3, F): corner k of every face
        if kernels is not None:
            # The compiled kernels (`compiled.kernels`): the faces around every vertex
            # (which the compiled solve needs anyway), closedness from them and the islands by
            # union-find, with NumPy's results.
            start = np.zeros(self.n_verts + 1, np.int64)
            pairs = np.empty(6 * len(self.tris), np.int32)
            kernels["vertex_incidence"](self.tris_t, start, pairs)
            self._vertex_incidence = (start, pairs)
            closed = bool(kernels["closed"](start, pairs))
            labels = np.empty(self.n_verts, np.int64)
            components = labels, int(kernels["components"](self.tris_t, np.empty(self.n_verts, np.int64), labels))
        else:
            # The two passes are independent and NumPy releases the GIL in their sorts and
            # gathers: a big mesh runs them side by side on the worker threads.
            jobs = [lambda: is_closed(self.tris, self.n_verts),
                    lambda: connected_components(self.tris, self.n_verts)]
            if self.n_verts >= parallel.MIN_VERTS_PER_PART:
                closed, components = parallel.run(lambda job: job(), jobs)
            else:
                closed, components = (job() for job in jobs)
        self.is_closed = closed
        self.labels, self.n_islands = components
        self.face_island = self.labels[self.tris[:, 0]]
        if self.n_islands == 1:
            self.island_order, self.island_start = np.arange(self.n_verts), np.zeros(1, np.int64)
        else:
            self.island_order = np.argsort(self.labels, kind="stable")
            self.island_start = np.searchsorted(self.labels[self.island_order], np.arange(self.n_islands))

    def island_bounds(self, verts):
        """(lo, hi), each (n_islands, 3): the bounding box of every island of `verts` (V, 3)."""
        if self.n_islands == 1:
            cols = np.ascontiguousarray(verts.T)   # reductions along contiguous rows are faster
            return cols.min(1)[None], cols.max(1)[None]
        grouped = verts[self.island_order]
        return (np.minimum.reduceat(grouped, self.island_start, axis=0),
                np.maximum.reduceat(grouped, self.island_start, axis=0))

    def matches(self, tris):
        """True when `tris` are the faces this topology was made from (same array contents)."""
        if tris is self.tris:          # the usual case: a re-embedding hands the topology's own
            return True
        t = np.asarray(tris)
        return t.shape == self.tris.shape and np.array_equal(t, self.tris)
