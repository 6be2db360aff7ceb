"""Exact volume-preserving FFD: the sequential per-direction closed form (paper sections 3-5).

Along one fixed direction e the volume is exactly linear in the control-point offsets, so each
direction is a least-squares problem with linear constraints (docs/design.md, "The closed form"):
minimise ``sum_i |t_i|^2 / m_i`` subject to ``C t = r``, solved by ``t = M C^T (C M C^T)^+ r`` with
M = diag(mobility). C has one volume row (alpha = (S B)^T g_e, eq. 10-12), or one per island, and
one row per pin (paper eq. 21). With one volume row and unit mobility this is eq. (17).
"""
import time
from dataclasses import dataclass

import numpy as np

from . import tolerances as tol
from .backends import default_steps
from .compiled import min_norm
from .steps import CAPABILITIES
from .volume import face_volumes

_AXES = {"X": 0, "Y": 1, "Z": 2}
_JOINT_ITERATIONS = 10   # Gauss-Newton steps for islands and pins (4 sufficed on real meshes)
#: The axes' unit directions (read-only: rows of it are handed around as directions).
_EYE = np.eye(3)
_EYE.flags.writeable = False
#: the axis of each signed unit axis vector, by its coordinates (every solve asks per step)
_AXIS_OF = {tuple(s * v for v in row): a for a, row in enumerate(np.eye(3).tolist()) for s in (1.0, -1.0)}
_OVERFLOW = "the correction overflowed: coordinates or displacements are too large for floating point"


@dataclass
class Solution:
    """Result of `Binding.solve`. Coordinates in lattice space."""
    verts: np.ndarray                 #: (V, 3) deformed, volume-corrected vertices
    points: np.ndarray                #: (N, 3) corrected control points: deform(points) == verts
    volume: float                     #: volume of `verts`
    target_volume: float              #: volume_scale * the rest volume (or the given target)
    plain_volume: float               #: volume of the plain FFD of the input points
    directions: np.ndarray            #: (m, 3) unit directions that were used, in order
    island_volumes: np.ndarray = None         #: (k,) per-island volumes when islands=True
    island_target_volumes: np.ndarray = None  #: (k,) their targets
    warnings: tuple = ()              #: constraints that could not be met, in words
    seconds: float = 0.0              #: wall time of the solve
    backend: str = None               #: the backend whose steps ran (`backends.py`): NUMPY, COMPILED, GPU


def parse_directions(axes, directions):
    """Unit directions (m, 3) from `directions` rows, or from an axis string such as "XZ"."""
    if directions is not None:
        d = np.asarray(directions, dtype=np.float64)
        if d.ndim == 1 and d.shape == (3,):
            d = d[None]
        if d.ndim != 2 or d.shape[1] != 3:
            raise ValueError(f"directions must have shape (m, 3), got {d.shape}")
        if not np.isfinite(d).all():
            raise ValueError("directions must be finite")
        d = d / np.abs(d).max(axis=1, keepdims=True).clip(min=np.finfo(float).tiny)  # no overflow
        norm = np.linalg.norm(d, axis=1)
        if (norm == 0).any() or not np.isfinite(norm).all():
            raise ValueError(f"direction {int(np.argmin(norm))} is the zero vector")
        return d / norm[:, None]
    if axes is None:
        axes = ""
    if not isinstance(axes, str):
        raise ValueError(f"axes must be a string such as 'XYZ', got {axes!r}")
    key = axes.upper()
    if any(c not in _AXES for c in key) or len(set(key)) != len(key):
        raise ValueError(f"axes must be distinct letters from 'XYZ', got {axes!r}")
    return np.eye(3)[[_AXES[c] for c in key]].reshape(-1, 3)


def _check_mobility(mobility, N):
    if mobility is None:
        return None
    m = np.asarray(mobility, dtype=np.float64)
    if m.shape != (N,):
        raise ValueError(f"mobility must have shape ({N},), got {m.shape}")
    if not np.isfinite(m).all() or (m < 0).any() or (m > 1).any():
        raise ValueError("mobility must be finite and within [0, 1] (0 keeps a control point fixed)")
    return m


