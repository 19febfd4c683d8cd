"""``jigctl can``: CANopen through the jig's SLCAN port with python-can and python-canopen.

Subcommands: ``scan`` (which node ids answer, with device type, name and identity),
``nmt`` (start/stop/pre-operational/reset a node or all), ``sdo read|write`` (typed from
an EDS), ``sdo dump|load`` (a node's settings as a CiA 402 parameter-set file, the format
of ``motorjig.can.paramset402`` and of a CiA 402 plan's golden set), ``dump`` (a live line per frame, optionally logged by python-can), ``lss``
(fast scan, node id, bit timing, store). Every input is checked before the port is
opened; failures are one sentence and an exit status like the rest of jigctl: 2 bad
input, 3 port (missing, or not an SLCAN port), 4 no answer, 5 a node refused (SDO abort,
LSS error).
"""

import argparse
import json
import logging
import os
import sys
import time

import can
import canopen
from canopen.lss import LssError

from motorjig.can import EDS_PATH, cia301
from motorjig.can import objects as O
from motorjig.can import paramset402
from motorjig.can.dump import FrameText, check_log_path, run_dump
from motorjig.can.port import DEFAULT_BITRATE, SLCAN_BITRATES, bus_session, network_session
from motorjig.commands import EXIT_COMM, EXIT_OK, EXIT_PORT, EXIT_STATUS, UsageError, fail

# CiA 305 bit timing table: bitrate -> table index.
LSS_BIT_TIMING = {1000000: 0, 800000: 1, 500000: 2, 250000: 3, 125000: 4, 100000: 5, 50000: 6, 20000: 7,
                  10000: 8}
NMT_EXPECT = {"start": (0x05,), "stop": (0x04,), "preop": (0x7F,), "reset": (0x00,), "reset-comm": (0x00,)}
PORT_HINT = "the jig's SLCAN port: its third USB serial port, e.g. /dev/ttyACM2"


class NoAnswer(Exception):
    """A node (or any node) did not answer in time (exit 4)."""


class Refused(Exception):
    """A node answered with an error: SDO abort, LSS error code (exit 5)."""


# --- arguments -------------------------------------------------------------------
def _can_options(p, suppress):
    d = (lambda v: argparse.SUPPRESS) if suppress else (lambda v: v)
    g = p.add_argument_group("CAN port (may also come before the CAN subcommand)")
    g.add_argument("--bitrate", default=d(os.environ.get("JIGCTL_CAN_BITRATE", str(DEFAULT_BITRATE))),
                   help="CAN bitrate in bit/s, one of %s (default $JIGCTL_CAN_BITRATE or %d)" % (
                       ", ".join(map(str, SLCAN_BITRATES)), DEFAULT_BITRATE))
    g.add_argument("--eds", default=d(None),
                   help="EDS file naming the objects (default for sdo: the jig's simulated CiA 402 drive, %s; "
                        "dump names SDOs and PDOs only when it is given)" % os.path.basename(EDS_PATH))


