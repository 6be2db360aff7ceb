"""Render the VP-FFD demo scenes headless and measure their volumes: `./dev demo [options]`.

For each demo (the bouncing ball, the twisting cube, the squeezed tube and the bent arm of the Add
menu) this
builds the extension
zip with Blender's own builder, installs it through Blender's own installer into a private
BLENDER_USER_RESOURCES folder (set before bpy is imported; the real Blender configuration is never
touched), starts from an empty scene, adds the demo with its operator
(``bpy.ops.object.vpffd_demo_bouncing_ball(new_scene=False)``), then for every frame:

* ``scene.frame_set(f)``, and measures each deformed object's volume independently of the solver:
  ``1/6 sum a . (b x c)`` over the triangles of the *evaluated* mesh (Blender's float32
  coordinates, in world space), as a percentage of the rest volume (the mesh's own, undeformed
  coordinates under the same world matrix);
* renders the frame with Blender's Workbench engine (``bpy.ops.render.render(write_still=True)``).

Output (default folder ``out/``, git-ignored), per demo::

    out/<demo>/frames/0001.png ...   every rendered frame
    out/<demo>/<demo>.gif            the animation, downscaled, looping
    out/<demo>/contact_sheet.png     12 frames with frame numbers and volumes
    out/<demo>/volume.png            % of rest volume against frame, one line per object
    out/<demo>/volumes.csv           every frame's volumes
    out/blender.log                  what Blender itself printed while installing and rendering

and a table on the terminal (every 5th frame, the first and last, and the frames where the
Lattice modifier's volume is lowest). Exits with status 1 when a VP-FFD object's volume leaves
its rest volume by more than 1e-5 (relative) on any frame.

Options: ``--out DIR``, ``--demos ball,cube,tube,arm``, ``--resolution WxH`` (default 480x270),
``--frame-step N`` (every N-th frame and the last only: a quick look), ``--update-readme`` (copies a contact sheet, a GIF and the plot of each demo to ``docs/``,
the pictures the README and docs/demos.md show, and rewrites the block of docs/demos.md between
``<!-- demos:start -->`` and ``<!-- demos:end -->``).
"""
import argparse
import contextlib
import csv
import ctypes
import datetime
import os
import shutil
import sys
import time
from typing import List, NamedTuple

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:          # run as a script rather than `python -m demos.render_demos`
    sys.path.insert(0, ROOT)

from tests import extension_harness as eh  # noqa: E402  (build and install with Blender's tools)

VOLUME_TOL = 1e-5                 # relative; a VP-FFD object further from rest fails the run
DEFAULT_RESOLUTION = (480, 270)
GIF_WIDTH = 320
SHEET_FRAMES = 12
SHEET_COLUMNS = 4
SHEET_TILE_WIDTH = 320
BACKGROUND = (255, 255, 255)      # behind transparent pixels (the demo scenes have no World)
DOCS = os.path.join(ROOT, "docs")
PAGE = os.path.join(DOCS, "demos.md")     # the page whose block --update-readme rewrites
README_START = "<!-- demos:start -->"
README_END = "<!-- demos:end -->"
DOCS_MAX_BYTES = 3 * 2 ** 20


class Demo(NamedTuple):
    key: str
    title: str
    operator: str         # bpy.ops.object.<operator>
    description: str


DEMOS = {
    "ball": Demo("ball", "Bouncing ball", "vpffd_demo_bouncing_ball",
                 "A ball ({n_verts:,} vertices) falls, squashes on the ground twice and stretches in "
                 "flight, driven by shape keys of its 4x4x4 lattice. Left: Blender's Lattice modifier; "
                 "right: VP-FFD correcting along the lattice's X and Y, so the squash spreads "
                 "sideways (the paper's Figure 1)."),
    "cube": Demo("cube", "Twisting cube", "vpffd_demo_twisting_cube",
                 "A subdivided cube ({n_verts:,} vertices) twisted from 0 to 360 degrees by its "
                 "4x4x8 lattice (a Simple Deform modifier on the lattice). Left: Blender's Lattice "
                 "modifier; middle: VP-FFD correcting along X and Y (top and bottom stay flat); "
                 "right: VP-FFD correcting along Z (the paper's Figure 6)."),
    "tube": Demo("tube", "Squeezed tube (cage)", "vpffd_demo_squeezed_tube",
                 "A capsule ({n_verts:,} vertices) in a cylindrical VP-FFD cage (an octagon with a ring "
                 "of quads, extruded into 6 layers; depth 3) whose middle a shape key squeezes. Left: the "
                 "cage's plain deformation (Correction None); middle: VP-FFD correcting along X, Y and Z; "
                 "right: VP-FFD correcting along Z only, so the squeezed volume goes into the length."),
    "arm": Demo("arm", "Bent arm (Armature, Target: Bind)", "vpffd_demo_bent_arm",
                "An arm ({n_verts:,} vertices) skinned to two bones, its weights blending over the "
                "elbow, bends to 110 degrees and back. Left: the Armature alone, whose blended "
                "skinning loses volume at the elbow; right: VP-FFD after the Armature, with a 4x4x4 "
                "lattice around the elbow whose deformation fades out beyond it (Outside: Falloff), "
                "correcting along X, Y and Z towards the volume the arm had at Bind, in its rest "
                "pose (Target: Bind)."),
}


