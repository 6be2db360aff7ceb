"""Baking to point caches (PC2, MDD) and playing them back with Blender's own Mesh Cache modifier.

The extension is installed through Blender's installer (conftest's `vpffd` fixture). A bound
icosphere is squashed by a lattice shape key over frames 1-10; every baked frame must equal the
live evaluated mesh exactly (float32), the Mesh Cache modifier must reproduce it, and a saved file
must reproduce it in a fresh Python process where the extension is not installed at all.
"""
import importlib
import json
import os
import struct
import subprocess
import sys
import textwrap

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

import vpffd_addon as core  # noqa: E402  (repository copy: test meshes and an independent reader)
from vpffd_addon import pointcache as pcache  # noqa: E402

from . import extension_harness as eh
from .blender_ref import triangle_mesh

pytestmark = pytest.mark.blender

FIRST, LAST = 1, 10
FRAMES = range(FIRST, LAST + 1)


# ------------------------------------------------------------------------------------ helpers

def _mesh_object(name, verts, tris):
    ob = bpy.data.objects.new(name, triangle_mesh(verts, tris, name))
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _rig(name="Ball", subdivisions=3):
    """A bound icosphere in a 4x4x4 B-spline lattice whose shape key squashes it over 1..10."""
    v, f = core.icosphere(subdivisions, 0.8)
    ball = _mesh_object(name, v, f)
    ball.location = (0.3, -0.2, 0.1)   # object transforms must not matter: caches are local
    lt = bpy.data.lattices.new("Lattice")
    lt.points_u = lt.points_v = lt.points_w = 4
    for a in "uvw":
        setattr(lt, f"interpolation_type_{a}", "KEY_BSPLINE")
    lat = bpy.data.objects.new("Lattice", lt)
    lat.scale = (2.0 / 3.0,) * 3
    lat.location = ball.location
    bpy.context.scene.collection.objects.link(lat)
    lat.shape_key_add(name="Basis")
    key = lat.shape_key_add(name="Squash")
    co = np.empty(len(lt.points) * 3, np.float32)
    lt.points.foreach_get("co", co)
    co = co.reshape(-1, 3)
    co[:, 2] *= 0.45
    co[:, :2] *= 1.05
    key.data.foreach_set("co", co.ravel())
    for frame, value in ((FIRST, 0.0), (6, 1.0), (LAST, 0.4)):
        key.value = value
        key.keyframe_insert("value", frame=frame)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = FIRST, LAST
    scene.frame_set(FIRST)
    ball.vpffd.lattice = lat
    ball.vpffd.axes = "XY"
    with bpy.context.temp_override(object=ball, active_object=ball, selected_objects=[ball]):
        assert bpy.ops.object.vpffd_bind() == {"FINISHED"}
    return ball, lat


def _evaluated(ob):
    """(V, 3) float32 local coordinates of the evaluated mesh."""
    dg = bpy.context.evaluated_depsgraph_get()
    me = ob.evaluated_get(dg).data
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def _live(ob, frames=FRAMES):
    scene = bpy.context.scene
    out = []
    for f in frames:
        scene.frame_set(f)
        out.append(_evaluated(ob))
    return np.stack(out)


def _volume(co, me):
    me.calc_loop_triangles()
    tris = np.empty(len(me.loop_triangles) * 3, np.int32)
    me.loop_triangles.foreach_get("vertices", tris)
    t = co.astype(np.float64)[tris.reshape(-1, 3)]
    return float(np.einsum("ij,ij->", t[:, 0], np.cross(t[:, 1], t[:, 2])) / 6.0)


def _pc2_independently(path):
    """Header and frames parsed here with struct, as the Mesh Cache modifier reads them."""
    with open(path, "rb") as fh:
        raw = fh.read()
    magic, version, points, start, rate, samples = struct.unpack("<12siiffi", raw[:32])
    data = np.frombuffer(raw[32:], "<f4").reshape(samples, points, 3)
    return magic, version, points, start, rate, samples, data


def _vp_modifier(ob):
    return [m for m in ob.modifiers if m.type == "NODES"][0]