def add_can_arguments(sp, common):
    """The can subcommands on sp; common(parser) adds jigctl's global options to a parser."""
    _can_options(sp, False)
    sub = sp.add_subparsers(dest="can_command", metavar="CAN_COMMAND")
    sub.required = True

    def add(parent, name, fn, help_text):
        p = parent.add_parser(name, help=help_text, description=help_text)
        common(p)
        _can_options(p, True)
        if fn is not None:
            p.set_defaults(can_fn=fn)
        return p

    p = add(sub, "scan", cmd_scan, "which node ids answer, with device type (profile), device name and identity "
                                   "(python-canopen's scanner: an SDO read of 0x1000 to every id)")
    p.add_argument("--wait", type=float, default=0.5, help="seconds to wait for answers (default 0.5)")

    p = add(sub, "nmt", cmd_nmt, "send an NMT command to a node or to all, and show the heartbeats that follow")
    p.add_argument("node", metavar="NODE|all", help="node id 1..127, or all")
    p.add_argument("nmt_command", metavar="COMMAND", help="start, stop, preop, reset or reset-comm")
    p.add_argument("--wait", type=float, default=1.0,
                   help="seconds to listen for heartbeats confirming the new state (default 1; 0: do not listen)")

    p = add(sub, "sdo", None, "read or write an object of a node by SDO, typed from the EDS")
    ssub = p.add_subparsers(dest="sdo_action", metavar="ACTION")
    ssub.required = True
    obj_help = "INDEX[:SUB]: numbers (0x6041, 0x1018:1) or names from the EDS (Statusword)"
    force_help = ("send even if the EDS lacks the object (values then as hex bytes), says it is read-only, "
                  "or the value is outside its limits: the node decides")
    r = add(ssub, "read", cmd_sdo_read, "read an object (a record or array: every sub-index)")
    r.add_argument("node", help="node id 1..127")
    r.add_argument("object", help=obj_help)
    r.add_argument("--force", action="store_true", help=force_help)
    w = add(ssub, "write", cmd_sdo_write, "write an object: the value is parsed by its type and checked against "
                                          "the EDS's range")
    w.add_argument("node", help="node id 1..127")
    w.add_argument("object", help=obj_help)
    w.add_argument("value", help="integers in decimal or 0x hex, true/false, a float, text, or hex bytes")
    w.add_argument("--force", action="store_true", help=force_help)
    d = add(ssub, "dump", cmd_sdo_dump, "read a node's settings into a CiA 402 parameter-set file on stdout (the "
                                        "format of a CiA 402 plan's golden set): jigctl can sdo dump 5 > set.toml")
    d.add_argument("node", help="node id 1..127")
    d.add_argument("--objects", metavar="LIST",
                   help="comma-separated INDEX[:SUB] or names (a record: its read-write sub-indexes); default: every "
                        "object the EDS lets one read and write at 0x1017 and from 0x2000 on, except the "
                        "controlword, the mode, the targets and the outputs")
    ld = add(ssub, "load", cmd_sdo_load, "write a CiA 402 parameter-set file's objects to a node (each checked "
                                         "against the EDS first), optionally store them (0x1010:01 \"save\")")
    ld.add_argument("node", help="node id 1..127")
    ld.add_argument("file", help="the parameter-set file (jigctl can sdo dump's format)")
    ld.add_argument("--store", action="store_true", help="then store them in the node: 0x1010:01 = \"save\"")

    p = add(sub, "dump", cmd_dump, "a live line per frame like candump, with its CANopen meaning; Ctrl-C ends it")
    p.add_argument("--count", "-n", type=int, help="stop after this many frames")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--log", help="also record to this file with python-can's logger for its extension "
                                 "(.asc, .blf, .csv, .log, ...)")
    p.add_argument("--listen-only", action="store_true", help="open the port listen-only (SLCAN L): no ACKs sent")

    p = add(sub, "lss", None, "layer setting services (CiA 305): find an unconfigured node, set its node id and "
                              "bitrate, store")
    lsub = p.add_subparsers(dest="lss_action", metavar="ACTION")
    lsub.required = True
    ident_help = ("switch only the node with this LSS address into configuration state first "
                  "(vendor,product,revision,serial: 0x1018:1..4)")
    stay_help = "leave the node in configuration state afterwards (default: switch every node back to waiting)"
    timeout_help = "ms to wait for each LSS answer (default 100)"
    f = add(lsub, "fast-scan", cmd_lss, "find an unconfigured node's identity bit by bit (it ends in configuration "
                                        "state)")
    f.add_argument("--lss-timeout", type=int, default=100, help=timeout_help)
    s = add(lsub, "set-id", cmd_lss, "configure the node id of the node in configuration state")
    s.add_argument("new_id", metavar="NEW", help="new node id 1..127 (255: unconfigured)")
    b = add(lsub, "set-bitrate", cmd_lss, "configure the bitrate of the node in configuration state (it takes "
                                          "effect once stored and the node restarts)")
    b.add_argument("new_bitrate", metavar="BITRATE",
                   help="bit/s, one of %s" % ", ".join(map(str, sorted(LSS_BIT_TIMING))))
    t = add(lsub, "store", cmd_lss, "store the configured node id and bitrate in the node")
    q = add(lsub, "inquire", cmd_lss, "ask the node in configuration state its node id and identity")
    for p in (s, b, t, q):
        p.add_argument("--identity", help=ident_help)
        p.add_argument("--lss-timeout", type=int, default=100, help=timeout_help)
    for p in (s, b):
        p.add_argument("--store", action="store_true", help="then store the configuration")
    for p in (s, b, t):
        p.add_argument("--stay", action="store_true", help=stay_help)
    q.set_defaults(stay=True)


