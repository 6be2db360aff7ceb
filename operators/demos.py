"""Demo scenes in the Add menu: the paper's bouncing ball and twisting cube (Hahmann et al.
2011, Figures 1 and 6), each next to a plain Lattice modifier copy so the difference shows in one frame, a tube
in a cylindrical cage (MacCracken & Joy), next to the same cage without correction, and an arm bent
by an Armature, alone and with VP-FFD keeping the volume it had at Bind."""
import math

import bpy
import numpy as np

from .. import vpffd_addon as vp
from . import cage
from .text import report
from .lifecycle import BindError, bind

BALL_FRAMES = (1, 60)
CUBE_FRAMES = (1, 60)
TUBE_FRAMES = (1, 60)
ARM_FRAMES = (1, 60)

PLAIN_COLOUR = (0.85, 0.30, 0.25, 1.0)
VPFFD_COLOUR = (0.20, 0.55, 0.90, 1.0)
VPFFD_COLOUR_2 = (0.25, 0.75, 0.45, 1.0)


# ------------------------------------------------------------------------------------ building

def _material(name, rgba):
    mat = bpy.data.materials.get(name) or bpy.data.materials.new(name)
    mat.diffuse_color = rgba                 # Workbench and the viewport
    if getattr(mat, "node_tree", None) is None and hasattr(mat, "use_nodes"):
        mat.use_nodes = True
    bsdf = mat.node_tree.nodes.get("Principled BSDF") if mat.node_tree else None
    if bsdf is not None:
        bsdf.inputs["Base Color"].default_value = rgba
        bsdf.inputs["Roughness"].default_value = 0.45
    return mat


def _mesh_object(scene, name, verts, tris, material=None, smooth=False):
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(verts))
    me.vertices.foreach_set("co", np.asarray(verts, np.float32).ravel())
    me.loops.add(tris.size)
    me.loops.foreach_set("vertex_index", tris.astype(np.int32).ravel())
    me.polygons.add(len(tris))
    me.polygons.foreach_set("loop_start", np.arange(0, tris.size, 3, dtype=np.int32))
    me.update(calc_edges=True)
    if smooth:
        me.shade_smooth()
    if material is not None:
        me.materials.append(material)
    ob = bpy.data.objects.new(name, me)
    scene.collection.objects.link(ob)
    return ob


def _lattice_object(scene, name, shape, half_extent, location):
    """Lattice whose rest grid spans +-half_extent (3,) around `location`, B-spline on all axes."""
    lt = bpy.data.lattices.new(name)
    lt.points_u, lt.points_v, lt.points_w = shape
    for a in "uvw":
        setattr(lt, f"interpolation_type_{a}", "KEY_BSPLINE")
    ob = bpy.data.objects.new(name, lt)
    grid_half = 0.5 * (np.array(shape, float) - 1.0)          # RNA-resized grids have unit spacing
    ob.scale = [h / g if g else 1.0 for h, g in zip(half_extent, grid_half)]
    ob.location = location
    scene.collection.objects.link(ob)
    return ob


def _label(scene, text, location, size=0.3):
    """Dark text on a light plate just behind it: readable on the dark background of the Solid
    viewport and on the light world of the renders alike."""
    curve = bpy.data.curves.new(f"Label {text}", "FONT")
    curve.body = text
    curve.align_x = "CENTER"
    curve.size = size
    ob = bpy.data.objects.new(f"Label {text}", curve)
    ob.location = location
    ob.rotation_euler = (math.radians(90), 0, 0)
    ob.data.materials.append(_material("VP-FFD Demo Label", (0.04, 0.04, 0.04, 1.0)))
    scene.collection.objects.link(ob)
    # The plate, in the text's own plane (text from about -0.25 to 0.8 of its size about the
    # baseline; a character about 0.55 of its size wide), a little behind it.
    half_w = 0.27 * size * len(text) + 0.1 * size
    lo, hi = -0.45 * size, 1.0 * size
    plate_v = np.array([[-half_w, lo, -0.01], [half_w, lo, -0.01], [half_w, hi, -0.01], [-half_w, hi, -0.01]])
    plate = _mesh_object(scene, f"Label Plate {text}", plate_v, np.array([[0, 1, 2], [0, 2, 3]]),
                         _material("VP-FFD Demo Label Plate", (0.95, 0.95, 0.93, 1.0)))
    plate.parent = ob
    return ob