class Variant(NamedTuple):
    key: str              # "plain", "vpffd_xy", "vpffd_z"
    label: str            # "Lattice modifier", "VP-FFD XY", ...
    obj: object           # the bpy Object (gone once the scene is reset: use only while it lives)
    preserved: bool       # bound to VP-FFD (its volume must stay the rest volume)
    colour: tuple         # RGB 0..1, from the object's material


class DemoResult(NamedTuple):
    demo: Demo
    variants: List[Variant]
    frames: np.ndarray    # (F,)
    volumes: np.ndarray   # (F, n_variants) world-space volumes
    rest: np.ndarray      # (n_variants,)
    frame_files: list     # PNG path per frame
    framing: list         # warnings: objects outside the camera's view
    seconds: float
    render_seconds: float
    n_verts: int          # vertices of each deformed object

    @property
    def ratios(self):
        return self.volumes / self.rest

    def column(self, key):
        return [v.key for v in self.variants].index(key)


# ------------------------------------------------------------------------------ measuring (bpy)

def evaluated_world(obj, depsgraph):
    """(world coordinates (V,3) float64 of the evaluated mesh's float32 vertices, triangles (F,3))."""
    ev = obj.evaluated_get(depsgraph)
    me = ev.data
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    me.calc_loop_triangles()
    tris = np.empty(len(me.loop_triangles) * 3, np.int32)
    me.loop_triangles.foreach_get("vertices", tris)
    return to_world(co.reshape(-1, 3), ev.matrix_world), tris.reshape(-1, 3)


def rest_world(obj, depsgraph):
    """World coordinates of the mesh's own (undeformed) float32 vertices, and its triangles."""
    me = obj.data
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    me.calc_loop_triangles()
    tris = np.empty(len(me.loop_triangles) * 3, np.int32)
    me.loop_triangles.foreach_get("vertices", tris)
    return to_world(co.reshape(-1, 3), obj.evaluated_get(depsgraph).matrix_world), tris.reshape(-1, 3)


def to_world(co, matrix):
    M = np.array(matrix, dtype=np.float64)
    return co.astype(np.float64) @ M[:3, :3].T + M[:3, 3]


