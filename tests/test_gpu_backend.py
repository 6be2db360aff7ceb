"""GPU path (operators/gpu_backend.py) against the CPU solve, headless.

The GPU backend is initialised by rendering one tiny Workbench frame (Mesa llvmpipe here). Where no
GPU context can be made, the tests that need one are skipped with the reason printed.
"""
import ast
import importlib.util
import os
import subprocess
import sys
import textwrap
import zlib

import numpy as np
import pytest

import vpffd_addon as vp

pytestmark = [pytest.mark.gpu, pytest.mark.blender]

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BACKEND = os.path.join(ROOT, "operators", "gpu_backend.py")


def _load():
    spec = importlib.util.spec_from_file_location("vpffd_gpu_backend", BACKEND)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def gb():
    """The backend module with Blender's GPU initialised (skips, printing why, when it cannot be)."""
    bpy = pytest.importorskip("bpy")
    mod = _load()
    scene = bpy.context.scene
    r = scene.render
    saved = (r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage)
    camera = None
    if scene.camera is None:  # earlier tests may leave an empty scene: a render needs a camera
        camera = bpy.data.objects.new("gpu-init camera", bpy.data.cameras.new("gpu-init camera"))
        scene.collection.objects.link(camera)
        scene.camera = camera
    try:
        r.engine = "BLENDER_WORKBENCH"
        r.resolution_x = r.resolution_y = 4
        r.resolution_percentage = 100
        bpy.ops.render.render()
    except Exception as exc:
        reason = f"no GPU context: the Workbench render failed ({type(exc).__name__}: {exc})"
        print(reason)
        pytest.skip(reason)
    finally:
        r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage = saved
        if camera is not None:
            data = camera.data
            bpy.data.objects.remove(camera)
            bpy.data.cameras.remove(data)
    ok, why = mod.available()
    if not ok:   # a GPU context exists (the render worked): a kernel that fails here is a bug
        pytest.fail(f"the GPU path is unavailable although Blender has a GPU context: {why}")
    print(f"GPU: {why}")
    return mod


def test_gpu_is_never_imported_at_module_level():
    # gpu_backend.py and the modules of the GPU path beside it (gpu_shaders, gpu_device, gpu_solver)
    paths = [os.path.join(ROOT, "operators", fn) for fn in sorted(os.listdir(os.path.join(ROOT, "operators")))
             if fn.startswith("gpu_") and fn.endswith(".py")]
    assert BACKEND in paths and len(paths) > 1
    for path in paths:
        tree = ast.parse(open(path).read())
        for node in tree.body:
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [a.name for a in node.names] + [getattr(node, "module", None) or ""]
                assert not any(n == "gpu" or n.startswith("gpu.") for n in names), (path, ast.dump(node))


