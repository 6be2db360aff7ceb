"""The parts the demo scenes (demo_scenes.py) are built from: materials, mesh and Lattice objects,
labels on a plate, the stage (ground, sun, camera and render settings), keyframes (in Blender 4.x's
and 5.x's actions alike), a capsule mesh, a Bind with given settings and a plain Lattice modifier."""
import math

import bpy
import numpy as np

from .lifecycle import bind


def material(name, rgba):
    """The material `name` (made if missing) in colour `rgba`, for Workbench and EEVEE/Cycles alike."""
    mat = bpy.data.materials.get(name) or bpy.data.materials.new(name)
    mat.diffuse_color = rgba                 # Workbench and the viewport
    if getattr(mat, "node_tree", None) is None and hasattr(mat, "use_nodes"):
        mat.use_nodes = True
    bsdf = mat.node_tree.nodes.get("Principled BSDF") if mat.node_tree else None
    if bsdf is not None:
        bsdf.inputs["Base Color"].default_value = rgba
        bsdf.inputs["Roughness"].default_value = 0.45
    return mat


def mesh_object(scene, name, verts, tris, mat=None, smooth=False):
    """A mesh object of triangles `tris` (F, 3) over `verts` (V, 3), linked to `scene`, with the
    material `mat`."""
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
    if mat is not None:
        me.materials.append(mat)
    ob = bpy.data.objects.new(name, me)
    scene.collection.objects.link(ob)
    return ob


def lattice_object(scene, name, shape, half_extent, location):
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


def label(scene, text, location, size=0.3):
    """Dark text on a light plate just behind it: readable on the dark background of the Solid
    viewport and on the light world of the renders alike."""
    curve = bpy.data.curves.new(f"Label {text}", "FONT")
    curve.body = text
    curve.align_x = "CENTER"
    curve.size = size
    ob = bpy.data.objects.new(f"Label {text}", curve)
    ob.location = location
    ob.rotation_euler = (math.radians(90), 0, 0)
    ob.data.materials.append(material("VP-FFD Demo Label", (0.04, 0.04, 0.04, 1.0)))
    scene.collection.objects.link(ob)
    # The plate, in the text's own plane (text from about -0.25 to 0.8 of its size about the
    # baseline; a character about 0.55 of its size wide), a little behind it.
    half_w = 0.27 * size * len(text) + 0.1 * size
    lo, hi = -0.45 * size, 1.0 * size
    plate_v = np.array([[-half_w, lo, -0.01], [half_w, lo, -0.01], [half_w, hi, -0.01], [-half_w, hi, -0.01]])
    plate = mesh_object(scene, f"Label Plate {text}", plate_v, np.array([[0, 1, 2], [0, 2, 3]]),
                        material("VP-FFD Demo Label Plate", (0.95, 0.95, 0.93, 1.0)))
    plate.parent = ob
    return ob


def stage(scene, camera_location, camera_target, frames, ground_size):
    """Ground, sun, camera and render settings shared by the demos."""
    ground_v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float) * [ground_size, ground_size, 0]
    mesh_object(scene, "Ground", ground_v, np.array([[0, 1, 2], [0, 2, 3]]),
                material("VP-FFD Demo Ground", (0.8, 0.8, 0.78, 1.0)))
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(40), math.radians(15), math.radians(30))
    scene.collection.objects.link(sun)
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    cam.location = camera_location
    direction = np.subtract(camera_target, camera_location)
    cam.rotation_euler = look_rotation(direction)
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


def look_rotation(direction):
    """Euler angles that point a camera (looking down its -Z) along `direction`."""
    x, y, z = direction
    pitch = math.atan2(math.hypot(x, y), -z)
    yaw = math.atan2(y, x) - math.pi / 2
    return (pitch, 0.0, yaw)


def keyframe(data, path, frame, value, interpolation=None):
    """Set `data.path` to `value` and key it at `frame`, with `interpolation` if given."""
    setattr(data, path, value)
    data.keyframe_insert(path, frame=frame)
    if interpolation:
        anim = data.id_data.animation_data if hasattr(data, "id_data") else None
        for fc in fcurves(anim):
            for kp in fc.keyframe_points:
                if kp.co[0] == frame:
                    kp.interpolation = interpolation


def fcurves(anim):
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


def bind_with(ob, depsgraph, progress=None, **settings):
    """Bind `ob` with `settings`; `progress()` is called once it is bound (the window's progress
    indicator: binding is most of a demo's build time)."""
    for k, v in settings.items():
        setattr(ob.vpffd, k, v)
    bind(ob, depsgraph)
    if progress is not None:
        progress()


def add_lattice_modifier(ob, lattice):
    """Blender's own Lattice modifier on `ob`: the demos' uncorrected copies."""
    mod = ob.modifiers.new("Lattice", "LATTICE")
    mod.object = lattice
    return mod


def capsule(radius, length, rings=48, segments=32, cap_rings=8):
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

