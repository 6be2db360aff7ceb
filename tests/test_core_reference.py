"""The core against independent dense reimplementations on small cases (V <= ~300, N <= 64).

- The dense FFD matrix S B (V, N) is built twice: by probing `deform` with unit control-point
  offsets, and from Blender's weight formulas written out here (docs/design.md, "The
  deformation"; Bernstein for BEZIER). The two must agree, so the probe is cross-checked.
- A one-direction solve is compared with the paper's eq. (17), alpha taken literally from eq. (10).
- General solves (three directions, mobility, pins, islands) are compared with a sequential dense
  KKT solve written here with np.linalg.solve.
"""
import itertools
from math import comb

import numpy as np
import pytest

import vpffd_addon as vp
from vpffd_addon import tolerances as tol

from . import _meshes as M

pytestmark = pytest.mark.core

KINDS = ("LINEAR", "CARDINAL", "CATMULL_ROM", "BSPLINE", "BEZIER")


# ---------------------------------------------------------------- reference weights

def ref_local_weights(t, kind):
    """Blender's key_curve_position_weights for one t: 4 weights for taps i-1, i, i+1, i+2."""
    if kind == "LINEAR":
        return [0.0, 1.0 - t, t, 0.0]
    if kind == "BSPLINE":
        return [(1 - t) ** 3 / 6, (3 * t ** 3 - 6 * t ** 2 + 4) / 6,
                (-3 * t ** 3 + 3 * t ** 2 + 3 * t + 1) / 6, t ** 3 / 6]
    fc = {"CARDINAL": 0.71, "CATMULL_ROM": 0.5}[kind]
    return [-fc * t ** 3 + 2 * fc * t ** 2 - fc * t,
            (2 - fc) * t ** 3 + (fc - 3) * t ** 2 + 1,
            (fc - 2) * t ** 3 + (3 - 2 * fc) * t ** 2 + fc * t,
            fc * t ** 3 - fc * t ** 2]


def ref_axis_weights(x, n, lo, hi, kind):
    """Dense (V, n) weights of one axis, one vertex at a time."""
    W = np.zeros((len(x), n))
    for v, xv in enumerate(x):
        if n == 1:
            W[v, 0] = 1.0
        elif kind == "BEZIER":
            u = min(max((xv - lo) / (hi - lo), 0.0), 1.0)
            for k in range(n):
                W[v, k] = comb(n - 1, k) * u ** k * (1 - u) ** (n - 1 - k)
        else:
            u = (xv - lo) / ((hi - lo) / (n - 1))
            i = int(np.floor(u))
            for k, w in enumerate(ref_local_weights(u - i, kind)):
                W[v, min(max(i - 1 + k, 0), n - 1)] += w
    return W


def ref_dense_B(lat, X, influence=None):
    """(V, N) matrix S B with control point index u + nu * (v + nv * w)."""
    Wu, Wv, Ww = (ref_axis_weights(X[:, a], lat.shape[a], lat.lo[a], lat.hi[a], lat.interpolation[a])
                  for a in range(3))
    B = np.einsum("vk,vj,vi->vkji", Ww, Wv, Wu).reshape(len(X), -1)
    if influence is not None:
        B = B * np.asarray(influence)[:, None]
    return B


def probe_dense_B(b):
    """(V, N) S B from the binding alone, by unit control-point offsets (the map is affine)."""
    P0 = b.lattice.rest_points
    base = b.deform(P0)
    N = len(P0)
    B = np.zeros((b.n_verts, N))
    for i in range(N):
        for c in range(3):
            P = P0.copy()
            P[i, c] += 1.0
            d = b.deform(P) - base
            # Offsets along c move the vertices along c only, by the same weights for every c.
            others = [k for k in range(3) if k != c]
            assert np.abs(d[:, others]).max() <= 1e-12
            if c == 0:
                B[:, i] = d[:, 0]
            else:
                np.testing.assert_allclose(d[:, c], B[:, i], rtol=0, atol=1e-12)
    return B


def small_case(seed, n_parts=1, shape=None, kinds=None, influence=False):
    rng = np.random.default_rng(seed)
    verts, tris, part = M.closed_mesh(rng, n_parts, max_subdivisions=1, max_resolution=2)
    if shape is None:
        shape = tuple(int(n) for n in rng.integers(2, 5, 3))
        while np.prod(shape) > 64:
            shape = tuple(max(2, n - 1) for n in shape)
    lat = M.random_lattice(rng, verts, shape=shape, kinds=kinds)
    s = rng.uniform(0.2, 1.0, len(verts)) if influence else None
    P = M.random_points(rng, lat, noise=0.3)
    return rng, verts, tris, part, lat, s, P


