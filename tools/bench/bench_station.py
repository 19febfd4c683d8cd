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

Then the proof that a busy PC does not fail a good drive (``--loaded N``, default 100):
the bench in a process of its own at a higher priority (as a jig is a board with a CPU of
its own), two CPU burners beside the station (load >= 4 on 2 cores), and ezi-step-eol run
N times on the healthy drive:
it prints how many runs ended FAIL (each one a false FAIL: the goal is 0) and ERROR
(a measurement the station could not trust, with the reasons), and the load average.
Then each injected fault, quiet and loaded: the plan must still fail at the step and
measurement meant to catch it.
"""

import argparse
import base64
import collections
import json
import os
import subprocess
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


# (fault, its value, the step that must catch it, a measurement that must fail there)
FAULTS = (("step-out=20000", "move_speed_50000", "following_error"),
          ("alarm=1@30", "move_speed_5000", "alarm"),
          ("sluggish=1.5", "move_speed_5000", "duration_ratio"),
          ("param=3:250", "parameters", "ram_axis_acc_time"),
          ("no-origin", "home", "origin_ok"),
          ("dead-input=26", "io", "relay_2_on"))


class Line:
    """What the loaded proof and the faults need of a drive kind: the plan, the bench's options
    for it, and how a run reaches the drive (the ports the bench printed)."""

    def __init__(self, plan, bench_args, run_kw=lambda urls: {}):
        self.plan = plan
        self.bench_args = list(bench_args)
        self.run_kw = run_kw


PLUSR = Line(EOL, ["--drivers", "2", "--wiring", EOL])


def start_sim(*faults, line=PLUSR):
    """`python -m motorjig.sim` wired as the plan says, in its own process: (process, the URLs it
    printed by name: tcp, slcan, ...)."""
    args = [sys.executable, "-m", "motorjig.sim", "--no-demo", "--no-pty"] + line.bench_args
    for f in faults:
        args += ["--fault", f]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(os.path.join(ROOT, d) for d in ("firmware", "tools")))
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, text=True, env=env, preexec_fn=_board_priority)
    urls = {}
    for out in proc.stdout:
        key, _, value = out.strip().partition(": ")
        if key in ("tcp", "slcan"):
            urls[key] = value.split()[0]
        if "tcp" in urls and ("--can-nodes" not in line.bench_args or "slcan" in urls):
            return proc, urls
    proc.kill()
    raise RuntimeError("the bench did not start")


def _board_priority():
    """The bench stands in for the jig, a board with a CPU of its own that the PC's load does not
    slow: it runs at a higher priority than the burners and the station, where the OS allows it
    (root, or CAP_SYS_NICE); elsewhere the bench itself falls behind under load and a PC's
    reply timeout can expire while the simulated jig catches up (an ERROR, never a FAIL)."""
    try:
        os.nice(-10)
    except OSError:
        pass


def board_priority_note():
    try:
        os.setpriority(os.PRIO_PROCESS, 0, os.getpriority(os.PRIO_PROCESS, 0))
        return "the bench at nice -10" if os.geteuid() == 0 else "the bench at the burners' priority (not root)"
    except OSError:
        return "the bench at the burners' priority"


def stop_sim(proc):
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()


def burners(n):
    """n busy processes: other work on the PC's cores."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def first_failure(record):
    """(step, failed measurement names) of the first step that did not pass, or None."""
    for ph in record.get("phases", []):
        if ph["outcome"] != "PASS":
            return ph["name"], sorted(n for n, m in ph.get("measurements", {}).items()
                                      if m.get("outcome") not in ("PASS", None, "UNSET"))
    return None


class Tally:
    """The verdicts of a loaded proof's runs: how many of each, the false FAILs and the ERRORs by
    step and reason, the load average after each run."""

    def __init__(self):
        self.verdicts, self.fails, self.errors = collections.Counter(), collections.Counter(), collections.Counter()
        self.loads = []

    def add(self, rec, why="?"):
        """One run's record (``why``: what ended it when it has no record)."""
        verdict = rec.get("outcome", "ERROR")
        self.verdicts[verdict] += 1
        where = first_failure(rec)
        if verdict == "FAIL":
            self.fails["%s: %s" % (where[0], ", ".join(where[1]))] += 1
        elif verdict != "PASS":
            details = [d.get("description", "") for d in rec.get("outcome_details", [])]
            self.errors["%s: %s" % (where[0] if where else "-", (details or [why])[0][:90])] += 1

    def report(self, head, t0):
        v = self.verdicts
        print("  %s in %.0f s, load average %.1f-%.1f: PASS %d, false FAIL %d (goal 0), ERROR %d"
              % (head, time.monotonic() - t0, min(self.loads), max(self.loads), v["PASS"], v["FAIL"],
                 sum(n for k, n in v.items() if k not in ("PASS", "FAIL"))))
        for what, n in self.fails.most_common():
            print("    FAIL  %3d x %s" % (n, what))
        for what, n in self.errors.most_common():
            print("    ERROR %3d x %s" % (n, what))


