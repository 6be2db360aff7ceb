"""Reference results from Blender's own Lattice modifier (bpy, headless).

Only imported by tests that first call ``pytest.importorskip("bpy")``.

What was measured with bpy 5.0.1 (the tests in test_blender_parity.py check it again):
- ``bpy.data.lattices.new`` gives 2x2x2 points spanning [-0.5, 0.5]. Resizing through RNA
  (points_u/_v/_w) keeps unit spacing, centred on 0: (4,5,6) spans [-1.5,1.5]x[-2,2]x[-2.5,2.5],
  (12,12,12) spans [-5.5,5.5]^3, (1,3,2) has co x = 0, y in {-1,0,1}, z in {-0.5,0.5}.
  So bounds come from ``co`` (min/max per axis); an axis with one point has co = 0 there.
- Along an axis with one point every vertex gets weight 1 from that axis, wherever it lies.
- The modifier works in the lattice object's local space: a mesh vertex x (mesh local) is taken to
  L = inv(M_lattice) @ M_mesh, deformed there, and mapped back with inv(L). The displacement is
  s * sum w_i w_j w_k (co_deform - co), s = weight * strength.
- Vertex group: unassigned vertices and vertices assigned with weight 0 both get s = 0; with
  ``invert_vertex_group`` s = (1 - weight) * strength, so unassigned vertices get s = strength.
  A group name the mesh lacks means no weighting (s = strength).
- Everything is stored and computed in float32: ``co_deform``, input and output vertex
  coordinates; the result matches a float64 evaluation of the formula to ~1e-6 of the lattice size.
"""

import math

import bpy
import mathutils
import numpy as np

from demos.render_demos import evaluated_world as _demo_evaluated_world

_PREFIX = "vpffd_ref_"


def remove_all():
    """Delete every object, mesh and lattice, leaving an empty scene."""
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob, do_unlink=True)
    for me in list(bpy.data.meshes):
        bpy.data.meshes.remove(me)
    for lt in list(bpy.data.lattices):
        bpy.data.lattices.remove(lt)


def _matrix(m):
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"matrix must be 4x4, got {m.shape}")
    return mathutils.Matrix(m.tolist())


def _get_vec3(collection, prop, n):
    buf = np.empty(3 * n, dtype=np.float32)
    collection.foreach_get(prop, buf)
    return buf.reshape(n, 3).astype(np.float64)


def triangle_mesh(verts, tris, name=_PREFIX + "mesh"):
    """Mesh datablock from verts (V,3) and triangles (F,3), all through foreach_set. The one
    helper the tests and the benchmark build their meshes with."""
    verts, tris = np.asarray(verts), np.asarray(tris)
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(verts))
    me.vertices.foreach_set("co", verts.astype(np.float32).ravel())
    if len(tris):
        f = len(tris)
        me.loops.add(3 * f)
        me.loops.foreach_set("vertex_index", tris.astype(np.int32).ravel())
        me.polygons.add(f)
        me.polygons.foreach_set("loop_start", np.arange(0, 3 * f, 3, dtype=np.int32))
    me.update(calc_edges=True)
    return me


def _add_vertex_group(ob, weights, name=None):
    """Vertex group from weights (V,) without a per-vertex Python loop; returns its name.

    A float point attribute converted by the operator; weight-0 vertices end up unassigned,
    which Blender treats as weight 0 (checked)."""
    me = ob.data
    before = len(ob.vertex_groups)
    attr = me.attributes.new(name or (_PREFIX + "weights"), "FLOAT", "POINT")
    attr.data.foreach_set("value", np.asarray(weights, np.float32))
    me.attributes.active = attr
    with bpy.context.temp_override(object=ob, active_object=ob):
        result = bpy.ops.geometry.attribute_convert(mode="VERTEX_GROUP")
    if result != {"FINISHED"} or len(ob.vertex_groups) != before + 1:
        raise RuntimeError("could not convert the weights into a vertex group")
    return ob.vertex_groups[-1].name


