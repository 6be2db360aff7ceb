"""The settings of each VP-FFD deformer, saved with the .blend file: `obj.vpffd` for the first,
`obj.vpffd_extra` for every further VP-FFD modifier of the mesh (deformers.py pairs them)."""
import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty,
                       FloatVectorProperty, IntProperty, PointerProperty, StringProperty)

from . import deformers, modifier
from ..vpffd_addon import outside as outside_modes

AXES_ITEMS = [
    ("XYZ", "XYZ", "Correct along all three axes"),
    ("XY", "XY", "Correct along X and Y only (a squash spreads sideways; Z faces stay put)"),
    ("XZ", "XZ", "Correct along X and Z only"),
    ("YZ", "YZ", "Correct along Y and Z only"),
    ("X", "X", "Correct along X only"),
    ("Y", "Y", "Correct along Y only"),
    ("Z", "Z", "Correct along Z only"),
    ("NONE", "None", "No volume correction: exactly Blender's Lattice modifier"),
]


def _poll_lattice(self, obj):
    from .cage import is_cage
    return obj.type == "LATTICE" or (is_cage(obj) and obj is not self.id_data)


def _poll_empty(self, obj):
    return obj.type == "EMPTY"


def _get_enabled(self):
    mod = deformers.modifier_of(self.id_data, self)
    return bool(mod and mod.show_viewport)


def _set_enabled(self, value):
    mod = deformers.modifier_of(self.id_data, self)
    if mod is not None:
        mod.show_viewport = value
        mod.show_render = value


def _redraw(self, context):
    for window in getattr(context.window_manager, "windows", ()):
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


def _settings_changed(self, context):
    from .update import request_update
    modifier.sync_inputs(deformers.modifier_of(self.id_data, self), self)
    request_update(self.id_data)


def _lattice_changed(self, context):
    modifier.set_lattice(deformers.modifier_of(self.id_data, self), self.lattice)
    _settings_changed(self, context)