def _stage(scene, camera_location, camera_target, frames, ground_size):
    """Ground, sun, camera and render settings shared by the demos."""
    ground_v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float) * [ground_size, ground_size, 0]
    _mesh_object(scene, "Ground", ground_v, np.array([[0, 1, 2], [0, 2, 3]]),
                 _material("VP-FFD Demo Ground", (0.8, 0.8, 0.78, 1.0)))
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(40), math.radians(15), math.radians(30))
    scene.collection.objects.link(sun)
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    cam.location = camera_location
    direction = np.subtract(camera_target, camera_location)
    cam.rotation_euler = _look_rotation(direction)
    cam.data.lens = 40
    scene.collection.objects.link(cam)
    scene.camera = cam
    scene.frame_start, scene.frame_end = frames
    scene.render.fps = 24
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "STUDIO"
    scene.display.shading.color_type = "MATERIAL"
    scene.display.shading.show_shadows = True
    scene.render.resolution_x, scene.render.resolution_y = 640, 360
    scene.render.film_transparent = False
    world = bpy.data.worlds.get("VP-FFD Demo World") or bpy.data.worlds.new("VP-FFD Demo World")
    world.color = (0.9, 0.9, 0.92)
    scene.world = world
    scene.render.use_lock_interface = True


def _look_rotation(direction):
    """Euler angles that point a camera (looking down its -Z) along `direction`."""
    x, y, z = direction
    pitch = math.atan2(math.hypot(x, y), -z)
    yaw = math.atan2(y, x) - math.pi / 2
    return (pitch, 0.0, yaw)


def _key(data, path, frame, value, interpolation=None):
    setattr(data, path, value)
    data.keyframe_insert(path, frame=frame)
    if interpolation:
        anim = data.id_data.animation_data if hasattr(data, "id_data") else None
        for fc in _fcurves(anim):
            for kp in fc.keyframe_points:
                if kp.co[0] == frame:
                    kp.interpolation = interpolation


def _fcurves(anim):
    """F-curves of an AnimData, in Blender 4.x (action.fcurves) and 5.x (layered actions)."""
    if anim is None or anim.action is None:
        return []
    action = anim.action
    if hasattr(action, "fcurves"):
        return list(action.fcurves)
    curves = []
    for layer in getattr(action, "layers", ()):
        for strip in layer.strips:
            for bag in strip.channelbags:
                curves.extend(bag.fcurves)
    return curves


def _bind(ob, depsgraph, progress=None, **settings):
    """Bind `ob` with `settings`; `progress()` is called once it is bound (the window's progress
    indicator: binding is most of a demo's build time)."""
    for k, v in settings.items():
        setattr(ob.vpffd, k, v)
    bind(ob, depsgraph)
    if progress is not None:
        progress()


def _plain(ob, lattice):
    mod = ob.modifiers.new("Lattice", "LATTICE")
    mod.object = lattice
    return mod


# -------------------------------------------------------------------------------- bouncing ball

def _ball_rig(scene, name, x, colour):
    """A ball parented to its own 4x4x4 lattice; the lattice falls, squashes on the ground
    (shape key "Squash": flattened towards its floor) and stretches in flight ("Stretch")."""
    radius, half = 0.5, 0.55
    lat = _lattice_object(scene, f"{name} Lattice", (4, 4, 4), (half,) * 3, (x, 0.0, 2.5))
    verts, tris = vp.icosphere(4, radius)
    ball = _mesh_object(scene, name, verts, tris, _material(f"VP-FFD Demo {name}", colour), smooth=True)
    ball.parent = lat
    ball.scale = [1.0 / s for s in lat.scale]                 # undo the lattice's grid scaling
    lat.shape_key_add(name="Basis")
    co = np.empty(len(lat.data.points) * 3, np.float32)
    lat.data.points.foreach_get("co", co)
    co = co.reshape(-1, 3).astype(np.float64)
    floor = co[:, 2].min()
    squash = co.copy()
    squash[:, 2] = floor + (co[:, 2] - floor) * 0.45
    stretch = co * [0.9, 0.9, 1.25]
    for key_name, target in (("Squash", squash), ("Stretch", stretch)):
        key = lat.shape_key_add(name=key_name)
        key.data.foreach_set("co", target.astype(np.float32).ravel())

    # Centre height: 2.5 -> ground contact (centre at `half`) at 15 and 45, apex at 30 and 60.
    ground = half
    for f, z in ((1, 2.5), (15, ground), (21, ground), (33, 1.9), (45, ground), (51, ground), (60, 1.4)):
        _key(lat, "location", f, (x, 0.0, z))
    keys = lat.data.shape_keys.key_blocks
    for f, v in ((1, 0.0), (14, 0.0), (18, 1.0), (21, 0.0), (44, 0.0), (48, 0.9), (51, 0.0), (60, 0.0)):
        _key(keys["Squash"], "value", f, v)
    for f, v in ((1, 0.0), (12, 0.5), (15, 0.0), (21, 0.0), (25, 0.45), (31, 0.0), (42, 0.45), (45, 0.0),
                 (51, 0.0), (55, 0.4), (60, 0.0)):
        _key(keys["Stretch"], "value", f, v)
    return ball, lat