def _check_pins(pins, binding):
    """(slots (k,), targets (k, 3) relative to their volume origins, vertex indices (k,))."""
    pins = list(pins) if pins is not None else []
    if not pins:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64)
    try:
        index = np.array([int(p[0]) for p in pins], dtype=np.int64)
        target = np.array([np.asarray(p[1], dtype=np.float64).reshape(3) for p in pins])
    except (TypeError, ValueError, IndexError) as exc:
        raise ValueError(f"pins must be a sequence of (vertex index, (x, y, z)) pairs: {exc}") from None
    bad = (index < 0) | (index >= binding.n_verts)
    if bad.any():
        raise ValueError(f"pin on vertex {int(index[bad][0])}, outside [0, {binding.n_verts})")
    if not np.isfinite(target).all():
        raise ValueError("pin targets must be finite")
    free = binding.influence[index] == 0
    if free.any():
        raise ValueError(f"pin on vertex {int(index[free][0])}, which the lattice does not influence "
                         "(its influence is 0)")
    return binding.slot[index], target - binding.origins(index), index


def _frame(e):
    """(axis, p, q): the axis index when e is a coordinate axis (sign does not matter), else None
    with unit p, q completing e to a right-handed orthonormal frame (e, p, q)."""
    axis = _AXIS_OF.get(tuple(e.tolist()))
    if axis is not None:
        return axis, None, None
    a = np.zeros(3)
    a[int(np.argmin(np.abs(e)))] = 1.0
    p = np.cross(e, a)
    p /= np.linalg.norm(p)
    return None, p, np.cross(e, p)


