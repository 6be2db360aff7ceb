"""Several VP-FFD deformers on one mesh, headless, added and bound as a user does (Add Modifier >
Deform > VP-FFD Lattice, Bind in the panel of the one shown, Lattice Deform Selected on a mesh that
has one):

- with Correction None, two VP-FFD modifiers equal two Blender Lattice modifiers in the same slots
  of a twin, on every frame, bare and in a rig's stack (Armature before, Subdivision after), and
  after reordering the stack;
- with XYZ each keeps the volume of what reaches it: measured here on evaluated meshes (the first
  slot's output with the second modifier switched off), and the panel's figures agree;
- with Target: Bind on both, the stack keeps the volume at Bind under an Armature's bend;
- save and open, undo and redo, Unbind, Apply and Delete of one deformer's lattice act on that
  deformer only; an F12 animation render solves the second deformer from the first one's result
  of the frame rendered, not of the frame shown before.
"""
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import vpffd_addon as core  # noqa: E402  (repository copy: only for building test meshes)

from .blender_ref import (bind as _bind, bone_weights_by_height, evaluated_volume,  # noqa: E402
                          evaluated_world, squash_lattice, triangle_mesh, two_bone_armature)

pytestmark = pytest.mark.blender

FRAMES = (1, 8, 14, 20)
SHAPE_TOL = 1e-5      # of the object's size
VOLUME_TOL = 1e-5     # relative


def _ops(ext):
    return ext.module.operators


def _lattices():
    """Two animated B-spline lattices: "Head" around the top of the capsule, "Belly" around its
    middle; they overlap, so the second deforms part of what the first deformed."""
    head, key_h = squash_lattice("Head", (4, 4, 3), (1.7, 1.7, 1.0), 0.6, 0.35, shear=0.25)
    head.location = (0.05, 0.0, 0.65)
    belly, key_b = squash_lattice("Belly", (3, 3, 4), (1.8, 1.8, 1.3), 0.7, 0.3)
    belly.location = (0.0, 0.05, -0.1)
    belly.rotation_euler = (0.0, 0.0, 0.4)
    for key, frames in ((key_h, (1, 20)), (key_b, (4, 17))):
        for f, value in zip(frames, (0.0, 1.0)):
            key.value = value
            key.keyframe_insert("value", frame=f)
    return head, belly


def _capsule(name, subdivisions=4):
    v, f = core.icosphere(subdivisions, 0.7)        # 2,562 vertices at 4
    ob = bpy.data.objects.new(name, triangle_mesh(v * (1.0, 1.0, 1.6), f, name))
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _rig(ob):
    bone_weights_by_height(ob, 0.35)
    mod = ob.modifiers.new("Armature", "ARMATURE")
    mod.object = bpy.data.objects.get("Rig") or two_bone_armature("Rig", 1.3)


def _user(ob, *selected):
    return bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob, *selected])


def _add_and_bind(ext, ob, lattice, **settings):
    """Add Modifier > Deform > VP-FFD Lattice with `lattice` selected too, then Bind in the panel
    (which names the modifier it shows). Returns the new modifier."""
    with _user(ob, lattice):
        assert bpy.ops.object.vpffd_modifier_add() == {"FINISHED"}
    mod = ob.modifiers.active
    ops = _ops(ext)
    d = ops.deformers.shown(ob)
    assert d.mod == mod and d.settings.lattice == lattice, "the panel shows the one added"
    for k, v in settings.items():
        setattr(d.settings, k, v)
    with _user(ob):
        assert bpy.ops.object.vpffd_bind(modifier=mod.name) == {"FINISHED"}
    return mod


def _two_deformers(ext, name, head, belly, rig=False, subsurf=False, **settings):
    """A capsule with [Armature], VP-FFD (Head), VP-FFD (Belly), [Subdivision]: the first bound as
    scripts do (ob.vpffd, Bind), the second added from the Add Modifier menu."""
    ob = _capsule(name)
    if rig:
        _rig(ob)
    assert _bind(ob, lattice=head, **settings) == {"FINISHED"}
    _add_and_bind(ext, ob, belly, **settings)
    if subsurf:
        ob.modifiers.new("Subdivision", "SUBSURF").levels = 1
    return ob


