"""python -m motorjig.sim: the virtual bench, interactive.

Starts the simulated jig and drivers in real time, prints the jig's protocol and
each driver's variant, the wiring and the injected faults, the pseudo-terminal path
and the pyserial TCP URL of the PC side and of the jig's capture port (its recording
of both buses: `jigctl capture --jig URL`), runs a short demo session (scan with
variant detection -> servo on -> move -> status) through the PC side's TCP port, then
keeps serving until Ctrl-C (or --duration seconds). Each driver is Ver6 or Ver8 on its own:
--drivers 2,3:v8. --wiring connects the jig's relays and inputs to a drive's I/O,
--fault makes drives fail the way real ones do. --can-nodes 5,6 adds a CAN bus with
simulated CiA 402 drives and serves the jig's SLCAN port (python-can's slcan interface,
jigctl can) on a TCP port and a pty of its own; a wiring with `node = 5` wires the jig
to CAN node 5's digital inputs and outputs instead of a Plus-R drive. The buses of the table of
simulated kinds (``sim.kinds.EXTRA_BUSES``) add their own options and run beside the bench.
"""

import argparse
import os
import signal
import subprocess
import sys
import textwrap
import time

from ..wiring import WiringError, load_wiring
from . import kinds as sim_kinds
from .bench import CAN_FAULT_PREFIX, Bench
from .canhal import SLCAN_RATES
from .driver import FAULTS, parse_fault_spec


class DriverSpec(tuple):
    """Parsed --drivers: the ids, and ``ver8`` (the ids of the Ver8 drivers)."""

    ver8 = ()


def _drivers(text):
    """'2,3:v8' -> ids (2, 3), ver8 (3,); a driver without a suffix is Ver6."""
    ids, ver8 = [], []
    for item in (x.strip() for x in text.split(",")):
        if not item:
            continue
        num, _, variant = item.partition(":")
        try:
            i = int(num)
        except ValueError:
            raise argparse.ArgumentTypeError("expected ids with an optional :v6 or :v8, e.g. 2,3:v8; not %r" % item)
        if not 0 <= i <= 15:
            raise argparse.ArgumentTypeError("driver ids must be 0..15, got %d" % i)
        if variant.lower() not in ("", "v6", "v8"):
            raise argparse.ArgumentTypeError("driver variant must be v6 or v8, not %r" % variant)
        if i in ids:
            raise argparse.ArgumentTypeError("driver id %d given twice" % i)
        ids.append(i)
        if variant.lower() == "v8":
            ver8.append(i)
    if not ids:
        raise argparse.ArgumentTypeError("give at least one driver id")
    spec = DriverSpec(ids)
    spec.ver8 = tuple(ver8)
    return spec


def _can_nodes(text):
    """'5,6' -> (5, 6): CANopen node ids 1..127."""
    ids = []
    for item in (x.strip() for x in text.split(",")):
        if not item:
            continue
        try:
            i = int(item)
        except ValueError:
            raise argparse.ArgumentTypeError("expected CANopen node ids, e.g. 5,6; not %r" % item) from None
        if not 1 <= i <= 127:
            raise argparse.ArgumentTypeError("CAN node ids must be 1..127, got %d" % i)
        if i in ids:
            raise argparse.ArgumentTypeError("CAN node id %d given twice" % i)
        ids.append(i)
    if not ids:
        raise argparse.ArgumentTypeError("give at least one CAN node id")
    return tuple(ids)


def _can_bitrate(text):
    try:
        rate = int(text)
    except ValueError:
        rate = None
    if rate not in SLCAN_RATES:
        raise argparse.ArgumentTypeError("the CAN bitrate must be one of the SLCAN rates %s, not %r"
                                         % (" ".join(map(str, SLCAN_RATES)), text))
    return rate


