"""Add > Lattice > VP-FFD Lattice Deform Selected: a lattice fitted around the selected meshes,
each bound to it with VP-FFD, in one step (and one undo step), as Blender's own "Lattice Deform
Selected" does for its Lattice modifier. The fitting is `vpffd_addon.fit_lattice`."""
import bpy
import numpy as np
from bpy.props import EnumProperty, FloatProperty, IntProperty

from . import deformers, meshio
from .cage import selected_meshes
from .text import report
from .lifecycle import BindError, add_deformer, bind
from .release import unbind

try:
    from ..vpffd_addon import fit_lattice
except ImportError:  # loaded outside the extension package
    from vpffd_addon import fit_lattice


def add_fitted_lattice(context, meshes, resolution=4, margin=0.05, axes="XYZ"):
    """Make a B-spline lattice around the evaluated `meshes` and bind each of them to it with
    correction `axes` (a mesh that has a bound VP-FFD deformer already gets another, at the end of
    its stack). Returns (lattice object, {mesh name: warnings or error text})."""
    lo, hi = meshio.world_bounds(meshes, context.evaluated_depsgraph_get())
    centre, size, shape = fit_lattice(np.stack([lo, hi]), margin=margin, resolution=resolution)
    data = bpy.data.lattices.new("VP-FFD Lattice")
    data.points_u, data.points_v, data.points_w = (int(n) for n in shape)
    for axis in "uvw":
        setattr(data, f"interpolation_type_{axis}", "KEY_BSPLINE")
    lat = bpy.data.objects.new("VP-FFD Lattice", data)
    context.collection.objects.link(lat)
    # The rest grid keeps unit spacing ((n - 1) wide): scale it to the fitted size.
    co = meshio.lattice_points(data, "co")
    span = co.max(0) - co.min(0)
    lat.location = centre
    lat.scale = [float(s / w) if w > 0 else float(s) for s, w in zip(size, span)]
    context.view_layer.update()
    results = {}
    for ob in meshes:
        added = None
        try:
            if deformers.is_bound(ob):
                d = added = add_deformer(ob, {"lattice": lat, "axes": axes})
                ob.modifiers.active = d.mod
            else:
                d = deformers.first(ob)
                d.settings.lattice, d.settings.axes = lat, axes
            results[ob.name] = bind(d, context.evaluated_depsgraph_get())
        except (BindError, ValueError) as exc:
            results[ob.name] = str(exc)
            # The deformer added for it goes with the failed Bind (a refused solve removed it
            # already: ask by uid, never through the removed modifier).
            left = [m for m in ob.modifiers if added is not None and m.persistent_uid == added.uid]
            if left:
                unbind(deformers.Deformer(ob, left[0], added.settings))
    return lat, results


def poll_refusal(context):
    """Why Lattice Deform Selected cannot run in `context`, in words, or "" when it can."""
    if context.mode != "OBJECT":
        return "Switch to Object Mode first"
    if not selected_meshes(context):
        return "Select the mesh objects to deform (a VP-FFD cage is a control, not a mesh to deform)"
    return ""


class OBJECT_OT_vpffd_lattice_deform_selected(bpy.types.Operator):
    """Add a lattice fitted around the selected meshes (as they reach the end of their modifier
    stacks) and bind each of them to it with VP-FFD, volume kept"""
    bl_idname = "object.vpffd_lattice_deform_selected"
    bl_label = "VP-FFD Lattice Deform Selected"
    bl_options = {"REGISTER", "UNDO"}

    resolution: IntProperty(name="Resolution", description="Lattice points along the longest side "
                            "(the other sides get as many as keep the cells about square)",
                            default=4, min=2, max=64)
    margin: FloatProperty(name="Margin", description="Room around the meshes on each side, as a "
                          "fraction of their largest extent", default=0.05, min=0.0, max=1.0,
                          subtype="FACTOR")
    axes: EnumProperty(name="Correction", description="Directions along which the volume is kept",
                       items=[(a, a, "") for a in ("XYZ", "XY", "XZ", "YZ", "X", "Y", "Z")],
                       default="XYZ")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        why = poll_refusal(context)
        if why and hasattr(cls, "poll_message_set"):     # Blender shows it on the greyed-out item
            cls.poll_message_set(why)
        return not why

    def execute(self, context: bpy.types.Context) -> set[str]:
        meshes = selected_meshes(context)          # a VP-FFD cage is a control, not a mesh to deform
        try:
            lat, results = add_fitted_lattice(context, meshes, self.resolution, self.margin, self.axes)
        except ValueError as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        failed = {name: r for name, r in results.items() if isinstance(r, str)}
        for name, text in failed.items():
            report(self, "WARNING", f"'{name}' was not bound: {text}")
        for name, warnings in results.items():
            if not isinstance(warnings, str):
                for text in warnings:
                    report(self, "WARNING", f"'{name}': {text}")
        if len(failed) == len(meshes):
            data = lat.data
            bpy.data.objects.remove(lat)
            bpy.data.lattices.remove(data)
            report(self, "ERROR", "no mesh could be bound: no lattice was added")
            return {"CANCELLED"}
        for ob in context.selected_objects:
            ob.select_set(False)
        lat.select_set(True)
        context.view_layer.objects.active = lat      # ready for Tab (Edit Mode)
        context.scene.render.use_lock_interface = True
        return {"FINISHED"}


def _menu(self, context):
    self.layout.operator(OBJECT_OT_vpffd_lattice_deform_selected.bl_idname, icon="MOD_LATTICE")


# Blender 5.0+ has Add > Lattice (with its own "Lattice Deform Selected"); 4.x adds a lattice
# straight from the Add menu.
_MENU = "VIEW3D_MT_lattice_add" if hasattr(bpy.types, "VIEW3D_MT_lattice_add") else "VIEW3D_MT_add"

classes = (OBJECT_OT_vpffd_lattice_deform_selected,)


def register():
    getattr(bpy.types, _MENU).append(_menu)


def unregister():
    getattr(bpy.types, _MENU).remove(_menu)
