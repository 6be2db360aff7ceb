"""Cages in Blender: made by the installed extension's operators, moved by shape keys,
hooks and direct edits, and checked against the core and against volumes measured independently
from the float32 coordinates Blender evaluates."""
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import vpffd_addon as core  # noqa: E402  (repository copy: the independent reference)

from .test_extension_blender import VOLUME_TOL, _bind, _evaluated, _mesh_object, _sphere, _volume
from . import extension_harness as eh

pytestmark = pytest.mark.blender


@pytest.fixture
def ext(vpffd):
    eh.reset_scene()
    yield vpffd
    eh.reset_scene()


def _select_only(*objects, active=None):
    for ob in bpy.context.view_layer.objects:
        ob.select_set(ob in objects)
    bpy.context.view_layer.objects.active = active or objects[-1]


def _co(ob, evaluated=False):
    src = ob.evaluated_get(bpy.context.evaluated_depsgraph_get()).data if evaluated else ob.data
    buf = np.empty(len(src.vertices) * 3, np.float32)
    src.vertices.foreach_get("co", buf)
    return buf.reshape(-1, 3).astype(np.float64)


def _cells(ext, cage_ob):
    return ext.module.operators.cage.cage_cells(cage_ob)


def _box_cage_around(ball, resolution=(2, 2, 2)):
    _select_only(ball)
    assert bpy.ops.object.vpffd_cage_add_box(resolution=resolution, margin=0.1) == {"FINISHED"}
    return bpy.context.view_layer.objects.active


def _squash_key(cage_ob, amount=0.5, frames=(1, 15, 30)):
    """Shape key squashing the cage along Z with a twist: 0 -> 1 -> 0 over the frames."""
    cage_ob.shape_key_add(name="Basis")
    key = cage_ob.shape_key_add(name="Squash")
    co = _co(cage_ob)
    a = 0.6 * co[:, 2]
    x, y = co[:, 0] * np.cos(a) - co[:, 1] * np.sin(a), co[:, 0] * np.sin(a) + co[:, 1] * np.cos(a)
    co = np.stack([x * (1 + 0.2 * amount), y, co[:, 2] * (1 - amount)], 1)
    key.data.foreach_set("co", co.astype(np.float32).ravel())
    for f, v in zip(frames, (0.0, 1.0, 0.0)):
        key.value = v
        key.keyframe_insert("value", frame=f)
    return key


def test_box_cage_squash_keeps_volume_every_frame_and_matches_the_core(ext):
    ball = _sphere(location=(0.2, -0.1, 0.3))
    ball.rotation_euler = (0.3, 0.1, 0.7)
    cage_ob = _box_cage_around(ball)
    assert len(_cells(ext, cage_ob)) == 8 and len(cage_ob.data.vertices) == 27
    cage_ob.rotation_euler = (0.0, 0.2, 0.4)   # a cage with its own transform
    _squash_key(cage_ob)
    rest = _volume(ball)
    rest_co = _co(ball)
    assert _bind(ball, lattice=cage_ob, axes="XYZ", cage_depth=2) == {"FINISHED"}
    ops = ext.module.operators
    for f in range(1, 31, 3):
        bpy.context.scene.frame_set(f)
        assert ops.status.stats(ball).get("error") is None
        assert abs(_volume(ball) / rest - 1) <= VOLUME_TOL, f
    # Plain cage FFD (no correction) against the core, fed with Blender's evaluated cage points.
    ball.vpffd.axes = "NONE"
    bpy.context.scene.frame_set(15)
    dg = bpy.context.evaluated_depsgraph_get()
    ops = ext.module.operators
    helper = ops.node_group.get_input(ops.modifier.find(ball), ops.node_group.SOLVER_INPUT)   # Bind saved it there
    cage_rest = np.array(helper["vpffd_cage_rest"]).reshape(-1, 3)
    cage = core.Cage(cage_rest, _cells(ext, cage_ob))
    M_cage = np.array(cage_ob.matrix_world)
    M_ball = np.array(ball.matrix_world)
    L = np.linalg.inv(M_cage) @ M_ball
    local = rest_co.astype(np.float32).astype(float) @ L[:3, :3].T + L[:3, 3]
    b = core.bind(cage, local, np.array([[0, 1, 2]]), depth=2)
    expected = b.deform(_co(cage_ob, evaluated=True)) @ M_cage[:3, :3].T + M_cage[:3, 3]
    got, _ = _evaluated(ball)
    assert np.abs(got - expected).max() <= 1e-5 * 3.0
    plain = _volume(ball)
    assert plain / rest < 0.9   # the squash does lose volume without the correction
    # At rest the mesh is where it was (the frame 1 key is 0).
    ball.vpffd.axes = "XYZ"
    bpy.context.scene.frame_set(1)
    assert np.abs(_evaluated(ball)[0] - (rest_co @ M_ball[:3, :3].T + M_ball[:3, 3])).max() <= 1e-5


