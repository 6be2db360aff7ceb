"""Cages of arbitrary topology against independent computations.

- Box cages: the embedding reproduces every point (W P0 = x) and translations; interior points
  converge to a tricubic uniform B-spline FFD of the same control points, written out here.
- An extruded disc: the region is flat at the ends and round along its length.
- The volume solve on random cages and deformations lands on the target, and a one-direction solve
  equals a dense KKT solve built from the probed matrix.
- Bad cages are refused with messages that name the problem.
"""
import numpy as np
import pytest

import vpffd_addon as vp
from vpffd_addon.cage import box_cage, extrude

from . import _meshes as M
from .test_core_reference import kkt_solve, probe_dense_B

pytestmark = pytest.mark.core


def cubic_bspline(s):
    """Uniform cubic B-spline basis centred at 0."""
    s = np.abs(s)
    return np.where(s < 1, (4 - 6 * s ** 2 + 3 * s ** 3) / 6, np.where(s < 2, (2 - s) ** 3 / 6, 0.0))


def disc_cage(k=8, layers=4, height=2.0):
    """A k-gon disc with a ring of quads around it, extruded: the cylinder of the paper's Figure 1."""
    ang = np.arange(k) * 2 * np.pi / k
    ring = [np.stack([r * np.cos(ang), r * np.sin(ang), 0 * ang], 1) for r in (0.5, 1.0)]
    polys = [list(range(k))] + [[i, (i + 1) % k, k + (i + 1) % k, k + i] for i in range(k)]
    return vp.Cage(*extrude(np.concatenate(ring), polys, (0, 0, height), layers))


def jittered_box_cage(rng, res, jitter=0.15):
    cage = box_cage(res)
    h = 2.0 / max(res)
    P = cage.rest_points + rng.uniform(-jitter, jitter, (cage.n_points, 3)) * h
    return vp.Cage(P, [list(c) for c in cage.cells])


# ---------------------------------------------------------------- the region of a box cage

@pytest.mark.parametrize("depth", [0, 1, 2, 3])
def test_box_cage_embeds_every_point_exactly(depth):
    rng = np.random.default_rng(depth)
    cage = box_cage((3, 2, 2))
    x = rng.uniform(-1, 1, (3000, 3))
    x[:8] = [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]   # corners too
    b = vp.bind(cage, x, np.array([[0, 1, 2]]), depth=depth)
    assert b.n_outside == 0
    P0 = cage.rest_points
    # deform(0) = x - W P0: the weights reproduce the point itself.
    assert np.abs(b.deform(np.zeros_like(P0))).max() <= 1e-9
    t = np.array([0.3, -0.7, 0.25])
    assert np.abs(b.deform(P0 + t) - (x + t)).max() <= 1e-12
    A = np.array([[1.1, 0.2, 0.0], [-0.1, 0.9, 0.3], [0.05, 0.0, 1.2]])
    assert np.abs(b.deform(P0 @ A.T) - x @ A.T).max() <= 1e-9   # linear maps too


def test_box_cage_converges_to_the_tricubic_bspline_ffd():
    n = 6
    cage = box_cage((n - 1,) * 3)
    h = 2.0 / (n - 1)
    rng = np.random.default_rng(7)
    # Points whose B-spline support and refinement stencils never reach the boundary rules.
    x = rng.uniform(-1 + 2 * h, 1 - 2 * h, (1500, 3))
    P = cage.rest_points + rng.normal(0, 0.1, (cage.n_points, 3))
    t = (x + 1) / h
    i = np.arange(n)
    Nu, Nv, Nw = (cubic_bspline(t[:, a, None] - i) for a in range(3))
    W = np.einsum("vk,vj,vi->vkji", Nw, Nv, Nu).reshape(len(x), -1)   # x fastest, as box_cage
    assert np.abs(W @ cage.rest_points - x).max() <= 1e-12
    reference = W @ P
    errors = []
    for depth in range(4):
        b = vp.bind(cage, x, np.array([[0, 1, 2]]), depth=depth)
        errors.append(float(np.abs(b.deform(P) - reference).max()))
    print("max distance to the tricubic B-spline FFD by depth:", ["%.3g" % e for e in errors])
    assert all(later < 0.5 * earlier for earlier, later in zip(errors, errors[1:]))
    assert errors[-1] < 2e-3


