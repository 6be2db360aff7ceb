"""Compiled per-frame kernels of a lattice solve (docs/performance.md, "The compiled solve").

A correction along one axis needs the volume gradient g at every slot and, from it, the
coefficients alpha = (S B)^T g and the sums x0_a . g and |s g|; after the step, the slots'
coordinates along that axis anew. These kernels do that in two passes over the slots per axis,
with no stored weights:

- `forward`: X[c] = x0[c] + S B D[c] for the components asked for, a block of slots at a time.
  Within one lattice cell the deformation is a tricubic polynomial in the cell coordinates: its
  64 coefficients are made once per run of blocks in a cell from the cell's control points, and
  each slot evaluates it at its cell coordinates (`Binding.params`: t_u, t_v, t_w and the
  influence s, 16 bytes a slot in float32, where NumPy's stored weights take 80) by Horner's
  rule, with no basis weights per slot;
- `gradient_transpose`: per slot, the gradient from the faces around it (a vertex-centred sum
  around a ring of neighbours where they close a fan: no scatter, no per-thread copies of g), and
  per block the two sums and the block's 64 moments of g s in the cell coordinates;
  `reduce_runs` adds the moments up in block order, a run of blocks in one cell and island at a
  time, and turns each run's into the entries of (S B)^T g at the cell's control points by the
  same cubics (`reduce_blocks`, which finds the runs itself, is its reference in the tests).
  So a result is the same whatever the number of threads. `gradient_runs` (`gradient_runs3` for
  three axes) is the pass with the runs' sums made in it where a part holds a run whole, and
  `reduce_runs` the transpose from them.

Blender's taps i-1..i+2 are clamped to the grid: a block gathers its control points at the clamped
indices (repeating the end points) instead of folding the weights, which is the same sum. Every
block holds one (island, cell) whose cell index is the unclamped one (`bases.axis_cells`), so its
slots share their taps.

`constants(interpolation, dtype)` makes the constants: every axis's four weights as cubics in t.
`define(njit, njit_sums, inline)` returns the kernels by name; `compiled.py` compiles them
(`njit_sums` may reorder the additions of a sum and fuse multiply-adds, to vectorise them; the
order is fixed when compiled, so results stay the same from run to run). Nothing here imports
numba.
"""
import numpy as np

from .bases import CARDINAL_FC


_CONSTANTS = {}


def constants(interpolation, dtype):
    """(3, 4, 4) in `dtype`: per axis, the coefficients of its four weights as cubics in t
    (``w_k = sum_p c[k, p] t^p``): Blender's key_curve_position_weights (`bases._local_weights`)
    multiplied out, so that one loop serves every kind. Made once per kind and precision and
    shared (every solve asks; the kernels only read it), so callers must not write to it."""
    key = (tuple(interpolation), np.dtype(dtype).str)
    got = _CONSTANTS.get(key)
    if got is None:
        got = _CONSTANTS[key] = _constants(interpolation, dtype)
    return got


def _constants(interpolation, dtype):
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


def define(njit, njit_sums, inline, sync=None):
    """The kernels, compiled by `njit` and `njit_sums` (helpers by `inline`, which numba inlines
    into their callers: a loop over arrays handed to a called function is not vectorised, as the
    compiler cannot tell that they do not overlap): {name: function}. The helpers are bound in
    this module's namespace, where the kernels find them by name (numba caches a kernel that
    calls a global function; one that calls a function it closes over is compiled anew in every
    process), and so is every kernel as `_k_<name>`, for the teams and the fused passes. `sync`:
    `atomics.define`'s functions; with them, the fused passes (`forward_then_<name>`) too."""
    space = globals()
    for name in _HELPERS:
        space[name] = inline(_SOURCE[name])
    kernels = {name: (njit_sums if kind == "njit_sums" else njit)(_SOURCE[name]) for name, kind in _KERNELS.items()}
    for name, kernel in kernels.items():
        space["_k_" + name] = kernel
    if sync is not None:
        space.update(sync)
        space["arrive_and_wait"] = inline(_SOURCE["arrive_and_wait"])
        kernels["wait_count"] = space["wait_count"] = njit(_SOURCE["wait_count"])
        kernels.update({name: njit(_SOURCE[name]) for name in _FUSED})
    return kernels


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


def change_basis(src, c, a, transposed, dst):
    # One axis of a block's 4 x 4 x 4 tensor (index (w * 4 + v) * 4 + u; a = 0 for u, 1 for v,
    # 2 for w) through axis a's cubics c[a] (`constants`): dst[.., x, ..] = sum_y src[.., y, ..]
    # c[a, y, x], from the values at the four taps to the coefficients of the powers of t, or
    # with c[a, x, y] (`transposed`) from moments back to the taps. In float64.
    stride = 1 if a == 0 else (4 if a == 1 else 16)
    for hi in range(0, 64, 4 * stride):
        for x in range(4):
            for lo in range(stride):
                t = 0.0
                for y in range(4):
                    w = c[a, x, y] if transposed else c[a, y, x]
                    t += src[hi + y * stride + lo] * np.float64(w)
                dst[hi + x * stride + lo] = t


def cell_polynomial(D, comp, idx, c, A, B, C):
    # The deformation of component comp within one cell as a tricubic polynomial: C (64,) its
    # coefficients, C[(r * 4 + q) * 4 + p] of u^p v^q w^r, from the cell's 64 control points
    # D[comp, idx] and the axes' weights as cubics in t (c: `constants`), one axis at a time
    # (A, B (64,) float64 scratch): sum_kji D[k, j, i] w_i(u) w_j(v) w_k(w).
    for q in range(64):
        C[q] = np.float64(D[comp, idx[q]])
    change_basis(C, c, 0, False, A)
    change_basis(A, c, 1, False, B)
    change_basis(B, c, 2, False, C)


