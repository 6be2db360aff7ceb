"""VP-FFD benchmark: bind / standard FFD / XYZ volume-preserving solve vs Blender's Lattice modifier.

Run from the repository root:

    ./dev bench [--sizes 6,7,8] [--repeat 7] [--out FILE.json] [--no-blender] [--update-readme]

Icospheres of subdivision 6, 7, 8 (40,962 / 163,842 / 655,362 vertices, radius 0.45) inside a
10x10x10 B-spline lattice spanning [-0.5, 0.5]^3, deformed deterministically (squash along Z, twist
about Z, small seeded noise). For float32 and float64 bindings it times bind (once), deform and
solve(axes="XYZ") (median and min over --repeat; max(3, repeat // 2) for sizes >= 8), and in the same
process Blender's own Lattice modifier on the same mesh and lattice (``modifier.execution_time``).
Progress goes to stderr, the JSON report to stdout (and to --out). This is a benchmark, not a test:
it prints figures and ratios and exits 0 whether or not the targets are met. --update-readme
rewrites the tables between the benchmark markers of docs/speed.md, and the speed line between
the speed-line markers of README.md, from this run's figures.
"""
import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time

import numpy as np

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)

import vpffd_addon as vp  # noqa: E402
from vpffd_addon import compiled  # noqa: E402
from vpffd_addon.steps import NumpySteps  # noqa: E402
from benchmarks.timing import timed  # noqa: E402

LATTICE_SHAPE = (10, 10, 10)
RADIUS = 0.45
DTYPES = (("float32", np.float32), ("float64", np.float64))
TARGET_BYTES_PER_VERTEX = 200
TARGET_SOLVE_OVER_BLENDER = 3.0
TARGET_SIZE_FOR_RATIO = 163842  # the ~160k mesh
TARGET_FRAME_SET_RATIO = 4.0     # frame_set with VP-FFD vs a plain Lattice modifier scene
TARGET_HANDLER_OVERHEAD_MS = 15.0
BLENDER_EVALS = 15
BLENDER_WARMUPS = 2
FRAME_SET_WARMUPS = 4            # frames stepped before timing frame_set (as BLENDER_WARMUPS)
FRAME_SET_REPEATS = 3            # whole frame_set comparisons; the report gives each and the median


def log(*args):
    print(*args, file=sys.stderr, flush=True)


def deformed_points(lat, seed=0):
    """Deterministic deformation of the rest grid: squash Z by 0.6, twist about Z, seeded noise."""
    p = lat.rest_points.copy()
    z = p[:, 2]
    angle = 0.5 * z                                  # +-0.25 rad (~14 deg) at the top and bottom
    c, s = np.cos(angle), np.sin(angle)
    x, y = p[:, 0].copy(), p[:, 1].copy()
    p[:, 0] = c * x - s * y
    p[:, 1] = s * x + c * y
    p[:, 2] = 0.6 * z
    p += np.random.default_rng(seed).normal(scale=0.01, size=p.shape)
    return p


def cage_shapes():
    """The benchmark's 20-cell cages around the icosphere (radius 0.45): a box of 5 x 2 x 2 hexahedra,
    and a disc (a quad with a ring of four quads, whose corners are extraordinary) extruded into
    four layers, like a limb."""
    box = vp.box_cage((2, 2, 5), ((-0.5,) * 3, (0.5,) * 3))
    ang = np.arange(4) * np.pi / 2 + np.pi / 4
    disc = np.concatenate([np.stack([r * np.cos(ang), r * np.sin(ang), 0 * ang], 1) for r in (0.3, 0.7)])
    polys = [[0, 1, 2, 3]] + [[i, (i + 1) % 4, 4 + (i + 1) % 4, 4 + i] for i in range(4)]
    limb = vp.Cage(*vp.extrude(disc - [0, 0, 0.5], polys, (0, 0, 1.0), 4))
    return {"box 2x2x5": box, "disc x 4 layers": limb}


