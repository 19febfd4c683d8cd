"""A simulated CANopen CiA 402 drive on the bench's simulated CAN bus: the drive's CANopen face.

The drive itself (its objects, the 402 power state machine, its modes, its axis and its
faults) is ``drive402.Drive402``; this module is how it speaks CANopen. The object
dictionary comes from the project's EDS (``motorjig.can.EDS_PATH``) read with
python-canopen's ``import_od``; the protocol is written here, on the bench's virtual clock
(python-canopen's own LocalNode runs on threads and wall time).

CiA 301: NMT (``NMT_COMMANDS``; boot-up at power-on and after a reset, SDO only in
pre-operational/operational, PDOs only in operational), heartbeat producer
(0x1017), SDO server (expedited and segmented, both directions; block transfer is
refused with 0x05040001; aborts by ``ABORT_NAMES``), PDOs (TPDO1-4/RPDO1-4:
transmission types 0-240 on SYNC, 254/255 on change with inhibit time and event
timer; mapping remapped at runtime by SDO as python-canopen does: disable, count
0, entries, count, enable), SYNC consumer, EMCY producer (0x1001, 0x1003, 0x603F),
store/restore (0x1010 "save", 0x1011 "load"). CiA 305 LSS slave (switch state
global/selective, configure node id and bit timing, store, inquire, identify,
fast scan); a node built with node id 0xFF answers LSS only until it has an id.

Faults: the drive's (``drive402.DRIVE_FAULTS``) and the bus's own (missed heartbeats, SDO
aborts), all in ``FAULTS``.
"""

import struct

from canopen.objectdictionary import import_od

from motorjig.can import EDS_PATH

from .drive402 import (ABORT_COMMAND, ABORT_GENERAL, ABORT_LENGTH,
                       ABORT_PDO_LENGTH, ABORT_READ_ONLY, ABORT_TIMEOUT, ABORT_TOGGLE, ABORT_UNSUPPORTED,
                       ABORT_VALUE, ABORT_WRITE_ONLY, DRIVE_FAULTS, FAULT_ALIASES, SERIAL_BASE, Drive402)
from .faults import Fault, FaultTable, number, switch

# --- CiA 301 ------------------------------------------------------------------------
NMT_INITIALISING = 0x00
NMT_STOPPED = 0x04
NMT_OPERATIONAL = 0x05
NMT_PRE_OPERATIONAL = 0x7F
NMT_NAMES = {NMT_INITIALISING: "INITIALISING", NMT_STOPPED: "STOPPED", NMT_OPERATIONAL: "OPERATIONAL",
             NMT_PRE_OPERATIONAL: "PRE-OPERATIONAL"}
# NMT command -> what it does (the node's NMT state after it; resets boot up to pre-operational)
NMT_COMMANDS = {0x01: "start", 0x02: "stop", 0x80: "pre-operational", 0x81: "reset node",
                0x82: "reset communication"}

COB_NMT = 0x000
COB_LSS_IN = 0x7E5
COB_LSS_OUT = 0x7E4
UNCONFIGURED = 0xFF


# LSS command specifiers (CiA 305)
LSS_SWITCH_GLOBAL = 0x04
LSS_CONFIGURE_NODE_ID = 0x11
LSS_CONFIGURE_BIT_TIMING = 0x13
LSS_ACTIVATE_BIT_TIMING = 0x15
LSS_STORE = 0x17
LSS_SELECTIVE = (0x40, 0x41, 0x42, 0x43)  # vendor, product, revision, serial
LSS_SELECTIVE_RESPONSE = 0x44
LSS_IDENTIFY_REMOTE = range(0x46, 0x4C)  # vendor, product, revision low/high, serial low/high
LSS_IDENTIFY_NON_CONFIGURED = 0x4C
LSS_IDENTIFY_SLAVE = 0x4F
LSS_NON_CONFIGURED_SLAVE = 0x50
LSS_FAST_SCAN = 0x51
LSS_INQUIRE = {0x5A: 0, 0x5B: 1, 0x5C: 2, 0x5D: 3}  # -> identity part
LSS_INQUIRE_NODE_ID = 0x5E
# CiA 305 bit timing table 0: index -> bit rate
LSS_BIT_TIMING = {0: 1000000, 1: 800000, 2: 500000, 3: 250000, 4: 125000, 6: 50000, 7: 20000, 8: 10000}