def test_unavailable_in_background_before_gpu_init_says_why():
    """A fresh background Blender has no GPU yet: available() says so and never raises; the solver
    refuses with GPUUnavailable (the engine falls back to the CPU with that reason)."""
    pytest.importorskip("bpy")
    code = textwrap.dedent(f"""
        import sys, importlib.util
        sys.path.insert(0, {ROOT!r})
        import bpy, numpy as np, vpffd_addon as vp
        spec = importlib.util.spec_from_file_location("gb", {BACKEND!r})
        gb = importlib.util.module_from_spec(spec); spec.loader.exec_module(gb)
        ok, why = gb.available()
        print("AVAILABLE", ok, why)
        v, f = vp.icosphere(1, 0.4)
        b = vp.bind(vp.Lattice((2, 2, 2)), v, f, dtype=np.float32)
        try:
            gb.GPUSolver(b)
            print("SOLVER built")
        except gb.GPUUnavailable as exc:
            print("SOLVER refused", exc)
        print("CHOOSE", gb.choose("GPU", 100000, dict(axes="XYZ")))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env=dict(os.environ))
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith(("AVAILABLE", "SOLVER", "CHOOSE"))]
    print("\n".join(lines))
    assert out.returncode == 0, out.stderr[-2000:]
    text = "\n".join(lines)
    # Blender's own reason: "... not available in background mode" (4.2-5.2), "... requires the
    # gpu module to be initialized. See gpu.init." (5.3)
    assert "AVAILABLE False" in text and ("background mode" in text or "gpu.init" in text)
    assert "SOLVER refused" in text
    assert "CHOOSE (False," in text


def test_supports_and_choose():
    mod = _load()
    assert mod.supports(dict(axes="XYZ"))[0]
    assert mod.supports(dict(axes="zx"))[0]
    assert mod.supports(dict(axes="XYZ", pins=[(0, (0, 0, 0))], mobility=np.ones(8)))[0]
    for opts in (dict(axes="XYZ", islands=True), dict(directions=np.eye(3)), dict(axes=""),
                 dict(axes="XYZ", preserve_volume=False)):
        ok, why = mod.supports(opts)
        assert not ok and why
    assert mod.choose("CPU", 10 ** 6, dict(axes="XYZ")) == (False, "CPU chosen")
    ok, why = mod.choose("AUTO", 100, dict(axes="XYZ"))
    assert not ok and "a mesh this small" in why
    ok, why = mod.choose("GPU", 10 ** 6, dict(axes="XYZ", islands=True))
    assert not ok and "island" in why
    # A binding made for this frame only (the mesh moves through the lattice): Auto keeps the
    # CPU, since the upload costs more than the GPU saves; an explicit GPU still takes it.
    ok, why = mod.choose("AUTO", 10 ** 6, dict(axes="XYZ"), fresh=True)
    assert not ok and "just bound or moved" in why and "keeps its place" in why
    assert "keeps its place" not in mod.choose("GPU", 10 ** 6, dict(axes="XYZ"), fresh=True)[1]


def test_auto_takes_the_gpu_on_a_hardware_renderer_from_50000_vertices(gb, monkeypatch):
    """The documented claim (docs/user-guide.md, Backend) for Auto's positive branch. Only the cost model's input is faked: the
    renderer's name (this machine renders with Mesa's llvmpipe); availability, the kernels and the
    options check are real."""
    monkeypatch.setattr(gb, "renderer", lambda: "NVIDIA H200/PCIe/SSE2")
    assert not gb.is_software_renderer()
    ok, why = gb.choose("AUTO", gb.AUTO_MIN_VERTS, dict(axes="XYZ"))
    assert ok, why
    assert "NVIDIA" in why
    ok, why = gb.choose("AUTO", gb.AUTO_MIN_VERTS - 1, dict(axes="XYZ"))
    assert not ok and "solves faster there" in why
    ok, why = gb.choose("AUTO", 10 * gb.AUTO_MIN_VERTS, dict(axes="XYZ"), fresh=True)
    assert not ok and "keeps its place" in why
    monkeypatch.setattr(gb, "renderer", lambda: "llvmpipe (LLVM 22.1.8, 256 bits)")
    ok, why = gb.choose("AUTO", 10 * gb.AUTO_MIN_VERTS, dict(axes="XYZ"))
    assert not ok and "software OpenGL" in why


def test_readback_matches_to_list_and_is_zero_copy(gb):
    """The read-back trap (docs/design.md, "The GPU dispatch plan"): our flattened zero-copy read
    equals Buffer.to_list(). Zero-copy is checked by structure, not by a clock: the array is a
    view of Blender's buffer (a per-texel Python loop or a copy would own its data)."""
    rng = np.random.default_rng(3)
    for channels, n in ((4, gb.TW * 3 + 17), (1, gb.TW * 2 + 5), (2, 1000)):
        data = rng.normal(size=(n, channels)).astype(np.float32)
        tex = gb.make_texture(data, channels)
        got = gb.read_texture(tex, n, channels)
        ref = np.array(tex.read().to_list(), np.float32).reshape(-1, channels)[:n]
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(got, data)
    big = gb.make_texture(rng.normal(size=(gb.TW * 256, 4)).astype(np.float32), 4)
    arr = gb.read_texture(big, gb.TW * 256, 4)
    assert arr.shape == (gb.TW * 256, 4)
    assert not arr.flags.owndata and arr.base is not None


