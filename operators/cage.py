"""Cages of any topology as mesh objects (docs/design.md, "Cages of any topology"): their
vertices are the cage points, their edges draw the cells, and the cells themselves travel in the
mesh as the integer custom property `vpffd_cells`. Operators make one from a box, by extruding
polygons into layers, and fit one around the selected meshes.
"""
import bpy
import numpy as np
from bpy.props import EnumProperty, FloatProperty, IntProperty, IntVectorProperty

from .. import vpffd_addon as vp
from ..vpffd_addon.cage_cells import decode_cells, encode_cells
from ..vpffd_addon.wireframe import cage_edges
from .meshio import matrix, mesh_coords, world_bounds
from .text import report

CELLS_PROPERTY = "vpffd_cells"


def is_cage(obj):
    return obj is not None and obj.type == "MESH" and CELLS_PROPERTY in obj.data


def cage_cells(obj):
    """The cells stored with a cage object (list of tuples of face loops)."""
    cells = decode_cells(obj.data[CELLS_PROPERTY])
    n = len(obj.data.vertices)
    used = max((v for faces in cells for f in faces for v in f), default=-1)
    if used >= n:
        raise ValueError(f"cage '{obj.name}' has {n} vertices but its cells use {used + 1}: its vertices "
                         "were deleted in Edit Mode; make the cage again")
    return cells


def new_cage_object(context, name, points, cells, matrix_world=None):
    """A wire-drawn mesh object holding a cage, linked to the active collection, selected and
    active; validated first (a bad cage raises ValueError)."""
    ob = cage_object(name, points, cells, matrix_world)
    (context.collection or context.scene.collection).objects.link(ob)
    for other in context.selected_objects:
        other.select_set(False)
    ob.select_set(True)
    context.view_layer.objects.active = ob
    return ob


def cage_object(name, points, cells, matrix_world=None):
    """A wire-drawn mesh object holding a cage, not linked to any scene yet."""
    vp.Cage(points, cells)
    edges = cage_edges(cells)
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(points))
    me.vertices.foreach_set("co", np.asarray(points, np.float32).ravel())
    me.edges.add(len(edges))
    me.edges.foreach_set("vertices", edges.astype(np.int32).ravel())
    me.update()
    me[CELLS_PROPERTY] = encode_cells(cells)
    ob = bpy.data.objects.new(name, me)
    ob.display_type = "WIRE"
    ob.show_in_front = True
    ob.hide_render = True
    if matrix_world is not None:
        ob.matrix_world = matrix_world
    return ob


def selected_meshes(context, exclude=None):
    """The selected mesh objects, VP-FFD cages (and `exclude`) left out."""
    return [ob for ob in context.selected_objects if ob.type == "MESH" and ob is not exclude
            and not is_cage(ob)]


def _padded_bounds(objects, depsgraph, margin, to_local=None):
    """`meshio.world_bounds` grown by `margin` times the largest extent on every side."""
    lo, hi = world_bounds(objects, depsgraph, to_local)
    pad = margin * max(float((hi - lo).max()), 1e-6)
    return lo - pad, hi + pad


class OBJECT_OT_vpffd_cage_add_box(bpy.types.Operator):
    """Add a box-shaped VP-FFD cage of hexahedral cells, fitted around the selected meshes when there are any"""
    bl_idname = "object.vpffd_cage_add_box"
    bl_label = "VP-FFD Cage Box"
    bl_options = {"REGISTER", "UNDO"}

    resolution: IntVectorProperty(
        name="Resolution", size=3, default=(2, 2, 2), min=1, soft_max=12,
        description="Cells along X, Y and Z")
    size: FloatProperty(
        name="Size", default=2.0, min=1e-6, soft_max=100.0, unit="LENGTH",
        description="Edge length of the box when nothing is selected to fit")
    margin: FloatProperty(
        name="Margin", default=0.05, min=0.0, soft_max=1.0, subtype="FACTOR",
        description="Space left around the selected meshes, as a fraction of their size")

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            targets = selected_meshes(context)
            if targets:
                lo, hi = _padded_bounds(targets, context.evaluated_depsgraph_get(), self.margin)
                hi = np.maximum(hi, lo + 1e-6)
            else:
                c = np.array(context.scene.cursor.location)
                lo, hi = c - 0.5 * self.size, c + 0.5 * self.size
            centre = 0.5 * (lo + hi)
            cage = vp.box_cage(self.resolution, (lo - centre, hi - centre))
            ob = new_cage_object(context, "Cage", cage.rest_points, cage.cells)
            ob.location = centre
        except ValueError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        report(self, "INFO", f"cage of {cage.n_cells:,} cells, {cage.n_points:,} points")
        return {"FINISHED"}


