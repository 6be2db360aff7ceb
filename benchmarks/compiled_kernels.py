"""The compiled solve against the NumPy steps, pass by pass, in one process, timed alternately (so
that a machine's drift hits both alike):

    python -m benchmarks.compiled_kernels [--subdivisions 7] [--lattice 6] [--rounds 9] [--threads N]

An icosphere (163,842 vertices at 7 subdivisions, radius 0.45) in a B-spline lattice spanning
[-0.5, 0.5]^3, squashed and jittered, float32 (as the extension binds). Prints JSON: the milliseconds
(median of the rounds) of

- `forward`: one component of X = x0 + S B D;
- `axis_pass`: what one correction direction needs from the mesh: the gradient along an axis,
  (S B)^T g, x0_a . g and sum |s g| (one fused pass compiled; four NumPy calls);
- `verts`: the deformed vertices from the slots;
- `solve`: a whole XYZ solve;
- `gathers` and `moments` (compiled only): the gradient pass's two halves apart, the gradient
  around every slot's faces and, per block, the moments of g s (the transposed entries are made from them in `reduce_runs`, once per run);

for the NumPy steps and the compiled ones, the bytes each pass reads and writes per slot, the
time `compiled.load()` took, how far the two solves' vertices are apart (in lattice sizes), and
what this machine does at best on one thread in the loops the passes are made of (`floor`:
multiply-adds a nanosecond, a gathered neighbour's cost), from which docs/performance.md works out
each pass's floor.
"""
import argparse
import json
import time

import numpy as np

import vpffd_addon as vp
from vpffd_addon import compiled, parallel, solve_kernels
from vpffd_addon.steps import NumpySteps


def _ms(fn):
    t0 = time.perf_counter()
    fn()
    return 1e3 * (time.perf_counter() - t0)


