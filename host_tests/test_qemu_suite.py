"""tools/firmware/qemu: the suite that runs on the emulated Cortex-M7 also runs (quickly) here.

Keeps the frozen test code from rotting between `make test-qemu` runs: the capture
module generator, the replay against CPython's own reports, the CRC parity and the
bridge benchmark harness must all pass under CPython too.
"""

import importlib
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_generated_captures_and_quick_suite(tmp_path, monkeypatch, capsys):
    gen = os.path.join(ROOT, "tools", "firmware", "qemu", "gen_captures.py")
    r = subprocess.run([sys.executable, gen, str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.syspath_prepend(os.path.join(ROOT, "tools", "firmware", "qemu"))
    monkeypatch.syspath_prepend(os.path.join(ROOT, "host_tests"))
    for name in ("qemu_captures", "qemu_suite"):
        sys.modules.pop(name, None)
    suite = importlib.import_module("qemu_suite")
    assert len(suite.qemu_captures.CAPTURES) == len(
        [n for n in os.listdir(os.path.join(ROOT, "host_tests", "captures")) if n.endswith(".cap")]
    )
    assert suite.main(quick=True) == 0
    out = capsys.readouterr().out
    assert "FAIL" not in out
    assert "captures give CPython's report" in out
    assert "bridge cut-through (" in out and "bridge store-and-forward (portable loop): forwarded" in out


def test_suite_reports_a_broken_capture(tmp_path, monkeypatch, capsys):
    monkeypatch.syspath_prepend(os.path.join(ROOT, "tools", "firmware", "qemu"))
    monkeypatch.syspath_prepend(os.path.join(ROOT, "host_tests"))
    sys.modules.pop("qemu_suite", None)
    suite = importlib.import_module("qemu_suite")
    fake = type(sys)("qemu_captures")
    fake.CAPTURES = (("x.cap", "AA CC 01 01 C1 E0 AA EE\nframe 01 01\ncounters good=1\n", "capture x.cap\nwrong"),)
    monkeypatch.setattr(suite, "qemu_captures", fake)
    suite.failures[:] = []
    suite.replay_captures()
    assert suite.failures and "x.cap" in suite.failures[0]
