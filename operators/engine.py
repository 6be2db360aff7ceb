"""Runtime of bound objects: bind, per-frame solve, offsets written for the VP-FFD modifier.

Everything a bound object needs survives in the .blend: the settings (`obj.vpffd`), the mesh's own
coordinates (never written), the per-vertex weights and pins (mesh attributes written at bind), the
VP-FFD modifier. The NumPy binding is a cache rebuilt on demand, e.g. after loading a file, or when
the mesh moves relative to the lattice (as Blender's Lattice modifier re-embeds every evaluation).
"""
import time

import bpy
import numpy as np

from .. import vpffd_addon as vp
from . import cage, gpu_backend, meshio, modifier

WEIGHT_ATTRIBUTE = "vpffd_weight"   # vertex-group weight at bind time (1 without a group)
PIN_ATTRIBUTE = "vpffd_pin"         # 1 for pinned vertices
JACOBIAN_ATTRIBUTE = "vpffd_jacobian"  # det of the deformation's Jacobian (on request)
CAGE_REST_PROPERTY = "vpffd_cage_rest"  # the cage's points at bind time, flat, in cage space
FOLD_CHECK_MAX_VERTS = 5000         # above this, folds are counted on request only (Check Folds)

_cache = {}   # object session_uid -> _Bound
_stats = {}   # object session_uid -> dict shown by the panel


class BindError(ValueError):
    """A problem the user must fix before binding (the message says what)."""


def stats(obj):
    return _stats.get(obj.session_uid, {})


_reported = {}  # object session_uid -> last error printed, so a failing frame range logs once


def _set_stats(obj, **values):
    _stats[obj.session_uid] = values
    error = values.get("error")
    if error and _reported.get(obj.session_uid) != error:
        print(f"VP-FFD: {obj.name}: {error}")  # the console and farm logs, once per new problem
    _reported[obj.session_uid] = error
    return values


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


def _lattice_model(lattice_data):
    """(vp.Lattice, rest grid (N, 3)) for a Blender Lattice datablock; bounds come from `co`."""
    grid = meshio.lattice_points(lattice_data, "co")
    shape = (lattice_data.points_u, lattice_data.points_v, lattice_data.points_w)
    interp = (lattice_data.interpolation_type_u, lattice_data.interpolation_type_v,
              lattice_data.interpolation_type_w)
    return vp.Lattice(shape, interp, bounds=(grid.min(0), grid.max(0))), grid


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


def _cage_model(state, obj, cage_ob):
    """(vp.Cage at bind time, its rest points (N, 3), key) for a bound mesh, cached per object."""
    flat = tuple(cage_ob.data[cage.CELLS_PROPERTY].to_list())
    rest = obj.data.get(CAGE_REST_PROPERTY)
    if rest is None:
        raise ValueError("the mesh was bound to another kind of lattice: Re-bind")
    rest = np.array(rest.to_list(), np.float64).reshape(-1, 3)
    key = (hash(flat), rest.tobytes())
    if state.cage_key != key:
        cells = cage.decode_cells(flat)
        if len(rest) != len(cage_ob.data.vertices):
            raise ValueError(f"cage '{cage_ob.name}' has {len(cage_ob.data.vertices)} points, "
                             f"{len(rest)} when bound: Re-bind")
        state.cage_model, state.cage_key = vp.Cage(rest, cells), key
    return state.cage_model, rest, ("cage", key[0])


