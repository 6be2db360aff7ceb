"""Compiled kernels of a lattice bind: the per-axis cells, the slots, what every slot holds (the
compiled solve's per-slot parameters, the influence, the rest coordinates) and the faces' volume
terms (docs/performance.md, "Re-embedding").

A mesh that moves through the lattice is embedded anew on every frame, so these passes are
per-frame work. The per-vertex, per-slot and per-face kernels loop over a range of their elements
(`layout.py` hands every worker thread its part); each kernel writes its output in place and
computes every value with the same operations, in the same order and precision, as the NumPy code in
`bases.axis_cells`, `binding.bind_lattice`, `binding.slot_faces` and `volume.face_volumes`: a binding
made with them is bit for bit the one NumPy makes (the tests compare every array).

`define(njit)` returns the kernels by name; `compiled.py` compiles them with its own options.
Nothing here imports numba.
"""
import numpy as np

#: The local (four-tap) interpolations, whose binds these kernels lay out (the compiled solve
#: computes their weights, `solve_kernels.constants`).
LOCAL_KINDS = ("LINEAR", "CARDINAL", "CATMULL_ROM", "BSPLINE")


def define(njit):
    """The kernels, compiled by `njit`: {name: function}."""

    @njit
    def slots(order, run_start, run_len, first_block, bs, slot, sorted_slot, r0, r1):
        # The slot of every vertex (slot, by vertex) and of every sorted position (sorted_slot)
        # of runs r0..r1-1: runs cut into blocks of bs. Counters, not j // bs and j % bs: an
        # integer division per vertex would cost more than the rest.
        # (Here and below every array read or written in order is a slice indexed from 0: numba
        # checks an index from a start known only at run time for a negative value, which costs
        # in every pass and keeps LLVM from vectorising; docs/performance.md, "Indices numba can
        # trust".)
        firsts, starts, lens = first_block[r0:r1], run_start[r0:r1], run_len[r0:r1]
        for r in range(firsts.shape[0]):
            blk = firsts[r]
            pos = 0
            a = starts[r]
            run_order = order[a:a + lens[r]]
            run_slots = sorted_slot[a:a + lens[r]]
            for j in range(run_order.shape[0]):
                if pos == bs:
                    blk += 1
                    pos = 0
                run_slots[j] = slot[run_order[j]] = blk * bs + pos
                pos += 1

    @njit
    def sorted_values(order, sorted_slot, verts, origin, rows, s, shape, lo, hi, eps, params, influence, x0, i0, i1):
        # Everything a slot holds, written in slot order from the vertices taken in sorted order
        # (positions i0..i1-1 of it: a worker thread's part)
        # (a row read each, where writing at scattered slots would touch a line per row of the
        # outputs): the compiled solve's per-slot parameters (4, n_slots) (t along each axis, as
        # `bases.axis_cells`, and the influence s), the influence (n_slots,) and the rest
        # coordinates x0 (3, n_slots) relative to the volume origins (origin (k, 3), rows (V,)
        # the row of each vertex, or empty for origin[0]: the subtraction that `cell_keys` makes,
        # so the same values, without reading its rows of 24 bytes from a second array at every
        # scattered vertex), in the binding's precision. Returns how many vertices lie outside
        # the lattice's box by more than eps, as `Lattice.outside_count` (an axis of one point
        # has no outside), in the part.
        outside = 0
        single = rows.shape[0] == 0
        du0 = (hi[0] - lo[0]) / (shape[0] - 1)
        du1 = (hi[1] - lo[1]) / (shape[1] - 1)
        du2 = (hi[2] - lo[2]) / (shape[2] - 1)
        part_order, part_slots = order[i0:i1], sorted_slot[i0:i1]
        for i in range(part_order.shape[0]):
            v = part_order[i]
            sl = part_slots[i]
            r = 0 if single else rows[v]
            out = False
            for a in range(3):
                x = verts[v, a]
                if shape[a] > 1 and (x < lo[a] - eps or x > hi[a] + eps):
                    out = True
                du = du0 if a == 0 else (du1 if a == 1 else du2)
                u = (x - lo[a]) / du
                if u < -3.0:
                    u = -3.0
                elif u > shape[a] + 2.0:
                    u = shape[a] + 2.0
                params[a, sl] = u - np.floor(u)
                x0[a, sl] = x - origin[r, a]
            params[3, sl] = s[v]
            influence[sl] = s[v]
            if out:
                outside += 1
        return outside

    @njit
    def face_volumes(rel, tris_t, face_vol, f0, f1):
        # The float64 volume terms of faces f0..f1-1 about the origin, as `volume.face_volumes`,
        # from the vertices' coordinates rel (V, 3) (in the mesh's own order, whose faces mostly
        # address nearby vertices).
        ta, tb, tc, out = tris_t[0, f0:f1], tris_t[1, f0:f1], tris_t[2, f0:f1], face_vol[f0:f1]
        for f in range(out.shape[0]):
            a = ta[f]
            b = tb[f]
            c = tc[f]
            x0, y0, z0 = rel[a, 0], rel[a, 1], rel[a, 2]
            x1, y1, z1 = rel[b, 0], rel[b, 1], rel[b, 2]
            x2, y2, z2 = rel[c, 0], rel[c, 1], rel[c, 2]
            out[f] = (x0 * (y1 * z2 - z1 * y2)
                      + y0 * (z1 * x2 - x1 * z2)
                      + z0 * (x1 * y2 - y1 * x2)) / 6.0

    @njit
    def face_volume_sums(rel, tris_t, chunk, sums, c0, c1):
        # Per chunk of `chunk` faces (chunks c0..c1-1): the sum of the faces' float64 volume terms
        # (as `face_volumes` makes them) and of their absolute values, each added in the faces'
        # order into sums[c] (2,), the terms themselves not written (`volume.chunked_sums` is the
        # same arithmetic in NumPy).
        F = tris_t.shape[1]
        for c in range(c0, c1):
            f0 = c * chunk
            f1 = min(f0 + chunk, F)
            ta, tb, tc = tris_t[0, f0:f1], tris_t[1, f0:f1], tris_t[2, f0:f1]
            total = 0.0
            size = 0.0
            for f in range(ta.shape[0]):
                a = ta[f]
                b = tb[f]
                d = tc[f]
                x0, y0, z0 = rel[a, 0], rel[a, 1], rel[a, 2]
                x1, y1, z1 = rel[b, 0], rel[b, 1], rel[b, 2]
                x2, y2, z2 = rel[d, 0], rel[d, 1], rel[d, 2]
                term = (x0 * (y1 * z2 - z1 * y2)
                        + y0 * (z1 * x2 - x1 * z2)
                        + z0 * (x1 * y2 - y1 * x2)) / 6.0
                total += term
                size += abs(term)
            sums[c, 0] = total
            sums[c, 1] = size

    @njit
    def face_volume_sums_about(points, origin, tris_t, chunk, sums, c0, c1):
        # `face_volume_sums` of the faces of points (V, 3) (float32 or float64) about origin
        # (3,) float64: each coordinate made float64 and the origin's taken from it as the
        # term is made, as `volume.measure_about` does in NumPy (the same values as
        # `face_volume_sums` of points - origin).
        F = tris_t.shape[1]
        ox, oy, oz = origin[0], origin[1], origin[2]
        for c in range(c0, c1):
            f0 = c * chunk
            f1 = min(f0 + chunk, F)
            ta, tb, tc = tris_t[0, f0:f1], tris_t[1, f0:f1], tris_t[2, f0:f1]
            total = 0.0
            size = 0.0
            for f in range(ta.shape[0]):
                a = ta[f]
                b = tb[f]
                d = tc[f]
                x0, y0, z0 = points[a, 0] - ox, points[a, 1] - oy, points[a, 2] - oz
                x1, y1, z1 = points[b, 0] - ox, points[b, 1] - oy, points[b, 2] - oz
                x2, y2, z2 = points[d, 0] - ox, points[d, 1] - oy, points[d, 2] - oz
                term = (x0 * (y1 * z2 - z1 * y2)
                        + y0 * (z1 * x2 - x1 * z2)
                        + z0 * (x1 * y2 - y1 * x2)) / 6.0
                total += term
                size += abs(term)
            sums[c, 0] = total
            sums[c, 1] = size

    @njit
    def face_volumes_about(points, origins, face_island, tris_t, face_vol, f0, f1):
        # `face_volumes` of the faces f0..f1-1 of points (V, 3) (float32 or float64), each about
        # the origin of its island (origins (k, 3) float64, face_island (F,) int64).
        ta, tb, tc, out = tris_t[0, f0:f1], tris_t[1, f0:f1], tris_t[2, f0:f1], face_vol[f0:f1]
        isl = face_island[f0:f1]
        for f in range(out.shape[0]):
            a = ta[f]
            b = tb[f]
            c = tc[f]
            o = isl[f]
            ox, oy, oz = origins[o, 0], origins[o, 1], origins[o, 2]
            x0, y0, z0 = points[a, 0] - ox, points[a, 1] - oy, points[a, 2] - oz
            x1, y1, z1 = points[b, 0] - ox, points[b, 1] - oy, points[b, 2] - oz
            x2, y2, z2 = points[c, 0] - ox, points[c, 1] - oy, points[c, 2] - oz
            out[f] = (x0 * (y1 * z2 - z1 * y2)
                      + y0 * (z1 * x2 - x1 * z2)
                      + z0 * (x1 * y2 - y1 * x2)) / 6.0

    @njit
    def axis_cells(xyz, a, n, lo, hi, cell, tt, v0, v1):
        # `bases.axis_cells` for local axis a (n >= 2) of the coordinates xyz (V, 3): the
        # unclamped cell (V,) int64 and t (V,), of vertices v0..v1-1.
        du = (hi - lo) / (n - 1)
        top = n + 2.0
        for v in range(v0, v1):
            u = (xyz[v, a] - lo) / du
            if u < -3.0:
                u = -3.0
            elif u > top:
                u = top
            fi = np.floor(u)
            cell[v] = int(fi)
            tt[v] = u - fi

    @njit
    def cell_keys(verts, n, lo, hi, labels, dims, origin, rows, rel, key, counts, v0, v1):
        # The key (island, cell) of vertices v0..v1-1 into key (V,), counted by key into counts
        # (K,) (zeroed): (labels[v] * n_cells + (cw + 3) * dv + cv + 3) * du + cu + 3 with
        # dims = (du, dv, dw) (labels empty: one island), where cu, cv, cw are the unclamped
        # cells of the three axes made as `axis_cells` makes them from the coordinates verts
        # (V, 3) (finite: checked before), n (3,) points per axis (each >= 2), lo, hi (3,) the
        # lattice's box. The cells go straight into the key: no pass writes them and reads them
        # back. In the same pass, as `relative`: rel (V, 3) = verts - origin[rows[v]] (origin
        # (k, 3), rows (V,), or empty for origin[0]), which the faces' volume terms and x0 read
        # (subtracting there instead costs more than this pass's writes).
        du, dv = dims[0], dims[1]
        n_cells = dims[0] * dims[1] * dims[2]
        one = labels.shape[0] == 0
        d0 = (hi[0] - lo[0]) / (n[0] - 1)
        d1 = (hi[1] - lo[1]) / (n[1] - 1)
        d2 = (hi[2] - lo[2]) / (n[2] - 1)
        t0, t1, t2 = n[0] + 2.0, n[1] + 2.0, n[2] + 2.0
        single = rows.shape[0] == 0
        P, R, keys = verts[v0:v1], rel[v0:v1], key[v0:v1]
        part_rows = rows if single else rows[v0:v1]
        part_labels = labels if one else labels[v0:v1]
        for v in range(P.shape[0]):
            r = 0 if single else part_rows[v]
            for a in range(3):
                R[v, a] = P[v, a] - origin[r, a]
            u0 = (P[v, 0] - lo[0]) / d0
            u1 = (P[v, 1] - lo[1]) / d1
            u2 = (P[v, 2] - lo[2]) / d2
            u0 = -3.0 if u0 < -3.0 else (t0 if u0 > t0 else u0)
            u1 = -3.0 if u1 < -3.0 else (t1 if u1 > t1 else u1)
            u2 = -3.0 if u2 < -3.0 else (t2 if u2 > t2 else u2)
            k = ((int(np.floor(u2)) + 3) * dv + int(np.floor(u1)) + 3) * du + int(np.floor(u0)) + 3
            if not one:
                k += part_labels[v] * n_cells
            keys[v] = k
            counts[k] += 1

    @njit
    def key_starts(counts, start, place):
        # From every part's counts (P, K): where every key's vertices begin in the order (start
        # (K + 1,)) and where each part's vertices of that key go (place (P, K)): parts in vertex
        # order within a key, so the order is stable whatever the number of parts.
        pos = 0
        for k in range(counts.shape[1]):
            start[k] = pos
            for p in range(counts.shape[0]):
                place[p, k] = pos
                pos += counts[p, k]
        start[counts.shape[1]] = pos

    @njit
    def place_slots(key, place, base, entry_start, order, slot, sorted_slot, count, v0, v1):
        # Vertices v0..v1-1 into the order at their key's next place (place (K,), a part's row)
        # and their slots: a run of one key fills its blocks in order, so the vertex at place p
        # of key k has slot base[k] + p (base: the run's first slot less where the key begins;
        # the `slots` pass without a pass of its own). In the same loop each vertex's count of
        # entries of the faces around it (entry_start (V + 1,): where they begin) into
        # count[slot + 1], which summed gives where every slot's entries begin
        # (`solve_kernels.slot_incidence_start`, read here in the vertices' order).
        part, part_slot, starts = key[v0:v1], slot[v0:v1], entry_start[v0:v1 + 1]
        for i in range(part.shape[0]):
            k = part[i]
            p = place[k]
            sl = p + base[k]
            order[p] = v0 + i
            sorted_slot[p] = sl
            part_slot[i] = sl
            count[sl + 1] = starts[i + 1] - starts[i]
            place[k] = p + 1

    @njit
    def running_sum(a):
        # a[i] += a[i - 1] in place, in order (np.cumsum, which took three times as long).
        total = 0
        for i in range(a.shape[0]):
            total += a[i]
            a[i] = total

    @njit
    def components(tris_t, parent, labels):
        # `mesh.connected_components` by union-find: every face's edges join their vertices'
        # sets, the larger root hooked under the smaller, so a root is its component's lowest
        # vertex; labels (V,) then number the components by that vertex, as NumPy's do.
        # Returns their count.
        n = parent.shape[0]
        for v in range(n):
            parent[v] = v
        for f in range(tris_t.shape[1]):
            for k in range(2):
                a = tris_t[k, f]
                while parent[a] != a:           # (path halving)
                    parent[a] = parent[parent[a]]
                    a = parent[a]
                b = tris_t[k + 1, f]
                while parent[b] != b:
                    parent[b] = parent[parent[b]]
                    b = parent[b]
                if a < b:
                    parent[b] = a
                elif b < a:
                    parent[a] = b
        count = 0
        for v in range(n):
            r = v
            while parent[r] != r:
                r = parent[r]
            if r == v:
                labels[v] = count
                count += 1
            else:
                labels[v] = labels[r]
        return count

    @njit
    def closed(start, pairs):
        # `mesh.is_closed` from the faces around every vertex (`solve_kernels.vertex_incidence`:
        # at vertex a, face (a, m, n) gives the edges a -> m and n -> a): closed and consistently
        # oriented when, at every vertex and leaving degenerate faces out, the vertices its edges
        # go to are the vertices its edges come from, each once.
        n_faces = 0
        most = 0
        for a in range(start.shape[0] - 1):
            most = max(most, start[a + 1] - start[a])
        out = np.empty(most, np.int64)
        inc = np.empty(most, np.int64)
        for a in range(start.shape[0] - 1):
            deg = 0
            for e in range(start[a], start[a + 1]):
                m = pairs[2 * e]
                n = pairs[2 * e + 1]
                if m == a or n == a or m == n:
                    continue
                out[deg] = m
                inc[deg] = n
                deg += 1
            n_faces += deg
            for k in range(deg):                # (a handful of entries: count, no sort)
                going = 0
                coming = 0
                for j in range(deg):
                    if out[j] == out[k]:
                        going += 1
                    if inc[j] == out[k]:
                        coming += 1
                if going != 1 or coming != 1:   # (as many of each: then every one comes once)
                    return False
        return n_faces > 0

    @njit
    def positions(verts, labels, out, lo, hi, v0, v1):
        # out (V, 3) = verts in float64 and, per island (labels (V,), or empty for one), the
        # bounds lo, hi (k, 3) of its finite coordinates, as `mesh.check_verts` and
        # `Topology.island_bounds` compute them; one pass instead of five, over vertices v0..v1-1
        # (a part's bounds; the caller takes the least and greatest of the parts'). Returns how
        # many have a non-finite coordinate (the caller then says which, in NumPy).
        for r in range(lo.shape[0]):
            for a in range(3):
                lo[r, a] = np.inf
                hi[r, a] = -np.inf
        bad = 0
        one = labels.shape[0] == 0
        P, O = verts[v0:v1], out[v0:v1]
        if one:
            # (one island: the bounds in registers; stored in lo and hi at every vertex, which
            # the compiler cannot tell from out, the pass took 2.7 times its bytes' time)
            l0, l1, l2 = np.inf, np.inf, np.inf
            h0, h1, h2 = -np.inf, -np.inf, -np.inf
            for v in range(P.shape[0]):
                x = np.float64(P[v, 0])
                y = np.float64(P[v, 1])
                z = np.float64(P[v, 2])
                O[v, 0] = x
                O[v, 1] = y
                O[v, 2] = z
                # (the comparisons of the loop below, so the same bounds, signed zeros too)
                if np.isfinite(x):
                    if x < l0:
                        l0 = x
                    if x > h0:
                        h0 = x
                if np.isfinite(y):
                    if y < l1:
                        l1 = y
                    if y > h1:
                        h1 = y
                if np.isfinite(z):
                    if z < l2:
                        l2 = z
                    if z > h2:
                        h2 = z
                if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                    bad += 1
            lo[0, 0], lo[0, 1], lo[0, 2] = l0, l1, l2
            hi[0, 0], hi[0, 1], hi[0, 2] = h0, h1, h2
            return bad
        part_labels = labels[v0:v1]
        for v in range(P.shape[0]):
            r = part_labels[v]
            finite = True
            for a in range(3):
                x = np.float64(P[v, a])
                O[v, a] = x
                if np.isfinite(x):
                    if x < lo[r, a]:
                        lo[r, a] = x
                    if x > hi[r, a]:
                        hi[r, a] = x
                else:
                    finite = False
            if not finite:
                bad += 1
        return bad

    @njit
    def relative(verts, origin, labels, rel, v0, v1):
        # rel (V, 3) = verts - the origin of each vertex's island (origin (k, 3); labels empty
        # when every vertex takes origin[0]), for vertices v0..v1-1.
        one = labels.shape[0] == 0
        for v in range(v0, v1):
            r = 0 if one else labels[v]
            for a in range(3):
                rel[v, a] = verts[v, a] - origin[r, a]

    return {"slots": slots, "sorted_values": sorted_values, "face_volumes": face_volumes,
            "face_volume_sums": face_volume_sums, "face_volumes_about": face_volumes_about,
            "face_volume_sums_about": face_volume_sums_about,
            "axis_cells": axis_cells, "positions": positions, "relative": relative,
            "cell_keys": cell_keys, "key_starts": key_starts, "place_slots": place_slots, "running_sum": running_sum,
            "components": components, "closed": closed}


