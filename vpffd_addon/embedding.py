"""Embedding points in refined cage cells (MacCracken & Joy, section 4).

Hexahedral cells (type 3) carry trilinear coordinates (u, v, w); other cells are split into
tetrahedra about their centre, two per quad face (Figure 6), and carry barycentric coordinates.
Each embedded point is then a fixed combination of at most 8 refined points.
"""
import numpy as np

from .cells import TET_DW, face_triangles
from .linalg3 import det3, inv3, solve3
from .sparse import Sparse

#: Corners of a trilinear cell in bit order: corner k sits at (k & 1, k >> 1 & 1, k >> 2 & 1).
_BITS = np.array([[(k >> a) & 1 for a in range(3)] for k in range(8)], np.float64)
_NEWTON_STEPS = 30
_INSIDE = 1e-9          # parameter slack when deciding that a point lies in a cell
_NEAREST = 4            # boundary elements tried per outside point


def hex_order(faces):
    """The 8 corners of a hexahedral cell (six quads, three at every corner) in trilinear bit order
    with a right-handed (u, v, w) frame, or None when the cell is not such a hexahedron."""
    pts = {p for f in faces for p in f}
    if len(faces) != 6 or len(pts) != 8 or any(len(f) != 4 for f in faces):
        return None
    if any(sum(p in f for f in faces) != 3 for p in pts):
        return None
    v0, b, ab, a = faces[0]            # outward loop: (a, v0, b) turn => u along a, v along b
    nbrs = {q for f in faces if v0 in f for q in (f[f.index(v0) - 1], f[(f.index(v0) + 1) % 4])}
    (c,) = nbrs - {a, b}

    def opposite(x, y):  # the corner diagonal to v0 in the face through v0, x and y
        f = next(f for f in faces if {v0, x, y} <= set(f))
        return f[(f.index(v0) + 2) % 4]

    ac, bc = opposite(a, c), opposite(b, c)
    (abc,) = pts - {v0, a, b, ab, c, ac, bc}
    return [v0, a, b, ab, c, ac, bc, abc]


def trilinear(u):
    """Weights (m, 8) and their derivatives (m, 8, 3) at trilinear coordinates u (m, 3)."""
    m = len(u)
    f = np.stack([1.0 - u, u], 1)                          # (m, 2, 3): factors for bit 0 and 1
    fx, fy, fz = f[:, None, None, :, 0], f[:, None, :, None, 1], f[:, :, None, None, 2]
    d = np.array([-1.0, 1.0])
    dx, dy, dz = d[None, None, None, :], d[None, None, :, None], d[None, :, None, None]
    w = (fz * fy * fx).reshape(m, 8)                      # index x + 2 y + 4 z
    dw = np.empty((m, 8, 3))
    dw[:, :, 0] = (fz * fy * dx).reshape(m, 8)
    dw[:, :, 1] = (fz * dy * fx).reshape(m, 8)
    dw[:, :, 2] = (dz * fy * fx).reshape(m, 8)
    return w, dw


def barycentric_weights(lam):
    """Weights (m, 8) of a tetrahedron's corners (then 4 unused) at barycentric lam (m, 3)."""
    w = np.zeros((len(lam), 8))
    w[:, 0] = 1.0 - lam.sum(1)
    w[:, 1:4] = lam
    return w


