"""The plan format of CiA 402 drives, as data: their ``[drive]`` keys, their step kinds and the
reference text of their parameter-set files (``schema``'s vocabulary; ``kind_cia402`` puts them
in the table of kinds)."""

from motorjig.station.schema import I32, PROMPT, REQUIRED, U32, Kind, key

SLCAN_BITRATES = (10000, 20000, 50000, 100000, 125000, 250000, 500000, 750000, 1000000)  # the jig's S0..S8

DRIVE_KEYS = (
    key("node_id", "int", REQUIRED, "the drive's CANopen node id", lo=1, hi=127),
    key("bitrate", "int", 500000, "the CAN bitrate, bit/s: one the jig's SLCAN port can set", choices=SLCAN_BITRATES),
    key("eds", "str", None, "the drive's EDS file, relative to the plan (default: the EDS of the bench's "
        "simulated drive, tools/motorjig/can/motorjig-cia402.eds); every object the plan writes or compares "
        "must be in it, of its type, within its limits"),
)

MOVE_LIMITS = (
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

STEP_KINDS = (
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
    ) + MOVE_LIMITS, ("duration", "duration_ratio", "expected_duration", "position_error",
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
    PROMPT,
)


def paramset_reference():
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