def build_bouncing_ball(scene, depsgraph=None, progress=None):
    """Two balls falling side by side: a plain Lattice modifier (left) and VP-FFD correcting in
    the horizontal directions (right), so the squash spreads sideways (paper section 5.1).
    Returns {'plain': ball, 'vpffd': ball, 'lattices': [...]}."""
    plain, plain_lat = _ball_rig(scene, "Ball Lattice Modifier", -1.2, PLAIN_COLOUR)
    ours, our_lat = _ball_rig(scene, "Ball VP-FFD XY", 1.2, VPFFD_COLOUR)
    _label(scene, "Lattice modifier", (-1.2, 0.0, 3.4), size=0.26)
    _label(scene, "VP-FFD (XY)", (1.2, 0.0, 3.4), size=0.26)
    _stage(scene, camera_location=(0.0, -8.5, 2.2), camera_target=(0.0, 0.0, 1.5), frames=BALL_FRAMES,
           ground_size=5.0)
    _plain(plain, plain_lat)
    scene.frame_set(scene.frame_start)
    dg = depsgraph or scene.view_layers[0].depsgraph
    _bind(ours, dg, progress=progress, lattice=our_lat, axes="XY", space="LATTICE")
    return {"plain": plain, "vpffd": ours, "lattices": [plain_lat, our_lat]}


# ------------------------------------------------------------------------------- twisting cube

def _cube_rig(scene, name, x, colour):
    """A subdivided cube (6,146 vertices, as the paper's) in a 4x4x8 lattice that a Simple Deform
    modifier twists from 0 to 360 degrees about Z."""
    half = 0.55
    lat = _lattice_object(scene, f"{name} Lattice", (4, 4, 8), (half, half, half), (x, 0.0, 0.9))
    verts, tris = vp.box(32, 1.0)
    cube = _mesh_object(scene, name, verts, tris, _material(f"VP-FFD Demo {name}", colour))
    cube.parent = lat
    cube.scale = [1.0 / s for s in lat.scale]
    twist = lat.modifiers.new("Twist", "SIMPLE_DEFORM")
    twist.deform_method = "TWIST"
    twist.deform_axis = "Z"
    _key(twist, "angle", CUBE_FRAMES[0], 0.0, "LINEAR")
    _key(twist, "angle", CUBE_FRAMES[1], 2.0 * math.pi, "LINEAR")
    return cube, lat


