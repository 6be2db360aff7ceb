"""The node group of the VP-FFD modifier (modifier.py), its inputs and the attributes of its tap
(see docs/stack.md for the evaluation order).

Its node group does two things with the geometry that reaches it:
- the *tap*: a copy of the input's points (radius 0, marked `vpffd_tap`), with the live
  vertex-group weight of every point (`vpffd_weight`; packed with the positions in Blender 4.4+,
  see PACK). It passes through the modifiers after the
  slot untouched, so the handler reads the slot's input from the end of the stack;
- the *result*: the input moved by per-point offsets read, by index, from the object's solver
  helper (a hidden vertex-only mesh object that the handler writes after every solve).
In Blender 4.4 and newer the tap is instances of nothing, each carrying PACK of the input's points
as attributes: Python reads them from the object's evaluated geometry, while renders and exporters
(Alembic, USD), which see only instances of something, get nothing of VP-FFD's. Blender 4.2 and 4.3 offer Python no way to read those, so there
the tap is a point cloud, which those exporters write as a second copy of the mesh.
"""
import bpy

from . import node_inputs


NODE_GROUP_NAME = "VP-FFD"


GROUP_TAG = "vpffd_offset_group"  # custom property marking our node group, whatever it is renamed to


#: how many groups `_build` has tagged in this session: a group is tagged after bpy.data holds it,
#: so a look at the groups in between (an update that Bind runs) must not be kept
builds = [0]

GROUP_VERSION = 8                 # the tag's value: groups of older versions are rebuilt


_KIND = "vpffd_tap_kind"     # how the group's tap is made: "INSTANCES" or "POINTS"


LATTICE_INPUT = "Lattice"   # object input: makes the lattice or cage a dependency of the mesh


SOLVER_INPUT = "Solver"     # object input: the helper holding the offsets


GROUP_INPUT = "Vertex Group"


INVERT_INPUT = "Invert Vertex Group"


FACES_INPUT = "Tap Faces"   # on when the handler needs the faces at the slot (see read_tap)


SLOT_INPUT = "Slot"         # the modifier's persistent_uid, stored on its tap (several per stack)


TAP_ATTRIBUTE = "vpffd_tap"


FACE_ATTRIBUTE = "vpffd_face"          # marks the face tap's points


CORNER_ATTRIBUTES = ("vpffd_c0", "vpffd_c1", "vpffd_c2")   # a triangle's vertex indices


WEIGHT_ATTRIBUTE = "vpffd_weight"


# The point tap's positions also as a plain attribute (version 8): a later modifier that moves the
# points (a Transform of copies it joins) leaves it as it was, as it leaves the packed instance tap.
POINT_POSITION = "vpffd_position"


# Which VP-FFD modifier made a tap element: a mesh may have several, and the taps of earlier ones
# pass through the later ones to the end of the stack beside theirs.
SLOT_ATTRIBUTE = "vpffd_slot"


# The tap of Blender 4.4+ packs PACK vertices into every instance (making an instance costs far
# more than a value stored on it): of n = ceil(V / PACK) instances, vertex k * n + i of the slot is
# instance i's vpffd_co{k} and vpffd_w{k} (so that each attribute read is a contiguous run of the
# vertices); every instance also carries the slot's vertex count.
PACK = 8


PACKED_POSITIONS = tuple(f"vpffd_co{k}" for k in range(PACK))


PACKED_WEIGHTS = tuple(f"vpffd_w{k}" for k in range(PACK))


COUNT_ATTRIBUTE = "vpffd_count"


def _socket(ng, name, socket_type, in_out="INPUT", description=""):
    item = ng.interface.new_socket(name, in_out=in_out, socket_type=socket_type)
    item.description = description
    return item


def _set_triangulation(node):
    """Quads split on their first and third corners, n-gons by ear clipping: node properties up
    to Blender 4.5, menu inputs from 5.0."""
    if hasattr(node, "quad_method"):
        node.quad_method, node.ngon_method = "FIXED", "CLIP"
    else:
        node.inputs["Quad Method"].default_value = "Fixed"
        node.inputs["N-gon Method"].default_value = "Clip"


