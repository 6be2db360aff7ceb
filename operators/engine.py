"""Runtime of bound objects: the thin layer between Blender and `vpffd_addon.Pipeline`.

Every update reads what reached the VP-FFD slot (the modifier's tap), the evaluated lattice and the
settings, hands them to the pipeline, and writes the resulting offsets into the modifier's solver
helper; Blender then evaluates the object again with them (docs/stack.md). Everything a bound
object needs survives in the .blend: the settings (`obj.vpffd`), the mesh's own coordinates (never
written), the VP-FFD modifier and its solver helper (which also keeps what Bind saves: pins, a
cage's rest shape). The pipeline's caches are rebuilt on demand, e.g. after loading a file.
"""
import dataclasses
import logging
import time
from typing import Optional

import numpy as np

from .. import vpffd_addon as vp
from ..vpffd_addon import cage_cells, lattice_space, linalg3, wireframe
from ..vpffd_addon import outside as outside_modes
from ..vpffd_addon.frame_key import FrameKey
from ..vpffd_addon.steps import NumpySteps
from . import cage, compiled_backend, gpu_backend, meshio, modifier
from .cache_modifier import find_cache, using_cache
from .status_line import open_mesh_words
from .text import percent

log = logging.getLogger(__name__)

LEGACY_ATTRIBUTES = ("vpffd_offset", "vpffd_weight")  # written by earlier versions
PIN_ATTRIBUTE = "vpffd_pin"         # pinned vertices, in files of earlier versions
PIN_PROPERTY = "vpffd_pins"         # on the solver helper: the pinned vertices' indices
JACOBIAN_ATTRIBUTE = "vpffd_jacobian"  # det of the deformation's Jacobian (on request)
CAGE_REST_PROPERTY = "vpffd_cage_rest"  # on the helper: the cage's points at Bind, flat, cage space
BIND_VOLUME_PROPERTY = "vpffd_bind_volumes"  # on the helper: each island's volume at Bind (object space)
FOLD_CHECK_MAX_VERTS = 5000         # above this, folds are counted on request only (Check Folds)

_cache = {}   # object session_uid -> _Bound
_stats = {}   # object session_uid -> Status shown by the panel


class BindError(ValueError):
    """A problem the user must fix before binding (the message says what)."""


@dataclasses.dataclass
class Status:
    """What the last update of an object found: the panel shows these fields. Volumes are
    percentages of the reference volume: the volume that reached the VP-FFD slot, or with
    Target: Bind the volume at Bind; None where not known."""
    error: Optional[str] = None            #: why nothing (or only the input) is shown, in words
    switched_off: bool = False             #: the modifier is off in the viewport
    paused: Optional[str] = None           #: why VP-FFD is not solving now (no figures then)
    warnings: tuple = ()                   #: what the solve could not do, in words
    volume_percent: Optional[float] = None
    plain_percent: Optional[float] = None  #: what the plain Lattice modifier would give
    input_volume: Optional[float] = None   #: in lattice space
    seconds: Optional[float] = None        #: the whole update
    core_seconds: Optional[float] = None   #: the frame pipeline alone
    backend: str = "CPU"
    backend_reason: str = ""
    n_verts: Optional[int] = None          #: points that reached the slot
    closed: Optional[bool] = None          #: whether their faces close a volume
    encloses_nothing: bool = False         #: open, with no volume about the lattice's centre
    mirrored: bool = False                 #: the lattice turns the volume's sign (a mirror)
    folds: Optional[int] = None            #: vertices where the lattice folds space
    rebound: bool = False                  #: whether this update embedded the input anew
    outside: Optional[int] = None          #: points outside the lattice's box or cage's region
    outside_follow: bool = True            #: whether those follow the boundary (else they stay)
    outside_mode: str = "FOLLOW"           #: the lattice's Outside setting as solved
    falloff: Optional[int] = None          #: points outside that the falloff moves partly
    still: Optional[int] = None            #: points with no influence (left exactly in place)
    beyond: Optional[int] = None           #: points the Outside setting keeps still
    target_from: Optional[str] = None      #: "bind" when the volume at Bind is the reference
    input_percent: Optional[float] = None  #: the input's volume, with Target: Bind
    editing: bool = False                  #: solved from the mesh as edited (its Edit Mode)
    kernels: Optional[str] = None          #: on the CPU: "compiled" or "NumPy"
    kernels_why: Optional[str] = None      #: why NumPy's kernels ran, in words
    awaits_kernels: bool = False           #: NumPy solved while the compiled kernels compiled


def status(obj):
    """The typed `Status` of the object's last update (an empty one before any)."""
    return _stats.get(obj.session_uid) or Status()


def stats(obj):
    """`status(obj)` as a dict of the fields that are set (for scripts)."""
    return {k: v for k, v in dataclasses.asdict(status(obj)).items() if v is not None}


_reported = {}  # object session_uid -> last error printed, so a failing frame range logs once


def _set_stats(obj, **values):
    st = _stats[obj.session_uid] = Status(**values)
    if st.error and _reported.get(obj.session_uid) != st.error:
        log.warning("%s: %s", obj.name, st.error)  # the console and farm logs, once per new problem
    _reported[obj.session_uid] = st.error
    return st


def forget(obj=None):
    """Drop cached bindings (all, or one object's)."""
    states = list(_cache.values()) if obj is None else [_cache.get(obj.session_uid)]
    for state in states:
        if state is not None:
            state.free()
    if obj is None:
        _cache.clear()
        _stats.clear()
        _reported.clear()
    else:
        for table in (_cache, _stats, _reported):
            table.pop(obj.session_uid, None)


def relink_after_undo(obj, objects):
    """Point a bound object back at the lattice it lost to Delete when undo brought that lattice
    back. VP-FFD lets go of a deleted lattice in its update handler, after Delete's undo step was
    written, so the step before Delete holds the same object data as the step of Delete and
    Blender's undo keeps the object as it is in memory, link cleared (Blender clears its own
    modifier's link inside the operator, before the step is written). `objects`: bpy.data.objects.
    Returns True when the link was restored."""
    state = _cache.get(obj.session_uid)
    if state is None or not state.deleted or obj.vpffd.lattice is not None or not obj.vpffd.is_bound:
        return False
    back = objects.get(state.deleted)
    if not _is_control(back) or not any(True for _ in back.users_scene):
        return False
    obj.vpffd.lattice = back        # its update callback points the modifier's input at it too
    state.deleted = None
    return True


def invalidate():
    """Make the next update of every object solve again (after undo, redo): the solves' inputs
    may be restored to other values, the helpers to other offsets. Caches stay."""
    for state in _cache.values():
        state.signature = None
        state.written = None


