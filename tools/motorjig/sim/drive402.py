"""A simulated CiA 402 drive, whatever bus it is on: its objects, its power state machine, its modes.

The device profile, without a bus: the object dictionary's values (read, written with the
checks and effects an SDO download has, saved and restored by 0x1010/0x1011), the power
state machine ``TRANSITIONS`` (commands decoded by ``COMMANDS``, states shown by
``STATES``) with quick stop (0x605A), halt (bit 8) and fault reaction (0x605E); profile
position (set-point handshake bits 4/5/6, acknowledge bit 12, target reached bit 10 with
0x6067/0x6068, following error bit 13 and 0x6065/0x6066), profile velocity (0x60FF), homing
(0x6098 methods 19-22 on the rotary axis' origin flag, 35/37 here; 0x6099, 0x609A). Digital
inputs 0x60FD (bit 0 negative limit, 1 positive limit, 2 home switch, 16-31 vendor inputs;
the bench's wiring connects the jig's relays to them: ``connect_inputs``): a limit switch
active in the direction of motion stops the axis with the quick stop deceleration 0x6085 and
shows as internal limit active (statusword bit 11). Digital outputs 0x60FE:1 masked by
0x60FE:2 (``out_bits``).

The shaft is the bench's shared axis (``axis.Motion``: counts, counts/s, counts/s², 10 000
counts a turn). A bus face subclasses ``Drive402``: the CANopen node (``sim.cia402``: NMT,
SDO, PDO, LSS) and the EtherCAT slave's CoE face each add their protocol and answer three
hooks: ``_emergency`` (send an EMCY), ``_on_change`` (event-driven process data) and
``_reset_values``' caller (their own resets).

Faults of a failing drive: ``set_fault(name, value)`` with the names of ``DRIVE_FAULTS``
(following error, overcurrent, sluggish, dead input, a parameter off its golden value, no
origin); a bus face adds its own. A faulted drive ends in FAULT until a fault reset.
"""

import math
import re

from canopen.objectdictionary import ODArray, ODRecord, ODVariable, import_od
from canopen.objectdictionary.datatypes import INTEGER_TYPES, SIGNED_TYPES

from motorjig.can import EDS_PATH

from .axis import STEP_MS, Motion, at_origin, ramp_ms
from .faults import SLUGGISH, Fault, FaultTable, dead_input, in_range, speed_limit, switch

# --- SDO abort codes (CiA 301): what an object access answers, on CAN and in CoE alike ---------
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
MODE_CSP = 8  # cyclic synchronous position: the master sends a target position every cycle
MODE_CSV = 9  # cyclic synchronous velocity
MODES = (0, MODE_PP, MODE_PV, MODE_HOMING)  # what a CANopen face offers; cyclic modes need a cyclic bus
CYCLIC_MODES = (MODE_CSP, MODE_CSV)
CSV_ACCEL = 10 ** 9  # counts/s²: in CSV the drive takes each cycle's velocity at once
CSP_IDLE_US = 3000.0  # a CSP drive without a new target for this long stands (velocity 0)
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
def _param_fault(value):
    key, v = _param_value(value)
    check_param(_eds_variables(), key, v)
    return key, v


# the faults of the drive itself; a bus face adds its own (sim.faults.FaultTable)
DRIVE_FAULTS = {
    "following-error": speed_limit(
        "following-error", "above PPS counts/s the motor loses steps: position actual (0x6064) falls behind the "
                           "demand; once the following error 0x60F4 stays above the window 0x6065 for the time "
                           "out 0x6066 the drive faults with EMCY 0x8611"),
    "overcurrent": Fault("overcurrent", "MS", 30.0, "MS ms after a move starts (homing too) the drive faults mid-move "
                                                    "with EMCY 0x2310",
                         lambda v: in_range(v, float, "a time in ms >= 0", 0, None)),
    "sluggish": SLUGGISH,
    "dead-input": dead_input("digital input of 0x60FD"),
    "no-origin": switch("no-origin", "the home switch never reads active: a homing gives up after two turns with "
                                     "the homing error bit 13"),
    "param": Fault("param", "INDEX[:SUB]=VALUE", None,
                   "object INDEX:SUB (an integer in the EDS) reads VALUE, now and after a reset (its saved value "
                   "too; the drive uses it): a parameter off the golden set (repeatable; a write by SDO replaces it)",
                   _param_fault),
}
FAULT_ALIASES = {"step-out": "following-error"}  # the Plus-R drive's name for the same failure


