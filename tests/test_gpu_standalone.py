"""The standalone GPU benchmark (`benchmarks/gpu_benchmark.py --standalone`) runs the extension's
own kernels and solve driver through `benchmarks/moderngl_gpu.py`, which supplies the calls of
Blender's `gpu` module on moderngl. The hardware-GPU figures of docs/speed.md come from it, so here it is
run for real (Mesa's software OpenGL through EGL) and its result checked against the CPU path; and
that table is checked to be what `--readme` writes from the committed measurement."""
import json
import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.gpu

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MEASURED = os.path.join(ROOT, "benchmarks", "results", "gpu_hardware.json")


def test_standalone_kernels_match_the_cpu_path(tmp_path):
    pytest.importorskip("moderngl")
    out = tmp_path / "gpu.json"
    run = subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", "gpu_benchmark.py"),
                          "--standalone", "--sizes", "4", "--repeat", "1", "--out", str(out)],
                         capture_output=True, text=True, timeout=600, cwd=str(tmp_path))
    assert run.returncode == 0, run.stderr[-3000:]
    report = json.loads(out.read_text())
    assert report["gpu_available"], report["gpu_reason"]
    assert report["standalone"] and report["gl_version"]
    (row,) = report["rows"]
    assert row["n_verts"] == 2562
    # The same tolerance as the GPU path inside Blender (tests/test_gpu_backend.py).
    assert row["max_coord_diff_over_lattice_size"] <= 5e-7
    assert row["gpu_volume_rel_error"] <= 1e-6
    kernels = row["gpu_kernels"]
    assert {"forward", "gradient", "reduce_slots", "pieces", "alpha", "gather"} <= set(kernels)
    # XYZ: three gradients, three transposed products (pieces + alpha), one final gather.
    assert kernels["gradient"][0] == 3 and kernels["alpha"][0] == 3 and kernels["gather"][0] == 1


def test_the_standalone_gpu_refuses_to_replace_blenders_own(monkeypatch):
    from benchmarks import moderngl_gpu
    monkeypatch.setitem(sys.modules, "bpy", object())
    with pytest.raises(RuntimeError, match="Blender's own gpu"):
        moderngl_gpu.install()


def test_the_hardware_table_is_the_committed_measurement():
    from benchmarks import gpu_benchmark
    with open(MEASURED) as fh:
        report = json.load(fh)
    assert not report["software_renderer"] and report["standalone"]
    assert all(r["max_coord_diff_over_lattice_size"] <= 5e-7 for r in report["rows"])
    with open(gpu_benchmark.SPEED_PAGE) as fh:
        page = fh.read()
    assert gpu_benchmark.SPEED_PAGE == os.path.join(ROOT, "docs", "speed.md")
    assert gpu_benchmark.readme_block(report) in page