class _State:
    """Per-solve working state.

    D (N, 3): current control-point displacements P - P0. X (3, n_slots): slot coordinates relative
    to the volume origins, a component refreshed (x0 + S B D) only when a gradient needs it: a step
    along axis a changes only component a, and its volume before and after follows from
    ``V = x0_a . g + D_a . alpha`` (homogeneity), so no forward product is spent on it.
    """

    def __init__(self, b, points, mobility, pins, islands, targets, steps=None):
        self.b = b
        # P is updated alongside D so that points with zero offset come back bit-identical.
        self.P = np.array(points, dtype=np.float64)
        self.D = self.P - b.lattice.rest_points
        self.k = (steps or default_steps)(b)        # the per-slot work (NumPy, compiled, or GPU)
        self.mob = mobility
        self.pin_slots, self.pin_targets, self.pin_index = pins
        self.pin_rows = b.rows(self.pin_slots) if len(self.pin_slots) else None
        self.islands = islands
        self.targets = targets                      # (k,) volume targets (k = 1 or islands)
        self.slot_island = b.slot_island if islands else None
        self.volumes = None                         # (k,) current volumes, known after a gradient
        self.used = np.zeros(len(targets), bool)    # volume rows that could move at least once
        self.unmet_pins = set()
        self.skipped = []                            # steps refused as absurd, in words
        self.plain = None                            # (k,) volumes of the plain deformation
        self.mirrored = False                        # whether some target's sign was turned
        self.moves = 0                               # how often the control points moved
        self._last_gradient = None                   # ((direction, moves), gradient(e))
        self._fused = {}                             # {(direction, moves): gradient(e)} (`gradients`)
        self._alpha = None                           # (g, alpha_rows(g)) of the last g asked for
        f32 = self.k.float32
        self.degenerate = tol.DEGENERATE_REL_F32 if f32 else tol.DEGENERATE_REL_F64
        self.met_rel = tol.MET_REL_F32 if f32 else tol.MET_REL_F64
        rest = b.rest_island_volumes if islands else np.array([b.rest_volume])
        scale = np.maximum(np.abs(targets), np.abs(rest))
        self.vol_scale = np.maximum(scale, np.abs(b.rest_volume) * 1e-6 + 1e-300)

    def in_float64(self):
        """Go on with float64 steps where the steps offer them (`in_float64`): the steps over
        islands, whose small bodies' volumes float32 coordinates cannot resolve to the tolerance
        (a body 1% of the lattice's size rounds at ~1e-5 of its volume), run in float64 from the
        start; the compiled passes cost about as much in float64 (they wait on gathers, not on
        arithmetic: docs/performance.md). A volume then counts as met at a tenth of the float32
        tolerance (what is left for the rounding of the result to float32). Returns whether it
        switched."""
        to64 = getattr(self.k, "in_float64", None)
        if to64 is None or not self.k.float32:
            return False
        self.k = to64()
        self.degenerate, self.met_rel = tol.DEGENERATE_REL_F64, 0.1 * tol.MET_REL_F32
        self._last_gradient = None
        self._fused = {}
        return True

    @property
    def _rows(self):
        """(rows, k) for the steps' per-row sums: None for one volume row, else the islands."""
        return (self.slot_island, len(self.targets)) if self.islands else (None, 1)

    def gradient(self, e):
        """(axis, g, base) for unit direction e: g the e-gradient at the current vertices (a
        handle of the steps) and, for an axis, base (k,) = x0_a . g per row, so
        V = base + D_a . alpha. The last one is kept until the control points move (the joint
        iteration measures along its first direction and then starts there again)."""
        key = (tuple(np.asarray(e, np.float64).tolist()), self.moves)
        if self._last_gradient is not None and self._last_gradient[0] == key:
            return self._last_gradient[1]
        result = self._fused.get(key) if self._fused else None
        if result is None:
            result = self._gradient(e)
        self._last_gradient = (key, result)
        return result

    def gradients(self, dirs):
        """Ready the gradients along every one of `dirs` at the current control points: where
        they are the three axes and the steps offer `axis_gradients`, from one pass over the
        faces (the joint steps linearise every direction at the same coordinates)."""
        fused = getattr(self.k, "axis_gradients", None)
        axes = [_frame(e)[0] for e in dirs]
        if fused is None or sorted(a for a in axes if a is not None) != [0, 1, 2] or len(axes) != 3:
            return
        if self._fused and next(iter(self._fused))[1] == self.moves:
            return
        self._fused = {}
        for a, g in enumerate(fused(self.D)):
            e = _EYE[a]
            self._fused[(tuple(e.tolist()), self.moves)] = (a, g, self.k.x0_dot(a, g, *self._rows))
        for e, a in zip(dirs, axes):   # the directions as given (-X measures as +X)
            self._fused[(tuple(np.asarray(e, np.float64).tolist()), self.moves)] = \
                self._fused[(tuple(_EYE[a].tolist()), self.moves)]

    def _gradient(self, e):
        axis, p, q = _frame(e)
        if axis is not None:
            g = self.k.axis_gradient(axis, self.D)
            return axis, g, self.k.x0_dot(axis, g, *self._rows)
        return None, self.k.direction_gradient(p, q, self.D), None

    def measure(self, e, axis, g, base, alpha):
        """(k,) current volumes from the e-gradient g (V is homogeneous of degree one along e)."""
        if axis is None or alpha is None:
            return self.k.x_dot(e, axis, g, *self._rows, D=self.D)
        return base + _mv(alpha, self.D[:, axis])

    def volume_met(self):
        return np.abs(self.volumes - self.targets) <= self.met_rel * self.vol_scale

    def alpha_rows(self, g):
        """(k, N) volume coefficients (S B)^T g, one row per volume row (island); the last one is
        kept (a measure and the step after it ask for the same)."""
        if self._alpha is None or self._alpha[0] is not g:
            self._alpha = (g, self.k.transpose(g, *self._rows))
        return self._alpha[1]

    def measured(self, e):
        """(k,) current volumes, from the gradient along unit direction e (with its coefficients
        where e is an axis: V = x0_a . g + D_a . alpha)."""
        axis, g, base = self.gradient(e)
        return self.measure(e, axis, g, base, None if axis is None else self.alpha_rows(g))

    def _note_plain(self, volumes):
        """Keep the plain deformation's volumes. The target is on the volume's magnitude: where
        the lattice mirrors space (the plain deformation turns a volume's sign), the mirrored
        shape keeps its size instead of being turned inside out to reach the rest volume's sign."""
        self.plain = volumes.copy()
        flip = (np.sign(volumes) * np.sign(self.targets)) < 0
        self.targets[flip] *= -1.0
        self.mirrored = bool(flip.any())

    def start(self, e):
        """Measure the plain deformation's volumes (along unit direction e) without a step."""
        self.volumes = self.measured(e)
        if self.plain is None:      # (a refused sweep noted it, and turned the targets, already)
            self._note_plain(self.volumes)

    def step(self, e, divisor, preserve_volume):
        """One closed-form correction along unit direction e; the volume rows ask for 1/divisor of
        what remains. Updates D (and X) and the measured volumes; returns the volumes before."""
        b = self.b
        axis, g, base = self.gradient(e)
        if axis is not None:
            e = _EYE[axis]  # -X corrects exactly as +X: t absorbs the sign
        alpha = self.alpha_rows(g) if preserve_volume else None
        before = self.volumes = self.measure(e, axis, g, base, alpha)
        if self.plain is None:
            self._note_plain(before)
        rows, rhs = [], []
        if preserve_volume:
            # A row is degenerate when its coefficients are negligible next to the total volume
            # flux sum |s_v g_v| along e (e.g. a pure translation, or every point immobile).
            flux = self.k.flux(g, *self._rows)
            weighted = alpha if self.mob is None else alpha * np.sqrt(self.mob)
            movable = _row_norms(weighted) > self.degenerate * flux
            volume_rows = np.flatnonzero(movable)
            for r in volume_rows:
                rows.append(alpha[r])
                rhs.append((self.targets[r] - before[r]) / divisor)
        if self.pin_rows is not None:
            x_pin = _mm(self.pin_rows, self.D) + b.x0[:, self.pin_slots].T
            rows.extend(self.pin_rows)
            rhs.extend(_mv(self.pin_targets - x_pin, e))
        if not rows:
            return before
        C = np.array(rows)
        r = np.array(rhs)
        CM = C if self.mob is None else C * self.mob
        gram = _mm(CM, C.T)
        if not (np.isfinite(gram).all() and np.isfinite(r).all()):
            raise ValueError(_OVERFLOW)   # (LAPACK may never return on NaN input)
        if len(r) == 1:
            # One row (the volume alone): lstsq of a 1 x 1 system is r / gram, or 0 where gram
            # is 0 (a singular value under any rcond); LAPACK's call costs more than the rest.
            lam = r / gram[0] if gram[0, 0] != 0.0 else np.zeros(1)
        else:
            lam = np.linalg.lstsq(gram, r, rcond=tol.GRAM_RCOND)[0]
        t = _mv(CM.T, lam)
        reach = float(np.abs(t).max()) if len(t) else 0.0
        if not np.isfinite(reach):
            raise ValueError(_OVERFLOW)
        if reach > tol.MAX_STEP_LATTICE * b.lattice.size:
            # Coefficients that are rounding noise (e.g. a mesh squashed flat across e) would fling
            # control points away: refuse the step rather than return a wrecked lattice.
            self.skipped.append(f"a correction along {np.round(e, 3).tolist()} would move lattice "
                                f"points by {reach / b.lattice.size:.3g} lattice sizes; it was skipped "
                                "(the deformed mesh is flat or nearly flat across that direction)")
            return before
        if preserve_volume:
            self.used[volume_rows] = True
        n_pins = len(self.pin_slots)
        if n_pins:
            missed = np.abs((_mv(C, t) - r)[len(r) - n_pins:]) > self.met_rel * b.lattice.size
            self.unmet_pins.update(self.pin_index[missed].tolist())
        self.move(e, axis, t)
        self.volumes = self.measure(e, axis, g, base, alpha)
        return before

    def move(self, e, axis, t):
        """Move the control points by t (N,) along unit direction e (`axis` when e is one)."""
        self.moves += 1
        if axis is not None:
            self.D[:, axis] += t
            self.P[:, axis] += t
            self.k.stale(axis)
        else:
            self.k.add_along(e, t)
            self.D += t[:, None] * e
            self.P += t[:, None] * e

    def sweep(self, dirs):
        """The first correction over islands: one joint linearised step (every direction at the
        same coordinates, as `joint`), applied one direction at a time. Along one direction the
        volume is exactly linear, so each direction after the first is re-solved at the
        coordinates the earlier ones left, for what the joint step planned for it (the last one
        for all that remains), starting from the planned move: only the change the earlier moves
        made to the coefficients is solved for. Returns False when there is nothing to do."""
        b = self.b
        self.gradients(dirs)
        N = b.lattice.n_points
        plan, grads = [], []
        for e in dirs:
            axis, g, base = self.gradient(e)
            e = _EYE[axis] if axis is not None else e
            grads.append((e, axis, g, base))
            plan.append(self.alpha_rows(g))
        e0, axis0, g0, base0 = grads[0]
        self.volumes = self.measure(e0, axis0, g0, base0, plan[0])
        if self.plain is None:
            self._note_plain(self.volumes)
        J = np.concatenate(plan, axis=1)
        usable = np.abs(J).max(axis=1, initial=0.0) > 0
        if not usable.any():
            return False
        self.used |= usable
        r = np.where(usable, self.targets - self.volumes, 0.0)
        mob = None if self.mob is None else np.tile(self.mob, len(dirs))
        t = _min_norm_step(J[usable], r[usable], mob)
        if not np.isfinite(t).all() or np.abs(t).max(initial=0.0) > tol.MAX_STEP_LATTICE * b.lattice.size:
            return False
        for d, ((e, axis, _, _), alpha_plan) in enumerate(zip(grads, plan)):
            u = t[d * N:(d + 1) * N]
            if d:
                axis_, g, base = self.gradient(dirs[d])
                alpha = self.alpha_rows(g)
                before = self.measure(e, axis, g, base, alpha)
                want = self.targets - before if d == len(dirs) - 1 else _mv(alpha_plan, u)
                miss = np.where(usable, want - _mv(alpha, u), 0.0)
                du = _min_norm_step(alpha[usable], miss[usable], self.mob, tol.SWEEP_RCOND)
                if np.isfinite(du).all() and np.abs(du).max(initial=0.0) <= tol.MAX_STEP_LATTICE * b.lattice.size:
                    u = u + du
            self.move(e, axis, u)
            if d == len(dirs) - 1 and axis is not None:
                self.volumes = before + _mv(alpha, u) if d else self.volumes + _mv(alpha_plan, u)
        if grads[-1][1] is None:    # (the last direction is no axis: its volumes are measured)
            self.gradients(dirs)
            self.volumes = self.measured(dirs[0])
        return True

    def joint(self, dirs, preserve_volume):
        """One Gauss-Newton step over all directions at once: the volume rows (one per island)
        linearised along every direction, the pin rows (exact: a pinned point is linear in the
        control points), all solved together, minimum-norm in the mobility metric. Returns False
        when there is nothing to do (no usable row, or an absurd step, which is refused)."""
        b = self.b
        blocks, grads = [], []
        self.gradients(dirs)
        for e in dirs:
            axis, g, base = self.gradient(e)
            e = _EYE[axis] if axis is not None else e
            grads.append((e, axis, g, base))
            blocks.append(self.alpha_rows(g) if preserve_volume else None)
        e0, axis0, g0, base0 = grads[0]
        self.volumes = self.measure(e0, axis0, g0, base0, blocks[0])
        rows, rhs = [], []
        N, m = b.lattice.n_points, len(dirs)
        if preserve_volume:
            J = np.concatenate(blocks, axis=1)                      # (k, m N)
            r = self.targets - self.volumes
            usable = np.abs(J).max(axis=1, initial=0.0) > 0
            self.used |= usable
            rows.extend(J[usable])
            rhs.extend(r[usable])
        if self.pin_rows is not None:
            x_pin = _mm(self.pin_rows, self.D) + b.x0[:, self.pin_slots].T
            for d, (e, _, _, _) in enumerate(grads):
                block = np.zeros((len(self.pin_rows), m * N))
                block[:, d * N:(d + 1) * N] = self.pin_rows
                rows.extend(block)
                rhs.extend(_mv(self.pin_targets - x_pin, e))
        if not rows:
            return False
        C, r = np.array(rows), np.array(rhs)
        t = _min_norm_step(C, r, None if self.mob is None else np.tile(self.mob, m))
        if not np.isfinite(t).all() or np.abs(t).max(initial=0.0) > tol.MAX_STEP_LATTICE * b.lattice.size:
            return False
        for d, (e, axis, _, _) in enumerate(grads):
            self.move(e, axis, t[d * N:(d + 1) * N])
        return True

    def pins_met(self):
        if self.pin_rows is None:
            return True
        x_pin = _mm(self.pin_rows, self.D) + self.b.x0[:, self.pin_slots].T
        return bool((np.abs(x_pin - self.pin_targets).max(1) <= self.met_rel * self.b.lattice.size).all())