def forward(params, c, block_cell, shape, D, x0, comps, X, b0, b1):
    # X[comp] = x0[comp] + S B D[comp] for comp in comps, blocks b0..b1-1. D (3, N) and X, x0
    # (3, n_slots) in the steps' precision (or one row each, comps then [0]); c: `constants`.
    # Once per run of blocks in one cell, each component's tricubic (`cell_polynomial`); per
    # slot then 16 cubics in u by Horner's rule, 4 in v and one in w: 64 multiply-adds and no
    # weights (docs/performance.md, "The per-frame passes").
    bs = params.shape[1] // block_cell.shape[0]
    dt = params.dtype
    n_comps = comps.shape[0]
    C = np.empty((n_comps, 64), dt)
    A = np.empty(64)
    B = np.empty(64)
    Cc = np.empty(64)
    acc = np.empty(bs, dt)
    uu = np.empty(bs, dt)
    vv = np.empty(bs, dt)
    ww = np.empty(bs, dt)
    idx = np.empty(64, np.int64)
    last = -1
    for bl in range(b0, b1):
        base = bl * bs
        if last < 0 or not same_cell(block_cell, last, bl):
            taps(block_cell[bl], shape, idx)
            last = bl
            for ci in range(n_comps):
                cell_polynomial(D, comps[ci], idx, c, A, B, Cc)
                for q in range(64):
                    C[ci, q] = Cc[q]
        pu = params[0, base:base + bs]
        pv = params[1, base:base + bs]
        pw = params[2, base:base + bs]
        for s in range(bs):
            uu[s] = pu[s]
            vv[s] = pv[s]
            ww[s] = pw[s]
        for ci in range(n_comps):
            comp = comps[ci]
            for s in range(bs):
                acc[s] = 0.0
            for r in range(3, -1, -1):
                o = r * 16
                k00, k01, k02, k03 = C[ci, o], C[ci, o + 1], C[ci, o + 2], C[ci, o + 3]
                k10, k11, k12, k13 = C[ci, o + 4], C[ci, o + 5], C[ci, o + 6], C[ci, o + 7]
                k20, k21, k22, k23 = C[ci, o + 8], C[ci, o + 9], C[ci, o + 10], C[ci, o + 11]
                k30, k31, k32, k33 = C[ci, o + 12], C[ci, o + 13], C[ci, o + 14], C[ci, o + 15]
                for s in range(bs):
                    u = uu[s]
                    v = vv[s]
                    e0 = ((k03 * u + k02) * u + k01) * u + k00
                    e1 = ((k13 * u + k12) * u + k11) * u + k10
                    e2 = ((k23 * u + k22) * u + k21) * u + k20
                    e3 = ((k33 * u + k32) * u + k31) * u + k30
                    acc[s] = acc[s] * ww[s] + (((e3 * v + e2) * v + e1) * v + e0)
            xo = X[comp, base:base + bs]
            xi = x0[comp, base:base + bs]
            ps = params[3, base:base + bs]
            for s in range(bs):
                xo[s] = xi[s] + ps[s] * acc[s]


def block_powers(params, base, bs, pu, pv, pw):
    # The powers of the block's cell coordinates in float64, per slot: pu[p] = u^p (p = 1..3),
    # pv[q] = v^q and pw[r] = s w^r with the influence s (q, r = 0..3), all (4, bs).
    b0, b1, b2, b3 = (params[0, base:base + bs], params[1, base:base + bs], params[2, base:base + bs],
                      params[3, base:base + bs])
    for s in range(bs):
        u = np.float64(b0[s])
        v = np.float64(b1[s])
        w = np.float64(b2[s])
        si = np.float64(b3[s])
        pu[1, s] = u
        pu[2, s] = u * u
        pu[3, s] = u * u * u
        pv[0, s] = 1.0
        pv[1, s] = v
        pv[2, s] = v * v
        pv[3, s] = v * v * v
        pw[0, s] = si
        pw[1, s] = si * w
        pw[2, s] = si * w * w
        pw[3, s] = si * w * w * w


def block_moments(gs, bs, pu, pv, pw, h, M):
    # M (64,) = the block's moments of g s in its cell coordinates, M[(r * 4 + q) * 4 + p] =
    # sum_s g s w^r v^q u^p, g = gs (bs,), from the powers of `block_powers` (h (bs,) scratch):
    # what the block gives (S B)^T g, turned into the control points' entries by `reduce_runs`
    # once per run of blocks in one cell (the change of basis is linear, so the moments of a run
    # add up first). Two powers of v at a time: a slot's powers of u are read once for both.
    for r in range(4):
        for s in range(bs):
            h[s] = gs[s] * pw[r, s]
        for q in range(0, 4, 2):
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            a3 = 0.0
            b0 = 0.0
            b1 = 0.0
            b2 = 0.0
            b3 = 0.0
            for s in range(bs):
                u1 = pu[1, s]
                u2 = pu[2, s]
                u3 = pu[3, s]
                x = h[s] * pv[q, s]
                a0 += x
                a1 += x * u1
                a2 += x * u2
                a3 += x * u3
                y = h[s] * pv[q + 1, s]
                b0 += y
                b1 += y * u1
                b2 += y * u2
                b3 += y * u3
            o = (r * 4 + q) * 4
            M[o] = a0
            M[o + 1] = a1
            M[o + 2] = a2
            M[o + 3] = a3
            M[o + 4] = b0
            M[o + 5] = b1
            M[o + 6] = b2
            M[o + 7] = b3


