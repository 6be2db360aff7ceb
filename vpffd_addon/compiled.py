"""Compiled per-frame kernels (numba, where it is installed), one pass over the faces or blocks
each with no temporary arrays (docs/performance.md, "Compiled kernels"): the volume gradient
along an axis, behind the steps interface of `steps.py`, and the layout of a lattice bind
(`layout_kernels.py`), which a mesh moving through the lattice pays on every frame. The NumPy code
stays the reference and the fallback.

Nothing compiles on import: `load()` compiles the kernels, or loads them from numba's cache, and
from then on `default_steps(binding)` hands solves the compiled steps and `bind_kernels` hands
binds the layout kernels. numba holds the GIL while it compiles (seconds), so an interactive host
calls `load()` where a pause does not matter.

Each kernel call is serial and sums in a fixed order; calls run on the fixed parts of
`parallel.py`, as NumPy's kernels do, so a result never depends on what ran before (chunked renders
stay bit-identical to one render on the same machine).
"""
import numpy as np

from . import layout_kernels, parallel, solve_kernels
from .bases import CARDINAL_FC, axis_cells, axis_taps
from .steps import CAPABILITIES, NumpySteps, Steps
from .volume import face_volumes

#: numba releases the kernels are checked with (first, last), as (major, minor).
NUMBA_RANGE = ((0, 61), (0, 68))
#: NumPy releases numba 0.68 accepts (first, last): Blender shares one NumPy between extensions,
#: and numba refuses a newer one at import; checked first, so that the panel says so plainly.
NUMPY_RANGE = ((1, 24), (2, 5))

_state = {"kernels": None, "why": "not loaded (vpffd_addon.compiled.load() compiles the kernels)"}


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


def load(cache=True):
    """Compile the kernels (or load them from numba's cache when `cache`). Returns True when they
    are ready; otherwise False, with `why()` saying why (numba missing, a version outside
    `NUMBA_RANGE`, a NumPy outside `NUMPY_RANGE`, a compile error). The cache folder is numba's
    (`NUMBA_CACHE_DIR`, set by the host before the first import of numba)."""
    if _state["kernels"] is not None:
        return True
    if _state.get("loaded") is not None:
        _state["kernels"], _state["why"] = _state["loaded"], None
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
    except Exception as exc:
        _state["why"] = f"the kernels did not compile ({type(exc).__name__}: {exc})"
        return False
    _state["kernels"], _state["why"] = kernels, None
    return True


def _compile(numba, cache):
    njit = numba.njit(cache=cache, nogil=True, fastmath=False, error_model="numpy")
    # Sums whose order the compiler may choose (to vectorise them) and fused multiply-adds: still
    # one fixed order once compiled, so every run gives the same result.
    fast = {"reassoc", "contract"}
    njit_sums = numba.njit(cache=cache, nogil=True, fastmath=fast, error_model="numpy")
    inline = numba.njit(inline="always", fastmath=fast, error_model="numpy")

    @njit
    def gradient(xp, xq, corners, g):
        # g[corner k of f] += p_m q_n - q_m p_n, (m, n) the face's other corners in cyclic order,
        # products in the coordinates' precision, sums in float64 (as volume.gradient_component).
        n_faces = corners.shape[1]
        for k in range(3):
            m = (k + 1) % 3
            n = (k + 2) % 3
            for f in range(n_faces):
                cm = corners[m, f]
                cn = corners[n, f]
                c = xp[cm] * xq[cn] - xq[cm] * xp[cn]
                g[corners[k, f]] += c
        for i in range(g.shape[0]):
            g[i] *= 1.0 / 6.0

    return {"gradient": gradient, **layout_kernels.define(njit), **solve_kernels.define(njit, njit_sums, inline)}


