"""Blender in, `FrameInputs` out: what reached the VP-FFD slot (the modifier's tap), its faces, the
control object, the settings, pins and target read for one update of a bound object (`read`),
with its change key (`vpffd_addon/frame_key.py`)."""
import dataclasses
from typing import Optional

import numpy as np

from .. import vpffd_addon as vp
from ..vpffd_addon import lattice_space, linalg3
from ..vpffd_addon.frame_key import FrameKey
from . import deformers, meshio, modifier, node_group, solver_helper
from .control_read import control_inputs, is_control, missing_control, mobility_of
from .publish import zero_offsets
from .saved_data import BIND_VOLUME_PROPERTY, PIN_ATTRIBUTE, PIN_PROPERTY, float_attribute
from .status import set_status
from .tap import read_tap


@dataclasses.dataclass
class Frame:
    """What Blender hands over for one update of a bound object, ready for the core."""
    helper: object              #: its solver helper, where the offsets go
    inputs: "vp.FrameInputs"
    signature: FrameKey         #: matching keys give equal results
    faces_from: Optional[str]   #: "mesh", "final", "tap" or None (see `_faces`)
    lattice_matrix: np.ndarray  #: (4, 4) world matrix of the lattice object
    warnings: list
    stale_weights: bool         #: the vertex-group input changed: solve again next evaluation
    editing: bool               #: the mesh is in Edit Mode


def read(d, state, depsgraph, helpers_taken):
    """The `Frame` of this evaluation of deformer `d`, or None when there is nothing to solve (the
    panel says why). Raises ValueError for what the user must fix."""
    obj, mod = d.obj, d.mod
    rendering = depsgraph.mode == "RENDER"
    # Read what reached the slot before touching the modifier: writing its inputs tags the
    # object, and Blender 4.4+ then refuses to hand out its evaluated geometry.
    ob_eval = obj.evaluated_get(depsgraph)
    slot = node_group.get_input(mod, node_group.SLOT_INPUT)
    tap = read_tap(ob_eval, depsgraph, slot if slot == mod.persistent_uid else None,
                   node_group.packs_by_stride(mod.node_group))
    if tap is not None and slot != mod.persistent_uid and len(modifier.find_all(obj)) > 1:
        tap = None      # the tap of a modifier whose slot input is set below, for the next evaluation
    stale_weights = False
    if not rendering:
        stale_weights = modifier.sync_inputs(mod, d.settings)
        helper = solver_helper.helper(obj, mod, exclusive_of=helpers_taken or ())
    else:
        helper = node_group.get_input(mod, node_group.SOLVER_INPUT)
    if helper is None:
        raise ValueError("the VP-FFD modifier has no solver helper: Re-bind")
    if helpers_taken is not None:
        helpers_taken.add(helper)
    lat_ob = _control(d, state, depsgraph)
    if lat_ob is None:
        return None
    if tap is None:
        if not (mod.show_render if rendering else mod.show_viewport):
            set_status(d, error="the VP-FFD modifier is switched off: switch it on to solve")
            return None
        if slot != mod.persistent_uid and not rendering:
            state.signature = None  # its tap is marked from the next evaluation on
            return None
        zero_offsets(d, state)     # a defined result: whatever reaches the slot, undeformed
        state.signature = None      # solve again once something reaches it
        set_status(d, error="nothing reaches VP-FFD's slot at the end of the stack (a "
                            "Geometry Nodes modifier after it drops instances or point clouds?)")
        return None
    # Animated settings (volume scale, strength, ...) have this evaluation's values on the
    # evaluated object only: a render's depsgraph does not write them back to the original.
    state.settings = deformers.evaluated_settings(d, ob_eval)
    return _frame(d, ob_eval, state, lat_ob, depsgraph, tap=tap, helper=helper,
                  saved=solver_helper.saved_on(obj, mod, helper),
                  stale_weights=stale_weights, may_write=not rendering)


def _in_a_scene(ob, depsgraph):
    """Whether object `ob` is in a scene: the depsgraph's own (a lookup by name, whatever the
    scene's size), else any (`Object.users_scene` walks every object of every scene: milliseconds
    in a big shot, so only for a lattice outside the shown scene)."""
    scene = depsgraph.scene
    if scene is not None and scene.objects.get(ob.name) == ob:
        return True
    return any(True for _ in ob.users_scene)


