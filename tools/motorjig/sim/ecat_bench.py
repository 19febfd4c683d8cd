"""The bench's EtherCAT bus as a program: simulated CiA 402 servos behind a network interface a master opens.

    python -m motorjig.sim.ecat_bench [--slaves N] [--fault [POS:]NAME[=VALUE]] [--capture FILE] [--tag TAG]

makes a network namespace with a veth pair (``ecat_bus.Wire``), puts N simulated servos
(``ecat_servo.EcatServo``) in a line on its inner end, prints the interface a master opens
(``EtherCAT bench: ... interface mjm1234``), and answers frames until Ctrl-C or SIGTERM, then
removes the namespace. ``--capture FILE`` records every frame, the master's and the one that
came back, in a pcapng file Wireshark decodes as EtherCAT with CoE. ``python -m motorjig.sim --ecat-slaves N`` starts it beside the jig's
bench. It needs root; without root it says so in one sentence and exits 2.
"""

import argparse
import gc
import os
import signal
import sys
import time

from motorjig.capture import pcapng

from .clock import PacedClock
from .ecat_bus import Segment, Wire
from .ecat_servo import FAULTS, EcatServo

MAX_SLAVES = 64
RT_PRIORITY = 50  # above a master's cycle (40): SOEM spins while it waits for the frame back, and the slaves stand for hardware that never waits


def parse_fault(spec, slaves):
    """``[POS:]NAME[=VALUE]`` -> (positions, name, value); POS is the slave's position from 0 (all
    slaves without it). ValueError with the reason."""
    head, eq, value = spec.strip().partition("=")
    pos, colon, name = head.partition(":")
    if not colon:
        positions, name = list(range(slaves)), head
    else:
        try:
            p = int(pos)
        except ValueError:
            raise ValueError("expected [POS:]NAME[=VALUE], e.g. 0:following-error=20000; %r is not a slave "
                             "position" % pos) from None
        if not 0 <= p < slaves:
            raise ValueError("slave position %d is not on the bus (0..%d)" % (p, slaves - 1))
        positions = [p]
    name = name.strip()
    FAULTS.parse(name, value.strip() if eq else None)
    return positions, name, value.strip() if eq else None


def command(servos, line, out=sys.stdout, segment=None):
    """One line of the bench's control channel (``--control``): ``fault [POS:]NAME[=VALUE]``,
    ``clear [POS]``, ``state [POS]``, ``power-cycle [POS]``; the answer is one line, ``ok ...`` or ``error ...``."""
    word, _, rest = line.strip().partition(" ")
    try:
        if word == "fault":
            positions, name, value = parse_fault(rest, len(servos))
            for p in positions:
                servos[p].set_fault(name, value)
            said = "ok %s on %s" % (name, ", ".join(str(p) for p in positions))
        elif word in ("clear", "state", "power-cycle"):
            positions = [int(rest)] if rest.strip() else list(range(len(servos)))
            for p in positions:
                if word == "clear":
                    servos[p].clear_faults()
                elif word == "power-cycle":
                    servos[p].power_on()
            said = "ok " + "; ".join("%d: AL 0x%02X, %s, velocity %d, faults %s" % (
                p, servos[p].esc.u16(0x0130), servos[p].state, servos[p].velocity_actual(),
                ",".join(servos[p].active_faults()) or "none") for p in positions)
            if word == "state" and segment is not None:
                said += "; bus: " + segment.turnaround_text()
        else:
            said = "error unknown command %r (fault, clear, state, power-cycle)" % word
    except (ValueError, IndexError) as exc:
        said = "error %s" % exc
    print(said, file=out, flush=True)


class Capture:
    """The bus's frames in a pcapng file (``pcapng.ethernet_*``), each written as it passes."""

    def __init__(self, path, ifname, slaves):
        self.f = open(path, "wb")
        self.f.write(pcapng.section_header("MotorJig EtherCAT bench") + pcapng.ethernet_interface(
            ifname, "EtherCAT bench: %d simulated servos" % slaves))
        self.frames = 0

    def __call__(self, request, reply):
        t = int(time.time() * 1e6)
        self.f.write(pcapng.ethernet_packet(0, t, request, 2))
        if reply is not None:
            self.f.write(pcapng.ethernet_packet(0, t, reply, 1))
        self.frames += 1
        if self.frames % 100 == 0:
            self.f.flush()

    def close(self):
        self.f.close()


def _realtime():
    """This process on SCHED_FIFO when allowed (root): the slaves answer each frame at once, as
    hardware does, however busy the machine is (a master's 1 ms cycle waits for them)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RT_PRIORITY))
        return True
    except (AttributeError, PermissionError, OSError):
        return False


def build(clock, slaves):
    """The servos in line order, each slave's clock offset by its own power-up time."""
    return [EcatServo(clock, n, clock_offset_ns=(n + 1) * 1234567) for n in range(slaves)]


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m motorjig.sim.ecat_bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--slaves", type=int, default=2, help="simulated servos on the line (1..%d, default 2)" % MAX_SLAVES)
    ap.add_argument("--fault", action="append", default=[], metavar="[POS:]NAME[=VALUE]",
                    help="make a servo fail (all servos without POS): " + ", ".join(FAULTS))
    ap.add_argument("--capture", metavar="FILE", help="record the bus's frames in this pcapng file (Wireshark)")
    ap.add_argument("--tag", help="the namespace's and interfaces' suffix (default: this process id)")
    ap.add_argument("--control", action="store_true",
                    help="read commands on stdin (fault [POS:]NAME[=VALUE], clear [POS], state [POS], power-cycle [POS]): for tests")
    args = ap.parse_args(argv)
    if not 1 <= args.slaves <= MAX_SLAVES:
        print("ecat_bench: --slaves must be 1..%d, got %d" % (MAX_SLAVES, args.slaves), file=sys.stderr)
        return 2
    try:
        faults = [parse_fault(f, args.slaves) for f in args.fault]
    except ValueError as exc:
        print("ecat_bench: --fault: %s" % exc, file=sys.stderr)
        return 2
    why = Wire.check_permissions()
    if why:
        print("ecat_bench: %s." % why, file=sys.stderr)
        return 2
    realtime = _realtime()
    clock = PacedClock()
    servos = build(clock, args.slaves)
    for positions, name, value in faults:
        for p in positions:
            servos[p].set_fault(name, value)
    gc.freeze()  # the models built: collections stay short while frames wait for an answer
    wire = Wire(args.tag)
    try:
        wire.create()
    except OSError as exc:
        print("ecat_bench: cannot make the EtherCAT wire: %s" % exc, file=sys.stderr)
        return 3
    capture = None
    if args.capture:
        try:
            capture = Capture(args.capture, wire.master_ifname, len(servos))
        except OSError as exc:
            wire.remove()
            print("ecat_bench: --capture: cannot write %s: %s" % (args.capture, exc.strerror or exc), file=sys.stderr)
            return 2
    stopping = []
    signal.signal(signal.SIGTERM, lambda *_a: stopping.append(1))
    try:
        print("EtherCAT bench: %d simulated servo%s (%s) on interface %s (namespace %s%s); Ctrl-C stops" % (
            len(servos), "" if len(servos) == 1 else "s", servos[0].name, wire.master_ifname, wire.netns,
            ", real-time priority" if realtime else ""), flush=True)
        segment = Segment(servos)
        control = (sys.stdin, lambda line: command(servos, line, segment=segment)) if args.control else None
        wire.serve(segment, clock, stop=lambda: bool(stopping), control=control, on_frame=capture)
    except KeyboardInterrupt:
        pass
    finally:
        wire.remove()
        if capture is not None:
            capture.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