def cage_figures(sizes, repeat, depth=3):
    """Bind, deform and XYZ solve (float32, as the extension) with the 20-cell cages at `depth`."""
    rows = []
    for name, cage in cage_shapes().items():
        P = cage.rest_points.copy()
        angle = 0.5 * P[:, 2]
        c, s = np.cos(angle), np.sin(angle)
        P[:, 0], P[:, 1] = c * P[:, 0] - s * P[:, 1], s * P[:, 0] + c * P[:, 1]
        P[:, 2] *= 0.6
        for sub in sizes:
            verts, tris = vp.icosphere(sub, RADIUS)
            rep = max(3, repeat // 2) if sub >= 8 else repeat
            t0 = time.perf_counter()
            b = vp.bind(cage, verts, tris, depth=depth, dtype=np.float32)
            bind_ms = (time.perf_counter() - t0) * 1e3
            b.deform(P)
            d_med, _, _ = timed(lambda: b.deform(P), rep)
            b.solve(P, axes="XYZ")
            s_med, _, sol = timed(lambda: b.solve(P, axes="XYZ"), rep)
            V = len(verts)
            row = {"cage": name, "n_cells": cage.n_cells, "n_points": cage.n_points, "depth": depth,
                   "n_verts": V, "n_outside": int(b.n_outside), "bind_ms": bind_ms,
                   "deform_ms_median": d_med, "solve_xyz_ms_median": s_med,
                   "solve_xyz_ns_per_vertex": s_med * 1e6 / V, "bytes_per_vertex": b.nbytes / V,
                   "plain_change_pct": 100.0 * (sol.plain_volume / b.rest_volume - 1.0),
                   "relative_error": abs(sol.volume - sol.target_volume) / abs(sol.target_volume)}
            rows.append(row)
            log(f"  cage {name} depth {depth}: V={V:,} bind {bind_ms:7.0f} ms | deform {d_med:6.1f} ms | "
                f"solve XYZ {s_med:6.1f} ms ({row['solve_xyz_ns_per_vertex']:.0f} ns/v) | plain "
                f"{row['plain_change_pct']:+.1f}% -> rel err {row['relative_error']:.1e}")
            del b, sol
    for name in cage_shapes():
        mine = [r for r in rows if r["cage"] == name]
        if len(mine) > 1:
            fit = np.polyfit(np.log([r["n_verts"] for r in mine]), np.log([r["solve_xyz_ms_median"] for r in mine]), 1)
            for r in mine:
                r["solve_fitted_exponent"] = float(fit[0])
    return rows


def cage_convergence(n=6, depths=(0, 1, 2, 3), seed=7):
    """Max distance, over interior points, between a box cage's deformation and the tricubic uniform
    B-spline FFD of the same control points, per depth (MacCracken & Joy: the interior refinement
    rules are the B-spline's, so the error should fall about 4x per level)."""
    cage = vp.box_cage((n - 1,) * 3)
    h = 2.0 / (n - 1)
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1 + 2 * h, 1 - 2 * h, (1500, 3))
    P = cage.rest_points + rng.normal(0, 0.1, (cage.n_points, 3))

    def basis(t):
        t = np.abs(t)
        return np.where(t < 1, (4 - 6 * t ** 2 + 3 * t ** 3) / 6, np.where(t < 2, (2 - t) ** 3 / 6, 0.0))
    t = (x + 1) / h
    Nu, Nv, Nw = (basis(t[:, a, None] - np.arange(n)) for a in range(3))
    reference = np.einsum("vk,vj,vi->vkji", Nw, Nv, Nu).reshape(len(x), -1) @ P
    errors = [float(np.abs(vp.bind(cage, x, np.array([[0, 1, 2]]), depth=d).deform(P) - reference).max())
              for d in depths]
    log("  cage convergence to the tricubic B-spline FFD by depth: " + ", ".join(f"{e:.2e}" for e in errors))
    return {"cage_cells": (n - 1) ** 3, "depths": list(depths), "max_error": errors}


# ------------------------------------------------------------------------------------ Blender

def _build_scene(verts, tris, points):
    """Mesh at identity and a 10x10x10 B-spline lattice whose object maps its rest grid onto
    [-0.5, 0.5]^3, deformed to `points`. Returns (mesh object, lattice object, lattice data,
    rest co (N, 3), scale, deformed co_deform as float32 flat)."""
    import bpy

    scene = bpy.context.scene
    nu, nv, nw = LATTICE_SHAPE
    n_points = nu * nv * nw

    # Mesh at identity, built through foreach_set only.
    from tests.blender_ref import triangle_mesh
    ob = bpy.data.objects.new("bench_mesh", triangle_mesh(verts, tris, "bench_mesh"))
    scene.collection.objects.link(ob)

    # Lattice: rest co spans [-4.5, 4.5] (unit spacing); the object scale maps it onto [-0.5, 0.5].
    lat = bpy.data.lattices.new("bench_lattice")
    lat.points_u, lat.points_v, lat.points_w = nu, nv, nw
    lat.interpolation_type_u = lat.interpolation_type_v = lat.interpolation_type_w = "KEY_BSPLINE"
    co = np.empty(3 * n_points, np.float32)
    lat.points.foreach_get("co", co)
    co = co.reshape(n_points, 3).astype(np.float64)
    extent = co.max(0) - co.min(0)                    # 9 per axis
    scale = float(extent[0])
    lat_ob = bpy.data.objects.new("bench_lattice", lat)
    lat_ob.scale = (1.0 / scale,) * 3
    scene.collection.objects.link(lat_ob)
    base = (np.asarray(points, np.float64) * scale).astype(np.float32).ravel()
    lat.points.foreach_set("co_deform", base)

    return ob, lat_ob, lat, co, scale, base