# ---------------------------------------------------------------- (c) the FFD matrix

@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("kinds", [("BSPLINE",) * 3, ("LINEAR", "CARDINAL", "CATMULL_ROM"),
                                   ("BEZIER", "BSPLINE", "CARDINAL"), ("CATMULL_ROM", "BEZIER", "LINEAR")])
def test_probed_matrix_matches_weight_formulas(seed, kinds):
    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(1, 5, 3))
    lo = rng.uniform(-1.0, -0.2, 3)
    lat = vp.Lattice(shape, kinds, bounds=(lo, lo + rng.uniform(0.5, 2.0, 3)))
    # Points inside, outside (several cells beyond the clamped edges) and exactly on knots.
    X = lat.lo + rng.uniform(-0.8, 1.8, (60, 3)) * (lat.hi - lat.lo)
    X[:8] = lat.rest_points[rng.integers(0, lat.n_points, 8)]
    s = rng.uniform(0.0, 1.5, len(X))
    b = vp.bind(lat, X, np.array([[0, 1, 2], [3, 4, 5]]), influence=s)
    ref = ref_dense_B(lat, X, s)
    np.testing.assert_allclose(probe_dense_B(b), ref, rtol=0, atol=1e-12)
    # deform is x0 + S B (P - P0) for any P.
    P = lat.rest_points + rng.normal(0, 0.3, (lat.n_points, 3))
    np.testing.assert_allclose(b.deform(P), X + ref @ (P - lat.rest_points), rtol=0, atol=1e-12)


@pytest.mark.parametrize("kind", KINDS)
def test_weights_sum_to_one(kind):
    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 5, 7):
        x = rng.uniform(-3.0, 4.0, 200)
        W = ref_axis_weights(x, n, 0.0, 1.0, kind)
        np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-14)
    # Through the binding: a uniform offset c of every control point moves each vertex by s * c.
    lat = vp.Lattice((3, 4, 2), kind, bounds=((-1, -1, -1), (1, 2, 0.5)))
    X = rng.uniform(-2.0, 2.5, (50, 3))
    s = rng.uniform(0, 1, 50)
    c = np.array([0.3, -1.2, 0.7])
    b = vp.bind(lat, X, np.array([[0, 1, 2]]), influence=s)
    np.testing.assert_allclose(b.deform(lat.rest_points + c), X + s[:, None] * c, atol=1e-13)


@pytest.mark.parametrize("kind,interior", [("BEZIER", (0.0, 1.0)), ("LINEAR", (0.0, 1.0)),
                                           ("BSPLINE", (1.0, -1.0)), ("CATMULL_ROM", (1.0, -1.0))])
def test_bases_reproduce_the_identity(kind, interior):
    """sum_i w_i(x) P0_i = x where the basis has linear precision: everywhere in the box for Bezier
    and trilinear, away from the clamped end cells for the cubic B-spline and Catmull-Rom
    (in cell units: u in [1, n - 2])."""
    n = 6
    lat = vp.Lattice((n, n, n), kind, bounds=((-1.0, -0.5, 0.0), (2.0, 1.5, 1.0)))
    rng = np.random.default_rng(3)
    if kind in ("BEZIER", "LINEAR"):
        X = lat.lo + rng.uniform(0, 1, (100, 3)) * (lat.hi - lat.lo)
    else:
        u = rng.uniform(1.0, n - 2.0, (100, 3))
        X = lat.lo + u * (lat.hi - lat.lo) / (n - 1)
    P0 = lat.rest_points
    W = ref_dense_B(lat, X)
    np.testing.assert_allclose(W @ P0, X, atol=1e-13)
    # So an affine map of the control grid is reproduced by the deformation there.
    A = np.eye(3) + rng.uniform(-0.4, 0.4, (3, 3))
    c = rng.uniform(-1, 1, 3)
    P = P0 @ A.T + c
    b = vp.bind(lat, X, np.array([[0, 1, 2]]))
    np.testing.assert_allclose(b.deform(P), X @ A.T + c, atol=1e-12)
    np.testing.assert_allclose(vp.jacobian_det(b, P), np.linalg.det(A), rtol=1e-12)


