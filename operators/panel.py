"""The VP-FFD panel in the Modifier properties, built as Blender's own panels are: a main panel
(lattice, weights, bind) and sub-panels for Cage, Correction, Pins, Folds, Corrected Lattice,
Bake and Status, with split properties and no animation decorators."""
import bpy

from . import bake_ops, cage, compiled_backend, deformers
from .cache_modifier import using_cache
from ..vpffd_addon import outside as outside_modes
from .status_line import applied_lattice, headline, status_lines
from .text import count, lines, percent, sentence
from .saved_data import JACOBIAN_ATTRIBUTE
from .status import outside_message, status


def _deformer(context):
    """The deformer the panel shows (`deformers.shown`: the active VP-FFD modifier, else the
    first), or None for what is not a mesh to deform."""
    ob = context.object
    return None if ob is None or ob.type != "MESH" or cage.is_cage(ob) else deformers.shown(ob)


def _settings(context):
    d = _deformer(context)
    return None if d is None else d.settings


def button(layout, d, idname, **kwargs):
    """An operator button acting on deformer `d` (its modifier named, when it has one)."""
    props = layout.operator(idname, **kwargs)
    if d.mod is not None:
        props.modifier = d.mod.name
    return props


def message(layout, context, text, icon="NONE"):
    """`text` as a sentence, wrapped to the panel's width (labels never wrap on their own)."""
    width = (context.region.width if context.region else 300) / (7.0 * context.preferences.view.ui_scale)
    col = layout.column(align=True)
    for k, line in enumerate(lines(sentence(text), width - 4)):
        col.label(text=line, icon=icon if k == 0 else "BLANK1")


def outside_row(layout, s, prop, kind):
    """The Outside setting `prop` as one button per mode of the table (`vpffd_addon.outside`):
    the earlier names the setting still accepts are not offered."""
    split = layout.split(factor=0.4, align=True)
    split.alignment = "RIGHT"
    split.label(text="Outside")
    row = split.row(align=True)
    for m in outside_modes.modes(kind):
        row.prop_enum(s, prop, m.name)


class _Panel:
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "modifier"

    def draw_split(self):
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        return layout


class _SubPanel(_Panel):
    bl_parent_id = "OBJECT_PT_vpffd"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return _settings(context) is not None


class _BoundSubPanel(_SubPanel):
    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        s = _settings(context)
        return s is not None and s.is_bound


class OBJECT_PT_vpffd(_Panel, bpy.types.Panel):
    bl_label = "Volume-Preserving Lattice (VP-FFD)"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return context.object is not None and context.object.type == "MESH"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.draw_split()
        ob = context.object
        if cage.is_cage(ob):
            self.draw_cage(layout, context, ob)
            return
        d = deformers.shown(ob)
        s = d.settings
        which = deformers.label(d)
        if which:
            # Several VP-FFD modifiers: say whose settings these are, as the Geometry Nodes
            # editor follows the active modifier.
            message(layout, context, f"showing VP-FFD modifier {which}: click another one's "
                                     "header to show its settings", icon="MODIFIER")
        # First line: what VP-FFD does to this object now (details in the Status sub-panel).
        text, icon = headline(status(d), s.is_bound, s.is_bound and using_cache(ob),
                              applied_lattice(s), compiled_backend.status()[0])
        message(layout, context, text, icon=icon)
        col = layout.column()
        col.prop(s, "lattice")
        row = col.row(align=True)
        row.prop_search(s, "vertex_group", ob, "vertex_groups", text="Vertex Group")
        row.prop(s, "invert_vertex_group", text="", icon="ARROW_LEFTRIGHT")
        col.prop(s, "strength", slider=True)
        if s.is_bound and d.mod is not None and not using_cache(ob):
            col.prop(s, "enabled")     # on the cache, "Use Live Solve" switches back instead

        row = layout.row(align=True)
        if s.is_bound:
            button(row, d, "object.vpffd_bind", text="Re-bind", icon="FILE_REFRESH")
            button(row, d, "object.vpffd_apply", icon="CHECKMARK")
            button(row, d, "object.vpffd_unbind", icon="X")
            button(layout, d, "object.vpffd_save_shape_key", icon="SHAPEKEY_DATA")
        else:
            button(row, d, "object.vpffd_bind", icon="MOD_LATTICE")
        if s.is_bound:
            layout.operator("object.vpffd_modifier_add", text="Add Another VP-FFD Lattice", icon="ADD")

    @staticmethod
    def draw_cage(layout, context, ob):
        try:
            cells = cage.cage_cells(ob)
            message(layout, context, f"VP-FFD cage: {count(len(cells))} cells, "
                                     f"{count(len(ob.data.vertices))} points", icon="MESH_ICOSPHERE")
        except ValueError as exc:
            message(layout, context, str(exc), icon="ERROR")
        message(layout, context, "bind meshes to it from their own VP-FFD panel")
        layout.operator("object.vpffd_cage_fit", icon="FULLSCREEN_ENTER")


