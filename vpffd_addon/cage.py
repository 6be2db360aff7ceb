"""Cages of arbitrary topology (MacCracken & Joy 1996): points and closed polyhedral cells.

A cell is given by its faces, each a loop of point indices seen counter-clockwise from outside;
hexahedra, prisms, pyramids and tetrahedra may be given by their corners alone (`CELL_TEMPLATES`).
The deformable region is the limit of volumetric Catmull-Clark refinement with the paper's
boundary control (`subdivision.py`); a mesh is embedded in the refined cells (`cage_binding.py`).
"""
import numpy as np

from .lattice import Bounded
from .cells import face_triangles, tet_volumes, unique_rows
from .embedding import locate_in_tets
from .mesh import check_verts
from .subdivision import Complex, refine

#: Faces of the cells that may be given by their corners alone, keyed by the number of corners.
#: Corner order as in VTK / Blender's primitives: the base loop first, counter-clockwise seen
#: from the apex or the top, then the top loop above it.
CELL_TEMPLATES = {
    4: ((0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)),                                  # tetrahedron
    5: ((0, 3, 2, 1), (0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)),                   # pyramid
    6: ((0, 2, 1), (3, 4, 5), (0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)),             # prism
    8: ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)),  # hexahedron
}


def _parse_cell(i, cell, n_points):
    """One cell -> tuple of faces (tuples of ints); raises ValueError naming cell i."""
    try:
        items = list(cell)
    except TypeError:
        raise ValueError(f"cell {i} must be a list of corners or a list of faces, got {cell!r}") from None
    if items and all(np.ndim(x) == 0 for x in items):
        n = len(items)
        if n not in CELL_TEMPLATES:
            raise ValueError(f"cell {i} has {n} corners: give 4 (tetrahedron), 5 (pyramid), 6 (prism) "
                             "or 8 (hexahedron) corners, or the cell's faces")
        corners = [_index(i, x, n_points) for x in items]
        faces = [tuple(corners[k] for k in f) for f in CELL_TEMPLATES[n]]
    else:
        faces = []
        for f in items:
            try:
                face = tuple(_index(i, x, n_points) for x in f)
            except TypeError:
                raise ValueError(f"cell {i}: a face must be a list of point indices, got {f!r}") from None
            faces.append(face)
    if len(faces) < 4:
        raise ValueError(f"cell {i} has {len(faces)} faces: a closed cell needs at least 4")
    for f in faces:
        if len(f) < 3 or len(set(f)) != len(f):
            raise ValueError(f"cell {i} has a face {list(f)} that is not a loop of 3 or more distinct points")
    if len(set(map(lambda f: tuple(sorted(f)), faces))) != len(faces):
        raise ValueError(f"cell {i} lists the same face twice")
    # Closed and consistently oriented: every directed edge once, its reverse once.
    directed = {}
    for f in faces:
        for a, b in zip(f, f[1:] + f[:1]):
            if (a, b) in directed:
                raise ValueError(f"cell {i}: its faces are not consistently oriented (edge {a}-{b} "
                                 "runs the same way in two faces); list every face counter-clockwise "
                                 "seen from outside")
            directed[(a, b)] = True
    for a, b in directed:
        if (b, a) not in directed:
            raise ValueError(f"cell {i} is open: edge {a}-{b} belongs to only one of its faces")
    return tuple(faces)


def _index(i, x, n_points):
    if isinstance(x, (bool, np.bool_)) or not float(x).is_integer():
        raise ValueError(f"cell {i}: point index {x!r} is not an integer")
    k = int(x)
    if not 0 <= k < n_points:
        raise ValueError(f"cell {i}: point index {k} is outside [0, {n_points})")
    return k


def tet_partition(points, faces):
    """Tetrahedra (k, 4, 3) of a cell about its centre: every face split into triangles (quads by
    the diagonal through their lowest point, larger faces about their centroid), each triangle
    joined to the cell centre. Positive volume for an outward-oriented, star-shaped cell."""
    centre = points[sorted({p for f in faces for p in f})].mean(0)
    tets = []
    for f in faces:
        for a, b, c in face_triangles(f):
            A = points[a] if a >= 0 else points[list(f)].mean(0)
            tets.append((A, points[c], points[b], centre))
    return np.array(tets)