# --- input checks ------------------------------------------------------------------
def _int(text):
    try:
        return int(str(text).strip().replace("_", ""), 0)
    except ValueError:
        return None


def node_id(text, allow_all=False):
    if allow_all and str(text).lower() == "all":
        return 0
    v = _int(text)
    if v is None or not 1 <= v <= 127:
        raise UsageError("node id must be 1..127%s, not %r" % (" or all" if allow_all else "", text))
    return v


def bitrate(args):
    v = _int(args.bitrate)
    if v not in SLCAN_BITRATES:
        raise UsageError("--bitrate must be one of %s, not %r" % (", ".join(map(str, SLCAN_BITRATES)), args.bitrate))
    return v


def port_of(args):
    """--port, else $JIGCTL_CAN_PORT (which also wins over $JIGCTL_PORT, the RS-485 port's)."""
    port = args.port
    env_can = os.environ.get("JIGCTL_CAN_PORT")
    if env_can and (not port or port == os.environ.get("JIGCTL_PORT")):
        port = env_can
    if not port:
        raise UsageError("give --port PORT (%s) or set $JIGCTL_CAN_PORT" % PORT_HINT)
    return port


def timeout_s(args):
    return args.timeout / 1000.0


def identity(text):
    parts = [p for p in (text or "").replace(" ", "").split(",")]
    values = [_int(p) for p in parts]
    if len(values) != 4 or any(v is None or not 0 <= v <= 0xFFFFFFFF for v in values):
        raise UsageError("--identity must be four numbers vendor,product,revision,serial (0..0xFFFFFFFF), not %r"
                         % text)
    return values


def _seconds(value, name):
    if value is None:
        return None
    if not value >= 0 or value == float("inf"):
        raise UsageError("%s must be a number of seconds of at least 0, not %r" % (name, value))
    return value


def _eds(args, default=True):
    path = args.eds or (EDS_PATH if default else None)
    if path is None:
        return None, None
    return O.load_eds(path), os.path.basename(path)


# --- the command -------------------------------------------------------------------
def cmd_can(args):
    """Run the chosen CAN subcommand; its refusals and silences become one sentence."""
    # python-canopen logs each transfer it gives up ("Transfer aborted by client with code
    # 0x05040000") as an error of its own: the sentence below says it, once.
    logging.getLogger("canopen.sdo.client").setLevel(logging.CRITICAL)
    try:
        return args.can_fn(args)
    except NoAnswer as exc:
        return fail(EXIT_COMM, str(exc))
    except Refused as exc:
        return fail(EXIT_STATUS, str(exc))
    except can.CanError as exc:
        return fail(EXIT_PORT, "the SLCAN port failed: %s" % str(exc).rstrip("."))


def _out(args, text, data):
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        print(text)


def _sdo(node, what, label, fn):
    try:
        return fn()
    except canopen.SdoAbortedError as exc:
        raise Refused("node %d aborted the %s of %s: %s" % (node.id, what, label, cia301.abort_text(exc.code))) from None
    except canopen.SdoCommunicationError as exc:
        raise NoAnswer("node %d did not answer the %s of %s (%s); is the node there, at this bitrate?" % (
            node.id, what, label, str(exc).rstrip(".").lower())) from None


def _remote(network, nid, od, timeout):
    node = canopen.RemoteNode(nid, od if od is not None else canopen.ObjectDictionary())
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = timeout
    return node


