"""What a user does in Blender's real window, driven from timers inside the GUI (not `-b`).

Run by `gui_window.run_session` as `blender --python gui_session.py -- OUT_DIR`: Blender opens its
window on a virtual display; this script registers one timer that steps through a generator. Each
`yield SECONDS` hands control back to Blender's event loop (playback, undo steps, modal
operators and redraws happen only there). Operators run with the window's own 3D viewport in
their context, as a click or a shortcut would run them. A screenshot is asked of the host (which
captures the X display) by writing OUT_DIR/shot-NAME.request and waiting for
OUT_DIR/shot-NAME.png.

Writes OUT_DIR/results.json: {"checks": [[name, ok, detail], ...], "error": traceback or null},
then quits Blender. The host test asserts on it; nothing here asserts.
"""
import json
import os
import sys
import time
import traceback

import bmesh
import bpy
import numpy as np

OUT = sys.argv[sys.argv.index("--") + 1]
CHECKS = []
VOLUME_TOL = 1e-5


def check(name, ok, detail=""):
    CHECKS.append([name, bool(ok), str(detail)])


def operators():
    name = next(m for m in sys.modules if m.endswith(".operators") and "vpffd" in m)
    return sys.modules[name]


def window_context():
    win = bpy.context.window_manager.windows[0]
    area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
    region = next(r for r in area.regions if r.type == "WINDOW")
    return dict(window=win, screen=win.screen, area=area, region=region)


def op(path, **kw):
    """Run bpy.ops.PATH in the window's 3D viewport as the user's click would: with an undo step
    (a call from Python pushes none unless asked)."""
    fn = bpy.ops
    for part in path.split("."):
        fn = getattr(fn, part)
    with bpy.context.temp_override(**window_context()):
        return fn("EXEC_DEFAULT", True, **kw)


def show_modifier_tab():
    win = bpy.context.window_manager.windows[0]
    for area in win.screen.areas:
        if area.type == "PROPERTIES":
            area.spaces[0].context = "MODIFIER"


def framed(objects):
    """(whether the window's 3D viewport looks through the camera, the share of the view's width
    that the objects' bounds span, whether every bound corner lies inside the view)."""
    from bpy_extras.view3d_utils import location_3d_to_region_2d
    from mathutils import Vector
    ctx = window_context()
    region, rv3d = ctx["region"], ctx["area"].spaces[0].region_3d
    xs, inside = [], True
    for ob in objects:
        for corner in ob.bound_box:
            p = location_3d_to_region_2d(region, rv3d, ob.matrix_world @ Vector(corner))
            inside = inside and p is not None and 0 <= p.x <= region.width and 0 <= p.y <= region.height
            xs.append(p.x if p is not None else np.nan)
    return rv3d.view_perspective == "CAMERA", float(np.ptp(xs) / region.width), inside


def select_only(ob):
    layer = bpy.context.window_manager.windows[0].view_layer
    for o in layer.objects:
        o.select_set(o == ob)
    layer.objects.active = ob


def depsgraph():
    return bpy.context.window_manager.windows[0].view_layer.depsgraph


def mesh_arrays(me):
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    me.calc_loop_triangles()
    tris = np.empty(len(me.loop_triangles) * 3, np.int32)
    me.loop_triangles.foreach_get("vertices", tris)
    return co.reshape(-1, 3), tris.reshape(-1, 3)