# Every part of a pass at once on numba's own worker threads (`compiled.over`; docs/performance.md,
# "Every core"): part j covers edges[j]..edges[j + 1] - 1 and makes the same call that
# `parallel.run` makes for it (with its own row of the per-part arrays), so a binding stays NumPy's
# bit for bit. `compiled.py` binds `prange` and the compiled kernels (`_k_<name>`)
# by name in this module, where numba finds and caches them.
prange = range


def positions_team(edges, got, verts, labels, out, lo, hi):
    # lo, hi (parts, k, 3): every part's bounds; got (parts, 1): its count of non-finite vertices.
    for j in prange(edges.shape[0] - 1):
        got[j, 0] = _k_positions(verts, labels, out, lo[j], hi[j], edges[j], edges[j + 1])  # noqa: F821


def relative_team(edges, verts, origin, labels, rel):
    for j in prange(edges.shape[0] - 1):
        _k_relative(verts, origin, labels, rel, edges[j], edges[j + 1])  # noqa: F821


def axis_cells_team(edges, xyz, a, n, lo, hi, cell, tt):
    for j in prange(edges.shape[0] - 1):
        _k_axis_cells(xyz, a, n, lo, hi, cell, tt, edges[j], edges[j + 1])  # noqa: F821


def cell_keys_team(edges, verts, n, lo, hi, labels, dims, origin, rows, rel, key, counts):
    # counts (parts, K): every part's own counts.
    for j in prange(edges.shape[0] - 1):
        _k_cell_keys(verts, n, lo, hi, labels, dims, origin, rows, rel, key, counts[j],  # noqa: F821
                     edges[j], edges[j + 1])


