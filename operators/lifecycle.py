"""Bind, Apply and Save as Shape Key: what turns a mesh into a bound one and its deformed shape
into the mesh's own (Unbind and the release of a removed modifier: `release.py`)."""
import numpy as np

from .. import vpffd_addon as vp
from ..vpffd_addon import linalg3
from . import cage, deformers, meshio, modifier, node_group, solver_helper
from .bound import forget, states
from .control_read import cage_points, is_control, missing_control
from .release import note_applied, unbind
from .saved_data import (BIND_VOLUME_PROPERTY, CAGE_REST_PROPERTY, LEGACY_ATTRIBUTES, PIN_ATTRIBUTE,
                         PIN_PROPERTY, remove_attribute)
from .status import deformer_of, outside_message, status
from .status_line import open_mesh_words
from .update import slot_output, update, update_object


class BindError(ValueError):
    """A problem the user must fix before binding (the message says what)."""


def check_bindable(target):
    """Raise BindError naming what stops deformer `target` (or a mesh object's first) from being
    bound."""
    if target is None or getattr(target, "type", "MESH") != "MESH":
        raise BindError("select a mesh object to bind")
    d = deformer_of(target)
    obj = d.obj
    if obj.type != "MESH":
        raise BindError("select a mesh object to bind")
    if obj.mode == "EDIT":
        raise BindError("leave Edit Mode before binding")
    s = d.settings
    if not is_control(s.lattice):
        raise BindError("pick a Lattice object or a VP-FFD cage first" if s.lattice is None
                        else missing_control(s.lattice))
    if s.lattice.type == "LATTICE" and s.lattice.data.is_editmode:
        raise BindError(f"leave the Edit Mode of lattice '{s.lattice.name}' before binding")
    if len(obj.data.polygons) == 0:
        raise BindError(f"mesh '{obj.data.name}' has no faces: there is no volume to keep")


def add_deformer(obj, settings_from=None):
    """A new VP-FFD deformer of `obj`: a VP-FFD modifier at the end of the stack, with settings of
    its own (`obj.vpffd` while that is free, else a new entry of `obj.vpffd_extra`), copied from
    `settings_from` (a dict of setting values) when given. Not bound yet."""
    if obj is None or obj.type != "MESH":
        raise BindError("select a mesh object")
    mod = modifier.add(obj)
    s = deformers.claim(obj, mod)
    for name, value in (settings_from or {}).items():
        setattr(s, name, value)
    modifier.sync_inputs(mod, s)
    return deformers.Deformer(obj, mod, s)


def bind(target, depsgraph):
    """Bind deformer `target` (a `deformers.Deformer`, or a mesh object for its first deformer,
    whose settings are obj.vpffd) to its lattice. Returns warnings (list of str)."""
    d = deformer_of(target)
    check_bindable(d)
    obj, s = d.obj, d.settings
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
            cage_rest = cage_points(cage_eval, len(s.lattice.data.vertices))
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
            remove_attribute(mesh, legacy)
    mod = d.mod if d.mod is not None else modifier.add(obj)
    deformers.claim(obj, mod)           # the settings name their modifier from now on
    d = deformers.Deformer(obj, mod, s)
    s.is_bound = True
    s.applied_lattice = ""
    modifier.prepare(obj, mod, s)
    # What Bind saves goes on the solver helper, local data even when the mesh is linked.
    helper = solver_helper.helper(obj, mod)
    helper[solver_helper.BOUND_HERE] = True     # a library override's own Bind (`saved_on`)
    for key, value in ((PIN_PROPERTY, np.flatnonzero(pins > 0).tolist() if pins.any() else None),
                       (CAGE_REST_PROPERTY, None if cage_rest is None else cage_rest.ravel().tolist()),
                       (BIND_VOLUME_PROPERTY, None)):   # captured below, from this Bind's input
        if value is not None:
            helper[key] = value
        elif key in helper:
            del helper[key]
    forget(d=d)
    depsgraph.update()
    update(d, depsgraph, force=True)
    if node_group.get_input(mod, node_group.FACES_INPUT):
        depsgraph.update()              # the modifier now passes its input's faces along
        update(d, depsgraph, force=True)
    info = status(d)
    if info.error:
        unbind(d)
        raise BindError(info.error)
    state = states[d.key]
    b = state.result.binding if state.result is not None else None
    if b is not None:
        # Target: Bind keeps these: each island's volume as it reached the slot now, in the
        # object's space (the binding measured it in lattice space).
        helper[BIND_VOLUME_PROPERTY] = (b.rest_island_volumes / linalg3.det3(state.matrix[:3, :3])).tolist()
        if s.target == "BIND":
            update(d, depsgraph, force=True)
            info = status(d)
    if len(modifier.find_all(obj)) > 1:
        update_object(obj, depsgraph)   # the deformers after this one read its new result

    warnings = []
    if b is not None and not b.is_closed:
        warnings.append(open_mesh_words(info))
    if info.outside:
        warnings.append(outside_message(info, b is not None and isinstance(b.lattice, vp.Cage)))
    if info.folds:
        warnings.append(f"the lattice folds space: {info.folds:,} inverted vertices")
    warnings.extend(info.warnings)
    return warnings