# scan ---------------------------------------------------------------------------------
def _try_upload(node, index, sub):
    try:
        return node.sdo.upload(index, sub)
    except (canopen.SdoAbortedError, canopen.SdoCommunicationError):
        return None


def _u32(raw):
    return int.from_bytes(raw[:4], "little") if raw and len(raw) >= 4 else None


def describe_node(network, nid, timeout):
    """What scan shows of a node: device type and profile, name, identity (None where it aborted)."""
    node = _remote(network, nid, None, timeout)
    dtype = _u32(_try_upload(node, 0x1000, 0))
    name = _try_upload(node, 0x1008, 0)
    ident = [_u32(_try_upload(node, 0x1018, s)) for s in (1, 2, 3, 4)]
    return {
        "node": nid,
        "device_type": dtype,
        "profile": cia301.profile_name(dtype) if dtype is not None else None,
        "name": name.decode("ascii", "replace").rstrip("\x00") if name is not None else None,
        "vendor": ident[0], "product": ident[1], "revision": ident[2], "serial": ident[3],
    }


def _hex32(v):
    return "-" if v is None else "0x%08X" % v


def cmd_scan(args):
    rate, url = bitrate(args), port_of(args)
    wait = _seconds(args.wait, "--wait")
    with network_session(url, rate) as network:
        network.scanner.reset()
        network.scanner.search()
        time.sleep(wait)
        ids = sorted(network.scanner.nodes)
        rows = [describe_node(network, nid, timeout_s(args)) for nid in ids]
    if not rows:
        raise NoAnswer("no node answered on %s at %d bit/s within %g s" % (url, rate, wait))
    lines = []
    for r in rows:
        dtype = "device type -" if r["device_type"] is None else "%s (0x1000 = 0x%08X)" % (r["profile"], r["device_type"])
        lines.append("node %3d  %s" % (r["node"], dtype))
        lines.append("          name %s" % (repr(r["name"]) if r["name"] is not None else "-"))
        lines.append("          vendor %s  product %s  revision %s  serial %s" % (
            _hex32(r["vendor"]), _hex32(r["product"]), _hex32(r["revision"]), _hex32(r["serial"])))
    _out(args, "\n".join(lines), rows)
    return EXIT_OK


# nmt ----------------------------------------------------------------------------------
def cmd_nmt(args):
    target = node_id(args.node, allow_all=True)
    command = args.nmt_command.lower()
    if command not in cia301.NMT_COMMANDS:
        raise UsageError("NMT command must be one of %s, not %r" % (", ".join(cia301.NMT_COMMANDS), args.nmt_command))
    wait = _seconds(args.wait, "--wait")
    rate, url = bitrate(args), port_of(args)
    heard = {}  # node -> [states after the command, in order]

    def on_heartbeat(can_id, data, timestamp):
        if len(data) == 1:
            heard.setdefault(can_id - 0x700, []).append(data[0] & 0x7F)

    with network_session(url, rate) as network:
        for nid in ([target] if target else range(1, 128)):
            network.subscribe(0x700 + nid, on_heartbeat)
        network.send_message(0x000, bytes([cia301.NMT_COMMANDS[command], target]))
        end = time.monotonic() + wait
        while time.monotonic() < end:
            if target and any(s in NMT_EXPECT[command] for s in heard.get(target, ())):
                time.sleep(0.05)  # a reset's boot-up: its first heartbeat may follow at once
                break
            time.sleep(0.01)
    states = {nid: [cia301.nmt_state_name(s) for s in seq] for nid, seq in sorted(heard.items())}
    who = "node %d" % target if target else "all nodes"
    lines = ["NMT %s sent to %s" % (cia301.NMT_COMMAND_NAMES[cia301.NMT_COMMANDS[command]], who)]
    if wait:
        if target and target not in states:
            lines.append("nothing heard from node %d within %g s to confirm it (heartbeat off, or no such node)"
                         % (target, wait))
        for nid, seq in states.items():
            lines.append("node %d: %s (heartbeat)" % (nid, " -> ".join(_collapse(seq))))
    _out(args, "\n".join(lines), {"command": command, "node": target or "all",
                                  "heard": {str(n): s[-1] for n, s in states.items()}})
    return EXIT_OK


