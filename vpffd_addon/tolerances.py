"""Shared numerical tolerances (relative unless stated otherwise)."""

#: A correction direction is unusable when the norm of its volume coefficients is below this
#: fraction of the total absolute volume flux along it (float64 bindings).
DEGENERATE_REL_F64 = 1e-9
#: The same for float32 bindings, whose gradients carry ~1e-7 rounding per term.
DEGENERATE_REL_F32 = 1e-6

#: Relative cut-off for the small (k x k) constraint systems: singular values below this
#: fraction of the largest are treated as zero (least-squares / minimum-norm answer).
GRAM_RCOND = 1e-12

#: Relative cut-off for the joint Gauss-Newton step, applied to the singular values of the
#: constraint matrix itself (not squared): independent island rows of nearby small bodies reach
#: ~1e-7 of the largest; rows equal to rounding are dropped.
JACOBIAN_RCOND = 1e-10

#: Relative cut-off for the per-axis re-solves of the islands' first move (`solve._State.sweep`):
#: they correct what the earlier axes changed, a second-order amount, and the rows of nearby
#: small bodies along one axis alone are nearly parallel, where that amount would be amplified
#: into moves of lattice sizes; directions this weak are left to the joint steps, which separate
#: such bodies over all axes at once.
SWEEP_RCOND = 1e-4

#: A constraint counts as met when its residual is below this fraction of its scale
#: (volume rows: the target volume; pin rows: the lattice size).
MET_REL_F64 = 1e-9
MET_REL_F32 = 1e-5

#: A single correction step may move control points by at most this many lattice sizes; beyond,
#: its coefficients are rounding noise (a mesh squashed flat across the direction) and it is skipped.
MAX_STEP_LATTICE = 100.0
