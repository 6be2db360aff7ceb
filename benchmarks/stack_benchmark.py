"""VP-FFD in the modifier stack: `scene.frame_set()` against Blender's Lattice modifier in the same
slot, same process, for the ways things move in a shot.

    ./dev bench --stack-only [--update-readme]      (also part of a plain ./dev bench)

An icosphere of 163,842 vertices in a 6x6x6 B-spline lattice; VP-FFD corrects along XYZ. For each
scenario two scenes are built (VP-FFD in the slot; a Lattice modifier in the slot), each stepped
through FRAME_WARMUPS untimed frames and then FRAMES timed ones; the figure is the median frame
time with its spread (min and max), and the ratio of the medians; ROUNDS rounds of every scenario,
the one with the median ratio shown:
- `lattice points`: a shape key of the lattice animates, nothing else moves;
- `mesh moves`: the mesh object travels through the static lattice (it is re-embedded every frame);
- `lattice moves`: the lattice object travels over the static mesh;
- `armature`: an Armature modifier before the slot bends the mesh, and the lattice is parented to
  the bending bone; compared with Armature + Lattice modifier. VP-FFD makes Blender evaluate the
  object's stack twice per frame (once to read what reaches the slot, once with the offsets), so
  the Armature-only frame time is printed too: it is what that second evaluation costs upstream.
Each VP-FFD frame is also split at the frame-change handlers: Blender's evaluation before them
(what reaches the slot; nothing to evaluate when only the mesh object's transform changed), the
handlers (VP-FFD's update), and the evaluation that the update's offsets cause.
And the mesh moving through a 20-cell box cage (depth 3), whose binding is rebuilt every frame.
Also: `vp.bind` at 163,842 and 655,362 vertices, the Bind operator, and the first frame after an
undo against an ordinary frame. A benchmark, not a test: it prints figures and exits 0.
"""
import os
import statistics
import sys
import time

import numpy as np

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)

import vpffd_addon as vp  # noqa: E402

SUBDIVISIONS = 7          # 163,842 vertices
LATTICE = (6, 6, 6)
FRAMES = 12
FRAME_WARMUPS = 3
#: Every scenario is measured in this many rounds (each: Lattice-modifier scene, then VP-FFD's);
#: the row shown is the round with the median ratio, beside every round's ratio, since frame times
#: on shared machines drift by tens of percent within minutes.
ROUNDS = 3
SCENARIOS = ("lattice points", "mesh moves", "lattice moves", "armature")
CAGE_FRAMES = 4


def log(*args):
    print(*args, file=sys.stderr, flush=True)


def _spread(ms):
    return {"median": statistics.median(ms), "min": min(ms), "max": max(ms)}


def _mesh_object(bpy, verts, tris):
    from tests.blender_ref import triangle_mesh
    ob = bpy.data.objects.new("Ball", triangle_mesh(verts, tris, "Ball"))
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _lattice(bpy):
    from tests.blender_ref import squash_lattice
    return squash_lattice("Lattice", LATTICE, (1.0 / (LATTICE[0] - 1),) * 3, 0.6, 0.15)  # [-0.5, 0.5]


def _scene(bpy, eh, scenario, slot, verts, tris):
    """Build one scene: `slot` is "vpffd", "lattice" or "none" (the Armature alone)."""
    eh.reset_scene()
    ob = _mesh_object(bpy, verts, tris)
    lat_ob, key = _lattice(bpy)
    last = FRAME_WARMUPS + FRAMES + 2
    if scenario == "lattice points":
        for f, v in ((1, 0.0), (last, 1.0)):
            key.value = v
            key.keyframe_insert("value", frame=f)
    else:
        key.value = 0.7
        mover = {"mesh moves": ob, "lattice moves": lat_ob}.get(scenario)
        if mover is not None:
            for f, x in ((1, -0.05), (last, 0.05)):
                mover.location = (x, 0.05 * x, 0)
                mover.keyframe_insert("location", frame=f)
        if scenario == "armature":
            from tests.blender_ref import bone_weights_by_height, two_bone_armature
            rig = two_bone_armature("Rig", 0.5, frames=(1, last))
            lat_ob.parent = rig
            lat_ob.parent_type = "BONE"
            lat_ob.parent_bone = "Upper"
            lat_ob.location = (0, -0.5, 0)    # the bone's tail is the parent's origin: back to centre
            bone_weights_by_height(ob, 0.15)
            ob.modifiers.new("Armature", "ARMATURE").object = rig
    if slot == "lattice":
        ob.modifiers.new("Lattice", "LATTICE").object = lat_ob
    elif slot == "vpffd":
        ob.vpffd.lattice = lat_ob
        ob.vpffd.axes = "XYZ"
        bpy.context.scene.frame_set(1)
        with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
            if bpy.ops.object.vpffd_bind() != {"FINISHED"}:
                raise RuntimeError("binding failed")
    return ob


