"""Operators: add a VP-FFD modifier, bind, unbind, apply, save as shape key, check folds. Thin
wrappers over `lifecycle`, `release` and `update`. Each acts on one deformer of the active mesh:
the VP-FFD modifier named by its `modifier` property (the panel names the one it shows), or,
from a script that names none, the first (whose settings are `obj.vpffd`)."""
import bpy
from bpy.props import StringProperty

from . import deformers
from .text import report
from .lifecycle import BindError, add_deformer, apply, bind, save_shape_key
from .release import unbind
from .status import status
from .update import check_folds


class _ObjectOperator:
    bl_options = {"REGISTER", "UNDO"}

    modifier: StringProperty(
        name="Modifier", options={"SKIP_SAVE"},
        description="The VP-FFD modifier to act on (empty: the first, whose settings are obj.vpffd)")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        ob = context.object
        return ob is not None and ob.type == "MESH"

    def deformer(self, context):
        """The deformer this operator acts on (KeyError when its modifier is not a VP-FFD one)."""
        return deformers.named(context.object, self.modifier)


class _BoundOperator(_ObjectOperator):
    """An operator on a deformer that is bound already."""

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return super().poll(context) and deformers.is_bound(context.object)

    def bound_deformer(self, context):
        """The deformer to act on, or None after reporting why it cannot be acted on."""
        try:
            d = self.deformer(context)
        except KeyError as exc:
            report(self, "ERROR", str(exc.args[0]))
            return None
        if not d.settings.is_bound:
            report(self, "ERROR", f"{deformers.label(d) or 'VP-FFD'} is not bound: Bind it first")
            return None
        return d


class OBJECT_OT_vpffd_modifier_add(_ObjectOperator, bpy.types.Operator):
    """Add a VP-FFD modifier at the end of the stack: a lattice deformation that keeps the volume
    (pick its lattice and Bind in its panel); a mesh may have any number"""
    bl_idname = "object.vpffd_modifier_add"
    bl_label = "VP-FFD Lattice"

    def execute(self, context: bpy.types.Context) -> set[str]:
        ob = context.object
        lattice = next((o for o in context.selected_objects if o.type == "LATTICE"), None)
        d = add_deformer(ob, {"lattice": lattice} if lattice is not None else None)
        ob.modifiers.active = d.mod         # the panel shows the new one, as Blender's Add Modifier
        report(self, "INFO", f"added '{d.mod.name}': pick its lattice and Bind" if lattice is None
               else f"added '{d.mod.name}' with lattice '{lattice.name}': Bind to deform")
        return {"FINISHED"}


class OBJECT_OT_vpffd_bind(_ObjectOperator, bpy.types.Operator):
    """Bind the mesh to its lattice with exact volume preservation (adds the VP-FFD modifier at the end of the stack)"""
    bl_idname = "object.vpffd_bind"
    bl_label = "Bind"

    @classmethod
    def description(cls, context: bpy.types.Context, properties) -> str:
        ob = context.object
        if ob is not None and ob.type == "MESH" and deformers.is_bound(ob):
            return ("Bind the mesh again with the current settings (pins, a cage's rest shape); "
                    "the VP-FFD modifier stays where it is in the stack")
        return cls.__doc__

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            warnings = bind(self.deformer(context), context.evaluated_depsgraph_get())
        except KeyError as exc:
            report(self, "ERROR", str(exc.args[0]))
            return {"CANCELLED"}
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
        d = self.bound_deformer(context)
        if d is None:
            return {"CANCELLED"}
        unbind(d)
        return {"FINISHED"}


class OBJECT_OT_vpffd_apply(_BoundOperator, bpy.types.Operator):
    """Make the current volume-preserved shape the mesh's own, and unbind"""
    bl_idname = "object.vpffd_apply"
    bl_label = "Apply"

    def execute(self, context: bpy.types.Context) -> set[str]:
        d = self.bound_deformer(context)
        if d is None:
            return {"CANCELLED"}
        try:
            apply(d, context.evaluated_depsgraph_get())
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
        d = self.bound_deformer(context)
        if d is None:
            return {"CANCELLED"}
        try:
            name, before = save_shape_key(d, context.evaluated_depsgraph_get())
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
        d = self.bound_deformer(context)
        if d is None:
            return {"CANCELLED"}
        n = check_folds(d, context.evaluated_depsgraph_get())
        if n is None:
            report(self, "ERROR", f"{status(d).error}")
            return {"CANCELLED"}
        report(self, "WARNING" if n else "INFO", f"{n:,} inverted vertices")
        return {"FINISHED"}


def _modifier_menu(self, context):
    if context.object is not None and context.object.type == "MESH":
        self.layout.operator(OBJECT_OT_vpffd_modifier_add.bl_idname, icon="MOD_LATTICE")


classes = (OBJECT_OT_vpffd_modifier_add, OBJECT_OT_vpffd_bind, OBJECT_OT_vpffd_unbind,
           OBJECT_OT_vpffd_apply, OBJECT_OT_vpffd_save_shape_key, OBJECT_OT_vpffd_check_folds)


def register():
    """Add Modifier > Deform offers VP-FFD Lattice beside Blender's Lattice."""
    bpy.types.OBJECT_MT_modifier_add_deform.append(_modifier_menu)


def unregister():
    bpy.types.OBJECT_MT_modifier_add_deform.remove(_modifier_menu)