def block_moments3(gs, bs, pu, pv, pw, h, M0, M1, M2):
    # `block_moments` of three gradients at once, gs (3, bs) into M0, M1, M2 (64,) (h (3, bs)
    # scratch): every slot's powers are read once for the three, which halves the loads that
    # bound the loop (so the three sums share one loop here rather than calling `block_moments`
    # three times).
    for r in range(4):
        for s in range(bs):
            p = pw[r, s]
            h[0, s] = gs[0, s] * p
            h[1, s] = gs[1, s] * p
            h[2, s] = gs[2, s] * p
        for q in range(4):
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            a3 = 0.0
            b0 = 0.0
            b1 = 0.0
            b2 = 0.0
            b3 = 0.0
            c0 = 0.0
            c1 = 0.0
            c2 = 0.0
            c3 = 0.0
            for s in range(bs):
                v = pv[q, s]
                u1 = pu[1, s]
                u2 = pu[2, s]
                u3 = pu[3, s]
                x = h[0, s] * v
                a0 += x
                a1 += x * u1
                a2 += x * u2
                a3 += x * u3
                y = h[1, s] * v
                b0 += y
                b1 += y * u1
                b2 += y * u2
                b3 += y * u3
                z = h[2, s] * v
                c0 += z
                c1 += z * u1
                c2 += z * u2
                c3 += z * u3
            o = (r * 4 + q) * 4
            M0[o] = a0
            M0[o + 1] = a1
            M0[o + 2] = a2
            M0[o + 3] = a3
            M1[o] = b0
            M1[o + 1] = b1
            M1[o + 2] = b2
            M1[o + 3] = b3
            M2[o] = c0
            M2[o + 1] = c1
            M2[o + 2] = c2
            M2[o + 3] = c3


def fan_gradient(xp, xq, fan, is_ring):
    # The sum over the faces around one slot of xp[m] xq[n] - xq[m] xp[n] (component a of m x n
    # for the face (v, m, n), the other two coordinates xp, xq), `fan` its entries: where they form
    # one closed fan (`is_ring`: entries r_0 .. r_d-1, faces (v, r_k, r_k+1) and (v, r_d-1, r_0))
    # each neighbour's two coordinates are gathered once, else the pairs (m, n) one face at a time
    # (`vertex_rings`).
    acc = 0.0
    d = fan.shape[0]
    if is_ring:
        r = fan[0]
        p0 = xp[r]
        q0 = xq[r]
        pm = p0
        qm = q0
        for e in range(1, d):
            n = fan[e]
            pn = xp[n]
            qn = xq[n]
            acc += pm * qn - qm * pn
            pm = pn
            qm = qn
        acc += pm * q0 - qm * p0
    else:
        for e in range(0, d, 2):
            m = fan[e]
            n = fan[e + 1]
            acc += xp[m] * xq[n] - xq[m] * xp[n]
    return acc


def gradient_transpose(xp, xq, inc_start, inc, ring, params, x0a, g, M, sums, b0, b1):
    # Blocks b0..b1-1: g (n_slots,) float64, the volume gradient along the axis that xp, xq
    # (n_slots,) complete (products in their precision, a product and a difference possibly fused
    # into one rounding, sums in float64; `volume.gradient_component` is the NumPy reference);
    # per block M[bl] (64,) its moments of g s (`block_moments`, float64: `reduce_runs` makes
    # (S B)^T g of them), sums[0, bl] = x0a . g (when x0a is not empty) and
    # sums[1, bl] = sum |s g|.
    n_blocks = M.shape[0]
    bs = g.shape[0] // n_blocks
    pu, pv, pw = np.empty((4, bs)), np.empty((4, bs)), np.empty((4, bs))
    gs = np.empty(bs)
    h = np.empty(bs)
    with_x0 = x0a.shape[0] > 0
    for bl in range(b0, b1):
        # (the block's slices: indices from 0 up, see `householder`)
        base = bl * bs
        st = inc_start[base:base + bs + 1]
        rg = ring[base:base + bs]
        gb = g[base:base + bs]
        sb = params[3, base:base + bs]
        xb = x0a[base:base + bs] if with_x0 else x0a
        sx = 0.0
        sf = 0.0
        for s in range(bs):
            acc = fan_gradient(xp, xq, inc[st[s]:st[s + 1]], rg[s])
            gv = acc * (1.0 / 6.0)
            gb[s] = gv
            gs[s] = gv
            if with_x0:
                sx += xb[s] * gv
            sf += abs(sb[s] * gv)
        sums[0, bl] = sx
        sums[1, bl] = sf
        block_powers(params, base, bs, pu, pv, pw)
        block_moments(gs, bs, pu, pv, pw, h, M[bl])


def gradient_runs(xp, xq, inc_start, inc, ring, params, x0a, g, M, sums, run_start, A, done, b0, b1):
    # `gradient_transpose` over blocks b0..b1-1, then the sums of the moments of every run of
    # blocks in one cell and island that lies wholly in b0..b1-1 (`sum_runs`), while they are still
    # in this thread's caches: the calling thread's `reduce_runs` then reads the runs' sums instead
    # of every block's moments, written on other cores (docs/performance.md, "The runs' sums in the
    # gradient pass"). run_start (n_runs + 1,): every run's first block, then n_blocks
    # (`compiled.cell_runs`).
    _k_gradient_transpose(xp, xq, inc_start, inc, ring, params, x0a, g, M, sums, b0, b1)  # noqa: F821
    _k_sum_runs(M, run_start, A, done, b0, b1)  # noqa: F821