def test_cardinal_lacks_linear_precision_and_bspline_clamps_at_the_ends():
    """Blender's CARDINAL (tension 0.71) does not reproduce x, and the clamped B-spline does not
    at the end cells: both are what Blender does, and the core must not 'fix' them."""
    lat = vp.Lattice((5, 1, 1), "CARDINAL", bounds=((0, 0, 0), (4, 1, 1)))
    X = np.array([[1.5, 0, 0], [2.25, 0, 0], [0.5, 0, 0]])
    b = vp.bind(lat, X, np.array([[0, 1, 2]]))
    P = lat.rest_points * [2.0, 1.0, 1.0]   # x -> 2x on the grid
    got = b.deform(P)[:, 0]
    ref = X[:, 0] + ref_dense_B(lat, X) @ (P - lat.rest_points)[:, 0]
    np.testing.assert_allclose(got, ref, atol=1e-14)
    assert abs(got[1] - 2 * X[1, 0]) > 1e-3          # cardinal: not linear in the middle
    lat = vp.Lattice((5, 1, 1), "BSPLINE", bounds=((0, 0, 0), (4, 1, 1)))
    b = vp.bind(lat, X, np.array([[0, 1, 2]]))
    got = b.deform(P)[:, 0]
    np.testing.assert_allclose(got[:2], 2 * X[:2, 0], atol=1e-14)   # interior: exact
    t = 0.5                                         # end cell: u = 0.5, tap -1 clamps onto 0
    assert abs(got[2] - (2 * 0.5 + (1 - t) ** 3 / 6 * 1.0)) < 1e-14


# ---------------------------------------------------------------- (a) eq. (17) with eq. (10)

def eq10_alpha(SB, Xbar, tris):
    """alpha_ijk = sum_faces (B(u_l) + B(u_m) + B(u_n)) / 6 * |y_m-y_l  y_n-y_l ; z_m-z_l  z_n-z_l|."""
    alpha = np.zeros(SB.shape[1])
    for l, m, n in tris:
        y, z = Xbar[:, 1], Xbar[:, 2]
        det = (y[m] - y[l]) * (z[n] - z[l]) - (y[n] - y[l]) * (z[m] - z[l])
        alpha += (SB[l] + SB[m] + SB[n]) / 6.0 * det
    return alpha


@pytest.mark.parametrize("seed", range(10))
def test_single_direction_is_eq17(seed):
    kinds = [KINDS[(seed + k) % 5] for k in range(3)]
    rng, verts, tris, _, lat, s, P = small_case(seed, kinds=kinds, influence=seed % 2 == 1)
    b = vp.bind(lat, verts, tris, influence=s)
    SB = ref_dense_B(lat, verts, s)
    D = P - lat.rest_points
    Xbar = verts + SB @ D                              # the plain FFD, M-bar
    scale = float(rng.uniform(0.6, 1.4))
    V_ref = scale * M.face_volume(verts, tris)
    a = V_ref - M.face_volume(Xbar, tris)
    alpha = eq10_alpha(SB, Xbar, tris)
    delta = a / np.dot(alpha, alpha) * alpha           # eq. (17)

    sol = b.solve(P, axes="X", volume_scale=scale)
    exp_points = P.copy()
    exp_points[:, 0] += delta
    exp_verts = verts + SB @ (exp_points - lat.rest_points)
    size = lat.size
    np.testing.assert_allclose(sol.points, exp_points, rtol=0, atol=1e-10 * size)
    np.testing.assert_allclose(sol.verts, exp_verts, rtol=0, atol=1e-10 * size)
    assert abs(M.face_volume(exp_verts, tris) - V_ref) <= 1e-10 * abs(V_ref)   # the reference works
    assert abs(sol.plain_volume - M.face_volume(Xbar, tris)) <= 1e-12 * abs(V_ref)


def test_eq10_is_the_transposed_gradient():
    """Sanity of the reference itself: eq. (10) equals (S B)^T g_x on a closed mesh."""
    rng, verts, tris, _, lat, s, P = small_case(11, influence=True)
    SB = ref_dense_B(lat, verts, s)
    Xbar = verts + SB @ (P - lat.rest_points)
    g = M.volume_gradient(Xbar, tris)
    np.testing.assert_allclose(eq10_alpha(SB, Xbar, tris), SB.T @ g[:, 0], atol=1e-13)


# ---------------------------------------------------------------- (b) sequential dense KKT

