"""jigctl capture: record a Plus-R bus to pcapng for Wireshark, with a live line per frame.

    jigctl capture --sniff /dev/ttyUSB1 [-w bus.pcapng [--max-size 10M --files 5]] [--bus pc]
    jigctl capture --sniff /dev/ttyUSB1 -w - | wireshark -k -i -
    jigctl capture --jig /dev/ttyACM1 -w both.pcapng   # the jig's own recording of both buses
    jigctl capture --install-dissector      # plusr.lua into Wireshark's personal plugin folder
    jigctl capture --install-extcap         # the motorjig-sniff and motorjig-jig interfaces

``--sniff`` listens through a listen-only USB-RS-485 adapter (or any pyserial URL)
and frames what it hears with the firmware's parser; ``--jig`` reads the jig's own
record stream from its capture port (both Plus-R buses and, when the jig has a CAN
port, the CAN bus; directions, the jig's µs clock, ``jigport``; ``--bus`` keeps some
of them). Either way every frame, dropped fragment and run of noise becomes a
pcapng packet with the parser's verdict in its comment. The live view goes to
standard output (standard error when that carries the pcapng; ``-q`` switches it
off); ``--json`` prints it as JSON lines.
"""

import contextlib
import json
import math
import os
import signal
import sys

from motorjig.capture import install, pcapng
from motorjig.capture import record as R
from motorjig.capture.jigport import HELLO_WAIT_S, JigCapture
from motorjig.capture.sniff import DEFAULT_INTERBYTE_MS, Sniffer, open_port
from motorjig.capture.textview import TextView
from motorjig.commands import EXIT_OK, UsageError
from motorjig.errors import JigError, PortError

_UNITS = {"": 1, "k": 1000, "m": 1000 ** 2, "g": 1000 ** 3}


def size(text):
    """'500k', '10M', '1G' or a number of bytes (k = 1000 bytes, as dumpcap counts)."""
    t = str(text).strip().lower().rstrip("b")
    unit = t[-1:] if t[-1:] in _UNITS and t[-1:] else ""
    try:
        value = float(t[:-1] if unit else t) * _UNITS[unit]
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise UsageError("%r is not a size (give bytes, or a number with k, M or G)" % text)
    if value < 1024:
        raise UsageError("--max-size must be at least 1024 bytes, not %r" % text)
    return int(value)


SHARED_OPTIONS = (
    "Of the connection options: --baud is the adapter's baud rate with --sniff (with --jig the jig's hello "
    "gives both buses' bauds); --ver6 / --ver8 read every frame in that variant (default: each frame's "
    "variant is told from the frame itself); --json prints the live view as JSON lines. --port, --slave, "
    "--jig-id, --timeout, --retries, --echo and --verbose are for the commands that talk on the bus: a capture "
    "only listens.")


def add_capture_arguments(sp):
    sp.epilog = SHARED_OPTIONS
    src = sp.add_argument_group("what to capture (one of --sniff, --jig)")
    src.add_argument("--sniff", metavar="PORT",
                     help="listen on a Plus-R bus through this listen-only adapter (/dev/ttyUSB1, COM7) or "
                          "pyserial URL (socket://host:port); --baud sets its baud rate")
    src.add_argument("--jig", metavar="PORT",
                     help="the jig's own recording of both buses (and of the CAN bus when the jig has a CAN "
                          "port), from its capture port (the board's second USB port, /dev/ttyACM1) or a pyserial "
                          "URL (socket://127.0.0.1:N on the virtual bench): directions and the jig's microsecond "
                          "clock; the bauds and the CAN bitrate come from the jig")
    src.add_argument("--bus", default=None, metavar="BUS",
                     help="with --sniff: which bus the adapter listens on, pc or drivers, names the pcapng interface "
                          "(default pc); with --jig: the buses to keep in the view and the file, comma-separated "
                          "from pc, drivers, can (default all; the jig's lost-records reports are always kept)")
    src.add_argument("--interbyte-timeout", type=float, default=None, metavar="MS",
                     help="with --sniff: silence inside a frame that drops it, in ms (default %g: longer than a USB "
                          "adapter's usual hold-back; the jig itself uses 5)" % DEFAULT_INTERBYTE_MS)
    src.add_argument("--duration", type=float, metavar="S", help="stop after this many seconds (default: Ctrl-C, SIGTERM or SIGHUP, which end it "
                          "alike: X to the jig, the file closed, the summary; with --jig before the hello: "
                          "'stopped before the jig answered', exit 0)")
    src.add_argument("--count", type=int, metavar="N",
                     help="stop after N records (frames, fragments, noise; with --jig also lost-records reports)")
    out = sp.add_argument_group("output")
    out.add_argument("-w", "--write", metavar="FILE",
                     help="write pcapng to FILE, or '-' for standard output (for wireshark -k -i -)")
    out.add_argument("--max-size", type=str, metavar="SIZE",
                     help="with -w FILE: start a new file when one reaches SIZE (bytes, or 500k, 10M, 1G); "
                          "-w bus.pcapng then writes bus_00001_<time>.pcapng, bus_00002_<time>.pcapng, ... as dumpcap "
                          "does (numbers go on after the highest already there)")
    out.add_argument("--files", type=int, metavar="N", help="with --max-size: keep only the newest N files")
    out.add_argument("--quiet", "-q", action="store_true", help="no live view, only the summary at the end")
    inst = sp.add_argument_group("Wireshark set-up")
    inst.add_argument("--install-dissector", action="store_true",
                      help="copy the Plus-R dissector into Wireshark's personal Lua plugin folder and say where")
    inst.add_argument("--install-extcap", action="store_true",
                      help="install the capture interfaces motorjig-sniff (an adapter) and motorjig-jig (the jig's "
                           "recording) for Wireshark and tshark and say where")


