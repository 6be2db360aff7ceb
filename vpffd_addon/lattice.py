"""The lattice: resolution, per-axis interpolation and the box its rest grid spans."""
import numpy as np

from .bases import INTERPOLATIONS, tap_count


class Bounded:
    """`centre` and `size` of anything with `lo` and `hi` (3,) bounds: a lattice or a cage."""

    @property
    def centre(self):
        """(3,) centre of the bounds; volumes of open meshes are measured about it."""
        return 0.5 * (self.lo + self.hi)

    @property
    def diagonal(self):
        """Length of the bounds' diagonal: the most a correction may move a control point."""
        return float(np.linalg.norm(self.hi - self.lo)) or 1.0

    @property
    def size(self):
        """Largest extent of the bounds (1.0 when there is no extent): the length scale."""
        extent = float((self.hi - self.lo).max())
        return extent if extent > 0 else 1.0


class Lattice(Bounded):
    """A regular control grid in its own (lattice) space, as Blender's Lattice data.

    shape: (nu, nv, nw) points per axis, each >= 1.
    interpolation: one name or three (per axis) from `INTERPOLATIONS`; Blender's
        ``KEY_LINEAR`` style names are accepted too.
    bounds: ((lo_x, lo_y, lo_z), (hi_x, hi_y, hi_z)), the box the rest grid spans. An axis with one
        point sits at (lo + hi) / 2 and needs no extent; other axes need hi > lo.
    """

    def __init__(self, shape, interpolation=("BSPLINE",) * 3, bounds=((-0.5,) * 3, (0.5,) * 3)):
        shape = tuple(shape) if np.ndim(shape) else (shape,)
        if len(shape) != 3:
            raise ValueError(f"lattice shape must have 3 entries (nu, nv, nw), got {shape!r}")
        for axis, n in zip("uvw", shape):
            if isinstance(n, bool) or not float(n).is_integer() or n < 1:
                raise ValueError(f"lattice shape: {axis} resolution must be an integer >= 1, got {n!r}")
        self.shape = tuple(int(n) for n in shape)

        if isinstance(interpolation, str):
            interpolation = (interpolation,) * 3
        interpolation = tuple(interpolation)
        if len(interpolation) != 3:
            raise ValueError(f"interpolation needs one name or three (u, v, w), got {interpolation!r}")
        names = []
        for name in interpolation:
            key = str(name).upper()
            key = key[4:] if key.startswith("KEY_") else key
            if key not in INTERPOLATIONS:
                raise ValueError(f"unknown interpolation {name!r}; expected one of {', '.join(INTERPOLATIONS)}")
            names.append(key)
        self.interpolation = tuple(names)

        lo, hi = (np.array(b, dtype=np.float64).reshape(3) for b in bounds)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise ValueError(f"lattice bounds must be finite, got lo={lo}, hi={hi}")
        for a, n in enumerate(self.shape):
            if n > 1 and not hi[a] > lo[a]:
                raise ValueError(f"lattice bounds: axis {'xyz'[a]} has {n} points but hi ({hi[a]}) <= lo ({lo[a]})")
        self.lo, self.hi = lo, hi

    @property
    def n_points(self):
        """Number of control points N = nu * nv * nw."""
        return self.shape[0] * self.shape[1] * self.shape[2]

    @property
    def taps(self):
        """(Ku, Kv, Kw): control points per axis that one vertex depends on."""
        return tuple(tap_count(n, k) for n, k in zip(self.shape, self.interpolation))

    def axis_coords(self, axis):
        """(n,) rest coordinates of the grid along `axis` (0, 1, 2)."""
        n = self.shape[axis]
        if n == 1:
            return np.array([self.centre[axis]])
        return np.linspace(self.lo[axis], self.hi[axis], n)

    @property
    def rest_points(self):
        """(N, 3) rest grid, u fastest, then v, then w (Blender's point order); read-only, made
        once per lattice (a solve asks for it several times: docs/performance.md)."""
        got = self.__dict__.get("_rest_points")
        if got is None:
            cu, cv, cw = (self.axis_coords(a) for a in range(3))
            w, v, u = np.meshgrid(cw, cv, cu, indexing="ij")
            got = np.stack([u.ravel(), v.ravel(), w.ravel()], 1)
            got.flags.writeable = False
            self._rest_points = got
        return got

    def outside_count(self, verts):
        """How many of `verts` (V, 3) (lattice space) lie outside the lattice's box, beyond a
        millionth of its size (an axis with a single point has no extent to be outside of)."""
        v = np.asarray(verts, dtype=np.float64)
        eps = 1e-6 * self.size
        spans = np.flatnonzero(np.array(self.shape) > 1)
        out = np.zeros(len(v), bool)
        for a in spans:
            col = v[:, a]
            out |= (col < self.lo[a] - eps) | (col > self.hi[a] + eps)
        return int(out.sum())

    def __repr__(self):
        return (f"Lattice(shape={self.shape}, interpolation={self.interpolation}, "
                f"bounds=({tuple(self.lo)}, {tuple(self.hi)}))")
