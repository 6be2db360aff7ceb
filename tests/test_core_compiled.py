"""The compiled kernels (`vpffd_addon.compiled`, numba) against the NumPy steps they stand in for:
the same gradient, the same solves (vertices to 1e-6 of the lattice's size, volumes to 1e-7),
the same result on every run; and the NumPy path, with the reason in words, where numba cannot be
imported."""
import math
import os
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("numba", reason="numba is not installed in this environment")

import vpffd_addon as vp  # noqa: E402
from vpffd_addon import backends, compiled, frame, parallel, volume  # noqa: E402
from vpffd_addon import offsets as offsets_  # noqa: E402
from vpffd_addon.steps import NumpySteps  # noqa: E402

from . import _meshes as M  # noqa: E402
from ._process import cpu_while_asleep  # noqa: E402
from .test_core_reembed import _two_spheres  # noqa: E402

pytestmark = pytest.mark.core

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def kernels():
    # (with the teams for numba's threads, which load() leaves out on machines of fewer cores)
    assert compiled.load(teams=True), compiled.why()
    yield compiled
    compiled.unload()


def _problem(dtype, n_sub=4, islands=False, seed=3):
    rng = np.random.default_rng(seed)
    v, f = vp.icosphere(n_sub, 0.7)
    if islands:
        v2, f2 = vp.icosphere(2, 0.2)
        v, f = np.vstack([v, v2 + 0.45]), np.vstack([f, f2 + len(v)])
    lat = vp.Lattice((5, 4, 6), ("BSPLINE", "CARDINAL", "LINEAR"))
    b = vp.bind(lat, v * [1.0, 0.9, 1.1], f, dtype=dtype)
    P = lat.rest_points + rng.normal(0, 0.04, lat.rest_points.shape)
    P[:, 2] *= 0.75
    return b, P


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("islands", [False, True])
def test_the_compiled_pass_equals_numpys_gradient_and_sums(kernels, dtype, islands):
    # One pass gives the gradient, (S B)^T g per volume row, x0_a . g and sum |s g|: each equal
    # to what the NumPy steps compute separately, along every axis and along a direction.
    b, P = _problem(dtype, islands=islands)
    D = P - b.lattice.rest_points
    ref, fast = NumpySteps(b), kernels.CompiledSteps(b)
    rows, k = (b.slot_island, b.n_islands) if islands else (None, 1)
    rel = 1e-6 if dtype == np.float32 else 1e-12
    ref.refresh((0, 1, 2), D)
    fast.refresh((0, 1, 2), D)
    # The two forward products agree to the rounding of the binding's precision; from here on both
    # kinds of steps start from the same coordinates, so that the gradients can be held to float64.
    assert np.abs(fast.X - ref.X).max() <= 2 * np.finfo(dtype).eps * np.abs(ref.X).max()
    fast.X[:] = ref.X
    # A slot's gradient sums about six products of coordinates: in float32 the compiled kernel may
    # fuse a product and a difference (one rounding fewer), so they agree to the rounding of those
    # products; in float64 to that of the float64 sums.
    terms = 6 * np.abs(ref.X).max() ** 2
    g_tol = (4 * np.finfo(np.float32).eps if dtype == np.float32 else 1e-14) * terms
    for axis in range(3):
        g_ref, g = ref.axis_gradient(axis, D), fast.axis_gradient(axis, D)
        assert np.abs(g.g - g_ref).max() <= g_tol
        alpha_ref, alpha = ref.transpose(g_ref, rows, k), fast.transpose(g, rows, k)
        assert alpha.shape == alpha_ref.shape == (k, b.lattice.n_points)
        assert np.abs(alpha - alpha_ref).max() <= rel * np.abs(alpha_ref).max()
        for name in ("x0_dot", "flux"):
            args = (axis, g_ref, rows, k) if name == "x0_dot" else (g_ref, rows, k)
            want = getattr(ref, name)(*args)
            got = getattr(fast, name)(*((axis, g, rows, k) if name == "x0_dot" else (g, rows, k)))
            scale = np.abs(b.x0).max() * np.abs(g_ref).sum()
            assert np.abs(got - want).max() <= rel * scale, name
    p, q = np.array([0.6, 0.8, 0.0]), np.array([0.0, 0.0, 1.0])
    g_ref, g = ref.direction_gradient(p, q, D), fast.direction_gradient(p, q, D)
    assert np.abs(g.g - g_ref).max() <= 1e-14 * terms     # (in float64 for both, as p @ X)