@pytest.fixture(scope="module")
def bake_module(vpffd):
    """operators/bake.py of the installed extension, the operators of bake_ops.py registered (by
    the extension itself once it wires them in; else here, for this module only)."""
    mod = importlib.import_module(vpffd.module_name + ".operators.bake")
    registered = []
    for cls in importlib.import_module(vpffd.module_name + ".operators.bake_ops").classes:
        if not hasattr(bpy.types, cls.__name__):
            bpy.utils.register_class(cls)
            registered.append(cls)
    yield mod
    for cls in reversed(registered):
        if hasattr(bpy.types, cls.__name__):
            bpy.utils.unregister_class(cls)


def ops_of(bake_module):
    """The extension's operators package (the bake module's own package)."""
    return sys.modules[bake_module.__package__]


@pytest.fixture
def bk(bake_module):
    eh.reset_scene()
    yield bake_module
    eh.reset_scene()


# -------------------------------------------------------------------------------------- tests

def test_pc2_frames_equal_the_live_result_exactly(bk, tmp_path):
    ball, _ = _rig()
    live = _live(ball)
    rest = np.empty(len(ball.data.vertices) * 3, np.float32)
    ball.data.vertices.foreach_get("co", rest)
    rest = rest.reshape(-1, 3)
    assert np.abs(live - rest).max() > 0.1, "the squash must move the mesh"

    scene = bpy.context.scene
    scene.frame_set(4)
    calls = []
    path = str(tmp_path / "ball.pc2")
    result = bk.bake(ball, scene, path, FIRST, LAST, progress=lambda d, t: calls.append((d, t)))
    assert result.filepath == os.path.realpath(path) and result.format == "PC2"
    assert (result.frame_start, result.frame_end, result.n_verts) == (FIRST, LAST, len(rest))
    assert calls == [(i, len(FRAMES)) for i in range(1, len(FRAMES) + 1)]
    assert scene.frame_current == 4, "the scene's frame is restored"
    assert _vp_modifier(ball).show_viewport and ops_of(bk).cache_modifier.find_cache(ball) is None

    frames, start, rate = pcache.read_pc2(path)
    assert frames.dtype == np.float32 and frames.shape == live.shape
    assert (start, rate) == (FIRST, 1.0)
    np.testing.assert_array_equal(frames, live)      # bit for bit, every frame

    magic, version, points, start, rate, samples, data = _pc2_independently(path)
    assert (magic, version, points, start, rate, samples) == (
        b"POINTCACHE2\0", 1, len(rest), float(FIRST), 1.0, len(FRAMES))
    np.testing.assert_array_equal(data, live)

    rest_volume = _volume(rest, ball.data)
    for f, co in zip(FRAMES, frames):
        assert abs(_volume(co, ball.data) / rest_volume - 1.0) < 1e-5, f"frame {f}"


def test_mdd_frames_equal_the_live_result_exactly(bk, tmp_path):
    ball, _ = _rig()
    live = _live(ball, range(3, 8))
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = 25, 1.0
    path = str(tmp_path / "ball.mdd")
    bk.bake(ball, scene, path, 3, 7, fmt="MDD")
    frames, times = pcache.read_mdd(path)
    np.testing.assert_array_equal(frames, live)
    np.testing.assert_array_equal(times, (np.arange(3, 8) / 25.0).astype(np.float32))
    with open(path, "rb") as fh:
        assert struct.unpack(">ii", fh.read(8)) == (5, len(ball.data.vertices))