def sum_runs(M, run_start, A, done, b0, b1):
    # Every run r (blocks run_start[r]..run_start[r + 1] - 1) lying wholly in blocks b0..b1-1: its
    # blocks' moments M (n_blocks, 64) added up in block order into column r of A (64, n_runs),
    # from zero, as `reduce_blocks` adds them; done[r] = 1. Compiled without reordered sums.
    n_runs = A.shape[1]
    acc = np.empty(64)
    r = np.searchsorted(run_start[:n_runs], b0)
    while r < n_runs and run_start[r + 1] <= b1:
        for q in range(64):
            acc[q] = 0.0
        for bl in range(run_start[r], run_start[r + 1]):
            moments = M[bl]
            for q in range(64):
                acc[q] += moments[q]
        for q in range(64):
            A[q, r] = acc[q]
        done[r] = 1
        r += 1


def gradient_runs3(X, inc_start, inc, ring, params, x0, g, M, sums, run_start, A, done, b0, b1):
    # `gradient_transpose3` over blocks b0..b1-1, then each axis's runs' sums as `gradient_runs`
    # makes them: A (3, 64, n_runs), done (3, n_runs).
    _k_gradient_transpose3(X, inc_start, inc, ring, params, x0, g, M, sums, b0, b1)  # noqa: F821
    for a in range(3):
        _k_sum_runs(M[a], run_start, A[a], done[a], b0, b1)  # noqa: F821


def gradient_transpose3(X, inc_start, inc, ring, params, x0, g, M, sums, b0, b1):
    # `gradient_transpose` for the three axes at once, from one gathering of the faces around each
    # slot (the gradient along axis a is component a of the sum of the faces' cross products):
    # for the joint steps, which linearise every axis at the same coordinates X (3, n_slots).
    # g (3, n_slots), M (3, n_blocks, 64), sums (3, 2, n_blocks); x0 (3, n_slots) always given.
    n_blocks = M.shape[1]
    bs = g.shape[1] // n_blocks
    pu, pv, pw = np.empty((4, bs)), np.empty((4, bs)), np.empty((4, bs))
    gs = np.empty((3, bs))
    h = np.empty((3, bs))
    x = X[0]
    y = X[1]
    z = X[2]
    for bl in range(b0, b1):
        base = bl * bs
        st = inc_start[base:base + bs + 1]
        rg = ring[base:base + bs]
        sb = params[3, base:base + bs]
        g0b, g1b, g2b = g[0, base:base + bs], g[1, base:base + bs], g[2, base:base + bs]
        x0b, x1b, x2b = x0[0, base:base + bs], x0[1, base:base + bs], x0[2, base:base + bs]
        sx0 = 0.0
        sx1 = 0.0
        sx2 = 0.0
        sf0 = 0.0
        sf1 = 0.0
        sf2 = 0.0
        for s in range(bs):
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            fan = inc[st[s]:st[s + 1]]
            d = fan.shape[0]
            if rg[s]:                   # (one closed fan: see `fan_gradient`)
                r = fan[0]
                x_0, y_0, z_0 = x[r], y[r], z[r]
                xm, ym, zm = x_0, y_0, z_0
                for e in range(1, d):
                    n = fan[e]
                    xn, yn, zn = x[n], y[n], z[n]
                    a0 += ym * zn - zm * yn
                    a1 += zm * xn - xm * zn
                    a2 += xm * yn - ym * xn
                    xm, ym, zm = xn, yn, zn
                a0 += ym * z_0 - zm * y_0
                a1 += zm * x_0 - xm * z_0
                a2 += xm * y_0 - ym * x_0
            else:
                for e in range(0, d, 2):
                    m = fan[e]
                    n = fan[e + 1]
                    a0 += y[m] * z[n] - z[m] * y[n]
                    a1 += z[m] * x[n] - x[m] * z[n]
                    a2 += x[m] * y[n] - y[m] * x[n]
            g0 = a0 * (1.0 / 6.0)
            g1 = a1 * (1.0 / 6.0)
            g2 = a2 * (1.0 / 6.0)
            g0b[s] = g0
            g1b[s] = g1
            g2b[s] = g2
            gs[0, s] = g0
            gs[1, s] = g1
            gs[2, s] = g2
            sx0 += x0b[s] * g0
            sx1 += x1b[s] * g1
            sx2 += x2b[s] * g2
            si = sb[s]
            sf0 += abs(si * g0)
            sf1 += abs(si * g1)
            sf2 += abs(si * g2)
        sums[0, 0, bl] = sx0
        sums[1, 0, bl] = sx1
        sums[2, 0, bl] = sx2
        sums[0, 1, bl] = sf0
        sums[1, 1, bl] = sf1
        sums[2, 1, bl] = sf2
        block_powers(params, base, bs, pu, pv, pw)
        block_moments3(gs, bs, pu, pv, pw, h, M[0, bl], M[1, bl], M[2, bl])


