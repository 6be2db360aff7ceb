"""End-to-end test with Debian's real `blender` binary in a debootstrap chroot
(the newest Debian packages; see blender_chroot.py).

Process 1 (`blender -b --python make_scene.py`): builds an icosphere inside a 4x4x4 lattice,
animates the lattice with a shape key (value 0 at frame 1 -> 1 at frame 3; the key scales the
lattice points by 1.3, 1.3, 0.5), deforms the sphere with it, writes the undeformed mesh's
float32 coordinates and saves scene.blend.
Process 2, a fresh one (`blender -b scene.blend --python record.py -s 1 -e 3 -a`): renders 3
Workbench frames at 32x32; for every frame, a render_write handler reads the evaluated sphere
from the render pipeline's depsgraph (kept from frame_change_post, which is the only handler that
gets it) and writes its float32 vertex coordinates, triangles and volume. The host recomputes the
volumes with numpy from those coordinates, checks them, and checks the images.

The deformer is a parameter: "lattice" (Blender's Lattice modifier); "vpffd" builds the extension
from this working tree, installs it in the chroot's Blender and binds with
`sphere.vpffd.lattice = lattice; bpy.ops.object.vpffd_bind()`, then expects the volume to stay
the rest volume; "cage" does the same with a VP-FFD cage made by `vpffd_cage_add_box` (hidden
from renders) and squashed by the same shape key. All three run by default; choose with
VPFFD_E2E_DEFORMERS=lattice,vpffd,cage (or change DEFORMERS below).
VPFFD_E2E_KEEP=1 keeps the work folder (<chroot>/tmp/vpffd-e2e-*) for inspection.

Skipped only when not root or when debootstrap cannot be installed; anything else failing
(network, apt, Blender) fails the test. First run: ~100 s to make the chroot; later ~5 s.
"""
import json
import os
import textwrap

import numpy as np
import pytest

from . import blender_chroot as bc

DEFORMERS = os.environ.get("VPFFD_E2E_DEFORMERS", "lattice,vpffd,cage").split(",")
FRAMES = (1, 2, 3)
SQUASH = (1.3, 1.3, 0.5)        # lattice shape-key scale at full value (frame 3)
KEY_VALUE = {1: 0.0, 2: 0.5, 3: 1.0}   # two auto-clamped keys: exactly 0.5 half-way

# ---------------------------------------------------------------- scripts run inside Blender ---
MAKE_SCENE = r'''
# argv after "--": OUT_BLEND DEFORMER SX SY SZ. Runs with the work folder as cwd.
import os
import sys
import bmesh
import bpy
import numpy as np

argv = sys.argv[sys.argv.index("--") + 1:]
out_blend, deformer = argv[0], argv[1]
SQUASH = tuple(float(v) for v in argv[2:5])

bpy.ops.wm.read_homefile(use_empty=True)   # keeps the preferences (enabled add-ons)
scene = bpy.context.scene

lt = bpy.data.lattices.new("Lattice")
lt.points_u = lt.points_v = lt.points_w = 4
lattice = bpy.data.objects.new("Lattice", lt)
scene.collection.objects.link(lattice)
lattice.scale = (2.5, 2.5, 2.5)          # lattice spans [-1.25, 1.25]^3 around the unit sphere

me = bpy.data.meshes.new("Sphere")
bm = bmesh.new()
bmesh.ops.create_icosphere(bm, subdivisions=2, radius=1.0)
bm.to_mesh(me)
bm.free()
sphere = bpy.data.objects.new("Sphere", me)
scene.collection.objects.link(sphere)

# The undeformed mesh, for the host to compute the rest volume from.
os.makedirs("measure", exist_ok=True)
rest = np.empty(len(me.vertices) * 3, np.float32)
me.vertices.foreach_get("co", rest)
rest.tofile("measure/rest_coords.f32")
me.calc_loop_triangles()
rest_tris = np.empty(len(me.loop_triangles) * 3, np.int32)
me.loop_triangles.foreach_get("vertices", rest_tris)
rest_tris.tofile("measure/rest_tris.i32")



def squash_key(ob):
    """Shape key scaling the object's points by SQUASH: value 0 at frame 1, 1 at frame 3."""
    ob.shape_key_add(name="Basis", from_mix=False)
    key = ob.shape_key_add(name="Squash", from_mix=False)
    for p in key.data:
        p.co = (p.co[0] * SQUASH[0], p.co[1] * SQUASH[1], p.co[2] * SQUASH[2])
    key.value = 0.0
    key.keyframe_insert("value", frame=1)
    key.value = 1.0
    key.keyframe_insert("value", frame=3)


# Animate the lattice: keyframed co_deform is not animatable, a shape key value is.
squash_key(lattice)

if deformer == "lattice":
    mod = sphere.modifiers.new("Lattice", "LATTICE")
    mod.object = lattice
elif deformer == "cage":
    # A VP-FFD cage (a mesh object, hidden from renders as the extension makes it) around the
    # sphere, squashed by the same shape key, with the sphere bound to it.
    for ob in scene.objects:
        ob.select_set(ob is sphere)
    bpy.context.view_layer.objects.active = sphere
    with bpy.context.temp_override(active_object=sphere, object=sphere, selected_objects=[sphere]):
        res = bpy.ops.object.vpffd_cage_add_box(resolution=(2, 2, 2), margin=0.1)
    assert res == {"FINISHED"}, res
    cage = bpy.context.view_layer.objects.active
    assert cage is not sphere and cage.hide_render
    squash_key(cage)
    sphere.vpffd.lattice = cage
    sphere.vpffd.cage_depth = 2
    with bpy.context.temp_override(object=sphere, active_object=sphere, selected_objects=[sphere]):
        res = bpy.ops.object.vpffd_bind()
    assert res == {"FINISHED"}, res
    print("VPFFD_E2E_BOUND")
elif deformer == "vpffd":
    # The extension (installed by the test into this run's user resources) replaces the Lattice
    # modifier: pick the lattice in the object's VP-FFD settings, then bind.
    assert hasattr(sphere, "vpffd"), "the VP-FFD extension is not enabled"
    sphere.vpffd.lattice = lattice
    for ob in scene.objects:
        ob.select_set(ob is sphere)
    bpy.context.view_layer.objects.active = sphere
    with bpy.context.temp_override(object=sphere, active_object=sphere, selected_objects=[sphere]):
        res = bpy.ops.object.vpffd_bind()
    assert res == {"FINISHED"}, res
    print("VPFFD_E2E_BOUND")
else:
    raise SystemExit("unknown deformer " + deformer)

cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
scene.collection.objects.link(cam)
cam.location = (0.0, -6.0, 0.0)
cam.rotation_euler = (1.5707963, 0.0, 0.0)
scene.camera = cam

scene.render.engine = "BLENDER_WORKBENCH"
scene.render.resolution_x = scene.render.resolution_y = 32
scene.render.resolution_percentage = 100
scene.render.image_settings.file_format = "PNG"
scene.render.filepath = "//frames/f_"
scene.render.use_lock_interface = True
scene.frame_start, scene.frame_end = 1, 3
scene.frame_set(1)
bpy.ops.wm.save_as_mainfile(filepath=out_blend)
print("VPFFD_E2E_SAVED", out_blend)
'''

