"""The installed extension in a headless Blender session: bind, frames, settings, bad input, files.

The extension is built into a zip and installed through Blender's own installer (conftest's
`vpffd` fixture). Volumes are measured here, independently, from the float32 coordinates of the
evaluated meshes; deformations are compared with real Lattice modifiers.
"""
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import vpffd_addon as core  # noqa: E402  (repository copy: only for building test meshes)

from . import extension_harness as eh
from .blender_ref import bind as _bind, evaluated_volume, evaluated_world, triangle_mesh

pytestmark = pytest.mark.blender

VOLUME_TOL = 1e-5


# ------------------------------------------------------------------------------------ helpers

def _mesh_object(name, verts, tris, location=(0, 0, 0)):
    ob = bpy.data.objects.new(name, triangle_mesh(verts, tris, name))
    ob.location = location
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _sphere(name="Ball", subdivisions=3, radius=0.8, location=(0, 0, 0)):
    v, f = core.icosphere(subdivisions, radius)
    return _mesh_object(name, v, f, location)


def _lattice(name="Lattice", shape=(4, 4, 4), interp="KEY_BSPLINE", scale=2.0 / 3.0, location=(0, 0, 0)):
    lt = bpy.data.lattices.new(name)
    lt.points_u, lt.points_v, lt.points_w = shape
    for a in "uvw":
        setattr(lt, f"interpolation_type_{a}", interp)
    ob = bpy.data.objects.new(name, lt)
    ob.scale = (scale,) * 3          # rest grid of a 4-point axis spans [-1.5, 1.5]
    ob.location = location
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _points(lat_ob, attr="co"):
    buf = np.empty(len(lat_ob.data.points) * 3, np.float32)
    lat_ob.data.points.foreach_get(attr, buf)
    return buf.reshape(-1, 3).astype(np.float64)


def _animate_squash(lat_ob, amount=0.6, frames=(1, 15, 30)):
    """Shape key squashing the lattice along its Z (towards z = 0): 0 -> amount -> 0."""
    lat_ob.shape_key_add(name="Basis")
    key = lat_ob.shape_key_add(name="Squash")
    co = _points(lat_ob)
    co[:, 2] *= 1.0 - amount
    co[:, :2] *= 1.0 + 0.1 * amount   # a little sideways bulge as well
    key.data.foreach_set("co", co.astype(np.float32).ravel())
    for f, v in zip(frames, (0.0, 1.0, 0.0)):
        key.value = v
        key.keyframe_insert("value", frame=f)
    return key


_evaluated = evaluated_world
_volume = evaluated_volume


def _mesh_co(ob):
    buf = np.empty(len(ob.data.vertices) * 3, np.float32)
    ob.data.vertices.foreach_get("co", buf)
    return buf


def _plain_copy(ob, lat_ob, name="Plain"):
    """A copy with its own mesh and a real Lattice modifier."""
    cp = ob.copy()
    cp.data = ob.data.copy()
    cp.name = name
    for m in list(cp.modifiers):
        cp.modifiers.remove(m)
    for a in list(cp.data.attributes):
        if a.name.startswith("vpffd"):
            cp.data.attributes.remove(a)
    bpy.context.scene.collection.objects.link(cp)
    mod = cp.modifiers.new("Lattice", "LATTICE")
    mod.object = lat_ob
    return cp, mod


@pytest.fixture
def ext(vpffd):
    eh.reset_scene()
    yield vpffd
    eh.reset_scene()


def _ops(ext):
    return ext.module.operators


# -------------------------------------------------------------------------------------- tests

def test_squash_keeps_volume_every_frame_while_the_lattice_modifier_loses_it(ext):
    ball = _sphere(subdivisions=3)
    lat = _lattice()
    _animate_squash(lat, amount=0.6)
    rest = _volume(ball)
    assert _bind(ball, lattice=lat, axes="XY") == {"FINISHED"}
    plain, _ = _plain_copy(ball, lat)
    scene = bpy.context.scene
    worst_plain = 1.0
    for f in range(1, 31):
        scene.frame_set(f)
        v = _volume(ball)
        assert abs(v / rest - 1.0) <= VOLUME_TOL, f"frame {f}: volume {v / rest:.8f} of rest"
        worst_plain = min(worst_plain, _volume(plain) / rest)
        info = _ops(ext).status.stats(ball)
        assert info.get("error") is None
        assert abs(info["volume_percent"] - 100.0) <= 100 * VOLUME_TOL
    assert worst_plain <= 0.8, f"plain Lattice modifier kept {worst_plain:.1%}: the test squash is too weak"


