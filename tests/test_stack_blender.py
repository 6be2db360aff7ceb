"""VP-FFD anywhere in a modifier stack, headless: it deforms what reaches its slot.

For each kind of modifier before it (Armature with a bending bone, animated mesh shape keys,
Subdivision Surface, Simple Deform, another Lattice) and a Subdivision Surface after it, on every
frame of an animation:
- Correction None equals a real Lattice modifier in the same slot of a twin object;
- with XYZ, the volume of the slot's output equals the volume that reaches the slot, both measured
  here on evaluated meshes (the input on a twin that stops before the slot, the output with the
  modifiers after the slot switched off), and the panel's figure is that ratio.
Also: vertex-group weights repainted after Bind, the lattice's own vertex group, and the lattice's
Edit Mode (points moved with `transform.resize`, a Mobility Group set).
"""
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import vpffd_addon as core  # noqa: E402  (repository copy: only for building test meshes)

from . import extension_harness as eh
from .blender_ref import (bind as _bind, bone_weights_by_height, evaluated_volume,
                          evaluated_world, squash_lattice, triangle_mesh, two_bone_armature)

pytestmark = pytest.mark.blender

FRAMES = (1, 7, 14, 20)
SHAPE_TOL = 1e-5      # of the object's size
VOLUME_TOL = 1e-5     # relative
PANEL_TOL = 1e-6      # relative, panel figure against the measured ratio


def _ops(ext):
    return ext.module.operators


# ----------------------------------------------------------------------------------- the scene

def _lattice():
    """A 4x4x4 B-spline lattice around the mesh whose shape key squashes it (frames 1 -> 20)."""
    ob, key = squash_lattice("Lattice", (4, 4, 4), (0.8, 0.8, 1.1), 0.55, 0.3, shear=0.2)
    for f, v in ((1, 0.0), (20, 1.0)):
        key.value = v
        key.keyframe_insert("value", frame=f)
    return ob


def _capsule_mesh(subdivisions=5):
    v, f = core.icosphere(subdivisions, 0.7)        # 10,242 vertices at 5
    v = v * (1.0, 1.0, 1.5)
    return v, f


def _object(name, subdivisions=5):
    v, f = _capsule_mesh(subdivisions)
    ob = bpy.data.objects.new(name, triangle_mesh(v, f, name))
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _shape_keys(ob):
    ob.shape_key_add(name="Basis")
    key = ob.shape_key_add(name="Bulge")
    co = np.empty(len(ob.data.vertices) * 3, np.float32)
    ob.data.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    co[:, :2] *= (1.0 + 0.35 * np.exp(-4 * co[:, 2:3] ** 2))
    key.data.foreach_set("co", co.ravel())
    for f, value in ((1, 0.0), (20, 1.0)):
        key.value = value
        key.keyframe_insert("value", frame=f)


def _second_lattice(cache={}):
    ob = bpy.data.objects.get("Before")
    if ob is None:
        lt = bpy.data.lattices.new("Before")
        lt.points_u = lt.points_v = lt.points_w = 3
        ob = bpy.data.objects.new("Before", lt)
        ob.scale = (1.6, 1.6, 2.4)
        bpy.context.scene.collection.objects.link(ob)
        co = np.empty(27 * 3, np.float32)
        lt.points.foreach_get("co", co)
        co = co.reshape(-1, 3)
        co += np.random.default_rng(5).normal(0, 0.08, co.shape)
        lt.points.foreach_set("co_deform", co.ravel())
        for f, x in ((1, 0.0), (20, 0.4)):
            ob.location = (x, 0, 0)
            ob.keyframe_insert("location", frame=f)
    return ob


def _before(ob, kind):
    """Add the modifiers (or shape keys) that come before the VP-FFD slot."""
    if kind == "armature":
        bone_weights_by_height(ob, 0.35)
        mod = ob.modifiers.new("Armature", "ARMATURE")
        mod.object = bpy.data.objects.get("Rig") or two_bone_armature("Rig", 1.2)
    elif kind == "shape_keys":
        _shape_keys(ob)
    elif kind == "subsurf_before":
        ob.modifiers.new("Subdivision", "SUBSURF").levels = 1
    elif kind == "simple_deform":
        mod = ob.modifiers.new("Bend", "SIMPLE_DEFORM")
        mod.deform_method = "BEND"
        mod.deform_axis = "Z"
        for f, angle in ((1, 0.0), (20, 1.2)):
            mod.angle = angle
            mod.keyframe_insert("angle", frame=f)
    elif kind == "lattice_before":
        ob.modifiers.new("Before", "LATTICE").object = _second_lattice()


