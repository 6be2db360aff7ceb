"""A shot's size: what VP-FFD adds to a frame and to an unrelated edit, against the number of
unrelated objects in the scene.

    ./dev bench --shot-size        (also part of a plain ./dev bench)

The scene: one icosphere of 2,562 vertices in a 4x4x4 lattice whose scale is keyframed, corrected
along XYZ, and N unrelated objects (half of them meshes sharing one cube, half empties) spread over
SUB_COLLECTIONS collections nested in chains below one collection of the scene. Every figure comes
from a fresh Blender process of its own:
- `vpffd`: VP-FFD installed through Blender's own installer, the sphere bound to the lattice;
- `lattice`: the same scene with Blender's Lattice modifier on the sphere, in a Blender where
  VP-FFD is not installed (its handlers cannot run there at all).
In each: the median of FRAMES `scene.frame_set()` calls after FRAME_WARMUPS untimed ones (a frame),
and the median of EDITS moves of one unrelated empty (there for every N), each followed by
`view_layer.update()`, which runs the depsgraph handlers (an edit). VP-FFD's added cost is the
difference of the two processes' medians; the growth is the added cost at N over the added cost
at N = 0. The process without the extension also times Blender's evaluation after one mesh's
data changed from Python (`Mesh.update()`, then `view_layer.update()`): what a frame handler that
writes a result costs Blender itself. A benchmark, not a test: it prints figures and exits 0.
"""
import json
import os
import statistics
import subprocess
import sys
import tempfile
import textwrap

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

COUNTS = (0, 1000, 10000)
SUB_COLLECTIONS = 50
FRAMES = 40
FRAME_WARMUPS = 5
EDITS = 40
ROUNDS = 3          # each count is measured this many times (both processes); the medians shown

_SCENE = textwrap.dedent('''
    import json, statistics, time
    import bpy
    import numpy as np
    KIND, N, SUBS, FRAMES, WARMUPS, EDITS = {args}
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    root = bpy.data.collections.new("Set")
    scene.collection.children.link(root)
    collections = []
    for i in range(SUBS):                      # chains of five, each collection below the last
        c = bpy.data.collections.new(f"Set.{{i:03d}}")
        (root if i % 5 == 0 else collections[-1]).children.link(c)
        collections.append(c)
    cube = bpy.data.meshes.new("Cube")
    cube.from_pydata([(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)], [],
                     [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)])
    for i in range(N):
        ob = bpy.data.objects.new(f"Prop.{{i:05d}}", cube if i % 2 else None)
        ob.location = (3 + i % 100, i // 100, 0)
        collections[i % SUBS].objects.link(ob)
    # the unrelated object each edit moves (there in every scene, N = 0 too)
    scene.collection.objects.link(bpy.data.objects.new("Edited", None))
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=4, radius=0.4)
    ball = bpy.context.active_object
    lattice = bpy.data.objects.new("Lattice", bpy.data.lattices.new("Lattice"))
    scene.collection.objects.link(lattice)
    lattice.data.points_u = lattice.data.points_v = lattice.data.points_w = 4
    for f, s in ((1, (1.0, 1.0, 1.0)), (FRAMES + WARMUPS + 2, (1.4, 1.4, 0.6))):
        lattice.scale = s
        lattice.keyframe_insert("scale", frame=f)
    if KIND == "lattice":
        ball.modifiers.new("Lattice", "LATTICE").object = lattice
    else:
        ball.vpffd.lattice = lattice
        ball.vpffd.axes = "XYZ"
        with bpy.context.temp_override(object=ball, active_object=ball, selected_objects=[ball]):
            assert bpy.ops.object.vpffd_bind() == {{"FINISHED"}}
    scene.frame_set(1)
    for f in range(2, WARMUPS + 2):
        scene.frame_set(f)
    frame = []
    for f in range(WARMUPS + 2, WARMUPS + FRAMES + 2):
        t0 = time.perf_counter()
        scene.frame_set(f)
        frame.append(1e3 * (time.perf_counter() - t0))
    prop = bpy.data.objects["Edited"]
    view_layer = bpy.context.view_layer
    edit = []
    for i in range(EDITS):
        prop.location.z = 0.01 * (i + 1)
        t0 = time.perf_counter()
        view_layer.update()
        edit.append(1e3 * (time.perf_counter() - t0))
    # Blender's own evaluation after one mesh's data changed from Python (what any deformer that
    # writes a frame's result from a handler causes), in the process without the extension
    retag = []
    if KIND == "lattice":
        for i in range(EDITS):
            ball.data.update()
            t0 = time.perf_counter()
            view_layer.update()
            retag.append(1e3 * (time.perf_counter() - t0))
    error = None
    if KIND == "vpffd":
        error = ext.operators.status.stats(ball).get("error")
    print("SHOT-SIZE " + json.dumps(dict(frame=statistics.median(frame), edit=statistics.median(edit),
                                         retag=statistics.median(retag) if retag else None,
                                         objects=len(bpy.data.objects), error=error)), flush=True)
''')


