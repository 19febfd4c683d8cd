"""`make bench`: runs every benchmark in turn and prints their figures.

A benchmark that fails does not hide the ones after it: each runs in a process of its
own, the run goes on, and it ends non-zero naming the scripts that failed. ``--quick``
runs each in its quick mode (the smallest sizes, one run each), as `make test` does.
"""

import argparse
import datetime
import os
import platform
import subprocess
import sys
import time

TOOLS = os.path.dirname(os.path.abspath(__file__))

# In the order `make bench` prints them; host_tests/test_benchmarks.py checks that every
# tools/bench/bench_*.py is here.
BENCHMARKS = ("bench_parser.py", "bench_bridge.py", "bench_trace.py", "bench_can.py", "bench_station.py",
              "bench_station402.py", "bench_store.py", "bench_ecat.py", "bench_multiup.py")


def run(script, quick):
    """Runs one benchmark with its output on ours: (exit status, seconds)."""
    cmd = [sys.executable, script] + (["--quick"] if quick else [])
    t0 = time.monotonic()
    try:
        rc = subprocess.call(cmd)
    except OSError as exc:
        print("run_benchmarks: cannot start %s: %s" % (script, exc), file=sys.stderr)
        rc = 127
    return rc, time.monotonic() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="each benchmark's quick mode: a few seconds each")
    ap.add_argument("scripts", nargs="*", metavar="SCRIPT",
                    help="benchmark scripts to run (default: all of them, in make bench's order)")
    args = ap.parse_args(argv)
    scripts = args.scripts or [os.path.join(TOOLS, name) for name in BENCHMARKS]
    print("make bench%s, %s, %s on %s, %d cores" % (" --quick" if args.quick else "",
                                                  datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
                                                  platform.python_implementation() + " " + platform.python_version(),
                                                  platform.machine(), os.cpu_count() or 1), flush=True)
    failed, times = [], []
    for script in scripts:
        name = os.path.basename(script)
        print("\n=== %s" % name, flush=True)
        rc, seconds = run(script, args.quick)
        times.append("%s %.0f s" % (name, seconds))
        if rc != 0:
            failed.append("%s (exit status %d)" % (name, rc))
            print("=== %s FAILED with exit status %d; going on with the rest" % (name, rc), flush=True)
    print("\n%d benchmarks: %s" % (len(scripts), ", ".join(times)))
    if failed:
        print("make bench: %d failed: %s" % (len(failed), ", ".join(failed)))
        return 1
    print("make bench: all %d ran to the end" % len(scripts))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        print("run_benchmarks: interrupted")
        sys.exit(130)