def _float_attribute(mesh, name, values=None):
    """Write (V,) float point attribute `name`, or read it (None when missing)."""
    attr = mesh.attributes.get(name)
    if values is None:
        if attr is None or attr.data_type != "FLOAT" or len(attr.data) != len(mesh.vertices):
            return None
        out = np.empty(len(mesh.vertices), np.float32)
        attr.data.foreach_get("value", out)
        return out.astype(np.float64)
    data = meshio.float32_or_raise(values, f"the values of '{name}'")
    if attr is not None:
        mesh.attributes.remove(attr)
    attr = mesh.attributes.new(name, "FLOAT", "POINT")
    attr.data.foreach_set("value", data)
    return attr


def _is_control(ob):
    """Whether `ob` can deform a bound mesh: a Lattice object or a VP-FFD cage mesh."""
    return ob is not None and (ob.type == "LATTICE" or cage.is_cage(ob))


def _missing_control(ob):
    """What is wrong with `ob` as the lattice setting (it is not `_is_control`), in words."""
    if ob is not None and ob.type == "MESH":
        return (f"mesh '{ob.name}' is not a VP-FFD cage (it has no cells): make one with "
                "Add > VP-FFD Cage, or pick a Lattice object")
    return "the lattice is missing: pick a Lattice object or a VP-FFD cage, or Unbind"


def _cage_points(cage_eval, n_points):
    """(N, 3) evaluated cage points (shape keys, hooks, armatures and modifiers applied)."""
    points = meshio.mesh_coords(cage_eval.data)
    if len(points) != n_points:
        # In Edit Mode the evaluated mesh wraps the edit mesh and lists no vertices: convert it.
        try:
            points = meshio.mesh_coords(cage_eval.to_mesh())
        finally:
            cage_eval.to_mesh_clear()
    if len(points) != n_points:
        raise ValueError(f"cage '{cage_eval.name}' evaluates to {len(points)} points instead of "
                         f"{n_points}: remove modifiers that add or remove its vertices")
    return points


def _saved(helper, obj, name):
    """What Bind saved under `name`: on the solver helper (or on the mesh, in earlier versions)."""
    value = helper.get(name) if helper is not None else None
    return obj.data.get(name) if value is None else value


def _cage_model(state, obj, cage_ob, helper):
    """(vp.Cage at bind time, its rest points (N, 3), key) for a bound mesh, cached per object."""
    flat = tuple(cage_ob.data[cage.CELLS_PROPERTY].to_list())
    rest = _saved(helper, obj, CAGE_REST_PROPERTY)
    if rest is None:
        raise ValueError("the mesh was bound to another kind of lattice: Re-bind")
    rest = np.array(rest.to_list(), np.float64).reshape(-1, 3)
    key = (hash(flat), rest.tobytes())
    if state.cage_key != key:
        cells = cage_cells.decode_cells(flat)
        if len(rest) != len(cage_ob.data.vertices):
            raise ValueError(f"cage '{cage_ob.name}' has {len(cage_ob.data.vertices)} points, "
                             f"{len(rest)} when bound: Re-bind")
        state.cage_model, state.cage_key = vp.Cage(rest, cells), key
    return state.cage_model, rest, ("cage", key[0])


class _Bound:
    """Cached per-object state: the frame pipeline (topology and binding caches), the faces of
    the slot's input, the last solve's signature, result and overlay. Nothing in it is needed for
    a frame's result to be right: it only saves work (docs/stack.md)."""

    def __init__(self):
        self.pipeline = vp.Pipeline(solver=self._solve)
        self.faces = self.faces_key = None
        self.signature = None
        self.result = None
        self.output = None      # (V, 3) float32 slot output of the last solve
        self.moved = 0.0        # the largest offset of the last solve (tells Apply from removal)
        self.written = None     # offsets last written to the solver helper
        self.overlay = None
        self.gpu = None         # GPUSolver for the current binding, made on first GPU use
        self.gpu_binding = None
        self.last_binding = None  # the binding of the last solve (Auto uploads one used twice)
        self.backend = ("CPU", "")
        self.matrix = None      # object -> lattice space of the last solve
        self.falloff_box = None  # world corners (8, 3) of the falloff's outer box, for the overlay
        self.orientation = 1.0  # -1 while the lattice mirrors space (folds count against it)
        self.encloses_nothing = False  # the last input had no volume to keep (`_evaluate`)
        self.costs = {}         # last solve's seconds per (path, vertices, options) for Auto
        self.settings = None
        self.deleted = None     # name of the lattice that the user deleted, for the panel
        self.cage_model = self.cage_key = None

    @property
    def binding(self):
        return self.pipeline.binding

    @property
    def points(self):
        return None if self.result is None else self.result.points

    def free(self):
        if self.gpu is not None:
            self.gpu.free()
            self.gpu = self.gpu_binding = None

    def _solve(self, binding, P, options):
        """The pipeline's solver: the GPU path when the settings' backend and the machine allow
        it (and for Auto, when this mesh's GPU solves measure faster than its CPU solves), else (or
        when it fails) the CPU path: the compiled kernels when loaded, or NumPy's alone for
        CPU (NumPy)."""
        s = self.settings
        fresh = binding is not self.gpu_binding and binding is not self.last_binding
        self.last_binding = binding
        if s.backend == "NUMPY":
            self.backend = ("CPU", "")
            return binding.solve(P, steps=NumpySteps, **options)
        use_gpu, why = gpu_backend.choose(s.backend, binding.n_verts, options, binding, fresh)
        key = (binding.n_verts, options["axes"], options["directions"] is not None, options["islands"])
        if use_gpu and s.backend == "AUTO":
            use_gpu, why = self._measured(key, why)
        if use_gpu:
            try:
                if self.gpu is None or self.gpu_binding is not binding:
                    self.free()
                    self.gpu, self.gpu_binding = gpu_backend.GPUSolver(binding), binding
                sol = self.gpu.solve(P, **options)
                self.backend = ("GPU", why)
                self.costs[("GPU",) + key] = sol.seconds
                return sol
            except gpu_backend.GPUUnavailable as exc:
                self.free()
                why = f"the GPU failed, using the CPU: {exc}"
        self.backend = ("CPU", why)
        sol = binding.solve(P, **options)
        self.costs[("CPU",) + key] = sol.seconds
        return sol

    def _measured(self, key, why):
        """Auto's last word once both paths have solved this mesh with these options: (use_gpu,
        reason). The GPU stays in use while its last solve was no slower than the CPU's."""
        gpu, cpu = self.costs.get(("GPU",) + key), self.costs.get(("CPU",) + key)
        if gpu is None or cpu is None or gpu <= cpu:
            return True, why
        return False, (f"Auto chose the CPU: it solved this mesh in {1e3 * cpu:.1f} ms, the GPU "
                       f"in {1e3 * gpu:.1f} ms")