def _smoke(kernels):
    """Run each kernel once on a tiny problem of each precision (compiles them now, not in a
    frame) and check it against the sum worked by hand."""
    for dtype in (np.float32, np.float64):
        g = np.zeros(4)
        # One face (0, 1, 2) with p = (1, 0, 0) and q = (0, 2, 0) at its corners: the gradient at
        # corner 0 is (p1 q2 - q1 p2) / 6 = 0, at corner 1 (p2 q0 - q2 p0) / 6 = 0, and at
        # corner 2 (p0 q1 - q0 p1) / 6 = 2 / 6.
        kernels["gradient"](np.array([1, 0, 0, 0], dtype), np.array([0, 2, 0, 0], dtype),
                            np.array([[0], [1], [2]], np.int64), g)
        if not np.allclose(g, [0.0, 0.0, 2.0 / 6.0, 0.0]):
            raise RuntimeError(f"the volume gradient gave {g}")
    # The layout kernels must give NumPy's values bit for bit (binds are compared array by array
    # in the tests); here a few coordinates in, at the edges of and outside a small axis.
    x = np.array([-0.9, -0.5, -0.31, 0.0, 0.2, 0.5, 0.77, 1.6])
    for kind, code in layout_kernels.KIND_CODES.items():
        for n in (2, 3, 5):
            first, w, cell, t = np.empty(len(x), np.int64), np.empty((len(x), 4)), np.empty(len(x), np.int64), np.empty(len(x))
            kernels["axis_taps"](x, n, -0.5, 0.5, code, CARDINAL_FC.get(kind, 0.0), first, w, cell, t)
            ref_first, ref_w = axis_taps(x, n, -0.5, 0.5, kind)
            ref_cell, ref_t = axis_cells(x, n, -0.5, 0.5)
            if not (np.array_equal(first, ref_first) and np.array_equal(w, ref_w)
                    and np.array_equal(cell, ref_cell) and np.array_equal(t, ref_t)):
                raise RuntimeError(f"the {kind} taps of a {n}-point axis differ from NumPy's")
    coords = np.array([[0.0, 1.0, 0.0, 0.3], [0.0, 0.0, 1.0, 0.2], [0.0, 0.0, 0.0, 1.1]])
    tris_t = np.array([[0, 1, 3], [1, 2, 2], [2, 3, 0]], np.int64)
    corners, order, vol = np.empty(9, np.int64), np.empty(3, np.int64), np.empty(3)
    kernels["face_layout"](np.arange(4), tris_t, 2, 1, coords, np.array([0, 3]), corners, order, vol,
                           np.zeros(3, np.int64), np.zeros(1), np.zeros(1))
    if not (np.array_equal(corners.reshape(3, 3), tris_t) and np.array_equal(vol, face_volumes(coords, tris_t))):
        raise RuntimeError("the faces' volume terms differ from NumPy's")