def _copy_beside():
    """A Geometry Nodes group that joins its geometry with a copy of it moved aside (a mirror or
    array rig does much the same): after the slot it copies VP-FFD's tap too, after the slot's own."""
    ng = bpy.data.node_groups.get("Copy Beside")
    if ng is None:
        ng = bpy.data.node_groups.new("Copy Beside", "GeometryNodeTree")
        ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
        gin, gout = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
        move = ng.nodes.new("GeometryNodeTransform")
        move.inputs["Translation"].default_value = (3.0, 0.0, 0.0)
        join = ng.nodes.new("GeometryNodeJoinGeometry")
        ng.links.new(gin.outputs[0], move.inputs["Geometry"])
        ng.links.new(gin.outputs[0], join.inputs[0])
        ng.links.new(move.outputs[0], join.inputs[0])
        ng.links.new(join.outputs[0], gout.inputs[0])
    return ng


def _after(ob, kind):
    if kind == "subsurf_after":
        ob.modifiers.new("Subdivision After", "SUBSURF").levels = 1
    if kind == "copied_after":
        ob.modifiers.new("Copy Beside", "NODES").node_group = _copy_beside()


KINDS = ("armature", "shape_keys", "subsurf_before", "simple_deform", "lattice_before", "subsurf_after",
         "copied_after")


def _vpffd_object(kind, lattice, **settings):
    ob = _object("VPFFD_" + kind)
    _before(ob, kind)
    assert _bind(ob, lattice=lattice, **settings) == {"FINISHED"}
    _after(ob, kind)
    return ob


def _lattice_twin(kind, lattice, subdivisions=5, **modifier_settings):
    ob = _object("Twin_" + kind, subdivisions)
    _before(ob, kind)
    mod = ob.modifiers.new("Lattice", "LATTICE")
    mod.object = lattice
    for k, v in modifier_settings.items():
        setattr(mod, k, v)
    _after(ob, kind)
    return ob


def _input_twin(kind):
    """The same object with the stack cut at the VP-FFD slot: its evaluated mesh is the input."""
    ob = _object("Input_" + kind)
    _before(ob, kind)
    return ob


# ------------------------------------------------------------------------------- measurements

_evaluated = evaluated_world
_volume = evaluated_volume


def _slot_output_volume(ob):
    """Volume of the VP-FFD slot's output: the object's evaluated mesh with the modifiers after
    the slot switched off (they are switched on again)."""
    after = []
    seen = False
    for m in ob.modifiers:
        if seen and m.show_viewport:
            after.append(m)
        seen = seen or (m.type == "NODES" and m.name.startswith("VP-FFD"))
    for m in after:
        m.show_viewport = False
    try:
        return _volume(ob)
    finally:
        for m in after:
            m.show_viewport = True


# ------------------------------------------------------------------------------------- tests

@pytest.mark.parametrize("kind", KINDS)
def test_correction_none_equals_a_lattice_modifier_in_the_same_slot(ext, kind):
    lat = _lattice()
    ours = _vpffd_object(kind, lat, axes="NONE")
    twin = _lattice_twin(kind, lat)
    source = _input_twin(kind)
    _after(source, kind)             # the same stack without the slot
    scene = bpy.context.scene
    moved = 0.0
    for f in FRAMES + (3,):          # and back in time: nothing carries over
        scene.frame_set(f)
        assert _ops(ext).status.stats(ours).get("error") is None, _ops(ext).status.stats(ours)["error"]
        a, _ = _evaluated(ours)
        b, _ = _evaluated(twin)
        size = float(np.ptp(b, 0).max())
        assert a.shape == b.shape
        assert np.abs(a - b).max() <= SHAPE_TOL * size, f"frame {f}"
        moved = max(moved, float(np.abs(b - _evaluated(source)[0]).max()))
    assert moved > 0.05, "the lattice must move the mesh"