def _install(args):
    folders = install.wireshark_folders()
    lines = []
    if args.install_dissector:
        try:
            path = install.install_dissector(folders)
        except OSError as exc:
            raise UsageError("cannot install the dissector: %s" % exc) from None
        lines.append("dissector installed: %s (restart Wireshark, or Analyze > Reload Lua Plugins)" % path)
    if args.install_extcap:
        try:
            written = install.install_extcap(folders)
        except OSError as exc:
            raise UsageError("cannot install the extcap: %s" % exc) from None
        for path, why in written:
            lines.append("extcap installed: %s (%s)" % (path, why))
        for name in install.EXTCAP_NAMES:
            lines.append("capture interface: %s (tshark -D lists it; in tshark: -i %s -o extcap.%s.port:PORT)"
                         % (name, name, name.replace("-", "_")))
    if not folders:
        lines.append("(tshark was not found: installed into the default folders of Wireshark 4.2 and later)")
    print("\n".join(lines))
    return EXIT_OK


def _check(args):
    if args.sniff is None and args.jig is None:
        raise UsageError("give --sniff PORT (a listen-only adapter on the bus) or --jig PORT (the jig's capture "
                         "port), or --install-dissector / --install-extcap")
    if args.sniff is not None and args.jig is not None:
        raise UsageError("give --sniff PORT or --jig PORT, not both (one capture at a time)")
    args.keep = None
    if args.jig is not None:
        if args.interbyte_timeout is not None:
            raise UsageError("--interbyte-timeout is for --sniff: the jig records its buses with its own parser")
        if args.bus is not None:
            args.keep = _bus_filter(args.bus)
    elif args.bus is not None and args.bus not in R.BUS_NAMES:
        raise UsageError("--bus must be pc or drivers with --sniff, not %r (can is the jig's: --jig)" % args.bus)
    if args.bus is None or args.jig is not None:
        args.bus = "pc"
    if args.interbyte_timeout is None:
        args.interbyte_timeout = DEFAULT_INTERBYTE_MS
    if args.max_size is not None:
        args.max_size = size(args.max_size)
        if args.write in (None, "-"):
            raise UsageError("--max-size needs -w FILE (a file to rotate)")
    if args.files is not None:
        if args.max_size is None:
            raise UsageError("--files needs --max-size")
        if args.files < 1:
            raise UsageError("--files must be at least 1, not %d" % args.files)
    if not math.isfinite(args.interbyte_timeout):
        raise UsageError("--interbyte-timeout must be a finite number of ms, not %r" % args.interbyte_timeout)
    if args.interbyte_timeout <= 0:
        raise UsageError("--interbyte-timeout must be more than 0 ms")
    if args.duration is not None and not math.isfinite(args.duration):
        raise UsageError("--duration must be a finite number of seconds, not %r" % args.duration)
    if args.duration is not None and args.duration < 0:
        raise UsageError("--duration cannot be negative")
    if args.count is not None and args.count < 1:
        raise UsageError("--count must be at least 1")


