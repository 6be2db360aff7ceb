"""Per-Island Volume's first move (`solve._State.sweep`: one joint linearised step applied a
direction at a time), its float64 steps (`CompiledSteps.in_float64`, kept per binding), the
three-axis gradient cache (`_State.gradients`) and the compiled least-norm step
(`compiled.min_norm`).

Every island's volume is measured independently from the returned vertices (`_meshes`) and the
solve is compared with the NumPy steps', in the cases the sweep treats apart: one or two
directions, directions that are no axes, negative axes, immobile control points, other targets,
a mirroring lattice, islands the lattice does not reach, a flat island; and the state a refused
sweep leaves (nothing half moved, the plain deformation's notes kept)."""
import os
import subprocess
import sys

import numpy as np
import pytest

import vpffd_addon as vp
from vpffd_addon import backends, compiled
from vpffd_addon.solve import _State
from vpffd_addon.steps import NumpySteps

from . import _meshes as M
from ._process import cpu_while_asleep

pytestmark = pytest.mark.core

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def kernels():
    pytest.importorskip("numba", reason="numba is not installed in this environment")
    assert compiled.load(), compiled.why()
    yield compiled
    compiled.unload()


def _three_bodies(dtype=np.float64, seed=1, scale=1.0):
    """Three closed star-shaped bodies side by side in a 4x4x4 B-spline lattice, and control points
    moved at random (jitter and a global squash, twist or bend): (binding, points, tris, part)."""
    rng = np.random.default_rng(seed)
    verts, tris, part = M.closed_mesh(rng, n_parts=3)
    lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=((-1.1,) * 3, (1.1,) * 3))
    P = M.random_points(rng, lat, noise=0.3)
    if scale != 1.0:
        lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=((-1.1 * scale,) * 3, (1.1 * scale,) * 3))
        verts, P = verts * scale, P * scale
    b = vp.bind(lat, verts, tris, dtype=dtype)
    assert b.n_islands == 3 and np.array_equal(b.island_labels, part)
    return b, P, tris, part