@pytest.mark.parametrize("kind", KINDS)
def test_xyz_keeps_the_volume_that_reaches_the_slot_on_every_frame(ext, kind):
    lat = _lattice()
    ours = _vpffd_object(kind, lat, axes="XYZ")
    plain = _lattice_twin(kind, lat)
    source = _input_twin(kind)
    scene = bpy.context.scene
    worst_plain = 0.0
    volumes_in = []
    for f in range(1, 21):
        scene.frame_set(f)
        info = _ops(ext).status.stats(ours)
        assert info.get("error") is None, info.get("error")
        v_in = _volume(source)
        v_out = _slot_output_volume(ours)
        volumes_in.append(v_in)
        assert abs(v_out / v_in - 1) <= VOLUME_TOL, f"frame {f}: {v_out / v_in:.8f}"
        assert abs(info["volume_percent"] / 100 - v_out / v_in) <= PANEL_TOL, f"frame {f}"
        if kind != "subsurf_after":
            worst_plain = max(worst_plain, abs(_volume(plain) / v_in - 1))
    if kind != "subsurf_after":
        assert worst_plain > 0.05, "the plain lattice must change the volume for this test to mean anything"
    if kind in ("shape_keys", "armature", "simple_deform", "lattice_before"):
        assert np.ptp(volumes_in) > 0, "the input animates"


def _repaint(ob, name, weights):
    g = ob.vertex_groups.get(name) or ob.vertex_groups.new(name=name)
    for i, w in enumerate(weights):
        g.add([i], float(w), "REPLACE")
    ob.data.update()


@pytest.mark.parametrize("invert", [False, True])
def test_weights_repainted_after_bind_and_the_lattices_own_group_follow_live(ext, invert):
    rng = np.random.default_rng(11)
    lat = _lattice()
    ours = _object("Ours")
    twin = _object("Twin")
    n = len(ours.data.vertices)
    first = rng.uniform(0, 1, n)
    for ob in (ours, twin):
        _repaint(ob, "W", first)
    assert _bind(ours, lattice=lat, axes="NONE", vertex_group="W", invert_vertex_group=invert,
                 strength=0.8) == {"FINISHED"}
    mod = twin.modifiers.new("Lattice", "LATTICE")
    mod.object, mod.vertex_group, mod.invert_vertex_group, mod.strength = lat, "W", invert, 0.8
    scene = bpy.context.scene

    def check(f, what):
        scene.frame_set(f)
        a, b = _evaluated(ours)[0], _evaluated(twin)[0]
        assert np.abs(a - b).max() <= SHAPE_TOL * np.ptp(b, 0).max(), what

    check(14, "at bind")
    second = rng.uniform(0, 1, n)
    for ob in (ours, twin):
        _repaint(ob, "W", second)
    check(15, "weights repainted after Bind")
    group = lat.vertex_groups.new(name="LW")
    lw = rng.uniform(0, 1, len(lat.data.points))
    lw[::3] = 0.0
    for i, w in enumerate(lw):
        if w > 0:
            group.add([i], float(w), "REPLACE")
    lat.data.vertex_group = "LW"
    check(16, "the lattice's own vertex group")
    ours.vpffd.axes = "XYZ"
    scene.frame_set(17)
    ours.modifiers[-1].show_viewport = False
    v_in = _volume(ours)
    ours.modifiers[-1].show_viewport = True
    assert abs(_volume(ours) / v_in - 1) <= VOLUME_TOL


def test_lattice_edit_mode_follows_live_with_a_mobility_group(ext):
    """Tab into the lattice with a Mobility Group set (this crashed Blender), move points with
    the transform operator: the meshes follow without leaving Edit Mode."""
    lat = _lattice()
    group = lat.vertex_groups.new(name="Mobile")
    for i in range(len(lat.data.points)):
        group.add([i], 0.25 + 0.75 * (i % 2), "REPLACE")
    plain = _object("Plain")
    keep = _object("Keep")
    twin = _lattice_twin("none", lat)
    source = _input_twin("none")
    assert _bind(plain, lattice=lat, axes="NONE", mobility_group="Mobile") == {"FINISHED"}
    assert _bind(keep, lattice=lat, axes="XYZ", mobility_group="Mobile") == {"FINISHED"}
    scene = bpy.context.scene
    scene.frame_set(1)
    rest = _volume(keep)
    view_layer = bpy.context.view_layer
    for ob in view_layer.objects:
        ob.select_set(ob == lat)
    view_layer.objects.active = lat
    with bpy.context.temp_override(object=lat, active_object=lat, selected_objects=[lat],
                                   selected_editable_objects=[lat]):
        assert bpy.ops.object.mode_set(mode="EDIT") == {"FINISHED"}
        try:
            assert lat.data.is_editmode
            bpy.ops.lattice.select_all(action="DESELECT")
            bpy.ops.lattice.select_random(ratio=0.5, seed=3)
            assert bpy.ops.transform.resize(value=(1.3, 1.0, 0.6)) == {"FINISHED"}
            assert bpy.ops.transform.translate(value=(0.1, 0.0, -0.05)) == {"FINISHED"}
            for ob in (plain, keep):
                assert _ops(ext).status.stats(ob).get("error") is None, _ops(ext).status.stats(ob)["error"]
            a, b = _evaluated(plain)[0], _evaluated(twin)[0]
            assert np.abs(b - _evaluated(source)[0]).max() > 0.02, "the edit moves the mesh"
            assert np.abs(a - b).max() <= SHAPE_TOL * np.ptp(b, 0).max()
            assert abs(_volume(keep) / rest - 1) <= VOLUME_TOL
            assert lat.data.is_editmode
        finally:
            bpy.ops.object.mode_set(mode="OBJECT")
    scene.frame_set(2)
    assert _ops(ext).status.stats(keep).get("error") is None
    assert abs(_volume(keep) / rest - 1) <= VOLUME_TOL