TRANSFORMS = {
    "identity": (None, None),
    "rotated_scaled": (((0.3, -0.2, 0.5), (1.2, 0.8, 1.1)), None),
    "negative_scale": (((0.0, 0.0, 0.7), (-1.0, 1.1, 0.9)), ((0.1, 0.2, -0.3), (1.0, -1.0, 1.0))),
    "parented": ("parent", "parent"),
}


@pytest.mark.parametrize("case", sorted(TRANSFORMS))
def test_no_correction_equals_the_lattice_modifier(ext, case):
    rng = np.random.default_rng(7)
    ball = _sphere(subdivisions=2, radius=0.9)
    lat = _lattice(interp="KEY_CATMULL_ROM")
    lt_co = _points(lat)
    moved = lt_co + rng.normal(0, 0.25, lt_co.shape)
    lat.data.points.foreach_set("co_deform", moved.astype(np.float32).ravel())
    weights = rng.uniform(0, 1, len(ball.data.vertices))
    weights[rng.random(len(weights)) < 0.2] = 0.0
    attr = ball.data.attributes.new("w", "FLOAT", "POINT")
    attr.data.foreach_set("value", weights.astype(np.float32))
    ball.data.attributes.active = attr
    with bpy.context.temp_override(object=ball, active_object=ball):
        assert bpy.ops.geometry.attribute_convert(mode="VERTEX_GROUP") == {"FINISHED"}
    group = ball.vertex_groups[0].name
    mesh_tf, lat_tf = TRANSFORMS[case]
    for ob, tf in ((ball, mesh_tf), (lat, lat_tf)):
        if tf == "parent":
            parent = bpy.data.objects.new("Parent_" + ob.name, None)
            bpy.context.scene.collection.objects.link(parent)
            parent.location = (0.2, -0.1, 0.3)
            parent.rotation_euler = (0.2, 0.4, -0.3)
            parent.scale = (1.1, 0.9, 1.0)
            ob.parent = parent
        elif tf is not None:
            ob.rotation_euler, ob.scale = tf
    plain, mod = _plain_copy(ball, lat)
    mod.vertex_group = group
    mod.invert_vertex_group = True
    mod.strength = 0.7
    assert _bind(ball, lattice=lat, axes="NONE", vertex_group=group, invert_vertex_group=True,
                 strength=0.7) == {"FINISHED"}
    bpy.context.scene.frame_set(1)
    ours, _ = _evaluated(ball)
    theirs, _ = _evaluated(plain)
    size = np.ptp(_evaluated(plain)[0], axis=0).max()
    assert np.abs(ours - theirs).max() <= 1e-5 * size


def test_unbind_restores_the_original_coordinates_bit_exactly(ext):
    ball = _sphere()
    lat = _lattice()
    _animate_squash(lat)
    before = _mesh_co(ball).tobytes()
    _bind(ball, lattice=lat)
    bpy.context.scene.frame_set(15)
    assert not np.array_equal(_evaluated(ball)[0], _evaluated(ball)[0] * 0)  # deformed
    with bpy.context.temp_override(object=ball, active_object=ball):
        assert bpy.ops.object.vpffd_unbind() == {"FINISHED"}
    assert _mesh_co(ball).tobytes() == before
    assert len(ball.modifiers) == 0
    assert not [a.name for a in ball.data.attributes if a.name.startswith("vpffd")]
    evaluated, _ = _evaluated(ball)
    np.testing.assert_array_equal(evaluated.astype(np.float32).ravel(), np.frombuffer(before, np.float32))


def test_apply_makes_the_current_shape_permanent(ext):
    ball = _sphere()
    lat = _lattice()
    _animate_squash(lat)
    _bind(ball, lattice=lat, axes="XY")
    bpy.context.scene.frame_set(15)
    shape, _ = _evaluated(ball)
    with bpy.context.temp_override(object=ball, active_object=ball):
        assert bpy.ops.object.vpffd_apply() == {"FINISHED"}
    assert len(ball.modifiers) == 0 and not ball.vpffd.is_bound
    np.testing.assert_allclose(_mesh_co(ball).reshape(-1, 3), shape, atol=1e-6)


def test_meshes_sharing_a_lattice_each_keep_their_volume(ext):
    a = _sphere("A", radius=0.5, location=(-0.4, 0, 0))
    b = _sphere("B", subdivisions=2, radius=0.35, location=(0.5, 0.2, 0))
    lat = _lattice()
    _animate_squash(lat, 0.5)
    rest = {ob.name: _volume(ob) for ob in (a, b)}
    for ob in (a, b):
        assert _bind(ob, lattice=lat, axes="XYZ") == {"FINISHED"}
    bpy.context.scene.frame_set(15)
    for ob in (a, b):
        assert abs(_volume(ob) / rest[ob.name] - 1) <= VOLUME_TOL