class _Phases:
    """Clocks around the frame-change handlers: `frame_set` -> frame_change_pre (last) ->
    Blender's first evaluation -> frame_change_post (first ... last: VP-FFD's update among them) ->
    the evaluation that its writes cause -> `frame_set` returns. Times in ms per frame."""

    def __init__(self, bpy):
        self.h = bpy.app.handlers
        self.t = {}
        self.rows = []

    def _at(self, name):
        def mark(*_args):
            self.t[name] = time.perf_counter()
        return mark

    def __enter__(self):
        self.marks = (self._at("pre"), self._at("post0"), self._at("post1"))
        self.h.frame_change_pre.append(self.marks[0])
        self.h.frame_change_post.insert(0, self.marks[1])
        self.h.frame_change_post.append(self.marks[2])
        return self

    def __exit__(self, *exc):
        self.h.frame_change_pre.remove(self.marks[0])
        self.h.frame_change_post.remove(self.marks[1])
        self.h.frame_change_post.remove(self.marks[2])

    def frame(self, start, end):
        t = self.t
        self.rows.append((1e3 * (t["post0"] - start), 1e3 * (t["post1"] - t["post0"]),
                          1e3 * (end - t["post1"])))

    def medians(self):
        cols = list(zip(*self.rows))
        return {k: statistics.median(c) for k, c in zip(("first_evaluation", "handlers", "after_update"), cols)}


def _frames(bpy, status=None, ob=None):
    """(wall ms per frame, VP-FFD update ms per frame, phase medians) over the timed frames."""
    scene = bpy.context.scene
    scene.frame_set(1)
    for f in range(2, FRAME_WARMUPS + 2):
        scene.frame_set(f)
    wall, update = [], []
    with _Phases(bpy) as phases:
        for f in range(FRAME_WARMUPS + 2, FRAME_WARMUPS + FRAMES + 2):
            t0 = time.perf_counter()
            scene.frame_set(f)
            t1 = time.perf_counter()
            wall.append((t1 - t0) * 1e3)
            phases.frame(t0, t1)
            if status is not None:
                info = status.stats(ob)
                if info.get("error"):
                    raise RuntimeError(info["error"])
                update.append(info["seconds"] * 1e3)
    return wall, update, phases.medians()


def cage_figures(bpy, eh, status, cage_module, verts, tris):
    """The mesh moving through a static 20-cell box cage (depth 3): a cage binding is rebuilt on
    every frame. No Blender modifier to compare with: the Lattice modifier's scene is given for
    scale."""
    cage = vp.box_cage((2, 2, 5), ((-0.5,) * 3, (0.5,) * 3))
    eh.reset_scene()
    ob = _mesh_object(bpy, verts, tris)
    cage_ob = cage_module.cage_object("Cage", cage.rest_points, cage.cells)
    bpy.context.scene.collection.objects.link(cage_ob)
    last = FRAME_WARMUPS + CAGE_FRAMES + 2
    for f, x in ((1, -0.1), (last, 0.1)):
        ob.location = (x, 0.02 * x, 0)
        ob.keyframe_insert("location", frame=f)
    ob.vpffd.lattice = cage_ob
    ob.vpffd.axes = "XYZ"
    with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
        if bpy.ops.object.vpffd_bind() != {"FINISHED"}:
            raise RuntimeError("binding to the cage failed")
    scene = bpy.context.scene
    for f in range(1, FRAME_WARMUPS + 2):
        scene.frame_set(f)
    wall, update = [], []
    for f in range(FRAME_WARMUPS + 2, last):
        t0 = time.perf_counter()
        scene.frame_set(f)
        wall.append((time.perf_counter() - t0) * 1e3)
        info = status.stats(ob)
        if info.get("error"):
            raise RuntimeError(info["error"])
        update.append(info["seconds"] * 1e3)
    row = {"scenario": "mesh moves through a 20-cell cage (depth 3)", "vpffd_ms": _spread(wall),
           "vpffd_update_ms": _spread(update), "volume_percent": status.stats(ob)["volume_percent"]}
    log(f"  cage, mesh moves: {row['vpffd_ms']['median']:.0f} ms per frame")
    return row