_ROT = M.rotation(np.random.default_rng(3))
_N = 64
#: The options of each case, from the binding (targets are per island).
CASES = {
    "Z": lambda b: {"axes": "Z"},
    "XY": lambda b: {"axes": "XY"},
    "ZX": lambda b: {"axes": "ZX"},
    "-X -Y -Z": lambda b: {"directions": -np.eye(3)},
    "-Z X -Y": lambda b: {"directions": [[0, 0, -1], [1, 0, 0], [0, -1, 0]]},
    "rotated frame": lambda b: {"directions": _ROT},
    "one rotated direction": lambda b: {"directions": _ROT[:1]},
    "two rotated directions": lambda b: {"directions": _ROT[:2]},
    "axis then rotated": lambda b: {"directions": [[1, 0, 0], _ROT[0]]},
    "rotated then axis": lambda b: {"directions": [_ROT[0], [1, 0, 0]]},
    "X Y Z and a diagonal": lambda b: {"directions": [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]]},
    "X and -X": lambda b: {"directions": [[1, 0, 0], [-1, 0, 0]]},
    "every other point immobile": lambda b: {"mobility": (np.arange(_N) % 2).astype(float)},
    "half the lattice immobile along Z": lambda b: {
        "axes": "Z", "mobility": np.where(np.arange(_N) < _N // 2, 0.0, np.linspace(0.2, 1.0, _N))},
    "volume_scale": lambda b: {"volume_scale": 0.7},
    "target_volumes": lambda b: {"target_volumes": b.rest_island_volumes * [0.8, 1.25, 1.0],
                                 "volume_scale": 1.1},
}


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("case", list(CASES))
def test_every_island_keeps_its_volume_after_the_sweep(kernels, case, dtype):
    # Measured independently from the returned vertices: the volumes the solve reports, the
    # targets, and the NumPy steps' solve (float32 there, float64 in the compiled steps).
    b, P, tris, part = _three_bodies(dtype)
    kw = CASES[case](b)
    sol = b.solve(P, islands=True, **kw)
    ref = b.solve(P, islands=True, steps=NumpySteps, **kw)
    assert sol.warnings == () and ref.warnings == ()
    now = M.island_volumes(sol.verts, tris, part)
    rel = 1e-9 if dtype == np.float64 else 1e-6       # (a tenth of float32's tolerance: in_float64)
    np.testing.assert_allclose(now, sol.island_target_volumes, rtol=rel, atol=0)
    np.testing.assert_allclose(sol.island_volumes, now, rtol=rel, atol=0)
    np.testing.assert_allclose(M.island_volumes(ref.verts, tris, part), ref.island_target_volumes,
                               rtol=1e-9 if dtype == np.float64 else 1e-5, atol=0)
    assert np.abs(sol.verts - ref.verts).max() <= 1e-6 * b.lattice.size
    if "mobility" in kw:
        still = kw["mobility"] == 0
        np.testing.assert_array_equal(sol.points[still], P[still])


@pytest.mark.parametrize("axes", ["XYZ", "Z"])
def test_a_mirroring_lattice_keeps_every_islands_size_after_the_sweep(kernels, axes):
    b, P, tris, part = _three_bodies()
    P = P.copy()
    P[:, 0] = 2 * b.lattice.centre[0] - P[:, 0]
    for steps in (None, NumpySteps):
        sol = b.solve(P, islands=True, axes=axes, volume_scale=1.1, steps=steps)
        now = M.island_volumes(sol.verts, tris, part)
        np.testing.assert_allclose(now, -1.1 * b.rest_island_volumes, rtol=1e-9, atol=0)
        np.testing.assert_allclose(sol.island_volumes, now, rtol=1e-9, atol=0)
        assert len(sol.warnings) == 1 and "mirrors space" in sol.warnings[0]


def test_islands_out_of_reach_or_flat_keep_their_volumes(kernels):
    # An island outside the lattice, one with influence 0 (their coefficient rows are zero: no
    # usable row), a flat one (volume 0), beside a body the lattice squashes.
    flat_v, flat_f = vp.box(2, 0.3, center=(0.4, -0.4, 0.2))
    flat_v = flat_v.copy()
    flat_v[:, 2] = 0.2
    verts, tris, part = M.union([vp.icosphere(2, 0.4), vp.icosphere(2, 0.3, center=(3, 0, 0)),
                                 vp.box(2, 0.3, center=(0.5, 0.5, 0.3)), (flat_v, flat_f)])
    lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    P = M.random_points(np.random.default_rng(4), lat, noise=0.3, global_kind="squash")
    influence = np.where(part == 2, 0.0, 1.0)
    b = vp.bind(lat, verts, tris, influence=influence)
    rest = M.island_volumes(verts, tris, part)
    for axes in ("XYZ", "Z"):
        for steps in (None, NumpySteps):
            sol = b.solve(P, islands=True, axes=axes, steps=steps)
            assert sol.warnings == ()
            now = M.island_volumes(sol.verts, tris, part)
            assert np.abs(now - rest).max() <= 1e-9 * np.abs(rest).max()
            assert np.abs(sol.island_volumes - now).max() <= 1e-9 * np.abs(rest).max()


def test_a_refused_sweep_leaves_the_plain_deformation_unmoved(kernels):
    # A target no move within 100 lattice sizes reaches: the sweep refuses its step before
    # moving anything, the joint steps refuse theirs, and the plain deformation comes back with
    # its volumes as measured (not a half-moved lattice).
    b, P, tris, part = _three_bodies()
    for steps in (None, NumpySteps):
        sol = b.solve(P, islands=True, volume_scale=1e4, steps=steps)
        np.testing.assert_array_equal(sol.points, P)
        plain = M.island_volumes(b.deform(P), tris, part)
        np.testing.assert_allclose(sol.island_volumes, plain, rtol=1e-12, atol=0)
        assert any("could not reach the target" in w for w in sol.warnings)


@pytest.mark.parametrize("steps", [None, NumpySteps])
def test_a_refused_sweep_keeps_the_mirror_warning(kernels, steps):
    # The sweep notes the plain deformation (turning the targets' signs where the lattice
    # mirrors), then refuses its step; the fallback `start` noted it again, saw no sign left to
    # turn and dropped `mirrored`: the mirror warning the joint steps alone gave is lost.
    b, P, tris, part = _three_bodies()
    P = P.copy()
    P[:, 0] = 2 * b.lattice.centre[0] - P[:, 0]
    sol = b.solve(P, islands=True, volume_scale=1e4, steps=steps)
    np.testing.assert_array_equal(sol.points, P)
    assert any("could not reach the target" in w for w in sol.warnings)
    assert any("mirrors space" in w for w in sol.warnings), sol.warnings


@pytest.mark.parametrize("steps", [None, NumpySteps])
def test_islands_in_a_lattice_of_huge_coordinates_keep_their_volumes(kernels, steps):
    # Lattice and mesh 1e80 across (float64): coefficients ~1e160, whose squares overflow in the
    # compiled QR's unscaled column norms; LAPACK's least squares (before) scaled them and met
    # every volume. Now NaN reaches LAPACK (which `_min_norm_step` says may never return) and
    # the solve raises LinAlgError.
    b, P, tris, part = _three_bodies(scale=1e80)
    sol = b.solve(P, islands=True, steps=steps)
    assert sol.warnings == ()
    now = M.island_volumes(sol.verts, tris, part)
    np.testing.assert_allclose(now, b.rest_island_volumes, rtol=1e-9, atol=0)


@pytest.mark.parametrize("c", [1e-170, 1e170])
def test_the_least_norm_step_does_not_depend_on_the_rows_scale(kernels, c):
    # min_norm(c A, c r) is min_norm(A, r), as LAPACK's lstsq gives it at any scale: the QR's
    # column norms underflow to 0 (1e-170: the reflection is skipped and the raw entries are
    # taken as R, a wrong u) or overflow (1e170: NaN into LAPACK).
    rng = np.random.default_rng(11)
    A, r = rng.standard_normal((5, 60)), rng.standard_normal(5)
    ref = np.linalg.lstsq(A, r, rcond=1e-10)[0]
    assert np.abs(np.linalg.lstsq(c * A, c * r, rcond=1e-10)[0] - ref).max() <= 1e-12
    got = kernels.min_norm(c * A, c * r, 1e-10)
    assert got is None or np.abs(got - ref).max() <= 1e-9 * np.abs(ref).max()


def test_the_float64_copies_are_made_once_per_binding(kernels):
    b, P, tris, part = _three_bodies(np.float32)
    b.solve(P, islands=True)
    dtype, params, x0 = b.converted
    assert dtype == np.float64 and params.dtype == x0.dtype == np.float64
    np.testing.assert_array_equal(x0, b.x0.astype(np.float64))
    b.solve(P * 1.01, islands=True, axes="Z")
    assert b.converted[1] is params and b.converted[2] is x0
    b64, *_ = _three_bodies(np.float64)
    b64.solve(P, islands=True)
    assert "converted" not in vars(b64)


def test_the_float64_copies_count_in_the_bindings_nbytes(kernels):
    # `nbytes` counts what the binding holds, lazily made parts included (corner_parts, the
    # incidence): the float64 copies an islands solve keeps on a float32 binding (7 float64 per
    # slot, about half again the binding's ~100 bytes per vertex) are left out.
    b, P, tris, part = _three_bodies(np.float32)
    b.solve(P, islands=True)
    _, params, x0 = b.converted
    arrays = sum(a.nbytes for a in vars(b).values() if isinstance(a, np.ndarray))
    assert b.nbytes >= arrays + params.nbytes + x0.nbytes


def test_the_three_axis_gradients_are_taken_again_after_a_move(kernels):
    # `_State.gradients` keeps the three axis gradients of one pass keyed by the number of moves:
    # after a move they are taken again, and the volumes measured with them (and with the kept
    # coefficients, `alpha_rows`) are those of the moved lattice.
    b, P, tris, part = _three_bodies()
    none = (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64))
    st = _State(b, P, None, none, True, b.rest_island_volumes.copy())
    assert hasattr(st.k, "axis_gradients")
    dirs = np.eye(3)
    st.gradients(dirs)
    _, g0, _ = st.gradient(dirs[2])
    np.testing.assert_allclose(st.measured(dirs[2]), M.island_volumes(b.deform(P), tris, part),
                               rtol=1e-12, atol=0)
    t = np.random.default_rng(2).uniform(-0.05, 0.05, b.lattice.n_points)
    st.move(dirs[0], 0, t)
    st.gradients(dirs)
    _, g1, _ = st.gradient(dirs[2])
    assert g1 is not g0
    fresh = compiled.CompiledSteps(b).axis_gradient(2, st.D)
    assert np.abs(g1.g - fresh.g).max() <= 1e-12 * np.abs(fresh.g).max()
    moved = P.copy()
    moved[:, 0] += t
    np.testing.assert_array_equal(st.P, moved)
    want = M.island_volumes(b.deform(moved), tris, part)
    for e in dirs:
        np.testing.assert_allclose(st.measured(e), want, rtol=1e-12, atol=0)


