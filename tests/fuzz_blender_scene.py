"""The Blender fuzzer's scene: its settings from the environment, the bugs it knows (by the test
that shows each), and helpers that build, pick and measure fuzzed objects. Coordinates and
triangles are read through the product's own `operators.meshio`. Used by
`fuzz_blender_machine.py` and the regression tests; imported only after bpy was."""
import collections
import os
import re
import tempfile

import bpy
import numpy as np
from hypothesis import note

from .blender_ref import triangle_mesh

EXAMPLES = int(os.environ.get("VPFFD_FUZZ_EXAMPLES", "40"))
STEPS = int(os.environ.get("VPFFD_FUZZ_STEPS", "30"))
RANDOM = os.environ.get("VPFFD_FUZZ_RANDOM", "") not in ("", "0")
SEED = os.environ.get("VPFFD_FUZZ_SEED")
STRICT = os.environ.get("VPFFD_FUZZ_STRICT", "1") != "0"   # a known bug fails unless exploring
WATCHDOG = float(os.environ.get("VPFFD_FUZZ_WATCHDOG", "300"))   # seconds per step; 0: off

# Bugs this fuzzer found, each reproduced and described by the test named here (in
# tests/test_regressions_blender.py unless a path is given). A violation that matches a fixed one
# fails the run, labelled; so does one that matches an open one (VPFFD_FUZZ_STRICT=0, for a long
# exploratory run, counts open ones in the summary instead, so the run goes on looking for others).
BUGS = {
    "operator-raises-with-modifier-off": "test_regression_operator_raises_with_modifier_off",
    "apply-with-modifier-off": "test_regression_apply_with_modifier_off",
    "flat-lattice-blowup": "test_regression_flat_lattice_blowup_in_blender",
    "failed-bind-changes-weights": "test_regression_failed_bind_changes_weights",
    "linked-duplicate-of-bound-mesh": "test_regression_linked_duplicate_of_bound_mesh",
    "stale-signature": "test_fixed_bug_stale_signature",
    "stale-after-undo": "test_fixed_bug_stale_after_undo",
    "float32-attribute-overflow": "test_fixed_bug_float32_attribute_overflow",
    "plain-volume-about-lattice-centre": "test_fixed_bug_plain_volume_about_lattice_centre",
    "open-mesh-float32-cancellation":
        "tests/test_fuzz_core.py::test_known_bug_open_mesh_float32_cancellation",
}
OPEN_BUGS = {"open-mesh-float32-cancellation"}

KIND = "fuzz_kind"        # object custom property: "mesh", "lattice" or "empty"
OID = "fuzz_id"           # object custom property: stable id (names are fuzzed)
MID = "fuzz_mesh_id"      # mesh custom property: stable id of the datablock
ORIG = "fuzz_orig"        # mesh custom property: expected coordinates (float32 bytes)
SHARED = "fuzz_shared_bound"      # mesh flag: a bound object was linked-duplicated (known bug)
FAILED_REBIND = "fuzz_failed_rebind"  # mesh flag: a Bind failed on it while bound (known bug)

AXES = ["XYZ", "XY", "XZ", "YZ", "X", "Y", "Z", "NONE"]
INTERP = ["KEY_LINEAR", "KEY_CARDINAL", "KEY_CATMULL_ROM", "KEY_BSPLINE"]
VOLUME_REL = 1e-5         # the documented bound (docs/design.md, Accuracy): against independent volume, relative
TARGET_REL = 1e-5         # the documented bound: reported against target when no warning
FLUX_REL = 1e-5           # float32 rounding allowance, relative to sum |face terms|

# Errors an engine reports as "<Type>: message" are exceptions other than ValueError: bugs.
UNEXPECTED = re.compile(r"^[A-Z][A-Za-z]*(Error|Exception|Warning): ")

COUNTS = {"sequences": 0, "steps": 0, "checks": 0, "volume_checks": 0, "target_checks": 0,
          "exact_coordinate_checks": 0, "fresh_recompute_checks": 0,
          "rules": collections.Counter(), "bind": collections.Counter(),
          "known_bugs": collections.Counter(),
          "reported_errors": collections.Counter(), "warnings": collections.Counter(),
          "seconds": 0.0}