def kkt_solve(lat, verts, tris, SB, P, E, scale, mobility=None, pins=(), labels=None):
    """The sequential per-direction minimum-norm correction, written densely.

    Per direction e_d (d = 1..m): gradient at the current vertices; volume rows alpha_k =
    (S B)^T (g . e_d) restricted to island k (one row without islands); pin rows (S B)_s;
    rhs (V_target - V_now) / (m - d + 1) and (T_s - x_s) . e_d; minimise sum t^2 / mobility over
    the mobile points through the KKT system [[2W, C^T], [C, 0]] [t; lam] = [0; r].
    """
    c = lat.centre
    P = np.array(P, float)
    N = len(P)
    mob = np.ones(N) if mobility is None else np.asarray(mobility, float)
    free = np.flatnonzero(mob > 0)
    if labels is None:
        labels = np.zeros(len(verts), int)
    k = labels.max() + 1
    face_lab = labels[tris[:, 0]]
    targets = scale * np.array([M.face_volume(verts, tris[face_lab == j], origin=c) for j in range(k)])
    m = len(E)
    for d, e in enumerate(E):
        X = verts + SB @ (P - lat.rest_points)
        ge = M.volume_gradient(X, tris, origin=c) @ e
        rows, rhs = [], []
        for j in range(k):
            alpha = SB.T @ np.where(labels == j, ge, 0.0)
            flux = np.abs(np.where(labels == j, ge, 0.0) * SB.sum(1)).sum()
            assert np.linalg.norm(alpha * np.sqrt(mob)) > 1e-6 * flux, "degenerate case: bad setup"
            rows.append(alpha)
            rhs.append((targets[j] - M.face_volume(X, tris[face_lab == j], origin=c)) / (m - d))
        for vi, T in pins:
            rows.append(SB[vi])
            rhs.append((np.asarray(T) - X[vi]) @ e)
        C = np.array(rows)[:, free]
        q = len(rows)
        K = np.zeros((len(free) + q, len(free) + q))
        K[:len(free), :len(free)] = np.diag(2.0 / mob[free])
        K[:len(free), len(free):] = C.T
        K[len(free):, :len(free)] = C
        sol = np.linalg.solve(K, np.concatenate([np.zeros(len(free)), rhs]))
        t = np.zeros(N)
        t[free] = sol[:len(free)]
        P += np.outer(t, e)
    return P, verts + SB @ (P - lat.rest_points), targets


def _compare(b, sol, lat, verts, tris, SB, P, E, scale, **kw):
    exp_P, exp_X, targets = kkt_solve(lat, verts, tris, SB, P, E, scale, **kw)
    size = lat.size
    # Reference sanity: its volume(s) and pins are met.
    labels = kw.get("labels")
    if labels is None:
        assert abs(M.face_volume(exp_X, tris, origin=lat.centre) - targets.sum()) <= 1e-10 * abs(targets.sum())
    for vi, T in kw.get("pins", ()):
        np.testing.assert_allclose(exp_X[vi], T, atol=1e-10 * size)
    assert sol.warnings == ()
    np.testing.assert_allclose(sol.points, exp_P, rtol=0, atol=1e-9 * size)
    np.testing.assert_allclose(sol.verts, exp_X, rtol=0, atol=1e-9 * size)


@pytest.mark.parametrize("seed", range(8))
def test_xyz_with_mobility_matches_kkt(seed):
    rng, verts, tris, _, lat, s, P = small_case(100 + seed, influence=seed % 2 == 0)
    b = vp.bind(lat, verts, tris, influence=s)
    SB = probe_dense_B(b)
    mob = rng.uniform(0.1, 1.0, lat.n_points)
    mob[rng.random(lat.n_points) < 0.25] = 0.0
    scale = float(rng.uniform(0.6, 1.4))
    axes = ["XYZ", "ZXY", "YZX", "XZY"][seed % 4]
    E = np.eye(3)[["XYZ".index(a) for a in axes]]
    sol = b.solve(P, axes=axes, volume_scale=scale, mobility=mob)
    _compare(b, sol, lat, verts, tris, SB, P, E, scale, mobility=mob)


