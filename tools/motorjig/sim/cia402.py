"""A simulated CANopen CiA 402 drive on the bench's simulated CAN bus.

One axis model, two protocol faces: the shaft moves with the Plus-R drive's
``axis.Motion`` (positions in counts, speeds in counts/s, accelerations in
counts/s², 10 000 counts a turn), and this module is its CANopen face. The object
dictionary comes from the project's EDS (``motorjig.can.EDS_PATH``) read with
python-canopen's ``import_od``; the protocol is written here, on the bench's
virtual clock (python-canopen's own LocalNode runs on threads and wall time).

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

CiA 402: the power state machine is the table ``TRANSITIONS`` (commands decoded
by ``COMMANDS``, states shown by ``STATES``), with quick stop (0x605A), halt (bit
8) and fault reaction (0x605E); profile position (set-point handshake bits 4/5/6,
acknowledge bit 12, target reached bit 10 with 0x6067/0x6068, following error bit
13 and 0x6065/0x6066), profile velocity (0x60FF), homing (0x6098 methods 19-22 on
the rotary axis' origin flag, 35/37 here; 0x6099, 0x609A). Digital inputs 0x60FD
(bit 0 negative limit, 1 positive limit, 2 home switch, 16-31 vendor inputs; the
bench's wiring connects the jig's relays to them: ``connect_inputs``): a limit
switch active in the direction of motion stops the axis with the quick stop
deceleration 0x6085 and shows as internal limit active (statusword bit 11).
Digital outputs 0x60FE:1 masked by 0x60FE:2 (``out_bits``, the wiring's side
towards the jig's inputs).

Faults of a failing drive: ``set_fault(name, value)`` with the names of ``FAULTS``
(following error, overcurrent, sluggish, dead input, a parameter off its golden value,
no origin, missed heartbeats, SDO aborts); ``clear_faults()``. A faulted drive ends in
FAULT (operation disabled) until a fault reset.
"""

import math
import re
import struct

from canopen.objectdictionary import ODArray, ODRecord, ODVariable, import_od
from canopen.objectdictionary.datatypes import INTEGER_TYPES, SIGNED_TYPES

from motorjig.can import EDS_PATH

from .axis import STEP_MS, Motion, at_origin, ramp_ms

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

ABORT_TOGGLE = 0x05030000
ABORT_TIMEOUT = 0x05040000
ABORT_COMMAND = 0x05040001
ABORT_UNSUPPORTED = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE = 0x06090030
ABORT_VALUE_HIGH = 0x06090031
ABORT_VALUE_LOW = 0x06090032
ABORT_GENERAL = 0x08000000
ABORT_STORE = 0x08000020
ABORT_NAMES = {
    ABORT_TOGGLE: "toggle bit not alternated",
    ABORT_TIMEOUT: "SDO protocol timed out",
    ABORT_COMMAND: "client/server command specifier not valid or unknown",
    ABORT_UNSUPPORTED: "unsupported access to an object",
    ABORT_WRITE_ONLY: "attempt to read a write only object",
    ABORT_READ_ONLY: "attempt to write a read only object",
    ABORT_NO_OBJECT: "object does not exist in the object dictionary",
    ABORT_NOT_MAPPABLE: "object cannot be mapped to the PDO",
    ABORT_PDO_LENGTH: "the number and length of the objects to be mapped would exceed the PDO length",
    ABORT_LENGTH: "data type does not match, length of service parameter does not match",
    ABORT_NO_SUBINDEX: "sub-index does not exist",
    ABORT_VALUE: "invalid value for parameter",
    ABORT_VALUE_HIGH: "value of parameter written too high",
    ABORT_VALUE_LOW: "value of parameter written too low",
    ABORT_GENERAL: "general error",
    ABORT_STORE: "data cannot be transferred or stored to the application",
}

SIG_SAVE = 0x65766173  # "save"
NOT_STORED = (0x1003, 0x1010, 0x1011, 0x6040)  # writable objects that 0x1010 does not save
SIG_LOAD = 0x64616F6C  # "load"
DYNAMIC = (0x1001, 0x6041, 0x603F, 0x6061, 0x6062, 0x6064, 0x606C, 0x60F4, 0x60FD)  # what _refresh computes

# EMCY error codes the drive raises, and the error register (0x1001) bits they set
EMCY_RESET = 0x0000
EMCY_OVERCURRENT = 0x2310
EMCY_FOLLOWING_ERROR = 0x8611
ERR_GENERIC = 0x01
ERR_CURRENT = 0x02
ERR_PROFILE = 0x20

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

# --- CiA 402 --------------------------------------------------------------------------
NOT_READY = "NOT READY TO SWITCH ON"
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
FAULT_REACTION = "FAULT REACTION ACTIVE"
FAULT = "FAULT"

