"""Fuzzing the NumPy core (`vpffd_addon`) with hostile input (hypothesis).

Inputs: NaN and inf anywhere (vertices, control points, influence, pin targets, mobility,
directions, volume scale, lattice bounds); huge and tiny magnitudes (1e-300 .. 1e300, up to the
largest float); degenerate meshes (every vertex on one plane, on one line or on one point), inverted
meshes, zero-area faces, duplicated vertices, faces that use one vertex twice, single triangles,
closed meshes of zero volume, triangle soups, unused vertices, meshes far from the origin; lattices
of 1..5 points per axis with any interpolation and extreme bounds; control points jittered, flung
far away, collapsed to a plane, a line or a point, mirrored; random correction directions (parallel,
tiny, huge), mobility, pins and islands; float32 and float64 bindings.

What must hold:

* Non-finite input raises ValueError whose message names the argument and says "finite".
* Anything else either raises ValueError with a non-empty message, or gives finite results: every
  array and number of a Binding's public attributes, `deform`, `jacobian_det` and every field of a
  `Solution`; never NaN, never inf.
* A Solution is self-consistent: `deform(sol.points)` is `sol.verts`, and `sol.volume` is the
  volume of `sol.verts` (measured here independently), within rounding of the coordinates.

CI runs a bounded, derandomized number of examples per test (`VPFFD_FUZZ_CORE_EXAMPLES`, default
150). Longer, randomized:

    VPFFD_FUZZ_CORE_EXAMPLES=20000 VPFFD_FUZZ_RANDOM=1 ./dev test tests/test_fuzz_core.py

Counts (inputs tried per test, outcomes, the ValueError messages seen) are printed at the end and
written as JSON to `$VPFFD_FUZZ_CORE_REPORT` (default: `vpffd-fuzz-core.json` in the temporary
folder). Bugs found by the fuzzer are shown by deterministic strict-xfail tests at the end; an
input that matches one fails the fuzz run too, labelled with the bug (VPFFD_FUZZ_STRICT=0, for a
long exploratory run, counts them instead so that the run goes on looking for others).
"""
import collections
import json
import os
import pickle
import re
import signal
import tempfile
import time
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

import vpffd_addon as vp

pytestmark = pytest.mark.fuzz

EXAMPLES = int(os.environ.get("VPFFD_FUZZ_CORE_EXAMPLES", "150"))
RANDOM = os.environ.get("VPFFD_FUZZ_RANDOM", "") not in ("", "0")
STRICT = os.environ.get("VPFFD_FUZZ_STRICT", "1") != "0"   # a known bug fails unless exploring

KNOWN_BUGS = {
    "flat-lattice-blowup":
        "when the deformed mesh is flat (all control points on one plane) the correction along the "
        "in-plane axes treats rounding noise as a volume gradient: control points are flung "
        "1e6..1e18 away, Solution.volume (the target) is not the volume of Solution.verts, and no "
        "warning is given (test_known_bug_flat_lattice_blowup)",
    "float64-range":
        "finite input whose products overflow or underflow float64 gives inf, NaN or a wrong "
        "volume instead of a ValueError: "
        "bind's rest_volume and rest_island_volumes for coordinates beyond ~1e102 from the volume "
        "origin (inf, then NaN); jacobian_det for displacements ~1e100 x the lattice spacing (inf); "
        "solve with direction rows longer than ~1e154 (the norm overflows, the directions become "
        "zero: NaN volumes); solve with a volume_scale whose target overflows (target_volume inf, "
        "a Solution instead of a ValueError) (test_known_bug_float64_overflow)",
    "float32-range":
        "float32 bindings do not check the float32 range: deform returns inf for displacements "
        "above ~3.4e38, and jacobian_det returns NaN for lattice cells smaller than ~1e-38 "
        "(the derivative weights overflow in float32) (test_known_bug_float32_range)",
}

KNOWN_BUGS["solve-hangs"] = (
    "solve can hang forever: when intermediate values overflow, NaN reaches numpy.linalg.lstsq, "
    "whose LAPACK driver loops (it prints '** On entry to DLASCL parameter number 4 had an "
    "illegal value' and never returns); the same inputs with one direction give a Solution with "
    "volume NaN (test_known_bug_solve_hangs)")
KNOWN_BUGS["far-translation-volume"] = (
    "Solution.volume is measured about the rest pose's island centres: when the control points "
    "translate the mesh far from its rest position (1e5 x its size and more) the measurement "
    "cancels catastrophically (a sphere translated by 1e8 lattice sizes: Solution.volume 0.206, "
    "the vertices enclose 0.259, no warning) (test_known_bug_far_translation_volume)")
KNOWN_BUGS["open-mesh-float32-cancellation"] = (
    "an open mesh's volume is measured about the lattice centre; with float32 bindings a mesh "
    "that is small compared with its distance from that centre has a volume below the rounding "
    "of the terms: at rest (no deformation) the solve moves the lattice to chase the noise, and "
    "Solution.volume (the target) is not the volume of Solution.verts (distance/size 140: 0.1% "
    "off; 1400: 17%; 14000: 98%), no warning (test_known_bug_open_mesh_float32_cancellation)")
KNOWN_BUGS["float32-plain-volume-nan"] = (
    "with a float32 binding and displacements around 1e19 (their products overflow float32 in the "
    "volume gradient), solve can return a Solution whose plain_volume is NaN (volume and "
    "vertices finite, no error) (test_known_bug_float32_plain_volume_nan)")
SOLVE_TIMEOUT = float(os.environ.get("VPFFD_FUZZ_SOLVE_TIMEOUT", "60"))   # a hang, not a slow machine

COUNTS = collections.defaultdict(collections.Counter)
_T0 = time.perf_counter()