class OBJECT_OT_vpffd_cage_from_polygons(bpy.types.Operator):
    """Make a VP-FFD cage by extruding the active mesh's polygons into layers of cells (a disc of polygons gives a cylinder); the mesh itself is left as it is"""
    bl_idname = "object.vpffd_cage_from_polygons"
    bl_label = "Cage from Polygons"
    bl_options = {"REGISTER", "UNDO"}

    layers: IntProperty(
        name="Layers", default=2, min=1, soft_max=16,
        description="Cells stacked along the extrusion")
    thickness: FloatProperty(
        name="Thickness", default=1.0, min=1e-6, soft_max=100.0, unit="LENGTH",
        description="Total length of the extrusion")
    direction: EnumProperty(
        name="Direction", default="NORMAL",
        items=[("NORMAL", "Normal", "Along the polygons' average normal"),
               ("X", "X", "Along the object's X axis"),
               ("Y", "Y", "Along the object's Y axis"),
               ("Z", "Z", "Along the object's Z axis")],
        description="Direction of the extrusion, in the object's space")
    use_centered: bpy.props.BoolProperty(
        name="Centered", default=True,
        description="Extrude to both sides of the polygons, so that they sit in the cage's middle")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        ob = context.active_object
        return ob is not None and ob.type == "MESH" and ob.mode == "OBJECT" and not is_cage(ob)

    def execute(self, context: bpy.types.Context) -> set[str]:
        ob = context.active_object
        me = ob.data
        if not len(me.polygons):
            report(self, "ERROR", f"'{ob.name}' has no polygons to extrude")
            return {"CANCELLED"}
        points = mesh_coords(me)
        starts = np.empty(len(me.polygons), np.int32)
        totals = np.empty(len(me.polygons), np.int32)
        me.polygons.foreach_get("loop_start", starts)
        me.polygons.foreach_get("loop_total", totals)
        loops = np.empty(len(me.loops), np.int32)
        me.loops.foreach_get("vertex_index", loops)
        polys = [loops[s:s + t].tolist() for s, t in zip(starts, totals)]
        used = np.unique(loops)
        if self.direction == "NORMAL":
            normals = np.empty(3 * len(me.polygons), np.float32)
            areas = np.empty(len(me.polygons), np.float32)
            me.polygons.foreach_get("normal", normals)
            me.polygons.foreach_get("area", areas)
            axis = (normals.reshape(-1, 3) * areas[:, None]).sum(0)
            if not np.linalg.norm(axis) > 0:
                report(self, "ERROR", "the polygons' normals cancel out: pick X, Y or Z as the direction")
                return {"CANCELLED"}
        else:
            axis = np.eye(3)["XYZ".index(self.direction)]
        offset = self.thickness * axis / np.linalg.norm(axis)
        # Keep only the points the polygons use, renumbered.
        remap = np.full(len(points), -1)
        remap[used] = np.arange(len(used))
        base = points[used] - (0.5 * offset if self.use_centered else 0.0)
        try:
            P, cells = vp.extrude(base, [remap[p].tolist() for p in polys], offset, self.layers)
            cage = new_cage_object(context, ob.name + " Cage", P, cells, ob.matrix_world.copy())
        except ValueError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        report(self, "INFO", f"cage '{cage.name}': {len(cells):,} cells, {len(P):,} points")
        return {"FINISHED"}


class OBJECT_OT_vpffd_cage_fit(bpy.types.Operator):
    """Move and scale the active cage's points so that it encloses the other selected meshes (do this before binding)"""
    bl_idname = "object.vpffd_cage_fit"
    bl_label = "Fit Cage to Selected"
    bl_options = {"REGISTER", "UNDO"}

    margin: FloatProperty(
        name="Margin", default=0.05, min=0.0, soft_max=1.0, subtype="FACTOR",
        description="Space left around the selected meshes, as a fraction of their size")
    use_uniform: bpy.props.BoolProperty(
        name="Uniform", default=False,
        description="Scale the cage by one factor on all axes (keeps its proportions)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        ob = context.active_object
        return is_cage(ob) and ob.mode == "OBJECT"

    def execute(self, context: bpy.types.Context) -> set[str]:
        cage_ob = context.active_object
        targets = selected_meshes(context, exclude=cage_ob)
        if not targets:
            report(self, "ERROR", "select the meshes to enclose, then the cage last (active)")
            return {"CANCELLED"}
        to_local = np.linalg.inv(matrix(cage_ob.matrix_world))
        lo, hi = _padded_bounds(targets, context.evaluated_depsgraph_get(), self.margin, to_local)
        me = cage_ob.data
        P = mesh_coords(me)
        plo, phi = P.min(0), P.max(0)
        scale = (hi - lo) / np.maximum(phi - plo, 1e-12)
        if self.use_uniform:
            scale[:] = scale.max()
        # Flat cages (e.g. one layer of extruded polygons seen edge-on) keep their extent.
        scale = np.where(phi - plo > 1e-12, scale, 1.0)
        new = (P - 0.5 * (plo + phi)) * scale + 0.5 * (lo + hi)
        try:
            vp.Cage(new, cage_cells(cage_ob))
        except ValueError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        me.vertices.foreach_set("co", new.astype(np.float32).ravel())
        me.update()
        return {"FINISHED"}


class VIEW3D_MT_vpffd_cages(bpy.types.Menu):
    bl_label = "VP-FFD Cage"
    bl_idname = "VIEW3D_MT_vpffd_cages"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        layout.operator(OBJECT_OT_vpffd_cage_add_box.bl_idname, icon="MESH_CUBE")
        layout.operator(OBJECT_OT_vpffd_cage_from_polygons.bl_idname, icon="MOD_SOLIDIFY")
        layout.operator(OBJECT_OT_vpffd_cage_fit.bl_idname, icon="FULLSCREEN_ENTER")


def _add_menu(self, context):
    self.layout.menu(VIEW3D_MT_vpffd_cages.bl_idname, icon="MESH_ICOSPHERE")


classes = (OBJECT_OT_vpffd_cage_add_box, OBJECT_OT_vpffd_cage_from_polygons, OBJECT_OT_vpffd_cage_fit,
           VIEW3D_MT_vpffd_cages)


def register():
    bpy.types.VIEW3D_MT_add.append(_add_menu)


def unregister():
    bpy.types.VIEW3D_MT_add.remove(_add_menu)
