"""The compiled kernels against the NumPy steps, in one process, timed alternately (so that a
machine's drift hits both alike): `python -m benchmarks.compiled_kernels [--subdivisions 7]`.

Prints JSON: the milliseconds (median of the rounds) of the volume gradient along an axis and of a
whole XYZ solve (163,842 vertices at 7 subdivisions, a 6x6x6 B-spline lattice, float32), for the
NumPy steps and the compiled ones, the time `compiled.load()` took, and how far the two solves'
vertices are apart (in units of the lattice's size)."""
import argparse
import json
import time

import numpy as np

import vpffd_addon as vp
from vpffd_addon import compiled
from vpffd_addon.steps import NumpySteps


def _ms(fn):
    t0 = time.perf_counter()
    fn()
    return 1e3 * (time.perf_counter() - t0)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--subdivisions", type=int, default=7)
    ap.add_argument("--rounds", type=int, default=7)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    if not compiled.load():
        raise SystemExit(f"compiled kernels unavailable: {compiled.why()}")
    load_s = time.perf_counter() - t0
    v, f = vp.icosphere(args.subdivisions, 0.8)
    lat = vp.Lattice((6, 6, 6), ("BSPLINE",) * 3)
    b = vp.bind(lat, v, f, dtype=np.float32)
    rng = np.random.default_rng(0)
    P = lat.rest_points + rng.normal(0, 0.03, lat.rest_points.shape)
    P[:, 2] *= 0.7
    D = P - lat.rest_points
    kinds = {"numpy": NumpySteps, "compiled": compiled.CompiledSteps}
    steps = {k: make(b) for k, make in kinds.items()}
    for s in steps.values():
        s.refresh((0, 1, 2), D)
    times = {f"{what}_{k}": [] for what in ("gradient", "solve") for k in kinds}
    for _ in range(args.rounds):
        for k, make in kinds.items():
            times[f"gradient_{k}"].append(_ms(lambda: steps[k]._gradient(1, 2)))
            times[f"solve_{k}"].append(_ms(lambda: vp.solve.solve(b, P, axes="XYZ", steps=make)))
    ref = vp.solve.solve(b, P, axes="XYZ", steps=NumpySteps)
    out = vp.solve.solve(b, P, axes="XYZ", steps=compiled.CompiledSteps)
    report = {"vertices": b.n_verts, "load_seconds": round(load_s, 2),
              "max_vertex_difference_rel": float(np.abs(out.verts - ref.verts).max() / np.ptp(lat.rest_points, 0).max())}
    report.update({k: round(float(np.median(v)), 2) for k, v in times.items()})
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
