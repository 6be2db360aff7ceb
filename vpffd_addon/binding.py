"""Binding a mesh to a lattice: the rest embedding, stored so that per-frame products are cheap.

The whole deformation is ``x' = x0 + S B (P - P0)`` (docs/design.md, "The deformation"). B depends only on the rest
embedding, so it is built once here. Vertices are sorted by (island, lattice cell) and cut into
blocks of `block` slots that share one set of Ku*Kv*Kw control points; products with B and B^T are
then batched small matrix products per block. B is kept factored, (v x u) weights and w weights per
vertex, to hold memory near 100 bytes per vertex in float32.
"""
import numpy as np

from . import compiled, layout, parallel, volume
from .bases import _local_weights, axis_cells, axis_taps, tap_count
from .jacobian import lattice_jacobian_det
from .lattice import Lattice
from .mesh import Topology, check_verts
from .solve import solve
from .volume import face_volumes, gradient_component

_BLOCK_SIZES = (64, 32, 16, 8)
_MAX_PADDING = 1.15  # accept a block size when padded slots stay within 15% of the vertex count


class BindingBase:
    """What every binding shares: a mesh embedded in a control structure (a `Lattice` or a
    `Cage`, kept as `lattice`), its vertices stored in "slots" (a reordering, possibly padded),
    coordinates relative to per-island volume origins, faces as slot triples.

    Subclasses provide the products with S B: `forward`, `transpose`, `island_transpose`,
    `rows`, and `jacobian_det`. What the solve's steps (`steps`, `compiled`, the GPU path) ask of
    every binding besides: `forward_many`, `gather`, `gradient`, `gradient_of`, `displacements`,
    `origins`, `to_verts`.

    Public attributes: `lattice`, `dtype`, `n_verts`, `n_faces`, `is_closed`, `rest_volume`,
    `n_islands`, `island_labels` (V,), `rest_island_volumes` (n_islands,), `influence` (V,),
    `n_outside` (vertices outside the lattice's box or the cage's region), `nbytes`.

    Set on a lattice binding by a compiled bind, or by the compiled steps on first use (absent
    until then; `compiled`): `incidence` (start (n_slots + 1,) int64, entries uint32, ring
    (n_slots,) int8), the faces around every slot as rings of neighbours where they close a fan,
    as pairs elsewhere (`solve_kernels.vertex_rings`).
    Set by the compiled steps on first use:
    `vertex_rows` (V,) int64, the row of `island_origin` of every vertex; `converted` (dtype,
    params (4, n_slots), x0 (3, n_slots)), the binding's values in another precision.
    """

    def deform(self, points):
        """Standard FFD (Blender's Lattice modifier) for control points `points` (N, 3): (V, 3) float64."""
        D = self.displacements(points)
        X = self.x0 + np.stack([self.forward(D[:, c]) for c in range(3)])
        verts = self.to_verts(X)
        if not np.isfinite(verts).all():
            raise ValueError(f"the deformation overflows {self.dtype.name}: the control points are too far away")
        return verts

    def solve(self, points, axes="XYZ", directions=None, volume_scale=1.0, preserve_volume=True,
              mobility=None, pins=(), islands=False, steps=None, target_volumes=None):
        """Volume-preserving FFD for control points `points` (N, 3): a `Solution`.
        The options are documented at `vpffd_addon.solve.solve`."""
        return solve(self, points, axes=axes, directions=directions, volume_scale=volume_scale,
                     preserve_volume=preserve_volume, mobility=mobility, pins=pins, islands=islands,
                     steps=steps, target_volumes=target_volumes)

    @property
    def influence(self):
        """(V,) per-vertex influence (vertex-group weight * strength), in the binding's dtype."""
        return self.slot_influence[self.slot]

    @property
    def island_labels(self):
        """(V,) connected component of each vertex, numbered 0..n_islands-1 by lowest vertex."""
        return self.slot_island[self.slot]

    @property
    def nbytes(self):
        """Bytes held by the arrays of this binding."""
        arrays = [a for a in vars(self).values() if isinstance(a, np.ndarray)] + vars(self).get("corner_parts", [])
        arrays += [a for a in vars(self).get("incidence", ()) if isinstance(a, np.ndarray)]
        arrays += list(vars(self).get("converted", ())[1:])     # float64 copies (islands' steps)
        return int(sum(a.nbytes for a in arrays))

    #: What the NumPy products need beyond the compiled ones, made on first use (a binding laid out
    #: by the compiled kernels never needs them unless NumPy's steps, the GPU path, pins or the
    #: Jacobian ask): the faces as (3, F_part) slot arrays per worker part, and (for a lattice)
    #: the stored weights.
    _LAZY = ("corner_parts",)

    def __getattr__(self, name):
        # Only called for attributes not set: make a lazy one, once.
        if name in type(self)._LAZY:
            self._materialise(name)
            return vars(self)[name]
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def _materialise(self, name):
        if name == "corner_parts":
            self.corner_parts = corner_parts(self)

    def gather(self, x):
        """Slot values x (n_slots,) at the face corners: a list with one (3, F_part) array per
        face part (`corner_parts`), in x's dtype."""
        return parallel.run(lambda c: np.take(x, c), self.corner_parts)

    def gradient_of(self, xp, xq):
        """`gradient` straight from slot coordinates xp, xq (n_slots,): gathers and gradient in one
        pass per face part (one hand-over to the worker threads instead of three). (n_slots,)
        float64."""
        n = self.x0.shape[1]

        def part(c):
            return gradient_component(np.take(xp, c), np.take(xq, c), c, n)
        parts = parallel.run(part, self.corner_parts)
        return parts[0] if len(parts) == 1 else np.sum(parts, 0)

    def forward_many(self, D):
        """`forward` of several fields D (k, N) on the control points at once: (k, n_slots) in the
        binding's dtype."""
        return np.stack([self.forward(d) for d in D])

    def gradient(self, P, Q):
        """Volume gradient along e at every slot from gathered corner coordinates P, Q (`gather` of
        the (n_slots,) coordinates on the frame vectors completing e: one (3, F_part) array per
        face part; see `volume.gradient_component`): (n_slots,) float64."""
        n = self.x0.shape[1]
        parts = parallel.run(lambda k: gradient_component(P[k], Q[k], self.corner_parts[k], n),
                             list(range(len(P))))
        return parts[0] if len(parts) == 1 else np.sum(parts, 0)

    def displacements(self, points):
        """Control points `points` (N, 3), validated (shape and finiteness: ValueError), minus the
        rest grid: (N, 3) float64."""
        P = np.asarray(points, dtype=np.float64)
        N = self.lattice.n_points
        if P.shape != (N, 3):
            raise ValueError(f"points must have shape ({N}, 3) for {self.lattice!r}, got {P.shape}")
        if not np.isfinite(P).all():    # (per point only then: a reduction along rows of 3 is slow)
            bad = ~np.isfinite(P).all(1)
            raise ValueError(f"points has non-finite coordinates at {int(bad.sum())} control points "
                             f"(first: index {int(np.argmax(bad))})")
        return P - self.lattice.rest_points

    def origins(self, vertices):
        """Volume origins of the vertices `vertices` (k,) int (their islands' origins): (k, 3)
        float64, a read-only broadcast view when the binding has one origin."""
        if len(self.island_origin) == 1:
            return np.broadcast_to(self.island_origin[0], (len(vertices), 3))
        return self.island_origin[self.slot_island[self.slot[vertices]]]

    def to_verts(self, X):
        """Slot-ordered coordinates X (3, n_slots), relative to the island origins -> (V, 3)
        float64 in lattice space (the vertices' own order)."""
        out = np.empty((self.n_verts, 3))
        single = len(self.island_origin) == 1

        def part(vs):
            idx = self.slot[vs]
            for c in range(3):
                out[vs, c] = np.take(X[c], idx)
            out[vs] += self.island_origin[0] if single else self.origins(np.arange(vs.start, vs.stop))
        parallel.run(part, self.vertex_parts)
        return out


