"""Re-embedding with a reused `Topology`: a mesh moving through the lattice re-binds on every
frame, and what the faces alone determine is computed once. The result must not depend on that:
a bind with a reused topology equals a bind from scratch, array for array, and the layout depends
only on the bind's own arguments, never on an earlier binding."""
import numpy as np
import pytest

import vpffd_addon as vp

from . import _meshes as M

pytestmark = pytest.mark.core


def _arrays(b):
    out = {k: v for k, v in vars(b).items() if isinstance(v, np.ndarray)}
    out.update({f"corner_part_{i}": c for i, c in enumerate(b.corner_parts)})
    return out


def _two_spheres():
    v1, f1 = vp.icosphere(2, 0.3)
    v2, f2 = vp.icosphere(1, 0.2)
    return np.concatenate([v1 - (0.35, 0, 0), v2 + (0.4, 0.1, 0)]), np.concatenate([f1, f2 + len(v1)])


@pytest.mark.parametrize("interp", ["BSPLINE", "LINEAR", "CARDINAL", "BEZIER"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_reused_topology_gives_the_same_binding(interp, dtype):
    v, f = _two_spheres()
    lat = vp.Lattice((5, 4, 3), interp, bounds=((-0.7, -0.5, -0.4), (0.8, 0.5, 0.45)))
    topo = vp.Topology(f, len(v))
    rng = np.random.default_rng(3)
    for shift in [(0, 0, 0), (0.31, -0.12, 0.05), (-0.9, 0.4, 0.3)]:   # the last one half outside
        moved = v @ M.rotation(rng).T * 0.9 + shift
        fresh = vp.bind(lat, moved, f, dtype=dtype)
        reused = vp.bind(lat, moved, f, dtype=dtype, topology=topo)
        a, b = _arrays(fresh), _arrays(reused)
        assert a.keys() == b.keys()
        for k in a:
            assert np.array_equal(a[k], b[k]), k
        assert fresh.rest_volume == reused.rest_volume
        P = lat.rest_points + rng.normal(0, 0.05, (lat.n_points, 3))
        s1, s2 = fresh.solve(P, axes="XYZ"), reused.solve(P, axes="XYZ")
        assert np.array_equal(s1.verts, s2.verts)


def test_layout_does_not_depend_on_the_previous_binding():
    """Frame B bound after frame A equals frame B bound alone (chunked renders rely on it)."""
    v, f = vp.icosphere(3, 0.5)
    lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    topo = vp.Topology(f, len(v))
    vp.bind(lat, v + 0.3, f, dtype=np.float32, topology=topo)
    after = vp.bind(lat, v - 0.2, f, dtype=np.float32, topology=topo)
    alone = vp.bind(lat, v - 0.2, f, dtype=np.float32, topology=vp.Topology(f, len(v)))
    for k, arr in _arrays(alone).items():
        assert np.array_equal(arr, _arrays(after)[k]), k


def test_topology_of_other_faces_is_refused():
    v, f = vp.icosphere(1, 0.5)
    topo = vp.Topology(f, len(v))
    lat = vp.Lattice((3, 3, 3))
    with pytest.raises(ValueError, match="other faces"):
        vp.bind(lat, v, f[::-1], topology=topo)
    with pytest.raises(ValueError, match="Topology"):
        vp.bind(lat, v, f, topology="not a topology")


def test_island_bounds_match_a_loop():
    v, f = _two_spheres()
    topo = vp.Topology(f, len(v))
    lo, hi = topo.island_bounds(v)
    for k in range(topo.n_islands):
        sel = v[topo.labels == k]
        assert np.array_equal(lo[k], sel.min(0)) and np.array_equal(hi[k], sel.max(0))


@pytest.mark.parametrize("seed", range(40))
def test_is_closed_matches_the_definition(seed):
    """Every edge used exactly twice, in opposite directions: checked against a dictionary count."""
    rng = np.random.default_rng(seed)
    v, f = vp.icosphere(1, 1.0)
    f = f.copy()
    kind = seed % 4
    if kind == 1:
        f = f[1:]                                   # a hole
    elif kind == 2:
        f[0] = f[0, ::-1]                           # one face flipped
    elif kind == 3:
        f = np.concatenate([f, f[:1]])              # a face used twice
    f = f[rng.permutation(len(f))]
    count = {}
    for a, b, c in f:
        for e in ((a, b), (b, c), (c, a)):
            count[e] = count.get(e, 0) + 1
    expected = all(n == 1 and count.get((e[1], e[0])) == 1 for e, n in count.items())
    assert vp.mesh.is_closed(f, len(v)) == expected
    assert expected == (kind == 0)


def _frame_inputs(v, f, lat, shift, squash, **kw):
    P = lat.rest_points.copy()
    P[:, 2] *= squash
    M = np.eye(4)
    M[:3, 3] = shift
    return vp.FrameInputs(positions=v.astype(np.float32), tris=f, lattice=lat, points=P, matrix=M, **kw)


def test_pipeline_results_do_not_depend_on_the_frame_before():
    v, f = _two_spheres()
    lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    frames = [_frame_inputs(v, f, lat, (0.1 * k, 0, 0), 0.9 - 0.1 * k, axes="XY", volume_scale=1 + 0.05 * k)
              for k in range(3)]
    warm = vp.Pipeline()
    history = [warm.evaluate(fr) for fr in frames + frames[::-1]]
    for k, fr in enumerate(frames):
        alone = vp.Pipeline().evaluate(fr)
        for got in (history[k], history[len(history) - 1 - k]):
            assert np.array_equal(got.positions, alone.positions)
            assert np.array_equal(got.points, alone.points)
    assert not history[1].rebound or history[1].binding is not history[0].binding


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_pipeline_follows_the_weights_from_frame_to_frame(dtype):
    # Weights as Blender hands them over (float32, a new array every frame, or the caller's one
    # buffer refilled): a frame's result is a fresh pipeline's whatever weights came before,
    # including equal values in a new array and changes made in place between frames.
    v, f = _two_spheres()
    lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    P = lat.rest_points * [1.0, 1.0, 0.7]
    base = np.ones(len(v), np.float32)
    base[: len(v) // 3] = 0.25
    zeros = base.copy()
    zeros[::7] = 0.0
    sequence = [base, base * 0.5, base.copy(), zeros, base, zeros.copy(), None]
    pipeline, buffer = vp.Pipeline(), base.copy()
    for weights in sequence:
        if weights is not None:
            buffer[:] = weights            # (the same array as the frame before, refilled)
        given = None if weights is None else buffer

        def inputs(w):
            return vp.FrameInputs(positions=v, tris=f, lattice=lat, points=P, matrix=np.eye(4),
                                  weights=w, axes="XYZ", dtype=dtype)
        got = pipeline.evaluate(inputs(given))
        alone = vp.Pipeline().evaluate(inputs(None if weights is None else weights.copy()))
        assert np.array_equal(got.positions, alone.positions) and got.still == alone.still
        assert np.array_equal(got.float32_offsets()[0], alone.float32_offsets()[0])
    assert alone.still == 0 and vp.Pipeline().evaluate(inputs(zeros)).still == int((zeros == 0).sum())


def test_pipeline_keeps_scale_times_the_volume_that_comes_in():
    v, f = vp.icosphere(3, 0.6)
    lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    pipe = vp.Pipeline()
    for k, scale in enumerate((1.0, 1.2, 0.8)):
        moved = v * (1.0, 1.0, 1.0 + 0.2 * k)          # what reaches the slot changes too
        inp = _frame_inputs(moved, f, lat, (0.05 * k, 0, 0), 0.5, axes="XYZ", volume_scale=scale)
        res = pipe.evaluate(inp)
        v_in = vp.signed_volume(moved.astype(np.float32).astype(float), f)
        v_out = vp.signed_volume(res.positions, f)
        assert abs(v_out / (scale * v_in) - 1) <= 1e-5
        assert abs(res.input_volume / v_in - 1) <= 1e-5    # in lattice space: the same here (unit matrix)
        assert abs(res.volume / res.input_volume - scale) <= 1e-5 * scale


def test_pipeline_without_faces_gives_the_plain_deformation_only():
    v, f = vp.icosphere(2, 0.6)
    lat = vp.Lattice((4, 4, 4), "CATMULL_ROM", bounds=((-1,) * 3, (1,) * 3))
    with_faces = vp.Pipeline().evaluate(_frame_inputs(v, f, lat, (0.1, 0, 0), 0.6, correct=False, strength=0.7))
    without = vp.Pipeline().evaluate(_frame_inputs(v, None, lat, (0.1, 0, 0), 0.6, correct=False, strength=0.7))
    assert np.abs(with_faces.positions - without.positions).max() <= 1e-6
    assert without.volume is None and without.binding is None
    with pytest.raises(ValueError, match="no faces"):
        vp.Pipeline().evaluate(_frame_inputs(v, None, lat, (0, 0, 0), 0.6))


def test_a_frame_that_cannot_be_corrected_gives_the_plain_deformation_and_says_why():
    """A lattice with one point per axis only translates: no correction can change the volume.
    The frame gives the plain result (the Lattice modifier's) and a warning in words."""
    v, f = vp.icosphere(2, 0.6)
    lat = vp.Lattice((1, 1, 1), "BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    inp = vp.FrameInputs(positions=v.astype(np.float32), tris=f, lattice=lat,
                         points=lat.rest_points + 0.1, matrix=np.eye(4), axes="XYZ", volume_scale=1.5)
    res = vp.Pipeline().evaluate(inp)
    assert any("not corrected on this frame" in w for w in res.warnings)
    np.testing.assert_allclose(res.positions, v.astype(np.float32) + 0.1, atol=1e-6)