class _Bound:
    """Cached per-object state: rest mesh, weights, pins and the NumPy binding."""

    def __init__(self, obj):
        mesh = obj.data
        self.rest32 = meshio.mesh_coords(mesh, np.float32)
        self.rest = self.rest32.astype(np.float64)
        self.tris = meshio.mesh_triangles(mesh)
        weight = _float_attribute(mesh, WEIGHT_ATTRIBUTE)
        self.weight = np.ones(len(self.rest)) if weight is None else weight
        pins = _float_attribute(mesh, PIN_ATTRIBUTE)
        self.pins = np.zeros(0, np.int64) if pins is None else np.flatnonzero(pins > 0)
        self.binding = None
        self.key = None
        self.signature = None
        self.overlay = None
        self.gpu = None        # GPUSolver for the current binding, made on first GPU use
        self.cage_model = self.cage_key = None

    def free(self):
        if self.gpu is not None:
            self.gpu.free()
            self.gpu = None

    def edited(self, mesh):
        """True when the mesh's own coordinates differ from those this state was built from."""
        return not np.array_equal(meshio.mesh_coords(mesh, np.float32), self.rest32)

    def binding_for(self, lattice, model_key, grid, L, influence, cage_options=None):
        """The binding for this lattice or cage, mesh-to-lattice matrix and influence (rebuilt on
        change). cage_options: (depth, outside) for a cage."""
        key = (model_key, cage_options, grid.tobytes(), L.round(12).tobytes(), influence.tobytes())
        if key != self.key:
            verts = meshio.transform(self.rest, L)
            self.free()
            extra = {} if cage_options is None else dict(depth=cage_options[0], outside=cage_options[1])
            self.binding = vp.bind(lattice, verts, self.tris, influence=influence, dtype=np.float32, **extra)
            self.key, self.L = key, L
        return self.binding


def _influence(s, state):
    w = state.weight
    return 1.0 - w if (s.invert_vertex_group and s.vertex_group) else w


def _directions(s, lat_matrix):
    """(axes string, directions (m, 3) or None) in lattice space for the settings `s`."""
    if s.axes == "NONE":
        return "", None
    if s.space == "LATTICE":
        return s.axes, None
    # A world displacement e is inv(M3) e in lattice space (not unit length under scale: the
    # solver normalises; the volume is exact along any direction).
    inv3 = np.linalg.inv(lat_matrix[:3, :3])
    world = np.eye(3)[["XYZ".index(c) for c in s.axes]]
    return "", world @ inv3.T


def _pin_targets(s, state, lat_matrix):
    """[(vertex, target in lattice space)] for the pinned vertices, following the pin Empty."""
    if s.pin_mode == "NONE" or len(state.pins) == 0:
        return []
    if s.pin_target is None:
        raise ValueError("pins need a target Empty (Pin Target)")
    M_t = meshio.matrix(s.pin_target.matrix_world)
    M_t0 = np.array(s.pin_target_rest).reshape(4, 4)
    M_mesh0 = np.array(s.pin_mesh_rest).reshape(4, 4)
    carry = np.linalg.inv(lat_matrix) @ M_t @ np.linalg.inv(M_t0) @ M_mesh0
    targets = meshio.transform(state.rest[state.pins], carry)
    return list(zip(state.pins.tolist(), targets))


def _mobility(s, lattice_object):
    """(N,) mobility from a vertex group of the lattice or cage, or None."""
    if not s.mobility_group:
        return None
    return meshio.lattice_group_weights(lattice_object, s.mobility_group)


def _zero_offsets(obj):
    mesh = obj.data
    if mesh.attributes.get(meshio.OFFSET_ATTRIBUTE) is not None:
        meshio.write_offsets(mesh, np.zeros((len(mesh.vertices), 3)))


def update(obj, depsgraph, force=False):
    """Solve the current frame for a bound object and write its offsets. Never raises: problems
    go to the panel (`stats(obj)['error']`) and the console. Returns True when offsets were written.
    `force` solves even when the inputs did not change and the modifier is switched off (Bind,
    Apply, Check Folds and Bake need the solve)."""
    # Overflow is detected on the results and reported in words; NumPy's own warnings would only
    # repeat it on the console for every frame.
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        return _update(obj, depsgraph, force)


