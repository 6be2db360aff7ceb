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
"""
import numpy as np

from .cage import Topology
from .sparse import Sparse


class Refinement:
    """A cage refined `depth` times.

    chain: [S_1, ..., S_depth] (`Sparse`), so that refined points = S_depth ... S_1 P.
    topology: the refined cells (`cage.Topology`), all of type n (section 2.2) when depth >= 1.
    points: (n, 3) refined rest points.
    """

    def __init__(self, cage, depth):
        self.depth = depth
        self.chain = []
        topo = cage.topology
        for _ in range(depth):
            S, cells = refine_once(topo)
            self.chain.append(S)
            topo = Topology(S.shape[0], cells)
        self.topology = topo
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
        t = self.topology
        return [t.face_verts[f] for f, c in enumerate(t.face_cells) if len(c) == 1]


def refine(cage, depth):
    """`Refinement` of `cage` to `depth` levels (an integer >= 0)."""
    if isinstance(depth, bool) or not float(depth).is_integer() or not 0 <= depth <= 6:
        raise ValueError(f"depth must be an integer from 0 to 6, got {depth!r}")
    return Refinement(cage, int(depth))


def refine_once(topo):
    """One level: (S (n_new, n_old) `Sparse`, new cells as tuples of outward face loops).

    New points are numbered vertex points first (same index as the old point), then one per edge,
    one per face and one per cell, in the topology's order.
    """
    n, ne, nf = topo.n_points, len(topo.edge_verts), len(topo.face_verts)
    E0, F0, C0 = n, n + ne, n + ne + nf
    boundary_face, sharp, boundary_edge, kind = topo.classify()
    rows, cols, vals = [], [], []

    def put(row, points, weight):
        rows.extend([row] * len(points))
        cols.extend(points)
        vals.extend([weight / len(points)] * len(points))

    cell_pts = [topo.cell_points(c) for c in range(len(topo.cells))]
    for c, pts in enumerate(cell_pts):
        put(C0 + c, pts, 1.0)
    for f, owners in enumerate(topo.face_cells):
        if boundary_face[f]:
            put(F0 + f, topo.face_verts[f], 1.0)
        else:
            put(F0 + f, topo.face_verts[f], 0.5)
            for c in owners:
                put(F0 + f, cell_pts[c], 0.25)
    for e, (a, b) in enumerate(topo.edge_verts):
        row = E0 + e
        if sharp[e]:
            put(row, (a, b), 1.0)
        elif boundary_edge[e]:
            put(row, (a, b), 0.5)
            bf = [f for f in topo.edge_faces[e] if boundary_face[f]]
            for f in bf:
                put(row, topo.face_verts[f], 0.5 / len(bf))
        else:
            k = len(topo.edge_faces[e])
            cells = topo.edge_cells[e]
            for c in cells:
                put(row, cell_pts[c], 1.0 / (k * len(cells)))
            for f in topo.edge_faces[e]:
                put(row, topo.face_verts[f], 2.0 / (k * k))
            put(row, (a, b), (k - 3.0) / k)
    ev = topo.edge_verts
    for p in range(n):
        if kind[p] == 3:
            put(p, (p,), 1.0)
        elif kind[p] == 2:
            ends = [ev[e][0] + ev[e][1] - p for e in topo.point_edges[p] if sharp[e]]
            put(p, (p,), 0.75)
            put(p, ends, 0.25)
        elif kind[p] == 1:
            edges = [e for e in topo.point_edges[p] if boundary_edge[e]]
            faces = [f for f in topo.point_faces[p] if boundary_face[f]]
            k = len(edges)
            for f in faces:
                put(p, topo.face_verts[f], 1.0 / (k * len(faces)))
            for e in edges:
                put(p, ev[e], 2.0 / (k * k))
            put(p, (p,), (k - 3.0) / k)
        else:
            cells, faces, edges = topo.point_cells[p], topo.point_faces[p], topo.point_edges[p]
            for c in cells:
                put(p, cell_pts[c], 1.0 / (8 * len(cells)))
            for f in faces:
                put(p, topo.face_verts[f], 3.0 / (8 * len(faces)))
            for e in edges:
                put(p, ev[e], 3.0 / (8 * len(edges)))
            put(p, (p,), 1.0 / 8)
    S = Sparse(rows, cols, vals, (C0 + len(topo.cells), n))

    def edge(a, b):
        return E0 + topo.edge_id[(a, b) if a < b else (b, a)]

    new_cells = []
    for c, faces in enumerate(topo.cells):
        cp = C0 + c
        at = {}   # point -> [(face point, previous point, next point)] around it in this cell
        for f in faces:
            fp = F0 + topo.face_id[tuple(sorted(f))]
            m = len(f)
            for j, v in enumerate(f):
                at.setdefault(v, []).append((fp, f[j - 1], f[(j + 1) % m]))
        for v, around in at.items():
            sub = [(v, edge(v, nx), fp, edge(pv, v)) for fp, pv, nx in around]
            into = {nx: fp for fp, pv, nx in around}      # face where the edge runs v -> x
            out_of = {pv: fp for fp, pv, nx in around}    # face where it runs x -> v
            sub.extend((edge(v, x), out_of[x], cp, into[x]) for x in into)
            new_cells.append(tuple(sub))
    return S, new_cells
