"""CiA 402 station benchmark (part of `make bench`): prints figures, asserts nothing.

Runs plans/cia402-eol.toml on the real-time virtual bench through the jig's CAN port
(its SLCAN port, python-canopen on the PC side; a healthy simulated CiA 402 drive at node 5
wired as the plan says) at 500 kbit/s and 1 Mbit/s, and splits each run's wall time as
tools/bench/bench_station.py does for the Plus-R plan:

* motion: the time the axis was moving in the moves and the homing (their measured durations) and
  in the limit-sensor and stop-response steps (their traces' moving span), as for the Plus-R plan,
* bus: the time the station waited for answers (the drive's SDO replies and the jig's PC-port
  round trips; during a move that overlaps the motion),
* steps: the time inside the step functions; engine = run - steps (OpenHTF, the pre-flight, the
  outputs: JSON, JUnit, HTML).

And the moves' TPDO trace rate (statusword, position, velocity, following error, sampled by the
drive and dated by the jig's clock). Goal (issue 25): >= 500 Hz at 1 Mbit/s.

Then, as tools/bench/bench_station.py does for the Plus-R plan, the proof that a busy PC does not fail
a good drive (``--loaded N``, default 100): cia402-eol N times on a healthy drive beside CPU
burners, the bench in its own process at a higher priority (false FAILs: goal 0; ERRORs counted
with their reasons), then each injected fault, quiet and loaded, caught at its step.
"""

import argparse
import os
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
for sub in ("firmware", "tools"):
    p = os.path.join(ROOT, sub)
    if p not in sys.path:
        sys.path.insert(0, p)

from motorjig.sim import Bench  # noqa: E402
from motorjig.station import load_plan, run_plan  # noqa: E402

from bench_station import Line, faults_proof, loaded_proof, motion_seconds, sample_rates  # noqa: E402


EOL = os.path.join(ROOT, "plans", "cia402-eol.toml")
NODE = 5
CIA402 = Line(EOL, ["--drivers", "2", "--can-nodes", str(NODE), "--wiring", EOL],
              run_kw=lambda urls: {"can_port": urls["slcan"]})
# (fault, the step that must catch it, a measurement that must fail there)
FAULTS = (("can:following-error=20000", "move_speed_50000", "following_error"),
          ("can:overcurrent=30", "move_speed_5000", "emcy"),
          ("can:sluggish=1.5", "move_speed_5000", "duration_ratio"),
          ("can:param=0x6065=500", "parameters", "x6065_00"),
          ("can:no-origin", "home", "homing_attained"),
          ("can:dead-input=16", "io", "relay_2_on"),
          ("can:missed-heartbeat", "bus-health", "heartbeat_jitter"))


def one_run(bitrate, out_dir):
    plan = load_plan(EOL)
    plan.drive.bitrate = bitrate  # the plan says 500 kbit/s; the same drive on a 1 Mbit/s bus too
    with Bench(driver_ids=(2,), can_nodes=(NODE,), can_bitrate=bitrate, pty=False, wiring=plan.wiring) as b:
        t0 = time.monotonic()
        ctx = run_plan(plan, b.tcp_url, can_port=b.slcan_url, out_dir=out_dir, out=None, timeout_ms=300,
                       confirm=lambda m: True)
        wall = time.monotonic() - t0
    return plan, ctx, wall


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=2, help="runs per bitrate (default 2)")
    ap.add_argument("--loaded", type=int, default=100, metavar="N",
                    help="runs of cia402-eol beside CPU burners for the false-FAIL count (default 100; 0: skip "
                         "it and the faults)")
    ap.add_argument("--burners", type=int, default=2, help="CPU burners beside the loaded runs (default 2)")
    ap.add_argument("--quick", action="store_true", help="a few seconds: the smallest sizes, one run each (make test runs it)")
    args = ap.parse_args(argv)
    if args.quick:
        args.runs, args.loaded, args.burners = 1, 1, 1
    if args.runs < 1 or args.loaded < 0 or args.burners < 0:
        print("error: --runs must be at least 1, --loaded and --burners at least 0", file=sys.stderr)
        return 2
    print("CiA 402 station benchmark: plans/cia402-eol.toml on the real-time bench, node %d through the "
          "jig's SLCAN port" % NODE)
    print("  %-9s %7s %7s %7s %7s %7s %7s %12s %12s" % ("bitrate", "run s", "motion", "bus", "steps", "engine",
                                                       "steps n", "engine/step", "TPDO Hz"))
    with tempfile.TemporaryDirectory() as out:
        for bitrate in (500000,) if args.quick else (500000, 1000000):
            for _ in range(args.runs):
                plan, ctx, wall = one_run(bitrate, out)
                rec = ctx.record
                label = "%d k" % (bitrate // 1000)
                if rec["outcome"] != "PASS":
                    print("  %-9s the run did not pass (%s: %s): no figures" % (
                        label, rec["outcome"],
                        "; ".join(d.get("description", "") for d in rec.get("outcome_details", []))[:120]))
                    continue
                in_steps = sum(t for _, t, _ in ctx.timings)
                bus = sum(b for _, _, b in ctx.timings)
                n = len(ctx.timings)
                rates = sample_rates(plan, rec)
                print("  %-9s %7.2f %7.2f %7.2f %7.2f %7.2f %7d %9.1f ms %6.1f-%-6.1f"
                      % (label, wall, motion_seconds(plan, rec), bus, in_steps, wall - in_steps, n,
                         (wall - in_steps) / n * 1000, min(rates), max(rates)))
    print("  (motion: moves, homing, limit and stop steps; bus: waiting for SDO replies and the jig's round trips, overlapping")
    print("   the motion while a move is traced; engine = run - steps: OpenHTF, pre-flight, outputs;")
    print("   TPDO Hz: the moves' trace, sampled by the drive, dated by the jig; goal >= 500 Hz at 1 Mbit/s)")
    if args.loaded:
        with tempfile.TemporaryDirectory() as out:
            loaded_proof(args.loaded, args.burners, out, CIA402)
            faults_proof(out, args.burners, FAULTS[:1] if args.quick else FAULTS, CIA402)
    return 0


if __name__ == "__main__":
    sys.exit(main())
