"""Input validation, degenerate cases, open meshes and hostile-but-finite input of the VP-FFD core.

Bad input must raise ValueError whose message names the problem; hostile input that is still
valid must give finite results (or a ValueError that says why), never NaN.
"""
import numpy as np
import pytest

import vpffd_addon as vp

from . import _meshes as M

pytestmark = pytest.mark.core


@pytest.fixture(scope="module")
def sphere():
    return vp.icosphere(2, 0.4)


@pytest.fixture(scope="module")
def lat():
    return vp.Lattice((4, 3, 5), ("BSPLINE", "LINEAR", "BEZIER"), bounds=((-0.5,) * 3, (0.5,) * 3))


@pytest.fixture(scope="module")
def bound(lat, sphere):
    return vp.bind(lat, *sphere)


def _moved(lat, seed=0, amount=0.08):
    rng = np.random.default_rng(seed)
    return lat.rest_points + rng.uniform(-amount, amount, (lat.n_points, 3))


# ---------------------------------------------------------------- Lattice

@pytest.mark.parametrize("shape,msg", [((0, 2, 2), "resolution"), ((2, -1, 2), "resolution"),
                                       ((2, 2, 2.5), "resolution"), ((2, 2), "3 entries"),
                                       ((2, 2, 2, 2), "3 entries"), ((), "3 entries")])
def test_bad_lattice_shape(shape, msg):
    with pytest.raises(ValueError, match=msg):
        vp.Lattice(shape)


@pytest.mark.parametrize("interp", ["CUBIC", ("BSPLINE", "LINEAR", "NURBS"), ("BSPLINE", "LINEAR")])
def test_bad_interpolation(interp):
    with pytest.raises(ValueError, match="interpolation"):
        vp.Lattice((3, 3, 3), interp)


def test_interpolation_names_are_accepted_in_blender_spelling():
    lat = vp.Lattice((3, 3, 3), ("KEY_BSPLINE", "key_linear", "bezier"))
    assert lat.interpolation == ("BSPLINE", "LINEAR", "BEZIER")


@pytest.mark.parametrize("bounds", [((0, 0, 0), (1, 0, 1)), ((0, 0, 0), (1, 1, -1)),
                                    ((0, 2, 0), (1, 1, 1))])
def test_bounds_need_extent_on_multi_point_axes(bounds):
    with pytest.raises(ValueError, match="bounds"):
        vp.Lattice((2, 2, 2), bounds=bounds)


def test_bounds_may_be_flat_on_one_point_axes():
    lat = vp.Lattice((3, 1, 3), bounds=((0, 5, 0), (1, 5, 1)))
    assert np.allclose(lat.rest_points[:, 1], 5.0)


def test_non_finite_bounds():
    with pytest.raises(ValueError, match="finite"):
        vp.Lattice((2, 2, 2), bounds=((0, 0, 0), (1, np.inf, 1)))


# ---------------------------------------------------------------- bind

@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_verts(lat, sphere, bad):
    v, f = sphere
    v = v.copy()
    v[7, 1] = bad
    with pytest.raises(ValueError, match="non-finite"):
        vp.bind(lat, v, f)


def test_verts_wrong_shape(lat, sphere):
    v, f = sphere
    with pytest.raises(ValueError, match="shape"):
        vp.bind(lat, v[:, :2], f)


def test_non_finite_influence(lat, sphere):
    v, f = sphere
    s = np.ones(len(v))
    s[3] = np.nan
    with pytest.raises(ValueError, match="influence"):
        vp.bind(lat, v, f, influence=s)


def test_influence_wrong_shape(lat, sphere):
    v, f = sphere
    with pytest.raises(ValueError, match="influence"):
        vp.bind(lat, v, f, influence=np.ones(len(v) - 1))


@pytest.mark.parametrize("index", [-1, 10 ** 6])
def test_tris_out_of_range(lat, sphere, index):
    v, f = sphere
    f = f.copy()
    f[5, 2] = index
    with pytest.raises(ValueError, match="out of range"):
        vp.bind(lat, v, f)
    with pytest.raises(ValueError, match="out of range"):
        vp.signed_volume(v, f)