RECORD = r'''
# Registered before `-a`: records every rendered frame of the Sphere into ./measure/.
import json
import os
import bpy
import numpy as np
from bpy.app.handlers import persistent

OUT = os.path.join(os.getcwd(), "measure")
os.makedirs(OUT, exist_ok=True)
RESULT = {"frames": {}, "written": [], "blender": bpy.app.version_string}


def dump():
    with open(os.path.join(OUT, "volumes.json"), "w") as f:
        json.dump(RESULT, f, indent=1, sort_keys=True)


def measure(obj, depsgraph):
    ob = obj.evaluated_get(depsgraph)
    me = ob.to_mesh()
    try:
        co = np.empty(len(me.vertices) * 3, np.float32)
        me.vertices.foreach_get("co", co)
        me.calc_loop_triangles()
        tris = np.empty(len(me.loop_triangles) * 3, np.int32)
        me.loop_triangles.foreach_get("vertices", tris)
    finally:
        ob.to_mesh_clear()
    c = co.reshape(-1, 3).astype(np.float64)
    t = tris.reshape(-1, 3)
    vol = float(np.einsum("ij,ij->i", c[t[:, 0]], np.cross(c[t[:, 1]], c[t[:, 2]])).sum() / 6.0)
    return co, tris, vol


DEPSGRAPH = {}


def save(frame, key, depsgraph):
    co, tris, vol = measure(bpy.data.objects["Sphere"], depsgraph)
    if key == "volume":
        co.tofile(os.path.join(OUT, "coords_%04d.f32" % frame))
        tris.tofile(os.path.join(OUT, "tris_%04d.i32" % frame))
    rec = RESULT["frames"].setdefault(str(frame), {})
    rec.update({key: vol, "n_verts": len(co) // 3, "n_tris": len(tris) // 3, "mode": depsgraph.mode})
    dump()


@persistent
def on_frame(scene, depsgraph=None):
    # During `-a` this gets the render pipeline's depsgraph, evaluated at the frame about to be
    # rendered (render_pre/post/write get none, and the context's one is not advanced). Data
    # written by frame_change_post handlers (VP-FFD's offsets) is evaluated only after them.
    if depsgraph is None:
        return
    DEPSGRAPH["render"] = depsgraph
    save(scene.frame_current, "volume_frame_change", depsgraph)


@persistent
def on_write(scene, *args):
    # After the frame was rendered and its image written: the same depsgraph now holds exactly
    # what was rendered, including any updates the frame handlers made.
    RESULT["written"].append(scene.frame_current)
    save(scene.frame_current, "volume", DEPSGRAPH["render"])


bpy.app.handlers.frame_change_post.append(on_frame)
bpy.app.handlers.render_write.append(on_write)
dump()
'''


def _volume(co, tris):
    c = co.reshape(-1, 3).astype(np.float64)
    t = tris.reshape(-1, 3)
    return float(np.einsum("ij,ij->i", c[t[:, 0]], np.cross(c[t[:, 1]], c[t[:, 2]])).sum() / 6.0)


