"""The tools that write figures into the documentation find their places there: `./dev bench
--update-readme` (the tables of docs/speed.md and the README's speed line), `./dev bench
--stack-only --update-readme` (the stack table of docs/speed.md), `benchmarks/gpu_benchmark.py
--readme` (the hardware table of docs/speed.md) and `./dev demo --update-readme` (the block of
docs/demos.md). A full run takes minutes, and a page without its markers would only fail at its
end; here each page is checked to hold its markers once, and the bench's rewriting is run on copies
of the pages with a made-up report, leaving everything outside the markers as it was."""
import os
import re
import shutil

import pytest

from benchmarks import benchmark, gpu_benchmark

pytestmark = pytest.mark.core

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SPEED = os.path.join(ROOT, "docs", "speed.md")
DEMOS = os.path.join(ROOT, "docs", "demos.md")
README = os.path.join(ROOT, "README.md")
STACK = ("<!-- stack-bench:start -->", "<!-- stack-bench:end -->")


def _text(path):
    with open(path, encoding="utf-8") as fh:
        return fh.read()


def _once(text, start, end):
    assert text.count(start) == 1 and text.count(end) == 1, (start, end)
    assert text.index(start) < text.index(end)


def test_each_tool_writes_to_the_page_that_holds_its_markers():
    assert benchmark.SPEED_PAGE == SPEED and gpu_benchmark.SPEED_PAGE == SPEED
    assert benchmark.README == README
    speed = _text(SPEED)
    _once(speed, benchmark.README_START, benchmark.README_END)
    _once(speed, *STACK)
    _once(speed, gpu_benchmark.README_START, gpu_benchmark.README_END)
    _once(_text(README), benchmark.LINE_START, benchmark.LINE_END)
    demos = _text(DEMOS)
    for start, end in (("<!-- demos:start -->", "<!-- demos:end -->"),):
        _once(demos, start, end)
    # update_stack_readme's default is the speed page (it needs Blender to run)
    assert benchmark.update_stack_readme.__defaults__ == (SPEED,)


def test_no_other_page_holds_a_tools_markers():
    """A second copy of a block would go stale: the tools rewrite only the first."""
    markers = [benchmark.README_START, STACK[0], gpu_benchmark.README_START, benchmark.LINE_START,
               "<!-- demos:start -->"]
    for name in ["README.md"] + sorted("docs/" + n for n in os.listdir(os.path.join(ROOT, "docs"))
                                       if n.endswith(".md")):
        text = _text(os.path.join(ROOT, name))
        expected = {"README.md": {benchmark.LINE_START}, "docs/speed.md": set(markers[:3]),
                    "docs/demos.md": {"<!-- demos:start -->"}}.get(name, set())
        assert {m for m in markers if m in text} == expected, name


def _report():
    """A made-up report with the fields the bench's markdown reads (figures no run measured)."""
    def dtype(ms):
        return {"deform_ms_median": ms, "solve_xyz_ms_median": 3 * ms, "solve_xyz_compiled_ms_median": 2 * ms,
                "bytes_per_vertex": 111.0, "bind_ms": 10 * ms}
    row = {"n_verts": 1234, "dtypes": {"float32": dtype(1.0), "float64": dtype(2.0)},
           "blender": {"execution_time_ms_median": 1.5},
           "ratios_vs_blender": {"float32": {"solve_xyz": 2.0, "solve_xyz_compiled": 1.33},
                                 "float64": {"solve_xyz": 4.0}},
           "extension_frame_set": {"frames": 12, "vpffd_frame_set_ms_median": 98.7,
                                   "plain_frame_set_ms_median": 12.3, "frame_set_ratio": 8.02,
                                   "frame_set_ratio_runs": [8.02], "kernels": "compiled",
                                   "vpffd_core_solve_ms_median": 45.6, "handler_overhead_ms_median": 1.0}}
    return {"environment": {"date": "1999-01-02T03:04:05", "cpu_count": 7, "python": "3.x",
                            "numpy": "9.9", "bpy": "9.9.9"},
            "results": [row], "gpu": None, "cages": None, "cage_convergence": None,
            "summary": {"linearity": {"float32": {"solve_xyz": {}}, "float64": {"solve_xyz": {}}}}}


def _outside(text, start, end):
    return text[:text.index(start)], text[text.index(end) + len(end):]


def test_the_bench_rewrites_the_speed_page_and_the_readme_line(tmp_path):
    speed, readme = tmp_path / "speed.md", tmp_path / "README.md"
    shutil.copyfile(SPEED, speed)
    shutil.copyfile(README, readme)
    benchmark.update_readme(_report(), path=str(speed), readme=str(readme))
    new_speed, new_readme = speed.read_text(), readme.read_text()
    marks = (benchmark.README_START, benchmark.README_END)
    assert _outside(new_speed, *marks) == _outside(_text(SPEED), *marks)
    block = new_speed[new_speed.index(marks[0]):new_speed.index(marks[1])]
    assert "Measured 1999-01-02 on 7 CPU cores" in block and "| 1,234 |" in block
    line = (benchmark.LINE_START, benchmark.LINE_END)
    assert _outside(new_readme, *line) == _outside(_text(README), *line)
    said = new_readme[new_readme.index(line[0]):new_readme.index(line[1])]
    assert "98.7 ms" in said and "12.3 ms" in said and "1,234 vertices" in said and "45.6 ms" in said


def test_the_readme_speed_line_has_the_figures_of_the_speed_page():
    """Both are written by the same `./dev bench --update-readme`: the README's frame time, the
    Lattice modifier's and the core's evaluation's are those of the page's frame_set sentence."""
    speed = _text(SPEED)
    m = re.search(r"In Blender, ([\d,]+) vertices, .*?takes ([\d.]+) ms with VP-FFD .*? against "
                  r"([\d.]+) ms with a plain Lattice modifier .*?core's evaluation \(the solve and the "
                  r"frame's own passes, ([\d.]+) ms\)", speed)
    assert m, "the speed page's frame_set sentence"
    readme = _text(README)
    line = readme[readme.index(benchmark.LINE_START):readme.index(benchmark.LINE_END)]
    n, vpffd, plain, solve = m.groups()
    for figure in (f"{n} vertices", f"{vpffd} ms", f"{plain} ms", f"{solve} ms"):
        assert figure in line, (figure, line)


def test_the_readme_gives_the_command_ci_runs():
    """`.ci/run` runs the README's test command, and the README's set-up is `./dev` itself."""
    with open(os.path.join(ROOT, ".ci", "run"), encoding="utf-8") as fh:
        commands = [line.strip() for line in fh if line.strip().startswith("./dev ")]
    assert commands == ["./dev test -q -p no:cacheprovider"], commands
    readme = _text(README)
    development = readme[readme.index("## Development"):]
    assert f"`{commands[0]}`" in development and "`.ci/run`" in development
    assert "./dev test " in development and "./dev demo " in development
