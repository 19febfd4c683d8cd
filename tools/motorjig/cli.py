"""jigctl: the command line for the MotorJig bus (scan, status, moves, parameters, monitor...).

This module is the command line itself: argument types, the parser with a
``--help`` for every subcommand, and ``main``, which runs ``motorjig.commands``
and turns every failure into one sentence on stderr and a non-zero exit status,
never a traceback:

    0 ok, 1 test/motion failure, 2 bad input, 3 port problem, 4 no/bad reply,
    5 the slave refused (error status), 130 interrupted.

Output is text for people, or one JSON document (``--json``; JSON lines for the
repeating ``status --watch`` and ``monitor``).
"""

import argparse
import os
import sys

import serial

from jig import frame as F

from motorjig.commands import (EXIT_COMM, EXIT_FAIL, EXIT_INTERRUPT, EXIT_OK, EXIT_PORT, EXIT_STATUS,
                               EXIT_USAGE, UsageError, fail, cmd_alarm_reset, cmd_crashlog, cmd_estop,
                               cmd_info, cmd_io,
                               cmd_monitor, cmd_motion_test, cmd_move, cmd_param, cmd_ports, cmd_raw, cmd_scan,
                               cmd_servo, cmd_stats, cmd_status, cmd_stop)
from motorjig.errors import CommError, JigError, PortError, StatusError
from motorjig.master import BAUD_RATES, DEFAULT_BAUD

MAX_SPEED = 2500000  # pps, the drives' speed parameter limit


# --- argument types --------------------------------------------------------------
def number(text):
    try:
        return int(str(text).replace("_", ""), 0)
    except ValueError:
        raise argparse.ArgumentTypeError("%r is not a number" % text) from None


def seconds(text):
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError("%r is not a number of seconds" % text) from None
    if v < 0:
        raise argparse.ArgumentTypeError("a time cannot be negative")
    return v


def speed(text):
    v = number(text)
    if not 1 <= v <= MAX_SPEED:
        raise argparse.ArgumentTypeError("speed must be 1..%d pps, not %d" % (MAX_SPEED, v))
    return v


def position(text):
    v = number(text)
    if not -0x80000000 <= v <= 0x7FFFFFFF:
        raise argparse.ArgumentTypeError("%d does not fit a 32-bit position" % v)
    return v


def direction(text):
    t = text.lower()
    if t in ("+", "plus", "pos", "cw", "1"):
        return 1
    if t in ("-", "minus", "neg", "ccw", "0"):
        return 0
    raise argparse.ArgumentTypeError("direction must be + or -, not %r" % text)

# --- argument parser -------------------------------------------------------------
def _env_int(name, default):
    v = os.environ.get(name)
    try:
        return int(v, 0) if v else default
    except ValueError:
        return default


def _global_options(p, suppress):
    d = (lambda v: argparse.SUPPRESS) if suppress else (lambda v: v)
    g = p.add_argument_group("connection and output (may also come before the subcommand)")
    g.add_argument("--port", "-p", default=d(os.environ.get("JIGCTL_PORT")),
                   help="serial port or pyserial URL, e.g. /dev/ttyUSB0, COM7, socket://127.0.0.1:5000 "
                        "(default: $JIGCTL_PORT)")
    g.add_argument("--baud", "-b", type=number, default=d(_env_int("JIGCTL_BAUD", DEFAULT_BAUD)),
                   help="baud rate, one of %s (default %d)" % (", ".join(map(str, BAUD_RATES)), DEFAULT_BAUD))
    g.add_argument("--slave", "-s", type=number, default=d(_env_int("JIGCTL_SLAVE", 2)),
                   help="slave id 0..15 to talk to (default: $JIGCTL_SLAVE or 2, the first driver; the jig is 1)")
    g.add_argument("--jig-id", type=number, default=d(1), help="slave id of the jig itself (default 1)")
    g.add_argument("--timeout", "-t", type=number, default=d(100),
                   help="reply timeout in ms (default 100, longer for slow frames)")
    g.add_argument("--retries", type=number, default=d(2),
                   help="re-sends of a failed request that is safe to repeat (default 2)")
    g.add_argument("--ver8", action="store_true", default=d(False),
                   help="use Ver8 framing (sync number) for every slave, no detection")
    g.add_argument("--ver6", action="store_true", default=d(False),
                   help="use Ver6 framing for every slave, no detection (default: each slave's variant is "
                        "detected at first contact, as the vendor library does)")
    g.add_argument("--echo", action="store_true", default=d(False),
                   help="the adapter hears its own transmissions: skip the copy of each request")
    g.add_argument("--json", action="store_true", default=d(False), help="machine-readable JSON output")
    g.add_argument("--verbose", "-v", action="store_true", default=d(False),
                   help="show every frame sent and received on stderr")