@pytest.mark.parametrize("shape", [(2, 2, 2), (10, 10, 10)])
@pytest.mark.parametrize("team_parts", [3, 100])
@pytest.mark.parametrize("islands", [False, True])
def test_the_runs_summed_in_the_gradient_pass_give_the_blocks_transpose_bit_for_bit(kernels, shape, team_parts,
                                                                                     islands, monkeypatch):
    # A gradient pass sums the moments of every run of blocks in one cell and island that its part
    # holds whole (`gradient_runs`, and `gradient_runs3` for the three axes at once); the transpose
    # adds up the runs no part held whole and turns them all into the control points' entries.
    # That must be what `reduce_blocks` makes from every block's moments, bit for bit, however the
    # parts cut the runs, for one volume and (islands) a row per island: a 2x2x2 lattice has one
    # cell, so one run per island that every cut crosses; 10x10x10 a few hundred. On the Python
    # threads and (team_parts 3) on numba's. Asked for twice, a transpose gives the same.
    monkeypatch.setattr(compiled, "TEAM_PARTS", team_parts)
    monkeypatch.setattr(parallel, "MIN_VERTS_PER_PART", 1024)      # (5 parts of a small mesh)
    v, f = vp.icosphere(5, 0.45)
    if islands:     # (two bodies, the small one inside the big one's cells)
        v2, f2 = vp.icosphere(3, 0.1)
        v, f = np.vstack([v, v2 + 0.05]), np.vstack([f, f2 + len(v)])
    lat = vp.Lattice(shape, "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    P = lat.rest_points * [1.0, 1.1, 0.6]
    previous = parallel.set_workers(1)
    results = {}
    try:
        for n in (1, 2, 3, 5):
            parallel.set_workers(n)
            b = vp.bind(lat, v, f, dtype=np.float32)
            assert len(b.block_parts) == n and b.n_islands == 1 + islands
            rows, k = (b.slot_island, b.n_islands) if islands else (None, 1)
            block_row = b.block_island if islands else np.zeros(len(b.block_cell), np.int64)
            steps = kernels.CompiledSteps(b)
            D = P - lat.rest_points
            runs = compiled.cell_runs(b)
            assert np.array_equal(b.block_island[runs[:-1]], np.sort(b.block_island[runs[:-1]]))
            crossed = [r for r in range(len(runs) - 1) if any(
                p.start in range(runs[r] + 1, runs[r + 1]) for p in b.block_parts)]
            three = steps.axis_gradients(D)
            for axis in range(3):
                for way, g in (("one", steps.axis_gradient(axis, D)), ("three", three[axis])):
                    assert [r for r in range(len(runs) - 1) if not g.done[r]] == crossed
                    from_blocks = np.zeros((k, lat.n_points))
                    kernels.kernels()["reduce_blocks"](g.M, b.block_cell, block_row, steps.shape, steps.coef,
                                                       from_blocks)
                    alpha = steps.transpose(g, rows, k)
                    np.testing.assert_array_equal(alpha, from_blocks)
                    np.testing.assert_array_equal(steps.transpose(g, rows, k), alpha)
                    results.setdefault((axis, way), []).append(alpha)
                steps.stale((axis + 1) % 3)
            if shape == (2, 2, 2):
                assert len(runs) == 2 + islands and bool(crossed) == (n > 1)
    finally:
        parallel.set_workers(previous)
    for key, got in results.items():
        for alpha in got[1:]:
            np.testing.assert_array_equal(alpha, got[0])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_compiled_forward_product_and_vertices_equal_numpys(kernels, dtype):
    # Blender's Lattice modifier, as the binding's own (NumPy) deform computes it; a mesh partly
    # outside the lattice, so the clamped taps repeat end points.
    b, P = _problem(dtype)
    assert b.n_outside > 0
    D = P - b.lattice.rest_points
    fast = kernels.CompiledSteps(b)
    size = np.ptp(b.lattice.rest_points, 0).max()
    rel = 1e-6 if dtype == np.float32 else 1e-13
    assert np.abs(fast.verts(D) - b.deform(P)).max() <= rel * size


@pytest.mark.parametrize("dtype,islands,axes", [(np.float32, False, "XYZ"), (np.float64, False, "XY"),
                                                (np.float32, True, "XYZ"), (np.float64, True, "Z")])
def test_solves_with_the_compiled_steps_equal_numpys(kernels, dtype, islands, axes):
    b, P = _problem(dtype, islands=islands)
    assert isinstance(backends.default_steps(b), compiled.CompiledSteps)
    ref = vp.solve.solve(b, P, axes=axes, islands=islands, steps=NumpySteps)
    out = b.solve(P, axes=axes, islands=islands)            # the default: the compiled steps
    assert (ref.backend, out.backend) == ("NUMPY", "COMPILED")
    again = b.solve(P, axes=axes, islands=islands)
    size = np.ptp(b.lattice.rest_points, 0).max()
    assert np.abs(out.verts - ref.verts).max() <= 1e-6 * size
    assert abs(out.volume / ref.volume - 1) <= 1e-7
    np.testing.assert_array_equal(out.verts, again.verts)   # deterministic


def test_cages_keep_the_numpy_steps(kernels):
    cage = vp.box_cage((2, 2, 2))
    v, f = vp.icosphere(2, 0.5)
    b = vp.bind(cage, v, f)
    assert type(backends.default_steps(b)) is NumpySteps
    assert backends.choose("CPU", b) == (backends.NUMPY, "CPU chosen")


def test_without_numba_the_numpy_steps_run_and_say_why():
    code = ("import sys; sys.modules['numba'] = None\n"       # as in a Blender without the wheels
            "import vpffd_addon as vp\n"
            "from vpffd_addon import backends, compiled\n"
            "print(compiled.load(), compiled.why())\n"
            "v, f = vp.icosphere(2, 0.5); lat = vp.Lattice((3, 3, 3))\n"
            "b = vp.bind(lat, v, f)\n"
            "print(type(backends.default_steps(b)).__name__, round(b.solve(lat.rest_points * 0.9).volume / b.rest_volume, 9))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                          env=dict(os.environ, PYTHONPATH=ROOT))
    assert proc.returncode == 0, proc.stderr
    first, second = proc.stdout.splitlines()
    assert first.startswith("False numba cannot be imported"), first
    assert second == "NumpySteps 1.0", second


def _arrays(b):
    """Every array a binding holds, those made on first use too (NumPy's stored weights and face
    parts: a compiled bind leaves them to NumPy, from its own slots), and its rest volume."""
    names = {k for k, v in vars(b).items() if isinstance(v, np.ndarray) and not k.startswith("_")}
    out = {k: getattr(b, k) for k in names | {"wuv", "ww"}}
    out.update({f"corner_parts[{k}]": c for k, c in enumerate(b.corner_parts)})
    out["rest_volume"] = np.array(b.rest_volume)
    return out


def _bind_both(lattice, verts, tris, **kw):
    """A bind with NumPy's layout and one with the compiled layout kernels, in that order."""
    compiled.unload()
    ref = vp.bind(lattice, verts, tris, **kw)
    assert compiled.load(), compiled.why()
    assert compiled.bind_kernels(lattice) is not None
    return ref, vp.bind(lattice, verts, tris, **kw)


@pytest.mark.parametrize("shape", [(2, 2, 2), (3, 4, 5), (6, 6, 6), (9, 2, 4)])
@pytest.mark.parametrize("kind", ["LINEAR", "CARDINAL", "CATMULL_ROM", "BSPLINE"])
def test_the_compiled_bind_layout_is_numpys_bit_for_bit(kernels, shape, kind):
    # A mesh partly outside the lattice (clamped taps), a weight per vertex, both precisions.
    rng = np.random.default_rng(sum(shape))
    v, f = vp.icosphere(3, 0.7)
    v = v * [1.3, 0.8, 1.1] + rng.normal(0, 0.01, v.shape)
    lat = vp.Lattice(shape, (kind, "BSPLINE", kind), bounds=((-0.6, -0.4, -0.45), (0.5, 0.4, 0.7)))
    for dtype in (np.float32, np.float64):
        ref, out = _bind_both(lat, v, f, dtype=dtype, influence=rng.uniform(0, 1, len(v)))
        # The compiled solve needs no stored weights and no sorted faces: a compiled bind (what a
        # mesh moving through the lattice pays on every frame) does not make them.
        assert not {"wuv", "ww", "corner_parts"} & set(vars(out))
        ref_arrays, arrays = _arrays(ref), _arrays(out)
        assert ref.n_outside > 0 and out.n_outside == ref.n_outside
        assert ref_arrays.keys() == arrays.keys()
        for name, a in ref_arrays.items():
            assert a.dtype == arrays[name].dtype and a.shape == arrays[name].shape, name
            np.testing.assert_array_equal(arrays[name], a, err_msg=name)


def test_the_compiled_bind_layout_keeps_islands_and_big_meshes_bit_for_bit(kernels):
    # Several islands (sorted by island, then cell), and a mesh big enough for the worker threads.
    v, f = vp.icosphere(7, 0.5)
    v2, f2 = vp.icosphere(3, 0.15)
    verts = np.vstack([v, v2 + 0.3, v2 - 0.3])
    tris = np.vstack([f, f2 + len(v), f2 + len(v) + len(v2)])
    lat = vp.Lattice((5, 6, 4), ("CATMULL_ROM", "LINEAR", "BSPLINE"))
    ref, out = _bind_both(lat, verts, tris, dtype=np.float32)
    assert ref.n_islands == 3 and len(ref.corner_parts) > 1
    for name, a in _arrays(ref).items():
        np.testing.assert_array_equal(_arrays(out)[name], a, err_msg=name)


@pytest.mark.parametrize("n_islands", [16, 200])
def test_a_compiled_bind_of_many_islands_is_numpys_bit_for_bit(kernels, n_islands):
    # 16 small spheres in a 10x10x10 lattice make 16 x 4,096 keys (island, cell): the counting
    # sort; 200 make more keys than four per vertex, so NumPy sorts the keys the compiled pass of
    # the cells gives. Both must lay the binding out as NumPy does.
    v, f = vp.icosphere(1, 0.04)
    rng = np.random.default_rng(n_islands)
    centres = rng.uniform(-0.45, 0.45, (n_islands, 3))
    verts = np.vstack([v + c for c in centres])
    tris = np.vstack([f + k * len(v) for k in range(n_islands)])
    lat = vp.Lattice((10, 10, 10), "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    n_keys = 16 ** 3 * n_islands
    assert (n_keys <= max(4 * len(verts), 1 << 16)) == (n_islands == 16)
    ref, out = _bind_both(lat, verts, tris, dtype=np.float32)
    assert ref.n_islands == n_islands
    for name, a in _arrays(ref).items():
        np.testing.assert_array_equal(_arrays(out)[name], a, err_msg=name)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_compiled_re_embedding_is_numpys_bit_for_bit(kernels, dtype):
    # A re-embedding (the faces' topology given, what a mesh moving through the lattice pays on
    # every frame) checks and measures the positions in one compiled pass and sorts the vertices
    # by counting: islands of a closed mesh (origins from their own bounds) and of an open one
    # (the lattice's centre), positions handed as Blender hands them (float32) and as float64.
    v, f = vp.icosphere(4, 0.5)
    v2, f2 = vp.icosphere(2, 0.15)
    closed = (np.vstack([v, v2 + 0.3, v2 - 0.3]), np.vstack([f, f2 + len(v), f2 + len(v) + len(v2)]))
    opened = (closed[0], closed[1][3:])
    lat = vp.Lattice((5, 6, 4), ("CATMULL_ROM", "LINEAR", "BSPLINE"))
    for verts, tris in (closed, opened):
        topology = vp.Topology(tris, len(verts))
        moved = (verts * 1.05 + [0.02, -0.01, 0.03]).astype(dtype)
        ref, out = _bind_both(lat, moved, tris, dtype=np.float32, topology=topology)
        assert out.n_islands == 3 and out.is_closed == (tris is closed[1])
        for name, a in _arrays(ref).items():
            np.testing.assert_array_equal(_arrays(out)[name], a, err_msg=name)
        moved[7, 1] = np.nan
        with pytest.raises(ValueError, match=r"rest_verts has non-finite coordinates at 1 vertices \(first: index 7\)"):
            vp.bind(lat, moved, tris, dtype=np.float32, topology=topology)


@pytest.mark.parametrize("team_parts", [99, 3])
def test_a_compiled_bind_writes_every_element_of_the_memory_it_takes_unset(kernels, team_parts, monkeypatch):
    # A compiled bind takes most of its arrays unset (`np.empty`: the slots' values, the counting
    # sort's counts, with only the padding slots set to zero) and relies on its passes to write
    # every other element. Here every unset array comes filled with a byte pattern (as memory
    # freed by an earlier frame would be), and the binding must still be NumPy's bit for bit: one
    # island, islands (counting sort), many islands (NumPy's sort), a re-embedding, on the Python
    # threads and on numba's.
    monkeypatch.setattr(compiled, "TEAM_PARTS", team_parts)
    previous = parallel.set_workers(3)
    real_empty, real_empty_like = np.empty, np.empty_like

    def filled(out):
        out.reshape(-1).view(np.uint8).fill(0xA5)
        return out
    v, f = vp.icosphere(6, 0.5)
    v2, f2 = vp.icosphere(5, 0.2)
    two = (np.vstack([v * 0.6 - [0.2, 0, 0], v2 + [0.35, 0.1, 0.0]]), np.vstack([f, f2 + len(v)]))
    small, small_f = vp.icosphere(1, 0.04)
    many = (np.vstack([small + c for c in np.random.default_rng(1).uniform(-0.4, 0.4, (200, 3))]),
            np.vstack([small_f + k * len(small) for k in range(200)]))
    lat = vp.Lattice((6, 5, 4), ("BSPLINE", "CARDINAL", "LINEAR"), bounds=((-0.6,) * 3, (0.6,) * 3))
    try:
        for verts, tris, topology in ((v, f, None), (*two, None), (*many, None),
                                      (v * 1.1, f, vp.Topology(f, len(v)))):
            compiled.unload()
            ref = vp.bind(lat, verts, tris, dtype=np.float32)
            assert compiled.load(teams=True), compiled.why()
            monkeypatch.setattr(np, "empty", lambda *a, **k: filled(real_empty(*a, **k)))
            monkeypatch.setattr(np, "empty_like", lambda *a, **k: filled(real_empty_like(*a, **k)))
            out = vp.bind(lat, verts, tris, dtype=np.float32, topology=topology)
            monkeypatch.setattr(np, "empty", real_empty)
            monkeypatch.setattr(np, "empty_like", real_empty_like)
            assert out.x0.shape[1] > out.n_verts        # (there are padding slots)
            assert len(out.vertex_parts) == (3 if out.n_verts > 30000 else 1)
            for name, a in _arrays(ref).items():
                np.testing.assert_array_equal(_arrays(out)[name], a, err_msg=name)
    finally:
        parallel.set_workers(previous)


@pytest.mark.parametrize("team_parts", [99, 3])
@pytest.mark.parametrize("threads", [1, 2, 5])
def test_one_islands_volume_sums_are_numpys_in_chunks_on_any_number_of_threads(kernels, threads, team_parts,
                                                                                monkeypatch):
    # One island: the compiled bind adds the faces' volume terms in chunks as it makes them,
    # without writing them (`layout_kernels.face_volume_sums`). On a mesh of many chunks, the last
    # one short, its rest volume and the sum of the terms' sizes are NumPy's bit for bit on any
    # number of threads, and they are the sums: within rounding of an exact sum of the terms.
    # An open mesh (80,921 faces) is measured about the lattice's centre, which lies outside it
    # here: the terms have both signs.
    v, f = vp.icosphere(6, 0.45)
    f = f[:-999]
    assert len(f) % vp.volume.FACE_CHUNK and len(f) > 10 * vp.volume.FACE_CHUNK
    lat = vp.Lattice((6, 6, 6), "BSPLINE")
    topology = vp.Topology(f, len(v))
    moved = (v * [1.1, 0.9, 1.0] + [0.6, -0.01, 0.03]).astype(np.float32)
    monkeypatch.setattr(compiled, "TEAM_PARTS", team_parts)
    previous = parallel.set_workers(threads)
    try:
        ref, out = _bind_both(lat, moved, f, dtype=np.float32, topology=topology)
    finally:
        parallel.set_workers(previous)
    assert out.n_islands == 1 and len(out.vertex_parts) == threads
    for name, a in _arrays(ref).items():
        np.testing.assert_array_equal(_arrays(out)[name], a, err_msg=name)
    rel = moved.astype(np.float64) - out.island_origin[0]
    terms = vp.volume.face_volumes(np.ascontiguousarray(rel.T), topology.tris_t)
    assert (terms < 0).sum() > 1000 and (terms > 0).sum() > 1000
    assert abs(out.rest_volume - math.fsum(terms)) <= 1e-13 * math.fsum(np.abs(terms))
    assert out.rest_volume_noise[0] == pytest.approx(4 * np.finfo(np.float32).eps * math.fsum(np.abs(terms)),
                                                     rel=1e-12)


@pytest.mark.parametrize("team_parts", [99, 3])
@pytest.mark.parametrize("threads", [1, 3, 5])
def test_a_re_embedding_on_any_number_of_threads_is_numpys_bit_for_bit(kernels, threads, team_parts, monkeypatch):
    # Every pass of a compiled re-embedding is split over the worker threads (the positions and
    # their bounds, the cells, the counting sort, the slots, what they hold, the faces' terms);
    # what the parts give is combined so that the binding is NumPy's on any number of threads.
    # Three islands, one partly outside the lattice, big enough for five parts.
    v, f = vp.icosphere(6, 0.5)
    v2, f2 = vp.icosphere(5, 0.2)
    verts = np.vstack([v, v2 + [0.35, 0.1, 0.0], v2 * 1.5 - [0.3, 0.2, 0.6]])
    tris = np.vstack([f, f2 + len(v), f2 + len(v) + len(v2)])
    lat = vp.Lattice((5, 6, 4), ("CATMULL_ROM", "LINEAR", "BSPLINE"))
    topology = vp.Topology(tris, len(verts))
    moved = (verts * 1.05 + [0.02, -0.01, 0.03]).astype(np.float32)
    # On the Python worker threads, and (team_parts 3) as one call of each pass on numba's threads.
    monkeypatch.setattr(compiled, "TEAM_PARTS", team_parts)
    previous = parallel.set_workers(threads)
    try:
        ref, out = _bind_both(lat, moved, topology.tris, dtype=np.float32, topology=topology)
    finally:
        parallel.set_workers(previous)
    assert len(out.vertex_parts) == threads and out.n_islands == 3 and out.n_outside > 0
    for name, a in _arrays(ref).items():
        np.testing.assert_array_equal(_arrays(out)[name], a, err_msg=name)


@pytest.mark.parametrize("many", [False, True])
@pytest.mark.parametrize("team_parts", [99, 3])
@pytest.mark.parametrize("threads", [1, 2, 3, 5])
def test_a_binds_faces_around_every_slot_are_its_vertexs_renumbered_on_any_number_of_threads(
        kernels, threads, team_parts, many, monkeypatch):
    # A compiled bind renumbers the faces around every vertex into the slots' order in the hand-over
    # that writes the slots' values and sums the faces' terms, cut by cost (`layout.mixed_parts`).
    # Checked in NumPy from the topology's faces around every vertex: every slot holds its
    # vertex's entries as slots, in order, and whether they are a ring; padding slots hold none.
    # Three islands and an open one (open fans keep their faces as pairs), where the counting sort
    # places the slots; or 10,240 small closed islands, more keys than the counting sort takes
    # (NumPy sorts, the slots pass places them).
    lat = vp.Lattice((5, 6, 4), ("CATMULL_ROM", "LINEAR", "BSPLINE"))
    if many:
        corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) * 0.02
        at = np.random.default_rng(4).uniform(-0.45, 0.43, (10240, 1, 3))
        verts = (corners[None] + at).reshape(-1, 3)
        tris = (np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])[None] + 4 * np.arange(10240)[:, None, None])
        tris = tris.reshape(-1, 3)
    else:
        v, f = vp.icosphere(6, 0.5)
        v2, f2 = vp.icosphere(5, 0.2)
        verts = np.vstack([v, v2 + [0.35, 0.1, 0.0], v2 * 1.5 - [0.3, 0.2, 0.6], v2 * 0.5])
        tris = np.vstack([f, f2 + len(v), f2 + len(v) + len(v2), (f2 + len(v) + 2 * len(v2))[:-300]])
    topology = vp.Topology(tris, len(verts))
    moved = (verts * 1.05 + [0.02, -0.01, 0.03]).astype(np.float32)
    monkeypatch.setattr(compiled, "TEAM_PARTS", team_parts)
    previous = parallel.set_workers(threads)
    try:
        b = vp.bind(lat, moved, topology.tris, dtype=np.float32, topology=topology)
    finally:
        parallel.set_workers(previous)
    assert len(b.vertex_parts) == threads
    n_keys = b.n_islands * np.prod(np.array(lat.shape) + 6)
    assert (n_keys > 4 * len(verts)) == many            # (the path asked for)
    start, entries, ring = b.incidence
    rstart, entries_v, ring_v = compiled.vertex_rings(topology)
    assert 0 < ring_v.sum() < len(ring_v) or many       # (rings, and pairs at the open fans)
    n_slots = b.x0.shape[1]
    count = np.zeros(n_slots, np.int64)
    count[b.slot] = np.diff(rstart)
    assert start[0] == 0 and np.array_equal(np.diff(start), count) and n_slots > len(verts)
    where = np.repeat(start[b.slot] - rstart[:-1], np.diff(rstart)) + np.arange(rstart[-1])
    np.testing.assert_array_equal(entries[where], b.slot[entries_v[:rstart[-1]]])
    assert len(entries) == rstart[-1]
    want = np.zeros(n_slots, np.int8)
    want[b.slot] = ring_v
    np.testing.assert_array_equal(ring, want)