def parse_can_fault(spec):
    """``can:[ID:]NAME[=VALUE]`` -> (node id or None, "can:NAME", value or None)."""
    head, eq, value = spec[len(CAN_FAULT_PREFIX):].strip().partition("=")
    node, colon, name = head.partition(":")
    if not colon:
        node, name = None, head
    else:
        try:
            node = int(node)
        except ValueError:
            raise ValueError("expected can:[ID:]NAME[=VALUE]; %r is not a CAN node id" % node) from None
    name = name.strip()
    if not name:
        raise ValueError("expected can:[ID:]NAME[=VALUE], e.g. can:5:NAME")
    return node, CAN_FAULT_PREFIX + name, value.strip() if eq else None


def _protocol(text):
    t = text.lower().lstrip("v").replace("ver", "")
    if t not in ("6", "8"):
        raise argparse.ArgumentTypeError("jig protocol must be 6 or 8, not %r" % text)
    return int(t)


def _fault_help():
    lines = ["faults (--fault [ID:]NAME[=VALUE]; without ID: the wired drive, else every driver):"]
    for name, (value, default, what) in FAULTS.items():
        spec = name + ("=" + value if value else "")
        text = what + (" (default %s)" % default if default is not None else "")
        lines.append(textwrap.fill(text, 96, initial_indent="  %-18s " % spec, subsequent_indent=" " * 21))
    lines.append("e.g. --fault step-out=20000 --fault 3:alarm=4@50 --fault param=3:250 --fault no-origin")
    CAN_FAULTS = sim_kinds.can_faults()
    lines.append("CAN node faults (--can-nodes; --fault can:[ID:]NAME[=VALUE]; without ID: the wired node, else every CAN node):")
    for name, (value, default, what) in CAN_FAULTS.items():
        spec = "can:" + name + ("=" + value if value else "")
        text = what + (" (default %s)" % default if default is not None and "default" not in what else "")
        lines.append(textwrap.fill(text, 96, initial_indent="  %-22s " % spec, subsequent_indent=" " * 25))
    lines.append("e.g. --can-nodes 5,6 --fault can:5:following-error=20000 --fault can:missed-heartbeat"
                 " --fault can:5:param=0x6065=500")
    lines.append("wiring file: a [wiring] table (a test plan or a wiring-only file), see docs/sim.md")
    return "\n".join(lines)


def parse_args(argv):
    ap = argparse.ArgumentParser(prog="python -m motorjig.sim", description=__doc__.split("\n\n")[1],
                                 epilog=_fault_help(), formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--drivers", type=_drivers, default=_drivers("2,3"), metavar="IDS",
                    help="simulated driver ids, each optionally :v6 (default) or :v8, e.g. 2,3:v8 (default 2,3)")
    ap.add_argument("--jig-protocol", type=_protocol, default=6, metavar="{6,8}",
                    help="the jig's protocol parameter: 6 (Ver6, default) or 8 (Ver8)")
    ap.add_argument("--baud", type=int, default=115200, help="baud rate of both buses (default 115200)")
    ap.add_argument("--tcp-port", type=int, default=0, help="TCP port for socket:// (default: a free one)")
    ap.add_argument("--capture-port", type=int, default=0, metavar="N",
                    help="TCP port of the jig's capture stream, one reader at a time (default: a free one)")
    ap.add_argument("--can-nodes", type=_can_nodes, default=(), metavar="IDS",
                    help="add a CAN bus with simulated CiA 402 drives of these node ids (1..127), e.g. 5,6;"
                         " the jig's SLCAN port is then served too")
    ap.add_argument("--can-bitrate", type=_can_bitrate, default=500000, metavar="BPS",
                    help="the CAN bus's bitrate, one of the SLCAN rates (default 500000)")
    ap.add_argument("--slcan-port", type=int, default=0, metavar="N",
                    help="TCP port of the jig's SLCAN port, one host at a time (default: a free one)")
    for bus in sim_kinds.extra_buses():
        bus.add_arguments(ap)
    ap.add_argument("--no-demo", action="store_true", help="skip the scripted demo session")
    ap.add_argument("--no-pty", action="store_true",
                    help="create no pseudo-terminals (neither the PC side's nor the capture or SLCAN port's)")
    ap.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (default: run until Ctrl-C)")
    ap.add_argument("--wiring", metavar="FILE",
                    help="wire the jig's relays and inputs to a drive's I/O: a TOML file with a [wiring] table"
                         " (slave = N: a Plus-R drive of --drivers; node = N: a CiA 402 node of --can-nodes)")
    ap.add_argument("--slots", metavar="FILE",
                    help="wire a multi-up fixture: a slots file (jigctl test --slots), each slot's wiring to its "
                         "drive (its drives are added to --drivers / --can-nodes); not with --wiring")
    ap.add_argument("--fault", action="append", default=[], metavar="SPEC",
                    help="make a drive fail: [ID:]NAME[=VALUE], repeatable (the list below)")
    return ap.parse_args(argv)