def frame_set_figures(bpy, eh, status, verts, tris):
    rows = []
    for scenario in SCENARIOS:
        row = {"scenario": scenario}
        ob = _scene(bpy, eh, scenario, "lattice", verts, tris)
        row["lattice_modifier_ms"] = _spread(_frames(bpy)[0])
        ob = _scene(bpy, eh, scenario, "vpffd", verts, tris)
        wall, update, phases = _frames(bpy, status, ob)
        row["vpffd_ms"] = _spread(wall)
        row["vpffd_update_ms"] = _spread(update)
        row["vpffd_phases_ms"] = phases
        row["volume_percent"] = status.stats(ob)["volume_percent"]
        if scenario == "armature":
            _scene(bpy, eh, scenario, "none", verts, tris)
            row["armature_only_ms"] = _spread(_frames(bpy)[0])
        row["ratio"] = row["vpffd_ms"]["median"] / row["lattice_modifier_ms"]["median"]
        log(f"  {scenario}: VP-FFD {row['vpffd_ms']['median']:.1f} ms, Lattice modifier "
            f"{row['lattice_modifier_ms']['median']:.1f} ms, ratio {row['ratio']:.2f}")
        rows.append(row)
    return rows


def lattice_modifier_alone(bpy, eh, verts, tris):
    """Blender's Lattice modifier in the *lattice points* scene, three runs of frames: measured
    before VP-FFD has run in this process and again after it (its kernels loaded, its worker
    threads idle), to show that VP-FFD does not slow Blender's own modifiers."""
    _scene(bpy, eh, "lattice points", "lattice", verts, tris)
    wall = []
    for _ in range(3):
        wall += _frames(bpy)[0]
    eh.reset_scene()
    return _spread(wall)


