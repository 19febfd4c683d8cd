"""The jig's own sampler (jig.trace), part of `make bench`: prints figures, asserts nothing.

On the virtual bench's timeline, with the jig's CPU time on the M7 modelled as in
tools/bench/bench_bridge.py (``JIG_CPU_MODEL``: instruction counts from `make test-qemu`,
400 MHz, one instruction per cycle assumed), the drive's turnaround 100 µs:

1. the trace's rate (samples over the time from the first to the last, on the
   jig's clock) and the jitter of its sample instants on the jig's clock, at
   115 200 and 921 600 baud (goals: >= 150 Hz and >= 1 000 Hz): the highest rate
   (period 100 µs: the sampler goes back to back, one request per round trip), and
   the goal's period with the bus to itself and with a PC that meanwhile moves the
   axis, polls another drive every 20 ms and reads the trace every 50 ms. An
   instant's offset is its tick minus its slot on the grid (StartTrace's tick plus
   whole periods);
2. the bridge's figures while a trace runs for another slave: a pyserial-style
   master polling GetAllStatus from driver 2 through the jig (as bench_bridge's
   polling table) while the jig samples driver 3, against the same without the
   trace: the rate, and the hops (the jig's added latency) of the requests that were
   not held behind a sample and of those that were.
"""

import argparse
import os
import struct
import sys

ROOT = os.path.dirname(os.path.abspath(__file__))
for sub in ("../../firmware", "..", ".", "../../host_tests"):
    p = os.path.normpath(os.path.join(ROOT, sub))
    if p not in sys.path:
        sys.path.insert(0, p)

from bench_bridge import DRIVER_TURNAROUND_US, JIG_CPU_MODEL, M7_HZ  # noqa: E402
from jig import diag as D  # noqa: E402
from jig import frame as F  # noqa: E402
from motorjig.sim import CpuModel, SimBench  # noqa: E402

MASK = 0x3FFFFFFF
GOALS = ((115200, 150.0), (921600, 1000.0))

# The sampler's own CPU time, from `make test-qemu` (2026-12-02, HAL calls at the board's
# prices): building and sending a slot's request (Trace.poll) 27 145 instructions, and
# the slow pass costs 4 620 more while a trace runs (24 040 against 19 420). Charged on
# the virtual timeline before the request goes out, so it delays the sample instant as
# it would on the board. (The reply's parse and store, 32 442, is about what the model
# already charges for its 41 bytes and one pass: 2 366 + 41 x 641 = 28 647.)
TRACE_REQUEST_INSTR = 27145 + 4620


def _charge_trace(b, us):
    """Model the sampler's request building: the virtual clock moves on by ``us`` before a
    due slot's request can go out (the jig's CPU is busy with it meanwhile)."""
    from jig.compat import ticks_diff
    from jig.trace import T_NEXT, T_ON, T_WAITING

    tr = b.app.trace
    orig = tr.poll
    clock = b.clock
    hal = b.hal

    def poll(now):
        ts = tr.ts
        if ts[T_ON] and not ts[T_WAITING] and ticks_diff(now, ts[T_NEXT]) >= 0 and not b.app.bridge.busy():
            hal.cpu_us += us
            clock.run_until(clock.now + us)
        orig(now)

    tr.poll = poll


def _bench(baud, cpu_model, ids=(2, 3)):
    b = SimBench(driver_ids=ids, baud=baud, turnaround_us=DRIVER_TURNAROUND_US, record=False, servo_on=True,
                 cpu_model=cpu_model)
    if any(cpu_model):
        _charge_trace(b, TRACE_REQUEST_INSTR / M7_HZ * 1e6)  # (as JIG_CPU_MODEL)
    for i in ids:
        _w, d = b.request(i, F.GET_SLAVE_INFO)  # the jig sees each drive answer
        if d is None or d[0]:
            raise RuntimeError("driver %d does not answer" % i)
    return b


def _start(b, slave, period_us):
    _w, d = b.request(1, D.START_TRACE, struct.pack("<BIB", slave, period_us, 1))
    if d is None or d[0]:
        raise RuntimeError("StartTrace refused: %r" % (d,))
    return D.decode_trace_start(d)[1]


