"""Volumetric Catmull-Clark refinement with boundary control (MacCracken & Joy, sections 2-3).

Every refined point is a fixed linear combination of the points one level up, so a level is a
sparse matrix S_k (n_k, n_{k-1}) and the region's points after `depth` levels are
S_depth ... S_1 P: linear in the cage points, which is what keeps the volume solve exact.

Rules, for cell points C, face centroids A and edge midpoints M:
- interior: cell point = mean of the cell's points; face point (C0 + 2A + C1) / 4; edge point
  (C_avg + 2 A_avg + (n - 3) M) / n with n faces on the edge; vertex point
  (C_avg + 3 A_avg + 3 M_avg + P) / 8;
- boundary faces and their non-sharp edges and points: Catmull-Clark surface rules (face point A,
  edge point (M + A_avg) / 2, vertex point (Q + 2 R + (n - 3) P) / n on the boundary surface);
- sharp edges: cubic B-spline curve rules (edge point M, vertex point (P_a + 6 P + P_b) / 8);
- corners stay where they are.
Which points, edges and faces are on the boundary, sharp or corners is decided from the topology
(`Complex.classify`).

A level is held as arrays ("cell faces": every face of every cell, as an outward loop), so that
refining cages of thousands of cells stays a matter of NumPy passes.
"""
import numpy as np

from .cells import unique_rows
from .sparse import Sparse


def _pairs(rows, cols):
    """Distinct (row, col) pairs, as two arrays sorted by row."""
    u, _ = unique_rows(np.stack([rows, cols], 1))
    return u[:, 0], u[:, 1]


def _average(rows, cols, n_rows, n_cols, mask=None, scale=1.0):
    """Sparse (n_rows, n_cols): row r = scale * the mean of the distinct cols paired with r
    (rows without pairs stay empty). mask (n_rows,) keeps only some rows; scale (n_rows,) or float."""
    r, c = _pairs(rows, cols)
    if mask is not None:
        keep = mask[r]
        r, c = r[keep], c[keep]
    count = np.bincount(r, minlength=n_rows)
    w = np.broadcast_to(np.asarray(scale, np.float64), (n_rows,))[r] / count[r]
    return Sparse(r, c, w, (n_rows, n_cols))


def _stack(blocks, n_cols):
    """Rows of several `Sparse` blocks (each (n_i, n_cols)) one after another."""
    rows, cols, vals, offset = [], [], [], 0
    for b in blocks:
        rows.append(b.rows + offset)
        cols.append(b.cols)
        vals.append(b.vals)
        offset += b.shape[0]
    return Sparse(np.concatenate(rows), np.concatenate(cols), np.concatenate(vals), (offset, n_cols))


def _sum(blocks):
    """Sum of `Sparse` matrices of one shape."""
    shape = blocks[0].shape
    return Sparse(np.concatenate([b.rows for b in blocks]), np.concatenate([b.cols for b in blocks]),
                  np.concatenate([b.vals for b in blocks]), shape)


def _diag(values):
    n = len(values)
    keep = np.flatnonzero(values)
    return Sparse(keep, keep, np.asarray(values, np.float64)[keep], (n, n))


