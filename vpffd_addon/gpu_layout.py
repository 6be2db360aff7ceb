"""The arrays the GPU path uploads for a lattice binding, built here in NumPy so that their
layout is tested without Blender (docs/design.md, "The GPU dispatch plan").

Every array is flat, in the order its kernel reads it:

- per slot: ``x0`` (n_slots, 3) rest coordinates; ``wuv`` (n_slots * Kuv) and ``ww``
  (n_slots * Kw) the factored weights, slot-major; ``s`` the influence;
- ``block_run`` (n_blocks) and ``run_idx`` (n_runs * Kw * Kuv): a block's run, a run's points;
- the one-ring CSR: ``ring_start`` (n_slots + 1) and ``ring`` (corners, 2): for every face
  corner owned by a slot, the face's two other corners in cyclic order, grouped by slot (stable:
  a slot's faces keep the binding's order), so the gradient at a slot is a gather;
- the control-point CSR: ``cp_start`` (N + 1) and ``cp_piece``: the (block, tap) pieces that land
  on each control point, in (block, tap) order, so the transposed product is a fixed-order sum;
- ``slot`` (V): the slot of each vertex.
"""
import numpy as np


def gpu_layout(b):
    """The GPU arrays of a lattice `Binding` `b` (see the module docstring): a dict."""
    if not hasattr(b, "ww"):
        raise ValueError("the GPU layout is for Lattice bindings (a cage binding has none)")
    n_slots = b.x0.shape[1]
    corners = (np.concatenate(b.corner_parts, axis=1) if b.corner_parts
               else np.zeros((3, 0), np.int64))
    owner = corners.ravel()
    others = np.stack([np.concatenate([corners[1], corners[2], corners[0]]),
                       np.concatenate([corners[2], corners[0], corners[1]])], 1)
    order = np.argsort(owner, kind="stable")
    ring_start = np.zeros(n_slots + 1, np.int64)
    np.cumsum(np.bincount(owner, minlength=n_slots), out=ring_start[1:])
    pieces_cp = b.run_idx[b.block_run].reshape(-1)          # the control point of piece j
    cp_order = np.argsort(pieces_cp, kind="stable")
    N = b.lattice.n_points
    cp_start = np.zeros(N + 1, np.int64)
    np.cumsum(np.bincount(pieces_cp, minlength=N), out=cp_start[1:])
    return {
        "x0": np.ascontiguousarray(b.x0.T), "wuv": b.wuv.transpose(0, 2, 1).reshape(-1),
        "ww": b.ww.transpose(0, 2, 1).reshape(-1), "s": b.slot_influence,
        "block_run": b.block_run, "run_idx": b.run_idx.reshape(-1), "slot": b.slot,
        "ring_start": ring_start, "ring": others[order], "cp_start": cp_start, "cp_piece": cp_order,
    }
