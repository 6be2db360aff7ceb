"""The compiled passes of a lattice bind, split over the worker threads (docs/performance.md,
"Re-embedding and the first bind").

A mesh that moves through the lattice is embedded anew on every frame, so every pass here is
per-frame work and runs on every core: each thread takes a contiguous part of the vertices (or of
the sorted vertices, or of the faces), and what the parts give is combined so that the result is
the same bit for bit on any number of threads (bounds by least and greatest, counts by sums, the
counting sort's places laid out part after part within every key). `kernels` is
`compiled.bind_kernels(...)`; the kernels themselves are in `layout_kernels.py`.
"""
import math

import numpy as np

from . import compiled, parallel, volume

#: Parts of the counting sort keep a count per key each: more parts only where those counts stay
#: small beside the vertices (many islands give many keys).
_KEYS_PER_VERTEX = 0.25


def positions(kernels, verts, labels, k):
    """verts (V, 3) float32 or float64 -> (out (V, 3) float64, lo (k, 3), hi (k, 3), bad): the
    positions in float64, every island's bounds of its finite coordinates (labels (V,) int64, or
    empty for one island) and how many vertices have a non-finite coordinate."""
    V = len(verts)
    out = np.empty((V, 3))
    parts = parallel.split(V, V)
    lo, hi = np.empty((len(parts), k, 3)), np.empty((len(parts), k, 3))
    got = compiled.over("positions", parts, verts, labels, out, lo, hi, returns=1, per_part=(3, 4), kernels=kernels)
    return out, lo.min(axis=0), hi.max(axis=0), int(sum(part[0] for part in got))


def relative(kernels, verts, origin, labels):
    """verts (V, 3) - the origin (k, 3) of each vertex's island (labels (V,), or empty for every
    vertex to take origin[0]) -> (V, 3) float64."""
    V = len(verts)
    rel = np.empty_like(verts)
    compiled.over("relative", parallel.split(V, V), verts, origin, labels, rel, kernels=kernels)
    return rel


def axis_cells(kernels, verts, lattice):
    """verts (V, 3) float64 coordinates -> [(cell (V,) int64, t (V,) float64)] per axis: the
    unclamped cell and the coordinate within it (`bases.axis_cells`), every axis local."""
    V = len(verts)
    cells = [(np.empty(V, np.int64), np.empty(V)) for _ in range(3)]
    args = [(int(lattice.shape[a]), float(lattice.lo[a]), float(lattice.hi[a])) for a in range(3)]
    parts = parallel.split(V, V)
    if compiled.teams("axis_cells", parts, kernels):
        for a in range(3):
            compiled.over("axis_cells", parts, verts, a, *args[a], *cells[a], kernels=kernels)
        return cells

    def part(p):        # (the three axes in one hand-over per part)
        for a in range(3):
            kernels["axis_cells"](verts, a, *args[a], *cells[a], p.start, p.stop)
    parallel.run(part, parts)
    return cells


def cell_keys(kernels, verts, lattice, labels, dims, n_keys, origin, rows):
    """The first half of a counting sort of the vertices by their key (island, cell), the stable
    order of `binding.bind_lattice`'s keys: one pass (`layout_kernels.cell_keys`) makes every
    vertex's cells (`bases.axis_cells`, every axis local) and key from its coordinates verts
    (V, 3) float64 (finite), counts the keys, and writes the coordinates relative to the volume
    origins (as `relative`: origin (k, 3), rows (V,) int64 or empty); then where every key's
    vertices begin. labels (V,) int64 (empty: one island), dims (3,) int64 the cells per axis
    (n + 6), n_keys = islands x cells. Returns (start (n_keys + 1,), rel (V, 3) float64, sorting:
    what `place_slots` needs to finish the sort)."""
    V = len(verts)
    parts = parallel.split(V, V)
    if len(parts) > 1 and n_keys * len(parts) > _KEYS_PER_VERTEX * V:
        parts = [slice(0, V)]
    P = len(parts)
    key, rel = np.empty(V, np.int64), np.empty_like(verts)
    counts = np.zeros((P, n_keys), np.int64)
    compiled.over("cell_keys", parts, verts, np.array(lattice.shape, np.int64), lattice.lo, lattice.hi,
                  labels, dims, origin, rows, rel, key, counts, per_part=(10,), kernels=kernels)
    start, place = np.empty(n_keys + 1, np.int64), np.empty((P, n_keys), np.int64)
    kernels["key_starts"](counts, start, place)
    return start, rel, (key, place, parts)