def check_setup(args):
    """The wiring and the faults of the command line: (wiring or None, [(id, name, value)]).
    ValueError with a one-line message for the user."""
    wiring = None
    if getattr(args, "slots", None):
        if args.wiring:
            raise ValueError("--slots wires every slot's position: give it or --wiring, not both")
        wiring = slot_wirings(args)
    if args.wiring:
        try:
            wiring = load_wiring(args.wiring)
        except WiringError as exc:
            raise ValueError("--wiring: %s" % exc) from None
        if wiring.slave is not None and wiring.slave not in args.drivers:
            raise ValueError("--wiring: %s: wiring.slave %d is not one of the --drivers (%s)"
                             % (args.wiring, wiring.slave, ",".join(str(i) for i in args.drivers)))
        if wiring.node is not None and wiring.node not in args.can_nodes:
            raise ValueError("--wiring: %s: wiring.node %d is not one of the --can-nodes (%s)"
                             % (args.wiring, wiring.node, ",".join(str(i) for i in args.can_nodes) or "none"))
    faults = []
    for spec in args.fault:
        if spec.strip().startswith(CAN_FAULT_PREFIX):
            try:
                node, name, value = parse_can_fault(spec.strip())
            except ValueError as exc:
                raise ValueError("--fault %s: %s" % (spec, exc)) from None
            if not args.can_nodes:
                raise ValueError("--fault %s: a CAN fault needs --can-nodes" % spec)
            if node is not None and node not in args.can_nodes:
                raise ValueError("--fault %s: no CAN node %d (--can-nodes %s)"
                                 % (spec, node, ",".join(str(i) for i in args.can_nodes)))
            try:  # (without the node model, parse_can_fault returns None: its set_fault judges)
                sim_kinds.parse_can_fault(name[len(CAN_FAULT_PREFIX):], value)
            except ValueError as exc:
                raise ValueError("--fault %s: %s" % (spec, exc)) from None
            faults.append((node, name, value))
            continue
        try:
            slave, name, value = parse_fault_spec(spec)
        except ValueError as exc:
            raise ValueError("--fault %s: %s" % (spec, exc)) from None
        if slave is not None and slave not in args.drivers:
            raise ValueError("--fault %s: no driver %d (--drivers %s)"
                             % (spec, slave, ",".join(str(i) for i in args.drivers)))
        faults.append((slave, name, value))
    return wiring, faults


def slot_wirings(args):
    """The wirings of a slots file's slots, each to its slot's drive (added to --drivers or
    --can-nodes); ValueError with one sentence."""
    from ..wiring import load_slot_fixtures

    try:
        fixtures = load_slot_fixtures(args.slots)
    except WiringError as exc:
        raise ValueError("--slots: %s" % exc) from None
    for slave, node, _wiring in fixtures:
        if slave is not None and slave not in args.drivers:
            ver8 = args.drivers.ver8
            args.drivers = DriverSpec(tuple(args.drivers) + (slave,))
            args.drivers.ver8 = ver8
        if node is not None and node not in args.can_nodes:
            args.can_nodes = tuple(args.can_nodes) + (node,)
    return [w for _s, _n, w in fixtures if w is not None] or None


