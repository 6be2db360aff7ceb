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

from . import layout_kernels, parallel
from .bases import CARDINAL_FC, axis_taps
from .steps import NumpySteps
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

    return {"gradient": gradient, **layout_kernels.define(njit)}


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
            first, w = np.empty(len(x), np.int64), np.empty((len(x), 4))
            kernels["axis_taps"](x, n, -0.5, 0.5, code, CARDINAL_FC.get(kind, 0.0), first, w)
            ref_first, ref_w = axis_taps(x, n, -0.5, 0.5, kind)
            if not (np.array_equal(first, ref_first) and np.array_equal(w, ref_w)):
                raise RuntimeError(f"the {kind} taps of a {n}-point axis differ from NumPy's")
    coords = np.array([[0.0, 1.0, 0.0, 0.3], [0.0, 0.0, 1.0, 0.2], [0.0, 0.0, 0.0, 1.1]])
    tris_t = np.array([[0, 1, 3], [1, 2, 2], [2, 3, 0]], np.int64)
    corners, order, vol = np.empty(9, np.int64), np.empty(3, np.int64), np.empty(3)
    kernels["face_layout"](np.arange(4), tris_t, 2, 1, coords, np.array([0, 3]), corners, order, vol,
                           np.zeros(3, np.int64), np.zeros(1), np.zeros(1))
    if not (np.array_equal(corners.reshape(3, 3), tris_t) and np.array_equal(vol, face_volumes(coords, tris_t))):
        raise RuntimeError("the faces' volume terms differ from NumPy's")


class CompiledSteps(NumpySteps):
    """The NumPy steps with the axis gradient compiled, for a lattice `Binding`: the kernel
    releases the GIL and runs on the worker threads of `parallel.py`, each part of the faces on the
    thread NumPy's kernel gives it (the parts summed in part order, as NumPy's). The forward and
    transposed products stay NumPy's batched small matrix products, which compiled loops have not
    beaten (docs/performance.md, "Compiled kernels")."""

    def __init__(self, binding):
        super().__init__(binding)
        self.K = _state["kernels"]

    def _gradient(self, a1, a2):
        n = self.b.x0.shape[1]
        xp, xq = self.X[a1], self.X[a2]
        kernel = self.K["gradient"]

        def part(corners):
            g = np.zeros(n)
            kernel(xp, xq, corners, g)
            return g
        parts = parallel.run(part, self.b.corner_parts)
        return parts[0] if len(parts) == 1 else np.sum(parts, 0)


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
    if _state["kernels"] is not None and hasattr(binding, "wuv"):
        return CompiledSteps(binding)
    return NumpySteps(binding)