def _mv(A, x):
    """A (k, n) @ x (n,) without BLAS: the OpenBLAS of NumPy 1.26 (Blender 4.2 to 5.0) runs even a
    (64, 216) product on its threads, which then spin for about a tenth of a second and take the
    cores from the next passes and from Blender (docs/performance.md, "Keep BLAS out of the
    frame"); `einsum` without `optimize` sums in its own loop."""
    return np.einsum("ij,j->i", A, x)


def _row_norms(A):
    """(k,) Euclidean norms of the rows of A (k, n): `np.linalg.norm(A, axis=1)` less its checks and
    dispatch (a solve asks on every step)."""
    return np.sqrt(np.einsum("ij,ij->i", A, A))


def _mm(A, B):
    """A (k, n) @ B (n, m) without BLAS (see `_mv`)."""
    return np.einsum("ij,jk->ik", A, B)


def _min_norm_step(C, r, mobility=None, rcond=tol.JACOBIAN_RCOND):
    """t (n,) with C t = r for C (k, n), r (k,), of least norm in the mobility metric
    (sum t_i^2 / mobility_i; mobility 0 keeps a coordinate fixed); least squares where the rows
    cannot all be met. Solved on C itself (an SVD of C W, W = sqrt(mobility)), not on the Gram
    matrix C W^2 C^T, which squares the condition number: island volume rows of nearby small
    bodies are nearly parallel (singular values spanning ~1e-7), and a cut on the squared values
    drops the very directions that separate them (docs/design.md, "Islands and pins")."""
    if not (np.isfinite(C).all() and np.isfinite(r).all()):
        raise ValueError(_OVERFLOW)   # (LAPACK may never return on NaN input)
    w = None if mobility is None else np.sqrt(mobility)
    CW = C if w is None else C * w
    u = min_norm(CW, r, rcond)
    if u is None:
        u = np.linalg.lstsq(CW, r, rcond=rcond)[0]
    return u if w is None else w * u


