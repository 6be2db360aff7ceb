"""Add > Lattice > "VP-FFD Lattice Deform Selected": one step from selected meshes to a fitted,
bound lattice, checked on Blender's evaluated meshes (headless)."""
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import vpffd_addon as core  # noqa: E402  (repository copy: only for building test meshes)

from .blender_ref import evaluated_volume, evaluated_world, triangle_mesh  # noqa: E402

pytestmark = pytest.mark.blender


def _run(objects, active, **kw):
    for ob in bpy.context.view_layer.objects:
        ob.select_set(ob in objects)
    bpy.context.view_layer.objects.active = active
    with bpy.context.temp_override(selected_objects=objects, active_object=active, object=active):
        return bpy.ops.object.vpffd_lattice_deform_selected(**kw)


def _world_box(lat):
    co = np.array([p.co for p in lat.data.points], np.float64)
    m = np.array(lat.matrix_world)
    w = co @ m[:3, :3].T + m[:3, 3]
    return w.min(0), w.max(0)


def test_fits_what_reaches_the_slot_binds_every_selected_mesh_and_keeps_the_volume(ext):
    v, f = core.icosphere(3, 0.5)
    ball = bpy.data.objects.new("Ball", triangle_mesh(v, f, "Ball"))
    bv, bf = core.box(3, 0.6)
    crate = bpy.data.objects.new("Crate", triangle_mesh(bv, bf, "Crate"))
    crate.location = (1.4, 0.2, 0.0)
    for ob in (ball, crate):
        bpy.context.scene.collection.objects.link(ob)
    # What reaches the slot is stretched along Z: the lattice fits that, not the mesh's own points.
    stretch = crate.modifiers.new("Stretch", "SIMPLE_DEFORM")
    stretch.deform_method, stretch.deform_axis, stretch.factor = "STRETCH", "Z", 0.8
    bpy.context.view_layer.update()
    reach = np.concatenate([evaluated_world(ob)[0] for ob in (ball, crate)])
    before = {ob.name: evaluated_volume(ob) for ob in (ball, crate)}

    assert _run([ball, crate], ball, resolution=5) == {"FINISHED"}
    lat = bpy.context.view_layer.objects.active
    assert lat.type == "LATTICE" and lat.select_get()
    assert not ball.select_get() and not crate.select_get()
    assert {lat.data.interpolation_type_u, lat.data.interpolation_type_v,
            lat.data.interpolation_type_w} == {"KEY_BSPLINE"}
    assert max(lat.data.points_u, lat.data.points_v, lat.data.points_w) == 5
    assert lat.data.points_u == 5                      # the longest side is X
    lo, hi = _world_box(lat)
    assert (lo < reach.min(0)).all() and (hi > reach.max(0)).all(), "the lattice encloses the input"
    margin = 0.05 * np.ptp(reach, 0).max()
    np.testing.assert_allclose(lo, reach.min(0) - margin, atol=1e-5)
    np.testing.assert_allclose(hi, reach.max(0) + margin, atol=1e-5)
    for ob in (ball, crate):
        assert ob.vpffd.is_bound and ob.vpffd.lattice == lat and ob.vpffd.axes == "XYZ"
        assert ob.modifiers[-1].name == "VP-FFD"
    # Bound at rest: nothing moves yet. Squash the lattice: both keep their volume.
    for ob in (ball, crate):
        assert abs(evaluated_volume(ob) / before[ob.name] - 1) <= 1e-5
    co = np.array([p.co for p in lat.data.points], np.float32)
    co[:, 2] *= 0.5
    lat.data.points.foreach_set("co_deform", co.ravel())
    lat.data.update_tag()
    bpy.context.view_layer.update()
    for ob in (ball, crate):
        assert abs(evaluated_volume(ob) / before[ob.name] - 1) <= 1e-5, ob.name


def test_nothing_selected_that_can_be_bound_is_refused(ext):
    """A lattice alone, or a VP-FFD cage alone: nothing to bind."""
    lt = bpy.data.lattices.new("L")
    other = bpy.data.objects.new("L", lt)
    bpy.context.scene.collection.objects.link(other)
    for ob in bpy.context.view_layer.objects:
        ob.select_set(ob == other)
    bpy.context.view_layer.objects.active = other
    with bpy.context.temp_override(selected_objects=[other], active_object=other, object=other):
        assert not bpy.ops.object.vpffd_lattice_deform_selected.poll()
    # A VP-FFD cage is a mesh object too, but a control, not a mesh to deform: alone it is refused,
    # and beside a mesh the fitted lattice leaves it out.
    assert bpy.ops.object.vpffd_cage_add_box(resolution=(2, 2, 2), size=1.0) == {"FINISHED"}
    cage_ob = bpy.context.view_layer.objects.active
    with bpy.context.temp_override(selected_objects=[cage_ob], active_object=cage_ob, object=cage_ob):
        assert not bpy.ops.object.vpffd_lattice_deform_selected.poll()
    v, f = core.icosphere(2, 0.3)
    ball = bpy.data.objects.new("Ball", triangle_mesh(v, f, "Ball"))
    bpy.context.scene.collection.objects.link(ball)
    bpy.context.view_layer.update()
    assert _run([ball, cage_ob], ball) == {"FINISHED"}
    assert ball.vpffd.is_bound and not cage_ob.vpffd.is_bound
    assert not any(m.type == "NODES" for m in cage_ob.modifiers)


@pytest.mark.parametrize("resolution, margin, axes", [(3, 0.3, "XY"), (7, 0.0, "Z")])
def test_every_option_shapes_the_fitted_lattice_as_documented(ext, resolution, margin, axes):
    """Resolution: the points along the longest side; Margin: room on each side, a fraction of the
    meshes' largest extent; Correction: each mesh's. Each differs from its default here."""
    v, f = core.icosphere(3, 0.5)
    ball = bpy.data.objects.new("Ball", triangle_mesh(v * [1.6, 1.0, 0.7], f, "Ball"))
    bpy.context.scene.collection.objects.link(ball)
    bpy.context.view_layer.update()
    reach = evaluated_world(ball)[0]
    assert _run([ball], ball, resolution=resolution, margin=margin, axes=axes) == {"FINISHED"}
    lat = bpy.context.view_layer.objects.active
    shape = (lat.data.points_u, lat.data.points_v, lat.data.points_w)
    assert shape[0] == max(shape) == resolution, shape         # the longest side is X
    lo, hi = _world_box(lat)
    room = margin * np.ptp(reach, 0).max()
    np.testing.assert_allclose(lo, reach.min(0) - room, atol=1e-5)
    np.testing.assert_allclose(hi, reach.max(0) + room, atol=1e-5)
    assert ball.vpffd.is_bound and ball.vpffd.axes == axes