def reduce_blocks(M, block_cell, block_row, shape, c, alpha):
    # The reference of `reduce_runs` (the start-up check and the tests compare them bit for bit):
    # it finds the runs itself, where the solve takes the binding's.
    # alpha[row] += (S B)^T g from every block's moments M (n_blocks, 64) (`block_moments`): the
    # moments of a run of blocks in one cell and row added up in block order, then turned into
    # the entries of the cell's control points, T[k, j, i] = sum_pqr c[0, i, p] c[1, j, q]
    # c[2, k, r] M[r, q, p] (c: `constants`), one axis at a time: the transpose of
    # `cell_polynomial` and the forward's evaluation. One thread, in block order: the same
    # result on any number of threads. Every run's sums go to a column of one (64, runs) array,
    # whose changes of basis are made for all runs at once, a run in every vector lane
    # (`change_basis_runs`): a run at a time, the 768 products and sums of its three changes of
    # basis, which may not be fused or reordered, took twice as long (docs/performance.md, "Pass
    # by pass, against this machine").
    n_blocks = M.shape[0]
    last = np.empty(n_blocks, np.int64)         # (the last block of every run)
    n_runs = 0
    for bl in range(n_blocks):
        if not (bl + 1 < n_blocks and block_row[bl + 1] == block_row[bl]
                and same_cell(block_cell, bl, bl + 1)):
            last[n_runs] = bl
            n_runs += 1
    A = np.empty((64, n_runs))
    acc = np.zeros(64)
    bl = 0
    for r in range(n_runs):
        while bl <= last[r]:
            moments = M[bl]
            for q in range(64):
                acc[q] += moments[q]
            bl += 1
        for q in range(64):
            A[q, r] = acc[q]
            acc[q] = 0.0
    runs_to_points(A, last[:n_runs], block_cell, block_row, shape, c, alpha)


def reduce_runs(M, run_start, A, done, block_cell, block_row, shape, c, alpha):
    # `reduce_blocks` from the runs' sums that the gradient passes made (`gradient_runs`: columns
    # of A (64, n_runs) with done[r] = 1), the runs of blocks in one cell and island (run_start
    # (n_runs + 1,)); block_row: zeros for one volume row, the blocks' islands for a row each. The
    # runs they left, those crossing from one part into the next, are added up here from M first,
    # in the same order: the same result bit for bit.
    n_runs = A.shape[1]
    for r in range(n_runs):
        if done[r] == 0:
            _k_sum_runs(M, run_start, A, done, run_start[r], run_start[r + 1])  # noqa: F821
    last = np.empty(n_runs, np.int64)
    for r in range(n_runs):
        last[r] = run_start[r + 1] - 1
    runs_to_points(A, last, block_cell, block_row, shape, c, alpha)


def runs_to_points(A, last, block_cell, block_row, shape, c, alpha):
    # Every run's moments summed (A (64, n_runs), read only: a gradient's transpose may be asked
    # for again) turned into the entries of its cell's control points and added to alpha[row] in
    # run order (`last`: every run's last block).
    n_runs = A.shape[1]
    B = np.empty((64, n_runs))
    C = np.empty((64, n_runs))
    change_basis_runs(A, c, 0, B)
    change_basis_runs(B, c, 1, C)
    change_basis_runs(C, c, 2, B)
    # (a cell whose 64 control points are all inside the lattice: at fixed offsets from its first)
    nu, nv, nw = shape[0], shape[1], shape[2]
    offset = np.empty(64, np.int64)
    for q in range(64):
        offset[q] = ((q >> 4) * nv + ((q >> 2) & 3)) * nu + (q & 3)
    idx = np.empty(64, np.int64)
    for k in range(n_runs):
        bl = last[k]
        cx, cy, cz = block_cell[bl, 0], block_cell[bl, 1], block_cell[bl, 2]
        out = alpha[block_row[bl]]
        if cx >= 1 and cy >= 1 and cz >= 1 and cx + 2 < nu and cy + 2 < nv and cz + 2 < nw:
            first = ((cz - 1) * nv + (cy - 1)) * nu + (cx - 1)
            for q in range(64):
                out[first + offset[q]] += B[q, k]
        else:
            taps(block_cell[bl], shape, idx)
            for q in range(64):
                out[idx[q]] += B[q, k]


def change_basis_runs(src, c, a, dst):
    # `change_basis` (transposed) of many runs' tensors at once: src, dst (64, n_runs), a run in
    # each column; the same products and sums in the same order for every run.
    stride = 1 if a == 0 else (4 if a == 1 else 16)
    n = src.shape[1]
    for hi in range(0, 64, 4 * stride):
        for x in range(4):
            w0 = np.float64(c[a, x, 0])
            w1 = np.float64(c[a, x, 1])
            w2 = np.float64(c[a, x, 2])
            w3 = np.float64(c[a, x, 3])
            for lo in range(stride):
                i = hi + lo
                s0 = src[i]
                s1 = src[i + stride]
                s2 = src[i + 2 * stride]
                s3 = src[i + 3 * stride]
                d = dst[hi + x * stride + lo]
                for k in range(n):
                    d[k] = (((0.0 + s0[k] * w0) + s1[k] * w1) + s2[k] * w2) + s3[k] * w3


def reflection(M, tau, j):
    # Householder reflection j from row j of M (k, n), right of column j, in place: beta on the
    # diagonal, the vector's entries after its first (1, implied) right of it, its factor in tau[j]
    # (0 where the row is already 0 there).
    v = M[j, j:]
    m = v.size
    s = 0.0
    for i in range(m):
        s += v[i] * v[i]
    alpha = v[0]
    norm = np.sqrt(s)
    if norm == 0.0:
        tau[j] = 0.0
        return
    beta = -norm if alpha >= 0.0 else norm
    v0 = alpha - beta
    for i in range(1, m):
        v[i] /= v0
    tau[j] = (beta - alpha) / beta
    v[0] = beta