class Cage(Bounded):
    """A control cage of any topology: points (N, 3) and closed polyhedral cells.

    cells: a sequence of cells; each either its corners (4 tetrahedron, 5 pyramid, 6 prism,
    8 hexahedron, ordered as in `CELL_TEMPLATES`) or its faces, each a loop of point indices
    counter-clockwise seen from outside the cell. Neighbouring cells share faces (listed in
    opposite directions). Raises ValueError for open cells, inconsistent orientation, inverted or
    self-intersecting rest cells, overlapping cells, a face in more than two cells, no cells, or
    points that no cell uses.

    Plays the part of `Lattice` for `bind`: `rest_points`, `n_points`, `size`, `centre`.
    """

    def __init__(self, points, cells):
        P = check_verts(points, "cage points")
        N = len(P)
        try:
            cells = list(cells)
        except TypeError:
            raise ValueError(f"cells must be a sequence of cells, got {type(cells).__name__}") from None
        if not cells:
            raise ValueError("the cage has no cells: give at least one closed cell")
        parsed = [_parse_cell(i, c, N) for i, c in enumerate(cells)]
        _check_incidence(N, parsed)
        self._points = P
        self._regions = {}
        self.cells = parsed
        self._check_rest_cells()

    @property
    def rest_points(self):
        """(N, 3) the cage's points as given (the rest state)."""
        return self._points.copy()

    @property
    def n_points(self):
        return len(self._points)

    @property
    def n_cells(self):
        return len(self.cells)

    @property
    def lo(self):
        """(3,) low corner of the points' bounding box."""
        return self._points.min(0)

    @property
    def hi(self):
        """(3,) high corner of the points' bounding box."""
        return self._points.max(0)

    def region(self, depth=3):
        """The cage refined `depth` times (`subdivision.Refinement`): its points approach the
        deformable region as depth grows. Kept per depth: a cage does not change once made, and
        every mesh bound to it (or re-bound as it moves) shares the refinement."""
        if depth not in self._regions:
            self._regions[depth] = refine(self, depth)
        return self._regions[depth]

    def _check_rest_cells(self):
        P = self._points
        scale = self.size ** 3
        for c, faces in enumerate(self.cells):
            vol = tet_volumes(tet_partition(P, faces))
            if vol.sum() <= 1e-12 * scale:
                raise ValueError(f"cell {c} is inverted or flat at rest (volume {vol.sum():.3g}); list its "
                                 "faces counter-clockwise seen from outside")
            if (vol <= 1e-12 * scale).any():
                raise ValueError(f"cell {c} folds over itself at rest (it is not star-shaped about its "
                                 "centre: a twisted or self-intersecting cell)")
        # Overlapping cells: no point, edge middle or centre of one cell may lie strictly inside
        # another (shared points and edges lie on the boundary, not inside; a face centroid would
        # not, for a warped quad).
        probes, probe_cell, tets, owner = [], [], [], []
        for c, faces in enumerate(self.cells):
            pts = sorted({p for f in faces for p in f})
            loops = [P[list(f)] for f in faces]
            mids = [0.5 * (q + np.roll(q, -1, 0)) for q in loops]
            own = np.concatenate([P[pts], P[pts].mean(0)[None]] + mids)
            probes.append(own)
            probe_cell.append(np.full(len(own), c))
            t = tet_partition(P, faces)
            tets.append(t)
            owner.append(np.full(len(t), c))
        probe_cell, owner = np.concatenate(probe_cell), np.concatenate(owner)
        for probe, tet in locate_in_tets(np.concatenate(probes), np.concatenate(tets), margin=1e-9):
            if owner[tet] != probe_cell[probe]:
                raise ValueError(f"cells {int(probe_cell[probe])} and {int(owner[tet])} overlap at rest "
                                 "(part of one lies inside the other)")

    def __repr__(self):
        return f"Cage({self.n_points} points, {self.n_cells} cells)"