def signed_volume(co, tris):
    """1/6 sum over triangles of a . (b x c)."""
    a, b, c = co[tris[:, 0]], co[tris[:, 1]], co[tris[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0)


def in_view_fraction(scene, co_world, depsgraph):
    """Fraction of the points inside the scene camera's frame (and in front of it)."""
    cam = scene.camera
    r = scene.render
    P = np.array(cam.calc_matrix_camera(depsgraph, x=r.resolution_x, y=r.resolution_y,
                                        scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y))
    V = np.array(cam.evaluated_get(depsgraph).matrix_world.inverted())
    h = np.c_[co_world, np.ones(len(co_world))] @ (P @ V).T
    w = h[:, 3]
    front = w > 1e-9
    ndc = h[:, :2] / np.where(front, w, 1.0)[:, None]
    return float((front & (np.abs(ndc) <= 1.0).all(axis=1)).mean())


def find_variants(scene):
    """The demo's deformed objects, left to right: plain Lattice-modifier copies and VP-FFD ones."""
    out = []
    meshes = [ob for ob in scene.objects if ob.type == "MESH"]
    for ob in sorted(meshes, key=lambda o: o.matrix_world.translation.x):
        if ob.vpffd.is_bound and ob.vpffd.axes == "NONE":   # a cage without correction
            key, label, preserved = "plain", "Cage, no correction", False
        elif ob.vpffd.is_bound:
            axes = ob.vpffd.axes
            key, label, preserved = f"vpffd_{axes.lower()}", f"VP-FFD {axes}", True
            if ob.vpffd.target == "BIND":
                key, label = "vpffd", f"VP-FFD {axes}, Target: Bind"
        elif any(m.type == "LATTICE" for m in ob.modifiers):
            key, label, preserved = "plain", "Lattice modifier", False
        elif any(m.type == "ARMATURE" for m in ob.modifiers):
            key, label, preserved = "plain", "Armature alone", False
        else:
            continue
        mat = ob.active_material
        colour = tuple(mat.diffuse_color[:3]) if mat is not None else (0.5, 0.5, 0.5)
        out.append(Variant(key, label, ob, preserved, colour))
    return out


def build(demo):
    """Add `demo` ("ball", "cube", "tube" or "arm") to the current scene with its operator; returns
    its variants."""
    import bpy
    operator = getattr(bpy.ops.object, DEMOS[demo].operator)
    result = operator(new_scene=False)
    if result != {"FINISHED"}:
        raise RuntimeError(f"bpy.ops.object.{DEMOS[demo].operator} returned {result}")
    scene = bpy.context.scene
    variants = find_variants(scene)
    if not any(v.preserved for v in variants) or not any(not v.preserved for v in variants):
        raise RuntimeError(f"the {demo} demo has no plain and VP-FFD objects: "
                           f"{[ob.name for ob in scene.objects]}")
    return scene, variants


# ---------------------------------------------------------------------------- Blender's output

def _flush_c_stdio():
    """Flush C stdio buffers (Blender prints with printf) so nothing lands on the wrong fd."""
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):  # no C library handle on this platform
        pass


@contextlib.contextmanager
def blender_output_to(log):
    """Send what Blender prints (C stdio and Python, fds 1 and 2) to the open file `log`."""
    if log is None:
        yield
        return
    sys.stdout.flush()
    sys.stderr.flush()
    _flush_c_stdio()
    saved = os.dup(1), os.dup(2)
    os.dup2(log.fileno(), 1)
    os.dup2(log.fileno(), 2)
    try:
        yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        _flush_c_stdio()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])


def render_still(scene, path, log=None):
    """Render the current frame with the scene's engine and write it to `path` (PNG)."""
    import bpy
    scene.render.image_settings.file_format = "PNG"
    scene.render.use_file_extension = False
    scene.render.filepath = path
    with blender_output_to(log):
        result = bpy.ops.render.render(write_still=True)
    if result != {"FINISHED"} or not os.path.isfile(path):
        raise RuntimeError(f"rendering {path} failed ({result})")


# ---------------------------------------------------------------------------------- one demo

def run_demo(demo, out_dir, resolution, log=None, say=print, frame_step=1):
    """Build `demo` in an empty scene, step and render every frame (every `frame_step`-th and
    the last), measure volumes."""
    import bpy
    t0 = time.perf_counter()
    eh.reset_scene()
    scene, variants = build(demo)
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x, scene.render.resolution_y = resolution
    scene.render.resolution_percentage = 100
    frames_dir = os.path.join(out_dir, "frames")
    if os.path.isdir(frames_dir):
        shutil.rmtree(frames_dir)
    os.makedirs(frames_dir)

    frames = np.arange(scene.frame_start, scene.frame_end + 1, frame_step)
    if frames[-1] != scene.frame_end:
        frames = np.append(frames, scene.frame_end)
    scene.frame_set(int(frames[0]))
    dg = bpy.context.evaluated_depsgraph_get()
    rest_geometry = [rest_world(v.obj, dg) for v in variants]
    rest = np.array([signed_volume(co, tris) for co, tris in rest_geometry])
    volumes = np.empty((len(frames), len(variants)))
    in_view = np.empty((len(frames), len(variants)))
    files, render_seconds = [], 0.0
    tag = f"[{demo}]"
    for i, f in enumerate(frames):
        scene.frame_set(int(f))
        dg = bpy.context.evaluated_depsgraph_get()
        for j, v in enumerate(variants):
            co, tris = evaluated_world(v.obj, dg)
            volumes[i, j] = signed_volume(co, tris)
            in_view[i, j] = in_view_fraction(scene, co, dg)
        path = os.path.join(frames_dir, f"{int(f):04d}.png")
        t = time.perf_counter()
        render_still(scene, path, log)
        render_seconds += time.perf_counter() - t
        files.append(path)
        pct = "  ".join(f"{v.label} {100 * volumes[i, j] / rest[j]:{'.6f' if v.preserved else '.2f'}}%"
                        for j, v in enumerate(variants))
        say(f"{tag} frame {int(f):>3}/{int(frames[-1])}  {pct}  "
            f"(render {time.perf_counter() - t:.2f} s)")

    framing = []
    for j, v in enumerate(variants):
        out = frames[in_view[:, j] < 1.0]
        if len(out):
            framing.append(
                f"{v.obj.name!r} is {'entirely' if in_view[:, j].min() == 0 else 'partly'} outside "
                f"the camera's view on {len(out)} of {len(frames)} frames (first {out[0]}, as little "
                f"as {100 * in_view[:, j].min():.0f}% of its vertices in view)")
    return DemoResult(DEMOS[demo], variants, frames, volumes, rest, files, framing,
                      time.perf_counter() - t0, render_seconds, len(variants[0].obj.data.vertices))