def lattice_modifier_reference(verts, tris, shape, interpolation, deformed_points=None, *,
                               lattice_matrix=None, mesh_matrix=None, weights=None,
                               strength=1.0, invert=False):
    """Run Blender's Lattice modifier on a mesh and return what it computed.

    verts (V,3) mesh-local coordinates, tris (F,3) vertex indices, shape (nu, nv, nw),
    interpolation: one name or three ('LINEAR', 'CARDINAL', 'CATMULL_ROM', 'BSPLINE'),
    deformed_points (N,3) lattice-local control points in Blender order (u fastest) or None for
    the rest grid, lattice_matrix / mesh_matrix 4x4 matrix_world, weights (V,) vertex-group
    weights or None for no group.

    Returns a dict: 'rest_points' (N,3) lattice ``co``; 'deformed_points' (N,3) the evaluated
    ``co_deform`` (float32-rounded); 'verts' (V,3) evaluated mesh coordinates (mesh local);
    'verts_in' (V,3) the mesh's stored float32 input coordinates; 'execution_time' seconds
    the modifier reported. All arrays float64.
    """
    verts = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    tris = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    nu, nv, nw = (int(n) for n in shape)
    n_points = nu * nv * nw
    if isinstance(interpolation, str):
        interpolation = (interpolation,) * 3
    if len(interpolation) != 3:
        raise ValueError("interpolation needs one name or three")

    remove_all()
    scene = bpy.context.scene

    lat = bpy.data.lattices.new(_PREFIX + "lattice")
    lat.points_u, lat.points_v, lat.points_w = nu, nv, nw
    lat.interpolation_type_u, lat.interpolation_type_v, lat.interpolation_type_w = (
        "KEY_" + name.upper() for name in interpolation)
    if deformed_points is not None:
        pts = np.asarray(deformed_points, dtype=np.float64)
        if pts.shape != (n_points, 3):
            raise ValueError(f"deformed_points must be ({n_points}, 3), got {pts.shape}")
        lat.points.foreach_set("co_deform", pts.astype(np.float32).ravel())
    lat_ob = bpy.data.objects.new(_PREFIX + "lattice", lat)
    scene.collection.objects.link(lat_ob)

    me = triangle_mesh(verts, tris)
    ob = bpy.data.objects.new(_PREFIX + "mesh", me)
    scene.collection.objects.link(ob)
    if lattice_matrix is not None:
        lat_ob.matrix_world = _matrix(lattice_matrix)
    if mesh_matrix is not None:
        ob.matrix_world = _matrix(mesh_matrix)

    mod = ob.modifiers.new("Lattice", "LATTICE")
    mod.object = lat_ob
    mod.strength = float(strength)
    if weights is not None:
        weights = np.asarray(weights, dtype=np.float64).reshape(-1)
        if weights.shape != (len(verts),):
            raise ValueError("weights must have one entry per vertex")
        mod.vertex_group = _add_vertex_group(ob, weights)
        mod.invert_vertex_group = bool(invert)

    depsgraph = bpy.context.evaluated_depsgraph_get()
    depsgraph.update()
    ob_eval = ob.evaluated_get(depsgraph)
    me_eval = ob_eval.data
    lat_eval = lat_ob.evaluated_get(depsgraph).data
    if len(me_eval.vertices) != len(verts):
        raise RuntimeError("Blender changed the vertex count")

    return {
        "rest_points": _get_vec3(lat_eval.points, "co", n_points),
        "deformed_points": _get_vec3(lat_eval.points, "co_deform", n_points),
        "verts": _get_vec3(me_eval.vertices, "co", len(verts)),
        "verts_in": _get_vec3(me.vertices, "co", len(verts)),
        "execution_time": float(ob_eval.modifiers[0].execution_time),
    }


def bind(ob, **settings):
    """Set `ob.vpffd`'s `settings` and press Bind with `ob` active and selected, as a user does;
    the operator's result."""
    for k, v in settings.items():
        setattr(ob.vpffd, k, v)
    with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
        return bpy.ops.object.vpffd_bind()


def evaluated_world(ob):
    """(world coords (V, 3) float64 of the float32 evaluated mesh of `ob`, tris (F, 3)): the demos'
    own measurement, on the context's depsgraph."""
    return _demo_evaluated_world(ob, bpy.context.evaluated_depsgraph_get())


