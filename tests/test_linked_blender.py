"""Rigs as studios use them: bound and saved in their own file, linked into a shot.

Each step runs in a fresh Blender process on real files, as a studio's steps do: the rig file is
made and saved by one process, the shot links it in another, the saved shot is reopened in a
third. The rig nests its objects as riggers do (Character > Meshes, Character > Deform). Its mesh
has shape keys and an Armature (at rest in the rig file) before two VP-FFD modifiers: a lattice
whose shape key squashes it (keyframed in the rig file) and a smaller one over its upper half. A
twin of the mesh has the same stack with Blender's own Lattice modifiers.
- A library override (made with `override_hierarchy_create`, and with Blender's operator
  `object.make_override_library`): Correction None equals the twin, XYZ keeps the volume that
  reaches the first slot, on every frame, also when the shot animates the overridden lattice and
  poses the overridden Armature, after the shot is saved and reopened, and in an animation
  render of the reopened shot (the render's own depsgraph, as `blender -b shot.blend -a`); a rig
  re-bound in its file is followed on reopening.
- A plain collection instance: nothing can be written into linked data, so the panel and the
  console say so for each VP-FFD modifier, naming the object; a rig baked in its file (Bake to
  Point Cache) plays its cache exactly in every instance.
"""
import json
import textwrap

import pytest

bpy = pytest.importorskip("bpy")

from . import extension_harness as eh

# Each test runs several fresh Blender processes: on the newest Blender and 4.2 LTS (the passes
# that run the whole suite), not in the layer passes between them.
pytestmark = [pytest.mark.blender, pytest.mark.studio]

SHAPE_TOL = 1e-5      # of the mesh's size
VOLUME_TOL = 1e-5     # relative

# Shared by every process: the measurements, made independently of VP-FFD (the evaluated float32
# coordinates, the volume as 1/6 sum a . (b x c) over their triangles).
_COMMON = '''
import json, sys, importlib
import bpy
import numpy as np
ext = importlib.import_module(module)
ops = ext.operators

def evaluated(ob):
    dg = bpy.context.evaluated_depsgraph_get()
    e = ob.evaluated_get(dg)
    me = e.to_mesh()
    me.calc_loop_triangles()
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    tris = np.empty(len(me.loop_triangles) * 3, np.int64)
    me.loop_triangles.foreach_get("vertices", tris)
    e.to_mesh_clear()
    return co.reshape(-1, 3).astype(np.float64), tris.reshape(-1, 3)

def triangle_volume(co, t):
    a, b, c = co[t[:, 0]], co[t[:, 1]], co[t[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)

def volume(ob):
    return triangle_volume(*evaluated(ob))

def vp_modifier(ob):
    return next(m for m in ob.modifiers if m.type == "NODES")

def deformers(ob):
    return ops.deformers.bound(ob)

def errors(ob):
    return [ops.status.stats(d).get("error") for d in deformers(ob)]

def input_volume(body):
    """What reaches the first VP-FFD modifier: the volume with every VP-FFD modifier off."""
    ds = deformers(body)
    for d in ds:
        d.mod.show_viewport = False
    v_in = volume(body)
    for d in ds:
        d.mod.show_viewport = True
    return v_in

def measure(body, twin, frames):
    """Per frame, with every VP-FFD deformer of the body: |None - twin| / size, |V_XYZ / V_in - 1|
    (V_in: what reaches the first, the stack with VP-FFD switched off), the panel's errors."""
    out = []
    for f in frames:
        bpy.context.scene.frame_set(f)
        ds = deformers(body)
        v_in = input_volume(body)
        v_out = volume(body)
        error = errors(body)
        for d in ds:
            d.settings.axes = "NONE"
        bpy.context.scene.frame_set(f)
        a, _ = evaluated(body)
        b, _ = evaluated(twin)
        for d in ds:
            d.settings.axes = "XYZ"
        bpy.context.scene.frame_set(f)
        out.append(dict(frame=f, shape=float(np.abs(a - b).max() / np.ptp(b, 0).max()),
                        volume=abs(v_out / v_in - 1), error=error, deformers=len(ds)))
    return out

def report(**values):
    print("VPFFD-REPORT " + json.dumps(values), flush=True)
'''

