"""A re-embedding, pass by pass, against this machine's memory: what a mesh moving through the
lattice pays on every frame before its solve (`vp.bind` with the faces' topology reused, which
also renumbers the faces around every slot for the solve), each pass timed where the bind calls
it, on one thread, on two and on every core (or --max-threads), beside the bytes it streams and
what those bytes take at the memory bandwidth this machine gives the same threads. The core
alone, compiled kernels, no Blender:

    python -m benchmarks.reembed_passes [--subdivisions 7] [--rounds 21] [--max-threads N] [--idle MS] [--shuffle]

An icosphere (163,842 vertices at 7 subdivisions) in a 6x6x6 B-spline lattice, float32, moved a
little between re-embeddings. Per pass, the median over the rounds of its wall time (its hand-over
to the worker threads included). The bytes count every array the pass reads or writes once each
(a gathered array as if streamed: a scattered read costs a whole cache line, so for those passes
the floor is lower than what the memory could ever give them); the floor counts a written byte
twice (the processor reads a line before it writes it), at the rate of a copy of 256 MB split
over the same threads, counted the same way (`bandwidth`). docs/performance.md ("Re-embedding and
the first bind") keeps the table. `--idle MS`: the process sleeps MS milliseconds before every
re-embedding (untimed), as a frame's re-embedding comes after Blender's evaluation, the last
frame's solve and the rest of its update instead of straight after the last re-embedding; the
same passes then take longer (performance.md, "A re-embedding in a frame"). `--shuffle`: the
icosphere's vertices renumbered in a random order (seeded), as a mesh whose vertex order has no
relation to where its vertices lie. Prints JSON on
stdout, a table on stderr.
"""
import argparse
import collections
import json
import os
import statistics
import sys
import time

import numpy as np

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)

import vpffd_addon as vp  # noqa: E402
from vpffd_addon import compiled, layout, parallel, volume  # noqa: E402

LATTICE = (6, 6, 6)

#: The passes as the bind calls them: (module, function, what it does).
PASSES = (
    (layout, "positions", "positions to float64, finite, bounds per island"),
    (layout, "cell_keys", "counting sort, first pass: cells, keys, relative coordinates; where keys begin"),
    (layout, "place_slots", "counting sort, second pass: every vertex's place and slot; its count of "
                            "entries of the faces around it, where each slot's begin"),
    (layout, "slot_values_and_faces", "what every slot holds; the faces' volume sums; the faces around every "
                                      "slot, renumbered (one hand-over)"),
)