class Elements:
    """The embedding elements of a refinement: trilinear hexahedra and tetrahedra.

    ext: `Sparse` (n_ext, n) appending the extra points the tetrahedra need (cell centres, and
    centroids of faces with more than four sides) to the refined points.
    corners: (k, 8) indices into the extended points (tetrahedra use the first 4).
    is_hex: (k,) bool. cell: (k,) refined cell of each element. on_boundary: (k,) whether that
    cell has a face on the region's boundary.
    """

    def __init__(self, cage, refinement):
        cx = refinement.complex
        if refinement.depth == 0:
            self._from_cells(cx.n_points, cage.cells)
        else:
            self._from_refinement(refinement)
        boundary_cells = np.unique(cx.cell[(cx.face_cells == 1)[cx.loop_face]])
        self.on_boundary = np.isin(self.cell, boundary_cells)

    def _from_refinement(self, ref):
        """After a refinement: hexahedra where the parent point had valence 3 (their corners come
        from the refinement); the other cells (type n > 3) as 4n tetrahedra about their centre."""
        cx = ref.complex
        n = cx.n_points
        tet_cells = np.flatnonzero(ref.valence != 3)
        # The centre of every type-n cell: mean of its distinct points.
        is_tet_cell = np.zeros(cx.n_cells, bool)
        is_tet_cell[tet_cells] = True
        centre_row = np.full(cx.n_cells, -1, np.int64)
        centre_row[tet_cells] = n + np.arange(len(tet_cells))
        loops = np.flatnonzero(is_tet_cell[cx.cell])
        pairs = np.unique(np.stack([np.repeat(cx.cell[loops], 4), cx.loops[loops, :4].ravel()], 1), axis=0)
        count = np.bincount(pairs[:, 0], minlength=cx.n_cells)
        rows = np.concatenate([np.arange(n), centre_row[pairs[:, 0]]])
        cols = np.concatenate([np.arange(n), pairs[:, 1]])
        vals = np.concatenate([np.ones(n), 1.0 / count[pairs[:, 0]]])
        self.ext = Sparse(rows, cols, vals, (n + len(tet_cells), n))
        # Two triangles per quad, split by the diagonal through its lowest point (the same split
        # from both sides of a face); tetrahedron (a, c, b, centre) for outward (a, b, c).
        q = cx.loops[loops, :4]
        q = np.take_along_axis(q, (np.argmin(q, 1)[:, None] + np.arange(4)) % 4, 1)
        centre = centre_row[cx.cell[loops]]
        tets = np.concatenate([np.stack([q[:, 0], q[:, 2], q[:, 1], centre], 1),
                               np.stack([q[:, 0], q[:, 3], q[:, 2], centre], 1)])
        n_hex = len(ref.hex_cells)
        self.corners = np.zeros((n_hex + len(tets), 8), np.int64)
        self.corners[:n_hex] = ref.hex_corners
        self.corners[n_hex:, :4] = tets
        self.is_hex = np.r_[np.ones(n_hex, bool), np.zeros(len(tets), bool)]
        self.cell = np.r_[ref.hex_cells, np.tile(cx.cell[loops], 2)]

    def _from_cells(self, n, cells):
        """The cage's own cells (depth 0): hexahedra trilinear, any other cell as tetrahedra about
        its centre (faces of more than four sides about their centroid)."""
        extra_rows, extra_cols, extra_vals = [], [], []
        n_extra = 0

        def extra(points):
            nonlocal n_extra
            row = n + n_extra
            n_extra += 1
            extra_rows.extend([row] * len(points))
            extra_cols.extend(points)
            extra_vals.extend([1.0 / len(points)] * len(points))
            return row

        face_centre = {}
        corners, is_hex, cell_of = [], [], []
        for c, faces in enumerate(cells):
            order = hex_order(faces)
            if order is not None:
                corners.append(order)
                is_hex.append(True)
                cell_of.append(c)
                continue
            centre = extra(sorted({p for f in faces for p in f}))
            for f in faces:
                for a, b, d in face_triangles(f):
                    if a < 0:
                        key = tuple(sorted(f))
                        if key not in face_centre:
                            face_centre[key] = extra(list(f))
                        a = face_centre[key]
                    corners.append([a, d, b, centre, 0, 0, 0, 0])   # positive for outward (a, b, d)
                    is_hex.append(False)
                    cell_of.append(c)
        rows = np.concatenate([np.arange(n), np.array(extra_rows, np.int64)])
        cols = np.concatenate([np.arange(n), np.array(extra_cols, np.int64)])
        vals = np.concatenate([np.ones(n), np.array(extra_vals)])
        self.ext = Sparse(rows, cols, vals, (n + n_extra, n))
        self.corners = np.array(corners, np.int64).reshape(-1, 8)
        self.is_hex = np.array(is_hex, bool)
        self.cell = np.array(cell_of, np.int64)