def _disc_mesh(k=8):
    """A k-gon surrounded by a ring of quads, in the XY plane."""
    ang = np.arange(k) * 2 * np.pi / k
    pts = np.concatenate([np.stack([r * np.cos(ang), r * np.sin(ang), 0 * ang], 1) for r in (0.6, 1.2)])
    me = bpy.data.meshes.new("Disc")
    polys = [list(range(k))] + [[i, (i + 1) % k, k + (i + 1) % k, k + i] for i in range(k)]
    me.from_pydata(pts.tolist(), [], polys)
    me.update()
    ob = bpy.data.objects.new("Disc", me)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def test_extruded_disc_cage_follows_hooks_and_edits_and_survives_a_reload(ext, tmp_path):
    disc = _disc_mesh()
    _select_only(disc)
    assert bpy.ops.object.vpffd_cage_from_polygons(layers=3, thickness=2.4, direction="Z") == {"FINISHED"}
    cage_ob = bpy.context.view_layer.objects.active
    assert cage_ob is not disc and len(_cells(ext, cage_ob)) == 9 * 3
    co = _co(cage_ob)
    assert abs(co[:, 2].min() + 1.2) < 1e-6 and abs(co[:, 2].max() - 1.2) < 1e-6   # centred
    v, f = core.icosphere(3, 1.0)
    limb = _mesh_object("Limb", v * [0.7, 0.7, 1.05], f)
    rest = _volume(limb)
    assert _bind(limb, lattice=cage_ob, axes="XYZ", cage_depth=2) == {"FINISHED"}
    ops = ext.module.operators
    assert ops.status.stats(limb).get("error") is None
    # A hook on the top ring, driven by an Empty.
    empty = bpy.data.objects.new("Hook", None)
    bpy.context.scene.collection.objects.link(empty)
    top = np.flatnonzero(co[:, 2] > 1.0)
    group = cage_ob.vertex_groups.new(name="Top")
    group.add(top.tolist(), 1.0, "REPLACE")
    hook = cage_ob.modifiers.new("Hook", "HOOK")
    hook.object = empty
    hook.vertex_group = "Top"
    empty.location = (0.5, 0.0, -0.6)
    bpy.context.view_layer.update()
    assert np.abs(_co(cage_ob, evaluated=True) - co).max() > 0.4       # the hook moved the cage
    assert ops.status.stats(limb).get("error") is None
    assert abs(_volume(limb) / rest - 1) <= VOLUME_TOL
    moved = _evaluated(limb)[0]
    assert np.abs(moved - v * [0.7, 0.7, 1.05]).max() > 0.1
    # Editing the cage's own vertices moves the mesh too (the rest shape is kept per bound mesh).
    edited = co.copy()
    edited[top, 0] += 0.3
    cage_ob.data.vertices.foreach_set("co", edited.astype(np.float32).ravel())
    cage_ob.data.update()
    bpy.context.view_layer.update()
    assert abs(_volume(limb) / rest - 1) <= VOLUME_TOL
    after_edit = _evaluated(limb)[0]
    assert np.abs(after_edit - moved).max() > 0.05
    # The cells travel in the .blend: a reopened file deforms the same way with no action.
    path = str(tmp_path / "cage.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    limb = bpy.data.objects["Limb"]
    bpy.context.view_layer.update()
    bpy.context.scene.frame_set(1)
    assert ops.status.stats(limb).get("error") is None
    np.testing.assert_allclose(_evaluated(limb)[0], after_edit, atol=1e-5)


def test_fit_cage_encloses_the_selection(ext):
    ball = _sphere(radius=1.5, location=(3.0, 1.0, -2.0))
    _select_only(ball)
    bpy.ops.object.select_all(action="DESELECT")
    bpy.context.scene.cursor.location = (0, 0, 0)
    assert bpy.ops.object.vpffd_cage_add_box(resolution=(3, 1, 2), size=1.0) == {"FINISHED"}
    cage_ob = bpy.context.view_layer.objects.active
    _select_only(ball, cage_ob, active=cage_ob)
    assert bpy.ops.object.vpffd_cage_fit(margin=0.1) == {"FINISHED"}
    co = _co(cage_ob) + np.array(cage_ob.location)
    lo, hi = co.min(0), co.max(0)
    assert np.allclose(lo, [1.5 - 0.3, -0.5 - 0.3, -3.5 - 0.3], atol=1e-3)
    assert np.allclose(hi, [4.5 + 0.3, 2.5 + 0.3, -0.5 + 0.3], atol=1e-3)
    assert _bind(ball, lattice=cage_ob, axes="XY", cage_depth=1) == {"FINISHED"}
    assert ext.module.operators.status.stats(ball).get("error") is None


def test_bad_cages_report_clear_errors_and_lose_nothing(ext):
    ops = ext.module.operators
    ball = _sphere()
    original = _co(ball).copy()
    # A mesh that is not a cage.
    plain = _mesh_object("NotACage", *core.icosphere(1, 2.0))
    ball.vpffd.lattice = plain
    with pytest.raises(RuntimeError, match="'NotACage' is not a VP-FFD cage .it has no cells."):
        _bind(ball)
    # A cage whose stored cells are inside out.
    cage_ob = _box_cage_around(ball)
    cells = [tuple(tuple(reversed(f)) for f in faces) for faces in _cells(ext, cage_ob)]
    cage_ob.data["vpffd_cells"] = ext.module.vpffd_addon.cage_cells.encode_cells(cells)
    ball.vpffd.lattice = cage_ob
    with pytest.raises(RuntimeError, match="(?i)inverted"):
        _bind(ball)
    assert not ball.vpffd.is_bound
    # A good cage, bound; then a cage vertex is deleted.
    cage_ob.data["vpffd_cells"] = ext.module.vpffd_addon.cage_cells.encode_cells(
        [tuple(tuple(reversed(f)) for f in faces) for faces in cells])
    assert _bind(ball, axes="XYZ", cage_depth=1) == {"FINISHED"}
    bpy.context.view_layer.objects.active = cage_ob
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.select_all(action="DESELECT")
    bpy.ops.object.mode_set(mode="OBJECT")
    cage_ob.data.vertices[26].select = True
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.delete(type="VERT")
    bpy.ops.object.mode_set(mode="OBJECT")
    bpy.context.view_layer.update()
    bpy.context.scene.frame_set(2)
    error = ops.status.stats(ball).get("error") or ""
    assert "cage" in error and "vertices" in error
    assert np.isfinite(_evaluated(ball)[0]).all()
    assert np.array_equal(_co(ball), original)       # the mesh's own coordinates are untouched
    with bpy.context.temp_override(object=ball, active_object=ball, selected_objects=[ball]):
        assert bpy.ops.object.vpffd_unbind() == {"FINISHED"}
    assert np.array_equal(_co(ball), original)


def test_overlay_draws_the_corrected_cage_and_folds_are_counted(ext):
    ops = ext.module.operators
    ball = _sphere()
    cage_ob = _box_cage_around(ball, resolution=(2, 1, 1))
    _squash_key(cage_ob, amount=0.6)
    assert _bind(ball, lattice=cage_ob, axes="XY", cage_depth=1, show_overlay=True) == {"FINISHED"}
    bpy.context.scene.frame_set(15)
    points, edges, label = ops.overlay.overlay_geometry(ball)
    assert len(points) == len(cage_ob.data.vertices) and len(edges) == len(cage_ob.data.edges)
    assert label.endswith("% volume")
    M = np.array(cage_ob.matrix_world)
    user = _co(cage_ob, evaluated=True) @ M[:3, :3].T + M[:3, 3]
    assert np.abs(points - user).max() > 1e-3                 # the correction moved the cage
    assert np.abs((points - user)[:, 2]).max() <= 1e-6        # XY: no vertical motion
    assert ops.status.stats(ball)["folds"] == 0
    # Fold the cage: one end of its top layer pushed through the bottom (the whole top layer
    # pushed through would be a mirror, which folds nothing).
    co = _co(cage_ob)
    top = (co[:, 2] > co[:, 2].mean()) & (co[:, 0] > co[:, 0].mean())
    co[top, 2] = co[:, 2].min() - 0.5
    ball.vpffd.axes = "NONE"
    cage_ob.shape_key_clear()
    cage_ob.data.vertices.foreach_set("co", co.astype(np.float32).ravel())
    cage_ob.data.update()
    bpy.context.scene.frame_set(1)
    assert 0 < ops.status.stats(ball)["folds"] < len(ball.data.vertices), ops.status.stats(ball)


def test_cage_follows_edit_mode_and_an_armature(ext):
    import bmesh
    ops = ext.module.operators
    v, f = core.icosphere(3, 0.5)
    limb = _mesh_object("Limb", v * [1.0, 1.0, 1.8], f)
    _select_only(limb)
    assert bpy.ops.object.vpffd_cage_add_box(resolution=(1, 1, 3), margin=0.15) == {"FINISHED"}
    cage_ob = bpy.context.view_layer.objects.active
    rest = _volume(limb)
    assert _bind(limb, lattice=cage_ob, axes="XYZ", cage_depth=2) == {"FINISHED"}
    before = _evaluated(limb)[0]
    # Edit Mode: move the top ring of the cage with bmesh, as a grab would, and update.
    bpy.context.view_layer.objects.active = cage_ob
    bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(cage_ob.data)
    top = max(vert.co.z for vert in bm.verts)
    for vert in bm.verts:
        if vert.co.z > top - 1e-6:
            vert.co.x += 0.4
    bmesh.update_edit_mesh(cage_ob.data)
    bpy.context.view_layer.update()
    edited = _evaluated(limb)[0]
    assert ops.status.stats(limb).get("error") is None
    assert np.abs(edited - before).max() > 0.1
    assert abs(_volume(limb) / rest - 1) <= VOLUME_TOL
    bpy.ops.object.mode_set(mode="OBJECT")
    # An armature bending the upper half of the cage.
    arm = bpy.data.objects.new("Rig", bpy.data.armatures.new("Rig"))
    bpy.context.scene.collection.objects.link(arm)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    bone = arm.data.edit_bones.new("Upper")
    bone.head, bone.tail = (0, 0, 0), (0, 0, 1)
    bpy.ops.object.mode_set(mode="OBJECT")
    co = _co(cage_ob)
    group = cage_ob.vertex_groups.new(name="Upper")
    group.add(np.flatnonzero(co[:, 2] > 0.1).tolist(), 1.0, "REPLACE")
    mod = cage_ob.modifiers.new("Armature", "ARMATURE")
    mod.object = arm
    arm.pose.bones["Upper"].rotation_mode = "XYZ"
    arm.pose.bones["Upper"].rotation_euler = (0.6, 0, 0)
    bpy.context.view_layer.update()
    bent = _evaluated(limb)[0]
    assert ops.status.stats(limb).get("error") is None
    assert np.abs(bent - edited).max() > 0.1
    assert abs(_volume(limb) / rest - 1) <= VOLUME_TOL


@pytest.mark.parametrize("kind", ["cage", "lattice"])
def test_renders_deform_with_the_cage_or_lattice_hidden_from_render(ext, kind, tmp_path):
    """F12 evaluates a render depsgraph of its own: a cage or lattice hidden from renders must still
    be evaluated there (the VP-FFD modifier names it as a dependency), or the render shows the mesh
    undeformed while the viewport shows it deformed."""
    ball = _sphere(radius=0.6)
    if kind == "cage":
        control = _box_cage_around(ball, resolution=(2, 2, 2))
        _squash_key(control, amount=0.6)
        settings = dict(lattice=control, axes="NONE", cage_depth=1)
    else:
        from .test_extension_blender import _animate_squash, _lattice
        control = _lattice()
        _animate_squash(control, 0.6)
        settings = dict(lattice=control, axes="NONE")
    assert _bind(ball, **settings) == {"FINISHED"}
    control.hide_render = True
    scene = bpy.context.scene
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    scene.collection.objects.link(cam)
    cam.location = (0, -6, 0)
    cam.rotation_euler = (1.5708, 0, 0)
    scene.camera = cam
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x = scene.render.resolution_y = 64
    scene.render.film_transparent = True
    areas = {}
    for frame in (1, 15):
        scene.frame_set(frame)
        path = str(tmp_path / f"{kind}_{frame}.png")
        scene.render.filepath = path
        bpy.ops.render.render(write_still=True)
        img = bpy.data.images.load(path)
        px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
        img.pixels.foreach_get(px)
        areas[frame] = int((px.reshape(-1, 4)[:, 3] > 0.5).sum())
    # The squash flattens the ball to 40% of its height: its silhouette shrinks a lot.
    assert areas[15] < 0.8 * areas[1], areas


def test_mobility_group_of_the_cage_keeps_unassigned_points_still(ext):
    ops = ext.module.operators
    ball = _sphere()
    cage_ob = _box_cage_around(ball, resolution=(2, 2, 2))
    _squash_key(cage_ob, amount=0.5)
    co = _co(cage_ob)
    free = np.flatnonzero(co[:, 0] > co[:, 0].mean() - 1e-6)           # the +X half may move
    cage_ob.vertex_groups.new(name="Free").add(free.tolist(), 1.0, "REPLACE")
    rest = _volume(ball)
    assert _bind(ball, lattice=cage_ob, axes="XYZ", cage_depth=2, mobility_group="Free",
                 show_overlay=True) == {"FINISHED"}
    bpy.context.scene.frame_set(15)
    assert ops.status.stats(ball).get("error") is None
    assert abs(_volume(ball) / rest - 1) <= VOLUME_TOL
    points, _, _ = ops.overlay.overlay_geometry(ball)
    M = np.array(cage_ob.matrix_world)
    user = _co(cage_ob, evaluated=True) @ M[:3, :3].T + M[:3, 3]
    moved = np.abs(points - user).max(1)
    fixed = np.setdiff1d(np.arange(len(co)), free)
    assert moved[fixed].max() <= 1e-9 and moved[free].max() > 1e-3


@pytest.mark.parametrize("seed", range(4))
def test_random_cages_and_deformations_keep_the_volume_in_blender(ext, seed):
    """Random cages (jittered boxes, extruded discs of random polygons) as cage objects, deformed
    by random shape keys: the evaluated mesh (float32) keeps its volume to 1e-5."""
    rng = np.random.default_rng(seed)
    cage_mod = ext.module.operators.cage
    if seed % 2 == 0:
        box = core.box_cage(tuple(int(n) for n in rng.integers(1, 4, 3)), ((-1.0,) * 3, (1.0,) * 3))
        points = box.rest_points + rng.uniform(-0.08, 0.08, (box.n_points, 3))
        cells = box.cells
    else:
        k = int(rng.integers(3, 8))
        ang = np.arange(k) * 2 * np.pi / k + rng.uniform(-0.15, 0.15, k) * 2 * np.pi / k
        disc = np.concatenate([np.stack([r * np.cos(ang), r * np.sin(ang), 0 * ang], 1) for r in (0.6, 1.3)])
        polys = [list(range(k))] + [[i, (i + 1) % k, k + (i + 1) % k, k + i] for i in range(k)]
        points, cells = core.extrude(disc - [0, 0, 1.0], polys, (0, 0, 2.0), int(rng.integers(1, 4)))
    cage_ob = cage_mod.cage_object("Random Cage", points, cells)
    bpy.context.scene.collection.objects.link(cage_ob)
    cage_ob.location = rng.normal(0, 0.5, 3)
    cage_ob.rotation_euler = rng.uniform(-1, 1, 3)
    ball = _sphere(radius=0.45)
    ball.location = cage_ob.location
    ball.rotation_euler = rng.uniform(-1, 1, 3)
    cage_ob.shape_key_add(name="Basis")
    key = cage_ob.shape_key_add(name="Random")
    moved = np.asarray(points) + rng.normal(0, 0.18, np.shape(points))
    key.data.foreach_set("co", moved.astype(np.float32).ravel())
    key.value = 0.0
    key.keyframe_insert("value", frame=1)
    key.value = 1.0
    key.keyframe_insert("value", frame=5)
    rest = _volume(ball)
    bpy.context.scene.frame_set(1)       # the cage's rest shape is the one shown when binding
    axes = ["XYZ", "XY", "Z", "YZ"][seed]
    assert _bind(ball, lattice=cage_ob, axes=axes, cage_depth=int(rng.integers(1, 4)),
                 volume_scale=float(rng.uniform(0.8, 1.2))) == {"FINISHED"}
    ops = ext.module.operators
    scale = ball.vpffd.volume_scale
    for frame in range(1, 6):
        bpy.context.scene.frame_set(frame)
        info = ops.status.stats(ball)
        assert info.get("error") is None, info
        assert not info.get("warnings"), info
        assert abs(_volume(ball) / (scale * rest) - 1) <= VOLUME_TOL, (frame, _volume(ball) / rest)