def _lattice_twin(name, lattices, rig=False, subsurf=False):
    ob = _capsule(name)
    if rig:
        _rig(ob)
    for lat in lattices:
        ob.modifiers.new(lat.name, "LATTICE").object = lat
    if subsurf:
        ob.modifiers.new("Subdivision", "SUBSURF").levels = 1
    return ob


def _input_twin(name, rig=False):
    ob = _capsule(name)
    if rig:
        _rig(ob)
    return ob


def _same_shape(ob, twin):
    a, b = evaluated_world(ob)[0], evaluated_world(twin)[0]
    assert a.shape == b.shape
    return float(np.abs(a - b).max() / np.ptp(b, 0).max())


def _with_off(mods, measure):
    """`measure()` with the modifiers `mods` switched off in the viewport (then on again)."""
    for m in mods:
        m.show_viewport = False
    try:
        return measure()
    finally:
        for m in mods:
            m.show_viewport = True


def render_frame(frame, tmp_path, capture, camera=None):
    """An F12 animation render of scene frame `frame` alone (Workbench, 32 x 32, through `camera`,
    or a new one looking at the origin from -Y); returns [what `capture()` returned when the frame
    was written]."""
    scene = bpy.context.scene
    if camera is None:
        camera = bpy.data.objects.new("Cam", bpy.data.cameras.new("Cam"))
        scene.collection.objects.link(camera)
    camera.location, camera.rotation_euler = (0, -6, 0), (1.5708, 0, 0)
    scene.camera = camera
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x = scene.render.resolution_y = 32
    scene.render.filepath = str(tmp_path / "frame_")
    scene.frame_start = scene.frame_end = frame
    written = []

    def snapshot(*_args):
        written.append(capture())

    bpy.app.handlers.render_write.append(snapshot)
    try:
        bpy.ops.render.render(animation=True)
    finally:
        bpy.app.handlers.render_write.remove(snapshot)
    return written


# ------------------------------------------------------------------------------------- tests

@pytest.mark.parametrize("rig", [False, True], ids=["bare", "rig_and_subdivision"])
def test_two_lattices_with_correction_none_equal_two_lattice_modifiers(ext, rig):
    head, belly = _lattices()
    ob = _two_deformers(ext, "Ours", head, belly, rig=rig, subsurf=rig, axes="NONE")
    twin = _lattice_twin("Twin", (head, belly), rig=rig, subsurf=rig)
    ops = _ops(ext)
    assert len(ops.deformers.bound(ob)) == 2
    plain = _lattice_twin("Input", (), rig=rig, subsurf=rig)
    for f in FRAMES:
        bpy.context.scene.frame_set(f)
        assert _same_shape(ob, twin) <= SHAPE_TOL, f"frame {f}"
        for d in ops.deformers.bound(ob):
            assert ops.status.status(d).error is None, (f, d.mod.name, ops.status.status(d))
    assert _same_shape(ob, plain) > 0.02            # it does deform


@pytest.mark.parametrize("rig", [False, True], ids=["bare", "rig"])
def test_each_deformer_keeps_the_volume_that_reaches_it(ext, rig):
    """XYZ on both: the first slot's output keeps the input's volume, the second keeps the first's
    output's, so the stack keeps the input's; the panel's figure of each is the measured one."""
    head, belly = _lattices()
    ob = _two_deformers(ext, "Ours", head, belly, rig=rig, axes="XYZ")
    source = _input_twin("Input", rig=rig)
    plain = _lattice_twin("Plain", (head, belly), rig=rig)
    ops = _ops(ext)
    first, second = ops.deformers.bound(ob)
    for f in FRAMES[1:]:
        bpy.context.scene.frame_set(f)
        reached = evaluated_volume(source)
        after_first = _with_off([second.mod], lambda: evaluated_volume(ob))
        after_both = evaluated_volume(ob)
        assert abs(after_first / reached - 1) <= VOLUME_TOL, f
        assert abs(after_both / reached - 1) <= VOLUME_TOL, f
        assert abs(evaluated_volume(plain) / reached - 1) > 0.01, "the lattices do change the volume"
        for d in (first, second):
            info = ops.status.status(d)
            assert info.error is None and abs(info.volume_percent - 100) <= 100 * VOLUME_TOL, (f, info)


