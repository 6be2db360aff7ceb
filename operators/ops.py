"""Operators: bind, unbind, apply, save as shape key, check folds. Thin wrappers over `lifecycle`, `release` and `update`."""
import bpy

from .text import report
from .lifecycle import BindError, apply, bind, save_shape_key
from .release import unbind
from .status import status
from .update import check_folds


class _ObjectOperator:
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        ob = context.object
        return ob is not None and ob.type == "MESH"


class _BoundOperator(_ObjectOperator):
    """An operator on a mesh that is bound already."""

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return super().poll(context) and context.object.vpffd.is_bound


class OBJECT_OT_vpffd_bind(_ObjectOperator, bpy.types.Operator):
    """Bind the mesh to its lattice with exact volume preservation (adds the VP-FFD modifier at the end of the stack)"""
    bl_idname = "object.vpffd_bind"
    bl_label = "Bind"

    @classmethod
    def description(cls, context: bpy.types.Context, properties) -> str:
        ob = context.object
        if ob is not None and ob.type == "MESH" and ob.vpffd.is_bound:
            return ("Bind the mesh again with the current settings (pins, a cage's rest shape); "
                    "the VP-FFD modifier stays where it is in the stack")
        return cls.__doc__

    def execute(self, context: bpy.types.Context) -> set[str]:
        ob = context.object
        try:
            warnings = bind(ob, context.evaluated_depsgraph_get())
        except (BindError, ValueError) as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        for text in warnings:
            report(self, "WARNING", text)
        context.scene.render.use_lock_interface = True  # handlers write data during renders
        return {"FINISHED"}


class OBJECT_OT_vpffd_unbind(_BoundOperator, bpy.types.Operator):
    """Remove VP-FFD from the mesh; its own coordinates were never changed"""
    bl_idname = "object.vpffd_unbind"
    bl_label = "Unbind"

    def execute(self, context: bpy.types.Context) -> set[str]:
        unbind(context.object)
        return {"FINISHED"}


class OBJECT_OT_vpffd_apply(_BoundOperator, bpy.types.Operator):
    """Make the current volume-preserved shape the mesh's own, and unbind"""
    bl_idname = "object.vpffd_apply"
    bl_label = "Apply"

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            apply(context.object, context.evaluated_depsgraph_get())
        except (BindError, ValueError) as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class OBJECT_OT_vpffd_save_shape_key(_BoundOperator, bpy.types.Operator):
    """Save what VP-FFD gives on this frame as a new shape key of the mesh, keeping the modifier
    (Blender's own Save as Shape Key does not work on a Geometry Nodes modifier)"""
    bl_idname = "object.vpffd_save_shape_key"
    bl_label = "Save as Shape Key"

    def execute(self, context: bpy.types.Context) -> set[str]:
        ob = context.object
        try:
            name, before = save_shape_key(ob, context.evaluated_depsgraph_get())
        except (BindError, ValueError) as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        if before:
            report(self, "WARNING", f"shape key '{name}' includes the modifiers before "
                                     f"VP-FFD ({', '.join(before)})")
        else:
            report(self, "INFO", f"saved shape key '{name}'")
        return {"FINISHED"}


class OBJECT_OT_vpffd_check_folds(_BoundOperator, bpy.types.Operator):
    """Count the vertices where the lattice folds space: turned inside out against the rest (a mirror alone folds nothing)"""
    bl_idname = "object.vpffd_check_folds"
    bl_label = "Check Folds"
    bl_options = {"REGISTER"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        ob = context.object
        n = check_folds(ob, context.evaluated_depsgraph_get())
        if n is None:
            report(self, "ERROR", f"{status(ob).error}")
            return {"CANCELLED"}
        report(self, "WARNING" if n else "INFO", f"{n:,} inverted vertices")
        return {"FINISHED"}


classes = (OBJECT_OT_vpffd_bind, OBJECT_OT_vpffd_unbind, OBJECT_OT_vpffd_apply,
           OBJECT_OT_vpffd_save_shape_key, OBJECT_OT_vpffd_check_folds)