_RIG = '''
sys.path.insert(0, REPO)
from tests import blender_ref as br
import vpffd_addon as core
bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
scene = bpy.context.scene
# Character > Meshes and Character > Deform, as riggers nest them
char = bpy.data.collections.new("Character")
scene.collection.children.link(char)
meshes, deform = bpy.data.collections.new("Meshes"), bpy.data.collections.new("Deform")
char.children.link(meshes)
char.children.link(deform)
def into(collection, ob):
    for c in ob.users_collection:
        c.objects.unlink(ob)
    collection.objects.link(ob)
lat, key = br.squash_lattice("Lattice", (4, 4, 4), (0.8, 0.8, 1.1), 0.55, 0.3, shear=0.2)
# a second, smaller lattice over the upper half: a second VP-FFD modifier after the first
belly, belly_key = br.squash_lattice("Belly", (3, 3, 3), (0.7, 0.7, 0.5), 0.7, 0.25)
belly.location.z = 0.45
for k in (key, belly_key):
    for f, v in ((1, 0.0), (20, 1.0)):
        k.value = v
        k.keyframe_insert("value", frame=f)
# an Armature before VP-FFD, at rest in the rig file (the shot poses it)
arm = br.two_bone_armature("Armature", 1.3)
arm.animation_data_clear()
arm.pose.bones["Upper"].rotation_euler = (0, 0, 0)
for ob in (lat, belly, arm):
    into(deform, ob)
v, t = core.icosphere(3, 0.7)
for name in ("Body", "Twin"):
    ob = bpy.data.objects.new(name, br.triangle_mesh(v * (1.0, 1.0, 1.5), t, name))
    meshes.objects.link(ob)
    # a shape key before the slot grows the mesh (frames 1 -> 20): its volume at Bind depends on
    # the frame Bind ran at
    ob.shape_key_add(name="Basis")
    grow = ob.shape_key_add(name="Grow")
    grow.data.foreach_set("co", (v * (1.0, 1.0, 1.5) * 1.2).astype(np.float32).ravel())
    for f, value in ((1, 0.0), (20, 1.0)):
        grow.value = value
        grow.keyframe_insert("value", frame=f)
    br.bone_weights_by_height(ob, 0.35)
    ob.modifiers.new("Armature", "ARMATURE").object = arm
twin = bpy.data.objects["Twin"]
twin.modifiers.new("Lattice", "LATTICE").object = lat
twin.modifiers.new("Belly", "LATTICE").object = belly
body = bpy.data.objects["Body"]
scene.frame_set(BIND_FRAME)
assert br.bind(body, lattice=lat, axes="XYZ", target=TARGET) == {"FINISHED"}
with bpy.context.temp_override(object=body, active_object=body, selected_objects=[body, belly]):
    assert bpy.ops.object.vpffd_modifier_add() == {"FINISHED"}
second = body.modifiers.active
d = ops.deformers.shown(body)
assert d.mod == second and d.settings.lattice == belly
d.settings.axes, d.settings.target = "XYZ", TARGET
with bpy.context.temp_override(object=body, active_object=body, selected_objects=[body]):
    assert bpy.ops.object.vpffd_bind(modifier=second.name) == {"FINISHED"}
scene.frame_set(10)
bpy.ops.wm.save_as_mainfile(filepath=RIG_FILE)
if BAKE:        # a path relative to the rig file, as Blender resolves it for linked data
    ops.bake.bake(body, scene, "//body.pc2", 1, 20, switch=True)
    scene.frame_set(10)
    bpy.ops.wm.save_as_mainfile(filepath=RIG_FILE)
report(saved=RIG_FILE)
'''


@pytest.fixture(scope="module")
def _user(tmp_path_factory):
    """One Blender user folder for the module's processes (the compiled kernels' cache is made
    once)."""
    return tmp_path_factory.mktemp("linked_user")