def _update(obj, depsgraph, force):
    s = obj.vpffd
    uid = obj.session_uid
    try:
        if not s.is_bound:
            return False
        mod = modifier.find(obj)
        if mod is None:
            _set_stats(obj, error="the VP-FFD modifier was removed: Bind again, or Unbind")
            return False
        if not force and not (mod.show_render if depsgraph.mode == "RENDER" else mod.show_viewport):
            if depsgraph.mode != "RENDER":
                # Switched off in the viewport: the panel says so instead of an error of an earlier
                # solve (the last figures stay, e.g. from Check Folds); switching it on solves again.
                _set_stats(obj, **{**stats(obj), "error": None, "switched_off": True})
                state = _cache.get(uid)
                if state is not None:
                    state.signature = None
            return False  # switched off for this evaluation, like any modifier
        if obj.data.users > 1:
            _set_stats(obj, error=f"mesh '{obj.data.name}' is shared by {obj.data.users} objects "
                                  "(a linked duplicate?): make it single user, then Re-bind")
            return False
        if obj.mode == "EDIT":
            _set_stats(obj, **{**stats(obj), "error": "paused while the mesh is in Edit Mode"})
            state = _cache.get(uid)
            if state is not None:
                state.signature = None   # leaving Edit Mode solves again, which clears the message
            return False
        mesh = obj.data
        if meshio.topology_signature(mesh) != tuple(s.bound_topology):
            _zero_offsets(obj)
            _cache.pop(uid, None)
            _set_stats(obj, error="the mesh's topology changed since binding: Re-bind")
            return False
        lat_ob = s.lattice
        if not _is_control(lat_ob):
            _zero_offsets(obj)
            _set_stats(obj, error=_missing_control(lat_ob))
            return False

        lat_eval = lat_ob.evaluated_get(depsgraph)
        ob_eval = obj.evaluated_get(depsgraph)
        # Animated settings (volume scale, strength, ...) have this evaluation's values on the
        # evaluated object only: a render's depsgraph does not write them back to the original.
        s = ob_eval.vpffd
        state = _cache.get(uid)
        if state is None or state.edited(mesh):
            # First use (e.g. after loading), or the vertices were moved in Edit Mode: embed the
            # mesh's coordinates as they are now, as the Lattice modifier would.
            state = _cache[uid] = _Bound(obj)
        cage_options = None
        if lat_ob.type == "LATTICE":
            lattice, grid = _lattice_model(lat_eval.data)
            points = meshio.lattice_points(lat_eval.data, "co_deform")
            model_key = (lattice.shape, lattice.interpolation)
        else:
            lattice, grid, model_key = _cage_model(state, obj, lat_ob)
            points = _cage_points(lat_eval, lattice.n_points)
            cage_options = (s.cage_depth, s.cage_outside)
        M_lat = meshio.matrix(lat_eval.matrix_world)
        L = np.linalg.inv(M_lat) @ meshio.matrix(ob_eval.matrix_world)
        axes, directions = _directions(s, M_lat)
        influence = _influence(s, state)
        pins = _pin_targets(s, state, M_lat)
        mobility = _mobility(s, lat_ob)
        signature = (points.tobytes(), L.tobytes(), grid.tobytes(), model_key, cage_options, axes, s.space,
                     s.strength, s.volume_scale, s.use_islands, influence.tobytes(), repr(pins),
                     s.use_fold_attribute, None if mobility is None else mobility.tobytes())
        if not force and signature == state.signature:
            return False

        t0 = time.perf_counter()
        binding = state.binding_for(lattice, model_key, grid, L, influence, cage_options)
        t_core = time.perf_counter()
        # Strength scales every displacement alike, so it scales the lattice offsets instead of
        # the binding's weights (no re-bind when it is animated).
        P = grid + s.strength * (points - grid)
        backend = "CPU"
        backend_reason = ""
        if axes or directions is not None or pins:
            options = dict(axes=axes, directions=directions, pins=pins, mobility=mobility,
                           islands=s.use_islands, preserve_volume=bool(axes or directions is not None))
            sol, backend, backend_reason = _solve(state, binding, P, s, options)
            verts, volume, plain, warnings = sol.verts, sol.volume, sol.plain_volume, list(sol.warnings)
            used_points = sol.points
        else:
            # No correction: the plain deformation, its volume measured as the solver measures
            # (a closed mesh's islands about their own centres, not about the lattice centre).
            sol = binding.solve(P, axes="", preserve_volume=False)
            verts, volume, plain, warnings = sol.verts, sol.volume, sol.plain_volume, []
            used_points = P
        core_seconds = time.perf_counter() - t_core
        offsets = meshio.transform(verts, np.linalg.inv(L)) - state.rest
        if not np.isfinite(offsets).all():
            raise ValueError("the solve produced non-finite offsets; nothing was written")
        meshio.write_offsets(mesh, offsets)
        seconds = time.perf_counter() - t0
        state.signature, state.points = signature, used_points
        edges = _lattice_edges(lattice.shape) if isinstance(lattice, vp.Lattice) else cage.cage_edges(lattice.cells)
        state.overlay = (meshio.transform(used_points, M_lat), edges)

        rest_volume = binding.rest_volume
        info = dict(error=None, seconds=seconds, core_seconds=core_seconds, warnings=warnings,
                    rest_volume=rest_volume, backend=backend, backend_reason=backend_reason,
                    closed=binding.is_closed, n_verts=binding.n_verts, folds=None)
        if rest_volume:
            info["volume_percent"] = 100.0 * volume / rest_volume
            info["plain_percent"] = 100.0 * plain / rest_volume
        if s.use_fold_attribute:
            det = vp.jacobian_det(binding, used_points)
            _float_attribute(mesh, JACOBIAN_ATTRIBUTE, det)
            info["folds"] = int((det <= 0).sum())
        elif binding.n_verts <= FOLD_CHECK_MAX_VERTS:
            info["folds"] = count_folds(binding, used_points)
        _set_stats(obj, **info)
        return True
    except Exception as exc:  # a handler must never raise into Blender
        _set_stats(obj, error=f"{type(exc).__name__}: {exc}" if not isinstance(exc, ValueError) else str(exc))
        return False


