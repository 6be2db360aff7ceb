"""VP-FFD GPU benchmark: CPU (NumPy, float32 binding) and GPU (Blender compute shaders) frame times.

Run from the repository root with a bpy venv:

    .venv/bin/python benchmarks/gpu_benchmark.py [--sizes 7,8] [--axes XYZ] [--repeat 5] [--out FILE.json]

Icospheres of subdivision 7 and 8 (163,842 / 655,362 vertices, radius 0.45) in a 10x10x10 B-spline
lattice spanning [-0.5, 0.5]^3, deformed as in benchmarks/benchmark.py. The GPU backend is
initialised headless by rendering one tiny Workbench frame. For each size it reports bind, GPU
upload (once per binding), and per frame the CPU solve and the GPU solve (median and min), with the
agreement of the two (max coordinate difference / lattice size, relative volume error). On software
OpenGL (Mesa llvmpipe) the GPU path is expected to be slower than NumPy: the figures say so, they
are not a target. Progress to stderr, JSON to stdout (and --out).
"""
import argparse
import importlib.util
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
from benchmarks.benchmark import deformed_points  # noqa: E402  (the same deformation)

LATTICE_SHAPE = (10, 10, 10)
RADIUS = 0.45


def log(*args):
    print(*args, file=sys.stderr, flush=True)


def load_gpu_backend():
    """operators/gpu_backend.py as a standalone module (the operators package needs the extension)."""
    spec = importlib.util.spec_from_file_location(
        "vpffd_gpu_backend", os.path.join(_ROOT, "operators", "gpu_backend.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def init_gpu():
    """Initialise Blender's GPU backend headless: render one 4x4 Workbench frame. (ok, reason)."""
    try:
        import bpy
        scene = bpy.context.scene
        if scene.camera is None:  # a render needs a camera
            scene.camera = bpy.data.objects.new("gpu-init camera", bpy.data.cameras.new("gpu-init camera"))
            scene.collection.objects.link(scene.camera)
        scene.render.engine = "BLENDER_WORKBENCH"
        scene.render.resolution_x = scene.render.resolution_y = 4
        scene.render.resolution_percentage = 100
        bpy.ops.render.render()
        return True, "ok"
    except Exception as exc:
        return False, f"{type(exc).__name__}: {exc}"


def timed(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return out, 1000 * statistics.median(times), 1000 * min(times)


def bench_size(gb, sub, axes, repeat):
    verts, tris = vp.icosphere(sub, RADIUS)
    lat = vp.Lattice(LATTICE_SHAPE, interpolation="BSPLINE")
    P = deformed_points(lat)
    log(f"icosphere({sub}): {len(verts)} vertices, {len(tris)} faces")
    t = time.perf_counter()
    b = vp.bind(lat, verts, tris, dtype=np.float32)
    bind_ms = 1000 * (time.perf_counter() - t)
    cpu, cpu_med, cpu_min = timed(lambda: b.solve(P, axes=axes), repeat)
    log(f"  CPU solve {axes}: median {cpu_med:.1f} ms, min {cpu_min:.1f} ms")
    t = time.perf_counter()
    solver = gb.GPUSolver(b)
    upload_ms = 1000 * (time.perf_counter() - t)
    t = time.perf_counter()
    solver.solve(P, axes=axes)            # first frame: the driver compiles the kernels
    first_ms = 1000 * (time.perf_counter() - t)
    gpu, gpu_med, gpu_min = timed(lambda: solver.solve(P, axes=axes), repeat)
    log(f"  GPU solve {axes}: median {gpu_med:.1f} ms, min {gpu_min:.1f} ms "
        f"(upload {upload_ms:.0f} ms, first frame {first_ms:.0f} ms)")
    vol = vp.signed_volume(gpu.verts, tris, origin=lat.centre)
    row = dict(subdivisions=sub, n_verts=len(verts), n_faces=len(tris), axes=axes, bind_ms=bind_ms,
               cpu_solve_ms_median=cpu_med, cpu_solve_ms_min=cpu_min,
               gpu_upload_ms=upload_ms, gpu_first_frame_ms=first_ms,
               gpu_solve_ms_median=gpu_med, gpu_solve_ms_min=gpu_min,
               gpu_over_cpu=gpu_med / cpu_med,
               gpu_texture_mb=solver.nbytes / 2 ** 20,
               max_coord_diff_over_lattice_size=float(np.abs(gpu.verts - cpu.verts).max() / lat.size),
               gpu_volume_rel_error=float(abs(vol - cpu.target_volume) / abs(cpu.target_volume)))
    solver.free()
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="7,8", help="icosphere subdivisions (7: 163,842 vertices, 8: 655,362)")
    ap.add_argument("--axes", default="XYZ")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    gb = load_gpu_backend()
    ok, why = init_gpu()
    avail, reason = gb.available()
    report = dict(date=time.strftime("%Y-%m-%d"), machine=platform.machine(), cpus=os.cpu_count(),
                  python=platform.python_version(), gpu_init=why, gpu_available=avail, gpu_reason=reason,
                  renderer=gb.renderer(), software_renderer=gb.is_software_renderer(), rows=[])
    try:
        import bpy
        report["blender"] = bpy.app.version_string
    except Exception:
        pass
    log(f"GPU: {reason}")
    if avail:
        for sub in (int(s) for s in args.sizes.split(",") if s):
            report["rows"].append(bench_size(gb, sub, args.axes, args.repeat))
    text = json.dumps(report, indent=2)
    print(text)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(text + "\n")
    log("\n| vertices | CPU solve (ms) | GPU solve (ms) | GPU / CPU | upload (ms) |")
    for r in report["rows"]:
        log(f"| {r['n_verts']:,} | {r['cpu_solve_ms_median']:.0f} | {r['gpu_solve_ms_median']:.0f} | "
            f"{r['gpu_over_cpu']:.1f}x | {r['gpu_upload_ms']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
