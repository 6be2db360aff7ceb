"""The Blender fuzzer's state machine (hypothesis): the rules a user can apply to a scene of
bound meshes and lattices, and the invariants checked after every step (docstring of
test_fuzz_blender.py)."""
import faulthandler
import os
import sys
import tempfile

import bpy
import numpy as np
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule

import vpffd_addon as core  # repository copy: only to build meshes

from . import extension_harness as eh
from .fuzz_blender_scene import (AXES, COUNTS, FAILED_REBIND, FLUX_REL, INTERP, KIND, MID, OID,
                                 ORIG, SHARED, TARGET_REL, UNEXPECTED, VOLUME_REL, WATCHDOG,
                                 _HOOKED, _Tee, _clear_flags, _closed, _co, _ops, _evaluated_co,
                                 _exception_from_operator, _known, _lattice_co, _lattice_object,
                                 _link, _matrix, _mesh_object, _modifier, _new_id, _norm, _note,
                                 _op, _pick, _remember, _set_co, _tagged, _tris, _volume,
                                 _watchdog_file)


SETTINGS = st.fixed_dictionaries({}, optional={
    "axes": st.sampled_from(AXES),
    "space": st.sampled_from(["LATTICE", "WORLD"]),
    "volume_scale": st.sampled_from([1.0, 0.0, 0.5, 1.3, 2.5, 1e-6, 40.0]),
    "strength": st.sampled_from([1.0, 0.0, 0.5, -0.7, 2.0]),
    "use_islands": st.booleans(),
    "vertex_group": st.sampled_from(["", "Weights", "Pin", "Missing"]),
    "invert_vertex_group": st.booleans(),
    "mobility_group": st.sampled_from(["", "Mob", "Missing"]),
    "pin_mode": st.sampled_from(["NONE", "VERTEX", "GROUP"]),
    "pin_vertex": st.sampled_from([0, 5, 161, 641, 5000]),
    "pin_vertex_group": st.sampled_from(["", "Pin", "Weights", "Missing"]),
    "pin_target": st.sampled_from(["empty", None, "mesh"]),
    "show_overlay": st.booleans(),
    "backend": st.sampled_from(["AUTO", "CPU", "NUMPY", "GPU"]),
    "use_fold_attribute": st.booleans(),
    "outside": st.sampled_from(["FOLLOW", "FALLOFF", "INSIDE"]),
    "falloff_distance": st.sampled_from([0.5, 0.001, 0.2, 3.0]),
    "target": st.sampled_from(["INPUT", "BIND"]),
})
# Settings that bind (most of the time): what a sequence starts from.
SANE_SETTINGS = st.fixed_dictionaries({
    "axes": st.sampled_from(AXES),
    "space": st.sampled_from(["LATTICE", "WORLD"]),
    "volume_scale": st.sampled_from([1.0, 1.0, 0.7, 1.4]),
    "use_islands": st.booleans(),
    "vertex_group": st.sampled_from(["", "", "Weights"]),
    "invert_vertex_group": st.booleans(),
    "mobility_group": st.sampled_from(["", "", "Mob"]),
}, optional={
    "pin_mode": st.just("GROUP"), "pin_vertex_group": st.just("Pin"), "pin_target": st.just("empty"),
})
INDEX = st.integers(0, 3)
SEEDS = st.integers(0, 2 ** 32 - 1)


