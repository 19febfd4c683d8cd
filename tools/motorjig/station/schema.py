"""The test-plan format, as data: every table, step kind and key with its type and meaning.

This is the one source of the plan format. ``motorjig.station.plan`` checks plan
files against it, and ``render_reference()`` writes the format's reference in
docs/station.md from it (a test keeps the two equal), so the documentation cannot
drift from what the loader accepts.

A key is ``Key(name, type, default, doc, ...)``; ``default`` is ``REQUIRED`` for a
key that must be given. Types:

* ``str``, ``int``, ``num`` (int or float), ``bool``
* ``regex``: a string that is a valid Python regular expression (checked when the plan loads)
* ``range``: ``[min, max]``, two numbers, min <= max (a limit)
* ``ref``: a relay or jig-input reference, its number or its ``name`` in the wiring
* ``choice``: one of ``choices``
* ``protocols``: 6, 8, or a list of them (the variants a drive may speak)
* ``protocol``: the drive's protocol, ``"plusr"`` or ``"cia402"`` (or, as plans before CiA 402
  drives wrote it, the Plus-R variants ``6``, ``8``, ``[6, 8]``)

A plan is for one kind of drive (``[drive] protocol``): ``DRIVE_KEYS`` are every drive's,
``PROTOCOL_DRIVE_KEYS[protocol]`` that protocol's; the step kinds a protocol has, with their
keys, are ``PROTOCOL_KINDS[protocol]`` (``STEP_KINDS``/``KINDS``: Plus-R's, as before). A key
with ``obj`` set is written to that object of a CiA 402 drive: the plan's EDS must have it, and
the value must fit its data type and limits.

A key with ``sweep=True`` may also be given as a list of values: the step then runs
once per value (``speed = [1000, 20000, 50000]``). Every step may repeat
(``repeat = 3``).
"""

from collections import namedtuple

REQUIRED = object()

Key = namedtuple("Key", "name type default doc choices lo hi sweep obj")
Key.__new__.__defaults__ = ((), None, None, False, None)


def key(name, type_, default, doc, choices=(), lo=None, hi=None, sweep=False, obj=None):
    return Key(name, type_, default, doc, tuple(choices), lo, hi, sweep, obj)


Kind = namedtuple("Kind", "name doc keys measurements")

I32 = (-0x80000000, 0x7FFFFFFF)
SPEED = (1, 2500000)

# --- the plan's tables ---------------------------------------------------------------
PLAN_KEYS = (
    key("name", "str", REQUIRED, "the plan's name (the test name in every record)"),
    key("version", "str", REQUIRED, "the plan's version, e.g. \"1.2\""),
    key("description", "str", "", "what the plan is for"),
    key("stop_on_fail", "bool", True, "end the run at the first failed step"),
    key("on_end", "choice", "stop-servo-off",
        "what a run that fails, errors or is interrupted does to the axis at the end: MoveStop "
        "(EmergencyStop when interrupted) and servo off, or nothing",
        choices=("stop-servo-off", "none")),
    key("reset_jig_counters", "bool", True,
        "reset the jig's bus counters when the run starts, so bus-health covers this run only"),
    key("sampling", "choice", "auto",
        "who samples the axis during moving steps: the jig itself at a fixed period on its own clock "
        "(`jig`: a busy PC cannot spoil a measurement), this PC through the jig (`pc`), or the jig when "
        "its firmware can (`auto`)", choices=("auto", "jig", "pc")),
    key("sample_rate_min", "num", 100.0,
        "samples per second below which a moving step's trace cannot judge the drive: the step ends "
        "ERROR (not FAIL), as it does for a gap of 4 sample periods (at least 20 ms)", lo=0, hi=100000),
)

PROTOCOLS = ("plusr", "cia402")
SLCAN_BITRATES = (10000, 20000, 50000, 100000, 125000, 250000, 500000, 750000, 1000000)  # the jig's S0..S8
U32 = (0, 0xFFFFFFFF)

DRIVE_KEYS = (
    key("protocol", "protocol", "plusr", "the drive's protocol: `\"plusr\"` (Ezi-STEP Plus-R on RS-485) or "
        "`\"cia402\"` (a CANopen CiA 402 drive on the jig's CAN port); the other keys of `[drive]` are that "
        "protocol's (below). `6`, `8` or `[6, 8]` is `\"plusr\"` with those variants (plans written before "
        "CiA 402 drives)", choices=PROTOCOLS),
    key("jig_id", "int", 1, "the jig's own slave id on its PC port (its counters, relays and inputs)", lo=0, hi=15),
)

