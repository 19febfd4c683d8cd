"""A simulated EtherCAT CiA 402 servo drive: the bench's drive (``drive402``) behind an ESC, speaking CoE.

The drive is the one the CAN nodes are (``drive402.Drive402``: objects, power state machine,
modes, axis, faults) with the cyclic modes a cyclic bus allows (CSP 8, CSV 9). Its EtherCAT
face: an ESC (``ecat_esc.Esc``) whose SII comes from the project's ESI
(``motorjig/ecat/motorjig-servo.xml``), the firmware's state machine and mailbox
(``ecat_slave.EcatSlave``), SDOs and emergencies over CoE (``ecat_coe``), and process data
laid out by the PDO assignment 0x1C12/0x1C13 and the mappings 0x1600-0x1603 / 0x1A00-0x1A03,
which a master may rewrite in PRE-OP (count 0, entries, count; assignment likewise).

The object dictionary is the CAN drive's EDS less CANopen's communication objects (SYNC, EMCY
COB-ID, heartbeat, SDO server, PDO communication), plus 0x1C00 (sync manager types), 0x1C12,
0x1C13 and 0x6007 (abort connection option code: what the drive does when the master goes
away; 1, fault, by default). When the master's process data stop (the watchdog) or it takes
the slave out of OP, the drive reacts as 0x6007 says: a drive moving under a dead master stops.

Faults: the drive's (``drive402.DRIVE_FAULTS``) and EtherCAT's own: ``sdo-abort``, ``refuse-op``
(OP refused with an AL status code), ``link-down`` (the slave's port 0 sees no frame: it and
those after it fall off the bus), ``lost-frames`` (every Nth frame is dropped on its way).
"""


from canopen.objectdictionary import ODArray, ODVariable, import_od
from canopen.objectdictionary.datatypes import INTEGER16, UNSIGNED8, UNSIGNED16

from motorjig.can import EDS_PATH
from motorjig.ecat import esi, sii

from . import ecat_coe
from .drive402 import (ABORT_GENERAL, ABORT_NOT_MAPPABLE, ABORT_PDO_LENGTH, ABORT_UNSUPPORTED, ABORT_VALUE,
                       CYCLIC_MODES, DRIVE_FAULTS, FAULT_ALIASES, MODES, SERIAL_BASE, Drive402)
from .ecat_esc import Esc
from .ecat_slave import PREOP, EcatSlave
from .faults import Fault, FaultTable, in_range, number, switch

ESI_PATH = esi.__file__.replace("esi.py", "motorjig-servo.xml")
EMCY_CONNECTION_LOST = 0x8130  # CiA 301 "life guard error or heartbeat error": the master went silent
ABORT_STATE = 0x08000022  # data cannot be transferred or stored because of the present device state
CAN_ONLY = (0x1005, 0x1014, 0x1017, 0x1200, 0x1400, 0x1401, 0x1402, 0x1403, 0x1800, 0x1801, 0x1802, 0x1803)
RX_MAPS = range(0x1600, 0x1604)
TX_MAPS = range(0x1A00, 0x1A04)


def _sdo_abort(value):
    code, _, obj = str(value).partition("@") if not isinstance(value, tuple) else (value[0], "", "")
    v = number(code, int, "CODE[@INDEX[:SUB]], an SDO abort code")
    if not 0 < v <= 0xFFFFFFFF:
        raise ValueError("expected an SDO abort code, got %r" % (code,))
    if isinstance(value, tuple):
        return v, value[1]
    if not obj:
        return v, None
    index, colon, sub = obj.partition(":")
    try:
        return v, (int(index, 16), int(sub, 16) if colon else None)
    except ValueError:
        raise ValueError("expected CODE[@INDEX[:SUB]] (INDEX, SUB hex), got %r" % (value,)) from None


_D = DRIVE_FAULTS
FAULTS = FaultTable([
    _D["following-error"], _D["overcurrent"], _D["sluggish"], _D["dead-input"], _D["no-origin"], _D["param"],
    Fault("sdo-abort", "CODE[@INDEX[:SUB]]", ABORT_GENERAL, "every SDO request (or only those for object INDEX, "
                                                            "INDEX:SUB; hex) is answered with abort CODE", _sdo_abort),
    Fault("refuse-op", "CODE", 0x001A, "the slave refuses OP with AL status code CODE (default 0x001A "
                                       "synchronization error)", lambda v: in_range(v, int, "an AL status code", 1, 0xFFFF)),
    switch("link-down", "the slave's port 0 loses its link: it and every slave after it fall off the bus"),
    Fault("lost-frames", "N", 100, "in OP, every Nth frame is lost on its way through the slave (none comes back)",
          lambda v: in_range(v, int, "a frame count N >= 2", 2, None)),
], FAULT_ALIASES)