_EXT = None  # the installed extension (set by the test)


def _report_path():
    default = os.path.join(tempfile.gettempdir(),
                           f"vpffd-fuzz-blender-{bpy.app.version_string.split()[0]}.json")
    return os.environ.get("VPFFD_FUZZ_REPORT", default)


def _ops():
    return _EXT.module.operators


def _modifier():
    return _EXT.module.operators.modifier


# ------------------------------------------------------------------------- scene helpers

def _meshio():
    return _EXT.module.operators.meshio


def _co(mesh):
    """The mesh's own coordinates, flat float32 (as stored), through the product's reader."""
    return _meshio().mesh_coords(mesh, np.float32).ravel()


def _set_co(mesh, co):
    mesh.vertices.foreach_set("co", np.ascontiguousarray(co, np.float32).ravel())
    mesh.update()


def _tris(mesh):
    return _meshio().mesh_triangles(mesh)


def _matrix(m):
    return _meshio().matrix(m)


def _lattice_co(lt, attr):
    return _meshio().lattice_points(lt, attr)


def _tagged(kind):
    scene = bpy.context.scene
    return sorted((ob for ob in scene.objects if ob.get(KIND) == kind), key=lambda o: o[OID])


def _pick(kind, i):
    obs = _tagged(kind)
    return obs[i % len(obs)] if obs else None


def _new_id(prefix):
    n = bpy.context.scene.get("fuzz_counter", 0) + 1
    bpy.context.scene["fuzz_counter"] = n
    return f"{prefix}{n}"


def _remember(mesh):
    """Store the mesh's current coordinates as the expected ones (custom property: undo-safe)."""
    if MID not in mesh:
        mesh[MID] = _new_id("me")
    data = _co(mesh).tobytes()
    if ORIG in mesh:
        del mesh[ORIG]   # re-assigning a bytes property copies it as a C string (up to a NUL byte)
    mesh[ORIG] = data
    assert bytes(mesh[ORIG]) == data
    return mesh[MID], data


def _clear_flags(mesh):
    for key in (SHARED, FAILED_REBIND):
        if key in mesh:
            del mesh[key]


def _link(ob):
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _mesh_object(verts, tris, rng):
    me = triangle_mesh(verts, tris, "FuzzMesh")
    ob = _link(bpy.data.objects.new("FuzzMesh", me))
    ob[KIND], ob[OID] = "mesh", _new_id("ob")
    V = len(verts)
    weights = ob.vertex_groups.new(name="Weights")
    w = rng.uniform(0, 1, V)
    assigned = rng.random(V) > 0.1
    for value in np.unique(np.round(w[assigned], 1)):
        idx = np.flatnonzero(assigned & (np.round(w, 1) == value)).tolist()
        weights.add(idx, float(value), "REPLACE")
    co = np.asarray(verts)
    top = np.flatnonzero(co[:, 2] > np.quantile(co[:, 2], 0.97)).tolist()
    ob.vertex_groups.new(name="Pin").add(top, 1.0, "REPLACE")
    _remember(me)
    return ob


def _lattice_object(shape, interp, rng, animated):
    lt = bpy.data.lattices.new("FuzzLattice")
    lt.points_u, lt.points_v, lt.points_w = shape
    lt.interpolation_type_u, lt.interpolation_type_v, lt.interpolation_type_w = interp
    ob = _link(bpy.data.objects.new("FuzzLattice", lt))
    ob[KIND], ob[OID] = "lattice", _new_id("lat")
    # Blender's rest grid spans (n - 1) units per axis: scale it to about 2.2 around the mesh.
    ob.scale = [2.2 / (n - 1) if n > 1 else 1.0 for n in shape]
    ob.location = rng.uniform(-0.1, 0.1, 3)
    ob.rotation_euler = rng.uniform(-0.3, 0.3, 3)
    mob = ob.vertex_groups.new(name="Mob")
    for i in range(len(lt.points)):
        if rng.random() < 0.8:
            mob.add([i], float(rng.uniform(0, 1)), "REPLACE")
    if animated:
        ob.shape_key_add(name="Basis")
        key = ob.shape_key_add(name="Squash")
        co = _lattice_co(lt, "co")
        co[:, 2] *= rng.uniform(0.3, 0.9)
        co += rng.normal(0, 0.05, co.shape)
        key.data.foreach_set("co", co.astype(np.float32).ravel())
        for f, v in ((1, 0.0), (20, 1.0), (40, 0.0)):
            key.value = v
            key.keyframe_insert("value", frame=f)
    return ob