def place_slots_team(edges, key, place, base, entry_start, order, slot, sorted_slot, count):
    # place (parts, K): every part's own places.
    for j in prange(edges.shape[0] - 1):
        _k_place_slots(key, place[j], base, entry_start, order, slot, sorted_slot, count,  # noqa: F821
                       edges[j], edges[j + 1])


def slots_team(edges, order, run_start, run_len, first_block, bs, slot, sorted_slot):
    # edges: runs, not vertices.
    for j in prange(edges.shape[0] - 1):
        _k_slots(order, run_start, run_len, first_block, bs, slot, sorted_slot, edges[j], edges[j + 1])  # noqa: F821


def sorted_values_team(edges, got, order, sorted_slot, verts, origin, rows, s, shape, lo, hi, eps, params, influence,
                       x0):
    # got (parts, 1): every part's count of vertices outside the lattice.
    for j in prange(edges.shape[0] - 1):
        got[j, 0] = _k_sorted_values(order, sorted_slot, verts, origin, rows, s, shape, lo, hi, eps,  # noqa: F821
                                     params, influence, x0, edges[j], edges[j + 1])


def face_volumes_team(edges, rel, tris_t, face_vol):
    for j in prange(edges.shape[0] - 1):
        _k_face_volumes(rel, tris_t, face_vol, edges[j], edges[j + 1])  # noqa: F821


def face_volume_sums_team(edges, rel, tris_t, chunk, sums):
    for j in prange(edges.shape[0] - 1):
        _k_face_volume_sums(rel, tris_t, chunk, sums, edges[j], edges[j + 1])  # noqa: F821


def face_volumes_about_team(edges, points, origins, face_island, tris_t, face_vol):
    for j in prange(edges.shape[0] - 1):
        _k_face_volumes_about(points, origins, face_island, tris_t, face_vol, edges[j], edges[j + 1])  # noqa: F821


def face_volume_sums_about_team(edges, points, origin, tris_t, chunk, sums):
    for j in prange(edges.shape[0] - 1):
        _k_face_volume_sums_about(points, origin, tris_t, chunk, sums, edges[j], edges[j + 1])  # noqa: F821


_TEAMS = ("positions", "relative", "axis_cells", "cell_keys", "place_slots", "slots", "sorted_values",
          "face_volumes", "face_volume_sums", "face_volumes_about", "face_volume_sums_about")