@pytest.mark.parametrize("shape", [(10, 4), (10,), (2, 3, 3)])
def test_tris_wrong_shape(lat, sphere, shape):
    v, _ = sphere
    with pytest.raises(ValueError, match=r"tris must have shape \(F, 3\)"):
        vp.bind(lat, v, np.zeros(shape, np.int64))


def test_float_tris(lat, sphere):
    v, f = sphere
    # Whole numbers stored as floats are fine ...
    a = vp.bind(lat, v, f.astype(np.float64))
    assert a.rest_volume == pytest.approx(vp.signed_volume(v, f), rel=1e-14)
    # ... fractions and non-finite floats are not.
    g = f.astype(np.float64)
    g[0, 0] += 0.5
    with pytest.raises(ValueError, match="integer"):
        vp.bind(lat, v, g)
    g = f.astype(np.float64)
    g[0, 0] = np.nan
    with pytest.raises(ValueError, match="integer"):
        vp.bind(lat, v, g)


def test_empty_tris(lat, sphere):
    v, _ = sphere
    with pytest.raises(ValueError, match="empty"):
        vp.bind(lat, v, np.zeros((0, 3), np.int64))


def test_bind_needs_a_lattice(sphere):
    with pytest.raises(ValueError, match="Lattice"):
        vp.bind("lattice", *sphere)


# ---------------------------------------------------------------- deform / solve inputs

