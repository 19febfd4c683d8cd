"""Start MotorJig Desk: the web server, the shared bus session, the Test tab's station and, on request, the bench.

    jigctl gui [--port PORT] [--baud B] [--http-port N] [--host 127.0.0.1] [--open]
               [--plans DIR] [--out DIR] [--operator NAME] [--station NAME] [--slots FILE|ADDRS] [--read-only]
               [--capture-port PORT] [--can-port PORT] [--can-bitrate BPS]
    python -m motorjig.desk --bench [--drivers 2,3] [--can-nodes 5,6]     the virtual bench and the page on it (`make`)

``--slots`` makes the Test tab multi-up: the chosen plan runs in every slot of a
slots file (``station.slots``, docs/station.md) or at the drives' addresses (2,3) at
once; with ``--bench`` the bench gets the slots' drives and fixture wiring.
``--capture-port`` is the jig's capture port (its second USB port): the raw-frames
tab then records both buses through the jig and offers the recording as pcapng
(``capture``); with ``--bench`` the bench's own capture port is used.
``--can-port`` is the jig's SLCAN port (its third USB port): the CAN tab offers
to open it (``cantab``); with ``--bench --can-nodes 5,6`` the bench simulates
CANopen nodes on the jig's CAN bus and the tab is pointed at the bench's SLCAN port.

The page listens on 127.0.0.1 unless another address is asked for. Bound to any
other address it needs a token: a random one is made at start and printed in the
URL (``http://HOST:PORT/?token=...``); without it every page, file and websocket
is answered 401/403 (``auth``); on loopback a request under any other name than
127.0.0.1, localhost or [::1] is refused with 403 (DNS rebinding). ``--read-only`` shows the status and the runs and
refuses everything that would send to the bus.
"""

import argparse
import ipaddress
import os
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


def security_warning(host, read_only=False):
    """The sentence printed when the page is reachable from other machines, or None."""
    if is_loopback(host):
        return None
    if read_only:
        return ("NOTE: MotorJig Desk listens on %s, read-only: whoever has the URL with its token sees the "
                "status and the runs; nothing can be sent to the bus from the page." % host)
    return ("WARNING: MotorJig Desk listens on %s: anyone who has the URL with its token can move the "
            "motors. There is no TLS: keep it to a network that is yours, or use --read-only." % host)


def page_url(host, port, token=None):
    if host in ("0.0.0.0", ""):
        shown = "127.0.0.1"
    elif host == "::":
        shown = "[::1]"
    else:
        shown = "[%s]" % host if ":" in host else host
    return "http://%s:%d/%s" % (shown, port, "?token=%s" % token if token else "")


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


def _can_ids(text):
    try:
        ids = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError("expected comma-separated CANopen node ids, e.g. 5,6") from None
    if not ids or any(not 1 <= i <= 127 for i in ids):
        raise argparse.ArgumentTypeError("CANopen node ids must be 1..127")
    return ids


#: SLCAN's S0..S8 (canlink.BITRATES; here without importing python-can for the options)
CAN_BITRATES = (10000, 20000, 50000, 100000, 125000, 250000, 500000, 750000, 1000000)