def locate(points, X, elements):
    """Find the element holding each point.

    points (V, 3); X (n_ext, 3) extended rest points. Returns (element (V,) with -1 where no
    element holds the point, parameters (V, 3)).
    """
    V = len(points)
    corners = elements.corners
    hexes = elements.is_hex
    cx = X[corners]                                                   # (k, 8, 3)
    lo = np.where(hexes[:, None], cx.min(1), cx[:, :4].min(1))
    hi = np.where(hexes[:, None], cx.max(1), cx[:, :4].max(1))
    pi, ei = _bbox_pairs(points, lo, hi)
    best = np.full(V, -1, np.int64)
    param = np.zeros((V, 3))
    if len(pi) == 0:
        return best, param
    margin = np.full(len(pi), -np.inf)
    prm = np.zeros((len(pi), 3))
    h = hexes[ei]
    if h.any():
        # The cell's affine approximation at its centre rules out most candidates cheaply and
        # gives Newton's method a close start.
        hx = np.flatnonzero(hexes)
        w, dw = trilinear(np.full((len(hx), 3), 0.5))
        centre = np.einsum("mk,mkc->mc", w, cx[hx])
        J = np.einsum("mka,mkc->mca", dw, cx[hx])
        good = np.abs(det3(J)) > 1e-300
        Jinv = np.zeros_like(J)
        Jinv[good] = inv3(J[good])
        slot = np.full(len(hexes), -1)
        slot[hx] = np.arange(len(hx))
        hp = np.flatnonzero(h)
        s = slot[ei[hp]]
        u0 = 0.5 + np.einsum("mac,mc->ma", Jinv[s], points[pi[hp]] - centre[s])
        near = ((u0 > -0.5) & (u0 < 1.5)).all(1) | ~good[s]
        hp, u0 = hp[near], u0[near]
        u, ok = invert_trilinear(points[pi[hp]], cx[ei[hp]], start=np.clip(u0, 0.0, 1.0))
        prm[hp] = u
        margin[hp] = np.where(ok, np.minimum(u, 1.0 - u).min(1), -np.inf)
    t = ~h
    if t.any():
        lam = barycentric(points[pi[t]], cx[ei[t], :4])
        prm[t] = lam
        margin[t] = np.minimum(lam.min(1), 1.0 - lam.sum(1))
    inside = margin >= -_INSIDE
    pi, ei, margin, prm = pi[inside], ei[inside], margin[inside], prm[inside]
    if not len(pi):
        return best, param
    order = np.lexsort((-margin, pi))                  # per point, the most interior element first
    pi, ei, prm = pi[order], ei[order], prm[order]
    first = np.r_[True, pi[1:] != pi[:-1]]
    best[pi[first]] = ei[first]
    param[pi[first]] = prm[first]
    return best, param


def nearest_boundary(points, X, elements):
    """For points outside the region: (element (V,), parameters (V, 3)) of the closest point of
    the boundary elements, parameters clamped into the element."""
    cand = np.flatnonzero(elements.on_boundary)
    corners = elements.corners[cand]
    hexes = elements.is_hex[cand]
    cx = X[corners]
    centre = np.where(hexes[:, None], cx.mean(1), cx[:, :4].mean(1))
    V = len(points)
    k = min(_NEAREST, len(cand))
    near = np.empty((V, k), np.int64)
    c2 = (centre ** 2).sum(1)
    for s in range(0, V, 4096):
        d = c2[None] - 2.0 * points[s:s + 4096] @ centre.T     # |p - c|^2 - |p|^2
        near[s:s + 4096] = np.argpartition(d, k - 1, axis=1)[:, :k] if k < len(cand) else np.arange(k)
    pi = np.repeat(np.arange(V), k)
    ei = near.ravel()
    prm = np.zeros((len(pi), 3))
    h = hexes[ei]
    if h.any():
        u, _ = invert_trilinear(points[pi[h]], cx[ei[h]], steps=12)
        prm[h] = np.clip(u, 0.0, 1.0)
    t = ~h
    if t.any():
        lam = np.clip(barycentric(points[pi[t]], cx[ei[t], :4]), 0.0, None)
        total = lam.sum(1, keepdims=True)
        prm[t] = np.where(total > 1.0, lam / np.maximum(total, 1e-300), lam)
    w = np.where(h[:, None], trilinear(prm)[0], barycentric_weights(prm))
    pos = np.einsum("mk,mkc->mc", w, cx[ei])
    dist = ((pos - points[pi]) ** 2).sum(1).reshape(V, k)
    pick = np.argmin(dist, 1)
    rows = np.arange(V) * k + pick
    return cand[ei[rows]], prm[rows]