PROTOCOL_DRIVE_KEYS = {
    "plusr": (
        key("slave", "int", 2, "the drive's slave id", lo=0, hi=15),
        key("variant", "protocols", (6,), "the drive's protocol variant: 6 (Ver6), 8 (Ver8) or [6, 8] (either); a "
            "drive of another variant is refused before anything moves", choices=(6, 8)),
        key("slave_type", "int", 20, "the slave type the drive must report (20 Ezi-STEP Plus-R ST)", lo=0, hi=255),
    ),
    "cia402": (
        key("node_id", "int", REQUIRED, "the drive's CANopen node id", lo=1, hi=127),
        key("bitrate", "int", 500000, "the CAN bitrate, bit/s: one the jig's SLCAN port can set", choices=SLCAN_BITRATES),
        key("eds", "str", None, "the drive's EDS file, relative to the plan (default: the EDS of the bench's "
            "simulated drive, tools/motorjig/can/motorjig-cia402.eds); every object the plan writes or compares "
            "must be in it, of its type, within its limits"),
    ),
}

COMMON_STEP_KEYS = (
    key("kind", "choice", REQUIRED, "the step kind (below)"),
    key("name", "str", None, "the step's name in the records (default: its kind, numbered when a kind comes "
        "again); two steps given the same name are refused"),
    key("repeat", "int", 1, "run the step this many times", lo=1, hi=1000),
)

_MOVE_LIMITS = (
    key("duration_s", "range", None, "limits of the move's duration, seconds"),
    key("duration_tolerance", "num", 0.15,
        "without duration_s: the duration must be within this fraction of the time the trapezoid "
        "profile takes (distance, speed, accel/decel times)", lo=0, hi=10),
    key("position_error_max", "int", 0, "largest allowed |target - actual position| after the move, pulses",
        lo=0),
    key("following_error_max", "int", 0,
        "largest allowed |command - actual position| sampled during the move, pulses", lo=0),
    key("timeout_s", "num", 30.0, "give up waiting for the axis after this many seconds", lo=0.1, hi=3600),
)

