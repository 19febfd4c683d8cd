"""The plan format of EtherCAT CiA 402 drives, as data: their ``[drive]`` keys and step kinds (``schema``'s
vocabulary; ``kind_ecat`` puts them in the table of kinds).

The steps are CiA 402's (``schema_cia402``) where they mean the same on EtherCAT; ``move`` and
``stop-response`` run in cyclic synchronous position with the station's own trapezoid, and
``bus-health`` judges the cycle (frames, working counters, the period) instead of a CAN port.
"""

from motorjig.station import schema_cia402 as C
from motorjig.station.schema import PROMPT, REQUIRED, U32, I32, Kind, key

DRIVE_KEYS = (
    key("position", "int", 0, "the slave's position on the line, from 0 (the first slave after the PC)", lo=0,
        hi=65534),
    key("cycle_ms", "num", 1.0, "the process-data cycle, ms: the period of the CSP targets and of the samples",
        lo=0.25, hi=10.0),
    key("esi", "str", None, "the drive's ESI file, relative to the plan (default: the ESI of the bench's simulated "
        "servo, tools/motorjig/ecat/motorjig-servo.xml): the identity the pre-flight expects"),
    key("eds", "str", None, "the drive's object dictionary as an EDS, relative to the plan (default: the bench's "
        "servo's, tools/motorjig/can/motorjig-cia402.eds): every object the plan writes or compares must be in it"),
)

_BY_NAME = {k.name: k for k in C.STEP_KINDS}

MOVE = Kind("move", "Cyclic synchronous position (0x6060 = 8): the station sends a target position 0x607A every "
            "cycle along the trapezoid of the step's speed, acceleration and deceleration (the drive's 0x6083/0x6084 "
            "when not given), as an EtherCAT master does; sampled every cycle from the process data (statusword, "
            "position actual 0x6064, velocity actual 0x606C, following error 0x60F4), dated by the distributed "
            "clock. A cycle the PC sent late or a frame lost makes the step ERROR, not FAIL.", (
    key("mode", "choice", "inc", "abs: to a position; inc: by a distance", choices=("abs", "inc")),
    key("position", "int", None, "abs: the target position, counts", lo=I32[0], hi=I32[1], sweep=True),
    key("distance", "int", None, "inc: the distance, counts (may be negative)", lo=I32[0], hi=I32[1], sweep=True),
    key("speed", "int", REQUIRED, "the trapezoid's speed, counts/s", lo=1, hi=U32[1], sweep=True),
    key("accel", "int", None, "its acceleration, counts/s² (default: the drive's 0x6083)", lo=1, hi=U32[1],
        sweep=True, obj=0x6083),
    key("decel", "int", None, "its deceleration, counts/s² (default: the drive's 0x6084)", lo=1, hi=U32[1],
        sweep=True, obj=0x6084),
) + C.MOVE_LIMITS, _BY_NAME["move"].measurements)

STOP_RESPONSE = _BY_NAME["stop-response"]._replace(
    doc="Start a CSP move, then quick stop (controlword: the drive's own reaction, 0x605A) or halt (the station "
        "ramps its targets down along 0x6084): the time to standstill and the overshoot, dated by the distributed "
        "clock.")

BUS_HEALTH = Kind("bus-health", "The EtherCAT cycle over the run: frames that did not come back, working counters "
                  "short of the expected, cycles the PC sent late, the period's spread (median, p99, max) on the "
                  "master's side, and every emergency the drive sent, its CiA 301 code named.", (
    key("frames_lost_max", "int", 0, "frames that did not come back", lo=0),
    key("wkc_errors_max", "int", 0, "frames whose working counter was not the expected one", lo=0),
    key("late_cycles_max", "int", None, "cycles the PC sent more than 1.5 periods after the one before: reported "
        "always, judged when set (a PC's lateness, not the drive's)", lo=0),
    key("emcy_max", "int", 0, "emergencies the drive sent over the run", lo=0),
), ("frames_lost", "wkc_errors", "late_cycles", "period_p99", "period_max", "emcy"))

STEP_KINDS = (_BY_NAME["identify"], _BY_NAME["parameters"], _BY_NAME["servo"], _BY_NAME["alarm-reset"], MOVE,
              _BY_NAME["home"], STOP_RESPONSE, BUS_HEALTH, PROMPT)