def test_settings_named_as_frame_inputs_reach_the_core_as_they_are(ext):
    """Every field of FrameInputs with a setting of its name is read from that setting (a new
    setting so named needs no line in frame_read.py); the ones the Blender layer computes keep
    their own values. Checked on the frame read for a bound mesh, after every such setting was
    changed from its default."""
    ops = _ops(ext)
    ball, lat = _sphere(), _lattice()
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    s = ball.vpffd
    named = ops.frame_read.same_named_settings(s)
    assert {"strength", "volume_scale", "cage_depth", "cage_outside"} <= set(named), named
    s.strength, s.volume_scale, s.cage_depth, s.cage_outside = 0.7, 1.2, 2, "STAY"
    depsgraph = bpy.context.evaluated_depsgraph_get()
    state = ops.bound.state_of(ball)
    frame = ops.frame_read.read(ops.deformers.first(ball), state, depsgraph, None)
    assert (frame.inputs.strength, frame.inputs.volume_scale, frame.inputs.cage_depth,
            frame.inputs.cage_outside) == (pytest.approx(0.7), pytest.approx(1.2), 2, "STAY")
    # Computed by frame_read.py, not read as they are: the lattice (a model, not the object),
    # the axes (World or lattice ones), Outside (a cage has its own).
    assert isinstance(frame.inputs.lattice, ext.module.vpffd_addon.Lattice) and frame.inputs.axes == "XYZ"


def test_volume_scale_is_animatable_and_world_axes_work(ext):
    ball = _sphere()
    lat = _lattice()
    lat.rotation_euler = (0.3, 0.5, 0.1)
    _animate_squash(lat, 0.4)
    rest = _volume(ball)
    _bind(ball, lattice=lat, axes="XY", space="WORLD")
    s = ball.vpffd
    s.volume_scale = 1.0
    s.keyframe_insert("volume_scale", frame=1)
    s.volume_scale = 1.3
    s.keyframe_insert("volume_scale", frame=30)
    scene = bpy.context.scene
    for f in (1, 10, 20, 30):
        scene.frame_set(f)
        target = s.volume_scale                      # the animated value at this frame
        assert (f == 1 and target == 1.0) or target > 1.0
        assert abs(_volume(ball) / rest - target) <= VOLUME_TOL * target
    # World X/Y corrections move vertices only in world X and Y: compare with lattice-axes result.
    world, _ = _evaluated(ball)
    s.space = "LATTICE"
    scene.frame_set(30)
    lattice_axes, _ = _evaluated(ball)
    assert np.abs(world - lattice_axes).max() > 1e-3


def test_pinned_vertex_group_follows_its_empty(ext):
    ball = _sphere()
    lat = _lattice()
    _animate_squash(lat, 0.3)
    co = _mesh_co(ball).reshape(-1, 3)
    top = np.flatnonzero(co[:, 2] > 0.7)
    group = ball.vertex_groups.new(name="Top")
    group.add(top.tolist(), 1.0, "REPLACE")
    empty = bpy.data.objects.new("Handle", None)
    bpy.context.scene.collection.objects.link(empty)
    rest = _volume(ball)
    assert _bind(ball, lattice=lat, axes="XYZ", pin_mode="GROUP", pin_vertex_group="Top",
                 pin_target=empty) == {"FINISHED"}
    empty.location = (0.0, 0.0, 0.15)
    bpy.context.scene.frame_set(15)
    got, _ = _evaluated(ball)
    want = co[top] + [0.0, 0.0, 0.15]
    assert np.abs(got[top] - want).max() <= 1e-4
    assert abs(_volume(ball) / rest - 1) <= VOLUME_TOL


def test_islands_keep_their_own_volumes(ext):
    v1, f1 = core.icosphere(2, 0.4, (-0.45, 0, 0))
    v2, f2 = core.icosphere(2, 0.3, (0.5, 0, 0.1))
    ob = _mesh_object("Pair", np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)]))
    lat = _lattice()
    co = _points(lat)
    co[:, 2] *= np.where(co[:, 0] < 0, 0.5, 1.0)     # squash only the left half
    lat.data.points.foreach_set("co_deform", co.astype(np.float32).ravel())
    assert _bind(ob, lattice=lat, axes="XYZ", use_islands=True) == {"FINISHED"}
    bpy.context.scene.frame_set(1)
    got, tris = _evaluated(ob)
    n = len(v1)
    for sel, verts, faces in ((slice(0, n), v1, f1), (slice(n, None), v2, f2)):
        rest = core.signed_volume(verts.astype(np.float32).astype(float), faces)
        now = core.signed_volume(got[sel], faces)
        assert abs(now / rest - 1) <= VOLUME_TOL