def trilinear_coefficients(cx):
    """(m, 8, 3) coefficients of x(u, v, w) = c0 + c1 u + c2 v + c3 w + c4 u v + c5 u w + c6 v w
    + c7 u v w for cells with corners cx (m, 8, 3) in bit order."""
    a = cx
    c = np.empty_like(a)
    c[:, 0] = a[:, 0]
    c[:, 1] = a[:, 1] - a[:, 0]
    c[:, 2] = a[:, 2] - a[:, 0]
    c[:, 3] = a[:, 4] - a[:, 0]
    c[:, 4] = a[:, 3] - a[:, 1] - a[:, 2] + a[:, 0]
    c[:, 5] = a[:, 5] - a[:, 1] - a[:, 4] + a[:, 0]
    c[:, 6] = a[:, 6] - a[:, 2] - a[:, 4] + a[:, 0]
    c[:, 7] = a[:, 7] - a[:, 3] - a[:, 5] - a[:, 6] + a[:, 1] + a[:, 2] + a[:, 4] - a[:, 0]
    return c


def invert_trilinear(p, cx, steps=_NEWTON_STEPS, start=None, chunk=262144):
    """Trilinear coordinates (m, 3) of points p (m, 3) in cells with corners cx (m, 8, 3), by
    Newton's method from `start` (m, 3) (default the centre), and whether it converged within
    `steps`. Works on the polynomial form, in chunks, so that no (m, 8, 3) temporaries repeat."""
    m = len(p)
    u = np.full((m, 3), 0.5) if start is None else np.array(start, np.float64)
    ok = np.zeros(m, bool)
    for s0 in range(0, m, chunk):
        sl = slice(s0, min(m, s0 + chunk))
        c = trilinear_coefficients(cx[sl])
        scale = np.abs(c[:, 1:4]).max((1, 2)) + 1e-300
        u[sl], ok[sl] = _newton(p[sl], c, u[sl], scale, steps)
    return u, ok


def _newton(p, c, u, scale, steps):
    """Newton iterations on the polynomial form; the working arrays shrink to the unconverged."""
    ok = np.zeros(len(p), bool)
    active = np.arange(len(p))
    ca, pa, ua, sa = c, p, u.copy(), scale
    for _ in range(steps):
        x, y, z = ua[:, 0:1], ua[:, 1:2], ua[:, 2:3]
        xy = x * y
        pos = (ca[:, 0] + ca[:, 1] * x + ca[:, 2] * y + ca[:, 3] * z + ca[:, 4] * xy
               + ca[:, 5] * (x * z) + ca[:, 6] * (y * z) + ca[:, 7] * (xy * z))
        r = pa - pos
        done = np.abs(r).max(1) <= 1e-13 * sa
        u[active[done]] = ua[done]
        ok[active[done]] = True
        keep = ~done
        if not keep.any():
            return u, ok
        active, ca, pa, ua, sa, r = active[keep], ca[keep], pa[keep], ua[keep], sa[keep], r[keep]
        x, y, z = ua[:, 0:1], ua[:, 1:2], ua[:, 2:3]
        ju = ca[:, 1] + ca[:, 4] * y + ca[:, 5] * z + ca[:, 7] * (y * z)
        jv = ca[:, 2] + ca[:, 4] * x + ca[:, 6] * z + ca[:, 7] * (x * z)
        jw = ca[:, 3] + ca[:, 5] * x + ca[:, 6] * y + ca[:, 7] * (x * y)
        # Cramer's rule for J du = r, J = [ju jv jw].
        cvw, cwu, cuv = np.cross(jv, jw), np.cross(jw, ju), np.cross(ju, jv)
        det = np.einsum("ij,ij->i", ju, cvw)
        good = np.abs(det) > 1e-300
        inv = np.where(good, 1.0 / np.where(good, det, 1.0), 0.0)[:, None]
        step = np.stack([np.einsum("ij,ij->i", r, cvw), np.einsum("ij,ij->i", r, cwu),
                         np.einsum("ij,ij->i", r, cuv)], 1) * inv
        ua = np.clip(ua + step, -4.0, 5.0)
    u[active] = ua
    return u, ok


