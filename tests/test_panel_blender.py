"""What VP-FFD's panel says, checked against what Blender shows, on real lattices in bpy: the
first line (`status_line.headline`) and the Status sub-panel's lines (`status_line.status_lines`,
the very words the panel draws) say what is true and agree with each other.

- An open mesh that encloses no volume (a grid through the lattice's centre) deforms as Blender's
  Lattice modifier does, whatever the Correction, and the first line says so.
- The warnings the first line counts are the ones Status lists, each once: a mirror (which folds
  nothing), a lattice with a single point on an axis, a refused correction (with no check mark
  beside its volume figure).
- The panel's volume figure is the volume measured on Blender's evaluated mesh, also when the
  target cannot be met.
- The vertices counted outside the lattice, fading and beyond the falloff use one definition of
  outside (a vertex on the lattice's face is inside).
- After Apply, an unbound mesh whose Lattice field still holds the applied lattice is told that
  Bind would deform it again.
- While the compiled kernels compile, the first line says so.
"""
import dataclasses

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import vpffd_addon as core  # noqa: E402  (repository copy: only for building test meshes)

from .blender_ref import bind as _bind, evaluated_volume, evaluated_world, triangle_mesh  # noqa: E402
from .blender_ref import squashed_lattice as _lattice  # noqa: E402

pytestmark = pytest.mark.blender


def _ops(ext):
    return ext.module.operators


def _ball(name="Ball", radius=0.8):
    v, f = core.icosphere(3, radius)
    ob = bpy.data.objects.new(name, triangle_mesh(v, f, name))
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _first_line(ext, ob, **kw):
    ops = _ops(ext)
    s = ob.vpffd
    return ops.status_line.headline(ops.status.status(ob), s.is_bound, False,
                                    ops.status_line.applied_lattice(s), **kw)


def _status_lines(ext, ob):
    return _ops(ext).status_line.status_lines(_ops(ext).status.status(ob), False, ob.vpffd.backend)


def _counted(text):
    """The number of warnings the first line `text` counts (0 when it names none)."""
    if "in Status)" not in text:
        return 0
    return int(text.rsplit("(", 1)[1].split()[0])


def _assert_counts_agree(ext, ob):
    """The first line counts exactly the warnings Status lists, and Status lists each once."""
    text, icon = _first_line(ext, ob)
    listed = [t for t, i in _status_lines(ext, ob) if i == "ERROR"]
    assert len(listed) == len(set(listed)), listed
    assert _counted(text) == len(listed), (text, listed)
    assert (icon == "ERROR") == bool(listed), (text, icon, listed)
    return listed


def test_an_open_mesh_enclosing_no_volume_deforms_as_the_lattice_modifier_whatever_the_correction(ext):
    """A grid through the lattice's centre has no volume about it: aiming at zero would bend the
    grid into another shape. It deforms exactly as Blender's Lattice modifier deforms a twin, and
    the first line says why, not "Correction: None" while Correction shows XYZ."""
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=10, y_subdivisions=10, size=1.6)
    grid = bpy.context.object
    lat = _lattice(1.0, (3, 3, 3))
    co = np.empty(len(lat.data.points) * 3, np.float32)
    lat.data.points.foreach_get("co", co)
    co = co.reshape(-1, 3)
    co[:, 2] += 0.4 * co[:, 0] ** 2              # bend the grid
    co[:, 0] *= 0.8
    lat.data.points.foreach_set("co_deform", co.ravel())
    twin = bpy.data.objects.new("Twin", grid.data.copy())
    bpy.context.scene.collection.objects.link(twin)
    twin.modifiers.new("Lattice", "LATTICE").object = lat
    assert _bind(grid, lattice=lat, axes="XYZ") == {"FINISHED"}
    ours, theirs = evaluated_world(grid)[0], evaluated_world(twin)[0]
    rest = np.array([v.co for v in grid.data.vertices])
    assert np.abs(theirs - rest).max() > 0.1, "the lattice must deform the grid"
    assert np.abs(ours - theirs).max() <= 1e-6 * np.ptp(theirs, 0).max()
    text, icon = _first_line(ext, grid)
    assert text.startswith("the mesh is open and encloses no volume: the lattice deforms it as "
                           "the Lattice modifier does, whatever the Correction"), text
    assert "Correction: None" not in text and icon != "ERROR"
    assert any("encloses no volume" in t for t, _ in _status_lines(ext, grid))
    _assert_counts_agree(ext, grid)
    # Moved off the centre it has a volume about it, which is kept; back, none again.
    ops = _ops(ext)
    grid.location.z = 0.2
    bpy.context.view_layer.update()
    assert not ops.status.status(grid).encloses_nothing and abs(ops.status.status(grid).volume_percent - 100) <= 1e-3
    grid.location.z = 0.0
    bpy.context.view_layer.update()
    assert ops.status.status(grid).encloses_nothing
    assert np.abs(evaluated_world(grid)[0] - theirs).max() <= 1e-6 * np.ptp(theirs, 0).max()