@pytest.mark.parametrize("n_parts", [1, 2, 3, 7, 16])
def test_mixed_parts_cover_every_task_once_in_order(n_parts):
    # Passes laid end to end and cut by cost: every unit of every task in exactly one part, each
    # part's pieces in the tasks' order, and the parts' costs even within one unit.
    from vpffd_addon import layout
    rng = np.random.default_rng(n_parts)
    for _ in range(50):
        tasks = [(name, int(rng.integers(0, 5000)), float(rng.uniform(0.1, 50.0))) for name in ("a", "b", "c")]
        if rng.random() < 0.2:      # (a task that costs nothing, as the faces around no face)
            i = int(rng.integers(0, 3))
            tasks[i] = (tasks[i][0], tasks[i][1], 0.0)
        parts = layout.mixed_parts(tasks, n_parts)
        assert len(parts) == n_parts
        for name, n, w in tasks:
            got = [(a, z) for part in parts for (m, a, z) in part if m == name]
            assert all(z > a for a, z in got)
            covered = np.concatenate([np.arange(a, z) for a, z in got]) if got else np.zeros(0, int)
            np.testing.assert_array_equal(covered, np.arange(n))
        order = {"a": 0, "b": 1, "c": 2}
        for part in parts:
            assert [order[m] for m, _, _ in part] == sorted(order[m] for m, _, _ in part)
        cost = [sum((z - a) * dict((m, w) for m, _, w in tasks)[m] for m, a, z in part) for part in parts]
        total = sum(n * w for _, n, w in tasks)
        assert max(cost) - total / n_parts <= 3 * max(w for _, _, w in tasks)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_solve_on_any_number_of_threads_is_the_same_bit_for_bit(kernels, dtype, monkeypatch):
    # From compiled.TEAM_PARTS parts on (here 4), every pass runs as one call on numba's own
    # threads (a "team"); below, on the Python worker threads. Both make the same call per part and the
    # blocks are added in order, so a solve (the closed form along XYZ; islands: the joint steps
    # in float64, over the three gradients at once) and its frame's passes (the affine maps, the
    # float32 offsets) give the same numbers on 1, 2, 4 and 5 parts, whatever this machine's cores.
    v, f = vp.icosphere(6, 0.45)
    v2, f2 = vp.icosphere(4, 0.12)
    verts = np.vstack([v, v2 + [0.25, 0.2, 0.1]])
    tris = np.vstack([f, f2 + len(v)])
    lat = vp.Lattice((6, 5, 6), ("BSPLINE", "CATMULL_ROM", "BSPLINE"), bounds=((-0.5,) * 3, (0.5,) * 3))
    P = lat.rest_points * [1.0, 1.1, 0.6] + np.random.default_rng(4).normal(0, 0.01, lat.rest_points.shape)
    mat = np.array([[0.9, 0.1, 0.0, 0.2], [-0.1, 1.1, 0.05, 0.0], [0.0, 0.2, 0.8, -0.3], [0.0, 0.0, 0.0, 1.0]])
    topology = vp.Topology(tris, len(verts))
    assert compiled.kernels().get("forward_team") is not None, "numba's parallel mode is not in use"
    monkeypatch.setattr(compiled, "TEAM_PARTS", 4)      # (on any machine, 4 and 5 parts as teams)
    results = {}
    previous = parallel.set_workers(1)
    try:
        for n in (1, 2, 4, 5):
            parallel.set_workers(n)
            b = vp.bind(lat, verts, tris, dtype=dtype, topology=topology)
            assert len(b.block_parts) == n and len(b.vertex_parts) == n
            one = b.solve(P, axes="XYZ")
            many = b.solve(P, axes="XYZ", islands=True)
            mapped = frame._affine(one.verts.astype(np.float32), mat)
            offsets = offsets_.float32_offsets(mapped, verts.astype(np.float32), None)
            # the same pass making the output from the solve's vertices (mapped, some kept still)
            fused = offsets_.float32_offsets(one.verts, verts.astype(np.float32), None, matrix=mat,
                                             still=np.arange(len(verts)) % 7 == 0)
            results[n] = [one.verts, one.points, many.verts, many.points, mapped, offsets[0], offsets[1],
                          fused[0], fused[1]]
    finally:
        parallel.set_workers(previous)
    for n in (2, 4, 5):
        for a, ref in zip(results[n], results[1]):
            np.testing.assert_array_equal(a, ref, err_msg=f"{n} parts")
    assert cpu_while_asleep(0.3) < 20.0         # numba's idle threads wait without spinning


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_two_passes_in_one_hand_over_are_the_two_passes_bit_for_bit(kernels, dtype, monkeypatch):
    # On the Python threads a forward pass and the pass after it run in one hand-over per part,
    # with a barrier between them (`CompiledSteps._refresh_then`). However the parts meet there,
    # a solve and its islands' joint steps must be the two passes' bit for bit: when every part
    # waits long enough; when they wait one look only (the parts that arrive first skip their
    # second pass and the caller runs it); when the caller stops looking for the parts done at
    # once (it then sleeps on the workers); and with the fused passes switched off.
    monkeypatch.setattr(parallel, "CORES", max(2, parallel.CORES))   # (2 parts even on 1 core)
    monkeypatch.setattr(parallel, "MIN_VERTS_PER_PART", 1024)      # (and on a small mesh)
    monkeypatch.setattr(compiled, "FUSED_MISSES", 10 ** 9)         # (fused however often they fall back)
    calls = {}
    K = kernels.kernels()
    for name in [k for k in K if k.startswith("forward_then_")]:
        def counted(*args, _fn=K[name], _name=name):
            calls[_name] = calls.get(_name, 0) + 1
            return _fn(*args)
        monkeypatch.setitem(K, name, counted)
    previous = parallel.set_workers(2)
    spins = dict(compiled._state["spins"])
    try:
        b, P = _problem(dtype, n_sub=5, islands=True)
        assert len(b.block_parts) == len(b.vertex_parts) == 2
        results = {}
        for way, set_spins in (("off", None), ("wait", spins), ("skip", {**spins, "barrier": 1}),
                               ("sleep", {**spins, "done": 1}), ("neither", {"barrier": 1, "done": 1})):
            monkeypatch.setitem(compiled._state, "spins", set_spins)
            monkeypatch.setattr(compiled, "_fused", {"misses": 0, "rest": 0})   # (no rest left from the way before)
            before = sum(calls.values())
            one, many = b.solve(P, axes="XYZ"), b.solve(P, axes="XYZ", islands=True)
            assert (sum(calls.values()) > before) == (way != "off"), way
            results[way] = [one.verts, one.points, many.verts, many.points, np.asarray(many.island_volumes)]
    finally:
        parallel.set_workers(previous)
    assert set(calls) == {"forward_then_gradient_runs", "forward_then_gradient_runs3",
                          "forward_then_to_verts"}, calls
    for way in ("wait", "skip", "sleep", "neither"):
        for a, ref in zip(results[way], results["off"]):
            np.testing.assert_array_equal(a, ref, err_msg=way)


