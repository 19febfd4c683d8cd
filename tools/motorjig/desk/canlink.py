"""The Desk's CAN link: the jig's SLCAN port on python-can and python-canopen, without any web code.

One ``CanLink`` per Desk server, shared by every browser tab like the bus session.
``open(url, bitrate)`` opens the SLCAN port with python-can's own ``slcan``
interface (a device, a pty or a ``socket://`` URL: it opens ports with pyserial's
``serial_for_url``) and checks that an SLCAN adapter answers its ``V`` command;
python-canopen's ``Network`` then runs on that bus, with its notifier thread
reading the port. Every frame read or sent goes into a bounded log, named as
CANopen names it (``describe``: NMT, SYNC, EMCY with its error code named,
TPDO/RPDO n, SDO rx/tx, heartbeat with its state, LSS); heartbeats give each
node's NMT state.

``scan()`` is python-canopen's ``network.scanner.search()`` followed by SDO reads
of each node's device type (0x1000), name (0x1008) and identity (0x1018);
``sdo_read``/``sdo_write`` take an object as ``index:sub`` or by its name in the
EDS (``motorjig.can.EDS_PATH`` unless another is given) and type values from it;
an SDO abort is named (python-canopen's table of CiA 301's abort codes).

The methods block (an SDO transfer waits for its answer): the page runs them in a
worker thread. Every failure the operator can meet is a ``UserError`` with one
sentence; a port that fails while open switches the link to ``lost``.
"""

import collections
import struct
import threading
import time

import can
import canopen
from canopen.emcy import EmcyError
from canopen.objectdictionary import ODVariable
from canopen.objectdictionary import datatypes as T
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from motorjig.can import EDS_PATH
from motorjig.desk.session import UserError

#: the bitrates of SLCAN's S0..S8 (python-can's slcan table, the jig's SLCAN_BITRATES)
BITRATES = (10000, 20000, 50000, 100000, 125000, 250000, 500000, 750000, 1000000)
LOG_SIZE = 2000  # frames kept for the tab's log (the newest)
SDO_TIMEOUT = 1.0  # seconds an SDO answer may take (through the jig and a PC's USB)
SCAN_WAIT = 0.6  # seconds the scan listens for answers after its requests
VERSION_WAIT = 1.0  # seconds the port has to answer SLCAN's V before it is called no SLCAN port
HEARTBEAT_STALE = 3.0  # a node silent this long is shown as silent, with its last state

#: NMT commands (CiA 301): the tab's buttons
NMT_COMMANDS = {"start": 0x01, "stop": 0x02, "pre-operational": 0x80, "reset node": 0x81,
                "reset communication": 0x82}
NMT_COMMAND_NAMES = {v: k for k, v in NMT_COMMANDS.items()}

#: the NMT state a heartbeat carries (0x00 is the boot-up message)
NMT_STATES = {0x00: "boot-up", 0x04: "stopped", 0x05: "operational", 0x7F: "pre-operational"}

#: EMCY error codes (CiA 301 / CiA 402) by name; others by their class (python-canopen's table)
EMCY_CODES = {0x0000: "error reset", 0x1000: "generic error", 0x2310: "continuous overcurrent",
              0x3210: "DC link overvoltage", 0x3220: "DC link undervoltage", 0x4210: "device overtemperature",
              0x5000: "device hardware", 0x6000: "device software", 0x8110: "CAN overrun",
              0x8120: "CAN error passive", 0x8130: "heartbeat or life guard error", 0x8140: "recovered from bus-off",
              0x8611: "following error", 0x8612: "reference limit", 0xFF00: "device specific"}

#: CiA device profiles: the low 16 bits of 0x1000
PROFILES = {0: "no profile", 401: "CiA 401 I/O", 402: "CiA 402 drive", 404: "CiA 404 measuring",
            406: "CiA 406 encoder", 418: "CiA 418 battery", 419: "CiA 419 charger"}

FrameEntry = collections.namedtuple("FrameEntry", "seq t direction can_id ext rtr data text")
FrameEntry.__doc__ = "One frame of the log: direction 'rx' (from the bus) or 'tx' (sent by the Desk)."


# --- naming frames -------------------------------------------------------------------------------------
def emcy_name(code):
    """An EMCY error code in words: its own name, else its class (python-canopen's table)."""
    if code in EMCY_CODES:
        return EMCY_CODES[code]
    desc = EmcyError(code, 0, b"", 0).get_desc()
    return (desc.lower() + " error") if desc else "unknown error"