def _array(od, index, name, data_type, values, writable):
    arr = ODArray(name, index)
    count = ODVariable("Number of entries", index, 0)
    count.data_type = UNSIGNED8
    count.access_type = "rw" if writable else "ro"
    count.default = len([v for v in values if v])
    arr.add_member(count)
    for n, v in enumerate(values, 1):
        var = ODVariable("%s %d" % (name, n), index, n)
        var.data_type = data_type
        var.access_type = "rw" if writable else "ro"
        var.default = v
        arr.add_member(var)
    od.add_object(arr)


def _mapping_entry(e):
    return e.index << 16 | e.sub << 8 | e.bits


def object_dictionary(device):
    """The servo's object dictionary: the CAN drive's EDS, its CANopen communication objects taken
    out, EtherCAT's sync manager objects added, the default PDOs those of ``device`` (the ESI)."""
    od = import_od(EDS_PATH, 1)
    for index in CAN_ONLY:
        if index in od:
            del od[index]
    _array(od, 0x1C00, "Sync manager type", UNSIGNED8, [1, 2, 3, 4], False)
    rx = [p.index for p in device.rx_pdos]
    tx = [p.index for p in device.tx_pdos]
    _array(od, 0x1C12, "RxPDO assign", UNSIGNED16, (rx + [0, 0, 0, 0])[:4], True)
    _array(od, 0x1C13, "TxPDO assign", UNSIGNED16, (tx + [0, 0, 0, 0])[:4], True)
    for pdo in device.rx_pdos + device.tx_pdos:
        if pdo.index in od:
            obj = od[pdo.index]
            obj[0].default = len(pdo.entries)
            for n in range(1, 9):
                if n in obj:
                    obj[n].default = _mapping_entry(pdo.entries[n - 1]) if n <= len(pdo.entries) else 0
    abort_option = ODVariable("Abort connection option code", 0x6007, 0)
    abort_option.data_type = INTEGER16
    abort_option.access_type = "rw"
    abort_option.default = 1
    abort_option.min, abort_option.max = 0, 3
    od.add_object(abort_option)
    if 0x6502 in od:
        od[0x6502].default = (od[0x6502].default or 0) | 1 << 7 | 1 << 8  # CSP, CSV
    return od