def bytes_moved(b, incidence):
    """{pass: (bytes read, bytes written)} of each pass, every array counted once (V vertices, S
    slots, F faces, E ring entries), for a float32 binding of one island from float32 positions."""
    V, F = b.n_verts, b.n_faces
    S = b.x0.shape[1]
    E = len(incidence[1])
    n_chunks = -(-F // volume.FACE_CHUNK)
    return {
        # float32 positions in, float64 out
        "positions": (V * 12, V * 24),
        # positions in, relative coordinates and keys out (the counts stay in cache)
        "cell_keys": (V * 24, V * (24 + 8)),
        # the keys and where every vertex's entries begin in; the order, the slot of every vertex
        # and of every sorted position, the slots' counts of entries out; their sum in place
        "place_slots": (V * (8 + 8), V * (8 + 8 + 8) + S * 8 + S * 8),
        # sorted_values: order, sorted slots, positions, influence in; params (4 rows), influence
        # and x0 (3 rows) out in float32. The face sums: the faces' three corners and the
        # relative coordinates in, the chunks' sums out. The faces around every slot: slot,
        # the vertices' starts and ring flags, the vertex-numbered entries and the slot of every
        # entry's vertex in, the entries and the slots' ring flags out
        "slot_values_and_faces": (V * (8 + 8 + 24 + 8) + F * 24 + V * 24 + V * (8 + 8 + 1) + E * (4 + 8),
                                  S * (16 + 4 + 12) + n_chunks * 16 + E * 4 + S),
    }


def bandwidth(threads, mb=256, rounds=5):
    """GB/s of a copy of `mb` MB of float64 split over `threads` parts on the worker threads
    (NumPy's `copyto`, which releases the GIL), a copied value counted as 24 bytes: read, and its
    destination read and written (a processor reads a line before it writes it)."""
    n = mb * (1 << 20) // 8
    a, c = np.ones(n), np.empty(n)
    edges = np.linspace(0, n, threads + 1).astype(int)
    parts = [slice(int(edges[k]), int(edges[k + 1])) for k in range(threads)]

    def copy(p):
        np.copyto(c[p], a[p])
    copy(slice(0, n))
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        parallel.run(copy, parts)
        times.append(time.perf_counter() - t0)
    return 24 * n / min(times) / 1e9


def run(subdivisions=7, rounds=21, max_threads=None, idle_ms=0.0, shuffle=False):
    if not compiled.load():
        raise SystemExit(f"compiled kernels unavailable: {compiled.why()}")
    v, f = vp.icosphere(subdivisions, 0.45)
    if shuffle:     # (new vertex k is old vertex perm[k]; the faces renamed to match)
        perm = np.random.default_rng(0).permutation(len(v))
        new = np.empty_like(perm)
        new[perm] = np.arange(len(perm))
        v, f = v[perm], new[f]
    lat = vp.Lattice(LATTICE, "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    topology = vp.Topology(f, len(v))
    positions = v.astype(np.float32)
    times = collections.defaultdict(list)
    originals = {}

    def timed_pass(mod, name):
        fn = originals[(mod, name)] = getattr(mod, name)

        def wrapper(*args, **kwargs):
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            times[name].append(time.perf_counter() - t0)
            return out
        setattr(mod, name, wrapper)

    def reembed(k):
        moved = positions + np.float32(0.001 * (k % 7))
        b = vp.bind(lat, moved, topology.tris, dtype=np.float32, topology=topology)
        return b, compiled.incidence(b)

    cores = parallel.WORKERS
    counts = sorted({1, min(2, cores), max_threads or cores})
    previous = parallel.WORKERS
    rows = []
    try:
        for n in counts:
            parallel.set_workers(n)
            b, inc = reembed(0)                     # (warm: every kernel and team called once)
            for mod, name, _ in PASSES:
                timed_pass(mod, name)
            times.clear()
            whole = []
            try:
                for k in range(rounds):
                    if idle_ms > 0:
                        time.sleep(idle_ms / 1e3)
                    t0 = time.perf_counter()
                    b, inc = reembed(k + 1)
                    whole.append(time.perf_counter() - t0)
            finally:
                for (mod, name), fn in originals.items():
                    setattr(mod, name, fn)
                originals.clear()
            gbs = bandwidth(n)
            moved = bytes_moved(b, inc)
            row = {"threads": n, "gb_per_s": round(gbs, 1),
                   "whole_ms": round(1e3 * statistics.median(whole), 2), "passes": {}}
            for mod, name, _ in PASSES:
                ms = 1e3 * statistics.median(times[name])
                # (a written byte is read first: two bytes at the copy's rate)
                floor = (moved[name][0] + 2 * moved[name][1]) / (gbs * 1e6)
                row["passes"][name] = {"ms": round(ms, 3), "read": moved[name][0], "written": moved[name][1],
                                       "floor_ms": round(floor, 3)}
            rows.append(row)
    finally:
        parallel.set_workers(previous)
    return {"vertices": b.n_verts, "faces": b.n_faces, "slots": int(b.x0.shape[1]), "ring_entries": len(inc[1]),
            "lattice": list(LATTICE), "cores": cores, "idle_ms": idle_ms, "shuffled": shuffle, "rows": rows}


def markdown(report):
    rows = report["rows"]
    head = " | ".join(f"{r['threads']} thread{'s' if r['threads'] > 1 else ''}: ms (floor)" for r in rows)
    lines = [f"{report['vertices']:,} vertices, {report['faces']:,} faces, {report['slots']:,} slots, "
             f"{report['ring_entries']:,} ring entries, {'x'.join(map(str, report['lattice']))} B-spline lattice, "
             "float32; memory: " + ", ".join(f"{r['gb_per_s']} GB/s on {r['threads']}" for r in rows)
             + (f"; {report['idle_ms']:g} ms idle before every re-embedding" if report.get("idle_ms") else "")
             + ("; the vertices in a random order" if report.get("shuffled") else "")
             + "\n",
             f"| pass | what it does | MB read / written | {head} |", "|---|---|---|" + "---|" * len(rows)]

    def mb(p):
        return f"{p['read'] / 1e6:.1f} / {p['written'] / 1e6:.1f}"
    for mod, name, what in PASSES:
        cells = " | ".join(f"{r['passes'][name]['ms']:.2f} ({r['passes'][name]['floor_ms']:.2f})" for r in rows)
        lines.append(f"| `{name}` | {what} | {mb(rows[0]['passes'][name])} | {cells} |")
    total = " | ".join(f"{sum(p['ms'] for p in r['passes'].values()):.2f} "
                       f"({sum(p['floor_ms'] for p in r['passes'].values()):.2f})" for r in rows)
    both = {k: sum(p[k] for p in rows[0]["passes"].values()) for k in ("read", "written")}
    lines.append(f"| the passes | | {mb(both)} | {total} |")
    lines.append("| the rest (the runs and their blocks, the blocks' control points, the checks: NumPy, "
                 "one thread) | | | " + " | ".join(
                     f"{r['whole_ms'] - sum(p['ms'] for p in r['passes'].values()):.2f}" for r in rows) + " |")
    lines.append("| the whole re-embedding | | | " + " | ".join(f"{r['whole_ms']:.2f}" for r in rows) + " |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--subdivisions", type=int, default=7)
    ap.add_argument("--rounds", type=int, default=21)
    ap.add_argument("--max-threads", type=int, default=None)
    ap.add_argument("--idle", type=float, default=0.0, metavar="MS",
                    help="sleep this many ms before every re-embedding, as between a frame's")
    ap.add_argument("--shuffle", action="store_true", help="the vertices renumbered in a random order")
    args = ap.parse_args(argv)
    report = run(args.subdivisions, args.rounds, args.max_threads, args.idle, args.shuffle)
    print(markdown(report), file=sys.stderr)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