def _evaluated_co(ob, depsgraph=None):
    dg = depsgraph or bpy.context.evaluated_depsgraph_get()
    me = ob.evaluated_get(dg).data
    buf = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", buf)
    return buf


def _closed(tris, n):
    t = tris[(tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 2] != tris[:, 0])]
    if len(t) == 0:
        return False
    fwd = sorted(zip(t.ravel().tolist(), t[:, [1, 2, 0]].ravel().tolist()))
    if len(set(fwd)) != len(fwd):
        return False
    return sorted((b, a) for a, b in fwd) == fwd


def _volume(v, tris):
    a, b, c = v[tris[:, 0]], v[tris[:, 1]], v[tris[:, 2]]
    terms = np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0
    return float(terms.sum()), float(np.abs(terms).sum())


_HOOKED = []   # exceptions sys.excepthook saw (the machine's hook appends here)


def _op(name, ob, **kw):
    """Run bpy.ops.object.<name> on `ob`: (result, error text or None). A reported VP-FFD error
    (an ERROR report raises RuntimeError in background bpy) is a legitimate outcome: ("ERROR",
    text). An exception raised inside the operator is not: ("EXCEPTION", text)."""
    fn = getattr(bpy.ops.object, name)
    with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
        if not fn.poll():
            return "POLL", None
        seen = len(_HOOKED)
        try:
            return fn(**kw), None
        except RuntimeError as exc:
            # Blender also hands the operator's exception to sys.excepthook: it is reported
            # here, not by a handler.
            del _HOOKED[seen:]
            text = str(exc)
            if "Traceback" in text or "VP-FFD:" not in text:
                return "EXCEPTION", text
            return "ERROR", text


def _norm(text):
    """An error message with numbers and quoted names removed, for counting."""
    return re.sub(r"'[^']*'", "'…'", re.sub(r"-?\d+(\.\d+)?(e[-+]?\d+)?", "N", str(text)))[:140]


def _note(text):
    try:
        note(text)
    except Exception:  # outside a hypothesis run (the deterministic reproductions below)
        pass


_WATCHDOG_FILE = []


def _watchdog_file():
    if not _WATCHDOG_FILE:
        _WATCHDOG_FILE.append(open(_report_path() + ".watchdog.txt", "w"))
    return _WATCHDOG_FILE[0]


def _known(bug, detail):
    """A violation matching a known bug: count it (fail in strict mode, or when it was fixed)."""
    COUNTS["known_bugs"][bug] += 1
    _note(f"known bug {bug}: {detail}")
    if STRICT or bug not in OPEN_BUGS:
        raise AssertionError(f"{'known' if bug in OPEN_BUGS else 'fixed'} bug {bug} (see "
                             f"{BUGS[bug]}):\n{detail}")


def _exception_from_operator(ob, name, text):
    mod = _modifier().find(ob)
    if ob.vpffd.is_bound and mod is not None and not mod.show_viewport \
            and name in ("vpffd_bind", "vpffd_check_folds"):
        _known("operator-raises-with-modifier-off", f"{name}: {text.splitlines()[-2:]}")
        return
    raise AssertionError(f"bpy.ops.object.{name} raised inside the operator:\n{text}")


class _Tee:
    """Wraps sys.stdout / sys.stderr to see what handlers print."""

    def __init__(self, stream, sink):
        self.stream, self.sink = stream, sink

    def write(self, text):
        self.sink.append(text)
        return self.stream.write(text)

    def __getattr__(self, name):
        return getattr(self.stream, name)