def build_twisting_cube(scene, depsgraph=None, progress=None):
    """Three cubes twisted by their lattices (paper Figure 6): a plain Lattice modifier, VP-FFD
    correcting in XY (top and bottom stay flat) and VP-FFD correcting in Z.
    Returns {'plain': cube, 'vpffd_xy': cube, 'vpffd_z': cube, 'lattices': [...]}."""
    plain, plain_lat = _cube_rig(scene, "Cube Lattice Modifier", -2.0, PLAIN_COLOUR)
    xy, xy_lat = _cube_rig(scene, "Cube VP-FFD XY", 0.0, VPFFD_COLOUR)
    z, z_lat = _cube_rig(scene, "Cube VP-FFD Z", 2.0, VPFFD_COLOUR_2)
    for text, x in (("Lattice modifier", -2.0), ("VP-FFD (XY)", 0.0), ("VP-FFD (Z)", 2.0)):
        _label(scene, text, (x, 0.0, 1.85), size=0.22)
    _stage(scene, camera_location=(0.0, -7.5, 3.3), camera_target=(0.0, 0.0, 0.85), frames=CUBE_FRAMES,
           ground_size=6.0)
    _plain(plain, plain_lat)
    scene.frame_set(scene.frame_start)
    dg = depsgraph or scene.view_layers[0].depsgraph
    _bind(xy, dg, progress=progress, lattice=xy_lat, axes="XY", space="LATTICE")
    _bind(z, dg, progress=progress, lattice=z_lat, axes="Z", space="LATTICE")
    return {"plain": plain, "vpffd_xy": xy, "vpffd_z": z, "lattices": [plain_lat, xy_lat, z_lat]}


# ------------------------------------------------------------------------------- squeezed tube

def _capsule(radius, length, rings=48, segments=32, cap_rings=8):
    """A closed capsule along Z (a cylinder of `length` with hemispherical caps): (verts, tris)."""
    zs = [(-length / 2 - radius * math.cos(a), radius * math.sin(a))
          for a in np.linspace(0, math.pi / 2, cap_rings + 1)[1:]]
    zs += [(z, radius) for z in np.linspace(-length / 2, length / 2, rings + 1)[1:-1]]
    zs += [(-z, r) for z, r in reversed(zs[:cap_rings])]
    ang = np.arange(segments) * 2 * math.pi / segments
    ring_verts = [np.stack([r * np.cos(ang), r * np.sin(ang), np.full(segments, z)], 1) for z, r in zs]
    verts = np.concatenate([[[0, 0, -length / 2 - radius]], *ring_verts, [[0, 0, length / 2 + radius]]])
    n, top = len(zs), len(verts) - 1
    tris = []
    for j in range(segments):
        k = (j + 1) % segments
        tris.append((0, 1 + k, 1 + j))
        tris.append((top, 1 + (n - 1) * segments + j, 1 + (n - 1) * segments + k))
        for i in range(n - 1):
            a, b = 1 + i * segments, 1 + (i + 1) * segments
            tris += [(a + j, a + k, b + k), (a + j, b + k, b + j)]
    return verts, np.array(tris, np.int64)


def _tube_rig(scene, name, x, colour):
    """A capsule in a cylindrical cage: an octagon with a ring of quads, extruded into 6 layers.
    A shape key squeezes the cage's middle rings."""
    k, height = 8, 2.0
    ang = np.arange(k) * 2 * np.pi / k + np.pi / k
    disc = np.concatenate([np.stack([r * np.cos(ang), r * np.sin(ang), 0 * ang], 1) for r in (0.27, 0.54)])
    polys = [list(range(k))] + [[i, (i + 1) % k, k + (i + 1) % k, k + i] for i in range(k)]
    points, cells = vp.extrude(disc - [0, 0, height / 2], polys, (0, 0, height), 6)
    cage_ob = cage.cage_object(f"{name} Cage", points, cells)
    cage_ob.location = (x, 0.0, 1.25)
    scene.collection.objects.link(cage_ob)
    verts, tris = _capsule(0.36, 1.15)
    tube = _mesh_object(scene, name, verts, tris, _material(f"VP-FFD Demo {name}", colour), smooth=True)
    tube.location = cage_ob.location
    cage_ob.shape_key_add(name="Basis")
    squeeze = points.copy()
    z = np.abs(points[:, 2])
    squeeze[:, :2] *= np.where(z < 0.1, 0.4, np.where(z < 0.5, 0.75, 1.0))[:, None]
    key = cage_ob.shape_key_add(name="Squeeze")
    key.data.foreach_set("co", squeeze.astype(np.float32).ravel())
    for f, v in ((1, 0.0), (25, 1.0), (40, 1.0), (60, 0.0)):
        _key(key, "value", f, v)
    return tube, cage_ob