def _solve(state, binding, P, s, options):
    """(Solution, "GPU" or "CPU", why) for this frame: the GPU path when the settings' backend
    and the machine allow it, else (or when it fails) the CPU path."""
    use_gpu, why = gpu_backend.choose(s.backend, binding.n_verts, options, binding)
    if use_gpu:
        try:
            if state.gpu is None:
                state.gpu = gpu_backend.GPUSolver(binding)
            return state.gpu.solve(P, axes=options["axes"], volume_scale=s.volume_scale), "GPU", why
        except gpu_backend.GPUUnavailable as exc:
            state.free()
            why = f"the GPU failed, using the CPU: {exc}"
    sol = binding.solve(P, axes=options["axes"], directions=options["directions"],
                        volume_scale=s.volume_scale, preserve_volume=options["preserve_volume"],
                        mobility=options["mobility"], pins=options["pins"], islands=options["islands"])
    return sol, "CPU", why


def _lattice_edges(shape):
    """(E, 2) index pairs of neighbouring lattice points, u fastest."""
    nu, nv, nw = shape
    index = np.arange(nu * nv * nw).reshape(nw, nv, nu)
    pairs = []
    for axis in range(3):
        if index.shape[axis] > 1:
            a = np.take(index, range(index.shape[axis] - 1), axis=axis).ravel()
            b = np.take(index, range(1, index.shape[axis]), axis=axis).ravel()
            pairs.append(np.stack([a, b], 1))
    return np.concatenate(pairs) if pairs else np.zeros((0, 2), np.int64)


def overlay_geometry(obj):
    """(corrected lattice or cage points in world space (N, 3), edges (E, 2), label) of the last
    solve, or None before the first one."""
    state = _cache.get(obj.session_uid)
    if state is None or getattr(state, "overlay", None) is None:
        return None
    info = stats(obj)
    label = (f"{info['volume_percent']:.3f}% volume" if "volume_percent" in info else "") \
        if not info.get("error") else "VP-FFD: error"
    return state.overlay + (label,)


def check_folds(obj, depsgraph):
    """Solve the current frame and count folds whatever the mesh size; None on error."""
    if not update(obj, depsgraph, force=True) and stats(obj).get("error"):
        return None
    state = _cache[obj.session_uid]
    info = stats(obj)
    info["folds"] = count_folds(state.binding, state.points)
    return info["folds"]


def count_folds(binding, points):
    """Vertices where the deformation's Jacobian determinant is <= 0 (the lattice folds there)."""
    return int((vp.jacobian_det(binding, points) <= 0).sum())


def bound_objects(scene):
    return [ob for ob in scene.objects if ob.type == "MESH" and ob.vpffd.is_bound]


def update_scene(scene, depsgraph):
    for ob in bound_objects(scene):
        update(ob, depsgraph)


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
    if obj.data.users > 1:
        raise BindError(f"mesh '{obj.data.name}' is shared by {obj.data.users} objects (linked "
                        "duplicates); make it single user (Object > Relations > Make Single User)")
    if len(obj.data.polygons) == 0:
        raise BindError(f"mesh '{obj.data.name}' has no faces: there is no volume to keep")


