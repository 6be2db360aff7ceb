"""The VP-FFD entry in the modifier stack: a Geometry Nodes modifier that adds the offsets the solver
stores on the mesh (attribute `vpffd_offset`) to the positions. Being a real modifier, it can be
toggled for viewport and render, reordered and removed like any other."""
import bpy

from .meshio import OFFSET_ATTRIBUTE

MODIFIER_NAME = "VP-FFD"
NODE_GROUP_NAME = "VP-FFD Offset"
_TAG = "vpffd_offset_group"  # custom property marking our node group, whatever it is renamed to
LATTICE_INPUT = "Lattice"   # object input: makes the lattice or cage a dependency of the mesh


def offset_node_group():
    """The shared node group (created once per file): Set Position with Offset = Named Attribute."""
    for ng in bpy.data.node_groups:
        if ng.get(_TAG):
            return ng
    ng = bpy.data.node_groups.new(NODE_GROUP_NAME, "GeometryNodeTree")
    ng[_TAG] = True
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin, gout = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    offset = ng.nodes.new("GeometryNodeInputNamedAttribute")
    offset.data_type = "FLOAT_VECTOR"
    offset.inputs["Name"].default_value = OFFSET_ATTRIBUTE
    move = ng.nodes.new("GeometryNodeSetPosition")
    ng.links.new(gin.outputs[0], move.inputs["Geometry"])
    ng.links.new(offset.outputs["Attribute"], move.inputs["Offset"])
    ng.links.new(move.outputs["Geometry"], gout.inputs[0])
    gin.location, offset.location, move.location, gout.location = (-400, 0), (-400, -150), (-150, 0), (100, 0)
    _ensure_lattice_input(ng)
    return ng


def _ensure_lattice_input(ng):
    """The group's object input for the lattice or cage (added to groups made by older versions).
    The modifier's object inputs are dependencies of the mesh, so every evaluation, a render's
    included, evaluates the lattice or cage before the mesh, even when it is hidden from renders
    (the solver reads it from the render's own depsgraph)."""
    for item in ng.interface.items_tree:
        if getattr(item, "in_out", None) == "INPUT" and item.name == LATTICE_INPUT:
            return item.identifier
    item = ng.interface.new_socket(LATTICE_INPUT, in_out="INPUT", socket_type="NodeSocketObject")
    item.description = "The Lattice or VP-FFD cage the solver reads (set by Bind)"
    return item.identifier


def set_lattice(obj, lattice):
    """Point the VP-FFD modifier's lattice input at `lattice` (an Object or None), when it differs."""
    mod = find(obj)
    if mod is None:
        return
    key = _ensure_lattice_input(mod.node_group)
    if mod.get(key) is not lattice:
        mod[key] = lattice


def find(obj):
    """The object's VP-FFD modifier, or None."""
    for m in obj.modifiers:
        if m.type == "NODES" and m.node_group is not None and m.node_group.get(_TAG):
            return m
    return None


def ensure(obj):
    """Find or add the VP-FFD modifier; a new one goes first in the stack, where a Lattice
    modifier would normally sit (it deforms the mesh's own coordinates)."""
    mod = find(obj)
    if mod is not None:
        return mod
    mod = obj.modifiers.new(MODIFIER_NAME, "NODES")
    mod.node_group = offset_node_group()
    index = len(obj.modifiers) - 1
    if index:
        try:
            with bpy.context.temp_override(object=obj, active_object=obj):
                bpy.ops.object.modifier_move_to_index(modifier=mod.name, index=0)
        except RuntimeError:
            pass  # no suitable context (e.g. some background scripts): it stays last
    return mod


def remove(obj):
    mod = find(obj)
    if mod is not None:
        obj.modifiers.remove(mod)