def _pins(s, obj, helper):
    """(k,) indices of the pinned vertices of the mesh (saved at Bind)."""
    if s.pin_mode == "NONE":
        return np.zeros(0, np.int64)
    saved = helper.get(PIN_PROPERTY)
    if saved is not None:
        return np.array(saved.to_list() if hasattr(saved, "to_list") else saved, np.int64)
    pins = _float_attribute(obj.data, PIN_ATTRIBUTE)        # a file bound by an earlier version
    return np.zeros(0, np.int64) if pins is None else np.flatnonzero(pins > 0)


def _bind_target(s, helper, warnings):
    """The volumes Target: Bind keeps (object space; one per island with Per-Island Volume, else
    their sum), or None for Target: Input or when none were captured (a warning then says so)."""
    if s.target != "BIND":
        return None
    saved = helper.get(BIND_VOLUME_PROPERTY)
    if saved is None:
        warnings.append("Target is Bind, but no volume was captured at Bind (bound by an earlier "
                        "version): keeping the input's volume; Re-bind to capture it")
        return None
    volumes = np.array(saved.to_list() if hasattr(saved, "to_list") else saved, np.float64)
    return volumes if s.use_islands else np.array([volumes.sum()])


def _pin_targets(s, pins, X, lat_matrix):
    """[(vertex, target in lattice space)] for the pinned vertices (`lattice_space.pin_targets`)."""
    if len(pins) == 0:
        return []
    if s.pin_target is None:
        raise ValueError("pins need a target Empty (Pin Target)")
    return lattice_space.pin_targets(pins, X, lat_matrix, meshio.matrix(s.pin_target.matrix_world),
                                     s.pin_target_rest, s.pin_mesh_rest)


# Lattice data read in Object Mode. In a lattice's Edit Mode, `LatticePoint.co` holds garbage and
# `LatticePoint.groups` reads out of bounds (it can crash Blender): there, the rest grid and the
# group weights come from the last Object Mode read (or from Bind), never from the points.
_lattice_reads = {}   # lattice data session_uid -> {"grid": (N, 3), "groups": {name: (N,)}}


def _lattice_entry(lat_ob):
    return _lattice_reads.setdefault(lat_ob.data.session_uid, {"grid": None, "groups": {}})


def _lattice_rest(lat_ob, s):
    """(vp.Lattice, rest grid (N, 3)) of a Lattice object; safe in the lattice's Edit Mode."""
    data = lat_ob.data
    shape = (data.points_u, data.points_v, data.points_w)
    interp = (data.interpolation_type_u, data.interpolation_type_v, data.interpolation_type_w)
    entry = _lattice_entry(lat_ob)
    if not data.is_editmode:
        entry["grid"] = meshio.lattice_points(data, "co")
    grid = entry["grid"]
    if grid is None or len(grid) != len(data.points):
        lattice = vp.Lattice(shape, interp, bounds=(s.lattice_rest_lo, s.lattice_rest_hi))  # Bind's
        return lattice, lattice.rest_points
    return vp.Lattice(shape, interp, bounds=(grid.min(0), grid.max(0))), grid


def _lattice_group(lat_ob, name):
    """(N,) weights of vertex group `name` of the lattice or cage, or raise ValueError. Read in
    Object Mode only (see `_lattice_reads`)."""
    if lat_ob.type != "LATTICE":
        return meshio.lattice_group_weights(lat_ob, name)
    entry = _lattice_entry(lat_ob)
    if not lat_ob.data.is_editmode:
        weights = meshio.lattice_group_weights(lat_ob, name)
        entry["groups"][name] = weights
        return weights
    weights = entry["groups"].get(name)
    if weights is None or len(weights) != len(lat_ob.data.points):
        raise ValueError(f"the weights of vertex group '{name}' are read in Object Mode: leave the "
                         "lattice's Edit Mode once")
    return weights


def _lattice_weights(lat_ob):
    """(N,) weights of the lattice's own vertex group (Lattice > Vertex Group), or None."""
    if lat_ob.type != "LATTICE" or not lat_ob.data.vertex_group:
        return None
    if lat_ob.vertex_groups.get(lat_ob.data.vertex_group) is None:
        return None              # a name the lattice lacks: Blender's modifier ignores it too
    return _lattice_group(lat_ob, lat_ob.data.vertex_group)


def _mobility(s, lattice_object):
    """(N,) mobility from a vertex group of the lattice or cage, or None."""
    if not s.mobility_group:
        return None
    return _lattice_group(lattice_object, s.mobility_group)


def _faces(state, obj, ob_eval, n, tapped, mod, may_write, editing=False):
    """((F, 3) triangles of the `n` positions that reach the slot or None when unknown, where
    they came from: "mesh", "final", "tap" or None).

    Deform-only modifiers before the slot keep the mesh's own topology (same vertex count); when
    modifiers before it change the count, the faces are those of the evaluated mesh at the end of
    the stack, provided that nothing after the slot changed the count again; otherwise the
    modifier is asked to pass the triangles of its input along (its Tap Faces input, which costs a
    triangulation per evaluation, so it is on only while needed). `tapped`: the triangles that
    came with the tap, or None.

    In the mesh's Edit Mode the mesh's own data is not the edited mesh (Blender writes it back on
    leaving), so the faces come with the tap; on the update that enters Edit Mode, before the tap
    brings them, the edited mesh is still the one last solved, and so are its faces."""
    mesh = obj.data
    if editing:
        if may_write:
            modifier.set_input(mod, modifier.FACES_INPUT, True)
        if tapped is not None and len(tapped) and int(tapped.max()) < n:
            return tapped, "tap"
        if state.faces is not None and len(state.faces) and int(state.faces.max()) < n:
            return state.faces, state.faces_key[0]
        return None, None
    if n == len(mesh.vertices):
        source, key = mesh, ("mesh", meshio.topology_signature(mesh))
    else:
        final = ob_eval.data
        if final is None or len(final.vertices) != n:
            if may_write:
                modifier.set_input(mod, modifier.FACES_INPUT, True)
            if tapped is not None and len(tapped) and int(tapped.max()) < n:
                return tapped, "tap"
            return None, None
        source, key = final, ("final", meshio.topology_signature(final))
    if may_write:
        modifier.set_input(mod, modifier.FACES_INPUT, False)
    if state.faces_key != key:
        state.faces, state.faces_key = meshio.mesh_triangles(source), key
    return state.faces, key[0]