def _version():
    try:
        from importlib.metadata import version

        return version("motorjig")
    except Exception:  # not installed (running from the source tree)
        return "unknown"


def build_parser():
    p = argparse.ArgumentParser(
        prog="jigctl",
        description="Talk to the MotorJig bus: the jig (slave 1) and FASTECH Plus-R drives behind it.",
        epilog="exit status: 0 ok, 1 test failed, 2 bad input, 3 port problem, 4 no reply, 5 slave refused")
    _global_options(p, False)
    p.add_argument("--version", action="version", version="jigctl (motorjig) %s" % _version())
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    def add(name, fn, help_text):
        sp = sub.add_parser(name, help=help_text, description=help_text)
        _global_options(sp, True)
        sp.set_defaults(fn=fn)
        return sp

    add("ports", cmd_ports, "list the serial ports of this computer")
    sp = add("scan", cmd_scan, "find the slaves on the bus and their protocol variant (Ver6/Ver8)")
    sp.add_argument("--first", type=number, default=0, help="first id (default 0)")
    sp.add_argument("--last", type=number, default=F.MAX_SLAVE_ID, help="last id (default 15)")
    sp.add_argument("--via-jig", action="store_true",
                    help="let the jig scan its driver bus (frames 0xF2/0xF3) instead of probing from here")
    add("info", cmd_info, "slave type, firmware version, motor, alarm and position of --slave")
    sp = add("status", cmd_status, "decoded axis flags, positions, velocity and I/O of --slave")
    sp.add_argument("--watch", "-w", action="store_true", help="refresh in place until Ctrl-C (or --count)")
    sp.add_argument("--interval", type=seconds, default=0.2, help="seconds between refreshes (default 0.2)")
    sp.add_argument("--count", "-n", type=number, help="stop after this many readings")

    sp = add("move", cmd_move, "start a move: abs, inc, jog, home, limit")
    msub = sp.add_subparsers(dest="kind", metavar="KIND")
    msub.required = True

    def add_move(name, help_text, speed_arg=True):
        mp = msub.add_parser(name, help=help_text, description=help_text)
        _global_options(mp, True)
        if speed_arg:
            mp.add_argument("--speed", type=speed, default=5000, help="speed in pps (default 5000)")
        mp.add_argument("--wait", action="store_true", help="wait until the axis stops")
        mp.add_argument("--wait-timeout", type=seconds, default=60.0, help="give up waiting after this (s)")
        return mp

    add_move("abs", "move to an absolute position (pulses)").add_argument("position", type=position)
    add_move("inc", "move by a distance (pulses, may be negative)").add_argument("distance", type=position)
    mp = add_move("jog", "run at --speed in a direction until `jigctl stop` (or --for)")
    mp.add_argument("direction", type=direction, help="+ or -")
    mp.add_argument("--for", dest="duration", type=seconds, help="stop after this many seconds")
    add_move("home", "origin search (homing per the drive's parameters 17-24)", speed_arg=False)
    mp = add_move("limit", "run to a limit sensor")
    mp.add_argument("direction", type=direction, help="+ or -")

    sp = add("stop", cmd_stop, "decelerating stop")
    sp.add_argument("--all", action="store_true", help="broadcast to every slave")
    sp = add("estop", cmd_estop, "emergency (immediate) stop")
    sp.add_argument("--all", action="store_true", help="broadcast to every slave")
    sp = add("servo", cmd_servo, "switch the drive on or off (Ezi-STEP: energise the motor)")
    sp.add_argument("state", choices=("on", "off"))
    sp = add("alarm-reset", cmd_alarm_reset, "clear the drive's alarm")
    sp.add_argument("--kind", choices=("auto", "step", "servo"), default="auto",
                    help="reset method; auto asks the slave type (default)")

    sp = add("param", cmd_param, "read, write, save and list parameters (Ezi-STEP table, or the jig's with --slave 1)")
    psub = sp.add_subparsers(dest="action", metavar="ACTION")
    psub.required = True

    def add_param(name, help_text):
        pp = psub.add_parser(name, help=help_text, description=help_text)
        _global_options(pp, True)
        pp.add_argument("--jig", action="store_true", help="use the jig's parameter table")
        return pp

    pp = add_param("get", "read one parameter (number or name)")
    pp.add_argument("param")
    pp.add_argument("--rom", action="store_true", help="read the value stored in ROM")
    pp = add_param("set", "write one parameter to RAM (range-checked first)")
    pp.add_argument("param")
    pp.add_argument("value", type=number)
    add_param("save", "SaveAllParameters: keep the RAM values after power-off")
    pp = add_param("list", "all parameters with names, units, ranges and current values")
    pp.add_argument("--offline", action="store_true", help="only the table, do not read the slave")
    pp = add_param("dump", "every parameter of the drive into a parameter-set file (the format of a plan's golden set)")
    pp.add_argument("file", nargs="?", help="file to write (default or '-': standard output)")
    pp.add_argument("--rom", action="store_true", help="the values stored in ROM instead of RAM")
    pp = add_param("load", "write a parameter-set file's values to the drive's RAM (range-checked first)")
    pp.add_argument("file")
    pp.add_argument("--save", action="store_true", help="then SaveAllParameters (ROM)")

    sp = add("io", cmd_io, "show or set I/O: io [show] | io out --set B --clear B | io in ... | io map PIN [MASK LEVEL]")
    sp.add_argument("action", nargs="?", choices=("show", "out", "in", "map", "read-rom"))
    sp.add_argument("pin", nargs="?", type=number, help="pin index (io map)")
    sp.add_argument("mask", nargs="?", type=number, help="logic bit mask to assign (io map)")
    sp.add_argument("level", nargs="?", type=number, help="0 low active, 1 high active (io map)")
    sp.add_argument("--set", help="bits to switch on: a number or names like user_out0,brake")
    sp.add_argument("--clear", help="bits to switch off")

    sp = add("raw", cmd_raw, "send one frame given in hex (ID TYPE DATA...) and show the decoded reply")
    sp.add_argument("hex", nargs="+", help="e.g. 02 40 (GetAxisStatus to slave 2); with --no-crc the full wire bytes")
    sp.add_argument("--no-crc", action="store_true",
                    help="send the bytes exactly as typed (no header, CRC or stuffing added)")
    sp = add("monitor", cmd_monitor, "live decoded view of every frame on the line, logged to a file")
    sp.add_argument("--duration", type=seconds, help="stop after this many seconds (default: until Ctrl-C)")
    sp.add_argument("--log", help="log file (default jigctl-monitor-DATE-TIME.log; '-' for none)")
    sp = add("motion-test", cmd_motion_test, "repeated +/- moves with a pass/fail summary")
    sp.add_argument("--cycles", type=number, default=5, help="number of out-and-back cycles (default 5)")
    sp.add_argument("--distance", type=position, default=10000, help="pulses per move (default 10000)")
    sp.add_argument("--speed", type=speed, default=20000, help="pps (default 20000)")
    sp.add_argument("--move-timeout", type=seconds, default=30.0, help="seconds one move may take (default 30)")
    sp.add_argument("--servo-on", action="store_true", help="switch the drive on first")
    sp.add_argument("--stop-on-fail", action="store_true", help="stop at the first failed move")
    sp = add("stats", cmd_stats, "the jig's own counters (frames, errors, turnaround)")
    sp.add_argument("--reset", action="store_true", help="reset the counters after reading them")
    add("crashlog", cmd_crashlog, "the jig's crash summary (crash counts and the last exception)")
    sp = add("test", cmd_test, "run a test plan (MotorJig Station): records, JUnit XML, HTML report; "
                               "exit 0 pass, 1 fail, 2 error")
    from motorjig.testcmd import add_test_arguments

    add_test_arguments(sp)
    from motorjig.resultscmd import add_results_arguments, cmd_results

    sp = add("results", cmd_results, "the results database of the test runs: list, show, yield, stats, export")
    add_results_arguments(sp)
    sp = add("capture", cmd_capture, "record both buses through the jig (--jig CAPTURE_PORT) or one bus through a "
                                     "listen-only adapter (--sniff PORT) to pcapng for Wireshark, with a live line "
                                     "per frame; install the dissector and the extcaps")
    from motorjig.capture.capturecmd import add_capture_arguments

    add_capture_arguments(sp)
    sp = add("can", cmd_can, "CANopen through the jig's SLCAN port (python-can, python-canopen): scan, nmt, "
                             "sdo read/write, dump, lss")
    from motorjig.can.cancmd import add_can_arguments

    add_can_arguments(sp, lambda p: _global_options(p, True))
    sp = add("ecat", cmd_ecat, "an EtherCAT line from this PC's network interface (SOEM): scan, state, sdo "
                               "read/write, pdo, dump (root)")
    from motorjig.ecat.ecatcmd import add_ecat_arguments

    add_ecat_arguments(sp)
    sp = add("gui", cmd_gui, "MotorJig Desk: the bench program as a local web page (prints its URL)")
    from motorjig.desk.server import add_gui_arguments

    add_gui_arguments(sp)
    return p


