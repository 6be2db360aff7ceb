"""Compiled per-frame kernels of a lattice solve (docs/performance.md, "The compiled solve").

A correction along one axis needs the volume gradient g at every slot and, from it, the
coefficients alpha = (S B)^T g and the sums x0_a . g and |s g|; after the step, the slots'
coordinates along that axis anew. These kernels do that in two passes over the slots per axis,
with no stored weights:

- `forward`: X[c] = x0[c] + S B D[c] for the components asked for, a block of slots at a time.
  The block's 64 control points are gathered once and each slot's basis weights are computed from
  its cell coordinates (`Binding.params`: t_u, t_v, t_w and the influence s, 16 bytes a slot in
  float32, where the stored weights took 80);
- `gradient_transpose`: per slot, the gradient from the faces around it (a vertex-centred sum: no
  scatter, no per-thread copies of g), and per block the 64 entries of (S B)^T g and the two sums.
  They are kept per block and added up in block order (`reduce_blocks`), so a result is the same
  whatever the number of threads.

Blender's taps i-1..i+2 are clamped to the grid: a block gathers its control points at the clamped
indices (repeating the end points) instead of folding the weights, which is the same sum. Every
block holds one (island, cell) whose cell index is the unclamped one (`bases.axis_cells`), so its
slots share their taps.

`constants(interpolation, dtype)` makes the constants the weights are computed with.
`define(njit, njit_sums, inline)` returns the kernels by name; `compiled.py` compiles them
(`njit_sums` may reorder the additions of a sum and fuse multiply-adds, to vectorise them; the
order is fixed when compiled, so results stay the same from run to run). Nothing here imports
numba.
"""
import numpy as np

from .bases import CARDINAL_FC


def constants(interpolation, dtype):
    """(3, 4, 4) in `dtype`: per axis, the coefficients of its four weights as cubics in t
    (``w_k = sum_p c[k, p] t^p``): Blender's key_curve_position_weights (`bases._local_weights`)
    multiplied out, so that one loop serves every kind."""
    c = np.zeros((3, 4, 4))
    for a, kind in enumerate(interpolation):
        if kind == "LINEAR":
            c[a] = [[0, 0, 0, 0], [1, -1, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0]]
        elif kind == "BSPLINE":
            c[a] = np.array([[1, -3, 3, -1], [4, 0, -6, 3], [1, 3, 3, -3], [0, 0, 0, 1]]) / 6.0
        else:
            f = CARDINAL_FC[kind]
            c[a] = [[0, -f, 2 * f, -f], [1, 0, f - 3, 2 - f], [0, f, 3 - 2 * f, f - 2], [0, 0, -f, f]]
    return c.astype(dtype)


def define(njit, njit_sums, inline):
    """The kernels, compiled by `njit` and `njit_sums` (helpers by `inline`, which numba inlines
    into their callers: a loop over arrays handed to a called function is not vectorised, as the
    compiler cannot tell that they do not overlap): {name: function}. The helpers are bound in
    this module's namespace, where the kernels find them by name (numba caches a kernel that
    calls a global function; one that calls a function it closes over is compiled anew in every
    process)."""
    for name in _HELPERS:
        globals()[name] = inline(_SOURCE[name])
    return {name: (njit_sums if kind == "njit_sums" else njit)(_SOURCE[name]) for name, kind in _KERNELS.items()}


