"""The hardware-in-the-loop suite itself, run against the virtual bench.

host_tests/hil only runs when a jig is attached (--port), so nothing else would
notice if it rotted before the first board arrives. Here it runs as a user would
run it on hardware, with the bench standing in for the jig and driver id 2.
"""

import os
import subprocess
import sys

from bench_fixtures import ROOT, SUBPROCESS_ENV, bench_process


def test_hil_suite_passes_against_the_bench():
    with bench_process() as urls:
        cmd = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider",
               os.path.join(ROOT, "host_tests", "hil", "test_hil.py"), "--port", urls["tcp"], "--driver-id", "2",
               "--allow-move", "-rA"]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=SUBPROCESS_ENV, cwd=ROOT)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    lines = out.splitlines()
    # Every test ran for real: none skipped, none failed.
    assert not [line for line in lines if line.startswith(("SKIPPED", "FAILED", "ERROR"))], out
    assert sum(1 for line in lines if line.startswith("PASSED")) >= 7, out