STEP_KINDS = (
    Kind("identify", "GetSlaveInfo and GetMotorInfo: the slave type and the name/version text.", (
        key("slave_type", "int", None, "expected slave type (default: the plan's drive.slave_type)", lo=0, hi=255),
        key("name_pattern", "regex", ".*", "regular expression the GetSlaveInfo text must match (re.search)"),
        key("motor_pattern", "regex", None, "regular expression for the GetMotorInfo text (not checked if absent)"),
    ), ("slave_type", "slave_name", "name_ok", "motor_name", "motor_ok")),
    Kind("parameters", "RAM and ROM parameters against a parameter-set file (the format of `jigctl param "
         "dump`): verify them, or write them, save to ROM and verify.", (
        key("file", "str", REQUIRED, "the parameter-set file, relative to the plan file"),
        key("mode", "choice", "verify", "verify: compare; apply: write RAM, SaveAllParameters, compare",
            choices=("verify", "apply")),
        key("memory", "choice", "both", "which values are compared", choices=("ram", "rom", "both")),
    ), ("ram_<name>", "rom_<name>")),
    Kind("servo", "Switch the drive on or off; no alarm afterwards.", (
        key("on", "bool", True, "servo on (true) or off (false)"),
    ), ("servo_on", "alarm")),
    Kind("alarm-reset", "Clear the drive's alarm (Ezi-STEP: assert then release); no alarm afterwards.", (),
         ("alarm",)),
    Kind("move", "A move with the trapezoid profile, sampled through the jig; the trace (time, command, "
         "actual, velocity) goes into the record.", (
        key("mode", "choice", "inc", "abs: to a position; inc: by a distance", choices=("abs", "inc")),
        key("position", "int", None, "abs: the target position, pulses", lo=I32[0], hi=I32[1], sweep=True),
        key("distance", "int", None, "inc: the distance, pulses (may be negative)", lo=I32[0], hi=I32[1],
            sweep=True),
        key("speed", "int", REQUIRED, "speed, pps", lo=SPEED[0], hi=SPEED[1], sweep=True),
        key("accel_ms", "int", None, "acceleration time, ms (default: the drive's parameter 3); sent with the "
            "Ex move frame", lo=1, hi=9999, sweep=True),
        key("decel_ms", "int", None, "deceleration time, ms (default: the drive's parameter 4)", lo=1, hi=9999,
            sweep=True),
    ) + _MOVE_LIMITS, ("duration", "duration_ratio", "expected_duration", "position_error", "following_error",
                       "in_position", "alarm", "samples", "sample_rate")),
    Kind("home", "Origin search per the drive's parameters 17-24: done within limits, origin flag set.", (
        key("duration_s", "range", (0.0, 30.0), "limits of the search's duration, seconds"),
        key("timeout_s", "num", 60.0, "give up (MoveStop) after this many seconds", lo=0.1, hi=3600),
    ), ("duration", "origin_ok", "alarm")),
    Kind("io", "Through the wiring: each jig relay on and off, read the drive's inputs; each wired drive "
         "output on and off, read the jig's inputs.", (
        key("relays", "list", None, "the relays to check (numbers or wiring names; default: every wired relay)"),
        key("senses", "list", None, "the jig inputs to check (default: every wired one)"),
        key("settle_ms", "int", 20, "wait after switching before reading, ms", lo=0, hi=10000),
    ), ("relay_<n>_on", "relay_<n>_off", "sense_<n>_on", "sense_<n>_off")),
    Kind("limit-sensor", "Start a move towards a limit and assert the limit input through the wiring: the "
         "drive must stop and flag the limit.", (
        key("relay", "ref", REQUIRED, "the relay wired to the drive's limit input (number or wiring name)"),
        key("speed", "int", 5000, "speed of the move, pps", lo=SPEED[0], hi=SPEED[1], sweep=True),
        key("after_ms", "int", 100, "assert the relay this long after the move started, ms", lo=0, hi=60000),
        key("stop_time_s", "range", (0.0, 0.5), "limits of the time from the relay to standstill, seconds (see "
            "*Choosing the limits*)"),
        key("timeout_s", "num", 10.0, "give up after this many seconds", lo=0.1, hi=3600),
    ), ("stopped", "limit_flag", "stop_time")),
    Kind("stop-response", "Start a move, send MoveStop or EmergencyStop, measure the time to standstill and "
         "the overshoot (pulses travelled after the stop).", (
        key("stop", "choice", "move-stop", "the stop sent", choices=("move-stop", "emergency-stop")),
        key("speed", "int", 20000, "speed of the move, pps", lo=SPEED[0], hi=SPEED[1], sweep=True),
        key("after_ms", "int", 200, "send the stop this long after the move started, ms", lo=0, hi=60000),
        key("stop_time_s", "range", (0.0, 0.5), "limits of the time to standstill, seconds (see *Choosing the "
            "limits*)"),
        key("overshoot_max", "int", 100000, "largest allowed travel after the stop, pulses; a MoveStop's "
            "deceleration ramp counts: v * td / 2, 1 000 at 20 000 pps and 100 ms (see *Choosing the limits*)", lo=0),
        key("recover", "bool", True, "after an emergency stop: servo off and on again, so later steps can move"),
    ), ("stopped", "stop_time", "overshoot")),
    Kind("bus-health", "The jig's own counters over the run, the drive's response times on the jig's clock and "
         "the round trips seen by the station.", (
        key("crc_errors_max", "int", 0, "CRC errors on either bus", lo=0),
        key("stuffing_errors_max", "int", 0, "stuffing errors on either bus", lo=0),
        key("timeouts_max", "int", 0, "forwarded requests that got no reply", lo=0),
        key("overflows_max", "int", 0, "receive-buffer overflows", lo=0),
        key("turnaround_max_us", "int", 5000, "the jig's longest handling time (last byte in to its answer "
            "starting), us (see *Choosing the limits*)", lo=0),
        key("roundtrip_max_ms", "num", None, "the longest request/reply round trip through the jig as this PC "
            "saw it, ms: reported always, judged only when the plan sets this (a busy PC, not the drive, makes "
            "it long; see *Choosing the limits*)", lo=0),
        key("drive_response_max_us", "int", None, "the drive's longest response on the jig's clock: from a "
            "GetAllStatus request's last stop bit on the driver bus to its reply's last byte, the drive's "
            "turnaround plus the reply's wire time (3.6 ms at 115 200 baud), us; the step asks 8 times. Reported "
            "when the jig dates the requests it forwards, judged when set", lo=0),
    ), ("crc_errors", "stuffing_errors", "timeouts", "overflows", "turnaround_max", "roundtrip_max",
        "roundtrip_avg", "roundtrip_min", "drive_response_max")),
    Kind("prompt", "An operator instruction, confirmed on the console or in the Desk (`--yes` confirms "
         "unattended).", (
        key("message", "str", REQUIRED, "what the operator must do"),
    ), ("confirmed",)),
)