# --- faults: the drive's and the bus's own (set_fault(name, value)) ------------------------------
def _sdo_abort(value):
    code, scope = _abort_scope(value)
    v = number(code, int, "CODE[@INDEX[:SUB]], an SDO abort code")
    if not 0 < v <= 0xFFFFFFFF:
        raise ValueError("%r is out of range for CODE[@INDEX[:SUB]]" % (code,))
    return v, scope


_D = DRIVE_FAULTS
FAULTS = FaultTable([
    _D["following-error"], _D["overcurrent"], _D["sluggish"], _D["dead-input"], _D["no-origin"],
    switch("missed-heartbeat", "the drive stops producing its heartbeat (0x1017) while set"),
    Fault("sdo-abort", "CODE[@INDEX[:SUB]]", ABORT_GENERAL, "every SDO request (or only those for object INDEX, "
                                                            "INDEX:SUB; hex) is answered with abort CODE (default "
                                                            "0x08000000)", _sdo_abort),
    _D["param"],
], FAULT_ALIASES)


def parse_fault(name, value=None):
    """(name, checked value) of a fault of ``FAULTS`` (None: its default); numbers may be
    text. ValueError with a one-line reason otherwise. ``param``'s value is ((index,
    sub), value), checked against the EDS."""
    return FAULTS.parse(name, value)


def _abort_scope(value):
    """sdo-abort's value: (CODE, None) or (CODE, (index, sub or None)) from "CODE@INDEX[:SUB]"
    or a tuple; the code left as given."""
    if isinstance(value, tuple):
        return value
    if not isinstance(value, str) or "@" not in value:
        return value, None
    code, _, obj = value.partition("@")
    index, colon, sub = obj.partition(":")
    try:
        return code, (int(index, 16), int(sub, 16) if colon else None)
    except ValueError:
        raise ValueError("expected CODE[@INDEX[:SUB]] (INDEX, SUB hex), e.g. 0x06020000@0x6065, got %r"
                         % (value,)) from None