# --------------------------------------------------------------------------- tables and files

def notable_frames(result):
    """Frames where a plain object's volume is lowest (when below rest), highest (when above),
    or at a dip (a local minimum more than 5% below rest)."""
    notable = set()
    for j, v in enumerate(result.variants):
        if v.preserved:
            continue
        r = result.ratios[:, j]
        if r.min() < 0.995:
            notable.add(int(result.frames[np.argmin(r)]))
        if r.max() > 1.005:
            notable.add(int(result.frames[np.argmax(r)]))
        for i in range(1, len(r) - 1):
            if r[i] < r[i - 1] and r[i] <= r[i + 1] and r[i] < 0.95:
                notable.add(int(result.frames[i]))
    return notable


def table_frames(result, step=5):
    f = [int(x) for x in result.frames]
    return sorted({f[0], f[-1]} | {x for x in f if x % step == 0} | notable_frames(result))


def table(result):
    """Lines of the terminal table: frame, then % of rest volume per object."""
    width = max(12, *(len(v.label) + 2 for v in result.variants))
    lines = [f"{result.demo.title}: volume as % of rest (measured from Blender's evaluated meshes)",
             f"{'frame':>5}" + "".join(f"{v.label:>{width}}" for v in result.variants)]
    notable = notable_frames(result)
    for f in table_frames(result):
        i = int(np.flatnonzero(result.frames == f)[0])
        cells = "".join(f"{100 * result.ratios[i, j]:>{width}{'.6f' if v.preserved else '.2f'}}"
                        for j, v in enumerate(result.variants))
        lines.append(f"{f:>5}{cells}" + ("  <-" if f in notable else ""))
    return lines


def summary(result):
    """(lines, ok): the plain objects' extremes and the VP-FFD objects' largest deviation."""
    lines, ok = [], True
    frames = result.frames
    for j, v in enumerate(result.variants):
        r = result.ratios[:, j]
        if v.preserved:
            dev = np.abs(r - 1.0)
            i = int(np.argmax(dev))
            good = dev[i] <= VOLUME_TOL
            ok &= bool(good)
            lines.append(f"  {v.label}: largest deviation from rest {dev[i]:.1e} (frame {frames[i]}); "
                         f"limit {VOLUME_TOL:.0e}: {'OK' if good else 'FAILED'}")
        else:
            lo, hi = int(np.argmin(r)), int(np.argmax(r))
            lines.append(f"  {v.label}: lowest {100 * r[lo]:.2f}% of rest at frame {frames[lo]} "
                         f"({100 * (1 - r[lo]):.1f}% lost), highest {100 * r[hi]:.2f}% at frame "
                         f"{frames[hi]}, last frame {100 * r[-1]:.2f}%")
    return lines, ok


def shown(path):
    """`path` relative to the current folder when it is inside it."""
    rel = os.path.relpath(path)
    return path if rel.startswith("..") else rel


def write_csv(result, path):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame"] + [f"{v.key}_{what}" for v in result.variants
                                for what in ("volume", "percent_of_rest")])
        w.writerow(["rest"] + [x for j in range(len(result.variants))
                               for x in (f"{result.rest[j]:.9g}", "100")])
        for i, f in enumerate(result.frames):
            w.writerow([int(f)] + [x for j in range(len(result.variants))
                                   for x in (f"{result.volumes[i, j]:.9g}",
                                             f"{100 * result.ratios[i, j]:.7f}")])


def _rgb(path):
    from PIL import Image
    im = Image.open(path).convert("RGBA")
    bg = Image.new("RGBA", im.size, BACKGROUND + (255,))
    return Image.alpha_composite(bg, im).convert("RGB")


