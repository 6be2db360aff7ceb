"""A corrected frame's own passes in the core, beside its solve, as Blender's update makes them
(`vpffd_addon/frame.py`, `offsets.py`): only the lattice's points move from frame to frame, as
in the stack benchmark's *lattice points* scene. No Blender: NumPy, and numba where installed.

    python -m benchmarks.frame_passes [--subdivisions 7] [--frames 41] [--still] [--moving]

Per frame (medians): `Pipeline.evaluate` whole and its solve (`Solution.seconds`), and what a
frame writes, the float32 offsets: in one pass from the solve's vertices (`FrameResult.
float32_offsets`: the map back to the object's space, the positions that no influence moves, the
offsets) against the three passes it replaces (the map back, `frame._affine`; the still positions
set back; the offsets of the mapped positions, `offsets.float32_offsets`), both on the same
frames. `--moving`: the mesh moves a little through the lattice on every frame, so that every
frame embeds it anew (the stack benchmark's *mesh moves*). Prints JSON on stdout, a table on stderr.
"""
import argparse
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
from vpffd_addon import compiled, frame, offsets  # noqa: E402

LATTICE = (6, 6, 6)


def _scene(subdivisions, still=False):
    """(positions (V, 3) float32 in the object's space, faces, lattice, object -> lattice matrix,
    weights (V,) float32: 1, or with `still` a tenth of them 0): a sphere in a B-spline lattice,
    the object turned and moved against the lattice as in a scene."""
    v, f = vp.icosphere(subdivisions, 0.45)
    lat = vp.Lattice(LATTICE, "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    c, s = np.cos(0.3), np.sin(0.3)
    M = np.array([[c, -s, 0, 0.02], [s, c, 0, -0.01], [0, 0, 1, 0.03], [0, 0, 0, 1.0]])
    back = np.linalg.inv(M)
    positions = (v @ back[:3, :3].T + back[:3, 3]).astype(np.float32)
    weights = np.ones(len(v), np.float32)
    if still:
        weights[np.arange(len(v)) % 10 == 0] = 0.0
    return positions, f, lat, M, weights


def _points(lat, k):
    """Frame k's control points: a squash that grows with k, and a little noise."""
    rng = np.random.default_rng(k)
    return lat.rest_points * [1.0, 1.0, 1.0 - 0.01 * k] + rng.normal(0, 0.005, lat.rest_points.shape)


def _one_pass(result, positions, weights, written):
    return result.float32_offsets(written)


def _three_passes(result, positions, weights, written):
    slot = result.slot
    mapped = frame._affine(slot.verts, slot.back)
    still = weights == 0
    if still.any():
        mapped[still] = positions[still].astype(np.float64)
    return offsets.float32_offsets(mapped, positions, written)


def run(subdivisions=7, frames=41, still=False, moving=False):
    kernels = "compiled" if compiled.load() else f"NumPy ({compiled.why()})"
    positions, f, lat, M, weights = _scene(subdivisions, still)
    pipeline = vp.Pipeline()
    rows = {"evaluate": [], "solve": [], "one_pass": [], "three_passes": []}
    written = None
    for k in range(frames + 3):                 # (the first three: binding, warm caches)
        if moving:      # (the mesh moves through the lattice: a new embedding every frame)
            positions = positions + np.float32([0.002, 0.001, 0.0]) * np.float32(1 if k % 40 < 20 else -1)
        inp = vp.FrameInputs(positions=positions, tris=f, lattice=lat, points=_points(lat, k % 30),
                             matrix=M, weights=weights, axes="XYZ", dtype=np.float32)
        t0 = time.perf_counter()
        result = pipeline.evaluate(inp)
        t1 = time.perf_counter()
        # (the two ways in turns first, so that neither always finds the vertices in cache)
        timed = {}
        for way in (("one_pass", "three_passes") if k % 2 else ("three_passes", "one_pass")):
            a = time.perf_counter()
            timed[way] = (_one_pass if way == "one_pass" else _three_passes)(result, positions, weights, written)
            timed[way + "_ms"] = time.perf_counter() - a
        got, before = timed["one_pass"], timed["three_passes"]
        if not all(np.array_equal(a, b) for a, b in zip(got[:2], before[:2])):
            raise RuntimeError("the one pass and the three passes differ")
        written = got[0]
        if k >= 3:
            for name, ms in (("evaluate", t1 - t0), ("solve", result.solution.seconds),
                             ("one_pass", timed["one_pass_ms"]), ("three_passes", timed["three_passes_ms"])):
                rows[name].append(1e3 * ms)
    return {"vertices": len(positions), "lattice": list(LATTICE), "kernels": kernels, "moving": moving,
            "frames": frames, "still": int((weights == 0).sum()), "medians_ms": {k: statistics.median(v) for k, v in rows.items()}}


def markdown(report):
    m = report["medians_ms"]
    return (f"{report['vertices']:,} vertices, {'x'.join(map(str, report['lattice']))} B-spline lattice, "
            f"XYZ, float32, {report['kernels']} kernels, {report['still']:,} vertices of weight 0, "
            f"{'the mesh moving through the lattice, ' if report.get('moving') else ''}"
            f"medians of {report['frames']} frames:\n\n"
            "| evaluate | its solve | evaluate besides the solve | offsets in one pass | "
            "the three passes it replaces |\n|---|---|---|---|---|\n"
            f"| {m['evaluate']:.2f} ms | {m['solve']:.2f} ms | {m['evaluate'] - m['solve']:.2f} ms | "
            f"{m['one_pass']:.2f} ms | {m['three_passes']:.2f} ms |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--subdivisions", type=int, default=7)
    ap.add_argument("--frames", type=int, default=41)
    ap.add_argument("--still", action="store_true", help="a tenth of the vertices of weight 0 (they stay still)")
    ap.add_argument("--moving", action="store_true",
                    help="the mesh moves through the lattice: embedded anew on every frame")
    args = ap.parse_args(argv)
    report = run(args.subdivisions, args.frames, args.still, args.moving)
    print(markdown(report), file=sys.stderr)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
