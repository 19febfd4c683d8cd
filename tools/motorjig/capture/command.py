"""jigctl capture: record a Plus-R bus to pcapng for Wireshark, with a live line per frame.

    jigctl capture --sniff /dev/ttyUSB1 [-w bus.pcapng [--max-size 10M --files 5]] [--bus pc]
    jigctl capture --sniff /dev/ttyUSB1 -w - | wireshark -k -i -
    jigctl capture --install-dissector      # plusr.lua into Wireshark's personal plugin folder
    jigctl capture --install-extcap         # the motorjig-sniff interface for Wireshark/tshark

``--sniff`` listens through a listen-only USB-RS-485 adapter (or any pyserial URL)
and frames what it hears with the firmware's parser; every frame, dropped fragment
and run of noise becomes a pcapng packet with the parser's verdict in its comment.
The live view goes to standard output (standard error when that carries the
pcapng; ``-q`` switches it off); ``--json`` prints it as JSON lines.
"""

import json
import sys

from motorjig.capture import install, pcapng
from motorjig.capture import record as R
from motorjig.capture.sniff import DEFAULT_INTERBYTE_MS, Sniffer, open_port
from motorjig.capture.textview import TextView
from motorjig.commands import EXIT_OK, UsageError

_UNITS = {"": 1, "k": 1000, "m": 1000 ** 2, "g": 1000 ** 3}


def size(text):
    """'500k', '10M', '1G' or a number of bytes (k = 1000 bytes, as dumpcap counts)."""
    t = str(text).strip().lower().rstrip("b")
    unit = t[-1:] if t[-1:] in _UNITS and t[-1:] else ""
    try:
        value = float(t[:-1] if unit else t) * _UNITS[unit]
    except ValueError:
        raise UsageError("%r is not a size (give bytes, or a number with k, M or G)" % text) from None
    if value < 1024:
        raise UsageError("--max-size must be at least 1024 bytes, not %r" % text)
    return int(value)


def add_capture_arguments(sp):
    src = sp.add_argument_group("what to capture")
    src.add_argument("--sniff", metavar="PORT",
                     help="listen on a Plus-R bus through this listen-only adapter (/dev/ttyUSB1, COM7) or "
                          "pyserial URL (socket://host:port); --baud sets its baud rate")
    src.add_argument("--bus", choices=R.BUS_NAMES, default="pc",
                     help="which bus the adapter listens on: names the pcapng interface (default pc)")
    src.add_argument("--interbyte-timeout", type=float, default=DEFAULT_INTERBYTE_MS, metavar="MS",
                     help="silence inside a frame that drops it, in ms (default %g: longer than a USB "
                          "adapter's usual hold-back; the jig itself uses 5)" % DEFAULT_INTERBYTE_MS)
    src.add_argument("--duration", type=float, metavar="S", help="stop after this many seconds (default: Ctrl-C)")
    src.add_argument("--count", type=int, metavar="N", help="stop after N records (frames, fragments, noise)")
    out = sp.add_argument_group("output")
    out.add_argument("-w", "--write", metavar="FILE",
                     help="write pcapng to FILE, or '-' for standard output (for wireshark -k -i -)")
    out.add_argument("--max-size", type=str, metavar="SIZE",
                     help="with -w FILE: start a new file when one reaches SIZE (bytes, or 500k, 10M, 1G); "
                          "-w bus.pcapng then writes bus_00001.pcapng, bus_00002.pcapng, ...")
    out.add_argument("--files", type=int, metavar="N", help="with --max-size: keep only the newest N files")
    out.add_argument("--quiet", "-q", action="store_true", help="no live view, only the summary at the end")
    inst = sp.add_argument_group("Wireshark set-up")
    inst.add_argument("--install-dissector", action="store_true",
                      help="copy the Plus-R dissector into Wireshark's personal Lua plugin folder and say where")
    inst.add_argument("--install-extcap", action="store_true",
                      help="install the motorjig-sniff capture interface for Wireshark and tshark and say where")


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
        lines.append("capture interface: %s (tshark -D lists it; in tshark: -i %s -o extcap.%s.port:PORT)"
                     % (install.EXTCAP_NAME, install.EXTCAP_NAME, install.EXTCAP_NAME.replace("-", "_")))
    if not folders:
        lines.append("(tshark was not found: installed into the default folders of Wireshark 4.2 and later)")
    print("\n".join(lines))
    return EXIT_OK