def _two_islands():
    a, fa = vp.icosphere(2, 0.2, center=(-0.22, 0.05, 0.0))
    b, fb = vp.box(3, 0.3, center=(0.22, -0.05, 0.1))
    return np.vstack([a, b]), np.vstack([fa, fb + len(a)])


def _case(name):
    rng = np.random.default_rng(zlib.crc32(name.encode()))   # stable across processes
    influence = None
    if name == "icosphere-bspline":
        v, f = vp.icosphere(3, 0.42)
        lat = vp.Lattice((4, 5, 3), interpolation="BSPLINE")
    elif name == "box-cardinal-weights":
        v, f = vp.box(4, 0.8)
        lat = vp.Lattice((3, 3, 3), interpolation="CARDINAL")
        influence = rng.uniform(0.3, 1.0, len(v))
    elif name == "islands-linear":
        v, f = _two_islands()
        lat = vp.Lattice((2, 3, 4), interpolation="LINEAR")
    elif name == "mixed-one-point-axis":
        v, f = vp.icosphere(2, 0.4)
        lat = vp.Lattice((1, 4, 3), interpolation=("BSPLINE", "CATMULL_ROM", "LINEAR"))
    elif name == "bezier":
        v, f = vp.icosphere(2, 0.4)
        lat = vp.Lattice((3, 3, 4), interpolation="BEZIER", bounds=((-0.6,) * 3, (0.5, 0.6, 0.7)))
    elif name == "open-cup":
        v, f = vp.icosphere(3, 0.4)
        keep = v[f].mean(1)[:, 2] < 0.2          # the cap removed: an open mesh
        f = f[keep]
        lat = vp.Lattice((3, 4, 3), interpolation="BSPLINE")
    else:
        raise KeyError(name)
    P = lat.rest_points + rng.normal(scale=0.06, size=(lat.n_points, 3))
    P[:, 2] *= 0.8
    return lat, v, f, influence, P


CASES = ("icosphere-bspline", "box-cardinal-weights", "islands-linear", "mixed-one-point-axis", "bezier",
         "open-cup")
AXES = ("XYZ", "XY", "Z", "ZX", "YZX")


@pytest.mark.parametrize("name", CASES)
def test_gpu_matches_cpu(gb, name):
    lat, v, f, influence, P = _case(name)
    b = vp.bind(lat, v, f, influence=influence, dtype=np.float32)
    solver = gb.GPUSolver(b)
    for axes in AXES:
        for scale in (1.0, 0.9):
            cpu = b.solve(P, axes=axes, volume_scale=scale)
            gpu = solver.solve(P, axes=axes, volume_scale=scale)
            what = f"{name} {axes} scale {scale}"
            assert gpu.verts.shape == (len(v), 3) and gpu.verts.dtype == np.float64
            err = np.abs(gpu.verts - cpu.verts).max() / lat.size
            # Float32 rounding of the per-slot sums only: measured up to 6e-8 of the lattice size.
            assert err <= 5e-7, f"{what}: coordinates differ by {err:.3g} of the lattice size"
            target = cpu.target_volume
            assert gpu.target_volume == pytest.approx(target, rel=1e-12)
            vol = vp.signed_volume(gpu.verts, f, origin=lat.centre)
            assert abs(vol - target) <= 1e-5 * abs(target), f"{what}: volume {vol} vs {target}"
            assert abs(gpu.volume - target) <= 1e-5 * abs(target), what
            assert abs(gpu.plain_volume - cpu.plain_volume) <= 1e-5 * abs(target), what
            assert np.abs(gpu.points - cpu.points).max() <= 5e-7 * lat.size, what
            assert gpu.warnings == cpu.warnings, what
            np.testing.assert_array_equal(gpu.directions, cpu.directions)