def barycentric(p, tx):
    """Barycentric coordinates (m, 3) (of corners 1..3) of points p (m, 3) in tetrahedra (m, 4, 3)."""
    M = (tx[:, 1:4] - tx[:, :1]).transpose(0, 2, 1)
    det = det3(M)
    lam = np.full((len(p), 3), -np.inf)
    good = np.abs(det) > 1e-300
    lam[good] = solve3(M[good], p[good] - tx[good, 0])
    return lam


def locate_in_tets(points, tets, margin):
    """[(point, tet)] for points (m, 3) strictly inside tetrahedra (k, 4, 3) by `margin`."""
    pi, ti = _bbox_pairs(points, tets.min(1), tets.max(1))
    if not len(pi):
        return []
    lam = barycentric(points[pi], tets[ti])
    inside = np.minimum(lam.min(1), 1.0 - lam.sum(1)) > margin
    return list(zip(pi[inside].tolist(), ti[inside].tolist()))


def _bbox_pairs(points, lo, hi):
    """(point index, box index) pairs with the point inside the box (slightly enlarged), through a
    uniform grid of about one box per grid cell."""
    if len(points) == 0 or len(lo) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pad = 1e-9 * (hi - lo).max() + 1e-300
    lo, hi = lo - pad, hi + pad
    glo, ghi = lo.min(0), hi.max(0)
    # Grid cells about half a box on each axis: a point then meets few boxes besides its own.
    h = np.maximum(0.5 * np.median(hi - lo, axis=0), 1e-300)
    h = np.maximum(h, 1e-6 * (ghi - glo).max() + 1e-300)
    dims = np.maximum(np.ceil((ghi - glo) / h).astype(np.int64), 1)
    limit = min(64 * len(lo), 4 * len(points)) + 64
    while dims.prod() > limit:
        h *= 1.25
        dims = np.maximum(np.ceil((ghi - glo) / h).astype(np.int64), 1)
    i0 = np.clip(np.floor((lo - glo) / h).astype(np.int64), 0, dims - 1)
    i1 = np.clip(np.floor((hi - glo) / h).astype(np.int64), 0, dims - 1)
    span = i1 - i0 + 1
    count = span.prod(1)
    box = np.repeat(np.arange(len(lo)), count)
    local = np.arange(len(box)) - np.repeat(np.cumsum(count) - count, count)
    sx, sy = span[box, 0], span[box, 1]
    cell = i0[box] + np.stack([local % sx, (local // sx) % sy, local // (sx * sy)], 1)
    key = (cell[:, 2] * dims[1] + cell[:, 1]) * dims[0] + cell[:, 0]
    order = np.argsort(key, kind="stable")
    key, box = key[order], box[order]
    pc = np.floor((points - glo) / h).astype(np.int64)
    inside_grid = ((pc >= 0) & (pc < dims)).all(1)
    pkey = (pc[:, 2] * dims[1] + pc[:, 1]) * dims[0] + pc[:, 0]
    # Per grid cell, where its boxes start in the sorted list (a dense table: the grid is small).
    first = np.r_[0, np.cumsum(np.bincount(key, minlength=int(dims.prod())))]
    pkey = np.where(inside_grid, pkey, 0)
    start = first[pkey]
    n = np.where(inside_grid, first[pkey + 1] - start, 0)
    pi = np.repeat(np.arange(len(points)), n)
    k = np.repeat(start, n) + (np.arange(len(pi)) - np.repeat(np.cumsum(n) - n, n))
    bi = box[k]
    within = ((points[pi] >= lo[bi]) & (points[pi] <= hi[bi])).all(1)
    return pi[within], bi[within]