def _bus_filter(text):
    """--bus with --jig: 'pc,can' -> the Record.bus indices to keep."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    bad = [n for n in names if n not in R.JIG_BUS_NAMES]
    if bad or not names:
        raise UsageError("--bus takes pc, drivers or can (comma-separated) with --jig, not %r" % text)
    return frozenset(R.JIG_BUS_NAMES.index(n) for n in names)


def _check_output(args):
    """A -w FILE that cannot be written fails before the port is asked anything (the
    jig's recording is started only when the output can take it)."""
    if args.write in (None, "-"):
        return
    path = os.path.abspath(args.write)
    folder = os.path.dirname(path)
    if not os.path.isdir(folder):
        raise UsageError("cannot write %s: No such file or directory" % args.write)
    if os.path.isdir(path):
        raise UsageError("cannot write %s: Is a directory" % args.write)
    if not os.access(folder, os.W_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
        raise UsageError("cannot write %s: Permission denied" % args.write)


def _open_writer(args, buses, hardware=None):
    if args.write is None:
        return None
    if args.write == "-":
        return pcapng.Writer(sys.stdout.buffer, buses, flush_each=True, hardware=hardware)
    try:
        if args.max_size is not None:
            return pcapng.RotatingWriter(args.write, buses, args.max_size, args.files, hardware=hardware)
        return pcapng.Writer(open(args.write, "wb"), buses, hardware=hardware)
    except OSError as exc:
        raise UsageError("cannot write %s: %s" % (args.write, exc.strerror)) from None


class _Sinks:
    """The writer, the live view and the verdict counts of one capture."""

    def __init__(self, args, buses, writer, forced):
        self.args = args
        self.writer = writer
        self.counts = {}
        self.view = TextView(buses, forced)
        self.shown = None if args.quiet else (sys.stderr if args.write == "-" else sys.stdout)
        self.sinks = ([self.write] if writer is not None else []) + [self.show]

    def write(self, rec):
        try:
            self.writer.write(rec)
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise OutputError(_output_name(self.args, self.writer), exc) from None

    def show(self, rec):
        name = "can" if rec.is_can else R.verdict_name(rec.verdict)
        self.counts[name] = self.counts.get(name, 0) + 1
        if self.shown is not None:
            d = self.view.as_dict(rec)
            self.shown.write((json.dumps(d) if self.args.json else self.view.line(rec, d)) + "\n")
            self.shown.flush()

    def banner(self, text):
        if self.shown is not None and not self.args.json:
            sys.stderr.write("capturing %s%s; Ctrl-C ends\n" % (text, "" if self.args.write is None else (
                ", pcapng to %s" % ("standard output" if self.args.write == "-" else self.args.write))))


class OutputError(PortError):
    """Writing the pcapng failed (a full disk, an I/O error): not the port's fault."""

    def __init__(self, name, exc):
        super().__init__("writing %s failed: %s" % (name, exc.strerror or exc))


def _output_name(args, writer):
    if args.write == "-":
        return "standard output"
    if isinstance(writer, pcapng.RotatingWriter):
        return writer.current
    return args.write


def _close_writer(args, writer, quiet=False):
    """Flush (-w -) or close the output; a failure is an OutputError unless ``quiet``
    (the capture already failed, or the reader went away)."""
    if writer is None:
        return
    try:
        writer.flush() if args.write == "-" else writer.close()
    except BrokenPipeError:
        pass
    except OSError as exc:
        if isinstance(writer, pcapng.Writer) and args.write != "-":
            try:  # the buffer could not be written: drop it, or a second close tries again
                writer.stream.close()
            except OSError:
                pass
        if not quiet:
            raise OutputError(_output_name(args, writer), exc) from None


@contextlib.contextmanager
def _signals_as_ctrl_c():
    """SIGTERM (``timeout``, a service manager) and SIGHUP (a closed terminal) end the
    capture as Ctrl-C does: X to the jig, the file closed, the summary. Once: a second
    signal during the clean-up is ignored."""
    state = {"fired": False}

    def handler(signum, frame):
        if not state["fired"]:
            state["fired"] = True
            raise KeyboardInterrupt

    old = {}
    for name in ("SIGTERM", "SIGHUP"):
        sig = getattr(signal, name, None)
        if sig is None:
            continue
        try:
            old[sig] = signal.signal(sig, handler)
        except (ValueError, OSError):  # not the main thread
            pass
    try:
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def cmd_capture(args):
    if args.install_dissector or args.install_extcap:
        return _install(args)
    _check(args)
    if args.jig is not None:
        return _capture_jig(args)
    forced = 8 if args.ver8 else 6 if args.ver6 else None
    bus = R.make_bus(args.bus, args.baud, args.sniff)
    port = open_port(args.sniff, args.baud)
    sniffer = Sniffer(port, args.sniff, args.baud, interbyte_timeout_ms=args.interbyte_timeout,
                      ver8=True if forced == 8 else None)
    with _signals_as_ctrl_c():
        return _record(args, sniffer, port.close, [bus], "%s (%s) at %d baud" % (args.sniff, bus.name, args.baud),
                       forced=forced, finish=sniffer.finish)


def _capture_jig(args):
    """--jig PORT: X and S, the hello, records until the end, X (also after Ctrl-C, a broken
    pipe or a failure)."""
    forced = 8 if args.ver8 else 6 if args.ver6 else None
    _check_output(args)
    cap = JigCapture(args.jig)
    with _signals_as_ctrl_c():
        try:
            hello = cap.start(HELLO_WAIT_S)
        except KeyboardInterrupt:
            cap.close()
            sys.stderr.write("jigctl: stopped before the jig answered.\n")
            return EXIT_OK
        except BaseException:
            cap.close()
            raise
        if args.keep is not None:
            if R.CAN_BUS in args.keep and not cap.stream.has_can:
                cap.close()
                raise UsageError("--bus can: the jig at %s has no CAN port (its hello gives no CAN bitrate)" % args.jig)
            keep = args.keep
            cap.keep = lambda rec: rec.bus in keep or rec.verdict == R.LOST  # (a lost report concerns every bus)
        banner = "the jig's recording from %s: PC bus %d baud, driver bus %d baud%s (%s, jig id %d)" % (
            args.jig, hello["up_baud"], hello["down_baud"],
            ", CAN bus %d bit/s" % hello["can_bitrate"] if hello["can_bitrate"] else "", hello["variant"],
            hello["slave_id"])
        return _record(args, cap, cap.close, cap.stream.buses(), banner, hardware=cap.stream.description(),
                       forced=forced, jig=cap.stream)


def _record(args, source, close, buses, banner, hardware=None, forced=None, finish=None, jig=None):
    """Records of ``source`` (a Sniffer or a JigCapture) into the outputs until the end
    (--duration, --count, Ctrl-C, a failure); then ``close()`` the port, close the output,
    print the summary, and raise the first failure after it. ``finish(sinks)``: what the
    source left unfinished, after the end. A reader that went away ends it quietly."""
    writer = failed = None
    try:
        writer = _open_writer(args, buses, hardware=hardware)
        out = _Sinks(args, buses, writer, forced)
        out.banner(banner)
        try:
            source.run(out.sinks, duration=args.duration, count=args.count)
        except KeyboardInterrupt:
            pass
        except JigError as exc:  # the port, the stream or the output failed: the summary first
            failed = exc
        if finish is not None:
            try:
                finish(out.sinks)
            except KeyboardInterrupt:
                pass
            except JigError as exc:
                failed = failed or exc
    except BrokenPipeError:  # the reader of -w - (or of the live view) went away
        close()
        _close_writer(args, writer, quiet=True)
        return EXIT_OK
    except BaseException:
        close()
        _close_writer(args, writer, quiet=True)
        raise
    close()
    try:
        _close_writer(args, writer, quiet=failed is not None)
    except OutputError as exc:
        failed = exc
    _summary(args, source.records, source.bytes, out.counts, writer, jig)
    if failed is not None:
        raise failed
    return EXIT_OK


def _summary(args, records, nbytes, counts, writer, jig=None):
    files = []
    if isinstance(writer, pcapng.RotatingWriter):
        files = writer.written
    elif writer is not None and args.write != "-":
        files = [args.write]
    if args.json and args.write != "-":
        summary = {"records": records, "bytes": nbytes, "verdicts": counts, "files": files}
        if jig is not None:
            summary.update(lost=jig.lost, noise={"pc": jig.noise[0], "drivers": jig.noise[1]}, jig=jig.hello,
                           can_frames=jig.can_frames)
        print(json.dumps({"summary": summary}), flush=True)
        return
    parts = ", ".join("%s %d" % kv for kv in sorted(counts.items())) or "nothing heard"
    extra = ""
    if jig is not None:
        extra = "; the jig lost %d records, counted %d + %d noise bytes (PC bus + driver bus)" % (
            jig.lost, jig.noise[0], jig.noise[1])
    sys.stderr.write("%d records (%d bytes): %s%s%s\n" % (
        records, nbytes, parts, extra, "; written: %s" % ", ".join(files) if files else ""))
