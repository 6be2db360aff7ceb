"""One frame of a deformer in a modifier stack, as a pure function of that frame's inputs.

`FrameInputs` holds everything a frame's result depends on: the positions that reach the
deformer's slot (in the object's space), their faces, the lattice (or cage) with its evaluated
control points, the object-to-lattice matrix, the weights and the correction settings.
`Pipeline.evaluate` turns them into a `FrameResult`: the slot's output positions, the corrected
control points, the input and output volumes and the warnings. The pipeline keeps what is costly
to rebuild (the faces' `Topology`, the binding of the last embedding) as a cache whose keys hold
every input it was built from, so a result never depends on which frame was evaluated before.
See docs/stack.md for where this sits in Blender's evaluation.
"""
from dataclasses import dataclass, field

import numpy as np

from . import backends, compiled, lattice_eval, parallel
from .arrays import same_array
from .binder import bind
from .cage import Cage
from .outside import mode as outside_mode, outside_factor
from .jacobian import jacobian_det
from .lattice import Lattice
from .linalg3 import affine, affine_inverse, det3
from .mesh import Topology
from .offsets import float32_offsets
from .volume import MeasuredIn, origins_about


@dataclass(eq=False)
class FrameInputs:
    """The inputs of one frame (arrays are not copied; do not change them afterwards).

    positions: (V, 3) positions that reach the slot, in the object's space.
    tris: (F, 3) their triangles, or None when they are unknown (then the plain deformation only).
    lattice: a `Lattice` or `Cage` (its rest state); points: (N, 3) its evaluated control points
        in lattice space.
    matrix: (4, 4) object space -> lattice space.
    weights: (V,) per-position weight (vertex group), or None for 1.
    lattice_weights: (N,) weights of the lattice's own vertex group, or None. As in Blender's
        Lattice modifier, a position's influence is then multiplied by its weight times the
        lattice-interpolated group weight.
    strength: scales every displacement (Blender's Strength).
    correct: False for the plain deformation (Correction None, no pins).
    axes / directions, volume_scale, mobility (N,), pins [(vertex, target in lattice space)],
    islands: the correction, as for `Binding.solve`. The target volume is volume_scale times the
    volume that reaches the slot.
    cage_depth, cage_outside: for a `Cage`.
    dtype: the binding's float type.
    backend: the Backend setting (AUTO, CPU, NUMPY, GPU). Where no solver is given, the solve runs
        on the CPU backend that the registry chooses for it (`backends.cpu_preference`): the
        compiled kernels once they are loaded, NumPy (the reference) for NUMPY. NUMPY also lays
        the binding out with NumPy (`backends.compiled_layout`; either layout is bit for bit
        the other). With a solver, the correction's kernels are its.
    outside, falloff: what a lattice does to positions outside its rest box (`outside.py`, the
        table of modes: "FOLLOW" as Blender's Lattice modifier, "FALLOFF" fading out over
        `falloff` lattice-size units, "STAY" not at all); a factor on the influence, from the
        positions as they enter.
    target_volumes: the volume to keep, in the object's space, instead of the volume that reaches
        the slot (None): one number, or one per island with `islands` (e.g. the volume at Bind);
        volume_scale multiplies it. When its count does not match the islands that reach the
        slot, the frame keeps their own volume and says so in its warnings.
    """
    positions: np.ndarray
    tris: object
    lattice: object
    points: np.ndarray
    matrix: np.ndarray
    weights: object = None
    lattice_weights: object = None
    strength: float = 1.0
    correct: bool = True
    axes: str = "XYZ"
    directions: object = None
    volume_scale: float = 1.0
    mobility: object = None
    pins: list = field(default_factory=list)
    islands: bool = False
    cage_depth: int = 3
    cage_outside: str = "FOLLOW"
    dtype: object = np.float32
    backend: str = "AUTO"
    outside: str = "FOLLOW"
    falloff: float = 0.5
    target_volumes: object = None


