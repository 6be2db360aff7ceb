"""Break the product on purpose and show that the test suite goes red (`./dev mutate`).

Each mutation edits one line of a copy of the repository (the working tree is never touched),
runs a slice of the suite there with the newest Blender's environment (.venv), the strict skip
policy on, and expects pytest to fail. The slices are the tests that should catch the breakage;
the whole suite contains them, so a red slice means a red `./dev test`. See docs/testing.md.

    python -m tests.mutate [NAME ...]     (default: every mutation)

Exit status 0 when every mutation was caught, 1 when one survived (the suite let it through).
"""
import os
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# name: (file, the exact text to replace, its replacement, pytest arguments, extra environment)
MUTATIONS = {
    "volume-target-bias": (
        "vpffd_addon/solve.py",
        "        self.targets = targets                      # (k,)",
        "        self.targets = targets * (1 + 5e-5)         # (k,)",
        ["-m", "core", "tests/test_core_reference.py", "tests/test_core_properties.py"], {}),
    "apply-raises": (
        "operators/lifecycle.py",
        'the deformer first among the enabled modifiers, and no shape keys."""\n    d = deformer_of(target)\n',
        'the deformer first among the enabled modifiers, and no shape keys."""\n    raise RuntimeError("mutation: Apply is broken")\n',
        ["tests/test_regressions_blender.py", "tests/test_extension_blender.py"], {}),
    "gpu-kernel-invalid": (
        "operators/gpu_shaders.py",
        "int global_index() { return",
        "int global_index() { this is not GLSL; return",
        ["tests/test_gpu_backend.py"], {}),
    "bake-esc-ignored": (
        "operators/bake_ops.py",
        '        if event.type == "ESC" and event.value == "PRESS":',
        '        if event.type == "NONE_SUCH" and event.value == "PRESS":',
        ["tests/e2e/test_gui_window.py"], {"VPFFD_NO_E2E": ""}),
    "compiled-gradient-scale": (
        "vpffd_addon/solve_kernels.py",
        "            gv = acc * (1.0 / 6.0)",
        "            gv = acc * (1.0 / 6.00001)",
        ["tests/test_core_compiled.py", "tests/test_compiled_blender.py"], {}),
    "compiled-transpose-axis": (
        "vpffd_addon/solve_kernels.py",
        "    change_basis_runs(B, c, 1, C)\n",
        "    change_basis_runs(B, c, 0, C)\n",
        ["tests/test_core_compiled.py"], {}),
    "moments-run-rows": (
        "vpffd_addon/solve_kernels.py",
        "        if not (bl + 1 < n_blocks and block_row[bl + 1] == block_row[bl]\n",
        "        if not (bl + 1 < n_blocks\n",
        ["tests/test_core_compiled.py"], {}),
    "compiled-forward-axis": (
        "vpffd_addon/solve_kernels.py",
        "    change_basis(A, c, 1, False, B)\n",
        "    change_basis(A, c, 0, False, B)\n",
        ["tests/test_core_compiled.py"], {}),
    "offsets-still-moved": (
        "vpffd_addon/frame_kernels.py",
        "        if keep and still[v]:\n",
        "        if False:\n",
        ["tests/test_core_compiled.py"], {}),
    "offsets-map-transposed": (
        "vpffd_addon/frame_kernels.py",
        "            q1 = p0 * m10 + p1 * m11 + p2 * m12 + m13\n",
        "            q1 = p0 * m01 + p1 * m11 + p2 * m21 + m13\n",
        ["tests/test_core_compiled.py"], {}),
    "weights-kept-stale": (
        "vpffd_addon/frame.py",
        "                    and last[0].dtype == w.dtype and np.array_equal(last[0], w):\n",
        "                    and last[0].dtype == w.dtype:\n",
        ["tests/test_core_reembed.py"], {}),
    "team-part-short": (
        "vpffd_addon/solve_kernels.py",
        "        _k_forward(params, c, block_cell, shape, D, x0, comps, X, edges[k], edges[k + 1])",
        "        _k_forward(params, c, block_cell, shape, D, x0, comps, X, edges[k], edges[k + 1] - 1)",
        ["tests/test_core_compiled.py", "-k", "any_number_of_threads_is_the_same"], {}),
    "fused-skip-lost": (
        "vpffd_addon/compiled.py",
        "        for j in skipped:           # (ran out of spins at the barrier)\n",
        "        for j in []:\n",
        ["tests/test_core_compiled.py", "-k", "hand_over"], {}),
    "fused-no-barrier": (
        "vpffd_addon/solve_kernels.py",
        "    return wait_count(sync, 0, n, looks)\n",
        "    return True\n",
        ["tests/test_core_compiled.py"], {}),
    "compiled-ring-unclosed": (
        "vpffd_addon/solve_kernels.py",
        "        acc += pm * q0 - qm * p0\n",
        "        acc += 0.0\n",
        ["tests/test_core_compiled.py"], {}),
    "rings-reuse-faces": (
        "vpffd_addon/solve_kernels.py",
        "                    if pairs_v[2 * e] == nxt and not used[e - s0]:",
        "                    if pairs_v[2 * e] == nxt:",
        ["tests/test_core_compiled.py", "-k", "rings_and_pairs"], {}),
    "tap-copies-read": (
        "operators/tap.py",
        "        own = marked[:m]\n",
        "        own = marked\n",
        ["tests/test_stack_blender.py", "-k", "copied_after"], {}),
    "compiled-bind-influence": (
        "vpffd_addon/layout_kernels.py",
        "            params[3, sl] = s[v]",
        "            params[3, sl] = 1.0",
        ["tests/test_core_compiled.py"], {}),
    "islands-float32": (
        "vpffd_addon/solve.py",
        "        st.in_float64()\n",
        "        pass\n",
        ["tests/test_core_compiled.py"], {}),
    "islands-sweep-unsolved": (
        "vpffd_addon/solve.py",
        "                    u = u + du\n",
        "                    u = u + 0.0 * du\n",
        ["tests/test_core_reference.py", "-k", "islands_match"], {}),
    "joint-lstsq-threads": (
        "vpffd_addon/compiled.py",
        "    if K is None or k > n or k == 0:\n        return None\n    # Scaled",
        "    if True:\n        return None\n    # Scaled",
        ["tests/test_core_compiled.py", "-k", "spinning"], {}),
    "face-sums-signed-size": (
        "vpffd_addon/layout_kernels.py",
        "                x2, y2, z2 = rel[d, 0], rel[d, 1], rel[d, 2]\n"
        "                term = (x0 * (y1 * z2 - z1 * y2)\n"
        "                        + y0 * (z1 * x2 - x1 * z2)\n"
        "                        + z0 * (x1 * y2 - y1 * x2)) / 6.0\n"
        "                total += term\n"
        "                size += abs(term)",
        "                x2, y2, z2 = rel[d, 0], rel[d, 1], rel[d, 2]\n"
        "                term = (x0 * (y1 * z2 - z1 * y2)\n"
        "                        + y0 * (z1 * x2 - x1 * z2)\n"
        "                        + z0 * (x1 * y2 - y1 * x2)) / 6.0\n"
        "                total += term\n"
        "                size += term",
        ["tests/test_core_compiled.py", "-k", "volume_sums"], {}),
    "volume-kept-stale": (
        "vpffd_addon/frame.py",
        "        if kept is not None and kept[0] is topology and same_array(kept[1], X):",
        "        if kept is not None and kept[0] is topology:",
        ["tests/test_core_compiled.py", "-k", "kept_only_for_the_same_positions"], {}),
    "runs-crossing-left": (
        "vpffd_addon/solve_kernels.py",
        "        if done[r] == 0:\n",
        "        if done[r] == 2:\n",
        ["tests/test_core_compiled.py", "-k", "runs_summed"], {}),
    "runs-sums-carried": (
        "vpffd_addon/solve_kernels.py",
        "    while r < n_runs and run_start[r + 1] <= b1:\n        for q in range(64):\n            acc[q] = 0.0\n",
        "    acc[:] = 0.0\n    while r < n_runs and run_start[r + 1] <= b1:\n",
        ["tests/test_core_compiled.py", "-k", "runs_summed"], {}),
    "runs3-one-axis": (
        "vpffd_addon/solve_kernels.py",
        "    for a in range(3):\n        _k_sum_runs(M[a], run_start, A[a], done[a], b0, b1)",
        "    for a in range(1):\n        _k_sum_runs(M[a], run_start, A[a], done[a], b0, b1)",
        ["tests/test_core_compiled.py", "-k", "runs_summed"], {}),
    "runs-sums-overwritten": (
        "vpffd_addon/solve_kernels.py",
        "    change_basis_runs(B, c, 1, C)\n    change_basis_runs(C, c, 2, B)",
        "    change_basis_runs(B, c, 1, A)\n    change_basis_runs(A, c, 2, B)",
        ["tests/test_core_compiled.py", "-k", "runs_summed"], {}),
    "override-writes-linked-helper": (
        "operators/solver_helper.py",
        "    linked = tagged and not writable(ob)\n",
        "    linked = False\n",
        ["tests/test_linked_blender.py", "-k", "overrides_it"], {}),
    "override-reference-without-settings": (
        "operators/deformers.py",
        "    if reference is not None and obj.library is None:\n        reference.vpffd\n",
        "",
        ["tests/test_stack_blender.py", "-k", "library_override_of_a_linked"], {}),
    "instances-skipped": (
        "operators/tracked_objects.py",
        "            evaluated = ob.evaluated_get(depsgraph).is_evaluated\n",
        "            evaluated = ob.library is None and ob.evaluated_get(depsgraph).is_evaluated\n",
        ["tests/test_linked_blender.py", "-k", "unbaked"], {}),
    "tracked-groups-before-tag": (
        "operators/tracked_objects.py",
        "    key = (len(node_groups), node_group.builds[0])",
        "    key = (len(node_groups), 0)",
        ["tests/test_extension_blender.py", "-k", "pinned_vertex_group_follows"], {}),
    "render-nested-collections-unseen": (
        "operators/update.py",
        "        stack.extend(layer_collection.children)\n",
        "        pass\n",
        ["tests/test_linked_blender.py", "-k", "overrides_it and python"], {}),
    "qr-pair-unfolded": (
        "vpffd_addon/solve_kernels.py",
        "            da2 = t2 * (da2 - da1 * c)\n            db2 = t2 * (db2 - db1 * c)",
        "            da2 = t2 * da2\n            db2 = t2 * db2",
        ["tests/test_core_compiled.py", "-k", "least_norm"], {}),
    "reembed-pads-unset": (
        "vpffd_addon/binding.py",
        "    b.x0[:, pads] = 0\n",
        "",
        ["tests/test_core_compiled.py", "-k", "memory_it_takes"], {}),
    "smoke-points-fortran": (
        "vpffd_addon/compiled.py",
        "    for points in (np.ascontiguousarray(coords.T), np.ascontiguousarray(coords.T, dtype=np.float32)):",
        "    for points in (np.ascontiguousarray(coords.T), coords.T.astype(np.float32)):",
        ["tests/test_core_compiled.py", "-k", "compiles_no_kernel"], {}),
    "reembed-fill-short": (
        "vpffd_addon/layout.py",
        '        tasks.insert(0, ("fill", V, _NS_PER["fill"]',
        '        tasks.insert(0, ("fill", V - 1, _NS_PER["fill"]',
        ["tests/test_core_compiled.py", "-k", "faces_around_every_slot"], {}),
    "reembed-slots-shifted": (
        "vpffd_addon/binding.py",
        "        base[keyed] = first_block * bs - run_start\n",
        "        base[keyed] = first_block * bs - run_start + 1\n",
        ["tests/test_core_compiled.py", "-k", "re_embedding or bit_for_bit"], {}),
    "reembed-island-origin": (
        "vpffd_addon/layout_kernels.py",
        "            r = 0 if single else part_rows[v]\n            for a in range(3):\n                R[v, a] = P[v, a] - origin[r, a]",
        "            r = 0 if single else part_rows[v]\n            for a in range(3):\n                R[v, a] = P[v, a] - origin[0, a]",
        ["tests/test_core_compiled.py", "-k", "re_embedding"], {}),
    "reembed-parts-unordered": (
        "vpffd_addon/layout_kernels.py",
        "        for k in range(counts.shape[1]):\n            start[k] = pos\n            for p in range(counts.shape[0]):",
        "        for k in range(counts.shape[1]):\n            start[k] = pos\n            for p in range(counts.shape[0] - 1, -1, -1):",
        ["tests/test_core_compiled.py", "-k", "any_number_of_threads"], {}),
    "topology-open-as-closed": (
        "vpffd_addon/layout_kernels.py",
        "                if going != 1 or coming != 1:",
        "                if going != 1:",
        ["tests/test_core_compiled.py", "-k", "topology"], {}),
    "deformers-stale-input": (
        "operators/update.py",
        "            depsgraph.update()\n",
        "            pass\n",
        ["tests/test_deformers_blender.py", "-k", "render or reordering"], {}),
    "rebuild-drops-inputs": (
        "operators/node_group.py",
        "            if not is_current(ng) and ng.library is None:\n                _rebuild(ng)\n",
        "            if not is_current(ng) and ng.library is None:\n                _build(ng)\n",
        ["tests/test_deformers_blender.py", "-k", "file_of"], {}),
    "override-uids-renewed": (
        "operators/deformers.py",
        "    if slot and slot != uid and not any(m.persistent_uid == slot for m in mods):",
        "    if False:",
        ["tests/test_deformers_more_blender.py", "-k", "override"], {}),
    "target-bind-from-result": (
        "operators/lifecycle.py",
        "helper[BIND_VOLUME_PROPERTY] = (b.rest_island_volumes / ",
        "helper[BIND_VOLUME_PROPERTY] = (b.rest_island_volumes * abs(state.result.volume / b.rest_volume) / ",
        ["tests/test_outside_target_blender.py", "-k", "volume_scale"], {}),
    "bind-island-volumes-order": (
        "operators/lifecycle.py",
        "helper[BIND_VOLUME_PROPERTY] = (b.rest_island_volumes / ",
        "helper[BIND_VOLUME_PROPERTY] = (b.rest_island_volumes[::-1] / ",
        ["tests/test_outside_target_blender.py", "-k", "gives_back"], {}),
    "undo-relink-noop": (
        "operators/handlers.py",
        "                relink_after_undo(d, bpy.data.objects)",
        "                pass",
        ["tests/test_lifecycle_blender.py", "-k", "undo"], {}),
    "fit-margin-ignored": (
        "operators/fit.py",
        "add_fitted_lattice(context, meshes, self.resolution, self.margin, self.axes)",
        "add_fitted_lattice(context, meshes, self.resolution, 0.05, self.axes)",
        ["tests/test_fit_blender.py", "-k", "every_option"], {}),
    "fit-resolution-ignored": (
        "operators/fit.py",
        "add_fitted_lattice(context, meshes, self.resolution, self.margin, self.axes)",
        "add_fitted_lattice(context, meshes, 4, self.margin, self.axes)",
        ["tests/test_fit_blender.py", "-k", "every_option"], {}),
    "fit-correction-ignored": (
        "operators/fit.py",
        "add_fitted_lattice(context, meshes, self.resolution, self.margin, self.axes)",
        "add_fitted_lattice(context, meshes, self.resolution, self.margin)",
        ["tests/test_fit_blender.py", "-k", "every_option"], {}),
    "panel-percent-from-target": (
        "operators/publish.py",
        'info["volume_percent"] = 100.0 * abs(result.volume / reference)',
        'info["volume_percent"] = 100.0 * s.volume_scale',
        ["tests/test_panel_blender.py", "-k", "measured or refused"], {}),
    "mirror-counted-as-fold": (
        "operators/publish.py",
        "state.orientation = mirrored, -1.0 if mirrored else 1.0",
        "state.orientation = mirrored, 1.0",
        ["tests/test_panel_blender.py", "-k", "mirror"], {}),
    "warnings-miscounted": (
        "operators/status_line.py",
        "    warned = problems(info)\n    if info.volume_percent is not None:\n        text",
        "    warned = list(info.warnings)\n    if info.volume_percent is not None:\n        text",
        ["tests/test_panel_blender.py"], {}),
    "single-point-only-at-bind": (
        "operators/publish.py",
        "    if isinstance(lattice, vp.Lattice) and 1 in lattice.shape:",
        "    if False:",
        ["tests/test_panel_blender.py", "-k", "single_point"], {}),
    "falloff-counts-face-vertices": (
        "operators/publish.py",
        "    return max(result.outside - result.beyond, 0)",
        "    return result.falloff",
        ["tests/test_panel_blender.py", "-k", "falloff"], {}),
    "open-mesh-aims-at-zero": (
        "operators/update.py",
        "    state.encloses_nothing = inputs.correct and encloses_nothing(result)",
        "    state.encloses_nothing = False",
        ["tests/test_panel_blender.py", "-k", "open_mesh"], {}),
    "apply-forgets-the-lattice": (
        "operators/lifecycle.py",
        "    note_applied(d)\n    unbind(d)",
        "    unbind(d)",
        ["tests/test_panel_blender.py", "-k", "after_apply"], {}),
    "fit-poll-silent": (
        "operators/fit.py",
        "            cls.poll_message_set(why)",
        "            pass",
        ["tests/test_panel_blender.py", "-k", "says_why"], {}),
    "compiling-unsaid": (
        "operators/status_line.py",
        '    if kernels == "compiling" and info.awaits_kernels:',
        "    if False:",
        ["tests/test_panel_blender.py", "-k", "compile"], {}),
    "demo-view-kept": (
        "operators/demos.py",
        "        frame_views(context, user_scene if scene != user_scene else None)",
        "        frame_views(context)",
        ["tests/e2e/test_gui_window.py"], {"VPFFD_NO_E2E": ""}),
    "bpy-missing": (
        None, None, None,
        ["tests/test_stack_blender.py"], {"PYTHONPATH": "{stub}"}),
}