def householder(M, tau):
    # The QR factorisation A = Q R of A = M^T (n, k), n >= k, by Householder reflections, in place
    # on M (k, n) (row j of M is column j of A, so every loop runs along a row): R^T is then the
    # lower triangle of M[:, :k] and row j right of column j holds reflection j's vector (its
    # first entry 1 implied), tau (k,) their factors. (The joint steps' rows, reduced to k x k
    # without LAPACK: see `compiled.min_norm`.) The rows after a pair of reflections j, j + 1 take
    # both in one pass, with H_j's change to row c folded into H_(j+1)'s factor through
    # v_j . v_(j+1), and two rows at a time, which share the two vectors' loads: the matrix goes
    # through the cache half as often as one reflection at a time (docs/performance.md,
    # "Per-Island Volume"). Every loop runs over a slice from a constant start: numba cannot tell
    # that an index from a start known only at run time is not negative, and the check for it
    # keeps LLVM from vectorising the loop (3.5 times slower).
    k, n = M.shape
    j = 0
    while j < k:
        reflection(M, tau, j)
        if j + 1 == k:
            break
        t1 = tau[j]
        reflect(M[j, j:], t1, M[j + 1, j:])     # H_j on row j + 1, then H_(j+1) from it
        reflection(M, tau, j + 1)
        t2 = tau[j + 1]
        v = M[j, j + 1:]            # H_j's vector from column j + 1 (1 at column j, implied)
        m = v.size
        w = M[j + 1, j + 1:]        # H_(j+1)'s vector from column j + 1 (w[0]: 1, implied)
        c = v[0]                    # v_j . v_(j+1)
        for i in range(1, m):
            c += v[i] * w[i]
        # Row c: d1 = t1 (v_j . row), row -= d1 v_j; d2 = t2 (v_(j+1) . row) after that change,
        # = t2 (v_(j+1) . row - d1 c); row -= d2 v_(j+1).
        row = j + 2
        while row < k:
            pair = row + 1 < k
            b = row + 1 if pair else row
            ra = M[row, j + 1:]
            rb = M[b, j + 1:]
            a1 = ra[0]
            b1 = rb[0]
            da1 = M[row, j] + v[0] * a1
            db1 = M[b, j] + v[0] * b1
            da2 = a1
            db2 = b1
            for i in range(1, m):
                x = ra[i]
                y = rb[i]
                da1 += v[i] * x
                da2 += w[i] * x
                db1 += v[i] * y
                db2 += w[i] * y
            da1 *= t1
            db1 *= t1
            da2 = t2 * (da2 - da1 * c)
            db2 = t2 * (db2 - db1 * c)
            M[row, j] -= da1
            ra[0] = a1 - da1 * v[0] - da2
            for i in range(1, m):
                ra[i] -= da1 * v[i] + da2 * w[i]
            if pair:
                M[b, j] -= db1
                rb[0] = b1 - db1 * v[0] - db2
                for i in range(1, m):
                    rb[i] -= db1 * v[i] + db2 * w[i]
            row += 2
        j += 2


def reflect(v, t, y):
    # y <- H y for the reflection of vector v (its first entry 1, implied: v[0] holds something
    # else) and factor t, v and y (m,) from the same column on.
    d = y[0]
    for i in range(1, v.size):
        d += v[i] * y[i]
    d *= t
    y[0] -= d
    for i in range(1, v.size):
        y[i] -= d * v[i]


def apply_q(M, tau, x):
    # x (n,) <- Q x with the reflections `householder` left in M, tau (applied last to first;
    # slices from constant starts, as there).
    k, n = M.shape
    for j in range(k - 1, -1, -1):
        reflect(M[j, j:], tau[j], x[j:])


def triangular_solve(L, b, x, transposed):
    # x = L^-1 b (or L^-T b when `transposed`) for L (k, k) lower triangular. L^-T goes backwards
    # a column of L^T at a time, each a contiguous row of L (a multiple of it taken from the
    # rest: the loop vectorises, where a sum along a column of L would not).
    k = L.shape[0]
    if not transposed:
        for i in range(k):
            s = b[i]
            for j in range(i):
                s -= L[i, j] * x[j]
            x[i] = s / L[i, i]
    else:
        x[:] = b
        for j in range(k - 1, -1, -1):
            x[j] /= L[j, j]
            row = L[j, :j]
            xj = x[j]
            for i in range(row.size):
                x[i] -= row[i] * xj


def condition(L, rounds):
    # An estimate of L's condition number sigma_max / sigma_min (L (k, k) lower triangular, no zero
    # on its diagonal): power iterations on L^T L and on (L^T L)^-1 from a fixed start, `rounds`
    # each (each round multiplies a wrong direction's share by the square of a singular value
    # ratio, so a handful settle both to a few percent). The products and the substitutions go
    # column by column, adding a multiple of a contiguous row of L or of its transpose to the
    # result: no sum waits on the last, and the loops vectorise (a sum per entry, along a column
    # of L, did neither: twice the time at k = 64).
    k = L.shape[0]
    LT = np.ascontiguousarray(L.T)
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
                y[:] = 0.0
                z[:] = 0.0
                for j in range(k):
                    col = LT[j, j:]
                    ys = y[j:]
                    xj = x[j]
                    for i in range(col.size):
                        ys[i] += col[i] * xj
                for j in range(k):
                    row = L[j, :j + 1]
                    yj = y[j]
                    for i in range(row.size):
                        z[i] += row[i] * yj
            else:                       # y = L^-T x, z = L^-1 y (forwards, by the columns of L)
                triangular_solve(L, x, y, True)
                z[:] = y
                for j in range(k):
                    z[j] /= L[j, j]
                    col = LT[j, j + 1:]
                    zs = z[j + 1:]
                    zj = z[j]
                    for i in range(col.size):
                        zs[i] -= col[i] * zj
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


