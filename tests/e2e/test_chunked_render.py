"""Chunk independence with Debian's real `blender` binary in a debootstrap chroot
(the newest Debian packages; see blender_chroot.py).

A render farm splits an animation into chunks rendered by separate, fresh Blender processes, in any
order. That is only safe if every frame depends on that frame's inputs alone. This test renders the
same 24 frames of a bound VP-FFD animation

- once in a single `blender -b scene.blend -s 1 -e 24 -a` process (the reference),
- as four chunks, 1-6, 7-12, 13-18 and 19-24, in four separate fresh processes,
- in reverse, `-f 24,23,...,1`, in one process (every frame after the later ones),
- and as single frames started mid-range, `-f 17` and `-f 3`, each in its own process,

and records, for every rendered frame, the evaluated mesh's float32 vertex coordinates (read in
render_write from the render pipeline's depsgraph, kept from frame_change_post, as in
test_blender_binary.py) and the PNG. Coordinates must be bit-identical to the reference's for every
frame, and the PNG files byte-identical (all stamp metadata, which holds dates and render times, is
switched off).

The scene (built once, extension installed in the chroot's Blender, bound, saved at frame 10 so the
offsets stored in the file belong to no chunk's first frame): an icosphere of 2,562 vertices in a
4x4x4 lattice with independent animations, on different keys, so that every frame differs: an
Armature before VP-FFD bending the sphere's upper half, a lattice shape key (squash and twist), the
VP-FFD Volume Scale, the lattice object's location and rotation, and the sphere object travelling
through the lattice (so the input is embedded anew on every frame). `-f 1` alone checks the first
frame of the animation render started from the saved frame 10 against a single-frame render.

test_chunks_render_what_one_process_renders: the identity above, and that the frames really differ.
test_rendered_volume_follows_animated_volume_scale: the reference render is right, not just
reproducible: every frame's volume (recomputed here from the recorded coordinates) is the rest
volume times that frame's Volume Scale. Both share one module-scoped set of renders.

Skipped only when not root or when debootstrap cannot be installed (as test_blender_binary.py).
VPFFD_E2E_KEEP=1 keeps the work folder (<chroot>/tmp/vpffd-e2e-*). About 15 s with the chroot made.
"""
import json
import os
import textwrap

import numpy as np
import pytest

from . import blender_chroot as bc
from .test_blender_binary import _check, _volume

FRAMES = list(range(1, 25))
SAVED_FRAME = 10
# name -> Blender frame arguments; each entry is one fresh `blender -b` process.
RUNS = {
    "single": ["-s", "1", "-e", "24", "-a"],
    "chunk1": ["-s", "1", "-e", "6", "-a"],
    "chunk2": ["-s", "7", "-e", "12", "-a"],
    "chunk3": ["-s", "13", "-e", "18", "-a"],
    "chunk4": ["-s", "19", "-e", "24", "-a"],
    "reverse": ["-f", ",".join(str(f) for f in reversed(FRAMES))],
    "only17": ["-f", "17"],
    "only3": ["-f", "3"],
    "only1": ["-f", "1"],
}
EXPECTED_ORDER = {
    "single": FRAMES,
    "chunk1": FRAMES[0:6],
    "chunk2": FRAMES[6:12],
    "chunk3": FRAMES[12:18],
    "chunk4": FRAMES[18:24],
    "reverse": FRAMES[::-1],
    "only17": [17],
    "only3": [3],
    "only1": [1],
}