KINDS = {k.name: k for k in STEP_KINDS}

# --- the step kinds of CiA 402 drives ------------------------------------------------------
_CIA402_MOVE_LIMITS = (
    key("duration_s", "range", None, "limits of the move's duration, seconds"),
    key("duration_tolerance", "num", 0.15,
        "without duration_s: the duration must be within this fraction of the time the trapezoid "
        "profile takes (distance, speed, acceleration, deceleration)", lo=0, hi=10),
    key("position_error_max", "int", 0, "largest allowed |target - position actual 0x6064| after the move, counts",
        lo=0),
    key("following_error_max", "int", 0,
        "largest allowed |following error actual 0x60F4| traced during the move, counts", lo=0),
    key("timeout_s", "num", 30.0, "give up waiting for the axis after this many seconds", lo=0.1, hi=3600),
)

CIA402_KINDS = (
    Kind("identify", "SDO uploads of the device type 0x1000, the names and versions 0x1008-0x100A and the "
         "identity 0x1018, against the values and patterns given.", (
        key("device_type", "int", 0x00020192, "expected device type 0x1000 (its bits in `device_type_mask`)",
            lo=U32[0], hi=U32[1]),
        key("device_type_mask", "int", 0x0000FFFF, "the bits of 0x1000 compared; the default compares the low 16 "
            "bits, the profile: 402", lo=U32[0], hi=U32[1]),
        key("name_pattern", "regex", ".*", "regular expression the device name 0x1008 must match (re.search)"),
        key("vendor_id", "int", None, "expected vendor id 0x1018:1 (not checked if absent)", lo=U32[0], hi=U32[1]),
        key("product_code", "int", None, "expected product code 0x1018:2 (not checked if absent)",
            lo=U32[0], hi=U32[1]),
        key("revision", "int", None, "expected revision number 0x1018:3 (not checked if absent)",
            lo=U32[0], hi=U32[1]),
        key("serial_pattern", "regex", None, "regular expression for the serial number 0x1018:4 as 8 hex digits, "
            "e.g. \"^5349\" (not checked if absent)"),
    ), ("device_type", "device_name", "hardware_version", "software_version", "name_ok", "vendor_id",
        "product_code", "revision", "serial", "serial_ok")),
    Kind("parameters", "Object-dictionary entries against a CiA 402 parameter-set file (the format of `jigctl can "
         "sdo dump`): verify them by SDO upload, or write them, store them (0x1010:01 \"save\") and verify; "
         "every object is checked against the EDS when the plan loads (exists, type, limits, writable for "
         "apply).", (
        key("file", "str", REQUIRED, "the parameter-set file, relative to the plan file"),
        key("mode", "choice", "verify", "verify: compare; apply: write each, store (0x1010:01), compare",
            choices=("verify", "apply")),
    ), ("x<index>_<sub>",)),
    Kind("servo", "The CiA 402 power state machine (controlword 0x6040, statusword 0x6041) to OPERATION "
         "ENABLED or back to SWITCH ON DISABLED, each transition timed; no fault afterwards.", (
        key("on", "bool", True, "operation enabled (true) or switch on disabled (false)"),
    ), ("state", "transition_time_max", "fault")),
    Kind("alarm-reset", "Fault reset (controlword bit 7 rising): the drive leaves FAULT; no fault afterwards.", (),
         ("fault", "state")),
    Kind("move", "Profile position mode (0x6060 = 1): target 0x607A, profile velocity, acceleration and "
         "deceleration 0x6081/0x6083/0x6084, the new-set-point handshake; traced by TPDOs (statusword, "
         "position actual 0x6064, velocity actual 0x606C, following error actual 0x60F4) dated by the jig's "
         "clock; the trace goes into the record.", (
        key("mode", "choice", "inc", "abs: to a position; inc: by a distance", choices=("abs", "inc")),
        key("position", "int", None, "abs: the target position 0x607A, counts", lo=I32[0], hi=I32[1], sweep=True,
            obj=0x607A),
        key("distance", "int", None, "inc: the distance, counts (may be negative)", lo=I32[0], hi=I32[1],
            sweep=True),
        key("speed", "int", REQUIRED, "profile velocity 0x6081, counts/s", lo=1, hi=U32[1], sweep=True,
            obj=0x6081),
        key("accel", "int", None, "profile acceleration 0x6083, counts/s² (default: the drive's)", lo=1, hi=U32[1],
            sweep=True, obj=0x6083),
        key("decel", "int", None, "profile deceleration 0x6084, counts/s² (default: the drive's)", lo=1, hi=U32[1],
            sweep=True, obj=0x6084),
    ) + _CIA402_MOVE_LIMITS, ("duration", "duration_ratio", "expected_duration", "position_error",
                              "following_error", "target_reached", "fault", "samples", "sample_rate")),
    Kind("home", "Homing mode (0x6060 = 6): method 0x6098, speeds 0x6099, acceleration 0x609A; homing "
         "attained (statusword bits 12 and 10) within the limits.", (
        key("method", "int", None, "homing method 0x6098 (default: the drive's)", lo=-128, hi=127, obj=0x6098),
        key("speed_switch", "int", None, "speed during search for switch 0x6099:1, counts/s (default: the drive's)",
            lo=1, hi=U32[1], obj=(0x6099, 1)),
        key("speed_zero", "int", None, "speed during search for zero 0x6099:2, counts/s (default: the drive's)",
            lo=1, hi=U32[1], obj=(0x6099, 2)),
        key("accel", "int", None, "homing acceleration 0x609A, counts/s² (default: the drive's)", lo=1, hi=U32[1],
            obj=0x609A),
        key("duration_s", "range", (0.0, 30.0), "limits of the homing's duration, seconds"),
        key("timeout_s", "num", 60.0, "give up (halt) after this many seconds", lo=0.1, hi=3600),
    ), ("duration", "homing_attained", "fault")),
    Kind("io", "Through the wiring: each jig relay on and off, read the drive's digital inputs 0x60FD; each "
         "wired drive output (0x60FE:1) on and off, read the jig's inputs.", (
        key("relays", "list", None, "the relays to check (numbers or wiring names; default: every wired relay)"),
        key("senses", "list", None, "the jig inputs to check (default: every wired one)"),
        key("settle_ms", "int", 20, "wait after switching before reading, ms", lo=0, hi=10000),
    ), ("relay_<n>_on", "relay_<n>_off", "sense_<n>_on", "sense_<n>_off")),
    Kind("limit-sensor", "Start a move towards a limit and assert the limit input through the wiring: the "
         "drive must stop and show the limit in 0x60FD (bit 0 negative, bit 1 positive limit switch).", (
        key("relay", "ref", REQUIRED, "the relay wired to the drive's limit input (number or wiring name)"),
        key("speed", "int", 5000, "speed of the move, counts/s", lo=1, hi=U32[1], sweep=True, obj=0x6081),
        key("after_ms", "int", 100, "assert the relay this long after the move started, ms", lo=0, hi=60000),
        key("stop_time_s", "range", (0.0, 0.5), "limits of the time from the relay to standstill, seconds"),
        key("timeout_s", "num", 10.0, "give up after this many seconds", lo=0.1, hi=3600),
    ), ("stopped", "limit_flag", "stop_time")),
    Kind("stop-response", "Start a move, then quick stop (controlword, the drive's reaction per 0x605A) or halt "
         "(controlword bit 8): the time to standstill and the overshoot (counts travelled after the stop), "
         "dated by the jig's clock.", (
        key("stop", "choice", "quick-stop", "the stop sent", choices=("quick-stop", "halt")),
        key("speed", "int", 20000, "speed of the move, counts/s", lo=1, hi=U32[1], sweep=True, obj=0x6081),
        key("after_ms", "int", 200, "stop this long after the move started, ms", lo=0, hi=60000),
        key("stop_time_s", "range", (0.0, 0.5), "limits of the time to standstill, seconds"),
        key("overshoot_max", "int", 100000, "largest allowed travel after the stop, counts; a ramp counts: "
            "v² / 2d, 200 at 20 000 counts/s and 1 000 000 counts/s²", lo=0),
        key("recover", "bool", True, "after a quick stop: back to OPERATION ENABLED, so later steps can move"),
    ), ("stopped", "stop_time", "overshoot", "state")),
    Kind("bus-health", "The jig's CAN port counters over the run (error frames, TEC/REC, bus-off, lost frames), "
         "the drive's heartbeat regularity (0x1017) and every EMCY received, its CiA 301 code named.", (
        key("error_frames_max", "int", 0, "CAN error frames the jig counted", lo=0),
        key("heartbeat_jitter_max_ms", "num", None, "largest allowed deviation of a heartbeat interval from "
            "0x1017, ms: reported always, judged when set", lo=0),
        key("emcy_max", "int", 0, "EMCY messages the drive sent over the run", lo=0),
    ), ("error_frames", "tec_max", "rec_max", "bus_off", "lost_frames", "heartbeat_jitter", "emcy")),
    Kind("lss", "A drive fresh from its box: LSS fast scan finds it at the factory node id (or none) by its "
         "identity, gives it the plan's node id and bitrate, stores them (CiA 305) and the run goes on.", (
        key("factory_node_id", "int", 255, "the node id the drive comes with (255: unconfigured)", lo=1, hi=255),
    ), ("found", "vendor_id", "product_code", "serial", "node_id")),
    KINDS["prompt"],
)

