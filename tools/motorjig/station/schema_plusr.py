"""The plan format of Plus-R drives, as data: their ``[drive]`` keys and their step kinds (``schema``'s
vocabulary; ``kind_plusr`` puts them in the table of kinds)."""

from motorjig.station.schema import I32, PROMPT, REQUIRED, SPEED, Kind, key

DRIVE_KEYS = (
    key("slave", "int", 2, "the drive's slave id", lo=0, hi=15),
    key("variant", "protocols", (6,), "the drive's protocol variant: 6 (Ver6), 8 (Ver8) or [6, 8] (either); a "
        "drive of another variant is refused before anything moves", choices=(6, 8)),
    key("slave_type", "int", 20, "the slave type the drive must report (20 Ezi-STEP Plus-R ST)", lo=0, hi=255),
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
    PROMPT,
)

KINDS = {k.name: k for k in STEP_KINDS}