# ---------------------------------------------------------------- scripts run inside Blender ---
MAKE_SCENE = r'''
# argv after "--": OUT_BLEND SAVED_FRAME. Runs with the work folder as cwd.
import json
import math
import os
import sys
import bmesh
import bpy
import numpy as np

argv = sys.argv[sys.argv.index("--") + 1:]
out_blend, saved_frame = argv[0], int(argv[1])

bpy.ops.wm.read_homefile(use_empty=True)   # keeps the preferences (enabled add-ons)
scene = bpy.context.scene
scene.frame_start, scene.frame_end = 1, 24

lt = bpy.data.lattices.new("Lattice")
lt.points_u = lt.points_v = lt.points_w = 4
lattice = bpy.data.objects.new("Lattice", lt)
scene.collection.objects.link(lattice)
lattice.scale = (2.6, 2.6, 2.6)          # lattice spans [-1.3, 1.3]^3 around the unit sphere

me = bpy.data.meshes.new("Sphere")
bm = bmesh.new()
bmesh.ops.create_icosphere(bm, subdivisions=5, radius=1.0)  # 2,562 vertices in 4.3
bm.to_mesh(me)
bm.free()
sphere = bpy.data.objects.new("Sphere", me)
scene.collection.objects.link(sphere)

os.makedirs("measure", exist_ok=True)
rest = np.empty(len(me.vertices) * 3, np.float32)
me.vertices.foreach_get("co", rest)
rest.tofile("measure/rest_coords.f32")
me.calc_loop_triangles()
tris = np.empty(len(me.loop_triangles) * 3, np.int32)
me.loop_triangles.foreach_get("vertices", tris)
tris.tofile("measure/tris.i32")

# 0. An Armature before VP-FFD bends the sphere's upper half (the slot's input changes every
#    frame), and the sphere object travels through the lattice.
arm = bpy.data.armatures.new("Rig")
rig = bpy.data.objects.new("Rig", arm)
scene.collection.objects.link(rig)
bpy.context.view_layer.objects.active = rig
with bpy.context.temp_override(object=rig, active_object=rig, selected_objects=[rig]):
    bpy.ops.object.mode_set(mode="EDIT")
    lower = arm.edit_bones.new("Lower")
    lower.head, lower.tail = (0.0, 0.0, -1.0), (0.0, 0.0, 0.0)
    upper = arm.edit_bones.new("Upper")
    upper.head, upper.tail = (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)
    upper.parent = lower
    bpy.ops.object.mode_set(mode="OBJECT")
pose = rig.pose.bones["Upper"]
pose.rotation_mode = "XYZ"
for frame, angle in ((1, 0.0), (13, 0.7), (24, 0.3)):
    pose.rotation_euler = (angle, 0.0, 0.0)
    pose.keyframe_insert("rotation_euler", frame=frame)
groups = [sphere.vertex_groups.new(name=n) for n in ("Lower", "Upper")]
for v in me.vertices:
    t = min(1.0, max(0.0, (v.co.z + 0.3) / 0.6))
    groups[0].add([v.index], 1.0 - t, "REPLACE")
    groups[1].add([v.index], t, "REPLACE")
sphere.modifiers.new("Armature", "ARMATURE").object = rig
for frame, loc in ((1, (-0.15, 0.0, 0.0)), (24, (0.15, 0.05, -0.1))):
    sphere.location = loc
    sphere.keyframe_insert("location", frame=frame)
# The same object without VP-FFD: its evaluated volume is what reaches VP-FFD's slot.
source = sphere.copy()
scene.collection.objects.link(source)

# 1. A lattice shape key: squash in z, widen in x and y, twist about z (more with height).
lattice.shape_key_add(name="Basis", from_mix=False)
key = lattice.shape_key_add(name="SquashTwist", from_mix=False)
for p in key.data:
    x, y, z = p.co
    a = 0.8 * z
    x, y = x * math.cos(a) - y * math.sin(a), x * math.sin(a) + y * math.cos(a)
    p.co = (1.25 * x, 1.2 * y, 0.55 * z)
for frame, value in ((1, 0.0), (9, 1.0), (17, 0.35), (24, 0.8)):
    key.value = value
    key.keyframe_insert("value", frame=frame)

# 2. The lattice object moves and turns relative to the mesh (the binding changes every frame).
for frame, loc, rot in ((1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
                        (12, (0.12, -0.08, 0.15), (0.15, -0.1, 0.4)),
                        (24, (-0.1, 0.1, -0.05), (-0.1, 0.2, 0.9))):
    lattice.location, lattice.rotation_euler = loc, rot
    lattice.keyframe_insert("location", frame=frame)
    lattice.keyframe_insert("rotation_euler", frame=frame)

# 3. Bind with VP-FFD, then animate its Volume Scale.
assert hasattr(sphere, "vpffd"), "the VP-FFD extension is not enabled"
scene.frame_set(1)
sphere.vpffd.lattice = lattice
for ob in scene.objects:
    ob.select_set(ob is sphere)
bpy.context.view_layer.objects.active = sphere
with bpy.context.temp_override(object=sphere, active_object=sphere, selected_objects=[sphere]):
    res = bpy.ops.object.vpffd_bind()
assert res == {"FINISHED"}, res
for frame, value in ((1, 1.0), (7, 1.3), (15, 0.8), (24, 1.15)):
    sphere.vpffd.volume_scale = value
    sphere.keyframe_insert('vpffd.volume_scale', frame=frame)
action = sphere.animation_data.action
if hasattr(action, "fcurves"):        # Blender before 5.0
    fc = action.fcurves.find('vpffd.volume_scale')
else:                                 # slotted actions: the F-curves live in a channel bag
    fc = next(c for layer in action.layers for strip in layer.strips for bag in strip.channelbags
              for c in bag.fcurves if c.data_path == 'vpffd.volume_scale')
assert fc is not None
volume_scale = {str(f): fc.evaluate(f) for f in range(1, 25)}

cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
scene.collection.objects.link(cam)
cam.location = (0.0, -6.0, 0.5)
cam.rotation_euler = (1.4835, 0.0, 0.0)
scene.camera = cam

r = scene.render
r.engine = "BLENDER_WORKBENCH"
r.resolution_x = r.resolution_y = 32
r.resolution_percentage = 100
r.image_settings.file_format = "PNG"
r.filepath = "//frames/f_"
r.use_lock_interface = True
# No metadata in the PNGs: dates, render times and host names differ between processes.
r.use_stamp = False
for name in dir(r):
    if name.startswith("use_stamp_") and isinstance(getattr(r, name), bool):
        try:
            setattr(r, name, False)
        except (AttributeError, TypeError):
            pass

def _source_volume():
    ev = source.evaluated_get(bpy.context.evaluated_depsgraph_get())
    m = ev.to_mesh()
    try:
        co = np.empty(len(m.vertices) * 3, np.float32)
        m.vertices.foreach_get("co", co)
    finally:
        ev.to_mesh_clear()
    p = co.reshape(-1, 3).astype(np.float64)[tris.reshape(-1, 3)]
    return float(np.einsum("ij,ij->", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6.0)


input_volume = {}
for frame in range(1, 25):
    scene.frame_set(frame)
    input_volume[str(frame)] = _source_volume()
bpy.data.objects.remove(source)
scene.frame_set(saved_frame)
with open("measure/scene.json", "w") as f:
    json.dump({"volume_scale": volume_scale, "input_volume": input_volume, "n_verts": len(me.vertices),
               "blender": bpy.app.version_string}, f, indent=1)
bpy.ops.wm.save_as_mainfile(filepath=out_blend)
print("VPFFD_E2E_SAVED", out_blend)
'''