# ---------------------------------------------------------------- an extruded disc (Figure 5)

def test_extruded_disc_region_is_flat_at_the_ends_and_round_along_its_length():
    k = 8
    cage = disc_cage(k)
    r = cage.region(3)
    faces = r.boundary_faces()
    X = r.points
    flat = []
    for f in faces:
        z = X[list(f), 2]
        if np.ptp(z) < 1e-9 and (abs(z[0]) < 1e-9 or abs(z[0] - 2) < 1e-9):
            flat.append(f)
    cap_points = np.unique(np.concatenate([list(f) for f in flat]))
    # The caps are planes: every refined face of the cage's cap polygons lies in them (per cap, the
    # k-gon splits into k quads at the first level, each quad into 4 per level).
    assert len(flat) == 2 * (k * 4 ** 2 + k * 4 ** 3)
    assert np.abs(np.minimum(np.abs(X[cap_points, 2]), np.abs(X[cap_points, 2] - 2))).max() <= 1e-12
    assert X[:, 2].min() == 0.0 and X[:, 2].max() == 2.0
    side = np.unique(np.concatenate([list(f) for f in faces]))
    side = side[(X[side, 2] > 0.25) & (X[side, 2] < 1.75)]
    radius = np.hypot(X[side, 0], X[side, 1])
    polygon = 1 / np.cos(np.pi / k)        # the octagon's radius ratio, corner over edge middle
    assert radius.max() / radius.min() < 1 + 0.03 * (polygon - 1)


def test_points_outside_the_region_follow_its_boundary_or_stay():
    cage = box_cage((2, 2, 2))
    x = np.array([[1.5, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, -1.25, 0.3]])
    tris = np.array([[0, 1, 2]])
    P = cage.rest_points.copy()
    P[:, 0] *= 1.5              # stretch along x
    follow = vp.bind(cage, x, tris, depth=2)
    assert follow.n_outside == 2
    got = follow.deform(P)
    np.testing.assert_allclose(got[0], [2.0, 0.0, 0.0], atol=1e-12)     # boundary x=1 -> 1.5, +0.5
    np.testing.assert_allclose(got[2], [0.0, -1.25, 0.3], atol=1e-12)   # its boundary point did not move
    stay = vp.bind(cage, x, tris, depth=2, outside="STAY")
    np.testing.assert_allclose(stay.deform(P)[0], x[0], atol=0)
    np.testing.assert_allclose(stay.deform(P + 1.0)[[0, 2]], x[[0, 2]], atol=0)


# ---------------------------------------------------------------- exact volume

def cage_cases():
    rng = np.random.default_rng(11)
    yield "jittered box", jittered_box_cage(rng, (3, 2, 2)), 2
    yield "disc", disc_cage(6, layers=2), 2
    prism_pts = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [2, 2, 0]], float)
    yield "prisms", vp.Cage(*extrude(prism_pts, [[0, 1, 2], [1, 3, 2]], (0, 0, 2), 2)), 2
    P = box_cage((1, 1, 2)).rest_points
    yield "one column", box_cage((1, 1, 2)), 3