def place_slots(kernels, sorting, base, entry_start, n_slots, pads):
    """The second half of `cell_keys`' sort, with the slots (`layout_kernels.place_slots`): every
    vertex at its key's place in the order and in its slot, base (n_keys,) int64 every key's first
    slot less where its vertices begin (keys of no vertex: any); and where the entries of the
    faces around every slot begin, from where every vertex's begin (entry_start (V + 1,)). Returns
    (order (V,), slot (V,), sorted_slot (V,), the entries' starts (n_slots + 1,)), as the `slots`
    pass and `solve_kernels.slot_incidence_start` make them. pads (int64): the slots that no
    vertex takes (`binding.bind_lattice`), where no entries begin."""
    key, place, parts = sorting
    V = len(key)
    order, slot, sorted_slot = np.empty(V, np.int64), np.empty(V, np.int64), np.empty(V, np.int64)
    count = np.empty(n_slots + 1, np.int64)     # (the pass writes every vertex's slot + 1)
    count[0] = 0
    count[pads + 1] = 0
    compiled.over("place_slots", parts, key, place, base, entry_start, order, slot, sorted_slot, count,
                  per_part=(1,), kernels=kernels)
    kernels["running_sum"](count)
    return order, slot, sorted_slot, count


def slots(kernels, runs, bs, slot, sorted_slot):
    """The slot of every vertex into slot (V,) and of every sorted position into sorted_slot (V,)
    (`layout_kernels.slots`), from runs = (order (V,), run_start, run_len, first_block); each
    thread a part of the runs, cut where the sorted vertices' parts begin."""
    order, run_start = runs[0], runs[1]
    V = len(order)
    cuts = [0] + [int(np.searchsorted(run_start, p.start)) for p in parallel.split(V, V)[1:]] + [len(run_start)]
    compiled.over("slots", [slice(cuts[j], cuts[j + 1]) for j in range(len(cuts) - 1)], *runs, bs, slot,
                  sorted_slot, kernels=kernels)


#: What one unit of each pass that shares the slot pass's hand-over costs one thread, in ns (a ring
#: entry renumbered, a face's volume term, a vertex's slot values; measured at 163,842 vertices,
#: 2026-12-05, `benchmarks.reembed_passes`): only the balance of the parts depends on them, never
#: a result.
_NS_PER = {"fill": 0.9, "faces": 6.4, "values": 9.8}


def mixed_parts(tasks, n_parts):
    """Cut a run of passes into n_parts parts of about equal cost: tasks [(name, units, ns per
    unit)], laid end to end in that order. Returns [[(name, start, stop), ...] per part], every
    task's units 0..units-1 covered once, in order, each part's pieces in the tasks' order."""
    total = sum(n * w for _, n, w in tasks)
    out = [[] for _ in range(n_parts)]
    offset = 0.0
    for name, n, w in tasks:
        if n <= 0:
            continue
        if not (w > 0 and total > 0 and math.isfinite(total / w)):   # (no cost: whole, where it falls)
            j = min(n_parts - 1, int(n_parts * offset / total)) if total > 0 else 0
            out[j].append((name, 0, n))
            continue
        cuts = [min(n, max(0, int(round((total * j / n_parts - offset) / w)))) if 0 < j < n_parts
                else (0 if j == 0 else n) for j in range(n_parts + 1)]
        for j in range(n_parts):
            if cuts[j + 1] > cuts[j]:
                out[j].append((name, cuts[j], cuts[j + 1]))
        offset += n * w
    return out