def cmd_test(args):
    from motorjig.testcmd import cmd_test as run

    return run(args)


def cmd_capture(args):
    from motorjig.capture.capturecmd import cmd_capture as run

    return run(args)


def cmd_can(args):
    from motorjig.can.cancmd import cmd_can as run

    return run(args)


def cmd_ecat(args):
    from motorjig.ecat.ecatcmd import cmd_ecat as run

    return run(args)


def cmd_gui(args):
    """Serve the page until Ctrl-C (the web parts are imported only here)."""
    from motorjig.desk.server import serve

    return serve(args)


def _validate(args):
    if args.baud not in BAUD_RATES:
        raise UsageError("baud rate %d is not one the drives support (%s)" % (args.baud, ", ".join(map(str, BAUD_RATES))))
    if not 0 <= args.slave <= F.MAX_SLAVE_ID:
        raise UsageError("slave id must be 0..%d, not %d" % (F.MAX_SLAVE_ID, args.slave))
    if not 0 <= args.jig_id <= F.MAX_SLAVE_ID:
        raise UsageError("jig id must be 0..%d, not %d" % (F.MAX_SLAVE_ID, args.jig_id))
    if not 1 <= args.timeout <= 60000:
        raise UsageError("timeout must be 1..60000 ms, not %d" % args.timeout)
    if not 0 <= args.retries <= 10:
        raise UsageError("retries must be 0..10, not %d" % args.retries)
    if args.ver8 and args.ver6:
        raise UsageError("--ver6 and --ver8 exclude each other (give neither to detect each slave's variant)")