def volume(co, tris):
    """Enclosed volume from float32 coordinates, in float64 about the centroid (independent of
    VP-FFD's own measurement)."""
    v = co.astype(np.float64)
    v -= v.mean(0)
    a, b, c = v[tris[:, 0]], v[tris[:, 1]], v[tris[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def evaluated(ob):
    ob_eval = ob.evaluated_get(depsgraph())
    me = ob_eval.to_mesh()
    try:
        return mesh_arrays(me)
    finally:
        ob_eval.to_mesh_clear()


def ratio(ob):
    """(evaluated volume / the mesh's own volume, evaluated coordinates): nothing sits before
    VP-FFD in the demos, so what reaches its slot is the mesh itself."""
    co, tris = evaluated(ob)
    own = volume(*mesh_arrays(ob.data))
    return volume(co, tris) / own, co


def screenshot(name):
    """Ask the host for a capture of the display; wait (in the event loop) until it is there."""
    request = os.path.join(OUT, f"shot-{name}.request")
    done = os.path.join(OUT, f"shot-{name}.png")
    open(request, "w").close()
    t0 = time.time()
    while not os.path.exists(done) and time.time() - t0 < 30:
        yield 0.2
    check(f"screenshot {name}", os.path.exists(done))


def press(key):
    """Ask the host to press `key` (an X keysym, e.g. Escape) on the display with xdotool: a real
    key event through the X server and Blender's own event queue. Waits until it was sent."""
    request = os.path.join(OUT, f"key-{key}.request")
    open(request, "w").close()
    t0 = time.time()
    while os.path.exists(request) and time.time() - t0 < 60:
        yield 0.1
    check(f"key {key} pressed", not os.path.exists(request))


def info_log():
    """The text of the Info editor's reports, read from the real UI: an area is switched to the
    Info editor, its reports selected and copied (Ctrl+C there), and the clipboard read."""
    win = bpy.context.window_manager.windows[0]
    area = next(a for a in win.screen.areas if a.type == "DOPESHEET_EDITOR" or a.ui_type == "TIMELINE")
    saved = area.ui_type
    area.ui_type = "INFO"
    try:
        region = next(r for r in area.regions if r.type == "WINDOW")
        with bpy.context.temp_override(window=win, screen=win.screen, area=area, region=region):
            bpy.ops.info.select_all(action="SELECT")
            bpy.ops.info.report_copy()
        return bpy.context.window_manager.clipboard
    finally:
        area.ui_type = saved


def session():
    ops = operators()
    prefs = bpy.context.preferences
    prefs.view.show_splash = False
    yield 0.5
    # The user's own scene and how its viewport looks, before any demo opens its own scene.
    user_scene = bpy.context.window_manager.windows[0].scene.name    # undo renews the data: by name
    user_view = window_context()["area"].spaces[0].region_3d
    view_before = (user_view.view_perspective, tuple(user_view.view_location), user_view.view_distance)

    # Add > VP-FFD Demos > Bouncing Ball, as from the Add menu.
    op("object.vpffd_demo_bouncing_ball")
    show_modifier_tab()
    ball = bpy.context.window_manager.windows[0].view_layer.objects.active
    check("demo leaves the VP-FFD ball active and selected",
          ball is not None and ball.vpffd.is_bound and ball.select_get(), getattr(ball, "name", None))
    lattice = ball.vpffd.lattice
    ball_name, lat_name = ball.name, lattice.name
    scene = bpy.context.window_manager.windows[0].scene
    scene.frame_set(18)                       # the squash
    yield 1.0
    demo_objects = [ob for ob in scene.objects if ob.type == "MESH" and ob.name.startswith("Ball")]
    camera, share, inside = framed(demo_objects)
    check("the demo frames itself: camera view, the balls in view and not small",
          camera and inside and share >= 0.25, (camera, share, inside, [o.name for o in demo_objects]))
    r, _ = ratio(ball)
    info = ops.status.status(ball)
    check("squash keeps the volume (evaluated mesh)", abs(r - 1) <= VOLUME_TOL, r)
    check("without numba (Debian's Blender, the universal package) NumPy solves and the panel "
          "says why", info.kernels == "NumPy" and "numba is not installed" in (info.kernels_why or ""),
          (info.kernels, info.kernels_why))
    check("panel figure is the measured volume", info.volume_percent is not None
          and abs(info.volume_percent / 100 - abs(r)) <= 1e-6, (info.volume_percent, r))
    yield from screenshot("panel")

    # Show Corrected Lattice: the overlay draws in the viewport.
    ball.vpffd.show_overlay = True
    yield 0.5
    check("overlay has the corrected lattice", ops.overlay.overlay_geometry(ball) is not None)
    yield from screenshot("overlay")
    ball.vpffd.enabled = False                # switched off: nothing stale is drawn or shown
    yield 0.5
    info = ops.status.status(ball)
    check("switched off: no overlay and no figures", ops.overlay.overlay_geometry(ball) is None
          and info.volume_percent is None and info.switched_off, info)
    ball.vpffd.enabled = True
    ball.vpffd.show_overlay = False
    yield 0.5

    # Hide (H) and unhide (Alt+H) on the squashed frame: the corrected shape comes back exactly,
    # with no error.
    _, before = ratio(ball)
    select_only(ball)
    op("object.hide_view_set")
    yield 0.5
    check("hidden: no error in the panel", ops.status.status(ball).error is None, ops.status.status(ball).error)
    op("object.hide_view_clear")
    yield 0.5
    _, after = ratio(ball)
    check("unhidden (Alt+H): the corrected shape is back", float(np.abs(after - before).max()) <= 1e-6,
          float(np.abs(after - before).max()))
    check("unhidden: no error in the panel", ops.status.status(ball).error is None, ops.status.status(ball).error)
    select_only(ball)

    # Playback (Space): every frame shown keeps the volume.
    scene.frame_set(1)
    yield 0.3
    seen = {}
    op("screen.animation_play")
    # Waits for frames, not for a time: a busy machine plays slower, never fewer frames (the
    # time-out is only there so that a playback that never advances ends the session).
    t0 = time.time()
    while len(seen) < 5 and time.time() - t0 < 180:
        yield 0.15
        r, _ = ratio(ball)
        seen[scene.frame_current] = r
    op("screen.animation_cancel", restore_frame=False)
    worst = max(abs(r - 1) for r in seen.values()) if seen else None
    check("playback ran through frames", len(seen) >= 5, sorted(seen))
    check("playback keeps the volume on every frame seen", worst is not None and worst <= VOLUME_TOL, worst)

    # Lattice Edit Mode: Tab, select all, scale along Z; the mesh follows live, volume kept.
    scene.frame_set(1)
    yield 0.3
    _, before = ratio(ball)
    select_only(lattice)
    op("object.mode_set", mode="EDIT")
    op("lattice.select_all", action="SELECT")
    op("transform.resize", value=(1.0, 1.0, 0.6))
    yield 0.5
    r, during = ratio(ball)
    check("lattice Edit Mode: the mesh follows", float(np.abs(during - before).max()) > 1e-3,
          float(np.abs(during - before).max()))
    check("lattice Edit Mode: the volume is kept", abs(r - 1) <= VOLUME_TOL, r)
    op("object.mode_set", mode="OBJECT")
    yield 0.5
    r, edited = ratio(ball)
    check("after Edit Mode the volume is kept", abs(r - 1) <= VOLUME_TOL, r)

    # Undo (Ctrl+Z) step by step back to before the edit, through the lattice's Edit Mode steps,
    # then Redo (Ctrl+Shift+Z) as many: every state shows its own shape with the volume kept.
    ratios, steps = [], 0
    while steps < 8:
        op("ed.undo")
        steps += 1
        yield 0.6
        r, undone = ratio(bpy.data.objects[ball_name])
        ratios.append(r)
        lat_now = bpy.data.objects[lat_name]
        if lat_now.mode == "OBJECT" and float(np.abs(undone - before).max()) <= 1e-5:
            break
    check("undo reaches the shape before the edit", float(np.abs(undone - before).max()) <= 1e-5,
          (steps, float(np.abs(undone - before).max())))
    for _ in range(steps):
        op("ed.redo")
        yield 0.6
        r, redone = ratio(bpy.data.objects[ball_name])
        ratios.append(r)
    check("redo shows the edited shape again", float(np.abs(redone - edited).max()) <= 1e-5,
          float(np.abs(redone - edited).max()))
    worst = max(abs(r - 1) for r in ratios)
    check("every undo and redo step keeps the volume", worst <= VOLUME_TOL, (worst, len(ratios)))
    if bpy.data.objects[lat_name].mode != "OBJECT":
        select_only(bpy.data.objects[lat_name])
        op("object.mode_set", mode="OBJECT")
        yield 0.3

    # The mesh's own Edit Mode (Tab): the deformation stays, solved live from the mesh as edited.
    ball = bpy.data.objects[ball_name]        # undo replaced the Python objects
    _, shown = ratio(ball)
    select_only(ball)
    op("object.mode_set", mode="EDIT")
    yield 0.8
    co, _ = evaluated(ball)
    check("mesh Edit Mode: the deformed shape stays", float(np.abs(co - shown).max()) <= 1e-6,
          float(np.abs(co - shown).max()))
    op("mesh.select_all", action="SELECT")
    op("transform.resize", value=(1.0, 1.0, 1.3))
    yield 0.8
    bm = bmesh.from_edit_mesh(ball.data)
    edited = np.array([tuple(v.co) for v in bm.verts], np.float32)
    co, tris = evaluated(ball)
    info = ops.status.status(ball)
    r = volume(co, tris) / volume(edited, tris)
    check("mesh Edit Mode: the edit shows deformed, the volume of the mesh as edited kept",
          abs(r - 1) <= VOLUME_TOL and float(np.abs(co - shown).max()) > 1e-2, (r, float(np.abs(co - shown).max())))
    check("mesh Edit Mode: the panel says it solves the mesh as edited", info.editing
          and info.error is None and abs(info.volume_percent / 100 - r) <= 1e-6, info)
    yield from screenshot("editmode")
    op("ed.undo")                             # the edit goes; Edit Mode stays
    yield 0.8
    op("object.mode_set", mode="OBJECT")
    yield 0.8
    ball = bpy.data.objects[ball_name]
    r, back = ratio(ball)
    check("after the mesh's Edit Mode: the shape before it", float(np.abs(back - shown).max()) <= 1e-5
          and abs(r - 1) <= VOLUME_TOL, (float(np.abs(back - shown).max()), r))

    # Ctrl+A on the VP-FFD modifier (Blender's own Apply): the mesh keeps what was shown.
    ball = bpy.data.objects[ball_name]
    check("after undo and redo the panel matches the mesh",
          abs(ops.status.status(ball).volume_percent / 100 - abs(ratio(ball)[0])) <= 1e-6,
          (ops.status.status(ball).volume_percent, ratio(ball)[0]))
    lattice = ball.vpffd.lattice
    scene = bpy.context.window_manager.windows[0].scene
    scene.frame_set(18)
    yield 0.5
    _, shown = ratio(ball)
    select_only(ball)
    mod = next(m for m in ball.modifiers if m.type == "NODES" and "VP-FFD" in m.name)
    op("object.modifier_apply", modifier=mod.name)
    yield 0.5
    own, _ = mesh_arrays(ball.data)
    check("Apply makes the shown shape the mesh's own", float(np.abs(own - shown).max()) <= 1e-5,
          float(np.abs(own - shown).max()))
    check("Apply leaves the object unbound, without VP-FFD attributes", not ball.vpffd.is_bound
          and not [a.name for a in ball.data.attributes if a.name.startswith("vpffd")],
          [a.name for a in ball.data.attributes])
    op("ed.undo")
    yield 0.8
    ball = bpy.data.objects[ball_name]
    lattice = ball.vpffd.lattice
    r, _ = ratio(ball)
    check("undo of Apply: bound and correcting again", ball.vpffd.is_bound and abs(r - 1) <= VOLUME_TOL, r)

    # Delete the lattice (X): the mesh shows undeformed and the panel says why. A twin with
    # Blender's Lattice modifier on the same lattice shows what undo and redo should do.
    op("mesh.primitive_ico_sphere_add", radius=0.5, location=(0.0, 3.0, 1.0))
    yield 0.3
    twin_name = bpy.context.window_manager.windows[0].view_layer.objects.active.name
    op("object.modifier_add", type="LATTICE")
    bpy.data.objects[twin_name].modifiers[-1].object = lattice
    op("ed.undo_push", message="Twin's lattice")
    yield 0.5

    def linked():
        ball, twin = bpy.data.objects[ball_name], bpy.data.objects[twin_name]
        return (ball.vpffd.lattice is not None, twin.modifiers[-1].object is not None
                and any(True for _ in twin.modifiers[-1].object.users_scene))

    _, shown = ratio(ball)
    select_only(lattice)
    op("object.delete")
    yield 0.8
    ball = bpy.data.objects[ball_name]
    co, _ = evaluated(ball)
    own, _ = mesh_arrays(ball.data)
    info = ops.status.status(ball)
    check("deleted lattice: the mesh shows undeformed", float(np.abs(co - own).max()) <= 1e-6,
          float(np.abs(co - own).max()))
    check("deleted lattice: the panel says so", "deleted" in (info.error or ""), info.error)
    # One Ctrl+Z brings the lattice, the link, the corrected shape and the panel back, as it
    # brings back the twin's; Ctrl+Shift+Z deletes it again; Ctrl+Z once more restores it.
    for step, expect in (("ed.undo", True), ("ed.redo", False), ("ed.undo", True)):
        op(step)
        yield 0.8
        ball = bpy.data.objects[ball_name]
        r, now = ratio(ball)
        error = ops.status.status(ball).error
        if expect:
            check(f"after Delete, {step}: linked again in one step, as Blender's Lattice modifier",
                  linked() == (True, True) and error is None, (linked(), error))
            check(f"after Delete, {step}: the corrected shape is back",
                  float(np.abs(now - shown).max()) <= 1e-6 and abs(r - 1) <= VOLUME_TOL,
                  (float(np.abs(now - shown).max()), r))
        else:
            check(f"after Delete, {step}: deleted again, the panel says so",
                  linked() == (False, False) and "deleted" in (error or ""), (linked(), error))

    # Unbind, then Ctrl+Z: bound and correcting again, the same shape.
    ball = bpy.data.objects[ball_name]
    select_only(ball)
    op("object.vpffd_unbind")
    yield 0.5
    ball = bpy.data.objects[ball_name]
    check("Unbind: the mesh shows its own shape", not ball.vpffd.is_bound and float(
        np.abs(evaluated(ball)[0] - mesh_arrays(ball.data)[0]).max()) <= 1e-6)
    op("ed.undo")
    yield 0.8
    ball = bpy.data.objects[ball_name]
    r, now = ratio(ball)
    check("undo of Unbind: bound, the same corrected shape", ball.vpffd.is_bound
          and float(np.abs(now - shown).max()) <= 1e-6 and ops.status.status(ball).error is None,
          (ball.vpffd.is_bound, float(np.abs(now - shown).max()), ops.status.status(ball).error))

    # A bake in progress, on the cage demo (slow enough to be seen).
    op("object.vpffd_demo_squeezed_tube")
    yield 0.5                                 # the Properties editor learns the new active object
    show_modifier_tab()
    tube = bpy.context.window_manager.windows[0].view_layer.objects.active
    path = os.path.join(OUT, "tube.pc2")
    with bpy.context.temp_override(**window_context(), object=tube, active_object=tube):
        bpy.ops.object.vpffd_bake("EXEC_DEFAULT", filepath=path)
    yield 0.3
    yield from screenshot("bake")
    t0 = time.time()
    while not os.path.exists(path) and time.time() - t0 < 120:
        yield 0.5
    check("the bake finishes in the window", os.path.exists(path))
    yield 0.5

    def playing(ob):
        """Names and viewport switches of the modifiers: what plays the tube."""
        return [(m.type, m.show_viewport) for m in ob.modifiers]

    tube_name = tube.name
    baked = playing(tube)
    # Ctrl+Z after the bake: the live solve again (the file stays: undo does not touch files);
    # Ctrl+Shift+Z: the cache plays again.
    op("ed.undo")
    yield 0.8
    tube = bpy.data.objects[tube_name]
    check("undo of a bake: the live solve plays, the volume kept",
          playing(tube)[-1] == ("NODES", True) and all(t != "MESH_CACHE" or not on for t, on in playing(tube))
          and ops.status.status(tube).error is None and ops.status.status(tube).volume_percent is not None,
          (baked, playing(tube), ops.status.status(tube).error))
    op("ed.redo")
    yield 0.8
    tube = bpy.data.objects[tube_name]
    check("redo of a bake: the cache plays again", playing(tube) == baked, (baked, playing(tube)))

    # Esc cancels a bake in progress: a long range, a real Escape key press once the bake has
    # stepped through a few frames; nothing is written, the live solve stays, the frame returns.
    with bpy.context.temp_override(**window_context(), object=tube, active_object=tube):
        bpy.ops.object.vpffd_use_live("EXEC_DEFAULT")
    yield 0.5
    scene = bpy.context.window_manager.windows[0].scene      # the demo made a scene of its own
    scene.frame_set(1)
    yield 0.3
    path = os.path.join(OUT, "tube-cancelled.pc2")
    with bpy.context.temp_override(**window_context(), object=tube, active_object=tube):
        started = bpy.ops.object.vpffd_bake("EXEC_DEFAULT", filepath=path, frame_start=1,
                                            frame_end=5000)
    check("a long bake starts as a modal operator", started == {"RUNNING_MODAL"}, started)
    frames = set()
    t0 = time.time()
    while len(frames) < 4 and time.time() - t0 < 120:
        yield 0.05
        frames.add(scene.frame_current)
    check("the bake steps through frames in the window", len(frames) >= 4, sorted(frames))
    yield from press("Escape")
    yield 1.0
    moved_after = scene.frame_current
    yield 1.0
    check("Esc stopped the bake (the frame no longer advances)", scene.frame_current == moved_after,
          (moved_after, scene.frame_current))
    leftovers = [n for n in os.listdir(OUT) if n.startswith("tube-cancelled")]
    check("a cancelled bake writes nothing", not leftovers, leftovers)
    log = info_log()
    check("the Info log says the bake was cancelled, and that nothing was written",
          "bake cancelled after" in log.lower() and "nothing was written" in log, log[-500:])
    check("after Esc the tube still solves live (no cache switched in)",
          [m.type for m in tube.modifiers if m.show_viewport][-1] == "NODES",
          [(m.name, m.type, m.show_viewport) for m in tube.modifiers])

    # Add > Lattice > VP-FFD Lattice Deform Selected, then one Ctrl+Z takes it all back.
    menu = getattr(bpy.types, "VIEW3D_MT_lattice_add", bpy.types.VIEW3D_MT_add)
    entries = [getattr(fn, "__module__", "") for fn in getattr(menu.draw, "_draw_funcs", [])]
    check("the Add menu offers VP-FFD Lattice Deform Selected",
          any(m.endswith(".operators.fit") for m in entries), entries)
    op("mesh.primitive_ico_sphere_add", radius=0.7, location=(4.0, 0.0, 1.0))
    yield 0.3
    sphere = bpy.context.window_manager.windows[0].view_layer.objects.active
    op("object.vpffd_lattice_deform_selected")
    yield 0.5
    layer = bpy.context.window_manager.windows[0].view_layer
    fitted = layer.objects.active
    check("Lattice Deform Selected: the fitted lattice is active, the sphere bound to it",
          fitted is not None and fitted.type == "LATTICE" and sphere.vpffd.is_bound
          and sphere.vpffd.lattice == fitted, (getattr(fitted, "type", None), sphere.vpffd.is_bound))
    fitted_name, sphere_name = fitted.name, sphere.name
    with bpy.context.temp_override(**window_context()):
        bpy.ops.view3d.view_selected()        # Numpad . on the fitted lattice, for the picture
        bpy.ops.view3d.zoom(delta=-2)
    show_modifier_tab()
    yield from screenshot("fit")
    op("ed.undo")
    yield 0.8
    sphere = bpy.data.objects.get(sphere_name)
    check("one Ctrl+Z removes the fitted lattice and the binding",
          bpy.data.objects.get(fitted_name) is None and sphere is not None
          and not sphere.vpffd.is_bound and not any(m.type == "NODES" for m in sphere.modifiers),
          (bpy.data.objects.get(fitted_name), sphere and sphere.vpffd.is_bound))

    yield from two_deformers(ops)

    # Add > VP-FFD Demos > Bent Arm: VP-FFD after an Armature (Target: Bind, a falloff lattice
    # around the elbow) gives back the volume the arm had at Bind; the Armature alone loses it.
    op("object.vpffd_demo_bent_arm")
    show_modifier_tab()
    arm = bpy.context.window_manager.windows[0].view_layer.objects.active
    check("bent-arm demo leaves the VP-FFD arm active, Target Bind, Outside Falloff",
          arm is not None and arm.vpffd.is_bound and arm.vpffd.target == "BIND"
          and arm.vpffd.outside == "FALLOFF", getattr(arm, "name", None))
    scene = bpy.context.window_manager.windows[0].scene
    scene.frame_set(30)                       # the deepest bend
    yield 1.0
    r, _ = ratio(arm)                         # bound in the rest pose: the mesh's own volume
    alone = next(ob for ob in scene.objects if ob.type == "MESH" and ob.name.startswith("Arm Armature"))
    r_alone = volume(*evaluated(alone)) / volume(*mesh_arrays(alone.data))
    info = ops.status.status(arm)
    check("bent arm: VP-FFD keeps the volume at Bind, the Armature alone loses it",
          abs(r - 1) <= VOLUME_TOL and r_alone < 0.95 and info.target_from == "bind",
          (r, r_alone, info.target_from))
    check("bent arm: the panel's figure is the measured share of the volume at Bind",
          info.volume_percent is not None and abs(info.volume_percent / 100 - abs(r)) <= 1e-6
          and abs(info.input_percent / 100 - r_alone) <= 1e-5, (info.volume_percent, info.input_percent, r, r_alone))
    arm.vpffd.show_overlay = True             # the corrected lattice and where the falloff ends
    yield 0.5
    check("bent arm: the overlay draws the falloff's box", ops.overlay.falloff_geometry(arm) is not None)
    yield from screenshot("arm")

    # Back to the user's own scene (the scene selector): its viewport shows the view it had
    # before the demos, not their camera view.
    bpy.context.window_manager.windows[0].scene = bpy.data.scenes[user_scene]
    yield 1.5
    rv3d = window_context()["area"].spaces[0].region_3d
    view_after = (rv3d.view_perspective, tuple(rv3d.view_location), rv3d.view_distance)
    check("back in the user's scene, the viewport shows the view it had before the demos",
          view_after[0] == view_before[0] != "CAMERA"
          and np.allclose(view_after[1], view_before[1], atol=1e-5)
          and abs(view_after[2] - view_before[2]) <= 1e-5, (view_before, view_after))
    yield from outliner_override(ops)


def outliner_override(ops):
    """A rig bound in its own file and linked into a shot, overridden from the Outliner's context
    menu (Library Override > Make > Selected & Content): its mesh follows the rig file's lattice
    animation, Correction None as a twin with Blender's Lattice modifier, XYZ keeping the volume."""
    win = bpy.context.window_manager.windows[0]
    win.scene = bpy.data.scenes.new("Rig")
    yield 0.5
    layer = win.view_layer
    char = bpy.data.collections.new("Character")
    win.scene.collection.children.link(char)

    def into_character(ob):
        for c in ob.users_collection:
            c.objects.unlink(ob)
        char.objects.link(ob)

    op("object.add", type="LATTICE", location=(0.0, 0.0, 0.0))
    lat = layer.objects.active
    lat.name, lat.scale = "Lattice", (1.8, 1.8, 1.8)
    lat.data.points_u = lat.data.points_v = lat.data.points_w = 3
    lat.shape_key_add(name="Basis")
    squash = lat.shape_key_add(name="Squash")
    for p in squash.data:                     # squashed, bulging in its middle
        x, y, z = p.co
        bulge = 1.0 + 0.35 * (1.0 - 4.0 * z * z)
        p.co = (x * bulge, y * bulge, z * 0.6)
    for f, v in ((1, 0.0), (20, 1.0)):
        squash.value = v
        squash.keyframe_insert("value", frame=f)
    into_character(lat)
    names = {}
    for name in ("Body", "Twin"):
        op("mesh.primitive_ico_sphere_add", subdivisions=3, radius=0.7, location=(0.0, 0.0, 0.0))
        ob = layer.objects.active
        ob.name = name
        into_character(ob)
        names[name] = ob.name
    twin = bpy.data.objects[names["Twin"]]
    twin.modifiers.new("Lattice", "LATTICE").object = lat
    body = bpy.data.objects[names["Body"]]
    select_only(body)
    body.vpffd.lattice, body.vpffd.axes = lat, "XYZ"
    op("object.vpffd_bind")
    yield 0.5
    rig_file = os.path.join(OUT, "char_rig.blend")
    bpy.data.libraries.write(rig_file, {char}, path_remap="RELATIVE_ALL")

    # The shot: the rig's collection linked, then Make > Selected & Content in the Outliner.
    win.scene = bpy.data.scenes.new("Shot")
    with bpy.data.libraries.load(rig_file, link=True) as (_src, dst):
        dst.collections = ["Character"]
    win.scene.collection.children.link(dst.collections[0])
    win.scene.frame_set(10)
    # The linked mesh made active and selected with the viewport's own selection operator, which
    # the Outliner follows (its synced selection) at its next redraw: the Outliner's operators
    # act on an active item, as the one right-clicked.
    linked_body = next(o for o in bpy.data.objects if o.name == "Body" and o.library is not None)
    yield 0.5
    layer = win.view_layer
    layer.objects.active = linked_body
    op("object.select_pattern", pattern="Body", extend=False)
    yield 1.0
    area = next(a for a in win.screen.areas if a.type == "OUTLINER")
    region = next(r for r in area.regions if r.type == "WINDOW")
    with bpy.context.temp_override(window=win, screen=win.screen, area=area, region=region):
        bpy.ops.outliner.select_all(action="SELECT")     # the linked collection and its content
        result = bpy.ops.outliner.liboverride_operation(
            "EXEC_DEFAULT", True, type="OVERRIDE_LIBRARY_CREATE_HIERARCHY",
            selection_set="SELECTED_AND_CONTENT")
    yield 1.0

    def overridden(name):
        # the override of the rig's object `name` (the rig's own copy here has that name)
        return next((o for o in bpy.data.objects if o.override_library is not None
                     and o.override_library.reference.name == name), None)
    body, twin = overridden("Body"), overridden("Twin")
    check("the Outliner's Library Override > Make overrides the linked rig", result == {"FINISHED"}
          and body is not None and twin is not None, (result, body, twin))
    if body is None or twin is None:
        return
    rows = []
    for f in (4, 16):
        win.scene.frame_set(f)
        yield 0.5
        mod = next(m for m in body.modifiers if m.type == "NODES")
        mod.show_viewport = False
        yield 0.3
        v_in = volume(*evaluated(body))
        mod.show_viewport = True
        yield 0.5
        co, tris = evaluated(body)
        body.vpffd.axes = "NONE"
        yield 0.5
        plain = evaluated(body)[0]
        body.vpffd.axes = "XYZ"
        yield 0.3
        other = evaluated(twin)[0]
        rows.append((f, abs(volume(co, tris) / v_in - 1), float(np.abs(plain - other).max()),
                     float(np.abs(other - mesh_arrays(twin.data)[0]).max()),
                     ops.status.stats(body).get("error")))
    check("the Outliner's override follows the rig's lattice: Correction None as the Lattice "
          "modifier, XYZ keeping the volume", all(vol <= VOLUME_TOL and shape <= 1e-5 and moved > 0.01
                                                  and error is None
                                                  for _, vol, shape, moved, error in rows), rows)


def two_deformers(ops):
    """Two VP-FFD modifiers on one mesh, added from Add Modifier > Deform > VP-FFD Lattice with
    a lattice selected and bound from the panel of the one shown, equal a twin with two Lattice
    modifiers (Correction None); Ctrl+Z takes the second one back, Ctrl+Shift+Z brings it again."""
    entries = [getattr(fn, "__module__", "") for fn in
               getattr(bpy.types.OBJECT_MT_modifier_add_deform.draw, "_draw_funcs", [])]
    check("Add Modifier > Deform offers VP-FFD Lattice", any(m.endswith(".operators.ops") for m in entries),
          entries)
    layer = bpy.context.window_manager.windows[0].view_layer
    made = {}
    for name, x in (("Ours", -3.0), ("Twin", -3.0)):     # one place: the same lattice space
        op("mesh.primitive_ico_sphere_add", subdivisions=3, radius=0.7, location=(x, 0.0, 1.0))
        made[name] = layer.objects.active.name
    for name, z, squash in (("Head", 1.5, 0.6), ("Belly", 0.9, 1.3)):
        op("object.add", type="LATTICE", location=(0.0, 0.0, z))
        lat = layer.objects.active
        lat.name = name
        lat.scale = (9.0, 2.0, 1.0)               # around both spheres
        pts = lat.data.points
        for p in pts:
            co = p.co.copy()
            p.co_deform = (co.x * (1.0 + 0.2 * co.z), co.y, co.z * squash)
        made[name] = lat.name
    yield 0.3
    ours, twin = bpy.data.objects[made["Ours"]], bpy.data.objects[made["Twin"]]
    head, belly = bpy.data.objects[made["Head"]], bpy.data.objects[made["Belly"]]
    for lat in (head, belly):
        select_only(twin)
        op("object.modifier_add", type="LATTICE")
        twin.modifiers[-1].object = lat
    for lat in (head, belly):
        select_only(ours)
        lat.select_set(True)
        op("object.vpffd_modifier_add")
        shown = ops.deformers.shown(ours)
        shown.settings.axes = "NONE"
        op("object.vpffd_bind", modifier=shown.mod.name)
        yield 0.5
    found = ops.deformers.bound(ours)
    check("two VP-FFD deformers bound, each to its lattice",
          [d.settings.lattice for d in found] == [head, belly], [d.settings.lattice for d in found])

    def same():
        a, b = evaluated(ours)[0], evaluated(twin)[0]
        return float(np.abs(a - b).max()) if a.shape == b.shape else float("inf")
    moved = float(np.abs(evaluated(ours)[0] - mesh_arrays(ours.data)[0]).max())
    check("two VP-FFD lattices with Correction None equal two Lattice modifiers",
          same() <= 1e-5 and moved > 0.05, (same(), moved))
    check("the panel shows the active VP-FFD modifier and says which",
          ops.deformers.label(ops.deformers.shown(ours)).endswith("(2 of 2)"),
          ops.deformers.label(ops.deformers.shown(ours)))
    twin_name, ours_name = twin.name, ours.name
    op("ed.undo")
    yield 0.8
    ours, twin = bpy.data.objects[ours_name], bpy.data.objects[twin_name]
    twin.modifiers[-1].show_viewport = False        # the twin with the first lattice only
    yield 0.5
    check("Ctrl+Z takes the second VP-FFD back; the first deforms as one Lattice modifier",
          len(ops.deformers.bound(ours)) == 1 and same() <= 1e-5, (len(ops.deformers.bound(ours)), same()))
    twin.modifiers[-1].show_viewport = True
    op("ed.redo")
    yield 0.8
    ours, twin = bpy.data.objects[ours_name], bpy.data.objects[twin_name]
    twin.modifiers[-1].show_viewport = True
    yield 0.5
    check("Ctrl+Shift+Z brings it again, equal to two Lattice modifiers",
          len(ops.deformers.bound(ours)) == 2 and same() <= 1e-5, (len(ops.deformers.bound(ours)), same()))


def main():
    gen = session()

    def tick():
        try:
            return next(gen)
        except StopIteration:
            finish(None)
        except Exception:
            finish(traceback.format_exc())
        return None

    bpy.app.timers.register(tick, first_interval=1.0)


def finish(error):
    with open(os.path.join(OUT, "results.json"), "w") as fh:
        json.dump({"checks": CHECKS, "error": error}, fh, indent=1)
    bpy.app.timers.register(lambda: bpy.ops.wm.quit_blender() and None, first_interval=0.2)


main()