PROTOCOL_KINDS = {"plusr": STEP_KINDS, "cia402": CIA402_KINDS}


def kinds(protocol="plusr"):
    """The step kinds of a drive kind (the table of kinds, ``station.kinds``), name -> Kind."""
    from motorjig.station import kinds as K

    return {k.name: k for k in K.get(protocol).step_kinds}


def kind_keys(kind, protocol="plusr"):
    """Every key a step of this kind accepts on this protocol's drives, name -> Key."""
    return {k.name: k for k in COMMON_STEP_KEYS + kinds(protocol)[kind].keys}


# --- the reference in docs/station.md ---------------------------------------------------
def _default_text(k):
    if k.default is REQUIRED:
        return "**required**"
    if k.default is None:
        return "-"
    if isinstance(k.default, bool):
        return "`%s`" % str(k.default).lower()
    if isinstance(k.default, tuple):
        return "`[%s]`" % ", ".join(str(v) for v in k.default)
    if isinstance(k.default, str):
        return '`"%s"`' % k.default
    if isinstance(k.default, int) and k.hi == U32[1] and k.default > 0xFF:
        return "`0x%08X`" % k.default  # a 32-bit identity or mask reads best in hex
    return "`%s`" % k.default


def _type_text(k):
    t = k.type
    if k.type == "protocols":
        t = "`6` / `8` / `[6, 8]`"
    elif k.type == "protocol":
        t = " / ".join('`"%s"`' % c for c in k.choices)
    elif k.choices and t in ("choice", "int"):
        t = " / ".join('`"%s"`' % c if isinstance(c, str) else "`%s`" % c for c in k.choices)
    elif k.lo is not None or k.hi is not None:
        t = "%s %s..%s" % (t, "" if k.lo is None else k.lo, "" if k.hi is None else k.hi)
    if k.sweep:
        t += " (or a list: sweep)"
    return t