def evaluated_volume(ob):
    """Volume of the evaluated mesh, independently: 1/6 sum a . (b x c) over its triangles."""
    co, tris = evaluated_world(ob)
    a, b, c = co[tris[:, 0]], co[tris[:, 1]], co[tris[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def two_bone_armature(name="Rig", half_length=1.0, bend=math.radians(60), frames=(1, 20)):
    """An armature object of two bones along +Z ("Lower" ending and "Upper" starting at the
    origin, each `half_length` long), linked to the scene; "Upper" bends about X from 0 at
    frames[0] to `bend` at frames[1]."""
    arm = bpy.data.armatures.new(name)
    ob = bpy.data.objects.new(name, arm)
    bpy.context.scene.collection.objects.link(ob)
    bpy.context.view_layer.objects.active = ob
    with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
        bpy.ops.object.mode_set(mode="EDIT")
        lower = arm.edit_bones.new("Lower")
        lower.head, lower.tail = (0, 0, -half_length), (0, 0, 0)
        upper = arm.edit_bones.new("Upper")
        upper.head, upper.tail = (0, 0, 0), (0, 0, half_length)
        upper.parent = lower
        bpy.ops.object.mode_set(mode="OBJECT")
    pose = ob.pose.bones["Upper"]
    pose.rotation_mode = "XYZ"
    for f, angle in zip(frames, (0.0, bend)):
        pose.rotation_euler = (angle, 0, 0)
        pose.keyframe_insert("rotation_euler", frame=f)
    return ob


def bone_weights_by_height(ob, blend):
    """Vertex groups "Lower" and "Upper" on mesh object `ob`, blending linearly over |z| < blend."""
    co = np.empty(len(ob.data.vertices) * 3, np.float32)
    ob.data.vertices.foreach_get("co", co)
    t = np.clip((co[2::3] + blend) / (2 * blend), 0, 1)
    _add_vertex_group(ob, 1 - t, "Lower")
    _add_vertex_group(ob, t, "Upper")


def squash_lattice(name, shape, scale, squash, bulge, shear=0.0):
    """A B-spline lattice object linked to the scene, scaled by `scale` (3,), with a shape key
    "Squash" that scales its z by `squash`, widens x and y by 1 + bulge * cos(z) and shears x by
    shear * z. Returns (object, shape key) with the key's value left at 0."""
    lt = bpy.data.lattices.new(name)
    lt.points_u, lt.points_v, lt.points_w = shape
    for a in "uvw":
        setattr(lt, f"interpolation_type_{a}", "KEY_BSPLINE")
    ob = bpy.data.objects.new(name, lt)
    ob.scale = scale
    bpy.context.scene.collection.objects.link(ob)
    ob.shape_key_add(name="Basis")
    key = ob.shape_key_add(name="Squash")
    co = np.empty(len(lt.points) * 3, np.float32)
    lt.points.foreach_get("co", co)
    co = co.reshape(-1, 3)
    co[:, 2] *= squash
    co[:, :2] *= 1.0 + bulge * np.cos(co[:, 2:3])
    co[:, 0] += shear * co[:, 2]
    key.data.foreach_set("co", co.ravel())
    return ob, key


def squashed_lattice(z_factor=0.5, shape=(4, 4, 4), name="Lattice"):
    """A lattice object 2 units wide (a 4-point axis spans 3 units in its own space) linked to the
    scene, its points' z scaled by `z_factor` (negative: a mirror; 0: flattened to zero thickness)."""
    lt = bpy.data.lattices.new(name)
    lt.points_u, lt.points_v, lt.points_w = shape
    ob = bpy.data.objects.new(name, lt)
    ob.scale = (2 / 3,) * 3
    bpy.context.scene.collection.objects.link(ob)
    co = np.empty(len(lt.points) * 3, np.float32)
    lt.points.foreach_get("co", co)
    co = co.reshape(-1, 3)
    co[:, 2] *= z_factor
    lt.points.foreach_set("co_deform", co.ravel())
    return ob