def test_toggle_like_a_modifier(ext):
    ball = _sphere()
    lat = _lattice()
    _animate_squash(lat)
    _bind(ball, lattice=lat)
    bpy.context.scene.frame_set(15)
    ball.vpffd.enabled = False
    mod = ext.module.operators.modifier.find(ball)
    assert not mod.show_viewport and not mod.show_render
    evaluated, _ = _evaluated(ball)
    np.testing.assert_array_equal(evaluated.astype(np.float32).ravel(), _mesh_co(ball))
    ball.vpffd.enabled = True
    assert not np.allclose(_evaluated(ball)[0].astype(np.float32).ravel(), _mesh_co(ball))


def test_bad_input_is_reported_and_nothing_is_lost(ext):
    ops = _ops(ext)
    ball = _sphere()
    lat = _lattice()
    _animate_squash(lat)
    original = _mesh_co(ball).tobytes()
    # Edit mode: binding is refused with a message.
    with bpy.context.temp_override(object=ball, active_object=ball):
        bpy.context.view_layer.objects.active = ball
        bpy.ops.object.mode_set(mode="EDIT")
        with pytest.raises(ops.lifecycle.BindError, match="Edit Mode"):
            ops.lifecycle.check_bindable(ball)
        bpy.ops.object.mode_set(mode="OBJECT")
    assert _bind(ball, lattice=lat) == {"FINISHED"}
    # Lattice renamed: still works. Lattice deleted: no exception, an error, the plain mesh.
    lat.name = "Renamed"
    bpy.context.scene.frame_set(10)
    assert ops.status.stats(ball).get("error") is None
    bpy.data.objects.remove(lat)
    bpy.context.scene.frame_set(11)
    assert "lattice" in ops.status.stats(ball)["error"]
    np.testing.assert_array_equal(_evaluated(ball)[0].astype(np.float32).ravel(), np.frombuffer(original, np.float32))
    # Topology edited after binding: the new topology is taken as it comes (no Re-bind), the
    # mesh's own coordinates stay intact.
    lat2 = _lattice("Lattice2")
    _animate_squash(lat2)
    ball.vpffd.lattice = lat2
    ball.data.vertices.add(1)
    rest = _volume(ball)
    bpy.context.scene.frame_set(15)
    assert ops.status.stats(ball).get("error") is None
    assert abs(_volume(ball) / rest - 1) <= VOLUME_TOL
    assert _mesh_co(ball)[:-3].tobytes() == original


def test_linked_duplicates_each_deform_their_own_placement(ext):
    """Alt-D: two objects share one mesh; each has its own VP-FFD modifier and solver helper, so
    each shows the solve for its own placement in the lattice (no Make Single User needed)."""
    ops = _ops(ext)
    ball = _sphere(radius=0.6)
    lat = _lattice()
    _animate_squash(lat)
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    twin = ball.copy()                       # copies the modifier (and its helper input) too
    bpy.context.scene.collection.objects.link(twin)
    twin.location = (0.3, 0.2, -0.1)
    plain, mod = _plain_copy(ball, lat)
    plain.location = twin.location
    scene = bpy.context.scene
    for f in (1, 8, 15):
        scene.frame_set(f)
        for ob in (ball, twin):
            assert ops.status.stats(ob).get("error") is None, f"{ob.name}: {ops.status.stats(ob).get('error')}"
        rest = ops.status.stats(twin)["input_volume"]
        assert abs(ops.status.stats(twin)["volume_percent"] - 100) <= 100 * VOLUME_TOL
    inputs = ext.module.operators.node_inputs
    helpers = {v for ob in (ball, twin) for v in inputs.values(ob.modifiers[-1]).values()
               if getattr(v, "type", None) == "MESH"}
    assert len(helpers) == 2, "each object has a solver helper of its own"
    ball.vpffd.axes = twin.vpffd.axes = "NONE"
    scene.frame_set(15)
    ours, theirs = _evaluated(twin)[0], _evaluated(plain)[0]
    assert np.abs(ours - theirs).max() <= 1e-5 * np.ptp(theirs, 0).max()
    assert rest > 0


