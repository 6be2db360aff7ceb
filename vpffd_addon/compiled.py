"""Compiled per-frame kernels (numba, where it is installed), one pass over the faces or blocks
each with no temporary arrays (docs/performance.md, "Compiled kernels"): the volume gradient
along an axis, behind the steps interface of `steps.py`, and the layout of a lattice bind
(`layout_kernels.py`), which a mesh moving through the lattice pays on every frame. The NumPy code
stays the reference and the fallback.

Nothing compiles on import: `load()` compiles the kernels, or loads them from numba's cache, and
from then on `backends.default_steps(binding)` hands solves the compiled steps and `bind_kernels` hands
binds the layout kernels. numba holds the GIL while it compiles (seconds), so an interactive host
calls `load()` where a pause does not matter.

Each kernel call is serial and sums in a fixed order; calls run on the fixed parts of
`parallel.py`, as NumPy's kernels do, so a result never depends on what ran before (chunked renders
stay bit-identical to one render on the same machine). `over` hands a pass's parts to the Python
worker threads, or, from `TEAM_PARTS` parts on, to numba's own threads in one call (the pass's
team): the same call per part either way (docs/performance.md, "Every core").
"""
import threading

import numpy as np

from . import atomics, frame_kernels, layout_kernels, parallel, solve_kernels
from .bases import axis_cells
from .linalg3 import affine
from .mesh import connected_components, is_closed
from .steps import CAPABILITIES, NumpySteps, Steps
from .volume import face_volumes

#: numba releases the kernels are checked with (first, last), as (major, minor).
NUMBA_RANGE = ((0, 61), (0, 68))
#: NumPy releases numba 0.68 accepts (first, last): Blender shares one NumPy between extensions,
#: and numba refuses a newer one at import; checked first, so that the panel says so plainly.
NUMPY_RANGE = ((1, 24), (2, 5))

_state = {"kernels": None, "why": "not loaded (vpffd_addon.compiled.load() compiles the kernels)",
          "teams": None}
#: How long a fused pass's part waits at its barrier for the other parts, and the calling thread
#: for the parts to be done, spinning, before taking the slow, sure way (microseconds; a worker's
#: wake takes 30-80 us on the project's two-core machines): docs/performance.md, "Fewer hand-overs".
SPIN_US = {"barrier": 2000, "done": 1000}
#: After this many fused passes in a row that ran out of spins (a part at its barrier, or the
#: caller looking for the parts done), the next `FUSED_REST` passes run one hand-over per pass:
#: where the threads do not get cores of their own (a busy machine, two solves at once, a
#: container given less CPU time than it has cores) spinning would only take time from them.
FUSED_MISSES, FUSED_REST = 3, 200
_fused = {"misses": 0, "rest": 0}


def why():
    """Why the compiled kernels are not in use, in words; None when they are."""
    return None if _state["kernels"] is not None else _state["why"]


def ready():
    """Whether `load()` succeeded (solves then use the compiled steps)."""
    return _state["kernels"] is not None


def unload():
    """Go back to the NumPy steps (the kernels stay compiled for a later `load()`)."""
    if _state["kernels"] is not None:
        _state["loaded"] = _state["kernels"]
    _state["kernels"] = None
    _state["why"] = "switched off (vpffd_addon.compiled.unload())"


def _version(text):
    parts = []
    for piece in text.split(".")[:2]:
        digits = "".join(ch for ch in piece if ch.isdigit())
        parts.append(int(digits or 0))
    return tuple(parts)


def load(cache=True, teams=None):
    """Compile the kernels (or load them from numba's cache when `cache`). Returns True when they
    are ready; otherwise False, with `why()` saying why (numba missing, a version outside
    `NUMBA_RANGE`, a NumPy outside `NUMPY_RANGE`, a compile error). The cache folder is numba's
    (`NUMBA_CACHE_DIR`, set by the host before the first import of numba). `teams`: whether to
    compile the passes for numba's own threads too (`over`); None: where this machine has
    `TEAM_PARTS` cores or more (on fewer, a frame never has that many parts, and their compile
    would double the first one's time for nothing)."""
    if teams is None:
        teams = parallel.CORES >= TEAM_PARTS
    if _state["kernels"] is None and _state.get("loaded") is not None:
        _state["kernels"], _state["why"] = _state["loaded"], None
    if _state["kernels"] is not None:
        if teams and _state["teams"] is None:       # (loaded without them before: add them)
            import numba
            _try_teams(numba, cache)
        return True
    if not NUMPY_RANGE[0] <= _version(np.__version__) <= NUMPY_RANGE[1]:
        lo, hi = (".".join(map(str, v)) for v in NUMPY_RANGE)
        _state["why"] = f"NumPy {np.__version__} is outside the range the compiled kernels support ({lo} to {hi})"
        return False
    try:
        import numba
    except Exception as exc:     # ImportError, or numba refusing this NumPy at import
        _state["why"] = f"numba cannot be imported ({type(exc).__name__}: {exc})"
        return False
    version = _version(numba.__version__)
    if not NUMBA_RANGE[0] <= version <= NUMBA_RANGE[1]:
        lo, hi = (".".join(map(str, v)) for v in NUMBA_RANGE)
        _state["why"] = f"numba {numba.__version__} is outside the checked range {lo} to {hi}"
        return False
    try:
        kernels = _compile(numba, cache)
        _smoke(kernels)
        _state["spins"] = atomics.spins_for(kernels["wait_count"], SPIN_US)
    except Exception as exc:
        _state["why"] = f"the kernels did not compile ({type(exc).__name__}: {exc})"
        return False
    _state["kernels"], _state["why"] = kernels, None
    if teams:
        _try_teams(numba, cache)
    return True


def _try_teams(numba, cache):
    """Add the teams to the loaded kernels and check them (`_smoke`); where that fails, the
    kernels stay without them (the Python threads then serve every part) and `_state["teams"]`
    says why."""
    kernels = _state["kernels"]
    try:
        _add_teams(numba, cache, kernels)
        _smoke(kernels)
    except Exception as exc:
        _state["teams"] = f"numba's threads are not used ({type(exc).__name__}: {exc})"
        for name in [k for k in kernels if k.endswith("_team")]:
            del kernels[name]


def _compile(numba, cache):
    njit = numba.njit(cache=cache, nogil=True, fastmath=False, error_model="numpy")
    # Sums whose order the compiler may choose (to vectorise them) and fused multiply-adds: still
    # one fixed order once compiled, so every run gives the same result.
    fast = {"reassoc", "contract"}
    njit_sums = numba.njit(cache=cache, nogil=True, fastmath=fast, error_model="numpy")
    inline = numba.njit(inline="always", fastmath=fast, error_model="numpy")

    return {**layout_kernels.define(njit), **solve_kernels.define(njit, njit_sums, inline, atomics.define()),
            **frame_kernels.define(njit)}