def _store(N, link, geometry, data_type, domain, name, value=None):
    """A Store Named Attribute node writing `value` (an output socket, or a constant) on
    `geometry`'s `domain`; returns the node."""
    store = N.new("GeometryNodeStoreNamedAttribute")
    store.data_type = data_type
    store.domain = domain
    store.inputs["Name"].default_value = name
    link(geometry, store.inputs["Geometry"])
    if isinstance(value, bpy.types.NodeSocket):
        link(value, store.inputs["Value"])
    else:
        store.inputs["Value"].default_value = value
    return store


def tap_kind():
    """The tap this Blender can read: instances of nothing (4.4+) or a point cloud."""
    return "INSTANCES" if hasattr(bpy.types.Object, "evaluated_geometry") else "POINTS"


def _sampled(N, link, geometry, data_type, value, index=None):
    """A Sample Index node reading field `value` of `geometry`'s points at `index` (an integer
    socket; by default the index of the element it is evaluated for). Out of range: zero."""
    sample = N.new("GeometryNodeSampleIndex")
    sample.data_type = data_type
    sample.domain = "POINT"
    link(geometry, sample.inputs["Geometry"])
    link(value, sample.inputs["Value"])
    link(index if index is not None else N.new("GeometryNodeInputIndex").outputs[0], sample.inputs["Index"])
    return sample.outputs[0]


def _int_math(N, link, operation, a, b, c=None):
    """a (op) b [(op) c] on integers: the Integer Math node where Blender has it, else the float
    Math node (exact below 2**24, far beyond any mesh a lattice deforms at interactive rates)."""
    if hasattr(bpy.types, "FunctionNodeIntegerMath"):
        node = N.new("FunctionNodeIntegerMath")
        node.operation = operation
    else:
        node = N.new("ShaderNodeMath")
        node.operation = {"DIVIDE_CEIL": "DIVIDE", "MULTIPLY_ADD": "MULTIPLY_ADD"}[operation]
    for socket, value in zip(node.inputs, (a, b, c)):
        if isinstance(value, bpy.types.NodeSocket):
            link(value, socket)
        elif value is not None:
            socket.default_value = value
    out = node.outputs[0]
    if operation == "DIVIDE_CEIL" and node.bl_idname == "ShaderNodeMath":
        ceil = N.new("ShaderNodeMath")
        ceil.operation = "CEIL"
        link(out, ceil.inputs[0])
        out = ceil.outputs[0]
    return out


def _vertex_tap(N, link, mesh, weight, slot, kind):
    """The tap of the vertices of `mesh` (in vertex order), with the float field `weight`
    (evaluated on the mesh); every element marked with TAP_ATTRIBUTE and SLOT_ATTRIBUTE (the integer
    socket `slot`). Made with a Points node that
    samples the mesh by index, not Mesh to Points, which copies every attribute of the mesh
    (7-14 ms per evaluation at 163,842 vertices against about 1 ms).
    - kind "POINTS": one point per vertex at its position (also as POINT_POSITION), the weight as
      WEIGHT_ATTRIBUTE and the vertex count (COUNT_ATTRIBUTE).
    - kind "INSTANCES": instances of nothing, each carrying PACK vertices (PACKED_POSITIONS,
      PACKED_WEIGHTS) and the vertex count (COUNT_ATTRIBUTE): an instance per vertex cost about
      5 ms per evaluation more.
    Returns (the first node, the marking node)."""
    size = N.new("GeometryNodeAttributeDomainSize")
    size.component = "MESH"
    link(mesh, size.inputs["Geometry"])
    count = size.outputs["Point Count"]
    points = N.new("GeometryNodePoints")
    points.inputs["Radius"].default_value = 0.0
    position = N.new("GeometryNodeInputPosition").outputs[0]
    if kind != "INSTANCES":
        link(count, points.inputs["Count"])
        link(_sampled(N, link, mesh, "FLOAT_VECTOR", position), points.inputs["Position"])
        tapped = _store(N, link, points.outputs[0], "FLOAT", "POINT", WEIGHT_ATTRIBUTE,
                        _sampled(N, link, mesh, "FLOAT", weight)).outputs[0]
        tapped = _store(N, link, tapped, "INT", "POINT", COUNT_ATTRIBUTE, count).outputs[0]
        tapped = _store(N, link, tapped, "FLOAT_VECTOR", "POINT", POINT_POSITION,
                        N.new("GeometryNodeInputPosition").outputs[0]).outputs[0]
        tapped = _store(N, link, tapped, "INT", "POINT", SLOT_ATTRIBUTE, slot).outputs[0]
        return points, _store(N, link, tapped, "BOOLEAN", "POINT", TAP_ATTRIBUTE, True)
    n = _int_math(N, link, "DIVIDE_CEIL", count, PACK)
    link(n, points.inputs["Count"])
    tapped = _store(N, link, points.outputs[0], "INT", "POINT", COUNT_ATTRIBUTE, count).outputs[0]
    for k in range(PACK):
        index = _int_math(N, link, "MULTIPLY_ADD", n, k, N.new("GeometryNodeInputIndex").outputs[0])
        tapped = _store(N, link, tapped, "FLOAT_VECTOR", "POINT", PACKED_POSITIONS[k],
                        _sampled(N, link, mesh, "FLOAT_VECTOR", position, index)).outputs[0]
        tapped = _store(N, link, tapped, "FLOAT", "POINT", PACKED_WEIGHTS[k],
                        _sampled(N, link, mesh, "FLOAT", weight, index)).outputs[0]
    instances = N.new("GeometryNodeInstanceOnPoints")
    link(tapped, instances.inputs["Points"])
    marked = _store(N, link, instances.outputs[0], "INT", "INSTANCE", SLOT_ATTRIBUTE, slot).outputs[0]
    return points, _store(N, link, marked, "BOOLEAN", "INSTANCE", TAP_ATTRIBUTE, True)