def _read(b, frm):
    out = []
    while True:
        _w, d = b.request(1, D.READ_TRACE, struct.pack("<HB", frm, 0), timeout_us=1e6)
        _state, frm, s = D.decode_trace_chunk(d)
        out += s
        if len(s) < D.TRACE_CHUNK:
            return out, frm


def _stop(b):
    _w, d = b.request(1, D.STOP_TRACE)
    return D.decode_trace_status(d)


def _pct(values, q):
    v = sorted(values)
    return v[min(len(v) - 1, int(q * len(v)))] if v else 0


def trace_run(baud, period_us, duration_us, pc_traffic=False, cpu_model=JIG_CPU_MODEL):
    """One trace of driver 2; returns a dict of figures."""
    b = _bench(baud, cpu_model)
    t_begin = b.clock.now
    t0 = _start(b, 2, period_us)
    samples = []
    frm = 0
    pc_requests = pc_failed = 0
    if pc_traffic:
        b.request(2, F.SET_PARAMETER, bytes([3]) + struct.pack("<i", 20))
        _w, d = b.request(2, F.MOVE_VELOCITY, struct.pack("<IB", 20000, 1))
        pc_requests += 1
        pc_failed += d is None or d[0] != 0
        t_next_read = b.clock.now + 50000
        while b.clock.now - t_begin < duration_us:
            _w, d = b.request(3, F.GET_AXIS_STATUS)
            pc_requests += 1
            pc_failed += d is None or d[0] != 0
            if b.clock.now >= t_next_read:
                s, frm = _read(b, frm)
                samples += s
                t_next_read = b.clock.now + 50000
            b.run_for(20000.0)
        _w, d = b.request(2, F.MOVE_STOP)
        pc_requests += 1
        pc_failed += d is None or d[0] != 0
    else:
        b.run_for(float(duration_us))
    st = _stop(b)
    s, frm = _read(b, frm)
    samples += s
    ticks = [x[0] for x in samples]
    offs = [((t - t0) & MASK) % period_us for t in ticks[1:]]  # (the first waits for StartTrace's reply)
    gaps = [(b_ - a) & MASK for a, b_ in zip(ticks, ticks[1:])]
    mean_gap = sum(gaps) / len(gaps) if gaps else 0.0
    span = (ticks[-1] - ticks[0]) & MASK if len(ticks) > 1 else 0
    return dict(baud=baud, period=period_us, rate=(len(samples) - 1) / (span / 1e6) if span else 0.0, n=len(samples),
                taken=st["taken"], skipped=st["skipped"], failed=st["failed"], lost=st["lost"],
                off_mean=sum(offs) / len(offs) if offs else 0.0, off_p95=_pct(offs, 0.95), off_max=max(offs or [0]),
                gap_mean=mean_gap, gap_min=min(gaps or [0]), gap_max=max(gaps or [0]),
                pc_requests=pc_requests, pc_failed=pc_failed, collisions=b.down_bus.collisions)