def _add_teams(numba, cache, kernels):
    """Add every pass's team (`<name>_team`, `over`) to `kernels`, where numba's threading layer
    allows (`_team_layer`); `_state["teams"]` then says "ready", else why not."""
    if not _team_layer(numba):
        _state["teams"] = ("numba's threads are not used (this process runs another of numba's threading "
                           "layers than workqueue, whose idle threads would spin)")
        return
    njit_team = numba.njit(cache=cache, nogil=True, parallel=True, error_model="numpy")
    for module in (solve_kernels, frame_kernels, layout_kernels):
        # Each module's teams call `prange` and its kernels (`_k_<name>`) as globals of the
        # module: numba caches a function that calls global functions, not one that calls a
        # function it closes over.
        space = vars(module)
        space["prange"] = numba.prange
        for name in module._TEAMS:
            space["_k_" + name] = kernels[name]
        kernels.update({name + "_team": njit_team(space[name + "_team"]) for name in module._TEAMS})
    _team["set_threads"] = numba.set_num_threads
    _team["most"] = int(numba.config.NUMBA_NUM_THREADS)
    _state["teams"] = "ready"


#: From this many parts on, a pass runs as one call on numba's own worker threads (`over`); below
#: it, on `parallel.py`'s Python threads. Their hand-overs go through the GIL one worker after
#: another, so their cost grows with the workers, while a team's launch costs about the same on
#: 2 or 16 threads; measured on 16 cores, the solve and the re-embedding gain from about 10 parts
#: on and not below (docs/performance.md, "Every core").
TEAM_PARTS = 10
_team = {"lock": threading.Lock(), "set_threads": None, "most": 0}


def _team_layer(numba):
    """Whether numba's parallel mode may run the teams: on its "workqueue" threading layer, whose
    idle threads wait on a condition (OpenMP's spin for a while after every call, holding cores),
    chosen here unless another user of numba in this process started a layer already. The
    workqueue layer must not be entered by two threads at once: `over` holds a lock around it."""
    try:
        from numba.np.ufunc import parallel as layer
        if getattr(layer, "_is_initialized", False):
            return numba.threading_layer() == "workqueue"
        numba.config.THREADING_LAYER = "workqueue"
        return True
    except Exception:       # (a numba without these: the Python threads serve every part)
        return False


def teams(name, parts, kernels=None):
    """Whether `over` runs kernel `name` over `parts` as one team call (else on the Python
    threads, where a caller may rather put several kernels into one hand-over per part)."""
    K = _state["kernels"] if kernels is None else kernels
    return len(parts) >= TEAM_PARTS and K is not None and K.get(name + "_team") is not None


def over(name, parts, *args, returns=0, per_part=(), kernels=None):
    """Kernel `name`(*args, start, stop) for every part of `parts` (slices): [its result per part]
    (`returns` values each; None where 0). The arguments at the indices `per_part` hold a row per
    part: part j gets row j. From `TEAM_PARTS` parts on, and where the kernel has a team
    (`<name>_team`), all parts in one call on numba's threads; otherwise on `parallel.py`'s.
    Either way every part makes the same call, so the result is the same bit for bit. `kernels`:
    the kernels the caller holds (default: the loaded ones; a solve's steps keep theirs even where
    `unload()` runs meanwhile)."""
    K = _state["kernels"] if kernels is None else kernels
    team = K[name + "_team"] if teams(name, parts, K) else None
    if team is None:
        fn = K[name]
        if per_part:
            got = parallel.run(lambda j: fn(*[a[j] if i in per_part else a for i, a in enumerate(args)],
                                            parts[j].start, parts[j].stop), list(range(len(parts))))
        else:
            got = parallel.run(lambda p: fn(*args, p.start, p.stop), parts)
        return [(r,) for r in got] if returns == 1 else got
    edges = np.array([p.start for p in parts] + [parts[-1].stop], np.int64)
    got = np.zeros((len(parts), returns)) if returns else None
    with _team["lock"]:
        _team["set_threads"](max(1, min(len(parts), _team["most"])))
        if returns:
            team(edges, got, *args)
        else:
            team(edges, *args)
    return [None] * len(parts) if got is None else [tuple(row) for row in got]


