"""The compiled passes of a lattice bind, split over the worker threads (docs/performance.md,
"Re-embedding and the first bind").

A mesh that moves through the lattice is embedded anew on every frame, so every pass here is
per-frame work and runs on every core: each thread takes a contiguous part of the vertices (or of
the sorted vertices, or of the faces), and what the parts give is combined so that the result is
the same bit for bit on any number of threads (bounds by least and greatest, counts by sums, the
counting sort's places laid out part after part within every key). `kernels` is
`compiled.bind_kernels(...)`; the kernels themselves are in `layout_kernels.py`.
"""
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


def cell_order(kernels, verts, lattice, labels, dims, n_keys, origin, rows):
    """The vertices in stable order of their key (island, cell), as np.argsort(kind="stable") of
    `binding.bind_lattice`'s keys, by a counting sort whose first pass makes every vertex's cells
    (`bases.axis_cells`, every axis local) and key from its coordinates verts (V, 3) float64
    (finite), and their coordinates relative to the volume origins (as `relative`: origin (k, 3),
    rows (V,) int64 or empty). labels (V,) int64 (empty: one island), dims (3,) int64 the cells
    per axis (n + 6), n_keys = islands x cells. Returns (start (n_keys + 1,) where every key's
    vertices begin, order (V,) int64, rel (V, 3) float64)."""
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
    order = np.empty(V, np.int64)
    compiled.over("place_keys", parts, key, place, order, per_part=(1,), kernels=kernels)
    return start, order, rel


def slots(kernels, runs, bs, slot, sorted_slot):
    """The slot of every vertex into slot (V,) and of every sorted position into sorted_slot (V,)
    (`layout_kernels.slots`), from runs = (order (V,), run_start, run_len, first_block); each
    thread a part of the runs, cut where the sorted vertices' parts begin."""
    order, run_start = runs[0], runs[1]
    V = len(order)
    cuts = [0] + [int(np.searchsorted(run_start, p.start)) for p in parallel.split(V, V)[1:]] + [len(run_start)]
    compiled.over("slots", [slice(cuts[j], cuts[j + 1]) for j in range(len(cuts) - 1)], *runs, bs, slot,
                  sorted_slot, kernels=kernels)


def slot_values_and_faces(kernels, b, lattice, verts, s, order, sorted_slot, rel, face_vol):
    """What every slot holds (b.params, b.slot_influence, b.x0: `layout_kernels.sorted_values`)
    and the faces' float64 volume terms from rel (V, 3): into face_vol (F,) where it is given,
    else only their sums in chunks (`layout_kernels.face_volume_sums`, for one island: the terms
    themselves are read by nothing else), each thread a part of the sorted vertices and then a
    part of the faces. Returns (how many vertices lie outside the lattice, the chunks' sums
    (n_chunks, 2) or None)."""
    V, tris_t = b.n_verts, b.topology.tris_t
    F = tris_t.shape[1]
    vparts = parallel.split(V, V)
    if face_vol is None:
        chunk = volume.FACE_CHUNK
        sums = np.empty((max(1, -(-F // chunk)), 2))
        fparts = parallel.split(len(sums), V)
        faces = ("face_volume_sums", (rel, tris_t, chunk, sums))
    else:
        sums, fparts = None, parallel.split(F, V)
        faces = ("face_volumes", (rel, tris_t, face_vol))
    shape = np.array(lattice.shape, np.int64)
    eps = 1e-6 * lattice.size

    values = (order, sorted_slot, verts, rel, s, shape, lattice.lo, lattice.hi, eps, b.params, b.slot_influence, b.x0)
    if compiled.teams("sorted_values", vparts, kernels):
        got = compiled.over("sorted_values", vparts, *values, returns=1, kernels=kernels)
        compiled.over(faces[0], fparts, *faces[1], kernels=kernels)
        return int(sum(part[0] for part in got)), sums
    face_kernel = kernels[faces[0]]

    def part(j):        # (both kernels in one hand-over per part)
        outside = 0
        if j < len(vparts):
            outside = kernels["sorted_values"](*values, vparts[j].start, vparts[j].stop)
        if j < len(fparts):
            face_kernel(*faces[1], fparts[j].start, fparts[j].stop)
        return outside
    return sum(parallel.run(part, list(range(max(len(vparts), len(fparts)))))), sums
