"""Parity of ``vpffd_addon``'s standard FFD with Blender's Lattice modifier.

Blender runs headless through bpy (see blender_ref.py). Error criterion everywhere:
max |core - blender| <= 1e-5 * size, size = the largest extent of the lattice's rest box in the
space compared in, a one-point axis counting as one unit wide (so the bound never collapses to 0).
"""

import itertools
import zlib

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
import bmesh  # noqa: E402  (only exists next to bpy)

from . import blender_ref as ref

pytestmark = pytest.mark.blender

REL_TOL = 1e-5
KINDS = ("LINEAR", "CARDINAL", "CATMULL_ROM", "BSPLINE")
MIXED = (("LINEAR", "CARDINAL", "BSPLINE"),
         ("BSPLINE", "CATMULL_ROM", "LINEAR"),
         ("CARDINAL", "BSPLINE", "CATMULL_ROM"))
SHAPES = ((1, 1, 1), (1, 3, 2), (2, 2, 2), (3, 4, 5), (4, 4, 4), (12, 2, 7), (5, 12, 3),
          (12, 12, 12))


@pytest.fixture(scope="module")
def vp():
    # Imported here so the harness checks below still run while the core is missing.
    import vpffd_addon
    return vpffd_addon


@pytest.fixture(autouse=True, scope="module")
def _clean_scene():
    ref.remove_all()
    yield
    ref.remove_all()


# ---------------------------------------------------------------- inputs

def _rest_grid(shape):
    """(N,3) Blender's rest grid for a fresh lattice: unit spacing centred on 0, u fastest."""
    axes = [np.arange(n, dtype=np.float64) - (n - 1) / 2.0 for n in shape]
    w, v, u = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return np.stack([u.ravel(), v.ravel(), w.ravel()], axis=1)


def _icosphere():
    """Unit icosphere: verts (642,3), tris (1280,3)."""
    bm = bmesh.new()
    bmesh.ops.create_icosphere(bm, subdivisions=4, radius=1.0)
    verts = np.array([v.co[:] for v in bm.verts], dtype=np.float64)
    tris = np.array([[v.index for v in f.verts] for f in bm.faces], dtype=np.int64)
    bm.free()
    return verts, tris


_ICO = _icosphere()


def _case(shape, seed, n_cloud=1500):
    """A mesh around the lattice and random control points, all in lattice local space.

    Returns verts (V,3): an ellipsoid reaching 30% beyond the rest box plus a loose point cloud
    filling a box 30% larger than it (so inside and outside vertices); tris (F,3) of the
    ellipsoid; points (N,3) rest grid moved by up to 40% of the (unit) spacing.
    """
    rng = np.random.default_rng(seed)
    rest = _rest_grid(shape)
    half = np.maximum((np.asarray(shape) - 1) / 2.0, 0.5)
    ico_verts, tris = _ICO
    cloud = rng.uniform(-1.3, 1.3, size=(n_cloud, 3)) * half
    verts = np.concatenate([ico_verts * 1.3 * half, cloud])
    points = rest + rng.uniform(-0.4, 0.4, size=rest.shape)
    return verts, tris, points


def _affine(loc, rot, scale):
    """4x4 matrix translate @ rotate (XYZ Euler, radians) @ scale."""
    cx, cy, cz = np.cos(rot)
    sx, sy, sz = np.sin(rot)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = rz @ ry @ rx @ np.diag(scale)
    m[:3, 3] = loc
    return m


def _apply(m, x):
    return x @ m[:3, :3].T + m[:3, 3]


def _size(rest, m=None):
    """Largest extent of the rest box (one-point axes one unit wide), mapped by m if given."""
    lo, hi = rest.min(0), rest.max(0)
    flat = hi - lo == 0
    lo, hi = np.where(flat, lo - 0.5, lo), np.where(flat, hi + 0.5, hi)
    corners = np.array(list(itertools.product(*zip(lo, hi))))
    if m is not None:
        corners = _apply(m, corners)
    return float((corners.max(0) - corners.min(0)).max())


def _influence(n, weights, strength, invert):
    """(V,) s = weight * strength as Blender applies it (float32 weights, invert -> 1 - weight)."""
    if weights is None:
        return None if strength == 1.0 else np.full(n, float(np.float32(strength)))
    w = weights.astype(np.float32).astype(np.float64)
    return (1.0 - w if invert else w) * float(np.float32(strength))