@pytest.mark.parametrize("fmt", ["PC2", "MDD"])
def test_switch_to_cache_plays_the_bake_through_the_mesh_cache_modifier(bk, tmp_path, fmt):
    ball, _ = _rig()
    # A modifier after VP-FFD: the cache must go where VP-FFD is, before the subdivision.
    sub = ball.modifiers.new("Subdivision", "SUBSURF")
    sub.levels = 1
    live = _live(ball)
    path = str(tmp_path / f"ball.{fmt.lower()}")
    bk.bake(ball, bpy.context.scene, path, FIRST, LAST, fmt=fmt, switch=True)

    vp = _vp_modifier(ball)
    cache = ops_of(bk).cache_modifier.find_cache(ball)
    assert [m.type for m in ball.modifiers] == ["MESH_CACHE", "NODES", "SUBSURF"]
    assert not vp.show_viewport and not vp.show_render, "VP-FFD is disabled, not removed"
    assert cache.show_viewport and cache.show_render and cache.cache_format == fmt
    assert (cache.play_mode, cache.time_mode, cache.frame_start, cache.frame_scale) == (
        "SCENE", "FRAME", float(FIRST), 1.0)
    assert ops_of(bk).cache_modifier.using_cache(ball) and not ball.vpffd.enabled

    cached = _live(ball)
    np.testing.assert_array_equal(cached, live)
    # Outside the baked range the modifier holds the first and last frames.
    np.testing.assert_array_equal(_live(ball, [FIRST - 3, LAST + 2]), live[[0, -1]])

    ops_of(bk).cache_switch.switch_to_live(ball)
    assert vp.show_viewport and vp.show_render and not cache.show_viewport
    assert ops_of(bk).cache_modifier.find_cache(ball) is not None and not ops_of(bk).cache_modifier.using_cache(ball)
    np.testing.assert_array_equal(_live(ball), live)

    # "Use Baked Cache" with no arguments uses the cache modifier's own settings.
    with bpy.context.temp_override(object=ball, active_object=ball):
        assert bpy.ops.object.vpffd_use_cache() == {"FINISHED"}
        assert ops_of(bk).cache_modifier.using_cache(ball) and not vp.show_viewport
        np.testing.assert_array_equal(_live(ball), live)
        assert bpy.ops.object.vpffd_use_live() == {"FINISHED"}
    assert not ops_of(bk).cache_modifier.using_cache(ball)


def test_time_stretching_still_maps_each_frame_to_its_bake(bk, tmp_path):
    ball, _ = _rig()
    scene = bpy.context.scene
    scene.render.frame_map_old, scene.render.frame_map_new = 100, 150   # scene time = 2/3 frame
    live = _live(ball)
    bk.bake(ball, scene, str(tmp_path / "s.pc2"), FIRST, LAST, switch=True)
    assert ops_of(bk).cache_modifier.find_cache(ball).frame_scale == 1.5
    np.testing.assert_array_equal(_live(ball), live)


def test_rebake_while_on_the_cache_bakes_the_live_solve(bk, tmp_path):
    ball, lat = _rig()
    path = str(tmp_path / "ball.pc2")
    bk.bake(ball, bpy.context.scene, path, FIRST, LAST, switch=True)
    ball.vpffd.volume_scale = 1.2          # change the live result while the cache plays
    ops_of(bk).cache_switch.switch_to_live(ball)
    live = _live(ball)
    ops_of(bk).cache_switch.switch_to_cache(ball, path, "PC2", FIRST)
    bk.bake(ball, bpy.context.scene, path, FIRST, LAST)
    assert ops_of(bk).cache_modifier.using_cache(ball) and not _vp_modifier(ball).show_viewport, "state restored"
    frames, _, _ = pcache.read_pc2(path)
    np.testing.assert_array_equal(frames, live)
    np.testing.assert_array_equal(_live(ball), live)


def test_cancel_or_failure_leaves_nothing_under_the_final_name(bk, tmp_path):
    ball, _ = _rig()
    scene = bpy.context.scene
    scene.frame_set(2)
    path = tmp_path / "ball.pc2"
    with pytest.raises(bk.BakeCancelled):
        bk.bake(ball, scene, str(path), FIRST, LAST, cancelled=lambda: scene.frame_current >= 4)
    assert os.listdir(tmp_path) == [], "no file, no temporary file"
    assert scene.frame_current == 2 and _vp_modifier(ball).show_viewport

    def explode(done, total):
        if done == 5:
            raise RuntimeError("disk on fire")
    with pytest.raises(RuntimeError, match="(?i)disk on fire"):
        bk.bake(ball, scene, str(path), FIRST, LAST, progress=explode)
    assert os.listdir(tmp_path) == []

    # An earlier cache under that name survives a cancelled re-bake untouched.
    bk.bake(ball, scene, str(path), FIRST, 3)
    before = path.read_bytes()
    with pytest.raises(bk.BakeCancelled):
        bk.bake(ball, scene, str(path), FIRST, LAST, cancelled=lambda: scene.frame_current >= 6)
    assert path.read_bytes() == before and os.listdir(tmp_path) == ["ball.pc2"]