def test_open_mesh_single_point_axis_and_outside_vertices_warn(ext):
    ops = _ops(ext)
    v, f = core.box(2, 1.6)
    ob = _mesh_object("OpenBox", v, f[2:])                     # two triangles removed: open
    lat = _lattice(shape=(3, 1, 3), scale=0.5)                 # narrower than the box: outside
    ob.vpffd.lattice = lat
    warnings = ops.lifecycle.bind(ob, bpy.context.evaluated_depsgraph_get())
    text = " ".join(warnings)
    assert "not closed" in text and "outside the lattice" in text and "single point" in text
    assert ops.status.stats(ob)["closed"] is False


def test_folded_lattice_reports_inverted_vertices_and_a_mirror_none(ext):
    """A mirror turns every vertex inside out alike: it mirrors space and folds nothing. Half the
    lattice mirrored onto the other half folds it: the vertices turned against the rest are
    inverted."""
    ops = _ops(ext)
    ball = _sphere(subdivisions=2, radius=0.45)
    lat = _lattice(shape=(2, 2, 2), interp="KEY_LINEAR", scale=2.0)
    co = _points(lat)
    co[:, 0] *= -1.0                                            # mirror: the map turns inside out
    lat.data.points.foreach_set("co_deform", co.astype(np.float32).ravel())
    ball.vpffd.lattice = lat
    ball.vpffd.axes = "NONE"
    warnings = ops.lifecycle.bind(ball, bpy.context.evaluated_depsgraph_get())
    assert ops.status.stats(ball)["folds"] == 0 and ops.status.stats(ball)["mirrored"]
    assert not any("inverted" in w for w in warnings)
    fold = _lattice(shape=(2, 2, 3), interp="KEY_LINEAR", scale=1.0)
    fold.scale = (1.0, 1.0, 0.5)
    co = _points(fold)
    co[co[:, 2] > 0, 0] *= -1.0          # the top layer mirrored in X: the upper half turns over
    fold.data.points.foreach_set("co_deform", co.astype(np.float32).ravel())
    ball.vpffd.lattice = fold
    warnings = ops.lifecycle.bind(ball, bpy.context.evaluated_depsgraph_get())
    folds = ops.status.stats(ball)["folds"]
    assert 0 < folds < len(ball.data.vertices) and not ops.status.stats(ball)["mirrored"]
    assert any(f"{folds:,} inverted" in w for w in warnings)


