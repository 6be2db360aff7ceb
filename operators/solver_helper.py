"""The solver helper of a VP-FFD modifier: a hidden vertex-only mesh object, named in the
modifier's Solver input, whose vertex positions are the offsets the node group adds to the slot's
input (docs/stack.md). It also keeps what Bind saves (saved_data.py)."""
import bpy
import numpy as np

from .node_group import SOLVER_INPUT, get_input, set_input


HELPER_TAG = "vpffd_solver"  # custom property of helper objects: the name of their mesh object


BOUND_HERE = "vpffd_bound_here"  # on a library override's own helper: Bind ran in this file


def writable(ob):
    """Whether offsets written into helper `ob` reach Blender: linked data is read-only (its
    writes are dropped without an error), so a helper linked from a library is not."""
    return ob is not None and ob.library is None and ob.is_editable \
        and ob.data is not None and ob.data.library is None and ob.data.is_editable


def _new_helper(obj):
    mesh = bpy.data.meshes.new(f".VP-FFD solver {obj.name}")
    ob = bpy.data.objects.new(f".VP-FFD solver {obj.name}", mesh)
    ob[HELPER_TAG] = obj.name
    ob.hide_viewport = ob.hide_render = True
    return ob


def free_helper(ob):
    if ob is None or ob.get(HELPER_TAG) is None:
        return
    if ob.users == 0:        # still used when a duplicate's modifier shares it
        _remove_helper(ob)


def _remove_helper(ob):
    mesh = ob.data
    bpy.data.objects.remove(ob)
    if mesh is not None and mesh.users == 0:
        bpy.data.meshes.remove(mesh)


def free_unused_helpers(obj):
    """Remove the solver helpers made for `obj` that no modifier uses any more (its VP-FFD
    modifier was removed or applied by Blender, which leaves the helper behind)."""
    tagged = [o for o in bpy.data.objects if o.get(HELPER_TAG) == obj.name]
    if not tagged:
        return
    # Blender's count can keep a user for the removed modifier's object input: ask who uses it.
    users = bpy.data.user_map(subset=tagged)
    for ob in tagged:
        if not users.get(ob):
            _remove_helper(ob)


def helper(obj, mod, exclusive_of=()):
    """The solver helper of `obj`'s VP-FFD modifier `mod` (`modifier.find(obj)`; None gives
    None), made when missing or when another object's modifier uses the same one (`exclusive_of`:
    helpers already claimed; duplicates of a bound object copy the modifier and with it the
    helper)."""
    if mod is None:
        return None
    ob = get_input(mod, SOLVER_INPUT)
    tagged = ob is not None and ob.get(HELPER_TAG) is not None
    # A helper linked from a library (a library override of an object bound in its library)
    # cannot be written here: the override gets one of its own, saved with it, and what Bind
    # saved stays readable on the library's (`saved_on`), so nothing of it is copied.
    linked = tagged and not writable(ob)
    if linked and (obj.library is not None or not obj.is_editable):
        return ob                       # linked itself: nothing here can be changed (update.py)
    if not tagged or linked or ob.type != "MESH" or ob in exclusive_of:
        shared = ob if tagged and not linked else None
        ob = _new_helper(obj)
        if shared is not None:          # a duplicate keeps what was saved at Bind (pins, cage)
            for key in shared.keys():
                if key != HELPER_TAG:
                    ob[key] = shared[key]
        set_input(mod, SOLVER_INPUT, ob)
    return ob


def saved_on(obj, mod, helper_ob):
    """The object that holds what Bind saved for `obj`'s VP-FFD modifier `mod`: its helper
    `helper_ob`, or, for a library override whose helper was made here (`helper`) and that was
    not bound here, the helper of the library's own object, so that a rig re-bound in its file
    is followed by every shot on reload."""
    if helper_ob is None or helper_ob.get(BOUND_HERE) or obj.override_library is None:
        return helper_ob
    reference = obj.override_library.reference
    if reference is None or reference.library is None or not writable(helper_ob):
        return helper_ob
    same = reference.modifiers.get(mod.name)
    if same is None or same.type != "NODES" or same.node_group is None:
        return helper_ob
    theirs = get_input(same, SOLVER_INPUT)
    if theirs is None or theirs == helper_ob or theirs.get(HELPER_TAG) is None:
        return helper_ob
    return theirs


def write_offsets(helper_ob, offsets):
    """Store (V, 3) float32 offsets as the helper's vertex positions (resized when V changed).
    ValueError for a helper that cannot be written (linked from a library): the panel must not
    describe a shape that Blender does not show."""
    if not writable(helper_ob):
        lib = helper_ob.library or helper_ob.data.library
        raise ValueError(f"the solver helper '{helper_ob.name}' is linked from "
                         f"{lib.filepath if lib else 'a library'} and cannot be written here: "
                         "VP-FFD's offsets would not reach the mesh")
    mesh = helper_ob.data
    values = np.ascontiguousarray(offsets, dtype=np.float32).reshape(-1, 3)
    if len(mesh.vertices) != len(values):
        mesh.clear_geometry()
        mesh.vertices.add(len(values))
    position = mesh.attributes.get("position")
    if position is not None and len(position.data) == len(values):
        position.data.foreach_set("vector", values.ravel())
    else:
        mesh.vertices.foreach_set("co", values.ravel())
    mesh.update()


def read_offsets(helper_ob):
    """(V, 3) float32 offsets currently stored in the helper (empty when none)."""
    if helper_ob is None:
        return np.zeros((0, 3), np.float32)
    mesh = helper_ob.data
    out = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", out)
    return out.reshape(-1, 3)


# ------------------------------------------------------------------------------------ the tap