def _zero_offsets(obj, state=None):
    """Show the slot's input undeformed (a defined result for a frame that cannot be solved)."""
    mod = modifier.find(obj)
    helper = modifier.get_input(mod, modifier.SOLVER_INPUT) if mod is not None else None
    if helper is None or helper.get(modifier.HELPER_TAG) is None:
        return
    if len(helper.data.vertices):
        modifier.write_offsets(helper, np.zeros((0, 3), np.float32))
    if state is not None:
        state.written = None


def _write(state, helper, offsets):
    """Write offsets to the helper unless it already holds exactly these (every write makes
    Blender evaluate the object again, and the handler runs again after it)."""
    values = meshio.float32_or_raise(offsets, "the offsets").reshape(-1, 3)
    if state.written is not None and np.array_equal(state.written, values) \
            and len(helper.data.vertices) == len(values):
        return values
    modifier.write_offsets(helper, values)
    state.written = values
    return values


def _pause(obj, **why):
    """Nothing is solved now (`why`: paused=text or switched_off=True): the panel shows no
    figures, since they would be those of another state; the next update solves again."""
    _set_stats(obj, **why)
    state = _cache.get(obj.session_uid)
    if state is not None:
        state.signature = None


def update(obj, depsgraph, force=False):
    """Solve the current frame for a bound object and write its offsets. Never raises: problems
    go to the panel (`status(obj).error`) and the console. Returns True when a solve ran.
    `force` solves even when the inputs did not change and the modifier is switched off (Bind,
    Apply, Check Folds and Bake need the solve)."""
    # Overflow is detected on the results and reported in words; NumPy's own warnings would only
    # repeat it on the console for every frame.
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        return _update(obj, depsgraph, force)


def _evaluated_here(obj, depsgraph):
    """Whether `depsgraph` evaluates `obj` at all: visible in its view layer (the viewport), or
    enabled for renders (a render evaluates what renders)."""
    try:
        if depsgraph.mode == "RENDER":
            return _renders(obj, depsgraph.view_layer)
        return bool(obj.visible_get(view_layer=depsgraph.view_layer))
    except (ReferenceError, RuntimeError, TypeError):
        return True


@dataclasses.dataclass
class _Frame:
    """What Blender hands over for one update of a bound object, ready for the core."""
    helper: object              #: its solver helper, where the offsets go
    inputs: "vp.FrameInputs"
    signature: FrameKey         #: matching keys give equal results
    faces_from: Optional[str]   #: "mesh", "final", "tap" or None (see `_faces`)
    lattice_matrix: np.ndarray  #: (4, 4) world matrix of the lattice object
    warnings: list
    stale_weights: bool         #: the vertex-group input changed: solve again next evaluation
    editing: bool               #: the mesh is in Edit Mode


def _renders(obj, view_layer):
    """Whether a render of `view_layer` renders `obj`: not hidden from renders itself, and in a
    collection that is neither excluded from the view layer nor hidden from renders, nor below
    one that is."""
    if obj.hide_render:
        return False
    stack = [view_layer.layer_collection]
    while stack:
        layer_collection = stack.pop()
        if layer_collection.exclude or layer_collection.collection.hide_render:
            continue
        if layer_collection.collection.objects.get(obj.name) == obj:
            return True
        stack.extend(layer_collection.children)
    return False


def _update(obj, depsgraph, force, helpers_taken=None):
    """One update in three steps: read what Blender hands over (`_read`), evaluate the core's
    pipeline on it (`_evaluate`), publish the result: offsets, panel figures, overlay (`_publish`)."""
    state = None
    try:
        mod = _slot_to_solve(obj, depsgraph, force)
        if mod is None:
            return False
        state = _cache.get(obj.session_uid)
        if state is None:
            state = _cache[obj.session_uid] = _Bound()
        frame = _read(obj, state, mod, depsgraph, helpers_taken)
        if frame is None or (not force and _unchanged(state, frame)):
            return False
        t0 = time.perf_counter()
        result = _evaluate(state, frame)
        _publish(obj, state, frame, result, t0)
        return True
    except Exception as exc:  # a handler must never raise into Blender
        try:
            _zero_offsets(obj, state)   # a defined result: the slot's input, undeformed
        except Exception:
            pass
        if state is not None:
            state.signature = None
        _set_stats(obj, error=f"{type(exc).__name__}: {exc}" if not isinstance(exc, ValueError) else str(exc))
        return False


def _slot_to_solve(obj, depsgraph, force):
    """The VP-FFD modifier of `obj` when this evaluation should solve it; else None, with the
    panel told why (removed, switched off, hidden)."""
    if not obj.vpffd.is_bound:
        return None
    mod = modifier.find(obj)
    rendering = depsgraph.mode == "RENDER"
    if mod is None:
        if not rendering:
            # Removed (X on the modifier) or applied (Ctrl+A): as with any modifier, the object
            # is no longer deformed by it. Its settings stay for a later Bind.
            release(obj)
        return None
    if not force and not (mod.show_render if rendering else mod.show_viewport):
        if not rendering:
            # Switched off in the viewport: the panel says so instead of an error or figures of
            # an earlier solve; switching it on solves again.
            _pause(obj, switched_off=True)
        return None  # switched off for this evaluation, like any modifier
    if not force and not _evaluated_here(obj, depsgraph):
        # Hidden (H, Disable in Viewports, a hidden or excluded collection): Blender does not
        # evaluate it, so nothing reaches the slot. Keep the offsets shown last and solve again
        # when it is shown: it comes back as it was, with no error.
        if not rendering:
            _pause(obj, paused="the object is hidden: VP-FFD solves again when it is shown")
        return None
    return mod


def _control(obj, state, depsgraph):
    """The bound object's Lattice or cage, or None (zero offsets shown, the panel says why). A
    lattice the user deleted is let go, as Blender's Lattice modifier lets go of it."""
    s = obj.vpffd
    lat_ob = s.lattice
    if lat_ob is not None and not any(True for _ in lat_ob.users_scene) \
            and depsgraph.mode != "RENDER":
        # Deleted (X): Delete only unlinks an object that still has users, and these settings
        # and the modifier's input are users (undo links it again: `relink_after_undo`).
        state.deleted = lat_ob.name
        s.lattice = None
        modifier.set_lattice(obj, None)
        lat_ob = None
    if not _is_control(lat_ob):
        _zero_offsets(obj, state)
        _set_stats(obj, error=(f"lattice '{state.deleted}' was deleted: pick another, or Unbind"
                               if lat_ob is None and state.deleted else _missing_control(lat_ob)))
        return None
    state.deleted = None
    return lat_ob


