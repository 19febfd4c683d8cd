"""Station benchmark (part of `make bench`): prints figures, asserts nothing.

Runs plans/ezi-step-eol.toml on the real-time virtual bench at 115 200 baud (the
jig's firmware modules on CPython, a healthy simulated Ezi-STEP wired as the plan
says) and splits the run's wall time:

* motion: the time the axis was moving in the steps that move it (their measured
  durations / stop times, sampled through the jig),
* bus traffic: the time the station spent waiting for replies (every request's
  round trip through the jig; during a move that overlaps the motion),
* steps: the time inside the step functions, and the rest of the run: the engine
  (OpenHTF's phase bookkeeping, the pre-flight, the outputs: JSON, JUnit, HTML).

Goals: the trace of a move sampled at >= 100 Hz through the jig at 115 200 baud; the
engine adds <= 100 ms per step beyond its own bus traffic and motion.
"""

import argparse
import base64
import json
import os
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
for sub in ("firmware", "tools"):
    p = os.path.join(ROOT, sub)
    if p not in sys.path:
        sys.path.insert(0, p)

from motorjig.sim import Bench  # noqa: E402
from motorjig.station import load_plan, run_plan  # noqa: E402
from motorjig.wiring import load_wiring  # noqa: E402

EOL = os.path.join(ROOT, "plans", "ezi-step-eol.toml")


def motion_seconds(plan, record):
    """Seconds the axis moved in each moving step: the move's measured duration, or its trace's span."""
    kinds = {s.name: s.kind for s in plan.steps}
    total = 0.0
    for ph in record["phases"]:
        kind = kinds.get(ph["name"])
        if kind in ("move", "home"):
            total += ph["measurements"]["duration"]["measured_value"]
        elif kind in ("limit-sensor", "stop-response"):
            trace = json.loads(base64.b64decode(ph["attachments"]["trace"]["data"]))
            moving = [r[0] for r in trace["rows"] if r[3] != 0]
            total += (moving[-1] - moving[0]) if moving else 0.0
    return total


def sample_rates(plan, record):
    kinds = {s.name: s.kind for s in plan.steps}
    return [ph["measurements"]["sample_rate"]["measured_value"] for ph in record["phases"]
            if kinds.get(ph["name"]) == "move"]


def one_run(ver8, out_dir):
    plan = load_plan(EOL)
    with Bench(driver_ids=(2,), baud=115200, pty=False, jig_ver8=ver8, ver8_drivers=(2,) if ver8 else (),
               wiring=load_wiring(EOL)) as b:
        t0 = time.monotonic()
        ctx = run_plan(plan, b.tcp_url, out_dir=out_dir, out=None, confirm=lambda m: True, timeout_ms=300)
        wall = time.monotonic() - t0
    return plan, ctx, wall


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=2, help="runs per protocol variant (default 2)")
    args = ap.parse_args(argv)
    if args.runs < 1:
        print("error: --runs must be at least 1", file=sys.stderr)
        return 2
    print("station benchmark: plans/ezi-step-eol.toml on the real-time bench, 115 200 baud, through the jig")
    print("  %-5s %8s %8s %8s %8s %8s %9s %12s %10s" % ("", "run s", "motion", "bus", "steps", "engine",
                                                       "steps n", "engine/step", "sample Hz"))
    with tempfile.TemporaryDirectory() as out:
        for ver8 in (False, True):
            for _ in range(args.runs):
                plan, ctx, wall = one_run(ver8, out)
                rec = ctx.record
                if rec["outcome"] != "PASS":
                    print("  Ver%d: the run did not pass (%s): no figures" % (8 if ver8 else 6, rec["outcome"]))
                    continue
                in_steps = sum(t for _, t, _ in ctx.timings)
                bus = sum(b for _, _, b in ctx.timings)
                n = len(ctx.timings)
                engine = wall - in_steps
                rates = sample_rates(plan, rec)
                print("  Ver%d  %8.2f %8.2f %8.2f %8.2f %8.2f %9d %9.1f ms %5.0f-%-4.0f"
                      % (8 if ver8 else 6, wall, motion_seconds(plan, rec), bus, in_steps, engine, n,
                         engine / n * 1000, min(rates), max(rates)))
    print("  (motion: the axis moving; bus: waiting for replies, overlapping the motion while a move is")
    print("   sampled; steps: inside the step functions; engine = run - steps: OpenHTF, pre-flight,")
    print("   outputs; goals: >= 100 Hz sampling, engine <= 100 ms per step)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
