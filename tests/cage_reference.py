"""A straightforward per-element implementation of the cage refinement rules (MacCracken & Joy,
sections 2.2 and 3), written with dictionaries and loops: the reference that the vectorised
`vpffd_addon.subdivision` is checked against (tests/test_cage_core.py)."""
import numpy as np

from vpffd_addon.sparse import Sparse


class _Incidence:
    """Incidence of a cell complex, with dictionaries: faces, edges and what contains what.

    cells: list of cells, each a tuple of faces, each a tuple of point indices (outward loops).
    Faces are keyed by their sorted point indices, edges by (low, high).
    """

    def __init__(self, n_points, cells):
        self.n_points = n_points
        self.cells = cells
        self.face_id, self.face_verts, self.face_cells = {}, [], []
        self.edge_id, self.edge_verts, self.edge_faces, self.edge_cells = {}, [], [], []
        self.point_cells = [[] for _ in range(n_points)]
        for c, faces in enumerate(cells):
            seen_edges = set()
            for f in faces:
                key = tuple(sorted(f))
                fid = self.face_id.get(key)
                if fid is None:
                    fid = self.face_id[key] = len(self.face_verts)
                    self.face_verts.append(f)
                    self.face_cells.append([])
                    for a, b in zip(f, f[1:] + f[:1]):
                        ekey = (a, b) if a < b else (b, a)
                        eid = self.edge_id.get(ekey)
                        if eid is None:
                            eid = self.edge_id[ekey] = len(self.edge_verts)
                            self.edge_verts.append(ekey)
                            self.edge_faces.append([])
                            self.edge_cells.append([])
                        self.edge_faces[eid].append(fid)
                self.face_cells[fid].append(c)
                for a, b in zip(f, f[1:] + f[:1]):
                    seen_edges.add((a, b) if a < b else (b, a))
            for ekey in seen_edges:
                self.edge_cells[self.edge_id[ekey]].append(c)
            for p in {p for f in faces for p in f}:
                self.point_cells[p].append(c)

    def cell_points(self, c):
        """Sorted distinct points of cell c."""
        return sorted({p for f in self.cells[c] for p in f})


class Topology(_Incidence):
    """The incidence tables plus what the rules need per point, and the classification."""

    def __init__(self, n_points, cells):
        super().__init__(n_points, cells)
        self.point_edges = [[] for _ in range(n_points)]
        for e, (a, b) in enumerate(self.edge_verts):
            self.point_edges[a].append(e)
            self.point_edges[b].append(e)
        self.point_faces = [[] for _ in range(n_points)]
        for fid, f in enumerate(self.face_verts):
            for p in f:
                self.point_faces[p].append(fid)

    def classify(self):
        """Boundary control of section 3, decided from the topology alone.

        Returns (boundary_face (n_faces,) bool, sharp_edge (n_edges,) bool, boundary_edge (n_edges,)
        bool, point_kind (n_points,) int: 0 interior, 1 smooth boundary, 2 crease, 3 corner).
        A face is on the boundary when one cell holds it. An edge is sharp when it lies on the
        boundary and one cell holds it (the edges of a box, the rims of an extruded disc); this is
        the paper's rule of "edges joining vertices in one or two cells" stated on the edge itself,
        so that a cage one cell thick is not creased across its faces. A point is a corner when
        three or more sharp edges meet there (which includes every point of only one cell), a crease
        point when two do.
        """
        boundary_face = np.array([len(c) == 1 for c in self.face_cells], bool)
        n_edges = len(self.edge_verts)
        boundary_edge = np.array([boundary_face[self.edge_faces[e]].any() for e in range(n_edges)], bool)
        sharp = boundary_edge & np.array([len(c) == 1 for c in self.edge_cells], bool)
        ev = np.array(self.edge_verts, np.int64).reshape(-1, 2)
        n_sharp = np.bincount(ev[sharp].ravel(), minlength=self.n_points)
        on_boundary = np.zeros(self.n_points, bool)
        on_boundary[ev[boundary_edge].ravel()] = True
        kind = np.where(on_boundary, 1, 0)
        kind[n_sharp == 2] = 2
        kind[n_sharp >= 3] = 3
        return boundary_face, sharp, boundary_edge, kind



def reference_levels(cage, depth):
    """Refined rest points (n, 3) and number of cells after `depth` levels."""
    topo = Topology(cage.n_points, list(cage.cells))
    P = cage.rest_points
    for _ in range(depth):
        S, cells = refine_once(topo)
        P = S.matvec(P)
        topo = Topology(S.shape[0], cells)
    return P, len(topo.cells)


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