class SlotOutput:
    """A frame's output positions, as the solve leaves them: `verts` (V, 3) float64 in lattice
    space, the map `back` (4, 4) into the object's space, and `still` (V,) bool or None: the
    positions that no influence moves, whose output is exactly their input `inputs` (V, 3) (not
    even the rounding of two transforms moves them). What a frame writes, its float32 offsets, is
    made from these in one pass (`float32_offsets`); the object-space positions themselves only
    when they are asked for (`positions`), as no frame in Blender needs them (docs/performance.md,
    "A frame's own passes")."""

    def __init__(self, verts, back, inputs, still=None):
        self.verts, self.back, self.inputs, self.still = verts, back, inputs, still
        self._positions = None

    @property
    def positions(self):
        """(V, 3) float64 in the object's space, made from the frame's arrays on first use, then
        kept (as `FrameInputs` says: do not change its arrays afterwards)."""
        if self._positions is None:
            out = _affine(self.verts, self.back)
            if self.still is not None:
                out[self.still] = np.asarray(self.inputs, dtype=np.float64)[self.still]
            self._positions = out
        return self._positions

    def float32_offsets(self, written=None):
        """`offsets.float32_offsets` of these positions against their inputs: (offsets (V, 3)
        float32, output (V, 3), changed against `written`, the largest |offset|)."""
        if self._positions is not None:
            return float32_offsets(self._positions, self.inputs, written)
        return float32_offsets(np.ascontiguousarray(self.verts, dtype=np.float64), self.inputs, written,
                               matrix=self.back, still=self.still)


@dataclass
class FrameResult:
    """What one frame gives. Positions in the object's space, points in lattice space."""
    slot: SlotOutput               #: the slot's output positions (`positions`, `float32_offsets`)
    points: np.ndarray             #: (N, 3) control points that produce it (strength applied)
    input_volume: float = None     #: volume that reaches the slot (None without faces)
    volume: float = None           #: volume of the output
    plain_volume: float = None     #: volume of the plain deformation
    warnings: tuple = ()
    binding: object = None         #: the binding used (None without faces)
    rebound: bool = False          #: whether this frame had to embed the positions anew
    solution: object = None        #: the `Solution` of a corrected frame
    outside: int = 0               #: positions outside the lattice's box (or the cage's region)
    falloff: int = 0               #: positions the falloff moves partly (0 < factor < 1)
    beyond: int = 0                #: positions beyond the falloff (or outside, Inside Only): factor 0
    still: int = 0                 #: positions with no influence at all, left exactly in place
    reference_volume: float = None  #: the volume aimed at before volume_scale: the input's, or
    #: the given target's (lattice space)
    target_given: bool = False     #: whether the given target_volumes were kept (not the input's)
    backend: str = None            #: the backend whose steps solved (`backends.py`; None: no solve)

    @property
    def positions(self):
        """(V, 3) float64 output of the slot, in the object's space."""
        return self.slot.positions

    def float32_offsets(self, written=None):
        """What the frame writes: (offsets (V, 3) float32 from the slot's input to its output,
        output (V, 3) as Blender adds them up, whether they differ from `written`, the largest
        |offset|), in one pass (`offsets.float32_offsets`)."""
        return self.slot.float32_offsets(written)


def _affine(points, mat):
    """`linalg3.affine` split over the worker threads (two of these a frame, each several passes
    over the whole mesh): (V, 3) float64."""
    points = np.asarray(points)
    parts = parallel.split(len(points), len(points))
    K = compiled.kernels()
    if K is not None and points.dtype in (np.float32, np.float64) and points.ndim == 2 \
            and points.shape[1:] == (3,):
        # One pass, bit for bit the same (`frame_kernels.affine`); NumPy's takes several.
        points = np.ascontiguousarray(points)
        m = np.ascontiguousarray(mat, dtype=np.float64)
        out = np.empty((len(points), 3))
        compiled.over("affine", parts, points, m, out, kernels=K)
        return out
    if len(parts) == 1:
        return affine(points, mat)
    out = np.empty((len(points), 3))

    def part(vs):
        out[vs] = affine(points[vs], mat)
    parallel.run(part, parts)
    return out