def describe_setup(sim, out=print):
    """Print the bench's wiring and the faults that are on."""
    if len(sim.wirings) > 1:
        for w in sim.wirings:
            out("  wiring (%s): %s" % (w.source, w.drive))
            for line in w.describe() or ["(no wires)"]:
                out("    " + line)
    elif sim.wiring is None:
        out("  wiring: none")
    else:
        if sim.wired_node is not None:
            out("  wiring (%s): CAN node %d (0x60FD inputs, 0x60FE:1 outputs)" % (sim.wiring.source, sim.wired_node))
        else:
            out("  wiring (%s): drive %d" % (sim.wiring.source, sim.wired_slave))
        for line in sim.wiring.describe() or ["(no wires)"]:
            out("    " + line)
    active = ["driver %d: %s" % (i, ", ".join(d.active_faults())) for i, d in sim.drivers.items() if d.active_faults()]
    for i, nd in sim.can_nodes.items():
        on = nd.active_faults() if hasattr(nd, "active_faults") else []
        if on:
            active.append("CAN node %d: %s" % (i, ", ".join(on)))
    out("  faults: %s" % ("; ".join(active) if active else "none"))


def demo(url, ids, out=print):
    """A session through the TCP port with ``motorjig.master.Master``: it finds every
    slave and its variant the way the vendor library does, then moves a drive."""
    from motorjig.errors import JigError
    from motorjig.master import Master

    with Master(url, timeout=0.3) as m:
        out("demo: scanning ids 0..15 (Ver6 GetCommandPos probe, then GetSlaveInfo in each slave's variant) ...")
        found = m.scan(range(16), timeout=0.05)
        for i, info in sorted(found.items()):
            what = "%s (type %d) %s" % (info.type_name, info.type, info.version) if info else "(no info)"
            out("  id %2d: Ver%d  %s" % (i, m.variants.get(i, 6), what))
        drivers = [i for i in found if i in ids]
        if not drivers:
            out("demo: no driver answered")
            return False
        d = drivers[0]
        try:
            m.servo_enable(d, True)
            out("demo: servo on id %d" % d)
            m.move_inc(d, 10000, 20000)
            out("demo: move id %d by 10000 pulses at 20000 pps" % d)
            for _ in range(8):
                time.sleep(0.15)
                st = m.get_all_status(d)
                out("  status: pos %6d  speed %6d pps  flags 0x%08X%s" % (
                    st.command_pos, st.actual_vel, int(st.axis), "  moving" if st.axis.motioning else ""))
                if not st.axis.motioning and st.command_pos == 10000:
                    break
        except JigError as exc:
            out("demo: %s" % exc)
            return False
        return True