def test_fused_passes_that_keep_running_out_of_spins_rest(kernels, monkeypatch):
    # Where the fused passes keep falling back (threads without cores of their own), spinning only
    # takes time from them: after `FUSED_MISSES` such passes in a row, the next `FUSED_REST` run one
    # hand-over per pass. Every fused pass is made a miss here by a caller that reports having
    # had to sleep on the workers; the results stay the same bit for bit.
    monkeypatch.setattr(parallel, "CORES", max(2, parallel.CORES))
    monkeypatch.setattr(parallel, "MIN_VERTS_PER_PART", 1024)
    monkeypatch.setattr(compiled, "_fused", {"misses": 0, "rest": 0})
    previous = parallel.set_workers(2)
    try:
        b, P = _problem(np.float32, n_sub=5)
    finally:
        parallel.set_workers(previous)
    want = b.solve(P, axes="XYZ").verts
    monkeypatch.setattr(compiled, "_fused", {"misses": 0, "rest": 0})
    counted, calls = parallel.run_counted, []

    def slept(*args):
        calls.append(1)
        counted(*args)
        return False
    monkeypatch.setattr(parallel, "run_counted", slept)
    for _ in range(3):      # (four fused passes a solve would be twelve)
        np.testing.assert_array_equal(b.solve(P, axes="XYZ").verts, want)
    assert len(calls) == compiled.FUSED_MISSES
    assert compiled._fused["rest"] == compiled.FUSED_REST - (12 - compiled.FUSED_MISSES)