def weights(params, a, base, bs, c, w):
    # The four weights of axis a at the block's slots: w (4, bs), each a cubic in t by
    # Horner's rule with the axis's coefficients c[a] (4, 4) (`constants`). One loop for every
    # kind, in the binding's precision (float32 slots are weighed in float32: twice the lanes).
    c00, c01, c02, c03 = c[a, 0, 0], c[a, 0, 1], c[a, 0, 2], c[a, 0, 3]
    c10, c11, c12, c13 = c[a, 1, 0], c[a, 1, 1], c[a, 1, 2], c[a, 1, 3]
    c20, c21, c22, c23 = c[a, 2, 0], c[a, 2, 1], c[a, 2, 2], c[a, 2, 3]
    c30, c31, c32, c33 = c[a, 3, 0], c[a, 3, 1], c[a, 3, 2], c[a, 3, 3]
    for s in range(bs):
        t = params[a, base + s]
        w[0, s] = ((c03 * t + c02) * t + c01) * t + c00
        w[1, s] = ((c13 * t + c12) * t + c11) * t + c10
        w[2, s] = ((c23 * t + c22) * t + c21) * t + c20
        w[3, s] = ((c33 * t + c32) * t + c31) * t + c30


def block_weights(params, base, bs, c, wu, wv, ww):
    # The block's weights per axis; ww carries the influence s.
    weights(params, 0, base, bs, c, wu)
    weights(params, 1, base, bs, c, wv)
    weights(params, 2, base, bs, c, ww)
    for k in range(4):
        for s in range(bs):
            ww[k, s] *= params[3, base + s]


def same_cell(block_cell, a, b):
    # Whether blocks a and b lie in one cell (consecutive blocks of a run do: taps once).
    return (block_cell[a, 0] == block_cell[b, 0] and block_cell[a, 1] == block_cell[b, 1]
            and block_cell[a, 2] == block_cell[b, 2])


def taps(cell, shape, out):
    # The 64 control points of a block in the cell `cell` (3,): (w, v, u) order, clamped.
    nu = shape[0]
    nv = shape[1]
    nw = shape[2]
    q = 0
    for k in range(4):
        pk = min(max(cell[2] - 1 + k, 0), nw - 1)
        for j in range(4):
            pj = min(max(cell[1] - 1 + j, 0), nv - 1)
            for i in range(4):
                pi = min(max(cell[0] - 1 + i, 0), nu - 1)
                out[q] = (pk * nv + pj) * nu + pi
                q += 1


def forward(params, c, block_cell, shape, D, x0, comps, X, b0, b1):
    # X[comp] = x0[comp] + S B D[comp] for comp in comps, blocks b0..b1-1. D (3, N) and X, x0
    # (3, n_slots) in the steps' precision (or one row each, comps then [0]); c: `constants`.
    bs = params.shape[1] // block_cell.shape[0]
    dt = params.dtype
    wu = np.empty((4, bs), dt)
    wv = np.empty((4, bs), dt)
    ww = np.empty((4, bs), dt)
    acc = np.empty(bs, dt)
    acck = np.empty(bs, dt)
    idx = np.empty(64, np.int64)
    last = -1
    for bl in range(b0, b1):
        base = bl * bs
        block_weights(params, base, bs, c, wu, wv, ww)
        if last < 0 or not same_cell(block_cell, last, bl):
            taps(block_cell[bl], shape, idx)
            last = bl
        for ci in range(comps.shape[0]):
            comp = comps[ci]
            for s in range(bs):
                acc[s] = 0.0
            for k in range(4):
                for s in range(bs):
                    acck[s] = 0.0
                for j in range(4):
                    q = (k * 4 + j) * 4
                    d0 = D[comp, idx[q]]
                    d1 = D[comp, idx[q + 1]]
                    d2 = D[comp, idx[q + 2]]
                    d3 = D[comp, idx[q + 3]]
                    for s in range(bs):
                        acck[s] += wv[j, s] * (wu[0, s] * d0 + wu[1, s] * d1 + wu[2, s] * d2 + wu[3, s] * d3)
                for s in range(bs):
                    acc[s] += ww[k, s] * acck[s]
            for s in range(bs):
                X[comp, base + s] = x0[comp, base + s] + acc[s]