RECORD = r'''
# Registered before the frame arguments: records every rendered frame of the Sphere into
# ./measure/$VPFFD_RUN/ (float32 coordinates per frame, the order frames were written in).
import json
import os
import bpy
import numpy as np
from bpy.app.handlers import persistent

OUT = os.path.join(os.getcwd(), "measure", os.environ["VPFFD_RUN"])
os.makedirs(OUT, exist_ok=True)
RESULT = {"written": [], "modes": {}, "blender": bpy.app.version_string}
DEPSGRAPH = {}


def dump():
    with open(os.path.join(OUT, "run.json"), "w") as f:
        json.dump(RESULT, f, indent=1, sort_keys=True)


@persistent
def on_frame(scene, depsgraph=None):
    # The render pipeline's depsgraph, evaluated at the frame about to be rendered; VP-FFD's
    # offsets (written by its own frame_change_post handler) are evaluated after the handlers.
    if depsgraph is not None:
        DEPSGRAPH["render"] = depsgraph


@persistent
def on_write(scene, *args):
    # After the frame's image was written: the depsgraph holds exactly what was rendered.
    depsgraph = DEPSGRAPH["render"]
    frame = scene.frame_current
    ob = bpy.data.objects["Sphere"].evaluated_get(depsgraph)
    me = ob.to_mesh()
    try:
        co = np.empty(len(me.vertices) * 3, np.float32)
        me.vertices.foreach_get("co", co)
    finally:
        ob.to_mesh_clear()
    co.tofile(os.path.join(OUT, "coords_%04d.f32" % frame))
    RESULT["written"].append(frame)
    RESULT["modes"][str(frame)] = depsgraph.mode
    dump()


bpy.app.handlers.frame_change_post.append(on_frame)
bpy.app.handlers.render_write.append(on_write)
dump()
'''