def _marked_points(N, link, geometry, mode, marker, slot, kind):
    """One tap element per `mode` element of `geometry` (attributes carried along), every one
    marked with the boolean attribute `marker` and SLOT_ATTRIBUTE (the integer socket `slot`):
    points of radius 0, or for kind "INSTANCES" instances of nothing on them. Returns (the first
    node, the marking node)."""
    points = N.new("GeometryNodeMeshToPoints")
    points.mode = mode
    points.inputs["Radius"].default_value = 0.0
    link(geometry, points.inputs["Mesh"])
    if kind != "INSTANCES":
        slotted = _store(N, link, points.outputs[0], "INT", "POINT", SLOT_ATTRIBUTE, slot).outputs[0]
        return points, _store(N, link, slotted, "BOOLEAN", "POINT", marker, True)
    instances = N.new("GeometryNodeInstanceOnPoints")
    link(points.outputs[0], instances.inputs["Points"])
    instances.location = (0, 0)
    slotted = _store(N, link, instances.outputs[0], "INT", "INSTANCE", SLOT_ATTRIBUTE, slot).outputs[0]
    return points, _store(N, link, slotted, "BOOLEAN", "INSTANCE", marker, True)


def _build(ng):
    """(Re)build the node group's nodes and interface, with the tap this Blender reads."""
    kind = tap_kind()
    ng.nodes.clear()
    for item in list(ng.interface.items_tree):
        ng.interface.remove(item)
    _socket(ng, "Geometry", "NodeSocketGeometry")
    _socket(ng, "Geometry", "NodeSocketGeometry", "OUTPUT")
    _socket(ng, LATTICE_INPUT, "NodeSocketObject",
            description="The Lattice or VP-FFD cage the solver reads (set by Bind)")
    _socket(ng, SOLVER_INPUT, "NodeSocketObject",
            description="VP-FFD's own helper object holding the solved offsets (set by Bind)")
    _socket(ng, GROUP_INPUT, "NodeSocketString", description="Vertex group weighting the deformation")
    _socket(ng, INVERT_INPUT, "NodeSocketBool", description="Invert the vertex group's weights")
    _socket(ng, FACES_INPUT, "NodeSocketBool",
            description="Also pass the input's triangles to VP-FFD (set when it cannot find them)")
    _socket(ng, SLOT_INPUT, "NodeSocketInt",
            description="Which VP-FFD modifier of the stack this is (set by VP-FFD)")
    N, link = ng.nodes, ng.links.new
    gin, gout = N.new("NodeGroupInput"), N.new("NodeGroupOutput")

    # Result: position + offsets[index] from the solver helper (out of range: no offset).
    info = N.new("GeometryNodeObjectInfo")
    info.transform_space = "ORIGINAL"
    link(gin.outputs[SOLVER_INPUT], info.inputs["Object"])
    sample = N.new("GeometryNodeSampleIndex")
    sample.data_type = "FLOAT_VECTOR"
    sample.domain = "POINT"
    link(info.outputs["Geometry"], sample.inputs["Geometry"])
    link(N.new("GeometryNodeInputPosition").outputs[0], sample.inputs["Value"])
    link(N.new("GeometryNodeInputIndex").outputs[0], sample.inputs["Index"])
    move = N.new("GeometryNodeSetPosition")
    link(gin.outputs[0], move.inputs["Geometry"])
    link(sample.outputs[0], move.inputs["Offset"])
    # The taps of VP-FFD modifiers earlier in the stack pass through unmoved: a point-cloud tap's
    # positions are what it carries.
    earlier = N.new("GeometryNodeInputNamedAttribute")
    earlier.data_type = "BOOLEAN"
    earlier.inputs["Name"].default_value = TAP_ATTRIBUTE
    untapped = N.new("FunctionNodeBooleanMath")
    untapped.operation = "NOT"
    link(earlier.outputs["Attribute"], untapped.inputs[0])
    link(untapped.outputs[0], move.inputs["Selection"])

    # Tap: the input's points with their weight: group weight (1 - weight when inverted), or 1
    # when the mesh has no such group, as the Lattice modifier weighs them.
    group = N.new("GeometryNodeInputNamedAttribute")
    group.data_type = "FLOAT"
    link(gin.outputs[GROUP_INPUT], group.inputs["Name"])
    inverted = N.new("ShaderNodeMath")
    inverted.operation = "SUBTRACT"
    inverted.inputs[0].default_value = 1.0
    link(group.outputs["Attribute"], inverted.inputs[1])
    pick_invert = N.new("GeometryNodeSwitch")
    pick_invert.input_type = "FLOAT"
    link(gin.outputs[INVERT_INPUT], pick_invert.inputs["Switch"])
    link(group.outputs["Attribute"], pick_invert.inputs["False"])
    link(inverted.outputs[0], pick_invert.inputs["True"])
    pick_exists = N.new("GeometryNodeSwitch")
    pick_exists.input_type = "FLOAT"
    link(group.outputs["Exists"], pick_exists.inputs["Switch"])
    pick_exists.inputs["False"].default_value = 1.0
    link(pick_invert.outputs[0], pick_exists.inputs["True"])
    points, mark = _vertex_tap(N, link, gin.outputs[0], pick_exists.outputs[0], gin.outputs[SLOT_INPUT], kind)

    # Face tap (only when asked): one point per triangle of the triangulated input, carrying its
    # three vertex indices, in the triangle's own corner order.
    # Split as Blender's own triangles of a mesh (quads on their first and third corners, n-gons
    # by ear clipping): the volume of non-planar faces depends on the split, and VP-FFD measures
    # every other input on those triangles.
    # Only the input's mesh: the taps of VP-FFD modifiers earlier in the stack come with it, and
    # Mesh to Points and Instance on Points would carry them along into this tap.
    mesh_only = N.new("GeometryNodeSeparateComponents")
    link(gin.outputs[0], mesh_only.inputs[0])
    faces = N.new("GeometryNodeTriangulate")
    _set_triangulation(faces)
    link(mesh_only.outputs["Mesh"], faces.inputs["Mesh"])
    geometry = faces.outputs[0]
    for k, name in enumerate(CORNER_ATTRIBUTES):
        corner = N.new("GeometryNodeCornersOfFace")
        corner.inputs["Sort Index"].default_value = k
        link(N.new("GeometryNodeInputIndex").outputs[0], corner.inputs["Face Index"])
        vertex = N.new("GeometryNodeVertexOfCorner")
        link(corner.outputs["Corner Index"], vertex.inputs["Corner Index"])
        store = _store(N, link, geometry, "INT", "FACE", name, vertex.outputs["Vertex Index"])
        geometry = store.outputs[0]
        store.location = (-150 + 200 * k, -700)
    face_points, face_mark = _marked_points(N, link, geometry, "FACES", FACE_ATTRIBUTE,
                                            gin.outputs[SLOT_INPUT], kind)
    only_if = N.new("GeometryNodeSwitch")
    only_if.input_type = "GEOMETRY"
    link(gin.outputs[FACES_INPUT], only_if.inputs["Switch"])
    link(face_mark.outputs[0], only_if.inputs["True"])

    join = N.new("GeometryNodeJoinGeometry")
    link(mark.outputs[0], join.inputs[0])
    link(only_if.outputs[0], join.inputs[0])
    link(move.outputs[0], join.inputs[0])
    link(join.outputs[0], gout.inputs[0])
    for node, x, y in ((gin, -900, 0), (info, -650, -250), (sample, -400, -200), (move, -150, 0),
                       (group, -900, -450), (inverted, -650, -500), (pick_invert, -450, -450),
                       (pick_exists, -250, -450), (points, 50, -300),
                       (mark, 250, -300), (faces, -450, -700), (face_points, 450, -700),
                       (face_mark, 650, -700), (only_if, 850, -500), (join, 1050, 0), (gout, 1250, 0),
                       (earlier, -650, 150), (untapped, -400, 150), (mesh_only, -650, -700)):
        node.location = (x, y)
    ng[GROUP_TAG] = GROUP_VERSION
    ng[_KIND] = kind
    builds[0] += 1