class Complex:
    """A cell complex as arrays.

    n_points; loops (m, L) int: every face of every cell as an outward loop, padded with -1;
    sizes (m,): loop lengths; cell (m,): the cell of each loop; n_cells.
    Derived: half-edges (one per loop side): he_loop, he_from, he_to, he_prev (index of the
    half-edge before it in its loop), he_edge; loop_face (m,) global face of each loop;
    face_loop (n_faces,) one loop of each face, face_cells (n_faces,) how many cells hold it;
    edge_verts (n_edges, 2).
    """

    def __init__(self, n_points, loops, sizes, cell, n_cells):
        self.n_points, self.loops, self.sizes, self.cell, self.n_cells = n_points, loops, sizes, cell, n_cells
        m, L = loops.shape
        j = np.arange(L)
        valid = j[None, :] < sizes[:, None]
        rows, cols = np.nonzero(valid)
        H = len(rows)
        he_id = np.full((m, L), -1, np.int64)
        he_id[rows, cols] = np.arange(H)
        nxt = (cols + 1) % sizes[rows]
        prv = (cols - 1) % sizes[rows]
        self.he_loop = rows
        self.he_from = loops[rows, cols]
        self.he_to = loops[rows, nxt]
        self.he_prev = he_id[rows, prv]
        # Faces: loops with the same points (sorted) are one face.
        key = np.sort(np.where(valid, loops, -1), axis=1)
        _, self.loop_face = unique_rows(key)
        _, self.face_loop = np.unique(self.loop_face, return_index=True)   # first loop of each face
        self.n_faces = len(self.face_loop)
        self.face_cells = np.bincount(self.loop_face, minlength=self.n_faces)
        lo = np.minimum(self.he_from, self.he_to)
        hi = np.maximum(self.he_from, self.he_to)
        self.edge_verts, self.he_edge = unique_rows(np.stack([lo, hi], 1))
        self.n_edges = len(self.edge_verts)

    @classmethod
    def from_cells(cls, n_points, cells):
        """From cells given as tuples of outward face loops."""
        loops = [f for faces in cells for f in faces]
        L = max(len(f) for f in loops)
        arr = np.full((len(loops), L), -1, np.int64)
        for i, f in enumerate(loops):
            arr[i, :len(f)] = f
        sizes = np.array([len(f) for f in loops], np.int64)
        owner = np.repeat(np.arange(len(cells)), [len(faces) for faces in cells])
        return cls(n_points, arr, sizes, owner, len(cells))

    def classify(self):
        """Boundary control of section 3, from the topology alone: (boundary_face (n_faces,),
        sharp (n_edges,), boundary_edge (n_edges,), point kind (n_points,): 0 interior, 1 smooth
        boundary, 2 crease, 3 corner).

        A face is on the boundary when one cell holds it. An edge is sharp when it lies on the
        boundary and one cell holds it (the edges of a box, the rims of an extruded disc): the
        paper's "edges joining vertices in one or two cells" stated on the edge itself, so that a
        cage one cell thick is not creased across its faces. A point is a corner where three or
        more sharp edges meet (every point of a single cell among them), a crease point where two do.
        """
        boundary_face = self.face_cells == 1
        he_face = self.loop_face[self.he_loop]
        he_cell = self.cell[self.he_loop]
        boundary_edge = np.zeros(self.n_edges, bool)
        boundary_edge[self.he_edge[boundary_face[he_face]]] = True
        e, c = _pairs(self.he_edge, he_cell)
        sharp = boundary_edge & (np.bincount(e, minlength=self.n_edges) == 1)
        ev = self.edge_verts
        n_sharp = np.bincount(ev[sharp].ravel(), minlength=self.n_points)
        kind = np.zeros(self.n_points, np.int64)
        kind[ev[boundary_edge].ravel()] = 1
        kind[n_sharp == 2] = 2
        kind[n_sharp >= 3] = 3
        return boundary_face, sharp, boundary_edge, kind