def test_target_bind_on_both_keeps_the_volume_at_bind_under_a_bend(ext):
    head, belly = _lattices()
    source = _input_twin("Input", rig=True)
    bpy.context.scene.frame_set(1)      # the rig unbent, as it was made
    ob = _two_deformers(ext, "Ours", head, belly, rig=True, axes="XYZ", target="BIND")
    at_bind = evaluated_volume(ob)
    assert abs(at_bind / evaluated_volume(source) - 1) <= VOLUME_TOL
    for f in (10, 20):
        bpy.context.scene.frame_set(f)
        assert abs(evaluated_volume(source) / at_bind - 1) > 1e-3, "the bend changes the volume"
        assert abs(evaluated_volume(ob) / at_bind - 1) <= VOLUME_TOL, f


def test_reordering_the_stack_follows_the_slots(ext):
    head, belly = _lattices()
    ob = _two_deformers(ext, "Ours", head, belly, axes="NONE")
    twin = _lattice_twin("Twin", (belly, head))
    with _user(ob):
        bpy.ops.object.modifier_move_to_index(modifier=ob.modifiers[-1].name, index=0)
    ops = _ops(ext)
    assert [d.settings.lattice for d in ops.deformers.bound(ob)] == [belly, head]
    for f in (8, 20):
        bpy.context.scene.frame_set(f)
        assert _same_shape(ob, twin) <= SHAPE_TOL, f


def test_the_panel_follows_the_active_modifier_and_says_which(ext):
    head, belly = _lattices()
    ob = _two_deformers(ext, "Ours", head, belly, axes="XYZ")
    ops = _ops(ext)
    first, second = ops.modifier.find_all(ob)
    ob.modifiers.active = first
    d = ops.deformers.shown(ob)
    assert d.settings == ob.vpffd and d.settings.lattice == head
    assert ops.deformers.label(d) == f"'{first.name}' (1 of 2)"
    ob.modifiers.active = second
    d = ops.deformers.shown(ob)
    assert d.settings.lattice == belly and ops.deformers.label(d) == f"'{second.name}' (2 of 2)"
    # A setting changed in the panel changes that deformer only.
    d.settings.volume_scale = 1.2
    bpy.context.scene.frame_set(9)
    source = _input_twin("Input")
    ratio = evaluated_volume(ob) / evaluated_volume(source)
    assert abs(ratio - 1.2) <= VOLUME_TOL * 1.2
    assert ops.status.status(ops.deformers.first(ob)).volume_percent == pytest.approx(100, abs=1e-3)


def test_lattice_deform_selected_on_a_bound_mesh_adds_another(ext):
    head, _ = _lattices()
    ob = _capsule("Ours")
    assert _bind(ob, lattice=head, axes="XYZ") == {"FINISHED"}
    with _user(ob):
        assert bpy.ops.object.vpffd_lattice_deform_selected(resolution=3) == {"FINISHED"}
    ops = _ops(ext)
    found = ops.deformers.bound(ob)
    assert len(found) == 2 and found[0].settings.lattice == head
    fitted = found[1].settings.lattice
    assert fitted is not None and fitted.type == "LATTICE" and fitted != head
    assert ops.status.status(found[1]).error is None