def hide_inputs(ng):
    """Show none of the group's inputs in the modifier: VP-FFD's panel sets them all, and a second,
    editable Lattice or Solver field there could only break the binding. Changes a group in place
    (an older file's group keeps its sockets, so its modifiers keep their values)."""
    if ng.library is not None:
        return
    for item in node_inputs.value_sockets(ng):
        if not getattr(item, "hide_in_modifier", True):
            item.hide_in_modifier = True


def is_current(ng):
    return ng.get(GROUP_TAG) == GROUP_VERSION and ng.get(_KIND) == tap_kind()


def packs_by_stride(ng):
    """Whether group `ng` packs the instance tap with vertex k * n + i on instance i (version 8
    and newer); older groups put vertex PACK * i + k there. A linked group is not rebuilt."""
    return ng is None or (ng.get(GROUP_TAG) or 0) >= 8


def _rebuild(ng):
    """Rebuild `ng` keeping every modifier's input values: a rebuilt interface has new socket
    identifiers, and the values are keyed by those (the Solver input names the helper that keeps
    what Bind saved)."""
    users = [m for ob in bpy.data.objects if ob.library is None for m in ob.modifiers
             if m.type == "NODES" and m.node_group == ng]
    names = {item.identifier: item.name for item in node_inputs.value_sockets(ng)}
    kept = [(m, {names[k]: v for k, v in node_inputs.values(m).items() if k in names and v is not None})
            for m in users]
    _build(ng)
    for m, values in kept:
        m.node_group = ng               # the modifier takes the new interface
        for name, value in values.items():
            set_input(m, name, value)