def test_gpu_matches_cpu_with_pins_and_mobility(gb):
    """Pins and mobility go through the one solve driver on either path: the GPU supplies only
    the per-slot sums and products, so its result is the CPU's to float32 rounding."""
    lat, v, f, influence, P = _case("icosphere-bspline")
    b = vp.bind(lat, v, f, influence=influence, dtype=np.float32)
    rng = np.random.default_rng(3)
    mobility = rng.uniform(0.2, 1.0, lat.n_points)
    pins = [(0, v[0] + (0.0, 0.0, 0.02)), (len(v) // 2, v[len(v) // 2] - (0.01, 0.0, 0.0))]
    for options in (dict(axes="XYZ", mobility=mobility), dict(axes="XY", pins=pins),
                    dict(axes="XYZ", pins=pins, mobility=mobility, volume_scale=0.95)):
        cpu = b.solve(P, **options)
        gpu = gb.GPUSolver(b).solve(P, **options)
        assert np.abs(gpu.verts - cpu.verts).max() <= 5e-7 * lat.size, options
        assert abs(gpu.volume / cpu.target_volume - 1) <= 1e-5, options
        assert gpu.warnings == cpu.warnings, options


def test_untouched_points_come_back_bit_identical(gb):
    lat, v, f, influence, P = _case("icosphere-bspline")
    b = vp.bind(lat, v, f, dtype=np.float32)
    gpu = gb.GPUSolver(b).solve(P, axes="Z")
    np.testing.assert_array_equal(gpu.points[:, :2], P[:, :2])


def test_errors_match_cpu(gb):
    lat, v, f, influence, P = _case("icosphere-bspline")
    b = vp.bind(lat, v, f, dtype=np.float32)
    s = gb.GPUSolver(b)
    for bad in (P[:-1], np.where(np.arange(len(P))[:, None] == 3, np.nan, P)):
        with pytest.raises(ValueError):
            s.solve(bad)
    with pytest.raises(ValueError):
        s.solve(P, axes="XX")
    with pytest.raises(ValueError):
        s.solve(P, volume_scale=-1)
    # One point per axis: the volume cannot change (as the CPU path says).
    one = vp.Lattice((1, 1, 1))
    b1 = vp.bind(one, v, f, dtype=np.float32)
    with pytest.raises(ValueError, match="cannot change"):
        b1.solve(one.rest_points, volume_scale=0.5)
    with pytest.raises(ValueError, match="cannot change"):
        gb.GPUSolver(b1).solve(one.rest_points, volume_scale=0.5)
    s.free()
    with pytest.raises(gb.GPUUnavailable):
        s.solve(P)


def test_compiled_kernels_are_compiled_once_per_block_layout(gb, monkeypatch):
    """A second solve with the same block size and tap counts reuses the kernels compiled for the
    first (compiling six compute shaders costs far more than a solve); `available()`, which the
    choice of backend calls, compiles none either once they are there."""
    lat, v, f, influence, P = _case("box-cardinal-weights")
    b = vp.bind(lat, v, f, influence=influence, dtype=np.float32)
    gb.GPUSolver(b).solve(P, axes="XYZ")
    cache = gb.gpu_device.kernel_cache
    assert cache and all(isinstance(k, tuple) and len(k) == 3 for k in cache), list(cache)
    made = []
    create = gb.gpu_device.gpu_module().shader.create_from_info
    monkeypatch.setattr(gb.gpu_device.gpu_module().shader, "create_from_info",
                        lambda info: made.append(info) or create(info))
    gb.GPUSolver(b).solve(P, axes="XYZ")
    assert gb.available()[0]
    assert made == []


def test_release_drops_compiled_kernels(gb):
    gb.release()
    assert not gb.gpu_device.kernel_cache
    assert gb.available()[0]      # compiles again on demand


def test_rest_pose_is_identity(gb):
    lat, v, f, influence, P = _case("box-cardinal-weights")
    b = vp.bind(lat, v, f, influence=influence, dtype=np.float32)
    sol = gb.GPUSolver(b).solve(lat.rest_points, axes="XYZ")
    cpu = b.solve(lat.rest_points, axes="XYZ")
    # Both paths may nudge the points by float32 rounding of the measured volume, no more.
    assert np.abs(sol.verts - v).max() <= 1e-6 * lat.size
    assert np.abs(sol.points - lat.rest_points).max() <= 1e-6 * lat.size
    assert np.abs(cpu.points - lat.rest_points).max() <= 1e-6 * lat.size


def test_the_extension_solves_on_the_gpu_when_asked_and_says_why_when_it_does_not(gb, vpffd):
    """A bound object with backend GPU is solved by the compute shaders (same volume as the CPU);
    Auto keeps the CPU on software OpenGL and says so."""
    import bpy
    from . import extension_harness as eh
    from .blender_ref import triangle_mesh
    ops = vpffd.module.operators
    eh.reset_scene()
    verts, tris = vp.icosphere(3, 0.8)
    ob = bpy.data.objects.new("Ball", triangle_mesh(verts, tris, "Ball"))
    bpy.context.scene.collection.objects.link(ob)
    lt = bpy.data.lattices.new("L")
    lt.points_u = lt.points_v = lt.points_w = 4
    lat = bpy.data.objects.new("L", lt)
    lat.scale = (2.0 / 3.0,) * 3
    bpy.context.scene.collection.objects.link(lat)
    co = np.empty(64 * 3, np.float32)
    lt.points.foreach_get("co", co)
    co = co.reshape(-1, 3)
    co[:, 2] *= 0.5
    lt.points.foreach_set("co_deform", co.ravel())
    ob.vpffd.lattice = lat
    ob.vpffd.axes = "XY"
    ob.vpffd.backend = "GPU"
    with bpy.context.temp_override(object=ob, active_object=ob):
        assert bpy.ops.object.vpffd_bind() == {"FINISHED"}
    info = ops.status.stats(ob)
    assert info["backend"] == "GPU", info.get("backend_reason")
    assert abs(info["volume_percent"] - 100.0) <= 1e-3
    ob.vpffd.backend = "AUTO"
    assert ops.update.update(ob, bpy.context.evaluated_depsgraph_get(), force=True)
    info = ops.status.stats(ob)
    assert info["backend"] == "CPU" and "Auto" in info["backend_reason"]
    eh.reset_scene()


def test_auto_offers_the_gpu_a_binding_only_once_a_second_frame_uses_it(vpffd, monkeypatch):
    """Uploading an embedding costs several CPU solves (docs/performance.md), so the engine tells
    the backend choice which bindings are fresh: every frame's when the mesh moves through the
    lattice (embedded anew each time), only the first when just the lattice's points move."""
    import bpy
    from . import extension_harness as eh
    from .blender_ref import squash_lattice, triangle_mesh
    gpu_backend = vpffd.module.operators.gpu_backend
    real = gpu_backend.choose
    seen = []

    def recording(backend, n_verts, options=None, binding=None, fresh=False):
        seen.append((fresh, binding))     # kept alive: ids of freed bindings can recur
        return real(backend, n_verts, options, binding, fresh)

    monkeypatch.setattr(gpu_backend, "choose", recording)
    for moving in ("lattice points", "mesh"):
        eh.reset_scene()
        verts, tris = vp.icosphere(3, 0.4)
        ob = bpy.data.objects.new("Ball", triangle_mesh(verts, tris, "Ball"))
        bpy.context.scene.collection.objects.link(ob)
        lat, key = squash_lattice("L", (4, 4, 4), (1.0 / 3.0,) * 3, 0.6, 0.15)
        for f, v in ((1, 0.2), (6, 0.9)):
            if moving == "mesh":
                ob.location = (0.1 * v, 0, 0)
                ob.keyframe_insert("location", frame=f)
            else:
                key.value = v
                key.keyframe_insert("value", frame=f)
        ob.vpffd.lattice = lat
        ob.vpffd.axes = "XYZ"
        bpy.context.scene.frame_set(1)
        with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
            assert bpy.ops.object.vpffd_bind() == {"FINISHED"}
        del seen[:]
        for f in range(2, 6):
            bpy.context.scene.frame_set(f)
        assert seen, "the engine never asked where to solve"
        fresh = [f for f, _ in seen]
        bindings = {id(b) for _, b in seen}
        if moving == "mesh":
            # A new embedding on every frame, each fresh when it is first solved.
            assert len(bindings) >= 4 and fresh.count(True) == len(bindings), seen
        else:
            # One embedding for every frame: never fresh again after its first solve.
            assert len(bindings) == 1 and not any(fresh), seen
    eh.reset_scene()


def test_auto_goes_back_to_the_cpu_when_the_gpu_measures_slower(gb, vpffd, monkeypatch):
    """Auto trusts measured times over its rules: with the software renderer taken for a hardware
    GPU, the mesh is solved on the CPU first (a fresh embedding), then on the GPU, and from then on
    on whichever path measured faster, the panel giving both times when it is the CPU (here, with
    llvmpipe about 17 times slower than the CPU path, that is the CPU)."""
    import bpy
    from . import extension_harness as eh
    from .blender_ref import squash_lattice, triangle_mesh
    ops, gpu_backend = vpffd.module.operators, vpffd.module.operators.gpu_backend
    monkeypatch.setattr(gpu_backend, "is_software_renderer", lambda: False)
    eh.reset_scene()
    verts, tris = vp.icosphere(6, 0.4)            # 40,962 vertices
    monkeypatch.setattr(gpu_backend, "AUTO_MIN_VERTS", 1000)
    ob = bpy.data.objects.new("Ball", triangle_mesh(verts, tris, "Ball"))
    bpy.context.scene.collection.objects.link(ob)
    lat, key = squash_lattice("L", (4, 4, 4), (1.0 / 3.0,) * 3, 0.6, 0.15)
    for f, v in ((1, 0.2), (8, 0.9)):
        key.value = v
        key.keyframe_insert("value", frame=f)
    ob.vpffd.lattice, ob.vpffd.axes, ob.vpffd.backend = lat, "XYZ", "AUTO"
    bpy.context.scene.frame_set(1)
    with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
        assert bpy.ops.object.vpffd_bind() == {"FINISHED"}
    costs = ops.bound.state_of(ob).costs
    paths = [ops.status.stats(ob)["backend"]]
    # (Bind solves twice: its own solve, the first, on the CPU, and the update after it.)
    assert paths == ["GPU"] and any(k[0] == "CPU" for k in costs), (paths, costs)
    for f in range(2, 6):
        # The path each frame must take follows from the times measured so far, whatever this
        # machine's speed: the GPU while its last solve was no slower than the CPU's.
        gpu = next(t for k, t in costs.items() if k[0] == "GPU")
        cpu = next(t for k, t in costs.items() if k[0] == "CPU")
        bpy.context.scene.frame_set(f)
        info = ops.status.stats(ob)
        paths.append(info["backend"])
        assert info["backend"] == ("GPU" if gpu <= cpu else "CPU"), (f, paths, gpu, cpu)
        if gpu > cpu:
            assert info["backend_reason"].startswith("Auto chose the CPU: it solved this mesh in "), info["backend_reason"]
        assert abs(info["volume_percent"] - 100.0) <= 1e-3
    eh.reset_scene()


def test_falloff_and_a_bind_target_solve_on_the_gpu_as_on_the_cpu(gb):
    """Outside: Falloff is a factor on the influence and Target: Bind a given target volume: the
    GPU path takes both through the one solve driver, with the CPU's results."""
    v, f = vp.icosphere(4, 0.45)
    v = v + [0.5, 0.0, 0.0]                                   # half outside the lattice
    lat = vp.Lattice((4, 4, 4), "BSPLINE")
    factor = vp.outside_factor(lat, v, "FALLOFF", 0.3)
    b = vp.bind(lat, v, f, influence=factor, dtype=np.float32)
    P = lat.rest_points.copy()
    P[:, 2] *= 0.7
    target = 1.02 * b.rest_volume                             # e.g. a volume lost before the slot
    gpu = gb.GPUSolver(b).solve(P, axes="XYZ", target_volumes=target)
    cpu = b.solve(P, axes="XYZ", target_volumes=target)
    assert abs(gpu.volume / target - 1) <= 1e-5 and abs(cpu.volume / target - 1) <= 1e-5
    assert np.abs(gpu.verts - cpu.verts).max() <= 1e-6 * lat.size
    beyond = factor == 0
    assert beyond.sum() > 20
    np.testing.assert_allclose(gpu.verts[beyond], v[beyond], rtol=0, atol=1e-6)