def can_bitrate(text):
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError("%r is not a CAN bitrate" % text) from None
    if v not in CAN_BITRATES:
        raise argparse.ArgumentTypeError("the CAN bitrate must be one of %s" % ", ".join(map(str, CAN_BITRATES)))
    return v


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
    p.add_argument("--wiring", metavar="FILE",
                   help="with --bench: wire the bench's jig to its drive as FILE's [wiring] says (a plan will do; "
                        "default: the plans folder's ezi-step-eol.toml, so that plan can pass on the bench)")
    p.add_argument("--plans", metavar="DIR", help="the Test tab's plans folder (default: the repository's plans/)")
    p.add_argument("--out", metavar="DIR", default="results",
                   help="where the Test tab's runs leave their records and reports (default ./results)")
    p.add_argument("--operator", default=os.environ.get("USER", ""),
                   help="the operator's name the Test tab starts with (default: $USER)")
    p.add_argument("--station", help="station name in the run records (default: this computer's name)")
    p.add_argument("--slots", metavar="FILE|ADDRS",
                   help="multi-up: the Test tab runs the chosen plan in every slot of FILE (a slots file: each slot's "
                        "drive, serial and fixture wiring, docs/station.md) or at the drives ADDRS (e.g. 2,3) at once, "
                        "each slot with its own serial, progress and verdict (with --bench: the bench gets the "
                        "slots' drives and wiring)")
    p.add_argument("--db", default=os.environ.get("JIGCTL_DB") or None, metavar="PATH|URL|none",
                   help="results database the Test tab stores every run in and lists them from (as jigctl "
                        "test --db; default: $JIGCTL_DB, else ~/.local/share/motorjig/results.sqlite; 'none': "
                        "the records in --out)")
    p.add_argument("--read-only", action="store_true",
                   help="show the status and the runs, refuse everything that would send to the bus")
    p.add_argument("--capture-port", metavar="PORT",
                   help="the jig's capture port (its second USB port, e.g. /dev/ttyACM1, or a pyserial URL): the "
                        "raw-frames tab records both buses through the jig and downloads them as pcapng (with "
                        "--bench: the bench's own)")
    p.add_argument("--can-port", metavar="PORT_OR_URL",
                   help="the jig's SLCAN port (its third USB port, e.g. /dev/ttyACM2, or a pyserial URL): the CAN "
                        "tab offers to open it (with --bench --can-nodes: the bench's own)")
    p.add_argument("--can-bitrate", type=can_bitrate, default=500000, metavar="BPS",
                   help="the CAN tab's bitrate (default 500000); with --bench also the simulated CAN bus's")
    p.add_argument("--can-nodes", type=_can_ids, default=(), metavar="IDS",
                   help="with --bench: simulated CiA 402 nodes on the jig's CAN bus, e.g. 5,6 (default none)")
    from motorjig.desk import kindtabs

    for m in kindtabs.modules():  # the drive kinds' own tabs and their options
        m.add_arguments(p)


def build_parser():
    p = argparse.ArgumentParser(
        prog="python -m motorjig.desk",
        description="MotorJig Desk: the jig's PC program as a local web page (the same as `jigctl gui`).")
    p.add_argument("--port", "-p", help="serial port or pyserial URL to connect to at start")
    p.add_argument("--baud", "-b", type=baud, default=115200, help="baud rate (default 115200)")
    v = p.add_mutually_exclusive_group()
    v.add_argument("--ver8", action="store_true", help="Ver8 framing (sync number) for every slave")
    v.add_argument("--ver6", action="store_true", help="Ver6 framing for every slave (default: each slave's "
                                                      "variant detected, as jigctl scan does)")
    p.add_argument("--timeout", "-t", type=int, default=100, help="reply timeout in ms (default 100)")
    add_gui_arguments(p)
    return p


def bench_slots(spec, drivers):
    """What the bench needs for the slots ``spec`` (a slots file or addresses; with addresses, the
    plan keeps its own wiring): (the driver ids, with the slots' drives added; the slots' fixture
    wirings, or None). ValueError with the reason."""
    from motorjig.wiring import WiringError, load_slot_fixtures

    if not (spec.endswith(".toml") or os.path.isfile(spec)):  # addresses: the plan's own wiring, if any
        try:
            return tuple(sorted(set(drivers) | {int(x, 0) for x in spec.split(",") if x.strip()})), None
        except ValueError:
            raise ValueError("%r: give a slots file (.toml) or the drives' addresses, e.g. 2,3" % spec) from None
    try:
        fixtures = load_slot_fixtures(spec)
    except WiringError as exc:
        raise ValueError(str(exc)) from None
    ids = set(drivers) | {slave for slave, _node, _w in fixtures if slave is not None}
    wirings = [w for _s, _n, w in fixtures if w is not None]
    return tuple(sorted(ids)), wirings or None


def open_results(db, out):
    """The results database for the Test tab, or None (then the records of --out are listed)."""
    if db is not None and str(db).strip().lower() == "none":
        return None
    try:
        from motorjig.station.store import open_store

        return open_store(db)
    except Exception as exc:  # no SQLAlchemy, a bad URL, a server that does not answer: the page still works
        out.write("Test tab: no results database (%s); the runs are listed from the records in --out\n" % exc)
        return None