class Binding(BindingBase):
    """A mesh bound to a `Lattice`; made by `bind`. Coordinates are in lattice space.

    Extra public attribute: `source`, (positions (V, 3) float64, influence (V,) float64) as bound
    (what NumPy's stored weights `wuv`, `ww` are made from on first use)."""

    _LAZY = BindingBase._LAZY + ("wuv", "ww")

    @property
    def weight_shape(self):
        """(n_blocks, Kw, Kv * Ku): the shape of NumPy's stored weights per block (`ww` has Kw rows
        a block, `wuv` Kv * Ku), known without making them."""
        Ku, Kv, Kw = (tap_count(n, kind) for n, kind in zip(self.lattice.shape, self.lattice.interpolation))
        return len(self.block_run), Kw, Kv * Ku

    def _materialise(self, name):
        if name in ("wuv", "ww"):
            verts, s = self.source
            _numpy_weights(self, _lattice_taps(self.lattice, verts, None), s, len(self.block_run))
        else:
            super()._materialise(name)

    @property
    def slot_island(self):
        """(n_slots,) island of every slot (padding slots take their block's island)."""
        return np.repeat(self.block_island, self.block_size)

    def jacobian_det(self, points):
        """det(d x' / d x) at every vertex for control points `points` (N, 3): (V,) float64."""
        return lattice_jacobian_det(self, points)

    # -- products with the factored B (all in slot order; slots = padded, block-sorted vertices) --

    def forward(self, d, wuv=None, ww=None):
        """(S B d) at every slot for a scalar field d (N,) on the control points: (n_slots,) in the
        binding's dtype. `wuv` (n_blocks, Kv * Ku, block), `ww` (n_blocks, Kw, block) replace the
        stored weight factors (same layout, `block_layout`), e.g. by their derivatives."""
        wuv = self.wuv if wuv is None else wuv
        ww = self.ww if ww is None else ww
        # Contract the (v x u) weights first: the intermediate is then Kw values per vertex.
        D = np.asarray(d, dtype=self.dtype)[self.run_idx]
        out = np.empty((self.ww.shape[0], self.block_size), self.dtype)

        def part(bl):
            T = np.matmul(D[self.block_run[bl]], wuv[bl])
            np.einsum("bks,bks->bs", T, ww[bl], out=out[bl])
        parallel.run(part, self.block_parts)
        return out.reshape(-1)

    def forward_many(self, D):
        """`forward` of several fields D (k, N) on the control points at once, in one pass over the
        blocks: (k, n_slots) in the binding's dtype."""
        D = np.asarray(D, dtype=self.dtype)
        out = np.empty((len(D), self.ww.shape[0], self.block_size), self.dtype)

        def part(bl):
            for k, d in enumerate(D):
                T = np.matmul(d[self.run_idx][self.block_run[bl]], self.wuv[bl])
                np.einsum("bks,bks->bs", T, self.ww[bl], out=out[k, bl])
        parallel.run(part, self.block_parts)
        return out.reshape(len(D), -1)

    def block_layout(self, per_vertex):
        """Per-vertex factors (V, K) -> the (n_blocks, K, block) layout of `wuv` and `ww`, in the
        binding's dtype (padding slots zero)."""
        out = np.zeros((self.x0.shape[1], per_vertex.shape[1]), self.dtype)
        out[self.slot] = per_vertex
        return np.ascontiguousarray(out.reshape(-1, self.block_size, out.shape[1]).transpose(0, 2, 1))

    def _run_transpose(self, g):
        """Per-run pieces of (S B)^T g for g (n_slots,): (n_runs, Kw, Kv*Ku), to scatter with run_idx.
        A run is the blocks of one (island, cell): they share control points, so they sum first."""
        g = np.asarray(g, dtype=self.dtype).reshape(-1, 1, self.block_size)
        out = np.empty((self.ww.shape[0],) + self.run_idx.shape[1:], self.dtype)

        def part(bl):
            np.matmul(self.ww[bl] * g[bl], self.wuv[bl].transpose(0, 2, 1), out=out[bl])
        parallel.run(part, self.block_parts)
        return np.add.reduceat(out, self.run_first_block, axis=0)

    def transpose(self, g):
        """(S B)^T g for g (n_slots,): (N,) float64."""
        return np.bincount(self.run_idx.ravel(), self._run_transpose(g).ravel(), self.lattice.n_points)

    def rows(self, slots):
        """Rows of S B for the given vertex slots (k,) int: dense (k, N) float64. From the slots' cell
        coordinates where the binding has them (a compiled bind then needs no stored weights for
        the pins of a frame), else from the stored weights."""
        slots = np.asarray(slots, dtype=np.int64)
        blk, pos = np.divmod(slots, self.block_size)
        N, k = self.lattice.n_points, len(slots)
        if getattr(self, "params", None) is not None:
            lat = self.lattice
            # Blender's taps i-1..i+2 of each axis, clamped; (k, 4) weights and grid indices.
            w = [_local_weights(self.params[a, slots].astype(np.float64), lat.interpolation[a], False)[0]
                 for a in range(3)]
            i = [np.clip(self.block_cell[blk, a, None] - 1 + np.arange(4), 0, lat.shape[a] - 1) for a in range(3)]
            nu, nv, _ = lat.shape
            idx = (i[2][:, :, None, None] * nv + i[1][:, None, :, None]) * nu + i[0][:, None, None, :]
            w = (w[2][:, :, None, None] * w[1][:, None, :, None] * w[0][:, None, None, :]
                 * self.params[3, slots, None, None, None])
        else:
            w = self.ww[blk, :, pos][:, :, None] * self.wuv[blk, :, pos][:, None, :]
            idx = self.run_idx[self.block_run[blk]]
        keys = (np.arange(k)[:, None] * N + idx.reshape(k, -1)).ravel()
        return np.bincount(keys, w.reshape(k, -1).ravel().astype(np.float64), k * N).reshape(k, N)

    def island_transpose(self, g, k):
        """(S B)^T g for g (n_slots,) restricted to each island's slots (islands 0..k-1): (k, N)
        float64, one row per island."""
        N = self.lattice.n_points
        keys = (self.run_island[:, None, None] * N + self.run_idx).ravel()
        return np.bincount(keys, self._run_transpose(g).ravel(), k * N).reshape(-1, N)