def _fuzz_settings(n=None):
    kw = dict(max_examples=n or EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
    if not RANDOM:
        kw.update(derandomize=True, database=None)
    return settings(**kw)


def _count(test, outcome, message=None):
    COUNTS[test][outcome] += 1
    if message is not None:
        COUNTS["messages"][re.sub(r"-?\d+(\.\d+)?(e[-+]?\d+)?", "N", str(message))[:120]] += 1


# Found by this fuzzer and fixed since (the regression tests at the end show them): any input
# that hits them again fails the run. "float64-range" stays counted, not failing: its overflow
# cases are fixed (regression tests), but underflow-sized meshes (~0 or 1e-100 across) can still
# report a volume off by ~1e-22 from the one measured.
FIXED_BUGS = {"flat-lattice-blowup", "float32-range", "solve-hangs", "float32-plain-volume-nan",
              "open-mesh-float32-cancellation"}


def _known(bug, detail):
    COUNTS["known_bugs"][bug] += 1
    note(f"known bug {bug}: {detail}")
    if STRICT or bug in FIXED_BUGS:
        raise AssertionError(f"{'fixed' if bug in FIXED_BUGS else 'known'} bug {bug}: "
                             f"{KNOWN_BUGS[bug]}\n{detail}")


@pytest.fixture(scope="module", autouse=True)
def _summary(request):
    global _T0
    _T0 = time.perf_counter()
    yield
    path = os.environ.get("VPFFD_FUZZ_CORE_REPORT",
                          os.path.join(tempfile.gettempdir(), "vpffd-fuzz-core.json"))
    report = {k: dict(v.most_common()) for k, v in COUNTS.items()}
    report["seconds"] = time.perf_counter() - _T0
    report["examples_setting"] = EXAMPLES
    report["randomized"] = RANDOM
    with open(path, "w") as fh:
        json.dump(report, fh, indent=1)
    tests = {k: sum(v.values()) for k, v in COUNTS.items()
             if k not in ("messages", "known_bugs", "volume")}
    tried = sum(tests.values())
    parts = ", ".join(f"{k}: {n}" for k, n in tests.items())
    reporter = request.config.pluginmanager.get_plugin("terminalreporter")
    capture = request.config.pluginmanager.get_plugin("capturemanager")
    if reporter is not None and capture is not None:
        with capture.global_and_fixture_disabled():
            reporter.write_line(
                f"\nVP-FFD core fuzz: {tried} inputs tried ({parts}), {report['seconds']:.1f} s; "
                f"known bugs hit: {dict(COUNTS['known_bugs']) or 'none'}; report {path}")


# ------------------------------------------------------------------------- building blocks

KINDS = list(vp.INTERPOLATIONS)
MESH_KINDS = ["sphere", "box", "inverted", "coplanar", "collinear", "one point", "zero-area faces",
              "duplicated vertices", "repeated corner", "single triangle", "flat closed", "soup",
              "unused vertices", "two islands", "open"]
SCALES = [1.0, 1.0, 1.0, 1e-300, 1e-12, 1e8, 1e15, 1e150, 1e300]
OFFSETS = [0.0, 0.0, 1e3, 1e8, 1e15, 1e300]


def _mesh(kind, rng, scale, offset):
    """(verts (V, 3) float64, tris (F, 3)) of a hostile mesh about `offset` of size `scale`."""
    if kind in ("sphere", "inverted", "coplanar", "collinear", "one point", "zero-area faces",
                "duplicated vertices", "repeated corner", "unused vertices", "open"):
        v, f = vp.icosphere(int(rng.integers(0, 3)), 0.4)
    elif kind == "box":
        v, f = vp.box(int(rng.integers(1, 3)), 0.8)
    elif kind == "single triangle":
        v, f = rng.uniform(-0.5, 0.5, (3, 3)), np.array([[0, 1, 2]])
    elif kind == "flat closed":
        v = np.array([[0, 0, 0], [0.3, 0, 0], [0, 0.3, 0], [0.1, 0.1, 0]], float)
        f = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    elif kind == "soup":
        n = int(rng.integers(3, 30))
        v = rng.uniform(-0.5, 0.5, (n, 3))
        f = rng.integers(0, n, (int(rng.integers(1, 40)), 3))
    else:  # two islands, the second one inside out half of the time
        a, fa = vp.icosphere(1, 0.2, (-0.25, 0, 0))
        b, fb = vp.box(1, 0.3, (0.25, 0, 0))
        if rng.random() < 0.5:
            fb = fb[:, ::-1]
        v, f = np.vstack([a, b]), np.vstack([fa, fb + len(a)])
    v = np.array(v, float)
    f = np.array(f, np.int64)
    if kind == "inverted":
        f = f[:, ::-1].copy()
    elif kind == "coplanar":
        v[:, int(rng.integers(3))] = rng.uniform(-0.3, 0.3)
    elif kind == "collinear":
        d = rng.normal(size=3)
        v = np.outer(rng.uniform(-0.4, 0.4, len(v)), d / np.linalg.norm(d))
    elif kind == "one point":
        v[:] = rng.uniform(-0.3, 0.3, 3)
    elif kind == "zero-area faces":
        k = int(rng.integers(1, 5))
        a, b = rng.integers(0, len(v), (2, k))
        f = np.vstack([f, np.stack([a, a, b], 1), np.stack([a, b, a], 1), np.stack([a, a, a], 1)])
    elif kind == "duplicated vertices":
        k = rng.choice(len(v), size=min(len(v), int(rng.integers(1, 8))), replace=False)
        v = np.vstack([v, v[k]])
        # Rewire a few faces to the duplicates: the surface is cut open along them.
        for j, old in enumerate(k):
            uses = np.flatnonzero((f == old).any(1))
            if len(uses) and rng.random() < 0.7:
                g = uses[int(rng.integers(len(uses)))]
                f[g][f[g] == old] = len(v) - len(k) + j
    elif kind == "repeated corner":
        g = rng.choice(len(f), size=min(len(f), 3), replace=False)
        f[g, 1] = f[g, 0]
    elif kind == "unused vertices":
        v = np.vstack([v, rng.uniform(-5, 5, (int(rng.integers(1, 5)), 3))])
    elif kind == "open":
        f = f[int(rng.integers(1, max(2, len(f) // 2))):]
    return v * scale + offset, f


def _lattice(rng, verts, shape, kinds, how):
    if how == "fit":
        lo, hi = verts.min(0), verts.max(0)
        ext = np.where(hi > lo, hi - lo, np.maximum(np.abs(lo), 1.0) * 1e-3 + 1e-300)
        lo = lo - rng.uniform(-0.1, 0.3, 3) * ext
        hi = hi + rng.uniform(-0.1, 0.3, 3) * ext
    elif how == "unit":
        lo, hi = np.full(3, -0.5), np.full(3, 0.5)
    elif how == "tiny":
        c = rng.uniform(-1, 1, 3) * float(rng.choice([1.0, 1e12]))
        lo, hi = c - 1e-12, c + 1e-12
    elif how == "huge":
        lo, hi = np.full(3, -1e300), np.full(3, 1e300)
    else:  # "far": nowhere near the mesh
        lo = np.full(3, 1e9)
        hi = lo + 1.0
    return vp.Lattice(shape, kinds, bounds=(lo, hi))


def _points(lat, rng, how, magnitude):
    P0 = lat.rest_points
    P = P0.copy()
    size = lat.size
    if how == "jitter":
        P = P0 + rng.normal(0, magnitude * size, P0.shape)
    elif how == "huge":
        k = rng.random(len(P)) < 0.5
        P[k] += rng.choice([-1.0, 1.0], (int(k.sum()), 3)) * magnitude
    elif how == "plane":
        P[:, int(rng.integers(3))] = float(lat.centre[0] + rng.uniform(-0.1, 0.1) * size)
    elif how == "line":
        axes = rng.choice(3, size=2, replace=False)
        P[:, axes] = lat.centre[axes]
    elif how == "point":
        P[:] = P[int(rng.integers(len(P)))]
    elif how == "mirror":
        a = int(rng.integers(3))
        P[:, a] = 2 * lat.centre[a] - P[:, a]
    elif how == "scale":
        P = lat.centre + (P0 - lat.centre) * float(rng.choice([0.0, 1e-300, -1.0, 1e300]))
    elif how == "max":
        P[int(rng.integers(len(P)))] = rng.choice([-1.0, 1.0], 3) * np.finfo(float).max
    return P


def _directions(rng, how):
    if how == "axes":
        return "".join(rng.permutation(list("XYZ"))[:int(rng.integers(1, 4))]), None
    if how == "none":
        return "", None
    m = int(rng.integers(1, 4))
    d = rng.normal(size=(m, 3))
    if how == "parallel":
        d[:] = d[0] * rng.choice([-2.0, 1.0, 3.0], (m, 1))
    elif how == "tiny":
        d *= 1e-300
    elif how == "huge":
        d *= 1e300
    return "XYZ", d


def _stretch(b, P):
    """Largest displacement over the smallest lattice spacing (the size of the Jacobian's terms)."""
    lat = b.lattice
    n = np.array(lat.shape)
    spacing = ((lat.hi - lat.lo) / np.maximum(n - 1, 1))[n > 1]
    D = np.abs(np.asarray(P, float) - lat.rest_points).max(initial=0)
    return float(D / spacing.min()) if len(spacing) else 0.0


def _beyond_float32(b, P):
    """A float32 binding asked for numbers outside float32's range: displacements, rest
    coordinates or derivative weights (1 / lattice spacing) beyond ~1e37, or below ~1e-37."""
    if b.dtype != np.float32:
        return False
    lat = b.lattice
    n = np.array(lat.shape)
    spacing = ((lat.hi - lat.lo) / np.maximum(n - 1, 1))[n > 1]
    D = np.abs(np.asarray(P, float) - lat.rest_points)
    return bool(D.max(initial=0) > 1e37 or (len(spacing) and spacing.min() < 1e-36)
                or np.ptp(b.to_verts(b.x0), 0).max() > 1e37)


def _all_finite(*values):
    for x in values:
        if x is None:
            continue
        a = np.asarray(x, dtype=np.float64)
        if not np.isfinite(a).all():
            return False
    return True


def _binding_arrays_finite(b):
    public = [b.rest_volume, b.rest_island_volumes, b.influence, b.lattice.lo, b.lattice.hi,
              b.lattice.rest_points]
    return _all_finite(*public)


def _volume_about(verts, tris, origin):
    """(volume, bound): the volume about `origin`, and sum |a| |b| |c| / 6 over the faces, which
    bounds every term before cancellation (the scale of its rounding)."""
    v = verts - origin
    a, b, c = v[tris[:, 0]], v[tris[:, 1]], v[tris[:, 2]]
    terms = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    n = np.linalg.norm(v, axis=1)
    bound = (n[tris[:, 0]] * n[tris[:, 1]] * n[tris[:, 2]]).sum() / 6.0
    return float(terms.sum()), float(bound)


def _value_error(exc, test):
    assert isinstance(exc, ValueError)
    assert str(exc).strip(), f"{test}: ValueError with an empty message"
    _count(test, "ValueError", exc)


# ------------------------------------------------------------------------- non-finite input

POISON = st.sampled_from([np.nan, np.inf, -np.inf])


@_fuzz_settings()
@given(target=st.sampled_from(["verts", "points", "influence", "pin target", "mobility",
                               "directions", "volume_scale", "bounds", "jacobian points",
                               "signed_volume verts"]),
       bad=POISON, seed=st.integers(0, 2 ** 32 - 1), dtype=st.sampled_from([np.float32, np.float64]),
       shape=st.tuples(*[st.integers(1, 4)] * 3))
def test_non_finite_input_is_rejected_by_name(target, bad, seed, dtype, shape):
    rng = np.random.default_rng(seed)
    v, f = vp.icosphere(1, 0.4)
    lat = vp.Lattice(shape, tuple(rng.choice(KINDS, 3)), bounds=((-0.5,) * 3, (0.5,) * 3))
    P = lat.rest_points + rng.normal(0, 0.05, (lat.n_points, 3))
    where = int(rng.integers(len(v)))
    names = {"verts": "rest_verts", "points": "points", "influence": "influence",
             "pin target": "pin", "mobility": "mobility", "directions": "directions",
             "volume_scale": "volume_scale", "bounds": "bounds", "jacobian points": "points",
             "signed_volume verts": "verts"}
    with pytest.raises(ValueError) as info:
        if target == "verts":
            v = v.copy()
            v[where, int(rng.integers(3))] = bad
            vp.bind(lat, v, f, dtype=dtype)
        elif target == "influence":
            s = np.ones(len(v))
            s[where] = bad
            vp.bind(lat, v, f, influence=s, dtype=dtype)
        elif target == "bounds":
            lo = [-0.5, -0.5, -0.5]
            lo[int(rng.integers(3))] = bad
            vp.Lattice(shape, bounds=(lo, (0.5,) * 3))
        elif target == "signed_volume verts":
            v = v.copy()
            v[where, 0] = bad
            vp.signed_volume(v, f)
        else:
            b = vp.bind(lat, v, f, dtype=dtype)
            if target in ("points", "jacobian points"):
                P[int(rng.integers(len(P))), int(rng.integers(3))] = bad
                if target == "points":
                    (b.solve if rng.random() < 0.5 else b.deform)(P)
                else:
                    vp.jacobian_det(b, P)
            elif target == "pin target":
                b.solve(P, pins=[(where, (0.0, bad, 0.0))])
            elif target == "mobility":
                m = np.ones(lat.n_points)
                m[0] = bad
                b.solve(P, mobility=m)
            elif target == "directions":
                b.solve(P, directions=[[1.0, 0.0, 0.0], [0.0, bad, 1.0]])
            else:
                b.solve(P, volume_scale=bad)
    message = str(info.value)
    _count("non-finite", "ValueError", message)
    assert names[target] in message, f"the message does not name {names[target]!r}: {message!r}"
    assert "finite" in message, f"the message does not say 'finite': {message!r}"


# ------------------------------------------------------------------------- hostile but finite

MESH = st.fixed_dictionaries({
    "kind": st.sampled_from(MESH_KINDS),
    "scale": st.sampled_from(SCALES),
    "offset": st.sampled_from(OFFSETS),
})
LATTICE = st.fixed_dictionaries({
    "shape": st.tuples(*[st.integers(1, 5)] * 3),
    "kinds": st.tuples(*[st.sampled_from(KINDS)] * 3),
    "bounds": st.sampled_from(["fit", "fit", "fit", "unit", "tiny", "huge", "far"]),
})
POINTS = st.fixed_dictionaries({
    "how": st.sampled_from(["rest", "jitter", "jitter", "huge", "plane", "line", "point", "mirror",
                            "scale", "max"]),
    "magnitude": st.sampled_from([1e-12, 0.1, 1.0, 10.0, 1e8, 1e15, 1e100, 1e300]),
})
SOLVE = st.fixed_dictionaries({
    "directions": st.sampled_from(["axes", "axes", "axes", "none", "random", "parallel", "tiny",
                                   "huge"]),
    "volume_scale": st.sampled_from([1.0, 1.0, 0.0, 1e-300, 0.5, 2.0, 1e300]),
    "mobility": st.sampled_from([None, None, "random", "zeros", "some zeros"]),
    "pins": st.sampled_from([0, 0, 1, 3]),
    "pin_offset": st.sampled_from([0.0, 0.05, 1e10]),
    "islands": st.booleans(),
    "preserve_volume": st.sampled_from([True, True, True, False]),
})
INFLUENCE = st.sampled_from([None, None, "random", "zeros", "some zeros", "negative and large"])


def _influence(how, V, rng):
    if how is None:
        return None
    if how == "random":
        return rng.uniform(0, 1, V)
    if how == "zeros":
        return np.zeros(V)
    if how == "some zeros":
        return np.where(rng.random(V) < 0.3, 0.0, 1.0)
    return rng.uniform(-3, 5, V)


def _bind_or_error(test, lat, verts, tris, influence, dtype):
    try:
        b = vp.bind(lat, verts, tris, influence=influence, dtype=dtype)
    except ValueError as exc:
        _value_error(exc, test)
        return None
    assert b.n_verts == len(verts) and b.n_faces == len(tris)
    reach = max(float(np.ptp(verts, 0).max()), float(np.abs(verts - lat.centre).max()))
    if not _binding_arrays_finite(b) and _all_finite(b.influence) and reach > 1e100:
        _known("float64-range", f"bind: rest_volume {b.rest_volume} for coordinates {reach:.3g} "
               "from the origin")
        return None
    assert _binding_arrays_finite(b), (
        f"bind returned non-finite values: rest_volume {b.rest_volume}, island volumes "
        f"{b.rest_island_volumes}")
    return b


def _hostile_binding(rng, mesh, lattice, points, influence, dtype):
    """(verts, tris, lattice, binding, control points) drawn from the strategies' values, or None
    when making the lattice or binding raised the expected ValueError (counted)."""
    verts, tris = _mesh(mesh["kind"], rng, mesh["scale"], mesh["offset"])
    try:
        lat = _lattice(rng, verts, lattice["shape"], lattice["kinds"], lattice["bounds"])
    except ValueError as exc:
        _value_error(exc, "lattice")
        return None
    b = _bind_or_error("bind", lat, verts, tris, _influence(influence, len(verts), rng), dtype)
    if b is None:
        return None
    return verts, tris, lat, b, _points(lat, rng, points["how"], points["magnitude"])


@_fuzz_settings()
@given(mesh=MESH, lattice=LATTICE, points=POINTS, influence=INFLUENCE,
       dtype=st.sampled_from([np.float32, np.float64]), seed=st.integers(0, 2 ** 32 - 1))
def test_hostile_meshes_bind_and_deform_finitely(mesh, lattice, points, influence, dtype, seed):
    rng = np.random.default_rng(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # overflow warnings are fine; NaN is not
        made = _hostile_binding(rng, mesh, lattice, points, influence, dtype)
        if made is None:
            return
        verts, tris, lat, b, P = made
        _count("bind", "ok")
        try:
            out = b.deform(P)
        except ValueError as exc:
            _value_error(exc, "deform")
        else:
            _count("deform", "ok")
            assert out.shape == verts.shape
            if not _all_finite(out) and _beyond_float32(b, P):
                _known("float32-range", f"deform: {int((~np.isfinite(out)).any(1).sum())} "
                       "non-finite vertices")
                out = np.zeros(1)
            assert _all_finite(out), (f"deform returned non-finite vertices "
                                      f"({int((~np.isfinite(out)).any(1).sum())} of {len(out)})")
        try:
            det = vp.jacobian_det(b, P)
        except ValueError as exc:
            _value_error(exc, "jacobian_det")
        else:
            _count("jacobian_det", "ok")
            assert det.shape == (len(verts),)
            if not _all_finite(det) and _beyond_float32(b, P):
                _known("float32-range", f"jacobian_det: {int((~np.isfinite(det)).sum())} non-finite")
                return
            if not _all_finite(det) and not np.isnan(det).any() and _stretch(b, P) > 1e90:
                _known("float64-range", f"jacobian_det: inf for displacements {_stretch(b, P):.3g} "
                       "x the lattice spacing")
                return
            assert _all_finite(det), "jacobian_det returned non-finite values"


@_fuzz_settings()
@given(mesh=MESH, lattice=LATTICE, points=POINTS, solve=SOLVE, influence=INFLUENCE,
       dtype=st.sampled_from([np.float32, np.float64]), seed=st.integers(0, 2 ** 32 - 1))
def test_hostile_solves_are_finite_and_self_consistent(mesh, lattice, points, solve, influence,
                                                       dtype, seed):
    rng = np.random.default_rng(seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        made = _hostile_binding(rng, mesh, lattice, points, influence, dtype)
        if made is None:
            return
        verts, tris, lat, b, P = made
        axes, directions = _directions(rng, solve["directions"])
        mobility = {None: None, "random": rng.uniform(0, 1, lat.n_points),
                    "zeros": np.zeros(lat.n_points),
                    "some zeros": np.where(rng.random(lat.n_points) < 0.3, 0.0, 1.0)}[solve["mobility"]]
        pins = []
        for k in rng.choice(len(verts), size=min(solve["pins"], len(verts)), replace=False):
            pins.append((int(k), verts[k] + rng.normal(0, 1, 3) * solve["pin_offset"]))
        run = lambda: b.solve(  # noqa: E731
            P, axes=axes, directions=directions, volume_scale=solve["volume_scale"],
            preserve_volume=solve["preserve_volume"], mobility=mobility, pins=pins,
            islands=solve["islands"])
        extreme = [verts, P, lat.lo, lat.hi, [solve["volume_scale"]]] + [t for _, t in pins] \
            + ([directions] if directions is not None else [])
        try:
            # Where values can overflow (the known hang needs NaN), solve in a child process.
            sol = _isolated(run) if _extreme(*extreme) else run()
        except ValueError as exc:
            _value_error(exc, "solve")
            return
        except _Hung:
            _count("solve", "hung")
            _known("solve-hangs", f"no answer after {SOLVE_TIMEOUT} s")
            return
        _count("solve", "ok" if not sol.warnings else "ok with warnings")
        if b.dtype == np.float32 and not _all_finite(sol.plain_volume) \
                and _all_finite(sol.volume, sol.verts) and np.abs(P - lat.rest_points).max() > 1e18:
            _known("float32-plain-volume-nan", f"plain_volume {sol.plain_volume} for displacements "
                   f"{np.abs(P - lat.rest_points).max():.3g}")
            return
        if directions is not None and np.abs(directions).max() > 1e150 \
                and not _all_finite(sol.volume, sol.plain_volume):
            _known("float64-range", f"solve: volume {sol.volume} with directions "
                   f"{np.abs(directions).max():.3g} long")
            return
        if not _all_finite(sol.volume, sol.plain_volume) and _extreme(P - lat.rest_points, verts):
            _known("float64-range", f"solve: volume {sol.volume}, plain {sol.plain_volume} for "
                   f"displacements {np.abs(P - lat.rest_points).max():.3g}")
            return
        if not _all_finite(sol.target_volume) and not np.isfinite(solve["volume_scale"] * b.rest_volume):
            _known("float64-range", f"solve: target_volume {sol.target_volume} for volume_scale "
                   f"{solve['volume_scale']:g} x rest volume {b.rest_volume:.3g}")
            return
        _check_solution(b, tris, P, sol, solve["islands"])


def _extreme(*arrays):
    """Some magnitude beyond 1e100 (products can overflow) or nonzero below 1e-100."""
    for a in arrays:
        a = np.abs(np.asarray(a, float))
        if a.size and (a.max() > 1e100 or ((a > 0) & (a < 1e-100)).any()):
            return True
    return False


class _Hung(Exception):
    pass


def _isolated(fn, timeout=SOLVE_TIMEOUT):
    """fn() in a forked child (a hang cannot stop the run): its return value, or its exception
    re-raised here (ValueError as itself, anything else as AssertionError with the traceback);
    _Hung when it runs past `timeout` seconds."""
    if not hasattr(os, "fork"):
        return fn()
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: run, send the pickled outcome, leave without any clean-up
        try:
            os.close(read)
            try:
                out = ("ok", fn())
            except ValueError as exc:
                out = ("ValueError", str(exc))
            except BaseException as exc:  # noqa: BLE001 (reported to the parent)
                import traceback
                out = ("other", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}")
            try:
                data = pickle.dumps(out)
            except BaseException as exc:  # noqa: BLE001
                data = pickle.dumps(("other", f"could not pickle the outcome: {exc!r}"))
            view = memoryview(data)
            while len(view):
                view = view[os.write(write, view):]
        finally:
            os._exit(0)   # never return into pytest in the child, whatever happened
    os.close(write)
    chunks, deadline = [], time.monotonic() + timeout
    import select
    with os.fdopen(read, "rb") as fh:
        while True:
            left = deadline - time.monotonic()
            ready = select.select([fh], [], [], max(left, 0))[0] if left > 0 else []
            if not ready:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                raise _Hung()
            chunk = os.read(fh.fileno(), 1 << 20)
            if not chunk:
                break
            chunks.append(chunk)
    os.waitpid(pid, 0)
    kind, value = pickle.loads(b"".join(chunks))
    if kind == "ok":
        return value
    if kind == "ValueError":
        raise ValueError(value)
    raise AssertionError(f"solve raised something other than ValueError:\n{value}")


def _check_solution(b, tris, P, sol, islands):
    fields = dict(verts=sol.verts, points=sol.points, volume=sol.volume,
                  target_volume=sol.target_volume, plain_volume=sol.plain_volume,
                  directions=sol.directions, island_volumes=sol.island_volumes,
                  island_target_volumes=sol.island_target_volumes)
    bad = [k for k, x in fields.items() if not _all_finite(x)]
    assert not bad, f"non-finite Solution fields: {bad}"
    assert sol.verts.shape == (b.n_verts, 3) and sol.points.shape == P.shape
    assert all(isinstance(w, str) and w for w in sol.warnings)
    if islands:
        assert sol.island_volumes is not None and len(sol.island_volumes) == b.n_islands
    # deform(points) reproduces verts (the solution is an FFD of its own control points).
    again = b.deform(sol.points)
    # ... up to rounding of the largest number involved (the displacements included: huge ones
    # that cancel leave their rounding behind).
    mag = max(1.0, float(np.abs(sol.verts).max()), float(np.abs(sol.points).max()),
              float(np.abs(P).max()), float(np.abs(b.to_verts(b.x0)).max()),
              float(np.abs(P - b.lattice.rest_points).max()),
              float(np.abs(sol.points - b.lattice.rest_points).max()))
    rel = 1e-5 if b.dtype == np.float32 else 1e-9
    assert _all_finite(again)
    err = float(np.abs(again - sol.verts).max())
    assert err <= rel * mag, f"deform(sol.points) differs from sol.verts by {err:.3g} (scale {mag:.3g})"
    # sol.volume is the volume of sol.verts, measured independently (closed: any origin; open:
    # about the lattice centre, as documented).
    if b.is_closed:
        origin = 0.5 * (sol.verts.min(0) + sol.verts.max(0))
    else:
        origin = b.lattice.centre
    measured, flux = _volume_about(sol.verts, tris, origin)
    if not np.isfinite(measured):
        return   # the verts are finite but their volume overflows: nothing to compare
    rest_mag = max(abs(sol.volume), abs(sol.target_volume), abs(b.rest_volume))
    # Rounding bounds the disagreement: relative rounding of the volume terms (x the flux), and
    # the absolute rounding delta of every coordinate (far from the origin, a small mesh cannot be
    # represented well), which changes the volume by at most delta x the surface area.
    eps = 1e-5 if b.dtype == np.float32 else 1e-10
    unit = float(np.finfo(b.dtype).eps)
    # The solver's coordinates are x0 + s B D: each carries rounding of the displacement's size
    # too (a tiny mesh moved by a large displacement cancels in the binding's precision).
    shift = max(float(np.abs(P - b.lattice.rest_points).max()),
                float(np.abs(sol.points - b.lattice.rest_points).max()))
    reach = float(np.abs(sol.verts - origin).max()) + float(np.abs(b.influence).max()) * shift
    delta = 4 * (unit * reach + 2.3e-16 * float(np.abs(sol.verts).max()))
    e1 = sol.verts[tris[:, 1]] - sol.verts[tris[:, 0]]
    e2 = sol.verts[tris[:, 2]] - sol.verts[tris[:, 0]]
    area = float(0.5 * np.linalg.norm(np.cross(e1, e2), axis=1).sum())
    L = float(np.abs(sol.verts - origin).max())
    # first order: delta x area; beyond it (delta comparable to the mesh): the triple products'
    # perturbation bound per face
    d, L = np.float64(delta), np.float64(L)      # NumPy floats: inf instead of OverflowError
    size = np.float64(np.ptp(b.to_verts(b.x0), 0).max())    # the rest mesh: volumes below
    with np.errstate(over="ignore"):                          # eps x size^3 are noise
        allowance = eps * (flux + rest_mag + size ** 3) + d * area * 3 \
            + len(tris) * (d * L * L + d * d * L + d ** 3)
    COUNTS["volume"]["compared"] += 1
    if abs(measured - sol.volume) > allowance and any("rounding of its terms" in w for w in sol.warnings):
        COUNTS["volume"]["warned: below rounding"] += 1   # the solver said it cannot be kept
        return
    if abs(measured - sol.volume) > allowance:
        rest = b.to_verts(b.x0)
        size = float(np.ptp(rest, 0).max())
        far = float(np.abs(0.5 * (rest.min(0) + rest.max(0)) - b.lattice.centre).max())
        if not b.is_closed and b.dtype == np.float32 and size > 0 and far > 10 * size:
            _known("open-mesh-float32-cancellation", f"claimed {sol.volume:.6g}, measured "
                   f"{measured:.6g}, the open mesh {far / size:.3g} x its size from the centre")
            return
        shift = float(np.abs(0.5 * (sol.verts.min(0) + sol.verts.max(0))
                             - 0.5 * (rest.min(0) + rest.max(0))).max())
        if size > 0 and shift > 1e5 * size:
            _known("far-translation-volume", f"claimed {sol.volume:.6g}, measured {measured:.6g} "
                   f"after a translation of {shift / size:.3g} x the mesh size")
            return
        if float(np.ptp(rest, 0).max()) < 1e-90:
            _known("float64-range", f"solve: claimed {sol.volume:.6g}, measured {measured:.6g} for "
                   f"a mesh of size {float(np.ptp(rest, 0).max()):.3g}")
            return
        moved = float(np.abs(sol.points - P).max()) / max(b.lattice.size, float(np.ptp(P, 0).max()))
        if moved > 1e3 and _flat(P, b.lattice):
            _known("flat-lattice-blowup", f"claimed {sol.volume:.6g}, measured {measured:.6g}, "
                   f"points moved {moved:.3g} lattice sizes")
            return
        raise AssertionError(
            f"Solution.volume {sol.volume!r} but the vertices enclose {measured!r} "
            f"(allowance {allowance:.3g}, flux {flux:.3g}, warnings {sol.warnings})")


def _flat(P, lattice):
    """The control points lie on one plane (their spread along some direction is ~0)."""
    c = P - P.mean(0)
    s = np.linalg.svd(c, compute_uv=False) if len(P) >= 3 else np.zeros(1)
    return bool(s[-1] <= 1e-9 * max(float(s[0]), 1e-300)) if len(s) == 3 else True


# ----------------------------------------- bugs the fuzzer found: fixed (regressions), or known (xfail)

@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_regression_flat_lattice_blowup(dtype):
    """Smallest reproduction: an icosphere in a 2x2x2 LINEAR lattice squashed onto the plane
    z = 0.01, corrected along XYZ. Expected: the volume comes back by moving points along Z
    (or a ValueError / warning); got: points flung ~1e15 along X/Y, Solution.volume = target while
    the vertices enclose another volume, no warning."""
    v, f = vp.icosphere(2, 0.4)
    lat = vp.Lattice((2, 2, 2), "LINEAR", bounds=((-0.5,) * 3, (0.5,) * 3))
    b = vp.bind(lat, v, f, dtype=dtype)
    P = lat.rest_points.copy()
    P[:, 2] = 0.01
    sol = b.solve(P, axes="XYZ")
    measured = vp.signed_volume(sol.verts, f)
    assert abs(measured - sol.volume) <= 1e-6 * abs(b.rest_volume) or sol.warnings
    assert np.abs(sol.points - P).max() < 100 * lat.size


@pytest.mark.parametrize("case", ["bind", "jacobian_det", "solve directions", "volume_scale",
                                  "tiny mesh with a pin"])
def test_regression_float64_overflow(case):
    """Smallest reproductions: (bind) an icosphere of radius 4e149 binds without error,
    rest_volume NaN (radius 4e102: inf); (jacobian_det) a unit lattice scaled by 1e300 about its
    centre: inf determinants; (solve directions) directions=[[1e300, 1e300, 0]] with
    preserve_volume=False: volume and plain_volume NaN; (volume_scale) a sphere of radius 4e7 in a
    1x1x1 lattice solved with volume_scale=1e300: a Solution with target_volume inf; (tiny mesh
    with a pin) a flat tetrahedron of size 3e-101 in a 1x2x1 lattice, one vertex pinned 0.05
    away: Solution.volume 0.0, the vertices enclose 2.3e-23, no warning. Expected: a ValueError naming the problem,
    or finite results."""
    v, f = vp.icosphere(1, 0.4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            if case == "bind":
                v = v * 1e150
                lat = vp.Lattice((2, 2, 2), bounds=(v.min(0), v.max(0)))
                out = [vp.bind(lat, v, f).rest_volume]
            elif case == "jacobian_det":
                lat = vp.Lattice((2, 2, 2), "LINEAR", bounds=((-0.5,) * 3, (0.5,) * 3))
                out = vp.jacobian_det(vp.bind(lat, v, f), lat.rest_points * 1e300)
            elif case == "solve directions":
                lat = vp.Lattice((2, 2, 2), "LINEAR", bounds=((-0.5,) * 3, (0.5,) * 3))
                sol = vp.bind(lat, v, f).solve(lat.rest_points, directions=[[1e300, 1e300, 0.0]],
                                               preserve_volume=False)
                out = [sol.volume, sol.plain_volume]
            elif case == "volume_scale":
                v = v * 1e8
                lat = vp.Lattice((1, 1, 1), bounds=(v.min(0), v.max(0)))
                sol = vp.bind(lat, v, f).solve(lat.rest_points, volume_scale=1e300)
                out = [sol.target_volume, sol.volume]
            else:
                v = np.array([[0, 0, 0], [0.3, 0, 0], [0, 0.3, 0], [0.1, 0.1, 0]]) * 1e-100
                f = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
                lo, hi = v.min(0), v.max(0)
                hi[2] = lo[2] + 1e-103
                lat = vp.Lattice((1, 2, 1), "LINEAR", bounds=(lo, hi))
                sol = vp.bind(lat, v, f).solve(lat.rest_points, pins=[(1, v[1] + [0.015, -0.035, 0.05])])
                measured = vp.signed_volume(sol.verts, f)
                assert abs(measured - sol.volume) <= 1e-6 * abs(measured) or sol.warnings, \
                    (sol.volume, measured)
                return
        except ValueError:
            return
    assert np.isfinite(out).all(), out


@pytest.mark.parametrize("case", ["deform", "jacobian_det"])
def test_regression_float32_range(case):
    """Smallest reproductions (float32 bindings; float64 is fine): (deform) one control point of a
    2x2x2 lattice moved by 1e39 gives inf vertices; (jacobian_det) a sphere of radius 4e-46 in a
    lattice fitted around it gives NaN determinants at the rest pose. Expected: a ValueError, or
    finite results."""
    v, f = vp.icosphere(2, 0.4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        if case == "deform":
            lat = vp.Lattice((2, 2, 2), "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
            b = vp.bind(lat, v, f, dtype=np.float32)
            P = lat.rest_points.copy()
            P[0] += 1e39
            try:
                out = b.deform(P)
            except ValueError:
                return
        else:
            v = v * 1e-45
            lat = vp.Lattice((1, 1, 2), "LINEAR", bounds=(v.min(0), v.max(0)))
            b = vp.bind(lat, v, f, dtype=np.float32)
            try:
                out = vp.jacobian_det(b, lat.rest_points)
            except ValueError:
                return
    assert np.isfinite(out).all()


_HANG_SCRIPT = """
import numpy as np, vpffd_addon as vp, warnings
warnings.simplefilter("ignore")
v, f = vp.icosphere(1, 0.4)
v = v * 1e15
lat = vp.Lattice((4, 1, 5), ("CATMULL_ROM", "CARDINAL", "BSPLINE"), bounds=((-1e300,) * 3, (1e300,) * 3))
influence = np.ones(len(v))
influence[[2, 5, 9, 25, 28, 31, 33, 35, 37]] = 0
b = vp.bind(lat, v, f, influence=influence)
d = [0.23872312, -0.79516732, 0.86447958]
try:
    sol = b.solve(np.zeros((lat.n_points, 3)), directions=[d, d], pins=[(k, v[k]) for k in (29, 19, 16)])
    print("returned", np.isfinite([sol.volume, sol.plain_volume]).all())
except ValueError as exc:
    print("ValueError", exc)
"""


def test_regression_solve_hangs():
    """Smallest reproduction found (in a subprocess, killed after 10 s): a sphere of radius 4e14
    in a 4x1x5 lattice with bounds +-1e300, every control point moved to the origin, two
    identical correction directions and three pins at their vertices' rest positions: solve
    never returns. Expected: a ValueError (the values overflow) or a finite Solution."""
    import subprocess
    import sys
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root)
    try:
        out = subprocess.run([sys.executable, "-c", _HANG_SCRIPT], capture_output=True, text=True,
                             timeout=10, env=env, cwd=root)
    except subprocess.TimeoutExpired:
        raise AssertionError("solve did not return within 10 s")
    assert out.stdout.startswith(("ValueError", "returned True")), out.stdout + out.stderr


@pytest.mark.xfail(strict=True, reason="known bug far-translation-volume (see KNOWN_BUGS)")
def test_known_bug_far_translation_volume():
    """Smallest reproduction: an icosphere in a 1x1x1 lattice whose single point is moved by
    1e8; solve(preserve_volume=False) (no correction: a pure translation). Expected
    Solution.volume == the volume of Solution.verts (the rest volume); got ~20% off."""
    v, f = vp.icosphere(2, 0.4)
    lat = vp.Lattice((1, 1, 1), "LINEAR", bounds=(v.min(0), v.max(0)))
    b = vp.bind(lat, v, f)
    P = lat.rest_points + np.array([[3.1e7, -7.7e7, 5.3e7]])
    sol = b.solve(P, preserve_volume=False)
    measured = vp.signed_volume(sol.verts - sol.verts.mean(0), f)
    assert abs(sol.volume - measured) <= 1e-6 * abs(measured), (sol.volume, measured)


@pytest.mark.parametrize("size", [1e-3, 1e-4])
def test_fixed_bug_open_mesh_float32_cancellation(size):
    """Smallest reproduction: an open mesh (an icosphere with an open bowl) of size ~`size`,
    0.14 from the centre of a 2x2x2 lattice, float32 binding, solved at rest (no deformation):
    the lattice moves (8e-5 / 0.03) and the vertices enclose 0.9988 / 0.708 of the rest volume
    while Solution.volume said 1.0, no warning. float64 is right to 1e-9. Fixed: the volume is
    right, or a warning says it is below float32's rounding."""
    v1, f1 = vp.icosphere(2, 0.5)
    hv, hf = vp.icosphere(1, 0.2, (0.75, 0.6, 0.55))
    hf = hf[hv[hf].mean(1)[:, 2] < 0.55]
    v = np.vstack([v1, hv]) * size + np.array([0.1, -0.05, 0.08])
    f = np.vstack([f1, hf + len(v1)])
    lat = vp.Lattice((2, 2, 2), "LINEAR", bounds=((-0.5,) * 3, (0.5,) * 3))
    b = vp.bind(lat, v, f, dtype=np.float32)
    sol = b.solve(lat.rest_points, axes="XYZ")
    measured = vp.signed_volume(sol.verts, f, origin=lat.centre)
    assert abs(measured / b.rest_volume - 1) <= 1e-4 or sol.warnings, measured / b.rest_volume


def test_fixed_bug_float32_plain_volume_nan():
    """The fuzzer's case: a flat closed tetrahedron at 1e15 in a 1x1x2 LINEAR lattice, float32,
    both control points flung ~2e19, corrected along Z then Y: gave Solution(volume=0.0,
    plain_volume=nan). Fixed: a ValueError (overflow), as for the other fields."""
    v = np.array([[0, 0, 0], [0.25, 0, 0], [0, 0.25, 0], [0.125, 0.125, 0]]) + 1e15
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    lat = vp.Lattice((1, 1, 2), "LINEAR", bounds=((1e15, 1e15, 1000083610590425.5),
                                                   (1e15 + 0.25, 1e15 + 0.25, 1000265102230911.1)))
    b = vp.bind(lat, v, f, dtype=np.float32)
    P = np.array([[2.3667510738399764e+19, 1.718972776710319e+19, -1.277120615780433e+19],
                  [-2.296534186858809e+19, -1.1310910467870028e+19, 7.510322437428608e+17]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            sol = b.solve(P, axes="ZY")
        except ValueError:
            return
    assert np.isfinite([sol.volume, sol.plain_volume, sol.target_volume]).all(), sol
