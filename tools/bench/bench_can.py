"""The jig's CAN port under a loaded bus, part of `make bench`: prints figures, asserts nothing.

On the virtual bench's timeline, at 500 kbit/s and 1 Mbit/s, CiA 402 nodes
(``motorjig.sim.cia402``) load the bus to over 90 %: every node's four TPDOs on a
2 ms event timer, and heartbeats every 100 ms. A host on the SLCAN port -- the
jig's (firmware ``jig.canport`` on the bench), then for reference a plain USB
adapter on the same bus (``canhal.DirectSlcanAdapter``) -- sends NMT start, then an
SDO upload (0x1000) to node 1 every 20 ms at a varied point of the USB frame, the
same instants for both (over runs with the nodes started at other instants: the
phase of their bursts against the USB frames). Printed for each bitrate and adapter:

* the bus load over the measured window (``CanBus.load``);
* frames on the bus from the nodes against the frames the host received as SLCAN
  lines (goal: none lost), and where any were lost (the controller's FIFO, the
  jig's RX ring: its counters);
* the host-to-bus latency of a frame: the host's line sent -> the frame's end on
  the bus (min/avg/max over the SDO requests), which includes the wait for the next
  USB frame and for the loaded bus;
* an SDO upload's round trip (request line sent -> reply line received), and what
  the jig adds to it against the direct adapter (goal: at most one frame time).

The model's assumptions are printed beside the figures.
"""

import argparse
import os
import random
import sys

ROOT = os.path.dirname(os.path.abspath(__file__))
for sub in ("../../firmware", ".."):
    p = os.path.normpath(os.path.join(ROOT, sub))
    if p not in sys.path:
        sys.path.insert(0, p)

from jig import diag as D  # noqa: E402
from jig.canport import CAN_POLL_US  # noqa: E402
from motorjig.sim import SimBench  # noqa: E402
from motorjig.sim.canbus import frame_bits  # noqa: E402
from motorjig.sim.canhal import SLCAN_RATES  # noqa: E402
from motorjig.sim.cia402 import Cia402Node  # noqa: E402
from motorjig.sim.hal import USB_FRAME_US  # noqa: E402

# The load: node ids per bitrate (four TPDOs each, 3/6/8/6 bytes, every EVENT_MS).
NODES = {500000: (1, 2), 1000000: (1, 2, 3, 4)}
EVENT_MS = 2
HEARTBEAT_MS = 100
SDO_PERIOD_US = 20000  # one SDO upload from the host this often
SDO_NODE = 1
SDO_REQUEST = b"t60%d84000100000000000\r" % SDO_NODE  # upload 0x1000:00
PHASES = 20  # runs, each with the nodes started at other instants (see run_one)
SETTLE_US = 20000  # after NMT start, before measuring
DRAIN_US = 30000  # after the load stops, for the last lines to reach the host


def make_node(clock, bus, node_id):
    return Cia402Node(clock, bus, node_id, heartbeat_ms=HEARTBEAT_MS)


def load_nodes(b):
    """Every node's TPDOs on the event timer (transmission type 255), as an SDO client
    would set them (after the boot-up)."""
    for node in b.can_nodes.values():
        for k in range(4):
            cob = node.read(0x1800 + k, 1)
            for sub, value in ((1, cob | 0x80000000), (2, 255), (5, EVENT_MS), (1, cob & 0x7FF)):
                code = node.write(0x1800 + k, sub, value)
                if code:
                    raise SystemExit("bench_can: node %d refused TPDO%d setting %d (SDO abort 0x%08X)"
                                     % (node.node_id, k + 1, sub, code))


def run_one(bitrate, direct, seconds, seed):
    """One adapter at one bitrate: the figures of PHASES runs of seconds / PHASES each,
    added up.

    A node's timers run on its own clock, the host's USB frames on the PC's: nothing
    ties the phase of the nodes' TPDO bursts to the USB frames. Run after run the
    nodes are started (NMT start from a master on the bus) at other instants, so the
    figures average over that phase instead of depending on one value of it."""
    total = None
    for phase in range(PHASES):
        r = run_phase(bitrate, direct, seconds / PHASES, seed * 1000 + phase)
        if total is None:
            total = r
            continue
        for k, v in r.items():
            total[k] = total[k] + v
    total["load"] = total["busy_us"] / (total["window_s"] * 1e6)
    return total