def test_the_spin_calibration_stays_bounded_on_a_coarse_clock(kernels, monkeypatch):
    # The waits of the fused passes are counted in looks, calibrated once against the clock: a
    # clock that ticks once a millisecond (some virtual machines') must not read a loop as
    # instantaneous and turn a 2 ms wait into minutes.
    from vpffd_addon import atomics
    real = atomics.time.perf_counter
    monkeypatch.setattr(atomics.time, "perf_counter", lambda: float(np.floor(real() * 1e3)) / 1e3)
    got = atomics.spins_for(kernels.kernels()["wait_count"], {"barrier": 2000, "done": 1})
    assert 1000 <= got["barrier"] <= atomics.MOST_LOOKS_PER_US * 2000
    assert got["done"] == 1000 or got["done"] <= atomics.MOST_LOOKS_PER_US


def test_a_containers_cpu_quota_caps_the_cores():
    files = {"/sys/fs/cgroup/cpu.max": "200000 100000\n"}
    assert parallel.cpu_quota(files.get) == 2.0
    assert parallel.cpu_quota({"/sys/fs/cgroup/cpu.max": "max 100000\n"}.get) is None
    v1 = {"/sys/fs/cgroup/cpu/cpu.cfs_quota_us": "150000\n", "/sys/fs/cgroup/cpu/cpu.cfs_period_us": "100000\n"}
    assert parallel.cpu_quota(v1.get) == 1.5
    assert parallel.cpu_quota({**v1, "/sys/fs/cgroup/cpu/cpu.cfs_quota_us": "-1\n"}.get) is None
    assert parallel.cpu_quota({}.get) is None
    assert parallel.cpu_quota({"/sys/fs/cgroup/cpu.max": "garbage"}.get) is None
    quota = parallel.cpu_quota()
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = os.cpu_count()
    assert parallel.cores() == (affinity if quota is None else max(1, min(affinity, int(np.ceil(quota)))))


