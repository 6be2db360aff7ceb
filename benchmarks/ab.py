"""The core's solves on this working tree against another commit's, in one process, one solve of
each in turn: the machine's speed drifts by tens of percent within seconds, so two runs one after
the other cannot tell a change of a few percent; alternate solves in one process can. The other
commit's `vpffd_addon` is copied (`git archive`) into a temporary folder under another name and
imported beside this tree's. The core alone (compiled kernels where numba loads), no Blender:

    python -m benchmarks.ab [--base REV] [--rounds 41] [--case single40k single160k islands]

Cases: `single40k` / `single160k`, an XYZ solve of an icosphere of 40,962 / 163,842 vertices in a
10x10x10 B-spline lattice; `islands`, the stack benchmark's 64 islands (`island_problem`), the
single-volume solve and the Per-Island one. Prints each case's medians and the change on stderr,
JSON on stdout. The copy's kernels compile when it loads (about half a minute), as it lives in a
new folder every time.
"""
import argparse
import importlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)

import vpffd_addon as vp  # noqa: E402
from benchmarks.stack_benchmark import island_problem  # noqa: E402


def load_base(rev, folder):
    """The package as it is at commit `rev`, imported as `vpffd_base` from `folder`."""
    target = os.path.join(folder, "vpffd_base")
    os.makedirs(target)
    archive = subprocess.run(["git", "-C", _ROOT, "archive", rev, "vpffd_addon"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", target, "--strip-components=1"], input=archive, check=True)
    sys.path.insert(0, folder)
    return importlib.import_module("vpffd_base")


def problems(case, module):
    """[(label, binding, points, islands)] of `case`, made with `module`."""
    if case == "islands":
        verts, tris, lat, P = island_problem(module)
        b = module.bind(lat, verts, tris, dtype=np.float32)
        return [("islands: single volume", b, P, False), ("islands: per island", b, P, True)]
    verts, tris = module.icosphere({"single40k": 6, "single160k": 7}[case], 0.45)
    lat = module.Lattice((10, 10, 10), "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    return [(case, module.bind(lat, verts, tris, dtype=np.float32), lat.rest_points * [1.0, 1.1, 0.6], False)]


def compare(base, cases, rounds):
    """{label: {"base_ms", "tree_ms", "change"}}: medians of `rounds` solves of each, alternately."""
    out = {}
    for case in cases:
        runs = {name: problems(case, module) for name, module in (("base", base), ("tree", vp))}
        times = {(name, i): [] for name in runs for i in range(len(runs[name]))}
        for name in runs:
            for _, b, P, islands in runs[name]:
                b.solve(P, axes="XYZ", islands=islands)
        for r in range(rounds):
            for name in (("base", "tree") if r % 2 else ("tree", "base")):
                for i, (_, b, P, islands) in enumerate(runs[name]):
                    t0 = time.perf_counter()
                    b.solve(P, axes="XYZ", islands=islands)
                    times[name, i].append((time.perf_counter() - t0) * 1e3)
        for i, (label, *_) in enumerate(runs["tree"]):
            old, new = statistics.median(times["base", i]), statistics.median(times["tree", i])
            out[label] = {"base_ms": old, "tree_ms": new, "change": new / old - 1}
            print(f"{label}: {old:.2f} ms at the base, {new:.2f} ms here ({100 * (new / old - 1):+.1f}%)",
                  file=sys.stderr)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", default="HEAD", help="the commit to compare with (default HEAD)")
    ap.add_argument("--rounds", type=int, default=41)
    ap.add_argument("--case", nargs="+", default=["single40k", "single160k", "islands"],
                    choices=["single40k", "single160k", "islands"])
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        base = load_base(args.base, folder)
        kernels = {"base": bool(base.compiled.load()), "tree": bool(vp.compiled.load())}
        print(f"compiled kernels: base {kernels['base']}, this tree {kernels['tree']}; {os.cpu_count()} CPUs",
              file=sys.stderr)
        report = {"base": args.base, "rounds": args.rounds, "kernels": kernels,
                  "cases": compare(base, args.case, args.rounds)}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
