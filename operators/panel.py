"""The VP-FFD panel, in the Modifier properties next to the modifier stack."""
import bpy

from . import bake, cage, engine, modifier


class OBJECT_PT_vpffd(bpy.types.Panel):
    bl_label = "Volume-Preserving Lattice (VP-FFD)"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "modifier"

    @classmethod
    def poll(cls, context):
        return context.object is not None and context.object.type == "MESH"

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        ob = context.object
        if cage.is_cage(ob):
            self.draw_cage(layout, ob)
            return
        s = ob.vpffd
        bound = s.is_bound

        col = layout.column()
        col.prop(s, "lattice")
        if cage.is_cage(s.lattice):
            col.prop(s, "cage_depth")
            col.prop(s, "cage_outside")
        row = col.row(align=True)
        row.prop_search(s, "vertex_group", ob, "vertex_groups", text="Vertex Group")
        row.prop(s, "invert_vertex_group", text="", icon="ARROW_LEFTRIGHT")
        col.prop(s, "strength", slider=True)

        col = layout.column()
        col.prop(s, "axes")
        col.prop(s, "space")
        col.prop(s, "volume_scale")
        if s.lattice is not None:
            col.prop_search(s, "mobility_group", s.lattice, "vertex_groups", text="Mobility Group")
        else:
            col.prop(s, "mobility_group")
        col.prop(s, "use_islands")
        col.prop(s, "backend")

        col = layout.column()
        col.prop(s, "pin_mode")
        if s.pin_mode == "VERTEX":
            col.prop(s, "pin_vertex")
        elif s.pin_mode == "GROUP":
            col.prop_search(s, "pin_vertex_group", ob, "vertex_groups", text="Pin Group")
        if s.pin_mode != "NONE":
            col.prop(s, "pin_target")

        row = layout.row(align=True)
        if bound:
            row.operator("object.vpffd_bind", text="Re-bind", icon="FILE_REFRESH")
            row.operator("object.vpffd_apply", icon="CHECKMARK")
            row.operator("object.vpffd_unbind", icon="X")
            layout.operator("object.vpffd_save_shape_key", icon="SHAPEKEY_DATA")
            if modifier.find(ob) is not None and not bake.using_cache(ob):
                layout.prop(s, "enabled")     # on the cache, "Use Live" switches back instead
            layout.prop(s, "show_overlay")
            layout.prop(s, "use_fold_attribute")
        else:
            row.operator("object.vpffd_bind", icon="MOD_LATTICE")
        if bound:
            self.draw_status(layout, ob)
            bake.draw_bake(layout, ob)

    @staticmethod
    def draw_cage(layout, ob):
        box = layout.box()
        try:
            cells = cage.cage_cells(ob)
            box.label(text=f"VP-FFD cage: {len(cells)} cells, {len(ob.data.vertices)} points", icon="MESH_ICOSPHERE")
        except ValueError as exc:
            box.label(text=str(exc), icon="ERROR")
        box.label(text="Bind meshes to it from their own VP-FFD panel")
        box.operator("object.vpffd_cage_fit", icon="FULLSCREEN_ENTER")

    @staticmethod
    def draw_status(layout, ob):
        info = engine.status(ob)
        box = layout.box()
        if info.error:
            box.label(text=info.error, icon="ERROR")
        if info.switched_off:
            box.label(text="The VP-FFD modifier is switched off in the viewport", icon="HIDE_ON")
        if info.volume_percent is not None:
            box.label(text=f"Volume {info.volume_percent:.4f}% of its input "
                           f"(plain lattice: {info.plain_percent:.2f}%)")
        if info.seconds is not None:
            box.label(text=f"Solve {1e3 * info.seconds:.1f} ms on the {info.backend}, "
                           f"{info.n_verts:,} vertices")
        if info.backend_reason and ob.vpffd.backend != "CPU":
            box.label(text=info.backend_reason, icon="INFO")
        if info.closed is False:
            box.label(text="Open mesh: volume measured about the lattice centre", icon="INFO")
        if info.folds:
            box.label(text=f"Lattice folds space: {info.folds} inverted vertices", icon="ERROR")
        for text in info.warnings:
            box.label(text=text, icon="ERROR")
        box.operator("object.vpffd_check_folds", icon="VIEWZOOM")


classes = (OBJECT_PT_vpffd,)
