"""The per-slot work of a solve, in NumPy: what `solve.solve` asks of a binding, behind one
interface that the GPU path (`operators/gpu_backend.py`) supplies with compute shaders too.

`solve` keeps the control-point displacements D (N, 3), the closed forms, shares, warnings and
errors; a steps object keeps the slot coordinates ``X = x0 + S B D`` (3, n_slots) and turns them
into what the closed forms need (docs/design.md, "The closed form"):

- `refresh(components, D)`: bring those components of X up to date with D;
- `stale(axis)`: D changed along `axis` (X[axis] must be refreshed before it is used);
- `axis_gradient(axis, D)`: the volume gradient g along a lattice axis (an opaque handle);
- `direction_gradient(p, q, D)`: the same along any direction completed by (p, q) (capability
  `directions`);
- `x0_dot(axis, g, rows)` and `flux(g, rows)`: per volume row, ``sum x0_axis * g`` and
  ``sum |s g|``; `x_dot(e, axis, g, rows)`: ``sum (e . X) * g`` (capability `plain_measure`);
- `transpose(g, rows)`: the rows ``(S B)^T g`` (k, N) float64, one per volume row (k > 1:
  capability `islands`);
- `add_along(e, t)`: X += e * (S B t) for a direction that is no axis;
- `verts(D)`: the deformed vertices (V, 3) float64 in lattice space; `finite()`.

`rows` is None for one volume row, else the (n_slots,) volume row of every slot. `float32`: the
precision the steps compute in (tolerances follow it). `Steps` keeps the bookkeeping both kinds
share (which components are fresh); a kind supplies the computations.
"""
import numpy as np

#: What NumPy steps can do; a GPU steps object lists fewer.
CAPABILITIES = frozenset({"directions", "islands", "plain_measure"})


class Steps:
    """What every kind of steps shares: which components of X are up to date with D, and the
    axis gradient from the two components that complete the axis. A kind supplies
    `_forward(components, D)` (those components of X, recomputed) and `_gradient(a1, a2)`."""

    def __init__(self):
        self.fresh = [False, False, False]

    def refresh(self, components, D):
        stale = [c for c in components if not self.fresh[c]]
        if stale:
            self._forward(stale, D)
            for c in stale:
                self.fresh[c] = True

    def stale(self, axis):
        self.fresh[axis] = False

    def axis_gradient(self, axis, D):
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3
        self.refresh((a1, a2), D)
        return self._gradient(a1, a2)


class NumpySteps(Steps):
    """The steps on the CPU, for a `Binding` or a `CageBinding`."""

    capabilities = CAPABILITIES
    backend = "NUMPY"       #: the name its backend is registered under (`backends.py`)

    def __init__(self, binding):
        super().__init__()
        self.b = binding
        self.float32 = binding.dtype == np.float32
        self.X = binding.x0.copy()

    def _forward(self, components, D):
        for c, field in zip(components, self.b.forward_many(D[:, components].T)):
            self.X[c] = self.b.x0[c] + field

    def _gradient(self, a1, a2):
        return self.b.gradient_of(self.X[a1], self.X[a2])

    def direction_gradient(self, p, q, D):
        self.refresh((0, 1, 2), D)
        return self.b.gradient(self.b.gather(p @ self.X), self.b.gather(q @ self.X))

    @staticmethod
    def _split(values, rows, k):
        if rows is None:
            return np.array([values.sum()])
        return np.bincount(rows, values, k)

    def x0_dot(self, axis, g, rows, k=1):
        return self._split(self.b.x0[axis] * g, rows, k)

    def x_dot(self, e, axis, g, rows, k=1, D=None):
        if axis is None:
            return self._split((e @ self.X) * g, rows, k)
        self.refresh((axis,), D)
        return self._split(self.X[axis] * g, rows, k)

    def flux(self, g, rows, k=1):
        return self._split(np.abs(g * self.b.slot_influence), rows, k)

    def transpose(self, g, rows, k=1):
        if rows is None:
            return self.b.transpose(g)[None]
        return self.b.island_transpose(g, k)

    def add_along(self, e, t):
        self.X += (e[:, None] * self.b.forward(t)).astype(self.X.dtype)

    def verts(self, D):
        self.refresh((0, 1, 2), D)
        return self.b.to_verts(self.X)

    def finite(self, verts=None):
        """Whether the slots' coordinates, and `verts` (what `verts` returned) where given, are
        all finite."""
        return bool(np.isfinite(self.X).all() and (verts is None or np.isfinite(verts).all()))