def _still(influence):
    """(the positions of no influence as a (V,) bool mask, or None where there are none; how many)."""
    still = influence == 0
    count = int(np.count_nonzero(still))
    return (still if count else None), count


class Pipeline:
    """Evaluates frames; holds the caches (topology, binding) between them.

    solver: optional callable ``solver(binding, points, options) -> Solution`` replacing
    `Binding.solve` (e.g. a GPU path); options are the keyword arguments of `Binding.solve`.
    """

    def __init__(self, solver=None):
        self.solver = solver
        self.topology = None
        self._faces = None
        self.binding = None
        self._binding_key = None
        self._last_space = None
        self._last_weights = None
        self._volume = None

    def clear(self):
        self.topology = self.binding = self._binding_key = self._faces = None
        self._last_space = self._last_weights = self._volume = None

    def _lattice_space(self, positions, M):
        """`positions` (V, 3) in lattice space, float64; the last frame's when its positions and
        matrix were the same (most frames of a lattice animation: only the lattice moves)."""
        X = np.asarray(positions)
        last = self._last_space
        if last is not None and last[1].shape == X.shape and np.array_equal(last[0], M) \
                and np.array_equal(last[1], X):
            return last[2]
        verts = _affine(X, M)
        self._last_space = (M.copy(), X.copy(), verts)
        return verts

    def _weights(self, weights, n):
        """(n,) float64 weights of this pipeline's own (never changed once returned): the last
        frame's very array while `weights` ((n,) or None for 1) are the same, so that the binding's
        key knows the influence by identity (a frame compares the float32 weights Blender hands
        over instead of converting and comparing float64 ones)."""
        last = self._last_weights
        if weights is None:
            if last is not None and last[0] is None and len(last[1]) == n:
                return last[1]
            out = np.ones(n)
        else:
            w = np.asarray(weights)
            if last is not None and last[0] is not None and last[0].shape == w.shape \
                    and last[0].dtype == w.dtype and np.array_equal(last[0], w):
                return last[1]
            out = np.array(w, dtype=np.float64)
            weights = w.copy()
        out.flags.writeable = False
        self._last_weights = (weights, out)
        return out

    def _topology(self, tris, n_verts, use_compiled=True):
        t = self.topology
        if t is None or t.n_verts != n_verts or not self._same_faces(tris):
            t = self.topology = Topology(tris, n_verts, compiled.kernels() if use_compiled else None)
            self._faces = tris
        return t

    def _same_faces(self, tris):
        """Whether `tris` are the faces of `self.topology`: the very array it was made from (the
        inputs are not changed after they are handed over, `FrameInputs`), or equal ones."""
        return tris is self._faces or self.topology.matches(tris)

    def _embed(self, inp, verts, influence):
        """(the binding of `verts` (lattice space), whether it was made anew, `_still(influence)`):
        reused when every input of it is unchanged (the influence among them, and with it which
        positions stay still)."""
        lat = inp.lattice
        cage = isinstance(lat, Cage)
        # A lattice is known by its values; a cage (large) by identity: the caller keeps one
        # `Cage` object while its rest state is unchanged.
        model = (("cage", id(lat), inp.cage_depth, inp.cage_outside) if cage else
                 ("lattice", lat.shape, lat.interpolation, lat.lo.tobytes(), lat.hi.tobytes()))
        key = (model, np.dtype(inp.dtype).name)
        old = self._binding_key
        if (old is not None and old[0] == key and self.binding is not None
                and (not cage or self.binding.lattice is lat)
                and old[1] is verts
                and (old[2] is influence or np.array_equal(old[2], influence)) and self.topology is not None
                and self._same_faces(inp.tris)):
            return self.binding, False, old[3]
        compiled_layout = backends.compiled_layout(inp.backend)
        topology = self._topology(inp.tris, len(verts), compiled_layout)
        extra = dict(depth=inp.cage_depth, outside=inp.cage_outside) if cage else {}
        if not cage and topology.is_closed:
            extra["measured_in"] = self._measured_in(inp, topology)
        self.binding = None   # never keep a binding whose inputs are not all in its key
        self.binding = bind(lat, verts, topology.tris, influence=influence, dtype=inp.dtype,
                            topology=topology, use_compiled=compiled_layout, **extra)
        if extra.get("measured_in") is not None:
            self._keep_volume(extra["measured_in"], topology)
        # `verts` is this pipeline's own array (`_lattice_space`, which never changes one it
        # returned, and returns it again while the positions and the matrix are unchanged): kept
        # as it is, the next frame's unchanged positions are known by identity. New positions
        # are a new array and are not compared with the old (a comparison of every vertex, 0.4 ms
        # a frame at 163,842 vertices, on every frame of a mesh moving through the lattice);
        # equal positions in a new array would only be embedded again, to the same binding.
        # (`influence` is the pipeline's own: its weights (`_weights`, known by identity next frame)
        # or an array made from them in `evaluate` that no one else holds)
        self._binding_key = (key, verts, influence, _still(influence))
        return self.binding, True, self._binding_key[3]

    def _measured_in(self, inp, topology):
        """A closed mesh's rest volume, measured in the object's space (the positions as handed
        over) and scaled into the lattice's: a `volume.MeasuredIn` with the sums kept from the
        last bind where the positions are the same (a mesh that only moves, or a lattice that
        moves over it, measures its faces once). Measured again or kept, the sums are the same
        bits: they depend on the positions alone (docs/performance.md, "The volume of a mesh that
        only moves")."""
        X = np.ascontiguousarray(inp.positions)
        if X.dtype not in (np.float32, np.float64):
            X = X.astype(np.float64)
        det = det3(np.asarray(inp.matrix, dtype=np.float64)[:3, :3])
        kept = self._volume
        if kept is not None and kept[0] is topology and same_array(kept[1], X):
            return MeasuredIn(X, det, kept[2], kept[3])
        origins = origins_about(X, topology)
        if not np.isfinite(origins).all():
            return None     # (non-finite positions: the bind says which, in words)
        return MeasuredIn(X, det, origins)

    def _keep_volume(self, measured, topology):
        """Keep what `_measured_in` compares the next positions with: a copy of this frame's
        positions (the caller's next ones may come in the same buffer), the one `_lattice_space`
        made of them in this `evaluate` where it is of the same type."""
        kept = self._volume
        if kept is None or kept[3] is not measured.sums:
            own = self._last_space[1]
            if own.dtype != measured.points.dtype or own.shape != measured.points.shape:
                own = measured.points.copy()
            self._volume = (topology, own, measured.origins, measured.sums)

    def evaluate(self, inp):
        """The `FrameResult` of `inp`. Raises ValueError for inputs that give no defined result."""
        M = np.asarray(inp.matrix, dtype=np.float64)
        lat = inp.lattice
        if not isinstance(lat, (Lattice, Cage)):
            raise ValueError(f"lattice must be a Lattice or a Cage, got {type(lat).__name__}")
        grid = lat.rest_points
        P = np.asarray(inp.points, dtype=np.float64)
        if P.shape != grid.shape:
            raise ValueError(f"points must have shape {grid.shape}, got {P.shape}")
        verts = self._lattice_space(inp.positions, M)
        weights = self._weights(inp.weights, len(verts))
        influence = weights
        if inp.lattice_weights is not None:
            if isinstance(lat, Cage):
                raise ValueError("a cage has no lattice vertex group")
            # Blender's Lattice modifier blends each position by its own weight times the lattice
            # group's weights interpolated with the lattice's basis (docs/stack.md).
            lw = lattice_eval.interpolate(lat, verts, np.asarray(inp.lattice_weights, np.float64))
            influence = weights * (weights * inp.strength) * lw
        factor = None
        if isinstance(lat, Lattice) and outside_mode(inp.outside).factor is not None:
            factor = outside_factor(lat, verts, inp.outside, inp.falloff)
            influence = influence * factor
        # Strength scales every displacement alike: it scales the control points' displacement.
        P_used = grid + float(inp.strength) * (P - grid)
        back = affine_inverse(M)
        if not np.isfinite(back).all():
            raise ValueError("matrix is singular: the object or the lattice is scaled to zero along an axis")
        if inp.tris is None:
            if inp.correct:
                raise ValueError("no faces: the volume cannot be corrected")
            out = verts + influence[:, None] * lattice_eval.interpolate(lat, verts, P_used - grid)
            outside = lat.outside_count(verts) if isinstance(lat, Lattice) else 0
            still, n_still = _still(influence)
            return FrameResult(slot=SlotOutput(out, back, inp.positions, still), points=P_used,
                               outside=outside, still=n_still)
        binding, rebound, (still, n_still) = self._embed(inp, verts, influence)
        # Without a solver of the caller's, and for the plain deformation, the CPU solves: the
        # registry's choice for the Backend setting on the CPU (NumPy alone for NUMPY).
        cpu_steps = backends.choose(backends.cpu_preference(inp.backend), binding)[0].steps
        warnings = []
        solution = None
        reference, target_given = binding.rest_volume, False
        if inp.correct:
            options = dict(axes=inp.axes, directions=inp.directions, volume_scale=inp.volume_scale,
                           preserve_volume=bool(inp.axes or inp.directions is not None),
                           mobility=inp.mobility, pins=inp.pins, islands=inp.islands)
            if inp.target_volumes is not None:
                target = np.asarray(inp.target_volumes, dtype=np.float64).reshape(-1)
                if target.shape == ((binding.n_islands,) if inp.islands else (1,)):
                    # Volumes in lattice space are the object's times det(M) (M: object -> lattice).
                    options["target_volumes"] = target * float(det3(M[:3, :3]))
                    reference, target_given = float(options["target_volumes"].sum()), True
                else:
                    warnings.append(f"the target holds {target.size} island volume(s), but "
                                    f"{binding.n_islands} island(s) reach VP-FFD: keeping their own "
                                    "volume on this frame")
            try:
                solution = (self.solver(binding, P_used, options) if self.solver is not None
                            else binding.solve(P_used, steps=cpu_steps, **options))
            except ValueError as exc:
                # No correction is possible on this frame: it shows the plain deformation, as the
                # Lattice modifier would, and says why; the next frame is solved afresh.
                warnings.append(f"the volume is not corrected on this frame: {exc}")
        if solution is not None:
            out, used, volume, plain = solution.verts, solution.points, solution.volume, solution.plain_volume
            warnings.extend(solution.warnings)
            backend = solution.backend
        else:
            sol = binding.solve(P_used, axes="", preserve_volume=False, steps=cpu_steps)
            out, used, volume, plain = sol.verts, P_used, sol.volume, sol.plain_volume
            backend = sol.backend
        falloff = 0 if factor is None else int(((factor > 0) & (factor < 1)).sum())
        beyond = 0 if factor is None else int((factor == 0).sum())
        return FrameResult(slot=SlotOutput(out, back, inp.positions, still), points=used,
                           input_volume=binding.rest_volume,
                           volume=volume, plain_volume=plain, warnings=tuple(warnings),
                           binding=binding, rebound=rebound, solution=solution,
                           outside=int(binding.n_outside), falloff=falloff, beyond=beyond, still=n_still,
                           reference_volume=reference, target_given=target_given, backend=backend)

    @staticmethod
    def folds(result):
        """Vertices of a frame's result where the deformation folds space (Jacobian det <= 0)."""
        if result.binding is None:
            return None
        return int((jacobian_det(result.binding, result.points) <= 0).sum())