def test_saved_file_reopens_and_keeps_working(ext, tmp_path):
    ball = _sphere()
    lat = _lattice()
    _animate_squash(lat, 0.6)
    rest = _volume(ball)
    _bind(ball, lattice=lat, axes="XY")
    path = str(tmp_path / "bound.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    ball = bpy.data.objects["Ball"]
    assert ball.vpffd.is_bound
    for f in (7, 15, 22):
        bpy.context.scene.frame_set(f)
        assert abs(_volume(ball) / rest - 1) <= VOLUME_TOL
    assert bpy.context.scene.render.use_lock_interface


def test_renders_run_the_solver_with_the_render_depsgraph(ext, tmp_path):
    ops = _ops(ext)
    ball = _sphere()
    lat = _lattice()
    _animate_squash(lat, 0.6)
    _bind(ball, lattice=lat, axes="XY")
    scene = bpy.context.scene
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    scene.collection.objects.link(cam)
    cam.location = (0, -5, 0)
    cam.rotation_euler = (1.5708, 0, 0)
    scene.camera = cam
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x = scene.render.resolution_y = 32
    scene.render.filepath = str(tmp_path / "frame_")
    scene.frame_start, scene.frame_end = 14, 16
    bpy.ops.render.render(animation=True)
    for f in (14, 15, 16):
        assert (tmp_path / f"frame_{f:04d}.png").exists()
    assert ops.status.stats(ball).get("error") is None
    assert abs(ops.status.stats(ball)["volume_percent"] - 100) <= 100 * VOLUME_TOL


def test_renders_leave_what_they_do_not_render_as_the_viewport_shows_it(ext, tmp_path):
    """A bound mesh in a collection hidden from renders (the camera icon) or excluded from the
    view layer (the checkbox) is not rendered: the render neither solves nor clears it, and the
    viewport keeps its corrected shape with no error; a rendered one is solved as usual."""
    ops = _ops(ext)
    scene = bpy.context.scene
    lat = _lattice()
    _animate_squash(lat, 0.6)
    balls = {}
    for name in ("Rendered", "NoRender", "Excluded"):
        ball = balls[name] = _sphere()
        ball.name = name
        if name != "Rendered":
            coll = bpy.data.collections.new(f"{name} Collection")
            scene.collection.children.link(coll)
            scene.collection.objects.unlink(ball)
            coll.objects.link(ball)
        _bind(ball, lattice=lat, axes="XY")
    scene.frame_set(15)
    shown = {name: evaluated_world(ball)[0] for name, ball in balls.items()}
    bpy.data.collections["NoRender Collection"].hide_render = True
    bpy.context.view_layer.layer_collection.children["Excluded Collection"].exclude = True
    cam = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
    scene.collection.objects.link(cam)
    cam.location, cam.rotation_euler = (0, -5, 0), (1.5708, 0, 0)
    scene.camera = cam
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x = scene.render.resolution_y = 32
    scene.render.filepath = str(tmp_path / "frame_")
    scene.frame_start, scene.frame_end = 14, 16
    ops_pkg = ext.module.operators

    def helper_of(ob):
        return ops_pkg.solver_helper.helper(ob, ops_pkg.modifier.find(ob))
    during = []

    def record(scene, depsgraph=None):     # runs after VP-FFD's own frame handler
        if depsgraph is not None and depsgraph.mode == "RENDER":
            during.append({name: (ops.status.stats(ball).get("error"), len(helper_of(ball).data.vertices))
                           for name, ball in balls.items()})

    bpy.app.handlers.frame_change_post.append(record)
    try:
        bpy.ops.render.render(animation=True)
    finally:
        bpy.app.handlers.frame_change_post.remove(record)
    assert len(during) >= 3
    for seen in during:
        for name, (error, n_offsets) in seen.items():
            assert error is None and n_offsets == len(balls[name].data.vertices), (name, seen)
    scene.frame_set(15)
    for name in ("Rendered", "NoRender"):
        np.testing.assert_allclose(evaluated_world(balls[name])[0], shown[name], atol=1e-6)
    bpy.context.view_layer.layer_collection.children["Excluded Collection"].exclude = False
    scene.frame_set(15)
    np.testing.assert_allclose(evaluated_world(balls["Excluded"])[0], shown["Excluded"], atol=1e-6)
    assert ops.status.stats(balls["Excluded"]).get("error") is None


def test_bind_appends_the_modifier_and_rebind_leaves_it_where_the_user_put_it(ext):
    """Bind adds VP-FFD where Blender's Add Modifier would (the end of the stack), so a modifier
    already there comes before it and is deformed with the mesh; Re-bind does not move it."""
    mod_of = ext.module.operators.modifier.find
    ball = _sphere()
    ball.modifiers.new("Smooth", "SMOOTH").factor = 0.8            # a modifier already in the stack
    lat = _lattice()
    _animate_squash(lat, 0.5)
    _bind(ball, lattice=lat, axes="XYZ")
    assert ball.modifiers[-1] == mod_of(ball)
    bpy.context.scene.frame_set(15)
    vp_mod = mod_of(ball)
    vp_mod.show_viewport = False
    smoothed = _volume(ball)                    # what reaches the VP-FFD slot
    vp_mod.show_viewport = True
    assert abs(_volume(ball) / smoothed - 1) <= VOLUME_TOL
    with bpy.context.temp_override(object=ball, active_object=ball):
        bpy.ops.object.modifier_move_to_index(modifier=vp_mod.name, index=0)
    _bind(ball)                                  # Re-bind
    assert ball.modifiers[0] == mod_of(ball)
    # Move the vertices (as an Edit Mode session would): the new shape is taken as it comes.
    ball.modifiers["Smooth"].show_viewport = False
    co = _mesh_co(ball).reshape(-1, 3)
    co[:, 0] *= 1.3
    ball.data.vertices.foreach_set("co", co.astype(np.float32).ravel())
    ball.data.update()
    rest = core.signed_volume(co.astype(np.float32).astype(float),
                              core.icosphere(3, 0.8)[1])
    bpy.context.scene.frame_set(15)
    assert _ops(ext).status.stats(ball).get("error") is None
    assert abs(_volume(ball) / rest - 1) <= VOLUME_TOL


def test_overlay_geometry_is_the_corrected_lattice_in_world_space(ext):
    ball = _sphere()
    lat = _lattice(location=(0.3, 0.0, 0.2))
    _animate_squash(lat, 0.5)
    _bind(ball, lattice=lat, axes="XY", show_overlay=True)
    bpy.context.scene.frame_set(15)
    points, edges, label = _ops(ext).overlay.overlay_geometry(ball)
    assert len(points) == 64 and label.endswith("% volume")
    M = np.array(lat.matrix_world)
    deformed = _points(lat.evaluated_get(bpy.context.evaluated_depsgraph_get()), "co_deform")
    user = deformed @ M[:3, :3].T + M[:3, 3]
    moved = np.abs(points - user).max(1)
    assert moved.max() > 1e-3                     # the correction moved lattice points sideways
    assert np.abs((points - user)[:, 2]).max() <= 1e-6   # XY correction: no vertical motion
    lines = ext.module.operators.overlay.lines(points, edges)
    assert lines.shape == (2 * 3 * 4 * 4 * 3, 3)  # 3 axes x 16 rows x 3 segments, 2 ends each
    # Every segment joins two lattice neighbours: one grid step along one lattice axis.
    step = np.linalg.norm(lines[1::2] - lines[0::2], axis=1)
    assert step.min() > 0


def test_fold_attribute_holds_the_jacobian_determinant(ext):
    ball = _sphere(subdivisions=2, radius=0.45)                # inside the lattice: |x|, |y| < 0.5
    lat = _lattice(shape=(2, 2, 3), interp="KEY_LINEAR", scale=1.0)
    lat.scale = (1.0, 1.0, 0.5)                                # z grid: -0.5, 0, 0.5
    co = _points(lat)
    fold = co.copy()
    fold[co[:, 2] > 0, 0] *= -1.0          # the top layer mirrored in X: the upper half turns over
    lat.data.points.foreach_set("co_deform", fold.astype(np.float32).ravel())
    assert _bind(ball, lattice=lat, axes="NONE", use_fold_attribute=True) == {"FINISHED"}
    bpy.context.scene.frame_set(1)
    attr = ball.data.attributes["vpffd_jacobian"]
    det = np.empty(len(ball.data.vertices), np.float32)
    attr.data.foreach_get("value", det)
    z = _mesh_co(ball).reshape(-1, 3)[:, 2]
    # Linear interpolation: x scales by (1 - 2t) with t the height fraction inside the top cell,
    # so det < 0 exactly above its middle (grid z > 0.5), and > 0 below.
    grid_z = z / lat.scale[2]
    assert (det[grid_z > 0.52] < 0).all() and (det[grid_z < 0.48] > 0).all()
    assert _ops(ext).status.stats(ball)["folds"] == int((det <= 0).sum()) > 0
    with bpy.context.temp_override(object=ball, active_object=ball):
        bpy.ops.object.vpffd_unbind()
    assert "vpffd_jacobian" not in ball.data.attributes


def _squashed_bound_ball(ops):
    """(ball bound with XY correction, its lattice) at frame 15 of a squash, solved without error."""
    ball = _sphere()
    lat = _lattice()
    _animate_squash(lat, 0.5)
    _bind(ball, lattice=lat, axes="XY")
    bpy.context.scene.frame_set(15)
    assert ops.status.stats(ball).get("error") is None
    return ball, lat


def test_entering_and_leaving_edit_mode_unchanged_keeps_shape_and_figures(ext):
    ops = _ops(ext)
    ball, _ = _squashed_bound_ball(ops)
    shown = evaluated_world(ball)[0]
    bpy.context.view_layer.objects.active = ball
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.context.view_layer.update()
    info = ops.status.stats(ball)
    assert info.get("error") is None and info.get("editing") and "paused" not in info, info
    assert info.get("volume_percent") is not None, "the mesh as edited is solved live"
    bpy.ops.object.mode_set(mode="OBJECT")         # nothing moved: the inputs are as before
    bpy.context.view_layer.update()
    info = ops.status.stats(ball)
    assert info.get("error") is None and not info.get("editing")
    np.testing.assert_array_equal(evaluated_world(ball)[0], shown)


def test_switched_off_modifier_says_so_and_switching_on_solves_again(ext):
    ops = _ops(ext)
    ball, lat = _squashed_bound_ball(ops)
    ball.vpffd.lattice = None                      # an error while on ...
    bpy.context.view_layer.update()
    assert "lattice" in (ops.status.stats(ball).get("error") or "")
    ball.vpffd.enabled = False                     # ... is not kept once switched off
    bpy.context.view_layer.update()
    assert ops.status.stats(ball).get("switched_off") and ops.status.stats(ball).get("error") is None
    ball.vpffd.lattice = lat
    ball.vpffd.enabled = True
    bpy.context.view_layer.update()
    info = ops.status.stats(ball)
    assert not info.get("switched_off") and info.get("error") is None
    assert abs(info["volume_percent"] - 100) <= 100 * VOLUME_TOL


def test_vertices_outside_the_lattice_are_reported_while_they_are_outside(ext):
    """The panel's outside-the-lattice warning holds while the mesh is partly outside (counted
    here independently in lattice space) and goes when it is back inside."""
    ops = _ops(ext)
    ball, lat = _squashed_bound_ball(ops)
    assert not ops.status.stats(ball).get("outside")
    ball.location.x = 0.7                              # the ball (radius 0.8) pokes out at x = 1
    bpy.context.view_layer.update()
    co = np.array([v.co for v in ball.data.vertices], np.float64)
    to_lat = np.array(lat.matrix_world.inverted() @ ball.matrix_world)
    in_lat = co @ to_lat[:3, :3].T + to_lat[:3, 3]
    grid = _points(lat)                                 # rest grid in lattice space
    eps = 1e-6 * float(np.linalg.norm(grid.max(0) - grid.min(0)))
    expected = int(((in_lat < grid.min(0) - eps) | (in_lat > grid.max(0) + eps)).any(1).sum())
    info = ops.status.stats(ball)
    assert expected > 0 and info.get("outside") == expected
    assert "outside the lattice" in ops.status.outside_message(ops.status.status(ball), False)
    ball.location.x = 0.0
    bpy.context.view_layer.update()
    assert not ops.status.stats(ball).get("outside")


def test_nothing_stale_is_drawn_or_shown_while_switched_off(ext):
    ops = _ops(ext)
    ball, _ = _squashed_bound_ball(ops)
    ball.vpffd.show_overlay = True
    bpy.context.view_layer.update()
    assert ops.overlay.overlay_geometry(ball) is not None
    ball.vpffd.enabled = False
    bpy.context.view_layer.update()
    assert ops.overlay.overlay_geometry(ball) is None
    assert "volume_percent" not in ops.status.stats(ball)
    ball.vpffd.enabled = True
    bpy.context.view_layer.update()
    assert ops.overlay.overlay_geometry(ball) is not None and "volume_percent" in ops.status.stats(ball)


def test_a_new_problem_is_logged_once_as_a_vpffd_line(ext, capsys):
    """The console (and a farm's log) gets one `VP-FFD: <object>: <problem>` line per new problem,
    through the extension's own logger."""
    ops = _ops(ext)
    ball, lat = _squashed_bound_ball(ops)
    capsys.readouterr()
    ball.vpffd.lattice = None
    bpy.context.view_layer.update()
    bpy.context.scene.frame_set(16)
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("VP-FFD: ")]
    assert len(lines) == 1 and lines[0].startswith(f"VP-FFD: {ball.name}: ") and "lattice" in lines[0]