class BlenderFuzz(RuleBasedStateMachine):
    def __init__(self):
        super().__init__()
        eh.reset_scene()
        _ops().bound.forget()
        COUNTS["sequences"] += 1
        self.tmp = tempfile.mkdtemp(prefix="vpffd-fuzz-")
        self.expected = {}          # mesh id -> expected coordinates (float32 bytes)
        self.ready = False
        self.output = []
        self.hooked = _HOOKED
        self.hooked.clear()
        self._hook = sys.excepthook
        self._streams = sys.stdout, sys.stderr

        def hook(kind, value, tb):
            self.hooked.append(f"{kind.__name__}: {value}")
            self._hook(kind, value, tb)
        sys.excepthook = hook
        sys.stdout, sys.stderr = _Tee(sys.stdout, self.output), _Tee(sys.stderr, self.output)

    def teardown(self):
        sys.excepthook = self._hook
        sys.stdout, sys.stderr = self._streams
        import shutil
        shutil.rmtree(self.tmp, ignore_errors=True)

    # -- bookkeeping

    def _step(self, name, detail=""):
        COUNTS["steps"] += 1
        COUNTS["rules"][name] += 1
        _note(f"step: {name} {detail}")
        if WATCHDOG:   # a hang (e.g. in LAPACK) ends the run with a traceback instead of stalling
            faulthandler.dump_traceback_later(WATCHDOG, exit=True, file=_watchdog_file())

    def _push(self, name):
        bpy.ops.ed.undo_push(message=f"fuzz {name}")

    def _sync_from_file(self):
        """After undo/redo: what the restored file says is expected."""
        self.expected = {}
        for ob in _tagged("mesh"):
            me = ob.data
            if MID in me and ORIG in me:
                self.expected[me[MID]] = bytes(me[ORIG])

    # -- set-up

    @initialize(seed=SEEDS, n_meshes=st.integers(1, 2), n_lattices=st.integers(1, 2),
                subdivisions=st.sampled_from([2, 3]), open_part=st.booleans(),
                shapes=st.lists(st.tuples(*[st.integers(1, 4)] * 3), min_size=2, max_size=2),
                interps=st.lists(st.tuples(*[st.sampled_from(INTERP)] * 3), min_size=2, max_size=2),
                animated=st.booleans(), settings=SANE_SETTINGS,
                bind=st.sampled_from([True, True, True, False]))
    def setup(self, seed, n_meshes, n_lattices, subdivisions, open_part, shapes, interps,
              animated, settings, bind):
        rng = np.random.default_rng(seed)
        scene = bpy.context.scene
        scene.frame_start, scene.frame_end = 1, 40
        scene.frame_set(1)
        for k in range(n_lattices):
            _lattice_object(shapes[k], interps[k], rng, animated and k == 0)
        for k in range(n_meshes):
            v, f = core.icosphere(subdivisions if k == 0 else 2, rng.uniform(0.4, 0.8),
                                  rng.uniform(-0.15, 0.15, 3))
            if open_part and k == 0:
                hv, hf = core.icosphere(1, 0.2, (0.75, 0.6, 0.55))
                hf = hf[hv[hf].mean(1)[:, 2] < 0.55]          # the bottom half: open
                f = np.vstack([f, hf + len(v)])
                v = np.vstack([v, hv])
            ob = _mesh_object(v, f, rng)
            ob.rotation_euler = rng.uniform(-0.4, 0.4, 3)
            ob.scale = rng.choice([1.0, 0.8, 1.2, -1.0], 3) if rng.random() < 0.3 else (1, 1, 1)
            ob.vpffd.lattice = _tagged("lattice")[k % n_lattices]
            mid, data = _remember(ob.data)
            self.expected[mid] = data
        empty = _link(bpy.data.objects.new("FuzzHandle", None))
        empty[KIND], empty[OID] = "empty", _new_id("em")
        cam = _link(bpy.data.objects.new("FuzzCam", bpy.data.cameras.new("FuzzCam")))
        cam.location, cam.rotation_euler = (0, -6, 0), (1.5708, 0, 0)
        scene.camera = cam
        scene.render.engine = "BLENDER_WORKBENCH"
        scene.render.resolution_x = scene.render.resolution_y = 16
        scene.render.filepath = os.path.join(self.tmp, "frame_")
        for ob in _tagged("mesh"):
            self._apply_settings(ob, settings)
            if bind:
                result, error = _op("vpffd_bind", ob)
                self._count_bind(result, error)
                assert result != "EXCEPTION", error
        self.ready = True
        self._step("setup", f"meshes={n_meshes} lattices={n_lattices} shapes={shapes[:n_lattices]}")
        self._push("setup")

    def _apply_settings(self, ob, values):
        s = ob.vpffd
        for key, value in values.items():
            if not hasattr(s, key):   # a setting this revision of the extension does not have
                continue
            if key == "pin_target":
                value = {"empty": _pick("empty", 0), "mesh": ob}.get(value)
                try:
                    s.pin_target = value
                except (TypeError, ValueError, AttributeError) as exc:
                    # the poll refuses non-Empties: fine, as long as it says so
                    assert str(exc), "pin_target assignment failed without a message"
                continue
            setattr(s, key, value)

    # -- rules

    @rule(i=INDEX, values=SETTINGS)
    def change_settings(self, i, values):
        ob = _pick("mesh", i)
        self._step("change_settings", values)
        if ob is not None:
            self._apply_settings(ob, values)
        self._push("settings")

    def _count_bind(self, result, error):
        COUNTS["bind"][str(sorted(result)) if isinstance(result, set) else result] += 1
        if error and result == "ERROR":
            COUNTS["bind"]["error: " + _norm(error)] += 1
            _note(f"bind reported: {error}")

    @rule(i=INDEX, values=st.one_of(SANE_SETTINGS, SETTINGS))
    def bind(self, i, values):
        ob = _pick("mesh", i)
        self._step("bind", values)
        if ob is None:
            return
        self._apply_settings(ob, values)
        before = _co(ob.data).tobytes()
        was_bound = ob.vpffd.is_bound
        result, error = _op("vpffd_bind", ob)
        self._count_bind(result, error)
        if result == "EXCEPTION":
            _exception_from_operator(ob, "vpffd_bind", error)
        assert _co(ob.data).tobytes() == before, "binding changed the mesh's coordinates"
        if result == {"FINISHED"}:
            assert ob.vpffd.is_bound and _modifier().find(ob) is not None
            if ob.data.users == 1:
                _clear_flags(ob.data)
        elif was_bound and ob.vpffd.is_bound:
            ob.data[FAILED_REBIND] = True
        self._push("bind")

    @rule(i=INDEX)
    def unbind(self, i):
        ob = _pick("mesh", i)
        self._step("unbind")
        if ob is None:
            return
        result, error = _op("vpffd_unbind", ob)
        assert error is None, error
        if result == {"FINISHED"}:
            assert not ob.vpffd.is_bound
            assert _modifier().find(ob) is None
            left = [a.name for a in ob.data.attributes if a.name.startswith("vpffd")]
            # another object sharing this mesh may still be bound and write its offsets back
            if ob.data.users == 1:
                assert not left, f"unbind left attributes {left}"
            expected = self.expected[ob.data[MID]]
            assert _co(ob.data).tobytes() == expected, "unbind did not restore the coordinates"
            if ob.data.users == 1:
                _clear_flags(ob.data)
            if not len(ob.modifiers):
                assert _evaluated_co(ob).tobytes() == expected, "unbound mesh evaluates differently"
            COUNTS["exact_coordinate_checks"] += 1
        self._push("unbind")

    @rule(i=INDEX)
    def apply(self, i):
        ob = _pick("mesh", i)
        self._step("apply")
        if ob is None:
            return
        before = _co(ob.data).tobytes()
        shown = _evaluated_co(ob).reshape(-1, 3).astype(np.float64)
        mod = _modifier().find(ob)
        switched_off = mod is not None and not mod.show_viewport
        stale = _stale_inputs(ob)
        result, error = _op("vpffd_apply", ob)
        assert result != "EXCEPTION", error
        if result == {"FINISHED"}:
            co = _co(ob.data)
            assert np.isfinite(co).all(), "Apply wrote non-finite coordinates"
            scale = max(1.0, float(np.abs(shown).max()))
            err = float(np.abs(co.reshape(-1, 3) - shown).max()) if len(shown) else 0.0
            if ob.data.users == 1 and len(ob.modifiers) == 0 and err > 1e-5 * scale \
                    and not ob.data.get(SHARED):
                if stale:
                    _known("stale-signature", f"Apply moved by {err:.3g} from what was shown")
                elif switched_off:
                    _known("apply-with-modifier-off", f"moved by {err:.3g} from what was shown")
                else:
                    raise AssertionError(f"Apply made a shape {err:.3g} away from the one shown")
            mid, data = _remember(ob.data)
            self.expected[mid] = data
            if ob.data.users == 1:
                _clear_flags(ob.data)
        else:
            if error:
                COUNTS["bind"]["apply error: " + _norm(error)] += 1
            assert _co(ob.data).tobytes() == before, "a failed Apply changed the coordinates"
        self._push("apply")

    @rule(i=INDEX, mode=st.sampled_from(["jitter", "jitter", "squash", "extreme", "plane", "point",
                                         "mirror", "nonfinite", "rest"]),
          magnitude=st.sampled_from([1e3, 1e8, 1e20, 1e30, 3e38]), seed=SEEDS)
    def move_lattice(self, i, mode, magnitude, seed):
        lat = _pick("lattice", i)
        self._step("move_lattice", f"{mode} {magnitude:g}")
        if lat is None:
            return
        rng = np.random.default_rng(seed)
        lt = lat.data
        keys = lt.shape_keys.key_blocks if lt.shape_keys else None
        target = keys[int(rng.integers(len(keys)))].data if keys else lt.points
        attr = "co" if keys else "co_deform"
        co = _lattice_co(lt, "co")
        if mode == "jitter":
            co += rng.normal(0, 0.3, co.shape)
        elif mode == "squash":
            co *= rng.uniform(0.2, 1.5, 3)
        elif mode == "extreme":
            k = rng.random(len(co)) < 0.3
            co[k] = rng.choice([-1.0, 1.0], (int(k.sum()), 3)) * magnitude
        elif mode == "plane":
            co[:, int(rng.integers(3))] = float(rng.uniform(-0.5, 0.5))
        elif mode == "point":
            co[:] = co[int(rng.integers(len(co)))]
        elif mode == "mirror":
            co[:, int(rng.integers(3))] *= -1.0
        elif mode == "nonfinite":
            co[int(rng.integers(len(co)))] = rng.choice([np.nan, np.inf, -np.inf])
        target.foreach_set(attr, co.astype(np.float32).ravel())
        lt.update_tag()
        lat.update_tag()
        self._push("move lattice")

    @rule(i=INDEX, shape=st.tuples(*[st.integers(1, 4)] * 3),
          interp=st.tuples(*[st.sampled_from(INTERP)] * 3))
    def reshape_lattice(self, i, shape, interp):
        lat = _pick("lattice", i)
        self._step("reshape_lattice", f"{shape} {interp}")
        if lat is None:
            return
        lt = lat.data
        lt.interpolation_type_u, lt.interpolation_type_v, lt.interpolation_type_w = interp
        if lt.shape_keys is None:   # Blender refuses new resolutions while shape keys exist
            lt.points_u, lt.points_v, lt.points_w = shape
        lat.update_tag()
        self._push("reshape lattice")

    @rule(i=INDEX, which=st.sampled_from(["enabled", "viewport", "render", "remove"]))
    def toggle_modifier(self, i, which):
        ob = _pick("mesh", i)
        self._step("toggle_modifier", which)
        if ob is None:
            return
        mod = _modifier().find(ob)
        if which == "enabled":
            ob.vpffd.enabled = not ob.vpffd.enabled
        elif mod is not None and which == "viewport":
            mod.show_viewport = not mod.show_viewport
        elif mod is not None and which == "render":
            mod.show_render = not mod.show_render
        elif mod is not None and which == "remove":
            ob.modifiers.remove(mod)
        self._push("toggle")

    @rule(i=INDEX, j=INDEX, what=st.sampled_from(["lattice", "none", "mesh"]))
    def set_lattice(self, i, j, what):
        ob = _pick("mesh", i)
        self._step("set_lattice", what)
        if ob is None:
            return
        value = {"lattice": _pick("lattice", j), "none": None, "mesh": ob}[what]
        try:
            ob.vpffd.lattice = value
        except (TypeError, ValueError, AttributeError) as exc:
            assert str(exc)
        self._push("set lattice")

    @rule(seed=SEEDS, shape=st.tuples(*[st.integers(1, 4)] * 3),
          interp=st.tuples(*[st.sampled_from(INTERP)] * 3), animated=st.booleans())
    def add_lattice(self, seed, shape, interp, animated):
        self._step("add_lattice")
        if len(_tagged("lattice")) < 3:
            _lattice_object(shape, interp, np.random.default_rng(seed), animated)
        self._push("add lattice")

    @rule(i=INDEX, kind=st.sampled_from(["lattice", "empty", "mesh"]))
    def delete_object(self, i, kind):
        ob = _pick(kind, i)
        self._step("delete_object", kind)
        if ob is None:
            return
        if kind == "mesh":
            mid = ob.data[MID]
            shared = ob.data.users > 1
            bpy.data.objects.remove(ob)
            if not shared:
                self.expected.pop(mid, None)
        else:
            bpy.data.objects.remove(ob)
        self._push("delete")

    @rule(kind=st.sampled_from(["empty", "mesh"]), seed=SEEDS)
    def add_object(self, kind, seed):
        self._step("add_object", kind)
        rng = np.random.default_rng(seed)
        if kind == "empty" and not _tagged("empty"):
            empty = _link(bpy.data.objects.new("FuzzHandle", None))
            empty[KIND], empty[OID] = "empty", _new_id("em")
        elif kind == "mesh" and len(_tagged("mesh")) < 3:
            v, f = core.icosphere(2, rng.uniform(0.3, 0.7), rng.uniform(-0.2, 0.2, 3))
            ob = _mesh_object(v, f, rng)
            lats = _tagged("lattice")
            if lats:
                ob.vpffd.lattice = lats[int(rng.integers(len(lats)))]
            self.expected[ob.data[MID]] = bytes(ob.data[ORIG])
        self._push("add")

    @rule(i=INDEX, kind=st.sampled_from(["lattice", "empty", "mesh", "mesh data", "lattice group"]),
          name=st.text(st.characters(codec="utf-8", exclude_categories=["Cs", "Cc"]),
                       min_size=1, max_size=70))
    def rename(self, i, kind, name):
        self._step("rename", kind)
        if kind == "lattice group":
            lat = _pick("lattice", i)
            if lat is not None and lat.vertex_groups:
                lat.vertex_groups[0].name = name
        elif kind == "mesh data":
            ob = _pick("mesh", i)
            if ob is not None:
                ob.data.name = name
        else:
            ob = _pick(kind, i)
            if ob is not None:
                ob.name = name
        self._push("rename")

    @rule(i=INDEX, j=INDEX, kind=st.sampled_from(["mesh", "lattice", "empty"]), seed=SEEDS,
          how=st.sampled_from(["small", "small", "rotate", "zero scale", "huge", "tiny", "parent",
                               "unparent"]))
    def transform(self, i, j, kind, seed, how):
        ob = _pick(kind, i)
        self._step("transform", f"{kind} {how}")
        if ob is None:
            return
        rng = np.random.default_rng(seed)
        if how == "small":
            ob.location = np.asarray(ob.location) + rng.normal(0, 0.1, 3)
        elif how == "rotate":
            ob.rotation_euler = rng.uniform(-3, 3, 3)
        elif how == "zero scale":
            s = list(ob.scale)
            s[int(rng.integers(3))] = 0.0
            ob.scale = s
        elif how == "huge":
            ob.scale = np.asarray(ob.scale) * 1e6
        elif how == "tiny":
            ob.scale = np.asarray(ob.scale) * 1e-6
        elif how == "parent":
            others = [o for o in _tagged("lattice") + _tagged("empty") + _tagged("mesh") if o != ob]
            parent = others[j % len(others)] if others else None
            try:
                ob.parent = parent
            except (TypeError, ValueError, RuntimeError) as exc:  # a loop: Blender refuses it
                assert str(exc)
        else:
            ob.parent = None
        self._push("transform")

    @rule(i=INDEX, mode=st.sampled_from(["add vertices", "delete vertices", "delete faces",
                                         "delete all faces"]), seed=SEEDS)
    def edit_topology(self, i, mode, seed):
        ob = _pick("mesh", i)
        self._step("edit_topology", mode)
        if ob is None:
            return
        import bmesh
        rng = np.random.default_rng(seed)
        me = ob.data
        old = _co(me).reshape(-1, 3)
        if mode == "add vertices":
            n = int(rng.integers(1, 4))
            me.vertices.add(n)
            me.update()
            want = np.vstack([old, np.zeros((n, 3), np.float32)])
        else:
            bm = bmesh.new()
            bm.from_mesh(me)
            bm.verts.ensure_lookup_table()
            bm.faces.ensure_lookup_table()
            if mode == "delete vertices":
                gone = set(rng.choice(len(bm.verts), size=min(3, len(bm.verts) - 1), replace=False).tolist())
                bmesh.ops.delete(bm, geom=[bm.verts[k] for k in gone], context="VERTS")
            elif mode == "delete faces" and len(bm.faces) > 1:
                gone_f = rng.choice(len(bm.faces), size=min(2, len(bm.faces) - 1), replace=False)
                bmesh.ops.delete(bm, geom=[bm.faces[int(k)] for k in gone_f], context="FACES_ONLY")
                gone = set()
            else:
                bmesh.ops.delete(bm, geom=list(bm.faces), context="FACES_ONLY")
                gone = set()
            bm.to_mesh(me)
            bm.free()
            me.update()
            keep = [k for k in range(len(old)) if k not in gone]
            want = old[keep]
        assert _co(me).tobytes() == want.astype(np.float32).tobytes(), \
            "a topology edit did not keep the other vertices' own coordinates"
        mid, data = _remember(me)
        self.expected[mid] = data
        self._push("topology")

    @rule(i=INDEX, seed=SEEDS, how=st.sampled_from(["some", "all", "scale"]))
    def move_vertices(self, i, seed, how):
        ob = _pick("mesh", i)
        self._step("move_vertices", how)
        if ob is None:
            return
        rng = np.random.default_rng(seed)
        co = _co(ob.data).reshape(-1, 3).copy()
        if how == "some":
            k = rng.random(len(co)) < 0.2
            co[k] += rng.normal(0, 0.05, (int(k.sum()), 3)).astype(np.float32)
        elif how == "all":
            co += rng.normal(0, 0.01, co.shape).astype(np.float32)
        else:
            co *= np.float32(rng.uniform(0.7, 1.3))
        _set_co(ob.data, co)
        mid, data = _remember(ob.data)
        self.expected[mid] = data
        self._push("move vertices")

    @rule(i=INDEX, move=st.booleans(), frame=st.integers(1, 40))
    def edit_mode_round_trip(self, i, move, frame):
        ob = _pick("mesh", i)
        self._step("edit_mode_round_trip", f"move={move}")
        if ob is None:
            return
        import bmesh
        ops = _ops()
        with bpy.context.temp_override(object=ob, active_object=ob, selected_objects=[ob]):
            bpy.context.view_layer.objects.active = ob
            bpy.ops.object.mode_set(mode="EDIT")
            try:
                bpy.context.scene.frame_set(frame)
                if ob.vpffd.is_bound and ops.status.stats(ob).get("error") is None and ob.vpffd.lattice:
                    mod = _modifier().find(ob)
                    if mod is not None and mod.show_viewport:
                        info = ops.status.stats(ob)
                        # Solved live from the mesh as edited (entering changes no shape).
                        assert info.get("editing") and "volume_percent" in info, info
                if move:
                    bm = bmesh.from_edit_mesh(ob.data)
                    for v in list(bm.verts)[::7]:
                        v.co.z += 0.02
                    bmesh.update_edit_mesh(ob.data)
            finally:
                bpy.ops.object.mode_set(mode="OBJECT")
        if move:
            mid, data = _remember(ob.data)
            self.expected[mid] = data
        self._push("edit mode")

    @rule(i=INDEX, j=INDEX)
    def duplicate_linked(self, i, j):
        ob = _pick("mesh", i)
        self._step("duplicate_linked")
        if ob is None or len(_tagged("mesh")) >= 3:
            return
        twin = _link(ob.copy())   # Alt-D: a new object sharing the mesh (and copying settings)
        twin[OID] = _new_id("ob")

        twin.location = np.asarray(ob.location) + [0.05 * (j + 1), 0, 0]
        self._push("duplicate")

    @rule(i=INDEX)
    def make_single_user(self, i):
        ob = _pick("mesh", i)
        self._step("make_single_user")
        if ob is None or ob.data.users < 2:
            return
        ob.data = ob.data.copy()
        ob.data[MID] = _new_id("me")
        self.expected[ob.data[MID]] = bytes(ob.data[ORIG])
        self._push("single user")

    @rule(frame=st.integers(-5, 45))
    def change_frame(self, frame):
        self._step("change_frame", frame)
        bpy.context.scene.frame_set(frame)
        self._push("frame")

    @rule()
    def save_and_reload(self):
        self._step("save_and_reload")
        path = os.path.join(self.tmp, "fuzz.blend")
        bpy.ops.wm.save_as_mainfile(filepath=path, check_existing=False)
        bpy.ops.wm.open_mainfile(filepath=path)
        # Python references died with the old file: everything is found again by its id.
        found = {ob.data[MID] for ob in _tagged("mesh") if MID in ob.data}
        assert found == set(self.expected), f"reload lost meshes: {set(self.expected) - found}"

    @rule(animation=st.booleans(), frame=st.integers(1, 40))
    def render(self, animation, frame):
        self._step("render", f"animation={animation}")
        scene = bpy.context.scene
        if scene.camera is None:
            cam = _link(bpy.data.objects.new("FuzzCam", bpy.data.cameras.new("FuzzCam")))
            cam.location, cam.rotation_euler = (0, -6, 0), (1.5708, 0, 0)
            scene.camera = cam
        scene.render.engine = "BLENDER_WORKBENCH"
        scene.render.resolution_x = scene.render.resolution_y = 16
        scene.render.filepath = os.path.join(self.tmp, "frame_")
        if animation:
            scene.frame_start, scene.frame_end = frame, frame + 1
            bpy.ops.render.render(animation=True)
            scene.frame_start, scene.frame_end = 1, 40
        else:
            scene.frame_set(frame)
            bpy.ops.render.render(write_still=False)
        self._push("render")

    @rule(redo=st.booleans(), times=st.integers(1, 3))
    def undo(self, redo, times):
        self._step("redo" if redo else "undo", times)
        op = bpy.ops.ed.redo if redo else bpy.ops.ed.undo
        for _ in range(times):
            if not op.poll():
                break
            op()
        self._sync_from_file()
        self._check_fresh_after_undo()

    def _check_fresh_after_undo(self):
        """What the mesh shows and the panel says after undo must be what solving the restored
        inputs from scratch gives. (Known bug stale-after-undo: counted, then the cache is
        dropped so that the rest of the sequence is checked from a consistent state.)"""
        ops = _ops()
        scene = bpy.context.scene
        scene.frame_set(scene.frame_current)
        for ob in _tagged("mesh"):
            if not ob.vpffd.is_bound or ob.data.users > 1:
                continue
            shown, error = _evaluated_co(ob), ops.status.stats(ob).get("error")
            ops.bound.forget(ob)
            scene.frame_set(scene.frame_current)
            again, error2 = _evaluated_co(ob), ops.status.stats(ob).get("error")
            scale = max(1.0, float(np.abs(again).max(initial=0)))
            err = float(np.abs(shown - again).max(initial=0)) if len(shown) == len(again) else np.inf
            if err > 1e-5 * scale or (error or None) != (error2 or None):
                _known("stale-after-undo", f"{ob.name}: shown {err:.3g} away from a fresh solve, "
                       f"error {error!r} -> {error2!r}")

    @rule(i=INDEX)
    def check_folds(self, i):
        ob = _pick("mesh", i)
        self._step("check_folds")
        if ob is None:
            return
        result, error = _op("vpffd_check_folds", ob)
        if result == "EXCEPTION":
            _exception_from_operator(ob, "vpffd_check_folds", error)
        if result == {"FINISHED"}:
            folds = _ops().status.stats(ob).get("folds")
            assert isinstance(folds, int) and 0 <= folds <= len(ob.data.vertices)

    @rule(i=INDEX)
    def fresh_recompute(self, i):
        """Drop the cached binding and solve again: the displayed mesh must not change."""
        ob = _pick("mesh", i)
        self._step("fresh_recompute")
        if ob is None or not ob.vpffd.is_bound or ob.data.users > 1 or ob.data.get(SHARED):
            return
        ops = _ops()
        scene = bpy.context.scene
        scene.frame_set(scene.frame_current)
        if ops.status.stats(ob).get("error"):
            return
        shown = _evaluated_co(ob).reshape(-1, 3).astype(np.float64)
        stale = _stale_inputs(ob)
        ops.bound.forget(ob)
        scene.frame_set(scene.frame_current)
        if ops.status.stats(ob).get("error"):
            raise AssertionError(f"solving from scratch fails where the cached solve did not: "
                                 f"{ops.status.stats(ob)['error']}")
        again = _evaluated_co(ob).reshape(-1, 3).astype(np.float64)
        scale = max(1.0, float(np.abs(again).max()))
        err = float(np.abs(shown - again).max()) if len(again) else 0.0
        COUNTS["fresh_recompute_checks"] += 1
        if err > 1e-5 * scale and stale:
            _known("stale-signature", f"{ob.name}: moved by {err:.3g} on a fresh solve")
            return
        if err > 1e-5 * scale and ob.data.get(FAILED_REBIND):
            _known("failed-bind-changes-weights", f"{ob.name}: moved by {err:.3g} on a fresh solve")
            return
        assert err <= 1e-5 * scale, (f"the displayed mesh differs from a fresh solve by {err:.3g} "
                                     f"(stale cached state)")

    # -- invariants

    @invariant()
    def everything_holds(self):
        if not self.ready:
            return
        COUNTS["checks"] += 1
        scene = bpy.context.scene
        scene.frame_set(scene.frame_current)        # let the handlers settle what the step changed
        ops = _ops()
        text = "".join(self.output)
        assert not self.hooked, f"an exception reached Blender (a handler raised): {self.hooked}"
        for bad in ("Traceback", "VP-FFD: update failed", "VP-FFD: after loading"):
            assert bad not in text, f"handler output contains {bad!r}:\n{text[-3000:]}"
        self.output.clear()
        dg = bpy.context.evaluated_depsgraph_get()
        meshes = _tagged("mesh")
        assert {ob.data[MID] for ob in meshes} <= set(self.expected)
        for ob in meshes:
            self._check_mesh(ob, dg, ops)

    def _check_mesh(self, ob, dg, ops):
        me = ob.data
        co = _co(me)
        expected = self.expected[me[MID]]
        assert bytes(me[ORIG]) == expected, "the file's record of the coordinates disagrees"
        assert co.tobytes() == expected, f"{ob.name}: the mesh's own coordinates changed"
        COUNTS["exact_coordinate_checks"] += 1
        for attr in me.attributes:
            if attr.name.startswith("vpffd") and attr.data_type in ("FLOAT", "FLOAT_VECTOR"):
                key = "value" if attr.data_type == "FLOAT" else "vector"
                width = 1 if attr.data_type == "FLOAT" else 3
                buf = np.empty(len(attr.data) * width, np.float32)
                attr.data.foreach_get(key, buf)
                if not np.isfinite(buf).all() and not np.isnan(buf).any() \
                        and attr.name in ("vpffd_offset", "vpffd_jacobian"):
                    _known("float32-attribute-overflow", f"{ob.name}: inf in {attr.name}")
                    return
                assert np.isfinite(buf).all(), f"{ob.name}: non-finite values in attribute {attr.name}"
        shown = _evaluated_co(ob, dg)
        assert np.isfinite(shown).all(), f"{ob.name}: the evaluated mesh has NaN or inf"

        s = ob.vpffd
        mod = _modifier().find(ob)
        info = ops.status.stats(ob)
        error = info.get("error")
        if error:
            COUNTS["reported_errors"][_norm(error)] += 1
            assert not UNEXPECTED.match(error), f"{ob.name}: unexpected exception in update: {error}"
        for w in info.get("warnings") or ():
            COUNTS["warnings"][_norm(w)] += 1
        others = [m for m in ob.modifiers if m != mod]
        if others:
            return
        if me.get(SHARED) and (s.is_bound or mod is not None):
            return   # another object writes into this mesh too (known bug): nothing to compare
        plain = (not s.is_bound or mod is None or not mod.show_viewport
                 or (error and ("lattice is missing" in error or "topology" in error)))
        if plain:
            assert shown.tobytes() == expected, \
                f"{ob.name}: unbound/disabled/lattice-less mesh does not evaluate to its own coordinates"
            return
        if error or "volume_percent" not in info or me.users > 1 or ob.mode != "OBJECT":
            return
        self._check_volume(ob, dg, info, shown)

    def _check_volume(self, ob, dg, info, shown):
        lat = ob.vpffd.lattice
        lat_eval = lat.evaluated_get(dg)
        grid = _lattice_co(lat_eval.data, "co")
        L = np.linalg.inv(_matrix(lat_eval.matrix_world)) @ _matrix(ob.evaluated_get(dg).matrix_world)
        tris = _tris(ob.data)
        rest = np.frombuffer(self.expected[ob.data[MID]], np.float32).reshape(-1, 3).astype(np.float64)
        now = shown.reshape(-1, 3).astype(np.float64)
        rest_l = rest @ L[:3, :3].T + L[:3, 3]
        now_l = now @ L[:3, :3].T + L[:3, 3]
        if _closed(tris, len(rest)):
            origin = 0.5 * (rest_l.min(0) + rest_l.max(0))
        else:
            origin = 0.5 * (grid.min(0) + grid.max(0))
        v_rest, flux_rest = _volume(rest_l - origin, tris)
        v_now, flux_now = _volume(now_l - origin, tris)
        if not (np.isfinite(v_rest) and np.isfinite(v_now)) or v_rest == 0:
            return
        # The panel gives sizes (a lattice that mirrors space turns the volume's sign with it).
        reference = abs(v_rest)
        if info.get("target_from") == "bind":
            # Percentages of the volume at Bind; the panel gives the input's share of it too.
            reference = abs(v_rest) / (info["input_percent"] / 100.0)
        reported = info["volume_percent"] / 100.0 * reference * (1.0 if v_now >= 0 else -1.0)
        scale = max(abs(v_rest), abs(v_now))
        # The evaluated coordinates are float32: each is off by up to eps * its magnitude (in
        # object space), which moves the volume by up to that times the surface area.
        delta = 2.0 ** -23 * float(np.abs(now).max(initial=0)) * float(np.linalg.norm(L[:3, :3], 2))
        e1, e2 = now_l[tris[:, 1]] - now_l[tris[:, 0]], now_l[tris[:, 2]] - now_l[tris[:, 0]]
        area = float(0.5 * np.linalg.norm(np.cross(e1, e2), axis=1).sum())
        allowance = VOLUME_REL * scale + FLUX_REL * max(flux_now, flux_rest) + 3 * delta * area
        COUNTS["volume_checks"] += 1
        if abs(reported - v_now) > allowance:
            if not _closed(tris, len(rest)):
                far = float(np.abs(0.5 * (rest_l.min(0) + rest_l.max(0)) - origin).max())
                size = float(np.ptp(rest_l, 0).max())
                if far > 10 * size:
                    _known("open-mesh-float32-cancellation", f"{ob.name}: reported "
                           f"{info['volume_percent']:.6f}%, measured {100 * v_now / v_rest:.6f}%, "
                           f"the open mesh {far / size:.3g} x its size from the lattice centre")
                    return
            if ob.vpffd.axes == "NONE" and _closed(tris, len(rest)):
                far = float(np.abs(0.5 * (rest_l.min(0) + rest_l.max(0))
                                   - 0.5 * (grid.min(0) + grid.max(0))).max())
                size = float(np.ptp(rest_l, 0).max())
                if far > 1e3 * size:
                    _known("plain-volume-about-lattice-centre", f"{ob.name}: reported "
                           f"{info['volume_percent']:.6f}%, measured {100 * v_now / v_rest:.6f}%, "
                           f"{far / size:.3g} x its size from the lattice centre")
                    return
            flung = _flung(ob, dg)
            if flung is not None and flung > 1e3 and ob.vpffd.pin_mode == "NONE":
                _known("flat-lattice-blowup", f"{ob.name}: reported {info['volume_percent']:.6f}%, measured "
                       f"{100 * v_now / v_rest:.6f}%, points moved {flung:.3g} x the lattice")
                return
        assert abs(reported - v_now) <= allowance, (
            f"{ob.name}: reported volume {info['volume_percent']:.6f}% of rest, measured "
            f"{100 * v_now / v_rest:.6f}% (axes {ob.vpffd.axes}, warnings {info.get('warnings')})")
        s = ob.vpffd
        if s.axes != "NONE" and not info.get("warnings") and s.pin_mode == "NONE":
            target = 100.0 * s.volume_scale
            COUNTS["target_checks"] += 1
            assert abs(info["volume_percent"] - target) <= 100 * TARGET_REL * max(1.0, s.volume_scale) \
                + 100 * (FLUX_REL * flux_now + 3 * delta * area) / abs(v_rest), (
                f"{ob.name}: no warning, but the volume is {info['volume_percent']:.6f}% for a "
                f"target of {target}%")