# state -> (statusword mask, value): what the statusword shows (bits 0-6)
STATES = {
    NOT_READY: (0x4F, 0x00),
    SWITCH_ON_DISABLED: (0x4F, 0x40),
    READY: (0x6F, 0x21),
    SWITCHED_ON: (0x6F, 0x23),
    OPERATION_ENABLED: (0x6F, 0x27),
    QUICK_STOP_ACTIVE: (0x6F, 0x07),
    FAULT_REACTION: (0x4F, 0x0F),
    FAULT: (0x4F, 0x08),
}
# controlword commands: (name, mask, value), first match wins; fault reset is bit 7's rising edge
COMMANDS = (
    ("DISABLE VOLTAGE", 0x82, 0x00),
    ("QUICK STOP", 0x86, 0x02),
    ("SHUTDOWN", 0x87, 0x06),
    ("SWITCH ON", 0x8F, 0x07),  # also "disable operation" (transition 5)
    ("ENABLE OPERATION", 0x8F, 0x0F),  # also "switch on + enable operation" (3+4)
)
FAULT_RESET = "FAULT RESET"
# (state, command) -> (next state, CiA 402 transition). Automatic ones, not in the table:
# 0+1 power-on -> SWITCH ON DISABLED; 12 QUICK STOP ACTIVE -> SWITCH ON DISABLED when the
# quick stop ends (0x605A 0-4); 13 any -> FAULT REACTION ACTIVE on a fault; 14 FAULT
# REACTION ACTIVE -> FAULT when the reaction ends. Transition 16 needs 0x605A 5-8.
TRANSITIONS = {
    (SWITCH_ON_DISABLED, "SHUTDOWN"): (READY, "2"),
    (READY, "SWITCH ON"): (SWITCHED_ON, "3"),
    (READY, "ENABLE OPERATION"): (OPERATION_ENABLED, "3+4"),
    (SWITCHED_ON, "ENABLE OPERATION"): (OPERATION_ENABLED, "4"),
    (OPERATION_ENABLED, "SWITCH ON"): (SWITCHED_ON, "5"),
    (SWITCHED_ON, "SHUTDOWN"): (READY, "6"),
    (READY, "DISABLE VOLTAGE"): (SWITCH_ON_DISABLED, "7"),
    (READY, "QUICK STOP"): (SWITCH_ON_DISABLED, "7"),
    (OPERATION_ENABLED, "SHUTDOWN"): (READY, "8"),
    (OPERATION_ENABLED, "DISABLE VOLTAGE"): (SWITCH_ON_DISABLED, "9"),
    (SWITCHED_ON, "DISABLE VOLTAGE"): (SWITCH_ON_DISABLED, "10"),
    (SWITCHED_ON, "QUICK STOP"): (SWITCH_ON_DISABLED, "10"),
    (OPERATION_ENABLED, "QUICK STOP"): (QUICK_STOP_ACTIVE, "11"),
    (QUICK_STOP_ACTIVE, "DISABLE VOLTAGE"): (SWITCH_ON_DISABLED, "12"),
    (QUICK_STOP_ACTIVE, "ENABLE OPERATION"): (OPERATION_ENABLED, "16"),
    (FAULT, FAULT_RESET): (SWITCH_ON_DISABLED, "15"),
}

MODE_PP = 1
MODE_PV = 3
MODE_HOMING = 6
MODES = (0, MODE_PP, MODE_PV, MODE_HOMING)
# homing methods: method -> search direction (0: the present position is home)
HOMING_METHODS = {19: 1, 20: 1, 21: -1, 22: -1, 35: 0, 37: 0}
HOMING_GIVE_UP_TURNS = 2  # a homing that has not seen the home switch after this many turns fails

SW_VOLTAGE_ENABLED = 1 << 4
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
SW_BIT12 = 1 << 12  # set-point acknowledge (PP), speed zero (PV), homing attained
SW_BIT13 = 1 << 13  # following error (PP), homing error
CW_NEW_SET_POINT = 1 << 4
CW_CHANGE_IMMEDIATELY = 1 << 5
CW_RELATIVE = 1 << 6
CW_FAULT_RESET = 1 << 7
CW_HALT = 1 << 8

IN_LIMIT_MINUS = 1 << 0
IN_LIMIT_PLUS = 1 << 1
IN_HOME = 1 << 2

SERIAL_BASE = 0x53490000  # serial number 0x1018:4 = SERIAL_BASE + node id (unless given)

# --- faults of a failing drive: set_fault(name, value) ------------------------------------
# name -> (value it takes, default, what it does)
FAULTS = {
    "following-error": ("PPS", 20000, "above PPS counts/s the motor loses steps: position actual (0x6064) falls "
                                      "behind the demand; once the following error 0x60F4 stays above the window "
                                      "0x6065 for the time out 0x6066 the drive faults with EMCY 0x8611"),
    "overcurrent": ("MS", 30.0, "MS ms after a move starts (homing too) the drive faults mid-move with EMCY 0x2310"),
    "sluggish": ("FACTOR", 1.5, "every move takes FACTOR times its profile time (the motor runs slow)"),
    "dead-input": ("BIT", None, "a broken wire: digital input BIT (0..31) of 0x60FD always reads 0 (repeatable)"),
    "no-origin": ("", None, "the home switch never reads active: a homing gives up after two turns with the "
                            "homing error bit 13"),
    "missed-heartbeat": ("", None, "the drive stops producing its heartbeat (0x1017) while set"),
    "sdo-abort": ("CODE[@INDEX[:SUB]]", ABORT_GENERAL, "every SDO request (or only those for object INDEX, "
                                                       "INDEX:SUB; hex) is answered with abort CODE (default "
                                                       "0x08000000)"),
    "param": ("INDEX[:SUB]=VALUE", None, "object INDEX:SUB (an integer in the EDS) reads VALUE, now and after a "
                                        "reset (its saved value too; the drive uses it): a parameter off the golden "
                                        "set (repeatable; a write by SDO replaces it)"),
}
FAULT_ALIASES = {"step-out": "following-error"}  # the Plus-R drive's name for the same failure
_SWITCHES = ("no-origin", "missed-heartbeat")


def _param_value(value):
    """``"0x6081:0=1234"`` / ``"0x6081=1234"`` / ``((index, sub), value)`` -> ((index, sub), value)."""
    if isinstance(value, tuple) and len(value) == 2 and isinstance(value[0], tuple):
        (index, sub), v = value
        return (int(index), int(sub)), int(v)
    text = str(value)
    obj, eq, v = text.rpartition("=")
    if not eq:
        raise ValueError("param: expected INDEX[:SUB]=VALUE, e.g. 0x6081:0=1234, got %r" % (value,))
    index, colon, sub = obj.partition(":")
    try:  # index and sub-index in hex, as the EDS writes them
        return (int(index, 16), int(sub, 16) if colon else 0), int(v, 0)
    except ValueError:
        raise ValueError("param: expected INDEX[:SUB]=VALUE (INDEX, SUB hex), e.g. 0x6081:0=1234, got %r"
                         % (value,)) from None