def polling_with_trace(baud, trace_period_us, n=200, cpu_model=JIG_CPU_MODEL):
    """A pyserial-style master polls GetAllStatus from driver 2 through the jig while the
    jig samples driver 3 every trace_period_us (0: no trace)."""
    b = _bench(baud, cpu_model)
    ends = {}

    def seen(seg, data):
        if data and not bytes(data[:3]) == b"\xaa\xcc\x03":  # (not the sampler's request to driver 3)
            ends[seg.node.name] = seg.end

    b.up_bus.monitor = seen
    b.down_bus.monitor = seen
    t_trace = b.clock.now
    if trace_period_us:
        _start(b, 3, trace_period_us)
    hops_free, hops_held, rep_hops = [], [], []
    t_start = None
    for i in range(n + 3):
        if i == 3:
            t_start = b.clock.now
        ends.clear()
        _w, d = b.request(2, F.GET_ALL_STATUS, timeout_us=1e6)
        if d is None or d[0] != 0:
            raise RuntimeError("%d baud: poll %d got no good reply" % (baud, i))
        if i >= 3:
            hop = ends["jig-down"] - ends["pc"]
            # a request held behind a sample leaves the jig whole after the PC's last byte;
            # cut through it leaves with it (a hop of about a byte time and the DE pre-delay)
            (hops_held if hop > 3 * 10e6 / baud + 5 else hops_free).append(hop)
            rep_hops.append(ends["jig-up"] - ends["driver-2"])
    period = (b.clock.now - t_start) / n
    out = dict(rate=1e6 / period, free=hops_free, held=hops_held, rep=sum(rep_hops) / len(rep_hops))
    if trace_period_us:
        st = _stop(b)
        out.update(trace_rate=st["taken"] / ((b.clock.now - t_trace) / 1e6), failed=st["failed"])
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description="The jig's own sampler: rate, jitter, and the bridge beside it.")
    ap.add_argument("--seconds", type=float, default=2.0, help="virtual seconds per trace (default 2)")
    ap.add_argument("--polls", type=int, default=200, help="polls per cell of the bridge table (default 200)")
    ap.add_argument("--no-cpu-model", action="store_true", help="an infinitely fast jig CPU (wire time only)")
    ap.add_argument("--quick", action="store_true", help="a few seconds: the smallest sizes, one run each (make test runs it)")
    args = ap.parse_args(argv)
    if args.quick:
        args.seconds, args.polls = 0.05, 1
    model = CpuModel() if args.no_cpu_model else JIG_CPU_MODEL
    dur = int(args.seconds * 1e6)
    print("trace benchmark: the jig samples driver 2 with GetAllStatus (virtual timeline, drive turnaround %.0f us,"
          % DRIVER_TURNAROUND_US)
    print("  jig CPU model as bench_bridge's, %s%s)" % (
        model.describe(M7_HZ), "" if model.off else ", + %d per sample's request" % TRACE_REQUEST_INSTR))
    print("  %7s %-34s %9s %8s %7s %6s %6s %23s %s" % ("baud", "run", "period us", "rate /s", "skipped", "failed",
                                                     "lost", "offset mean/p95/max us", "interval min..max us"))
    for baud, goal in GOALS:
        period = int(1e6 / goal)
        for title, per, pc in (("highest rate (period 100 us)", 100, False),
                               ("goal %g Hz, bus to itself" % goal, period, False),
                               ("goal %g Hz, PC moves/polls/reads" % goal, period, True)):
            r = trace_run(baud, per, dur, pc, model)
            print("  %7d %-34s %9d %8.1f %7d %6d %6d %8.1f /%6d /%6d   %d..%d%s"
                  % (baud, title, per, r["rate"], r["skipped"], r["failed"], r["lost"], r["off_mean"], r["off_p95"],
                     r["off_max"], r["gap_min"], r["gap_max"],
                     "   PC requests %d, unanswered %d, collisions %d" % (r["pc_requests"], r["pc_failed"],
                                                                       r["collisions"]) if pc else ""))
    print("  (offset: a sample's tick minus its slot t0 + k * period; at the highest rate the slots are 100 us apart")
    print("   and every round trip skips some, so the offset there says nothing)")
    print("  the bridge beside a trace: a pyserial-style master polls GetAllStatus from driver 2 through the jig")
    print("  while the jig samples driver 3")
    print("  %7s %-22s %9s %11s %-30s %-30s %11s" % ("baud", "trace of driver 3", "PC /s", "trace /s",
                                                     "req hop us, not held: n mean", "held behind a sample: n mean",
                                                     "reply hop"))
    for baud, goal in GOALS:
        for per in (0, 20000, int(1e6 / goal)):
            r = polling_with_trace(baud, per, args.polls, model)
            free, held = r["free"], r["held"]
            print("  %7d %-22s %9.1f %11s %5d %8.1f (max %6.1f)     %5d %8.1f (max %7.1f) %10.1f"
                  % (baud, "off" if not per else "every %d us" % per, r["rate"],
                     "-" if not per else "%.1f" % r["trace_rate"], len(free), sum(free) / max(1, len(free)),
                     max(free or [0]), len(held), sum(held) / max(1, len(held)), max(held or [0]), r["rep"]))
    print("  (hop: the PC request's last stop bit -> its last stop bit on the driver bus; the reply hop likewise;")
    print("   a request held behind a sample goes on whole once the sample's reply is in)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