def _volumes(b, verts, islands):
    """(k,) float64 volumes of `verts` (V, 3), per island or in total, about the binding's origins."""
    rel = verts - b.origins(np.arange(b.n_verts))
    face = face_volumes(np.ascontiguousarray(rel.T), b.topology.tris_t)
    if islands:
        return np.bincount(b.topology.face_island, face, b.n_islands)
    return np.array([face.sum()])


def solve(binding, points, axes="XYZ", directions=None, volume_scale=1.0, preserve_volume=True,
          mobility=None, pins=(), islands=False, steps=None, target_volumes=None):
    """Volume-preserving FFD of `binding` for control points `points` (N, 3).

    axes: correction directions as a string of distinct letters from "XYZ" (lattice axes), applied
        in that order; or directions: (m, 3) rows (normalised here), e.g. world axes in lattice space.
    volume_scale: target volume as a multiple of the rest volume (per island with islands=True).
    target_volumes: the volume to keep instead of the rest volume, in the binding's space: one
        number, or (n_islands,) with islands=True (e.g. the volume a mesh had when it was bound,
        before an Armature changed it); volume_scale multiplies it.
    preserve_volume: False turns off the volume rows (plain direct manipulation with pins).
    mobility: (N,) in [0, 1], how freely each control point may move (0 keeps it fixed; Remark 2).
    pins: (vertex index, (x, y, z) target) pairs; each pinned vertex lands on its target along the
        correction directions (Problem 2, eq. 21, any number of pins).
    islands: keep the volume of each connected component separately.
    steps: a callable ``steps(binding)`` giving the per-slot work (default
        `backends.default_steps`: the compiled steps once `compiled.load()` succeeded, else
        `steps.NumpySteps`; or the GPU's);
        options it cannot do raise ValueError before anything is computed.
    Returns a `Solution`. Raises ValueError for bad input, or when the volume must change but cannot
    along any direction; never returns NaN.
    """
    t0 = time.perf_counter()
    b = binding
    b.displacements(points)  # validates shape and finiteness
    dirs = parse_directions(axes, directions)
    scale = float(volume_scale)
    if not np.isfinite(scale) or scale < 0:
        raise ValueError(f"volume_scale must be finite and >= 0, got {volume_scale!r}")
    mob = _check_mobility(mobility, b.lattice.n_points)
    pin_slots, pin_targets, pin_index = _check_pins(pins, b)
    if len(dirs) == 0 and (preserve_volume or len(pin_slots)):
        raise ValueError("no correction directions: give axes (e.g. 'XYZ') or directions")

    caps = getattr(steps, "capabilities", CAPABILITIES)
    needs = {"directions": any(np.count_nonzero(e) != 1 for e in dirs), "islands": bool(islands),
             "plain_measure": not preserve_volume or not len(dirs)}
    missing = [what for what, needed in needs.items() if needed and what not in caps]
    if missing:
        raise ValueError(f"these solve steps cannot do {', '.join(missing)}")
    base = b.rest_island_volumes if islands else np.array([b.rest_volume])
    if target_volumes is not None:
        given = np.asarray(target_volumes, dtype=np.float64).reshape(-1)
        if given.shape != base.shape:
            raise ValueError(f"target_volumes must hold {len(base)} volume{'s' if len(base) > 1 else ''} "
                             f"({'one per island' if islands else 'the total'}), got {given.size}")
        if not np.isfinite(given).all():
            raise ValueError("target_volumes must be finite")
        base = given
    targets = scale * base
    if not np.isfinite(targets).all():
        raise ValueError(f"volume_scale {volume_scale!r} makes the target volume overflow")
    st = _State(b, points, mob, (pin_slots, pin_targets, pin_index), bool(islands), targets, steps)

    m = len(dirs)
    # Several island volumes share control points in every direction: one closed-form step per
    # direction would ask each direction alone to serve all of them (large, needless moves), so
    # they are solved jointly over all directions from the start. One volume keeps the exact
    # sequential closed form (the paper's).
    jointly = bool(islands) and preserve_volume and m > 0
    if m and not jointly:
        for d, e in enumerate(dirs):
            st.step(e, m - d, preserve_volume)
        plain = st.plain            # what the first step measured before moving anything
    elif jointly:
        st.in_float64()
        if len(pin_slots) or not st.sweep(dirs):
            st.gradients(dirs)
            st.start(dirs[0])
        plain = st.plain
    else:
        e = _EYE[0]
        plain = st.volumes = st.measure(e, *st.gradient(e), None)
    warnings = []
    if preserve_volume and m and not jointly and not st.volume_met().all():
        # Directions skipped as degenerate left their share: finish along the usable ones.
        for e in dirs:
            st.step(e, 1, preserve_volume)
            if st.volume_met().all():
                break
    if m and (islands or len(pin_slots)) and not (st.volume_met().all() and st.pins_met()):
        # Several volume rows (islands) or pins compete for the same control points along one
        # direction at a time; solved jointly over all directions, and iterated (each volume is
        # cubic in simultaneous moves), they meet wherever the lattice has the freedom.
        for _ in range(_JOINT_ITERATIONS):
            if not st.joint(dirs, preserve_volume):
                break
            st.gradients(dirs)      # the next step's, measured with
            st.volumes = st.measured(dirs[0])
            done = (not preserve_volume or st.volume_met().all()) and st.pins_met()
            if done:
                st.unmet_pins.clear()
                break
        if st.pins_met():
            st.unmet_pins.clear()
    if preserve_volume and m and not st.volume_met().all():
        unmet = ~st.volume_met()
        if unmet.any():
            if not st.used.any():
                raise ValueError("the volume cannot change along any of the correction directions "
                                 "(no lattice influence, all mobility 0, or a lattice with one point per axis)")
            miss = np.abs(st.volumes - st.targets) / np.maximum(np.abs(st.targets), 1e-300)
            if islands:
                worst = np.flatnonzero(unmet)[np.argsort(-miss[unmet])]
                listed = ", ".join(f"{i} ({miss[i]:.2g})" for i in worst[:8])
                more = f" and {len(worst) - 8} more" if len(worst) > 8 else ""
                what = f"the volume of islands {listed}{more} (relative miss)"
            else:
                what = f"the volume (missed by {float(miss[0]):.2g} of the target)"
            if islands and st.k.float32:
                # Not the lattice's fault as far as anyone knows: float32 coordinates of a small
                # body round at about 1e-7 of the lattice's size (steps with `in_float64` avoid it).
                warnings.append(f"{what} could not be met in float32 arithmetic (bodies this small need "
                                "the compiled kernels, which solve islands in float64)")
            else:
                warnings.append(f"{what} could not reach the target along the given directions")
    if preserve_volume and m:
        noise = b.rest_volume_noise if islands else np.array([b.rest_volume_noise.sum()])
        met_rel = tol.MET_REL_F32 if b.dtype == np.float32 else tol.MET_REL_F64   # the stored precision's
        if (noise > met_rel * st.vol_scale).any():
            warnings.append(f"the volume is below the rounding of its terms in {b.dtype.name} (the mesh is "
                            "tiny, or open and far from the lattice centre): it is kept only to about "
                            f"{float((noise / st.vol_scale).max()):.0e} of itself")
    if warnings or st.unmet_pins:
        # A refused step matters only when its share was not made up by the other directions.
        warnings.extend(dict.fromkeys(st.skipped))
    if st.unmet_pins:
        warnings.append(f"pins on vertices {sorted(st.unmet_pins)} could not reach their targets "
                        "(conflicting pins, immobile control points or missing directions)")
    if st.mirrored:
        warnings.append("the lattice mirrors space here: the mirrored shape keeps the size of the "
                        "volume (its sign turns with it)")
    P_in = np.asarray(points, dtype=np.float64)
    reach = float(_row_norms(st.P - P_in).max()) if len(P_in) else 0.0
    if reach > b.lattice.diagonal:
        # A correction this large is no correction but a different shape (a lattice flattened
        # across a direction, a fold): show the plain deformation and say why.
        warnings = [f"the correction was refused: it would move lattice points by "
                    f"{reach / b.lattice.diagonal:.3g} times the lattice's diagonal (the lattice is "
                    "flat or folded along the correction directions); the plain deformation is shown"]
        st = _State(b, points, mob, (pin_slots, pin_targets, pin_index), bool(islands), targets, steps)
        # Measured again in float64 from the positions: a lattice this distorted makes the
        # gradient's float32 terms cancel far beyond what the shape's own rounding allows.
        st.volumes = _volumes(b, st.k.verts(st.D), bool(islands))
        plain = st.volumes
    verts = st.k.verts(st.D)
    if not (st.k.finite(verts) and np.isfinite(st.P).all()
            and np.isfinite(st.volumes).all() and np.isfinite(plain).all()):
        raise ValueError(_OVERFLOW)

    total = float(st.volumes.sum())
    return Solution(
        verts=verts, points=st.P, volume=total, target_volume=float(targets.sum()),
        plain_volume=float(plain.sum()), directions=dirs,
        island_volumes=st.volumes.copy() if islands else None,
        island_target_volumes=targets if islands else None,
        warnings=tuple(warnings), seconds=time.perf_counter() - t0, backend=getattr(st.k, "backend", None))