#: Fans of more faces than this keep their pairs (`vertex_rings`).
RING_MOST = 64


def vertex_rings(start_v, pairs_v, rstart, entries, ring):
    # The faces around every vertex (`vertex_incidence`) as the gradient passes read them: where
    # they form one closed fan, its ring of d neighbours (ring[v] = 1; face k is (v, r_k, r_k+1),
    # the last wraps to r_0: `fan_gradient`), else its d pairs as 2d entries (ring[v] = 0: an
    # open fan, or one the walk below does not close). rstart (V + 1,): where each vertex's
    # entries begin; entries as long as pairs_v. The walk goes from face to face through unused
    # faces only and must come back to its first neighbour after all d: then the ring's terms are
    # the faces' terms, each once, whatever the fan's shape.
    n = start_v.shape[0] - 1
    used = np.zeros(RING_MOST, np.bool_)
    o = 0
    for v in range(n):
        s0 = start_v[v]
        s1 = start_v[v + 1]
        d = s1 - s0
        rstart[v] = o
        ok = 3 <= d <= RING_MOST      # (the walk costs d^2: a cone's apex of thousands keeps pairs)
        if ok:
            for k in range(d):
                used[k] = False
            first = pairs_v[2 * s0]
            entries[o] = first
            used[0] = True
            nxt = pairs_v[2 * s0 + 1]
            for k in range(1, d):
                found = -1
                for e in range(s0, s1):
                    if pairs_v[2 * e] == nxt and not used[e - s0]:
                        found = e
                        break
                if found < 0:
                    ok = False
                    break
                used[found - s0] = True
                entries[o + k] = nxt
                nxt = pairs_v[2 * found + 1]
            if nxt != first:
                ok = False
        if ok:
            ring[v] = 1
            o += d
        else:
            ring[v] = 0
            for e in range(s0, s1):
                entries[o] = pairs_v[2 * e]
                entries[o + 1] = pairs_v[2 * e + 1]
                o += 2
    rstart[n] = o


def slot_incidence_start(slot, start_v, start):
    # start (n_slots + 1,) zeroed: where each slot's entries begin (a vertex's, in slot order).
    for v in range(slot.shape[0]):
        start[slot[v] + 1] = start_v[v + 1] - start_v[v]
    for sl in range(start.shape[0] - 1):
        start[sl + 1] += start[sl]


def slot_incidence_fill(slot, start_v, entries_v, ring_v, start, entries, ring, v0, v1):
    # The entries of vertices v0..v1-1 (`vertex_rings`), as slots, at their slots' places (each
    # vertex its own), and whether each is a ring.
    # (slices indexed from 0, as in `householder`)
    part_slot, part_ring, part_start = slot[v0:v1], ring_v[v0:v1], start_v[v0:v1 + 1]
    for v in range(part_slot.shape[0]):
        sl = part_slot[v]
        ring[sl] = part_ring[v]
        src = entries_v[part_start[v]:part_start[v + 1]]
        dst = entries[start[sl]:start[sl] + src.shape[0]]
        for e in range(src.shape[0]):
            dst[e] = slot[src[e]]


def to_verts(X, slot, origin, vertex_row, out, v0, v1):
    # out[v] = X[:, slot[v]] + origin[vertex_row[v]] in float64, vertices v0..v1-1. Returns how
    # many of these coordinates are not finite (the solve's last check, here instead of a pass
    # of its own over the vertices on one thread).
    bad = 0
    sv = slot[v0:v1]
    rv = vertex_row[v0:v1]
    ov = out[v0:v1]
    x, y, z = X[0], X[1], X[2]
    for i in range(sv.shape[0]):
        sl = sv[i]
        o = origin[rv[i]]
        p = np.float64(x[sl]) + o[0]
        q = np.float64(y[sl]) + o[1]
        r = np.float64(z[sl]) + o[2]
        ov[i, 0] = p
        ov[i, 1] = q
        ov[i, 2] = r
        if not (np.isfinite(p) and np.isfinite(q) and np.isfinite(r)):
            bad += (not np.isfinite(p)) + (not np.isfinite(q)) + (not np.isfinite(r))
    return bad


# Every part of a pass at once on numba's own worker threads (`compiled.over`; docs/performance.md,
# "Every core"): part k covers edges[k]..edges[k + 1] - 1, the same call that `parallel.run`
# makes for it, so the results are the same bit for bit. `compiled.py` binds `prange` and the
# compiled kernels (`_k_<name>`) by name in this module, where numba finds and caches them.
prange = range


def forward_team(edges, params, c, block_cell, shape, D, x0, comps, X):
    for k in prange(edges.shape[0] - 1):
        _k_forward(params, c, block_cell, shape, D, x0, comps, X, edges[k], edges[k + 1])  # noqa: F821


def gradient_runs_team(edges, xp, xq, inc_start, inc, ring, params, x0a, g, M, sums, run_start, A, done):
    for k in prange(edges.shape[0] - 1):
        _k_gradient_runs(xp, xq, inc_start, inc, ring, params, x0a, g, M, sums,  # noqa: F821
                         run_start, A, done, edges[k], edges[k + 1])


def gradient_runs3_team(edges, X, inc_start, inc, ring, params, x0, g, M, sums, run_start, A, done):
    for k in prange(edges.shape[0] - 1):
        _k_gradient_runs3(X, inc_start, inc, ring, params, x0, g, M, sums,  # noqa: F821
                          run_start, A, done, edges[k], edges[k + 1])