def check_param(variables, key, value):
    """ValueError unless object ``key`` of ``variables`` ({(index, sub): ODVariable}) is an
    integer object that can hold ``value``."""
    var = variables.get(key)
    where = "param: 0x%04X:%02X" % key
    if var is None:
        raise ValueError("%s is not in the EDS" % where)
    if key[0] in NOT_STORED or key[0] in DYNAMIC:
        raise ValueError("%s is a command or a value the drive computes, not a parameter" % where)
    if var.data_type not in INTEGER_TYPES:
        raise ValueError("%s is not an integer object" % where)
    bits = 8 * var.STRUCT_TYPES[var.data_type].size
    lo, hi = (-(1 << bits - 1), (1 << bits - 1) - 1) if var.data_type in SIGNED_TYPES else (0, (1 << bits) - 1)
    if var.min is not None:
        lo = max(lo, var.min)
    if var.max is not None:
        hi = min(hi, var.max)
    if not lo <= value <= hi:
        raise ValueError("%s must be %d..%d, got %d" % (where, lo, hi, value))


def parse_fault(name, value=None):
    """(name, checked value) of a fault of ``FAULTS`` (None: its default); numbers may be
    text. ValueError with a one-line reason otherwise. ``param``'s value is ((index,
    sub), value), checked against the EDS by the node."""
    name = FAULT_ALIASES.get(name, name)
    if name not in FAULTS:
        raise ValueError("unknown fault %r (known: %s)" % (name, ", ".join(FAULTS)))
    if name == "param":
        if value is None:
            raise ValueError("param: needs a value: param=INDEX[:SUB]=VALUE")
        key, v = _param_value(value)
        check_param(_eds_variables(), key, v)
        return name, (key, v)
    if name in _SWITCHES:
        if value in (None, True, False):
            return name, value is not False
        raise ValueError("%s: takes no value, got %r" % (name, value))
    if value is None:
        value = FAULTS[name][1]
        if value is None:
            raise ValueError("%s: needs a value: %s=%s" % (name, name, FAULTS[name][0]))
    scope = None
    if name == "sdo-abort":
        value, scope = _abort_scope(value)
    try:
        if name in ("sluggish", "overcurrent"):
            v = float(value)
        else:
            v = int(value, 0) if isinstance(value, str) else int(value)
    except (TypeError, ValueError):
        raise ValueError("%s: expected %s, got %r" % (name, FAULTS[name][0], value)) from None
    ok = {"following-error": v > 0, "overcurrent": 0 <= v < float("inf"), "sluggish": 1 <= v < float("inf"),
          "dead-input": 0 <= v <= 31, "sdo-abort": 0 < v <= 0xFFFFFFFF}[name]
    if not ok:
        raise ValueError("%s: %r is out of range for %s" % (name, value, FAULTS[name][0]))
    if name == "sdo-abort":
        return name, (v, scope)
    return name, v


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
        raise ValueError("sdo-abort: expected CODE[@INDEX[:SUB]] (INDEX, SUB hex), e.g. 0x06020000@0x6065, got %r"
                         % (value,)) from None


def od_variables(od):
    """{(index, sub): ODVariable} of an object dictionary."""
    out = {}
    for index in od:
        obj = od[index]
        if isinstance(obj, (ODRecord, ODArray)):
            for sub in obj:
                out[(index, sub)] = obj[sub]
        elif isinstance(obj, ODVariable):
            out[(index, 0)] = obj
    return out


_EDS_VARIABLES = []


def _eds_variables():
    """The project EDS's objects (read once): what ``parse_fault`` checks ``param`` against."""
    if not _EDS_VARIABLES:
        _EDS_VARIABLES.append(od_variables(import_od(EDS_PATH, 1)))
    return _EDS_VARIABLES[0]


def _relative(raw, node_id):
    """A '$NODEID+0x180'-style EDS default for this node id."""
    rest = re.sub(r"\+?\$NODEID\+?", "", raw.replace(" ", "").upper())
    return int(rest, 0) + node_id