@pytest.mark.parametrize("seed", range(8))
def test_pins_with_mobility_match_kkt(seed):
    rng, verts, tris, _, lat, s, P = small_case(200 + seed, influence=seed % 2 == 1)
    b = vp.bind(lat, verts, tris, influence=s)
    SB = probe_dense_B(b)
    n_pins = 1 + seed % 2
    ok = np.flatnonzero(M.inside(lat, verts, 0.1) & ((s is None) or (s > 0.3)))
    at = M.farthest_points(verts, ok if len(ok) >= n_pins else np.arange(len(verts)), n_pins, rng)
    X = verts + SB @ (P - lat.rest_points)
    pins = [(i, X[i] + rng.uniform(-0.08, 0.08, 3) * lat.size) for i in at]
    mob = None if seed < 4 else rng.uniform(0.2, 1.0, lat.n_points)
    scale = float(rng.uniform(0.6, 1.4))
    if seed % 3 == 2:
        E = M.rotation(rng)                           # general orthonormal directions
        sol = b.solve(P, directions=E, volume_scale=scale, mobility=mob, pins=pins)
    else:
        E = np.eye(3)
        sol = b.solve(P, axes="XYZ", volume_scale=scale, mobility=mob, pins=pins)
    _compare(b, sol, lat, verts, tris, SB, P, E, scale, mobility=mob, pins=pins)


def _svd_min_norm(C, r, rcond):
    """t of least norm minimising |C t - r|, singular values of C under rcond times the largest
    dropped (written out: an SVD)."""
    U, S, Vt = np.linalg.svd(C, full_matrices=False)
    keep = S > rcond * S.max()
    return Vt[keep].T @ ((U[:, keep].T @ r) / S[keep])


def _kkt_min_norm(C, r):
    """t (n,) of least norm with C t = r, from the KKT system [[2I, C^T], [C, 0]] [t; lam] = [0; r]."""
    q, n = C.shape
    K = np.zeros((n + q, n + q))
    K[:n, :n] = 2.0 * np.eye(n)
    K[:n, n:] = C.T
    K[n:, :n] = C
    return np.linalg.solve(K, np.concatenate([np.zeros(n), r]))[:n]


def gauss_newton_solve(lat, verts, tris, SB, P, scale, labels, pins=(), met=1e-9, iterations=10):
    """Per-island volumes (and pins) over all three axes at once, written densely. Without pins
    the first move is the sweep: the minimum-norm move t of every control-point coordinate that
    meets the linearised island volumes (all axes at the plain deformation), applied an axis at a
    time, each axis after the first re-solved at the coordinates the earlier ones left (the
    minimum-norm change of its planned move that gives what the plan asked of it, singular values
    under `SWEEP_RCOND` of the largest left out; the last axis: all that remains). Then Gauss-Newton, each step the minimum-norm move that meets the
    linearised island volumes and the pins (the KKT system [[2I, C^T], [C, 0]] [t; lam] = [0; r]),
    until every island is within `met` of its target and every pin within `met` of the lattice
    size."""
    c = lat.centre
    P = np.array(P, float)
    N = len(P)
    k = labels.max() + 1
    face_lab = labels[tris[:, 0]]
    rest = np.array([M.face_volume(verts, tris[face_lab == j], origin=c) for j in range(k)])
    targets = scale * rest

    def volumes_and_rows(axes):
        X = verts + SB @ (P - lat.rest_points)
        now = np.array([M.face_volume(X, tris[face_lab == j], origin=c) for j in range(k)])
        rows = np.array([[SB.T @ M.volume_gradient(X, tris[face_lab == j], origin=c)[:, a] for j in range(k)]
                         for a in axes])                                    # (axes, k, N)
        return now, rows
    if not pins:
        now, plan = volumes_and_rows(range(3))
        t = _kkt_min_norm(np.concatenate(plan, axis=1), targets - now).reshape(3, N)
        for a in range(3):
            u = t[a]
            if a:
                now, (alpha,) = volumes_and_rows([a])
                want = targets - now if a == 2 else plan[a] @ u
                u = u + _svd_min_norm(alpha, want - alpha @ u, tol.SWEEP_RCOND)
            P[:, a] += u
    for _ in range(iterations):
        X = verts + SB @ (P - lat.rest_points)
        now = np.array([M.face_volume(X, tris[face_lab == j], origin=c) for j in range(k)])
        pin_miss = [np.abs(np.asarray(T) - X[vi]).max() for vi, T in pins]
        if (np.abs(now - targets) <= met * np.maximum(np.abs(targets), np.abs(rest))).all() and \
                all(d <= met * lat.size for d in pin_miss):
            break
        rows, rhs = [], []
        for j in range(k):
            G = M.volume_gradient(X, tris[face_lab == j], origin=c)      # (V, 3)
            rows.append(np.concatenate([SB.T @ G[:, a] for a in range(3)]))
            rhs.append(targets[j] - now[j])
        for vi, T in pins:
            for a in range(3):
                row = np.zeros(3 * N)
                row[a * N:(a + 1) * N] = SB[vi]
                rows.append(row)
                rhs.append(np.asarray(T)[a] - X[vi, a])
        C, q = np.array(rows), len(rows)
        K = np.zeros((3 * N + q, 3 * N + q))
        K[:3 * N, :3 * N] = 2.0 * np.eye(3 * N)
        K[:3 * N, 3 * N:] = C.T
        K[3 * N:, :3 * N] = C
        t = np.linalg.solve(K, np.concatenate([np.zeros(3 * N), rhs]))[:3 * N]
        P += t.reshape(3, N).T
    return P, verts + SB @ (P - lat.rest_points), targets