def build_squeezed_tube(scene, depsgraph=None, progress=None):
    """Three capsules squeezed in the middle by cylindrical cages: the cage's plain deformation
    (Correction None), VP-FFD along X, Y and Z, and VP-FFD along Z only (the squeezed volume goes
    into the capsule's length). Returns {'plain': tube, 'vpffd_xyz': tube, 'vpffd_z': tube,
    'cages': [...]}."""
    plain, plain_cage = _tube_rig(scene, "Tube Cage Plain", -1.6, PLAIN_COLOUR)
    xyz, xyz_cage = _tube_rig(scene, "Tube VP-FFD XYZ", 0.0, VPFFD_COLOUR)
    z, z_cage = _tube_rig(scene, "Tube VP-FFD Z", 1.6, VPFFD_COLOUR_2)
    for text, x in (("No correction", -1.6), ("VP-FFD (XYZ)", 0.0), ("VP-FFD (Z)", 1.6)):
        _label(scene, text, (x, 0.0, 3.05), size=0.22)
    _stage(scene, camera_location=(0.0, -8.0, 1.9), camera_target=(0.0, 0.0, 1.6), frames=TUBE_FRAMES,
           ground_size=6.0)
    scene.frame_set(scene.frame_start)
    dg = depsgraph or scene.view_layers[0].depsgraph
    _bind(plain, dg, progress=progress, lattice=plain_cage, axes="NONE", cage_depth=3)
    _bind(xyz, dg, progress=progress, lattice=xyz_cage, axes="XYZ", space="LATTICE", cage_depth=3)
    _bind(z, dg, progress=progress, lattice=z_cage, axes="Z", space="LATTICE", cage_depth=3)
    return {"plain": plain, "vpffd_xyz": xyz, "vpffd_z": z, "cages": [plain_cage, xyz_cage, z_cage]}


# ------------------------------------------------------------------------------------ bent arm

def _arm_rig(scene, name, x, colour):
    """An arm (a capsule along Z, its elbow at the origin of the rig) skinned to two bones with
    weights blending over the elbow; the upper bone bends to 110 degrees and back. Returns (arm,
    rig)."""
    half = 0.85
    rig = bpy.data.objects.new(f"{name} Rig", bpy.data.armatures.new(f"{name} Rig"))
    rig.location = (x, 0.0, 1.3)
    scene.collection.objects.link(rig)
    rig.data.display_type = "STICK"
    layer = scene.view_layers[0]
    layer.objects.active = rig      # bones are made in Edit Mode, which needs the rig active
    with bpy.context.temp_override(active_object=rig, object=rig, selected_objects=[rig],
                                   view_layer=layer, scene=scene):
        bpy.ops.object.mode_set(mode="EDIT")
        lower = rig.data.edit_bones.new("Lower")
        lower.head, lower.tail = (0, 0, -half), (0, 0, 0)
        upper = rig.data.edit_bones.new("Upper")
        upper.head, upper.tail = (0, 0, 0), (0, 0, half)
        upper.parent = lower
        bpy.ops.object.mode_set(mode="OBJECT")
    verts, tris = _capsule(0.2, 2 * half - 0.4)
    arm = _mesh_object(scene, name, verts, tris, _material(f"VP-FFD Demo {name}", colour), smooth=True)
    arm.location = rig.location
    # Linear blend weights over the elbow: the skinning that loses volume when the joint bends.
    t = np.clip((verts[:, 2] + 0.25) / 0.5, 0.0, 1.0)
    for group, w in (("Lower", 1.0 - t), ("Upper", t)):
        vg = arm.vertex_groups.new(name=group)
        for value in np.unique(w):
            vg.add(np.flatnonzero(w == value).tolist(), float(value), "REPLACE")
    arm.modifiers.new("Armature", "ARMATURE").object = rig
    pose = rig.pose.bones["Upper"]
    pose.rotation_mode = "XYZ"
    for f, angle in ((1, 0.0), (25, 110.0), (40, 110.0), (60, 0.0)):
        _key(pose, "rotation_euler", f, (0.0, 0.0, math.radians(angle)))   # bone Z: sideways in the camera
    return arm, rig


