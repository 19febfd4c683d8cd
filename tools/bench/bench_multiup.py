"""Multi-up benchmark (part of `make bench`): drives tested per hour with 1, 2 and 4 slots.

Each line runs its plan in 1, 2 and 4 slots at once on the real-time virtual bench (the
jig's firmware modules on CPython, simulated healthy drives wired as the fixture files in
plans/multiup/ say; the bench in a process of its own, as the jig is a board with a CPU of its
own), through ``station.slots.SlotRun`` as ``jigctl test --slots`` does:

* ``ezi-step-eol`` on Plus-R drives (slaves 2-5) at 115 200 and 921 600 baud,
* ``cia402-eol`` on CiA 402 drives (nodes 5-8) at 500 kbit/s and 1 Mbit/s,
* the mixed set: 2 Plus-R + 2 CiA 402 (ezi-step-eol and cia402-eol) at 921 600 baud and
  500 kbit/s (its speed-up: over running its four drives one by one).

For each: the wall time of the group, drives per hour (slots x 3600 / wall; "-" when a slot
did not pass: a run that ended early is no drive tested), the speed-up
over one slot (goal: >= 3.5x with 4 slots where the plan is motion-bound), the verdicts, the
load of the driver bus (RS-485) and of the CAN bus over the group (their wire time / the
wall time), the trace rate each slot's moves got (the lowest and the mean of the
``sample_rate`` measurements), and the engine's time per step (a slot's run time less its
steps' time, over its steps).

Then the loaded proof (``--loaded N``, default 25): ``ezi-step-eol`` in the 4 slots of
plans/multiup/ezi-step-4up.toml N rounds at 921 600 baud, the bench in a process of its
own above two CPU burners (as bench_station's proof): every FAIL is a false FAIL (the goal
is 0); an ERROR is a measurement the station could not trust, with its reason. Prints
figures, asserts nothing.
"""

import argparse
import json
import os
import re
import signal
import statistics
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
for sub in ("firmware", "tools"):
    p = os.path.join(ROOT, sub)
    if p not in sys.path:
        sys.path.insert(0, p)

from bench_station import Line, start_sim, stop_sim  # noqa: E402
from motorjig.station import slots as SL  # noqa: E402
from motorjig.station.plan import load_plan  # noqa: E402

PLANS = os.path.join(ROOT, "plans")
MULTIUP = os.path.join(PLANS, "multiup")
EOL = os.path.join(PLANS, "ezi-step-eol.toml")
EOL402 = os.path.join(PLANS, "cia402-eol.toml")
SMOKE = os.path.join(PLANS, "smoke.toml")


def plusr_slot(i, plan=EOL):
    """Slot i (0..3) of the 4-up Plus-R fixture: slave 2 + i, fixture position i + 1 (a plan with [wiring])."""
    table = {"name": str(i + 1), "slave": 2 + i}
    if load_plan(plan).wiring is not None:
        table["wiring"] = os.path.join(MULTIUP, "fixture-%d.toml" % (i + 1))
    return plan, table


def cia402_slot(i, bitrate, position=None):
    """Slot of node 5 + i at ``bitrate``, fixture position ``position`` (default i + 1)."""
    position = i + 1 if position is None else position
    return EOL402, {"name": str(position), "node_id": 5 + i, "bitrate": bitrate,
                    "wiring": os.path.join(MULTIUP, "fixture-402-%d.toml" % position)}


def slots_file(entries, folder):
    """A slots file of (plan, slot table) entries: the one the bench and the run read."""
    path = os.path.join(folder, "slots.toml")
    with open(path, "w") as f:
        for plan, table in entries:
            f.write("[[slot]]\nplan = %s\n" % json.dumps(plan))
            for k, v in table.items():
                f.write("%s = %s\n" % (k, json.dumps(v)))
    return path


def bus_time(sim):
    """The bench's buses' wire time so far (µs): (RS-485, CAN or None), asked with SIGUSR1."""
    sim.send_signal(signal.SIGUSR1)
    for text in sim.stdout:
        m = re.match(r"bus time: rs485 (\d+) us,(?: can (\d+) us,)? over", text)
        if m:
            return float(m.group(1)), float(m.group(2)) if m.group(2) else None
    raise RuntimeError("the bench did not say its bus time")