def _read(obj, state, mod, depsgraph, helpers_taken):
    """The `_Frame` of this evaluation, or None when there is nothing to solve (the panel says
    why). Raises ValueError for what the user must fix."""
    extra = modifier.find_all(obj)[1:]
    if extra:
        raise ValueError(f"one VP-FFD modifier per object: remove {', '.join(repr(m.name) for m in extra)}")
    rendering = depsgraph.mode == "RENDER"
    # Read what reached the slot before touching the modifier: writing its inputs tags the
    # object, and Blender 4.4+ then refuses to hand out its evaluated geometry.
    ob_eval = obj.evaluated_get(depsgraph)
    tap = modifier.read_tap(ob_eval, depsgraph)
    stale_weights = False
    if not rendering:
        stale_weights = modifier.sync_inputs(obj, mod)
        helper = modifier.helper(obj, mod, exclusive_of=helpers_taken or ())
    else:
        helper = modifier.get_input(mod, modifier.SOLVER_INPUT)
    if helper is None:
        raise ValueError("the VP-FFD modifier has no solver helper: Re-bind")
    if helpers_taken is not None:
        helpers_taken.add(helper)
    lat_ob = _control(obj, state, depsgraph)
    if lat_ob is None:
        return None
    if tap is None:
        if not (mod.show_render if rendering else mod.show_viewport):
            _set_stats(obj, error="the VP-FFD modifier is switched off: switch it on to solve")
            return None
        _zero_offsets(obj, state)   # a defined result: whatever reaches the slot, undeformed
        state.signature = None      # solve again once something reaches it
        _set_stats(obj, error="nothing reaches VP-FFD's slot at the end of the stack (a "
                              "Geometry Nodes modifier after it drops instances or point clouds?)")
        return None
    # Animated settings (volume scale, strength, ...) have this evaluation's values on the
    # evaluated object only: a render's depsgraph does not write them back to the original.
    s = state.settings = ob_eval.vpffd
    return _frame(obj, ob_eval, state, s, lat_ob, depsgraph, tap, mod, helper, stale_weights,
                  may_write=not rendering)


def _control_inputs(obj, state, s, lat_ob, depsgraph, helper):
    """(lattice or cage model, rest grid (N, 3), points now (N, 3), the lattice's own weights
    (N,) or None, (depth, outside) of a cage or None, the control object's world matrix)."""
    lat_eval = lat_ob.evaluated_get(depsgraph)
    if lat_ob.type == "LATTICE":
        lattice, grid = _lattice_rest(lat_ob, s)
        points = meshio.lattice_points(lat_eval.data, "co_deform")
        weights, cage_options = _lattice_weights(lat_ob), None
    else:
        lattice, grid, _ = _cage_model(state, obj, lat_ob, helper)
        points = _cage_points(lat_eval, lattice.n_points)
        weights, cage_options = None, (s.cage_depth, s.cage_outside)
    if len(points) != lattice.n_points:
        raise ValueError(f"lattice '{lat_ob.name}' has {len(points)} points, expected {lattice.n_points}")
    return lattice, grid, points, weights, cage_options, meshio.matrix(lat_eval.matrix_world)


def _frame(obj, ob_eval, state, s, lat_ob, depsgraph, tap, mod, helper, stale_weights, may_write):
    """The `_Frame` of the tap `tap`."""
    X, weights, tapped_tris = tap
    lattice, _, points, lattice_weights, cage_options, M_lat = _control_inputs(
        obj, state, s, lat_ob, depsgraph, helper)
    M_ob = meshio.matrix(ob_eval.matrix_world)
    for what, M in (("lattice", M_lat), ("mesh", M_ob)):
        if not abs(linalg3.det3(M[:3, :3])) > 1e-30:
            raise ValueError(f"the {what} object '{lat_ob.name if what == 'lattice' else obj.name}' "
                             "is scaled to zero along an axis on this frame: there is no lattice "
                             "space to deform in (the mesh shows undeformed)")
    L = linalg3.matmul4(linalg3.affine_inverse(M_lat), M_ob)
    axes, directions = lattice_space.directions(s.axes, s.space, M_lat)
    editing = obj.mode == "EDIT"
    tris, faces_from = _faces(state, obj, ob_eval, len(X), tapped_tris, mod, may_write, editing)
    warnings = []
    pins = _pins(s, obj, helper)
    if len(pins) and faces_from != "mesh" and len(X) != len(obj.data.vertices):
        warnings.append("pins are off: the vertex count that reaches VP-FFD is not the mesh's")
        pins = pins[:0]
    pin_targets = _pin_targets(s, pins, X, M_lat)
    mobility = _mobility(s, lat_ob)
    correct = bool(axes or directions is not None or pin_targets)
    if tris is None and correct:
        warnings.append("the volume is not corrected on this update: the faces that reach "
                        "VP-FFD are not known yet; they are passed along from the next "
                        "evaluation on")
        correct = False
    target_volumes = _bind_target(s, helper, warnings)
    outside = s.outside if isinstance(lattice, vp.Lattice) else "FOLLOW"   # a cage has its own rule
    inputs = vp.FrameInputs(
        positions=X, tris=tris, lattice=lattice, points=points, matrix=L, weights=weights,
        lattice_weights=lattice_weights, strength=s.strength, correct=correct, axes=axes,
        directions=directions, volume_scale=s.volume_scale, mobility=mobility, pins=pin_targets,
        islands=s.use_islands, cage_depth=s.cage_depth, cage_outside=s.cage_outside,
        dtype=np.float32, use_compiled=s.backend != "NUMPY", outside=outside,
        falloff=s.falloff_distance, target_volumes=target_volumes)
    # Beside the core's inputs, what changes what is shown: where the solve runs, the fold
    # attribute, where the faces came from (the panel says it) and Edit Mode.
    signature = FrameKey(inputs, extra=(s.backend, s.use_fold_attribute, faces_from, editing))
    return _Frame(helper=helper, inputs=inputs, signature=signature,
                  faces_from=faces_from, lattice_matrix=M_lat, warnings=warnings,
                  stale_weights=stale_weights, editing=editing)


def _unchanged(state, frame):
    """Whether `frame` has the inputs of the last solve (its result is already shown)."""
    return frame.signature.matches(state.signature)