class VPFFD_Settings(bpy.types.PropertyGroup):
    lattice: PointerProperty(
        name="Lattice", type=bpy.types.Object, poll=_poll_lattice, update=_lattice_changed,
        description="Lattice object that deforms this mesh (as with a Lattice modifier), or a VP-FFD "
                    "cage of any shape (Add > VP-FFD Cage)")
    cage_depth: IntProperty(
        name="Cage Depth", default=3, min=0, max=6, soft_max=4, update=_settings_changed,
        description="Refinement levels of a cage: each halves its cells, so the deformation comes "
                    "closer to the smooth limit; binding time and memory grow about 8x per level")
    cage_outside: EnumProperty(
        name="Outside", default="FOLLOW", update=_settings_changed, items=outside_modes.enum_items("cage"),
        description="What vertices outside a cage's region do")
    outside: EnumProperty(
        name="Outside", default="FOLLOW", update=_settings_changed, items=outside_modes.enum_items("lattice"),
        description="What the lattice does to the vertices outside its box")
    falloff_distance: FloatProperty(
        name="Falloff Distance", default=0.5, min=0.001, soft_max=2.0, update=_settings_changed,
        description="How far outside the lattice the deformation fades to nothing, in lattice sizes "
                    "per side (1: the lattice's own size along each axis)")
    vertex_group: StringProperty(
        name="Vertex Group", update=_settings_changed,
        description="Vertex group that scales the deformation per vertex, as the Lattice modifier's (read live)")
    invert_vertex_group: BoolProperty(
        name="Invert", default=False, update=_settings_changed,
        description="Invert the vertex group's influence")
    strength: FloatProperty(
        name="Strength", default=1.0, soft_min=0.0, soft_max=1.0, update=_settings_changed,
        description="Strength of the deformation, as the Lattice modifier's")
    axes: EnumProperty(
        name="Correction", items=AXES_ITEMS, default="XYZ", update=_settings_changed,
        description="Directions along which the lattice may be corrected to keep the volume")
    space: EnumProperty(
        name="Space", default="LATTICE", update=_settings_changed,
        items=[("LATTICE", "Lattice", "The lattice object's own axes"),
               ("WORLD", "World", "World axes")],
        description="Space of the correction directions")
    volume_scale: FloatProperty(
        name="Volume Scale", default=1.0, min=0.0, soft_min=0.5, soft_max=2.0, update=_settings_changed,
        description="Target volume as a multiple of the rest volume (animate it to breathe or inflate)")
    target: EnumProperty(
        name="Target", default="INPUT", update=_settings_changed,
        items=[("INPUT", "Input", "Keep the volume of what reaches VP-FFD, on every frame"),
               ("BIND", "Bind", "Keep the volume the mesh had at Bind (what reached VP-FFD then): "
                                "restores volume lost before VP-FFD in the stack, e.g. by an "
                                "Armature's bend; Re-bind captures it again")],
        description="Which volume the correction keeps (times Volume Scale)")
    mobility_group: StringProperty(
        name="Mobility Group", update=_settings_changed,
        description="Vertex group of the lattice or cage: how freely each point may move for the correction "
                    "(1 free, 0 fixed; unassigned points stay fixed). Empty: all points free")
    use_islands: BoolProperty(
        name="Per-Island Volume", default=False, update=_settings_changed,
        description="Keep the volume of every separate part of the mesh on its own")
    pin_mode: EnumProperty(
        name="Pins", default="NONE", update=_settings_changed,
        items=[("NONE", "None", "No pinned vertices"),
               ("VERTEX", "Vertex", "Pin one vertex (by index) to the target Empty"),
               ("GROUP", "Vertex Group", "Pin every vertex of a vertex group to the target Empty")],
        description="Vertices held on an Empty while the volume is corrected")
    pin_vertex: IntProperty(
        name="Pin Vertex", default=0, min=0, update=_settings_changed,
        description="Index of the pinned vertex")
    pin_vertex_group: StringProperty(
        name="Pin Group", update=_settings_changed,
        description="Vertex group whose vertices (weight > 0) are pinned")
    pin_target: PointerProperty(
        name="Pin Target", type=bpy.types.Object, poll=_poll_empty, update=_settings_changed,
        description="Empty that carries the pinned vertices: they follow its motion since binding")
    pin_target_rest: FloatVectorProperty(
        name="Pin Target at Bind", size=16, default=(1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1),
        options={"HIDDEN"}, description="World matrix of the pin target when the mesh was bound")
    pin_mesh_rest: FloatVectorProperty(
        name="Mesh at Bind", size=16, default=(1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1),
        options={"HIDDEN"}, description="World matrix of the mesh when it was bound")
    lattice_rest_lo: FloatVectorProperty(
        name="Lattice Rest Min", size=3, options={"HIDDEN"},
        description="Lower corner of the lattice's rest grid at Bind (used while the lattice is in Edit Mode)")
    lattice_rest_hi: FloatVectorProperty(
        name="Lattice Rest Max", size=3, options={"HIDDEN"},
        description="Upper corner of the lattice's rest grid at Bind (used while the lattice is in Edit Mode)")
    enabled: BoolProperty(
        name="Enabled", get=_get_enabled, set=_set_enabled,
        description="Show the VP-FFD modifier in viewport and render")
    is_bound: BoolProperty(name="Bound", default=False, options={"HIDDEN"},
                           description="Whether the mesh is bound to its lattice")
    modifier_uid: IntProperty(
        name="Modifier", default=0, options={"HIDDEN"},
        description="The persistent_uid of the VP-FFD modifier these settings belong to (0: the "
                    "first VP-FFD modifier that no other settings name)")
    applied_lattice: StringProperty(
        name="Applied Lattice", options={"HIDDEN"},
        description="The lattice whose deformation Apply made the mesh's own shape: Bind would "
                    "deform the mesh by it again (the panel says so)")
    backend: EnumProperty(
        name="Backend", default="AUTO", update=_settings_changed,
        # Numbered: files saved before CPU (NumPy) existed keep their choice.
        items=[("AUTO", "Auto", "The GPU where it solves this mesh faster (large meshes, a hardware "
                                "GPU); otherwise the CPU. Status says which, and why", 0),
               ("CPU", "CPU", "Always solve on the CPU, with the compiled kernels once they are "
                              "ready (NumPy while they compile, or where numba is missing, saying "
                              "why)", 1),
               ("NUMPY", "CPU (NumPy)", "Always solve on the CPU with NumPy only: the reference "
                                        "path, no compiled kernels", 3),
               ("GPU", "GPU", "Solve with compute shaders whenever possible (falls back to the CPU, "
                              "saying why, when it cannot)", 2)],
        description="Where the per-frame solve runs")
    use_fold_attribute: BoolProperty(
        name="Fold Attribute", default=False, update=_settings_changed,
        description="Write each vertex's Jacobian determinant to the attribute 'vpffd_jacobian', to "
                    "colour the mesh by it: negative where the lattice turns space over (at folds, or "
                    "everywhere under a mirror); costs about one more solve")
    show_overlay: BoolProperty(
        name="Show Corrected Lattice", default=False, update=_redraw,
        description="Draw the corrected lattice the solver used, and the volume percentage, "
                    "in the 3D viewport")


# Every setting can be changed on a library override of a linked character (and is saved with the
# override), as a Lattice modifier's settings can.
for _prop in VPFFD_Settings.__annotations__.values():
    _prop.keywords.setdefault("override", {"LIBRARY_OVERRIDABLE"})

classes = (VPFFD_Settings,)


def register():
    bpy.types.Object.vpffd = PointerProperty(type=VPFFD_Settings, override={"LIBRARY_OVERRIDABLE"})
    bpy.types.Object.vpffd_extra = CollectionProperty(
        type=VPFFD_Settings, override={"LIBRARY_OVERRIDABLE", "USE_INSERTION"},
        description="Settings of the mesh's further VP-FFD modifiers (the first one's: vpffd)")


def unregister():
    del bpy.types.Object.vpffd_extra
    del bpy.types.Object.vpffd
