"""The Desk's CAN link: the jig's SLCAN port on python-can and python-canopen, without any web code.

One ``CanLink`` per Desk server, shared by every browser tab like the bus session.
``open(url, bitrate)`` opens the SLCAN port as ``jigctl can`` does
(``motorjig.can.port.open_bus``: the port must answer SLCAN's ``V`` first, then
python-can's own ``slcan`` interface on it: a device, a pty or a ``socket://``
URL); python-canopen's ``Network`` then runs on that bus, its notifier thread
reading the port. Every frame read or sent goes into a bounded log, named as
``jigctl can dump`` names it (``motorjig.can.cia301``/``dump.FrameText`` with the
EDS: NMT, SYNC, EMCY with its error code named, TPDO/RPDO n with their mapped
objects, SDO rx/tx with the object's name and value, heartbeat with its state,
LSS); heartbeats give each node's NMT state.

``scan()`` is python-canopen's scanner (its request paced in blocks the jig's TX FIFO
takes: ``_search``) followed by each node's
device type (0x1000), name (0x1008) and identity (0x1018) by SDO
(``jigctl can scan``'s ``describe_node``); ``sdo_read``/``sdo_write`` take an
object as ``index:sub`` or by its name in the EDS (``motorjig.can.EDS_PATH``
unless another is given) and type values from it (``motorjig.can.objects``); an
SDO abort is named (CiA 301's table).

The methods block (an SDO transfer waits for its answer): the page runs them in a
worker thread. Every failure the operator can meet is a ``UserError`` with one
sentence; a port that fails while open switches the link to ``lost``.
"""

import collections
import os
import threading
import time

import can
import canopen

from motorjig.can import EDS_PATH, cia301
from motorjig.can import objects as O
from motorjig.can.cancmd import describe_node
from motorjig.can.dump import FrameText
from motorjig.can.port import NOTIFIER_CYCLE_S, SLCAN_BITRATES, open_bus
from motorjig.commands import UsageError
from motorjig.desk.axes import LinkAxis
from motorjig.desk.canaxis import parse_node_id
from motorjig.desk.session import UserError
from motorjig.errors import PortError

BITRATES = SLCAN_BITRATES  # S0..S8
LOG_SIZE = 2000  # frames kept for the tab's log (the newest)
SDO_TIMEOUT = 1.0  # seconds an SDO answer may take (through the jig and a PC's USB)
SCAN_WAIT = 0.6  # seconds the scan listens for answers after its requests
SCAN_BLOCK = 16  # scan requests sent at once (the jig's TX FIFO holds 64 frames; see _search)
SCAN_REQUEST = b"\x40\x00\x10\x00\x00\x00\x00\x00"  # python-canopen's scanner's: upload 0x1000:00
HEARTBEAT_STALE = 3.0  # a node silent this long is shown as silent, with its last state

#: the tab's NMT choices: jigctl can nmt's command -> words
NMT_CHOICES = {"start": "start", "preop": "pre-operational", "stop": "stop", "reset": "reset node",
               "reset-comm": "reset communication"}

FrameEntry = collections.namedtuple("FrameEntry", "seq t direction can_id ext rtr data text")
FrameEntry.__doc__ = "One frame of the log: direction 'rx' (from the bus) or 'tx' (sent by the Desk)."


def format_entry(e):
    """One log line: time, direction, id, length, data bytes, the CANopen meaning."""
    stamp = time.strftime("%H:%M:%S", time.localtime(e.t)) + ".%03d" % int(e.t % 1 * 1000)
    ident = ("%08X" if e.ext else "%03X") % e.can_id
    data = "remote" if e.rtr else bytes(e.data).hex(" ").upper()
    return "%s  %s  %s  [%d]  %-23s  %s" % (stamp, e.direction.upper(), ident, len(e.data), data, e.text)


def _hex32(v):
    return "" if v is None else "0x%08X" % v