def run_eol(urls, out_dir, line=PLUSR):
    ctx = run_plan(load_plan(line.plan), urls["tcp"], out_dir=out_dir, out=None, confirm=lambda m: True,
                   timeout_ms=300, **line.run_kw(urls))
    return ctx.record or {}


def loaded_proof(runs, n_burners, out_dir, line=PLUSR):
    name = os.path.splitext(os.path.basename(line.plan))[0]
    print("false FAILs on a busy PC: %s %d times on a healthy drive, the bench in its own "
          "process (%s, as a board has its own CPU), %d CPU burners beside it" % (name, runs, board_priority_note(),
                                                                                 n_burners))
    hogs = burners(n_burners)
    sim, urls = start_sim(line=line)
    tally = Tally()
    t0 = time.monotonic()
    try:
        time.sleep(2)  # the burners' load builds up
        for _ in range(runs):
            tally.add(run_eol(urls, out_dir, line))
            tally.loads.append(os.getloadavg()[0])
    finally:
        for h in hogs:
            h.kill()
        stop_sim(sim)
    tally.report("%d runs" % runs, t0)


def faults_proof(out_dir, n_burners, faults=FAULTS, line=PLUSR):
    print("each fault, quiet and with %d CPU burners: the step and measurement that catch it" % n_burners)
    for spec, step, measurement in faults:
        cells = []
        for loaded in (False, True):
            hogs = burners(n_burners) if loaded else []
            sim, urls = start_sim(spec, line=line)
            try:
                rec = run_eol(urls, out_dir, line)
            finally:
                for h in hogs:
                    h.kill()
                stop_sim(sim)
            where = first_failure(rec)
            ok = rec.get("outcome") == "FAIL" and where and where[0] == step and measurement in where[1]
            cells.append("%s %s%s" % ("ok" if ok else "MISSED", rec.get("outcome"),
                                      "" if ok else " at %s %s" % where if where else ""))
        print("  %-15s %-18s %-18s quiet: %-12s loaded: %s" % (spec, step, measurement, cells[0], cells[1]))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=2, help="runs per protocol variant (default 2)")
    ap.add_argument("--loaded", type=int, default=100, metavar="N",
                    help="runs of ezi-step-eol beside CPU burners for the false-FAIL count (default 100; 0: skip "
                         "it and the faults)")
    ap.add_argument("--burners", type=int, default=2, help="CPU burners beside the loaded runs (default 2)")
    ap.add_argument("--quick", action="store_true", help="a few seconds: the smallest sizes, one run each (make test runs it)")
    args = ap.parse_args(argv)
    if args.quick:
        args.runs, args.loaded, args.burners = 1, 1, 1
    if args.runs < 1 or args.loaded < 0 or args.burners < 0:
        print("error: --runs must be at least 1, --loaded and --burners at least 0", file=sys.stderr)
        return 2
    print("station benchmark: plans/ezi-step-eol.toml on the real-time bench, 115 200 baud, through the jig")
    print("  %-5s %8s %8s %8s %8s %8s %9s %12s %10s" % ("", "run s", "motion", "bus", "steps", "engine",
                                                       "steps n", "engine/step", "sample Hz"))
    with tempfile.TemporaryDirectory() as out:
        for ver8 in (False,) if args.quick else (False, True):
            for _ in range(args.runs):
                plan, ctx, wall = one_run(ver8, out)
                rec = ctx.record
                if rec["outcome"] != "PASS":
                    print("  Ver%d: the run did not pass (%s: %s): no figures" % (
                        8 if ver8 else 6, rec["outcome"],
                        "; ".join(d.get("description", "") for d in rec.get("outcome_details", []))[:120]))
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
    if args.loaded:
        with tempfile.TemporaryDirectory() as out:
            loaded_proof(args.loaded, args.burners, out)
            faults_proof(out, args.burners, FAULTS[:1] if args.quick else FAULTS)
    return 0


if __name__ == "__main__":
    sys.exit(main())