def test_undo_keeps_the_binding(ext):
    """After an undo with unchanged inputs the cached binding is reused (no re-embedding)."""
    ops = _ops(ext)
    lat = _lattice()
    ob = _object("Ball")
    assert _bind(ob, lattice=lat, axes="XYZ") == {"FINISHED"}
    bpy.context.scene.frame_set(10)
    state = ops.bound.state_of(ob)
    binding = state.binding
    ext.module.operators.handlers.on_undo()
    assert ops.bound.state_of(ob).binding is binding
    assert ops.status.stats(ob).get("rebound") is False


def test_save_as_shape_key_holds_the_slots_result(ext):
    """Blender cannot apply a Geometry Nodes modifier as a shape key: VP-FFD's own operator saves
    the current result; the key, at value 1 with VP-FFD switched off, shows the same shape."""
    lat = _lattice()
    ob = _object("Ball")
    assert _bind(ob, lattice=lat, axes="XY") == {"FINISHED"}
    bpy.context.scene.frame_set(14)
    shown, _ = _evaluated(ob)
    with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
        assert bpy.ops.object.vpffd_save_shape_key() == {"FINISHED"}
    key = ob.data.shape_keys.key_blocks["VP-FFD"]
    key.value = 1.0
    ob.vpffd.enabled = False
    keyed, _ = _evaluated(ob)
    assert np.abs(keyed - shown).max() <= 1e-6 * np.ptp(shown, 0).max()
    assert np.abs(keyed - _evaluated(_input_twin("none"))[0]).max() > 0.05


def test_a_copied_vpffd_modifier_gets_its_own_settings_and_deforms_nothing_until_bound(ext):
    """Duplicate on a VP-FFD modifier: the copy gets settings of its own (those of the one copied,
    not bound) and its own slot, and adds nothing; the original deforms as before (equal to a twin
    with one VP-FFD modifier)."""
    ops = _ops(ext)
    lat = _lattice()
    ob, twin = _object("Ball"), _object("Twin")
    for o in (ob, twin):
        assert _bind(o, lattice=lat, axes="XYZ", volume_scale=1.1) == {"FINISHED"}
    with bpy.context.temp_override(object=ob, active_object=ob):
        assert bpy.ops.object.modifier_copy(modifier=ob.modifiers[-1].name) == {"FINISHED"}
    bpy.context.scene.frame_set(14)
    copy = ops.modifier.find_all(ob)[-1]
    s = ops.deformers.settings_of(ob, copy)
    assert s is not None and s != ob.vpffd and not s.is_bound
    assert s.lattice == lat and s.axes == "XYZ" and s.volume_scale == pytest.approx(1.1)
    assert ops.status.stats(ob).get("error") is None
    shown, reference = _evaluated(ob)[0], _evaluated(twin)[0]
    np.testing.assert_allclose(shown, reference, rtol=0, atol=1e-6 * np.ptp(reference, 0).max())
    assert np.abs(shown - _evaluated(_input_twin("none"))[0]).max() > 0.05   # it does deform
    ob.modifiers.remove(copy)
    bpy.context.scene.frame_set(15)
    assert ops.status.stats(ob).get("error") is None
    assert [d.settings for d in ops.deformers.all_of(ob)] == [ob.vpffd]