def problem(subdivisions, lattice):
    """(binding, points): the benchmark's float32 binding and squashed, jittered control points."""
    v, f = vp.icosphere(subdivisions, 0.45)
    lat = vp.Lattice((lattice,) * 3, "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    b = vp.bind(lat, v, f, dtype=np.float32)
    rng = np.random.default_rng(0)
    P = lat.rest_points + rng.normal(0, 0.02, lat.rest_points.shape)
    P[:, 2] *= 0.7
    return b, P


def passes(steps, D):
    """{name: callable} of one kind of steps' passes at displacements D."""
    def axis_pass():
        g = steps.axis_gradient(0, D)
        steps.transpose(g, None)
        steps.x0_dot(0, g, None)
        steps.flux(g, None)
    return {"forward": lambda: steps._forward([0], D), "axis_pass": axis_pass, "verts": lambda: steps.verts(D)}


def halves(b, D):
    """{"gathers": callable, "moments": callable}: the compiled gradient pass's two halves, each
    as a kernel of its own (compiled here, from the solve's own helpers) over every block on the
    worker threads: the gradient around the faces of every slot along x, and per block the
    moments of g s."""
    import numba
    fast = numba.njit(nogil=True, fastmath={"reassoc", "contract"}, error_model="numpy")
    steps = compiled.CompiledSteps(b)
    steps.refresh((0, 1, 2), D)
    start, inc, ring = compiled.incidence(b)
    n_blocks = b.block_cell.shape[0]
    g, M = np.empty(b.x0.shape[1]), np.empty((n_blocks, 64))

    @fast
    def gathers(xp, xq, start, inc, ring, g, b0, b1):
        bs = g.shape[0] // n_blocks
        st, rg, out = start[b0 * bs:b1 * bs + 1], ring[b0 * bs:b1 * bs], g[b0 * bs:b1 * bs]
        for v in range(out.shape[0]):
            out[v] = solve_kernels.fan_gradient(xp, xq, inc[st[v]:st[v + 1]], rg[v]) * (1.0 / 6.0)

    @fast
    def moments(params, g, M, b0, b1):
        bs = g.shape[0] // M.shape[0]
        pu, pv, pw = np.empty((4, bs)), np.empty((4, bs)), np.empty((4, bs))
        h = np.empty(bs)
        for bl in range(b0, b1):
            solve_kernels.block_powers(params, bl * bs, bs, pu, pv, pw)
            solve_kernels.block_moments(g[bl * bs:(bl + 1) * bs], bs, pu, pv, pw, h, M[bl])
    parts = b.block_parts
    X = steps.X
    return {"gathers": lambda: parallel.run(lambda p: gathers(X[1], X[2], start, inc, ring, g, p.start, p.stop), parts),
            "moments": lambda: parallel.run(lambda p: moments(steps.params, g, M, p.start, p.stop), parts)}


def floor(b):
    """What this machine does at best, on one thread, in the loops the passes are made of (compiled
    here): {"fma_per_ns_f32", "fma_per_ns_f64": multiply-adds a nanosecond in a vectorised Horner
    loop over 4,096 values (in cache), 16 deep, as the forward's evaluation and the moments are;
    "ns_per_gather": a slot's ring of neighbours gathered (both coordinates of each, summed, no
    products) per neighbour, the gradient pass's own index pattern}. A pass's floor is then the
    larger of its arithmetic and its gathers at these rates and its bytes at the memory's."""
    import numba
    fast = numba.njit(nogil=True, fastmath={"reassoc", "contract"}, error_model="numpy")

    @fast
    def horner(x, k, out, reps):
        for _ in range(reps):
            for s in range(x.shape[0]):
                u = x[s]
                acc = k[0]
                for j in range(1, 17):
                    acc = acc * u + k[j]
                out[s] += acc

    @fast
    def gathers(xp, xq, start, inc, out):
        for v in range(start.shape[0] - 1):
            acc = 0.0
            fan = inc[start[v]:start[v + 1]]        # (indexed from 0: as the passes do it)
            for e in range(fan.shape[0]):
                n = fan[e]
                acc += xp[n] + xq[n]
            out[v] = acc

    report = {}
    for dtype, name in ((np.float32, "fma_per_ns_f32"), (np.float64, "fma_per_ns_f64")):
        x = np.linspace(0.1, 0.9, 4096).astype(dtype)
        k = np.linspace(-1.0, 1.0, 17).astype(dtype)
        out = np.zeros(4096, dtype)
        horner(x, k, out, 1)
        reps = 200
        t = min(_ms(lambda: horner(x, k, out, reps)) for _ in range(5))
        report[name] = round(16 * 4096 * reps / (t * 1e6), 2)
    steps = compiled.CompiledSteps(b)
    steps.refresh((0, 1, 2), np.zeros((b.lattice.n_points, 3)))     # (the slots' coordinates made)
    start, inc, _ring = compiled.incidence(b)
    out = np.empty(b.x0.shape[1])
    gathers(steps.X[1], steps.X[2], start, inc, out)
    t = min(_ms(lambda: gathers(steps.X[1], steps.X[2], start, inc, out)) for _ in range(9))
    report["ns_per_gather"] = round(t * 1e6 / len(inc), 3)
    return report


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--subdivisions", type=int, default=7)
    ap.add_argument("--lattice", type=int, default=6)
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--threads", type=int, default=None, help="worker threads (default: every core)")
    args = ap.parse_args(argv)
    if args.threads:
        parallel.set_workers(args.threads)
    t0 = time.perf_counter()
    if not compiled.load():
        raise SystemExit(f"compiled kernels unavailable: {compiled.why()}")
    load_s = time.perf_counter() - t0
    b, P = problem(args.subdivisions, args.lattice)
    D = P - b.lattice.rest_points
    kinds = {"numpy": NumpySteps, "compiled": compiled.CompiledSteps}
    steps = {k: make(b) for k, make in kinds.items()}
    for s in steps.values():
        s.refresh((0, 1, 2), D)
    work = {k: passes(s, D) for k, s in steps.items()}
    for k, make in kinds.items():
        work[k]["solve"] = lambda make=make: vp.solve.solve(b, P, axes="XYZ", steps=make)
    work["compiled"].update(halves(b, D))
    times = {f"{what}_{k}": [] for k in kinds for what in work[k]}
    for _ in range(args.rounds):
        for k in kinds:
            for what, fn in work[k].items():
                times[f"{what}_{k}"].append(_ms(fn))
    ref = vp.solve.solve(b, P, axes="XYZ", steps=NumpySteps)
    out = vp.solve.solve(b, P, axes="XYZ", steps=compiled.CompiledSteps)
    n_slots = b.x0.shape[1]
    start, entries, ring = compiled.incidence(b)
    report = {"vertices": b.n_verts, "slots": n_slots, "lattice": list(b.lattice.shape), "threads": len(b.block_parts),
              "load_seconds": round(load_s, 2),
              "max_vertex_difference_rel": float(np.abs(out.verts - ref.verts).max() / b.lattice.size),
              "volume_rel_error_compiled": abs(out.volume / out.target_volume - 1),
              # What the compiled passes stream per slot (float32): params 16 B, x0 and X 4 B each per
              # component, the faces around a slot (4 B a neighbour where they close a fan, 8 B a
              # face elsewhere, with where they start and whether a ring) and the gathered
              # coordinates; the NumPy steps read 80 B of stored weights per slot per product.
              "compiled_bytes_per_slot": {"forward": 16 + 8, "axis_pass": round(
                  16 + 4 + 8 + (entries.nbytes + start.nbytes + ring.nbytes) / n_slots + 8, 1)},
              "ring_slots": int(ring.sum()),
              "numpy_bytes_per_slot": {"forward": 80 + 8, "transpose": 80 + 8}}
    report.update({k: round(float(np.median(v)), 2) for k, v in times.items()})
    report["machine_one_thread"] = floor(b)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
