"""The Add > VP-FFD Demos menu and its operators: each builds its demo scene (demo_scenes.py), in a
new scene or the current one, then leaves a corrected object selected and the viewports looking
through the demo's camera (demo_views.py)."""
import bpy

from .demo_scenes import build_bent_arm, build_bouncing_ball, build_squeezed_tube, build_twisting_cube
from .demo_views import forget_views, frame_views
from .lifecycle import BindError
from .text import report


def _select_first_corrected(scene):
    """Leave the first VP-FFD object that corrects the volume active and alone selected, so that
    the Properties editor shows its panel right away."""
    bound = sorted((ob for ob in scene.objects if ob.type == "MESH" and ob.vpffd.is_bound
                    and ob.vpffd.axes != "NONE"), key=lambda ob: ob.name)
    if not bound:
        return
    for layer in scene.view_layers:
        for ob in layer.objects:
            ob.select_set(ob == bound[0], view_layer=layer)
        layer.objects.active = bound[0]


class _DemoOperator:
    bl_options = {"REGISTER", "UNDO"}
    new_scene: bpy.props.BoolProperty(
        name="New Scene", default=True,
        description="Build the demo in a new scene (otherwise in the current one)")

    def execute(self, context: bpy.types.Context) -> set[str]:
        scene = user_scene = context.scene
        if self.new_scene:
            scene = bpy.data.scenes.new(self.scene_name)
            if context.window is not None:
                context.window.scene = scene
        # Binding is most of the build (seconds for the cage demo): the mouse cursor counts the
        # bound objects, and the status bar says what is going on.
        wm = context.window_manager
        done = [0]

        def progress():
            done[0] += 1
            wm.progress_update(done[0])
        workspace = getattr(context, "workspace", None)
        if workspace is not None:
            workspace.status_text_set(f"VP-FFD: building the {self.scene_name[7:].lower()} demo ...")
        wm.progress_begin(0, self.binds)
        try:
            self.build(scene, scene.view_layers[0].depsgraph, progress=progress)
        except (BindError, ValueError) as exc:
            report(self, "ERROR", str(exc))
            return {"CANCELLED"}
        finally:
            wm.progress_end()
            if workspace is not None:
                workspace.status_text_set(None)
        _select_first_corrected(scene)
        frame_views(context, user_scene if scene != user_scene else None)
        return {"FINISHED"}


class OBJECT_OT_vpffd_demo_bouncing_ball(_DemoOperator, bpy.types.Operator):
    """Add the bouncing-ball demo: plain Lattice modifier beside VP-FFD (XY correction)"""
    bl_idname = "object.vpffd_demo_bouncing_ball"
    bl_label = "Bouncing Ball (VP-FFD Demo)"
    scene_name = "VP-FFD Bouncing Ball"
    binds = 1
    build = staticmethod(build_bouncing_ball)


class OBJECT_OT_vpffd_demo_twisting_cube(_DemoOperator, bpy.types.Operator):
    """Add the twisting-cube demo: plain Lattice modifier, VP-FFD XY and VP-FFD Z side by side"""
    bl_idname = "object.vpffd_demo_twisting_cube"
    bl_label = "Twisting Cube (VP-FFD Demo)"
    scene_name = "VP-FFD Twisting Cube"
    binds = 2
    build = staticmethod(build_twisting_cube)


class OBJECT_OT_vpffd_demo_squeezed_tube(_DemoOperator, bpy.types.Operator):
    """Add the squeezed-tube demo: a tube in a cylindrical VP-FFD cage, without and with correction"""
    bl_idname = "object.vpffd_demo_squeezed_tube"
    bl_label = "Squeezed Tube (VP-FFD Cage Demo)"
    scene_name = "VP-FFD Squeezed Tube"
    binds = 3
    build = staticmethod(build_squeezed_tube)


class OBJECT_OT_vpffd_demo_bent_arm(_DemoOperator, bpy.types.Operator):
    """Add the bent-arm demo: an arm bent by an Armature, alone and with VP-FFD keeping its volume at Bind"""
    bl_idname = "object.vpffd_demo_bent_arm"
    bl_label = "Bent Arm (VP-FFD Demo)"
    scene_name = "VP-FFD Bent Arm"
    binds = 1
    build = staticmethod(build_bent_arm)


class VIEW3D_MT_vpffd_demos(bpy.types.Menu):
    bl_label = "VP-FFD Demos"
    bl_idname = "VIEW3D_MT_vpffd_demos"

    def draw(self, context: bpy.types.Context) -> None:
        self.layout.operator(OBJECT_OT_vpffd_demo_bouncing_ball.bl_idname, icon="MESH_UVSPHERE")
        self.layout.operator(OBJECT_OT_vpffd_demo_twisting_cube.bl_idname, icon="MESH_CUBE")
        self.layout.operator(OBJECT_OT_vpffd_demo_squeezed_tube.bl_idname, icon="MESH_CYLINDER")
        self.layout.operator(OBJECT_OT_vpffd_demo_bent_arm.bl_idname, icon="BONE_DATA")


def _add_menu(self, context):
    self.layout.menu(VIEW3D_MT_vpffd_demos.bl_idname, icon="MOD_LATTICE")


classes = (OBJECT_OT_vpffd_demo_bouncing_ball, OBJECT_OT_vpffd_demo_twisting_cube,
           OBJECT_OT_vpffd_demo_squeezed_tube, OBJECT_OT_vpffd_demo_bent_arm, VIEW3D_MT_vpffd_demos)


def register():
    bpy.types.VIEW3D_MT_add.append(_add_menu)


def unregister():
    bpy.types.VIEW3D_MT_add.remove(_add_menu)
    forget_views()
