"""Names for the numbers on the wire: frame types, status codes, flag and I/O bits,
alarms, slave types and the Ezi-STEP Plus-R parameter table.

Frame-type and status *codes* come from ``jig.frame`` (the firmware's own module);
this module only adds the human side. The jig's own parameter table and counter
layout are NOT repeated here: ``jig_params()`` and ``jig_frame_names()`` read them
from the firmware modules.

Sources: docs/plusr-protocol.md of the shared design notes (sections 5-7).
"""

from jig import frame as F

# Constants in jig.frame that are not frame types.
_NOT_FRAME_TYPES = ("STUFF", "HEADER2", "TAIL2", "BROADCAST_ID", "MAX_SLAVE_ID", "MAX_DATA",
                    "MAX_BODY", "MAX_WIRE")


def _camel(const_name):
    words = const_name.split("_")
    out = []
    for w in words:
        if w in ("IO", "ROM", "PT"):
            out.append(w)
        else:
            out.append(w.capitalize())
    return "".join(out)


def _frame_types():
    table = {}
    for name in dir(F):
        if not name.isupper() or name.startswith("STATUS_") or name in _NOT_FRAME_TYPES:
            continue
        value = getattr(F, name)
        if isinstance(value, int) and 0 <= value <= 0xFF:
            table[value] = _camel(name)
    return table


#: frame type code -> CamelCase name, e.g. 0x40 -> "GetAxisStatus"
FRAME_NAMES = _frame_types()


def _jig_frames():
    """Frame types the jig adds (0xF0..0xF9), from the firmware's jig.diag."""
    from jig import diag as D

    return {getattr(D, n): _camel(n) for n in ("READ_COUNTERS", "RESET_COUNTERS", "START_BUS_SCAN",
                                               "GET_BUS_SCAN_RESULT", "READ_CRASH_LOG", "START_TRACE",
                                               "STOP_TRACE", "READ_TRACE", "GET_TRACE_STATUS",
                                               "READ_TRANSACTION_TIMES")}


FRAME_NAMES.update(_jig_frames())


def frame_name(ftype):
    return FRAME_NAMES.get(ftype, "Frame0x%02X" % ftype)


# --- Communication status (§4) -----------------------------------------------
STATUS_NAMES = {}
for _n in dir(F):
    if _n.startswith("STATUS_"):
        STATUS_NAMES[getattr(F, _n)] = _n[7:].lower()
del _n


def status_name(code):
    return STATUS_NAMES.get(code, "status_0x%02X" % code)


# --- Axis status flags (§7.3, Ezi-STEP column) ----------------------------------
#: (bit, name, meaning)
AXIS_FLAGS = (
    (0, "error_all", "any error"),
    (1, "hw_limit_plus", "hardware limit +"),
    (2, "hw_limit_minus", "hardware limit -"),
    (3, "sw_limit_plus", "software limit +"),
    (4, "sw_limit_minus", "software limit -"),
    (7, "step_alarm", "step alarm (servo: position overflow)"),
    (8, "over_current", "over-current"),
    (9, "over_speed", "over-speed"),
    (10, "step_out", "step-out (servo: position tracking error)"),
    (11, "overload", "overload (servo)"),
    (12, "over_temperature", "over-temperature"),
    (13, "back_emf", "back-EMF / regeneration"),
    (14, "motor_power", "motor power error"),
    (15, "low_power", "low power (servo: in-position error)"),
    (16, "emergency_stop", "emergency stop active"),
    (17, "slow_stop", "slow (decelerating) stop active"),
    (18, "origin_returning", "origin return in progress"),
    (19, "inposition", "in position (servo)"),
    (20, "servo_on", "servo on (servo)"),
    (21, "alarm_reset", "alarm reset active"),
    (22, "pt_stopped", "position table stopped"),
    (23, "origin_sensor", "origin sensor"),
    (24, "z_pulse", "Z pulse"),
    (25, "origin_ok", "origin return OK"),
    (26, "motion_dir", "motion direction +"),
    (27, "motioning", "axis moving"),
    (28, "motion_pause", "motion paused"),
    (29, "accelerating", "accelerating"),
    (30, "decelerating", "decelerating"),
    (31, "constant_speed", "constant speed"),
)
AXIS_FLAG_BITS = {name: bit for bit, name, _ in AXIS_FLAGS}
#: flags that mean something is wrong (shown highlighted by the CLI)
AXIS_ERROR_FLAGS = ("error_all", "hw_limit_plus", "hw_limit_minus", "sw_limit_plus", "sw_limit_minus",
                    "step_alarm", "over_current", "over_speed", "step_out", "overload",
                    "over_temperature", "back_emf", "motor_power", "low_power", "emergency_stop")