def slot_incidence_fill_team(edges, slot, rstart, entries_v, ring_v, start, entries, ring):
    for k in prange(edges.shape[0] - 1):
        _k_slot_incidence_fill(slot, rstart, entries_v, ring_v, start, entries, ring, edges[k], edges[k + 1])  # noqa: F821


def to_verts_team(edges, got, X, slot, origin, vertex_row, out):
    # got (parts, 1): every part's count of coordinates that are not finite.
    for k in prange(edges.shape[0] - 1):
        got[k, 0] = _k_to_verts(X, slot, origin, vertex_row, out, edges[k], edges[k + 1])  # noqa: F821


# Two passes in one hand-over per part (`compiled.CompiledSteps._refresh_then`; docs/performance.md,
# "Fewer hand-overs"): the forward pass over blocks b0..b1-1, then, once every part has made its
# coordinates (the second pass reads its neighbours' slots, which other parts make), the second
# pass over its range (blocks b0..b1-1, or vertices v0..v1-1 for to_verts). `sync`: the counters of
# `atomics.py` for n parts, (2 + 2 n,) int64: a part that runs out of `spins` at the barrier skips
# its second pass (sync[2 + k] stays 0; the caller then runs it), and every part adds itself to
# the parts done as its last act. The arguments: the forward pass's, then the second pass's (the
# same arrays where they are), then the counters and ranges. The same calls as the two passes on
# their own: the same results.

def wait_count(sync, i, n, looks):
    # Whether sync[i] reached n within `looks` (`atomics.spins_for` says how many take how long).
    for _ in range(looks):
        if load_acquire(sync, i) >= n:  # noqa: F821 (`atomics.define`'s, bound by `define`)
            return True
        spin_hint()  # noqa: F821
    return False


def arrive_and_wait(sync, n, looks):
    # This part has made its first pass: count it, then wait (bounded) for the other parts.
    fetch_add(sync, 0, 1)  # noqa: F821
    return wait_count(sync, 0, n, looks)


def forward_then_gradient_runs(params, c, block_cell, shape, D, x0, comps, X,
                               xp, xq, inc_start, inc, ring, params2, x0a, g, M, sums, run_start, A, done,
                               sync, k, spins, b0, b1, v0, v1):
    _k_forward(params, c, block_cell, shape, D, x0, comps, X, b0, b1)  # noqa: F821
    if arrive_and_wait(sync, (sync.shape[0] - 2) // 2, spins):  # noqa: F821
        _k_gradient_runs(xp, xq, inc_start, inc, ring, params2, x0a, g, M, sums, run_start, A, done,  # noqa: F821
                         v0, v1)
        sync[2 + k] = 1
    fetch_add(sync, 1, 1)  # noqa: F821


def forward_then_gradient_runs3(params, c, block_cell, shape, D, x0, comps, X,
                                X2, inc_start, inc, ring, params2, x02, g, M, sums, run_start, A, done,
                                sync, k, spins, b0, b1, v0, v1):
    _k_forward(params, c, block_cell, shape, D, x0, comps, X, b0, b1)  # noqa: F821
    if arrive_and_wait(sync, (sync.shape[0] - 2) // 2, spins):  # noqa: F821
        _k_gradient_runs3(X2, inc_start, inc, ring, params2, x02, g, M, sums, run_start, A, done,  # noqa: F821
                          v0, v1)
        sync[2 + k] = 1
    fetch_add(sync, 1, 1)  # noqa: F821


def forward_then_to_verts(params, c, block_cell, shape, D, x0, comps, X,
                          Xv, slot, origin, vertex_row, out,
                          sync, k, spins, b0, b1, v0, v1):
    _k_forward(params, c, block_cell, shape, D, x0, comps, X, b0, b1)  # noqa: F821
    n = (sync.shape[0] - 2) // 2
    if arrive_and_wait(sync, n, spins):  # noqa: F821
        sync[2 + n + k] = _k_to_verts(Xv, slot, origin, vertex_row, out, v0, v1)  # noqa: F821
        sync[2 + k] = 1
    fetch_add(sync, 1, 1)  # noqa: F821


_FUSED = ("forward_then_gradient_runs", "forward_then_gradient_runs3", "forward_then_to_verts")
_TEAMS = ("forward", "gradient_runs", "gradient_runs3", "slot_incidence_fill", "to_verts")
_HELPERS = ("same_cell", "taps", "change_basis", "change_basis_runs", "runs_to_points", "block_powers",
            "block_moments", "block_moments3", "triangular_solve", "fan_gradient", "cell_polynomial",
            "reflection", "reflect")
_KERNELS = {"forward": "njit_sums", "gradient_transpose": "njit_sums", "gradient_transpose3": "njit_sums",
            "sum_runs": "njit", "gradient_runs": "njit", "gradient_runs3": "njit",
            "reduce_blocks": "njit", "reduce_runs": "njit", "householder": "njit_sums", "apply_q": "njit_sums",
            "condition": "njit", "triangular_solve": "njit",
            "vertex_incidence": "njit", "vertex_rings": "njit", "slot_incidence_start": "njit",
            "slot_incidence_fill": "njit",
            "to_verts": "njit"}
#: The plain functions, as written (`define` rebinds the helpers' names to compiled ones).
_SOURCE = {name: globals()[name] for name in _HELPERS + tuple(_KERNELS) + _FUSED
           + ("wait_count", "arrive_and_wait")}
