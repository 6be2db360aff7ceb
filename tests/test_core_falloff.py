"""Outside the lattice (`vpffd_addon/falloff.py`) and the volume kept as it was at Bind
(`target_volumes`), in the core: the falloff keeps the deformation affine in the control points, so
the closed form keeps the volume exactly (float64, checked by an independent volume sum); its slope
is continuous across the lattice's faces (finite differences on both sides); nothing moves beyond
the falloff distance, nor outside the box with Inside Only; a target volume is met, per island too."""
import numpy as np
import pytest

import vpffd_addon as vp

pytestmark = pytest.mark.core


def _volume(verts, tris):
    """Enclosed volume by the divergence theorem, summed face by face in Python's own floats (an
    independent computation: no NumPy reduction, no code of the core)."""
    total = 0.0
    for a, b, c in tris.tolist():
        (ax, ay, az), (bx, by, bz), (cx, cy, cz) = verts[a].tolist(), verts[b].tolist(), verts[c].tolist()
        total += ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
    return total / 6.0


def _squash(lat, seed=1):
    rng = np.random.default_rng(seed)
    P = lat.rest_points.copy()
    P[:, 2] *= 0.6
    P[:, 0] += 0.15 * P[:, 2]
    return P + rng.normal(0, 0.01, P.shape)


def _half_outside(sub=3):
    """An icosphere half outside a 3x3x3 lattice (its centre on the lattice's +X face)."""
    v, f = vp.icosphere(sub, 0.45)
    return v + [0.5, 0.0, 0.0], f


def test_the_profile_is_one_at_the_box_zero_at_the_distance_and_flat_at_both():
    t = np.array([0.0, 1e-4, 0.5, 1 - 1e-4, 1.0, 2.0])
    w = vp.falloff.profile(t)
    assert w[0] == 1.0 and w[4] == 0.0 and w[5] == 0.0 and w[2] == 0.5
    assert abs(w[1] - 1.0) < 1e-7 and abs(w[3]) < 1e-7          # slopes 0 at both ends (O(t^2))


def test_distance_is_in_lattice_size_units_per_side():
    lat = vp.Lattice((3, 4, 2), bounds=((-1.0, 0.0, 0.0), (1.0, 4.0, 1.0)))   # sizes 2, 4, 1
    pts = np.array([[0.0, 2.0, 0.5], [2.0, 2.0, 0.5], [0.0, 6.0, 0.5], [0.0, 2.0, -0.5], [2.0, 6.0, 0.5]])
    np.testing.assert_allclose(vp.falloff.box_distance(lat, pts), [0.0, 0.5, 0.5, 0.5, np.sqrt(0.5)])


@pytest.mark.parametrize("kind", ["BSPLINE", "LINEAR", "CATMULL_ROM"])
def test_falloff_keeps_the_volume_exactly(kind):
    v, f = _half_outside()
    lat = vp.Lattice((3, 3, 3), kind)
    factor = vp.outside_factor(lat, v, "FALLOFF", 0.4)
    assert ((factor > 0) & (factor < 1)).sum() > 50 and (factor == 0).sum() > 20
    b = vp.bind(lat, v, f, influence=factor)
    sol = b.solve(_squash(lat), axes="XYZ")
    rest = _volume(v, f)
    assert abs(_volume(sol.verts, f) / rest - 1) <= 1e-12
    assert abs(sol.plain_volume / rest - 1) > 1e-3                  # there was something to correct


def test_the_displacement_has_a_continuous_slope_across_the_lattice_face():
    lat = vp.Lattice((4, 4, 4), "BSPLINE")
    P = _squash(lat, seed=4)
    for h in (1e-3, 1e-4):
        # Points along X crossing the +X face at 0.5, off the lattice's centre in Y and Z.
        x = 0.5 + h * np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
        pts = np.stack([x, np.full(5, 0.13), np.full(5, -0.21)], 1)
        tri = np.array([[0, 1, 2]])
        b = vp.bind(lat, pts, tri, influence=vp.outside_factor(lat, pts, "FALLOFF", 0.3))
        d = b.deform(P) - pts                                        # the displacement
        left, right = (d[2] - d[0]) / (2 * h), (d[4] - d[2]) / (2 * h)
        assert np.abs(left - right).max() <= 50 * h, (h, left, right)