def test_bad_paths_are_refused(bk, tmp_path):
    ball, _ = _rig()
    scene = bpy.context.scene
    assert bpy.data.filepath == ""

    def refused(filepath, match, fmt="PC2", **kw):
        with pytest.raises(ops_of(bk).bake_files.BakeError, match=match):
            bk.bake(ball, scene, filepath, FIRST, 2, fmt=fmt, **kw)

    refused("//ball.pc2", "not saved")                        # relative to an unsaved file
    refused("ball.pc2", "relative path")                      # would land in the working folder
    refused("", "choose a file")
    refused(str(tmp_path / "ball.txt"), "must end in '.pc2'")
    refused(str(tmp_path / "ball.pc2"), "must end in '.mdd'", fmt="MDD")
    refused(str(tmp_path / "ball.pc2"), "unknown cache format", fmt="OBJ")
    (tmp_path / "folder.pc2").mkdir()
    refused(str(tmp_path / "folder.pc2"), "is a folder")
    notes = tmp_path / "notes.pc2"
    notes.write_text("not a cache")
    refused(str(notes), "not a PC2 cache")
    assert notes.read_text() == "not a cache"
    refused(str(tmp_path / "missing" / "ball.pc2"), "does not exist")
    assert not (tmp_path / "missing").exists()
    refused(str(tmp_path / "a" / "b" / "ball.pc2"), "does not exist", make_folder=True)
    assert not (tmp_path / "a").exists(), "only the file's own folder may be created"
    with pytest.raises(ops_of(bk).bake_files.BakeError, match="before the start"):
        bk.bake(ball, scene, str(tmp_path / "x.pc2"), 5, 4)
    assert sorted(os.listdir(tmp_path)) == ["folder.pc2", "notes.pc2"]

    # Asked for, the one missing folder is made.
    bk.bake(ball, scene, str(tmp_path / "caches" / "ball.pc2"), FIRST, 2, make_folder=True)
    assert pcache.read_pc2(tmp_path / "caches" / "ball.pc2")[0].shape[0] == 2

    # The operator refuses the same way (errors reach Python as RuntimeError) and writes nothing.
    with bpy.context.temp_override(object=ball, active_object=ball):
        with pytest.raises(RuntimeError, match="(?i)not saved"):
            bpy.ops.object.vpffd_bake(filepath="//ball.pc2")
        with pytest.raises(RuntimeError, match="(?i)not a PC2 cache"):
            bpy.ops.object.vpffd_bake(filepath=str(notes))
    assert notes.read_text() == "not a cache"

    # Modifiers before VP-FFD and mesh shape keys are baked in: the cache holds what the slot gives.
    twist = ball.modifiers.new("Twist", "SIMPLE_DEFORM")
    twist.angle = 0.6
    with bpy.context.temp_override(object=ball, active_object=ball):
        bpy.ops.object.modifier_move_to_index(modifier=twist.name, index=0)
    ball.shape_key_add(name="Basis")
    path = tmp_path / "y.pc2"
    bk.bake(ball, scene, str(path), FIRST, 2)
    scene.frame_set(2)
    live = ops_of(bk).update.slot_output(ball)
    np.testing.assert_array_equal(pcache.read_pc2(path)[0][-1], live)
    assert not np.array_equal(live, np.array([v.co for v in ball.data.vertices], np.float32))


def test_switch_refuses_a_cache_that_does_not_fit(bk, tmp_path):
    ball, _ = _rig()
    other = tmp_path / "other.pc2"
    pcache.write_pc2(str(other), np.zeros((2, 5, 3)))
    with pytest.raises(ops_of(bk).bake_files.BakeError, match="5 points"):
        ops_of(bk).cache_switch.switch_to_cache(ball, str(other), "PC2", 1)
    with pytest.raises(ops_of(bk).bake_files.BakeError, match="does not exist"):
        ops_of(bk).cache_switch.switch_to_cache(ball, str(tmp_path / "none.pc2"), "PC2", 1)
    assert ops_of(bk).cache_modifier.find_cache(ball) is None and _vp_modifier(ball).show_viewport


def test_operator_bakes_and_switches(bk, tmp_path):
    ball, _ = _rig()
    live = _live(ball, range(2, 6))
    with bpy.context.temp_override(object=ball, active_object=ball):
        assert bpy.ops.object.vpffd_bake(filepath=str(tmp_path / "op.mdd"), format="MDD",
                                         frame_start=2, frame_end=5) == {"FINISHED"}
    np.testing.assert_array_equal(pcache.read_mdd(tmp_path / "op.mdd")[0], live)
    assert ops_of(bk).cache_modifier.using_cache(ball) and ops_of(bk).cache_modifier.find_cache(ball).cache_format == "MDD"
    np.testing.assert_array_equal(_live(ball, range(2, 6)), live)