class _Gradient:
    """What one pass of `gradient_transpose` leaves: g (n_slots,) float64 and, per block, its piece
    of (S B)^T g (n_blocks, 64) and the sums x0_a . g and |s g| (2, n_blocks)."""

    def __init__(self, n_slots, n_blocks):
        self.g = np.empty(n_slots)
        self.T = np.empty((n_blocks, 64))
        self.sums = np.empty((2, n_blocks))


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

    def __init__(self, binding):
        super().__init__()
        b = self.b = binding
        self.K = _state["kernels"]
        self.float32 = b.dtype == np.float32
        self.X = b.x0.copy()
        lat = b.lattice
        self.coef = solve_kernels.constants(lat.interpolation, b.dtype)
        self.shape = np.array(lat.shape, np.int64)
        self.n_blocks = len(b.block_cell)

    def _blocks(self, fn):
        parallel.run(lambda p: fn(p.start, p.stop), self.b.block_parts)

    def _forward(self, components, D):
        b, K = self.b, self.K
        Dt = np.ascontiguousarray(D.T, dtype=b.dtype)
        comps = np.array(components, np.int64)
        self._blocks(lambda b0, b1: K["forward"](b.params, self.coef, b.block_cell, self.shape, Dt,
                                                 b.x0, comps, self.X, b0, b1))

    def _pass(self, xp, xq, x0a):
        b, K = self.b, self.K
        start, inc = incidence(b)
        out = _Gradient(b.x0.shape[1], self.n_blocks)
        self._blocks(lambda b0, b1: K["gradient_transpose"](xp, xq, start, inc, b.params, self.coef,
                                                            x0a, out.g, out.T, out.sums, b0, b1))
        return out

    def axis_gradient(self, axis, D):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        self.refresh((a1, a2), D)
        return self._pass(self.X[a1], self.X[a2], self.b.x0[axis])

    def direction_gradient(self, p, q, D):
        self.refresh((0, 1, 2), D)
        X = self.X
        # Three scaled rows rather than p @ X: a (3,) @ (3, n) product would go to BLAS. In
        # float64, as NumPy's steps (p @ X promotes).
        xp, xq = (e[0] * X[0] + e[1] * X[1] + e[2] * X[2] for e in (p, q))
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
            X = self.X
            values = (e[0] * X[0] + e[1] * X[1] + e[2] * X[2]) * g.g
        else:
            self.refresh((axis,), D)
            values = self.X[axis] * g.g
        return NumpySteps._split(values, rows, k)

    def transpose(self, g, rows, k=1):
        b = self.b
        alpha = np.zeros((k, b.lattice.n_points))
        row = np.zeros(self.n_blocks, np.int64) if rows is None else b.block_island
        self.K["reduce_blocks"](g.T, b.block_cell, row, self.shape, alpha)
        return alpha

    def add_along(self, e, t):
        b = self.b
        field = np.zeros((1, b.x0.shape[1]), b.dtype)
        d = np.asarray(t, b.dtype)[None]
        self._blocks(lambda b0, b1: self.K["forward"](b.params, self.coef, b.block_cell, self.shape, d,
                                                      field, np.zeros(1, np.int64), field, b0, b1))
        self.X += (e[:, None] * field).astype(self.X.dtype)

    def verts(self, D):
        self.refresh((0, 1, 2), D)
        b = self.b
        out = np.empty((b.n_verts, 3))
        rows = vertex_rows(b)
        parallel.run(lambda p: self.K["to_verts"](self.X, b.slot, b.island_origin, rows, out, p.start, p.stop),
                     b.vertex_parts)
        return out

    def finite(self):
        return bool(np.isfinite(self.X).all())


def incidence(binding):
    """The faces around every slot of `binding` (`solve_kernels.incidence`): (start (n_slots + 1,),
    pairs (2 * 3F,) int32), made once per binding by the compiled kernel."""
    got = getattr(binding, "_incidence", None)
    if got is None:
        start = np.zeros(binding.x0.shape[1] + 1, np.int64)
        pairs = np.empty(6 * binding.n_faces, np.int32)
        _state["kernels"]["incidence"](binding.slot, binding.topology.tris_t, start, pairs)
        got = binding._incidence = (start, pairs)
    return got


def vertex_rows(binding):
    """(V,) the row of `binding.island_origin` that each vertex's coordinates are relative to."""
    got = getattr(binding, "_vertex_rows", None)
    if got is None:
        if len(binding.island_origin) == 1:
            got = np.zeros(binding.n_verts, np.int64)
        else:
            got = np.ascontiguousarray(binding.island_labels, dtype=np.int64)
        binding._vertex_rows = got
    return got


def bind_kernels(lattice):
    """The compiled kernels for binding a mesh to `lattice` once `load()` succeeded, or None (then
    NumPy binds). They cover Blender's four-tap interpolations; an axis with one point or a
    Bernstein (BEZIER) axis binds with NumPy."""
    kernels = _state["kernels"]
    if kernels is None or not all(n > 1 and kind in layout_kernels.KIND_CODES
                                  for n, kind in zip(lattice.shape, lattice.interpolation)):
        return None
    return kernels


def default_steps(binding):
    """The steps a solve uses when none are given: compiled ones for a lattice binding once
    `load()` succeeded, else the NumPy ones."""
    if _state["kernels"] is not None and getattr(binding, "params", None) is not None:
        return CompiledSteps(binding)
    return NumpySteps(binding)
