"""The demo scenes of the Add menu (bouncing ball, twisting cube) and `./dev demo`, headless.

The scenes are built with their operators in the installed extension (conftest's `vpffd`). Every
frame is stepped and every object's volume measured here, independently of the solver, from the
float32 coordinates of the evaluated mesh in world space; the rest volume is that of the mesh's
own (undeformed) coordinates. Small Workbench renders check that the pictures show the difference.
"""
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

from . import extension_harness as eh

from demos import render_demos as rd  # noqa: E402  (repository root is on sys.path: conftest)

pytestmark = pytest.mark.blender

VOLUME_TOL = 1e-5
DEMO_KEYS = {"ball": {"plain", "vpffd_xy"}, "cube": {"plain", "vpffd_xy", "vpffd_z"},
             "tube": {"plain", "vpffd_xyz", "vpffd_z"}, "arm": {"plain", "vpffd"}}


@pytest.fixture
def ext(vpffd):
    eh.reset_scene()
    yield vpffd
    eh.reset_scene()


def _world(co, matrix):
    M = np.array(matrix, dtype=np.float64)
    return co.reshape(-1, 3).astype(np.float64) @ M[:3, :3].T + M[:3, 3]


def _volume(co, tris):
    a, b, c = co[tris[:, 0]], co[tris[:, 1]], co[tris[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def _triangles(me):
    me.calc_loop_triangles()
    tris = np.empty(len(me.loop_triangles) * 3, np.int32)
    me.loop_triangles.foreach_get("vertices", tris)
    return tris.reshape(-1, 3)


def _evaluated_volume(ob):
    """Volume of the evaluated mesh: Blender's float32 coordinates, in world space."""
    ev = ob.evaluated_get(bpy.context.evaluated_depsgraph_get())
    me = ev.data
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    return _volume(_world(co, ev.matrix_world), _triangles(me))


def _rest_volume(ob):
    """Volume of the mesh's own coordinates (never written by VP-FFD) under the world matrix."""
    ev = ob.evaluated_get(bpy.context.evaluated_depsgraph_get())
    co = np.empty(len(ob.data.vertices) * 3, np.float32)
    ob.data.vertices.foreach_get("co", co)
    return _volume(_world(co, ev.matrix_world), _triangles(ob.data))


def _build(demo):
    op = {"ball": bpy.ops.object.vpffd_demo_bouncing_ball,
          "cube": bpy.ops.object.vpffd_demo_twisting_cube,
          "tube": bpy.ops.object.vpffd_demo_squeezed_tube,
          "arm": bpy.ops.object.vpffd_demo_bent_arm}[demo]
    assert op(new_scene=False) == {"FINISHED"}
    scene = bpy.context.scene
    variants = rd.find_variants(scene)
    assert {v.key for v in variants} == DEMO_KEYS[demo], [v.key for v in variants]
    return scene, variants


@pytest.mark.parametrize("demo", sorted(DEMO_KEYS))
def test_a_demo_leaves_a_vpffd_object_active_and_selected(ext, demo):
    """So that the Properties editor shows the VP-FFD panel right after Add > VP-FFD Demos."""
    scene, _ = _build(demo)
    active = bpy.context.view_layer.objects.active
    assert active is not None and active.vpffd.is_bound and active.vpffd.axes != "NONE"
    assert [ob for ob in scene.objects if ob.select_get()] == [active]


def _step_all(scene, variants):
    """(frames, ratios (F, n) of volume to rest volume) over every frame of the scene."""
    scene.frame_set(scene.frame_start)
    rest = np.array([_rest_volume(v.obj) for v in variants])
    assert (rest > 0).all(), rest
    frames = list(range(scene.frame_start, scene.frame_end + 1))
    ratios = np.empty((len(frames), len(variants)))
    for i, f in enumerate(frames):
        scene.frame_set(f)
        ratios[i] = [_evaluated_volume(v.obj) / r for v, r in zip(variants, rest)]
    return frames, ratios


def _check_volumes(demo):
    """Step every frame: VP-FFD objects keep their rest volume; returns the plain object's ratios
    (F,), which start at 1 (undeformed at the first frame)."""
    scene, variants = _build(demo)
    assert (scene.frame_start, scene.frame_end) == (1, 60)
    frames, ratios = _step_all(scene, variants)
    plain = None
    for j, v in enumerate(variants):
        r = ratios[:, j]
        if v.preserved:
            worst = int(np.argmax(np.abs(r - 1)))
            assert abs(r[worst] - 1) <= VOLUME_TOL, f"{v.label}: {r[worst]:.8f} of rest at frame {frames[worst]}"
        else:
            assert abs(r[0] - 1) <= VOLUME_TOL
            plain = r
    return plain


def test_bouncing_ball_keeps_its_volume_on_every_frame(ext):
    r = _check_volumes("ball")
    assert r.min() <= 0.80, f"the plain ball keeps {r.min():.1%} at its deepest squash"


def test_twisting_cube_keeps_its_volume_on_every_frame(ext):
    r = _check_volumes("cube")
    assert 1 - r[-1] > 0.30, f"the plain cube loses only {1 - r[-1]:.1%} by the last frame"
    assert (np.diff(r) <= 1e-6).all(), "the plain twist should lose volume monotonically"


def test_squeezed_tube_keeps_its_volume_on_every_frame(ext):
    r = _check_volumes("tube")
    assert r.min() <= 0.85, f"the plain tube keeps {r.min():.1%} at its deepest squeeze"


def test_bent_arm_keeps_its_volume_at_bind_where_the_armature_alone_loses_it(ext):
    r = _check_volumes("arm")
    assert r.min() <= 0.95, f"the Armature alone keeps {r.min():.1%} of the arm at its deepest bend"
    arm = bpy.data.objects["Arm VP-FFD Bind"]
    s = arm.vpffd
    assert (s.target, s.outside, s.axes) == ("BIND", "FALLOFF", "XYZ")
    ops = ext.module.operators
    info = ops.status.status(arm)
    assert info.target_from == "bind" and info.falloff > 0 and info.beyond > 0, info


@pytest.mark.parametrize("demo", ["ball", "cube", "tube", "arm"])
def test_demo_objects_stay_in_the_camera_view(ext, demo):
    scene, variants = _build(demo)
    for f in range(scene.frame_start, scene.frame_end + 1, 3):
        scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        for v in variants:
            co, _ = rd.evaluated_world(v.obj, dg)
            fraction = rd.in_view_fraction(scene, co, dg)
            assert fraction == 1.0, (
                f"frame {f}: only {fraction:.0%} of {v.obj.name!r}'s vertices are inside the view of "
                f"camera {scene.camera.name!r} (location {tuple(scene.camera.location)}, rotation "
                f"{tuple(scene.camera.rotation_euler)})")


# ------------------------------------------------------------------------------------ renders

RENDER_SIZE = (160, 90)


def _read_png(path):
    """(H, W, 4) float RGBA of a PNG, read with Blender's own image loader."""
    img = bpy.data.images.load(path, check_existing=False)
    try:
        w, h = img.size
        buf = np.empty(w * h * 4, np.float32)
        img.pixels.foreach_get(buf)
        return buf.reshape(h, w, 4)
    finally:
        bpy.data.images.remove(img)


def _silhouette(scene, only, path):
    """Pixels covered by object `only` when it is the only object rendered (transparent film)."""
    saved = {ob.name: ob.hide_render for ob in scene.objects}
    film = scene.render.film_transparent
    try:
        for ob in scene.objects:
            ob.hide_render = ob is not only
        scene.render.film_transparent = True
        rd.render_still(scene, path)
    finally:
        for ob in scene.objects:
            ob.hide_render = saved[ob.name]
        scene.render.film_transparent = film
    return int((_read_png(path)[..., 3] > 0.5).sum())


def _prepare_render(scene):
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x, scene.render.resolution_y = RENDER_SIZE
    scene.render.resolution_percentage = 100


@pytest.mark.parametrize("demo", ["ball", "cube", "tube"])   # the arm's difference is a few percent
def test_renders_show_the_plain_object_losing_what_vpffd_keeps(ext, demo, tmp_path):
    """At the ball's deepest squash and the cube's last frame: the whole scene renders to a PNG,
    and each object rendered alone covers a clearly larger area with VP-FFD than without."""
    scene, variants = _build(demo)
    _prepare_render(scene)
    plain = next(v for v in variants if not v.preserved)
    if demo in ("ball", "tube"):   # the frame where the plain object has lost most
        frames = range(scene.frame_start, scene.frame_end + 1)
        volumes = []
        for f in frames:
            scene.frame_set(f)
            volumes.append(_evaluated_volume(plain.obj))
        frame = frames[int(np.argmin(volumes))]
    else:
        frame = scene.frame_end
    scene.frame_set(frame)

    full = str(tmp_path / f"{demo}_{frame:04d}.png")
    rd.render_still(scene, full)
    pixels = _read_png(full)
    assert pixels.shape == (RENDER_SIZE[1], RENDER_SIZE[0], 4)
    assert pixels[..., :3].std() > 0.02, "the render is blank"

    areas = {v.key: _silhouette(scene, v.obj, str(tmp_path / f"{demo}_{v.key}.png")) for v in variants}
    image_area = RENDER_SIZE[0] * RENDER_SIZE[1]
    for key, area in areas.items():
        assert area > 0.002 * image_area, f"{key} is (almost) not in the picture: {areas}"
    for v in variants:
        if v.preserved:
            assert areas[v.key] > 1.1 * areas[plain.key], (
                f"frame {frame}: {v.label} covers {areas[v.key]} pixels, the Lattice modifier's "
                f"{areas[plain.key]}: the pictures do not show the difference")

    if demo == "ball":   # control: at rest the two balls, placed symmetrically, look the same
        scene.frame_set(scene.frame_start)
        rest = [_silhouette(scene, v.obj, str(tmp_path / f"rest_{v.key}.png")) for v in variants]
        assert abs(rest[0] - rest[1]) <= 0.05 * max(rest), rest


# ------------------------------------------------------------------------- the main command

def test_main_command_writes_every_file_and_the_table(tmp_path):
    """`python -m demos.render_demos` (what `./dev demo` runs), small and every 10th frame (the
    Workbench shadows of the cubes cost ~0.5 s a frame here whatever the size), in a fresh
    interpreter that builds and installs the extension itself; docs/ and its demos.md redirected."""
    pytest.importorskip("PIL")
    pytest.importorskip("matplotlib")
    out, docs = tmp_path / "out", tmp_path / "docs"
    docs.mkdir()
    page = docs / "demos.md"
    assert rd.PAGE == os.path.join(rd.ROOT, "docs", "demos.md")
    shutil.copyfile(rd.PAGE, page)
    env = dict(os.environ)
    env.pop(eh.ENV, None)        # the script isolates its own Blender user folder
    proc = subprocess.run(
        [sys.executable, "-m", "demos.render_demos", "--out", str(out), "--resolution", "64x36",
         "--frame-step", "10", "--update-readme", "--page", str(page), "--docs", str(docs)],
        cwd=rd.ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    text = proc.stdout
    frames = [1, 11, 21, 31, 41, 51, 60]
    for f in frames:
        assert f"[ball] frame {f:>3}/60" in text and f"[cube] frame {f:>3}/60" in text
    assert "Bouncing ball: volume as % of rest" in text and "Twisting cube: volume as % of rest" in text
    assert "EGL" not in text                       # Blender's own messages went to the log
    for demo, n_variants in (("ball", 2), ("cube", 3)):
        d = out / demo
        assert sorted(os.listdir(d / "frames")) == [f"{f:04d}.png" for f in frames]
        for name in (f"{demo}.gif", "contact_sheet.png", "volume.png", "volumes.csv"):
            assert (d / name).stat().st_size > 0, name
        rows = (d / "volumes.csv").read_text().splitlines()
        assert len(rows) == 2 + len(frames) and len(rows[0].split(",")) == 1 + 2 * n_variants
        from PIL import Image
        with Image.open(d / f"{demo}.gif") as gif:
            assert gif.n_frames == len(frames) and gif.info.get("loop") == 0
    assert (out / "blender.log").stat().st_size > 0
    body = page.read_text()
    block = body[body.index(rd.README_START):body.index(rd.README_END)]
    assert body.startswith("# The demos")                 # the page around the block is kept
    for demo in ("ball", "cube"):
        for name in (f"{demo}_contact_sheet.jpg", f"{demo}.gif", f"{demo}_volume.png"):
            assert f"]({name})" in block                  # linked relative to the page, beside it
            assert (docs / name).is_file()
    assert "66% lost" in block and "28%, 51%, 64%" in block
    assert sum(p.stat().st_size for p in docs.iterdir()) < 3 * 2 ** 20
