"""What Blender's own object and modifier operators do to a bound mesh, headless: they must leave
it as they leave a mesh with Blender's Lattice modifier.

- Delete (X) on the lattice: the lattice is freed (VP-FFD does not keep it alive or save it), the
  mesh shows what reaches the VP-FFD slot undeformed, and the panel says why. A lattice still
  linked in another scene only leaves this one and keeps deforming.
- X on the VP-FFD modifier, or Blender's Apply (Ctrl+A) on it: the object is no longer bound and
  no error stays behind; Apply leaves the deformed shape in the mesh.
- Opening a file saved with an older version's node group: the group is rebuilt and the mesh
  deforms as before.
"""
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import vpffd_addon as core  # noqa: E402  (repository copy: only for building test meshes)

from .blender_ref import bind as _bind, evaluated_volume, evaluated_world, triangle_mesh
from .blender_ref import squashed_lattice as _lattice

pytestmark = pytest.mark.blender


def _ops(ext):
    return ext.module.operators


def _ball(name="Ball"):
    v, f = core.icosphere(3, 0.8)
    ob = bpy.data.objects.new(name, triangle_mesh(v, f, name))
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _coords(ob):
    return evaluated_world(ob)[0]


def _delete(ob):
    with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob],
                                   selected_editable_objects=[ob]):
        assert bpy.ops.object.delete(use_global=False) == {"FINISHED"}
    bpy.context.view_layer.update()