def abort_name(code):
    """An SDO abort code in words (CiA 301, as python-canopen names them)."""
    text = SdoAbortedError.CODES.get(code)
    return text[0].lower() + text[1:] if text else "unknown abort code"


def _mux(data):
    if len(data) < 4:
        return "?"
    return "0x%04X:%02X" % (data[1] | data[2] << 8, data[3])


def _sdo_text(data, from_client):
    """The gist of one SDO frame: what a client asked, or what a server answered."""
    if not data:
        return "empty"
    cs = data[0] >> 5
    if cs == 4:
        code = struct.unpack_from("<I", data, 4)[0] if len(data) >= 8 else 0
        return "abort %s: 0x%08X %s" % (_mux(data), code, abort_name(code))
    if from_client:
        if cs == 1:
            if data[0] & 0x02:  # expedited: the value is in the frame
                n = 4 - (data[0] >> 2 & 3) if data[0] & 0x01 else 4
                return "download %s = %s" % (_mux(data), bytes(data[4:4 + n]).hex(" "))
            return "download %s (segmented)" % _mux(data)
        if cs == 2:
            return "upload %s" % _mux(data)
        if cs == 0:
            return "download segment"
        if cs == 3:
            return "upload segment request"
        return "block transfer" if cs in (5, 6) else "command %d" % cs
    if cs == 2:
        if data[0] & 0x02:
            n = 4 - (data[0] >> 2 & 3) if data[0] & 0x01 else 4
            return "upload %s = %s" % (_mux(data), bytes(data[4:4 + n]).hex(" "))
        return "upload %s (segmented)" % _mux(data)
    if cs == 3:
        return "download %s done" % _mux(data)
    if cs == 0:
        text = bytes(data[1:8 - (data[0] >> 1 & 7)])
        return "upload segment %r%s" % (text.decode("latin-1"), " (last)" if data[0] & 1 else "")
    if cs == 1:
        return "download segment done"
    return "block transfer" if cs in (5, 6) else "command %d" % cs


def describe(can_id, data=b"", ext=False, rtr=False):
    """A frame as CANopen names it (the predefined connection set of CiA 301)."""
    data = bytes(data)
    if ext:
        return "extended frame (not CANopen's)"
    fn, node = can_id & 0x780, can_id & 0x7F
    if can_id == 0x000:
        if len(data) >= 2:
            cmd = NMT_COMMAND_NAMES.get(data[0], "command 0x%02X" % data[0])
            return "NMT %s %s" % (cmd, "all nodes" if data[1] == 0 else "node %d" % data[1])
        return "NMT (short)"
    if can_id == 0x080:
        return "SYNC" + (" %d" % data[0] if data else "")
    if can_id == 0x100:
        return "TIME"
    if can_id == 0x7E5:
        return "LSS master request"
    if can_id == 0x7E4:
        return "LSS answer"
    if node == 0:
        return "frame 0x%03X" % can_id
    if fn == 0x080:
        if len(data) >= 3:
            code = data[0] | data[1] << 8
            return "EMCY node %d: 0x%04X %s (error register 0x%02X)" % (node, code, emcy_name(code), data[2])
        return "EMCY node %d" % node
    if fn in (0x180, 0x280, 0x380, 0x480):
        return "TPDO%d node %d%s" % (fn >> 8, node, " request (RTR)" if rtr else "")
    if fn in (0x200, 0x300, 0x400, 0x500):
        return "RPDO%d node %d" % ((fn >> 8) - 1, node)
    if fn == 0x580:
        return "SDO tx node %d: %s" % (node, _sdo_text(data, False))
    if fn == 0x600:
        return "SDO rx node %d: %s" % (node, _sdo_text(data, True))
    if fn == 0x700:
        if rtr:
            return "node guarding request node %d" % node
        if not data:
            return "heartbeat node %d (empty)" % node
        if data[0] == 0:
            return "boot-up node %d" % node
        return "heartbeat node %d: %s" % (node, NMT_STATES.get(data[0] & 0x7F, "state 0x%02X" % data[0]))
    return "frame 0x%03X" % can_id


def format_entry(e):
    """One log line: time, direction, id, length, data bytes, the CANopen name."""
    stamp = time.strftime("%H:%M:%S", time.localtime(e.t)) + ".%03d" % int(e.t % 1 * 1000)
    ident = ("%08X" if e.ext else "%03X") % e.can_id
    data = "remote" if e.rtr else bytes(e.data).hex(" ")
    return "%s  %s  %s  [%d]  %-23s  %s" % (stamp, e.direction.upper(), ident, len(e.data), data, e.text)