def refine_once(cx):
    """One level of refinement of a `Complex`: (S (n_new, n_old) `Sparse`, the refined `Complex`,
    valence (n_new_cells,) of each new cell's corner point in its parent cell: 3 for hexahedra,
    hex_corners (k, 8): trilinear corner order of the new cells of valence 3, hex_cells (k,)).

    New points: vertex points first (same index as the old point), then one per edge, one per
    face and one per cell, in the complex's order. A new cell is made for every (cell, point of
    the cell); its 2n quads are, for each half-edge V -> X of the cell leaving V, the quad in the
    old face (V, E(V X), F, E(prev V)) and the quad inside the cell (E(V X), F', C, F), F' the
    face holding the opposite half-edge X -> V.
    """
    n, ne, nf, nc = cx.n_points, cx.n_edges, cx.n_faces, cx.n_cells
    E0, F0, C0 = n, n + ne, n + ne + nf
    boundary_face, sharp, boundary_edge, kind = cx.classify()
    he_face = cx.loop_face[cx.he_loop]
    he_cell = cx.cell[cx.he_loop]

    # Centroids as sparse averages of the old points.
    Cm = _average(he_cell, cx.he_from, nc, n)                      # cell means
    Am = _average(he_face, cx.he_from, nf, n)                      # face centroids
    ev = cx.edge_verts
    Mm = Sparse(np.repeat(np.arange(ne), 2), ev.ravel(), np.full(2 * ne, 0.5), (ne, n))

    # Face points: A on the boundary, (C0 + 2 A + C1) / 4 inside.
    fc_face, fc_cell = _pairs(he_face, he_cell)
    interior_face = ~boundary_face
    S_face = _sum([_diag(np.where(boundary_face, 1.0, 0.5)).compose(Am),
                   _average(fc_face, fc_cell, nf, nc, mask=interior_face, scale=0.5).compose(Cm)])

    # Edge points.
    ef_edge, ef_face = _pairs(cx.he_edge, he_face)
    k = np.bincount(ef_edge, minlength=ne).astype(np.float64)       # faces on each edge
    interior_edge = ~boundary_edge
    smooth_boundary_edge = boundary_edge & ~sharp
    m_coef = np.where(sharp, 1.0, np.where(boundary_edge, 0.5, (k - 3.0) / np.maximum(k, 1.0)))
    bf = boundary_face[ef_face]
    S_edge = _sum([
        _diag(m_coef).compose(Mm),
        _average(ef_edge[bf], ef_face[bf], ne, nf, mask=smooth_boundary_edge, scale=0.5).compose(Am),
        _average(ef_edge, ef_face, ne, nf, mask=interior_edge, scale=2.0 / np.maximum(k, 1.0)).compose(Am),
        _average(cx.he_edge, he_cell, ne, nc, mask=interior_edge, scale=1.0 / np.maximum(k, 1.0)).compose(Cm),
    ])

    # Vertex points.
    corner, crease, smooth, interior = kind == 3, kind == 2, kind == 1, kind == 0
    pe_point = ev.ravel()
    pe_edge = np.repeat(np.arange(ne), 2)
    pe_other = ev[:, ::-1].ravel()
    is_sharp = sharp[pe_edge]
    is_bedge = boundary_edge[pe_edge]
    kb = np.bincount(pe_point[is_bedge], minlength=n).astype(np.float64)   # boundary edges at a point
    p_coef = np.where(corner, 1.0, np.where(crease, 0.75, np.where(smooth, (kb - 3.0) / np.maximum(kb, 1.0), 0.125)))
    pf_point, pf_face = _pairs(cx.he_from, he_face)
    bpf = boundary_face[pf_face]
    S_vert = _sum([
        _diag(p_coef),
        _average(pe_point[is_sharp], pe_other[is_sharp], n, n, mask=crease, scale=0.25),
        _average(pf_point[bpf], pf_face[bpf], n, nf, mask=smooth, scale=1.0 / np.maximum(kb, 1.0)).compose(Am),
        _average(pe_point[is_bedge], pe_edge[is_bedge], n, ne, mask=smooth,
                 scale=2.0 / np.maximum(kb, 1.0)).compose(Mm),
        _average(cx.he_from, he_cell, n, nc, mask=interior, scale=0.125).compose(Cm),
        _average(pf_point, pf_face, n, nf, mask=interior, scale=0.375).compose(Am),
        _average(pe_point, pe_edge, n, ne, mask=interior, scale=0.375).compose(Mm),
    ])
    S = _stack([S_vert, S_edge, S_face, Cm], n)

    # New cells, one per (cell, point): numbered in (cell, point) order.
    sub_key, he_sub = unique_rows(np.stack([he_cell, cx.he_from], 1))
    n_sub = len(sub_key)
    # The half-edge X -> V of the same cell, for every half-edge V -> X.
    order = np.lexsort((cx.he_to, cx.he_from, he_cell))
    keys = np.stack([he_cell, cx.he_from, cx.he_to], 1)[order]
    want = np.stack([he_cell, cx.he_to, cx.he_from], 1)
    pos = _search_rows(keys, want)
    twin = order[pos]
    e_here = E0 + cx.he_edge
    e_prev = E0 + cx.he_edge[cx.he_prev]
    f_here = F0 + he_face
    f_twin = F0 + he_face[twin]
    outer = np.stack([cx.he_from, e_here, f_here, e_prev], 1)
    inner = np.stack([e_here, f_twin, C0 + he_cell, f_here], 1)
    loops = np.concatenate([outer, inner])
    owner = np.concatenate([he_sub, he_sub])
    new = Complex(S.shape[0], loops, np.full(len(loops), 4, np.int64), owner, n_sub)

    # Hexahedral new cells (valence 3) and their trilinear corners.
    valence = np.bincount(he_sub, minlength=n_sub)
    hex_cells = np.flatnonzero(valence == 3)
    by_sub = np.argsort(he_sub, kind="stable")
    first = np.searchsorted(he_sub[by_sub], hex_cells)
    h = by_sub[first[:, None] + np.arange(3)]                      # (k, 3) half-edges leaving V
    h1 = h[:, 0]
    pv1 = cx.he_from[cx.he_prev[h1]]
    nx = cx.he_to[h]                                                # the three neighbours of V
    third = np.where((nx != nx[:, :1]) & (nx != pv1[:, None]), np.arange(3), 3).min(1)
    X = nx[np.arange(len(h)), third]
    pv = cx.he_from[cx.he_prev[h]]

    def face_between(p, q):
        hit = ((pv == p[:, None]) & (nx == q[:, None])) | ((pv == q[:, None]) & (nx == p[:, None]))
        return f_here[h[np.arange(len(h)), hit.argmax(1)]]
    hex_corners = np.stack([
        cx.he_from[h1], e_prev[h1], e_here[h1], f_here[h1],
        e_here[h[np.arange(len(h)), third]], face_between(pv1, X), face_between(nx[:, 0], X),
        C0 + he_cell[h1]], 1)
    return S, new, valence, hex_corners, hex_cells