def test_a_mirror_alone_mirrors_space_and_folds_nothing(ext):
    """Lattice points mirrored in Z: every vertex's Jacobian turns sign alike, which is a mirror,
    not a fold. Status says "mirrors space" once and counts no inverted vertices; the first line
    counts that one warning."""
    ball, lat = _ball(), _lattice(-0.7)
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    info = _ops(ext).status.status(ball)
    assert evaluated_volume(ball) < 0, "the mesh really is mirrored"
    assert info.mirrored and info.folds == 0, info
    listed = _assert_counts_agree(ext, ball)
    assert len(listed) == 1 and "mirrors space" in listed[0], listed
    assert not any("folds" in t or "inverted" in t for t, _ in _status_lines(ext, ball))
    # A real fold under the mirror is still counted: check it against the Jacobian's own sign.
    binding = _ops(ext).bound.state_of(ball).result.binding
    det = core.jacobian_det(binding, _ops(ext).bound.state_of(ball).result.points)
    assert (det < 0).all()


def test_a_single_point_on_an_axis_is_listed_in_status_and_counted(ext):
    """A lattice with one point along Z: Status keeps saying so (not only a report at Bind), and
    the first line counts it."""
    ball, lat = _ball(radius=0.5), _lattice(1.0, (4, 4, 1))
    co = np.empty(len(lat.data.points) * 3, np.float32)
    lat.data.points.foreach_get("co", co)
    co = co.reshape(-1, 3)
    co[:, 0] *= 0.7
    lat.data.points.foreach_set("co_deform", co.ravel())
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    bpy.context.scene.frame_set(2)                  # a later update, not Bind's
    listed = _assert_counts_agree(ext, ball)
    assert sum("single point on an axis" in t for t in listed) == 1, listed


def test_a_refused_correction_shows_the_measured_volume_with_no_check_mark(ext):
    """A lattice flattened to zero thickness: the correction is refused and the plain deformation
    shown. The panel's figure is the volume measured on Blender's evaluated mesh (float32
    coordinates, float64 sums), not the target; no check mark stands beside it; the first line
    counts the warnings Status lists (the refusal and the fold)."""
    ball, lat = _ball(), _lattice(0.0)
    rest = evaluated_volume(ball)
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    info = _ops(ext).status.status(ball)
    measured = 100.0 * evaluated_volume(ball) / rest
    assert measured < 50, "the target (100%) is not met"
    # The panel's figure is the core's float64 measurement of the same float32 output.
    assert abs(info.volume_percent - measured) <= 1e-6 * measured, (info.volume_percent, measured)
    text, icon = _first_line(ext, ball)
    assert text.startswith(f"volume {info.volume_percent:.3f}% of its input") and icon == "ERROR"
    listed = _assert_counts_agree(ext, ball)
    assert any("refused" in t for t in listed) and any("folds space" in t for t in listed), listed
    lines = _status_lines(ext, ball)
    assert not any(i == "CHECKMARK" for _, i in lines), lines
    assert not any("%" in t for t, _ in lines), "the plain figure is the volume: said once"


