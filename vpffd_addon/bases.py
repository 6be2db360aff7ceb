"""Per-axis basis functions of the lattice: Blender's four interpolations and Bernstein (BEZIER).

Every axis is described by a few *taps*: for each coordinate `x` (V,), a first grid index
`first` (V,) and weights `w` (V, K) so that the axis contributes `sum_k w[:, k] * D[clip(first + k)]`.
Blender's kinds use K = 4 taps around the cell with indices clamped to the grid; a one-point axis
uses K = 1 with weight 1; BEZIER uses all K = n points with the Bernstein polynomials.
"""
import numpy as np

#: Blender's lattice interpolation names (without the ``KEY_`` prefix) plus the global Bernstein basis.
INTERPOLATIONS = ("LINEAR", "CARDINAL", "CATMULL_ROM", "BSPLINE", "BEZIER")

# Tension of Blender's cardinal splines (key_curve_position_weights).
CARDINAL_FC = {"CARDINAL": 0.71, "CATMULL_ROM": 0.5}


def _local_weights(t, kind, derivative=True):
    """Blender's 4-tap weights and their t-derivatives for t (V,) in [0, 1): two (V, 4) arrays
    (the second is None without `derivative`)."""
    w = np.empty((len(t), 4))
    dw = np.empty((len(t), 4)) if derivative else None
    if kind == "LINEAR":
        w[:, 0] = 0.0
        np.subtract(1.0, t, out=w[:, 1])
        w[:, 2] = t
        w[:, 3] = 0.0
        if derivative:
            dw[:] = (0.0, -1.0, 1.0, 0.0)
        return w, dw
    t2 = t * t
    t3 = t2 * t
    if kind == "BSPLINE":
        s = 1.0 - t
        w[:, 0] = s * s * s
        w[:, 1] = 3 * t3 - 6 * t2 + 4
        w[:, 2] = -3 * t3 + 3 * t2 + 3 * t + 1
        w[:, 3] = t3
        w *= 1.0 / 6.0
        if derivative:
            dw[:, 0] = -3 * s * s
            dw[:, 1] = 9 * t2 - 12 * t
            dw[:, 2] = -9 * t2 + 6 * t + 3
            dw[:, 3] = 3 * t2
            dw *= 1.0 / 6.0
        return w, dw
    fc = CARDINAL_FC[kind]
    w[:, 0] = -fc * t3 + 2 * fc * t2 - fc * t
    w[:, 1] = (2 - fc) * t3 + (fc - 3) * t2 + 1
    w[:, 2] = (fc - 2) * t3 + (3 - 2 * fc) * t2 + fc * t
    w[:, 3] = fc * t3 - fc * t2
    if derivative:
        dw[:, 0] = -3 * fc * t2 + 4 * fc * t - fc
        dw[:, 1] = 3 * (2 - fc) * t2 + 2 * (fc - 3) * t
        dw[:, 2] = 3 * (fc - 2) * t2 + 2 * (3 - 2 * fc) * t + fc
        dw[:, 3] = 3 * fc * t2 - 2 * fc * t
    return w, dw


def _bernstein(t, degree):
    """Bernstein polynomials of `degree` at t (V,): (V, degree + 1), by de Casteljau's recurrence."""
    b = np.ones((len(t), 1))
    s = 1.0 - t
    for _ in range(degree):
        nb = np.zeros((len(t), b.shape[1] + 1))
        nb[:, :-1] += s[:, None] * b
        nb[:, 1:] += t[:, None] * b
        b = nb
    return b


def axis_cells(x, n, lo, hi):
    """The cell of a local (four-tap) axis with `n` >= 2 points spanning [lo, hi] that each
    coordinate `x` (V,) lies in, unclamped: ``(i (V,) int64, t (V,) float64)`` with
    ``x = lo + (i + t) du``, t in [0, 1). Blender's taps are grid points i-1..i+2, clamped to the grid.
    Beyond three cells outside, i stops (all taps clamp to the end point there anyway), so i lies in
    [-3, n + 2]."""
    du = (hi - lo) / (n - 1)
    u = np.clip((np.asarray(x, dtype=np.float64) - lo) / du, -3.0, n + 2.0)
    i = np.floor(u)
    return i.astype(np.int64), u - i


def axis_taps(x, n, lo, hi, kind, derivative=False):
    """Taps of one lattice axis for coordinates `x` (V,) in lattice space.

    Returns ``(first, w)`` or, with ``derivative``, ``(first, w, dw)``: `first` (V,) int64 grid
    index of tap 0 (tap k addresses grid index ``clip(first + k, 0, n - 1)``), weights `w` (V, K)
    and `dw` (V, K) = d w / d x. Out-of-grid taps are folded onto the clamped grid point, exactly
    as Blender's Lattice modifier clamps them, so vertices outside the lattice behave as in Blender.
    """
    x = np.asarray(x, dtype=np.float64)
    V = len(x)
    if n == 1:
        ones = np.ones((V, 1))
        out = (np.zeros(V, np.int64), ones)
        return out + (np.zeros((V, 1)),) if derivative else out
    if kind == "BEZIER":
        width = hi - lo
        u = (x - lo) / width
        inside = (u > 0.0) & (u < 1.0)
        t = np.clip(u, 0.0, 1.0)
        w = _bernstein(t, n - 1)
        first = np.zeros(V, np.int64)
        if not derivative:
            return first, w
        b = _bernstein(t, n - 2)
        dw = np.zeros_like(w)
        dw[:, :-1] -= b
        dw[:, 1:] += b
        dw *= (n - 1) / width * inside[:, None]  # clamped outside: the map is constant there
        return first, w, dw
    du = (hi - lo) / (n - 1)
    i, t = axis_cells(x, n, lo, hi)
    w, dw = _local_weights(t, kind, derivative)
    first = np.clip(i, 0, n - 1) - 1
    # Blender's taps are i-1..i+2 clamped to the grid. Inside (1 <= i <= n-3) they are first..first+3
    # as they stand; near and beyond the ends, fold the clamped taps onto offsets 0..3 from `first`.
    edge = np.flatnonzero((i < 1) | (i > n - 3))
    if len(edge):
        ie = i[edge]
        offsets = np.clip(ie[:, None] - 1 + np.arange(4), 0, n - 1) - first[edge, None]   # in 0..3
        rows = np.arange(len(edge))
        for arr in ((w, dw) if derivative else (w,)):
            src = arr[edge]
            folded = np.zeros_like(src)
            # Tap k lands on offset offsets[:, k]; each statement touches every row once, so the
            # fancy-indexed += is exact, and the taps add up in the order k = 0..3.
            for k in range(4):
                folded[rows, offsets[:, k]] += src[:, k]
            arr[edge] = folded
    if not derivative:
        return first, w
    return first, w, dw / du


def tap_count(n, kind):
    """Number of taps K of an axis with `n` points and interpolation `kind`."""
    if n == 1:
        return 1
    return n if kind == "BEZIER" else 4