def _evaluate(state, frame):
    """The core's pipeline on `frame` (its solver picks the CPU or the GPU; on the CPU, the
    compiled kernels once they are loaded): a vp.FrameResult.

    An open surface with no volume about the lattice's centre (a plane through it) has no volume
    to keep: aiming at zero would bend it into another shape. It deforms as the Lattice modifier
    does (pins still hold). Such a mesh stays so from frame to frame, so once found the plain
    deformation is tried first and the correction only when the mesh no longer is one."""
    if state.settings.backend != "NUMPY":
        compiled_backend.start()    # once per session; NumPy solves until the kernels are ready
    inputs = frame.inputs
    plain = dataclasses.replace(inputs, axes="", directions=None, correct=bool(inputs.pins))
    state.backend = ("CPU", "")
    if inputs.correct and state.encloses_nothing:
        result = state.pipeline.evaluate(plain)
        if encloses_nothing(result):
            return result
        state.backend = ("CPU", "")
    result = state.pipeline.evaluate(inputs)
    state.encloses_nothing = inputs.correct and encloses_nothing(result)
    if state.encloses_nothing:
        state.backend = ("CPU", "")
        result = state.pipeline.evaluate(plain)
    return result


def encloses_nothing(result):
    """Whether the frame's input is an open surface whose volume about the lattice's centre is
    zero to within the rounding of its terms: there is no volume to keep."""
    b = result.binding
    return (b is not None and not b.is_closed and result.reference_volume is not None
            and abs(result.reference_volume) <= float(np.sum(b.rest_volume_noise)))


def _publish(obj, state, frame, result, t0):
    """Write the offsets to the solver helper, keep what the overlay and the next update need,
    and give the panel its figures."""
    X = frame.inputs.positions
    lattice = frame.inputs.lattice
    core_seconds = time.perf_counter() - t0
    offsets = result.positions - X
    if not np.isfinite(offsets).all():
        raise ValueError("the solve produced non-finite offsets; nothing was written")
    offsets32 = _write(state, frame.helper, offsets)
    seconds = time.perf_counter() - t0
    # Weights read before the vertex-group input changed are the old group's: solve again
    # after the evaluation that the change brings.
    state.signature, state.result = (None if frame.stale_weights else frame.signature), result
    state.output = X + offsets32   # float32, the very sum the modifier's Set Position makes
    state.moved = float(np.abs(offsets32).max()) if len(offsets32) else 0.0
    edges = (wireframe.lattice_edges(lattice.shape) if isinstance(lattice, vp.Lattice)
             else wireframe.cage_edges(lattice.cells))
    state.overlay = (meshio.transform(result.points, frame.lattice_matrix), edges)
    state.matrix = frame.inputs.matrix      # object -> lattice space of this solve
    state.falloff_box = None
    mode = outside_modes.mode(frame.inputs.outside)
    if isinstance(lattice, vp.Lattice) and mode.has_distance:
        state.falloff_box = meshio.transform(wireframe.falloff_box(lattice, frame.inputs.falloff),
                                             frame.lattice_matrix)
    binding = result.binding
    backend, backend_reason = state.backend
    s = state.settings
    info = dict(error=None, seconds=seconds, core_seconds=core_seconds,
                warnings=tuple(frame.warnings) + tuple(result.warnings) + _lattice_notes(lattice),
                backend=backend,
                backend_reason=backend_reason, n_verts=len(X), folds=None,
                closed=None if binding is None else binding.is_closed,
                input_volume=result.input_volume, rebound=result.rebound, outside=result.outside,
                outside_follow=(mode if isinstance(lattice, vp.Lattice)
                                else outside_modes.mode(s.cage_outside, "cage")).follows,
                outside_mode=frame.inputs.outside, falloff=_fading(frame.inputs, result),
                still=result.still, beyond=result.beyond, editing=frame.editing,
                encloses_nothing=encloses_nothing(result))
    if backend == "CPU":
        compiled = s.backend != "NUMPY" and vp.compiled.ready() and isinstance(lattice, vp.Lattice)
        info["kernels"] = "compiled" if compiled else "NumPy"
        if not compiled:
            info["kernels_why"] = ("Backend is CPU (NumPy): the reference path" if s.backend == "NUMPY"
                                   else "cages solve with NumPy" if isinstance(lattice, vp.Cage)
                                   else compiled_backend.status()[1])
            info["awaits_kernels"] = (s.backend != "NUMPY" and isinstance(lattice, vp.Lattice)
                                      and compiled_backend.status()[0] == "compiling")
    reference = result.reference_volume
    # A mirror turns every vertex inside out alike: folds are the vertices turned against it.
    mirrored = bool(reference and result.plain_volume and result.plain_volume / reference < 0)
    info["mirrored"], state.orientation = mirrored, -1.0 if mirrored else 1.0
    if reference:
        # Sizes: a lattice that mirrors space turns the volume's sign with the shape.
        info["volume_percent"] = 100.0 * abs(result.volume / reference)
        info["plain_percent"] = 100.0 * abs(result.plain_volume / reference)
        if result.target_given:
            info["target_from"] = "bind"
            info["input_percent"] = 100.0 * abs(result.input_volume / reference)
    if binding is not None:
        if s.use_fold_attribute and frame.faces_from == "mesh" and obj.data.library is None:
            det = vp.jacobian_det(binding, result.points)
            _float_attribute(obj.data, JACOBIAN_ATTRIBUTE, det)
            info["folds"] = int((det * state.orientation <= 0).sum())
        elif binding.n_verts <= FOLD_CHECK_MAX_VERTS:
            info["folds"] = count_folds(binding, result.points, state.orientation)
    _set_stats(obj, **info)


def overlay_geometry(obj):
    """(corrected lattice or cage points in world space (N, 3), edges (E, 2), label) of the last
    solve, or None before the first one."""
    state = _cache.get(obj.session_uid)
    if state is None or getattr(state, "overlay", None) is None:
        return None
    info = status(obj)
    if info.error or info.paused or info.switched_off:
        return None     # the mesh shows no correction now: drawing the last one would be false
    label = f"{percent(info.volume_percent)} volume" if info.volume_percent is not None else ""
    return state.overlay + (label,)


def falloff_geometry(obj):
    """(corners in world space (8, 3), edges (12, 2)) of the box where the falloff of the last
    solve ends, or None (no falloff, or nothing shown now)."""
    state = _cache.get(obj.session_uid)
    if overlay_geometry(obj) is None or getattr(state, "falloff_box", None) is None:
        return None
    return state.falloff_box, wireframe.BOX_EDGES


