"""Reading and writing Blender data as flat NumPy arrays (foreach_get/foreach_set, float32 buffers)."""
import bpy
import numpy as np

from ..vpffd_addon.linalg3 import affine

_WEIGHT_ATTRIBUTE = "vpffd_weight_probe"


def mesh_coords(mesh, dtype=np.float64):
    """(V, 3) vertex positions of a Mesh datablock (its own, undeformed coordinates)."""
    n = len(mesh.vertices)
    buf = np.empty(n * 3, np.float32)
    position = mesh.attributes.get("position")
    if position is not None and position.data_type == "FLOAT_VECTOR" and len(position.data) == n:
        # The generic attribute copies the array in one go: ~25x faster than vertices' "co".
        position.data.foreach_get("vector", buf)
    else:
        mesh.vertices.foreach_get("co", buf)
    return buf.reshape(-1, 3).astype(dtype, copy=False)


def mesh_triangles(mesh):
    """(F, 3) int64 vertex indices of the mesh's triangulated faces."""
    mesh.calc_loop_triangles()
    buf = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("vertices", buf)
    return buf.reshape(-1, 3).astype(np.int64)


def topology_signature(mesh):
    """Cheap fingerprint of a mesh's topology: (vertices, edges, faces, corners)."""
    return (len(mesh.vertices), len(mesh.edges), len(mesh.polygons), len(mesh.loops))


def lattice_points(lattice_data, attr="co_deform"):
    """(N, 3) float64 lattice point positions (`co` rest grid or `co_deform`), Blender's order."""
    buf = np.empty(len(lattice_data.points) * 3, np.float32)
    lattice_data.points.foreach_get(attr, buf)
    return buf.reshape(-1, 3).astype(np.float64)


def lattice_group_weights(lattice_object, group_name):
    """(N,) weights of a vertex group of a Lattice or a cage mesh (unassigned points 0). N is the
    number of control points, small, so a loop over them is cheap."""
    group = lattice_object.vertex_groups.get(group_name)
    if group is None:
        raise ValueError(f"'{lattice_object.name}' has no vertex group '{group_name}'")
    data = lattice_object.data
    items = data.points if lattice_object.type == "LATTICE" else data.vertices
    w = np.zeros(len(items))
    for i, point in enumerate(items):
        for g in point.groups:
            if g.group == group.index:
                w[i] = g.weight
    return w


def _weight_probe_group(group_name):
    """A throw-away node group storing vertex group `group_name` as a float point attribute."""
    ng = bpy.data.node_groups.new(".vpffd weight probe", "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin, gout = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    read = ng.nodes.new("GeometryNodeInputNamedAttribute")
    read.data_type = "FLOAT"
    read.inputs["Name"].default_value = group_name
    store = ng.nodes.new("GeometryNodeStoreNamedAttribute")
    store.data_type = "FLOAT"
    store.domain = "POINT"
    store.inputs["Name"].default_value = _WEIGHT_ATTRIBUTE
    ng.links.new(gin.outputs[0], store.inputs["Geometry"])
    ng.links.new(read.outputs["Attribute"], store.inputs["Value"])
    ng.links.new(store.outputs[0], gout.inputs[0])
    return ng


def vertex_group_weights(obj, group_name):
    """(V,) weights of a mesh vertex group (unassigned vertices 0), read without a Python loop.

    Vertex groups have no flat array API, but Geometry Nodes see them as named attributes: a
    temporary modifier stores the group as a float attribute; every other modifier is switched off
    meanwhile so the evaluated mesh keeps the original vertices.
    """
    if obj.vertex_groups.get(group_name) is None:
        raise ValueError(f"'{obj.name}' has no vertex group '{group_name}'")
    mesh = obj.data
    saved = [(m, m.show_viewport) for m in obj.modifiers]
    ng = _weight_probe_group(group_name)
    probe = obj.modifiers.new(".vpffd weight probe", "NODES")
    try:
        probe.node_group = ng
        for m, _ in saved:
            m.show_viewport = False
        depsgraph = bpy.context.evaluated_depsgraph_get()
        depsgraph.update()
        evaluated = obj.evaluated_get(depsgraph).data
        attr = evaluated.attributes.get(_WEIGHT_ATTRIBUTE)
        if attr is None or len(evaluated.vertices) != len(mesh.vertices):
            raise RuntimeError(f"could not read vertex group '{group_name}' of '{obj.name}'")
        w = np.empty(len(mesh.vertices), np.float32)
        attr.data.foreach_get("value", w)
    finally:
        obj.modifiers.remove(probe)
        bpy.data.node_groups.remove(ng)
        for m, shown in saved:
            m.show_viewport = shown
    return w.astype(np.float64)


def float32_or_raise(values, what):
    """`values` as a contiguous float32 array; ValueError when some are not finite there (values
    finite in float64 can exceed float32's range, 3.4e38), so that nothing non-finite is written."""
    out = np.ascontiguousarray(values, dtype=np.float32)
    if not np.isfinite(out).all():
        raise ValueError(f"{what} exceed what Blender can store (float32): the lattice points or "
                         "the object scales are extreme; nothing was written")
    return out


def matrix(m):
    """A Blender 4x4 Matrix as a float64 (4, 4) array."""
    return np.array(m, dtype=np.float64).reshape(4, 4)


def transform(points, mat):
    """Apply a (4, 4) affine matrix to (V, 3) points (without BLAS: see `mesh.affine`)."""
    return affine(points, mat)


def world_bounds(objects, depsgraph, to_local=None):
    """(lo, hi) (3,) of the objects' evaluated vertices (what reaches the end of each one's
    modifier stack), in world space or through `to_local` (4, 4). ValueError when there are none."""
    pts = []
    for ob in objects:
        ev = ob.evaluated_get(depsgraph)
        co = mesh_coords(ev.data)
        M = matrix(ev.matrix_world)
        pts.append(transform(co, M if to_local is None else to_local @ M))
    pts = np.concatenate(pts) if pts else np.zeros((0, 3))
    if not len(pts):
        raise ValueError("the selected meshes have no vertices")
    return pts.min(0), pts.max(0)