class Cia402Node:
    """One simulated CiA 402 drive (see the module's docstring)."""

    def __init__(self, clock, bus, node_id, eds=EDS_PATH, heartbeat_ms=None, serial=None, turnaround_us=100.0,
                 boot_us=1000.0, sdo_timeout_ms=1000.0, name=None):
        if not (1 <= node_id <= 127 or node_id == UNCONFIGURED):
            raise ValueError("node id must be 1..127 or 0xFF (unconfigured), got %r" % (node_id,))
        self.clock = clock
        self.bus = bus
        self.node_id = node_id
        self.turnaround_us = turnaround_us
        self.boot_us = boot_us
        self.sdo_timeout_us = sdo_timeout_ms * 1000.0
        self.od = import_od(eds, None if node_id == UNCONFIGURED else node_id)
        self.vars = od_variables(self.od)  # (index, sub) -> ODVariable
        self.serial = SERIAL_BASE + node_id if serial is None else serial
        self.stored = {}  # (index, sub) -> value saved by 0x1010 (what a reset loads)
        if heartbeat_ms is not None:
            self.stored[(0x1017, 0)] = int(heartbeat_ms)
        self.values = {}
        self.can = bus.add_node(name or "cia402-%d" % node_id, self._on_frame)
        # the axis (the Plus-R drive's model) and its mechanics
        self.motion = Motion()
        self.t_motion = clock.now
        self.t_move_start = clock.now
        self.mech = 0.0  # where the shaft is, in counts (never reset by a homing)
        self.actual_offset = 0.0  # position actual - demand (lost steps)
        self.rev_pulses = 10000
        self.origin_pos = 2500  # the home switch: a flag a quarter turn on from power-up
        self.origin_width = 500
        self.inputs = 0  # digital input bits set from outside (limits, vendor bits), OR-ed in
        self.wire_source = None  # fn() -> input bits from the jig's relays (the bench's wiring)
        self.wire_mask = 0  # the input bits wired to the jig (only their wire drives them)
        self._tick_due = False
        # faults
        self.step_out_pps = None
        self.overcurrent_ms = None
        self.sluggish = 1.0
        self.dead_inputs = 0
        self.no_origin = False
        self.missed_heartbeat = False
        self.sdo_abort_code = None
        self.sdo_abort_scope = None  # None: every request; (index, sub or None): that object's
        self.param_faults = {}  # (index, sub) -> the value set_fault forced
        self._param_saved = {}  # (index, sub) -> (present value, stored value or None) before it
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
        self.transitions = []  # (t_us, CiA 402 transition number)
        self.sdo_requests = 0
        self.rpdo_length_errors = 0  # RPDOs shorter than their mapping (ignored)
        self.state = NOT_READY
        self._fe_since = None
        self._stepping = False
        self.power_on()

    # --- power, resets, NMT --------------------------------------------------------
    def power_on(self):
        """Power-on: every object to its stored/default value, the 402 state machine
        through NOT READY TO SWITCH ON to SWITCH ON DISABLED, boot-up."""
        self.node_id = self.lss_stored_id
        self.lss_pending_id = self.node_id
        self.motion.halt()
        self._reset(application=True)

    def _default(self, key):
        var = self.vars[key]
        if key in self.stored:
            return self.stored[key]
        if getattr(var, "relative", False) and var.default_raw is not None:
            return _relative(var.default_raw, self.node_id if self.node_id != UNCONFIGURED else 0)
        if key == (0x1018, 4):
            return self.serial
        if var.default is None:
            return "" if var.data_type == 0x9 else 0
        return var.default

    def _reset(self, application):
        """Reset node (application True) or reset communication: objects from their
        stored/default values, the pending LSS node id applied, boot-up after boot_us."""
        self.nmt = NMT_INITIALISING
        if self.lss_pending_id != self.node_id:
            self.node_id = self.lss_pending_id
        for key in self.vars:
            if application or key[0] < 0x2000:
                self.values[key] = self._default(key)
        self._hb_gen = getattr(self, "_hb_gen", 0) + 1
        self._sdo = None
        self._sdo_gen = getattr(self, "_sdo_gen", 0) + 1
        self._tpdo = [dict(count=0, last=None, sent_t=None, inhibit_due=False, gen=0) for _ in range(4)]
        self._rpdo_sync = [None] * 4
        if application:
            self._reset_drive()
        if self.node_id != UNCONFIGURED:
            self.clock.after(self.boot_us, self._boot_up, self._hb_gen)

    def _reset_drive(self):
        self.update()
        self.motion.halt()
        self.state = NOT_READY
        self.cw = 0
        self.err_reg = 0
        self.error_code = 0
        self.halted = False
        self.mode = self.values[(0x6060, 0)]
        self.values[(0x6061, 0)] = self.mode
        self.pp_target = int(round(self.motion.pos))
        self.pp_active = False
        self.pp_buffer = None
        self.pp_restart = False
        self.pp_ack = False
        self.pp_done_t = self.clock.now
        self.internal_limit = False
        self.limit_stopped = False  # the last move was stopped by a limit switch
        self.homing = None  # None, "search", "found", "attained", "error", "interrupted"
        self.homing_from = 0.0
        self._fe_since = None
        self._set_state(SWITCH_ON_DISABLED, "0+1")

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

    # --- object access ------------------------------------------------------------------
    def read(self, index, sub=0):
        """The present value of an object (dynamic ones brought up to date)."""
        self._refresh()
        return self.values[(index, sub)]

    def write(self, index, sub, value):
        """Write an object as an SDO download would (checks and effects); returns 0 or
        the SDO abort code."""
        var, code = self._lookup(index, sub)
        if var is None:
            return code
        if not var.writable:
            return ABORT_READ_ONLY
        code = self._store(index, sub, value)
        if not code:
            self._after_change()
        return code

    def _store(self, index, sub, value):
        """Check and store one value, then act on it. 0 or the abort code."""
        self.update()
        code = self._check(index, sub, value)
        if code:
            return code
        self.values[(index, sub)] = value
        self._written(index, sub, value)
        return 0

    def _check(self, index, sub, value):
        var = self.vars[(index, sub)]
        if isinstance(value, int):
            if var.min is not None and value < var.min:
                return ABORT_VALUE_LOW
            if var.max is not None and value > var.max:
                return ABORT_VALUE_HIGH
        if index == 0x1003 and value != 0:
            return ABORT_VALUE
        if index == 0x1010 and sub and value != SIG_SAVE:
            return ABORT_STORE
        if index == 0x1011 and sub and value != SIG_LOAD:
            return ABORT_STORE
        if index == 0x1005 and value & 0x7FFFF800:
            return ABORT_VALUE  # 11-bit COB-ID, consumer only
        if 0x1400 <= index <= 0x1403 or 0x1800 <= index <= 0x1803:
            return self._check_pdo_comm(index, sub, value)
        if 0x1600 <= index <= 0x1603 or 0x1A00 <= index <= 0x1A03:
            return self._check_pdo_map(index, sub, value)
        if index == 0x6060 and value not in MODES:
            return ABORT_VALUE
        if index == 0x6098 and value not in HOMING_METHODS:
            return ABORT_VALUE
        if index == 0x605A and not 0 <= value <= 8:
            return ABORT_VALUE
        if index == 0x605E and not 0 <= value <= 2:
            return ABORT_VALUE
        return 0

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

    def _check_map_entry(self, entry, rx):
        idx, sub, bits = entry >> 16, entry >> 8 & 0xFF, entry & 0xFF
        if rx and 2 <= idx <= 7 and sub == 0:  # dummy entry
            var = self.vars.get((idx, 0))
            if var is None:
                return ABORT_NOT_MAPPABLE
            return 0 if bits == 8 * var.STRUCT_TYPES[var.data_type].size else ABORT_NOT_MAPPABLE
        var = self.vars.get((idx, sub))
        if var is None:
            return ABORT_NO_OBJECT
        if not var.pdo_mappable or (rx and not var.writable) or (not rx and not var.readable):
            return ABORT_NOT_MAPPABLE
        st = var.STRUCT_TYPES.get(var.data_type)
        if st is None or bits != 8 * st.size:
            return ABORT_NOT_MAPPABLE
        return 0

    def _written(self, index, sub, value):
        """What a stored value does."""
        if index == 0x6040:
            self._controlword(value)
        elif index == 0x6060 and value != self.mode:
            self._set_mode(value)
        elif index == 0x60FF:
            self._pv_reconcile()
        elif index == 0x1017:
            self._start_heartbeat()
        elif index == 0x1003:
            for i in range(1, 9):
                self.values[(0x1003, i)] = 0
        elif index == 0x1010:
            self._save(sub)
        elif index == 0x1011:
            self._restore(sub)
        elif index == 0x2001:
            self.actual_offset = value - self.motion.pos
        elif 0x1800 <= index <= 0x1803 and sub in (1, 2, 5):
            n = index - 0x1800
            self._tpdo[n].update(count=0, last=None)
            self._tpdo[n]["gen"] += 1
            self._arm_event_timer(n)

    def _area(self, key, sub):
        """Is object ``key`` in the store/restore area of 0x1010/0x1011 sub-index ``sub``?"""
        comm = key[0] < 0x2000
        return sub == 1 or (sub == 2 and comm) or (sub == 3 and not comm)

    def _save(self, sub):
        for key, var in self.vars.items():
            if (not var.writable or not var.readable or key[0] in NOT_STORED or key[0] < 0x1000
                    or not self._area(key, sub)):
                continue
            self.stored.pop(key, None)
            if self.values[key] != self._default(key):
                self.stored[key] = self.values[key]

    def _restore(self, sub):
        for key in list(self.stored):
            if self._area(key, sub):
                del self.stored[key]

    def _refresh(self):
        """Bring the dynamic objects up to date (motion to now)."""
        self.update()
        v = self.values
        m = self.motion
        demand = int(round(m.pos))
        actual = int(round(m.pos + self.actual_offset))
        v[(0x6041, 0)] = self.statusword()
        v[(0x6062, 0)] = demand
        v[(0x6064, 0)] = actual
        v[(0x60F4, 0)] = demand - actual
        v[(0x606C, 0)] = self.velocity_actual()
        v[(0x60FD, 0)] = self.digital_inputs()
        v[(0x1001, 0)] = self.err_reg
        v[(0x603F, 0)] = self.error_code
        v[(0x6061, 0)] = self.mode

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

    def _lookup(self, index, sub):
        var = self.vars.get((index, sub))
        if var is not None:
            return var, 0
        return None, (ABORT_NO_SUBINDEX if index in self.od else ABORT_NO_OBJECT)

    def _encode(self, var, value):
        if var.data_type == 0x9:
            return value.encode("ascii") if isinstance(value, str) else bytes(value)
        return var.STRUCT_TYPES[var.data_type].pack(value)

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

    def _emcy(self, code, reg):
        self.err_reg = reg
        if code:
            for i in range(8, 1, -1):
                self.values[(0x1003, i)] = self.values[(0x1003, i - 1)]
            self.values[(0x1003, 1)] = code
            self.values[(0x1003, 0)] = min(8, self.values[(0x1003, 0)] + 1)
        if self.nmt in (NMT_PRE_OPERATIONAL, NMT_OPERATIONAL):
            self.emcys.append((self.clock.now, code, reg))
            self._send(self.values[(0x1014, 0)] & 0x7FF, struct.pack("<HB5x", code, reg))

    # --- LSS slave ------------------------------------------------------------------------
    def identity(self):
        return [self.values[(0x1018, i)] for i in (1, 2, 3, 4)]

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

    # --- CiA 402: the power state machine ----------------------------------------------
    def _set_state(self, state, transition):
        self.state = state
        self.transitions.append((self.clock.now, transition))

    def _controlword(self, cw):
        old, self.cw = self.cw, cw
        if cw & CW_FAULT_RESET and not old & CW_FAULT_RESET:
            cmd = FAULT_RESET
        else:
            cmd = None
            for name, mask, value in COMMANDS:
                if cw & mask == value:
                    cmd = name
                    break
        step = TRANSITIONS.get((self.state, cmd))
        if step is not None and not (step[1] == "16" and self.values[(0x605A, 0)] < 5):
            self._transition(*step)
        if self.state == OPERATION_ENABLED:
            self._mode_bits(old, cw)

    def _transition(self, new, label):
        old = self.state
        self._set_state(new, label)
        m = self.motion
        if label in ("3+4", "4", "16"):
            if label != "16":  # enabling: the demand takes the actual position
                m.halt()
                m.pos = float(round(m.pos + self.actual_offset))
                self.actual_offset = 0.0
                self._fe_since = None
            self.pp_target = int(round(m.pos))
            self.pp_active = False
            self.pp_buffer = None
            self.halted = bool(self.cw & CW_HALT)
            self._pv_reconcile()
        elif label == "5":
            self._stop(self.values[(0x6084, 0)])
        elif label == "11":
            option = self.values[(0x605A, 0)]
            if option == 0:
                m.halt()
                self._set_state(SWITCH_ON_DISABLED, "12")
            else:
                self._stop(self.values[(0x6084 if option in (1, 5) else 0x6085, 0)])
                self._quick_stop_done()
        elif label == "15":
            self.error_code = 0
            self._emcy(EMCY_RESET, 0)
        elif old in (OPERATION_ENABLED, QUICK_STOP_ACTIVE):  # 8, 9, 12: the power stage goes off
            m.halt()
        if self.homing == "search" and self.state != OPERATION_ENABLED:
            self.homing = "interrupted"

    def _quick_stop_done(self):
        if self.state == QUICK_STOP_ACTIVE and not self.motion.moving and self.values[(0x605A, 0)] <= 4:
            self._set_state(SWITCH_ON_DISABLED, "12")

    def fault(self, code, reg):
        """The drive detects a fault: FAULT REACTION ACTIVE (13), EMCY ``code``, the
        reaction of 0x605E, then FAULT (14)."""
        if self.state in (FAULT_REACTION, FAULT):
            return
        self._set_state(FAULT_REACTION, "13")
        self.error_code = code
        self._emcy(code, reg | ERR_GENERIC)
        if self.homing == "search":
            self.homing = "error"
        option = self.values[(0x605E, 0)]
        if option == 0:
            self.motion.halt()
        else:
            self._stop(self.values[(0x6084 if option == 1 else 0x6085, 0)])
        self._fe_since = None
        if not self.motion.moving:
            self._set_state(FAULT, "14")

    # --- CiA 402: modes ---------------------------------------------------------------------
    def _set_mode(self, mode):
        if mode != self.mode and self.motion.moving:
            self._stop(self.values[(0x6084, 0)])
        if self.homing == "search":
            self.homing = "interrupted"
        self.mode = mode
        self.pp_active = False
        self.pp_buffer = None
        self._pv_reconcile()

    def _stop(self, decel):
        m = self.motion
        if m.moving:
            m.stop(ramp_ms(abs(m.vel), decel))

    def _now(self):
        """The present instant: the step being run while the axis catches up, else the clock's."""
        return self.t_motion if self._stepping else self.clock.now

    def _move(self, target, speed, direction, acc, dec):
        self.motion.start(target, speed, direction, ramp_ms(speed, acc), ramp_ms(speed, dec), 1)
        self.t_motion = self.t_move_start = self._now()
        self._check_limit_switches()  # towards an active limit switch: stopped at once

    def _mode_bits(self, old, cw):
        """Bits 4-8 of the controlword in OPERATION ENABLED."""
        halt = bool(cw & CW_HALT)
        if halt != self.halted:
            self.halted = halt
            if halt:
                if self.homing == "search":
                    self.homing = "interrupted"
                self._stop(self.values[(0x6084, 0)])
            elif self.mode == MODE_PP and self.pp_active:
                self._pp_go(self.pp_target)
            self._pv_reconcile()
        rising = cw & CW_NEW_SET_POINT and not old & CW_NEW_SET_POINT
        if self.mode == MODE_PP:
            if rising and not halt:
                target = self.values[(0x607A, 0)]
                if cw & CW_RELATIVE:
                    target += self.pp_target
                if not self.pp_active or cw & CW_CHANGE_IMMEDIATELY:
                    self._pp_start(target)
                    self.pp_ack = True
                elif self.pp_buffer is None:
                    self.pp_buffer = target
                    self.pp_ack = True
            elif not cw & CW_NEW_SET_POINT and self.pp_buffer is None:
                self.pp_ack = False
        elif self.mode == MODE_HOMING and rising and not halt:
            self._homing_start()

    def _pp_start(self, target):
        self.limit_stopped = False
        lo, hi = self.values[(0x607D, 1)], self.values[(0x607D, 2)]
        self.internal_limit = not lo <= target <= hi
        target = min(max(target, lo), hi)
        self.pp_target = target
        self.pp_active = True
        self._pp_go(target)

    def _pp_go(self, target):
        m = self.motion
        if m.moving and (target - m.pos) * m.direction < 0:
            self.pp_restart = True  # reverse: stop first, then go
            self._stop(self.values[(0x6084, 0)])
            return
        if not m.moving and target == round(m.pos):
            self._pp_arrived()
            return
        v = self.values
        self._move(target, v[(0x6081, 0)], 1 if target > m.pos else -1, v[(0x6083, 0)], v[(0x6084, 0)])

    def _pp_arrived(self):
        self.pp_active = False
        self.pp_done_t = self._now()
        wait = self.values[(0x6068, 0)] * 1000.0
        if wait:
            self.clock.at(self.pp_done_t + wait, self._after_change)
        if self.pp_buffer is not None:
            target, self.pp_buffer = self.pp_buffer, None
            if not self.cw & CW_NEW_SET_POINT:
                self.pp_ack = False
            self._pp_start(target)

    def _pv_reconcile(self):
        """Profile velocity: steer the axis towards 0x60FF (stop first to reverse)."""
        if self.state != OPERATION_ENABLED or self.mode != MODE_PV:
            return
        m = self.motion
        v = self.values
        target = 0 if self.halted else v[(0x60FF, 0)]
        d = 1 if target > 0 else -1
        if self.digital_inputs() & (IN_LIMIT_PLUS if d > 0 else IN_LIMIT_MINUS):
            target = 0  # held by the limit switch
        if target == 0 or (m.moving and (m.direction != d or m.target is not None)):
            self._stop(v[(0x6084, 0)])
        elif not m.moving or m.stopping or m.vmax != abs(target):
            self._move(None, abs(target), d, v[(0x6083, 0)], v[(0x6084, 0)])

    def _homing_start(self):
        method = self.values[(0x6098, 0)]
        direction = HOMING_METHODS[method]
        if direction == 0:
            self._home_here()
            return
        speed = self.values[(0x6099, 1)]
        acc = self.values[(0x609A, 0)]
        self.homing = "search"
        self.homing_from = self.mech
        self._move(None, speed, direction, acc, acc)
        self._check_home_switch()

    def _home_here(self):
        self.motion.halt()
        self.motion.pos = float(self.values[(0x607C, 0)])
        self.actual_offset = 0.0
        self.pp_target = int(self.motion.pos)
        self.homing = "attained"

    def _check_limit_switches(self):
        """A limit switch active in the direction of motion stops the axis with the quick
        stop deceleration 0x6085 (a homing there fails): the move is over, not a fault."""
        m = self.motion
        if not m.moving:
            return
        bits = self.digital_inputs()
        if not bits & (IN_LIMIT_PLUS if m.direction > 0 else IN_LIMIT_MINUS):
            return
        if self.homing == "search":
            self.homing = "error"
        if self.mode == MODE_PP and self.pp_active:
            self.pp_active = False
            self.pp_buffer = None
            self.pp_restart = False
            self.pp_done_t = self._now()
        self.limit_stopped = True
        self._stop(self.values[(0x6085, 0)])

    def limit_active(self):
        """A limit switch input reads active (statusword bit 11, internal limit active)."""
        return bool(self.digital_inputs() & (IN_LIMIT_PLUS | IN_LIMIT_MINUS))

    def _check_home_switch(self):
        if self.homing != "search":
            return
        if self.digital_inputs() & IN_HOME:
            self.homing = "found"
            self._stop(self.values[(0x609A, 0)])
        elif abs(self.mech - self.homing_from) > HOMING_GIVE_UP_TURNS * (self.rev_pulses or 10000):
            self.homing = "error"
            self._stop(self.values[(0x609A, 0)])

    # --- the axis ---------------------------------------------------------------------------
    def update(self):
        """Run the axis up to the clock's present, STEP_MS step by step."""
        now = self.clock.now
        step_us = STEP_MS * 1000.0
        self._stepping = True
        try:
            while (self.motion.moving or self._fe_since is not None) and self.t_motion + step_us <= now:
                self.t_motion += step_us
                self._step(STEP_MS / 1000.0)
        finally:
            self._stepping = False
        if not self.motion.moving and self._fe_since is None:
            self.t_motion = now

    def _step(self, dt):
        m = self.motion
        was_moving = m.moving
        p0 = m.pos
        m.step(dt / self.sluggish)
        dp = m.pos - p0
        moved = dp
        if self.step_out_pps is not None and abs(dp) > self.step_out_pps * dt:
            moved = math.copysign(self.step_out_pps * dt, dp)
            self.actual_offset -= dp - moved
        self.mech += moved
        self._check_limit_switches()
        self._check_home_switch()
        if m.moving and self.overcurrent_ms is not None and self.t_motion - self.t_move_start >= self.overcurrent_ms * 1000.0:
            self.fault(EMCY_OVERCURRENT, ERR_CURRENT)
        self._check_following_error()
        if was_moving and not m.moving:
            self._motion_ended()

    def _check_following_error(self):
        window = self.values[(0x6065, 0)]
        if window != 0xFFFFFFFF and abs(self.actual_offset) > window and self.state in (OPERATION_ENABLED,
                                                                                       QUICK_STOP_ACTIVE):
            if self._fe_since is None:
                self._fe_since = self.t_motion
            elif self.t_motion - self._fe_since >= self.values[(0x6066, 0)] * 1000.0:
                self.fault(EMCY_FOLLOWING_ERROR, ERR_PROFILE)
        else:
            self._fe_since = None

    def _motion_ended(self):
        if self.state == FAULT_REACTION:
            self._set_state(FAULT, "14")
            return
        self._quick_stop_done()
        if self.homing == "found":
            self._home_here()
        if self.mode == MODE_PP and self.pp_active:
            if self.pp_restart:
                self.pp_restart = False
                self._pp_go(self.pp_target)
            elif round(self.motion.pos) == self.pp_target:
                self._pp_arrived()
        elif self.mode == MODE_PV:
            self._pv_reconcile()

    def _needs_tick(self):
        return self.motion.moving or self._fe_since is not None

    def _after_change(self):
        """After any event: event-driven TPDOs, and the axis' next tick while it moves."""
        self._tpdo_events()
        if self._needs_tick() and not self._tick_due:
            self._tick_due = True
            self.clock.at(self.t_motion + STEP_MS * 1000.0, self._tick)

    def _tick(self):
        self._tick_due = False
        self.update()
        self._after_change()

    # --- what the drive shows -------------------------------------------------------------
    def velocity_actual(self):
        v = self.motion.vel / self.sluggish
        if self.step_out_pps is not None and abs(v) > self.step_out_pps:
            v = math.copysign(self.step_out_pps, v)
        return int(round(v))

    def connect_inputs(self, source, mask):
        """Wire the input bits in ``mask`` to ``source()`` (the jig's relays through the
        bench's wiring), read whenever the drive looks at its inputs. A wired bit reads
        only its wire: the drive's own home switch is not connected if bit 2 is wired."""
        self.wire_source = source
        self.wire_mask = mask

    def digital_inputs(self):
        """0x60FD: the bits set from outside (``inputs``) OR the physical ones (the home
        switch, the wires to the jig) less the dead ones."""
        physical = 0
        if not self.no_origin and at_origin(self.mech, self.origin_pos, self.origin_width, self.rev_pulses):
            physical |= IN_HOME
        physical &= ~self.wire_mask
        if self.wire_source is not None:
            physical |= self.wire_source() & self.wire_mask
        return (self.inputs | (physical & ~self.dead_inputs)) & 0xFFFFFFFF

    def inputs_changed(self):
        """Something outside changed the inputs (a relay): event-driven TPDOs (0x60FD),
        a limit switch stopping the axis."""
        self.update()
        self._check_limit_switches()
        self._after_change()

    def out_bits(self):
        """The digital outputs as they reach the wires: 0x60FE:1 masked by 0x60FE:2."""
        return self.values[(0x60FE, 1)] & self.values[(0x60FE, 2)]

    def statusword(self):
        self.update()
        sw = STATES[self.state][1] | SW_REMOTE
        if self.state in (SWITCHED_ON, OPERATION_ENABLED, QUICK_STOP_ACTIVE):
            sw |= SW_VOLTAGE_ENABLED
        if self.state != OPERATION_ENABLED:
            return sw
        if self.limit_active():
            sw |= SW_INTERNAL_LIMIT
        m = self.motion
        if self.mode == MODE_PP:
            window = self.values[(0x6065, 0)]
            if window != 0xFFFFFFFF and abs(self.actual_offset) > window:
                sw |= SW_BIT13
            if self.pp_ack:
                sw |= SW_BIT12
            if self.internal_limit:
                sw |= SW_INTERNAL_LIMIT
            if not m.moving:
                actual = m.pos + self.actual_offset
                settled = self.clock.now - self.pp_done_t >= self.values[(0x6068, 0)] * 1000.0
                if (self.halted and self.pp_active) or (not self.pp_active and self.limit_stopped) or (
                        not self.pp_active and settled and abs(self.pp_target - actual) <= self.values[(0x6067, 0)]):
                    sw |= SW_TARGET_REACHED
        elif self.mode == MODE_PV:
            if not m.moving:
                sw |= SW_BIT12
                if self.halted or self.values[(0x60FF, 0)] == 0:
                    sw |= SW_TARGET_REACHED
            elif m.phase == 2 and not m.stopping and m.vmax * m.direction == self.values[(0x60FF, 0)]:
                sw |= SW_TARGET_REACHED
        elif self.mode == MODE_HOMING:
            h = self.homing
            if h == "attained":
                sw |= SW_BIT12 | SW_TARGET_REACHED
            elif h == "error":
                sw |= SW_BIT13 | (0 if m.moving else SW_TARGET_REACHED)
            elif h == "interrupted" and not m.moving:
                sw |= SW_TARGET_REACHED
        return sw

    # --- faults -------------------------------------------------------------------------------
    def set_fault(self, name, value=None):
        """Make the drive fail (``FAULTS``; None: the default value). ValueError for an
        unknown name or a bad value."""
        name, v = parse_fault(name, value)
        self.update()
        if name == "following-error":
            self.step_out_pps = v
        elif name == "overcurrent":
            self.overcurrent_ms = v
        elif name == "sluggish":
            self.sluggish = v
        elif name == "dead-input":
            self.dead_inputs |= 1 << v
        elif name == "no-origin":
            self.no_origin = v
        elif name == "missed-heartbeat":
            self.missed_heartbeat = v
        elif name == "sdo-abort":
            self.sdo_abort_code, self.sdo_abort_scope = v
        elif name == "param":
            key, value = v
            check_param(self.vars, key, value)
            self._param_saved.setdefault(key, (self.values[key], self.stored.get(key)))
            self.param_faults[key] = value
            self._force(key, value, value)

    def _force(self, key, value, stored):
        """Object ``key`` reads ``value`` now and ``stored`` after a reset (None: its default)."""
        if stored is None:
            self.stored.pop(key, None)
        else:
            self.stored[key] = stored
        self.values[key] = value
        self._written(key[0], key[1], value)
        self._after_change()

    def active_faults(self):
        """The faults that are on, as NAME[=VALUE]."""
        out = []
        if self.step_out_pps is not None:
            out.append("following-error=%d" % self.step_out_pps)
        if self.overcurrent_ms is not None:
            out.append("overcurrent=%g" % self.overcurrent_ms)
        if self.sluggish != 1.0:
            out.append("sluggish=%g" % self.sluggish)
        out += ["dead-input=%d" % b for b in range(32) if self.dead_inputs >> b & 1]
        if self.no_origin:
            out.append("no-origin")
        if self.missed_heartbeat:
            out.append("missed-heartbeat")
        if self.sdo_abort_code is not None:
            scope = self.sdo_abort_scope
            out.append("sdo-abort=0x%08X" % self.sdo_abort_code + (
                "" if scope is None else "@0x%04X" % scope[0] + ("" if scope[1] is None else ":%02X" % scope[1])))
        out += ["param=0x%04X:%02X=%d" % (k + (v,)) for k, v in sorted(self.param_faults.items())]
        return out

    def clear_faults(self):
        """Every fault of ``FAULTS`` off (a drive in FAULT stays there until reset)."""
        self.update()
        self.step_out_pps = None
        self.overcurrent_ms = None
        self.sluggish = 1.0
        self.dead_inputs = 0
        self.no_origin = False
        self.missed_heartbeat = False
        self.sdo_abort_code = None
        self.sdo_abort_scope = None
        saved, self._param_saved = self._param_saved, {}
        self.param_faults = {}
        for key, (value, stored) in saved.items():
            self._force(key, value, stored)

    @property
    def nmt_state(self):
        return NMT_NAMES[self.nmt]