# --- I/O bits (§7.1, §7.2; Ezi-STEP) -------------------------------------------
OUTPUT_BITS = (
    (0, "compare_out"), (2, "alarm"), (3, "run_stop"), (4, "acc_dec"), (5, "pt_ack"),
    (6, "pt_end"), (7, "alarm_blink"), (8, "origin_search_ok"), (11, "brake"),
    (12, "pt_out0"), (13, "pt_out1"), (14, "pt_out2"),
) + tuple((15 + k, "user_out%d" % k) for k in range(9))

INPUT_BITS = (
    (0, "limit_plus"), (1, "limit_minus"), (2, "origin"), (3, "clear_position"),
) + tuple((4 + k, "pt_a%d" % k) for k in range(8)) + (
    (12, "pt_start"), (13, "stop"), (14, "jog_plus"), (15, "jog_minus"), (16, "alarm_reset"),
    (18, "pause"), (19, "origin_search"), (20, "teaching"), (21, "estop"),
    (22, "jpt_in0"), (23, "jpt_in1"), (24, "jpt_in2"), (25, "jpt_start"),
) + tuple((26 + k, "user_in%d" % k) for k in range(6))


def bit_names(value, table):
    """Names of the set bits of value per a (bit, name, ...) table; unknown bits as 'bitN'."""
    known = {row[0]: row[1] for row in table}
    return [known.get(b, "bit%d" % b) for b in range(32) if value >> b & 1]


def bit_value(names, table):
    """Inverse of bit_names: a mask from names (or 'bitN', or numbers)."""
    known = {row[1]: row[0] for row in table}
    mask = 0
    for name in names:
        if name in known:
            mask |= 1 << known[name]
        elif name.startswith("bit") and name[3:].isdigit() and int(name[3:]) < 32:
            mask |= 1 << int(name[3:])
        else:
            raise KeyError(name)
    return mask


# --- Alarm types (§7.4) ----------------------------------------------------------
ALARM_NAMES = {
    0: "none", 1: "over-current", 2: "over-speed", 3: "step-out", 4: "overload",
    5: "over-temperature", 6: "back-EMF", 7: "motor connection", 8: "encoder connection",
    9: "motor power", 10: "in-position", 11: "system halt", 12: "ROM device",
    13: "reserved", 14: "high input voltage", 15: "position overflow", 16: "position changed",
}


# --- Slave type codes (§7.5, Ver6 list) -----------------------------------------
def _add_jig_type():
    """The jig's own GetSlaveInfo type and name, from the firmware's jig.diag."""
    from jig import diag as D

    SLAVE_TYPES[D.SLAVE_TYPE] = D.NAME.decode()


SLAVE_TYPES = {
    1: "Ezi-SERVO Plus-R ST", 3: "Ezi-SERVO Plus-R ADC", 10: "Ezi-MotionLink",
    11: "Ezi-MotionLink2", 20: "Ezi-STEP Plus-R ST", 30: "Ezi-SERVO Plus-R ALL",
    31: "Ezi-SERVO Plus-R ALL 60i", 35: "Ezi-SERVO Plus-R ALL Abs", 40: "Ezi-STEP Plus-R ALL",
    50: "Ezi-SERVO Plus-R mini", 60: "Ezi-STEP Plus-R MINI", 100: "Ezi-SERVO II Plus-R ST",
    102: "S-SERVO Plus-R ST", 105: "Ezi-SERVO Plus-R ALL-28", 108: "Ezi-SERVO Plus-R ALL-28 V2",
    120: "Ezi-SERVO II CC-Link", 130: "Ezi-STEP II Plus-R ST", 150: "Ezi-IO RS-485 IN16",
    155: "Ezi-IO RS-485 I8O8", 160: "Ezi-IO RS-485 OUT16", 180: "Ezi-SERVO II Plus-R TO",
    0xFE: "boot ROM", 0xFF: "boot ROM",
}
_add_jig_type()
#: slave types that are servo drives (alarm reset is 0x2B there, 0x2C on STEP)
SERVO_TYPES = frozenset((1, 3, 30, 31, 35, 50, 100, 102, 105, 108, 120, 180))


def slave_type_name(code):
    return SLAVE_TYPES.get(code, "unknown type %d" % code)


