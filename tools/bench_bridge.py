"""Bridge benchmark (part of `make bench`): prints figures, asserts nothing.

1. CPU time per transaction of the jig's main loop under CPython (forwarded
   transaction = PC request forwarded + driver reply relayed; local = answered by
   the jig), on an in-memory HAL so only firmware code is timed.
2. Heap use per transaction in steady state: CPython tracemalloc (net growth) and,
   if node + the WebAssembly MicroPython are installed, real MicroPython heap bytes
   with the collector disabled (goal: 0).
3. On the virtual bench's timeline, for every baud rate: the latency the jig adds
   over a direct PC<->driver connection beyond store-and-forward (goal: <= one
   byte time + the DE pre-delay per hop).
"""

import argparse
import os
import shutil
import subprocess
import sys
import time
import tracemalloc

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
for sub in ("firmware", "tools", "host_tests"):
    p = os.path.join(ROOT, sub)
    if p not in sys.path:
        sys.path.insert(0, p)

import bridge_probe  # noqa: E402
from jig import frame as F  # noqa: E402
from jig import params as P  # noqa: E402
from motorjig.sim import SimBench  # noqa: E402


def _seconds_per_call(fn, n, warmup=0):
    for _ in range(warmup):
        fn()
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n


def cpu_per_transaction(n):
    r = bridge_probe.Rig()
    fwd = _seconds_per_call(r.forward_once, n, warmup=200)
    loc = _seconds_per_call(r.local_once, n, warmup=200)
    idle = _seconds_per_call(r.app.poll, n)
    return fwd, loc, idle


def tracemalloc_per_transaction(n):
    r = bridge_probe.Rig()
    for _ in range(500):
        r.forward_once()
    tracemalloc.start()
    s0 = tracemalloc.take_snapshot()
    for _ in range(n):
        r.forward_once()
    s1 = tracemalloc.take_snapshot()
    tracemalloc.stop()
    stats = s1.compare_to(s0, "filename")
    blocks = sum(s.count_diff for s in stats if "tracemalloc" not in s.traceback[0].filename)
    size = sum(s.size_diff for s in stats if "tracemalloc" not in s.traceback[0].filename)
    return blocks / n, size / n


def micropython_heap(n):
    run_vm = os.path.join(ROOT, "host_tests", "wasm", "run_vm.mjs")
    pkg = os.path.join(ROOT, "host_tests", "wasm", "node_modules", "@micropython")
    if shutil.which("node") is None or not os.path.isdir(pkg):
        return None
    code = ("import sys\nsys.path.append('/data')\nimport bridge_probe as b\n"
            "print(b.forward_alloc(%d)[0], b.local_alloc(%d)[0], b.local_alloc(%d, True)[0])\n" % (n, n, n))
    r = subprocess.run(["node", run_vm, "--file", "bridge_probe.py=" + os.path.join(ROOT, "host_tests", "bridge_probe.py"), code],
                       capture_output=True, text=True, timeout=600)
    if r.returncode != 0:
        return None
    return [int(x) / n for x in r.stdout.split()]


DRIVER_TURNAROUND_US = 100.0  # the simulated driver's answer delay


def timeline(baud):
    b = SimBench(driver_ids=(2,), baud=baud, turnaround_us=DRIVER_TURNAROUND_US)
    segs = []
    for bus in (b.up_bus, b.down_bus):
        bus.monitor = lambda seg, data: segs.append((seg.node.name, seg.t0, seg.end))
    pre = b.app.params.get(P.P_DE_PRE_US)
    added_fwd, added_rel, rt = [], [], []
    for _ in range(20):
        segs.clear()
        wire, r = b.request(2, F.GET_ALL_STATUS, timeout_us=1e6)
        s = {name: (t0, t1) for name, t0, t1 in segs}
        added_fwd.append(s["jig-down"][0] - s["pc"][1])
        added_rel.append(s["jig-up"][0] - s["driver-2"][1])
        rt.append(s["jig-up"][1] - s["pc"][0])
    bt = 10e6 / baud
    req = len(F.encode(2, F.GET_ALL_STATUS)) * bt
    rep = len(wire) * bt
    direct = req + DRIVER_TURNAROUND_US + rep
    store_forward = direct + req + rep
    return dict(baud=baud, byte_us=bt, pre=pre, fwd=max(added_fwd), rel=max(added_rel),
                rt=max(rt), direct=direct, sf=store_forward)


def main(argv=None):
    ap = argparse.ArgumentParser(description="Bridge benchmark: CPU time, heap use and added latency per transaction.")
    ap.add_argument("-n", type=int, default=20000, help="transactions for the CPU/heap figures (default 20000)")
    ap.add_argument("--no-vm", action="store_true", help="skip the MicroPython (WebAssembly) heap measurement")
    args = ap.parse_args(argv)
    if args.n < 100:
        print("error: -n must be at least 100", file=sys.stderr)
        return 2
    print("bridge benchmark (%s %s)" % (sys.implementation.name, sys.version.split()[0]))
    fwd, loc, idle = cpu_per_transaction(args.n)
    print("  CPU per forwarded transaction (request forwarded + reply relayed): %7.1f us" % (fwd * 1e6))
    print("  CPU per local transaction (GetCommandPos to the jig):             %7.1f us" % (loc * 1e6))
    print("  CPU per idle main-loop pass:                                      %7.1f us" % (idle * 1e6))
    blocks, size = tracemalloc_per_transaction(min(args.n, 5000))
    print("  CPython tracemalloc, net growth per forwarded transaction:        %7.3f blocks, %.1f bytes" % (blocks, size))
    if not args.no_vm:
        mp = micropython_heap(300)
        if mp is None:
            print("  MicroPython heap per transaction: skipped (node or the WebAssembly VM missing)")
        else:
            print("  MicroPython heap bytes per transaction (gc off): forwarded %.1f, local %.1f, ReadCounters %.1f"
                  % tuple(mp))
    print("  added latency on the virtual timeline (goal per hop: <= 1 byte time + DE pre-delay):")
    print("    %7s %8s %8s %12s %12s %11s %11s" % ("baud", "byte us", "pre us", "fwd hop us", "relay hop us", "round trip", "S&F bound"))
    for baud in P.BAUD_RATES:
        t = timeline(baud)
        ok = t["fwd"] <= t["byte_us"] + t["pre"] + 1e-6 and t["rel"] <= t["byte_us"] + t["pre"] + 1e-6
        print("    %7d %8.1f %8d %12.1f %12.1f %11.0f %11.0f  %s"
              % (baud, t["byte_us"], t["pre"], t["fwd"], t["rel"], t["rt"], t["sf"], "ok" if ok else "OVER"))
    print("    (round trip = PC request start to relayed reply end; S&F bound = direct")
    print("     connection + both frames sent twice, i.e. pure store-and-forward)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