def _hangup_stops_the_desk():
    """A closed terminal or SSH session (SIGHUP) stops the Desk as Ctrl-C and SIGTERM do (the server's
    own shutdown, then stop_desk: a running test is aborted, the axis stopped, its records written)
    instead of killing it mid-move."""
    import signal
    import threading

    if hasattr(signal, "SIGHUP") and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGHUP, lambda signum, frame: os.kill(os.getpid(), signal.SIGTERM))


def stop_desk(session, station=None, store=None, bench=None, timeout=10.0, capture=None, can=None, links=()):
    """What the Desk does when it stops: a running test is aborted and waited for (its tearDown:
    stop, emergency stop, servo off), then the recording (X), the CAN tab's SLCAN port (C), the
    bus session, the results database and the bench are closed, in that order."""
    try:
        if station is not None and not station.shutdown(timeout):
            session.log("error", "the test run did not end within %g s of the Desk stopping" % timeout)
    finally:
        if capture is not None:
            capture.close()
        for link in ([can] if can is not None else []) + list(links):  # their axes made safe first
            if link.state != "closed":
                try:
                    link.close()
                except Exception:  # stopping: nothing to tell anyone
                    pass
        session.stop()
        if store is not None:
            store.close()
        if bench is not None:
            bench.stop()


def serve(args, out=None):
    """Run the page until Ctrl-C; returns an exit status. args: see build_parser."""
    out = out or sys.stdout
    try:
        from nicegui import app, ui
    except ImportError:
        sys.stderr.write("jigctl gui: the web GUI needs NiceGUI: run `make setup` (pip extra [gui]).\n")
        return 2
    from motorjig.desk import auth, page
    from motorjig.desk.capture import DeskCapture
    from motorjig.desk.session import BusSession, UserError
    from motorjig.desk.testrun import Station

    read_only = bool(getattr(args, "read_only", False))
    warning = security_warning(args.host, read_only)
    if warning:
        sys.stderr.write(warning + "\n")
        sys.stderr.flush()
    try:
        check_http_port(args.host, args.http_port)
    except OSError as exc:
        sys.stderr.write("jigctl gui: %s.\n" % exc)
        return 3

    bench = None
    slots_spec = getattr(args, "slots", None)
    if slots_spec and (slots_spec.endswith(".toml") or os.sep in slots_spec) and not os.path.isfile(slots_spec):
        sys.stderr.write("jigctl gui: --slots: %s does not exist.\n" % slots_spec)
        return 2
    port = getattr(args, "port", None)
    capture_port = getattr(args, "capture_port", None)
    can_port = getattr(args, "can_port", None)
    if args.bench:
        from motorjig.sim import Bench

        from motorjig.desk.testrun import default_plans_dir
        from motorjig.wiring import WiringError, load_wiring

        wiring = getattr(args, "wiring", None)
        eol = os.path.join(getattr(args, "plans", None) or default_plans_dir(), "ezi-step-eol.toml")
        fixture = None
        if slots_spec:  # (the slots' drives and their fixture wiring)
            try:
                args.drivers, fixture = bench_slots(slots_spec, args.drivers)
            except ValueError as exc:
                sys.stderr.write("jigctl gui: --slots: %s.\n" % str(exc).rstrip("."))
                return 2
        if wiring is None and fixture is None:
            wiring = eol if os.path.exists(eol) else None
        try:
            wiring = load_wiring(wiring) if wiring else fixture
        except WiringError as exc:
            sys.stderr.write("jigctl gui: %s.\n" % str(exc).rstrip("."))
            return 2
        can_nodes = tuple(getattr(args, "can_nodes", ()) or ())
        can_kw = {"can_nodes": can_nodes, "can_bitrate": args.can_bitrate} if can_nodes else {}
        if slots_spec:  # a multi-up line's driver bus: four moving slots get 250 samples/s each, not 53
            can_kw["down_baud"] = 921600
        bench = Bench(driver_ids=args.drivers, baud=args.baud, tcp_port=args.tcp_port, pty=True, wiring=wiring,
                      **can_kw)
        try:
            bench.start()
        except (OSError, ValueError, ImportError) as exc:  # ImportError: a bench without the CAN parts
            bench.stop()
            sys.stderr.write("jigctl gui: cannot start the virtual bench: %s.\n" % exc)
            return 1
        port = bench.tcp_url
        if capture_port is None:
            capture_port = bench.capture_url
        out.write("virtual bench: jig = slave 1, drivers %s; other programs can use %s%s\n" % (
            ",".join(map(str, args.drivers)), bench.tcp_url,
            " or %s" % bench.pty_path if bench.pty_path else ""))
        out.write("  the jig's capture port: %s (the raw-frames tab records through it)\n" % bench.capture_url)
        for w in wiring if isinstance(wiring, list) else [wiring] if wiring is not None else []:
            out.write("  wired as %s says: jig relays and inputs to %s\n" % (w.source, w.drive or "the first drive"))
        if can_nodes and can_port is None:
            can_port = getattr(bench, "slcan_url", None)
        if can_nodes:
            out.write("  the jig's SLCAN port: %s (CANopen nodes %s at %d kbit/s; the CAN tab opens it)\n" % (
                getattr(bench, "slcan_url", None), ",".join(map(str, can_nodes)), args.can_bitrate // 1000))

    session = BusSession(timeout=max(1, args.timeout) / 1000.0).start()
    ver8 = True if getattr(args, "ver8", False) else False if getattr(args, "ver6", False) else None
    if port:
        try:
            msg = session.connect(port, args.baud, ver8)
            if bench is not None or read_only:  # a read-only page cannot scan: it opens ready
                rows = session.scan(1, max(args.drivers) if bench is not None else 15)
                msg = "connected to %s; found %s; working with slave %s" % (
                    port, ", ".join("%d (%s)" % (r["id"], "jig" if r["jig"] else r["type_name"]) for r in rows),
                    session.axis)
            out.write(msg + "\n")
        except UserError as exc:
            if read_only:  # it cannot press Connect: it keeps trying by itself
                session.watch(port, args.baud, ver8, str(exc))
                out.write("could not connect yet: %s (read-only: it tries again every few seconds)\n" % exc)
            else:
                out.write("could not connect yet: %s (the page offers Connect)\n" % exc)
    session.read_only = read_only
    # The station's engine (OpenHTF) sets a signal handler when imported: that works in this thread only.
    store = open_results(getattr(args, "db", None), out)
    station = Station(session, plans_dir=getattr(args, "plans", None), out_dir=getattr(args, "out", "results"),
                      operator=getattr(args, "operator", ""), station=getattr(args, "station", None), store=store,
                      slots=slots_spec)
    if station.unavailable:
        out.write("Test tab: %s\n" % station.unavailable)
    capture = DeskCapture(capture_port)
    from motorjig.desk.cantab import make_link

    can_link, can_why = make_link(can_port or "", getattr(args, "can_bitrate", 500000), read_only)
    if can_why:
        out.write("CAN tab: %s\n" % can_why)
    from motorjig.desk import kindtabs

    extra = [(m,) + tuple(m.make_link(args, read_only)) for m in kindtabs.modules()]
    for m, _link, why in extra:
        if why:
            out.write("%s tab: %s\n" % (m.LABEL, why))
    links = [link for _m, link, _why in extra if link is not None]
    # a run borrows its ports from these axes
    station.axes = ([can_link.desk_axis] if can_link is not None else []) + [link.desk_axis for link in links]
    page.build(session, station, capture, can_link, extra)
    token = None
    if not is_loopback(args.host):
        token = auth.new_token()
        app.add_middleware(auth.TokenGate, token=token, port=args.http_port)
    else:  # no token needed, but only under this computer's own names (no DNS rebinding)
        app.add_middleware(auth.HostGate, host=args.host, port=args.http_port)
    app.on_shutdown(lambda: stop_desk(session, station, store, bench, capture=capture, can=can_link, links=links))
    url = page_url(args.host, args.http_port, token)
    out.write("MotorJig Desk: %s  (Ctrl-C stops)%s\n" % (url, "  read-only" if read_only else ""))
    if args.host in ("0.0.0.0", "::"):
        out.write("  from other computers: %s\n" % page_url(socket.gethostname(), args.http_port, token))
    out.flush()
    show = ("/?token=%s" % token if token else "/") if args.open else False
    _hangup_stops_the_desk()
    ui.run(host=args.host, port=args.http_port, title="MotorJig Desk", reload=False, show=show,
           show_welcome_message=False, uvicorn_logging_level="warning", favicon="🛠", dark=False)
    return 0


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        return serve(args)
    except KeyboardInterrupt:
        return 130