def stop_all(procs):
    """Stop the other buses' children (each removes what it made when it gets SIGTERM)."""
    for proc in procs:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _terminate(*_args):
    raise KeyboardInterrupt  # SIGTERM ends the bench as Ctrl-C does: everything it started is stopped


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    signal.signal(signal.SIGTERM, _terminate)
    if args.baud not in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600):
        print("error: --baud must be one of 9600 19200 38400 57600 115200 230400 460800 921600", file=sys.stderr)
        return 2
    ports = (("--tcp-port", args.tcp_port), ("--capture-port", args.capture_port), ("--slcan-port", args.slcan_port))
    for name, value in ports:
        if not 0 <= value <= 65535:
            print("error: %s must be 0..65535" % name, file=sys.stderr)
            return 2
    for i, (name, value) in enumerate(ports):
        for other, value2 in ports[i + 1:]:
            if value and value == value2:
                print("error: %s and %s must differ" % (name, other), file=sys.stderr)
                return 2
    try:
        wiring, faults = check_setup(args)
    except ValueError as exc:
        print("error: %s" % exc, file=sys.stderr)
        return 2
    extra = []  # the other buses, each a child process with its banner
    for bus in sim_kinds.extra_buses():
        try:
            proc = bus.start(args)
        except ValueError as exc:
            stop_all(extra)
            print("error: %s" % exc, file=sys.stderr)
            return 2
        if proc is not None:
            extra.append(proc)
    bench = Bench(driver_ids=tuple(args.drivers), baud=args.baud, tcp_port=args.tcp_port, pty=not args.no_pty,
                  capture_port=args.capture_port, slcan_port=args.slcan_port,
                  jig_ver8=args.jig_protocol == 8, ver8_drivers=args.drivers.ver8, wiring=wiring, faults=faults,
                  can_nodes=args.can_nodes, can_bitrate=args.can_bitrate)
    try:
        bench.start()
    except (OSError, ValueError, ImportError) as exc:  # (ValueError: a bad $MOTORJIG_SIM_START_US, a CAN fault)
        bench.stop()
        stop_all(extra)
        print("error: cannot start the bench: %s" % exc, file=sys.stderr)
        return 1
    try:
        drivers = ", ".join("%d (Ver%d)" % (i, 8 if i in args.drivers.ver8 else 6) for i in args.drivers)
        print("MotorJig virtual bench: jig = slave 1 (protocol Ver%d), drivers %s, %d baud"
              % (args.jig_protocol, drivers, args.baud))
        describe_setup(bench.sim)
        if bench.pty_path:
            print("  pty: %s" % bench.pty_path)
        print("  tcp: %s" % bench.tcp_url)
        print("  capture: %s" % bench.capture_url)
        if bench.capture_pty_path:
            print("  capture pty: %s" % bench.capture_pty_path)
        if bench.slcan_url:
            print("  CAN bus: %d bit/s, CiA 402 nodes %s" % (args.can_bitrate, ", ".join(map(str, args.can_nodes))))
            print("  slcan: %s" % bench.slcan_url)
            if bench.slcan_pty_path:
                print("  slcan pty: %s" % bench.slcan_pty_path)
        for proc in extra:
            print("  %s" % proc.banner)
        sys.stdout.flush()
        if not args.no_demo:
            demo(bench.tcp_url, args.drivers)
        print("serving; Ctrl-C to stop" + (" (stopping after %g s)" % args.duration if args.duration else ""))
        sys.stdout.flush()
        if hasattr(signal, "SIGUSR1"):  # `kill -USR1`: the buses' wire time so far (make bench reads it)
            signal.signal(signal.SIGUSR1, lambda *_a: print(bus_time(bench.sim), flush=True))
        t_end = time.monotonic() + args.duration if args.duration else None
        while t_end is None or time.monotonic() < t_end:
            if bench.error is not None:
                print("error: simulation stopped: %s" % bench.error, file=sys.stderr)
                return 1
            for proc in extra:
                if proc.poll() is not None:
                    print("error: %s stopped: %s" % (proc.title, proc.stderr.read().strip() or "exit %d" % proc.returncode),
                          file=sys.stderr)
                    return 1
            time.sleep(0.1)
    except KeyboardInterrupt:
        print("stopped")
        print(bus_time(bench.sim))
    finally:
        bench.stop()
        stop_all(extra)
    return 0


def bus_time(sim):
    """The wire time of the buses over the bench's life (benchmarks read it for a bus's load)."""
    span = sim.clock.now - sim.t_started
    can = " can %.0f us," % sim.can_bus.busy_us if sim.can_bus is not None else ""
    return "bus time: rs485 %.0f us,%s over %.0f us" % (sim.down_bus.busy_us, can, span)


if __name__ == "__main__":
    sys.exit(main())