def test_a_lattice_that_mirrors_space_mirrors_the_mesh_and_keeps_the_size_of_its_volume(ext):
    """The lattice's points mirrored in Z (and squashed): Correction None gives the Lattice
    modifier's mirrored mesh (negative volume); XYZ keeps the volume's size with the mirrored sign,
    stays close to that mirrored shape (never turned inside out) and the panel says so."""
    ops = _ops(ext)
    ball = _sphere()
    rest = _volume(ball)
    lat = _lattice()
    co = _points(lat)
    co[:, 2] *= -0.8
    lat.data.points.foreach_set("co_deform", co.astype(np.float32).ravel())
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    bpy.context.view_layer.update()
    corrected, _ = _evaluated(ball)
    vol = _volume(ball)
    info = ops.status.stats(ball)
    assert vol < 0 and abs(abs(vol) / rest - 1) <= VOLUME_TOL, (vol, rest)
    assert abs(info["volume_percent"] / 100 - abs(vol) / rest) <= 1e-6
    assert any("mirrors space" in w for w in info["warnings"]), info["warnings"]
    ball.vpffd.axes = "NONE"
    bpy.context.view_layer.update()
    plain, _ = _evaluated(ball)
    size = float(np.ptp(plain, 0).max())
    assert float(np.abs(corrected - plain).max()) <= 0.15 * size, "close to the mirrored shape"


def test_folds_are_counted_on_every_update_up_to_5000_vertices_and_on_request_above(ext):
    ops = _ops(ext)
    lat = _lattice()
    co = _points(lat)
    top = co[:, 2] > co[:, 2].max() - 1e-6
    co[top, 2] = co[:, 2].min() + 0.4          # the top layer drops below the next one: a fold
    lat.data.points.foreach_set("co_deform", co.astype(np.float32).ravel())
    small = _sphere("Small", subdivisions=3)                         # 642 vertices
    big = _sphere("Big", subdivisions=6, location=(0.01, 0, 0))      # 40,962 vertices
    for ob in (small, big):
        assert _bind(ob, lattice=lat, axes="NONE") == {"FINISHED"}
    bpy.context.view_layer.update()
    assert ops.status.stats(small).get("folds", 0) > 0
    assert "folds" not in ops.status.stats(big), "above 5,000 vertices folds are counted on request"
    with bpy.context.temp_override(object=big, active_object=big, selected_objects=[big]):
        assert bpy.ops.object.vpffd_check_folds() == {"FINISHED"}
    assert ops.status.stats(big)["folds"] > 0
