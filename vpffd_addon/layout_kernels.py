"""Compiled kernels of a lattice bind: the per-axis taps and cells, the slots, the per-slot
parameters of the compiled solve, the slot-ordered coordinates and the faces' volume terms
(docs/performance.md, "Re-embedding").

A mesh that moves through the lattice is embedded anew on every frame, so these passes are
per-frame work. Each kernel is one serial loop that writes its output in place and computes every
value with the same operations, in the same order and precision, as the NumPy code in
`bases.axis_taps`, `binding.bind_lattice`, `binding.slot_faces` and `volume.face_volumes`: a binding
made with them is bit for bit the one NumPy makes (the tests compare every array).

`define(njit)` returns the kernels by name; `compiled.py` compiles them with its own options.
Nothing here imports numba.
"""
import numpy as np

#: Kind codes of the local (four-tap) interpolations for the `axis_taps` kernel.
KIND_CODES = {"LINEAR": 0, "CARDINAL": 1, "CATMULL_ROM": 1, "BSPLINE": 2}


def define(njit):
    """The kernels, compiled by `njit`: {name: function}."""

    @njit
    def slots(order, run_start, run_len, first_block, bs, slot, sorted_slot):
        # The slot of every vertex (slot, by vertex) and of every sorted position (sorted_slot):
        # runs cut into blocks of bs. Counters, not j // bs and j % bs: an integer division per
        # vertex would cost more than the rest.
        for r in range(run_start.shape[0]):
            blk = first_block[r]
            pos = 0
            for j in range(run_len[r]):
                if pos == bs:
                    blk += 1
                    pos = 0
                i = run_start[r] + j
                sorted_slot[i] = slot[order[i]] = blk * bs + pos
                pos += 1

    @njit
    def slot_params(slot, tu, tv, tw, s, params, influence):
        # The compiled solve's per-slot parameters (4, n_slots): each vertex's t along the three
        # axes and its influence s, in the binding's precision, at its slot; influence (n_slots,).
        for v in range(slot.shape[0]):
            sl = slot[v]
            params[0, sl] = tu[v]
            params[1, sl] = tv[v]
            params[2, sl] = tw[v]
            params[3, sl] = s[v]
            influence[sl] = s[v]

    @njit
    def slot_coords(slot, rel, x0):
        # x0 (3, n_slots) in the binding's precision, from the coordinates relative to the volume
        # origins rel (V, 3); padding slots stay zero.
        for v in range(slot.shape[0]):
            sl = slot[v]
            for c in range(3):
                x0[c, sl] = rel[v, c]

    @njit
    def face_volumes(rel, tris_t, face_vol, f0, f1):
        # The float64 volume terms of faces f0..f1-1 about the origin, as `volume.face_volumes`,
        # from the vertices' coordinates rel (V, 3) (in the mesh's own order, whose faces mostly
        # address nearby vertices).
        for f in range(f0, f1):
            a = tris_t[0, f]
            b = tris_t[1, f]
            c = tris_t[2, f]
            x0, y0, z0 = rel[a, 0], rel[a, 1], rel[a, 2]
            x1, y1, z1 = rel[b, 0], rel[b, 1], rel[b, 2]
            x2, y2, z2 = rel[c, 0], rel[c, 1], rel[c, 2]
            face_vol[f] = (x0 * (y1 * z2 - z1 * y2)
                           + y0 * (z1 * x2 - x1 * z2)
                           + z0 * (x1 * y2 - y1 * x2)) / 6.0

    @njit
    def axis_cells(x, n, lo, hi, cell, tt):
        # `bases.axis_cells` for one local axis (n >= 2): the unclamped cell (V,) int64 and t (V,).
        du = (hi - lo) / (n - 1)
        top = n + 2.0
        for v in range(x.shape[0]):
            u = (x[v] - lo) / du
            if u < -3.0:
                u = -3.0
            elif u > top:
                u = top
            fi = np.floor(u)
            cell[v] = int(fi)
            tt[v] = u - fi

    return {"slots": slots, "slot_params": slot_params, "slot_coords": slot_coords,
            "face_volumes": face_volumes, "axis_cells": axis_cells}