def faces_task(b, rel, face_vol):
    """The faces' float64 volume terms of binding `b` from rel (V, 3) (the coordinates relative to
    the volume origins, made by `cell_keys`) as a task of `slot_values_and_faces`: into face_vol
    (F,) where it is given, else only their sums in chunks (`layout_kernels.face_volume_sums`,
    for one island: the terms themselves are read by nothing else). Returns (the task, the chunks'
    sums (n_chunks, 2) or None)."""
    return _faces(b, face_vol, ("face_volume_sums", (rel,)), ("face_volumes", (rel,)))


def faces_task_about(b, points, origins, face_vol):
    """As `faces_task`, the terms of points (V, 3) (float32 or float64) about every island's row
    of origins (k, 3) (`volume.MeasuredIn`; `layout_kernels.face_volume_sums_about`,
    `face_volumes_about`)."""
    return _faces(b, face_vol, ("face_volume_sums_about", (points, origins[0])),
                  ("face_volumes_about", (points, origins, b.topology.face_island)))


def _faces(b, face_vol, sums_kernel, terms_kernel):
    tris_t = b.topology.tris_t
    F = tris_t.shape[1]
    if face_vol is None:
        chunk = volume.FACE_CHUNK
        sums = np.empty((max(1, -(-F // chunk)), 2))
        name, head = sums_kernel
        return (name, head + (tris_t, chunk, sums), len(sums), _NS_PER["faces"] * chunk), sums
    name, head = terms_kernel
    return (name, head + (tris_t, face_vol), F, _NS_PER["faces"]), None


def slot_values_and_faces(kernels, b, lattice, verts, s, order, sorted_slot, rows, faces, around=None):
    """What every slot holds (b.params, b.slot_influence, b.x0: `layout_kernels.sorted_values`)
    (x0 from verts (V, 3) less the origin of its row `rows` (V,) of b.island_origin, or empty
    for its only row) and the faces' volume terms or their sums (`faces`: a task of `faces_task`
    or `faces_task_about`, or None where the volume is known); with `around` = (the topology's
    faces around every vertex, `compiled.vertex_rings`; start (n_slots + 1,) made from them;
    entries, ring to fill) also the faces around every slot (`solve_kernels.slot_incidence_fill`,
    what `compiled.incidence` makes). On the Python threads all of it is one hand-over, the three
    laid end to end and cut into parts of about equal cost (`mixed_parts`): the renumbering writes
    every slot's entries where its vertex takes them, so split by vertices its parts write into
    the same cache lines (two threads took as long as one); cut this way it stays whole in one
    part on up to about five threads.
    Returns how many vertices lie outside the lattice."""
    V = b.n_verts
    vparts = parallel.split(V, V)
    shape = np.array(lattice.shape, np.int64)
    eps = 1e-6 * lattice.size

    values = (order, sorted_slot, verts, b.island_origin, rows, s, shape, lattice.lo, lattice.hi, eps, b.params,
              b.slot_influence, b.x0)
    fill = None if around is None else (b.slot, *around[0], *around[1:])
    if compiled.teams("sorted_values", vparts, kernels):
        got = compiled.over("sorted_values", vparts, *values, returns=1, kernels=kernels)
        if faces is not None:
            compiled.over(faces[0], parallel.split(faces[2], V), *faces[1], kernels=kernels)
        if fill is not None:
            compiled.over("slot_incidence_fill", vparts, *fill, kernels=kernels)
        return int(sum(part[0] for part in got))
    tasks = [("values", V, _NS_PER["values"])]
    calls = {"values": (kernels["sorted_values"], values), "fill": (kernels["slot_incidence_fill"], fill)}
    if faces is not None:
        tasks.append((faces[0], faces[2], faces[3]))
        calls[faces[0]] = (kernels[faces[0]], faces[1])
    if fill is not None:
        tasks.insert(0, ("fill", V, _NS_PER["fill"] * len(around[0][1]) / max(V, 1)))

    def part(pieces):   # (every pass of the part in one hand-over)
        outside = 0
        for name, a, z in pieces:
            fn, args = calls[name]
            got = fn(*args, a, z)
            if name == "values":
                outside += got
        return outside
    pieces = [p for p in mixed_parts(tasks, len(vparts)) if p]
    return sum(parallel.run(part, pieces))