# --- objects and values ----------------------------------------------------------------------------------
def parse_object(text, od):
    """(index, sub, ODVariable or None) for ``index:sub`` (hex, ``0x`` optional: ``1008``,
    ``0x1018:2``), or an object's name in the EDS (``Manufacturer device name``,
    ``Identity object.Vendor-ID``). An index of the EDS without a sub-index means sub 0."""
    t = str(text or "").strip()
    if not t:
        raise UserError("which object? Give index:sub (e.g. 0x1008 or 0x1018:2) or its name in the EDS")
    head, _, sub_text = t.partition(":")
    try:
        index = int(head, 16)
        sub = int(sub_text, 16) if sub_text.strip() else 0
    except ValueError:
        index = None
    if index is not None:
        if not (0 <= index <= 0xFFFF and 0 <= sub <= 0xFF):
            raise UserError("%s is out of range: the index is 0..0xFFFF and the sub-index 0..0xFF" % t)
        var = od.get_variable(index, sub) if od is not None else None
        return index, sub, var
    if od is not None:
        try:
            obj = od[t]
        except KeyError:
            obj = _by_name_ignoring_case(od, t)
        if obj is not None:
            if not isinstance(obj, ODVariable):
                raise UserError("%s (0x%04X) has sub-indices: name one, e.g. 0x%04X:1 or %s.%s" % (
                    obj.name, obj.index, obj.index, obj.name, next(iter(obj.values())).name if len(obj) else "..."))
            return obj.index, obj.subindex, obj
    raise UserError("%s is neither index:sub (e.g. 0x1008 or 0x1018:2) nor an object's name in the EDS" % t)


def _by_name_ignoring_case(od, name):
    want = name.lower()
    for obj in od.values():
        if obj.name.lower() == want:
            return obj
        if "." in want and hasattr(obj, "values") and want.startswith(obj.name.lower() + "."):
            for var in obj.values():
                if "%s.%s" % (obj.name.lower(), var.name.lower()) == want:
                    return var
    return None


def object_label(index, sub, var):
    return "0x%04X:%02X%s" % (index, sub, " %s" % var.qualname if var is not None else "")


def parse_value(text, var):
    """The value typed in the tab as the object's type wants it (the EDS's data type)."""
    t = str(text if text is not None else "").strip()
    dt = var.data_type
    if dt in (T.VISIBLE_STRING, T.UNICODE_STRING):
        return str(text or "")
    if dt in (T.OCTET_STRING, T.DOMAIN):
        try:
            return bytes.fromhex(t.replace("0x", ""))
        except ValueError:
            raise UserError("%s takes bytes in hex (e.g. 01 02 0a), not %r" % (var.qualname, t)) from None
    if dt in T.FLOAT_TYPES:
        try:
            return float(t)
        except ValueError:
            raise UserError("%s takes a number, not %r" % (var.qualname, t)) from None
    if dt == T.BOOLEAN:
        low = t.lower()
        if low in ("1", "true", "on", "yes"):
            return True
        if low in ("0", "false", "off", "no"):
            return False
        raise UserError("%s takes true or false (1 or 0), not %r" % (var.qualname, t))
    if dt in T.INTEGER_TYPES:
        try:
            value = int(t.replace("_", ""), 0)
        except ValueError:
            raise UserError("%s takes a whole number (decimal or 0x hex), not %r" % (var.qualname, t)) from None
        bits = len(var)
        lo, hi = (-(1 << bits - 1), (1 << bits - 1) - 1) if dt in T.SIGNED_TYPES else (0, (1 << bits) - 1)
        if var.min is not None:
            lo = max(lo, var.min)
        if var.max is not None:
            hi = min(hi, var.max)
        if not lo <= value <= hi:
            raise UserError("%s takes %d..%d, not %d" % (var.qualname, lo, hi, value))
        return value
    raise UserError("%s is of a type this tab cannot write (0x%X)" % (var.qualname, dt or 0))