def _control(d, state, depsgraph):
    """The bound deformer's Lattice or cage, or None (zero offsets shown, the panel says why). A
    lattice the user deleted is let go, as Blender's Lattice modifier lets go of it."""
    s = d.settings
    lat_ob = s.lattice
    if lat_ob is not None and depsgraph.mode != "RENDER" and not _in_a_scene(lat_ob, depsgraph):
        # Deleted (X): Delete only unlinks an object that still has users, and these settings
        # and the modifier's input are users (undo links it again: `relink_after_undo`).
        state.deleted = lat_ob.name
        s.lattice = None
        modifier.set_lattice(d.mod, None)
        lat_ob = None
    if not is_control(lat_ob):
        zero_offsets(d, state)
        set_status(d, error=(f"lattice '{state.deleted}' was deleted: pick another, or Unbind"
                             if lat_ob is None and state.deleted else missing_control(lat_ob)))
        return None
    state.deleted = None
    return lat_ob


def _frame(d, ob_eval, state, lat_ob, depsgraph, *, tap, helper, saved, stale_weights, may_write):
    """The `Frame` of deformer `d` for the tap `tap` ((V, 3) positions, (V,) weights, triangles
    or None), with the settings of this evaluation (`state.settings`); `saved`: the object that
    holds what Bind saved (`solver_helper.saved_on`)."""
    obj, mod = d.obj, d.mod
    s = state.settings
    X, weights, tapped_tris = tap
    lattice, _, points, lattice_weights, cage_options, M_lat = control_inputs(
        obj, state, s, lat_ob, depsgraph, saved)
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
    pins = _pins(s, obj, saved)
    if len(pins) and faces_from != "mesh" and len(X) != len(obj.data.vertices):
        warnings.append("pins are off: the vertex count that reaches VP-FFD is not the mesh's")
        pins = pins[:0]
    pin_targets = _pin_targets(s, pins, X, M_lat)
    mobility = mobility_of(s, lat_ob)
    correct = bool(axes or directions is not None or pin_targets)
    if tris is None and correct:
        warnings.append("the volume is not corrected on this update: the faces that reach "
                        "VP-FFD are not known yet; they are passed along from the next "
                        "evaluation on")
        correct = False
    target_volumes = _bind_target(s, saved, warnings)
    outside = s.outside if isinstance(lattice, vp.Lattice) else "FOLLOW"   # a cage has its own rule
    computed = dict(
        positions=X, tris=tris, lattice=lattice, points=points, matrix=L, weights=weights,
        lattice_weights=lattice_weights, correct=correct, axes=axes, directions=directions,
        mobility=mobility, pins=pin_targets, islands=s.use_islands, dtype=np.float32,
        outside=outside, falloff=s.falloff_distance,
        target_volumes=target_volumes)
    inputs = vp.FrameInputs(**computed, **same_named_settings(s, computed))
    # Beside the core's inputs, what changes what is shown: the fold attribute, where the faces
    # came from (the panel says it) and Edit Mode.
    signature = FrameKey(inputs, extra=(s.use_fold_attribute, faces_from, editing))
    return Frame(helper=helper, inputs=inputs, signature=signature,
                  faces_from=faces_from, lattice_matrix=M_lat, warnings=warnings,
                  stale_weights=stale_weights, editing=editing)


def same_named_settings(s, computed=()):
    """{field: value} for every field of `vpffd_addon.FrameInputs` that is not in `computed` and
    has a setting of the same name in `s` (a deformer's settings): such a setting reaches the core as it is,
    with no line of its own here (docs/architecture.md, "A new setting")."""
    names = s.bl_rna.properties.keys()
    return {f.name: getattr(s, f.name) for f in dataclasses.fields(vp.FrameInputs)
            if f.name not in computed and f.name in names}


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
            node_group.set_input(mod, node_group.FACES_INPUT, True)
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
                node_group.set_input(mod, node_group.FACES_INPUT, True)
            if tapped is not None and len(tapped) and int(tapped.max()) < n:
                return tapped, "tap"
            return None, None
        source, key = final, ("final", meshio.topology_signature(final))
    if may_write:
        node_group.set_input(mod, node_group.FACES_INPUT, False)
    if state.faces_key != key:
        state.faces, state.faces_key = meshio.mesh_triangles(source), key
    return state.faces, key[0]


def _pins(s, obj, helper):
    """(k,) indices of the pinned vertices of the mesh (saved at Bind)."""
    if s.pin_mode == "NONE":
        return np.zeros(0, np.int64)
    saved = helper.get(PIN_PROPERTY)
    if saved is not None:
        return np.array(saved.to_list() if hasattr(saved, "to_list") else saved, np.int64)
    pins = float_attribute(obj.data, PIN_ATTRIBUTE)        # a file bound by an earlier version
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