def _check_incidence(n_points, cells):
    """Raise ValueError for points no cell uses, a face in more than two cells, or a face two cells
    list in the same direction (one of them inside out). cells: parsed face loops."""
    cx = Complex.from_cells(n_points, cells)
    used = np.zeros(n_points, bool)
    used[cx.he_from] = True
    unused = np.flatnonzero(~used)
    if len(unused):
        raise ValueError(f"{len(unused)} cage points belong to no cell (first: {int(unused[0])})")

    def loop(i):
        return [int(p) for p in cx.loops[i, :cx.sizes[i]]]
    crowded = np.flatnonzero(cx.face_cells > 2)
    if len(crowded):
        f = crowded[0]
        owners = sorted(int(c) for c in cx.cell[cx.loop_face == f])
        raise ValueError(f"face {loop(cx.face_loop[f])} is shared by {len(owners)} cells {owners}; a face "
                         "can bound at most two cells")
    # Within a cell every directed edge is used once (`_parse_cell`), so a directed edge found twice
    # on one face comes from two cells that list the face the same way round.
    he_face = cx.loop_face[cx.he_loop]
    _, inverse = unique_rows(np.stack([he_face, cx.he_from, cx.he_to], 1))
    twice = np.flatnonzero(np.bincount(inverse)[inverse] > 1)
    if len(twice):
        f = he_face[twice[0]]
        l0, l1 = sorted(np.flatnonzero(cx.loop_face == f), key=lambda i: cx.cell[i])
        raise ValueError(f"cells {int(cx.cell[l0])} and {int(cx.cell[l1])} share face {loop(l0)} in the same "
                         "orientation: one of them is inside out (a shared face runs opposite ways in its "
                         "two cells)")


def box_cage(resolution=(2, 2, 2), bounds=((-1.0,) * 3, (1.0,) * 3)):
    """A box of hexahedral cells: resolution (cells along x, y, z, each >= 1) over bounds
    ((lo_x, lo_y, lo_z), (hi_x, hi_y, hi_z)). Points are numbered x fastest, then y, then z."""
    res = tuple(int(r) for r in resolution)
    if len(res) != 3 or min(res) < 1:
        raise ValueError(f"resolution needs three cell counts >= 1, got {resolution!r}")
    lo, hi = (np.asarray(b, np.float64).reshape(3) for b in bounds)
    if not (hi > lo).all():
        raise ValueError(f"bounds must have hi > lo on every axis, got {lo}, {hi}")
    nu, nv, nw = (r + 1 for r in res)
    axes = [np.linspace(lo[a], hi[a], res[a] + 1) for a in range(3)]
    w, v, u = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    points = np.stack([u.ravel(), v.ravel(), w.ravel()], 1)

    def idx(i, j, k):
        return (k * nv + j) * nu + i
    cells = [[idx(i, j, k), idx(i + 1, j, k), idx(i + 1, j + 1, k), idx(i, j + 1, k),
              idx(i, j, k + 1), idx(i + 1, j, k + 1), idx(i + 1, j + 1, k + 1), idx(i, j + 1, k + 1)]
             for k in range(res[2]) for j in range(res[1]) for i in range(res[0])]
    return Cage(points, cells)


def extrude(points, polygons, offset, layers=1):
    """The paper's extrusion tool: every polygon of a surface mesh becomes a column of `layers`
    cells swept along `offset` (3,). points (n, 3); polygons: loops of point indices. Returns
    (points (n * (layers + 1), 3), cells as face lists) for `Cage`; layer l's copy of point p is
    l * n + p. Loops may run either way round: each cell is oriented outward."""
    P = check_verts(points, "polygon points")
    t = np.asarray(offset, np.float64).reshape(3)
    if not np.isfinite(t).all() or not np.linalg.norm(t) > 0:
        raise ValueError(f"the extrusion offset must be a non-zero vector, got {offset!r}")
    layers = int(layers)
    if layers < 1:
        raise ValueError(f"layers must be >= 1, got {layers}")
    polys = [list(map(int, loop)) for loop in polygons]
    if not polys:
        raise ValueError("there are no polygons to extrude")
    n = len(P)
    out = np.concatenate([P + (l / layers) * t for l in range(layers + 1)])
    cells = []
    for i, loop in enumerate(polys):
        if len(loop) < 3 or len(set(loop)) != len(loop) or min(loop) < 0 or max(loop) >= n:
            raise ValueError(f"polygon {i} is not a loop of 3 or more distinct points")
        q = P[loop]
        normal = np.cross(q - q.mean(0), np.roll(q, -1, 0) - q.mean(0)).sum(0)
        if abs(normal @ t) <= 1e-12 * np.linalg.norm(normal) * np.linalg.norm(t):
            raise ValueError(f"polygon {i} is parallel to the extrusion direction")
        if normal @ t < 0:
            loop = loop[::-1]
        for l in range(layers):
            a, b = l * n, (l + 1) * n
            faces = [tuple(a + p for p in reversed(loop)), tuple(b + p for p in loop)]
            faces += [(a + p, a + q, b + q, b + p) for p, q in zip(loop, loop[1:] + loop[:1])]
            cells.append(faces)
    return out, cells