def build_bent_arm(scene, depsgraph=None, progress=None):
    """Two arms bent by their Armatures: the Armature alone (left), which loses volume at the
    elbow, and VP-FFD after it (right): a lattice around the elbow, its deformation fading out
    beyond it (Outside: Falloff), correcting along X, Y and Z towards the volume the arm had at
    Bind, in the rest pose (Target: Bind). Returns {'plain': arm, 'vpffd': arm, 'lattices': [...]}."""
    plain, _ = _arm_rig(scene, "Arm Armature Alone", -1.1, PLAIN_COLOUR)
    ours, _ = _arm_rig(scene, "Arm VP-FFD Bind", 1.1, VPFFD_COLOUR)
    lat = _lattice_object(scene, "Arm VP-FFD Bind Elbow Lattice", (4, 4, 4), (0.35, 0.35, 0.35),
                          ours.location)
    for text, x in (("Armature alone", -1.1), ("VP-FFD (volume at Bind)", 1.1)):
        _label(scene, text, (x, 0.0, 2.55), size=0.18)
    _stage(scene, camera_location=(0.0, -5.6, 1.5), camera_target=(0.0, 0.0, 1.5), frames=ARM_FRAMES,
           ground_size=6.0)
    scene.frame_set(scene.frame_start)
    dg = depsgraph or scene.view_layers[0].depsgraph
    _bind(ours, dg, progress=progress, lattice=lat, axes="XYZ", space="LATTICE", target="BIND",
          outside="FALLOFF", falloff_distance=0.6)
    return {"plain": plain, "vpffd": ours, "lattices": [lat]}


# ----------------------------------------------------------------------------------- operators

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


#: The views the demos switched to their camera, to give back when the user's scene is shown
#: again: {area pointer: (name of the scene it showed, the view's settings)}. A 3D viewport's view
#: belongs to its area, not to the scene, so Blender alone would keep the camera view there.
_saved_views = {}
_VIEW_SETTINGS = ("view_perspective", "view_location", "view_rotation", "view_distance",
                  "view_camera_offset", "view_camera_zoom")


def _view_settings(rv3d):
    return {name: getattr(rv3d, name).copy() if hasattr(getattr(rv3d, name), "copy")
            else getattr(rv3d, name) for name in _VIEW_SETTINGS}


def _restore_views():
    """Timer: give each saved view back once its area shows the scene it showed before the demo.
    Returns the seconds to the next look, or None when nothing is left to give back."""
    try:
        windows = bpy.context.window_manager.windows
    except AttributeError:
        _saved_views.clear()
        return None
    for window in windows:
        for area in window.screen.areas:
            saved = _saved_views.get(area.as_pointer())
            if saved is None or saved[0] != window.scene.name or area.type != "VIEW_3D":
                continue
            rv3d = area.spaces.active.region_3d
            for name, value in saved[1].items():
                setattr(rv3d, name, value)
            area.tag_redraw()
            del _saved_views[area.as_pointer()]
    scenes = set(bpy.data.scenes.keys())
    for key in [k for k, (scene, _) in _saved_views.items() if scene not in scenes]:
        del _saved_views[key]           # that scene is gone: nothing to give back to
    return 0.5 if _saved_views else None


def _frame_views(context, user_scene=None):
    """Show the demo through its camera in every 3D viewport of the window, the camera's frame
    filling the view (as Numpad 0, then View > Cameras > Frame Camera Bounds). `user_scene`: the
    scene the window showed before the demo's own, whose views come back when it is shown again."""
    window, screen = context.window, getattr(context, "screen", None)
    if window is None or screen is None:
        return                          # no window (background, farm): nothing to frame
    for area in screen.areas:
        region = next((r for r in area.regions if r.type == "WINDOW"), None)
        if area.type != "VIEW_3D" or region is None or area.spaces.active.region_3d is None:
            continue
        rv3d = area.spaces.active.region_3d
        if user_scene is not None and area.as_pointer() not in _saved_views:
            _saved_views[area.as_pointer()] = (user_scene.name, _view_settings(rv3d))
        rv3d.view_perspective = "CAMERA"
        with context.temp_override(window=window, screen=screen, area=area, region=region):
            bpy.ops.view3d.view_center_camera()
    if _saved_views and not bpy.app.timers.is_registered(_restore_views):
        bpy.app.timers.register(_restore_views, first_interval=0.5)


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
        _frame_views(context, user_scene if scene != user_scene else None)
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
    if bpy.app.timers.is_registered(_restore_views):
        bpy.app.timers.unregister(_restore_views)
    _saved_views.clear()