@pytest.mark.parametrize("case", list(range(4)))
@pytest.mark.parametrize("seed", range(3))
def test_volume_after_random_cage_deformations_is_exact(case, seed):
    name, cage, depth = list(cage_cases())[case]
    rng = np.random.default_rng(100 * case + seed)
    verts, tris = vp.icosphere(3)
    lo, hi = cage.region(1).points.min(0), cage.region(1).points.max(0)
    # A sphere well inside the cage's bounding box, centred on the region.
    centre = 0.5 * (lo + hi)
    verts = centre + 0.3 * (hi - lo).min() * verts
    for dtype, tol in ((np.float64, 1e-9), (np.float32, 1e-5)):
        b = vp.bind(cage, verts, tris, depth=depth, dtype=dtype)
        P = cage.rest_points + rng.normal(0, 0.12 * cage.size, (cage.n_points, 3))
        axes = ["XYZ", "XY", "Z", "YZX"][seed % 4]
        scale = rng.uniform(0.8, 1.25)
        sol = b.solve(P, axes=axes, volume_scale=scale)
        target = scale * b.rest_volume
        assert sol.warnings == ()
        measured = M.face_volume(sol.verts, tris)
        assert abs(measured - target) <= tol * abs(target), (name, dtype)
        assert abs(sol.volume - target) <= tol * abs(target)
        # The corrected points reproduce the returned vertices.
        np.testing.assert_allclose(b.deform(sol.points), sol.verts, atol=1e-5 if dtype == np.float32 else 1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_cage_solve_matches_the_dense_kkt_solve(seed):
    rng = np.random.default_rng(seed)
    cage = jittered_box_cage(rng, (2, 2, 1))
    verts, tris, _ = M.closed_mesh(rng, 1, max_subdivisions=1, max_resolution=2)
    verts = 0.5 * verts / np.abs(verts).max()
    b = vp.bind(cage, verts, tris, depth=2)
    SB = probe_dense_B(b)
    P = cage.rest_points + rng.normal(0, 0.1, (cage.n_points, 3))
    E = np.eye(3)
    mob = rng.uniform(0.2, 1.0, cage.n_points)
    sol = b.solve(P, axes="XYZ", volume_scale=1.1, mobility=mob)
    # The reference measures about the cage centre; volumes of closed meshes do not depend on it.
    exp_P, exp_X, targets = kkt_solve(cage, verts, tris, SB, P, E, 1.1, mobility=mob)
    np.testing.assert_allclose(sol.points, exp_P, atol=1e-9)
    np.testing.assert_allclose(sol.verts, exp_X, atol=1e-9)


def test_pins_and_islands_work_with_cages():
    cage = box_cage((2, 2, 2))
    v, f = vp.icosphere(2)
    verts = np.concatenate([0.35 * v + [-0.45, 0, 0], 0.35 * v + [0.45, 0, 0]])
    tris = np.concatenate([f, f + len(v)])
    b = vp.bind(cage, verts, tris, depth=2)
    rng = np.random.default_rng(3)
    P = cage.rest_points + rng.normal(0, 0.1, (cage.n_points, 3))
    target = verts[5] + [0.05, 0.0, -0.02]
    sol = b.solve(P, axes="XYZ", islands=True, pins=[(5, target)])
    assert sol.warnings == ()
    np.testing.assert_allclose(sol.verts[5], target, atol=1e-9)
    for k in range(2):
        part = tris[:len(f)] if k == 0 else tris[len(f):]
        assert abs(M.face_volume(sol.verts, part) - b.rest_island_volumes[k]) <= 1e-9 * abs(b.rest_island_volumes[k])


def test_cage_jacobian_matches_finite_differences():
    rng = np.random.default_rng(5)
    cage = disc_cage(5, layers=2)
    x = rng.uniform(-0.6, 0.6, (200, 3)) * [1, 1, 0] + [0, 0, 1]
    x[:, 2] += rng.uniform(-0.7, 0.7, 200)
    P = cage.rest_points + rng.normal(0, 0.05, (cage.n_points, 3))
    tris = np.array([[0, 1, 2]])
    det = vp.jacobian_det(vp.bind(cage, x, tris, depth=2), P)
    eps = 1e-6
    cols = []
    for a in range(3):
        d = np.zeros(3)
        d[a] = eps
        plus = vp.bind(cage, x + d, tris, depth=2).deform(P)
        minus = vp.bind(cage, x - d, tris, depth=2).deform(P)
        cols.append((plus - minus) / (2 * eps))
    fd = np.linalg.det(np.stack(cols, 2))
    # Points that straddle an element boundary under +-eps see two pieces; compare the rest.
    ok = np.abs(fd - det) <= 1e-4 * np.abs(det).max()
    assert ok.mean() > 0.95
    assert abs(vp.jacobian_det(vp.bind(cage, x, tris, depth=2), cage.rest_points) - 1).max() <= 1e-9


# ---------------------------------------------------------------- bad cages

HEX = [0, 1, 2, 3, 4, 5, 6, 7]
CUBE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
CUBE_FACES = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]


def two_cubes():
    P = np.concatenate([CUBE, CUBE[4:] + [0, 0, 1]])
    return P, [HEX, [4, 5, 6, 7, 8, 9, 10, 11]]


