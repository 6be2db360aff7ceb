"""Enclosed volume of triangle meshes and its gradient (docs/design.md, "The volume and its
gradient"; paper eq. 5 and 10-12)."""
import numpy as np

from .mesh import check_tris, check_verts


def signed_volume(verts, tris, origin=None):
    """Signed volume enclosed by triangles `tris` (F, 3) over `verts` (V, 3), as float.

    ``V = 1/6 sum_faces x_l . (x_m x x_n)`` measured about `origin` (3,) (default: the coordinate
    origin); for a closed, consistently oriented mesh the origin does not matter. Outward normals
    give a positive volume, inward normals a negative one.
    """
    v = check_verts(verts)
    t = check_tris(tris, len(v))
    if origin is not None:
        v = v - np.asarray(origin, dtype=np.float64).reshape(1, 3)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def face_volumes(coords_t, tris_t):
    """(F,) float64 signed volume terms ``1/6 a . (b x c)`` of the faces `tris_t` (3, F) (row k:
    corner k of every face) over the coordinates `coords_t` (3, V) (rows x, y, z), taken about
    their origin. Rows are gathered whole, which is several times faster than (F, 3) gathers."""
    x, y, z = (np.take(c, tris_t) for c in coords_t)
    return (x[0] * (y[1] * z[2] - z[1] * y[2])
            + y[0] * (z[1] * x[2] - x[1] * z[2])
            + z[0] * (x[1] * y[2] - y[1] * x[2])) / 6.0


#: Faces per chunk of `chunked_sums` (fixed, so that the sums do not depend on how many threads
#: made them).
FACE_CHUNK = 4096