def _enabled_before(obj, mod):
    """Names of the modifiers enabled in the viewport that come before `mod` in obj's stack."""
    names = []
    for m in obj.modifiers:
        if m == mod:
            break
        if m.show_viewport:
            names.append(m.name)
    return names


def _solved_output(d, depsgraph, why):
    """Solve the current frame of deformer `d`; (V, 3) float32 slot output, one position per mesh
    vertex, or BindError (the solve's error, or `why` when the slot's point count is not the
    mesh's)."""
    update(d, depsgraph, force=True)
    info = status(d)
    if info.error:
        raise BindError(info.error)
    co = slot_output(d)
    n = len(d.obj.data.vertices)
    if co is None or len(co) != n:
        raise BindError(f"{0 if co is None else len(co)} points reach VP-FFD but the mesh has {n} "
                        f"vertices: {why}")
    return co


def save_shape_key(target, depsgraph, name="VP-FFD"):
    """Add a shape key holding what the slot of deformer `target` (or of a mesh object's first)
    gives on the current frame (Blender cannot apply a Geometry Nodes modifier as a shape key).
    Returns (key name, names of the enabled modifiers before it, whose effect the key then
    includes)."""
    d = deformer_of(target)
    obj, mod = d.obj, d.mod
    mesh = obj.data
    if mod is None:
        raise BindError("the VP-FFD modifier was removed: Bind again, or Unbind")
    co = _solved_output(d, depsgraph, "a shape key needs one position per vertex")
    before = _enabled_before(obj, mod)
    co = co.copy()
    if mesh.shape_keys is None:
        obj.shape_key_add(name="Basis", from_mix=False)
    key = obj.shape_key_add(name=name, from_mix=False)
    key.data.foreach_set("co", co.astype(np.float32).ravel())
    mesh.update()
    return key.name, before


def apply(target, depsgraph):
    """Make the current deformed shape of deformer `target` (or of a mesh object's first) the
    mesh's own coordinates, then unbind it. Only where the slot's input is the mesh's own
    coordinates: the deformer first among the enabled modifiers, and no shape keys."""
    d = deformer_of(target)
    obj = d.obj
    mesh = obj.data
    if mesh.library is not None:
        raise BindError(f"mesh '{mesh.name}' is linked from {mesh.library.filepath}: its coordinates "
                        "cannot be changed here (Save as Shape Key works, or apply in the library)")
    if mesh.shape_keys is not None:
        raise BindError("the mesh has shape keys: applying would only change the basis shape")
    mod = d.mod
    if mod is not None and not mod.show_viewport:
        raise BindError("the VP-FFD modifier is switched off: switch it on to apply, or Unbind")
    before = _enabled_before(obj, mod)
    if before:
        raise BindError(f"modifiers before VP-FFD ({', '.join(before)}) would be applied with it: "
                        "apply them first, or move VP-FFD to the top")
    co = _solved_output(d, depsgraph, "applying needs one position per vertex")
    co = co.copy()
    note_applied(d)
    unbind(d)
    mesh.vertices.foreach_set("co", co.astype(np.float32).ravel())
    mesh.update()