def test_operator_on_an_unsaved_file_bakes_into_the_temporary_folder(bk, tmp_path):
    assert not bpy.data.filepath
    ball, _ = _rig()
    live = _live(ball, range(2, 4))
    prefs = bpy.context.preferences.filepaths
    before = prefs.temporary_directory
    prefs.temporary_directory = str(tmp_path)
    try:
        with bpy.context.temp_override(object=ball, active_object=ball):
            assert bpy.ops.object.vpffd_bake(frame_start=2, frame_end=3) == {"FINISHED"}
    finally:
        prefs.temporary_directory = before
    path = tmp_path / "vpffd_Ball.pc2"
    np.testing.assert_array_equal(pcache.read_pc2(path)[0], live)
    assert ops_of(bk).cache_modifier.find_cache(ball).filepath == str(path)


_FRESH_SCRIPT = textwrap.dedent("""
    import json, sys
    import numpy as np
    import bpy
    blend, out, first, last = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    bpy.ops.wm.open_mainfile(filepath=blend)
    ob = bpy.data.objects["Ball"]
    scene = bpy.context.scene
    coords = []
    for f in range(first, last + 1):
        scene.frame_set(f)
        me = ob.evaluated_get(bpy.context.evaluated_depsgraph_get()).data
        buf = np.empty(len(me.vertices) * 3, np.float32)
        me.vertices.foreach_get("co", buf)
        coords.append(buf.reshape(-1, 3))
    np.save(out, np.stack(coords))
    report = {
        "version": bpy.app.version_string,
        "addons": sorted(bpy.context.preferences.addons.keys()),
        "vpffd_modules": sorted(m for m in sys.modules if "vpffd" in m),
        "object_has_vpffd_rna": "vpffd" in bpy.types.Object.bl_rna.properties,
        "operators": [hasattr(bpy.types, n)
                      for n in ("OBJECT_OT_vpffd_bind", "OBJECT_OT_vpffd_bake")],
        "modifiers": [[m.name, m.type, m.show_viewport, m.show_render] for m in ob.modifiers],
        "handlers": [h.__name__ for h in bpy.app.handlers.frame_change_post],
    }
    print("VPFFD-FRESH " + json.dumps(report), flush=True)
""")


def test_saved_file_reproduces_the_frames_without_the_extension(bk, tmp_path):
    """The issue's acceptance test: bake, switch, save; a fresh Python process with its own
    empty Blender user folder (no extension installed) opens the file and gets every frame
    through the Mesh Cache modifier within 1e-6 of the live volume-preserved result."""
    ball, _ = _rig()
    live = _live(ball)
    blend = tmp_path / "scene" / "squash.blend"
    blend.parent.mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    ball = bpy.data.objects["Ball"]
    with bpy.context.temp_override(object=ball, active_object=ball):
        # A path relative to the .blend: the file and its cache move to the farm together.
        assert bpy.ops.object.vpffd_bake(filepath="//cache/squash.pc2", make_folder=True,
                                         frame_start=FIRST, frame_end=LAST) == {"FINISHED"}
    assert ops_of(bk).cache_modifier.find_cache(ball).filepath == "//cache/squash.pc2"
    bpy.ops.wm.save_mainfile()

    farm = tmp_path / "farm"                       # the file and its cache, moved elsewhere
    (farm / "cache").mkdir(parents=True)
    (farm / "squash.blend").write_bytes(blend.read_bytes())
    baked = blend.parent / "cache" / "squash.pc2"
    (farm / "cache" / "squash.pc2").write_bytes(baked.read_bytes())

    user = tmp_path / "fresh-user"
    user.mkdir()
    env = dict(os.environ)
    env[eh.ENV] = str(user)
    out = tmp_path / "fresh.npy"
    proc = subprocess.run(
        [sys.executable, "-c", _FRESH_SCRIPT, str(farm / "squash.blend"), str(out),
         str(FIRST), str(LAST)],
        capture_output=True, text=True, timeout=240, env=env, cwd=str(user))
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("VPFFD-FRESH ")]
    assert proc.returncode == 0 and lines, (
        f"exit {proc.returncode}\nstdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}")
    report = json.loads(lines[-1][len("VPFFD-FRESH "):])
    assert report["vpffd_modules"] == [] and not report["object_has_vpffd_rna"], report
    assert report["operators"] == [False, False] and not any("vpffd" in a for a in report["addons"])
    assert report["modifiers"] == [["VP-FFD Cache", "MESH_CACHE", True, True],
                                   ["VP-FFD", "NODES", False, False]], report["modifiers"]

    fresh = np.load(out)
    assert fresh.shape == live.shape
    err = float(np.abs(fresh.astype(np.float64) - live).max())
    assert err <= 1e-6, f"max deviation {err:g} from the live result"