class EcatServo(Drive402):
    """One simulated EtherCAT servo (see the module's docstring) on the bench's ``clock``."""

    FAULTS = FAULTS
    modes = MODES + CYCLIC_MODES

    def __init__(self, clock, position, serial=None, esi_path=ESI_PATH, clock_offset_ns=0):
        device = esi.read(esi_path)[0]
        self.device = device
        serial = SERIAL_BASE + 0x1000 + position if serial is None else serial
        Drive402.__init__(self, clock, object_dictionary(device), serial)
        self.node_id = 0
        self.position = position
        self.clock_offset_ns = clock_offset_ns
        self.lost_every = None
        self.outputs_applied = 0
        self.emcys = []  # (t_us, code, register)
        self.power_on()

    def power_on(self):
        """Power-up: a fresh ESC (INIT, registers cleared, the SII loaded) and the drive's objects from
        their defaults (a PDO remap or a parameter written by SDO is gone, as in a real drive's RAM)."""
        device = self.device
        self.esc = Esc(self.local_ns, sii.image(device, self.serial))
        rx, tx = esi.sm_of(device, "MBoxOut")[1], esi.sm_of(device, "MBoxIn")[1]
        self.slave = EcatSlave(self.clock, self.esc, self, (rx.start, rx.size, tx.start, tx.size))
        self.sdo = ecat_coe.SdoServer(self, rx.size)
        self.clear_faults()
        self.motion.halt()
        self._reset_values(comm_only=False)
        self._reset_drive()

    def local_ns(self):
        """The slave's own clock (ns): the bench's, shifted as each slave powers up at its own time."""
        return int(self.clock.now * 1000.0) + self.clock_offset_ns

    @property
    def name(self):
        return self.device.name

    # --- what the EtherCAT firmware asks ---------------------------------------------------------
    def _layout(self, assign, maps):
        """[(index, sub, bits)] of the PDOs assigned in 0x1C12/0x1C13."""
        out = []
        for i in range(1, self.values[(assign, 0)] + 1):
            pdo = self.values[(assign, i)]
            if pdo not in maps:
                continue
            for n in range(1, self.values[(pdo, 0)] + 1):
                e = self.values[(pdo, n)]
                out.append((e >> 16, e >> 8 & 0xFF, e & 0xFF))
        return out

    def pdo_sizes(self):
        """(output bytes, input bytes) of the present PDO assignment and mapping."""
        return (sum(b for _i, _s, b in self._layout(0x1C12, RX_MAPS)) // 8,
                sum(b for _i, _s, b in self._layout(0x1C13, TX_MAPS)) // 8)

    def pd_outputs(self, data):
        """The master's outputs in OP: every mapped object written, the controlword last."""
        pos = 0
        writes = []
        for index, sub, bits in self._layout(0x1C12, RX_MAPS):
            n = bits // 8
            chunk = data[pos:pos + n]
            pos += n
            var = self.vars.get((index, sub))
            if var is None or index == 0:
                continue
            writes.append(((index, sub), var.STRUCT_TYPES[var.data_type].unpack(chunk)[0]))
        writes.sort(key=lambda w: w[0] == (0x6040, 0))
        for (index, sub), value in writes:
            if self.values.get((index, sub)) != value or index in (0x6040, 0x607A):
                self._store(index, sub, value)
        self.outputs_applied += 1
        self._after_change()

    def pd_inputs(self):
        """The inputs the master reads: every mapped object's present value."""
        self._refresh()
        out = bytearray()
        for index, sub, bits in self._layout(0x1C13, TX_MAPS):
            var = self.vars.get((index, sub))
            n = bits // 8
            if var is None or index == 0:
                out += bytes(n)
            else:
                out += self._encode(var, self.values[(index, sub)])[:n]
        return bytes(out)

    def outputs_lost(self, why):
        """The master went away (watchdog) or took the slave out of OP: 0x6007's reaction."""
        self.connection_lost(EMCY_CONNECTION_LOST)

    def coe(self, body):
        return self.sdo.request(body)

    # --- CoE's own object rules ------------------------------------------------------------------
    def _check(self, index, sub, value):
        code = Drive402._check(self, index, sub, value)
        if code:
            return code
        if index in (0x1C12, 0x1C13) or index in RX_MAPS or index in TX_MAPS:
            if self.slave.state != PREOP:
                return ABORT_STATE  # PDOs are assigned and mapped in PRE-OP only
            if sub and self.values[(index, 0)] != 0:
                return ABORT_UNSUPPORTED  # entries change while the count is 0
        if index in (0x1C12, 0x1C13):
            maps = RX_MAPS if index == 0x1C12 else TX_MAPS
            if sub == 0:
                return 0 if value <= 4 and all(self.values[(index, i)] in maps for i in range(1, value + 1)) \
                    else ABORT_VALUE
            return 0 if value in maps or value == 0 else ABORT_VALUE
        if index in RX_MAPS or index in TX_MAPS:
            rx = index in RX_MAPS
            if sub == 0:
                bits = 0
                for i in range(1, value + 1):
                    entry = self.values[(index, i)]
                    code = self._check_entry(entry, rx)
                    if code:
                        return code
                    bits += entry & 0xFF
                return ABORT_PDO_LENGTH if bits > 8 * 64 else 0
            return self._check_entry(value, rx) if value else 0
        return 0

    def _check_entry(self, entry, rx):
        if entry >> 16 == 0:
            return 0 if entry & 0xFF and not entry >> 8 & 0xFF else ABORT_NOT_MAPPABLE  # a gap
        return self._check_map_entry(entry, rx)

    def _emergency(self, code, reg):
        self.emcys.append((self.clock.now, code, reg))
        self.slave.send(3, ecat_coe.emergency(code, reg))

    # --- faults ----------------------------------------------------------------------------------
    def _apply_fault(self, name, v):
        if name == "sdo-abort":
            self.sdo.abort_code, self.sdo.abort_scope = v
        elif name == "refuse-op":
            self.slave.refuse_op = v
        elif name == "link-down":
            self.esc.link_up = not v
        elif name == "lost-frames":
            self.lost_every = v
        else:
            Drive402._apply_fault(self, name, v)

    def active_faults(self):
        out = Drive402.active_faults(self)
        if self.sdo.abort_code is not None:
            out.append("sdo-abort=0x%08X" % self.sdo.abort_code)
        if self.slave.refuse_op:
            out.append("refuse-op=0x%04X" % self.slave.refuse_op)
        if not self.esc.link_up:
            out.append("link-down")
        if self.lost_every:
            out.append("lost-frames=%d" % self.lost_every)
        return out

    def clear_faults(self):
        self.sdo.abort_code = self.sdo.abort_scope = None
        self.slave.refuse_op = None
        self.esc.link_up = True
        self.lost_every = None
        Drive402.clear_faults(self)
