"""VP-FFD GPU benchmark: CPU (NumPy, float32 binding) and GPU (Blender compute shaders) frame times.

Run from the repository root with a bpy venv:

    .venv/bin/python benchmarks/gpu_benchmark.py [--sizes 7,8] [--axes XYZ] [--repeat 5] [--out FILE.json]

or, on a GPU machine without Blender (any Python with NumPy and moderngl, OpenGL 4.3 through EGL):

    python3 benchmarks/gpu_benchmark.py --standalone --out benchmarks/results/gpu_hardware.json

`--standalone` runs the extension's own kernels and solve driver (operators/gpu_backend.py and the
modules beside it, vpffd_addon/solve.py) through benchmarks/moderngl_gpu.py, which supplies the calls of Blender's
`gpu` module; `--readme FILE.json` then writes such a run's figures into docs/speed.md.

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
    """operators/gpu_backend.py as a standalone module (the operators package needs the extension);
    it loads the modules beside it (`gpu_shaders`, `gpu_device`, `gpu_solver`) itself."""
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
    kernels = kernel_breakdown(gb, solver, P, axes)
    vol = vp.signed_volume(gpu.verts, tris, origin=lat.centre)
    row = dict(subdivisions=sub, n_verts=len(verts), n_faces=len(tris), axes=axes, bind_ms=bind_ms,
               cpu_solve_ms_median=cpu_med, cpu_solve_ms_min=cpu_min,
               gpu_upload_ms=upload_ms, gpu_first_frame_ms=first_ms,
               gpu_solve_ms_median=gpu_med, gpu_solve_ms_min=gpu_min,
               gpu_over_cpu=gpu_med / cpu_med,
               gpu_texture_mb=solver.nbytes / 2 ** 20, gpu_kernels=kernels,
               max_coord_diff_over_lattice_size=float(np.abs(gpu.verts - cpu.verts).max() / lat.size),
               gpu_volume_rel_error=float(abs(vol - cpu.target_volume) / abs(cpu.target_volume)))
    solver.free()
    return row


def kernel_breakdown(gb, solver, P, axes):
    """One more solve with every dispatch waited for: {kernel: [dispatches, ms]} and the rest
    (the driver, uploads and read-backs) as "other". Only where the standalone `gpu` can wait
    (`moderngl_gpu.context().finish()`); None inside Blender."""
    import gpu
    ctx = getattr(gpu, "_standalone_context", None)
    if ctx is None:
        return None
    names = {id(sh): name for kernels in gb.gpu_device.kernel_cache.values() for name, sh in kernels.items()}
    out, real = {}, gb.gpu_solver.dispatch          # (where the solver looks it up)

    def timed_dispatch(shader, n):
        ctx().finish()
        t = time.perf_counter()
        groups = real(shader, n)
        ctx().finish()
        row = out.setdefault(names.get(id(shader), "?"), [0, 0.0])
        row[0] += 1
        row[1] += 1000 * (time.perf_counter() - t)
        return groups

    gb.gpu_solver.dispatch = timed_dispatch
    try:
        t = time.perf_counter()
        solver.solve(P, axes=axes)
        total = 1000 * (time.perf_counter() - t)
    finally:
        gb.gpu_solver.dispatch = real
    out["other"] = [0, total - sum(ms for _, ms in out.values())]
    return out


README_START = "<!-- gpu-hardware:start -->"
README_END = "<!-- gpu-hardware:end -->"


def readme_block(report):
    """The hardware table of docs/speed.md (markdown between its markers) from a --standalone
    run's JSON."""
    lines = [README_START, "<!-- written by: python3 benchmarks/gpu_benchmark.py --readme FILE.json -->", "",
             f"Measured {report['date']} by `benchmarks/gpu_benchmark.py --standalone` on {report['renderer']} "
             f"({report.get('gl_version', '')}), {report['cpus']} CPU cores, Python {report['python']}, "
             f"NumPy {report.get('numpy', '?')}; 10x10x10 B-spline lattice, XYZ, float32, medians (min). The "
             "CPU column is that machine's NumPy path; *kernels* and *the rest* (the solve driver, "
             "uploads of the control points, read-backs) come from one more solve that waits for "
             "every kernel to finish, so they add up to more than the solve itself:", "",
             "| vertices | GPU solve | kernels | the rest | CPU solve | GPU upload (once per embedding) "
             "| max difference / lattice size | volume error |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in report["rows"]:
        k = r.get("gpu_kernels") or {}
        kern = sum(ms for name, (_, ms) in k.items() if name != "other")
        other = k.get("other", [0, float("nan")])[1]
        lines.append(f"| {r['n_verts']:,} | {r['gpu_solve_ms_median']:.1f} ms ({r['gpu_solve_ms_min']:.1f}) "
                     f"| {kern:.1f} ms | {other:.1f} ms | {r['cpu_solve_ms_median']:.1f} ms "
                     f"| {r['gpu_upload_ms']:.0f} ms | {r['max_coord_diff_over_lattice_size']:.1e} "
                     f"| {r['gpu_volume_rel_error']:.1e} |")
    lines += ["", README_END]
    return "\n".join(lines)


SPEED_PAGE = os.path.join(_ROOT, "docs", "speed.md")     # the page the hardware table is on


def write_readme(path, readme=SPEED_PAGE):
    """Write the hardware table of the --standalone run `path` (JSON) into `readme`'s markers."""
    with open(path) as fh:
        report = json.load(fh)
    with open(readme) as fh:
        text = fh.read()
    a, b = text.index(README_START), text.index(README_END) + len(README_END)
    with open(readme, "w") as fh:
        fh.write(text[:a] + readme_block(report) + text[b:])
    log(f"{readme}: hardware GPU table from {path}")
    return 0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="7,8", help="icosphere subdivisions (7: 163,842 vertices, 8: 655,362)")
    ap.add_argument("--axes", default="XYZ")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out")
    ap.add_argument("--standalone", action="store_true",
                    help="no Blender: Blender's gpu calls through moderngl (benchmarks/moderngl_gpu.py)")
    ap.add_argument("--readme", metavar="FILE.json",
                    help="write a --standalone run's figures into docs/speed.md and exit")
    args = ap.parse_args(argv)
    if args.readme:
        return write_readme(args.readme)
    if args.standalone:
        from benchmarks import moderngl_gpu
        moderngl_gpu.install()
    gb = load_gpu_backend()
    ok, why = (True, "standalone (moderngl)") if args.standalone else init_gpu()
    avail, reason = gb.available()
    report = dict(date=time.strftime("%Y-%m-%d"), machine=platform.machine(), cpus=os.cpu_count(),
                  python=platform.python_version(), numpy=np.__version__, gpu_init=why,
                  gpu_available=avail, gpu_reason=reason, renderer=gb.renderer(),
                  software_renderer=gb.is_software_renderer(), standalone=args.standalone, rows=[])
    if args.standalone:
        import gpu
        report["gl_version"] = gpu.platform.version_get()
    else:  # (importing bpy would put Blender's own gpu module back in place of the standalone one)
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