def bind(obj, depsgraph):
    """Bind `obj` to its lattice (settings in obj.vpffd). Returns warnings (list of str)."""
    check_bindable(obj)
    s = obj.vpffd
    mesh = obj.data
    # Everything is read and checked before anything is written: a refused Bind changes nothing.
    weight = (meshio.vertex_group_weights(obj, s.vertex_group) if s.vertex_group
              else np.ones(len(mesh.vertices)))
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
    if s.pin_mode != "NONE":
        if s.pin_target is None:
            raise BindError("pins need a target Empty (Pin Target)")
        s.pin_target_rest = np.asarray(s.pin_target.matrix_world, dtype=float).ravel().tolist()
        s.pin_mesh_rest = np.asarray(obj.matrix_world, dtype=float).ravel().tolist()
    _float_attribute(mesh, WEIGHT_ATTRIBUTE, weight)
    _float_attribute(mesh, PIN_ATTRIBUTE, pins)
    if cage_rest is not None:
        mesh[CAGE_REST_PROPERTY] = cage_rest.ravel().tolist()
    elif CAGE_REST_PROPERTY in mesh:
        del mesh[CAGE_REST_PROPERTY]

    s.bound_topology = meshio.topology_signature(mesh)
    s.is_bound = True
    modifier.ensure(obj)
    modifier.set_lattice(obj, s.lattice)
    forget(obj)
    state = _cache[obj.session_uid] = _Bound(obj)
    depsgraph.update()
    update(obj, depsgraph, force=True)
    info = stats(obj)
    if info.get("error"):
        unbind(obj)
        raise BindError(info["error"])

    warnings = []
    b = state.binding
    if not b.is_closed:
        warnings.append("the mesh is not closed: the volume of an open surface is measured about "
                        "the lattice centre")
    if isinstance(b.lattice, vp.Cage):
        if b.n_outside:
            what = "they follow its boundary" if b.outside == "FOLLOW" else "they stay where they are"
            warnings.append(f"{b.n_outside} of {b.n_verts} vertices lie outside the cage's region ({what})")
    else:
        inside = _inside_count(state, b.lattice)
        if inside < b.n_verts:
            warnings.append(f"{b.n_verts - inside} of {b.n_verts} vertices lie outside the lattice "
                            "(they follow its boundary, as with the Lattice modifier)")
        if 1 in b.lattice.shape:
            warnings.append("the lattice has a single point on an axis: it only moves along that axis")
    if info.get("folds"):
        warnings.append(f"the lattice folds space: {info['folds']} vertices inverted")
    return warnings


def _inside_count(state, lattice):
    v = meshio.transform(state.rest, state.L)
    eps = 1e-6 * lattice.size
    spans = np.array(lattice.shape) > 1  # a one-point axis has no extent to be outside of
    inside = (v >= lattice.lo - eps) & (v <= lattice.hi + eps)
    return int(inside[:, spans].all(1).sum())


def unbind(obj):
    """Remove the VP-FFD modifier (and a baked cache's Mesh Cache modifier) and the attributes;
    the mesh's coordinates were never changed."""
    from .bake import find_cache
    mesh = obj.data
    modifier.remove(obj)
    cache = find_cache(obj)
    if cache is not None:
        obj.modifiers.remove(cache)
    meshio.remove_offsets(mesh)
    for name in (WEIGHT_ATTRIBUTE, PIN_ATTRIBUTE, JACOBIAN_ATTRIBUTE):
        attr = mesh.attributes.get(name)
        if attr is not None:
            mesh.attributes.remove(attr)
    if CAGE_REST_PROPERTY in mesh:
        del mesh[CAGE_REST_PROPERTY]
    obj.vpffd.is_bound = False
    forget(obj)
    mesh.update_tag()


def apply(obj, depsgraph):
    """Make the current deformed shape the mesh's own coordinates, then unbind."""
    mesh = obj.data
    if mesh.shape_keys is not None:
        raise BindError("the mesh has shape keys: applying would only change the basis shape")
    mod = modifier.find(obj)
    if mod is not None and not mod.show_viewport:
        raise BindError("the VP-FFD modifier is switched off: switch it on to apply, or Unbind")
    update(obj, depsgraph, force=True)
    info = stats(obj)
    if info.get("error"):
        raise BindError(info["error"])
    co = meshio.mesh_coords(mesh) + meshio.read_offsets(mesh)
    unbind(obj)
    mesh.vertices.foreach_set("co", co.astype(np.float32).ravel())
    mesh.update()