def test_save_and_open_keeps_both(ext, tmp_path):
    head, belly = _lattices()
    ob = _two_deformers(ext, "Ours", head, belly, axes="NONE")
    _lattice_twin("Twin", (head, belly))
    path = str(tmp_path / "two.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    ob, twin = bpy.data.objects["Ours"], bpy.data.objects["Twin"]
    ops = _ops(ext)
    found = ops.deformers.bound(ob)
    assert [d.settings.lattice.name for d in found] == ["Head", "Belly"]
    for f in (8, 20):
        bpy.context.scene.frame_set(f)
        assert _same_shape(ob, twin) <= SHAPE_TOL, f


def test_undo_and_redo_of_the_second_bind(ext):
    head, belly = _lattices()
    ob = _capsule("Ours")
    twin_one = _lattice_twin("One", (head,))
    twin_two = _lattice_twin("Two", (head, belly))
    bpy.context.scene.frame_set(12)
    assert _bind(ob, lattice=head, axes="NONE") == {"FINISHED"}
    bpy.ops.ed.undo_push(message="first")
    _add_and_bind(ext, ob, belly, axes="NONE")
    bpy.ops.ed.undo_push(message="second")
    assert _same_shape(ob, twin_two) <= SHAPE_TOL
    bpy.ops.ed.undo()
    ob = bpy.data.objects["Ours"]
    bpy.context.view_layer.update()
    ops = _ops(ext)
    assert len(ops.deformers.bound(ob)) == 1
    assert _same_shape(ob, bpy.data.objects["One"]) <= SHAPE_TOL
    bpy.ops.ed.redo()
    ob = bpy.data.objects["Ours"]
    bpy.context.view_layer.update()
    assert len(ops.deformers.bound(ob)) == 2
    assert _same_shape(ob, bpy.data.objects["Two"]) <= SHAPE_TOL


def test_unbind_apply_and_delete_act_on_one_deformer(ext):
    head, belly = _lattices()
    ob = _two_deformers(ext, "Ours", head, belly, axes="NONE")
    ops = _ops(ext)
    bpy.context.scene.frame_set(14)
    first, second = ops.modifier.find_all(ob)
    # Unbind the second: the first deforms alone.
    with _user(ob):
        assert bpy.ops.object.vpffd_unbind(modifier=second.name) == {"FINISHED"}
    assert len(ops.modifier.find_all(ob)) == 1 and len(ops.deformers.bound(ob)) == 1
    assert _same_shape(ob, _lattice_twin("One", (head,))) <= SHAPE_TOL
    # Bind one again, then Apply the first: its shape becomes the mesh's, the second stays.
    second = _add_and_bind(ext, ob, belly, axes="NONE")
    bpy.context.scene.frame_set(14)
    shown = evaluated_world(ob)[0]
    with _user(ob):
        assert bpy.ops.object.vpffd_apply(modifier=first.name) == {"FINISHED"}
    found = ops.deformers.bound(ob)
    assert [d.mod for d in found] == [second]
    bpy.context.view_layer.update()
    assert np.abs(evaluated_world(ob)[0] - shown).max() <= SHAPE_TOL * np.ptp(shown, 0).max()
    # Delete the second's lattice: that deformer lets go of it and says so; nothing else breaks.
    with bpy.context.temp_override(selected_objects=[belly], selected_editable_objects=[belly],
                                   active_object=belly, object=belly):
        assert bpy.ops.object.delete() == {"FINISHED"}
    bpy.context.view_layer.update()
    info = ops.status.status(found[0])
    assert info.error and "deleted" in info.error


def test_an_animation_render_solves_the_second_deformer_on_the_frame_rendered(ext, tmp_path):
    """The render calls the frame handler once per frame: the second deformer must read what the
    first gives on that frame. The offsets the render wrote equal those the viewport solves for
    that frame (checked against two Lattice modifiers above)."""
    head, belly = _lattices()
    ob = _two_deformers(ext, "Ours", head, belly, axes="XYZ")
    ops = _ops(ext)
    scene = bpy.context.scene
    scene.frame_set(16)
    helpers = [ops.node_group.get_input(m, ops.node_group.SOLVER_INPUT) for m in ops.modifier.find_all(ob)]
    expected = [ops.solver_helper.read_offsets(h).copy() for h in helpers]
    scene.frame_set(2)                  # the viewport now shows another frame
    written = render_frame(16, tmp_path, lambda: [ops.solver_helper.read_offsets(h).copy() for h in helpers])
    assert written, "the render wrote its frame"
    size = 1.6 * 1.4
    for got, want in zip(written[0], expected):
        assert got.shape == want.shape
        assert np.abs(got - want).max() <= 1e-6 * size


def test_a_bake_holds_the_whole_result_and_plays_it_back(ext, tmp_path):
    """Bake with two deformers: the cache holds the last VP-FFD slot's output (the first one's
    result included); switched to the cache, the mesh shows two Lattice modifiers' result (Correction
    None) with every VP-FFD modifier off."""
    head, belly = _lattices()
    ob = _two_deformers(ext, "Ours", head, belly, axes="NONE")
    twin = _lattice_twin("Twin", (head, belly))
    ops = _ops(ext)
    bake = __import__(ops.__name__ + ".bake", fromlist=["bake"])
    result = bake.bake(ob, bpy.context.scene, str(tmp_path / "two.pc2"), 6, 10, switch=True)
    assert result.n_verts == len(ob.data.vertices)
    assert not any(m.show_viewport for m in ops.modifier.find_all(ob))
    for f in (6, 8, 10):
        bpy.context.scene.frame_set(f)
        assert _same_shape(ob, twin) <= SHAPE_TOL, f


def test_linked_duplicates_each_deform_for_their_own_placement(ext):
    """Alt+D of a mesh with two deformers: the duplicate shares the mesh and copies both VP-FFD
    modifiers and their settings; each object shows the solve for its own placement."""
    head, belly = _lattices()
    ob = _two_deformers(ext, "Ours", head, belly, axes="NONE")
    dup = ob.copy()                       # a linked duplicate: same mesh data
    dup.location = (0.3, -0.2, 0.1)
    bpy.context.scene.collection.objects.link(dup)
    twin, twin_dup = _lattice_twin("Twin", (head, belly)), _lattice_twin("TwinDup", (head, belly))
    twin_dup.location = dup.location
    ops = _ops(ext)
    for f in (8, 16):
        bpy.context.scene.frame_set(f)
        assert len(ops.deformers.bound(dup)) == 2
        assert _same_shape(ob, twin) <= SHAPE_TOL and _same_shape(dup, twin_dup) <= SHAPE_TOL, f
    helpers = {ops.node_group.get_input(m, ops.node_group.SOLVER_INPUT)
               for o in (ob, dup) for m in ops.modifier.find_all(o)}
    assert len(helpers) == 4, "every modifier has a solver helper of its own"


def test_a_file_of_the_one_deformer_version_opens_with_its_binding(ext, tmp_path):
    """What a file saved before several deformers existed holds: a node group of the previous
    version (rebuilt on load, which gives its sockets new identifiers) and settings that name no
    modifier. It opens with the same solver helper (what Bind saved: the volume at Bind), and
    deforms as before."""
    head, _ = _lattices()
    ob = _capsule("Ours")
    _input_twin("Input", rig=True)     # makes the rig
    _rig(ob)
    bpy.context.scene.frame_set(1)
    assert _bind(ob, lattice=head, axes="XYZ", target="BIND") == {"FINISHED"}
    ops = _ops(ext)
    bpy.context.scene.frame_set(15)
    shown = evaluated_world(ob)[0]
    mod = ops.modifier.find(ob)
    helper = ops.node_group.get_input(mod, ops.node_group.SOLVER_INPUT)
    saved = list(helper[ops.saved_data.BIND_VOLUME_PROPERTY])
    mod.node_group[ops.node_group.GROUP_TAG] = ops.node_group.GROUP_VERSION - 1
    ob.vpffd.modifier_uid = 0
    path = str(tmp_path / "old.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    ob = bpy.data.objects["Ours"]
    mod = ops.modifier.find(ob)
    assert mod.node_group.get(ops.node_group.GROUP_TAG) == ops.node_group.GROUP_VERSION
    helper = ops.node_group.get_input(mod, ops.node_group.SOLVER_INPUT)
    assert helper is not None and list(helper[ops.saved_data.BIND_VOLUME_PROPERTY]) == saved
    assert ob.vpffd.modifier_uid == mod.persistent_uid
    bpy.context.scene.frame_set(14)
    bpy.context.scene.frame_set(15)
    after = evaluated_world(ob)[0]
    assert np.abs(after - shown).max() <= SHAPE_TOL * np.ptp(shown, 0).max()
    assert ops.status.status(ob).error is None and ops.status.status(ob).target_from == "bind"