def _copy(dst):
    names = subprocess.run(["git", "-C", ROOT, "ls-files", "-co", "--exclude-standard", "-z"],
                           stdout=subprocess.PIPE, check=True).stdout.decode().split("\0")
    for name in filter(None, names):
        src = os.path.join(ROOT, name)
        if os.path.isfile(src):
            os.makedirs(os.path.dirname(os.path.join(dst, name)), exist_ok=True)
            shutil.copy2(src, os.path.join(dst, name))


def run(name, python):
    path, old, new, args, env = MUTATIONS[name]
    with tempfile.TemporaryDirectory(prefix=f"vpffd-mutate-{name}-") as work:
        _copy(work)
        if path is not None:
            target = os.path.join(work, path)
            text = open(target, encoding="utf-8").read()
            if text.count(old) != 1:
                raise SystemExit(f"mutate: {name}: the text to replace is not in {path} exactly once "
                                 "(update tests/mutate.py)")
            with open(target, "w", encoding="utf-8") as fh:
                fh.write(text.replace(old, new))
        stub = os.path.join(work, ".stub")
        os.makedirs(stub)
        with open(os.path.join(stub, "bpy.py"), "w") as fh:   # bpy missing (as pip failing leaves it)
            fh.write("raise ModuleNotFoundError(\"No module named 'bpy'\", name='bpy')\n")
        full_env = dict(os.environ, VPFFD_STRICT_SKIPS="1", VPFFD_PASS=f"mutation {name}",
                        VPFFD_NO_E2E="1")
        full_env.update({k: v.format(stub=stub) for k, v in env.items()})
        from tests.e2e import blender_chroot as bc      # the copy reuses this tree's chroot
        if bc._has_blender(bc.chroot_dir()):
            full_env.setdefault("VPFFD_BLENDER_CHROOT", bc.chroot_dir())
        t0 = time.time()
        proc = subprocess.run([python, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider"] + args,
                              cwd=work, env=full_env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
        tail = [ln for ln in proc.stdout.splitlines() if ln.strip()][-3:]
        caught = proc.returncode not in (0, 5)
        print(f"mutate: {name}: {'CAUGHT' if caught else 'SURVIVED'} (pytest exit "
              f"{proc.returncode}, {time.time() - t0:.0f} s): " + " | ".join(tail))
        return caught


def main(argv):
    names = argv or list(MUTATIONS)
    unknown = [n for n in names if n not in MUTATIONS]
    if unknown:
        raise SystemExit(f"mutate: unknown mutation(s) {unknown}; known: {list(MUTATIONS)}")
    survived = [n for n in names if not run(n, sys.executable)]
    print(f"mutate: {len(names) - len(survived)} of {len(names)} mutations caught"
          + (f"; survived: {survived}" if survived else ""))
    return 1 if survived else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