def run_group(entries, baud=115200, bitrate=500000):
    """The slots at once on a fresh bench in its own process (as the jig is a board: the station's
    threads do not slow it): (wall s, slots, {slot: RunContext}, {slot: error}, RS-485 load, CAN load)."""
    nodes = [t["node_id"] for _p, t in entries if "node_id" in t]
    with tempfile.TemporaryDirectory() as out:
        path = slots_file(entries, out)
        args = ["--slots", path, "--baud", str(baud), "--can-bitrate", str(bitrate)]
        if nodes:
            args += ["--can-nodes", ",".join(str(n) for n in nodes)]
        sim, urls = start_sim(line=Line(EOL, args))
        try:
            slots = SL.load_slots(path, EOL)
            run = SL.SlotRun(slots, urls["tcp"], baud=baud, out_dir=out, out=None, confirm=lambda m: True,
                             timeout_ms=300, db=None, can_port=urls.get("slcan"))
            busy0 = bus_time(sim)
            t0 = time.monotonic()
            ctxs = run.run()
            wall = time.monotonic() - t0
            busy1 = bus_time(sim)
        finally:
            stop_sim(sim)
    rs485 = (busy1[0] - busy0[0]) / (wall * 1e6)
    can = (busy1[1] - busy0[1]) / (wall * 1e6) if nodes else None
    return wall, slots, ctxs, run.errors, rs485, can


def verdicts(slots, ctxs, errors):
    return [SL.summary(s, ctxs.get(s.name), errors.get(s.name))["verdict"] for s in slots]


def trace_rates(ctxs):
    """The sample_rate of every move step of every slot (Hz)."""
    rates = []
    for ctx in ctxs.values():
        for ph in (ctx.record or {}).get("phases", []):
            m = ph.get("measurements", {}).get("sample_rate")
            if m and isinstance(m.get("measured_value"), (int, float)):
                rates.append(m["measured_value"])
    return rates


def engine_per_step_ms(ctxs):
    """A slot's run time less its steps' own time, over its steps (ms), the mean over the slots."""
    out = []
    for ctx in ctxs.values():
        r = ctx.record or {}
        if not ctx.timings or "end_time_millis" not in r:
            continue
        span = (r["end_time_millis"] - r["start_time_millis"]) / 1000.0
        out.append((span - sum(dt for _n, dt, _b in ctx.timings)) / len(ctx.timings) * 1000.0)
    return statistics.mean(out) if out else float("nan")


ALONE = {}  # plan name -> wall s of one slot (the mixed set's speed-up is over running its plans one by one)


def line(title, make_slots, counts, baud=115200, bitrate=500000):
    print("\n%s" % title)
    print("  %5s %7s %9s %8s %-24s %7s %7s %14s %10s" % ("slots", "wall s", "drives/h", "speed-up", "verdicts",
                                                       "RS-485", "CAN", "trace Hz min/mean", "engine/step"))
    base = None
    for n in counts:
        try:
            wall, slots, ctxs, errors, rs485, can = run_group(make_slots(n), baud, bitrate)
        except SL.SlotError as exc:  # (the station refuses what it could not judge: say so, go on)
            print("  %5d refused: %s" % (n, exc))
            continue
        per_hour = n * 3600.0 / wall
        if n == 1:
            ALONE.setdefault(slots[0].plan.name, wall)
        one_by_one = sum(ALONE.get(s.plan.name, float("nan")) for s in slots)
        base = base or (per_hour / n if n == 1 else n * 3600.0 / one_by_one)
        rates = trace_rates(ctxs)
        vs = verdicts(slots, ctxs, errors)
        judged = all(v == "PASS" for v in vs)  # (runs that ended early are no drives tested)
        print("  %5d %7.1f %9s %8s %-24s %6.0f%% %7s %14s %8.0f ms" % (
            n, wall, "%.0f" % per_hour if judged else "-", "%.2fx" % (per_hour / base) if judged else "-",
            " ".join(vs), rs485 * 100,
            "%.0f%%" % (can * 100) if can is not None else "-",
            "%.0f / %.0f" % (min(rates), statistics.mean(rates)) if rates else "-", engine_per_step_ms(ctxs)))
        for s in slots:
            if s.name in errors:
                print("        slot %s: %s" % (s.name, errors[s.name]))
            elif ctxs.get(s.name) is not None and SL.summary(s, ctxs[s.name])["verdict"] not in ("PASS",):
                print("        %s: %s" % (s.describe(), "; ".join(SL.summary(s, ctxs[s.name])["details"])[:160]))