def test_nothing_moves_beyond_the_falloff_distance_and_outside_the_box_with_inside_only():
    v, f = _half_outside()
    lat = vp.Lattice((3, 3, 3), "BSPLINE")
    P = _squash(lat)
    pipeline = vp.Pipeline()
    for mode, distance in (("FALLOFF", 0.2), ("INSIDE", 0.5)):
        inp = vp.FrameInputs(positions=v, tris=f, lattice=lat, points=P, matrix=np.eye(4),
                             outside=mode, falloff=distance, dtype=np.float64)
        out = pipeline.evaluate(inp)
        d = vp.falloff.box_distance(lat, v)
        far = d >= distance if mode == "FALLOFF" else d > vp.falloff.INSIDE_SLACK
        assert far.sum() > 20 and out.still == far.sum()
        offsets, output = out.float32_offsets()[:2]                 # what a frame writes
        assert not offsets[far].any() and np.array_equal(output[far], v[far])
        np.testing.assert_array_equal(out.positions[far], v[far])   # exactly in place
        assert np.abs(out.positions[~far] - v[~far]).max() > 1e-3
        np.testing.assert_array_equal(offsets, (out.positions - v).astype(np.float32))
        assert abs(_volume(out.positions, f) / _volume(v, f) - 1) <= 1e-12
        if mode == "FALLOFF":
            assert out.falloff == int(((d > 0) & (d < distance)).sum())


def test_inside_only_moves_inside_vertices_as_follow_does_uncorrected():
    v, f = _half_outside()
    lat = vp.Lattice((3, 3, 3), "BSPLINE")
    P = _squash(lat)
    runs = {mode: vp.Pipeline().evaluate(vp.FrameInputs(
        positions=v, tris=f, lattice=lat, points=P, matrix=np.eye(4), correct=False, outside=mode,
        dtype=np.float64)).positions for mode in ("FOLLOW", "INSIDE")}
    inside = vp.falloff.box_distance(lat, v) <= vp.falloff.INSIDE_SLACK
    np.testing.assert_allclose(runs["INSIDE"][inside], runs["FOLLOW"][inside], rtol=0, atol=1e-15)


def test_a_target_volume_is_met_in_the_objects_space_per_island_too():
    # Two balls, bound at their full size; the slot then receives them shrunk (as an Armature or a
    # shape key upstream would), the lattice somewhere else, scaled and turned.
    a, fa = vp.icosphere(3, 0.25)
    b, fb = vp.icosphere(2, 0.15)
    verts = np.vstack([a - [0.2, 0, 0], b + [0.25, 0.1, 0]])
    tris = np.vstack([fa, fb + len(a)])
    islands = [_volume(a - [0.2, 0, 0], fa), _volume(b + [0.25, 0.1, 0], fb)]
    shrunk = verts * [0.9, 0.95, 0.9]
    lat = vp.Lattice((4, 4, 4), "BSPLINE")
    c, s = np.cos(0.3), np.sin(0.3)
    M = np.array([[1.4 * c, -1.4 * s, 0, 0.1], [1.4 * s, 1.4 * c, 0, 0], [0, 0, 1.1, -0.05], [0, 0, 0, 1]])
    P = _squash(lat)
    for per_island, target in ((False, sum(islands)), (True, islands)):
        inp = vp.FrameInputs(positions=shrunk, tris=tris, lattice=lat, points=P, matrix=M,
                             islands=per_island, target_volumes=target, volume_scale=1.0,
                             dtype=np.float64)
        out = vp.Pipeline().evaluate(inp).positions
        if per_island:
            got = [_volume(out, fa), _volume(out, fb + len(a))]
            # Islands are solved jointly, to the solver's float64 bound (tolerances.MET_REL_F64).
            np.testing.assert_allclose(got, islands, rtol=1e-9)
        else:
            assert abs(_volume(out, tris) / sum(islands) - 1) <= 1e-12
    # A target for other islands than those that reach the slot: their own volume, and why.
    out = vp.Pipeline().evaluate(vp.FrameInputs(positions=shrunk, tris=tris, lattice=lat, points=P,
                                                matrix=M, islands=True, target_volumes=[1.0],
                                                dtype=np.float64))
    assert any("2 island(s) reach VP-FFD" in w for w in out.warnings), out.warnings
    assert abs(out.volume / out.input_volume - 1) <= 1e-9 and out.reference_volume == out.input_volume