def _param_value(value):
    """``"0x6081:0=1234"`` / ``"0x6081=1234"`` / ``((index, sub), value)`` -> ((index, sub), value)."""
    if isinstance(value, tuple) and len(value) == 2 and isinstance(value[0], tuple):
        (index, sub), v = value
        return (int(index), int(sub)), int(v)
    text = str(value)
    obj, eq, v = text.rpartition("=")
    if not eq:
        raise ValueError("expected INDEX[:SUB]=VALUE, e.g. 0x6081:0=1234, got %r" % (value,))
    index, colon, sub = obj.partition(":")
    try:  # index and sub-index in hex, as the EDS writes them
        return (int(index, 16), int(sub, 16) if colon else 0), int(v, 0)
    except ValueError:
        raise ValueError("expected INDEX[:SUB]=VALUE (INDEX, SUB hex), e.g. 0x6081:0=1234, got %r"
                         % (value,)) from None


def check_param(variables, key, value):
    """ValueError unless object ``key`` of ``variables`` ({(index, sub): ODVariable}) is an
    integer object that can hold ``value``."""
    var = variables.get(key)
    where = "0x%04X:%02X" % key
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



class Drive402:
    """One simulated CiA 402 drive without its bus (see the module's docstring); a bus face
    subclasses it, sets ``node_id`` (0 when its bus has none) and calls ``power_on``."""

    FAULTS = FaultTable(DRIVE_FAULTS.values(), FAULT_ALIASES)  # a face's own table replaces it
    modes = MODES  # the modes of operation 0x6060 takes (a cyclic bus's face adds CSP and CSV)

    def __init__(self, clock, od, serial):
        self.clock = clock
        self.od = od
        self.vars = od_variables(od)  # (index, sub) -> ODVariable
        self.serial = serial
        self.stored = {}  # (index, sub) -> value saved by 0x1010 (what a reset loads)
        self.values = {}
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
        self.param_faults = {}  # (index, sub) -> the value set_fault forced
        self._param_saved = {}  # (index, sub) -> (present value, stored value or None) before it
        # logs for tests
        self.transitions = []  # (t_us, CiA 402 transition number)
        self.state = NOT_READY
        self._fe_since = None
        self._stepping = False
        self.csp_t = None  # when the last CSP target came (µs)
        self.csp_vel = 0.0  # counts/s between the last two CSP targets
        self.csp_dt = 0.001  # the cycle the CSP targets come at (s), smoothed
        self.csp_since = None  # when the present CSP motion began (overcurrent's clock)

    # --- hooks of the bus face ------------------------------------------------------------------
    def _emergency(self, code, reg):
        """Tell the bus: EMCY ``code`` with error register ``reg`` (the face sends it)."""

    def _on_change(self):
        """After any event: the face's event-driven process data (TPDOs)."""

    def _reset_values(self, comm_only):
        """Every object back to its stored or default value (only 0x1000-0x1FFF: ``comm_only``)."""
        for key in self.vars:
            if not comm_only or key[0] < 0x2000:
                self.values[key] = self._default(key)

    # --- object access ----------------------------------------------------------------------------
    def _default(self, key):
        var = self.vars[key]
        if key in self.stored:
            return self.stored[key]
        if getattr(var, "relative", False) and var.default_raw is not None:
            return _relative(var.default_raw, self.node_id if 1 <= self.node_id <= 127 else 0)
        if key == (0x1018, 4):
            return self.serial
        if var.default is None:
            return "" if var.data_type == 0x9 else 0
        return var.default

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
        if index == 0x6060 and value not in self.modes:
            return ABORT_VALUE
        if index == 0x6098 and value not in HOMING_METHODS:
            return ABORT_VALUE
        if index == 0x605A and not 0 <= value <= 8:
            return ABORT_VALUE
        if index == 0x605E and not 0 <= value <= 2:
            return ABORT_VALUE
        return 0

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
        elif index == 0x607A and self.mode == MODE_CSP:
            self._csp_target(value)
        elif index == 0x1003:
            for i in range(1, 9):
                self.values[(0x1003, i)] = 0
        elif index == 0x1010:
            self._save(sub)
        elif index == 0x1011:
            self._restore(sub)
        elif index == 0x2001:
            self.actual_offset = value - self.motion.pos

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

    def _lookup(self, index, sub):
        var = self.vars.get((index, sub))
        if var is not None:
            return var, 0
        return None, (ABORT_NO_SUBINDEX if index in self.od else ABORT_NO_OBJECT)

    def _encode(self, var, value):
        if var.data_type == 0x9:
            return value.encode("ascii") if isinstance(value, str) else bytes(value)
        return var.STRUCT_TYPES[var.data_type].pack(value)

    def upload(self, index, sub):
        """An SDO upload of object ``index``:``sub`` as bytes: (data, 0), or (None, the abort code)."""
        var, code = self._lookup(index, sub)
        if var is None:
            return None, code
        if not var.readable:
            return None, ABORT_WRITE_ONLY
        self._refresh()
        return self._encode(var, self.values[(index, sub)]), 0

    def download(self, index, sub, data):
        """An SDO download of ``data`` (bytes) to object ``index``:``sub``: 0 or the abort code.
        The value is checked and acts as a written one does."""
        var, code = self._lookup(index, sub)
        if var is None:
            return code
        if not var.writable:
            return ABORT_READ_ONLY
        if var.data_type == 0x9:
            value = bytes(data).decode("ascii", errors="replace")
        else:
            st = var.STRUCT_TYPES[var.data_type]
            if len(data) != st.size:
                return ABORT_LENGTH
            (value,) = st.unpack(bytes(data))
        code = self._store(index, sub, value)
        if not code:
            self._after_change()
        return code

    def identity(self):
        return [self.values[(0x1018, i)] for i in (1, 2, 3, 4)]

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
        self.csp_t = self.csp_since = None
        self.csp_vel = 0.0
        self.internal_limit = False
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
        """Profile velocity and CSV: steer the axis towards 0x60FF (stop first to reverse; CSV at once)."""
        if self.state != OPERATION_ENABLED or self.mode not in (MODE_PV, MODE_CSV):
            return
        m = self.motion
        v = dict(self.values)
        if self.mode == MODE_CSV:
            v[(0x6083, 0)] = v[(0x6084, 0)] = CSV_ACCEL
        target = 0 if self.halted else v[(0x60FF, 0)]
        d = 1 if target > 0 else -1
        if self.digital_inputs() & (IN_LIMIT_PLUS if d > 0 else IN_LIMIT_MINUS):
            target = 0  # held by the limit switch
        if target == 0 or (m.moving and (m.direction != d or m.target is not None)):
            self._stop(v[(0x6084, 0)])
        elif not m.moving or m.stopping or m.vmax != abs(target):
            self._move(None, abs(target), d, v[(0x6083, 0)], v[(0x6084, 0)])

    def _csp_target(self, target):
        """Cyclic synchronous position: the demand is the master's target at once; the shaft follows
        unless it cannot (lost steps: the following error 0x60F4 grows, then the fault of 0x6065/0x6066)."""
        if self.state != OPERATION_ENABLED or self.halted:
            return
        self.update()
        now = self.clock.now
        m = self.motion
        # the drive interpolates on its own cycle: the mean time between targets, not each one's
        # arrival (a master's jitter is not a speed)
        if self.csp_t is not None and now - self.csp_t < CSP_IDLE_US:
            self.csp_dt += 0.05 * (max(1e-4, (now - self.csp_t) / 1e6) - self.csp_dt)
        dt = self.csp_dt
        dp = target - m.pos
        m.pos = float(target)
        moved = dp
        if self.step_out_pps is not None and abs(dp) > self.step_out_pps * dt:
            moved = math.copysign(self.step_out_pps * dt, dp)
            self.actual_offset -= dp - moved
        self.mech += moved
        self.csp_vel = dp / dt
        if dp and self.csp_since is None:
            self.csp_since = now
        elif not dp:
            self.csp_since = None
        self.csp_t = self.t_motion = now
        bits = self.digital_inputs()
        if dp and bits & (IN_LIMIT_PLUS if dp > 0 else IN_LIMIT_MINUS):
            self.internal_limit = True
        if self.csp_since is not None and self.overcurrent_ms is not None and \
                now - self.csp_since >= self.overcurrent_ms * 1000.0:
            self.fault(EMCY_OVERCURRENT, ERR_CURRENT)
        self._check_following_error()

    def connection_lost(self, emcy_code):
        """The bus lost its master (the EtherCAT watchdog, leaving OP): the reaction of 0x6007 (abort
        connection option code: 0 none, 1 fault with EMCY ``emcy_code``, 2 disable voltage, 3 quick stop)."""
        self.update()
        if self.state not in (OPERATION_ENABLED, QUICK_STOP_ACTIVE, SWITCHED_ON, READY):
            return
        option = self.values.get((0x6007, 0), 1)
        if option == 1:
            self.fault(emcy_code, ERR_GENERIC)
        elif option == 2:
            self.cw = 0
            self._controlword(0)  # disable voltage
        elif option == 3 and self.state == OPERATION_ENABLED:
            self._controlword(0x0002)  # quick stop
        self._after_change()

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
        self._on_change()
        if self._needs_tick() and not self._tick_due:
            self._tick_due = True
            self.clock.at(self.t_motion + STEP_MS * 1000.0, self._tick)

    def _tick(self):
        self._tick_due = False
        self.update()
        self._after_change()

    # --- what the drive shows -------------------------------------------------------------
    def velocity_actual(self):
        if self.mode == MODE_CSP and self.state == OPERATION_ENABLED:
            fresh = self.csp_t is not None and self.clock.now - self.csp_t < CSP_IDLE_US
            v = self.csp_vel if fresh else 0.0
            if self.step_out_pps is not None and abs(v) > self.step_out_pps:
                v = math.copysign(self.step_out_pps, v)
            return int(round(v))
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
        elif self.mode in CYCLIC_MODES:
            if not self.halted:
                sw |= SW_BIT12  # the target is followed (0: ignored)
            window = self.values[(0x6065, 0)]
            if self.mode == MODE_CSP and window != 0xFFFFFFFF and abs(self.actual_offset) > window:
                sw |= SW_BIT13
            if self.internal_limit:
                sw |= SW_INTERNAL_LIMIT
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
        name, v = self.FAULTS.parse(name, value)
        self.update()
        self._apply_fault(name, v)

    def _apply_fault(self, name, v):
        """Switch fault ``name`` on with its checked value ``v`` (a face adds its own names)."""
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
        elif name == "param":
            key, value = v
            try:
                check_param(self.vars, key, value)
            except ValueError as exc:
                raise ValueError("param: %s" % exc) from None
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
        saved, self._param_saved = self._param_saved, {}
        self.param_faults = {}
        for key, (value, stored) in saved.items():
            self._force(key, value, stored)

    def _emcy(self, code, reg):
        """Record EMCY ``code`` (0x1001, the error history 0x1003) and send it (``_emergency``)."""
        self.err_reg = reg
        if code:
            for i in range(8, 1, -1):
                self.values[(0x1003, i)] = self.values[(0x1003, i - 1)]
            self.values[(0x1003, 1)] = code
            self.values[(0x1003, 0)] = min(8, self.values[(0x1003, 0)] + 1)
        self._emergency(code, reg)