def test_subdivision_before_and_after_the_slot_still_keeps_the_volume(ext):
    """A Subdivision Surface both before and after VP-FFD: neither the mesh nor the end of the
    stack has the slot's vertex count, so the modifier passes its input's triangles along; the
    slot's output keeps the volume that reaches it, and Correction None is the Lattice modifier.
    Pins are off when modifiers before VP-FFD change the vertex count."""
    lat = _lattice()
    ours = _object("Ours", 3)
    ours.modifiers.new("Before", "SUBSURF").levels = 1
    assert _bind(ours, lattice=lat, axes="XYZ") == {"FINISHED"}
    ours.modifiers.new("After", "SUBSURF").levels = 1
    twin = _object("Twin", 3)
    twin.modifiers.new("Before", "SUBSURF").levels = 1
    twin.modifiers.new("Lattice", "LATTICE").object = lat
    twin.modifiers.new("After", "SUBSURF").levels = 1
    source = _object("Source", 3)
    source.modifiers.new("Before", "SUBSURF").levels = 1
    # As the window does after a change: the handler asks for the faces, Blender evaluates again.
    # The update that finds the faces missing shows the plain deformation and says so.
    bpy.context.view_layer.update()
    assert any("faces that reach VP-FFD are not known yet" in w
               for w in _ops(ext).status.stats(ours)["warnings"]), _ops(ext).status.stats(ours)
    bpy.context.view_layer.update()
    assert ext.module.operators.node_group.get_input(ours.modifiers["VP-FFD"], "Tap Faces") is True
    scene = bpy.context.scene
    for f in (14, 7):
        scene.frame_set(f)
        info = _ops(ext).status.stats(ours)
        assert info.get("error") is None and not info["warnings"], info
        assert abs(info["volume_percent"] - 100) <= 100 * VOLUME_TOL
        ours.modifiers["After"].show_viewport = False
        v_out = _volume(ours)
        ours.modifiers["After"].show_viewport = True
        assert abs(v_out / _volume(source) - 1) <= VOLUME_TOL, f"frame {f}"
    ours.vpffd.axes = "NONE"
    scene.frame_set(14)
    a, b = _evaluated(ours)[0], _evaluated(twin)[0]
    assert np.abs(a - b).max() <= SHAPE_TOL * np.ptp(b, 0).max()

    pinned = _object("Pinned", 3)
    pinned.modifiers.new("Before", "SUBSURF").levels = 1
    target = bpy.data.objects.new("Target", None)
    bpy.context.scene.collection.objects.link(target)
    assert _bind(pinned, lattice=lat, axes="XYZ", pin_mode="VERTEX", pin_vertex=3,
                 pin_target=target) == {"FINISHED"}
    bpy.context.scene.frame_set(15)
    info = _ops(ext).status.stats(pinned)
    assert info.get("error") is None
    assert any("pins are off" in w for w in info["warnings"]), info["warnings"]
    pinned.modifiers[-1].show_viewport = False
    v_in = _volume(pinned)
    pinned.modifiers[-1].show_viewport = True
    assert abs(_volume(pinned) / v_in - 1) <= VOLUME_TOL