def _run(vpffd, tmp_path, name, body, **constants):
    script = tmp_path / f"{name}.py"
    header = "".join(f"{k} = {v!r}\n" for k, v in constants.items())
    script.write_text(_COMMON + header + textwrap.dedent(body))
    proc = eh.run_in_fresh_process(vpffd.zip_path, str(_USER[0]), str(script))
    out = proc.stdout + proc.stderr
    reports = [json.loads(line.split(" ", 1)[1]) for line in proc.stdout.splitlines()
               if line.startswith("VPFFD-REPORT ")]
    assert reports, out[-4000:]
    return reports[-1], out


_USER = [None]


@pytest.fixture(autouse=True)
def _shared_user(_user):
    _USER[0] = _user


def _rig(vpffd, tmp_path, bind_frame=10, target="INPUT", bake=False, name="rig"):
    rig = str(tmp_path / "char_rig.blend")
    _run(vpffd, tmp_path, name, _RIG, REPO=eh.REPO_ROOT, RIG_FILE=rig, BIND_FRAME=bind_frame,
         TARGET=target, BAKE=bake)
    return rig


_LINK = '''
bpy.ops.wm.read_homefile(use_empty=True, use_factory_startup=True)
scene = bpy.context.scene
with bpy.data.libraries.load(RIG_FILE, link=True, relative=True) as (src, dst):
    dst.collections = ["Character"]
linked = dst.collections[0]
'''

_OVERRIDE = _LINK + '''
if HOW == "python":
    scene.collection.children.link(linked)
    override = linked.override_hierarchy_create(scene, bpy.context.view_layer)
    if linked.name in scene.collection.children:
        scene.collection.children.unlink(linked)
else:           # as a user does: a collection instance, then Object > Library Override > Make
    empty = bpy.data.objects.new("Character", None)
    empty.instance_type, empty.instance_collection = "COLLECTION", linked
    scene.collection.objects.link(empty)
    bpy.context.view_layer.objects.active = empty
    empty.select_set(True)
    with bpy.context.temp_override(active_object=empty, object=empty, selected_objects=[empty]):
        assert bpy.ops.object.make_override_library() == {"FINISHED"}
def local(name):
    return next(o for o in bpy.data.objects if o.name == name and o.override_library is not None)
body, twin, lat, arm = local("Body"), local("Twin"), local("Lattice"), local("Armature")
assert body.library is None and body.data.library is not None
before = measure(body, twin, (1, 7, 20))
helper = ops.node_group.get_input(vp_modifier(body), "Solver")
if ANIMATE:     # the shot animates the overridden lattice itself
    for f, s in ((1, 1.0), (20, 0.7)):
        lat.scale = (0.8 * s, 0.8 / s, 1.1)
        lat.keyframe_insert("scale", frame=f)
    # and poses the overridden Armature before VP-FFD
    bone = arm.pose.bones["Upper"]
    for f, angle in ((1, 0.0), (20, 0.5)):
        bone.rotation_euler = (angle, 0, 0)
        bone.keyframe_insert("rotation_euler", frame=f)
animated = measure(body, twin, (4, 16))
bpy.ops.wm.save_as_mainfile(filepath=SHOT_FILE)
report(before=before, animated=animated, helper_linked=helper.library is not None)
'''