def _table(keys):
    rows = ["| key | type | default | meaning |", "| --- | --- | --- | --- |"]
    for k in keys:
        rows.append("| `%s` | %s | %s | %s |" % (k.name, _type_text(k), _default_text(k), k.doc))
    return rows


def _wiring_tables():
    """The [wiring] tables from motorjig.wiring.WIRING_SCHEMA, the one source its parser checks."""
    from motorjig.wiring import WIRING_SCHEMA

    out = []
    for table, fields in WIRING_SCHEMA.items():
        header = "[[%s]]" % table if table != "wiring" else "[wiring]"
        out += ["", "#### `%s`" % header, "", "| key | type | required | meaning |", "| --- | --- | --- | --- |"]
        for f in fields:
            kind = "array of tables `[[wiring.%s]]`" % f.key if f.kind == "tables" else f.kind
            if f.lo is not None:
                kind += " %s..%s" % (f.lo, f.hi)
            out.append("| `%s` | %s | %s | %s |" % (f.key, kind, "yes" if f.required else "no", f.meaning))
    return out


def render_reference():
    """The plan format's reference as markdown (docs/station.md between its markers)."""
    out = ["### `[plan]`", ""] + _table(PLAN_KEYS)
    out += ["", "### `[drive]`", ""] + _table(DRIVE_KEYS)
    for protocol in PROTOCOLS:
        out += ["", "#### `protocol = \"%s\"`" % protocol, ""] + _table(PROTOCOL_DRIVE_KEYS[protocol])
    out += ["", "### `[wiring]`: the fixture (also read by `python -m motorjig.sim --wiring`)"] + _wiring_tables()
    out += ["", "### `[[steps]]`: keys of every step", ""] + _table(COMMON_STEP_KEYS)
    out += ["", "Step kinds by protocol (a kind the plan's protocol lacks is refused): " + "; ".join(
        "`%s`: %s" % (p, ", ".join(k.name for k in PROTOCOL_KINDS[p])) for p in PROTOCOLS) + "."]
    out += ["", "### Step kinds of Plus-R drives (`protocol = \"plusr\"`)"]
    out += _kinds_text(STEP_KINDS, "")
    out += ["", "### Step kinds of CiA 402 drives (`protocol = \"cia402\"`)", "",
            "Positions in counts, speeds in counts/s, accelerations in counts/s², as the drive's objects are. "
            "An EMCY with an error code during any step fails that step: every step but `bus-health` (which "
            "counts the run's) also has the measurement `emcy`, `\"none\"` or the codes received, named."]
    out += _kinds_text([k for k in CIA402_KINDS if k is not KINDS["prompt"]], " (cia402)")
    out += ["", "`prompt` as for Plus-R drives."]
    out += _paramset402_text()
    return "\n".join(out) + "\n"