def _read(path):
    with open(path, "rb") as f:
        return f.read()


@pytest.fixture(scope="module")
def renders(chroot, tmp_path_factory):
    """Build, install, make the scene once, then render every run of RUNS in its own process.
    Returns dict(coords={(run, frame): float32 bytes}, images={(run, frame): PNG bytes},
    rest=rest coordinates (float32), tris, scene=scene.json)."""
    work = bc.new_workdir(chroot)
    try:
        yield _render_all(work, tmp_path_factory.mktemp("scripts"))
    finally:
        if not os.environ.get("VPFFD_E2E_KEEP"):
            bc.remove_workdir(work)
        else:
            print("kept work folder", work)


def _render_all(work, scripts):
    (scripts / "make_scene.py").write_text(textwrap.dedent(MAKE_SCENE))
    (scripts / "record.py").write_text(textwrap.dedent(RECORD))
    measure = os.path.join(work, "measure")

    zip_path = bc.build_extension(bc.REPO_ROOT, work)
    bc.install_extension(zip_path, work)

    # No --factory-startup (the installed extension must load); --python-exit-code, because
    # Blender exits 0 after a failing --python script.
    out = _check(bc.run_blender(
        ["-b", "--python-exit-code", "1", "--python", "make_scene.py", "--",
         "{work}/scene.blend", str(SAVED_FRAME)],
        files=[str(scripts / "make_scene.py")], workdir=work, timeout=300), "make_scene")
    assert "VPFFD_E2E_SAVED" in out
    with open(os.path.join(measure, "scene.json")) as f:
        scene = json.load(f)
    assert scene["blender"] == bc.describe()["version"], (scene["blender"], bc.describe())
    bc.copy_files([str(scripts / "record.py")], work)

    # Every run is its own fresh `blender -b` process on the saved file, writing its images to
    # its own folder (-o must come before the frame arguments).
    coords, images = {}, {}
    for run, frame_args in RUNS.items():
        out = _check(bc.run_blender(
            ["-b", "scene.blend", "--python-exit-code", "1", "--python", "record.py",
             "-o", "//out_%s/f_####" % run] + frame_args,
            workdir=work, env={"VPFFD_RUN": run}, timeout=300), "render " + run)
        with open(os.path.join(measure, run, "run.json")) as f:
            result = json.load(f)
        assert result["written"] == EXPECTED_ORDER[run], (run, result, out[-2000:])
        assert set(result["modes"].values()) == {"RENDER"}, (run, result)
        for frame in EXPECTED_ORDER[run]:
            coords[run, frame] = _read(os.path.join(measure, run, "coords_%04d.f32" % frame))
            png = os.path.join(work, "out_%s" % run, "f_%04d.png" % frame)
            assert os.path.isfile(png), "%s: frame %d not rendered: %s" % (run, frame, out[-2000:])
            images[run, frame] = _read(png)
            assert images[run, frame][:8] == b"\x89PNG\r\n\x1a\n", (run, frame)
    noext = _render_without_extension(work)
    return dict(coords=coords, images=images, scene=scene, noext=noext,
                rest=np.fromfile(os.path.join(measure, "rest_coords.f32"), np.float32),
                tris=np.fromfile(os.path.join(measure, "tris.i32"), np.int32))


NOEXT_FRAMES = (3, SAVED_FRAME)