# ------------------------------------------- the modal path and the panel, driven with stand-ins
# Headless Blender has no window, so the operator runs its blocking path there. The modal path's
# own logic (a frame or more per timer event, progress, Esc) is driven here with stand-in
# context, event and operator objects; Blender's event loop itself is not.

class _Recorder:
    """Stands in for a window manager, workspace or layout: records every call."""

    def __init__(self, log, name="layout"):
        self.log, self.name = log, name

    def __getattr__(self, attr):
        def call(*args, **kw):
            self.log.append((self.name, attr, args, kw))
            return _Recorder(self.log, self.name)
        return call


def _modal_operator(bk, baker, filepath, use_switch):
    from types import SimpleNamespace
    op_cls = ops_of(bk).bake_ops.OBJECT_OT_vpffd_bake
    reports = []
    op = SimpleNamespace(_baker=baker, _timer=object(), filepath=filepath, use_switch=use_switch,
                         report=lambda kind, text: reports.append((set(kind), text)))
    for name in ("modal", "_modal", "_stop", "_status", "_finish", "cancel"):
        setattr(op, name, getattr(op_cls, name).__get__(op))
    log = []
    context = SimpleNamespace(window_manager=_Recorder(log, "wm"), workspace=_Recorder(log, "ws"))
    return op, context, reports, log


def test_modal_logic_with_recorded_window_calls(bk, tmp_path, monkeypatch):
    """The modal bake's bookkeeping, frame by frame, with the events and window-manager calls
    recorded (a stand-in context, not Blender's event loop): one frame per timer event, progress
    numbers, the Esc branch's report. Blender's real event loop, its progress display and a real
    Escape key press are tested in its window (tests/e2e/gui_session.py)."""
    from types import SimpleNamespace
    monkeypatch.setattr(ops_of(bk).bake_ops, "_MODAL_BUDGET_S", 0.0)   # one frame per timer event
    ball, _ = _rig()
    live = _live(ball)
    scene = bpy.context.scene
    path = str(tmp_path / "modal.pc2")

    baker = bk.Baker(ball, scene, path, FIRST, LAST)
    baker.start()
    op, context, reports, log = _modal_operator(bk, baker, path, use_switch=True)
    # Only what Blender's events have: type and value (no reference to the timer).
    other = SimpleNamespace(type="MOUSEMOVE", value="NOTHING")
    tick = SimpleNamespace(type="TIMER", value="NOTHING")
    assert op.modal(context, other) == {"RUNNING_MODAL"} and baker.done == 0
    states = [op.modal(context, tick) for _ in FRAMES]
    assert states == [{"RUNNING_MODAL"}] * (len(FRAMES) - 1) + [{"FINISHED"}]
    assert [c[2][0] for c in log if c[1] == "progress_update"] == list(range(1, len(FRAMES) + 1))
    assert ("wm", "progress_end", (), {}) in log and op._timer is None
    np.testing.assert_array_equal(pcache.read_pc2(path)[0], live)
    assert ops_of(bk).cache_modifier.using_cache(ball) and reports and "baked frames 1-10" in reports[-1][1].lower()

    ops_of(bk).cache_switch.switch_to_live(ball)
    before = open(path, "rb").read()
    baker = bk.Baker(ball, scene, path, FIRST, LAST)
    baker.start()
    op, context, reports, log = _modal_operator(bk, baker, path, use_switch=True)
    for _ in range(3):
        assert op.modal(context, tick) == {"RUNNING_MODAL"}
    esc = SimpleNamespace(type="ESC", value="PRESS")
    assert op.modal(context, esc) == {"CANCELLED"}
    assert reports[-1][0] == {"WARNING"} and "cancelled after 3 of 10" in reports[-1][1].lower()
    assert open(path, "rb").read() == before and os.listdir(tmp_path) == ["modal.pc2"]
    assert not ops_of(bk).cache_modifier.using_cache(ball) and _vp_modifier(ball).show_viewport


