"""How the core's per-frame work scales with the worker threads: the XYZ solve and a re-embedding
(a bind with the faces' topology reused, as a mesh moving through the lattice pays on every frame)
on 1, 2, ... every core of this machine, against the ideal (the one-thread time divided by the
threads). The core alone (NumPy, and numba where it is installed), no Blender:

    python -m benchmarks.scaling [--subdivisions 7] [--rounds 7] [--max-threads N]

`./dev bench` runs it too and prints the table. Prints JSON on stdout, the table on stderr.
"""
import argparse
import json
import os
import sys

import numpy as np

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)

import vpffd_addon as vp  # noqa: E402
from benchmarks.timing import timed  # noqa: E402
from vpffd_addon import compiled, parallel  # noqa: E402

LATTICE = (6, 6, 6)


def run(subdivisions=7, rounds=7, max_threads=None):
    """{"vertices", "kernels", "rows": [{"threads", "solve_ms", "reembed_ms", ...}]}: medians of
    `rounds` at every thread count from 1 to `max_threads` (default: every core)."""
    kernels = "compiled" if compiled.load() else f"NumPy ({compiled.why()})"
    v, f = vp.icosphere(subdivisions, 0.45)
    moved = v * 1.02 + 0.01
    lat = vp.Lattice(LATTICE, "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    P = lat.rest_points * [1.0, 1.0, 0.7] + np.random.default_rng(0).normal(0, 0.01, lat.rest_points.shape)
    topology = vp.Topology(f, len(v))
    cores = parallel.WORKERS
    rows = []
    previous = parallel.WORKERS
    try:
        for n in range(1, (max_threads or cores) + 1):
            parallel.set_workers(n)
            b = vp.bind(lat, v, f, dtype=np.float32, topology=topology)
            b.solve(P, axes="XYZ")                                  # warm: faces around slots made

            def reembed():
                moved_b = vp.bind(lat, moved, topology.tris, dtype=np.float32, topology=topology)
                if compiled.ready():
                    compiled.incidence(moved_b)                     # what its first solve needs
            reembed()
            rows.append({"threads": n, "parts": len(b.block_parts),
                         "solve_ms": timed(lambda: b.solve(P, axes="XYZ"), rounds)[0],
                         "reembed_ms": timed(reembed, rounds)[0]})
    finally:
        parallel.set_workers(previous)
    for row in rows:
        for what in ("solve", "reembed"):
            ideal = rows[0][f"{what}_ms"] / row["threads"]
            row[f"{what}_ideal_ms"] = ideal
            row[f"{what}_efficiency"] = ideal / row[f"{what}_ms"]
    return {"vertices": len(v), "lattice": list(LATTICE), "kernels": kernels, "cores": cores, "rows": rows}


def markdown(report):
    """The scaling table as Markdown."""
    lines = [f"{report['vertices']:,} vertices, {'x'.join(map(str, report['lattice']))} B-spline lattice, "
             f"XYZ, float32, {report['kernels']} kernels, {report['cores']} cores (medians):", "",
             "| threads | XYZ solve | ideal | efficiency | re-embedding | ideal | efficiency |",
             "|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        lines.append(f"| {r['threads']} | {r['solve_ms']:.1f} ms | {r['solve_ideal_ms']:.1f} ms | "
                     f"{100 * r['solve_efficiency']:.0f}% | {r['reembed_ms']:.1f} ms | {r['reembed_ideal_ms']:.1f} ms | "
                     f"{100 * r['reembed_efficiency']:.0f}% |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--subdivisions", type=int, default=7)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--max-threads", type=int, default=None)
    args = ap.parse_args(argv)
    report = run(args.subdivisions, args.rounds, args.max_threads)
    print(markdown(report), file=sys.stderr)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