def log(*args):
    print(*args, file=sys.stderr, flush=True)


def _figures(out):
    for line in out.splitlines():
        if line.startswith("SHOT-SIZE "):
            return json.loads(line[len("SHOT-SIZE "):])
    raise RuntimeError("the process printed no figures:\n" + out[-3000:])


def _measure(kind, n, zip_path, user_resources, folder):
    """Figures of one fresh process (`kind` "vpffd" or "lattice", `n` unrelated objects)."""
    args = (kind, n, SUB_COLLECTIONS, FRAMES, FRAME_WARMUPS, EDITS)
    script = os.path.join(folder, f"shot_{kind}_{n}.py")
    with open(script, "w") as fh:
        if kind == "vpffd":
            fh.write("import importlib\next = importlib.import_module(module)\n")
        fh.write(_SCENE.format(args=repr(args)))
    from tests import extension_harness as eh
    if kind == "vpffd":
        done = eh.run_in_fresh_process(zip_path, user_resources, script, timeout=900)
    else:
        bare = tempfile.mkdtemp(prefix="vpffd-bench-bare-", dir=folder)  # no extension installed
        env = dict(os.environ, **{eh.ENV: bare})
        env.pop("PYTHONPATH", None)
        done = subprocess.run([sys.executable, script], capture_output=True, text=True, timeout=900,
                              env=env, cwd=bare)
    figures = _figures(done.stdout)
    if figures.get("error"):
        raise RuntimeError(f"VP-FFD's panel: {figures['error']}")
    return figures


def run(counts=COUNTS, rounds=ROUNDS):
    """The report: for each count of unrelated objects, both processes' medians (of `rounds`
    rounds) and VP-FFD's added cost per frame and per edit, with its growth over N = 0."""
    from tests import extension_harness as eh
    folder = tempfile.mkdtemp(prefix="vpffd-bench-shot-")
    zip_path = eh.build_extension_zip(_ROOT, folder)
    user_resources = os.path.join(folder, "user")     # one for every VP-FFD process: one compile
    os.makedirs(user_resources)
    log(f"shot size: {counts} unrelated objects, {rounds} rounds, {FRAMES} frames, {EDITS} edits")
    rows = []
    for n in counts:
        runs = {"vpffd": [], "lattice": []}
        for _ in range(rounds):
            for kind in runs:
                runs[kind].append(_measure(kind, n, zip_path, user_resources, folder))
        row = {"objects": n, "lattice_retag_ms": statistics.median(r["retag"] for r in runs["lattice"])}
        for what in ("frame", "edit"):
            for kind in runs:
                row[f"{kind}_{what}_ms"] = statistics.median(r[what] for r in runs[kind])
            row[f"added_{what}_ms"] = row[f"vpffd_{what}_ms"] - row[f"lattice_{what}_ms"]
        rows.append(row)
        log(f"  {n:>6} objects: frame {row['vpffd_frame_ms']:.2f} vs {row['lattice_frame_ms']:.2f} ms, "
            f"edit {row['vpffd_edit_ms']:.2f} vs {row['lattice_edit_ms']:.2f} ms, "
            f"a mesh's data changed: {row['lattice_retag_ms']:.2f} ms")
    base = rows[0]
    for row in rows:
        for what in ("frame", "edit"):
            added = base[f"added_{what}_ms"]
            row[f"added_{what}_growth"] = row[f"added_{what}_ms"] / added if added > 0 else None
    return {"counts": list(counts), "rounds": rounds, "frames": FRAMES, "edits": EDITS,
            "sub_collections": SUB_COLLECTIONS, "rows": rows}


def markdown(report):
    def growth(x):
        return "" if x is None else f"{x:.2f}x"
    rows = ["| unrelated objects | frame: VP-FFD / Lattice modifier, ms | VP-FFD's added cost per frame | "
            "edit: VP-FFD / Lattice modifier, ms | VP-FFD's added cost per edit | "
            "Blender alone: one mesh's data changed, ms |",
            "|---|---|---|---|---|---|"]
    for r in report["rows"]:
        rows.append(f"| {r['objects']:,} | {r['vpffd_frame_ms']:.2f} / {r['lattice_frame_ms']:.2f} | "
                    f"{r['added_frame_ms']:.2f} ms ({growth(r['added_frame_growth'])}) | "
                    f"{r['vpffd_edit_ms']:.2f} / {r['lattice_edit_ms']:.2f} | "
                    f"{r['added_edit_ms']:.2f} ms ({growth(r['added_edit_growth'])}) | "
                    f"{r['lattice_retag_ms']:.2f} |")
    return "\n".join(rows)


if __name__ == "__main__":
    sys.path.insert(0, _ROOT)
    report = run()
    log(markdown(report))
    print(json.dumps(report, indent=2))