def _scaled(im, width):
    from PIL import Image
    if im.width == width:
        return im
    return im.resize((width, max(1, round(im.height * width / im.width))), Image.LANCZOS)


def write_gif(paths, out_path, width=GIF_WIDTH, fps=24):
    """Looping GIF of the frames, `width` pixels wide, one shared palette (no flicker)."""
    from PIL import Image
    frames = [_scaled(_rgb(p), width) for p in paths]
    step = max(1, len(frames) // 8)
    sample = frames[::step]
    montage = Image.new("RGB", (width, sum(f.height for f in sample)))
    y = 0
    for f in sample:
        montage.paste(f, (0, y))
        y += f.height
    palette = montage.quantize(colors=255, method=Image.Quantize.MEDIANCUT)
    indexed = [f.quantize(palette=palette, dither=Image.Dither.NONE) for f in frames]
    indexed[0].save(out_path, save_all=True, append_images=indexed[1:], loop=0,
                    duration=round(1000 / fps), disposal=1)


def _font(size):
    from PIL import ImageFont
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType
        return ImageFont.load_default()


def sheet_frames(result, n=SHEET_FRAMES):
    """About n frames spread evenly, with the notable ones (deepest squash) swapped in."""
    f = [int(x) for x in result.frames]
    picks = sorted({f[int(round(i))] for i in np.linspace(0, len(f) - 1, min(n, len(f)))})
    for x in sorted(notable_frames(result)):
        if x in picks:
            continue
        inner = [k for k in range(1, len(picks) - 1) if picks[k] not in notable_frames(result)]
        if not inner:
            break
        k = min(inner, key=lambda k: abs(picks[k] - x))
        picks[k] = x
    return sorted(set(picks))


def write_contact_sheet(result, out_path, tile_width=SHEET_TILE_WIDTH, columns=SHEET_COLUMNS):
    """Grid of frames, each captioned with its frame number and every object's volume."""
    from PIL import Image, ImageDraw
    picks = sheet_frames(result)
    tiles = []
    for f in picks:
        i = int(np.flatnonzero(result.frames == f)[0])
        tiles.append((f, i, _scaled(_rgb(result.frame_files[i]), tile_width)))
    th = tiles[0][2].height
    caption_h, title_h, pad = 34, 30, 6
    rows = -(-len(tiles) // columns)
    W = columns * tile_width + (columns + 1) * pad
    H = title_h + rows * (th + caption_h + pad) + pad
    sheet = Image.new("RGB", (W, H), (245, 245, 245))
    draw = ImageDraw.Draw(sheet)
    big, small = _font(16), _font(12)
    names = ", ".join(v.label for v in result.variants)
    draw.text((pad, 7), f"{result.demo.title} (left to right: {names}); volume as % of rest",
              fill=(20, 20, 20), font=big)
    for n, (f, i, im) in enumerate(tiles):
        x = pad + (n % columns) * (tile_width + pad)
        y = title_h + (n // columns) * (th + caption_h + pad)
        sheet.paste(im, (x, y))
        draw.text((x + 2, y + th + 2), f"frame {f}", fill=(20, 20, 20), font=big)
        cells = []
        for j, v in enumerate(result.variants):
            pct = 100 * result.ratios[i, j]
            short = "plain" if not v.preserved else v.label.replace("VP-FFD ", "")
            cells.append(f"{short} {pct:.1f}%" if not v.preserved else f"{short} {pct:.4f}%")
        draw.text((x + 2, y + th + 19), "   ".join(cells), fill=(60, 60, 60), font=small)
    sheet.save(out_path)
    return picks


def write_plot(result, out_path):
    """% of rest volume against frame per object, and the VP-FFD objects' deviation in ppm."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(6.4, 4.4), dpi=100, sharex=True,
                                  gridspec_kw=dict(height_ratios=(3, 1.25)))
    n_preserved = 0
    for j, v in enumerate(result.variants):
        if v.preserved:   # VP-FFD lines lie on top of each other: wide solid, then narrower dashed
            style = dict(lw=4.0, ls="-") if n_preserved == 0 else dict(lw=2.0, ls=(0, (4, 2)))
            n_preserved += 1
            ax.plot(result.frames, 100 * result.ratios[:, j], color=v.colour, label=v.label, **style)
            ax2.plot(result.frames, 1e6 * (result.ratios[:, j] - 1.0), color=v.colour,
                     **{**style, "lw": style["lw"] / 2})
        else:
            ax.plot(result.frames, 100 * result.ratios[:, j], color=v.colour, lw=2,
                    label=v.label + ("" if v.label == "Armature alone" else " (plain FFD)"))
    ax.axhline(100, color="0.5", lw=0.8, ls=":")
    ax.set_ylabel("volume, % of rest")
    ax.set_title(f"{result.demo.title}: volume over time")
    ax.legend(loc="lower left", fontsize=8, frameon=False)
    ax.grid(alpha=0.3)
    limit = 1e6 * VOLUME_TOL
    ax2.axhspan(-limit, limit, color="0.92", lw=0)
    for s in (-1, 1):
        ax2.axhline(s * limit, color="0.5", lw=0.8, ls="--")
    ax2.set_ylim(-1.4 * limit, 1.4 * limit)
    ax2.set_ylabel("VP-FFD\nminus rest (ppm)", fontsize=8)
    ax2.text(result.frames[-1], 1.05 * limit, f"limit {VOLUME_TOL:.0e}", ha="right", va="bottom",
             fontsize=7, color="0.4")
    ax2.set_xlabel("frame")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_path)
    plt.close(fig)


def write_outputs(result, out_dir):
    """GIF, contact sheet, plot and CSV of one demo; returns their paths."""
    key = result.demo.key
    paths = dict(gif=os.path.join(out_dir, f"{key}.gif"),
                 sheet=os.path.join(out_dir, "contact_sheet.png"),
                 plot=os.path.join(out_dir, "volume.png"),
                 csv=os.path.join(out_dir, "volumes.csv"))
    write_csv(result, paths["csv"])
    write_plot(result, paths["plot"])
    write_contact_sheet(result, paths["sheet"])
    write_gif(result.frame_files, paths["gif"])
    return paths


# ------------------------------------------------------------------------------ docs/demos.md

PAPER_NOTE = (
    "The paper's scenes are not ours, so compare the kind of effect, not the digits: its bouncing "
    "object is the RedBox scan (710,322 vertices) flattened on the ground, ours a ball of {ball_verts:,} "
    "vertices whose lattice a shape key flattens to 45% of its height; its twisting cube has 6,146 "
    "vertices{cube_verts}, but its lattice and twist angle are not given (ours: a 4x4x8 B-spline "
    "lattice, 0 to 360 degrees over {cube_frames} frames).")


def _wrap(text, width=100):
    import textwrap
    return textwrap.fill(text, width=width, break_long_words=False, break_on_hyphens=False)


def readme_block(results, env, pictures="docs"):
    """Markdown between the markers of docs/demos.md, from this run's results; `pictures`: the
    folder of the pictures, relative to the page."""
    by = {r.demo.key: r for r in results}
    pic = lambda name: f"{pictures}/{name}" if pictures not in ("", ".") else name  # noqa: E731
    lines = [README_START,
             "<!-- written by ./dev demo --update-readme; edit demos/render_demos.py instead -->", "",
             _wrap(f"Rendered by `./dev demo` on {env['date']} with Blender {env['blender']} (the `bpy` "
                   f"module, headless), Workbench engine, {env['resolution']}, {env['frames']}; the run "
                   f"took {env['seconds']:.0f} s on {env['cpus']} CPU cores. Volumes are measured from the "
                   "meshes Blender evaluates (float32 coordinates, world space), independently of the "
                   "solver. Red: plain FFD (Blender's Lattice modifier, or the cage without correction) "
                   "or the Armature alone; blue: VP-FFD correcting along the lattice's X and Y (X, Y and "
                   "Z for the tube and the arm); green: VP-FFD correcting along Z."), ""]
    for key in ("ball", "cube", "tube", "arm"):
        r = by[key]
        lines += [f"### {r.demo.title}", "", _wrap(r.demo.description.format(n_verts=r.n_verts)), "",
                  f"![{r.demo.title}: contact sheet]({pic(key + '_contact_sheet.jpg')})", "",
                  f"![{r.demo.title}: animation]({pic(key + '.gif')}) "
                  f"![{r.demo.title}: volume over time]({pic(key + '_volume.png')})", ""]

    ball, cube = by["ball"], by["cube"]

    def worst_dev(r):
        return ", ".join(f"{v.label.replace('VP-FFD ', '')}: {np.abs(r.ratios[:, j] - 1).max():.0e}"
                         for j, v in enumerate(r.variants) if v.preserved)

    cp = cube.ratios[:, cube.column("plain")]
    bp = ball.ratios[:, ball.column("plain")]
    dips = sorted(i for i, f in enumerate(ball.frames) if int(f) in notable_frames(ball) and bp[i] < 0.95)
    ball_cell = ", ".join(f"{100 * (1 - bp[i]):.1f}% lost at frame {ball.frames[i]}" for i in dips)
    if bp.max() > 1.0:
        ball_cell += f"; up to {100 * (bp.max() - 1):.1f}% gained in flight"
    lines += ["### Volumes next to the paper's", "",
              "| scene | plain FFD, this run (Lattice modifier) | plain FFD, paper | VP-FFD, this run: "
              "largest relative deviation from rest over all frames |",
              "|---|---|---|---|",
              f"| twisting cube, last frame | {100 * (1 - cp[-1]):.1f}% lost at frame {cube.frames[-1]} "
              f"| 66% lost at the last frame (Figure 6) | {worst_dev(cube)} |",
              f"| bouncing ball, squashed on the ground | {ball_cell} | RedBox (Figure 1): 28%, 51%, 64% "
              f"lost at frames 25, 30, 35 | {worst_dev(ball)} |", "",
              _wrap(f"The VP-FFD objects keep their rest volume to within {VOLUME_TOL:.0e} (relative) on "
                    "every frame (`./dev demo` fails otherwise); what remains is the float32 rounding of "
                    "Blender's coordinates. " + PAPER_NOTE.format(
                        ball_verts=ball.n_verts,
                        cube_verts=" like ours" if cube.n_verts == 6146 else f", ours {cube.n_verts:,}", cube_frames=int(cube.frames[-1] - cube.frames[0] + 1))),
              "", README_END]
    return "\n".join(lines)


def update_readme(results, env, out_dirs, readme=PAGE, docs=DOCS):
    """Copy small images to `docs` and rewrite the block between the markers of the page `readme`
    (docs/demos.md), its pictures linked relative to the page."""
    from PIL import Image
    with open(readme) as fh:
        text = fh.read()
    start, end = text.find(README_START), text.find(README_END)
    if start < 0 or end < start:
        raise SystemExit(f"{readme}: markers {README_START} ... {README_END} not found")
    os.makedirs(docs, exist_ok=True)
    written = []
    for r in results:
        key, src = r.demo.key, out_dirs[r.demo.key]
        sheet = Image.open(os.path.join(src, "contact_sheet.png")).convert("RGB")
        sheet = _scaled(sheet, min(sheet.width, 1000))
        sheet_path = os.path.join(docs, f"{key}_contact_sheet.jpg")
        sheet.save(sheet_path, quality=82, optimize=True)
        gif_path = os.path.join(docs, f"{key}.gif")
        shutil.copyfile(os.path.join(src, f"{key}.gif"), gif_path)
        plot_path = os.path.join(docs, f"{key}_volume.png")
        shutil.copyfile(os.path.join(src, "volume.png"), plot_path)
        written += [sheet_path, gif_path, plot_path]
    total = sum(os.path.getsize(p) for p in written)
    if total > DOCS_MAX_BYTES:
        raise SystemExit(f"the demo pictures come to {total} bytes, over {DOCS_MAX_BYTES}: "
                         "make them smaller (GIF_WIDTH, the contact sheet's width)")
    with open(readme, "w") as fh:
        pictures = os.path.relpath(docs, os.path.dirname(os.path.abspath(readme))).replace(os.sep, "/")
        fh.write(text[:start] + readme_block(results, env, pictures) + text[end + len(README_END):])
    return written, total


# -------------------------------------------------------------------------------------- main

def parse_args(argv):
    p = argparse.ArgumentParser(prog="./dev demo", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=os.path.join(ROOT, "out"), help="output folder (default out/)")
    p.add_argument("--demos", default="ball,cube,tube,arm",
                   help="comma-separated: ball, cube, tube, arm (default all)")
    p.add_argument("--resolution", default="%dx%d" % DEFAULT_RESOLUTION,
                   help="render size WxH (default %(default)s)")
    p.add_argument("--frame-step", type=int, default=1, metavar="N",
                   help="render and measure every N-th frame and the last (default every frame)")
    p.add_argument("--update-readme", action="store_true",
                   help="copy small images to docs/ (the README's and docs/demos.md's pictures) "
                        "and rewrite the demos block of docs/demos.md")
    p.add_argument("--page", default=PAGE, help=argparse.SUPPRESS)
    p.add_argument("--docs", default=DOCS, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    a.demos = [d.strip() for d in a.demos.split(",") if d.strip()]
    unknown = [d for d in a.demos if d not in DEMOS]
    if unknown or not a.demos:
        p.error(f"--demos: unknown {unknown}; choose from {', '.join(DEMOS)}")
    try:
        w, h = (int(x) for x in a.resolution.lower().split("x"))
        if w < 16 or h < 16:
            raise ValueError
    except ValueError:
        p.error(f"--resolution: expected WxH of at least 16x16, e.g. 480x270, not {a.resolution!r}")
    a.resolution = (w, h)
    if a.frame_step < 1:
        p.error("--frame-step must be at least 1")
    if a.update_readme and set(a.demos) != set(DEMOS):
        p.error("--update-readme needs every demo (leave out --demos)")
    return a


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    t0 = time.perf_counter()
    eh.isolate_user_resources()           # before bpy is imported: Blender reads it at start-up
    import bpy
    say = lambda *a: print(*a, flush=True)  # noqa: E731
    os.makedirs(args.out, exist_ok=True)
    log_path = os.path.join(args.out, "blender.log")
    with open(log_path, "w") as log:
        say(f"VP-FFD demos with Blender {bpy.app.version_string}: building the extension zip and "
            "installing it with Blender's installer (private user folder) ...")
        zip_dir = os.path.join(eh._ISOLATED, "zip")
        with blender_output_to(log):
            zip_path = eh.build_extension_zip(ROOT, zip_dir)
            eh.install_extension(zip_path)
        results, out_dirs, ok = [], {}, True
        for demo in args.demos:
            out_dir = out_dirs[demo] = os.path.join(args.out, demo)
            os.makedirs(out_dir, exist_ok=True)
            say(f"[{demo}] {DEMOS[demo].title}: rendering with Workbench at "
                f"{args.resolution[0]}x{args.resolution[1]} into {shown(out_dir)}/frames/")
            result = run_demo(demo, out_dir, args.resolution, log=log, say=say,
                              frame_step=args.frame_step)
            say(f"[{demo}] writing the GIF, contact sheet, plot and CSV ...")
            paths = write_outputs(result, out_dir)
            results.append(result)
            say("")
            for line in table(result):
                say(line)
            lines, good = summary(result)
            ok &= good
            for line in lines:
                say(line)
            for warning in result.framing:
                say(f"  WARNING: {warning}")
            say(f"  {len(result.frames)} frames in {result.seconds:.1f} s ({result.render_seconds:.1f} s "
                f"rendering); files: " + ", ".join(shown(p) for p in
                                                    [os.path.join(out_dir, 'frames')] + list(paths.values())))
            say("")
        seconds = time.perf_counter() - t0
        if ok:
            say(f"Every VP-FFD object stayed within {VOLUME_TOL:.0e} of its rest volume on every frame.")
        else:
            say(f"FAILED: a VP-FFD object left its rest volume by more than {VOLUME_TOL:.0e}.")
        framing = [w for r in results for w in r.framing]
        if framing:
            say("WARNING: some objects are outside the camera's view: the pictures do not show them "
                "(the cameras are set up in operators/demo_scenes.py).")
        if args.update_readme:
            if not ok or framing:
                say(f"{shown(args.page)} not updated: " + ("a VP-FFD object's volume check failed" if not ok else
                    "the pictures would not show every object (see the warnings above)") + ".")
                ok = False
            else:
                env = dict(date=datetime.date.today().isoformat(), blender=bpy.app.version_string,
                           resolution=f"{args.resolution[0]}x{args.resolution[1]}",
                           frames=", ".join(f"{len(r.frames)} frames ({r.demo.title.lower()})"
                                            for r in results),
                           seconds=seconds, cpus=os.cpu_count())
                written, total = update_readme(results, env, out_dirs, args.page, args.docs)
                say(f"{shown(args.page)} updated; {len(written)} images in {shown(args.docs)}/ "
                    f"({total / 2 ** 20:.2f} MiB): " + ", ".join(os.path.basename(p) for p in written))
        say(f"Done in {time.perf_counter() - t0:.0f} s; Blender's own messages are in "
            f"{shown(log_path)}.")
    return 0 if ok else 1


def _exit(code):
    """Exit with `code`. bpy 4.2 crashes while the interpreter shuts down once a property with an
    update callback was registered (the extension registers some), so leave at once there."""
    bpy = sys.modules.get("bpy")
    if bpy is not None and tuple(bpy.app.version) < (4, 3, 0):
        sys.stdout.flush()
        sys.stderr.flush()
        if eh._ISOLATED:
            shutil.rmtree(eh._ISOLATED, ignore_errors=True)
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    _exit(main())
