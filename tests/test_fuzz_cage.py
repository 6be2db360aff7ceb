"""Fuzzing cages with hostile input (hypothesis).

- Cage construction from random points (NaN, inf, huge, tiny, collapsed) and random cell lists
  (wrong lengths, repeated or out-of-range indices, random face loops, shuffled orientations) either
  builds a cage or raises ValueError with a message; nothing else, and never a hang.
- Valid cages (jittered boxes, extruded random polygon discs, prisms) at depths 0..2, with meshes
  partly outside, deformed by random, collapsing or far-flung points, solved along random axes in
  float32 and float64: either ValueError, or finite results where `deform(sol.points)` is
  `sol.verts`, and the volume of `sol.verts` (measured here) is the reported one; when no warning is
  given it is the target.

CI runs `VPFFD_FUZZ_CAGE_EXAMPLES` examples per test (default 40), derandomized; more with
`VPFFD_FUZZ_CAGE_EXAMPLES=2000 VPFFD_FUZZ_RANDOM=1 ./dev test tests/test_fuzz_cage.py`.
"""
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

import vpffd_addon as vp

pytestmark = pytest.mark.fuzz

EXAMPLES = int(os.environ.get("VPFFD_FUZZ_CAGE_EXAMPLES", "40"))
RANDOM = os.environ.get("VPFFD_FUZZ_RANDOM", "") not in ("", "0")
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=not RANDOM,
                suppress_health_check=list(HealthCheck))

SEEDS = st.integers(0, 2 ** 31 - 1)
MAGNITUDES = st.sampled_from([1e-300, 1e-12, 1e-3, 1.0, 1e3, 1e12, 1e150, 1e300])
BAD = st.sampled_from([np.nan, np.inf, -np.inf])


def _volume(verts, tris):
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


@FUZZ
@given(seed=SEEDS, n_points=st.integers(0, 14), n_cells=st.integers(0, 4), magnitude=MAGNITUDES,
       poison=st.one_of(st.none(), BAD), nested=st.booleans())
def test_random_cell_lists_build_or_raise_value_error(seed, n_points, n_cells, magnitude, poison, nested):
    rng = np.random.default_rng(seed)
    points = rng.normal(0, magnitude, (n_points, 3))
    if poison is not None and n_points:
        points[rng.integers(n_points), rng.integers(3)] = poison
    cells = []
    for _ in range(n_cells):
        if nested:
            faces = [list(rng.integers(-1, max(n_points, 1) + 1, rng.integers(2, 6)))
                     for _ in range(rng.integers(1, 8))]
            cells.append(faces)
        else:
            cells.append(list(rng.integers(-1, max(n_points, 1) + 1, rng.choice([3, 4, 5, 6, 7, 8, 9]))))
    note(f"points {points.tolist()}\ncells {cells}")
    try:
        cage = vp.Cage(points, cells)
    except ValueError as exc:
        assert str(exc)
        return
    # It built: then every point is finite and used, and every cell has positive volume.
    assert np.isfinite(cage.rest_points).all()
    assert cage.n_cells == n_cells


def _disc(rng, k):
    step = 2 * np.pi / k
    ang = np.arange(k) * step + rng.uniform(-0.15, 0.15, k) * step    # gaps < pi: a valid ring
    r = rng.uniform(0.6, 1.2)
    inner = np.stack([0.45 * r * np.cos(ang), 0.45 * r * np.sin(ang), 0 * ang], 1)
    outer = np.stack([r * np.cos(ang), r * np.sin(ang), 0 * ang], 1)
    polys = [list(range(k))] + [[i, (i + 1) % k, k + (i + 1) % k, k + i] for i in range(k)]
    return vp.Cage(*vp.extrude(np.concatenate([inner, outer]) - [0, 0, 0.8], polys, (0, 0, 1.6),
                               int(rng.integers(1, 4))))


def _cage(kind, rng):
    if kind == "box":
        res = tuple(int(n) for n in rng.integers(1, 4, 3))
        cage = vp.box_cage(res)
        h = 2.0 / max(res)
        P = cage.rest_points + rng.uniform(-0.12, 0.12, (cage.n_points, 3)) * h
        return vp.Cage(P, [list(c) for c in cage.cells])
    if kind == "disc":
        return _disc(rng, int(rng.integers(3, 9)))
    P = np.array([[-1, -1, 0], [1, -1, 0], [-1, 1, 0], [1, 1, 0]], float)
    return vp.Cage(*vp.extrude(P - [0, 0, 0.0], [[0, 1, 2], [1, 3, 2]], (0, 0, 1.5), 2))


