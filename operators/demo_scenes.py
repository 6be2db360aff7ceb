"""The demo scenes: the paper's bouncing ball and twisting cube (Hahmann et al. 2011, Figures 1 and
6), each next to a plain Lattice modifier copy so the difference shows in one frame, a tube in a
cylindrical cage (MacCracken & Joy), next to the same cage without correction, and an arm bent by
an Armature, alone and with VP-FFD keeping the volume it had at Bind. Each `build_*` builds its
demo into a scene; the operators of the Add menu (demos.py) and `./dev demo` call them."""
import math

import bpy
import numpy as np

from .. import vpffd_addon as vp
from . import cage
from .demo_parts import (add_lattice_modifier, bind_with, capsule, keyframe, label, lattice_object, material,
                         mesh_object, stage)

BALL_FRAMES = (1, 60)
CUBE_FRAMES = (1, 60)
TUBE_FRAMES = (1, 60)
ARM_FRAMES = (1, 60)

PLAIN_COLOUR = (0.85, 0.30, 0.25, 1.0)
VPFFD_COLOUR = (0.20, 0.55, 0.90, 1.0)
VPFFD_COLOUR_2 = (0.25, 0.75, 0.45, 1.0)


# -------------------------------------------------------------------------------- bouncing ball

def _ball_rig(scene, name, x, colour):
    """A ball parented to its own 4x4x4 lattice; the lattice falls, squashes on the ground
    (shape key "Squash": flattened towards its floor) and stretches in flight ("Stretch")."""
    radius, half = 0.5, 0.55
    lat = lattice_object(scene, f"{name} Lattice", (4, 4, 4), (half,) * 3, (x, 0.0, 2.5))
    verts, tris = vp.icosphere(4, radius)
    ball = mesh_object(scene, name, verts, tris, material(f"VP-FFD Demo {name}", colour), smooth=True)
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
        keyframe(lat, "location", f, (x, 0.0, z))
    keys = lat.data.shape_keys.key_blocks
    for f, v in ((1, 0.0), (14, 0.0), (18, 1.0), (21, 0.0), (44, 0.0), (48, 0.9), (51, 0.0), (60, 0.0)):
        keyframe(keys["Squash"], "value", f, v)
    for f, v in ((1, 0.0), (12, 0.5), (15, 0.0), (21, 0.0), (25, 0.45), (31, 0.0), (42, 0.45), (45, 0.0),
                 (51, 0.0), (55, 0.4), (60, 0.0)):
        keyframe(keys["Stretch"], "value", f, v)
    return ball, lat


def build_bouncing_ball(scene, depsgraph=None, progress=None):
    """Two balls falling side by side: a plain Lattice modifier (left) and VP-FFD correcting in
    the horizontal directions (right), so the squash spreads sideways (paper section 5.1).
    Returns {'plain': ball, 'vpffd': ball, 'lattices': [...]}."""
    plain, plain_lat = _ball_rig(scene, "Ball Lattice Modifier", -1.2, PLAIN_COLOUR)
    ours, our_lat = _ball_rig(scene, "Ball VP-FFD XY", 1.2, VPFFD_COLOUR)
    label(scene, "Lattice modifier", (-1.2, 0.0, 3.4), size=0.26)
    label(scene, "VP-FFD (XY)", (1.2, 0.0, 3.4), size=0.26)
    stage(scene, camera_location=(0.0, -8.5, 2.2), camera_target=(0.0, 0.0, 1.5), frames=BALL_FRAMES,
          ground_size=5.0)
    add_lattice_modifier(plain, plain_lat)
    scene.frame_set(scene.frame_start)
    dg = depsgraph or scene.view_layers[0].depsgraph
    bind_with(ours, dg, progress=progress, lattice=our_lat, axes="XY", space="LATTICE")
    return {"plain": plain, "vpffd": ours, "lattices": [plain_lat, our_lat]}


# ------------------------------------------------------------------------------- twisting cube

def _cube_rig(scene, name, x, colour):
    """A subdivided cube (6,146 vertices, as the paper's) in a 4x4x8 lattice that a Simple Deform
    modifier twists from 0 to 360 degrees about Z."""
    half = 0.55
    lat = lattice_object(scene, f"{name} Lattice", (4, 4, 8), (half, half, half), (x, 0.0, 0.9))
    verts, tris = vp.box(32, 1.0)
    cube = mesh_object(scene, name, verts, tris, material(f"VP-FFD Demo {name}", colour))
    cube.parent = lat
    cube.scale = [1.0 / s for s in lat.scale]
    twist = lat.modifiers.new("Twist", "SIMPLE_DEFORM")
    twist.deform_method = "TWIST"
    twist.deform_axis = "Z"
    keyframe(twist, "angle", CUBE_FRAMES[0], 0.0, "LINEAR")
    keyframe(twist, "angle", CUBE_FRAMES[1], 2.0 * math.pi, "LINEAR")
    return cube, lat