def test_solves_in_two_threads_at_once_share_the_workers_and_finish(kernels, monkeypatch):
    # Two solves handing their parts to the same worker at once (as two objects evaluated in
    # parallel by Blender): each part that waits at its barrier for a worker still busy with the
    # other solve gives up after its spins, so both finish, with the results of one at a time.
    import threading
    monkeypatch.setattr(parallel, "CORES", max(2, parallel.CORES))
    monkeypatch.setattr(parallel, "MIN_VERTS_PER_PART", 1024)
    previous = parallel.set_workers(2)
    try:
        problems = [_problem(np.float32, n_sub=5, seed=s) for s in (5, 6)]
    finally:
        parallel.set_workers(previous)
    alone = [b.solve(P, axes="XYZ").verts for b, P in problems]
    got, errors = [[None] * 8 for _ in problems], []

    def solve(i):
        try:
            b, P = problems[i]
            for r in range(8):
                got[i][r] = b.solve(P, axes="XYZ").verts
        except Exception as exc:        # (reported below: a thread's failure must fail the test)
            errors.append(exc)
    threads = [threading.Thread(target=solve, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not any(t.is_alive() for t in threads), "two solves at once did not finish"
    assert not errors, errors
    for i, want in enumerate(alone):
        for verts in got[i]:
            np.testing.assert_array_equal(verts, want)


def test_bezier_and_one_point_axes_bind_with_numpy(kernels):
    assert compiled.bind_kernels(vp.Lattice((4, 4, 4), "BEZIER")) is None
    assert compiled.bind_kernels(vp.Lattice((4, 1, 4))) is None
    assert compiled.bind_kernels(vp.Lattice((4, 2, 4))) is not None


def test_a_numpy_outside_the_supported_range_keeps_numpy_and_says_why():
    code = ("import numpy as np\n"
            "np.__version__ = '2.6.0'\n"                    # as a newer NumPy another extension brought
            "from vpffd_addon import backends, compiled\n"
            "print(compiled.load(), compiled.why())\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                          env=dict(os.environ, PYTHONPATH=ROOT))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == ("False NumPy 2.6.0 is outside the range the compiled kernels "
                                   "support (1.24 to 2.5)"), proc.stdout


def test_many_small_islands_keep_their_volumes_in_float32(kernels):
    # Squashed to half height: in float32 the coordinates of a body 1% of the lattice's size round
    # at ~1e-5 of its volume, so the joint island steps run in float64 (`CompiledSteps.in_float64`)
    # and every island's volume, measured from the float32 coordinates Blender would store, is
    # kept to 1e-5.
    verts, tris = M.small_bodies()
    lat = vp.Lattice((5, 5, 5), "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    P = lat.rest_points * [1.0, 1.0, 0.5] + np.random.default_rng(1).normal(0, 0.01, lat.rest_points.shape)
    b = vp.bind(lat, verts, tris, dtype=np.float32)
    assert b.n_islands == 44
    sol = b.solve(P, axes="XYZ", islands=True)
    assert not sol.warnings, sol.warnings
    topo = vp.Topology(tris, len(verts))

    def volumes(v):
        stored = np.ascontiguousarray(v.astype(np.float32).astype(np.float64).T)
        return np.bincount(topo.face_island, vp.volume.face_volumes(stored, topo.tris_t), topo.n_islands)
    rest, plain, out = volumes(verts), volumes(b.deform(P)), volumes(sol.verts)
    assert np.abs(plain / rest - 1).max() > 0.3                 # the squash changes them a lot
    assert np.abs(out / rest - 1).max() <= 1e-5, np.abs(out / rest - 1).max()


def test_a_compiled_solve_makes_none_of_numpys_stored_weights(kernels):
    # What a mesh moving through the lattice pays every frame: a re-embedding and a solve read the
    # cells and faces around the slots only (NumPy's weights and sorted faces would cost more than
    # the solve).
    b, P = _problem(np.float32, islands=True)
    moved = vp.bind(b.lattice, b.source[0] + 0.01, b.topology.tris, dtype=np.float32, topology=b.topology)
    for options in ({"axes": "XYZ"}, {"axes": "XY", "islands": True}, {"axes": "", "preserve_volume": False}):
        moved.solve(P, **options)
    assert not {"wuv", "ww", "corner_parts"} & set(vars(moved))
    assert moved.weight_shape == moved.ww.shape[:2] + (moved.wuv.shape[1],)     # (made now)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_pin_rows_come_from_the_cell_coordinates_and_equal_the_forward_product(kernels, dtype):
    # A pin's row of S B, from the slot's cell coordinates (a compiled bind makes no stored
    # weights for it), against NumPy's forward product with the stored weights at those slots.
    b, P = _problem(dtype)
    D = P - b.lattice.rest_points
    slots = b.slot[np.array([0, 7, 100, len(b.slot) - 1])]
    rows = b.rows(slots)
    assert not {"wuv", "ww"} & set(vars(b))
    rel = 1e-6 if dtype == np.float32 else 1e-12
    for c in range(3):
        want = b.forward(D[:, c])[slots]                      # (makes the stored weights now)
        assert np.abs(rows @ D[:, c] - want).max() <= rel * np.abs(D).max()


def test_what_is_made_on_first_use_is_made_from_the_positions_as_bound(kernels):
    # The caller's arrays may change after the bind: the stored weights made later are still
    # those of the positions and weights that were bound.
    b, _ = _problem(np.float32)
    verts, tris = b.source[0].copy(), b.topology.tris
    weights = np.linspace(0.2, 1.0, len(verts))
    ref = vp.bind(b.lattice, verts, tris, dtype=np.float32, influence=weights, use_compiled=False)
    out = vp.bind(b.lattice, verts, tris, dtype=np.float32, influence=weights)
    verts += 0.05
    weights[:] = 1.0
    np.testing.assert_array_equal(out.wuv, ref.wuv)
    np.testing.assert_array_equal(out.ww, ref.ww)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("islands", [False, True])
def test_the_three_axis_pass_equals_three_single_axis_passes(kernels, dtype, islands):
    # The joint steps over islands linearise every axis at the same coordinates and take the
    # three gradients from one pass over the faces: each must be what the single-axis pass gives
    # (the gradient, (S B)^T g per volume row, x0_a . g and sum |s g|).
    b, P = _problem(dtype, islands=islands)
    D = P - b.lattice.rest_points
    one, three = kernels.CompiledSteps(b), kernels.CompiledSteps(b)
    rows, k = (b.slot_island, b.n_islands) if islands else (None, 1)
    fused = three.axis_gradients(D)
    one.refresh((0, 1, 2), D)
    assert np.array_equal(one.X, three.X)
    for a in range(3):
        ref, got = one.axis_gradient(a, D), fused[a]
        scale = np.abs(ref.g).max()
        assert np.abs(got.g - ref.g).max() <= 1e-6 * scale
        assert np.allclose(three.transpose(got, rows, k), one.transpose(ref, rows, k), rtol=0,
                           atol=1e-6 * np.abs(one.transpose(ref, rows, k)).max())
        for name in ("x0_dot", "flux"):
            want, have = getattr(one, name)(a, ref, rows, k) if name == "x0_dot" else one.flux(ref, rows, k), \
                getattr(three, name)(a, got, rows, k) if name == "x0_dot" else three.flux(got, rows, k)
            assert np.allclose(have, want, rtol=1e-6, atol=0)


def test_the_least_norm_step_equals_lapacks(kernels):
    # The joint steps' least-norm move, from a compiled QR and a k x k LAPACK solve, against
    # LAPACK's own least squares on the whole k x n matrix: full rank, nearly parallel rows (small
    # bodies sharing cells), exactly repeated rows (cut by rcond), and more rows than unknowns
    # (left to LAPACK: min_norm says None).
    rng = np.random.default_rng(11)
    cases = [rng.standard_normal((k, n)) for k, n in ((1, 7), (6, 6), (40, 300))]
    near = rng.standard_normal((5, 60))
    near[3] = near[2] + 1e-8 * rng.standard_normal(60)
    twin = near.copy()
    twin[4] = twin[1]
    for i, A in enumerate(cases + [near, twin]):
        r = rng.standard_normal(len(A))
        for rcond in (1e-10, 1e-5):
            ref = np.linalg.lstsq(A, r, rcond=rcond)[0]
            got = kernels.min_norm(A, r, rcond)
            if i < len(cases):      # well conditioned: the same numbers
                assert np.abs(got - ref).max() <= 1e-9 * max(1.0, np.abs(ref).max())
            # Any conditioning: as close to the rows' targets (to the rounding of A u) and no
            # longer than LAPACK's.
            rounding = 1e-14 * np.linalg.norm(A) * np.linalg.norm(ref)
            assert np.linalg.norm(A @ got - r) <= 1.01 * np.linalg.norm(A @ ref - r) + rounding + 1e-12
            assert np.linalg.norm(got) <= (1 + 1e-6) * np.linalg.norm(ref) + 1e-12
    assert kernels.min_norm(rng.standard_normal((8, 5)), np.ones(8), 1e-10) is None


def test_a_solve_leaves_no_blas_threads_spinning(kernels):
    # OpenBLAS runs a k x n least-squares problem on its worker threads, which then spin for about
    # a tenth of a second: in Blender they would take the cores from the next frame and from
    # Blender's own evaluation (docs/performance.md, "Keep BLAS out of the frame"). A solve
    # with islands and pins (the joint steps) must leave the process idle once it returns:
    # measured as CPU time, not wall time, so a busy machine can only hide a spin, never fake one.
    verts, tris = M.small_bodies()
    lat = vp.Lattice((6, 6, 6), "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    P = lat.rest_points * [1.0, 1.0, 0.5]
    b = vp.bind(lat, verts, tris, dtype=np.float32)
    cpu_while_asleep(0.5)      # what earlier tests left spinning dies down
    for pins in ((), [(0, verts[0] * [1, 1, 0.5]), (700, verts[700] * [1, 1, 0.5])]):
        sol = b.solve(P, axes="XYZ", islands=True, pins=pins)
        assert not sol.warnings, sol.warnings
        assert cpu_while_asleep() < 20.0


def test_the_compiled_topology_is_numpys(kernels):
    # Closedness, islands and their order by the compiled kernels (a first bind) against NumPy's:
    # closed islands and a vertex no face uses; a face turned; a face missing (open); a face
    # doubled; a degenerate face; two bodies sharing a vertex (non-manifold but closed).
    rng = np.random.default_rng(2)
    v, f = vp.icosphere(3, 0.5)
    v2, f2 = vp.icosphere(1, 0.2)
    base = np.vstack([f, f2 + len(v), f2 + len(v) + len(v2)])
    n = len(v) + 2 * len(v2) + 1
    turned = base.copy()
    turned[5] = turned[5, ::-1]
    shared = np.vstack([f, np.where(f2 == 0, 0, f2 + len(v))])
    cases = [(base, n), (turned, n), (base[1:], n), (np.vstack([base, base[:1]]), n),
             (np.vstack([base, [[3, 3, 9]]]), n), (shared, len(v) + len(v2)),
             (base[rng.permutation(len(base))], n)]
    K = kernels.kernels()
    for tris, nv in cases:
        ref, out = vp.Topology(tris, nv), vp.mesh.Topology(tris, nv, K)
        assert out.is_closed == ref.is_closed and out.n_islands == ref.n_islands
        for name in ("labels", "face_island", "island_order", "island_start", "tris_t"):
            np.testing.assert_array_equal(getattr(out, name), getattr(ref, name), err_msg=name)
    assert [vp.Topology(t, nv).is_closed for t, nv in cases] == [True, False, False, False, True, True, True]


@pytest.mark.parametrize("case", ["closed", "open", "doubled", "degenerate", "shared vertex", "shuffled", "cone"])
def test_the_compiled_gradient_around_rings_and_pairs_is_numpys(kernels, case):
    # The gradient passes sum around a ring of neighbours where a vertex's faces close one fan and
    # face by face elsewhere (`solve_kernels.vertex_rings`): open fans, a face doubled, a
    # degenerate face, two bodies sharing a vertex, the faces in any order, a cone whose apex has
    # more faces than a ring takes; every axis and the three at once against NumPy's face-wise
    # gradient, in float64.
    rng = np.random.default_rng(5)
    v, f = vp.icosphere(3, 0.5)
    v2, f2 = vp.icosphere(1, 0.2)
    verts = np.vstack([v, v2 + 0.25, v2 - 0.25, [[0.1, 0.1, 0.1]]])
    base = np.vstack([f, f2 + len(v), f2 + len(v) + len(v2)])
    tris = {"closed": base, "open": base[7:], "doubled": np.vstack([base, base[:1]]),
            "degenerate": np.vstack([base, [[3, 3, 9]]]),
            "shared vertex": np.vstack([f, np.where(f2 == 0, 0, f2 + len(v))]),
            "shuffled": base[rng.permutation(len(base))]}.get(case)
    if case == "shared vertex":
        verts = np.vstack([v, v2 + v[0] * 1.4])
    if case == "cone":
        m = 100                                 # apex 0, base centre 1, rim 2 .. m + 1
        a = 2 * np.pi * np.arange(m) / m
        verts = np.vstack([[0, 0, 0.5], [0, 0, -0.3], np.stack([0.4 * np.cos(a), 0.4 * np.sin(a), -0.3 + 0 * a], 1)])
        rim, nxt = 2 + np.arange(m), 2 + (np.arange(m) + 1) % m
        tris = np.vstack([np.stack([0 * rim, rim, nxt], 1), np.stack([1 + 0 * rim, nxt, rim], 1)])
    lat = vp.Lattice((4, 5, 4), ("BSPLINE", "CARDINAL", "LINEAR"), bounds=((-0.8,) * 3, (0.8,) * 3))
    b = vp.bind(lat, verts, tris)
    rings = compiled.incidence(b)[2]
    assert 0 < int(rings.sum()) <= b.n_verts
    if case == "cone":
        assert rings[b.slot[0]] == 0 and rings[b.slot[2]] == 1 and int(rings.sum()) == b.n_verts - 2
    if case not in ("closed", "shuffled"):
        assert int(rings.sum()) < len(np.unique(tris))      # (some fans are summed face by face)
    D = lat.rest_points * [1.0, 1.1, 0.8] + rng.normal(0, 0.03, lat.rest_points.shape) - lat.rest_points
    ref, fast = NumpySteps(b), kernels.CompiledSteps(b)
    ref.refresh((0, 1, 2), D)
    fast.refresh((0, 1, 2), D)
    fast.X[:] = ref.X
    tol = 1e-14 * 6 * np.abs(ref.X).max() ** 2
    three = fast.axis_gradients(D)
    for axis in range(3):
        want = ref.axis_gradient(axis, D)
        assert np.abs(fast.axis_gradient(axis, D).g - want).max() <= tol
        assert np.abs(three[axis].g - want).max() <= tol


@pytest.mark.parametrize("correct", [False, True])
def test_a_frame_names_the_kernels_that_solved_it_and_backend_numpy_keeps_numpy(kernels, correct):
    """The pipeline's own solves (no solver of the caller's; the plain deformation) run where the
    Backend setting says: NumPy alone for NUMPY (the reference path), the compiled kernels for the
    others (the GPU needs a solver of its own); the result says which (`FrameResult.backend`)."""
    lat = vp.Lattice((4, 4, 4), bounds=((-1,) * 3, (1,) * 3))
    v, t = vp.icosphere(3, 0.7)
    P = lat.rest_points * [1.0, 1.0, 0.7]
    ran = {}
    for backend in ("NUMPY", "CPU", "AUTO", "GPU"):
        inputs = vp.FrameInputs(positions=v, tris=t, lattice=lat, points=P, matrix=np.eye(4),
                                correct=correct, axes="XYZ" if correct else "", backend=backend)
        result = vp.Pipeline().evaluate(inputs)
        ran[backend] = result.backend
        assert (result.solution is not None) == correct
    assert ran == {"NUMPY": "NUMPY", "CPU": "COMPILED", "AUTO": "COMPILED", "GPU": "COMPILED"}


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_compiled_offsets_are_numpys_bit_for_bit(kernels, dtype):
    # What a frame writes (`offsets.float32_offsets`): the compiled pass against NumPy's, on a
    # mesh big enough for the worker threads, unchanged and changed against what was written,
    # and the refusals (a non-finite offset, one beyond float32), with the same words.
    from vpffd_addon import offsets as O
    rng = np.random.default_rng(7)
    inputs = rng.normal(0, 3, (50_000, 3)).astype(dtype)
    positions = inputs.astype(np.float64) * 1.01 + rng.normal(0, 1e-3, inputs.shape)
    ref = O._numpy(positions, inputs, None)
    got = O.float32_offsets(positions, inputs)
    for a, b in zip(ref[:2], got[:2]):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(b, a)
    assert got[2] is True and got[3] == ref[3] == float(np.abs(ref[0]).max())
    assert O.float32_offsets(positions, inputs, ref[0].copy())[2] is False
    nudged = ref[0].copy()
    nudged[-1, 2] = np.nextafter(nudged[-1, 2], np.float32(np.inf))
    assert O.float32_offsets(positions, inputs, nudged)[2] is True
    assert O._numpy(positions, inputs, nudged)[2] is True
    for bad, words in ((np.nan, "non-finite offsets"), (1e39, "exceed what Blender can store")):
        broken = positions.copy()
        broken[123, 1] = bad
        for fn in (O.float32_offsets, O._numpy):
            with pytest.raises(ValueError, match=words):
                fn(broken, inputs, None)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_offsets_made_from_the_solves_vertices_are_numpys_bit_for_bit(kernels, dtype):
    # A frame writes its offsets straight from the solve's vertices in lattice space: the map back
    # to the object's space, the positions of no influence kept exactly at their input, and the
    # float32 offsets, in one pass. The same numbers as mapping the vertices with NumPy's
    # elementwise product, setting the still ones back, and NumPy's offsets of the result.
    from vpffd_addon import offsets as O
    rng = np.random.default_rng(11)
    inputs = rng.normal(0, 3, (40_000, 3)).astype(dtype)
    mat = np.array([[0.8, 0.3, -0.1, 1.5], [-0.2, 1.3, 0.4, -0.7], [0.05, -0.6, 0.9, 2.25], [0, 0, 0, 1.0]])
    back = np.linalg.inv(mat)
    verts = (inputs.astype(np.float64) @ mat[:3, :3].T + mat[:3, 3]) * 1.02 + rng.normal(0, 1e-3, inputs.shape)
    still = rng.random(len(inputs)) < 0.1
    mapped = np.empty((len(inputs), 3))
    for r in range(3):      # ((p0 m0 + p1 m1) + p2 m2) + m3, as the product is written out
        mapped[:, r] = verts[:, 0] * back[r, 0] + verts[:, 1] * back[r, 1] + verts[:, 2] * back[r, 2] + back[r, 3]
    kept = mapped.copy()
    kept[still] = inputs[still]
    for mask, expect in ((still, kept), (None, mapped)):
        want = O._numpy(expect, inputs, None)
        got = O.float32_offsets(verts, inputs, None, matrix=back, still=mask)
        fallback = O._numpy(O._output(verts, inputs, back, mask), inputs, None)    # without kernels
        for a, b in zip(want[:2] + want[:2], got[:2] + fallback[:2]):
            assert a.dtype == b.dtype and a.shape == b.shape
            np.testing.assert_array_equal(b, a)
        assert got[2] is fallback[2] is True and got[3] == fallback[3] == want[3]
        assert O.float32_offsets(verts, inputs, want[0].copy(), matrix=back, still=mask)[2] is False
    assert got[0][still].any(axis=1).all()          # (without the mask the still ones move)
    kept_offsets, kept_output = O.float32_offsets(verts, inputs, None, matrix=back, still=still)[:2]
    assert not kept_offsets[still].any() and np.array_equal(kept_output[still], inputs[still])
    broken = verts.copy()
    broken[321, 2] = np.inf
    for fn in (O.float32_offsets, lambda *a, **k: O._numpy(O._output(*a[:2], **k), a[1], None)):
        with pytest.raises(ValueError, match="non-finite offsets"):
            fn(broken, inputs, matrix=back, still=still)
    with pytest.raises(ValueError, match="still must be"):
        O.float32_offsets(verts, inputs, None, matrix=back, still=still[:-1])
    with pytest.raises(ValueError, match="matrix must be"):
        O.float32_offsets(verts, inputs, None, matrix=back[:3])


def test_the_frame_passes_benchmark_compares_equal_outputs(kernels):
    # `python -m benchmarks.frame_passes` times a frame's one pass against the three it replaced
    # on the same frames of a Pipeline, and stops when their offsets or outputs differ.
    from benchmarks import frame_passes
    for still, moving in ((False, False), (True, False), (False, True)):
        report = frame_passes.run(subdivisions=3, frames=3, still=still, moving=moving)
        assert report["kernels"] == "compiled" and (report["still"] > 0) == still
        assert set(report["medians_ms"]) == {"evaluate", "solve", "one_pass", "three_passes"}


def _turned(angle, scale, shift):
    """(4, 4) object -> lattice matrix: a turn about z, a scale (the determinant scale**3: below 0
    it mirrors) and a shift."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.eye(4)
    out[:3, :3] = scale * np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out[:3, 3] = shift
    return out


@pytest.mark.parametrize("backend", ["AUTO", "NUMPY"])
@pytest.mark.parametrize("islands", [False, True])
def test_a_closed_meshs_volume_is_measured_as_it_comes_in_and_kept_only_for_the_same_positions(kernels, backend,
                                                                                               islands):
    """A closed mesh's rest volume is measured from the positions as they are handed over (the
    object's space) and scaled by the matrix's determinant into lattice space; the pipeline keeps
    it from one bind to the next only while the positions are the same (the lattice moving over
    the mesh, or the mesh object moving). Every frame must be a fresh pipeline's, bit for bit,
    whatever came before: positions kept, changed, changed back, and the caller's buffer refilled
    in place; and the volume must be det x the positions' own volume (`signed_volume`, an
    independent sum, of the float32 positions made float64)."""
    v, f = _two_spheres()
    lat = vp.Lattice((4, 4, 4), "BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    P = lat.rest_points * [1.0, 1.0, 0.75]
    squashed = (v * (1.0, 1.0, 0.8)).astype(np.float32)
    frames = [(v, _turned(0.2, 1.3, (0.1, 0.0, 0.0))), (v, _turned(0.25, 1.3, (0.15, 0.05, 0.0))),
              (squashed, _turned(0.25, 1.3, (0.15, 0.05, 0.0))), (v, _turned(0.3, 0.9, (0.0, 0.1, 0.0))),
              (squashed, _turned(0.3, 0.9, (0.0, 0.1, 0.0))), (squashed, _turned(0.3, -1.1, (0.0, 0.1, 0.0)))]
    pipeline, buffer = vp.Pipeline(), np.empty((len(v), 3), np.float32)

    def inputs(positions, matrix):
        return vp.FrameInputs(positions=positions, tris=f, lattice=lat, points=P, matrix=matrix, axes="XYZ",
                              islands=islands, dtype=np.float32, backend=backend)
    for positions, matrix in frames + frames[::-1]:
        buffer[:] = positions              # (the same array as the frame before, refilled)
        got = pipeline.evaluate(inputs(buffer, matrix))
        alone = vp.Pipeline().evaluate(inputs(positions.astype(np.float32), matrix))
        assert np.array_equal(got.positions, alone.positions) and np.array_equal(got.points, alone.points)
        assert got.binding.rest_volume == alone.binding.rest_volume
        det = np.linalg.det(matrix[:3, :3])
        p64 = positions.astype(np.float32).astype(np.float64)
        assert got.binding.rest_volume == pytest.approx(det * vp.signed_volume(p64, f), rel=1e-12)
        topo = got.binding.topology
        for k in range(topo.n_islands):
            own = vp.signed_volume(p64, f[topo.face_island == k])
            assert got.binding.rest_island_volumes[k] == pytest.approx(det * own, rel=1e-12)
        assert abs(got.volume / got.input_volume - 1) <= 1e-5
    broken = v.astype(np.float32)
    broken[[0, 5]] = np.nan            # (the first is among the positions an origin is taken from)
    with pytest.raises(ValueError, match=r"non-finite coordinates at 2 vertices \(first: index 0\)"):
        pipeline.evaluate(inputs(broken, frames[0][1]))


def test_a_bind_measured_in_another_space_is_numpys_bit_for_bit(kernels):
    """A bind whose volume is measured from other points (`volume.MeasuredIn`) gives the same
    binding with the compiled kernels as with NumPy, measuring the sums or given them, for one
    island and for several; the sums it measures are `volume.measure_about`'s."""
    for v, f in (vp.icosphere(3, 0.5), _two_spheres()):
        lat = vp.Lattice((5, 4, 4), "BSPLINE", bounds=((-0.9,) * 3, (0.9,) * 3))
        topo = vp.Topology(f, len(v))
        points = v.astype(np.float32)
        matrix = _turned(0.4, 1.1, (0.05, -0.1, 0.2))
        moved = points.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
        det = np.linalg.det(matrix[:3, :3])
        origins = volume.origins_about(points, topo)
        made = {}
        for compiled in (True, False):
            fresh = volume.MeasuredIn(points, det, origins)
            b = vp.bind(lat, moved, f, dtype=np.float32, topology=topo, use_compiled=compiled, measured_in=fresh)
            total, sums = volume.measure_about(points, origins, topo)
            assert fresh.sums[0] == total and np.array_equal(fresh.sums[1], sums)
            given = vp.bind(lat, moved, f, dtype=np.float32, topology=topo, use_compiled=compiled,
                            measured_in=volume.MeasuredIn(points, det, origins, fresh.sums))
            made[compiled] = (b, given)
        for b in (*made[True], made[False][1]):
            a, want = _arrays(b), _arrays(made[False][0])
            assert a.keys() == want.keys()
            for k in want:
                assert np.array_equal(a[k], want[k]), k
            assert b.rest_volume == made[False][0].rest_volume
        with pytest.raises(ValueError, match="closed mesh"):
            vp.bind(lat, moved, f[1:], topology=vp.Topology(f[1:], len(v)),
                    measured_in=volume.MeasuredIn(points, det, origins))
        with pytest.raises(ValueError, match="an origin for every island"):
            vp.bind(lat, moved, f, topology=topo, measured_in=volume.MeasuredIn(points, det, np.zeros((3, 3))))
        with pytest.raises(ValueError, match=r"shape \(V, 3\)"):
            volume.MeasuredIn(points[:, :2], det, origins)
        with pytest.raises(ValueError, match="sums"):
            volume.MeasuredIn(points, det, origins, (1.0, np.zeros((2, len(origins) + 1))))
        as_list = volume.MeasuredIn(points.tolist(), det, origins)
        assert as_list.points.dtype == np.float64 and as_list.points.flags.c_contiguous


def _signatures():
    return {name: set(map(str, k.signatures)) for name, k in compiled._state["kernels"].items()
            if hasattr(k, "signatures")}


@pytest.mark.parametrize("team_parts", [99, 2])
def test_a_frame_compiles_no_kernel_that_loading_did_not(kernels, team_parts, monkeypatch):
    # numba compiles a kernel anew for every new combination of its arguments' types, layouts and
    # writability, and a compile in a frame stalls it by a second or more: the start-up check
    # (`compiled._smoke`) calls every kernel with what a frame hands it. Here frames as Blender
    # makes them (float32 positions and weights in C order, the pipeline's read-only weights, a
    # mesh and a lattice that move, islands, vertices of weight 0, both precisions), on the Python
    # threads and on numba's, and not one kernel may compile a signature it did not have.
    monkeypatch.setattr(compiled, "TEAM_PARTS", team_parts)
    previous = parallel.set_workers(2)
    v, f = vp.icosphere(6, 0.45)
    two = _two_spheres()
    lat = vp.Lattice((6, 6, 6), "BSPLINE", bounds=((-0.6,) * 3, (0.6,) * 3))
    before = _signatures()
    try:
        for verts, tris, islands in ((v, f, False), (two[0] * 1.5, two[1], True)):
            positions = verts.astype(np.float32)
            weights = np.ones(len(verts), np.float32)
            weights[::9] = 0.0
            for dtype in (np.float32, np.float64):
                pipeline = vp.Pipeline()
                for k in range(3):
                    matrix = _turned(0.1 * k, 1.0, (0.01 * k, 0.0, 0.0))
                    moved = positions + np.float32(0.002 * k) if k == 2 else positions
                    P = lat.rest_points * [1.0, 1.0, 0.8 + 0.02 * k]
                    pipeline.evaluate(vp.FrameInputs(positions=moved, tris=tris, lattice=lat, points=P,
                                                     matrix=matrix, weights=weights, axes="XYZ",
                                                     islands=islands, dtype=dtype)).float32_offsets()
    finally:
        parallel.set_workers(previous)
    after = _signatures()
    assert {name: after[name] - before.get(name, set()) for name in after
            if after[name] - before.get(name, set())} == {}
