"""Shared pytest setup: the firmware package is importable as ``jig`` from the source tree, the PC
side as ``motorjig``, and the benchmark and doc-generator scripts by their names."""

import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
for sub in ("firmware", "tools", os.path.join("tools", "bench"), os.path.join("tools", "docgen")):
    path = os.path.join(ROOT, sub)
    if path not in sys.path:
        sys.path.insert(0, path)

import shutil  # noqa: E402
import tempfile  # noqa: E402

import pytest  # noqa: E402

# Runs that tests start (jigctl test, the Desk's Test tab, also in child processes) store
# themselves in the default results database: a folder of this session, never the user's.
_DATA_HOME = tempfile.mkdtemp(prefix="motorjig-tests-data-")
os.environ["XDG_DATA_HOME"] = _DATA_HOME
os.environ.pop("JIGCTL_DB", None)


def pytest_sessionfinish(session, exitstatus):
    shutil.rmtree(_DATA_HOME, ignore_errors=True)

# The bridge suites run twice: on the portable main loop (what CPython and the
# WebAssembly VM run) and on jig.fastpath.pump, the board's machine-code hot path,
# whose very source runs here as Python. Both must pass the same tests.
JIG_LOOP_MODULES = {"test_bridge_faults", "test_sim_e2e", "test_bench_timing", "test_vendor_probe", "test_handlers",
                    "test_safety", "test_board", "test_soak", "test_hil_on_bench", "test_captures",
                    "test_capture_firmware"}


def pytest_generate_tests(metafunc):
    if metafunc.module.__name__.rsplit(".", 1)[-1] in JIG_LOOP_MODULES:
        metafunc.fixturenames.append("jig_loop")
        metafunc.parametrize("jig_loop", ["portable", "fastpath"])


@pytest.fixture(autouse=True)
def _select_jig_loop(request):
    """Sets the benches' main loop for a test parametrized with jig_loop (autouse:
    before any fixture that builds a bench)."""
    callspec = getattr(request.node, "callspec", None)
    loop = callspec.params.get("jig_loop") if callspec is not None else None
    if loop is None:
        yield
        return
    from motorjig.sim import bench

    old = bench.DEFAULT_FASTPATH
    bench.DEFAULT_FASTPATH = loop == "fastpath"
    yield
    bench.DEFAULT_FASTPATH = old
