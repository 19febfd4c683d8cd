"""Every benchmark of `make bench` still runs: each in its quick mode, as `make bench` would.

These tests do not judge the figures (the benchmarks print them for people); they fail
when a benchmark stops running to the end or stops printing its tables, so a benchmark
cannot rot unseen between two `make bench` runs.
"""

import glob
import os
import re
import subprocess
import sys

import pytest

import run_benchmarks

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOOLS = os.path.join(ROOT, "tools", "bench")
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join(os.path.join(ROOT, d) for d in ("firmware", "tools")))
NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?")

# At least this many lines of figures (three numbers or more) in each quick run: its tables.
FIGURE_LINES = {"bench_parser.py": 5, "bench_bridge.py": 30, "bench_trace.py": 12, "bench_can.py": 8,
                "bench_station.py": 3, "bench_station402.py": 1, "bench_store.py": 6,
                "bench_multiup.py": 2,
                "bench_ecat.py": 0 if os.geteuid() else 6}  # without root: only the line saying why


def figure_lines(text):
    return [ln for ln in text.splitlines() if len(NUMBER.findall(ln)) >= 3]


def test_make_bench_runs_every_benchmark_script():
    on_disk = {os.path.basename(p) for p in glob.glob(os.path.join(TOOLS, "bench_*.py"))}
    assert on_disk == set(run_benchmarks.BENCHMARKS) == set(FIGURE_LINES)


@pytest.mark.parametrize("name", run_benchmarks.BENCHMARKS)
def test_quick_mode_runs_to_the_end_and_prints_its_tables(name):
    r = subprocess.run([sys.executable, os.path.join(TOOLS, name), "--quick"], capture_output=True, text=True,
                       timeout=300, env=ENV, cwd=ROOT, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, "%s --quick exited %d:\n%s" % (name, r.returncode, (r.stdout + r.stderr)[-3000:])
    assert "Traceback" not in r.stderr, r.stderr[-3000:]
    rows = figure_lines(r.stdout)
    assert len(rows) >= FIGURE_LINES[name], "%s printed %d lines of figures:\n%s" % (name, len(rows), r.stdout)
    assert not re.search(r"\b(nan|inf)\b", r.stdout), r.stdout
    assert "no figures" not in r.stdout, r.stdout  # a station run that did not pass


def test_make_bench_goes_on_past_a_failing_benchmark_and_names_it(tmp_path):
    broken = tmp_path / "bench_broken.py"
    broken.write_text("print('figures %d %d' % (1,))\n")  # a printout that no longer matches its values
    fine = tmp_path / "bench_fine.py"
    fine.write_text("import sys\nprint('fine 1 2 3', sys.argv[1:])\n")
    r = subprocess.run([sys.executable, os.path.join(TOOLS, "run_benchmarks.py"), "--quick", str(broken), str(fine)],
                       capture_output=True, text=True, timeout=60, env=ENV)
    assert r.returncode == 1
    assert "fine 1 2 3 ['--quick']" in r.stdout  # the one after the broken one ran, in quick mode
    assert "make bench: 1 failed: bench_broken.py (exit status 1)" in r.stdout
    assert "TypeError" in r.stderr  # its own traceback is shown, not swallowed


def test_the_cpu_model_names_every_figure_it_charges():
    from motorjig.sim import CpuModel

    text = CpuModel(1.0, 2.0, 3.0, 4.0, 5.0).describe(400e6)
    assert [int(x) for x in NUMBER.findall(text)[:5]] == [400, 800, 1200, 1600, 2000]
    assert CpuModel().describe(400e6).startswith("off")
    assert CpuModel.of((1.0, 2.0)) == CpuModel(1.0, 2.0)
