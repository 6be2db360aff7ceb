"""The mesh's own Edit Mode: VP-FFD keeps deforming what is edited, live, as Blender's Lattice
modifier shows its result in Edit Mode (the modifier's "Edit Mode" toggle), and keeps the volume of
the mesh as edited. Checked on Blender's evaluated mesh against a Lattice modifier on a twin that
is given a copy of the mesh as edited (Correction None) and against the volume of the edited mesh's own float32
coordinates (XYZ). The real window's Edit Mode is checked in tests/e2e/gui_session.py."""
import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
import bmesh  # noqa: E402  (importable once bpy is)

from .test_lifecycle_blender import _ball, _ops, _lattice  # noqa: E402
from .blender_ref import bind as _bind, evaluated_world  # noqa: E402

pytestmark = pytest.mark.blender

VOLUME_TOL = 1e-5


def _evaluated(ob):
    """(V, 3) float32 evaluated coordinates as float64 (through `to_mesh`: in Edit Mode a
    deform-only stack's evaluated mesh is a wrapper of the edited mesh with no arrays of its own)."""
    ob_eval = ob.evaluated_get(bpy.context.evaluated_depsgraph_get())
    me = ob_eval.to_mesh()
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    ob_eval.to_mesh_clear()
    return co.reshape(-1, 3).astype(np.float64)


def _edited(ob):
    """(float32 coordinates as float64 (V, 3), triangles (F, 3)) of the mesh being edited."""
    bm = bmesh.from_edit_mesh(ob.data)
    bm.verts.ensure_lookup_table()
    bm.verts.index_update()
    co = np.array([tuple(v.co) for v in bm.verts], np.float32).astype(np.float64)
    tris = np.array([[loop.vert.index for loop in t] for t in bm.calc_loop_triangles()], np.int64)
    return co, tris


def _volume(co, tris):
    a, b, c = co[tris[:, 0]], co[tris[:, 1]], co[tris[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def _mode(ob, mode):
    layer = bpy.context.view_layer
    layer.objects.active = ob
    ob.select_set(True)
    with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
        assert bpy.ops.object.mode_set(mode=mode) == {"FINISHED"}
    layer.update()


def _settle():
    for _ in range(3):   # VP-FFD's write, then the evaluation it brings
        bpy.context.view_layer.update()


@pytest.mark.parametrize("axes", ["NONE", "XYZ"])
def test_edit_mode_deforms_the_mesh_as_edited(ext, axes):
    ball, lat = _ball(), _lattice()
    twin = bpy.data.objects.new("Twin", ball.data.copy())
    bpy.context.scene.collection.objects.link(twin)
    twin.modifiers.new("Lattice", "LATTICE").object = lat
    assert _bind(ball, lattice=lat, axes=axes) == {"FINISHED"}
    shown = _evaluated(ball)
    size = np.ptp(shown, 0).max()
    _mode(ball, "EDIT")
    np.testing.assert_array_equal(_evaluated(ball), shown)   # entering shows the same shape

    def check(what):
        _settle()
        co, tris = _edited(ball)
        ours, info = _evaluated(ball), _ops(ext).status.status(ball)
        assert info.error is None and info.editing, (what, info)
        assert len(ours) == len(co), what
        if axes == "NONE":
            # The twin, in Object Mode, gets a copy of the mesh as edited now.
            copy = bmesh.from_edit_mesh(ball.data).copy()
            copy.to_mesh(twin.data)
            copy.free()
            twin.data.update()
            bpy.context.view_layer.update()
            assert np.abs(ours - _evaluated(twin)).max() <= 1e-5 * size, what
        else:
            assert abs(_volume(ours, tris) / _volume(co, tris) - 1) <= VOLUME_TOL, what
            # The panel's figure is measured on the triangles the modifier passes along (quads
            # split on their first and third corners); BMesh splits a few non-planar quads on the
            # other diagonal, which moves the measured volume by ~2e-6 here.
            assert abs(info.volume_percent / 100 - _volume(ours, tris) / _volume(co, tris)) <= VOLUME_TOL, what

    bm = bmesh.from_edit_mesh(ball.data)
    for v in bm.verts:
        if v.co.z > 0.3:
            v.co.z += 0.25
    bmesh.update_edit_mesh(ball.data)
    check("vertices moved")
    bm = bmesh.from_edit_mesh(ball.data)
    bmesh.ops.subdivide_edges(bm, edges=[e for e in bm.edges if e.verts[0].co.x > 0.4], cuts=1,
                              use_grid_fill=True)
    bmesh.update_edit_mesh(ball.data)
    check("vertices added")
    _mode(ball, "OBJECT")
    _settle()
    info = _ops(ext).status.status(ball)
    assert info.error is None and not info.editing
    ours = _evaluated(ball)
    assert len(ours) == len(ball.data.vertices)
    if axes == "NONE":
        twin.data = ball.data
        bpy.context.view_layer.update()
        assert np.abs(ours - _evaluated(twin)).max() <= 1e-5 * size
    else:
        ball.modifiers[-1].show_viewport = False           # what reaches the slot: the mesh itself
        own, tris = evaluated_world(ball)
        ball.modifiers[-1].show_viewport = True
        ours, _ = evaluated_world(ball)
        assert abs(_volume(ours, tris) / _volume(own, tris) - 1) <= VOLUME_TOL