def _smoke(kernels):
    """Run every kernel on tiny problems in both precisions (so that they compile now, not in a
    frame) and check them: the layout kernels against NumPy bit for bit, the compiled solve against
    the NumPy steps."""
    # The layout kernels must give NumPy's values bit for bit (binds are compared array by array
    # in the tests); here a few coordinates in, at the edges of and outside a small axis.
    x = np.array([-0.9, -0.5, -0.31, 0.0, 0.2, 0.5, 0.77, 1.6])
    for n in (2, 3, 5):
        cell, t = np.empty(len(x), np.int64), np.empty(len(x))
        kernels["axis_cells"](np.stack([x, -x, x], 1), 2, n, -0.5, 0.5, cell, t, 0, len(x))
        _team_agrees(kernels, "axis_cells", (np.stack([x, -x, x], 1), 2, n, -0.5, 0.5, cell, t), len(x), (5, 6))
        if not all(np.array_equal(a, b) for a, b in zip((cell, t), axis_cells(x, n, -0.5, 0.5))):
            raise RuntimeError(f"the cells of a {n}-point axis differ from NumPy's")
    # A bind's other kernels, with the argument types a bind gives them (each signature compiles
    # once: here, not in the first frame).
    order = np.argsort(cell, kind="stable")
    runs = np.flatnonzero(np.r_[True, cell[order][1:] != cell[order][:-1]])
    lengths = np.diff(np.r_[runs, len(x)])
    slot, sorted_slot = np.empty(len(x), np.int64), np.empty(len(x), np.int64)
    kernels["slots"](order, runs, lengths, np.arange(len(runs)), 8, slot, sorted_slot, 0, len(runs))
    _team_agrees(kernels, "slots", (order, runs, lengths, np.arange(len(runs)), 8, slot, sorted_slot), len(runs), (5, 6))
    if not np.array_equal(slot[order] // 8, np.repeat(np.arange(len(runs)), lengths)):
        raise RuntimeError("the slots of the runs are not in their blocks")
    coords = np.array([[0.0, 1.0, 0.0, 0.3], [0.0, 0.0, 1.0, 0.2], [0.0, 0.0, 0.0, 1.1]])
    tris_t = np.array([[0, 1, 3], [1, 2, 2], [2, 3, 0]], np.int64)
    vol = np.empty(3)
    kernels["face_volumes"](np.ascontiguousarray(coords.T), tris_t, vol, 0, 3)
    _team_agrees(kernels, "face_volumes", (np.ascontiguousarray(coords.T), tris_t, vol), 3, (2,))
    if not np.array_equal(vol, face_volumes(coords, tris_t)):
        raise RuntimeError("the faces' volume terms differ from NumPy's")
    # Their sums in chunks of two faces (the last one short), as `volume.chunked_sums` adds them,
    # with a face turned (a negative term).
    turned = np.array([[0, 1, 3, 1, 3], [1, 3, 2, 2, 1], [2, 2, 0, 3, 2]], np.int64)
    terms = face_volumes(coords, turned)
    sums = np.empty((3, 2))
    kernels["face_volume_sums"](np.ascontiguousarray(coords.T), turned, 2, sums, 0, 3)
    _team_agrees(kernels, "face_volume_sums", (np.ascontiguousarray(coords.T), turned, 2, sums), 3, (3,))
    if not (terms.min() < 0 < terms.max()
            and np.array_equal(sums[:, 0], [terms[0] + terms[1], terms[2] + terms[3], terms[4]])
            and np.array_equal(sums[:, 1], [abs(terms[0]) + abs(terms[1]), abs(terms[2]) + abs(terms[3]),
                                            abs(terms[4])])):
        raise RuntimeError("the faces' volume sums differ from NumPy's")
    # The same about other origins, from points of either precision (`volume.MeasuredIn`): the
    # sums of one island about one origin, the terms of two islands each about its own.
    origins, face_island = np.array([[0.1, -0.2, 0.05], [0.3, 0.2, -0.1]]), np.array([0, 1, 0, 1, 1], np.int64)
    for points in (np.ascontiguousarray(coords.T), np.ascontiguousarray(coords.T, dtype=np.float32)):
        about = [face_volumes((points.astype(np.float64) - o).T, turned) for o in origins]
        kernels["face_volume_sums_about"](points, origins[0], turned, 2, sums, 0, 3)
        _team_agrees(kernels, "face_volume_sums_about", (points, origins[0], turned, 2, sums), 3, (4,))
        vol = np.empty(5)
        kernels["face_volumes_about"](points, origins, face_island, turned, vol, 0, 5)
        _team_agrees(kernels, "face_volumes_about", (points, origins, face_island, turned, vol), 5, (4,))
        if not (np.array_equal(sums[:, 0], [about[0][0] + about[0][1], about[0][2] + about[0][3], about[0][4]])
                and np.array_equal(vol, np.where(face_island == 0, about[0], about[1]))):
            raise RuntimeError("the faces' volume terms about other origins differ from NumPy's")
    n_slots = 8 * len(runs)
    # Closedness and islands: a tetrahedron, a second one beside it and a vertex no face uses;
    # then with a face turned, a face missing, a face doubled and a degenerate face added.
    tet = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]], np.int64)
    two = np.vstack([tet, tet + 4])
    for tris, n in ((two, 9), (np.vstack([two[:1, ::-1], two[1:]]), 8), (two[1:], 8),
                    (np.vstack([two, two[:1]]), 8), (np.vstack([two, [[0, 0, 5]]]), 8)):
        start, pairs = np.zeros(n + 1, np.int64), np.empty(6 * len(tris), np.int32)
        kernels["vertex_incidence"](np.ascontiguousarray(tris.T), start, pairs)
        labels = np.empty(n, np.int64)
        count = kernels["components"](np.ascontiguousarray(tris.T), np.empty(n, np.int64), labels)
        ref_labels, ref_count = connected_components(tris, n)
        if bool(kernels["closed"](start, pairs)) != is_closed(tris, n) or count != ref_count \
                or not np.array_equal(labels, ref_labels):
            raise RuntimeError("the compiled closedness or islands differ from NumPy's")
    # Cells and keys of coordinates in, at the edges of and outside a 5 x 4 x 3 lattice, twice over,
    # sorted in two parts (as on two worker threads): every key of the first part is in the second
    # too, and the parts' places must follow each other within a key.
    shape = np.array([5, 4, 3], np.int64)
    xyz = np.stack([x, -x[::-1], 0.5 * x], 1)
    xyz = np.ascontiguousarray(np.vstack([xyz, xyz[::-1]]))
    dims = shape + 6
    cells = [axis_cells(xyz[:, a], int(shape[a]), -0.5, 0.5)[0] + 3 for a in range(3)]
    V = len(xyz)
    origin = np.array([[0.1, -0.2, 0.3], [0.5, 0.25, -1.0], [0.0, 0.0, 0.0]])
    for labels in (np.zeros(0, np.int64), (np.arange(V) % 3).astype(np.int64)):
        k = 1 if len(labels) == 0 else 3
        K = k * int(np.prod(dims))
        key, counts, rel = np.empty(V, np.int64), np.zeros((2, K), np.int64), np.empty((V, 3))
        args = (xyz, shape, np.full(3, -0.5), np.full(3, 0.5), labels, dims, origin, labels, rel, key)
        for j, (v0, v1) in enumerate(((0, len(x)), (len(x), V))):
            kernels["cell_keys"](*args, counts[j], v0, v1)
        _team_agrees(kernels, "cell_keys", args + (counts,), V, (8, 9, 10), edges=(0, len(x), V))
        if not np.array_equal(rel, xyz - origin[labels if k > 1 else 0]):
            raise RuntimeError("the coordinates relative to the volume origins differ from NumPy's")
        start, place = np.empty(K + 1, np.int64), np.empty((2, K), np.int64)
        kernels["key_starts"](counts, start, place)
        place_start = place.copy()
        # (runs in blocks of 2 slots, as `slots` lays them out; every vertex 0 to 2 entries)
        run_len = np.diff(start)
        blocks = -(-run_len // 2)
        base = (np.cumsum(blocks) - blocks) * 2 - start[:-1]
        entry_start = np.concatenate([[0], np.cumsum(np.arange(V) % 3)]).astype(np.int64)
        p_n = 2 * int(blocks.sum())
        got, p_slot, p_sorted = np.empty(V, np.int64), np.empty(V, np.int64), np.empty(V, np.int64)
        count = np.zeros(p_n + 1, np.int64)
        placed = (key, place, base, entry_start, got, p_slot, p_sorted, count)
        for j, (v0, v1) in enumerate(((0, len(x)), (len(x), V))):
            kernels["place_slots"](*placed[:1], place[j], *placed[2:], v0, v1)
        _team_agrees(kernels, "place_slots", placed[:1] + (place_start,) + placed[2:], V, (4, 5, 6, 7),
                     edges=(0, len(x), V))
        want = (cells[2] * dims[1] + cells[1]) * dims[0] + cells[0] + (labels * (K // k) if k > 1 else 0)
        if not (np.array_equal(got, np.argsort(want, kind="stable")) and start[-1] == V
                and np.array_equal(key, want)):
            raise RuntimeError("the counting sort's keys or order differ from NumPy's")
        keyed = np.flatnonzero(run_len)
        want_slot, want_sorted = np.empty(V, np.int64), np.empty(V, np.int64)
        kernels["slots"](got, start[keyed], run_len[keyed], (np.cumsum(blocks) - blocks)[keyed], 2, want_slot,
                         want_sorted, 0, len(keyed))
        want_start = np.zeros(p_n + 1, np.int64)
        kernels["slot_incidence_start"](want_slot, entry_start, want_start)
        kernels["running_sum"](count)
        if not (np.array_equal(p_slot, want_slot) and np.array_equal(p_sorted, want_sorted)
                and np.array_equal(count, want_start)):
            raise RuntimeError("the slots placed with the sort differ from the slots pass's")
    xyz = np.stack([x, -x, 2 * x], 1)
    for labels in (np.zeros(0, np.int64), (np.arange(len(x)) % 2).astype(np.int64)):
        k = 1 if len(labels) == 0 else 2
        rows = np.zeros(len(x), np.int64) if k == 1 else labels
        for given in (xyz, xyz.astype(np.float32)):
            out, lo, hi, rel = np.empty((len(x), 3)), np.empty((k, 3)), np.empty((k, 3)), np.empty((len(x), 3))
            bad = kernels["positions"](given, labels, out, lo, hi, 0, len(x))
            kernels["relative"](out, 0.5 * (lo + hi), labels, rel, 0, len(x))
            _team_agrees(kernels, "positions", (given, labels, out, lo[None], hi[None]), len(x), (2, 3, 4),
                         edges=(0, len(x)), check=lambda got, bad=bad: got[0, 0] == bad)
            _team_agrees(kernels, "relative", (out, 0.5 * (lo + hi), labels, rel), len(x), (3,))
            want = given.astype(np.float64)
            if not (bad == 0 and np.array_equal(out, want)
                    and np.array_equal(lo, np.array([want[rows == r].min(0) for r in range(k)]))
                    and np.array_equal(hi, np.array([want[rows == r].max(0) for r in range(k)]))
                    and np.array_equal(rel, want - (0.5 * (lo + hi))[rows])):
                raise RuntimeError("the checked positions and their bounds differ from NumPy's")
    origin = np.array([[0.1, -0.2, 0.3], [-0.4, 0.5, 0.7]])
    fixed = np.ones(len(x))
    fixed.flags.writeable = False       # (a pipeline's weights are read-only: another signature)
    for dtype in (np.float32, np.float64):
        # (x0 relative to one origin, then to each vertex's island's row of two; weights one
        # may write and read-only ones)
        for rows, weights in zip((np.zeros(0, np.int64), (np.arange(len(x)) % 2).astype(np.int64)) * 2,
                                 (np.ones(len(x)),) * 2 + (fixed,) * 2):
            params, influence = np.zeros((4, n_slots), dtype), np.zeros(n_slots, dtype)
            x0 = np.zeros((3, n_slots), dtype)
            xyz = np.stack([x, x, x], 1)
            values = (order, sorted_slot, xyz, origin, rows, weights, np.array([5, 5, 5], np.int64),
                      np.full(3, -0.5), np.full(3, 0.5), 1e-6, params, influence, x0)
            outside = kernels["sorted_values"](*values, 0, len(x))
            want = x - origin[rows if len(rows) else 0, 2]
            if not (np.array_equal(params[0, slot], t.astype(dtype)) and np.array_equal(x0[2, slot], want.astype(dtype))
                    and outside == 3):                  # (-0.9, 0.77 and 1.6)
                raise RuntimeError("the per-slot values are not at their slots")
            _team_agrees(kernels, "sorted_values", values, len(x), (10, 11, 12), check=lambda got: got[:, 0].sum() == 3)
        _smoke_solve(kernels, dtype)


def _smoke_solve(kernels, dtype):
    """The kernels of a compiled solve on a tetrahedron in one block of a 4x4x4 lattice (three
    kinds of axes, partly outside so that taps clamp), against the same sums in NumPy."""
    from .bases import _local_weights
    from .volume import gradient_component
    kinds = ("BSPLINE", "CARDINAL", "LINEAR")
    tris_t = np.array([[0, 0, 0, 1], [2, 1, 3, 2], [1, 3, 2, 3]], np.int64)
    t = np.array([[0.1, 0.5, 0.9, 0.3], [0.7, 0.2, 0.4, 0.6], [0.25, 0.75, 0.5, 0.0]])
    params = np.vstack([t, [1.0, 0.5, 1.0, 0.8]]).astype(dtype)
    cell, shape = np.array([[0, 2, 1]], np.int64), np.array([4, 4, 4], np.int64)
    D = np.sin(np.arange(3 * 64, dtype=float)).reshape(3, 64).astype(dtype)
    x0 = np.cos(np.arange(12, dtype=float)).reshape(3, 4).astype(dtype)
    # NumPy's S B, (4 slots, 64 points): each axis's weights at its clamped taps i-1..i+2.
    rows = [np.zeros((4, n)) for n in shape]
    for a in range(3):
        w = _local_weights(t[a], kinds[a], derivative=False)[0]
        for k in range(4):
            np.add.at(rows[a], (np.arange(4), np.clip(cell[0, a] - 1 + k, 0, shape[a] - 1)), w[:, k])
    SB = params[3, :, None].astype(float) * np.einsum("sw,sv,su->swvu", rows[2], rows[1], rows[0]).reshape(4, 64)
    X = np.empty((3, 4), dtype)
    coef = solve_kernels.constants(kinds, dtype)
    kernels["forward"](params, coef, cell, shape, D, x0, np.arange(3), X, 0, 1)
    _team_agrees(kernels, "forward", (params, coef, cell, shape, D, x0, np.arange(3), X), 1, (7,))
    tol = 1e-5 if dtype == np.float32 else 1e-12
    if not np.allclose(X, x0 + D.astype(float) @ SB.T, rtol=0, atol=tol * 10):
        raise RuntimeError("the compiled forward product differs from NumPy's")
    # The gradient passes on the closed tetrahedron (every vertex's faces one closed fan: rings)
    # and on it without its last face (three open fans: pairs, and one ring).
    for faces, n_rings in ((tris_t, 4), (np.ascontiguousarray(tris_t[:, :3]), 1)):
        start_v, pairs_v = np.zeros(5, np.int64), np.empty(6 * faces.shape[1], np.int32)
        kernels["vertex_incidence"](faces, start_v, pairs_v)
        rstart, entries_v, ring_v = np.empty(5, np.int64), np.empty_like(pairs_v), np.empty(4, np.int8)
        kernels["vertex_rings"](start_v, pairs_v, rstart, entries_v, ring_v)
        slot = np.arange(4)
        start, entries, ring = np.zeros(5, np.int64), np.empty(rstart[-1], np.uint32), np.zeros(4, np.int8)
        kernels["slot_incidence_start"](slot, rstart, start)
        kernels["slot_incidence_fill"](slot, rstart, entries_v[:rstart[-1]], ring_v, start, entries, ring, 0, 4)
        _team_agrees(kernels, "slot_incidence_fill", (slot, rstart, entries_v[:rstart[-1]].copy(), ring_v, start,
                                                      entries, ring), 4, (5, 6))
        if int(ring.sum()) != n_rings:
            raise RuntimeError("the faces around the vertices were not made rings where they close")
        for xp, xq in ((X[1], X[2]), (X[1].astype(float), X[2].astype(float))):
            g, M, sums = np.empty(4), np.empty((1, 64)), np.empty((2, 1))
            runs, A, done = np.array([0, 1], np.int64), np.empty((64, 1)), np.zeros(1, np.uint8)
            kernels["gradient_runs"](xp, xq, start, entries, ring, params, x0[0], g, M, sums, runs, A, done, 0, 1)
            _team_agrees(kernels, "gradient_runs", (xp, xq, start, entries, ring, params, x0[0], g, M, sums,
                                                    runs, A, done), 1, (7, 8, 9, 11, 12))
            ref = gradient_component(xp[faces], xq[faces], faces, 4)
            alpha = np.zeros((1, 64))
            kernels["reduce_blocks"](M, cell, np.zeros(1, np.int64), shape, coef, alpha)
            # the run's sums as the pass made them, and as reduce_runs makes them where no part held the run
            for A_, done_ in ((A.copy(), done.copy()), (np.empty((64, 1)), np.zeros(1, np.uint8))):
                from_runs = np.zeros((1, 64))
                kernels["reduce_runs"](M, runs, A_, done_, cell, np.zeros(1, np.int64), shape, coef, from_runs)
                if not (done_[0] == 1 and np.array_equal(from_runs, alpha)):
                    raise RuntimeError("the compiled transpose from the runs' sums differs from the blocks'")
            if not (done[0] == 1 and np.allclose(g, ref, rtol=0, atol=tol)
                    and np.allclose(alpha[0], SB.T @ ref, rtol=0, atol=tol)
                    and np.isclose(sums[0, 0], x0[0].astype(float) @ ref, rtol=0, atol=tol)
                    and np.isclose(sums[1, 0], np.abs(params[3] * ref).sum(), rtol=0, atol=tol)):
                raise RuntimeError("the compiled gradient pass differs from NumPy's sums")
        g, M, sums = np.empty((3, 4)), np.empty((3, 1, 64)), np.empty((3, 2, 1))
        A, done = np.empty((3, 64, 1)), np.zeros((3, 1), np.uint8)
        kernels["gradient_runs3"](X, start, entries, ring, params, x0, g, M, sums, runs, A, done, 0, 1)
        _team_agrees(kernels, "gradient_runs3", (X, start, entries, ring, params, x0, g, M, sums, runs, A, done), 1,
                     (6, 7, 8, 10, 11))
        for a in range(3):
            ref = gradient_component(X[(a + 1) % 3][faces], X[(a + 2) % 3][faces], faces, 4)
            alpha = np.zeros((1, 64))
            kernels["reduce_blocks"](M[a], cell, np.zeros(1, np.int64), shape, coef, alpha)
            # (twice from the same runs' sums: a gradient's transpose may be asked for again)
            from_runs = np.zeros((2, 64))
            for row in (0, 1):
                kernels["reduce_runs"](M[a], runs, A[a], done[a], cell, np.array([row]), shape, coef, from_runs)
            if not (done[a, 0] == 1 and np.array_equal(from_runs[0], alpha[0])
                    and np.array_equal(from_runs[1], alpha[0])):
                raise RuntimeError("the compiled three-axis transpose from the runs' sums differs from the blocks'")
            if not (np.allclose(g[a], ref, rtol=0, atol=tol) and np.allclose(alpha[0], SB.T @ ref, rtol=0, atol=tol)
                    and np.isclose(sums[a, 0, 0], x0[a].astype(float) @ ref, rtol=0, atol=tol)
                    and np.isclose(sums[a, 1, 0], np.abs(params[3] * ref).sum(), rtol=0, atol=tol)):
                raise RuntimeError("the compiled three-axis gradient pass differs from NumPy's sums")
    # (five rows: the QR's pairs of reflections, rows taken two at a time and one alone)
    A = np.vstack([np.cos(np.arange(12.0)), np.sin(np.arange(12.0)), np.arange(12.0) % 5,
                   np.cos(0.7 * np.arange(12.0)) ** 2, np.arange(12.0) % 3])
    M, tau, u = A.copy(), np.empty(5), np.zeros(12)
    kernels["householder"](M, tau)
    u[:5] = np.linalg.solve(np.tril(M[:, :5]), np.ones(5))
    kernels["apply_q"](M, tau, u)
    if not np.allclose(u, np.linalg.lstsq(A, np.ones(5), rcond=None)[0], rtol=0, atol=1e-12):
        raise RuntimeError("the compiled QR's least-norm step differs from LAPACK's")
    mat = np.array([[0.3, -1.2, 0.7, 0.1], [2.0, 0.25, -0.5, -3.0], [0.1, 0.9, 1.7, 0.4], [0, 0, 0, 1.0]])
    for given in (A.T.copy(), np.ascontiguousarray(A.T, dtype=np.float32)):
        out = np.empty((len(given), 3))
        kernels["affine"](given, mat, out, 0, len(given))
        _team_agrees(kernels, "affine", (given, mat, out), len(given), (2,))
        if not np.array_equal(out, affine(given, mat)):
            raise RuntimeError("the compiled affine map differs from NumPy's")
    pos = np.array([[0.1, -2.5, 3.0], [1e-9, 7.25, -0.3]])
    for given in (pos[::-1].copy(), pos[::-1].astype(np.float32)):
        off, out = np.empty((2, 3), np.float32), np.empty((2, 3), np.result_type(given.dtype, np.float32))
        written = (pos - given).astype(np.float32)
        no_mat, no_still = np.zeros((0, 4)), np.zeros(0, np.bool_)
        flag, changed, moved = kernels["float32_offsets"](pos, no_mat, given, no_still, written, off, out, 0, 2)
        _team_agrees(kernels, "float32_offsets", (pos, no_mat, given, no_still, written, off, out), 2, (5, 6),
                     check=lambda got, r=(flag, changed, moved): (got[:, 0].max(), bool(got[:, 1].any()),
                                                                  got[:, 2].max()) == (r[0], bool(r[1]), r[2]))
        if not (flag == 0 and not changed and np.array_equal(off, written) and np.array_equal(out, given + written)
                and moved == float(np.abs(written).max())):
            raise RuntimeError("the compiled offsets differ from NumPy's")
        # mapped by a matrix, the second position kept at its input: as the map and then NumPy's
        still = np.array([False, True])
        kernels["float32_offsets"](pos, mat, given, still, np.zeros((0, 3), np.float32), off, out, 0, 2)
        mapped = affine(pos, mat)
        mapped[1] = given[1]
        if not np.array_equal(off, (mapped - given).astype(np.float32)):
            raise RuntimeError("the compiled offsets of mapped positions differ from NumPy's")
    L = np.array([[2.0, 0.0, 0.0], [1.0, 0.5, 0.0], [-1.0, 3.0, 4.0]])
    x, xt = np.empty(3), np.empty(3)
    kernels["triangular_solve"](L, np.arange(1.0, 4.0), x, False)
    kernels["triangular_solve"](L, np.arange(1.0, 4.0), xt, True)
    s = np.linalg.svd(L, compute_uv=False)
    if not (np.allclose(L @ x, np.arange(1.0, 4.0), rtol=0, atol=1e-12)
            and np.allclose(L.T @ xt, np.arange(1.0, 4.0), rtol=0, atol=1e-12)
            and abs(kernels["condition"](L, 12) / (s[0] / s[-1]) - 1) < 0.05):
        raise RuntimeError("the compiled triangular solves or condition estimate differ from LAPACK's")
    out = np.empty((4, 3))
    kernels["to_verts"](X, slot, np.zeros((1, 3)), np.zeros(4, np.int64), out, 0, 4)
    _team_agrees(kernels, "to_verts", (X, slot, np.zeros((1, 3)), np.zeros(4, np.int64), out), 4, (4,),
                 check=lambda got: got[:, 0].sum() == 0)
    if not np.array_equal(out, X.T.astype(float)):
        raise RuntimeError("the compiled vertices differ from the slots'")
    forward = (params, coef, cell, shape, D, x0)
    _fused_agrees(kernels, forward, X, "gradient_runs", (7, 8, 9, 11, 12), 1, lambda Y: (
        Y[1], Y[2], start, entries, ring, params, x0[0], np.empty(4), np.empty((1, 64)), np.empty((2, 1)),
        np.array([0, 1], np.int64), np.empty((64, 1)), np.zeros(1, np.uint8)))
    _fused_agrees(kernels, forward, X, "gradient_runs3", (6, 7, 8, 10, 11), 1, lambda Y: (
        Y, start, entries, ring, params, x0, np.empty((3, 4)), np.empty((3, 1, 64)), np.empty((3, 2, 1)),
        np.array([0, 1], np.int64), np.empty((3, 64, 1)), np.zeros((3, 1), np.uint8)))
    _fused_agrees(kernels, forward, X, "to_verts", (4,), 4, lambda Y: (
        Y, slot, np.zeros((1, 3)), np.zeros(4, np.int64), np.empty((4, 3))))


def _fused_agrees(kernels, forward, X, name, outs, stop, make_args):
    """Run `forward_then_<name>`, where loaded, on `forward`'s arguments (the forward pass's up to
    its components, all three here) with fresh coordinates Y and make_args(Y) (the second pass's,
    over 0..stop): in one part, and in two parts one after the other in this thread, whose first
    runs out of spins at its barrier and leaves its second pass undone (as a part whose partner
    never came would). Each must make X and what `name` made of make_args(X) (the arguments at
    `outs`, and to_verts' count), and count its parts as `CompiledSteps._refresh_then` reads them:
    so the fused passes compile now, not in a frame."""
    fused = kernels.get("forward_then_" + name)
    if fused is None:
        return
    want = make_args(X)
    returned = kernels[name](*want, 0, stop) or 0
    head = atomics.HEAD
    for parts, ran in ((((0, 1, 0, stop),), [1]), (((0, 0, 0, 0), (0, 1, 0, stop)), [0, 1])):
        Y = np.empty_like(X)
        args = make_args(Y)
        n = len(parts)
        sync = atomics.new_sync(n)
        for k, (b0, b1, v0, v1) in enumerate(parts):
            fused(*forward, np.arange(3, dtype=np.int64), Y, *args, sync, k, 100, b0, b1, v0, v1)
        if not (np.array_equal(Y, X) and all(np.array_equal(args[i], want[i]) for i in outs)
                and list(sync[head:head + n]) == ran and sync[atomics.DONE] == n
                and sync[head + 2 * n - 1] == returned):
            raise RuntimeError(f"the compiled forward pass and {name} in one call differ from the two calls")


def _team_agrees(kernels, name, args, stop, outs, edges=None, check=None):
    """Run kernel `name`'s team, where it has one, on `args` (what the kernel was just called with
    over 0..stop, per-part arrays with a row per part of `edges`) in the parts `edges` (default
    two halves) with fresh outputs (the arguments at `outs`), and check that it wrote what the
    kernel wrote (and, with `check`, that check(the parts' results (parts, 3)) holds): so the team
    compiles now, for these argument types, not in a frame."""
    team = kernels.get(name + "_team")
    if team is None:
        return
    fresh = list(args)
    for i in outs:
        fresh[i] = np.zeros_like(args[i])
    edges = np.array((0, stop // 2, stop) if edges is None else edges, np.int64)
    got = np.zeros((len(edges) - 1, 3))
    with _team["lock"]:
        team(edges, *(([got] if check is not None else []) + fresh))
    same = all(np.array_equal(fresh[i], args[i]) for i in outs) and (check is None or check(got))
    if not same:
        raise RuntimeError(f"the compiled {name} on numba's threads differs from its one call")


class _Gradient:
    """What one pass of `gradient_runs` leaves: g (n_slots,) float64 and, per block, its moments
    of g s (n_blocks, 64), whose sum `reduce_runs` turns into (S B)^T g, and the sums x0_a . g
    and |s g| (2, n_blocks); with `n_runs`, also the moments of every run of blocks in one cell
    and island (`cell_runs`) that one part held whole, summed (A (64, n_runs), done (n_runs,):
    which). `A` and `done` may be views of a three-axis pass's arrays (`axis_gradients`)."""

    def __init__(self, n_slots, n_blocks, n_runs=0):
        self.g = np.empty(n_slots)
        self.M = np.empty((n_blocks, 64))
        self.sums = np.empty((2, n_blocks))
        self.A = np.empty((64, n_runs))
        self.done = np.zeros(n_runs, np.uint8)


def cell_runs(binding):
    """(n_runs + 1,) int64: the first block of every run of `binding` (its blocks in one island
    and lattice cell, `Binding.run_first_block`), then the number of blocks; made once per binding
    (kept as `binding.cell_runs`). A gradient pass sums each run's moments where one part holds
    the whole run (`gradient_runs`)."""
    got = getattr(binding, "cell_runs", None)
    if got is None:
        first = binding.run_first_block
        got = np.empty(len(first) + 1, np.int64)
        got[:-1], got[-1] = first, len(binding.block_cell)
        binding.cell_runs = got
    return got


class CompiledSteps(Steps):
    """The steps of a solve in compiled kernels (`solve_kernels`), for a lattice `Binding` of
    Blender's four-tap interpolations (one with `params`): per axis one forward pass and one pass
    that yields the gradient with everything the closed form needs from it, the basis weights
    computed in the kernels. The passes run on the worker threads of `parallel.py` over the
    binding's block parts; every block's result is kept apart and the blocks are added up in
    order, so a solve gives the same result whatever the number of threads. Arithmetic in the
    binding's precision, sums in float64, as the NumPy steps (whose results these equal to
    rounding, not bit for bit)."""

    capabilities = CAPABILITIES
    backend = "COMPILED"

    def __init__(self, binding, dtype=None):
        super().__init__()
        b = self.b = binding
        self.K = _state["kernels"]
        dtype = np.dtype(b.dtype if dtype is None else dtype)
        self.float32 = dtype == np.float32
        if dtype == b.dtype:
            self.params, self.x0 = b.params, b.x0
        else:   # the binding's values, computed with in another precision (`in_float64`),
            # made once per binding (a lattice animating under a still mesh keeps its binding) and
            # kept as `b.converted`
            got = getattr(b, "converted", None)
            if got is None or got[0] != dtype:
                got = b.converted = (dtype, b.params.astype(dtype), b.x0.astype(dtype))
            self.params, self.x0 = got[1], got[2]
        # Every component is made by a forward pass before it is read (`Steps.refresh`: none is
        # fresh at first), so no copy of x0 is needed.
        self.X = np.empty_like(self.x0)
        self._checked = (None, False)
        lat = b.lattice
        self.coef = solve_kernels.constants(lat.interpolation, dtype)
        self.shape = np.array(lat.shape, np.int64)
        self.n_blocks = len(b.block_cell)

    def in_float64(self):
        """Steps of the same binding computed in float64 (a float32 binding's cell coordinates and
        rest coordinates as stored, the products and coordinates in float64): for the solve's
        joint steps over many small islands, whose float32 coordinates round at about 1e-7 of the
        lattice's size, more than a small body's volume allows. Their vertices are the deformation
        of the same weights, so they keep the volume the solve measured."""
        return self if not self.float32 else CompiledSteps(self.b, np.float64)

    def _blocks(self, name, *args):
        over(name, self.b.block_parts, *args, kernels=self.K)

    def _forward(self, components, D):
        b = self.b
        Dt = np.ascontiguousarray(D.T, dtype=self.X.dtype)
        comps = np.array(components, np.int64)
        self._blocks("forward", self.params, self.coef, b.block_cell, self.shape, Dt, self.x0, comps, self.X)

    def _refresh_then(self, components, D, name, *args, parts=None, returns=0):
        """`refresh(components, D)`, then kernel `name`(*args) over `parts` (default: the block
        parts): what each part returned (`returns` 1: a number; 0: nothing). Where forward passes
        are due and both passes go to the Python threads, the two run in one hand-over per part
        (`solve_kernels.forward_then_<name>`, with a barrier between them, and the calling thread
        sees the parts done without being woken: docs/performance.md, "Fewer hand-overs"). The
        same calls either way, so the same results bit for bit."""
        b, K = self.b, self.K
        parts = b.block_parts if parts is None else parts
        stale = [c for c in components if not self.fresh[c]]
        fused = K.get("forward_then_" + name)
        n = len(parts)
        spins = _state.get("spins")
        resting = _fused["rest"] > 0
        if resting:
            _fused["rest"] -= 1
        # (not where parts would wait at the barrier for threads that have no core to run on, nor
        # while another thread's pass is with the workers: its parts would come first)
        if (not stale or fused is None or spins is None or resting or not 2 <= n <= parallel.CORES
                or parallel.busy() or len(b.block_parts) != n or teams("forward", b.block_parts, K)
                or teams(name, parts, K)):
            self.refresh(components, D)
            got = over(name, parts, *args, returns=returns, kernels=K)
            return [r[0] for r in got] if returns else got
        Dt = np.ascontiguousarray(D.T, dtype=self.X.dtype)
        forward = (self.params, self.coef, b.block_cell, self.shape, Dt, self.x0, np.array(stale, np.int64), self.X)
        blocks, sync = b.block_parts, atomics.new_sync(n)
        barrier, done = spins["barrier"], spins["done"]

        def part(j):
            fused(*forward, *args, sync, j, barrier, blocks[j].start, blocks[j].stop, parts[j].start, parts[j].stop)
        seen = parallel.run_counted(part, range(n), lambda: K["wait_count"](sync, atomics.DONE, n, done))
        for c in stale:
            self.fresh[c] = True
        head = atomics.HEAD
        skipped = np.flatnonzero(sync[head:head + n] == 0)
        for j in skipped:           # (ran out of spins at the barrier)
            sync[head + n + j] = K[name](*args, parts[j].start, parts[j].stop) or 0
        _fused["misses"] = _fused["misses"] + 1 if not seen or len(skipped) else 0
        if _fused["misses"] >= FUSED_MISSES:
            _fused["misses"], _fused["rest"] = 0, FUSED_REST
        return list(sync[head + n:])

    def _pass(self, xp, xq, x0a, components=(), D=None):
        """The gradient pass on xp, xq, after the forward passes that `components` of X are due
        (in one hand-over with it where they can be)."""
        b = self.b
        start, inc, ring = incidence(b)
        runs = cell_runs(b)
        out = _Gradient(b.x0.shape[1], self.n_blocks, len(runs) - 1)
        self._refresh_then(components, D, "gradient_runs", xp, xq, start, inc, ring, self.params, x0a,
                           out.g, out.M, out.sums, runs, out.A, out.done)
        return out

    def axis_gradient(self, axis, D):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        return self._pass(self.X[a1], self.X[a2], self.x0[axis], (a1, a2), D)

    def axis_gradients(self, D):
        """The three axis gradients at the same coordinates, from one pass over the faces
        (`solve_kernels.gradient_runs3`): (g_x, g_y, g_z) as `axis_gradient` gives them."""
        b = self.b
        start, inc, ring = incidence(b)
        runs = cell_runs(b)
        n_slots, n_runs = b.x0.shape[1], len(runs) - 1
        g, M, sums = np.empty((3, n_slots)), np.empty((3, self.n_blocks, 64)), np.empty((3, 2, self.n_blocks))
        A, done = np.empty((3, 64, n_runs)), np.zeros((3, n_runs), np.uint8)
        self._refresh_then((0, 1, 2), D, "gradient_runs3", self.X, start, inc, ring, self.params, self.x0,
                           g, M, sums, runs, A, done)
        out = []
        for a in range(3):
            one = _Gradient(0, 0)
            one.g, one.M, one.sums, one.A, one.done = g[a], M[a], sums[a], A[a], done[a]
            out.append(one)
        return tuple(out)

    def direction_gradient(self, p, q, D):
        self.refresh((0, 1, 2), D)
        X = self.X
        xp, xq = (_along(e, X) for e in (p, q))
        return self._pass(xp, xq, np.zeros(0, X.dtype))

    def _per_row(self, values, rows, k):
        """Per-block values summed per volume row: (k,) (rows are the islands of the slots)."""
        if rows is None:
            return np.array([values.sum()])
        return np.bincount(self.b.block_island, values, k)

    def x0_dot(self, axis, g, rows, k=1):
        return self._per_row(g.sums[0], rows, k)

    def flux(self, g, rows, k=1):
        return self._per_row(g.sums[1], rows, k)

    def x_dot(self, e, axis, g, rows, k=1, D=None):
        if axis is None:
            values = _along(e, self.X) * g.g
        else:
            self.refresh((axis,), D)
            values = self.X[axis] * g.g
        return NumpySteps._split(values, rows, k)

    def transpose(self, g, rows, k=1):
        b = self.b
        alpha = np.zeros((k, b.lattice.n_points))
        row = np.zeros(self.n_blocks, np.int64) if rows is None else b.block_island
        if g.A.shape[1]:
            self.K["reduce_runs"](g.M, cell_runs(b), g.A, g.done, b.block_cell, row, self.shape, self.coef, alpha)
        return alpha

    def add_along(self, e, t):
        b = self.b
        field = np.zeros((1, b.x0.shape[1]), self.X.dtype)
        d = np.asarray(t, self.X.dtype)[None]
        self._blocks("forward", self.params, self.coef, b.block_cell, self.shape, d, field,
                     np.zeros(1, np.int64), field)
        self.X += (e[:, None] * field).astype(self.X.dtype)

    def verts(self, D):
        b = self.b
        out = np.empty((b.n_verts, 3))
        rows = vertex_rows(b)
        bad = self._refresh_then((0, 1, 2), D, "to_verts", self.X, b.slot, b.island_origin, rows, out,
                                 parts=b.vertex_parts, returns=1)
        self._checked = (out, sum(bad) == 0)
        return out

    def finite(self, verts=None):
        if verts is not None and self._checked[0] is verts:
            # (the vertices' coordinates were checked as they were made; a slot that no vertex
            # uses, a block's padding, does not matter)
            return self._checked[1]
        # (only the components a forward pass made: the others hold nothing yet)
        return bool(all(np.isfinite(self.X[c]).all() for c in range(3) if self.fresh[c])
                    and (verts is None or np.isfinite(verts).all()))


def _along(e, X):
    """e . X (n_slots,) float64 for a direction e (3,) and slot coordinates X (3, n_slots): three
    scaled rows rather than e @ X (a (3,) @ (3, n) product would go to BLAS), each row made float64
    first (NumPy's steps promote through e @ X; NumPy 1.x would keep a float32 row float32 when
    scaled by a float64 scalar)."""
    return e[0] * X[0].astype(np.float64) + e[1] * X[1].astype(np.float64) + e[2] * X[2].astype(np.float64)


def incidence(binding):
    """The faces around every slot of `binding` as the gradient passes read them
    (`solve_kernels.vertex_rings`): (start (n_slots + 1,) int64, entries uint32, ring (n_slots,)
    int8), kept as `binding.incidence`: a compiled bind makes them with its slots
    (`layout.slot_values_and_faces`), any other binding here on first use, from its topology's
    faces around every vertex (made once per topology: a mesh re-embedded on every frame only
    renumbers them).
    The entries are unsigned because numba checks every signed index for a negative value (to
    count it from the end) and the gradient passes gather by them: 5-8% of those passes."""
    got = getattr(binding, "incidence", None)
    if got is None:
        K, topo, slot = _state["kernels"], binding.topology, binding.slot
        around = vertex_rings(topo)
        n_slots = binding.x0.shape[1]
        start = np.zeros(n_slots + 1, np.int64)
        entries, ring = np.empty(len(around[1]), np.uint32), np.zeros(n_slots, np.int8)
        K["slot_incidence_start"](slot, around[0], start)
        over("slot_incidence_fill", binding.vertex_parts, slot, *around, start, entries, ring, kernels=K)
        got = binding.incidence = (start, entries, ring)
    return got


def vertex_rings(topology, kernels=None):
    """The faces around every vertex of a `Topology` as rings where they form one closed fan, as
    pairs elsewhere (`solve_kernels.vertex_rings`): (start (V + 1,) int64, entries int32,
    ring (V,) int8), made once per topology (kept on it). `kernels`: the caller's (default: the
    loaded ones)."""
    got = getattr(topology, "_vertex_rings", None)
    if got is None:
        K = _state["kernels"] if kernels is None else kernels
        around = getattr(topology, "_vertex_incidence", None)
        if around is None:          # (a NumPy topology, or one whose rings were made and dropped)
            start_v = np.zeros(topology.n_verts + 1, np.int64)
            pairs_v = np.empty(6 * len(topology.tris), np.int32)
            K["vertex_incidence"](topology.tris_t, start_v, pairs_v)
            around = topology._vertex_incidence = (start_v, pairs_v)
        rstart, entries, ring = np.empty(topology.n_verts + 1, np.int64), np.empty_like(around[1]), np.empty(topology.n_verts, np.int8)
        K["vertex_rings"](*around, rstart, entries, ring)
        got = topology._vertex_rings = (rstart, entries[:rstart[-1]].copy(), ring)
        topology._vertex_incidence = None      # (read by nothing once the rings are made)
    return got


def vertex_rows(binding):
    """(V,) int64: the row of `binding.island_origin` that each vertex's coordinates are relative
    to, made once per binding (kept as `binding.vertex_rows`)."""
    got = getattr(binding, "vertex_rows", None)
    if got is None:
        if len(binding.island_origin) == 1:
            got = np.zeros(binding.n_verts, np.int64)
        else:
            got = np.ascontiguousarray(binding.island_labels, dtype=np.int64)
        binding.vertex_rows = got
    return got


def kernels():
    """The compiled kernels ({name: function}) once `load()` succeeded, or None (NumPy then)."""
    return _state["kernels"]


def bind_kernels(lattice):
    """The compiled kernels for binding a mesh to `lattice` once `load()` succeeded, or None (then
    NumPy binds). They cover Blender's four-tap interpolations; an axis with one point or a
    Bernstein (BEZIER) axis binds with NumPy."""
    kernels = _state["kernels"]
    if kernels is None or not all(n > 1 and kind in layout_kernels.LOCAL_KINDS
                                  for n, kind in zip(lattice.shape, lattice.interpolation)):
        return None
    return kernels


def min_norm(A, r, rcond):
    """u (n,) of least norm with A u = r for A (k, n), r (k,), least squares where the rows cannot
    all be met, singular values under rcond times the largest cut (as `numpy.linalg.lstsq`); or
    None where the kernels are not loaded or k > n. A is reduced to k x k by a Householder QR of
    A^T in a compiled kernel (A = R^T Q^T, u = Q y with R^T y = r), which keeps the singular values
    of A (no Gram matrix). Where R's condition number (estimated, `solve_kernels.condition`) is
    far below 1 / rcond, the triangular system is solved in a kernel too; otherwise the k x k
    least squares goes to LAPACK. OpenBLAS runs LAPACK's k x n factorisation (and, in NumPy 1.26,
    even a 64 x 64 one) on its worker threads, which then spin for about a tenth of a second and
    take the cores from the solve's own threads (and from Blender's). docs/performance.md,
    "Keep BLAS out of the frame"."""
    K = _state["kernels"]
    k, n = A.shape
    if K is None or k > n or k == 0:
        return None
    # Scaled to a largest entry of 1 (u is unchanged): the reflections' norms would overflow
    # beyond ~1e154 and vanish below ~1e-162.
    scale = float(np.abs(A).max())
    if not (np.isfinite(scale) and scale > 0.0):
        return None
    M = np.array(A, dtype=np.float64, order="C") / scale
    tau = np.empty(k)
    K["householder"](M, tau)
    if not np.isfinite(M).all():
        return None
    RT = np.ascontiguousarray(np.tril(M[:, :k]))
    r = np.asarray(r, np.float64) / scale
    diagonal = np.abs(np.diagonal(RT))
    if diagonal.min() > 0.0 and K["condition"](RT, 8) < 0.1 / rcond:
        # Well inside the cut (no singular value near rcond of the largest): the solution is the
        # one of the triangular system, without LAPACK (NumPy 1.26's OpenBLAS runs even a
        # 64 x 64 least squares on its spinning threads).
        y = np.empty(k)
        K["triangular_solve"](RT, r, y, False)
    else:
        y = np.linalg.lstsq(RT, r, rcond=rcond)[0]
    u = np.zeros(n)
    u[:k] = y
    K["apply_q"](M, tau, u)
    return u