def build_twisting_cube(scene, depsgraph=None, progress=None):
    """Three cubes twisted by their lattices (paper Figure 6): a plain Lattice modifier, VP-FFD
    correcting in XY (top and bottom stay flat) and VP-FFD correcting in Z.
    Returns {'plain': cube, 'vpffd_xy': cube, 'vpffd_z': cube, 'lattices': [...]}."""
    plain, plain_lat = _cube_rig(scene, "Cube Lattice Modifier", -2.0, PLAIN_COLOUR)
    xy, xy_lat = _cube_rig(scene, "Cube VP-FFD XY", 0.0, VPFFD_COLOUR)
    z, z_lat = _cube_rig(scene, "Cube VP-FFD Z", 2.0, VPFFD_COLOUR_2)
    for text, x in (("Lattice modifier", -2.0), ("VP-FFD (XY)", 0.0), ("VP-FFD (Z)", 2.0)):
        label(scene, text, (x, 0.0, 1.85), size=0.22)
    stage(scene, camera_location=(0.0, -7.5, 3.3), camera_target=(0.0, 0.0, 0.85), frames=CUBE_FRAMES,
          ground_size=6.0)
    add_lattice_modifier(plain, plain_lat)
    scene.frame_set(scene.frame_start)
    dg = depsgraph or scene.view_layers[0].depsgraph
    bind_with(xy, dg, progress=progress, lattice=xy_lat, axes="XY", space="LATTICE")
    bind_with(z, dg, progress=progress, lattice=z_lat, axes="Z", space="LATTICE")
    return {"plain": plain, "vpffd_xy": xy, "vpffd_z": z, "lattices": [plain_lat, xy_lat, z_lat]}


# ------------------------------------------------------------------------------- squeezed tube

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
    verts, tris = capsule(0.36, 1.15)
    tube = mesh_object(scene, name, verts, tris, material(f"VP-FFD Demo {name}", colour), smooth=True)
    tube.location = cage_ob.location
    cage_ob.shape_key_add(name="Basis")
    squeeze = points.copy()
    z = np.abs(points[:, 2])
    squeeze[:, :2] *= np.where(z < 0.1, 0.4, np.where(z < 0.5, 0.75, 1.0))[:, None]
    key = cage_ob.shape_key_add(name="Squeeze")
    key.data.foreach_set("co", squeeze.astype(np.float32).ravel())
    for f, v in ((1, 0.0), (25, 1.0), (40, 1.0), (60, 0.0)):
        keyframe(key, "value", f, v)
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
        label(scene, text, (x, 0.0, 3.05), size=0.22)
    stage(scene, camera_location=(0.0, -8.0, 1.9), camera_target=(0.0, 0.0, 1.6), frames=TUBE_FRAMES,
          ground_size=6.0)
    scene.frame_set(scene.frame_start)
    dg = depsgraph or scene.view_layers[0].depsgraph
    bind_with(plain, dg, progress=progress, lattice=plain_cage, axes="NONE", cage_depth=3)
    bind_with(xyz, dg, progress=progress, lattice=xyz_cage, axes="XYZ", space="LATTICE", cage_depth=3)
    bind_with(z, dg, progress=progress, lattice=z_cage, axes="Z", space="LATTICE", cage_depth=3)
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
    verts, tris = capsule(0.2, 2 * half - 0.4)
    arm = mesh_object(scene, name, verts, tris, material(f"VP-FFD Demo {name}", colour), smooth=True)
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
        keyframe(pose, "rotation_euler", f, (0.0, 0.0, math.radians(angle)))   # bone Z: sideways in the camera
    return arm, rig


def build_bent_arm(scene, depsgraph=None, progress=None):
    """Two arms bent by their Armatures: the Armature alone (left), which loses volume at the
    elbow, and VP-FFD after it (right): a lattice around the elbow, its deformation fading out
    beyond it (Outside: Falloff), correcting along X, Y and Z towards the volume the arm had at
    Bind, in the rest pose (Target: Bind). Returns {'plain': arm, 'vpffd': arm, 'lattices': [...]}."""
    plain, _ = _arm_rig(scene, "Arm Armature Alone", -1.1, PLAIN_COLOUR)
    ours, _ = _arm_rig(scene, "Arm VP-FFD Bind", 1.1, VPFFD_COLOUR)
    lat = lattice_object(scene, "Arm VP-FFD Bind Elbow Lattice", (4, 4, 4), (0.35, 0.35, 0.35),
                         ours.location)
    for text, x in (("Armature alone", -1.1), ("VP-FFD (volume at Bind)", 1.1)):
        label(scene, text, (x, 0.0, 2.55), size=0.18)
    stage(scene, camera_location=(0.0, -5.6, 1.5), camera_target=(0.0, 0.0, 1.5), frames=ARM_FRAMES,
          ground_size=6.0)
    scene.frame_set(scene.frame_start)
    dg = depsgraph or scene.view_layers[0].depsgraph
    bind_with(ours, dg, progress=progress, lattice=lat, axes="XYZ", space="LATTICE", target="BIND",
              outside="FALLOFF", falloff_distance=0.6)
    return {"plain": plain, "vpffd": ours, "lattices": [lat]}
