"""Compiled kernels of a lattice bind: the per-axis basis weights, the block layout of the weights
and the slot-ordered coordinates, faces and face volumes (docs/performance.md, "Re-embedding").

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
    def axis_taps(x, n, lo, hi, kind, fc, first, w, cell, tt):
        # One axis of `bases.axis_taps` for a local kind (n >= 2): first (V,) int64 and w (V, 4)
        # float64 written in place. Blender's clamped taps are folded onto offsets 0..3 of `first`.
        # Also the unclamped cell (V,) int64 and t (V,) float64 of `bases.axis_cells`.
        du = (hi - lo) / (n - 1)
        top = n + 2.0
        sixth = 1.0 / 6.0
        fold = np.zeros(4)
        for v in range(x.shape[0]):
            u = (x[v] - lo) / du
            if u < -3.0:
                u = -3.0
            elif u > top:
                u = top
            fi = np.floor(u)
            t = u - fi
            i = int(fi)
            cell[v] = i
            tt[v] = t
            if kind == 0:
                w0, w1, w2, w3 = 0.0, 1.0 - t, t, 0.0
            elif kind == 2:
                t2 = t * t
                t3 = t2 * t
                s = 1.0 - t
                w0 = s * s * s * sixth
                w1 = (3.0 * t3 - 6.0 * t2 + 4.0) * sixth
                w2 = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) * sixth
                w3 = t3 * sixth
            else:
                t2 = t * t
                t3 = t2 * t
                w0 = -fc * t3 + 2.0 * fc * t2 - fc * t
                w1 = (2.0 - fc) * t3 + (fc - 3.0) * t2 + 1.0
                w2 = (fc - 2.0) * t3 + (3.0 - 2.0 * fc) * t2 + fc * t
                w3 = fc * t3 - fc * t2
            f = min(max(i, 0), n - 1) - 1
            first[v] = f
            if i < 1 or i > n - 3:
                for k in range(4):
                    fold[k] = 0.0
                fold[min(max(i - 1, 0), n - 1) - f] += w0
                fold[min(max(i, 0), n - 1) - f] += w1
                fold[min(max(i + 1, 0), n - 1) - f] += w2
                fold[min(max(i + 2, 0), n - 1) - f] += w3
                for k in range(4):
                    w[v, k] = fold[k]
            else:
                w[v, 0] = w0
                w[v, 1] = w1
                w[v, 2] = w2
                w[v, 3] = w3

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
    def block_weights(sorted_slot, shift, wu, wv, ww, s, wuv, wws, influence, cast):
        # The weights in the (n_blocks, K, 2**shift) layout of the slots `slots` gives
        # (sorted_slot), from the taps wu, wv, ww (V, K) and influences s (V,) of the vertices in
        # sorted order (read in order: gathering them through the sort's permutation cost twice
        # as much): wuv = Wv * Wu with both factors first rounded to the binding's precision
        # (through `cast`, 8 values of it), as NumPy's per-block gathers and product do;
        # ww = (w * s) in float64, then rounded.
        Ku = wu.shape[1]
        Kv = wv.shape[1]
        Kw = ww.shape[1]
        mask = (1 << shift) - 1
        for v in range(sorted_slot.shape[0]):
            sl = sorted_slot[v]
            blk = sl >> shift
            pos = sl & mask
            for k in range(Ku):
                cast[k] = wu[v, k]
            for k in range(Kv):
                cast[4 + k] = wv[v, k]
            for kv in range(Kv):
                for ku in range(Ku):
                    wuv[blk, kv * Ku + ku, pos] = cast[4 + kv] * cast[ku]
            for k in range(Kw):
                wws[blk, k, pos] = ww[v, k] * s[v]
            influence[sl] = s[v]

    @njit
    def slot_coords(slot, rel, coords, x0):
        # coords (3, n_slots) float64 and x0 (3, n_slots) in the binding's precision, from the
        # coordinates relative to the volume origins rel (V, 3); padding slots stay zero.
        for v in range(slot.shape[0]):
            sl = slot[v]
            for c in range(3):
                coords[c, sl] = rel[v, c]
                x0[c, sl] = rel[v, c]

    @njit
    def face_layout(slot, tris_t, shift, n_blocks, coords, edges, corners, face_order, face_vol,
                    face_island, island_vol, island_abs):
        # Faces as slot triples ordered by the block of their lowest slot (a stable counting
        # sort: ties keep the faces' own order), and their float64 volume terms about the
        # origin, as `volume.face_volumes`. Blocks hold 2**shift slots. The faces are cut into
        # parts at `edges` (k + 1,); part j is stored as a contiguous (3, F_j) array at
        # corners[3 edges[j]:3 edges[j + 1]] (flat), ready for the worker threads. The volume
        # terms are summed per island (face_island (F,) in the faces' own order) in sorted face
        # order, into island_vol and, as absolute values, island_abs: NumPy's bincount order.
        F = tris_t.shape[1]
        start = np.zeros(n_blocks + 1, np.int64)
        block = np.empty(F, np.int64)
        for f in range(F):
            a = slot[tris_t[0, f]]
            b = slot[tris_t[1, f]]
            c = slot[tris_t[2, f]]
            block[f] = min(min(a, b), c) >> shift
            start[block[f] + 1] += 1
        for k in range(n_blocks):
            start[k + 1] += start[k]
        n_parts = edges.shape[0] - 1
        for f in range(F):
            p = start[block[f]]
            start[block[f]] += 1
            face_order[p] = f
            part = 0
            while p >= edges[part + 1]:
                part += 1
            width = edges[part + 1] - edges[part]
            at = 2 * edges[part] + p
            for k in range(3):
                corners[at + k * width] = slot[tris_t[k, f]]
        for part in range(n_parts):
            lo = edges[part]
            width = edges[part + 1] - lo
            for p in range(lo, lo + width):
                at = 2 * lo + p
                a = corners[at]
                b = corners[at + width]
                c = corners[at + 2 * width]
                x0, y0, z0 = coords[0, a], coords[1, a], coords[2, a]
                x1, y1, z1 = coords[0, b], coords[1, b], coords[2, b]
                x2, y2, z2 = coords[0, c], coords[1, c], coords[2, c]
                vol = (x0 * (y1 * z2 - z1 * y2)
                       + y0 * (z1 * x2 - x1 * z2)
                       + z0 * (x1 * y2 - y1 * x2)) / 6.0
                face_vol[p] = vol
                island = face_island[face_order[p]]
                island_vol[island] += vol
                island_abs[island] += abs(vol)

    return {"axis_taps": axis_taps, "slots": slots, "block_weights": block_weights, "slot_coords": slot_coords,
            "face_layout": face_layout}