def _stale_inputs(ob):
    """The cached solve used inputs that the current settings no longer give (the known
    stale-signature bug): another interpolation, or an inverted vertex group (whose influence
    depends on whether a group is set)."""
    state = _ops().bound.state_of(ob)
    binding = getattr(state, "binding", None)
    lat = ob.vpffd.lattice
    if binding is None or lat is None or lat.type != "LATTICE":
        return ob.vpffd.invert_vertex_group
    now = tuple(getattr(lat.data, f"interpolation_type_{a}")[4:] for a in "uvw")
    return now != tuple(binding.lattice.interpolation) or ob.vpffd.invert_vertex_group


def _flung(ob, dg):
    """How far the last solve moved the lattice points, in lattice sizes (None if unknown)."""
    state = _ops().bound.state_of(ob)
    points = getattr(state, "points", None)
    if points is None or ob.vpffd.lattice is None:
        return None
    lt = ob.vpffd.lattice.evaluated_get(dg).data
    grid, moved = _lattice_co(lt, "co"), _lattice_co(lt, "co_deform")
    if len(points) != len(grid):
        return None
    P = grid + ob.vpffd.strength * (moved - grid)
    size = max(float(np.ptp(grid, 0).max()), float(np.ptp(P, 0).max())) or 1.0
    return float(np.abs(points - P).max()) / size