def main(argv=None):
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse already printed usage + the error, or --help
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    try:
        _validate(args)
        return args.fn(args)
    except UsageError as exc:
        return fail(EXIT_USAGE, str(exc))
    except PortError as exc:
        return fail(EXIT_PORT, str(exc))
    except CommError as exc:
        return fail(EXIT_COMM, str(exc) + " (check --port, --baud and --slave)")
    except StatusError as exc:
        return fail(EXIT_STATUS, str(exc))
    except JigError as exc:
        return fail(EXIT_FAIL, str(exc))
    except ValueError as exc:
        return fail(EXIT_USAGE, str(exc))
    except BrokenPipeError:  # output piped into e.g. `head`, which has exited
        try:
            sys.stdout = open(os.devnull, "w")
        except OSError:
            pass
        return EXIT_OK
    except (serial.SerialException, OSError) as exc:
        return fail(EXIT_PORT, "port error: %s" % exc)
    except KeyboardInterrupt:
        sys.stderr.write("\ninterrupted\n")
        return EXIT_INTERRUPT
    except Exception as exc:  # a bug: still one sentence, the traceback only with -v
        if getattr(args, "verbose", False):
            import traceback

            traceback.print_exc()
        return fail(70, "internal error (%s: %s); run with -v for details" % (type(exc).__name__, exc))


def run():
    sys.exit(main())


if __name__ == "__main__":
    run()