def check_folds(obj, depsgraph):
    """Solve the current frame and count folds whatever the mesh size; None on error."""
    if not update(obj, depsgraph, force=True) and status(obj).error:
        return None
    state = _cache.get(obj.session_uid)
    if state is None or state.result is None or state.result.binding is None:
        return None
    info = status(obj)
    info.folds = count_folds(state.result.binding, state.result.points, state.orientation)
    return info.folds


def count_folds(binding, points, orientation=1.0):
    """Vertices where the deformation's Jacobian determinant is <= 0 (the lattice folds there),
    or >= 0 under a lattice that mirrors space (`orientation` -1): a mirror alone folds nothing."""
    return int((vp.jacobian_det(binding, points) * orientation <= 0).sum())


def _lattice_notes(lattice):
    """What the user should know about the lattice itself, shown with the solve's warnings."""
    if isinstance(lattice, vp.Lattice) and 1 in lattice.shape:
        return ("the lattice has a single point on an axis: it only moves along that axis",)
    return ()


def _fading(inputs, result):
    """Vertices outside the lattice that Falloff moves partly: those outside (one definition of
    outside for every count: a vertex on the lattice's face is inside) and not beyond the
    falloff distance."""
    if not outside_modes.mode(inputs.outside).has_distance or not isinstance(inputs.lattice, vp.Lattice):
        return result.falloff
    return max(result.outside - result.beyond, 0)


def slot_output(obj):
    """(V, 3) float32 positions the VP-FFD slot gave in the last solve (object space), or None."""
    state = _cache.get(obj.session_uid)
    return None if state is None else state.output


def bound_objects(scene):
    return [ob for ob in scene.objects if ob.type == "MESH" and ob.vpffd.is_bound]


def update_scene(scene, depsgraph):
    taken = set()   # each object's modifier gets a solver helper of its own (duplicates share one)
    for ob in bound_objects(scene):
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            _update(ob, depsgraph, False, taken)


def request_update(obj):
    """Settings changed: have the next depsgraph update recompute this object."""
    if getattr(obj, "type", None) == "MESH" and obj.vpffd.is_bound:
        obj.update_tag()


# ---------------------------------------------------------------------------------------- bind

def check_bindable(obj):
    """Raise BindError naming what stops `obj` from being bound."""
    if obj is None or obj.type != "MESH":
        raise BindError("select a mesh object to bind")
    if obj.mode == "EDIT":
        raise BindError("leave Edit Mode before binding")
    s = obj.vpffd
    if not _is_control(s.lattice):
        raise BindError("pick a Lattice object or a VP-FFD cage first" if s.lattice is None
                        else _missing_control(s.lattice))
    if s.lattice.type == "LATTICE" and s.lattice.data.is_editmode:
        raise BindError(f"leave the Edit Mode of lattice '{s.lattice.name}' before binding")
    if len(obj.data.polygons) == 0:
        raise BindError(f"mesh '{obj.data.name}' has no faces: there is no volume to keep")


def bind(obj, depsgraph):
    """Bind `obj` to its lattice (settings in obj.vpffd). Returns warnings (list of str)."""
    check_bindable(obj)
    s = obj.vpffd
    mesh = obj.data
    # Everything is read and checked before anything is written: a refused Bind changes nothing.
    pins = np.zeros(len(mesh.vertices))
    if s.pin_mode == "VERTEX":
        if s.pin_vertex >= len(mesh.vertices):
            raise BindError(f"pin vertex {s.pin_vertex} does not exist (the mesh has {len(mesh.vertices)})")
        pins[s.pin_vertex] = 1.0
    elif s.pin_mode == "GROUP":
        if not s.pin_vertex_group:
            raise BindError("choose the vertex group to pin")
        pins = (meshio.vertex_group_weights(obj, s.pin_vertex_group) > 0).astype(float)
    cage_rest = None
    if s.lattice.type != "LATTICE":
        # A cage's rest state is its evaluated shape now; every bound mesh keeps its own copy.
        cage_eval = s.lattice.evaluated_get(depsgraph)
        try:
            cells = cage.cage_cells(s.lattice)
            cage_rest = _cage_points(cage_eval, len(s.lattice.data.vertices))
            vp.Cage(cage_rest, cells)
        except ValueError as exc:
            raise BindError(f"cage '{s.lattice.name}': {exc}") from None
    else:
        grid = meshio.lattice_points(s.lattice.data, "co")
        s.lattice_rest_lo, s.lattice_rest_hi = grid.min(0).tolist(), grid.max(0).tolist()
    if s.pin_mode != "NONE":
        if s.pin_target is None:
            raise BindError("pins need a target Empty (Pin Target)")
        s.pin_target_rest = np.asarray(s.pin_target.matrix_world, dtype=float).ravel().tolist()
        s.pin_mesh_rest = np.asarray(obj.matrix_world, dtype=float).ravel().tolist()
    if mesh.library is None:
        for legacy in (PIN_ATTRIBUTE, CAGE_REST_PROPERTY) + LEGACY_ATTRIBUTES:
            _remove_attribute(mesh, legacy)
    s.is_bound = True
    s.applied_lattice = ""
    modifier.ensure(obj)
    # What Bind saves goes on the solver helper, local data even when the mesh is linked.
    helper = modifier.helper(obj)
    for key, value in ((PIN_PROPERTY, np.flatnonzero(pins > 0).tolist() if pins.any() else None),
                       (CAGE_REST_PROPERTY, None if cage_rest is None else cage_rest.ravel().tolist()),
                       (BIND_VOLUME_PROPERTY, None)):   # captured below, from this Bind's input
        if value is not None:
            helper[key] = value
        elif key in helper:
            del helper[key]
    forget(obj)
    depsgraph.update()
    update(obj, depsgraph, force=True)
    if modifier.get_input(modifier.find(obj), modifier.FACES_INPUT):
        depsgraph.update()              # the modifier now passes its input's faces along
        update(obj, depsgraph, force=True)
    info = status(obj)
    if info.error:
        unbind(obj)
        raise BindError(info.error)
    state = _cache[obj.session_uid]
    b = state.result.binding if state.result is not None else None
    if b is not None:
        # Target: Bind keeps these: each island's volume as it reached the slot now, in the
        # object's space (the binding measured it in lattice space).
        helper[BIND_VOLUME_PROPERTY] = (b.rest_island_volumes / linalg3.det3(state.matrix[:3, :3])).tolist()
        if s.target == "BIND":
            update(obj, depsgraph, force=True)
            info = status(obj)

    warnings = []
    if b is not None and not b.is_closed:
        warnings.append(open_mesh_words(info))
    if info.outside:
        warnings.append(outside_message(info, b is not None and isinstance(b.lattice, vp.Cage)))
    if info.folds:
        warnings.append(f"the lattice folds space: {info.folds:,} inverted vertices")
    warnings.extend(info.warnings)
    return warnings