def chunked_sums(face_vol):
    """(sum, sum of absolute values) of face_vol (F,) float64, in a fixed order: each chunk of
    `FACE_CHUNK` faces summed in the faces' order, then the chunks' sums in theirs, each addition
    one float64 rounding. The compiled bind makes these sums as it makes the terms, in chunks on
    the worker threads, without writing the terms (`layout_kernels.face_volume_sums`); this is the
    same arithmetic in NumPy (`cumsum` adds in order), so both give the same bits."""
    F = len(face_vol)
    n = max(1, -(-F // FACE_CHUNK))
    padded = np.zeros(n * FACE_CHUNK)
    padded[:F] = face_vol
    chunks = padded.reshape(n, FACE_CHUNK)
    per_chunk = np.stack([np.cumsum(chunks, axis=1)[:, -1], np.cumsum(np.abs(chunks), axis=1)[:, -1]])
    return np.cumsum(per_chunk, axis=1)[:, -1]


def gradient_component(P, Q, corners, n_slots):
    """Volume gradient along a direction e, at every vertex slot, from the other two coordinates.

    P, Q: (3, F) coordinates of the face corners on unit vectors p, q that complete e to a
    right-handed orthonormal frame (e, p, q), measured from the volume's origin (P = p[corners]).
    corners: (3, F) vertex slots of the faces (row k = corner k of every face).
    Returns (n_slots,) float64 ``dV/d(x.e) = 1/6 sum_{faces (v, m, n)} (p_m q_n - q_m p_n)``, which does
    not depend on the e-coordinates, so ``V = sum_v (x_v . e) * g_v`` (V is homogeneous of degree one
    in them).
    """
    c = np.empty(P.shape, dtype=P.dtype)
    tmp = np.empty(P.shape[1], dtype=P.dtype)
    for k, (m, n) in enumerate(((1, 2), (2, 0), (0, 1))):
        np.multiply(P[m], Q[n], out=c[k])
        np.multiply(Q[m], P[n], out=tmp)
        c[k] -= tmp
    # bincount sums in float64 whatever the input precision.
    g = np.bincount(corners.ravel(), c.ravel(), n_slots)
    g *= 1.0 / 6.0
    return g


#: About how many of one island's vertices its origin is taken from (`origins_about`): the
#: origin only keeps the terms' rounding small, and any point near the mesh serves.
ORIGIN_SAMPLES = 512


class MeasuredIn:
    """A closed mesh's rest volume measured from `points` (V, 3) float32 or float64 (C order),
    of which the positions a binding binds are an affine image with determinant `det`: the
    object's own space, for a mesh bound in the lattice's (docs/performance.md, "The volume of a
    mesh that only moves"). Every island's volume there is det times its volume here, so a mesh
    that only moves keeps the sums measured once, and a frame's result is the same whether they
    were kept or measured again: they depend on `points` alone.

    origins (k, 3) float64: per island, the point its terms are taken about (`origins_about`).
    sums: None until a bind measures them (it fills them in, `measure_about`'s result); a caller
    binding the same points again hands the same back and the bind skips the faces."""

    def __init__(self, points, det, origins, sums=None):
        points = np.asarray(points)
        if points.dtype not in (np.float32, np.float64):
            points = points.astype(np.float64)
        self.points = np.ascontiguousarray(points)
        self.origins = np.ascontiguousarray(origins, dtype=np.float64)
        self.det, self.sums = float(det), sums
        if self.points.ndim != 2 or self.points.shape[1:] != (3,):
            raise ValueError(f"MeasuredIn's points must have shape (V, 3), got {self.points.shape}")
        if self.origins.ndim != 2 or self.origins.shape[1:] != (3,) or not np.isfinite(self.origins).all():
            raise ValueError(f"MeasuredIn's origins must be finite, of shape (islands, 3), got {self.origins.shape}")
        if not np.isfinite(self.det):
            raise ValueError("MeasuredIn's determinant must be finite")
        if sums is not None and not (np.ndim(sums[0]) == 0 and np.shape(sums[1]) == (2, len(self.origins))):
            raise ValueError("MeasuredIn's sums must be (the total, (2, islands)), as measure_about gives them")

    def scaled(self):
        """(the total volume, (2, k): per island the volume and the sum of the terms' absolute
        values) in the binding's space: det times those measured here (|det| for the second)."""
        total, sums = self.sums
        return self.det * total, np.stack([self.det * sums[0], abs(self.det) * sums[1]])


def origins_about(points, topology):
    """(k, 3) float64: per island of `topology`, the point about which `measure_about` takes its
    terms: the centre of its bounding box; for one island, the box of about `ORIGIN_SAMPLES` of
    its vertices, evenly spaced in their order (a mesh that deforms on every frame measures its
    volume on every frame, and any point near the mesh keeps the terms small)."""
    if topology.n_islands == 1:
        step = max(1, len(points) // ORIGIN_SAMPLES)
        cols = np.ascontiguousarray(np.asarray(points[::step]).T, dtype=np.float64)
        return (0.5 * (cols.min(axis=1) + cols.max(axis=1)))[None]
    lo, hi = topology.island_bounds(np.asarray(points, np.float64))
    return 0.5 * (lo + hi)


def measure_about(points, origins, topology):
    """(total, (2, k)) of the faces of `topology` over points (V, 3), each island's terms about
    its row of origins (k, 3): the volume, and per island the volume and the sum of the terms'
    absolute values, as a bind adds them up (one island: `chunked_sums`; islands: per face, then
    per island, and the total NumPy's sum of the faces' terms). NumPy; the compiled bind makes the
    same bits (`layout_kernels.face_volume_sums_about`, `face_volumes_about`)."""
    p = np.asarray(points, np.float64)
    rel = p - (origins[0] if topology.n_islands == 1 else origins[topology.labels])
    face = face_volumes(np.ascontiguousarray(rel.T), topology.tris_t)
    if topology.n_islands == 1:
        sums = chunked_sums(face)[:, None]
        return float(sums[0, 0]), sums
    k, island = topology.n_islands, topology.face_island
    return float(face.sum()), np.stack([np.bincount(island, face, k), np.bincount(island, np.abs(face), k)])