@pytest.fixture
def workdir(chroot):
    work = bc.new_workdir(chroot)
    yield work
    if not os.environ.get("VPFFD_E2E_KEEP"):
        bc.remove_workdir(work)
    else:
        print("kept work folder", work)


def _check(result, what):
    rc, out, err, _ = result
    assert rc == 0, "%s failed (exit %s)\n--- stdout\n%s\n--- stderr\n%s" % (what, rc, out[-4000:], err[-4000:])
    return out


@pytest.mark.e2e
@pytest.mark.parametrize("deformer", DEFORMERS)
def test_blender_binary_renders_deformed_animation(deformer, workdir, tmp_path):
    scripts = tmp_path / "scripts"
    scripts.mkdir()
    (scripts / "make_scene.py").write_text(textwrap.dedent(MAKE_SCENE))
    (scripts / "record.py").write_text(textwrap.dedent(RECORD))
    measure = os.path.join(workdir, "measure")

    if deformer in ("vpffd", "cage"):
        zip_path = bc.build_extension(bc.REPO_ROOT, workdir)
        bc.install_extension(zip_path, workdir)

    # Process 1: build and save the scene. No --factory-startup (an installed extension must
    # load); --python-exit-code, because Blender exits 0 after a failing --python script.
    out = _check(bc.run_blender(
        ["-b", "--python-exit-code", "1", "--python", "make_scene.py", "--",
         "{work}/scene.blend", deformer] + [repr(k) for k in SQUASH],
        files=[str(scripts / "make_scene.py")], workdir=workdir, timeout=300), "make_scene")
    assert "VPFFD_E2E_SAVED" in out
    assert os.path.isfile(os.path.join(workdir, "scene.blend"))

    # Process 2: a fresh Blender renders frames 1..3 of the saved file, recording each frame.
    out = _check(bc.run_blender(
        ["-b", "scene.blend", "--python-exit-code", "1", "--python", "record.py",
         "-s", str(FRAMES[0]), "-e", str(FRAMES[-1]), "-a"],
        files=[str(scripts / "record.py")], workdir=workdir, timeout=300), "render")

    with open(os.path.join(measure, "volumes.json")) as f:
        result = json.load(f)
    assert result["blender"] == bc.describe()["version"], (result["blender"], bc.describe())
    assert sorted(result["written"]) == list(FRAMES), (result, out[-2000:])
    assert sorted(int(k) for k in result["frames"]) == list(FRAMES), result

    # Images: one PNG per frame, and the squash shows (frame 1 differs from frame 3).
    images = {}
    for frame in FRAMES:
        png = os.path.join(workdir, "frames", "f_%04d.png" % frame)
        assert os.path.isfile(png), "frame %d not rendered: %s" % (frame, out[-2000:])
        with open(png, "rb") as f:
            images[frame] = f.read()
        assert images[frame][:8] == b"\x89PNG\r\n\x1a\n" and len(images[frame]) > 100
    assert images[1] != images[3]

    # Volumes: recorded in Blender == recomputed here from the same float32 coordinates.
    rest_co = np.fromfile(os.path.join(measure, "rest_coords.f32"), np.float32)
    rest = _volume(rest_co, np.fromfile(os.path.join(measure, "rest_tris.i32"), np.int32))
    assert 3.5 < rest < 4.19, rest   # subdivision-2 unit icosphere (sphere: 4.18879)
    volumes, coords = {}, {}
    for frame in FRAMES:
        rec = result["frames"][str(frame)]
        assert rec["mode"] == "RENDER", rec
        co = np.fromfile(os.path.join(measure, "coords_%04d.f32" % frame), np.float32)
        tris = np.fromfile(os.path.join(measure, "tris_%04d.i32" % frame), np.int32)
        assert co.size == 3 * rec["n_verts"] == rest_co.size and tris.size == 3 * rec["n_tris"]
        assert np.isfinite(co).all()
        coords[frame] = co.reshape(-1, 3)
        volumes[frame] = _volume(co, tris)
        assert volumes[frame] == pytest.approx(rec["volume"], rel=1e-12, abs=1e-12), (frame, rec)
        if deformer == "lattice":   # no handler changes data, so both reads agree
            assert rec["volume_frame_change"] == rec["volume"], (frame, rec)
    # The mesh really was squashed in the render (z extent: 0.5x for the plain lattice).
    assert np.ptp(coords[3][:, 2]) < 0.9 * np.ptp(coords[1][:, 2])

    if deformer == "lattice":
        # The key scales the lattice affinely, so the volume scales by the determinant; at
        # frame 1 the undeformed lattice is the identity map.
        for frame in FRAMES:
            s = [1.0 + KEY_VALUE[frame] * (k - 1.0) for k in SQUASH]
            assert volumes[frame] == pytest.approx(rest * s[0] * s[1] * s[2], rel=1e-5), (frame, volumes)
    else:
        for frame in FRAMES:   # VP-FFD keeps the enclosed volume (float32 solver)
            assert volumes[frame] == pytest.approx(rest, rel=1e-5), (frame, rest, volumes)