def _collapse(seq):
    out = []
    for s in seq:
        if not out or out[-1] != s:
            out.append(s)
    return out


# sdo ----------------------------------------------------------------------------------
def _targets(args, od, eds_name):
    target = O.find(od, args.object, eds_name, force=args.force)
    if target.var is None and target.container is not None and target.sub == 0 and ":" not in args.object:
        return [O.Target(target.index, v.subindex, v, target.container) for v in O.members(target.container)]
    return [target]


def _row(nid, t, raw):
    row = {"node": nid, "index": t.index, "subindex": t.sub, "name": O.object_name(t.var, t.container) or None,
           "raw": raw.hex()}
    if t.var is None:
        row.update(type=None, value=raw.hex(), text=raw.hex(" ").upper() or "(empty)")
        return row
    try:
        value = O.decode(t.var, raw)
    except ValueError as exc:
        row.update(type=O.type_info(t.var)[0], value=raw.hex(), text="%s (%s)" % (raw.hex(" ").upper(), exc))
        return row
    row.update(type=O.type_info(t.var)[0], value=O.jsonable(value), text=O.show(t.var, value))
    return row


def cmd_sdo_read(args):
    nid = node_id(args.node)
    od, eds_name = _eds(args)
    targets = _targets(args, od, eds_name)
    for t in targets:
        if t.var is not None and t.var.access_type == "wo" and not args.force:
            raise UsageError("%s is write-only (access wo in %s; --force sends the read anyway)" % (t.label, eds_name))
    rate, url = bitrate(args), port_of(args)
    rows, aborted = [], []
    with network_session(url, rate) as network:
        node = _remote(network, nid, od, timeout_s(args))
        for t in targets:
            if len(targets) > 1:
                try:
                    raw = _sdo(node, "read", t.label, lambda: node.sdo.upload(t.index, t.sub))
                except Refused as exc:
                    aborted.append(str(exc))
                    rows.append({"node": nid, "index": t.index, "subindex": t.sub,
                                 "name": O.object_name(t.var, t.container) or None, "abort": str(exc)})
                    continue
            else:
                raw = _sdo(node, "read", t.label, lambda: node.sdo.upload(t.index, t.sub))
            rows.append(_row(nid, t, raw))
    lines = []
    for t, r in zip(targets, rows):
        lines.append("node %d %s = %s" % (nid, t.label, r["text"]) if "abort" not in r else
                     "node %d %s: aborted (%s)" % (nid, t.label, r["abort"]))
    _out(args, "\n".join(lines), rows[0] if len(rows) == 1 else rows)
    if aborted and len(aborted) == len(targets):
        return fail(EXIT_STATUS, aborted[0])
    return EXIT_OK


def cmd_sdo_write(args):
    nid = node_id(args.node)
    od, eds_name = _eds(args)
    t = O.find(od, args.object, eds_name, force=args.force)
    if t.var is None and t.container is not None and ":" not in args.object:
        raise UsageError("0x%04X %s has sub-indexes: give one, e.g. 0x%04X:1" % (t.index, t.container.name, t.index))
    if t.var is None:
        data = O.parse_hex(args.value, "%s (not in %s: hex bytes, least significant first)" % (t.label, eds_name))
        shown = data.hex(" ").upper()
    else:
        if t.var.access_type in ("ro", "const") and not args.force:
            raise UsageError("%s is read-only (access %s in %s; --force sends the write anyway)" % (
                t.label, t.var.access_type, eds_name))
        value = O.parse_value(t.var, args.value, t.label, force=args.force)
        data = O.encode(t.var, value)
        shown = O.show(t.var, value)
    rate, url = bitrate(args), port_of(args)
    with network_session(url, rate) as network:
        node = _remote(network, nid, od, timeout_s(args))
        _sdo(node, "write", t.label, lambda: node.sdo.download(t.index, t.sub, data))
    _out(args, "node %d %s := %s" % (nid, t.label, shown),
         {"node": nid, "index": t.index, "subindex": t.sub, "name": O.object_name(t.var, t.container) or None,
          "raw": data.hex(), "written": True})
    return EXIT_OK


