"""The GPU kernels inside Debian's real `blender` (the e2e chroot), on each of its GPU backends:
OpenGL and Vulkan (`--gpu-backend`, Mesa's llvmpipe and lavapipe here). The kernels compile and
the GPU solve matches the CPU solve, the same bounds as tests/test_gpu_backend.py.

Vulkan is offered from Blender 4.5 on: on trixie's 4.3 (the fallback chroot) that case is skipped,
saying so; anything else that keeps a backend from running fails the test.
"""
import json
import os

import pytest

from . import blender_chroot as bc

pytestmark = [pytest.mark.e2e, pytest.mark.gpu]


SCRIPT = r'''
import importlib.util, json, sys
import bpy, gpu
sys.path.insert(0, "{work}/src")
import numpy as np
import vpffd_addon as vp

out = {"blender": bpy.app.version_string}
if hasattr(gpu, "init"):          # Blender 5.3+: background GPU on request
    gpu.init()
else:                             # before: one tiny Workbench render starts the GPU backend
    r = bpy.context.scene.render
    r.engine, r.resolution_x, r.resolution_y = "BLENDER_WORKBENCH", 4, 4
    bpy.ops.render.render()
out["backend"] = gpu.platform.backend_type_get()
out["renderer"] = gpu.platform.renderer_get()
spec = importlib.util.spec_from_file_location("gb", "{work}/src/operators/gpu_backend.py")
gb = importlib.util.module_from_spec(spec)
spec.loader.exec_module(gb)
out["available"] = gb.available()
rows = []
if out["available"][0]:
    v, f = vp.icosphere(3, 0.42)
    lat = vp.Lattice((4, 3, 5), interpolation="BSPLINE")
    rng = np.random.default_rng(7)
    P = lat.rest_points + rng.uniform(-0.08, 0.08, lat.rest_points.shape)
    P[:, 2] *= 0.7
    b = vp.bind(lat, v, f, dtype=np.float32)
    solver = gb.GPUSolver(b)
    for axes in ("XYZ", "XY", "Z"):
        cpu = b.solve(P, axes=axes, volume_scale=0.9)
        g = solver.solve(P, axes=axes, volume_scale=0.9)
        rows.append({"axes": axes,
                     "coord_err": float(np.abs(g.verts - cpu.verts).max() / lat.size),
                     "volume_err": float(abs(vp.signed_volume(g.verts, f, origin=lat.centre)
                                             - cpu.target_volume) / abs(cpu.target_volume)),
                     "warnings_equal": list(g.warnings) == list(cpu.warnings)})
out["rows"] = rows
json.dump(out, open("{work}/gpu.json", "w"))
'''


@pytest.mark.parametrize("backend", ["opengl", "vulkan"])
def test_kernels_compile_and_match_the_cpu_on_each_backend(chroot, backend):
    version = tuple(int(x) for x in bc.describe()["version"].split()[0].split(".")[:2])
    if backend == "vulkan" and version < (4, 5):
        pytest.skip(f"Vulkan backend needs Blender 4.5 or newer (the chroot has {bc.describe()['text']})")
    work = bc.new_workdir(chroot)
    try:
        bc.copy_sources(work, "src", keep=lambda n: n.startswith(("vpffd_addon/", "operators/")))
        inside = bc._inside(chroot, work)
        script = os.path.join(work, "gpu_check.py")
        with open(script, "w") as fh:
            fh.write(SCRIPT.replace("{work}", inside))
        rc, out, err, _ = bc.run_blender(["-b", "--factory-startup", "--gpu-backend", backend,
                                          "--python-exit-code", "1", "--python", "gpu_check.py"],
                                         workdir=work, timeout=600)
        result_path = os.path.join(work, "gpu.json")
        assert rc == 0 and os.path.isfile(result_path), (rc, out[-2000:], err[-3000:])
        with open(result_path) as fh:
            result = json.load(fh)
        print(backend, result["blender"], result["backend"], result["renderer"])
        assert result["backend"] == backend.upper(), result
        assert result["available"][0], result["available"][1]
        assert [r["axes"] for r in result["rows"]] == ["XYZ", "XY", "Z"]
        for row in result["rows"]:
            assert row["coord_err"] <= 5e-7, row
            assert row["volume_err"] <= 1e-5, row
            assert row["warnings_equal"], row
    finally:
        bc.remove_workdir(work)