def loaded_proof(rounds, n_burners, baud=921600):
    """``rounds`` x 4 slots of ezi-step-eol on healthy drives beside CPU burners: the false FAILs."""
    from bench_station import Tally, board_priority_note, burners

    four_up = os.path.join(MULTIUP, "ezi-step-4up.toml")
    print("\nfalse FAILs on a busy PC with 4 slots: ezi-step-eol %d rounds x 4 healthy drives at %d baud, the bench in "
          "its own process (%s), %d CPU burners beside it" % (rounds, baud, board_priority_note(), n_burners))
    hogs = burners(n_burners)
    sim, urls = start_sim(line=Line(EOL, ["--slots", four_up, "--baud", str(baud)]))
    tally = Tally()
    t0 = time.monotonic()
    try:
        time.sleep(2)  # the burners' load builds up
        with tempfile.TemporaryDirectory() as out:
            for _ in range(rounds):
                slots = SL.load_slots(four_up, EOL)
                run = SL.SlotRun(slots, urls["tcp"], baud=baud, out_dir=out, out=None, confirm=lambda m: True,
                                 timeout_ms=300, db=None)
                ctxs = run.run()
                for s in slots:
                    ctx = ctxs.get(s.name)
                    tally.add((ctx.record if ctx else None) or {}, run.errors.get(s.name, "?"))
                tally.loads.append(os.getloadavg()[0])
    finally:
        for h in hogs:
            h.kill()
        stop_sim(sim)
    tally.report("%d rounds (%d runs)" % (rounds, rounds * 4), t0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke.toml in 1 and 2 slots at 921 600 baud only")
    ap.add_argument("--loaded", type=int, default=25, metavar="N",
                    help="rounds of 4 slots beside CPU burners for the false-FAIL count (default 25; 0: skip it)")
    ap.add_argument("--burners", type=int, default=2, help="CPU burners beside the loaded rounds (default 2)")
    ap.add_argument("--only-loaded", action="store_true", help="only the loaded proof")
    args = ap.parse_args(argv)
    if args.loaded < 0 or args.burners < 0:
        print("error: --loaded and --burners must be at least 0", file=sys.stderr)
        return 2
    if args.quick:
        line("smoke (quick mode), Plus-R, 921 600 baud", lambda n: [plusr_slot(i, SMOKE) for i in range(n)], (1, 2),
             baud=921600)
        return 0
    if args.only_loaded:
        loaded_proof(args.loaded, args.burners)
        return 0
    for baud in (115200, 921600):
        line("ezi-step-eol, Plus-R, %d baud" % baud, lambda n: [plusr_slot(i) for i in range(n)], (1, 2, 4), baud=baud)
    for bitrate in (500000, 1000000):
        line("cia402-eol, CiA 402, %d kbit/s" % (bitrate // 1000), lambda n, br=bitrate: [
            cia402_slot(i, br) for i in range(n)], (1, 2, 4), bitrate=bitrate)
    line("mixed: 2 ezi-step-eol (Plus-R) + 2 cia402-eol (CiA 402), 921 600 baud, 500 kbit/s",
         lambda n: [plusr_slot(0), plusr_slot(1), cia402_slot(0, 500000, 3), cia402_slot(1, 500000, 4)], (4,),
         baud=921600)
    if args.loaded:
        loaded_proof(args.loaded, args.burners)
    return 0


if __name__ == "__main__":
    sys.exit(main())