def _render_without_extension(work):
    """Render NOEXT_FRAMES of the saved scene in a fresh work folder whose Blender has no VP-FFD
    installed (a render worker someone forgot): (exit status, output, {frame: float32 bytes})."""
    bare = bc.new_workdir()
    try:
        bc.copy_files({"scene.blend": os.path.join(work, "scene.blend"),
                       "record.py": os.path.join(work, "record.py")}, bare)
        rc, out, err, _ = bc.run_blender(
            ["-b", "scene.blend", "--python-exit-code", "1", "--python", "record.py",
             "-o", "//out_noext/f_####", "-f", ",".join(str(f) for f in NOEXT_FRAMES)],
            workdir=bare, env={"VPFFD_RUN": "noext"}, timeout=300)
        coords = {f: _read(os.path.join(bare, "measure", "noext", "coords_%04d.f32" % f))
                  for f in NOEXT_FRAMES
                  if os.path.isfile(os.path.join(bare, "measure", "noext", "coords_%04d.f32" % f))}
        return rc, out + err, coords
    finally:
        bc.remove_workdir(bare)


@pytest.mark.e2e
def test_a_worker_without_the_extension_renders_stale_offsets_and_exits_0(renders):
    """The warning of docs/render-farms.md, as it happens: no error, exit status 0, nothing
    about VP-FFD in the output, and every frame gets the offsets saved with the file (right on
    the saved frame, wrong on the others)."""
    rc, out, coords = renders["noext"]
    assert rc == 0, out[-3000:]
    assert "VP-FFD" not in out, out[-3000:]
    assert sorted(coords) == sorted(NOEXT_FRAMES), out[-3000:]
    size = float(np.ptp(renders["rest"].reshape(-1, 3), 0).max())
    ref = {f: np.frombuffer(renders["coords"]["single", f], np.float32) for f in NOEXT_FRAMES}
    got = {f: np.frombuffer(coords[f], np.float32) for f in NOEXT_FRAMES}
    assert np.abs(got[SAVED_FRAME] - ref[SAVED_FRAME]).max() <= 1e-5 * size
    assert np.abs(got[3] - ref[3]).max() > 1e-2 * size, "frame 3 shows the live solve"


@pytest.mark.e2e
def test_chunks_render_what_one_process_renders(renders):
    coords, images = renders["coords"], renders["images"]
    ref = {f: np.frombuffer(coords["single", f], np.float32) for f in FRAMES}
    assert renders["scene"]["n_verts"] > 2000
    for f in FRAMES:
        assert ref[f].size == renders["rest"].size and np.isfinite(ref[f]).all(), f

    # The animation is really there: every frame has its own shape and (almost) its own image.
    for f in FRAMES[1:]:
        assert not np.array_equal(ref[f - 1], ref[f]), "frames %d and %d have the same shape" % (f - 1, f)
    distinct = len({images["single", f] for f in FRAMES})
    assert distinct >= 20, "only %d distinct images in 24 frames" % distinct

    # Chunk independence: bit-identical coordinates and byte-identical images in every run.
    mismatched = []
    for (run, frame), data in sorted(coords.items()):
        if run == "single":
            continue
        if data != coords["single", frame]:
            d = np.abs(np.frombuffer(data, np.float32) - ref[frame]).max()
            mismatched.append("%s frame %d: coordinates differ (max %.3g)" % (run, frame, d))
        if images[run, frame] != images["single", frame]:
            mismatched.append("%s frame %d: image differs" % (run, frame))
    assert not mismatched, "\n".join(mismatched)


@pytest.mark.e2e
def test_rendered_volume_follows_animated_volume_scale(renders):
    # Identical chunks are worth little if every process renders the same wrong thing: each
    # rendered frame must keep the volume that reaches VP-FFD's slot on that frame (after the
    # bending Armature, measured on a twin without VP-FFD) times that frame's animated Volume
    # Scale (float32 solve), whatever frame the file was saved at (SAVED_FRAME).
    tris, scale = renders["tris"], renders["scene"]["volume_scale"]
    source = renders["scene"]["input_volume"]
    assert max(source.values()) - min(source.values()) > 0, "the Armature changes the input"
    ratios = {f: _volume(np.frombuffer(renders["coords"]["single", f], np.float32), tris) / source[str(f)]
              for f in FRAMES}
    wrong = ["frame %d: volume %.5f x rest, Volume Scale %.5f" % (f, ratios[f], scale[str(f)])
             for f in FRAMES if abs(ratios[f] - scale[str(f)]) > 2e-5 * scale[str(f)]]
    assert not wrong, ("the render did not use the animated Volume Scale of each frame "
                       "(saved at frame %d):\n%s" % (SAVED_FRAME, "\n".join(wrong)))