def test_deleting_the_lattice_frees_it_and_the_mesh_shows_undeformed(ext, tmp_path):
    ball, lat = _ball(), _lattice()
    rest = _coords(ball)
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    assert np.abs(_coords(ball) - rest).max() > 0.05
    _delete(lat)
    bpy.context.scene.frame_set(2)
    info = _ops(ext).status.stats(ball)
    assert "'Lattice' was deleted" in info["error"]
    np.testing.assert_array_equal(_coords(ball), rest)
    assert ball.vpffd.lattice is None
    lattice = bpy.data.objects.get("Lattice")
    assert lattice is None or lattice.users == 0, "nothing of VP-FFD keeps the lattice alive"
    path = str(tmp_path / "after_delete.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    assert "Lattice" not in bpy.data.objects, "the deleted lattice is not saved into the file"
    assert bpy.data.objects["Ball"].vpffd.is_bound


def test_a_lattice_linked_in_another_scene_only_leaves_this_one(ext):
    ball, lat = _ball(), _lattice()
    other = bpy.data.scenes.new("Other")
    other.collection.objects.link(lat)
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    shown = _coords(ball)
    _delete(lat)
    bpy.context.scene.frame_set(2)
    assert _ops(ext).status.stats(ball).get("error") is None
    assert ball.vpffd.lattice is lat
    np.testing.assert_allclose(_coords(ball), shown, atol=1e-6)


def test_removing_the_modifier_unbinds_quietly(ext):
    ball, lat = _ball(), _lattice()
    rest = _coords(ball)
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    ball.modifiers.remove(ball.modifiers["VP-FFD"])
    bpy.context.view_layer.update()
    assert not ball.vpffd.is_bound and ball.vpffd.lattice is lat
    assert _ops(ext).status.stats(ball).get("error") is None
    np.testing.assert_array_equal(_coords(ball), rest)
    assert not [a.name for a in ball.data.attributes if a.name.startswith("vpffd")]


def test_blenders_apply_on_the_modifier_keeps_the_shape_and_unbinds(ext):
    ball, lat = _ball(), _lattice()
    assert _bind(ball, lattice=lat, axes="XY") == {"FINISHED"}
    shown = _coords(ball)
    volume = evaluated_volume(ball)
    with bpy.context.temp_override(object=ball, active_object=ball):
        bpy.ops.object.modifier_apply(modifier="VP-FFD")
    bpy.context.view_layer.update()
    assert not ball.vpffd.is_bound
    assert _ops(ext).status.stats(ball).get("error") is None
    assert not ball.modifiers
    np.testing.assert_allclose(_coords(ball), shown, atol=1e-6)
    assert abs(evaluated_volume(ball) / volume - 1) <= 1e-6
    assert len(ball.data.vertices) == len(shown), "only the mesh is applied, not VP-FFD's tap"


def test_a_mirroring_lattice_mirrors_the_mesh_and_keeps_its_volumes_size(ext):
    """Lattice points mirrored in Z: the Lattice modifier mirrors the mesh; VP-FFD gives the
    mirrored shape with |volume| kept (not a mesh turned inside out), and the panel says 100%."""
    ball = _ball()
    lat = _lattice()
    co = np.empty(len(lat.data.points) * 3, np.float32)
    lat.data.points.foreach_get("co", co)
    co = co.reshape(-1, 3)
    co[:, 2] *= -0.7
    lat.data.points.foreach_set("co_deform", co.ravel())
    rest = evaluated_volume(ball)
    assert _bind(ball, lattice=lat, axes="XY") == {"FINISHED"}
    plain = bpy.data.objects.new("Plain", ball.data.copy())
    bpy.context.scene.collection.objects.link(plain)
    plain.modifiers.clear()
    plain.modifiers.new("Lattice", "LATTICE").object = lat
    bpy.context.scene.frame_set(2)
    ours, theirs = _coords(ball), _coords(plain)
    assert evaluated_volume(plain) < 0 and evaluated_volume(ball) < 0
    assert abs(evaluated_volume(ball) / -rest - 1) <= 1e-5
    np.testing.assert_allclose(ours[:, 2], theirs[:, 2], atol=1e-5)   # XY only: z is the mirror's
    info = _ops(ext).status.stats(ball)
    assert abs(info["volume_percent"] - 100) <= 1e-3
    assert any("mirrors space" in w for w in info["warnings"])


def test_a_frame_that_cannot_be_solved_shows_the_same_whatever_came_before(ext):
    """The lattice's Z scale keyed to 0 on frame 10: there is no lattice space that frame. The mesh
    shows its input undeformed and the panel says why in words, reached from any other frame."""
    ball, lat = _ball(), _lattice()
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    for f, z in ((1, 2 / 3), (10, 0.0), (18, 2 / 3)):
        lat.scale = (2 / 3, 2 / 3, z)
        lat.keyframe_insert("scale", frame=f)
    rest = np.array([v.co for v in ball.data.vertices])
    scene = bpy.context.scene
    seen = []
    for before in (1, 9, 18, 10):
        scene.frame_set(before)
        scene.frame_set(10)
        seen.append(_coords(ball))
        assert "scaled to zero" in _ops(ext).status.stats(ball)["error"]
    for shown in seen[1:]:
        np.testing.assert_array_equal(shown, seen[0])
    np.testing.assert_allclose(seen[0], rest, atol=1e-6)
    scene.frame_set(5)
    assert _ops(ext).status.stats(ball).get("error") is None


def test_vpffd_apply_needs_its_input_to_be_the_meshs_own_coordinates(ext):
    """VP-FFD's own Apply writes the result into the mesh: refused (nothing changed) while an
    enabled modifier comes before it; with it first, the mesh takes the shown shape."""
    ball, lat = _ball(), _lattice()
    smooth = ball.modifiers.new("Smooth", "SMOOTH")
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    own = np.array([v.co for v in ball.data.vertices])
    with bpy.context.temp_override(object=ball, active_object=ball, selected_objects=[ball]):
        with pytest.raises(RuntimeError, match="(?i)modifiers before VP-FFD"):
            bpy.ops.object.vpffd_apply()
    np.testing.assert_array_equal(np.array([v.co for v in ball.data.vertices]), own)
    assert ball.vpffd.is_bound
    smooth.show_viewport = False
    shown = _coords(ball)
    with bpy.context.temp_override(object=ball, active_object=ball, selected_objects=[ball]):
        assert bpy.ops.object.vpffd_apply() == {"FINISHED"}
    assert not ball.vpffd.is_bound
    ball.modifiers.remove(smooth)
    np.testing.assert_allclose(_coords(ball), shown, atol=1e-6)


def test_a_file_with_an_older_node_group_is_rebuilt_when_it_loads(ext, tmp_path):
    """A file saved by an earlier version carries that version's node group, whose tap this one
    may not read: loading the file rebuilds the group, and the mesh deforms as before."""
    node_group = ext.module.operators.node_group
    ball, lat = _ball(), _lattice()
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    shown = _coords(ball)
    ng = ball.modifiers["VP-FFD"].node_group
    # What an older version left: its own version number, and a tree without today's tap.
    ng[node_group.GROUP_TAG] = node_group.GROUP_VERSION - 1
    ng.nodes.clear()
    ng.links.new(ng.nodes.new("NodeGroupInput").outputs[0], ng.nodes.new("NodeGroupOutput").inputs[0])
    path = str(tmp_path / "older.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    ball = bpy.data.objects["Ball"]
    ng = ball.modifiers["VP-FFD"].node_group
    assert ng.get(node_group.GROUP_TAG) == node_group.GROUP_VERSION
    bpy.context.scene.frame_set(bpy.context.scene.frame_current)
    assert _ops(ext).status.stats(ball).get("error") is None
    np.testing.assert_allclose(_coords(ball), shown, atol=1e-6)


def test_the_modifier_shows_none_of_its_insides(ext, tmp_path):
    """The VP-FFD modifier in the stack shows no input fields (Lattice, Solver, Vertex Group,
    Invert, Tap Faces) and no node-group selector: its panel sets them, and editing them there
    could only break the binding. A group from an older file gets its inputs hidden when bound
    again, keeping its sockets (so its modifiers keep their values)."""
    ball, lat = _ball(), _lattice()
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    mod = ball.modifiers["VP-FFD"]
    inputs = [item for item in mod.node_group.interface.items_tree
              if getattr(item, "in_out", None) == "INPUT" and item.socket_type != "NodeSocketGeometry"]
    assert {item.name for item in inputs} >= {"Lattice", "Solver", "Vertex Group", "Tap Faces"}
    assert all(item.hide_in_modifier for item in inputs), [(i.name, i.hide_in_modifier) for i in inputs]
    assert mod.show_group_selector is False
    # An older file's group, inputs shown: a Re-bind hides them in place.
    for item in inputs:
        item.hide_in_modifier = False
    mod.show_group_selector = True
    before = {item.identifier for item in inputs}
    shown = _coords(ball)
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    mod = ball.modifiers["VP-FFD"]
    inputs = [item for item in mod.node_group.interface.items_tree
              if getattr(item, "in_out", None) == "INPUT" and item.socket_type != "NodeSocketGeometry"]
    assert {item.identifier for item in inputs} == before
    assert all(item.hide_in_modifier for item in inputs) and mod.show_group_selector is False
    bpy.context.scene.frame_set(bpy.context.scene.frame_current)
    assert _ops(ext).status.stats(ball).get("error") is None
    np.testing.assert_allclose(_coords(ball), shown, atol=1e-6)


def _hide(ob, how, hidden):
    if how == "eye":                                  # H / Alt+H
        ob.hide_set(hidden)
    elif how == "viewport":                           # Disable in Viewports
        ob.hide_viewport = hidden
    else:                                             # the object's collection hidden
        coll = bpy.data.collections.get("Hideable") or bpy.data.collections.new("Hideable")
        if coll.name not in bpy.context.scene.collection.children:
            bpy.context.scene.collection.children.link(coll)
        if ob.name not in coll.objects:
            coll.objects.link(ob)
            bpy.context.scene.collection.objects.unlink(ob)
        bpy.context.view_layer.layer_collection.children[coll.name].hide_viewport = hidden
    bpy.context.view_layer.update()


@pytest.mark.parametrize("how", ["eye", "viewport", "collection"])
def test_hide_and_unhide_bring_the_corrected_shape_back(ext, how):
    """Hidden, Blender does not evaluate the object, so nothing reaches the slot: VP-FFD pauses
    (no error) and keeps its offsets; shown again, the corrected shape is back exactly, also
    after the lattice changed while it was hidden (it is solved again)."""
    ops = _ops(ext)
    ball, lat = _ball(), _lattice()
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    bpy.context.scene.frame_set(1)
    shown = _coords(ball)
    rest = evaluated_volume(ball)
    assert ops.status.stats(ball).get("error") is None
    _hide(ball, how, True)
    bpy.context.scene.frame_set(1)
    assert ops.status.stats(ball).get("error") is None, ops.status.stats(ball)
    assert "hidden" in (ops.status.status(ball).paused or "")
    _hide(ball, how, False)
    bpy.context.scene.frame_set(1)
    assert ops.status.stats(ball).get("error") is None, ops.status.stats(ball)
    np.testing.assert_allclose(_coords(ball), shown, rtol=0, atol=1e-6)
    # Changed while hidden: shown again, it is the new frame's corrected shape.
    _hide(ball, how, True)
    co = np.empty(len(lat.data.points) * 3, np.float32)
    lat.data.points.foreach_get("co_deform", co)
    co = co.reshape(-1, 3)
    co[:, 0] *= 1.3
    lat.data.points.foreach_set("co_deform", co.ravel())
    lat.data.update_tag()
    bpy.context.view_layer.update()
    _hide(ball, how, False)
    bpy.context.view_layer.update()
    after = _coords(ball)
    assert np.abs(after - shown).max() > 1e-3, "the lattice change shows"
    assert ops.status.stats(ball).get("error") is None, ops.status.stats(ball)
    assert abs(evaluated_volume(ball) / rest - 1) <= 1e-5


def test_the_panels_first_line_says_what_is_shown(ext):
    """The main panel's first line (`status_line.headline`): the volume kept, measured here on the
    evaluated mesh, or why nothing is solved."""
    line = ext.module.operators.status_line.headline
    ops = _ops(ext)
    ball, lat = _ball(), _lattice()

    def first_line():
        return line(ops.status.status(ball), ball.vpffd.is_bound, False)

    assert first_line()[0].startswith("not bound")
    rest_volume = evaluated_volume(ball)
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    text, icon = first_line()
    measured = 100.0 * evaluated_volume(ball) / rest_volume
    assert (text, icon) == (f"volume {measured:.3f}% of its input", "CHECKMARK")
    ball.hide_set(True)
    bpy.context.scene.frame_set(2)
    assert first_line() == ("the object is hidden: VP-FFD solves again when it is shown", "PAUSE")
    ball.hide_set(False)
    bpy.context.scene.frame_set(3)
    assert first_line()[1] == "CHECKMARK"
    _delete(lat)
    bpy.context.scene.frame_set(4)
    text, icon = first_line()
    assert icon == "ERROR" and "'Lattice' was deleted" in text


def test_undo_after_deleting_the_lattice_links_it_back(ext):
    """Delete the lattice (the mesh lets go of it), then Undo: Blender brings the lattice back
    but keeps the mesh as it is in memory, its Lattice field cleared (VP-FFD let go after Delete's
    undo step was written). VP-FFD's undo handler, which Blender calls after every undo, links the
    lattice back: the mesh deforms as before Delete and no error stays."""
    ball, lat = _ball(), _lattice()
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    shown = _coords(ball)
    ops = _ops(ext)
    _delete(lat)
    bpy.context.scene.frame_set(2)
    assert ball.vpffd.lattice is None and "'Lattice' was deleted" in ops.status.stats(ball)["error"]
    # What undo restores: the lattice object in the scene again, the mesh's field still cleared.
    bpy.context.scene.collection.objects.link(lat)
    bpy.context.view_layer.update()
    assert ball.vpffd.lattice is None
    ext.module.operators.handlers.on_undo()            # as Blender calls it after the undo
    assert ball.vpffd.lattice == lat
    bpy.context.scene.frame_set(3)
    assert ops.status.stats(ball).get("error") is None, ops.status.stats(ball)
    np.testing.assert_allclose(_coords(ball), shown, atol=1e-6)