@pytest.mark.parametrize("volume_scale", [1.0, 0.3])
def test_the_panels_figure_is_the_measured_volume_when_the_target_cannot_be_met(ext, volume_scale):
    """Correction Z only, with every lattice point but one row fixed by the Mobility Group: the
    solve cannot reach the target. The first line's figure is the volume measured on Blender's
    evaluated mesh, whatever the target."""
    ball, lat = _ball(), _lattice(0.5)
    group = lat.vertex_groups.new(name="Free")
    group.add([1 + 4 * 1 + 16 * 3], 1.0, "REPLACE")   # one point of the top layer free: too little
    rest = evaluated_volume(ball)
    assert _bind(ball, lattice=lat, axes="Z", mobility_group="Free",
                 volume_scale=volume_scale) == {"FINISHED"}
    info = _ops(ext).status.status(ball)
    measured = 100.0 * evaluated_volume(ball) / rest
    assert abs(measured - 100.0 * volume_scale) > 1.0, "the target must be out of reach"
    assert abs(info.volume_percent - measured) <= 1e-6 * measured, (info.volume_percent, measured)
    assert _first_line(ext, ball)[0].startswith(f"volume {info.volume_percent:.3f}% of its input")
    assert _assert_counts_agree(ext, ball), "the miss is reported"
    assert not any(i == "CHECKMARK" for _, i in _status_lines(ext, ball))


def _on_the_faces(lat):
    """A closed box mesh whose y and z faces lie on the faces of the (rotated) lattice, its
    coordinates rounded to float32 as Blender stores them (so some land a hair outside), reaching
    out of the lattice's +X face by half its width. Returns (mesh object, its vertices in the
    lattice's space, float64)."""
    m = np.array(lat.matrix_world)
    v, f = core.box(8, 1.0)                          # [-0.5, 0.5] per axis: the rest box
    v[:, 0] = (v[:, 0] + 0.5) * 1.5 - 0.5
    ob = bpy.data.objects.new("Box", triangle_mesh(v @ m[:3, :3].T + m[:3, 3], f, "Box"))
    bpy.context.scene.collection.objects.link(ob)
    world = np.array([p.co for p in ob.data.vertices], np.float64)     # the float32 values
    return ob, (world - m[:3, 3]) @ np.linalg.inv(m[:3, :3]).T


def test_falloff_counts_use_one_definition_of_outside(ext):
    """Vertices on the lattice's faces are inside for every count: those outside are the ones
    fading plus the ones beyond the falloff distance, each counted independently here from the
    mesh's float32 coordinates."""
    lt = bpy.data.lattices.new("L")                  # 2 points per axis: rest box [-0.5, 0.5]
    lat = bpy.data.objects.new("L", lt)
    lat.location, lat.scale = (0.37, -0.21, 0.13), (0.7, 0.9, 1.1)
    lat.rotation_euler = (0.3, -0.2, 0.5)
    bpy.context.scene.collection.objects.link(lat)
    bpy.context.view_layer.update()
    ob, local = _on_the_faces(lat)
    excess = np.maximum(np.abs(local) - 0.5, 0.0)    # the rest box is 1 wide along each axis
    d = np.sqrt((excess ** 2).sum(1))
    tol = 1e-6                                       # far above float32 rounding, far below a step
    outside, beyond = d > tol, d >= 0.25
    hair = (d > 0) & (d <= tol)                      # on a face, rounded a hair outside
    assert hair.sum() > 20 and outside.sum() > 20 and beyond.sum() > 0, (hair.sum(), outside.sum())
    assert _bind(ob, lattice=lat, axes="XYZ", outside="FALLOFF", falloff_distance=0.25) == {"FINISHED"}
    info = _ops(ext).status.status(ob)
    fading = outside & ~beyond
    assert (info.outside, info.falloff, info.beyond) == (outside.sum(), fading.sum(), beyond.sum()), info
    words = _ops(ext).status.outside_message(info, False)
    assert words.startswith(f"{outside.sum():,} of {len(local):,} vertices lie outside the lattice "
                            f"(the deformation fades out over {fading.sum():,} of them"), words
    # Said once, beside the Outside setting, not again in Status.
    assert not any("lie outside" in t for t, _ in _status_lines(ext, ob))