_REOPEN = '''
bpy.ops.wm.open_mainfile(filepath=SHOT_FILE)
def local(name):
    return next(o for o in bpy.data.objects if o.name == name and o.override_library is not None)
body, twin = local("Body"), local("Twin")
after = measure(body, twin, (3, 13, 20))
scene = bpy.context.scene
rendered = []
if RENDER:      # an animation render, as `blender -b shot.blend -a` on a farm
    from bpy.app.handlers import persistent
    seen = {}
    @persistent
    def on_frame(scene, depsgraph=None):
        # the render's own depsgraph at the frame about to be rendered; VP-FFD's offsets are
        # written by its frame handler and evaluated after it, so the mesh is read at render_write
        if depsgraph is not None:
            seen["dg"] = depsgraph
    @persistent
    def on_write(scene, *args):
        dg = seen["dg"]
        e = body.evaluated_get(dg)
        me = e.to_mesh()
        co = np.empty(len(me.vertices) * 3, np.float32)
        me.vertices.foreach_get("co", co)
        e.to_mesh_clear()
        rendered.append(dict(frame=scene.frame_current, mode=dg.mode, co=co))
    bpy.app.handlers.frame_change_post.append(on_frame)
    bpy.app.handlers.render_write.append(on_write)
    cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
    cam.location, cam.rotation_euler = (0, -6, 0), (1.5708, 0, 0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x = scene.render.resolution_y = 16
    scene.render.filepath = RENDER_DIR + "/f_"
    scene.frame_start, scene.frame_end = 6, 15
    scene.frame_step = 9
    bpy.ops.render.render(animation=True)
    bpy.app.handlers.frame_change_post.remove(on_frame)
    bpy.app.handlers.render_write.remove(on_write)
    # each rendered frame against the viewport's at that frame: the same shape, and the volume
    # of what reaches the first VP-FFD modifier
    for r in rendered:
        scene.frame_set(r["frame"])
        a, t = evaluated(body)
        co = r.pop("co").reshape(-1, 3).astype(np.float64)
        r.update(shape=float(np.abs(co - a).max() / np.ptp(a, 0).max()),
                 volume=abs(triangle_volume(co, t) / input_volume(body) - 1))
scene.frame_set(20)
info = ops.status.status(body)
report(after=after, rendered=rendered, target_from=info.target_from, percent=info.input_percent)
'''


def _check(rows):
    for row in rows:
        assert row["deformers"] == 2 and row["error"] == [None, None], row
        assert row["shape"] <= SHAPE_TOL, row
        assert row["volume"] <= VOLUME_TOL, row


@pytest.mark.parametrize("how", ["python", "operator"])
def test_a_rig_bound_in_its_file_deforms_in_a_shot_that_overrides_it(vpffd, tmp_path, how):
    """Bound and saved at frame 10 in its own file, linked into a shot with a library override:
    every frame follows both lattices (None equals Blender's Lattice modifiers, XYZ keeps the
    volume), the shot's own keys on the overridden lattice and Armature too, again after
    reopening, and in an animation render of the reopened shot."""
    rig = _rig(vpffd, tmp_path)
    shot = str(tmp_path / "shot.blend")
    shown, _ = _run(vpffd, tmp_path, "shot", _OVERRIDE, RIG_FILE=rig, SHOT_FILE=shot, HOW=how,
                    ANIMATE=True)
    assert not shown["helper_linked"], "the override still writes into the library's helper"
    _check(shown["before"])
    _check(shown["animated"])
    reopened, _ = _run(vpffd, tmp_path, "reopen", _REOPEN, SHOT_FILE=shot, RENDER=how == "python",
                       RENDER_DIR=str(tmp_path / "frames"))
    _check(reopened["after"])
    if how == "python":
        assert [(r["frame"], r["mode"]) for r in reopened["rendered"]] == [(6, "RENDER"), (15, "RENDER")]
        for r in reopened["rendered"]:
            assert r["shape"] <= SHAPE_TOL and r["volume"] <= VOLUME_TOL, r
        assert sorted(p.name for p in (tmp_path / "frames").iterdir()) == ["f_0006.png", "f_0015.png"]


def test_a_shot_follows_its_rig_bound_again_in_its_file(vpffd, tmp_path):
    """Target: Bind keeps the volume saved at Bind in the rig file. The rig is bound again in
    its file at another frame (another volume to keep); the shot, reopened, keeps the new one."""
    rig = _rig(vpffd, tmp_path, bind_frame=1, target="BIND")
    shot = str(tmp_path / "shot.blend")
    _run(vpffd, tmp_path, "shot", _OVERRIDE, RIG_FILE=rig, SHOT_FILE=shot, HOW="python", ANIMATE=False)
    first, _ = _run(vpffd, tmp_path, "reopen", _REOPEN, SHOT_FILE=shot, RENDER=False)
    _rig(vpffd, tmp_path, bind_frame=20, target="BIND", name="rig_again")
    second, _ = _run(vpffd, tmp_path, "reopen_again", _REOPEN, SHOT_FILE=shot, RENDER=False)
    assert first["target_from"] == second["target_from"] == "bind"
    # The shape key grows the input by 1.2 (frames 1 -> 20). Bound at frame 1, frame 20's input
    # is 1.2^3 times the volume kept; bound again at frame 20 in the rig file, it is the volume.
    assert abs(first["percent"] / 100 - 1.2 ** 3) < 1e-3, first
    assert abs(second["percent"] / 100 - 1) < 1e-5, second