def test_draw_bake_offers_the_right_buttons(bk, tmp_path):
    ball, _ = _rig()

    def drawn():
        log = []
        ops_of(bk).bake_ops.draw_bake(_Recorder(log), ball)
        return [c[2][0] for c in log if c[1] == "operator"]

    assert drawn() == ["object.vpffd_bake"]
    bk.bake(ball, bpy.context.scene, str(tmp_path / "b.pc2"), FIRST, 3, switch=True)
    assert drawn() == ["object.vpffd_bake", "object.vpffd_use_live"]
    ops_of(bk).cache_switch.switch_to_live(ball)
    assert drawn() == ["object.vpffd_bake", "object.vpffd_use_cache"]


def test_status_panel_logic_in_a_recording_layout(bk, tmp_path):
    """The Status sub-panel's draw(), into a recording layout (a stand-in, not Blender's UI):
    figures while VP-FFD solves (the volume as the status measured it), none while the modifier
    is off or the baked cache plays. The real panel is drawn and captured in Blender's window
    (tests/e2e/gui_session.py)."""
    import importlib
    from types import SimpleNamespace
    status_panel = importlib.import_module(bk.__package__ + ".panel").OBJECT_PT_vpffd_status
    ball, _ = _rig()
    bpy.context.scene.frame_set(6)

    def drawn():
        log = []
        fake = SimpleNamespace(layout=_Recorder(log))
        context = SimpleNamespace(object=ball, region=None, preferences=bpy.context.preferences)
        status_panel.draw(fake, context)
        return " ".join(c[3].get("text", "") for c in log if c[1] == "label")

    info = ops_of(bk).status.status(ball)
    text = drawn()
    plain = f"Lattice modifier would give {info.plain_percent:.3f}% of its input"
    assert plain in text and "switched off" not in text
    _vp_modifier(ball).show_viewport = False
    bpy.context.view_layer.update()
    text = drawn()
    assert "switched off" in text and "would give" not in text
    _vp_modifier(ball).show_viewport = True
    bpy.context.view_layer.update()
    bk.bake(ball, bpy.context.scene, str(tmp_path / "s.pc2"), FIRST, 3, switch=True)
    text = drawn()
    assert "playing the baked cache" in text.lower() and "would give" not in text


@pytest.mark.parametrize("how", ["apply", "remove"])
def test_blenders_apply_or_remove_after_a_bake_leaves_nothing_of_vpffds(bk, tmp_path, how):
    """Bake, switch back to the live solve (the cache modifier stays, switched off), then
    Blender's own Apply (Ctrl+A) or X on the VP-FFD modifier: the switched-off cache goes with it,
    and so does the solver helper; a cache that is playing stays (it is what is shown)."""
    ball, _ = _rig()
    scene = bpy.context.scene
    bk.bake(ball, scene, str(tmp_path / "b.pc2"), FIRST, LAST, switch=True)
    ops_of(bk).cache_switch.switch_to_live(ball)
    scene.frame_set(6)
    helper_name = ops_of(bk).node_group.get_input(_vp_modifier(ball), ops_of(bk).node_group.SOLVER_INPUT).name
    if how == "apply":
        with bpy.context.temp_override(object=ball, active_object=ball):
            assert bpy.ops.object.modifier_apply(modifier=_vp_modifier(ball).name) == {"FINISHED"}
    else:
        ball.modifiers.remove(_vp_modifier(ball))
    bpy.context.view_layer.update()
    assert not ball.vpffd.is_bound
    assert [m.name for m in ball.modifiers] == []
    assert bpy.data.objects.get(helper_name) is None, "the solver helper was left behind"

    # A playing cache stays when the VP-FFD modifier goes: it is what the object shows.
    ball2, _ = _rig("Ball2")
    bk.bake(ball2, scene, str(tmp_path / "c.pc2"), FIRST, LAST, switch=True)
    assert ops_of(bk).cache_modifier.using_cache(ball2)
    ball2.modifiers.remove(_vp_modifier(ball2))
    bpy.context.view_layer.update()
    assert [m.name for m in ball2.modifiers] == ["VP-FFD Cache"]
