"""Wireshark extcap: the MotorJig interfaces, ``motorjig-sniff`` (a Plus-R bus through a
listen-only adapter) and ``motorjig-jig`` (the jig's own recording of its buses).

Wireshark runs this program (the launchers ``jigctl capture --install-extcap``
writes, one per interface) in the steps of the extcap interface::

    --extcap-interfaces                          the interface list
    --extcap-interface motorjig-sniff --extcap-dlts     its link types (USER0/USER1, the dissector's)
    --extcap-interface motorjig-sniff --extcap-config   its options: port/URL, baud, bus, timeout
    --extcap-interface motorjig-sniff --capture --fifo PATH --port URL [--baud N] ...
    --extcap-interface motorjig-jig --extcap-dlts       its link types (USER0/USER1, CAN_SOCKETCAN)
    --extcap-interface motorjig-jig --extcap-config     its option: the jig's capture port/URL
    --extcap-interface motorjig-jig --capture --fifo PATH --port URL

and the capture writes pcapng into the fifo (the same writer as ``jigctl capture
-w``; for the jig two interfaces, the PC bus and the driver bus, and a third, the
CAN bus as SocketCAN frames, when the jig has a CAN port) until Wireshark
closes it or stops the program. In tshark the options are preferences:
``-o extcap.motorjig_sniff.port:/dev/ttyUSB1`` (also ``baud``, ``bus``,
``interbytetimeout``), ``-o extcap.motorjig_jig.port:/dev/ttyACM1``.
"""

import argparse
import select
import signal
import sys

from motorjig.capture import pcapng
from motorjig.capture import record as R
from motorjig.capture.jigport import JigCapture
from motorjig.capture.sniff import DEFAULT_INTERBYTE_MS, Sniffer, open_port
from motorjig.errors import JigError
from motorjig.master import BAUD_RATES, DEFAULT_BAUD

INTERFACE = "motorjig-sniff"
JIG_INTERFACE = "motorjig-jig"
INTERFACES = (INTERFACE, JIG_INTERFACE)
_DISPLAY = {INTERFACE: "MotorJig: FASTECH Plus-R bus (listen-only RS-485 adapter)",
            JIG_INTERFACE: "MotorJig jig: PC bus, driver bus and CAN bus (the jig's own recording)"}


def _version():
    try:
        from importlib.metadata import version

        return version("motorjig")
    except Exception:
        return "0.1.0"


def interfaces(which=INTERFACES):
    return ["extcap {version=%s}{display=MotorJig}" % _version()] + [
        "interface {value=%s}{display=%s}" % (name, _DISPLAY[name]) for name in which]


def dlts(interface=INTERFACE):
    out = ["dlt {number=%d}{name=USER0}{display=FASTECH Plus-R, PC bus (MotorJig records)}" % pcapng.LINKTYPES["pc"],
           "dlt {number=%d}{name=USER1}{display=FASTECH Plus-R, driver bus (MotorJig records)}"
           % pcapng.LINKTYPES["drivers"]]
    if interface == JIG_INTERFACE:
        out.append("dlt {number=%d}{name=CAN_SOCKETCAN}{display=CAN bus, SocketCAN frames (MotorJig records)}"
                   % pcapng.LINKTYPES["can"])
    return out


def config(interface=INTERFACE):
    if interface == JIG_INTERFACE:
        return ["arg {number=0}{call=--port}{display=Capture port or URL}{type=string}{required=true}"
                "{tooltip=The jig's capture port (its second USB port, /dev/ttyACM1, COM8) or a pyserial URL "
                "(socket://127.0.0.1:N on the virtual bench)}"]
    lines = ["arg {number=0}{call=--port}{display=Port or URL}{type=string}{required=true}"
             "{tooltip=The listen-only adapter (/dev/ttyUSB1, COM7) or a pyserial URL (socket://host:port)}"]
    lines.append("arg {number=1}{call=--baud}{display=Baud rate}{type=selector}{tooltip=The bus's baud rate}")
    for b in BAUD_RATES:
        lines.append("value {arg=1}{value=%d}{display=%d}{default=%s}" % (b, b, "true" if b == DEFAULT_BAUD else "false"))
    lines.append("arg {number=2}{call=--bus}{display=Bus}{type=selector}{tooltip=Which bus the adapter listens on}")
    lines.append("value {arg=2}{value=pc}{display=PC bus}{default=true}")
    lines.append("value {arg=2}{value=drivers}{display=driver bus}{default=false}")
    lines.append("arg {number=3}{call=--interbyte-timeout}{display=Inter-byte timeout [ms]}{type=double}"
                 "{default=%g}{tooltip=Silence that ends a frame; keep it above the adapter's latency}"
                 % DEFAULT_INTERBYTE_MS)
    return lines