def bind_lattice(lattice, rest_verts, tris, influence=None, dtype=np.float64, depth=None,
                 topology=None, use_compiled=True, measured_in=None):
    """`bind` for a `Lattice` (see `vpffd_addon.binder.bind`): a `Binding`. measured_in: a
    `volume.MeasuredIn` for a closed mesh whose rest volume is measured in another space (filled
    in when its sums are None), or None (measured here about every island's own centre)."""
    if measured_in is not None and not (isinstance(topology, Topology) and topology.is_closed
                                        and len(measured_in.points) == topology.n_verts
                                        and len(measured_in.origins) == topology.n_islands):
        raise ValueError("measured_in needs a closed mesh's Topology, a point for every vertex and an "
                         "origin for every island")
    if not isinstance(lattice, Lattice):
        raise ValueError(f"bind needs a vpffd_addon.Lattice or Cage, got {type(lattice).__name__}")
    if depth is not None:
        raise ValueError("depth applies to cages only; a Lattice has no refinement")
    b = Binding()
    kernels = compiled.bind_kernels(lattice) if use_compiled else None
    # (the compiled layout makes the coordinates relative to the volume origins in its first pass)
    verts, tris, s, labels, rel = prepare(b, lattice, rest_verts, tris, influence, dtype, topology, kernels,
                                          relative=not kernels)
    V = b.n_verts

    # Sort by (island, cell); cut every run into blocks of `bs` slots (the last one padded). The
    # cell is the unclamped one of a local axis (in [-3, n + 2]): vertices outside the lattice
    # whose clamped taps differ do not share a run, so a run's slots share their taps exactly
    # (what the compiled solve needs, `solve_kernels`). A Bernstein or one-point axis has one.
    # With the kernels every axis is local.
    taps = None if kernels else _lattice_taps(lattice, verts, None)
    dims = ([n + 6 for n in lattice.shape] if kernels else
            [n + 6 if len(tap) > 2 else 1 for n, tap in zip(lattice.shape, taps)])
    n_cells = dims[0] * dims[1] * dims[2]
    n_keys = n_cells * b.n_islands
    run_cells = None                # (the unclamped cell of every run, (runs, 3), where local)
    sorting = None                  # (a counting sort to finish once the blocks are known)
    if kernels:
        verts = np.ascontiguousarray(verts)
        # (the row of `island_origin` of each vertex, as `compiled.vertex_rows`)
        rows = _NO_LABELS if len(b.island_origin) == 1 else np.ascontiguousarray(labels, np.int64)
    if kernels and n_keys <= max(4 * V, 1 << 16):
        # A counting sort over the keys (the same order), which also gives the runs; the cells
        # are made in its first pass (with the coordinates relative to the volume origins), and
        # every run's cells read back from its key. Its second pass (below, once the blocks are
        # known) places every vertex in the order and in its slot at once.
        islands = np.ascontiguousarray(labels, np.int64) if b.n_islands > 1 else _NO_LABELS
        start, rel, sorting = layout.cell_keys(kernels, verts, lattice, islands, np.array(dims, np.int64),
                                               n_keys, b.island_origin, rows)
        run_len = np.diff(start)
        keyed = np.flatnonzero(run_len > 0)
        run_start = start[:-1][keyed]
        run_len = run_len[keyed]
        cell = keyed % n_cells
        run_cells = np.stack([cell % dims[0], cell // dims[0] % dims[1], cell // (dims[0] * dims[1])], 1) - 3
    else:
        if kernels:
            taps = _lattice_taps(lattice, verts, kernels)
            rel = layout.relative(kernels, verts, b.island_origin, rows)
        cells = [tap[2] + 3 if len(tap) > 2 else np.zeros(V, np.int64) for tap in taps]
        cell = (cells[2] * dims[1] + cells[1]) * dims[0] + cells[0]
        key = cell if b.n_islands == 1 else labels * n_cells + cell
        order = stable_order(key) if int(key.max()) < 2 ** 32 else np.argsort(key, kind="stable")
        sorted_key = key[order]
        run_start = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
        run_len = np.diff(np.r_[run_start, V])
    for bs in _BLOCK_SIZES:
        blocks_per_run = -(-run_len // bs)
        if blocks_per_run.sum() * bs <= _MAX_PADDING * V:
            break
    n_blocks = int(blocks_per_run.sum())
    first_block = np.cumsum(blocks_per_run) - blocks_per_run
    n_slots = n_blocks * bs
    b.block_size = bs
    placed = None
    # The padding slots (each run's last block past its vertices): the compiled layout writes
    # every vertex's slot and zeros only these, instead of zeroing every slot first (a memset of
    # every slot array on every frame of a mesh moving through the lattice).
    pads = _ranges(first_block * bs + run_len, blocks_per_run * bs - run_len) if kernels else None
    if sorting is not None:
        base = np.zeros(n_keys, np.int64)
        base[keyed] = first_block * bs - run_start
        order, *placed = layout.place_slots(kernels, sorting, base, compiled.vertex_rings(b.topology, kernels)[0],
                                            n_slots, pads)
    runs = (order, run_start, run_len, first_block)
    local = kernels is not None or all(len(tap) > 2 for tap in taps)
    # For what is made on first use (`_LAZY`): the positions and weights as bound, copied where
    # they are the caller's own arrays (which the caller may change after the bind).
    b.source = tuple(a.copy() if given is not None and np.may_share_memory(a, given) else a
                      for a, given in ((verts, rest_verts), (s, influence)))
    if kernels:
        faces = _compiled_layout(b, lattice, verts, s, runs, n_blocks, rows, rel, kernels, pads, placed,
                                 measured_in)
    else:
        _numpy_blocks(b, taps, s, runs, n_blocks)
        if local:
            b.params = np.zeros((4, n_slots), b.dtype)
            for a in range(3):
                b.params[a, b.slot] = taps[a][3]
            b.params[3, b.slot] = s
        faces = None

    # Control points of each run (blocks of a run share them), from the run's first vertex.
    Ku, Kv, Kw = (tap_count(n, kind) for n, kind in zip(lattice.shape, lattice.interpolation))
    run_vertex = order[run_start]
    if local and run_cells is None:
        run_cells = np.stack([taps[a][2][run_vertex] for a in range(3)], 1)
    if kernels:     # (no taps stored: a local axis's first tap is clip(cell, 0, n - 1) - 1)
        firsts = [np.clip(run_cells[:, a], 0, n - 1) - 1 for a, n in enumerate(lattice.shape)]
    else:
        firsts = [tap[0][run_vertex] for tap in taps]
    grid = [np.clip(firsts[a][:, None] + np.arange(K), 0, lattice.shape[a] - 1)
            for a, K in enumerate((Ku, Kv, Kw))]
    nu, nv, _ = lattice.shape
    b.run_idx = ((grid[2][:, :, None, None] * nv + grid[1][:, None, :, None]) * nu
                 + grid[0][:, None, None, :]).reshape(len(run_len), Kw, Kv * Ku)
    b.block_run = np.repeat(np.arange(len(run_len)), blocks_per_run)
    b.run_first_block = first_block
    b.run_island = labels[run_vertex]
    b.block_island = b.run_island[b.block_run]
    if local:
        # The unclamped cell of every block (`solve_kernels` gathers its taps from it).
        b.block_cell = run_cells[b.block_run]

    finish(b, rel, tris, labels, n_slots, faces, measured_in)
    b.block_parts = parallel.split(n_blocks, V)
    if not kernels:                 # (the compiled layout counted them on its way)
        b.n_outside = lattice.outside_count(verts)
    return b


def _lattice_taps(lattice, verts, kernels):
    """The taps of the three axes (`bases.axis_taps`): (first (V,), w (V, K)) and, for a local
    axis, also its unclamped cell (V,) and t (V,) (`bases.axis_cells`). With `kernels` (every
    axis is then local) only the cells and t, by the compiled kernel. On the worker threads for a
    big mesh."""
    V = len(verts)
    if kernels:
        # The compiled solve computes the weights itself: only the cells and t (`first` and the
        # weights are None; a run's first tap is clip(cell, 0, n - 1) - 1), every axis of a part
        # of the vertices on each worker thread.
        return [(None, None) + cell_t for cell_t in layout.axis_cells(kernels, np.ascontiguousarray(verts), lattice)]
    cols = np.ascontiguousarray(verts.T)

    def taps_of(a):
        n, lo, hi, kind = lattice.shape[a], lattice.lo[a], lattice.hi[a], lattice.interpolation[a]
        first, w = axis_taps(cols[a], n, lo, hi, kind)
        if n == 1 or kind == "BEZIER":
            return first, w
        return (first, w) + axis_cells(cols[a], n, lo, hi)
    # The three axes are independent and NumPy and the kernels release the GIL: big meshes use
    # the worker threads.
    if V >= parallel.MIN_VERTS_PER_PART:
        return parallel.run(taps_of, [0, 1, 2])
    return [taps_of(a) for a in range(3)]


def _numpy_blocks(b, taps, s, runs, n_blocks):
    """Fill b.slot, b.wuv, b.ww and b.slot_influence from the per-vertex taps (NumPy). `runs`:
    (order (V,), run_start, run_len, first_block), the vertices sorted by (island, cell) and the
    runs of equal keys with their first blocks."""
    order, run_start, run_len, first_block = runs
    V, bs = b.n_verts, b.block_size
    run_of = np.repeat(np.arange(len(run_len)), run_len)               # run of each sorted vertex
    local = np.arange(V) - run_start[run_of]
    slot = np.empty(V, np.int64)
    slot[order] = (first_block[run_of] + local // bs) * bs + local % bs
    b.slot = slot
    _numpy_weights(b, taps, s, n_blocks)
    b.slot_influence = np.zeros(n_blocks * bs, b.dtype)
    b.slot_influence[slot] = s


def _numpy_weights(b, taps, s, n_blocks):
    """Fill b.wuv and b.ww (the stored weights of NumPy's products) from the per-vertex taps and
    influences s (V,), once b.slot is known."""
    V, bs, slot = b.n_verts, b.block_size, b.slot
    n_slots = n_blocks * bs
    Ku, Kv = taps[0][1].shape[1], taps[1][1].shape[1]
    # Stored per block as (K, block) so that products run along contiguous vertex rows. Built by
    # gathering each slot's vertex (padding slots read a zero row), straight into that layout.
    source = np.full(n_slots, V, np.int64)
    source[slot] = np.arange(V)
    source = source.reshape(n_blocks, bs)

    def per_block(w):
        padded = np.zeros((V + 1, w.shape[1]), b.dtype)
        padded[:V] = w
        return np.ascontiguousarray(padded[source].transpose(0, 2, 1))     # (n_blocks, K, bs)
    Wu, Wv = per_block(taps[0][1]), per_block(taps[1][1])
    b.wuv = (Wv[:, :, None, :] * Wu[:, None, :, :]).reshape(n_blocks, Kv * Ku, bs)
    b.ww = per_block(taps[2][1] * s[:, None])


def _ranges(starts, lengths):
    """The integers of the ranges [starts[i], starts[i] + lengths[i]) one after the other (int64
    arrays of one length, lengths >= 0)."""
    ends = np.cumsum(lengths)
    if not len(ends) or not ends[-1]:
        return np.zeros(0, np.int64)
    return np.arange(ends[-1], dtype=np.int64) + np.repeat(starts - (ends - lengths), lengths)


def _compiled_layout(b, lattice, verts, s, runs, n_blocks, rows, rel, kernels, pads, placed=None,
                     measured_in=None):
    """The slots, what every slot holds (the compiled solve's `params`, the influence and x0) and
    the faces' volumes (`face_volume_sums`; with `measured_in`, `volume.MeasuredIn`, measured from
    its points where its sums are not known yet, else not at all), by the compiled kernels on the
    worker threads; NumPy's stored weights are left to be made if something asks for them
    (`Binding._materialise`). The faces around every slot are made too (b.incidence, as
    `compiled.incidence`). `placed`: (slot, sorted_slot, where every slot's entries begin) where
    the counting sort made them (`layout.place_slots`). Returns what `slot_faces` returns."""
    bs, dt, n_slots = b.block_size, b.dtype, n_blocks * b.block_size
    around = compiled.vertex_rings(b.topology, kernels)
    if placed is None:
        b.slot, sorted_slot = np.empty(b.n_verts, np.int64), np.empty(b.n_verts, np.int64)
        layout.slots(kernels, runs, bs, b.slot, sorted_slot)
        start = np.zeros(n_slots + 1, np.int64)
        kernels["slot_incidence_start"](b.slot, around[0], start)
    else:
        b.slot, sorted_slot, start = placed
    # (every vertex's slot is written by `sorted_values`; the padding slots are zero)
    b.slot_influence, b.params, b.x0 = np.empty(n_slots, dt), np.empty((4, n_slots), dt), np.empty((3, n_slots), dt)
    b.slot_influence[pads] = 0
    b.params[:, pads] = 0
    b.x0[:, pads] = 0
    # (one island: only the terms' sums, in the chunks of `volume.chunked_sums`)
    face_vol = None if b.n_islands == 1 else np.empty(b.topology.tris_t.shape[1])
    known = measured_in is not None and measured_in.sums is not None
    if known:
        task, chunks = None, None
    elif measured_in is not None:
        task, chunks = layout.faces_task_about(b, measured_in.points, measured_in.origins, face_vol)
    else:
        task, chunks = layout.faces_task(b, rel, face_vol)
    # The faces around every slot too (`compiled.incidence`, which the compiled solve reads), in
    # the same hand-over: a mesh moving through the lattice needs them anew on every frame.
    incidence = (start, np.empty(len(around[1]), np.uint32), np.zeros(n_slots, np.int8))
    b.n_outside = layout.slot_values_and_faces(kernels, b, lattice, verts, s, runs[0], sorted_slot, rows, task,
                                               (around,) + incidence)
    b.incidence = incidence
    if not known:
        measured = ((None, np.cumsum(chunks, axis=0)[-1][:, None]) if face_vol is None
                    else (face_vol, _volume_sums(b, face_vol)))
        if measured_in is None:
            return measured
        face, sums = measured       # (the total as `volume.measure_about` makes it)
        measured_in.sums = (float(sums[0, 0]) if face is None else float(face.sum()), sums)
    return _measured(b, measured_in)


def stable_order(keys):
    """np.argsort(keys, kind="stable") for non-negative integer keys below 2**32, as two passes of
    NumPy's 16-bit radix sort (several times faster than a comparison sort of 32- or 64-bit keys)."""
    keys = np.asarray(keys)
    order = np.argsort((keys & 0xFFFF).astype(np.uint16), kind="stable")
    if keys.size and int(keys.max()) > 0xFFFF:
        high = (keys[order] >> 16).astype(np.uint16)
        order = order[np.argsort(high, kind="stable")]
    return order


def prepare(b, lattice, rest_verts, tris, influence, dtype, topology=None, kernels=None, relative=True):
    """Validate a bind's inputs and fill the binding's mesh facts; shared by every kind of binding.
    `topology` (a `Topology` of `tris`, or None to make one) carries what does not depend on the
    positions; `kernels` (`compiled.bind_kernels`) check and measure the positions in one pass
    where the topology is given (a re-embedding: every frame of a mesh moving through the
    lattice), with the same results.
    Returns (verts (V, 3), tris (F, 3), influence (V,), island labels (V,), coordinates relative
    to the volume origins (V, 3), or None unless `relative`)."""
    dtype = np.dtype(dtype)
    if dtype not in (np.float32, np.float64):
        raise ValueError(f"dtype must be float32 or float64, got {dtype}")
    measured = _measured_positions(rest_verts, topology, kernels)
    verts = measured[0] if measured is not None else check_verts(rest_verts, "rest_verts")
    V = len(verts)
    if topology is None:
        topology = Topology(tris, V, compiled.kernels() if kernels else None)
        if kernels:                 # (the positions in one pass, now that the islands are known)
            measured = _measured_positions(verts, topology, kernels)
    elif not isinstance(topology, Topology):
        raise ValueError(f"topology must be a vpffd_addon.Topology, got {type(topology).__name__}")
    elif topology.n_verts != V or not topology.matches(tris):
        raise ValueError("topology was made for other faces or another vertex count: make a new one")
    tris = topology.tris
    if influence is None:
        s = np.ones(V)
    else:
        s = np.asarray(influence, dtype=np.float64)
        if s.shape != (V,):
            raise ValueError(f"influence must have shape ({V},), got {s.shape}")
        if not np.isfinite(s).all():
            raise ValueError(f"influence has non-finite values at {int((~np.isfinite(s)).sum())} vertices")
    b.lattice, b.dtype, b.n_verts, b.n_faces = lattice, dtype, V, len(tris)
    b.topology = topology
    b.is_closed = topology.is_closed
    labels = topology.labels
    b.n_islands = topology.n_islands
    # Internal coordinates are relative to a volume origin per island.
    if b.is_closed:
        lo, hi = topology.island_bounds(verts) if measured is None else measured[1:3]
        b.island_origin = 0.5 * (lo + hi)
    else:
        b.island_origin = lattice.centre[None].copy()
    single = not b.is_closed or b.n_islands == 1
    if not relative:
        rel = None
    elif measured is None:
        rel = verts - (b.island_origin[0] if single else b.island_origin[labels])
    else:
        rel = layout.relative(kernels, verts, b.island_origin, _NO_LABELS if single else measured[3])
    return verts, tris, s, labels, rel


_NO_LABELS = np.zeros(0, np.int64)


def _measured_positions(rest_verts, topology, kernels):
    """(verts (V, 3) float64, lo, hi (k, 3) per island, labels) by the compiled `positions` pass
    when `kernels` are given with a matching `Topology` and the positions are a (V, 3) float32 or
    float64 array; else None (NumPy checks them). Raises as `check_verts` for non-finite ones."""
    if kernels is None or not isinstance(topology, Topology):
        return None
    v = rest_verts
    if not (isinstance(v, np.ndarray) and v.dtype in (np.float32, np.float64) and v.ndim == 2
            and v.shape[1] == 3 and len(v) == topology.n_verts and len(v)):
        return None
    v = np.ascontiguousarray(v)
    k = topology.n_islands
    labels = np.ascontiguousarray(topology.labels, dtype=np.int64) if k > 1 else _NO_LABELS
    out, lo, hi, bad = layout.positions(kernels, v, labels, k)
    if bad:
        check_verts(v, "rest_verts")     # raises, naming the vertices
    return out, lo, hi, labels


def _measured(b, measured_in):
    """What `slot_faces` returns, from `measured_in` (`volume.MeasuredIn`), measuring its sums in
    NumPy where they are not known yet (the compiled layout measures them in its hand-over
    first): (None, the binding's (2, k) sums, its total volume)."""
    if measured_in.sums is None:
        measured_in.sums = volume.measure_about(measured_in.points, measured_in.origins, b.topology)
    total, sums = measured_in.scaled()
    return None, sums, total


def slot_faces(b, rel, n_slots, measured_in=None):
    """The rest coordinates in slot order and the faces' volumes (from the coordinates relative to
    the volume origins `rel` (V, 3)), once `b.slot` (V,) is known, in NumPy: sets b.x0 (in the
    binding's precision: the same rounding as storing the float64 ones straight into it) and
    returns `face_volume_sums` (with `measured_in`: `_measured`)."""
    coords = np.zeros((3, n_slots))
    coords[:, b.slot] = rel.T
    b.x0 = coords.astype(b.dtype)
    return face_volume_sums(b, rel) if measured_in is None else _measured(b, measured_in)


def face_volume_sums(b, rel):
    """(face_vol (F,), sums (2, n_islands)): the faces' float64 volume terms in their own order
    from the coordinates relative to the volume origins `rel` (V, 3), and per island their sum and
    the sum of their absolute values (summed in the faces' own order, whatever laid the slots
    out), in NumPy (the compiled bind: `layout.slot_values_and_faces`, bit for bit the same)."""
    tris_t = b.topology.tris_t
    face_vol = np.empty(tris_t.shape[1])
    cols = np.ascontiguousarray(rel.T)

    def volumes(fs):
        face_vol[fs] = face_volumes(cols, tris_t[:, fs])
    parallel.run(volumes, parallel.split(tris_t.shape[1], b.n_verts))
    return face_vol, _volume_sums(b, face_vol)


def _volume_sums(b, face_vol):
    """(2, n_islands): per island the sum of the faces' volume terms face_vol (F,) and of their
    absolute values, in the faces' own order (one island: in `volume.chunked_sums`' order, as the
    compiled bind sums them)."""
    if b.n_islands == 1:
        return volume.chunked_sums(face_vol)[:, None]
    island = b.topology.face_island
    return np.stack([np.bincount(island, face_vol, b.n_islands),
                     np.bincount(island, np.abs(face_vol), b.n_islands)])


def corner_parts(b):
    """The faces as slot triples, one (3, F_part) array per worker part, ordered by the block of
    their lowest slot so that NumPy's gathers walk memory forwards (a stable sort: ties keep the
    faces' own order). Everything face-wise is kept as (3, F) rows: gathers of whole rows are
    several times faster than gathers of (F, 3) rows."""
    corners = np.take(b.slot, b.topology.tris_t)
    lowest = np.minimum(np.minimum(corners[0], corners[1]), corners[2])
    face_order = stable_order(lowest // getattr(b, "block_size", 1))
    corners = np.take(corners, face_order, axis=1)
    return [np.ascontiguousarray(corners[:, fs]) for fs in parallel.split(corners.shape[1], b.n_verts)]


def finish(b, rel, tris, labels, n_slots, faces=None, measured_in=None):
    """Store rest coordinates, faces and volumes once `b.slot` (V,) is known; `faces`: what
    `slot_faces` returned when it already ran ((face_vol, sums), or (None, sums, the total) for a
    volume measured elsewhere, `measured_in`)."""
    face_vol, sums, *total = faces if faces is not None else slot_faces(b, rel, n_slots, measured_in)
    b.vertex_parts = parallel.split(b.n_verts, b.n_verts)
    b.rest_island_volumes = sums[0]
    # (one island: its sum is this one, made the same way; a mesh moving through the lattice pays
    # for every pass over its faces on every frame)
    b.rest_volume = (float(total[0]) if total else float(sums[0][0]) if len(sums[0]) == 1
                     else float(face_vol.sum()))
    # The volume's rounding in the binding's precision: a few ulps of every face's term. An open
    # mesh far from the lattice centre, or a very small one, can enclose less than that.
    b.rest_volume_noise = 4 * float(np.finfo(b.dtype).eps) * sums[1]
    if not (np.isfinite(b.rest_island_volumes).all() and np.isfinite(b.rest_volume)):
        raise ValueError("rest_verts are too large: their volume overflows floating point")
    if not np.isfinite(b.x0).all():
        raise ValueError(f"rest_verts do not fit in {b.dtype.name}")