def test_every_sweep_path_leaves_no_blas_threads_spinning(kernels):
    # `test_core_compiled` checks XYZ; the sweep's one-direction, two-direction and rotated
    # paths, and more islands than control points (min_norm leaves those to LAPACK).
    verts, tris = M.small_bodies()
    cpu_while_asleep(0.5)
    for shape, kw in (((6, 6, 6), {"axes": "Z"}), ((6, 6, 6), {"axes": "XY"}),
                      ((6, 6, 6), {"directions": _ROT}), ((3, 3, 3), {"axes": "Z"})):
        lat = vp.Lattice(shape, "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
        b = vp.bind(lat, verts, tris, dtype=np.float32)
        b.solve(lat.rest_points * [1.0, 1.0, 0.5], islands=True, **kw)
        assert cpu_while_asleep() < 20.0, (shape, kw)


def test_without_numba_islands_keep_their_volumes():
    code = ("import sys; sys.modules['numba'] = None\n"
            "import numpy as np\n"
            "import vpffd_addon as vp\n"
            "from vpffd_addon import backends, compiled\n"
            "from tests import _meshes as M\n"
            "assert not compiled.load()\n"
            "v, f, part = M.union([vp.icosphere(2, 0.4), vp.box(2, 0.3, center=(0.5, 0.5, 0.3))])\n"
            "lat = vp.Lattice((4, 4, 4), 'BSPLINE', bounds=((-1,) * 3, (1,) * 3))\n"
            "P = lat.rest_points * [1, 1, 0.7] + np.random.default_rng(0).normal(0, 0.03, (64, 3))\n"
            "for dt in (np.float32, np.float64):\n"
            "    b = vp.bind(lat, v, f, dtype=dt)\n"
            "    for kw in ({'axes': 'XYZ'}, {'axes': 'Z'}, {'directions': M.rotation(np.random.default_rng(1))}):\n"
            "        sol = b.solve(P, islands=True, **kw)\n"
            "        miss = np.abs(M.island_volumes(sol.verts, f, part) / M.island_volumes(v, f, part) - 1).max()\n"
            "        ok = miss < (1e-5 if dt == np.float32 else 1e-9)\n"
            "        print(type(backends.default_steps(b)).__name__, sol.warnings, ok)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                          env=dict(os.environ, PYTHONPATH=ROOT))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == ["NumpySteps () True"] * 6, proc.stdout


def test_cage_islands_keep_their_volumes():
    cage = vp.box_cage((2, 2, 2))
    verts, tris, part = M.union([vp.icosphere(2, 0.3), vp.box(2, 0.25, center=(0.4, 0.4, 0.2))])
    b = vp.bind(cage, verts, tris)
    assert type(backends.default_steps(b)) is NumpySteps
    pts = np.asarray(cage.rest_points) * [1.0, 1.0, 0.7]
    rest = M.island_volumes(verts, tris, part)
    for axes in ("XYZ", "Z"):
        sol = b.solve(pts, islands=True, axes=axes)
        assert sol.warnings == ()
        np.testing.assert_allclose(M.island_volumes(sol.verts, tris, part), rest, rtol=1e-9, atol=0)