def median_rounds(rounds):
    """Per scenario, the row of the round whose ratio is the median, with every round's ratio."""
    rows = []
    for per_round in zip(*rounds):
        ranked = sorted(per_round, key=lambda r: r["ratio"])
        row = dict(ranked[len(ranked) // 2])
        row["ratios"] = [r["ratio"] for r in per_round]
        rows.append(row)
    return rows


def bind_figures(bpy, eh, status, handlers):
    out = {}
    lat = vp.Lattice(LATTICE, "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    compiled = vp.compiled.load()
    for sub in (7, 8):
        v, f = vp.icosphere(sub, 0.45)
        moved = v * 1.02 + 0.01          # the same mesh elsewhere in the lattice: a re-embedding
        topology = vp.Topology(f, len(v))
        for kind, use in (("numpy", False), ("compiled", True)):
            if use and not compiled:
                continue
            for what, pos, topo in (("first", v, None), ("reembed", moved, topology)):
                times = []
                for _ in range(3):
                    t0 = time.perf_counter()
                    vp.bind(lat, pos, f, dtype=np.float32, topology=topo, use_compiled=use)
                    times.append((time.perf_counter() - t0) * 1e3)
                out[f"vp_bind_ms_{what}_{kind}_{len(v)}"] = min(times)
                log(f"  vp.bind {what} {kind} {len(v):,} vertices: {min(times):.0f} ms (best of 3)")
    v, f = vp.icosphere(SUBDIVISIONS, 0.45)
    ob = _scene(bpy, eh, "lattice points", "none", v, f)
    ob.vpffd.lattice = bpy.data.objects["Lattice"]
    ob.vpffd.axes = "XYZ"
    t0 = time.perf_counter()
    with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
        bpy.ops.object.vpffd_bind()
    out["bind_operator_ms"] = (time.perf_counter() - t0) * 1e3
    log(f"  Bind operator {len(v):,} vertices: {out['bind_operator_ms']:.0f} ms")
    scene = bpy.context.scene
    ordinary = []
    for frame in (5, 6, 7, 8):
        t0 = time.perf_counter()
        scene.frame_set(frame)
        ordinary.append((time.perf_counter() - t0) * 1e3)
    # What Blender calls after an undo step (undo_post): the restored state is solved again, so
    # that the panel describes it, reusing the binding when its inputs are unchanged; then the
    # next frame, as playback after the undo gives it. Each timed on its own, three times.
    undo_step, after_undo, rebound = [], [], []
    for frame in (9, 10, 11):
        t0 = time.perf_counter()
        handlers.on_undo()
        t1 = time.perf_counter()
        scene.frame_set(frame)
        t2 = time.perf_counter()
        undo_step.append((t1 - t0) * 1e3)
        after_undo.append((t2 - t1) * 1e3)
        rebound.append(bool(status.stats(ob).get("rebound")))
    out["undo_handler_ms"] = statistics.median(undo_step)
    out["first_frame_after_undo_ms"] = statistics.median(after_undo)
    out["ordinary_frame_ms"] = statistics.median(ordinary)
    out["rebound_after_undo"] = any(rebound)
    log(f"  undo step {out['undo_handler_ms']:.0f} ms, first frame after it "
        f"{out['first_frame_after_undo_ms']:.0f} ms, ordinary frame {out['ordinary_frame_ms']:.0f} ms")
    return out


def island_problem(module=vp):
    """(verts, faces, lattice, points) of the islands' figure: 64 closed icospheres of 2,562
    vertices each (163,968 vertices) in a 6x6x6 B-spline lattice squashed to half its height, made
    with `module` (the package, or a copy of it under another name)."""
    vs, fs, n = [], [], 0
    rng = np.random.default_rng(5)
    for k in range(64):
        centre = ((k % 4 - 1.5) * 0.22, (k // 4 % 4 - 1.5) * 0.22, (k // 16 - 1.5) * 0.22)
        v, f = module.icosphere(4, rng.uniform(0.05, 0.09), centre)
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    lat = module.Lattice(LATTICE, "BSPLINE", bounds=((-0.5,) * 3, (0.5,) * 3))
    P = lat.rest_points.copy()
    P[:, 2] *= 0.5
    P[:, :2] *= 1.0 + 0.1 * np.cos(3.0 * P[:, 2:3])
    return np.concatenate(vs), np.concatenate(fs), lat, P


def island_figures(repeat=15):
    """The XYZ solve with Per-Island Volume (joint Gauss-Newton over every island) beside the
    single-volume solve, on 64 closed islands of 2,562 vertices each (163,968 vertices) in a
    6x6x6 B-spline lattice squashed to half its height. Core only (compiled kernels where loaded),
    the two solves alternately (this machine's speed drifts within seconds), medians of `repeat`."""
    verts, tris, lat, P = island_problem()
    b = vp.bind(lat, verts, tris, dtype=np.float32)
    out = {"vertices": len(verts), "islands": 64}
    cases = (("single_volume_ms", False), ("per_island_ms", True))
    times = {key: [] for key, _ in cases}
    for _, islands in cases:
        b.solve(P, axes="XYZ", islands=islands)
    for _ in range(repeat):
        for key, islands in cases:
            t0 = time.perf_counter()
            sol = b.solve(P, axes="XYZ", islands=islands)
            times[key].append((time.perf_counter() - t0) * 1e3)
    for key, _ in cases:
        out[key] = statistics.median(times[key])
    # Measured from the vertices as Blender would store them (float32), in float64.
    stored = np.ascontiguousarray(sol.verts.astype(np.float32).astype(np.float64).T)
    topo = b.topology
    now = np.bincount(topo.face_island, vp.volume.face_volumes(stored, topo.tris_t), topo.n_islands)
    out["worst_island_miss"] = float(np.abs(now / sol.island_target_volumes - 1).max())
    log(f"  islands: XYZ solve {out['single_volume_ms']:.0f} ms for one volume, "
        f"{out['per_island_ms']:.0f} ms per island ({out['islands']} islands, worst miss "
        f"{out['worst_island_miss']:.1e})")
    return out


def run(engine_module_loader):
    """Run every figure; `engine_module_loader()` installs the extension and returns its module."""
    import importlib

    import bpy
    from tests import extension_harness as eh
    module = engine_module_loader()
    status = importlib.import_module(module + ".operators.status")
    compiled_backend = importlib.import_module(module + ".operators.compiled_backend")
    handlers = importlib.import_module(module + ".operators.handlers")
    cage_module = importlib.import_module(module + ".operators.cage")
    verts, tris = vp.icosphere(SUBDIVISIONS, 0.45)
    log(f"stack benchmark: {len(verts):,} vertices, {LATTICE} B-spline lattice, XYZ, "
        f"{FRAMES} frames after {FRAME_WARMUPS} warm-up frames")
    alone_before = lattice_modifier_alone(bpy, eh, verts, tris)
    report = {"vertices": len(verts), "lattice": list(LATTICE), "frames": FRAMES,
              "warmups": FRAME_WARMUPS, "rounds": ROUNDS,
              "frame_set": median_rounds([frame_set_figures(bpy, eh, status, verts, tris)
                                          for _ in range(ROUNDS)]),
              "cage": cage_figures(bpy, eh, status, cage_module, verts, tris),
              "bind": bind_figures(bpy, eh, status, handlers),
              "islands": island_figures()}
    report["lattice_modifier_alone"] = {"before": alone_before,
                                        "after": lattice_modifier_alone(bpy, eh, verts, tris),
                                        "kernels": compiled_backend.status()[0]}
    eh.reset_scene()
    return report


def _rounds(row):
    ratios = row.get("ratios")
    if not ratios or len(ratios) < 2:
        return ""
    return " (rounds: " + ", ".join(f"{x:.2f}" for x in ratios) + ")"


def _phase_cell(row):
    ph = row.get("vpffd_phases_ms")
    if not ph:
        return ""
    return f"{ph['first_evaluation']:.1f} / {ph['after_update']:.1f}"


def markdown(report):
    rows = ["| scenario | Lattice modifier, ms (min-max) | VP-FFD XYZ, ms (min-max) | ratio | VP-FFD's own update, ms "
            "| Blender's evaluations before / after the update, ms |",
            "|---|---|---|---|---|---|"]
    for r in report["frame_set"]:
        lm, vf, up = r["lattice_modifier_ms"], r["vpffd_ms"], r["vpffd_update_ms"]
        name = r["scenario"]
        if "armature_only_ms" in r:
            name += f" (Armature alone: {r['armature_only_ms']['median']:.1f} ms, paid twice by VP-FFD)"
        rows.append(f"| {name} | {lm['median']:.1f} ({lm['min']:.1f}-{lm['max']:.1f}) | "
                    f"{vf['median']:.1f} ({vf['min']:.1f}-{vf['max']:.1f}) | {r['ratio']:.2f}x{_rounds(r)} | "
                    f"{up['median']:.1f} | {_phase_cell(r)} |")
    c = report.get("cage")
    if c:
        rows.append(f"| {c['scenario']} | (no such modifier) | {c['vpffd_ms']['median']:.0f} "
                    f"({c['vpffd_ms']['min']:.0f}-{c['vpffd_ms']['max']:.0f}) | | "
                    f"{c['vpffd_update_ms']['median']:.0f} | |")
    b = report["bind"]
    binds = []
    for n in sorted({int(k.rsplit("_", 1)[1]) for k in b if k.startswith("vp_bind_ms_")}):
        cells = []
        for what, words in (("first", "a first bind"), ("reembed", "a re-embedding (faces' topology reused)")):
            ms = [b.get(f"vp_bind_ms_{what}_{kind}_{n}") for kind in ("numpy", "compiled")]
            cells.append(f"{words} {' / '.join('-' if m is None else f'{m:.0f}' for m in ms)} ms")
        binds.append(f"{n:,} vertices: {', '.join(cells)}")
    rows.append("")
    rows.append(f"`vp.bind` (NumPy / compiled kernels, best of 3): {'; '.join(binds)}. "
                f"The Bind operator at {report['vertices']:,} vertices: "
                f"{b['bind_operator_ms']:.0f} ms. Undo: the undo step solves the restored frame again "
                f"({b['undo_handler_ms']:.0f} ms, so that the panel describes it), "
                f"{'re-embedding it' if b.get('rebound_after_undo') else 'without re-embedding'}; the "
                f"first frame after it takes {b['first_frame_after_undo_ms']:.0f} ms (an ordinary frame: "
                f"{b['ordinary_frame_ms']:.0f} ms; medians of three undo steps and of four "
                f"ordinary frames).")
    alone = report.get("lattice_modifier_alone")
    if alone:
        rows.append("")
        rows.append(f"Blender's Lattice modifier alone (*lattice points* scene, median of three runs of "
                    f"{FRAMES} frames): {alone['before']['median']:.1f} ms per frame before VP-FFD ran in "
                    f"this process, {alone['after']['median']:.1f} ms after it (its kernels "
                    f"{'loaded' if alone['kernels'] == 'ready' else 'not loaded: ' + alone['kernels']}, "
                    f"its worker threads idle; this machine's speed drifts by tens of percent).")
    isl = report.get("islands")
    if isl:
        rows.append("")
        rows.append(f"Per-Island Volume ({isl['islands']} closed islands, {isl['vertices']:,} vertices, the "
                    f"lattice squashed to half its height): the XYZ solve takes {isl['per_island_ms']:.0f} ms "
                    f"with every island kept (worst island off by {isl['worst_island_miss']:.1e}, measured "
                    f"from the vertices rounded to float32), against {isl['single_volume_ms']:.0f} ms for "
                    f"the one total volume ({isl['per_island_ms'] / isl['single_volume_ms']:.2f}x; core "
                    "alone, float32 binding, compiled kernels where loaded, the two solves alternately, "
                    "medians of 15).")
    return "\n".join(rows)