_INSTANCE = _LINK + '''
for k, x in enumerate((-3.0, 3.0)):
    empty = bpy.data.objects.new(f"Instance {k}", None)
    empty.instance_type, empty.instance_collection = "COLLECTION", linked
    empty.location.x = x
    scene.collection.objects.link(empty)
body = next(o for o in bpy.data.objects if o.name == "Body")
twin = next(o for o in bpy.data.objects if o.name == "Twin")
rows = []
for f in (1, 10, 20):
    scene.frame_set(f)
    dg = bpy.context.evaluated_depsgraph_get()
    # every instance of the body, in world space, against the same instance of the twin
    shapes = []
    for inst in dg.object_instances:
        if inst.is_instance and inst.object.type == "MESH" and inst.object.original in (body, twin):
            me = inst.object.to_mesh()
            co = np.empty(len(me.vertices) * 3, np.float32)
            me.vertices.foreach_get("co", co)
            inst.object.to_mesh_clear()
            m = np.array(inst.matrix_world)
            co = co.reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]
            shapes.append((inst.object.original.name, inst.parent.name, co))
    # what reaches the slot: the mesh grown by its shape key, 1 + 0.2 w times the basis
    w = body.data.shape_keys.key_blocks["Grow"].value
    basis = np.empty(len(body.data.vertices) * 3, np.float32)
    body.data.shape_keys.key_blocks["Basis"].data.foreach_get("co", basis)
    co = basis.reshape(-1, 3).astype(np.float64) * (1 + 0.2 * w)
    v_in = triangle_volume(co, evaluated(body)[1])
    rows.append(dict(frame=f, volume=volume(body) / v_in, error=errors(body),
                     shapes=[(a, p, c.tolist()) for a, p, c in shapes]))
report(rows=rows)
'''


def _instances(vpffd, tmp_path, rig):
    shown, out = _run(vpffd, tmp_path, "instance", _INSTANCE, RIG_FILE=rig)
    return shown["rows"], out


def test_a_plain_collection_instance_of_an_unbaked_rig_says_it_cannot_deform(vpffd, tmp_path):
    """Linked data is read-only: with no override, nothing VP-FFD solves can reach the mesh.
    The panel and the console say so, naming the object and what to do; never a silent shape."""
    rows, out = _instances(vpffd, tmp_path, _rig(vpffd, tmp_path))
    for row in rows:
        assert len(row["error"]) == 2, "both VP-FFD modifiers of the body say so"
        for error in row["error"]:
            assert error and "'Body' is linked from" in error, error
            assert "library override" in error and "point cache" in error
    said = [line for line in out.splitlines()
            if line.startswith("VP-FFD:") and "'Body' is linked from" in line]
    assert len(said) == len(set(said)) == 2, ("said once in the console for each VP-FFD modifier", said)


def test_a_rig_baked_in_its_file_plays_in_every_collection_instance(vpffd, tmp_path):
    """Baked in the rig file (Bake to Point Cache, a relative path), every instance plays the
    cache through Blender's Mesh Cache modifier: the corrected shape of each frame, keeping the
    volume of what reaches the slot (the mesh grown by its shape key)."""
    import numpy as np
    rig = _rig(vpffd, tmp_path, bake=True)
    rows, _ = _instances(vpffd, tmp_path, rig)
    for row in rows:
        assert not any(row["error"]), row
        bodies = [np.array(c) for name, _, c in row["shapes"] if name == "Body"]
        assert len(bodies) == 2, "both instances show the body"
        assert np.abs((bodies[0] - bodies[0].mean(0)) - (bodies[1] - bodies[1].mean(0))).max() < 1e-5
    for row in rows:
        assert abs(row["volume"] - 1) <= VOLUME_TOL, row["volume"]