class OBJECT_PT_vpffd_cage(_SubPanel, bpy.types.Panel):
    bl_label = "Cage"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        s = _settings(context)
        return s is not None and cage.is_cage(s.lattice)

    def draw(self, context: bpy.types.Context) -> None:
        d = _deformer(context)
        s = d.settings
        col = self.draw_split().column()
        col.prop(s, "cage_depth")
        outside_row(col, s, "cage_outside", "cage")
        if "cage" not in outside_modes.mode(s.outside).kinds:
            message(col, context, "Outside: Falloff is for lattices (a cage's region is not a box): "
                                  "this cage's own Outside applies", icon="INFO")
        info = status(d)
        if s.is_bound and info.outside:
            message(col, context, outside_message(info, True), icon="INFO")


class OBJECT_PT_vpffd_outside(_SubPanel, bpy.types.Panel):
    bl_label = "Outside"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        s = _settings(context)
        return s is not None and not cage.is_cage(s.lattice)

    def draw(self, context: bpy.types.Context) -> None:
        d = _deformer(context)
        s = d.settings
        col = self.draw_split().column()
        outside_row(col, s, "outside", "lattice")
        sub = col.column()
        sub.active = outside_modes.mode(s.outside).has_distance
        sub.prop(s, "falloff_distance")
        info = status(d)
        if s.is_bound and info.outside:
            message(col, context, outside_message(info, False), icon="INFO")


class OBJECT_PT_vpffd_correction(_SubPanel, bpy.types.Panel):
    bl_label = "Correction"

    def draw(self, context: bpy.types.Context) -> None:
        d = _deformer(context)
        s = d.settings
        col = self.draw_split().column()
        col.prop(s, "axes")
        sub = col.column()
        sub.active = s.axes != "NONE"
        sub.prop(s, "space")
        sub.prop(s, "volume_scale")
        sub.prop(s, "target")
        if s.target == "BIND" and s.is_bound:
            info = status(d)
            if info.input_percent is not None:
                message(sub, context, f"what reaches VP-FFD has {percent(info.input_percent)} of "
                                      "the volume at Bind", icon="INFO")
        if s.lattice is not None:
            sub.prop_search(s, "mobility_group", s.lattice, "vertex_groups", text="Mobility Group")
        else:
            sub.prop(s, "mobility_group")
        sub.prop(s, "use_islands")
        col.prop(s, "backend")


class OBJECT_PT_vpffd_pins(_SubPanel, bpy.types.Panel):
    bl_label = "Pins"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context: bpy.types.Context) -> None:
        ob = context.object
        s = _settings(context)
        col = self.draw_split().column()
        col.prop(s, "pin_mode")
        if s.pin_mode == "VERTEX":
            col.prop(s, "pin_vertex")
        elif s.pin_mode == "GROUP":
            col.prop_search(s, "pin_vertex_group", ob, "vertex_groups", text="Pin Group")
        if s.pin_mode != "NONE":
            col.prop(s, "pin_target")
            if s.is_bound:
                message(col, context, "pins are saved at Bind: Re-bind after changing them", icon="INFO")


class OBJECT_PT_vpffd_folds(_BoundSubPanel, bpy.types.Panel):
    bl_label = "Folds"
    bl_options = {"DEFAULT_CLOSED"}

    def draw_header(self, context: bpy.types.Context) -> None:
        self.layout.prop(_settings(context), "use_fold_attribute", text="")

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.draw_split()
        d = _deformer(context)
        info = status(d)
        if d.settings.use_fold_attribute:
            message(layout, context, f"the attribute '{JACOBIAN_ATTRIBUTE}' holds the "
                                     "Jacobian determinant of every vertex")
        if info.folds is not None and not (info.error or info.paused or info.switched_off):
            message(layout, context, f"{count(info.folds)} inverted vertices" if info.folds
                    else "the lattice does not fold space here",
                    icon="ERROR" if info.folds else "CHECKMARK")
        button(layout, d, "object.vpffd_check_folds", icon="VIEWZOOM")


class OBJECT_PT_vpffd_overlay(_BoundSubPanel, bpy.types.Panel):
    bl_label = "Corrected Lattice"
    bl_options = {"DEFAULT_CLOSED"}

    def draw_header(self, context: bpy.types.Context) -> None:
        self.layout.prop(_settings(context), "show_overlay", text="")

    def draw(self, context: bpy.types.Context) -> None:
        message(self.layout, context, "draws the control points the solver used and the volume "
                                      "in the 3D viewport, while VP-FFD is solving")


class OBJECT_PT_vpffd_bake(_BoundSubPanel, bpy.types.Panel):
    bl_label = "Bake"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context: bpy.types.Context) -> None:
        bake_ops.draw_bake(self.draw_split(), context.object)


class OBJECT_PT_vpffd_status(_BoundSubPanel, bpy.types.Panel):
    bl_label = "Status"

    def draw(self, context: bpy.types.Context) -> None:
        ob = context.object
        d = _deformer(context)
        for text, icon in status_lines(status(d), using_cache(ob), d.settings.backend):
            message(self.layout, context, text, icon=icon)

classes = (OBJECT_PT_vpffd, OBJECT_PT_vpffd_cage, OBJECT_PT_vpffd_outside, OBJECT_PT_vpffd_correction,
           OBJECT_PT_vpffd_pins, OBJECT_PT_vpffd_folds, OBJECT_PT_vpffd_overlay, OBJECT_PT_vpffd_bake,
           OBJECT_PT_vpffd_status)