class CanLinkAxis(LinkAxis):
    """The CAN tab's SLCAN port as one of the Desk's axes (``axes.DeskAxis``): STOP reaches its
    CiA 402 axis, and a run whose drive kind needs ``can_port`` borrows it."""

    title = "the CAN tab's SLCAN port"
    run_port = "can_port"
    missing = ("the jig's SLCAN port is not known: start the Desk with --can-port (or choose the SLCAN port in the "
               "CAN tab)")

    refusal = UserError

    def stop(self, emergency):
        return self.link.axis.stop(emergency)

    def port(self):
        return self.link.url

    def reopen_with(self):
        return self.link.bitrate if self.link.is_open else None

    def reopen(self, bitrate):
        self.link.open(self.link.url, bitrate)


class CanLink:
    """The SLCAN port, its CANopen network, the frame log and the node list (see the module docstring).

    ``url``/``bitrate``: what the tab offers to open (``--can-port``, or the bench's).
    ``read_only``: the port is opened listen-only and nothing is sent (the Desk's ``--read-only``).
    """

    def __init__(self, url="", bitrate=500000, eds=EDS_PATH, read_only=False, log_size=LOG_SIZE,
                 sdo_timeout=SDO_TIMEOUT):
        self.url = url or ""
        self.bitrate = bitrate
        self.eds = eds
        self.read_only = read_only
        self.sdo_timeout = sdo_timeout
        self.state = "closed"  # open, lost
        self.reason = ""  # why the port was lost
        self.opened_at = 0.0
        self.rx = self.tx = 0  # frames since open
        self.nodes = {}  # id -> row of the last scan
        self.heartbeats = {}  # id -> (state byte, time)
        self.emcys = {}  # id -> (error code, error register, time) of its last EMCY
        self.scanning = False
        self.lent = ""  # what has the port now (a CiA 402 test run of the Test tab): Open is refused
        self.keep = log_size
        self._od = None
        self._text = FrameText()  # frame names; with the EDS's objects once it is read
        self._net = None
        self._log = collections.deque(maxlen=log_size)
        self._seq = 0
        self._log_lock = threading.Lock()
        self._lock = threading.RLock()  # one job (open, close, scan, an SDO transfer) at a time
        from motorjig.desk.canaxis import CanAxis

        self.axis = CanAxis(self)  # the CAN tab's CiA 402 axis: made safe before the port closes
        self.desk_axis = CanLinkAxis(self)  # what the page's STOP and the Test tab see of it

    # --- the frame log -------------------------------------------------------------------------------
    def _frame(self, direction, can_id, ext, rtr, data, t=None):
        t = time.time() if t is None else t
        data = bytes(data)
        if direction == "rx" and not ext and not rtr and 0x701 <= can_id <= 0x77F and data:
            self.heartbeats[can_id & 0x7F] = (data[0] & 0x7F, t)
        elif direction == "rx" and not ext and not rtr and 0x81 <= can_id <= 0xFF and len(data) >= 3:
            self.emcys[can_id & 0x7F] = (data[0] | data[1] << 8, data[2], t)
        ft = self._text
        try:
            text = cia301.describe_frame(can_id, data, ext, rtr, ft.od_name, ft.od_decode, ft.pdo_decode)
        except Exception:  # a frame the tables cannot make sense of: its id says enough
            text = ""
        text = text or ("extended frame (not CANopen's)" if ext else "frame 0x%03X" % can_id)
        with self._log_lock:
            self._seq += 1
            if direction == "rx":
                self.rx += 1
            else:
                self.tx += 1
            self._log.append(FrameEntry(self._seq, t, direction, can_id, ext, rtr, data, text))

    def frames_since(self, seq):
        """The log's frames after seq (all it keeps when older ones were dropped), the newest last."""
        with self._log_lock:
            if self._log and self._log[0].seq > seq:
                return list(self._log)
            return [e for e in self._log if e.seq > seq]

    @property
    def last_seq(self):
        return self._seq

    def clear_log(self):
        with self._log_lock:
            self._log.clear()

    def log_text(self):
        with self._log_lock:
            entries = list(self._log)
        return "".join(format_entry(e) + "\n" for e in entries)

    # --- open / close ----------------------------------------------------------------------------------
    @property
    def is_open(self):
        return self.state == "open"

    def summary(self):
        """One line: the port's state."""
        if self.state == "open":
            return "open: %s at %d kbit/s%s; %d frames in, %d out" % (
                self.url, self.bitrate // 1000, ", listen-only" if self.read_only else "", self.rx, self.tx)
        if self.state == "lost":
            return "port lost: %s" % self.reason
        if self.lent:
            return "lent to %s" % self.lent
        return "closed"

    def open(self, url=None, bitrate=None):
        """Open the SLCAN port at bitrate (checked with V, then python-can's slcan), start the CANopen
        network on it; returns a sentence."""
        url = str(url if url is not None else self.url).strip()
        try:
            bitrate = int(bitrate if bitrate is not None else self.bitrate)
        except (TypeError, ValueError):
            bitrate = None
        if bitrate not in BITRATES:
            raise UserError("the CAN bitrate must be one of %s" % ", ".join(map(str, BITRATES)))
        if not url:
            raise UserError("no SLCAN port: give the jig's third USB port (e.g. /dev/ttyACM2) or a pyserial URL")
        with self._lock:
            if self.lent:
                raise UserError("the SLCAN port is lent to %s: it comes back with its verdict" % self.lent)
            if self._net is not None:
                raise UserError("the SLCAN port %s is open: close it first" % self.url)
            self._od_of_eds()  # a broken EDS is said before the port opens
            try:
                bus = open_bus(url, bitrate, listen_only=self.read_only)
            except PortError as exc:
                raise UserError(str(exc).rstrip(".")) from None
            net = _Network(bus, self)
            net.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
            net.listeners.append(_Tap(self))
            try:
                net.connect()
            except Exception as exc:
                _quietly(bus.shutdown)
                raise UserError("cannot start CANopen on %s: %s" % (url, _reason(exc))) from None
            self._net = net
            self.url, self.bitrate = url, bitrate
            self.state, self.reason = "open", ""
            self.opened_at = time.time()
            with self._log_lock:
                self.rx = self.tx = 0
            self.heartbeats.clear()
            self.emcys.clear()
        return "SLCAN port %s open at %d kbit/s%s" % (url, bitrate // 1000,
                                                      ", listen-only (read-only Desk)" if self.read_only else "")

    def close(self):
        """Close the port (python-can sends SLCAN's C); returns a sentence. A node the CAN axis enabled
        (or the one it watches, when enabled) is quick-stopped and disabled first."""
        problems = self.axis.make_safe() if self._net is not None and self.state == "open" else []
        with self._lock:
            net, self._net = self._net, None
            was = self.state
            self.state = "closed"
            if net is None:
                if was == "lost":
                    return "closed (the port had been lost: %s)" % self.reason
                raise UserError("the SLCAN port is not open")
            _quietly(net.disconnect)
        if problems:
            return "SLCAN port %s closed; making the axis safe first met: %s" % (self.url, "; ".join(problems))
        return "SLCAN port %s closed" % self.url

    def _lost(self, exc):
        if self.state == "open":
            self.reason = "%s: %s" % (self.url, _reason(exc))
            self.state = "lost"

    def _network(self):
        if self.read_only:
            raise UserError("refused: this Desk is read-only (--read-only): the CAN port is only listened to")
        net = self._net
        if self.state == "lost":
            raise UserError("the SLCAN port was lost (%s): close it and open it again" % self.reason)
        if net is None:
            if self.lent:
                raise UserError("the SLCAN port is lent to %s: it comes back with its verdict" % self.lent)
            raise UserError("the SLCAN port is not open: choose it and press Open")
        return net

    def _od_of_eds(self):
        if self._od is None:
            try:
                self._od = O.load_eds(self.eds)
            except UsageError as exc:
                raise UserError(str(exc)) from None
            self._text = FrameText(self._od)
        return self._od

    def _node(self, net, node_id):
        nid = parse_node_id(node_id)
        node = net.get(nid)
        if node is None or node.object_dictionary is not self._od:
            if node is not None:
                del net[nid]
            node = net.add_node(nid, self._od_of_eds())
        node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout
        return node

    # --- scan ------------------------------------------------------------------------------------------------
    def scan(self, wait=SCAN_WAIT):
        """python-canopen's scanner (an SDO upload of 0x1000 to every id, paced), then each node's device type,
        name and identity by SDO; returns the rows (also kept in ``nodes``)."""
        with self._lock:
            net = self._network()
            self.scanning = True
            try:
                net.scanner.reset()
                try:
                    self._search(net)
                except Exception as exc:
                    raise UserError(self._failure("scanning", exc)) from None
                time.sleep(wait)
                rows = {}
                for nid in sorted(set(net.scanner.nodes) | set(self.heartbeats)):
                    try:
                        r = describe_node(net, nid, self.sdo_timeout)
                    except Exception as exc:
                        raise UserError(self._failure("scanning node %d" % nid, exc)) from None
                    finally:
                        net.pop(nid, None)  # describe_node's node has no EDS: SDO adds its own
                    rows[nid] = {"id": nid, "name": r["name"] or "", "profile": r["profile"] or "",
                                 "device_type": _hex32(r["device_type"]), "vendor": _hex32(r["vendor"]),
                                 "product": _hex32(r["product"]), "revision": _hex32(r["revision"]),
                                 "serial": _hex32(r["serial"])}
                self.nodes = rows
            finally:
                self.scanning = False
        return list(rows.values())

    def _search(self, net):
        """The request of python-canopen's ``scanner.search()`` to ids 1..127, in blocks of SCAN_BLOCK
        with the time they take on the bus between them: sent at once, as search() does, 127 frames
        outrun the jig's TX FIFO and about 20 of them are refused (SLCAN's BEL, which python-can does
        not report), so nodes with high ids would go unseen. The scanner still collects the answers."""
        frame_s = 135.0 / self.bitrate  # an 8-byte standard frame with worst-case stuffing
        for first in range(1, 128, SCAN_BLOCK):
            for nid in range(first, min(first + SCAN_BLOCK, 128)):
                net.send_message(0x600 + nid, SCAN_REQUEST)
            time.sleep(SCAN_BLOCK * frame_s + 0.002)

    def node_rows(self, now=None):
        """The node list: the last scan's rows and every node heard since, each with its NMT state
        from its heartbeats."""
        now = time.time() if now is None else now
        rows = {nid: dict(r) for nid, r in self.nodes.items()}
        for nid in list(self.heartbeats):
            rows.setdefault(nid, {"id": nid, "name": "(heard, not scanned)", "profile": "", "device_type": "",
                                  "vendor": "", "product": "", "revision": "", "serial": ""})
        for nid, row in rows.items():
            beat = self.heartbeats.get(nid)
            if beat is None:
                row["nmt"] = "no heartbeat heard"
            else:
                state = cia301.nmt_state_name(beat[0])
                age = now - beat[1]
                row["nmt"] = state if age < HEARTBEAT_STALE else "%s, silent for %.0f s" % (state, age)
        return [rows[k] for k in sorted(rows)]

    # --- NMT -------------------------------------------------------------------------------------------------
    def nmt(self, command, node_id=0):
        """Send an NMT command (``NMT_CHOICES``: jigctl can nmt's names) to one node or, node_id 0, to
        all; returns a sentence."""
        if command not in cia301.NMT_COMMANDS:
            raise UserError("NMT command must be one of %s, not %r" % (", ".join(cia301.NMT_COMMANDS), command))
        nid = 0 if str(node_id).strip().lower() in ("", "0", "all") else parse_node_id(node_id)
        with self._lock:
            net = self._network()
            nmt = net.nmt if nid == 0 else canopen.nmt.NmtMaster(nid)
            nmt.network = net
            try:
                nmt.send_command(cia301.NMT_COMMANDS[command])
            except Exception as exc:
                raise UserError(self._failure("sending NMT %s" % command, exc)) from None
        return "NMT %s sent to %s" % (NMT_CHOICES.get(command, command), "all nodes" if nid == 0 else "node %d" % nid)

    # --- SDO -------------------------------------------------------------------------------------------------
    def _target(self, what):
        try:
            return O.find(self._od_of_eds(), str(what or ""), os.path.basename(self.eds), force=True)
        except UsageError as exc:
            raise UserError(str(exc)) from None

    def sdo_read(self, node_id, what):
        """Upload an object (``index:sub`` or its EDS name; a record: each of its sub-indices);
        returns (label, value text)."""
        with self._lock:
            net = self._network()
            node = self._node(net, node_id)
            t = self._target(what)
            if t.var is None and t.container is not None:
                parts = []
                for var in O.members(t.container):
                    parts.append("%d %s = %s" % (var.subindex, var.name, self._upload(node, var.index,
                                                                                      var.subindex, var)))
                return t.label, "; ".join(parts)
            return t.label, self._upload(node, t.index, t.sub, t.var)

    def _upload(self, node, index, sub, var):
        label = "0x%04X:%02X" % (index, sub)
        try:
            raw = node.sdo.upload(index, sub)
        except Exception as exc:
            raise UserError(self._failure("the upload of %s" % label, exc, node.id)) from None
        if var is not None:
            try:
                return O.show(var, O.decode(var, raw))
            except Exception:  # not the EDS's size: the bytes as they came
                pass
        return "%s (not in the EDS: the bytes)" % (bytes(raw).hex(" ").upper() or "no bytes")

    def sdo_write(self, node_id, what, value_text):
        """Download a value, typed as the EDS says, to an object; returns (label, value text)."""
        with self._lock:
            net = self._network()
            node = self._node(net, node_id)
            t = self._target(what)
            if t.var is None:
                if t.container is not None:
                    raise UserError("%s has sub-indices: name one to write, e.g. 0x%04X:1" % (t.label, t.index))
                raise UserError("%s is not in the EDS: its type is unknown, so nothing was written" % t.label)
            if not t.var.writable:
                raise UserError("%s is %s in the EDS: it cannot be written" % (
                    t.label, {"ro": "read-only", "const": "a constant"}.get(t.var.access_type, t.var.access_type)))
            try:
                value = O.parse_value(t.var, str(value_text or ""), t.label)
                data = O.encode(t.var, value)
            except UsageError as exc:
                raise UserError(str(exc)) from None
            except (ValueError, TypeError) as exc:
                raise UserError("%s cannot hold %r: %s" % (t.label, value_text, exc)) from None
            try:
                node.sdo.download(t.index, t.sub, data)
            except Exception as exc:
                raise UserError(self._failure("the download of %s" % t.label, exc, node.id)) from None
        return t.label, O.show(t.var, value)

    def _failure(self, what, exc, node_id=None):
        """One sentence for an SDO or bus failure (an abort by its name, a silent node, a lost port)."""
        who = "node %d" % node_id if node_id is not None else "the bus"
        if isinstance(exc, canopen.SdoAbortedError):
            return "%s aborted %s: %s" % (who, what, cia301.abort_text(exc.code))
        if isinstance(exc, canopen.SdoCommunicationError):
            return "%s did not answer %s (%s)" % (who, what, str(exc).rstrip(".").lower() or "no answer")
        self._lost(exc)
        return "%s failed: %s" % (what, _reason(exc))


def _reason(exc):
    return (str(exc).strip() or type(exc).__name__).rstrip(".")


def _quietly(fn):
    try:
        fn()
    except Exception:
        pass


class _Network(canopen.Network):
    """python-canopen's Network; every frame it sends is also logged (SLCAN does not echo them)."""

    def __init__(self, bus, link):
        super().__init__(bus)
        self.link = link

    def send_message(self, can_id, data, remote=False):
        super().send_message(can_id, data, remote)
        self.link._frame("tx", can_id, can_id > 0x7FF, remote, data)


class _Tap(can.Listener):
    """Every received frame into the link's log; a failing port makes the link lost."""

    def __init__(self, link):
        self.link = link

    def on_message_received(self, msg):
        if not msg.is_error_frame:
            self.link._frame("rx", msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.data)

    def on_error(self, exc):
        self.link._lost(exc)

    def stop(self):
        pass


__all__ = ["BITRATES", "CanLink", "FrameEntry", "NMT_CHOICES", "format_entry"]