# sdo dump / load ------------------------------------------------------------------------
DRIVE_OBJECTS = paramset402.DRIVE_KEYS  # [drive] key -> (index, sub) a parameter set names its drive by


def _drive_identity(node):
    """The [drive] values of a node ({key: int or None}) and its 0x1008 name (None if it aborted);
    NoAnswer when it does not answer the first (0x1000, which every CANopen node has)."""
    _sdo(node, "read", "0x1000:00 Device type", lambda: node.sdo.upload(0x1000, 0))
    ident = {k: _u32(_try_upload(node, index, sub)) for k, (index, sub) in DRIVE_OBJECTS.items()}
    name = _try_upload(node, 0x1008, 0)
    return ident, (name.decode("ascii", "replace").rstrip("\x00") if name is not None else None)


def cmd_sdo_dump(args):
    nid = node_id(args.node)
    od, eds_name = _eds(args)
    objs = paramset402.select(od, args.objects, eds_name) if args.objects else paramset402.default_objects(od)
    rate, url = bitrate(args), port_of(args)
    values = []
    with network_session(url, rate) as network:
        node = _remote(network, nid, od, timeout_s(args))
        ident, name = _drive_identity(node)
        for index, sub, var in objs:
            t = O.Target(index, sub, var)
            raw = _sdo(node, "read", t.label, lambda: node.sdo.upload(index, sub))
            try:
                values.append((index, sub, var, O.decode(var, raw)))
            except ValueError as exc:
                raise Refused("node %d answered %s with %s: %s" % (nid, t.label, raw.hex(" ").upper(), exc)) from None
    if args.json:
        print(json.dumps({"node": nid, "drive": ident, "name": name, "objects": [
            {"index": i, "subindex": s, "name": O.object_name(v), "value": O.jsonable(val)}
            for i, s, v, val in values]}, indent=2))
    else:
        sys.stdout.write(paramset402.dumps(values, nid, ident, name))
    return EXIT_OK


def cmd_sdo_load(args):
    from motorjig.tomlsource import SourceError

    nid = node_id(args.node)
    od, eds_name = _eds(args)
    try:
        ps = paramset402.load(args.file, od, eds_name, writable=True)
    except SourceError as exc:
        raise UsageError(str(exc).rstrip(".")) from None
    rate, url = bitrate(args), port_of(args)
    with network_session(url, rate) as network:
        node = _remote(network, nid, od, timeout_s(args))
        if ps.drive:
            ident, _ = _drive_identity(node)
            for k, want in ps.drive.items():
                if ident[k] != want:
                    index, sub = DRIVE_OBJECTS[k]
                    raise UsageError("%s is for a drive of %s 0x%08X, node %d has %s (0x%04X:%d): nothing was written"
                                     % (args.file, k, want, nid, _hex32(ident[k]), index, sub))
        for e in ps.entries:
            _sdo(node, "write", e.label, lambda: node.sdo.download(e.index, e.sub, O.encode(e.var, e.value)))
        if args.store:
            save = int.from_bytes(b"save", "little").to_bytes(4, "little")
            _sdo(node, "write", "0x1010:01 Store parameters (save)", lambda: node.sdo.download(0x1010, 1, save))
    n = len(ps.entries)
    _out(args, "node %d: %d object%s from %s written%s" % (
        nid, n, "" if n == 1 else "s", args.file,
        " and stored (0x1010:01 \"save\")" if args.store else " (--store, or 0x1010:01 = save, keeps them)"),
         {"node": nid, "file": args.file, "written": n, "stored": args.store})
    return EXIT_OK


# dump ---------------------------------------------------------------------------------
def cmd_dump(args):
    if args.count is not None and args.count < 1:
        raise UsageError("--count must be at least 1, not %d" % args.count)
    duration = _seconds(args.duration, "--duration")
    if args.log:
        check_log_path(args.log)
    od, _ = _eds(args, default=False)
    rate, url = bitrate(args), port_of(args)
    text = FrameText(od)
    with bus_session(url, rate, listen_only=args.listen_only) as bus:
        n = run_dump(bus, text, args.count, duration, args.log, as_json=args.json)
    if not args.json:
        sys.stderr.write("%d frame%s%s\n" % (n, "" if n == 1 else "s", " logged to %s" % args.log if args.log else ""))
    return EXIT_OK