def _apply(ob):
    with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
        return bpy.ops.object.vpffd_apply()


@pytest.mark.parametrize("how", ["vpffd", "blender"])
def test_after_apply_the_panel_says_bind_would_deform_the_mesh_again(ext, how):
    """Apply (VP-FFD's, or Blender's on the modifier) makes the deformed shape the mesh's own; the
    Lattice field still holds the lattice, still deformed. The first line says so and what Bind
    would do, instead of "Not bound: pick a Lattice". A new Bind is told no more; neither is a
    mesh whose modifier was only removed."""
    ball, lat = _ball(), _lattice(0.5)
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    shown = evaluated_world(ball)[0]
    if how == "vpffd":
        assert _apply(ball) == {"FINISHED"}
    else:
        with bpy.context.temp_override(object=ball, active_object=ball):
            assert bpy.ops.object.modifier_apply(modifier="VP-FFD") == {"FINISHED"}
    bpy.context.view_layer.update()
    assert not ball.vpffd.is_bound and ball.vpffd.lattice == lat
    np.testing.assert_allclose(np.array([v.co for v in ball.data.vertices]), shown, atol=1e-6)
    text, icon = _first_line(ext, ball)
    assert text.startswith("applied: this shape is now the mesh's own. Bind would deform it again "
                           "by 'Lattice' as it is now"), text
    ball.vpffd.lattice = _lattice(0.5, name="Other")
    assert _first_line(ext, ball)[0].startswith("not bound"), "another lattice: nothing applied by it"
    ball.vpffd.lattice = lat
    assert _bind(ball, lattice=lat, axes="XYZ") == {"FINISHED"}
    ball.modifiers.remove(ball.modifiers["VP-FFD"])          # removed, not applied
    bpy.context.view_layer.update()
    assert not ball.vpffd.is_bound and _first_line(ext, ball)[0].startswith("not bound")


def test_while_the_kernels_compile_the_first_line_says_so(ext):
    """The first line on the state `compiled_backend.status()` reports while the kernels compile
    in their own process, for a solve made with NumPy's kernels meanwhile."""
    ball, lat = _ball(), _lattice(0.5)
    assert _bind(ball, lattice=lat, axes="XYZ", backend="CPU") == {"FINISHED"}
    ops = _ops(ext)
    # Met, no warning: Status gives the plain lattice's figure, with a check mark.
    assert [i for t, i in _status_lines(ext, ball) if "%" in t] == ["CHECKMARK"]
    info = dataclasses.replace(ops.status.status(ball), kernels="NumPy", awaits_kernels=True)
    volume = f"volume {info.volume_percent:.3f}% of its input"
    line = ops.status_line.headline
    assert line(info, True, False, kernels="compiling") == (
        "compiling VP-FFD's kernels (first use only): solving with NumPy meanwhile, " + volume, "TIME")
    assert line(info, True, False, kernels="ready") == (volume, "CHECKMARK")
    assert line(info, True, False, kernels="off") == (volume, "CHECKMARK")
    # Solved with the compiled kernels, or with NumPy by choice (CPU (NumPy), a cage): nothing waits.
    for other in (dataclasses.replace(info, kernels="compiled", awaits_kernels=False),
                  dataclasses.replace(info, awaits_kernels=False)):
        assert line(other, True, False, kernels="compiling") == (volume, "CHECKMARK")


def test_lattice_deform_selected_says_why_it_cannot_run(ext):
    """Greyed out with a reason (Blender shows the poll message on the menu item and raises it to
    a script): nothing suitable selected."""
    lt = bpy.data.lattices.new("L")
    other = bpy.data.objects.new("L", lt)
    bpy.context.scene.collection.objects.link(other)
    with bpy.context.temp_override(selected_objects=[other], active_object=other, object=other):
        with pytest.raises(RuntimeError, match="Select the mesh objects to deform"):
            bpy.ops.object.vpffd_lattice_deform_selected()