def show_value(value, var=None):
    """A read value as the tab shows it: numbers in decimal and hex, text quoted, bytes in hex."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        text = "%d (0x%0*X)" % (value, max(2, len(var) // 4) if var is not None else 2, value & (1 << 64) - 1) \
            if value >= 0 else "%d" % value
        if var is not None and value in var.value_descriptions:
            text += " %s" % var.value_descriptions[value]
        return text
    if isinstance(value, float):
        return "%g" % value
    if isinstance(value, str):
        return '"%s"' % value
    return bytes(value).hex(" ") or "(no bytes)"


# --- the link ---------------------------------------------------------------------------------------------
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
        self.version = None  # the adapter's answer to V: (hardware, software)
        self.serial = None  # its answer to N
        self.opened_at = 0.0
        self.rx = self.tx = 0  # frames since open
        self.nodes = {}  # id -> row of the last scan
        self.heartbeats = {}  # id -> (state byte, time)
        self.scanning = False
        self._od = None
        self._net = None
        self.keep = log_size
        self._log = collections.deque(maxlen=log_size)
        self._seq = 0
        self._log_lock = threading.Lock()
        self._lock = threading.RLock()  # one job (open, close, scan, an SDO transfer) at a time

    # --- the frame log -------------------------------------------------------------------------------
    def _frame(self, direction, can_id, ext, rtr, data, t=None):
        t = time.time() if t is None else t
        data = bytes(data)
        if direction == "rx" and not ext and not rtr and 0x701 <= can_id <= 0x77F and data:
            self.heartbeats[can_id & 0x7F] = (data[0] & 0x7F, t)
        text = describe(can_id, data, ext, rtr)
        with self._log_lock:
            self._seq += 1
            if direction == "rx":
                self.rx += 1
            else:
                self.tx += 1
            self._log.append(FrameEntry(self._seq, t, direction, can_id, ext, rtr, data, text))

    def frames_since(self, seq):
        """The log's frames after seq (all it keeps, the newest last)."""
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
            ver = " (SLCAN adapter V%02d%02d%s)" % (self.version + (", serial %s" % self.serial if self.serial
                                                                     else "",)) if self.version else ""
            return "open: %s at %d kbit/s%s%s; %d frames in, %d out" % (
                self.url, self.bitrate // 1000, ", listen-only" if self.read_only else "", ver, self.rx, self.tx)
        if self.state == "lost":
            return "port lost: %s" % self.reason
        return "closed"

    def open(self, url=None, bitrate=None):
        """Open the SLCAN port at bitrate (python-can's slcan), check it is one, start the CANopen
        network on it; returns a sentence."""
        url = str(url if url is not None else self.url).strip()
        try:
            bitrate = int(bitrate if bitrate is not None else self.bitrate)
        except (TypeError, ValueError):
            raise UserError("the CAN bitrate must be one of %s" % ", ".join(map(str, BITRATES))) from None
        if not url:
            raise UserError("no SLCAN port: give the jig's third USB port (e.g. /dev/ttyACM2) or a pyserial URL")
        if bitrate not in BITRATES:
            raise UserError("the CAN bitrate must be one of %s, not %d" % (", ".join(map(str, BITRATES)), bitrate))
        with self._lock:
            if self._net is not None:
                raise UserError("the SLCAN port %s is open: close it first" % self.url)
            try:
                bus = can.Bus(interface="slcan", channel=url, bitrate=bitrate, sleep_after_open=0.1,
                              listen_only=self.read_only)
            except Exception as exc:  # CanInitializationError, ValueError, OSError: one sentence
                raise UserError("cannot open %s: %s" % (url, _reason(exc))) from None
            try:
                version = bus.get_version(VERSION_WAIT)
            except Exception:  # an answer that is not SLCAN's (python-can parses V's digits)
                version = (None, None)
            if version[0] is None:
                _quietly(bus.shutdown)
                raise UserError("%s is not an SLCAN port (it did not answer SLCAN's V command within %g s)"
                                % (url, VERSION_WAIT))
            try:
                serial = bus.get_serial_number(0.5)
            except Exception:
                serial = None
            net = _Network(bus, self)
            net.listeners.append(_Tap(self))
            try:
                net.connect()
            except Exception as exc:
                _quietly(bus.shutdown)
                raise UserError("cannot start CANopen on %s: %s" % (url, _reason(exc))) from None
            self._net = net
            self.url, self.bitrate = url, bitrate
            self.version, self.serial = version, (serial or "").strip() or None
            self.state, self.reason = "open", ""
            self.opened_at = time.time()
            with self._log_lock:
                self.rx = self.tx = 0
            self.heartbeats.clear()
        return "SLCAN port %s open at %d kbit/s%s" % (url, bitrate // 1000,
                                                      ", listen-only (read-only Desk)" if self.read_only else "")

    def close(self):
        """Close the port (python-can sends SLCAN's C); returns a sentence."""
        with self._lock:
            net, self._net = self._net, None
            was = self.state
            self.state = "closed"
            if net is None:
                if was == "lost":
                    return "closed (the port had been lost: %s)" % self.reason
                raise UserError("the SLCAN port is not open")
            _quietly(net.disconnect)
        return "SLCAN port %s closed" % self.url

    def _lost(self, exc):
        if self.state == "open":
            self.reason = "%s: %s" % (self.url, _reason(exc))
            self.state = "lost"

    def _network(self, sends=True):
        if sends and self.read_only:
            raise UserError("refused: this Desk is read-only (--read-only): the CAN port is only listened to")
        net = self._net
        if self.state == "lost":
            raise UserError("the SLCAN port was lost (%s): close it and open it again" % self.reason)
        if net is None:
            raise UserError("the SLCAN port is not open: choose it and press Open")
        return net

    def _od_of_eds(self):
        if self._od is None:
            try:
                self._od = canopen.import_od(self.eds)
            except Exception as exc:
                raise UserError("cannot read the EDS %s: %s" % (self.eds, _reason(exc))) from None
        return self._od

    def _node(self, net, node_id):
        try:
            nid = int(str(node_id).strip(), 0)
        except ValueError:
            raise UserError("the node id must be a number 1..127, not %r" % node_id) from None
        if not 1 <= nid <= 127:
            raise UserError("the node id must be 1..127, not %d" % nid)
        if nid not in net:
            node = net.add_node(nid, self._od_of_eds())
        else:
            node = net[nid]
        node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout
        return node

    # --- scan ------------------------------------------------------------------------------------------------
    def scan(self, limit=127, wait=SCAN_WAIT):
        """python-canopen's scanner (an SDO upload of 0x1000 to every id), then each node's device type,
        name and identity by SDO; returns the rows (also kept in ``nodes``)."""
        with self._lock:
            net = self._network()
            self.scanning = True
            try:
                net.scanner.reset()
                try:
                    net.scanner.search(limit)
                except Exception as exc:
                    raise UserError(self._failure("scanning", exc)) from None
                time.sleep(wait)
                ids = sorted(set(net.scanner.nodes) | set(self.heartbeats))
                rows = {}
                for nid in ids:
                    rows[nid] = self._identify(net, nid)
                self.nodes = rows
            finally:
                self.scanning = False
        return list(rows.values())

    def _identify(self, net, nid):
        node = self._node(net, nid)
        row = {"id": nid, "device_type": "", "profile": "", "name": "", "vendor": "", "product": "",
               "revision": "", "serial": "", "problem": ""}

        def read(index, sub):
            try:
                return node.sdo.upload(index, sub)
            except Exception as exc:
                if not row["problem"]:
                    row["problem"] = self._failure("0x%04X:%02X" % (index, sub), exc, nid)
                return None

        raw = read(0x1000, 0)
        if raw is not None and len(raw) >= 4:
            dt = struct.unpack_from("<I", raw)[0]
            row["device_type"] = "0x%08X" % dt
            row["profile"] = PROFILES.get(dt & 0xFFFF, "CiA %d" % (dt & 0xFFFF))
        raw = read(0x1008, 0)
        if raw is not None:
            row["name"] = raw.decode("ascii", "replace").rstrip("\x00")
        for key, sub in (("vendor", 1), ("product", 2), ("revision", 3), ("serial", 4)):
            raw = read(0x1018, sub)
            if raw is not None and len(raw) >= 4:
                row[key] = "0x%08X" % struct.unpack_from("<I", raw)[0]
        return row

    def node_rows(self, now=None):
        """The node list: the last scan's rows and every node heard since, each with its NMT state
        from its heartbeats."""
        now = time.time() if now is None else now
        rows = {nid: dict(r) for nid, r in self.nodes.items()}
        for nid in self.heartbeats:
            rows.setdefault(nid, {"id": nid, "device_type": "", "profile": "", "name": "(heard, not scanned)",
                                  "vendor": "", "product": "", "revision": "", "serial": "", "problem": ""})
        for nid, row in rows.items():
            beat = self.heartbeats.get(nid)
            if beat is None:
                row["nmt"] = "no heartbeat heard"
            else:
                state = NMT_STATES.get(beat[0], "state 0x%02X" % beat[0])
                age = now - beat[1]
                row["nmt"] = state if age < HEARTBEAT_STALE else "%s, silent for %.0f s" % (state, age)
        return [rows[k] for k in sorted(rows)]

    # --- NMT -------------------------------------------------------------------------------------------------
    def nmt(self, command, node_id=0):
        """Send an NMT command (``NMT_COMMANDS``) to one node or, node_id 0, to all; returns a sentence."""
        if command not in NMT_COMMANDS:
            raise UserError("NMT command must be one of %s, not %r" % (", ".join(NMT_COMMANDS), command))
        try:
            nid = int(str(node_id).strip() or "0", 0)
        except ValueError:
            raise UserError("the node id must be 0 (all) or 1..127, not %r" % node_id) from None
        if not 0 <= nid <= 127:
            raise UserError("the node id must be 0 (all) or 1..127, not %d" % nid)
        with self._lock:
            net = self._network()
            nmt = net.nmt if nid == 0 else canopen.nmt.NmtMaster(nid)
            nmt.network = net
            try:
                nmt.send_command(NMT_COMMANDS[command])
            except Exception as exc:
                raise UserError(self._failure("sending NMT %s" % command, exc)) from None
        return "NMT %s sent to %s" % (command, "all nodes" if nid == 0 else "node %d" % nid)

    # --- SDO -------------------------------------------------------------------------------------------------
    def sdo_read(self, node_id, what):
        """Upload an object (``index:sub`` or its EDS name); returns (label, value text)."""
        with self._lock:
            net = self._network()
            node = self._node(net, node_id)
            index, sub, var = parse_object(what, self._od_of_eds())
            label = object_label(index, sub, var)
            try:
                raw = node.sdo.upload(index, sub)
            except Exception as exc:
                raise UserError(self._failure("reading %s" % label, exc, node.id)) from None
        if var is not None:
            try:
                return label, show_value(var.decode_raw(raw), var)
            except Exception:  # not the EDS's length: the bytes as they came
                pass
        if len(raw) <= 4 and raw:
            return label, "%s (%s)" % (show_value(int.from_bytes(raw, "little")), raw.hex(" "))
        return label, show_value(raw)

    def sdo_write(self, node_id, what, value_text):
        """Download a value, typed as the EDS says, to an object; returns (label, value text)."""
        with self._lock:
            net = self._network()
            node = self._node(net, node_id)
            index, sub, var = parse_object(what, self._od_of_eds())
            label = object_label(index, sub, var)
            if var is None:
                raise UserError("0x%04X:%02X is not in the EDS (%s): its type is unknown, so nothing was written"
                                % (index, sub, self.eds.rsplit("/", 1)[-1]))
            if not var.writable:
                raise UserError("%s is %s in the EDS: it cannot be written" % (
                    label, {"ro": "read-only", "const": "a constant"}.get(var.access_type, var.access_type)))
            value = parse_value(value_text, var)
            try:
                data = var.encode_raw(value)
            except (ValueError, TypeError, struct.error) as exc:
                raise UserError("%s cannot hold %r: %s" % (label, value_text, exc)) from None
            try:
                node.sdo.download(index, sub, data)
            except Exception as exc:
                raise UserError(self._failure("writing %s" % label, exc, node.id)) from None
        return label, show_value(value, var)

    def _failure(self, what, exc, node_id=None):
        """One sentence for an SDO or bus failure (an abort by its name, a silent node, a lost port)."""
        who = "node %d" % node_id if node_id is not None else "the bus"
        if isinstance(exc, SdoAbortedError):
            return "%s refused %s: abort 0x%08X, %s" % (who, what, exc.code, abort_name(exc.code))
        if isinstance(exc, SdoCommunicationError):
            return "%s did not answer %s (%s)" % (who, what, str(exc).rstrip(".").lower() or "no answer")
        self._lost(exc)
        return "%s failed: %s" % (what, _reason(exc))


def _reason(exc):
    text = str(exc).strip().rstrip(".") or type(exc).__name__
    return text[0].lower() + text[1:] if text[:2] != text[:2].upper() else text


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


__all__ = ["BITRATES", "CanLink", "FrameEntry", "NMT_COMMANDS", "NMT_STATES", "abort_name", "describe",
           "emcy_name", "format_entry", "parse_object", "parse_value", "show_value"]