def parser():
    ap = argparse.ArgumentParser(prog="motorjig extcap",
                                 description="Wireshark extcap for FASTECH Plus-R buses (MotorJig).")
    ap.add_argument("--extcap-interfaces", action="store_true", help="list the interfaces")
    ap.add_argument("--extcap-interface", help="the interface to work on")
    ap.add_argument("--extcap-dlts", action="store_true", help="list the interface's link types")
    ap.add_argument("--extcap-config", action="store_true", help="list the interface's options")
    ap.add_argument("--extcap-version", help="the Wireshark version asking (ignored)")
    ap.add_argument("--extcap-capture-filter", help="a capture filter (not supported: ignored)")
    ap.add_argument("--capture", action="store_true", help="capture into --fifo")
    ap.add_argument("--fifo", help="where Wireshark reads the pcapng stream")
    ap.add_argument("--port", help="the listen-only adapter, the jig's capture port, or a pyserial URL")
    ap.add_argument("--baud", type=int, default=DEFAULT_BAUD, help="baud rate (default %d)" % DEFAULT_BAUD)
    ap.add_argument("--bus", choices=R.BUS_NAMES, default="pc", help="which bus it is (default pc)")
    ap.add_argument("--interbyte-timeout", type=float, default=DEFAULT_INTERBYTE_MS,
                    help="inter-byte timeout in ms (default %g)" % DEFAULT_INTERBYTE_MS)
    return ap


def _fail(text, name=INTERFACE):
    sys.stderr.write("%s: %s.\n" % (name, text.rstrip(".")))
    return 1


def _reader_alive(stream):
    """A check that the fifo still has a reader: a quiet bus writes nothing, so a closed
    fifo would otherwise go unnoticed until the next frame."""
    try:
        poller = select.poll()
        poller.register(stream.fileno(), 0)  # POLLERR / POLLHUP are reported anyway
    except (AttributeError, OSError, ValueError):  # no poll() (Windows)
        return None
    return lambda: not poller.poll(0)


def _open_fifo(args, name):
    """The fifo, opened before anything else: Wireshark (dumpcap) created it and waits in
    open() for this writer, so a failure must still open and close it or it waits for
    minutes. None (and the sentence said) if it cannot be opened."""
    try:
        return open(args.fifo, "wb")
    except OSError as exc:
        _fail("cannot open %s: %s" % (args.fifo, exc.strerror or exc), name)
        return None


def _stop_on_sigterm(stop):
    # Wireshark ends a capture with SIGTERM: leave the loop and close the stream.
    signal.signal(signal.SIGTERM, lambda *_: stop())


def _into_fifo(args, name, record):
    """What both interfaces do around their capture: the fifo opened first (Wireshark
    waits in its open()), ``record(fifo, keep)`` run (``keep(x)``: x is closed at the
    end), a failure as the interface's one sentence, everything closed. Returns the exit
    code: ``record``'s own (a refused option), else 0."""
    if not args.fifo:
        return _fail("no --fifo given", name)
    fifo = _open_fifo(args, name)
    if fifo is None:
        return 1
    opened = []
    try:
        return record(fifo, opened.append) or 0
    except (BrokenPipeError, KeyboardInterrupt):
        return 0  # Wireshark closed the fifo, or the user stopped the capture
    except JigError as exc:
        return _fail(str(exc), name)
    finally:
        for thing in opened:
            thing.close()
        _close_quietly(fifo)


def capture(args):
    return _into_fifo(args, INTERFACE, lambda fifo, keep: _sniff_into(args, fifo, keep))


def _sniff_into(args, fifo, keep):
    if not args.port:
        return _fail("no port given: set the interface's Port or URL option")
    if args.baud not in BAUD_RATES:
        return _fail("baud rate %d is not one the drives support" % args.baud)
    port = open_port(args.port, args.baud)
    keep(port)
    sniffer = Sniffer(port, args.port, args.baud, interbyte_timeout_ms=args.interbyte_timeout)
    _stop_on_sigterm(sniffer.stop)
    bus = R.make_bus(args.bus, args.baud, args.port)
    writer = pcapng.Writer(fifo, [bus], flush_each=True)
    try:
        sniffer.run([writer.write], alive=_reader_alive(fifo))
    finally:
        sniffer.finish([writer.write])
    return 0


def _close_quietly(fifo):
    try:
        fifo.close()
    except OSError:  # BrokenPipeError flushing what is left: the reader is gone
        pass


def capture_jig(args):
    return _into_fifo(args, JIG_INTERFACE, lambda fifo, keep: _jig_into(args, fifo, keep))


def _jig_into(args, fifo, keep):
    if not args.port:
        return _fail("no port given: set the interface's Capture port or URL option", JIG_INTERFACE)
    cap = JigCapture(args.port)
    keep(cap)
    _stop_on_sigterm(cap.stop)
    cap.start()
    writer = pcapng.Writer(fifo, cap.stream.buses(), flush_each=True, hardware=cap.stream.description())
    cap.run([writer.write], alive=_reader_alive(fifo))
    return 0


def main(argv=None, interface=None):
    """``interface``: the one interface a launcher offers (None: both)."""
    offered = INTERFACES if interface is None else (interface,)
    args = parser().parse_args(argv)
    if args.extcap_interfaces:
        print("\n".join(interfaces(offered)))
        return 0
    name = args.extcap_interface or offered[0]
    if name not in offered:
        return _fail("unknown interface %r (this program has %s)" % (name, ", ".join(offered)), offered[0])
    if args.extcap_dlts:
        print("\n".join(dlts(name)))
        return 0
    if args.extcap_config:
        print("\n".join(config(name)))
        return 0
    if args.capture:
        return capture_jig(args) if name == JIG_INTERFACE else capture(args)
    return _fail("nothing to do (Wireshark calls this with --extcap-interfaces, --extcap-config or --capture)", name)


if __name__ == "__main__":
    sys.exit(main())