def block_transpose(gs, bs, wu, wv, ww, h, T):
    # T (64,) = the block's piece of (S B)^T g, g = gs (bs,): sum_s ww[k] wv[j] wu[i] g.
    for k in range(4):
        for j in range(4):
            for s in range(bs):
                h[s] = ww[k, s] * wv[j, s] * gs[s]
            q = (k * 4 + j) * 4
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            a3 = 0.0
            for s in range(bs):
                a0 += h[s] * wu[0, s]
                a1 += h[s] * wu[1, s]
                a2 += h[s] * wu[2, s]
                a3 += h[s] * wu[3, s]
            T[q] = a0
            T[q + 1] = a1
            T[q + 2] = a2
            T[q + 3] = a3


def gradient_transpose(xp, xq, inc_start, inc, params, c, x0a, g, T, sums, b0, b1):
    # Blocks b0..b1-1: g (n_slots,) float64, the volume gradient along the axis that xp, xq
    # (n_slots,) complete (products in their precision, a product and a difference possibly fused
    # into one rounding, sums in float64; `volume.gradient_component` is the NumPy reference);
    # per block T[bl] (64,) its piece of (S B)^T g (float64),
    # sums[0, bl] = x0a . g (when x0a is not empty) and sums[1, bl] = sum |s g|.
    n_blocks = T.shape[0]
    bs = g.shape[0] // n_blocks
    dt = params.dtype
    wu = np.empty((4, bs), dt)
    wv = np.empty((4, bs), dt)
    ww = np.empty((4, bs), dt)
    gs = np.empty(bs)
    h = np.empty(bs)
    with_x0 = x0a.shape[0] > 0
    for bl in range(b0, b1):
        base = bl * bs
        sx = 0.0
        sf = 0.0
        for s in range(bs):
            v = base + s
            acc = 0.0
            for e in range(inc_start[v], inc_start[v + 1]):
                m = inc[2 * e]
                n = inc[2 * e + 1]
                acc += xp[m] * xq[n] - xq[m] * xp[n]
            gv = acc * (1.0 / 6.0)
            g[v] = gv
            gs[s] = gv
            if with_x0:
                sx += x0a[v] * gv
            sf += abs(params[3, v] * gv)
        sums[0, bl] = sx
        sums[1, bl] = sf
        block_weights(params, base, bs, c, wu, wv, ww)
        block_transpose(gs, bs, wu, wv, ww, h, T[bl])


def gradient_transpose3(X, inc_start, inc, params, c, x0, g, T, sums, b0, b1):
    # `gradient_transpose` for the three axes at once, from one gathering of the faces around each
    # slot (the gradient along axis a is component a of the sum of the faces' cross products):
    # for the joint steps, which linearise every axis at the same coordinates X (3, n_slots).
    # g (3, n_slots), T (3, n_blocks, 64), sums (3, 2, n_blocks); x0 (3, n_slots) always given.
    n_blocks = T.shape[1]
    bs = g.shape[1] // n_blocks
    dt = params.dtype
    wu = np.empty((4, bs), dt)
    wv = np.empty((4, bs), dt)
    ww = np.empty((4, bs), dt)
    gs = np.empty((3, bs))
    h = np.empty(bs)
    x = X[0]
    y = X[1]
    z = X[2]
    for bl in range(b0, b1):
        base = bl * bs
        sx0 = 0.0
        sx1 = 0.0
        sx2 = 0.0
        sf0 = 0.0
        sf1 = 0.0
        sf2 = 0.0
        for s in range(bs):
            v = base + s
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            for e in range(inc_start[v], inc_start[v + 1]):
                m = inc[2 * e]
                n = inc[2 * e + 1]
                a0 += y[m] * z[n] - z[m] * y[n]
                a1 += z[m] * x[n] - x[m] * z[n]
                a2 += x[m] * y[n] - y[m] * x[n]
            g0 = a0 * (1.0 / 6.0)
            g1 = a1 * (1.0 / 6.0)
            g2 = a2 * (1.0 / 6.0)
            g[0, v] = g0
            g[1, v] = g1
            g[2, v] = g2
            gs[0, s] = g0
            gs[1, s] = g1
            gs[2, s] = g2
            sx0 += x0[0, v] * g0
            sx1 += x0[1, v] * g1
            sx2 += x0[2, v] * g2
            si = params[3, v]
            sf0 += abs(si * g0)
            sf1 += abs(si * g1)
            sf2 += abs(si * g2)
        sums[0, 0, bl] = sx0
        sums[1, 0, bl] = sx1
        sums[2, 0, bl] = sx2
        sums[0, 1, bl] = sf0
        sums[1, 1, bl] = sf1
        sums[2, 1, bl] = sf2
        block_weights(params, base, bs, c, wu, wv, ww)
        for a in range(3):
            block_transpose(gs[a], bs, wu, wv, ww, h, T[a, bl])