class Cia402Node(Drive402):
    """One simulated CiA 402 drive on the CAN bus (see the module's docstring)."""

    FAULTS = FAULTS

    def __init__(self, clock, bus, node_id, eds=EDS_PATH, heartbeat_ms=None, serial=None, turnaround_us=100.0,
                 boot_us=1000.0, sdo_timeout_ms=1000.0, name=None):
        if not (1 <= node_id <= 127 or node_id == UNCONFIGURED):
            raise ValueError("node id must be 1..127 or 0xFF (unconfigured), got %r" % (node_id,))
        Drive402.__init__(self, clock, import_od(eds, None if node_id == UNCONFIGURED else node_id),
                          SERIAL_BASE + node_id if serial is None else serial)
        self.bus = bus
        self.node_id = node_id
        self.turnaround_us = turnaround_us
        self.boot_us = boot_us
        self.sdo_timeout_us = sdo_timeout_ms * 1000.0
        if heartbeat_ms is not None:
            self.stored[(0x1017, 0)] = int(heartbeat_ms)
        self.can = bus.add_node(name or "cia402-%d" % node_id, self._on_frame)
        # the bus's own faults
        self.missed_heartbeat = False
        self.sdo_abort_code = None
        self.sdo_abort_scope = None  # None: every request; (index, sub or None): that object's
        # LSS
        self.lss_mode = 0  # 0 waiting, 1 configuration
        self.lss_pending_id = node_id
        self.lss_stored_id = node_id
        self.lss_bit_timing = None  # pending bit rate (configure bit timing)
        self.bitrate = bus.bitrate
        self._lss_selective = 0  # parts of the LSS address matched so far (switch state selective)
        self._lss_identify = []  # (cs, value) of identify remote slave
        self._fs_pos = 0  # fast scan: the LSS address part this node checks next
        # statistics and logs for tests
        self.emcys = []  # (t_us, code, register) sent
        self.sdo_requests = 0
        self.rpdo_length_errors = 0  # RPDOs shorter than their mapping (ignored)
        self.power_on()

    # --- power, resets, NMT --------------------------------------------------------
    def power_on(self):
        """Power-on: every object to its stored/default value, the 402 state machine
        through NOT READY TO SWITCH ON to SWITCH ON DISABLED, boot-up."""
        self.node_id = self.lss_stored_id
        self.lss_pending_id = self.node_id
        self.motion.halt()
        self._reset(application=True)

    def _reset(self, application):
        """Reset node (application True) or reset communication: objects from their
        stored/default values, the pending LSS node id applied, boot-up after boot_us."""
        self.nmt = NMT_INITIALISING
        if self.lss_pending_id != self.node_id:
            self.node_id = self.lss_pending_id
        self._reset_values(comm_only=not application)
        self._hb_gen = getattr(self, "_hb_gen", 0) + 1
        self._sdo = None
        self._sdo_gen = getattr(self, "_sdo_gen", 0) + 1
        self._tpdo = [dict(count=0, last=None, sent_t=None, inhibit_due=False, gen=0) for _ in range(4)]
        self._rpdo_sync = [None] * 4
        if application:
            self._reset_drive()
        if self.node_id != UNCONFIGURED:
            self.clock.after(self.boot_us, self._boot_up, self._hb_gen)

    def _boot_up(self, gen):
        if gen != self._hb_gen:
            return
        self._send(0x700 + self.node_id, b"\x00")
        self.nmt = NMT_PRE_OPERATIONAL
        self._start_heartbeat()

    def _nmt(self, cmd):
        if cmd == 0x01:
            if self.nmt != NMT_OPERATIONAL:
                self.nmt = NMT_OPERATIONAL
                self._refresh()
                for n in range(4):  # event-driven TPDOs go out once on entering operational
                    if self._tpdo_enabled(n) and self.values[(0x1800 + n, 2)] >= 254:
                        self._send_tpdo(n)
        elif cmd == 0x02:
            self.nmt = NMT_STOPPED
            self._sdo = None
        elif cmd == 0x80:
            self.nmt = NMT_PRE_OPERATIONAL
        elif cmd == 0x81:
            self._reset(application=True)
        elif cmd == 0x82:
            self._reset(application=False)

    def _start_heartbeat(self):
        self._hb_gen += 1
        period = self.values[(0x1017, 0)]
        if period and self.nmt != NMT_INITIALISING:
            self.clock.after(period * 1000.0, self._heartbeat, self._hb_gen)

    def _heartbeat(self, gen):
        if gen != self._hb_gen:
            return
        if not self.missed_heartbeat:
            self._send(0x700 + self.node_id, bytes([self.nmt]))
        self.clock.after(self.values[(0x1017, 0)] * 1000.0, self._heartbeat, gen)

    # --- the bus ---------------------------------------------------------------------------
    def _send(self, cob, data):
        self.can.transmit(cob, False, False, bytes(data))

    def _reply(self, cob, data):
        self.clock.after(self.turnaround_us, self._send, cob, bytes(data))

    def _on_frame(self, t_us, can_id, ext, rtr, data):
        if ext:
            return
        if can_id == COB_LSS_IN:
            if len(data) == 8:
                self._lss(bytes(data))
            return
        if self.node_id == UNCONFIGURED or self.nmt == NMT_INITIALISING:
            return
        if can_id == COB_NMT:
            if len(data) == 2 and data[1] in (0, self.node_id) and data[0] in NMT_COMMANDS:
                self._nmt(data[0])
            return
        if self.nmt == NMT_STOPPED:
            return
        if can_id == 0x600 + self.node_id and not rtr:
            if len(data) == 8:
                self._sdo_request(bytes(data))
            return
        if self.nmt != NMT_OPERATIONAL:
            return
        if can_id == self.values[(0x1005, 0)] & 0x7FF:
            self._sync()
            return
        for n in range(4):
            if rtr and self._tpdo_enabled(n) and can_id == self.values[(0x1800 + n, 1)] & 0x7FF:
                if not self.values[(0x1800 + n, 1)] & 0x40000000:
                    self._refresh()
                    self._send_tpdo(n)
                return
            cob = self.values[(0x1400 + n, 1)]
            if not rtr and not cob & 0x80000000 and can_id == cob & 0x7FF:
                if self.values[(0x1400 + n, 2)] <= 240:
                    self._rpdo_sync[n] = bytes(data)  # applied at the next SYNC
                else:
                    self._rpdo_apply(n, bytes(data))
                    self._after_change()
                return

    # --- the CANopen objects: checks and effects beside the drive's ---------------------------------
    def _check(self, index, sub, value):
        code = Drive402._check(self, index, sub, value)
        if code:
            return code
        if index == 0x1005 and value & 0x7FFFF800:
            return ABORT_VALUE  # 11-bit COB-ID, consumer only
        if 0x1400 <= index <= 0x1403 or 0x1800 <= index <= 0x1803:
            return self._check_pdo_comm(index, sub, value)
        if 0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03:
            return self._check_pdo_map(index, sub, value)
        return 0

    def _written(self, index, sub, value):
        Drive402._written(self, index, sub, value)
        if index == 0x1017:
            self._start_heartbeat()
        elif 0x1800 <= index <= 0x1803 and sub in (1, 2, 5):
            n = index - 0x1800
            self._tpdo[n].update(count=0, last=None)
            self._tpdo[n]["gen"] += 1
            self._arm_event_timer(n)

    def _on_change(self):
        self._tpdo_events()

    def _emergency(self, code, reg):
        if self.nmt in (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL):
            self.emcys.append((self.clock.now, code, reg))
            self._send(self.values[(0x1014, 0)] & 0x7FF, struct.pack("<HB5x", code, reg))

    def _apply_fault(self, name, v):
        if name == "missed-heartbeat":
            self.missed_heartbeat = v
        elif name == "sdo-abort":
            self.sdo_abort_code, self.sdo_abort_scope = v
        else:
            Drive402._apply_fault(self, name, v)

    def active_faults(self):
        out = Drive402.active_faults(self)
        if self.missed_heartbeat:
            out.append("missed-heartbeat")
        if self.sdo_abort_code is not None:
            scope = self.sdo_abort_scope
            out.append("sdo-abort=0x%08X" % self.sdo_abort_code + (
                "" if scope is None else "@0x%04X" % scope[0] + ("" if scope[1] is None else ":%02X" % scope[1])))
        return out

    def clear_faults(self):
        self.missed_heartbeat = False
        self.sdo_abort_code = None
        self.sdo_abort_scope = None
        Drive402.clear_faults(self)

    def _check_pdo_comm(self, index, sub, value):
        old = self.values[(index, 1)]
        if sub == 1:
            if value & 0x20000000:
                return ABORT_VALUE  # no extended frames
            if not old & 0x80000000 and not value & 0x80000000 and (old ^ value) & 0x7FF:
                return ABORT_VALUE  # the COB-ID of a valid PDO cannot change
        elif sub == 2:
            if not (value <= 240 or value >= 254):
                return ABORT_VALUE
        elif sub == 3 and not old & 0x80000000:
            return ABORT_UNSUPPORTED  # inhibit time only while the PDO is disabled
        return 0

    def _check_pdo_map(self, index, sub, value):
        comm = index - 0x200
        if not self.values[(comm, 1)] & 0x80000000:
            return ABORT_UNSUPPORTED  # mapping only while the PDO is disabled
        rx = index < 0x1800
        if sub == 0:
            bits = 0
            for i in range(1, value + 1):
                entry = self.values[(index, i)]
                code = self._check_map_entry(entry, rx)
                if code:
                    return code
                bits += entry & 0xFF
            return ABORT_PDO_LENGTH if bits > 64 else 0
        if self.values[(index, 0)] != 0:
            return ABORT_UNSUPPORTED  # entries only while the count is 0
        return self._check_map_entry(value, rx) if value else 0

    # --- SDO server ------------------------------------------------------------------
    def _abort(self, index, sub, code):
        self._sdo = None
        self._reply(0x580 + self.node_id, struct.pack("<BHBI", 0x80, index, sub, code))

    def _sdo_request(self, d):
        self.sdo_requests += 1
        ccs = d[0] >> 5
        index, sub = struct.unpack_from("<HB", d, 1)
        if ccs == 4:  # the client aborts
            self._sdo = None
            return
        if self.sdo_abort_code is not None and self._aborts(ccs, index, sub):
            self._abort(index, sub, self.sdo_abort_code)
            return
        x = self._sdo
        if ccs == 0 or ccs == 3:  # a segment
            if x is None or x["up"] != (ccs == 3):
                self._abort(0 if x is None else x["index"], 0 if x is None else x["sub"], ABORT_COMMAND)
                return
            if (d[0] >> 4 & 1) != x["toggle"]:
                self._abort(x["index"], x["sub"], ABORT_TOGGLE)
                return
            self._arm_sdo_timeout()
            if ccs == 3:
                self._upload_segment(x)
            else:
                self._download_segment(x, d)
            return
        if ccs == 1:
            self._initiate_download(d, index, sub)
        elif ccs == 2:
            self._initiate_upload(index, sub)
        else:  # 5, 6: block transfer; 7: nothing
            self._abort(index, sub, ABORT_COMMAND)

    def _aborts(self, ccs, index, sub):
        """Does the sdo-abort fault answer this request? (segments carry no index: they go
        with their transfer, which started only if its object was not aborted)"""
        scope = self.sdo_abort_scope
        if scope is None:
            return True
        return ccs not in (0, 3) and index == scope[0] and scope[1] in (None, sub)

    def _initiate_upload(self, index, sub):
        var, code = self._lookup(index, sub)
        if var is None:
            self._abort(index, sub, code)
            return
        if not var.readable:
            self._abort(index, sub, ABORT_WRITE_ONLY)
            return
        self._refresh()
        data = self._encode(var, self.values[(index, sub)])
        if len(data) <= 4:
            n = 4 - len(data)
            self._reply(0x580 + self.node_id,
                        bytes([0x43 | n << 2]) + struct.pack("<HB", index, sub) + data + bytes(n))
            return
        self._sdo = dict(up=True, index=index, sub=sub, data=data, pos=0, toggle=0)
        self._arm_sdo_timeout()
        self._reply(0x580 + self.node_id, struct.pack("<BHBI", 0x41, index, sub, len(data)))

    def _upload_segment(self, x):
        chunk = x["data"][x["pos"] : x["pos"] + 7]
        x["pos"] += len(chunk)
        last = x["pos"] >= len(x["data"])
        n = 7 - len(chunk)
        self._reply(0x580 + self.node_id, bytes([x["toggle"] << 4 | n << 1 | last]) + chunk + bytes(n))
        x["toggle"] ^= 1
        if last:
            self._sdo = None

    def _initiate_download(self, d, index, sub):
        var, code = self._lookup(index, sub)
        if var is None:
            self._abort(index, sub, code)
            return
        if not var.writable:
            self._abort(index, sub, ABORT_READ_ONLY)
            return
        e, s = d[0] >> 1 & 1, d[0] & 1
        if e:
            data = d[4 : 8 - (d[0] >> 2 & 3)] if s else d[4:8]
            if not s and var.data_type != 0x9:
                data = data[: var.STRUCT_TYPES[var.data_type].size]
            self._finish_download(index, sub, var, data)
            return
        size = struct.unpack_from("<I", d, 4)[0] if s else None
        if size is not None and var.data_type != 0x9 and size != var.STRUCT_TYPES[var.data_type].size:
            self._abort(index, sub, ABORT_LENGTH)
            return
        self._sdo = dict(up=False, index=index, sub=sub, var=var, size=size, data=b"", toggle=0)
        self._arm_sdo_timeout()
        self._reply(0x580 + self.node_id, struct.pack("<BHBI", 0x60, index, sub, 0))

    def _download_segment(self, x, d):
        n = d[0] >> 1 & 7
        x["data"] += d[1 : 8 - n]
        reply = bytes([0x20 | x["toggle"] << 4]) + bytes(7)
        x["toggle"] ^= 1
        if not d[0] & 1:
            self._reply(0x580 + self.node_id, reply)
            return
        self._sdo = None
        if x["size"] is not None and len(x["data"]) != x["size"]:
            self._abort(x["index"], x["sub"], ABORT_LENGTH)
            return
        if self._finish_download(x["index"], x["sub"], x["var"], x["data"], confirm=False):
            self._reply(0x580 + self.node_id, reply)

    def _finish_download(self, index, sub, var, data, confirm=True):
        if var.data_type == 0x9:
            value = data.decode("ascii", errors="replace")
        else:
            st = var.STRUCT_TYPES[var.data_type]
            if len(data) != st.size:
                self._abort(index, sub, ABORT_LENGTH)
                return False
            (value,) = st.unpack(data)
        code = self._store(index, sub, value)
        if code:
            self._abort(index, sub, code)
            return False
        if confirm:
            self._reply(0x580 + self.node_id, struct.pack("<BHBI", 0x60, index, sub, 0))
        self._after_change()
        return True

    def _arm_sdo_timeout(self):
        self._sdo_gen += 1
        self.clock.after(self.sdo_timeout_us, self._sdo_timeout, self._sdo_gen)

    def _sdo_timeout(self, gen):
        if gen == self._sdo_gen and self._sdo is not None:
            self._abort(self._sdo["index"], self._sdo["sub"], ABORT_TIMEOUT)

    # --- PDOs, SYNC, EMCY ----------------------------------------------------------------------
    def _tpdo_enabled(self, n):
        return not self.values[(0x1800 + n, 1)] & 0x80000000

    def _pdo_map(self, n, rx):
        base = (0x1600 if rx else 0x1A00) + n
        return [self.values[(base, i)] for i in range(1, self.values[(base, 0)] + 1)]

    def _tpdo_data(self, n):
        out = b""
        for entry in self._pdo_map(n, False):
            key = (entry >> 16, entry >> 8 & 0xFF)
            var = self.vars.get(key)
            if var is not None:
                out += self._encode(var, self.values[key])[: (entry & 0xFF) // 8]
        return out

    def _send_tpdo(self, n):
        """Send TPDO n+1 now (dynamic values refreshed by the caller); restart its event timer."""
        t = self._tpdo[n]
        data = self._tpdo_data(n)
        self._send(self.values[(0x1800 + n, 1)] & 0x7FF, data)
        t["last"] = data
        t["sent_t"] = self.clock.now
        t["gen"] += 1
        self._arm_event_timer(n)

    def _arm_event_timer(self, n):
        ms = self.values[(0x1800 + n, 5)]
        if ms and self.values[(0x1800 + n, 2)] >= 254 and self._tpdo_enabled(n):
            self.clock.after(ms * 1000.0, self._event_timer, n, self._tpdo[n]["gen"])

    def _event_timer(self, n, gen):
        if gen == self._tpdo[n]["gen"] and self.nmt == NMT_OPERATIONAL and self._tpdo_enabled(n):
            self._refresh()
            self._send_tpdo(n)

    def _tpdo_events(self):
        """Event-driven TPDOs (254/255) whose data changed go out, no sooner than their inhibit time."""
        if self.nmt != NMT_OPERATIONAL:
            return
        refreshed = False
        for n in range(4):
            if not self._tpdo_enabled(n) or self.values[(0x1800 + n, 2)] < 254:
                continue
            t = self._tpdo[n]
            if not refreshed:
                self._refresh()
                refreshed = True
            if self._tpdo_data(n) == t["last"] or t["inhibit_due"]:
                continue
            inhibit_us = self.values[(0x1800 + n, 3)] * 100.0
            if t["sent_t"] is not None and self.clock.now < t["sent_t"] + inhibit_us:
                t["inhibit_due"] = True
                self.clock.at(t["sent_t"] + inhibit_us, self._inhibit_over, n)
            else:
                self._send_tpdo(n)

    def _inhibit_over(self, n):
        self._tpdo[n]["inhibit_due"] = False
        self._tpdo_events()

    def _sync(self):
        for n in range(4):  # synchronous RPDOs take effect at the SYNC
            data = self._rpdo_sync[n]
            if data is not None:
                self._rpdo_sync[n] = None
                self._rpdo_apply(n, data)
        self._refresh()
        for n in range(4):
            if not self._tpdo_enabled(n):
                continue
            ttype = self.values[(0x1800 + n, 2)]
            t = self._tpdo[n]
            if ttype == 0:
                if self._tpdo_data(n) != t["last"]:
                    self._send_tpdo(n)
            elif ttype <= 240:
                t["count"] += 1
                if t["count"] >= ttype:
                    t["count"] = 0
                    self._send_tpdo(n)
        self._after_change()

    def _rpdo_apply(self, n, data):
        entries = self._pdo_map(n, True)
        if sum(e & 0xFF for e in entries) // 8 > len(data):
            self.rpdo_length_errors += 1
            return
        pos = 0
        writes = []
        for entry in entries:
            size = (entry & 0xFF) // 8
            key = (entry >> 16, entry >> 8 & 0xFF)
            chunk = data[pos : pos + size]
            pos += size
            var = self.vars.get(key)
            if var is None or key[0] < 8:  # a dummy entry
                continue
            writes.append((key, var.STRUCT_TYPES[var.data_type].unpack(chunk)[0]))
        # the controlword acts last, on the PDO's other values (a mode, a target) already in place
        writes.sort(key=lambda w: w[0] == (0x6040, 0))
        for key, value in writes:
            self._store(key[0], key[1], value)

    def _lss_reply(self, data):
        self._reply(COB_LSS_OUT, bytes(data) + bytes(8 - len(data)))

    def _lss(self, d):
        cs = d[0]
        ident = self.identity()
        if cs == LSS_SWITCH_GLOBAL:
            if d[1] == 0 and self.lss_mode == 1:
                self.lss_mode = 0
                if self.node_id == UNCONFIGURED and self.lss_pending_id != UNCONFIGURED:
                    self._reset(application=False)  # the new node id takes effect
            elif d[1] == 1:
                self.lss_mode = 1
            self._lss_selective = 0
        elif cs in LSS_SELECTIVE:
            part = cs - LSS_SELECTIVE[0]
            value = struct.unpack_from("<I", d, 1)[0]
            if part == self._lss_selective and value == ident[part]:
                self._lss_selective += 1
                if self._lss_selective == 4:
                    self._lss_selective = 0
                    self.lss_mode = 1
                    self._lss_reply([LSS_SELECTIVE_RESPONSE])
            else:
                self._lss_selective = 0
        elif cs in LSS_IDENTIFY_REMOTE:
            self._lss_identify = [x for x in self._lss_identify if x[0] < cs]
            self._lss_identify.append((cs, struct.unpack_from("<I", d, 1)[0]))
            if cs == 0x4B and [x[0] for x in self._lss_identify] == list(LSS_IDENTIFY_REMOTE):
                v = dict(self._lss_identify)
                if (v[0x46] == ident[0] and v[0x47] == ident[1] and v[0x48] <= ident[2] <= v[0x49]
                        and v[0x4A] <= ident[3] <= v[0x4B]):
                    self._lss_reply([LSS_IDENTIFY_SLAVE])
        elif cs == LSS_IDENTIFY_NON_CONFIGURED:
            if self.node_id == UNCONFIGURED:
                self._lss_reply([LSS_NON_CONFIGURED_SLAVE])
        elif cs == LSS_FAST_SCAN:
            self._fast_scan(d, ident)
        elif self.lss_mode != 1:
            return  # the rest only in the configuration state
        elif cs == LSS_CONFIGURE_NODE_ID:
            ok = 1 <= d[1] <= 127 or d[1] == UNCONFIGURED
            if ok:
                self.lss_pending_id = d[1]
            self._lss_reply([cs, 0 if ok else 1])
        elif cs == LSS_CONFIGURE_BIT_TIMING:
            ok = d[1] == 0 and d[2] in LSS_BIT_TIMING
            if ok:
                self.lss_bit_timing = LSS_BIT_TIMING[d[2]]
            self._lss_reply([cs, 0 if ok else 1])
        elif cs == LSS_ACTIVATE_BIT_TIMING:
            if self.lss_bit_timing is not None:
                self.bitrate = self.lss_bit_timing
        elif cs == LSS_STORE:
            self.lss_stored_id = self.lss_pending_id
            self._lss_reply([cs, 0])
        elif cs in LSS_INQUIRE:
            self._lss_reply(struct.pack("<BI", cs, ident[LSS_INQUIRE[cs]]))
        elif cs == LSS_INQUIRE_NODE_ID:
            self._lss_reply([cs, self.node_id])

    def _fast_scan(self, d, ident):
        """CiA 305 fast scan: answer while bits 31..BitChecked of LSS address part
        LSSSub match IDNumber; after bit 0, go on to part LSSNext (after the last one:
        the configuration state)."""
        if self.lss_mode != 0 or self.node_id != UNCONFIGURED:
            return
        id_number, bit, sub, nxt = struct.unpack_from("<IBBB", d, 1)
        if bit == 0x80:
            self._fs_pos = 0
            self._lss_reply([LSS_IDENTIFY_SLAVE])
            return
        if bit > 31 or sub > 3 or sub != self._fs_pos or (id_number ^ ident[sub]) >> bit:
            return
        self._lss_reply([LSS_IDENTIFY_SLAVE])
        if bit == 0:
            self._fs_pos = nxt
            if nxt < sub:
                self.lss_mode = 1

    @property
    def nmt_state(self):
        return NMT_NAMES[self.nmt]