# --- Ezi-STEP Plus-R parameters 0-28 (§6) ----------------------------------------
class Param:
    """One row of a parameter table."""

    __slots__ = ("number", "name", "meaning", "unit", "min", "max", "default", "effect", "validator")
    _FIELDS = ("number", "name", "meaning", "unit", "min", "max", "default", "effect")

    def __init__(self, number, name, meaning, unit, lo, hi, default, effect=""):
        self.number = number
        self.name = name
        self.meaning = meaning
        self.unit = unit
        self.min = lo
        self.max = hi
        self.default = default
        self.effect = effect
        self.validator = None  # optional extra check: validator(number, value) -> bool

    def check(self, value):
        """Raise ValueError when value is outside the known range."""
        if self.min is not None and value < self.min or self.max is not None and value > self.max:
            raise ValueError("parameter %d (%s) must be between %s and %s%s, not %d" % (
                self.number, self.name, self.min, self.max, " " + self.unit if self.unit else "", value))
        if self.validator is not None and not self.validator(self.number, value):
            raise ValueError("%d is not an allowed value of parameter %d (%s)" % (value, self.number, self.name))

    def as_dict(self):
        return {k: getattr(self, k) for k in self._FIELDS}


_SPD = 2500000
_POS = 134217727
_I32 = (-0x80000000, 0x7FFFFFFF)
STEP_PARAMS = tuple(Param(*row) for row in (
    (0, "pulse_per_revolution", "resolution selector (index into a table)", "", _I32[0], _I32[1], None),
    (1, "axis_max_speed", "max speed", "pps", 1, _SPD, 500000),
    (2, "axis_start_speed", "start speed", "pps", 1, _SPD, 1),
    (3, "axis_acc_time", "acceleration time", "ms", 1, 9999, 100),
    (4, "axis_dec_time", "deceleration time", "ms", 1, 9999, 100),
    (5, "speed_override", "speed override", "%", 1, 500, 100),
    (6, "jog_high_speed", "jog speed", "pps", 1, _SPD, 5000),
    (7, "jog_low_speed", "jog start speed", "pps", 1, _SPD, 1),
    (8, "jog_acc_dec_time", "jog acc/dec time", "ms", 1, 9999, 100),
    (9, "alarm_logic", "alarm output logic", "", 0, 1, 0),
    (10, "run_stop_signal_logic", "run/stop input logic", "", 0, 1, 0),
    (11, "reset_logic", "alarm-reset input logic", "", 0, 1, 0),
    (12, "sw_limit_plus_value", "software limit +", "pulse", -_POS, _POS, _POS),
    (13, "sw_limit_minus_value", "software limit -", "pulse", -_POS, _POS, -_POS),
    (14, "soft_limit_stop_method", "stop method at software limit", "", 0, 1, 1),
    (15, "hard_limit_stop_method", "stop method at hardware limit", "", 0, 1, 1),
    (16, "limit_sensor_logic", "limit sensor logic", "", 0, 1, 0),
    (17, "org_speed", "homing speed", "pps", 1, _SPD, 5000),
    (18, "org_search_speed", "homing search (creep) speed", "pps", 1, _SPD, 1000),
    (19, "org_acc_dec_time", "homing acc/dec time", "ms", 1, 9999, 50),
    (20, "org_method", "homing method", "", 0, 4, 0),
    (21, "org_dir", "homing direction", "", 0, 1, 0),
    (22, "org_offset", "offset after homing", "pulse", -_POS, _POS, 0),
    (23, "org_position_set", "position value set at origin", "pulse", -_POS, _POS, 0),
    (24, "org_sensor_logic", "origin sensor logic", "", 0, 1, 0),
    # 25-28: ranges not confirmed for STEP; only the i32 wire range is enforced.
    (25, "stop_current", "standstill current", "%", _I32[0], _I32[1], None),
    (26, "motion_dir", "rotation direction", "", _I32[0], _I32[1], None),
    (27, "limit_sensor_dir", "limit sensor direction", "", _I32[0], _I32[1], None),
    (28, "encoder_multi_value", "encoder multiplication", "", _I32[0], _I32[1], None),
))


def jig_params():
    """The jig's own parameter table as Param rows, read from firmware/jig/params.py.

    ``TABLE`` there is ``(number, name, unit, min, max, default, when)``; ``when``
    becomes ``Param.effect`` and ``params.valid`` the extra check (baud rates).
    """
    from jig import params as P

    out = []
    for number, name, unit, lo, hi, default, when in P.TABLE:
        p = Param(number, name, "", unit, lo, hi, default, when)
        p.validator = P.valid
        out.append(p)
    return tuple(out)


def find_param(table, key):
    """A Param by number or (case-insensitive) name, or None."""
    if isinstance(key, int) or (isinstance(key, str) and key.lstrip("-").isdigit()):
        n = int(key)
        for p in table:
            if p.number == n:
                return p
        return None
    k = str(key).lower().replace("-", "_")
    for p in table:
        if p.name.lower() == k:
            return p
    return None