@pytest.mark.parametrize("points, cells, message", [
    (CUBE, [], "no cells"),
    (CUBE, [CUBE_FACES[:5]], "open"),
    (CUBE, [CUBE_FACES[:1] + [(4, 7, 6, 5)] + CUBE_FACES[2:]], "not consistently oriented"),
    (CUBE, [[4, 5, 6, 7, 0, 1, 2, 3]], "inverted"),
    (CUBE, [[0, 1, 2, 3, 4, 5, 7, 6]], "folds over itself"),
    (two_cubes()[0], [HEX, [8, 9, 10, 11, 4, 5, 6, 7]], "same orientation"),
    (np.concatenate([CUBE, CUBE + [0.3, 0.4, 0.45]]), [HEX, list(range(8, 16))], "overlap"),
    (np.concatenate([CUBE, [[5, 5, 5]]]), [HEX], "belong to no cell"),
    (CUBE, [[0, 1, 2]], "3 corners"),
    (CUBE, [[0, 1, 2, 3, 4, 5, 6, 9]], "outside"),
])
def test_bad_cages_are_refused_with_a_clear_message(points, cells, message):
    with pytest.raises(ValueError, match=message):
        vp.Cage(points, cells)


def test_a_face_in_three_cells_is_refused():
    P = np.concatenate([CUBE, [[0.5, 0.5, -1.0], [0.5, 0.5, -2.0]]])
    cells = [HEX, [0, 1, 2, 3, 8], [[0, 1, 2, 3], [0, 3, 9], [3, 2, 9], [2, 1, 9], [1, 0, 9]]]
    with pytest.raises(ValueError, match="at most two cells|overlap|same orientation"):
        vp.Cage(P, cells)


def test_bind_arguments_are_checked():
    cage = box_cage((1, 1, 1))
    v, f = vp.icosphere(1)
    with pytest.raises(ValueError, match="depth"):
        vp.bind(cage, 0.5 * v, f, depth=-1)
    with pytest.raises(ValueError, match="outside"):
        vp.bind(cage, 0.5 * v, f, outside="AWAY")
    with pytest.raises(ValueError, match="cages only"):
        vp.bind(vp.Lattice((2, 2, 2)), 0.4 * v, f, depth=2)
    with pytest.raises(ValueError, match="shape"):
        vp.bind(cage, 0.5 * v, f).deform(np.zeros((7, 3)))


# ---------------------------------------------------------------- the refinement against a reference

def _mixed_cage():
    """A hexahedron, a prism, a pyramid and a tetrahedron glued face to face, plus a hexagonal
    prism (a cell with two 6-sided faces)."""
    P = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1],
         [2, 0, 0], [2, 0, 1], [0.5, 0.5, 2.0]]
    cells = [[0, 1, 2, 3, 4, 5, 6, 7],
             [1, 8, 2, 5, 9, 6],                  # prism on the hexahedron's x = 1 face
             [4, 5, 6, 7, 10]]                    # pyramid on top
    ang = np.arange(6) * np.pi / 3
    ring = np.stack([3 + 0.6 * np.cos(ang), 3 + 0.6 * np.sin(ang), 0 * ang], 1)
    base = len(P)
    P = np.concatenate([np.array(P, float), ring, ring + [0, 0, 1]])
    bottom, top = list(range(base, base + 6)), list(range(base + 6, base + 12))
    faces = [tuple(reversed(bottom)), tuple(top)] + [(bottom[i], bottom[(i + 1) % 6], top[(i + 1) % 6], top[i])
                                                     for i in range(6)]
    return vp.Cage(P, cells + [faces])


@pytest.mark.parametrize("name", ["box", "jittered", "disc", "mixed"])
def test_vectorised_refinement_equals_the_reference_rules(name):
    from .cage_reference import reference_levels
    rng = np.random.default_rng(2)
    cage = {"box": lambda: box_cage((2, 3, 1)), "jittered": lambda: jittered_box_cage(rng, (2, 2, 2)),
            "disc": lambda: disc_cage(5, layers=2), "mixed": _mixed_cage}[name]()
    for depth in (1, 2):
        expected, n_cells = reference_levels(cage, depth)
        region = cage.region(depth)
        got = region.points
        assert region.complex.n_cells == n_cells and len(got) == len(expected)
        # Numbering differs; the point sets must agree.
        key = lambda a: a[np.lexsort(np.round(a, 9).T[::-1])]
        np.testing.assert_allclose(key(got), key(expected), atol=1e-12)
