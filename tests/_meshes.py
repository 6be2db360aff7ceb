"""Random test meshes, lattices and deformations shared by the core tests (NumPy only).

Everything is drawn from a `numpy.random.Generator`, so a hypothesis-drawn seed reproduces a case.
Nothing here calls the solver; the meshes come from `vpffd_addon.shapes` and are then transformed
in ways that keep them closed, consistently oriented and free of self-intersections:
radial jitter of a star-shaped mesh about its centre (every ray still meets the surface once),
then a linear map with positive determinant (non-uniform stretch and rotation), then a shift.
"""
import numpy as np

import vpffd_addon as vp

KINDS = ("LINEAR", "CARDINAL", "CATMULL_ROM", "BSPLINE", "BEZIER")


def rotation(rng):
    """Uniformly random proper rotation (3, 3)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def star_mesh(rng, max_subdivisions=2, max_resolution=3, jitter=0.25):
    """One closed star-shaped mesh centred on the origin with outward normals, radius about 1.

    Returns (verts, tris) with verts (V, 3) float64.
    """
    if rng.random() < 0.5:
        v, f = vp.icosphere(int(rng.integers(1, max_subdivisions + 1)), 1.0)
    else:
        v, f = vp.box(int(rng.integers(1, max_resolution + 1)), 1.5)
    v = v * (1.0 + jitter * rng.uniform(-1.0, 1.0, len(v)))[:, None]
    stretch = np.diag(rng.uniform(0.6, 1.4, 3))
    v = v @ (rotation(rng) @ stretch @ rotation(rng)).T
    return v - v.mean(0), f


def union(parts):
    """Concatenate meshes [(verts, tris), ...] into one: (verts, tris, part (V,) part index)."""
    verts, tris, part, base = [], [], [], 0
    for k, (v, f) in enumerate(parts):
        verts.append(v)
        tris.append(f + base)
        part.append(np.full(len(v), k))
        base += len(v)
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(part)


def closed_mesh(rng, n_parts=1, inward=False, **kw):
    """1-3 disjoint closed star-shaped meshes, placed side by side and shrunk to fit [-1, 1]^3.

    Returns (verts, tris, part) where part (V,) says which piece every vertex belongs to.
    With `inward`, every face is flipped (negative volume).
    """
    pieces = []
    for k in range(n_parts):
        v, f = star_mesh(rng, **kw)
        r = np.linalg.norm(v, axis=1).max()
        pieces.append((v / r, f))                      # inside the unit ball
    # Unit balls on a line with gaps, jittered across it; then everything scaled to fit [-1, 1]^3.
    shifted = []
    for k, (v, f) in enumerate(pieces):
        c = np.array([2.3 * (k - (n_parts - 1) / 2.0), 0.0, 0.0])
        c[1:] = rng.uniform(-0.3, 0.3, 2)
        shifted.append((v + c, f))
    verts, tris, part = union(shifted)
    verts = verts @ rotation(rng).T
    verts = verts / np.abs(verts).max()
    if inward:
        tris = tris[:, ::-1].copy()
    return verts, tris, part


def random_lattice(rng, verts, shape=None, kinds=None, min_n=1, max_n=6, margin=(-0.3, 0.15)):
    """A lattice whose box covers most of `verts`: per side, the bounding box moved outwards by up
    to -margin[0] of its extent or inwards by up to margin[1] (so some vertices may lie outside)."""
    if shape is None:
        shape = tuple(int(n) for n in rng.integers(min_n, max_n + 1, 3))
    if kinds is None:
        kinds = tuple(KINDS[int(i)] for i in rng.integers(0, len(KINDS), 3))
    mn, mx = verts.min(0), verts.max(0)
    ext = mx - mn
    lo = mn + rng.uniform(*margin, 3) * ext
    hi = mx - rng.uniform(*margin, 3) * ext
    return vp.Lattice(shape, interpolation=kinds, bounds=(lo, hi))


def spacing(lat):
    """(3,) grid spacing per axis; a one-point axis counts as the lattice size."""
    n = np.array(lat.shape, float)
    ext = lat.hi - lat.lo
    return np.where(n > 1, ext / np.maximum(n - 1, 1), lat.size)


def random_points(rng, lat, noise=0.4, global_kind=None):
    """Deformed control points: random displacements up to `noise` x spacing per axis, composed
    with a global squash, twist or bend of the rest grid about the lattice centre."""
    P0 = lat.rest_points
    c = lat.centre
    rel = P0 - c
    if global_kind is None:
        global_kind = ("none", "squash", "twist", "bend")[int(rng.integers(0, 4))]
    if global_kind == "squash":
        s = rng.uniform(0.6, 1.35)
        scale = np.array([1.0 / np.sqrt(s) * rng.uniform(0.9, 1.3), 1.0 / np.sqrt(s), s])
        rel = rel * scale[rng.permutation(3)]
    elif global_kind == "twist":
        ax = int(rng.integers(0, 3))
        a, b = [k for k in range(3) if k != ax]
        ang = rng.uniform(-0.8, 0.8) * (rel[:, ax] / (0.5 * lat.size))
        ca, sa = np.cos(ang), np.sin(ang)
        ra, rb = rel[:, a].copy(), rel[:, b].copy()
        rel = rel.copy()
        rel[:, a], rel[:, b] = ca * ra - sa * rb, sa * ra + ca * rb
    elif global_kind == "bend":
        ax = int(rng.integers(0, 3))
        other = (ax + 1 + int(rng.integers(0, 2))) % 3
        rel = rel.copy()
        rel[:, other] += rng.uniform(-0.3, 0.3) * rel[:, ax] ** 2 / lat.size
    d = rng.uniform(-noise, noise, P0.shape) * spacing(lat)
    return c + rel + d


def farthest_points(verts, candidates, k, rng):
    """k indices from `candidates` spread out by farthest-point sampling."""
    candidates = np.asarray(candidates)
    chosen = [int(candidates[rng.integers(0, len(candidates))])]
    d = np.linalg.norm(verts[candidates] - verts[chosen[0]], axis=1)
    while len(chosen) < k:
        j = int(candidates[int(np.argmax(d))])
        chosen.append(j)
        d = np.minimum(d, np.linalg.norm(verts[candidates] - verts[j], axis=1))
    return chosen


def inside(lat, verts, margin=0.05):
    """Mask of vertices strictly inside the lattice box (by `margin` of the extent) on multi-point axes."""
    ext = lat.hi - lat.lo
    ok = np.ones(len(verts), bool)
    for a, n in enumerate(lat.shape):
        if n > 1:
            ok &= (verts[:, a] > lat.lo[a] + margin * ext[a]) & (verts[:, a] < lat.hi[a] - margin * ext[a])
    return ok


# ----------------------------------------------------------------- independent reference maths

def face_volume(verts, tris, origin=None):
    """Signed volume by the divergence theorem, written independently of the core."""
    v = np.asarray(verts, float)
    if origin is not None:
        v = v - origin
    a, b, c = v[tris[:, 0]], v[tris[:, 1]], v[tris[:, 2]]
    return float(np.sum(a * np.cross(b, c)) / 6.0)


def volume_gradient(verts, tris, origin=None):
    """(V, 3) dV/dx_v = 1/6 sum over faces (v, m, n) in cyclic order of x_m x x_n."""
    v = np.asarray(verts, float)
    if origin is not None:
        v = v - origin
    g = np.zeros_like(v)
    for k in range(3):
        m, n = tris[:, (k + 1) % 3], tris[:, (k + 2) % 3]
        np.add.at(g, tris[:, k], np.cross(v[m], v[n]) / 6.0)
    return g


def many_small_islands(n=40, clusters=2, spread=0.1, seed=5):
    """(verts, tris, island (V,)) of `n` small closed bodies (alternately boxes and icospheres,
    radius 0.015-0.04) gathered in `clusters` tight groups inside [-1, 1]^3, so that
    several share each lattice cell, as teeth, claws and eyes do on a character."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-0.6, 0.6, (clusters, 3))
    parts = []
    for i in range(n):
        c = tuple(centres[i % clusters] + rng.uniform(-spread, spread, 3))
        r = float(rng.uniform(0.015, 0.04))
        parts.append(vp.icosphere(1, r, center=c) if i % 2 else vp.box(2, 1.5 * r, center=c))
    return union(parts)


def island_volumes(verts, tris, island):
    """(k,) float64 volume of each island about its own centre (the mean of its vertices)."""
    verts = np.asarray(verts, np.float64)
    face_island = island[tris[:, 0]]
    out = []
    for k in range(island.max() + 1):
        c = verts[island == k].mean(0)
        out.append(face_volume(verts, tris[face_island == k], origin=c))
    return np.array(out)


def small_bodies(n=44, seed=5):
    """(verts (V, 3), tris (F, 3)): n closed icospheres of 0.8% to 10% of a unit lattice's size
    scattered through [-0.4, 0.4]^3 (float64)."""
    rng = np.random.default_rng(seed)
    verts, tris, offset = [], [], 0
    for _ in range(n):
        v, f = vp.icosphere(3, rng.uniform(0.004, 0.05))
        verts.append(v + rng.uniform(-0.4, 0.4, 3))
        tris.append(f + offset)
        offset += len(v)
    return np.vstack(verts), np.vstack(tris)