def test_non_finite_points(bound, lat):
    P = _moved(lat)
    P[2, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        bound.deform(P)
    with pytest.raises(ValueError, match="non-finite"):
        bound.solve(P)
    with pytest.raises(ValueError, match="non-finite"):
        vp.jacobian_det(bound, P)


def test_points_wrong_shape(bound, lat):
    with pytest.raises(ValueError, match="points must have shape"):
        bound.solve(lat.rest_points[:-1])


@pytest.mark.parametrize("target", [(np.nan, 0, 0), (0, np.inf, 0)])
def test_non_finite_pin_target(bound, lat, target):
    with pytest.raises(ValueError, match="pin targets must be finite"):
        bound.solve(_moved(lat), pins=[(0, target)])


@pytest.mark.parametrize("index", [-1, 642, 10 ** 9])
def test_pin_out_of_range(bound, lat, index):
    with pytest.raises(ValueError, match="outside"):
        bound.solve(_moved(lat), pins=[(index, (0, 0, 0))])


def test_pin_on_uninfluenced_vertex(lat, sphere):
    v, f = sphere
    s = np.ones(len(v))
    s[10] = 0.0
    b = vp.bind(lat, v, f, influence=s)
    with pytest.raises(ValueError, match="influence"):
        b.solve(_moved(lat), pins=[(3, v[3]), (10, v[10] + 0.01)])


def test_malformed_pin(bound, lat):
    with pytest.raises(ValueError, match="pins"):
        bound.solve(_moved(lat), pins=[(0, (1.0, 2.0))])


@pytest.mark.parametrize("mob,msg", [(lambda N: np.full(N, 1.5), r"\[0, 1\]"),
                                     (lambda N: -np.ones(N), r"\[0, 1\]"),
                                     (lambda N: np.full(N, np.nan), r"\[0, 1\]"),
                                     (lambda N: np.ones(N - 1), "shape"),
                                     (lambda N: np.ones((N, 1)), "shape")])
def test_bad_mobility(bound, lat, mob, msg):
    with pytest.raises(ValueError, match="mobility") as info:
        bound.solve(_moved(lat), mobility=mob(lat.n_points))
    assert info.match(msg)


@pytest.mark.parametrize("axes", ["XX", "Q", "XYZX", "W", 3])
def test_bad_axes(bound, lat, axes):
    with pytest.raises(ValueError, match="axes"):
        bound.solve(_moved(lat), axes=axes)


def test_lower_case_axes_are_fine(bound, lat):
    P = _moved(lat)
    a = bound.solve(P, axes="xz")
    b = bound.solve(P, axes="XZ")
    assert np.array_equal(a.points, b.points)


def test_no_directions(bound, lat):
    with pytest.raises(ValueError, match="direction"):
        bound.solve(_moved(lat), axes="")


@pytest.mark.parametrize("dirs,msg", [([[1, 0, 0], [0, 0, 0]], "zero"), ([0, 0, 0], "zero"),
                                      ([[1, 0, 0], [0, np.nan, 1]], "finite"),
                                      ([[1, 0], [0, 1]], "shape")])
def test_bad_directions(bound, lat, dirs, msg):
    with pytest.raises(ValueError, match=msg):
        bound.solve(_moved(lat), directions=dirs)


def test_directions_are_normalised(bound, lat):
    P = _moved(lat)
    a = bound.solve(P, directions=[[3.0, 0, 0], [0, 0, 0.5]])
    np.testing.assert_allclose(a.directions, [[1, 0, 0], [0, 0, 1]])
    b = bound.solve(P, axes="XZ")
    np.testing.assert_allclose(a.points, b.points, atol=1e-14)


@pytest.mark.parametrize("scale", [-0.5, np.nan, np.inf])
def test_bad_volume_scale(bound, lat, scale):
    with pytest.raises(ValueError, match="volume_scale"):
        bound.solve(_moved(lat), volume_scale=scale)


# ---------------------------------------------------------------- the volume cannot change

def test_all_immobile_with_volume_change(bound, lat):
    P = lat.rest_points * 1.2   # scales the sphere: its volume changes
    with pytest.raises(ValueError, match="volume cannot change"):
        bound.solve(P, mobility=np.zeros(lat.n_points))


def test_no_influence_with_new_target(lat, sphere):
    v, f = sphere
    b = vp.bind(lat, v, f, influence=np.zeros(len(v)))
    with pytest.raises(ValueError, match="volume cannot change"):
        b.solve(_moved(lat), volume_scale=1.3)
    # ...while the unchanged target is simply met: nothing moves.
    sol = b.solve(_moved(lat))
    np.testing.assert_array_equal(sol.verts, v)


def test_one_point_lattice_translates_without_error(sphere):
    v, f = sphere
    lat = vp.Lattice((1, 1, 1), bounds=((-1, -1, -1), (1, 1, 1)))
    b = vp.bind(lat, v, f)
    shift = np.array([[0.3, -0.2, 0.7]])
    sol = b.solve(lat.rest_points + shift)
    assert sol.warnings == ()
    np.testing.assert_allclose(sol.verts, v + shift, atol=1e-14)
    assert sol.volume == pytest.approx(b.rest_volume, rel=1e-12)
    with pytest.raises(ValueError, match="volume cannot change"):
        b.solve(lat.rest_points + shift, volume_scale=0.8)


def test_degenerate_directions_are_skipped_and_others_take_the_share():
    """On a (1, 1, 2) trilinear lattice, corrections along X or Y are shears x += a + b z: they
    cannot change the volume. All of it must come from Z, wherever Z is in the order."""
    v, f = vp.icosphere(2, 0.4)
    lat = vp.Lattice((1, 1, 2), "LINEAR", bounds=((-0.5,) * 3, (0.5,) * 3))
    b = vp.bind(lat, v, f)
    P = lat.rest_points + [[0.05, 0.1, -0.1], [-0.1, 0.02, 0.05]]
    only_z = b.solve(P, axes="Z", volume_scale=1.2)
    assert only_z.volume == pytest.approx(1.2 * b.rest_volume, rel=1e-9)
    for axes in ("XYZ", "ZXY", "YZX"):
        sol = b.solve(P, axes=axes, volume_scale=1.2)
        assert sol.warnings == ()
        assert sol.volume == pytest.approx(1.2 * b.rest_volume, rel=1e-9)
        assert vp.signed_volume(sol.verts, f) == pytest.approx(1.2 * b.rest_volume, rel=1e-9)
        # X and Y moved nothing; Z's gradient does not depend on z, so one step or two is the same.
        np.testing.assert_allclose(sol.points, only_z.points, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="volume cannot change"):
        b.solve(P, axes="XY", volume_scale=1.2)


# ---------------------------------------------------------------- open and closed meshes

def _open_box():
    v, f = vp.box(2, 1.0)
    top = np.abs(v[f].mean(1)[:, 2] - 0.5) < 1e-9
    return v, f[~top]


def test_closed_box_is_closed():
    v, f = vp.box(3, 1.0)
    b = vp.bind(vp.Lattice((3, 3, 3)), v, f)
    assert b.is_closed
    assert b.rest_volume == pytest.approx(1.0, rel=1e-12)
    assert vp.bind(vp.Lattice((3, 3, 3)), *vp.icosphere(1)).is_closed


def test_open_box_volume_is_measured_about_the_lattice_centre():
    v, f = _open_box()
    lat = vp.Lattice((3, 3, 3), bounds=((-0.2, -0.4, -0.3), (1.0, 0.8, 1.5)))
    b = vp.bind(lat, v, f)
    assert not b.is_closed
    about_centre = vp.signed_volume(v, f, origin=lat.centre)
    assert abs(about_centre - vp.signed_volume(v, f)) > 0.05   # the origin matters here
    assert b.rest_volume == pytest.approx(about_centre, rel=1e-12)
    assert b.rest_volume == pytest.approx(M.face_volume(v, f, origin=lat.centre), rel=1e-12)
    P = _moved(lat, amount=0.1)
    sol = b.solve(P, volume_scale=1.1)
    assert sol.plain_volume == pytest.approx(vp.signed_volume(b.deform(P), f, origin=lat.centre), rel=1e-9)
    assert sol.volume == pytest.approx(1.1 * about_centre, rel=1e-9)
    assert vp.signed_volume(sol.verts, f, origin=lat.centre) == pytest.approx(1.1 * about_centre, rel=1e-9)


def test_inconsistently_oriented_mesh_is_not_closed():
    v, f = vp.box(2, 1.0)
    f = f.copy()
    f[0] = f[0, ::-1]
    assert not vp.bind(vp.Lattice((2, 2, 2)), v, f).is_closed


# ---------------------------------------------------------------- hostile but finite input

def test_huge_offsets_with_the_lattice_around_the_mesh():
    v, f = vp.icosphere(2, 0.4)
    off = np.array([1e6, -2e6, 3e6])
    lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=(off - 0.5, off + 0.5))
    b = vp.bind(lat, v + off, f)
    P = _moved(lat, amount=0.1)
    sol = b.solve(P, volume_scale=1.2)
    assert np.isfinite(sol.verts).all() and np.isfinite(sol.points).all()
    assert sol.warnings == ()
    target = 1.2 * vp.signed_volume(v, f)
    assert sol.volume == pytest.approx(target, rel=1e-9)
    assert vp.signed_volume(sol.verts, f, origin=off) == pytest.approx(target, rel=1e-6)