def offset_node_group():
    """The shared node group (created once per file, rebuilt when made by an older version or
    for another kind of tap, e.g. a file saved by Blender 4.2 opened in 4.4)."""
    for ng in bpy.data.node_groups:
        if ng.get(GROUP_TAG):
            if not is_current(ng) and ng.library is None:
                _rebuild(ng)
            return ng
    ng = bpy.data.node_groups.new(NODE_GROUP_NAME, "GeometryNodeTree")
    _build(ng)
    return ng


def _identifier(mod, name):
    for item in mod.node_group.interface.items_tree:
        if getattr(item, "in_out", None) == "INPUT" and item.name == name:
            return item.identifier
    return None


def get_input(mod, name):
    key = _identifier(mod, name)
    return None if key is None else node_inputs.get(mod, key)


#: session_uids of the objects whose VP-FFD inputs `set_input` changed since the update last asked
#: (update.update_object: a later deformer must not read a tap the change made stale)
retagged = set()


def set_input(mod, name, value):
    """Set the modifier's input `name` when it differs (writing tags the object for evaluation)."""
    key = _identifier(mod, name)
    if key is None:
        return False
    current = node_inputs.get(mod, key)
    if isinstance(value, (bpy.types.ID, type(None))):
        changed = current is not value
    else:
        changed = current != value
    if changed:
        node_inputs.put(mod, key, value)
        retagged.add(mod.id_data.session_uid)
        # A raw input value tags nothing by itself. An object input changes the depsgraph's
        # relations (a plain tag rebuilds them); any other only the object's data, and a plain
        # tag there would also re-evaluate its base flags, which Blender 4.2 to 5.1 can crash on
        # when a frame handler then evaluates again (several VP-FFD modifiers: update.py).
        if isinstance(value, (bpy.types.ID, type(None))):
            mod.id_data.update_tag()
        else:
            mod.id_data.update_tag(refresh={"DATA"})
    return changed