@pytest.mark.parametrize("seed", range(6))
def test_islands_match_gauss_newton(seed):
    """Per-Island Volume solves all islands jointly over all axes (their volume rows share
    control points in every direction); checked against the dense Gauss-Newton above."""
    rng, verts, tris, part, lat, s, P = small_case(300 + seed, n_parts=2, shape=(4, 4, 4))
    b = vp.bind(lat, verts, tris)
    SB = probe_dense_B(b)
    scale = float(rng.uniform(0.6, 1.4))
    pins = []
    if seed % 2:
        X = verts + SB @ (P - lat.rest_points)
        i = int(np.flatnonzero(M.inside(lat, verts, 0.15))[0])
        pins = [(i, X[i] + rng.uniform(-0.05, 0.05, 3) * lat.size)]
    sol = b.solve(P, axes="XYZ", volume_scale=scale, islands=True, pins=pins)
    exp_P, exp_X, _ = gauss_newton_solve(lat, verts, tris, SB, P, scale, part, pins)
    assert sol.warnings == ()
    np.testing.assert_allclose(sol.points, exp_P, rtol=0, atol=1e-9 * lat.size)
    np.testing.assert_allclose(sol.verts, exp_X, rtol=0, atol=1e-9 * lat.size)
    # Per-island volumes come out as the targets.
    face_part = part[tris[:, 0]]
    for k in range(2):
        rest_k = M.face_volume(verts, tris[face_part == k])
        assert abs(M.face_volume(sol.verts, tris[face_part == k]) - scale * rest_k) <= 1e-9 * abs(rest_k)


@pytest.mark.parametrize("signs", [(-1, -1, -1), (1, -1, 1)])
def test_signed_axis_directions_with_a_pin_match_kkt(signs):
    """Directions (+-X, +-Y, +-Z) given as rows must be treated as the lines they span."""
    rng, verts, tris, _, lat, s, P = small_case(400)
    b = vp.bind(lat, verts, tris)
    SB = probe_dense_B(b)
    X = verts + SB @ (P - lat.rest_points)
    i = int(np.flatnonzero(M.inside(lat, verts, 0.15))[0])
    pins = [(i, X[i] + np.array([0.04, -0.03, 0.05]) * lat.size)]
    E = np.diag(np.array(signs, float))
    sol = b.solve(P, directions=E, pins=pins)
    _compare(b, sol, lat, verts, tris, SB, P, E, 1.0, pins=pins)


@pytest.mark.parametrize("seed", range(4))
def test_open_mesh_matches_kkt_about_the_lattice_centre(seed):
    """An open mesh (a box without one side): the volume, its gradient and the targets are all
    measured about the lattice centre, which here is far from the coordinate origin."""
    rng = np.random.default_rng(500 + seed)
    verts, tris = vp.box(2, 1.0)
    tris = tris[np.abs(verts[tris].mean(1)[:, 2] - 0.5) > 1e-9]     # drop the top side
    verts = verts @ M.rotation(rng).T + rng.uniform(2.0, 3.0, 3)
    lat = M.random_lattice(rng, verts, shape=(3, 3, 3), margin=(-0.25, -0.05))
    assert np.linalg.norm(lat.centre) > 1.0
    P = M.random_points(rng, lat, noise=0.3)
    b = vp.bind(lat, verts, tris)
    assert not b.is_closed
    SB = probe_dense_B(b)
    scale = float(rng.uniform(0.7, 1.3))
    sol = b.solve(P, volume_scale=scale)
    _compare(b, sol, lat, verts, tris, SB, P, np.eye(3), scale)
    assert abs(sol.volume - scale * M.face_volume(verts, tris, origin=lat.centre)) <= 1e-9 * abs(sol.volume)