def run_phase(bitrate, direct, seconds, seed):
    """One adapter at one bitrate, the nodes started at instants drawn from seed."""
    b = SimBench(driver_ids=(2,), can_nodes=NODES[bitrate], can_bitrate=bitrate, direct_can=direct,
                 can_node_factory=make_node)
    b.run_for(5000)  # the nodes' boot-up
    load_nodes(b)
    port = b.slcan
    clock = b.clock
    received = []  # (t, chunk) the host got
    port.host_open()
    port.sink = lambda chunk: received.append((clock.now, bytes(chunk))) or len(chunk)
    adapter = b.can_adapter.can if direct else None
    counts = {"others": 0, "sdo_end": None}

    def monitor(t, f, kind):
        can = adapter if direct else b.hal.can
        if kind != "ok" or can is None or not can.node.online:
            return
        if f.node is can.node:
            if f.can_id == 0x600 + SDO_NODE and counts["sdo_end"] is None:
                counts["sdo_end"] = t
        else:
            counts["others"] += 1

    b.can_bus.monitor = monitor
    port.host_send(b"S%d\rO\r" % SLCAN_RATES.index(bitrate))
    b.run_for(15000)
    rnd = random.Random(seed)
    master = b.can_bus.add_node("nmt-master")
    t_start = clock.now
    for n in NODES[bitrate]:
        clock.at(t_start + rnd.uniform(0, EVENT_MS * 1000), master.transmit, 0x000, False, False, bytes([1, n]))
    b.run_for(SETTLE_US)
    t0 = clock.now
    to_bus = []
    round_trip = []
    for i in range(int(seconds * 1e6 // SDO_PERIOD_US)):
        when = t0 + i * SDO_PERIOD_US + rnd.randrange(USB_FRAME_US)
        b.run_for(max(0.0, when - clock.now))
        sent = clock.now
        counts["sdo_end"] = None
        mark = len(received)
        port.host_send(SDO_REQUEST)

        def waiting():
            return not any(b"t58%d8" % SDO_NODE in c for _, c in received[mark:])

        clock.run_while(waiting, SDO_PERIOD_US * 5)
        reply = [t for t, c in received[mark:] if b"t58%d8" % SDO_NODE in c]
        if not reply or counts["sdo_end"] is None:
            raise SystemExit("bench_can: no SDO reply %d at %d bit/s (%s)" % (i, bitrate, "direct" if direct else "jig"))
        to_bus.append(counts["sdo_end"] - sent)
        round_trip.append(reply[0] - sent)
    t1 = clock.now
    load = b.can_bus.load(t0, t1)
    for node in b.can_nodes.values():  # the load stops; what is on its way reaches the host
        b.can_bus.remove_node(node.can)
    b.run_for(DRAIN_US)
    text = b"".join(c for _, c in received)
    lines = sum(1 for ln in text.split(b"\r") if ln[:1] in (b"t", b"T", b"r", b"R"))
    out = {"busy_us": load * (t1 - t0), "others": counts["others"], "lines": lines, "to_bus": to_bus,
           "round_trip": round_trip, "window_s": (t1 - t0) / 1e6}
    if not direct:
        c = dict(zip(D.CAN_WIRE_NAMES, b.app.can.counter_values([0] * D.N_CAN_WIRE)))
        out["ring_lost"] = c["can_rx_lost"]
        out["fifo_overruns"] = c["can_rx_overruns"]
        out["refused"] = c["can_tx_refused"]
    return out


def stats(xs):
    return min(xs), sum(xs) / len(xs), max(xs)


def main(argv=None):
    ap = argparse.ArgumentParser(description="The jig's CAN port on a loaded simulated bus: frames lost, "
                                 "host-to-bus latency, an SDO upload through the jig against a direct adapter.")
    ap.add_argument("--seconds", type=float, default=10.0, help="simulated seconds per bitrate and adapter, over %d node phases (10)" % PHASES)
    ap.add_argument("--seed", type=int, default=24, help="seed of the SDO requests' instants (24)")
    ap.add_argument("--quick", action="store_true", help="a few seconds: the smallest sizes, one run each (make test runs it)")
    args = ap.parse_args(argv)
    least = PHASES * SDO_PERIOD_US / 1e6  # one SDO upload a phase
    if args.quick:
        args.seconds = least
    if not least <= args.seconds <= 60:
        ap.error("--seconds must be %g .. 60 (an SDO upload in each of the %d phases)" % (least, PHASES))
    print("CAN port under load (tools/bench/bench_can.py): virtual time; the jig's CPU is not modelled "
          "(its firmware runs in zero time on the bench, as does the direct adapter's)")
    print("  host <-> adapter: full-speed USB CDC, 1 ms frames both ways (lines to the host once a frame, the "
          "host's bytes in the next frame), the same for the jig's SLCAN port and the direct adapter")
    print("  jig: the port's own pass every %d µs while open (jig.canport.CAN_POLL_US); bus frames with "
          "worst-case bit stuffing; CiA 402 nodes' TPDOs every %d ms, heartbeats every %d ms; an SDO upload "
          "every %d ms" % (CAN_POLL_US, EVENT_MS, HEARTBEAT_MS, SDO_PERIOD_US // 1000))
    rows = []
    for bitrate in (500000, 1000000):
        jig = run_one(bitrate, False, args.seconds, args.seed)
        ref = run_one(bitrate, True, args.seconds, args.seed)
        frame_us = frame_bits(False, False, 8) * 1e6 / bitrate
        print()
        print("%d kbit/s, nodes %s, %.1f s measured, an 8-byte frame %.0f µs:" % (
            bitrate // 1000, ",".join(str(n) for n in NODES[bitrate]), jig["window_s"], frame_us))
        for name, r in (("jig", jig), ("direct adapter", ref)):
            lost = r["others"] - r["lines"]
            where = ""
            if name == "jig":
                where = " (RX ring %d, controller FIFO overruns %d)" % (r["ring_lost"], r["fifo_overruns"])
            lo, av, hi = stats(r["to_bus"])
            rlo, rav, rhi = stats(r["round_trip"])
            print("  %-14s bus load %5.1f %%; frames from the nodes %6d, lines to the host %6d, lost %d%s"
                  % (name, 100 * r["load"], r["others"], r["lines"], lost, where))
            print("  %-14s host line -> frame's end on the bus: min %5.0f avg %5.0f max %5.0f µs (%d SDO requests)"
                  % ("", lo, av, hi, len(r["to_bus"])))
            print("  %-14s SDO upload round trip:              min %5.0f avg %5.0f max %5.0f µs"
                  % ("", rlo, rav, rhi))
        added_bus = stats(jig["to_bus"])[1] - stats(ref["to_bus"])[1]
        added = stats(jig["round_trip"])[1] - stats(ref["round_trip"])[1]
        print("  the jig adds: host -> bus %+.0f µs, SDO round trip %+.0f µs on average = %.2f frame times "
              "(goal <= 1)" % (added_bus, added, added / frame_us))
        rows.append((bitrate, jig, ref, added, frame_us))
    print()
    print("| bitrate | bus load | frames lost (jig / direct) | host -> bus, jig (min/avg/max) | "
          "SDO round trip jig / direct (avg) | jig adds |")
    print("|---|---|---|---|---|---|")
    for bitrate, jig, ref, added, frame_us in rows:
        lo, av, hi = stats(jig["to_bus"])
        print("| %d kbit/s | %.1f %% | %d / %d | %.0f / %.0f / %.0f µs | %.0f / %.0f µs | %+.0f µs (%.2f frame) |" % (
            bitrate // 1000, 100 * jig["load"], jig["others"] - jig["lines"], ref["others"] - ref["lines"],
            lo, av, hi, stats(jig["round_trip"])[1], stats(ref["round_trip"])[1], added, added / frame_us))
    return 0


if __name__ == "__main__":
    sys.exit(main())