def _check(args):
    if args.sniff is None:
        raise UsageError("give --sniff PORT (a listen-only adapter on the bus), or --install-dissector / --install-extcap")
    if args.max_size is not None:
        args.max_size = size(args.max_size)
        if args.write in (None, "-"):
            raise UsageError("--max-size needs -w FILE (a file to rotate)")
    if args.files is not None:
        if args.max_size is None:
            raise UsageError("--files needs --max-size")
        if args.files < 1:
            raise UsageError("--files must be at least 1, not %d" % args.files)
    if args.interbyte_timeout <= 0:
        raise UsageError("--interbyte-timeout must be more than 0 ms")
    if args.duration is not None and args.duration < 0:
        raise UsageError("--duration cannot be negative")
    if args.count is not None and args.count < 1:
        raise UsageError("--count must be at least 1")


def _open_writer(args, buses):
    if args.write is None:
        return None
    if args.write == "-":
        return pcapng.Writer(sys.stdout.buffer, buses, flush_each=True)
    try:
        if args.max_size is not None:
            return pcapng.RotatingWriter(args.write, buses, args.max_size, args.files)
        return pcapng.Writer(open(args.write, "wb"), buses)
    except OSError as exc:
        raise UsageError("cannot write %s: %s" % (args.write, exc.strerror)) from None


def cmd_capture(args):
    if args.install_dissector or args.install_extcap:
        return _install(args)
    _check(args)
    forced = 8 if args.ver8 else 6 if args.ver6 else None
    bus = R.make_bus(args.bus, args.baud, args.sniff)
    port = open_port(args.sniff, args.baud)
    sniffer = Sniffer(port, args.sniff, args.baud, interbyte_timeout_ms=args.interbyte_timeout,
                      ver8=True if forced == 8 else None)
    writer = None
    counts = {}
    try:
        writer = _open_writer(args, [bus])
        view = TextView([bus], forced)
        shown = None if args.quiet else (sys.stderr if args.write == "-" else sys.stdout)

        def show(rec):
            name = R.verdict_name(rec.verdict)
            counts[name] = counts.get(name, 0) + 1
            if shown is not None:
                d = view.as_dict(rec)
                shown.write((json.dumps(d) if args.json else view.line(rec, d)) + "\n")
                shown.flush()

        sinks = ([writer.write] if writer is not None else []) + [show]
        if shown is not None and not args.json:
            sys.stderr.write("capturing %s (%s) at %d baud%s; Ctrl-C ends\n" % (
                args.sniff, bus.name, args.baud, "" if args.write is None else ", pcapng to %s" % (
                    "standard output" if args.write == "-" else args.write)))
        try:
            sniffer.run(sinks, duration=args.duration, count=args.count)
        except KeyboardInterrupt:
            pass
        try:
            sniffer.finish(sinks)
        except KeyboardInterrupt:
            pass
    except BrokenPipeError:  # the reader of -w - (or of the live view) went away
        return EXIT_OK
    finally:
        port.close()
        if writer is not None:
            try:
                writer.flush() if args.write == "-" else writer.close()
            except OSError:
                pass
    _summary(args, sniffer, counts, writer)
    return EXIT_OK


def _summary(args, sniffer, counts, writer):
    files = []
    if isinstance(writer, pcapng.RotatingWriter):
        files = writer.written
    elif writer is not None and args.write != "-":
        files = [args.write]
    if args.json and args.write != "-":
        print(json.dumps({"summary": {"records": sniffer.records, "bytes": sniffer.bytes, "verdicts": counts,
                                      "files": files}}), flush=True)
        return
    parts = ", ".join("%s %d" % kv for kv in sorted(counts.items())) or "nothing heard"
    sys.stderr.write("%d records (%d bytes): %s%s\n" % (
        sniffer.records, sniffer.bytes, parts, "; written: %s" % ", ".join(files) if files else ""))
