"""Start MotorJig Desk: the web server, the shared bus session and, on request, the bench.

    jigctl gui [--port PORT] [--baud B] [--http-port N] [--host 127.0.0.1] [--open]
    python -m motorjig.desk --bench [--drivers 2,3]     the virtual bench and the page on it (`make`)

The page listens on 127.0.0.1 unless another address is asked for; then a
warning says that anyone who can reach it can move the motors.
"""

import argparse
import ipaddress
import socket
import sys

DEFAULT_HTTP_PORT = 8470
LOOPBACK_NAMES = ("localhost",)


def is_loopback(host):
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def security_warning(host):
    """The sentence printed when the page is reachable from other machines, or None."""
    if is_loopback(host):
        return None
    return ("WARNING: MotorJig Desk listens on %s without a password: anyone who can reach this address "
            "can move the motors. Use --host 127.0.0.1 unless this network is yours alone." % host)


def page_url(host, port):
    shown = "127.0.0.1" if host in ("0.0.0.0", "") else ("[%s]" % host if ":" in host else host)
    return "http://%s:%d/" % (shown, port)


def check_http_port(host, port):
    """Raise OSError with a clear sentence when host:port cannot be listened on."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    s = socket.socket(family, socket.SOCK_STREAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, port))
    except OSError as exc:
        raise OSError("cannot listen on %s port %d (%s): choose another with --http-port"
                      % (host, port, exc.strerror or exc)) from None
    finally:
        s.close()


def _ids(text):
    try:
        ids = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError("expected comma-separated ids, e.g. 2,3") from None
    if not ids or any(not 2 <= i <= 15 for i in ids):
        raise argparse.ArgumentTypeError("driver ids must be 2..15 (the jig is 1)")
    return ids


def _port_number(text, what):
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError("%r is not a port number" % text) from None
    if not 1 <= v <= 65535:
        raise argparse.ArgumentTypeError("%s must be 1..65535, not %d" % (what, v))
    return v


def http_port(text):
    return _port_number(text, "the HTTP port")


def tcp_port(text):
    """The bench's TCP port; 0 picks a free one."""
    return 0 if str(text).strip() == "0" else _port_number(text, "the bench's TCP port")


def baud(text):
    from motorjig.master import BAUD_RATES

    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError("%r is not a baud rate" % text) from None
    if v not in BAUD_RATES:
        raise argparse.ArgumentTypeError("baud rate must be one of %s" % ", ".join(map(str, BAUD_RATES)))
    return v


def add_gui_arguments(p):
    """The options of `jigctl gui` that are not jigctl's global ones."""
    p.add_argument("--http-port", type=http_port, default=DEFAULT_HTTP_PORT,
                   help="port of the web page (default %d)" % DEFAULT_HTTP_PORT)
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this computer only; anything else "
                        "lets others move the motors)")
    p.add_argument("--open", action="store_true", help="open the page in the default browser")
    p.add_argument("--bench", action="store_true",
                   help="start the virtual bench in this process and connect to it (ignores --port)")
    p.add_argument("--drivers", type=_ids, default=(2, 3), help="with --bench: simulated driver ids (default 2,3)")
    p.add_argument("--tcp-port", type=tcp_port, default=0,
                   help="with --bench: the bench's TCP port for other programs (default: a free one)")


def build_parser():
    p = argparse.ArgumentParser(
        prog="python -m motorjig.desk",
        description="MotorJig Desk: the jig's PC program as a local web page (the same as `jigctl gui`).")
    p.add_argument("--port", "-p", help="serial port or pyserial URL to connect to at start")
    p.add_argument("--baud", "-b", type=baud, default=115200, help="baud rate (default 115200)")
    p.add_argument("--ver8", action="store_true", help="Ver8 framing (sync number)")
    p.add_argument("--timeout", "-t", type=int, default=100, help="reply timeout in ms (default 100)")
    add_gui_arguments(p)
    return p


def serve(args, out=None):
    """Run the page until Ctrl-C; returns an exit status. args: see build_parser."""
    out = out or sys.stdout
    try:
        from nicegui import app, ui
    except ImportError:
        sys.stderr.write("jigctl gui: the web GUI needs NiceGUI: run `make setup` (pip extra [gui]).\n")
        return 2
    from motorjig.desk import page
    from motorjig.desk.session import BusSession, UserError

    warning = security_warning(args.host)
    if warning:
        sys.stderr.write(warning + "\n")
        sys.stderr.flush()
    try:
        check_http_port(args.host, args.http_port)
    except OSError as exc:
        sys.stderr.write("jigctl gui: %s.\n" % exc)
        return 3

    bench = None
    port = getattr(args, "port", None)
    if args.bench:
        from motorjig.sim import Bench

        bench = Bench(driver_ids=args.drivers, baud=args.baud, tcp_port=args.tcp_port, pty=True)
        try:
            bench.start()
        except OSError as exc:
            bench.stop()
            sys.stderr.write("jigctl gui: cannot start the virtual bench: %s.\n" % exc)
            return 1
        port = bench.tcp_url
        out.write("virtual bench: jig = slave 1, drivers %s; other programs can use %s%s\n" % (
            ",".join(map(str, args.drivers)), bench.tcp_url,
            " or %s" % bench.pty_path if bench.pty_path else ""))

    session = BusSession(timeout=max(1, args.timeout) / 1000.0).start()
    if port:
        try:
            msg = session.connect(port, args.baud, args.ver8)
            if bench is not None:  # the bench's ids are known: scan them now, the page opens ready
                rows = session.scan(1, max(args.drivers))
                msg = "connected to %s; found %s; working with slave %s" % (
                    port, ", ".join("%d (%s)" % (r["id"], "jig" if r["jig"] else r["type_name"]) for r in rows),
                    session.axis)
            out.write(msg + "\n")
        except UserError as exc:
            out.write("could not connect yet: %s (the page offers Connect)\n" % exc)
    page.build(session)

    def shutdown():
        session.stop()
        if bench is not None:
            bench.stop()

    app.on_shutdown(shutdown)
    url = page_url(args.host, args.http_port)
    out.write("MotorJig Desk: %s  (Ctrl-C stops)\n" % url)
    out.flush()
    ui.run(host=args.host, port=args.http_port, title="MotorJig Desk", reload=False, show=bool(args.open),
           show_welcome_message=False, uvicorn_logging_level="warning", favicon="🛠", dark=False)
    return 0


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        return serve(args)
    except KeyboardInterrupt:
        return 130