def _paramset402_text():
    """The CiA 402 parameter-set format (motorjig.can.paramset402: its keys and rules)."""
    from motorjig.can import paramset402 as PS

    out = ["", "### CiA 402 parameter-set files (`jigctl can sdo dump` / `load`, the `parameters` step)", "",
           "```toml", "[drive]                     # optional: the drive the set is for (sdo load refuses another)"]
    example = {"device_type": 0x00020192, "vendor_id": 0x4D4A4947, "product_code": 0x402}  # the bench's drive
    for k, (index, sub) in PS.DRIVE_KEYS.items():
        out.append("%-27s # 0x%04X%s" % ("%s = 0x%08X" % (k, example.get(k, 0)), index, ":%d" % sub if sub else ""))
    out += ["", "[objects]", '"0x6065" = 1000             # INDEX: a single value (sub-index 0)',
            '"0x6099:01" = 5000          # INDEX:SUB, two digits are hex (as jigctl shows them)',
            '"Profile velocity" = 10000  # or the EDS\'s names', "```", "",
            "Every entry is checked against the plan's EDS when the plan loads: the object exists (a sub-index the EDS "
            "lists), it is one value, of its data type (integers for integer types, `true`/`false`, numbers, text, "
            "hex bytes as a string), within the type and the EDS's LowLimit/HighLimit; readable for `verify`, "
            "writable for `apply` and `sdo load`. `sdo dump` without `--objects` takes every object the EDS lets one "
            "read and write at 0x1017 and from 0x2000 on, except the orders (%s)." % ", ".join(
                "0x%04X%s" % (i, ":%d" % s if s else "") for i, s in sorted(PS.COMMANDS))]
    return out


def _kinds_text(kind_list, suffix):
    out = []
    for k in kind_list:
        out += ["", "#### `kind = \"%s\"`%s" % (k.name, suffix), "", k.doc, ""]
        if k.keys:
            out += _table(k.keys)
        else:
            out.append("No keys of its own.")
        out += ["", "Measurements: " + ", ".join("`%s`" % m for m in k.measurements) + "."]
    return out