def blender_modifier(verts, tris, points, evals=BLENDER_EVALS, warmups=BLENDER_WARMUPS):
    """Blender's Lattice modifier on the same mesh and lattice. Returns (dict, evaluated verts)."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    V = len(verts)
    ob, lat_ob, lat, co, scale, base = _build_scene(verts, tris, points)
    mod = ob.modifiers.new("Lattice", "LATTICE")
    mod.object = lat_ob

    depsgraph = bpy.context.evaluated_depsgraph_get()
    depsgraph.update()
    me_eval = ob.evaluated_get(depsgraph).data
    if len(me_eval.vertices) != V:
        raise RuntimeError("Blender changed the vertex count")
    out = np.empty(3 * V, np.float32)
    me_eval.vertices.foreach_get("co", out)
    evaluated = out.reshape(V, 3).astype(np.float64)
    rest_ok = bool(np.allclose(co / scale, vp.Lattice(LATTICE_SHAPE).rest_points, atol=1e-6))

    exec_ms, wall_ms = [], []
    for i in range(warmups + evals):
        # A tiny i-dependent change so that every evaluation really recomputes the modifier.
        lat.points.foreach_set("co_deform", base + np.float32(1e-4 * ((i % 2) + 1)))
        lat.update_tag()
        t0 = time.perf_counter()
        depsgraph.update()
        ms = float(ob.evaluated_get(depsgraph).modifiers[0].execution_time) * 1e3
        wall = (time.perf_counter() - t0) * 1e3
        if i >= warmups:
            exec_ms.append(ms)
            wall_ms.append(wall)

    info = {
        "execution_time_ms_median": statistics.median(exec_ms),
        "execution_time_ms_min": min(exec_ms),
        "depsgraph_update_wall_ms_median": statistics.median(wall_ms),
        "evaluations": evals,
        "warmups": warmups,
        "rest_grid_matches_core": rest_ok,
    }
    # Leave an empty scene so the next size does not carry this one's memory.
    bpy.ops.wm.read_factory_settings(use_empty=True)
    return info, evaluated


FRAME_SET_FRAMES = 12
_EXTENSION = {}


def _extension_status():
    """Install the built extension zip through Blender's own installer (once per process) and
    return its status module (`operators/status.py`). BLENDER_USER_RESOURCES was isolated before bpy was imported."""
    if "status" not in _EXTENSION:
        import importlib
        import tempfile
        eh = _harness()
        zip_path = eh.build_extension_zip(_ROOT, tempfile.mkdtemp(prefix="vpffd-bench-zip-"))
        module = eh.install_extension(zip_path)
        _EXTENSION["module"] = module
        _EXTENSION["status"] = importlib.import_module(module + ".operators.status")
    _harness().ensure_enabled(_EXTENSION["module"])  # read_factory_settings disables add-ons
    return _EXTENSION["status"]


def gpu_figures(sizes, repeat):
    """CPU and GPU (compute shader) XYZ solve side by side, float32, same process."""
    from benchmarks import gpu_benchmark as gbm

    gb = gbm.load_gpu_backend()
    init_ok, init_why = gbm.init_gpu()
    ok, why = gb.available()
    out = {"available": ok, "reason": why if ok else f"{why} (GPU init: {init_why})",
           "renderer": gb.renderer(), "software_renderer": gb.is_software_renderer(), "rows": []}
    log(f"GPU path: {out['reason']}")
    if ok:
        for sub in sizes:
            out["rows"].append(gbm.bench_size(gb, sub, "XYZ", max(3, repeat // 2)))
    return out


def _harness():
    from tests import extension_harness
    return extension_harness


def extension_frame_set(verts, tris, points, frames=FRAME_SET_FRAMES):
    """Median `scene.frame_set()` time with the mesh bound by VP-FFD (XYZ correction) and with a
    plain Lattice modifier, over the same animated lattice (a shape key from rest to `points`);
    the first FRAME_SET_WARMUPS frames after frame 1 are stepped but not timed, in both scenes."""
    import bpy

    status = _extension_status()
    eh = _harness()
    out = {"frames": frames}
    for kind in ("plain", "vpffd"):
        eh.reset_scene()
        ob, lat_ob, lat, co, scale, base = _build_scene(verts, tris, points)
        lat.points.foreach_set("co_deform", co.astype(np.float32).ravel())
        lat_ob.shape_key_add(name="Basis")
        key = lat_ob.shape_key_add(name="Deform")
        key.data.foreach_set("co", base)
        for frame, value in ((1, 0.0), (frames + FRAME_SET_WARMUPS + 1, 1.0)):
            key.value = value
            key.keyframe_insert("value", frame=frame)
        if kind == "plain":
            ob.modifiers.new("Lattice", "LATTICE").object = lat_ob
        else:
            ob.vpffd.lattice = lat_ob
            ob.vpffd.axes = "XYZ"
            with bpy.context.temp_override(object=ob, active_object=ob):
                if bpy.ops.object.vpffd_bind() != {"FINISHED"}:
                    raise RuntimeError("binding failed")
        scene = bpy.context.scene
        scene.frame_set(1)
        for f in range(2, FRAME_SET_WARMUPS + 2):   # not counted, for both scenes alike
            scene.frame_set(f)
        wall, update, core = [], [], []
        for f in range(FRAME_SET_WARMUPS + 2, FRAME_SET_WARMUPS + frames + 2):
            t0 = time.perf_counter()
            scene.frame_set(f)
            wall.append((time.perf_counter() - t0) * 1e3)
            if kind == "vpffd":
                info = status.stats(ob)
                if info.get("error"):
                    raise RuntimeError(info["error"])
                update.append(info["seconds"] * 1e3)
                core.append(info["core_seconds"] * 1e3)
        out[f"{kind}_frame_set_ms_median"] = statistics.median(wall)
        if kind == "vpffd":
            out["vpffd_update_ms_median"] = statistics.median(update)
            out["vpffd_core_solve_ms_median"] = statistics.median(core)
            out["handler_overhead_ms_median"] = float(statistics.median(np.subtract(update, core)))
            out["volume_percent_last"] = status.stats(ob)["volume_percent"]
            out["kernels"] = status.stats(ob).get("kernels")
    out["frame_set_ratio"] = out["vpffd_frame_set_ms_median"] / out["plain_frame_set_ms_median"]
    eh.reset_scene()
    return out


def repeated_frame_set(verts, tris, points, repeats=FRAME_SET_REPEATS):
    """`extension_frame_set` `repeats` times (fresh scenes each time): the run with the median
    ratio, plus every run's ratio under "frame_set_ratio_runs". The VM's timings drift between
    runs (the first is often the slowest), so one run alone says little."""
    runs = [extension_frame_set(verts, tris, points) for _ in range(repeats)]
    ratios = [r["frame_set_ratio"] for r in runs]
    out = dict(sorted(runs, key=lambda r: r["frame_set_ratio"])[len(runs) // 2])
    out["frame_set_ratio_runs"] = ratios
    return out


# ------------------------------------------------------------------------------------ one size

def bench_size(sub, repeat, use_blender):
    verts, tris = vp.icosphere(sub, RADIUS)
    V = len(verts)
    rep = max(3, repeat // 2) if sub >= 8 else repeat
    lat = vp.Lattice(LATTICE_SHAPE, interpolation="BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    points = deformed_points(lat)
    log(f"[size {sub}] V={V:,} F={len(tris):,} repeat={rep}")
    res = {"subdivisions": sub, "n_verts": V, "n_faces": int(len(tris)), "repeat": rep, "dtypes": {}}

    deformed64 = None
    for name, dt in DTYPES:
        t0 = time.perf_counter()
        b = vp.bind(lat, verts, tris, dtype=dt)
        bind_ms = (time.perf_counter() - t0) * 1e3
        b.deform(points)                               # warm-up
        d_med, d_min, d_out = timed(lambda: b.deform(points), rep)
        # The NumPy steps, named: once the compiled kernels are loaded they are the default.
        vp.solve.solve(b, points, axes="XYZ", steps=NumpySteps)                    # warm-up
        s_med, s_min, sol = timed(lambda: vp.solve.solve(b, points, axes="XYZ", steps=NumpySteps), rep)
        rest = b.rest_volume
        entry = {
            "bind_ms": bind_ms,
            "deform_ms_median": d_med, "deform_ms_min": d_min,
            "solve_xyz_ms_median": s_med, "solve_xyz_ms_min": s_min,
            "solve_reported_seconds_last": float(sol.seconds),
            "bind_ns_per_vertex": bind_ms * 1e6 / V,
            "deform_ns_per_vertex": d_med * 1e6 / V,
            "solve_xyz_ns_per_vertex": s_med * 1e6 / V,
            "binding_nbytes": int(b.nbytes),
            "bytes_per_vertex": b.nbytes / V,
            "volume": {
                "rest": float(rest),
                "plain_change_pct": 100.0 * (sol.plain_volume / rest - 1.0),
                "corrected_change_pct": 100.0 * (sol.volume / rest - 1.0),
                "target": float(sol.target_volume),
                "relative_error": abs(sol.volume - sol.target_volume) / abs(sol.target_volume),
            },
            "warnings": list(sol.warnings),
        }
        if compiled.ready():
            def fast():
                return vp.solve.solve(b, points, axes="XYZ", steps=compiled.CompiledSteps)
            fast()
            c_med, c_min, c_sol = timed(fast, rep)
            entry["solve_xyz_compiled_ms_median"], entry["solve_xyz_compiled_ms_min"] = c_med, c_min
            entry["compiled_vs_numpy_max_abs"] = float(np.abs(c_sol.verts - sol.verts).max())
        if name == "float64":
            deformed64 = d_out
        else:
            entry["deform_vs_float64_max_abs"] = None  # filled below
            deformed32 = d_out
        res["dtypes"][name] = entry
        log(f"  {name}: bind {bind_ms:8.1f} ms | deform {d_med:7.2f} ms ({d_med * 1e6 / V:6.1f} ns/v) | "
            f"solve XYZ {s_med:7.2f} ms ({s_med * 1e6 / V:6.1f} ns/v) | {b.nbytes / V:6.1f} B/v | "
            f"volume plain {entry['volume']['plain_change_pct']:+.2f}% -> "
            f"{entry['volume']['corrected_change_pct']:+.2e}% (rel err {entry['volume']['relative_error']:.1e})")
        del b, sol, d_out
    res["dtypes"]["float32"]["deform_vs_float64_max_abs"] = float(np.abs(deformed32 - deformed64).max())

    if use_blender:
        info, evaluated = blender_modifier(verts, tris, points)
        info["deform_max_abs_diff_vs_core_float64"] = float(np.abs(evaluated - deformed64).max())
        info["deform_max_abs_diff_vs_core_float32"] = float(np.abs(evaluated - deformed32).max())
        bl = info["execution_time_ms_median"]
        info["ns_per_vertex"] = bl * 1e6 / V
        res["blender"] = info
        if V == TARGET_SIZE_FOR_RATIO:
            res["extension_frame_set"] = fs = repeated_frame_set(verts, tris, points)
            log(f"  frame_set: plain Lattice modifier {fs['plain_frame_set_ms_median']:.1f} ms, VP-FFD "
                f"{fs['vpffd_frame_set_ms_median']:.1f} ms ({fs['frame_set_ratio']:.2f}x); handler "
                f"overhead beyond the core's evaluation {fs['handler_overhead_ms_median']:.1f} ms")
        res["ratios_vs_blender"] = {
            name: {"deform": e["deform_ms_median"] / bl, "solve_xyz": e["solve_xyz_ms_median"] / bl}
            for name, e in res["dtypes"].items()}
        for name, e in res["dtypes"].items():
            if "solve_xyz_compiled_ms_median" in e:
                res["ratios_vs_blender"][name]["solve_xyz_compiled"] = e["solve_xyz_compiled_ms_median"] / bl
        log(f"  blender modifier: {bl:7.2f} ms ({bl * 1e6 / V:6.1f} ns/v), depsgraph wall "
            f"{info['depsgraph_update_wall_ms_median']:.1f} ms | max |blender - core f64| "
            f"{info['deform_max_abs_diff_vs_core_float64']:.2e} | solve/blender " + ", ".join(
                f"{n} {r['solve_xyz']:.2f}x" for n, r in res["ratios_vs_blender"].items()))
    return res


def summarize(results, use_blender):
    summary = {"linearity": {}, "targets": {}}
    by_v = sorted(results, key=lambda r: r["n_verts"])
    keys = [("deform", "deform_ns_per_vertex"), ("solve_xyz", "solve_xyz_ns_per_vertex"),
            ("bind", "bind_ns_per_vertex")]
    for name, _ in DTYPES:
        lin = {}
        for label, key in keys:
            ns = [r["dtypes"][name][key] for r in by_v]
            lin[label] = {
                "ns_per_vertex_by_size": {str(r["n_verts"]): v for r, v in zip(by_v, ns)},
                # 1.0 = perfectly linear; > 1 means the per-vertex cost grows with V.
                "largest_over_smallest_ns_per_vertex": ns[-1] / ns[0] if len(ns) > 1 else None,
            }
            if len(ns) > 1:
                # Exponent k in time ~ V^k fitted over the sizes (1.0 = linear).
                vs = np.log([r["n_verts"] for r in by_v])
                ts = np.log([n * r["n_verts"] for n, r in zip(ns, by_v)])
                lin[label]["fitted_exponent"] = float(np.polyfit(vs, ts, 1)[0])
        summary["linearity"][name] = lin
    if use_blender:
        ns = [r["blender"]["ns_per_vertex"] for r in by_v]
        summary["linearity"]["blender"] = {
            "ns_per_vertex_by_size": {str(r["n_verts"]): v for r, v in zip(by_v, ns)},
            "largest_over_smallest_ns_per_vertex": ns[-1] / ns[0] if len(ns) > 1 else None}

    t = summary["targets"]
    t["bytes_per_vertex_target"] = TARGET_BYTES_PER_VERTEX
    for name, _ in DTYPES:
        worst = max(r["dtypes"][name]["bytes_per_vertex"] for r in results)
        t[f"bytes_per_vertex_max_{name}"] = worst
        t[f"bytes_per_vertex_ok_{name}"] = worst <= TARGET_BYTES_PER_VERTEX
    if use_blender:
        t["solve_over_blender_target"] = TARGET_SOLVE_OVER_BLENDER
        ref = [r for r in results if r["n_verts"] == TARGET_SIZE_FOR_RATIO]
        if not ref:  # the ~160k mesh was not run: judge on the closest size
            ref = [min(results, key=lambda r: abs(np.log(r["n_verts"] / TARGET_SIZE_FOR_RATIO)))]
        r = ref[0]
        t["solve_over_blender_judged_on_n_verts"] = r["n_verts"]
        for name, _ in DTYPES:
            ratio = r["ratios_vs_blender"][name]["solve_xyz"]
            t[f"solve_over_blender_{name}"] = ratio
            t[f"solve_over_blender_ok_{name}"] = ratio <= TARGET_SOLVE_OVER_BLENDER
        fs = r.get("extension_frame_set")
        if fs:
            t["frame_set_ratio_target"] = TARGET_FRAME_SET_RATIO
            t["frame_set_ratio"] = fs["frame_set_ratio"]
            t["frame_set_ratio_ok"] = fs["frame_set_ratio"] <= TARGET_FRAME_SET_RATIO
            t["handler_overhead_ms_target"] = TARGET_HANDLER_OVERHEAD_MS
            t["handler_overhead_ms"] = float(fs["handler_overhead_ms_median"])
            t["handler_overhead_ok"] = fs["handler_overhead_ms_median"] <= TARGET_HANDLER_OVERHEAD_MS
    return summary


def environment(use_blender):
    env = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "vpffd_addon": getattr(vp, "__version__", None),
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor() or None,
        "cpu_count": os.cpu_count(),
        "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "bpy": None,
    }
    if use_blender:
        import bpy
        env["bpy"] = bpy.app.version_string
    return env


README_START = "<!-- benchmark:start (written by ./dev bench --update-readme) -->"
README_END = "<!-- benchmark:end -->"
#: The page the tables are written to (README_START ... README_END, and the stack table's markers).
SPEED_PAGE = os.path.join(_ROOT, "docs", "speed.md")
#: The front page's one line on speed, between these markers of README.md.
README = os.path.join(_ROOT, "README.md")
LINE_START = "<!-- speed-line:start (written by ./dev bench --update-readme) -->"
LINE_END = "<!-- speed-line:end -->"


def markdown(report):
    """README table of a report: one row per mesh size."""
    env = report["environment"]
    lines = [README_START, "",
             f"Measured {env['date'][:10]} on {env['cpu_count']} CPU cores, Python {env['python']}, "
             f"NumPy {env['numpy']}, Blender (bpy) {env['bpy'] or 'not run'}; "
             "10x10x10 B-spline lattice, squash + twist; medians.", "",
             "| vertices | Blender's Lattice modifier | deform f32 | XYZ solve f32, NumPy | solve / Blender "
             "(f32) | XYZ solve f32, compiled | compiled / Blender | XYZ solve f64 | solve / Blender (f64) "
             "| bytes per vertex f32 / f64 | bind f32 |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in report["results"]:
        f32, f64 = r["dtypes"]["float32"], r["dtypes"]["float64"]
        bl = r.get("blender")
        ratio = r.get("ratios_vs_blender")
        blender = f"{bl['execution_time_ms_median']:.1f} ms" if bl else "-"
        r32 = f"{ratio['float32']['solve_xyz']:.2f}x" if ratio else "-"
        r64 = f"{ratio['float64']['solve_xyz']:.2f}x" if ratio else "-"
        fast = f32.get("solve_xyz_compiled_ms_median")
        fast_ms = f"{fast:.1f} ms" if fast is not None else "-"
        rfast = f"{ratio['float32']['solve_xyz_compiled']:.2f}x" if ratio and fast is not None else "-"
        lines.append(
            f"| {r['n_verts']:,} | {blender} | {f32['deform_ms_median']:.1f} ms | "
            f"{f32['solve_xyz_ms_median']:.1f} ms | {r32} | {fast_ms} | {rfast} | "
            f"{f64['solve_xyz_ms_median']:.1f} ms | {r64} | "
            f"{f32['bytes_per_vertex']:.0f} / {f64['bytes_per_vertex']:.0f} | {f32['bind_ms']:.0f} ms |")
    for r in report["results"]:
        fs = r.get("extension_frame_set")
        if fs:
            lines += ["", f"In Blender, {r['n_verts']:,} vertices, {fs['frames']} animated frames after "
                      f"{FRAME_SET_WARMUPS} not timed: "
                      f"`scene.frame_set()` takes {fs['vpffd_frame_set_ms_median']:.1f} ms with VP-FFD (XYZ, "
                      f"{fs.get('kernels') or 'NumPy'} kernels) "
                      f"against {fs['plain_frame_set_ms_median']:.1f} ms with a plain Lattice modifier "
                      f"({fs['frame_set_ratio']:.2f}x, the median of {len(fs.get('frame_set_ratio_runs', [1]))} "
                      "runs: " + ", ".join(f"{x:.2f}x" for x in fs.get("frame_set_ratio_runs", [fs["frame_set_ratio"]]))
                      + f"); the extension's own work beyond the core's evaluation (the solve and the frame's "
                      f"own passes, {fs['vpffd_core_solve_ms_median']:.1f} ms) is {fs['handler_overhead_ms_median']:.1f} ms."]
    gpu = report.get("gpu")
    if gpu and gpu["rows"]:
        kind = "software OpenGL, not a GPU" if gpu["software_renderer"] else "a hardware GPU"
        lines += ["", f"GPU path (compute shaders) on this machine's renderer, {gpu['renderer']} ({kind}), "
                  "XYZ solve, float32:", "",
                  "| vertices | CPU solve | GPU solve | GPU / CPU | GPU upload (once) |", "|---:|---:|---:|---:|---:|"]
        for row in gpu["rows"]:
            lines.append(f"| {row['n_verts']:,} | {row['cpu_solve_ms_median']:.1f} ms | "
                         f"{row['gpu_solve_ms_median']:.1f} ms | {row['gpu_over_cpu']:.1f}x | "
                         f"{row['gpu_upload_ms']:.0f} ms |")
    elif gpu:
        lines += ["", f"GPU path not measured: {gpu['reason']}"]
    cages = report.get("cages")
    if cages:
        blender = {r["n_verts"]: r["blender"]["execution_time_ms_median"] for r in report["results"] if r.get("blender")}
        lines += ["", f"Cages of arbitrary topology (20 cells, depth {cages[0]['depth']}, float32 as in the "
                  "extension; Blender has no such modifier, its Lattice modifier's time on the same mesh is "
                  "given for scale):", "",
                  "| cage | vertices | bind | deform | XYZ solve | ns per vertex | Lattice modifier | volume error |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in cages:
            bl = blender.get(r["n_verts"])
            lines.append(f"| {r['cage']} | {r['n_verts']:,} | {r['bind_ms'] / 1e3:.1f} s | {r['deform_ms_median']:.1f} ms | "
                         f"{r['solve_xyz_ms_median']:.1f} ms | {r['solve_xyz_ns_per_vertex']:.0f} | "
                         f"{f'{bl:.1f} ms' if bl else '-'} | {r['relative_error']:.0e} |")
        fits = {r["cage"]: r.get("solve_fitted_exponent") for r in cages if r.get("solve_fitted_exponent")}
        if fits:
            lines += ["", "Cage solve time grows as " + ", ".join(f"V^{k:.2f} ({n})" for n, k in fits.items())
                      + " (1.00 = linear)."]
    conv = report.get("cage_convergence")
    if conv:
        lines += ["", f"A {conv['cage_cells']}-cell box cage against the tricubic B-spline FFD of the same "
                  "control points (interior points, lattice spacing 0.4): max distance "
                  + ", ".join(f"{e:.2g} at depth {d}" for d, e in zip(conv["depths"], conv["max_error"])) + "."]
    lin = report["summary"]["linearity"]
    if "fitted_exponent" in lin["float32"]["solve_xyz"]:
        lines += ["", f"Solve time grows as V^{lin['float32']['solve_xyz']['fitted_exponent']:.2f} (float32) and "
                  f"V^{lin['float64']['solve_xyz']['fitted_exponent']:.2f} (float64) over these sizes "
                  "(1.00 = linear)."]
    lines += ["", README_END]
    return "\n".join(lines)


def speed_line(report):
    """The front page's sentence on speed from a report, or None when the report has no figure
    against Blender: a frame in Blender where it was measured, else the solve alone."""
    env = report["environment"]
    head = f"Measured by `./dev bench` on {env['date'][:10]}, {env['cpu_count']} CPU cores, Blender {env['bpy']}: "
    for r in report["results"]:
        fs = r.get("extension_frame_set")
        if fs:
            return (head + f"a mesh of {r['n_verts']:,} vertices in a 10x10x10 B-spline lattice plays at "
                    f"{fs['vpffd_frame_set_ms_median']:.1f} ms a frame (`scene.frame_set()`) with VP-FFD correcting "
                    f"along X, Y and Z ({fs.get('kernels') or 'NumPy'} kernels), against "
                    f"{fs['plain_frame_set_ms_median']:.1f} ms with Blender's Lattice modifier alone "
                    f"({fs['frame_set_ratio']:.1f}x); VP-FFD's core evaluation (the solve and the frame's own "
                    f"passes) is {fs['vpffd_core_solve_ms_median']:.1f} ms of it.")
    rows = [r for r in report["results"] if r.get("blender")]
    if not rows:
        return None
    r = rows[-1]
    f32 = r["dtypes"]["float32"]
    solve = f32.get("solve_xyz_compiled_ms_median") or f32["solve_xyz_ms_median"]
    kind = "compiled" if f32.get("solve_xyz_compiled_ms_median") else "NumPy"
    return (head + f"on a mesh of {r['n_verts']:,} vertices in a 10x10x10 B-spline lattice, VP-FFD's solve "
            f"along X, Y and Z takes {solve:.1f} ms ({kind} kernels, float32) against "
            f"{r['blender']['execution_time_ms_median']:.1f} ms for Blender's Lattice modifier.")


def _rewrite(path, start, end, block):
    """Replace the text from marker `start` to marker `end` (both kept) of file `path` by `block`
    (which begins with `start` and ends with `end`)."""
    with open(path) as fh:
        text = fh.read()
    a, b = text.find(start), text.find(end)
    if a < 0 or b < a:
        raise SystemExit(f"{path}: markers {start} ... {end} not found")
    with open(path, "w") as fh:
        fh.write(text[:a] + block + text[b + len(end):])


def update_readme(report, path=SPEED_PAGE, readme=README):
    """Write the report's tables into `path` (docs/speed.md) and its speed line into `readme`."""
    _rewrite(path, README_START, README_END, markdown(report))
    log(f"updated the benchmark tables in {path}")
    line = speed_line(report)
    if line is not None:
        _rewrite(readme, LINE_START, LINE_END, f"{LINE_START}\n{line}\n{LINE_END}")
        log(f"updated the speed line in {readme}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="6,7,8",
                    help="icosphere subdivisions, comma-separated (6: 40,962, 7: 163,842, 8: 655,362 verts)")
    ap.add_argument("--repeat", type=int, default=7, help="timed runs per figure (sizes >= 8: max(3, repeat//2))")
    ap.add_argument("--out", help="also write the JSON report to this file")
    ap.add_argument("--no-blender", action="store_true", help="skip Blender's Lattice modifier (no bpy needed)")
    ap.add_argument("--update-readme", action="store_true",
                    help="rewrite the tables of docs/speed.md and the speed line of README.md")
    ap.add_argument("--no-gpu", action="store_true", help="skip the GPU (compute shader) path")
    ap.add_argument("--no-cage", action="store_true", help="skip the cages of arbitrary topology")
    ap.add_argument("--no-stack", action="store_true", help="skip the modifier-stack frame_set figures")
    ap.add_argument("--stack-only", action="store_true",
                    help="only the modifier-stack figures (benchmarks/stack_benchmark.py)")
    ap.add_argument("--shot-size", action="store_true",
                    help="only VP-FFD's added cost against the number of unrelated objects "
                         "(benchmarks/shot_size.py)")
    ap.add_argument("--no-shot-size", action="store_true", help="skip the shot-size figures")
    ap.add_argument("--no-scaling", action="store_true",
                    help="skip the table of the core's solve and re-embedding on 1, 2, ... all cores")
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    if not sizes or args.repeat < 1:
        ap.error("need at least one size and --repeat >= 1")
    use_blender = not args.no_blender
    if use_blender:
        _harness().isolate_user_resources()   # before bpy is imported: the extension installs there
    if args.stack_only:
        if not use_blender:
            ap.error("--stack-only needs Blender")
        return stack_main(args)
    if args.shot_size:
        if not use_blender:
            ap.error("--shot-size needs Blender")
        return shot_size_main(args)

    t0 = time.perf_counter()
    if not compiled.load():
        log(f"compiled kernels not measured: {compiled.why()}")
    env = environment(use_blender)
    log(f"VP-FFD benchmark: sizes {sizes}, repeat {args.repeat}, lattice {LATTICE_SHAPE} BSPLINE, "
        f"numpy {env['numpy']}, bpy {env['bpy']}, {env['cpu_count']} CPUs")
    # Warm up the code paths once on a small mesh so the first timed bind is not a cold start.
    wv, wf = vp.icosphere(3, RADIUS)
    wlat = vp.Lattice(LATTICE_SHAPE, interpolation="BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    for _, dt in DTYPES:
        vp.bind(wlat, wv, wf, dtype=dt).solve(deformed_points(wlat), axes="XYZ")
    results = [bench_size(s, args.repeat, use_blender) for s in sizes]
    gpu = gpu_figures([s for s in sizes if s >= 7], args.repeat) if use_blender and not args.no_gpu else None
    cages = None if args.no_cage else cage_figures(sizes, args.repeat)
    convergence = None if args.no_cage else cage_convergence()
    stack = stack_figures() if use_blender and not args.no_stack else None
    scaling = None if args.no_scaling else scaling_figures()
    shot = shot_size_figures() if use_blender and not args.no_shot_size else None
    report = {
        "benchmark": "vpffd",
        "lattice": {"shape": list(LATTICE_SHAPE), "interpolation": "BSPLINE", "bounds": [[-0.5] * 3, [0.5] * 3],
                    "deformation": "squash z*0.6, twist 0.5 rad per unit z about z, N(0, 0.01) noise seed 0"},
        "mesh": {"kind": "icosphere", "radius": RADIUS},
        "environment": env,
        "results": results,
        "summary": summarize(results, use_blender),
        "gpu": gpu,
        "cages": cages,
        "cage_convergence": convergence,
        "stack": stack,
        "scaling": scaling,
        "shot_size": shot,
        "total_seconds": None,
    }
    report["total_seconds"] = time.perf_counter() - t0
    _emit(report, args.out)
    if args.update_readme:
        update_readme(report)
        if stack is not None:
            update_stack_readme(stack)
        if shot is not None:
            update_shot_size_readme(shot)
    log(f"done in {report['total_seconds']:.1f} s")
    return 0


def _emit(report, out):
    """The JSON report to stdout, and to the file `out` when given."""
    text = json.dumps(report, indent=2)
    print(text)
    if out:
        with open(out, "w") as fh:
            fh.write(text + "\n")


def _install_extension():
    _extension_status()
    return _EXTENSION["module"]


def scaling_figures():
    """The core's XYZ solve and re-embedding on 1, 2, ... all cores (benchmarks/scaling.py); the
    table goes to stderr."""
    from benchmarks import scaling
    report = scaling.run()
    log("  scaling with the worker threads:\n" + scaling.markdown(report))
    return report


def stack_figures():
    from benchmarks import stack_benchmark
    return stack_benchmark.run(_install_extension)


def update_stack_readme(stack, path=SPEED_PAGE):
    """Rewrite the modifier-stack table between its markers in docs/speed.md."""
    from benchmarks import stack_benchmark
    start, end = "<!-- stack-bench:start -->", "<!-- stack-bench:end -->"
    with open(path) as fh:
        text = fh.read()
    if start not in text or end not in text:
        raise SystemExit(f"{path} has no {start} ... {end} markers")
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    env = environment(True)
    import importlib
    state, why = importlib.import_module(_EXTENSION["module"] + ".operators.compiled_backend").status()
    kernels = "compiled kernels" if state == "ready" else f"NumPy kernels: {why}"
    body = (f"\n<!-- written by ./dev bench --stack-only --update-readme -->\n\nMeasured by `./dev bench "
            f"--stack-only` on {datetime.date.today().isoformat()} with Blender {env['bpy']} (the `bpy` "
            f"module), {env['cpu_count']} CPU cores; VP-FFD on the CPU with {kernels}.\n\n"
            + stack_benchmark.markdown(stack) + "\n")
    with open(path, "w") as fh:
        fh.write(head + start + body + end + tail)


def _one_table_main(args, name, key, figures, update):
    """Run one table's benchmark alone (`figures()`), emit its report as `key`, and rewrite its
    table with `update` when asked."""
    t0 = time.perf_counter()
    table = figures()
    report = {"benchmark": name, "environment": environment(True), key: table,
              "total_seconds": time.perf_counter() - t0}
    _emit(report, args.out)
    if args.update_readme:
        update(table)
    log(f"done in {report['total_seconds']:.1f} s")
    return 0


def stack_main(args):
    return _one_table_main(args, "vpffd-stack", "stack", stack_figures, update_stack_readme)


def shot_size_figures():
    """VP-FFD's added cost per frame and per unrelated edit against the number of unrelated
    objects, each figure from fresh processes (benchmarks/shot_size.py); the table to stderr."""
    from benchmarks import shot_size
    report = shot_size.run()
    log("  a shot's size:\n" + shot_size.markdown(report))
    return report


def update_shot_size_readme(shot, path=SPEED_PAGE):
    """Rewrite the shot-size table between its markers in docs/speed.md."""
    from benchmarks import shot_size
    env = environment(True)
    body = (f"\n<!-- written by ./dev bench --shot-size --update-readme -->\n\nMeasured by `./dev bench "
            f"--shot-size` on {datetime.date.today().isoformat()} with Blender {env['bpy']} (the `bpy` "
            f"module), {env['cpu_count']} CPU cores; medians of {shot['rounds']} rounds, each a fresh "
            f"process of {shot['frames']} frames and {shot['edits']} edits.\n\n"
            + shot_size.markdown(shot) + "\n")
    start, end = "<!-- shot-size:start -->", "<!-- shot-size:end -->"
    _rewrite(path, start, end, start + body + end)


def shot_size_main(args):
    return _one_table_main(args, "vpffd-shot-size", "shot_size", shot_size_figures,
                           update_shot_size_readme)


if __name__ == "__main__":
    sys.exit(main())
