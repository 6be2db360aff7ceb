"""How the core's per-frame work scales with the worker threads: the XYZ solve and a re-embedding
(a bind with the faces' topology reused, as a mesh moving through the lattice pays on every frame)
on 1, 2, ... every core of this machine, against the ideal (the one-thread time divided by the
threads). The core alone (NumPy, and numba where it is installed), no Blender:

    python -m benchmarks.scaling [--subdivisions 7] [--rounds 7] [--max-threads N] [--team-parts K]
                                 [--passes]

`./dev bench` runs it too and prints the table. Prints JSON on stdout, the table on stderr.
`--team-parts K` runs the passes on numba's own threads from K parts on (`compiled.TEAM_PARTS`;
a K above the cores keeps them on the Python worker threads, as before numba's were used);
`--passes` adds where a solve's time goes on 1, 2, 4, ... threads: each pass, the transposed
product's reduction (one thread) and the rest (the closed forms, NumPy on one thread); on two
threads or more, a forward pass and the pass after it run in one hand-over (`forward_then_next`).
"""
import argparse
import collections
import json
import os
import sys
import time

import numpy as np

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)

import vpffd_addon as vp  # noqa: E402
from benchmarks.timing import timed  # noqa: E402
from vpffd_addon import compiled, parallel  # noqa: E402

LATTICE = (6, 6, 6)


def _problem(subdivisions):
    """(verts, faces, lattice, points, topology): an icosphere squashed and jittered in a B-spline
    lattice spanning [-0.5, 0.5]^3, the faces' topology made once."""
    v, f = vp.icosphere(subdivisions, 0.45)
    lat = vp.Lattice(LATTICE, "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    P = lat.rest_points * [1.0, 1.0, 0.7] + np.random.default_rng(0).normal(0, 0.01, lat.rest_points.shape)
    return v, f, lat, P, vp.Topology(f, len(v))


def run(subdivisions=7, rounds=7, max_threads=None):
    """{"vertices", "kernels", "rows": [{"threads", "solve_ms", "reembed_ms", ...}]}: medians of
    `rounds` at every thread count from 1 to `max_threads` (default: every core)."""
    kernels = "compiled" if compiled.load() else f"NumPy ({compiled.why()})"
    v, f, lat, P, topology = _problem(subdivisions)
    moved = v * 1.02 + 0.01
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


def passes(subdivisions=7, rounds=21, threads=None):
    """{threads: {pass name: ms, "transpose", "rest", "solve"}}: the mean milliseconds of one
    XYZ solve's passes (summed over the solve's calls of each), by thread count (default 1, 2, 4,
    ... and every core)."""
    v, f, lat, P, topology = _problem(subdivisions)
    cores = parallel.WORKERS
    threads = threads or sorted({1, 2, 4, 8, 12, 16, cores} & set(range(1, cores + 1)))
    spent = collections.Counter()
    over, transpose, counted = compiled.over, compiled.CompiledSteps.transpose, parallel.run_counted

    def timed_over(name, parts, *args, **kw):
        t0 = time.perf_counter()
        got = over(name, parts, *args, **kw)
        spent[name] += time.perf_counter() - t0
        return got

    def timed_counted(*args):
        # (a forward pass and the pass after it in one hand-over: `CompiledSteps._refresh_then`)
        t0 = time.perf_counter()
        counted(*args)
        spent["forward_then_next"] += time.perf_counter() - t0

    def timed_transpose(self, *args):
        t0 = time.perf_counter()
        got = transpose(self, *args)
        spent["transpose"] += time.perf_counter() - t0
        return got
    out, previous = {}, parallel.WORKERS
    try:
        for n in threads:
            parallel.set_workers(n)
            b = vp.bind(lat, v, f, dtype=np.float32, topology=topology)
            b.solve(P, axes="XYZ")
            spent.clear()
            compiled.over, compiled.CompiledSteps.transpose = timed_over, timed_transpose
            parallel.run_counted = timed_counted
            t0 = time.perf_counter()
            for _ in range(rounds):
                b.solve(P, axes="XYZ")
            total = 1e3 * (time.perf_counter() - t0) / rounds
            compiled.over, compiled.CompiledSteps.transpose = over, transpose
            parallel.run_counted = counted
            row = {k: 1e3 * t / rounds for k, t in spent.items()}
            row["rest"] = total - sum(row.values())
            row["solve"] = total
            out[n] = row
    finally:
        compiled.over, compiled.CompiledSteps.transpose = over, transpose
        parallel.run_counted = counted
        parallel.set_workers(previous)
    return out


def passes_markdown(rows):
    """The passes' table as Markdown."""
    names = [k for k in dict.fromkeys(k for row in rows.values() for k in row)
             if k not in ("rest", "solve")] + ["rest", "solve"]
    lines = ["| threads | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for n, row in rows.items():
        lines.append(f"| {n} | " + " | ".join(f"{row.get(k, 0.0):.2f} ms" for k in names) + " |")
    return "\n".join(lines)


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
    ap.add_argument("--team-parts", type=int, default=None,
                    help="numba's threads from this many parts on (default: compiled.TEAM_PARTS)")
    ap.add_argument("--passes", action="store_true", help="also time a solve's passes by thread count")
    args = ap.parse_args(argv)
    if args.team_parts is not None:
        # (before `run` loads the kernels: their teams are compiled where the cores reach it)
        compiled.TEAM_PARTS = args.team_parts
    report = run(args.subdivisions, args.rounds, args.max_threads)
    report["team_parts"] = compiled.TEAM_PARTS
    print(markdown(report), file=sys.stderr)
    if args.passes and compiled.ready():
        report["passes"] = passes(args.subdivisions)
        print("\nA solve's passes (means of 21 solves):\n\n" + passes_markdown(report["passes"]), file=sys.stderr)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