# lss ----------------------------------------------------------------------------------
def _lss(fn, what):
    try:
        return fn()
    except LssError as exc:
        text = str(exc)
        if "No LSS response" in text:
            raise NoAnswer("no node answered the LSS %s (is a node in configuration state? lss fast-scan or "
                           "--identity puts one there)" % what) from None
        raise Refused("the node refused the LSS %s: %s" % (what, text.replace("LSS Error", "error code"))) from None


def cmd_lss(args):
    action = args.lss_action
    ident = identity(args.identity) if getattr(args, "identity", None) else None
    if args.lss_timeout < 1:
        raise UsageError("--lss-timeout must be at least 1 ms, not %d" % args.lss_timeout)
    new_id = new_rate = None
    if action == "set-id":
        new_id = _int(args.new_id)
        if new_id is None or not (1 <= new_id <= 127 or new_id == 255):
            raise UsageError("node id must be 1..127 (or 255: unconfigured), not %r" % args.new_id)
    if action == "set-bitrate":
        new_rate = _int(args.new_bitrate)
        if new_rate not in LSS_BIT_TIMING:
            raise UsageError("LSS bitrate must be one of the CiA table's %s, not %r" % (
                ", ".join(map(str, sorted(LSS_BIT_TIMING))), args.new_bitrate))
    rate, url = bitrate(args), port_of(args)
    result = {"action": action}
    lines = []
    with network_session(url, rate) as network:
        lss = network.lss
        lss.RESPONSE_TIMEOUT = args.lss_timeout / 1000.0
        if action == "fast-scan":
            found, ids = _lss(lss.fast_scan, "fast scan")
            if not found:
                raise NoAnswer("no unconfigured node answered the LSS fast scan")
            result["identity"] = dict(zip(("vendor", "product", "revision", "serial"), ids))
            lines.append("found an unconfigured node: vendor 0x%08X  product 0x%08X  revision 0x%08X  serial 0x%08X"
                         % tuple(ids))
            lines.append("it is now in LSS configuration state: jigctl can lss set-id NEW")
        else:
            if ident is not None:
                try:
                    ok = lss.send_switch_state_selective(*ident)
                except LssError:  # no answer to its last part
                    ok = False
                if not ok:
                    raise NoAnswer("no node has the LSS address %s (vendor,product,revision,serial)" % args.identity)
            if action == "set-id":
                _lss(lambda: lss.configure_node_id(new_id), "configure node id")
                lines.append("node id %d configured" % new_id)
                result["node_id"] = new_id
            elif action == "set-bitrate":
                _lss(lambda: lss.configure_bit_timing(LSS_BIT_TIMING[new_rate]), "configure bit timing")
                lines.append("bitrate %d bit/s configured (table index %d)" % (new_rate, LSS_BIT_TIMING[new_rate]))
                result["bitrate"] = new_rate
            elif action == "inquire":
                nid = _lss(lss.inquire_node_id, "inquire node id")
                parts = [_lss(lambda cs=cs: lss.inquire_lss_address(cs), "inquire identity") for cs in (0x5A, 0x5B, 0x5C, 0x5D)]
                result["node_id"] = nid
                result["identity"] = dict(zip(("vendor", "product", "revision", "serial"), parts))
                lines.append("node id %d  vendor 0x%08X  product 0x%08X  revision 0x%08X  serial 0x%08X"
                             % tuple([nid] + parts))
            if action == "store" or getattr(args, "store", False):
                _lss(lss.store_configuration, "store configuration")
                lines.append("configuration stored")
            if not args.stay:
                lss.send_switch_state_global(lss.WAITING_STATE)
                lines.append("every node switched back to LSS waiting state")
    _out(args, "\n".join(lines), result)
    return EXIT_OK