def reduce_blocks(T, block_cell, block_row, shape, alpha):
    # alpha[row] += every block's piece at its control points, in block order.
    idx = np.empty(64, np.int64)
    for bl in range(T.shape[0]):
        if bl == 0 or not same_cell(block_cell, bl - 1, bl):
            taps(block_cell[bl], shape, idx)
        row = block_row[bl]
        for q in range(64):
            alpha[row, idx[q]] += T[bl, q]


def householder(M, tau):
    # The QR factorisation A = Q R of A = M^T (n, k), n >= k, by Householder reflections, in place
    # on M (k, n) (row j of M is column j of A, so every loop runs along a row): R^T is then the
    # lower triangle of M[:, :k] and row j right of column j holds reflection j's vector (its
    # first entry 1 implied), tau (k,) their factors. (The joint steps' rows, reduced to k x k
    # without LAPACK: see `compiled.min_norm`.)
    k, n = M.shape
    for j in range(k):
        s = 0.0
        for i in range(j, n):
            s += M[j, i] * M[j, i]
        alpha = M[j, j]
        norm = np.sqrt(s)
        if norm == 0.0:
            tau[j] = 0.0
            continue
        beta = -norm if alpha >= 0.0 else norm
        v0 = alpha - beta
        for i in range(j + 1, n):
            M[j, i] /= v0
        tau[j] = (beta - alpha) / beta
        M[j, j] = beta
        for c in range(j + 1, k):
            d = M[c, j]
            for i in range(j + 1, n):
                d += M[j, i] * M[c, i]
            d *= tau[j]
            M[c, j] -= d
            for i in range(j + 1, n):
                M[c, i] -= d * M[j, i]


def apply_q(M, tau, x):
    # x (n,) <- Q x with the reflections `householder` left in M, tau (applied last to first).
    k, n = M.shape
    for j in range(k - 1, -1, -1):
        d = x[j]
        for i in range(j + 1, n):
            d += M[j, i] * x[i]
        d *= tau[j]
        x[j] -= d
        for i in range(j + 1, n):
            x[i] -= d * M[j, i]


def triangular_solve(L, b, x, transposed):
    # x = L^-1 b (or L^-T b when `transposed`) for L (k, k) lower triangular.
    k = L.shape[0]
    if not transposed:
        for i in range(k):
            s = b[i]
            for j in range(i):
                s -= L[i, j] * x[j]
            x[i] = s / L[i, i]
    else:
        for i in range(k - 1, -1, -1):
            s = b[i]
            for j in range(i + 1, k):
                s -= L[j, i] * x[j]
            x[i] = s / L[i, i]