def outside_message(info, is_cage):
    """Words for `info.outside` points of `info.n_verts` outside the lattice or cage."""
    where = "the cage's region" if is_cage else "the lattice"
    if not is_cage and outside_modes.mode(info.outside_mode).has_distance:
        what = (f"the deformation fades out over {info.falloff:,} of them; "
                f"{info.beyond or 0:,} beyond the falloff distance stay where they are")
    else:
        what = ("they follow its boundary" if info.outside_follow else "they stay where they are")
        if not is_cage and info.outside_follow:
            what += ", as with the Lattice modifier"
    return f"{info.outside:,} of {info.n_verts:,} vertices lie outside {where} ({what})"


def _remove_attribute(mesh, name):
    """Remove attribute (or custom property) `name` of the mesh, when it has one."""
    attr = mesh.attributes.get(name)
    if attr is not None:
        mesh.attributes.remove(attr)
    if name in mesh:
        del mesh[name]


def release(obj):
    """Forget the binding of an object whose VP-FFD modifier is gone (X on it, or Blender's
    Apply), leaving its settings, its other modifiers and its coordinates as they are. What was
    VP-FFD's goes with it: a baked cache switched off (a playing one stays: it is what is shown)
    and the solver helper nothing uses any more."""
    mesh = obj.data
    cache = find_cache(obj)
    if cache is not None and not using_cache(obj):
        obj.modifiers.remove(cache)
    modifier.free_unused_helpers(obj)
    if mesh.library is None:
        for name in (PIN_ATTRIBUTE, JACOBIAN_ATTRIBUTE, CAGE_REST_PROPERTY) + LEGACY_ATTRIBUTES:
            _remove_attribute(mesh, name)
    if _shows_last_solve(obj):
        _note_applied(obj)              # Blender's Apply: the mesh keeps the deformed shape
    obj.vpffd.is_bound = False
    forget(obj)


def _shows_last_solve(obj):
    """Whether the mesh's own coordinates are now the last solve's deformed output (Blender's
    Apply wrote it), rather than the undeformed input (the modifier was removed)."""
    state = _cache.get(obj.session_uid)
    out = None if state is None else state.output
    if out is None or len(out) != len(obj.data.vertices) or not len(out):
        return False
    size = float(np.ptp(out, 0).max()) or 1.0
    return state.moved > 1e-5 * size and np.abs(meshio.mesh_coords(obj.data) - out).max() <= 1e-6 * size


def _note_applied(obj):
    """Remember which lattice's deformation is now the mesh's own shape (the panel warns that
    Bind would deform it again)."""
    lat = obj.vpffd.lattice
    obj.vpffd.applied_lattice = lat.name if lat is not None else ""


def unbind(obj):
    """Remove the VP-FFD modifier (with its solver helper; and a baked cache's Mesh Cache
    modifier) and the attributes; the mesh's coordinates were never changed."""
    mesh = obj.data
    modifier.remove(obj)
    cache = find_cache(obj)
    if cache is not None:
        obj.modifiers.remove(cache)
    if mesh.library is None:
        for name in (PIN_ATTRIBUTE, JACOBIAN_ATTRIBUTE, CAGE_REST_PROPERTY) + LEGACY_ATTRIBUTES:
            _remove_attribute(mesh, name)
    obj.vpffd.is_bound = False
    forget(obj)
    mesh.update_tag()


def _enabled_before(obj, mod):
    """Names of the modifiers enabled in the viewport that come before `mod` in obj's stack."""
    names = []
    for m in obj.modifiers:
        if m == mod:
            break
        if m.show_viewport:
            names.append(m.name)
    return names


def _solved_output(obj, depsgraph, why):
    """Solve the current frame; (V, 3) float32 slot output, one position per mesh vertex, or
    BindError (the solve's error, or `why` when the slot's point count is not the mesh's)."""
    update(obj, depsgraph, force=True)
    info = status(obj)
    if info.error:
        raise BindError(info.error)
    co = slot_output(obj)
    n = len(obj.data.vertices)
    if co is None or len(co) != n:
        raise BindError(f"{0 if co is None else len(co)} points reach VP-FFD but the mesh has {n} "
                        f"vertices: {why}")
    return co


def save_shape_key(obj, depsgraph, name="VP-FFD"):
    """Add a shape key holding what the VP-FFD slot gives on the current frame (Blender cannot
    apply a Geometry Nodes modifier as a shape key). Returns (key name, names of the enabled
    modifiers before VP-FFD, whose effect the key then includes)."""
    mesh = obj.data
    mod = modifier.find(obj)
    if mod is None:
        raise BindError("the VP-FFD modifier was removed: Bind again, or Unbind")
    co = _solved_output(obj, depsgraph, "a shape key needs one position per vertex")
    before = _enabled_before(obj, mod)
    co = co.copy()
    if mesh.shape_keys is None:
        obj.shape_key_add(name="Basis", from_mix=False)
    key = obj.shape_key_add(name=name, from_mix=False)
    key.data.foreach_set("co", co.astype(np.float32).ravel())
    mesh.update()
    return key.name, before


def apply(obj, depsgraph):
    """Make the current deformed shape the mesh's own coordinates, then unbind. Only where the
    slot's input is the mesh's own coordinates: VP-FFD first among the enabled modifiers, and no
    shape keys."""
    mesh = obj.data
    if mesh.library is not None:
        raise BindError(f"mesh '{mesh.name}' is linked from {mesh.library.filepath}: its coordinates "
                        "cannot be changed here (Save as Shape Key works, or apply in the library)")
    if mesh.shape_keys is not None:
        raise BindError("the mesh has shape keys: applying would only change the basis shape")
    mod = modifier.find(obj)
    if mod is not None and not mod.show_viewport:
        raise BindError("the VP-FFD modifier is switched off: switch it on to apply, or Unbind")
    before = _enabled_before(obj, mod)
    if before:
        raise BindError(f"modifiers before VP-FFD ({', '.join(before)}) would be applied with it: "
                        "apply them first, or move VP-FFD to the top")
    co = _solved_output(obj, depsgraph, "applying needs one position per vertex")
    co = co.copy()
    unbind(obj)
    _note_applied(obj)
    mesh.vertices.foreach_set("co", co.astype(np.float32).ravel())
    mesh.update()