def _weights(rng, n):
    """(V,) random weights with exact 0s (unassigned in Blender) and 1s mixed in."""
    w = rng.random(n)
    w[rng.choice(n, n // 10, replace=False)] = 0.0
    w[rng.choice(n, n // 10, replace=False)] = 1.0
    return w


# ---------------------------------------------------------------- the comparison

def _frames(lattice_matrix, mesh_matrix):
    """(to_lat, to_mesh) 4x4: Blender deforms in lattice space, mesh local -> lattice local is
    inv(M_lat) @ M_mesh."""
    m_lat = np.eye(4) if lattice_matrix is None else np.asarray(lattice_matrix, float)
    m_mesh = np.eye(4) if mesh_matrix is None else np.asarray(mesh_matrix, float)
    to_lat = np.linalg.inv(m_lat) @ m_mesh
    return to_lat, np.linalg.inv(to_lat)


def _check_parity(vp, shape, interpolation, seed, lattice_matrix=None, mesh_matrix=None,
                  weights=None, strength=1.0, invert=False):
    to_lat, to_mesh = _frames(lattice_matrix, mesh_matrix)
    verts, tris, points = _case(shape, seed)
    # The case is built around the lattice; Blender gets it in mesh local space.
    out = ref.lattice_modifier_reference(
        _apply(to_mesh, verts), tris, shape, interpolation, points,
        lattice_matrix=lattice_matrix, mesh_matrix=mesh_matrix, weights=weights,
        strength=strength, invert=invert)
    rest = out["rest_points"]

    lo, hi = rest.min(0), rest.max(0)
    lat = vp.Lattice(shape, interpolation=tuple(interpolation),
                     bounds=(tuple(lo), tuple(hi)))
    np.testing.assert_allclose(lat.rest_points, rest, rtol=0, atol=1e-12 * _size(rest))

    influence = _influence(len(verts), weights, strength, invert)
    bound = vp.bind(lat, _apply(to_lat, out["verts_in"]), tris, influence=influence)
    got = _apply(to_mesh, np.asarray(bound.deform(out["deformed_points"]), dtype=np.float64))

    assert got.shape == out["verts"].shape
    size = _size(rest, to_mesh)
    # The displacement must be real, or the comparison says nothing.
    assert np.abs(out["verts"] - out["verts_in"]).max() > 1e-2 * size
    err = np.abs(got - out["verts"]).max()
    assert err <= REL_TOL * size, f"max error {err:.3g}, size {size:.3g}"


def _seed(*parts):
    """Fixed per-case seed (hash() of strings is salted per run, crc32 is not)."""
    return zlib.crc32(repr(parts).encode())


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: "x".join(map(str, s)))
@pytest.mark.parametrize("interpolation", [(k,) * 3 for k in KINDS] + list(MIXED),
                         ids=lambda t: "-".join(t))
def test_parity_shapes_and_interpolation(vp, shape, interpolation):
    _check_parity(vp, shape, interpolation, _seed(shape, interpolation))


TRANSFORMS = {
    "lattice_trs": (_affine((0.3, -1.2, 0.7), (0.4, -0.9, 1.3), (1.7, 0.6, 2.2)), None),
    "lattice_negative_scale": (_affine((2.0, 0.5, -1.0), (0.0, 0.3, 0.0), (-1.5, 0.8, 1.2)), None),
    "both_trs": (_affine((0.3, -1.2, 0.7), (0.4, -0.9, 1.3), (1.7, 0.6, 2.2)),
                 _affine((-0.5, 0.2, 1.0), (1.1, 0.2, -0.3), (0.8, 1.3, 1.1))),
    "mesh_only": (None, _affine((1.0, 0.0, -0.4), (-0.2, 0.7, 0.1), (0.5, 0.5, 0.9))),
}


@pytest.mark.parametrize("name", list(TRANSFORMS))
@pytest.mark.parametrize("shape,interpolation", [((3, 4, 5), ("BSPLINE",) * 3),
                                                 ((5, 12, 3), MIXED[2])],
                         ids=["3x4x5-bspline", "5x12x3-mixed"])
def test_parity_object_transforms(vp, name, shape, interpolation):
    m_lat, m_mesh = TRANSFORMS[name]
    _check_parity(vp, shape, interpolation, _seed(name, shape), lattice_matrix=m_lat,
                  mesh_matrix=m_mesh)


@pytest.mark.parametrize("invert", [False, True], ids=["direct", "inverted"])
@pytest.mark.parametrize("shape,interpolation", [((1, 3, 2), MIXED[0]),
                                                 ((4, 4, 4), ("CARDINAL",) * 3),
                                                 ((12, 2, 7), MIXED[1])],
                         ids=["1x3x2-mixed", "4x4x4-cardinal", "12x2x7-mixed"])
def test_parity_vertex_group(vp, shape, interpolation, invert):
    seed = _seed(shape, invert)
    weights = _weights(np.random.default_rng(seed), len(_case(shape, seed)[0]))
    _check_parity(vp, shape, interpolation, seed, weights=weights, strength=0.7, invert=invert)


def test_parity_strength_without_group(vp):
    _check_parity(vp, (4, 4, 4), ("BSPLINE",) * 3, seed=17, strength=0.7)


def test_parity_everything_at_once(vp):
    m_lat, m_mesh = TRANSFORMS["both_trs"]
    weights = _weights(np.random.default_rng(19), len(_case((12, 2, 7), 23)[0]))
    _check_parity(vp, (12, 2, 7), MIXED[2], seed=23, lattice_matrix=m_lat, mesh_matrix=m_mesh,
                  weights=weights, strength=0.7, invert=True)


# ---------------------------------------------------------------- checks of the harness itself
# A tiny independent NumPy version of the modifier, only to show the harness drives Blender the
# way the facts in blender_ref.py say. The core is never compared with it.

def _taps(t, kind):
    """(V,4) weights of the taps i-1..i+2 at fraction t (V,)."""
    t2, t3 = t * t, t * t * t
    if kind == "LINEAR":
        z = np.zeros_like(t)
        return np.stack([z, 1 - t, t, z], -1)
    if kind == "BSPLINE":
        return np.stack([(1 - t) ** 3, 3 * t3 - 6 * t2 + 4, -3 * t3 + 3 * t2 + 3 * t + 1, t3],
                        -1) / 6
    fc = 0.71 if kind == "CARDINAL" else 0.5
    return np.stack([-fc * t3 + 2 * fc * t2 - fc * t, (2 - fc) * t3 + (fc - 3) * t2 + 1,
                     (fc - 2) * t3 + (3 - 2 * fc) * t2 + fc * t, fc * t3 - fc * t2], -1)


def _numpy_modifier(x, shape, interpolation, rest, points, s):
    """x (V,3) lattice local, rest/points (N,3), s (V,) -> (V,3) deformed."""
    idx, wts = [], []
    for a, (n, kind) in enumerate(zip(shape, interpolation)):
        if n == 1:
            idx.append(np.zeros((len(x), 4), np.int64))
            wts.append(np.tile([0.0, 1.0, 0.0, 0.0], (len(x), 1)))
            continue
        lo, hi = rest[:, a].min(), rest[:, a].max()
        u = (x[:, a] - lo) / ((hi - lo) / (n - 1))
        i = np.floor(u)
        idx.append(np.clip(i.astype(np.int64)[:, None] + np.arange(-1, 3), 0, n - 1))
        wts.append(_taps(u - i, kind))
    nu, nv, _ = shape
    flat = (idx[0][:, None, None, :] + nu * (idx[1][:, None, :, None]
                                             + nv * idx[2][:, :, None, None]))
    d = (points - rest)[flat]  # (V,4w,4v,4u,3)
    disp = np.einsum("vk,vj,vi,vkjic->vc", wts[2], wts[1], wts[0], d)
    return x + (1.0 if s is None else s[:, None]) * disp


@pytest.mark.parametrize("shape", [(1, 1, 1), (4, 5, 6), (1, 3, 2), (12, 12, 12), (2, 2, 2)],
                         ids=lambda s: "x".join(map(str, s)))
def test_harness_rest_grid_and_identity(shape):
    verts, tris, _ = _case(shape, 1, n_cloud=200)
    out = ref.lattice_modifier_reference(verts, tris, shape, "BSPLINE")
    # Unit spacing centred on 0, u fastest; a one-point axis sits at 0.
    np.testing.assert_array_equal(out["rest_points"], _rest_grid(shape))
    np.testing.assert_array_equal(out["deformed_points"], out["rest_points"])
    np.testing.assert_array_equal(out["verts_in"], verts.astype(np.float32))
    # Undeformed lattice: every displacement is exactly 0.
    np.testing.assert_array_equal(out["verts"], out["verts_in"])
    assert out["execution_time"] >= 0.0


@pytest.mark.parametrize("shape,interpolation,weighting,transform", [
    ((4, 5, 6), ("BSPLINE",) * 3, None, None),
    ((1, 3, 2), MIXED[0], "direct", None),
    ((12, 12, 12), MIXED[1], "inverted", None),
    ((2, 2, 2), ("CATMULL_ROM",) * 3, "inverted", "both_trs"),
    ((5, 12, 3), ("LINEAR",) * 3, "direct", "lattice_negative_scale"),
], ids=["bspline", "weights", "inverted", "catmull-transformed", "linear-negative-scale"])
def test_harness_matches_formula(shape, interpolation, weighting, transform):
    verts, tris, points = _case(shape, 3)
    m_lat, m_mesh = TRANSFORMS[transform] if transform else (None, None)
    to_lat, to_mesh = _frames(m_lat, m_mesh)
    weights = None if weighting is None else _weights(np.random.default_rng(5), len(verts))
    strength = 1.0 if weighting is None else 0.7
    out = ref.lattice_modifier_reference(
        _apply(to_mesh, verts), tris, shape, interpolation, points, lattice_matrix=m_lat,
        mesh_matrix=m_mesh, weights=weights, strength=strength, invert=weighting == "inverted")
    np.testing.assert_array_equal(out["deformed_points"], points.astype(np.float32))
    s = _influence(len(verts), weights, strength, weighting == "inverted")
    want = _apply(to_mesh, _numpy_modifier(_apply(to_lat, out["verts_in"]), shape, interpolation,
                                           out["rest_points"], out["deformed_points"], s))
    size = _size(out["rest_points"], to_mesh)
    assert np.abs(out["verts"] - out["verts_in"]).max() > 1e-2 * size
    assert np.abs(want - out["verts"]).max() <= REL_TOL * size


def test_harness_does_not_leak():
    verts, tris, points = _case((2, 2, 2), 0, n_cloud=10)
    for _ in range(3):
        ref.lattice_modifier_reference(verts, tris, (2, 2, 2), "LINEAR", points)
    assert (len(bpy.data.objects), len(bpy.data.meshes), len(bpy.data.lattices)) == (2, 1, 1)


def test_harness_zero_weight_and_unassigned_vertices():
    # The harness leaves weight-0 vertices unassigned; Blender treats an explicit 0 the same.
    verts, tris, points = _case((3, 3, 3), 29, n_cloud=300)
    out = ref.lattice_modifier_reference(verts, tris, (3, 3, 3), "BSPLINE", points,
                                         weights=np.ones(len(verts)), strength=0.7)
    ob = bpy.data.objects[ref._PREFIX + "mesh"]
    group = ob.vertex_groups[0]
    group.add(range(0, 100), 0.0, "REPLACE")
    group.remove(range(100, 200))
    moved = {}
    for invert in (False, True):
        ob.modifiers[0].invert_vertex_group = invert
        depsgraph = bpy.context.evaluated_depsgraph_get()
        depsgraph.update()
        me = ob.evaluated_get(depsgraph).data
        co = np.empty(3 * len(me.vertices), np.float32)
        me.vertices.foreach_get("co", co)
        moved[invert] = np.abs(co.reshape(-1, 3) - out["verts_in"]).max(1)
    assert moved[False][:200].max() == 0.0 and moved[False][200:].min() > 0.0
    assert moved[True][200:].max() == 0.0
    # Inverted, assigned-0 and unassigned vertices both get s = strength: same as the full run.
    np.testing.assert_allclose(moved[True][:200],
                               np.abs(out["verts"] - out["verts_in"]).max(1)[:200], atol=1e-6)