@FUZZ
@given(kind=st.sampled_from(["box", "disc", "prisms"]), depth=st.integers(0, 2), seed=SEEDS,
       motion=st.sampled_from(["jitter", "squash", "flat", "point", "far", "huge", "mirror"]),
       axes=st.sampled_from(["XYZ", "XY", "Z", "YZX", ""]), scale=st.sampled_from([0.0, 0.5, 1.0, 1.7]),
       dtype=st.sampled_from([np.float32, np.float64]), outside=st.sampled_from(["FOLLOW", "STAY"]),
       mesh_scale=st.sampled_from([1e-6, 0.3, 0.8, 1.5]))
def test_cage_solves_are_finite_and_self_consistent(kind, depth, seed, motion, axes, scale, dtype,
                                                      outside, mesh_scale):
    rng = np.random.default_rng(seed)
    cage = _cage(kind, rng)
    verts, tris = vp.icosphere(2)
    verts = verts * mesh_scale + rng.normal(0, 0.1, 3)
    b = vp.bind(cage, verts, tris, depth=depth, dtype=dtype, outside=outside)
    assert 0 <= b.n_outside <= b.n_verts
    P = cage.rest_points.copy()
    if motion == "jitter":
        P += rng.normal(0, 0.15, P.shape)
    elif motion == "squash":
        P[:, 2] *= rng.uniform(0.2, 0.9)
    elif motion == "flat":
        P[:, 2] = 0.0
    elif motion == "point":
        P[:] = P[0]
    elif motion == "far":
        P += 1e8
    elif motion == "huge":
        P *= 1e200
    else:
        P[:, 0] *= -1
    note(f"{kind} depth {depth} {motion} axes {axes!r} scale {scale} {np.dtype(dtype).name}")
    try:
        plain = b.deform(P)
    except ValueError as exc:
        assert str(exc)
        return
    assert np.isfinite(plain).all()
    try:
        sol = b.solve(P, axes=axes, volume_scale=scale, preserve_volume=bool(axes))
    except ValueError as exc:
        assert str(exc)
        return
    for value in (sol.verts, sol.points, sol.volume, sol.plain_volume, sol.target_volume):
        assert np.isfinite(value).all()
    size = max(np.abs(sol.verts).max(), 1e-300)
    tol = 1e-4 if dtype == np.float32 else 1e-9
    np.testing.assert_allclose(b.deform(sol.points), sol.verts, rtol=0, atol=tol * size + 1e-300)
    measured = _volume(sol.verts, tris)
    scale_v = max(abs(measured), abs(sol.volume), size ** 3 * 1e-3)
    assert abs(measured - sol.volume) <= 100 * tol * scale_v
    if axes and not sol.warnings and motion in ("jitter", "squash", "mirror"):
        assert abs(sol.volume - sol.target_volume) <= 10 * tol * max(abs(sol.target_volume), scale_v)
    if axes == "" or not axes:
        assert sol.volume == sol.plain_volume


@FUZZ
@given(seed=SEEDS, target=st.sampled_from(["points", "cage points", "verts"]), bad=BAD)
def test_non_finite_cage_input_is_rejected(seed, target, bad):
    rng = np.random.default_rng(seed)
    cage = vp.box_cage((2, 1, 1))
    verts, tris = vp.icosphere(1, 0.5)
    P = cage.rest_points.copy()
    try:
        if target == "cage points":
            pts = cage.rest_points
            pts[rng.integers(len(pts))] = bad
            vp.Cage(pts, [list(c) for c in cage.cells])
        elif target == "verts":
            verts = verts.copy()
            verts[rng.integers(len(verts))] = bad
            vp.bind(cage, verts, tris, depth=1)
        else:
            P[rng.integers(len(P))] = bad
            vp.bind(cage, verts, tris, depth=1).solve(P)
    except ValueError as exc:
        assert "finite" in str(exc)
        return
    raise AssertionError("non-finite input was accepted")