def condition(L, rounds):
    # An estimate of L's condition number sigma_max / sigma_min (L (k, k) lower triangular, no zero
    # on its diagonal): power iterations on L^T L and on (L^T L)^-1 from a fixed start, `rounds`
    # each (each round multiplies a wrong direction's share by the square of a singular value
    # ratio, so a handful settle both to a few percent).
    k = L.shape[0]
    x = np.empty(k)
    y = np.empty(k)
    z = np.empty(k)
    estimates = np.zeros(2)
    for which in range(2):
        for i in range(k):
            x[i] = 1.0 + 0.5 * np.sin(1.0 + i)      # (not orthogonal to anything in particular)
        for _ in range(rounds):
            n = 0.0
            for i in range(k):
                n += x[i] * x[i]
            n = np.sqrt(n)
            for i in range(k):
                x[i] /= n
            if which == 0:              # y = L x, z = L^T y
                for i in range(k):
                    s = 0.0
                    for j in range(i + 1):
                        s += L[i, j] * x[j]
                    y[i] = s
                for i in range(k):
                    s = 0.0
                    for j in range(i, k):
                        s += L[j, i] * y[j]
                    z[i] = s
            else:                       # y = L^-T x, z = L^-1 y
                triangular_solve(L, x, y, True)
                triangular_solve(L, y, z, False)
            g = 0.0
            for i in range(k):
                g += z[i] * z[i]
                x[i] = z[i]
            estimates[which] = np.sqrt(np.sqrt(g))      # |(L^T L)^(+-1) x| -> sigma^(+-2)
    return estimates[0] * estimates[1]


def vertex_incidence(tris_t, start, pairs):
    # The faces around every vertex as the pairs (m, n) with (vertex, m, n) in the face's
    # cyclic order, in the faces' own order (a counting sort). start (V + 1,) zeroed.
    F = tris_t.shape[1]
    n = start.shape[0] - 1
    for f in range(F):
        for k in range(3):
            start[tris_t[k, f] + 1] += 1
    for v in range(n):
        start[v + 1] += start[v]
    pos = start[:n].copy()
    for f in range(F):
        for k in range(3):
            a = tris_t[k, f]
            p = pos[a]
            pairs[2 * p] = tris_t[(k + 1) % 3, f]
            pairs[2 * p + 1] = tris_t[(k + 2) % 3, f]
            pos[a] = p + 1


def slot_incidence_start(slot, start_v, start):
    # start (n_slots + 1,) zeroed: where each slot's pairs begin (a vertex's pairs, in slot order).
    for v in range(slot.shape[0]):
        start[slot[v] + 1] = start_v[v + 1] - start_v[v]
    for sl in range(start.shape[0] - 1):
        start[sl + 1] += start[sl]


def slot_incidence_fill(slot, start_v, pairs_v, start, pairs, v0, v1):
    # The pairs of vertices v0..v1-1, as slots, at their slots' places (each vertex its own).
    for v in range(v0, v1):
        o = start[slot[v]]
        for e in range(start_v[v], start_v[v + 1]):
            pairs[2 * o] = slot[pairs_v[2 * e]]
            pairs[2 * o + 1] = slot[pairs_v[2 * e + 1]]
            o += 1


def to_verts(X, slot, origin, vertex_row, out, v0, v1):
    # out[v] = X[:, slot[v]] + origin[vertex_row[v]] in float64, vertices v0..v1-1.
    for v in range(v0, v1):
        sl = slot[v]
        row = vertex_row[v]
        for c in range(3):
            out[v, c] = np.float64(X[c, sl]) + origin[row, c]


_HELPERS = ("weights", "block_weights", "same_cell", "taps", "block_transpose", "triangular_solve")
_KERNELS = {"forward": "njit_sums", "gradient_transpose": "njit_sums", "gradient_transpose3": "njit_sums",
            "reduce_blocks": "njit", "householder": "njit_sums", "apply_q": "njit_sums",
            "condition": "njit", "triangular_solve": "njit",
            "vertex_incidence": "njit", "slot_incidence_start": "njit", "slot_incidence_fill": "njit",
            "to_verts": "njit"}
#: The plain functions, as written (`define` rebinds the helpers' names to compiled ones).
_SOURCE = {name: globals()[name] for name in _HELPERS + tuple(_KERNELS)}