def _search_rows(sorted_rows, queries):
    """Index in `sorted_rows` (lexicographically sorted, (m, 3)) of every query row (q, 3)."""
    big = sorted_rows.max(0) + 1
    def flat(a):
        return (a[:, 0] * big[1] + a[:, 1]) * big[2] + a[:, 2]
    return np.searchsorted(flat(sorted_rows), flat(queries))


class Refinement:
    """A cage refined `depth` times.

    chain: [S_1, ..., S_depth] (`Sparse`), so that refined points = S_depth ... S_1 P.
    complex: the refined cells (`Complex`); points: (n, 3) refined rest points.
    For depth >= 1 also valence, hex_corners, hex_cells of the last level (see `refine_once`).
    """

    def __init__(self, cage, depth):
        self.depth = depth
        self.chain = []
        cx = Complex.from_cells(cage.n_points, cage.cells)
        self.valence = self.hex_corners = self.hex_cells = None
        for _ in range(depth):
            S, cx, self.valence, self.hex_corners, self.hex_cells = refine_once(cx)
            self.chain.append(S)
        self.complex = cx
        self.points = self.apply(cage.rest_points)

    def apply(self, P):
        """Refined points (n, k) for cage points P (N, k)."""
        for S in self.chain:
            P = S.matvec(P)
        return P

    def apply_transpose(self, Y):
        """(S_depth ... S_1)^T Y for Y (n, k) or (n,): back on the cage points."""
        for S in reversed(self.chain):
            Y = S.rmatvec(Y)
        return Y

    def boundary_faces(self):
        """Outward loops of the refined faces that bound the region: list of tuples."""
        cx = self.complex
        loops = cx.face_loop[cx.face_cells == 1]
        return [tuple(cx.loops[i, :cx.sizes[i]].tolist()) for i in loops]


def refine(cage, depth):
    """`Refinement` of `cage` to `depth` levels (an integer from 0 to 6)."""
    if isinstance(depth, bool) or not float(depth).is_integer() or not 0 <= depth <= 6:
        raise ValueError(f"depth must be an integer from 0 to 6, got {depth!r}")
    return Refinement(cage, int(depth))