def test_a_geometry_nodes_modifier_that_drops_point_clouds_is_reported(ext):
    lat = _lattice()
    ob = _object("Ball")
    assert _bind(ob, lattice=lat, axes="XYZ") == {"FINISHED"}
    ng = bpy.data.node_groups.new("Mesh Only", "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin, gout = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    split = ng.nodes.new("GeometryNodeSeparateComponents")
    ng.links.new(gin.outputs[0], split.inputs[0])
    ng.links.new(split.outputs["Mesh"], gout.inputs[0])
    ob.modifiers.new("Mesh Only", "NODES").node_group = ng
    source = _input_twin("none")
    bpy.context.scene.frame_set(14)
    assert "nothing reaches VP-FFD's slot" in _ops(ext).status.stats(ob)["error"]
    np.testing.assert_array_equal(_evaluated(ob)[0], _evaluated(source)[0])   # undeformed, not stale


def _overridden_character(tmp_path):
    """A rigged character ("Body" bent by "Rig") saved in a library file, linked into an empty
    scene with a library override; returns the override's mesh object (its mesh stays linked)."""
    library = str(tmp_path / "character.blend")
    body = _object("Body", 3)
    _before(body, "armature")
    character = bpy.data.collections.new("Character")
    bpy.context.scene.collection.children.link(character)
    for ob in (body, bpy.data.objects["Rig"]):
        bpy.context.scene.collection.objects.unlink(ob)
        character.objects.link(ob)
        # As a character saved where VP-FFD never looked at it: no VP-FFD settings on its objects
        # (the update reads them on every object of the scene, which makes them).
        ob.property_unset("vpffd")
        ob.property_unset("vpffd_extra")
    bpy.ops.wm.save_as_mainfile(filepath=library)
    eh.reset_scene()
    bpy.context.scene.frame_set(1)

    with bpy.data.libraries.load(library, link=True) as (src, dst):
        dst.collections = ["Character"]
    linked = dst.collections[0]
    scene = bpy.context.scene
    scene.collection.children.link(linked)
    override = linked.override_hierarchy_create(scene, bpy.context.view_layer)
    if linked.name in scene.collection.children:
        scene.collection.children.unlink(linked)
    body = next(ob for ob in override.all_objects if ob.type == "MESH")
    assert body.override_library is not None and body.data.library is not None
    return body


def test_a_library_override_of_a_linked_character_binds_and_deforms(ext, tmp_path):
    """A rigged character linked from another file with a library override: its mesh stays linked
    (nothing of it can be written), and VP-FFD binds, deforms like a Lattice modifier, keeps the
    volume, and does so again after saving and reopening the shot."""
    body = _overridden_character(tmp_path)
    override = body.users_collection[0]
    lat = _lattice()
    settings = dict(lattice=lat, axes="XYZ")
    assert _bind(body, **settings) == {"FINISHED"}
    twin = _lattice_twin("armature", lat, 3)
    twin.modifiers["Armature"].object = next(ob for ob in override.all_objects if ob.type == "ARMATURE")

    def check(f, body, twin):
        scene = bpy.context.scene
        scene.frame_set(f)
        assert _ops(ext).status.stats(body).get("error") is None, _ops(ext).status.stats(body)["error"]
        vp_mod = body.modifiers[-1]
        vp_mod.show_viewport = False
        v_in = _volume(body)
        vp_mod.show_viewport = True
        assert abs(_volume(body) / v_in - 1) <= VOLUME_TOL, f"frame {f}"
        body.vpffd.axes = "NONE"
        scene.frame_set(f)
        a, b = _evaluated(body)[0], _evaluated(twin)[0]
        body.vpffd.axes = "XYZ"
        assert np.abs(a - b).max() <= SHAPE_TOL * np.ptp(b, 0).max(), f"frame {f}"

    check(14, body, twin)
    # The character's file has no VP-FFD settings on its objects: what the override changed is
    # kept setting by setting, also when the reopened shot is saved again.
    shot = str(tmp_path / "shot.blend")
    for f in (17, 9):
        bpy.ops.wm.save_as_mainfile(filepath=shot)
        bpy.ops.wm.open_mainfile(filepath=shot)
        body = bpy.data.objects["Body"]
        twin = bpy.data.objects["Twin_armature"]
        assert body.vpffd.is_bound and body.vpffd.lattice is not None and body.data.library is not None
        assert body.override_library.reference.library is not None
        check(f, body, twin)


def test_a_library_override_keeps_the_volume_at_bind(ext, tmp_path):
    """Target: Bind on a linked character's override: bound in the rest pose, the bent frames
    get the rest volume back, also after saving and reopening the shot (the volume at Bind is
    kept with the override, its mesh still linked)."""
    body = _overridden_character(tmp_path)
    rest = _volume(body)                       # frame 1: the rest pose reaches the slot
    assert _bind(body, lattice=_lattice(), axes="XYZ", target="BIND") == {"FINISHED"}

    def check(f, body):
        bpy.context.scene.frame_set(f)
        info = _ops(ext).status.status(body)
        assert info.error is None and info.target_from == "bind", info
        assert abs(info.input_percent - 100) > 0.1, info    # the bend changed the volume
        assert abs(_volume(body) / rest - 1) <= VOLUME_TOL, f"frame {f}"

    check(14, body)
    shot = str(tmp_path / "shot.blend")
    bpy.ops.wm.save_as_mainfile(filepath=shot)
    bpy.ops.wm.open_mainfile(filepath=shot)
    body = bpy.data.objects["Body"]
    assert body.vpffd.target == "BIND" and body.data.library is not None
    check(17, body)