@pytest.mark.parametrize("distance", [1e2, 1e4, 1e6])
def test_mesh_far_outside_the_lattice_only_translates(distance):
    """A closed mesh far outside the lattice moves rigidly with the clamped edge of the lattice,
    so its volume is unchanged: with volume_scale 1 there is nothing to correct and no error."""
    v, f = vp.icosphere(2, 0.4)
    off = distance * np.array([1.0, -2.0, 3.0])
    lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    b = vp.bind(lat, v + off, f)
    P = lat.rest_points + np.array([0.01, 0.02, -0.03])
    sol = b.solve(P)
    assert np.isfinite(sol.verts).all()
    np.testing.assert_allclose(sol.verts, v + off + [0.01, 0.02, -0.03], rtol=0, atol=1e-9 * distance)


def test_duplicated_vertices_and_zero_area_faces():
    v, f = vp.icosphere(2, 0.4)
    V = len(v)
    v2 = np.concatenate([v, v[:20], [[0.1, 0.1, 0.1]] * 3])      # unused duplicates, a point thrice
    degenerate = np.array([[0, 0, 1], [2, 2, 2], [V + 20, V + 21, V + 22], [3, V + 3, 4]])
    f2 = np.concatenate([f, degenerate])
    lat = vp.Lattice((3, 3, 3), "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    b = vp.bind(lat, v2, f2)
    P = _moved(lat, amount=0.1)
    for kw in ({}, {"islands": True}, {"pins": [(5, v[5] + 0.01)]}):
        sol = b.solve(P, volume_scale=0.9, **kw)
        assert np.isfinite(sol.verts).all() and np.isfinite(sol.points).all()
        assert np.isfinite(sol.volume)
    sol = b.solve(P, volume_scale=0.9)
    assert vp.signed_volume(sol.verts[:V], f) == pytest.approx(0.9 * vp.signed_volume(v, f), rel=1e-6)


def test_all_vertices_on_one_point_and_flat_meshes():
    lat = vp.Lattice((3, 3, 3), "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    P = _moved(lat, amount=0.1)
    # Every vertex at the same point: zero volume, zero gradient.
    v = np.zeros((4, 3)) + 0.1
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    b = vp.bind(lat, v, f)
    sol = b.solve(P)
    assert np.isfinite(sol.verts).all() and np.isfinite(sol.volume)
    sol = b.solve(P, volume_scale=2.0)       # 2 x 0 is still 0: nothing to do
    assert np.isfinite(sol.verts).all() and abs(sol.volume) < 1e-12
    # A flat (zero volume) closed tetrahedron in the plane z = 0.
    v = np.array([[0, 0, 0], [0.3, 0, 0], [0, 0.3, 0], [0.1, 0.1, 0]], float)
    b = vp.bind(lat, v, f)
    for scale in (1.0, 0.0, 2.0):
        try:
            sol = b.solve(P, volume_scale=scale)
        except ValueError as exc:
            assert "volume" in str(exc)
            continue
        assert np.isfinite(sol.verts).all() and np.isfinite(sol.points).all()


def test_huge_displacements_stay_finite(sphere):
    v, f = sphere
    lat = vp.Lattice((3, 3, 3), "CARDINAL", bounds=((-0.5,) * 3, (0.5,) * 3))
    b = vp.bind(lat, v, f)
    rng = np.random.default_rng(4)
    P = lat.rest_points + rng.uniform(-1e5, 1e5, (lat.n_points, 3))
    try:
        sol = b.solve(P)
    except ValueError as exc:
        assert "volume" in str(exc) or "overflow" in str(exc)
        return
    assert np.isfinite(sol.verts).all() and np.isfinite(sol.points).all()
    assert sol.volume == pytest.approx(b.rest_volume, rel=1e-6) or sol.warnings


def test_solution_never_nan_with_conflicting_pins(bound, lat, sphere):
    v, _ = sphere
    P = _moved(lat)
    sol = bound.solve(P, pins=[(0, v[0] + 0.1), (0, v[0] - 0.1)])
    assert np.isfinite(sol.verts).all() and np.isfinite(sol.points).all()
    assert any("pin" in w for w in sol.warnings)


def test_a_mirroring_lattice_keeps_the_volumes_size_and_the_mirror():
    """Points mirrored in Z: Blender's modifier mirrors the mesh (its signed volume turns). The
    correction keeps |volume| = scale x |rest| with the mirrored sign, close to the plain mirrored
    shape, instead of turning the mesh inside out to reach the rest volume's sign."""
    v, f = vp.icosphere(3, 0.6)
    lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    P = lat.rest_points.copy()
    P[:, 2] *= -0.6                              # mirrored and squashed
    b = vp.bind(lat, v, f)
    sol = b.solve(P, axes="XY", volume_scale=1.2)
    plain = b.deform(P)
    assert vp.signed_volume(plain, f) < 0
    assert abs(vp.signed_volume(sol.verts, f) / (-1.2 * b.rest_volume) - 1) <= 1e-9
    assert any("mirrors space" in w for w in sol.warnings)
    # Corrected along X and Y only: z stays the plain mirrored z, and the shape only widens.
    np.testing.assert_allclose(sol.verts[:, 2], plain[:, 2], atol=1e-12)
    away = np.abs(plain[:, :2]) > 0.05
    assert (np.sign(sol.verts[:, :2]) == np.sign(plain[:, :2]))[away].all()


def test_a_correction_beyond_the_lattice_diagonal_is_refused():
    """A lattice flattened to a sheet: restoring the volume along X and Y would fling the points
    far away. The plain deformation comes back, with a warning that says why."""
    v, f = vp.icosphere(3, 0.6)
    lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    P = lat.rest_points.copy()
    P[:, 2] *= 1e-3
    b = vp.bind(lat, v, f)
    sol = b.solve(P, axes="XY")
    assert any("correction was refused" in w for w in sol.warnings)
    np.testing.assert_array_equal(sol.points, P)
    np.testing.assert_allclose(sol.verts, b.deform(P), atol=1e-12)
    assert sol.volume == pytest.approx(sol.plain_volume, rel=1e-9)


def _squashed_3x3x3(rng):
    """A 3x3x3 B-spline lattice over [-1, 1]^3, squashed to half its height and jittered."""
    lat = vp.Lattice((3, 3, 3), "BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    P = lat.rest_points.copy()
    P[:, 2] *= 0.5
    P += rng.normal(0, 0.05, P.shape)
    return lat, P


def test_islands_the_lattice_cannot_reach_are_named_with_their_miss():
    """Thirty small spheres in a 3x3x3 lattice of which only the centre point may move (Mobility
    Group): 3 coordinates cannot give 30 islands each its own volume. The warning names the
    islands that miss and by how much."""
    rng = np.random.default_rng(3)
    v, f, _ = M.union([vp.icosphere(1, 0.08, center=tuple(c)) for c in rng.uniform(-0.7, 0.7, (30, 3))])
    lat, P = _squashed_3x3x3(rng)
    mobility = np.zeros(lat.n_points)
    mobility[13] = 1.0
    sol = vp.bind(lat, v, f).solve(P, axes="XYZ", islands=True, mobility=mobility)
    miss = np.abs(sol.island_volumes / sol.island_target_volumes - 1)
    worst = int(np.argmax(miss))
    assert miss[worst] > 1e-6
    (text,) = sol.warnings
    assert f"{worst} ({miss[worst]:.2g})" in text and "relative miss" in text


def test_concentric_shells_each_keep_their_volume():
    """Five concentric shells in a 3x3x3 lattice: nested islands whose volume rows are nearly
    parallel, yet independent. Solved on the constraint matrix itself (not its Gram matrix),
    every shell meets its target and nothing is reported."""
    rng = np.random.default_rng(3)
    shells = [vp.icosphere(3, r) for r in (0.6, 0.55, 0.3, 0.28, 0.1)]
    v, f, _ = M.union([(sv, sf[:, ::-1] if k % 2 else sf) for k, (sv, sf) in enumerate(shells)])
    lat, P = _squashed_3x3x3(rng)
    b = vp.bind(lat, v, f)
    sol = b.solve(P, axes="XYZ", islands=True)
    assert sol.warnings == ()
    face_island = b.topology.face_island
    for k in range(5):
        want = vp.signed_volume(v, f[face_island == k])
        got = vp.signed_volume(sol.verts, f[face_island == k])
        assert abs(got / want - 1) <= 1e-8, (k, got, want)

@pytest.mark.parametrize("shape", [(5, 5, 5), (8, 8, 8)])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_many_small_islands_sharing_cells_each_keep_their_volume(shape, dtype):
    """Forty small closed bodies in three tight groups (several per lattice cell), the lattice
    squashed to half its height: every island keeps its volume, measured independently about its
    own centre (1e-9 in float64, docs/design.md's 1e-5 in float32), with no warning and modest moves."""
    v, f, island = M.many_small_islands()
    lat = vp.Lattice(shape, "BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    P = lat.rest_points.copy()
    P[:, 2] *= 0.5
    sol = vp.bind(lat, v, f, dtype=dtype).solve(P, axes="XYZ", islands=True)
    assert sol.warnings == ()
    rest = M.island_volumes(v, f, island)
    now = M.island_volumes(sol.verts.astype(dtype), f, island)
    miss = np.abs(now / rest - 1)
    assert miss.max() <= (1e-9 if dtype == np.float64 else 1e-5), (int(np.argmax(miss)), miss.max())
    assert np.abs(sol.points - P).max() <= 0.25 * lat.size
