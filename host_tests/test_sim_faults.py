"""The simulated drive moves as commanded, homes, fails like a real drive, and is wired
to the jig: every check goes through the real protocol (frames PC -> jig -> drive) on
the virtual bench, except the pure functions (profile_time, the wiring parser).

Times are measured where the drive sees them: ``SimDriver.record_requests`` gives the
instant each request reached the drive, so a move's duration is bracketed by the last
status poll that saw it moving and the first that saw it stopped (polls are ~2 ms apart).
"""

import struct
import subprocess
import sys

import pytest

from bench_fixtures import SUBPROCESS_ENV
from jig import frame as F
from motorjig.master import Master
from motorjig.sim import Bench, SimBench
from motorjig.sim import __main__ as sim_main
from motorjig.sim.driver import (FF_DECEL, FF_ERROR_ALL, FF_HW_MINUS, FF_HW_PLUS, FF_MOTIONING, FF_ORIGIN_OK,
                                 FF_ORIGIN_RETURNING, FF_SERVO_ON, FF_SLOW_STOP, FF_STEP_ALARM, parse_fault,
                                 parse_fault_spec, profile_time)
from motorjig.wiring import WIRING_SCHEMA, Wiring, WiringError, load_wiring, parse_wiring

DRIVE = 2
OTHER = 3
JIG = 1
TOL = 0.003  # s: "within a few ms"

WIRING = {
    "slave": DRIVE,
    "relay": [
        {"relay": 0, "drive_input": 0, "name": "limit+"},
        {"relay": 1, "drive_input": 1, "name": "limit-"},
        {"relay": 2, "drive_input": 13, "name": "stop"},
        {"relay": 3, "drive_input": 26, "name": "user in 0"},
    ],
    "sense": [
        {"jig_input": 0, "drive_output": 15, "name": "user out 0"},
        {"jig_input": 1, "drive_output": 2, "name": "alarm"},
        {"jig_input": 2, "drive_output": 3, "name": "run/stop"},
    ],
}


def make(wiring=None, **kw):
    kw.setdefault("servo_on", True)
    return SimBench(driver_ids=(DRIVE, OTHER), wiring=parse_wiring(wiring) if wiring else None, **kw)


def call(b, slave, ftype, data=b""):
    """Reply data after a status 0."""
    _w, r = b.request(slave, ftype, data)
    assert r is not None and r[0] == 0, "0x%02X -> %r" % (ftype, r)
    return r[1:]


def axis(b, slave=DRIVE):
    return struct.unpack("<I", call(b, slave, F.GET_AXIS_STATUS))[0]


def all_status(b, slave=DRIVE):
    """(inputs, outputs, flags, cmd, act, err, vel) of GetAllStatus."""
    return struct.unpack("<IIIiiii", call(b, slave, F.GET_ALL_STATUS)[:28])


def i32(b, slave, ftype):
    return struct.unpack("<i", call(b, slave, ftype))[0]


def set_param(b, num, value, slave=DRIVE):
    call(b, slave, F.SET_PARAMETER, struct.pack("<Bi", num, value))


def relays(b, on=0, off=0):
    """The jig's SetIOOutput (its relays)."""
    call(b, JIG, F.SET_IO_OUTPUT, struct.pack("<II", on, off))


def jig_inputs(b):
    return struct.unpack("<H", call(b, JIG, F.GET_IO_INPUT)[:2])[0]


def drive_inputs(b, slave=DRIVE):
    return struct.unpack("<I", call(b, slave, F.GET_IO_INPUT))[0]


def ex_option(acc=None, dec=None, ignore_stop=False):
    flags = (1 if ignore_stop else 0) | (2 if acc else 0) | (4 if dec else 0)
    return struct.pack("<IHH", flags, acc or 0, dec or 0) + bytes(24)


def velocity_ex(speed, direction, accdec=None, ignore_stop=False):
    flags = (1 if ignore_stop else 0) | (2 if accdec else 0)
    return struct.pack("<IBIH", speed, direction, flags, accdec or 0) + bytes(26)


def run_s(b, seconds):
    b.run_for(seconds * 1e6)


def start(b, slave, ftype, data=b""):
    """Send a motion command; the instant the drive got it (µs)."""
    d = b.drivers[slave]
    d.record_requests = True
    d.received = []
    call(b, slave, ftype, data)
    return d.received[0][0]


def until_stopped(b, slave, t0, expect_s, limit_s=20.0):
    """Poll the axis status from 10 ms before t0 + expect_s: (last time seen moving,
    first time seen stopped), in s after t0, each the instant the drive read the poll."""
    d = b.drivers[slave]
    b.clock.run_until(max(b.clock.now, t0 + (expect_s - 0.010) * 1e6))
    last_moving = None
    while True:
        n = len(d.received)
        flags = axis(b, slave)
        t = (d.received[n][0] - t0) / 1e6
        if not flags & FF_MOTIONING:
            return last_moving, t
        last_moving = t
        assert t < limit_s, "still moving after %g s" % t


def assert_took(b, slave, t0, expect_s):
    lo, hi = until_stopped(b, slave, t0, expect_s)
    assert lo is not None, "already stopped 10 ms before the profile's %.4f s" % expect_s
    assert lo <= expect_s + TOL and hi >= expect_s - TOL, (lo, hi, expect_s)


# --- profile_time ------------------------------------------------------------------------


def test_profile_time_is_the_trapezoid_and_the_triangle():
    # trapezoid: D/v + (ta + td)/2 (start speed 1 pps: within 0.05 %)
    assert profile_time(10000, 10000, 100, 100) == pytest.approx(1.1, rel=5e-4)
    assert profile_time(-10000, 5000, 300, 50) == pytest.approx(2.0 + 0.175, rel=5e-4)
    # start speed: D/v + (ta + td)(v - vs)^2 / (2 v^2)
    assert profile_time(10000, 5000, 100, 100, start_speed=1000) == pytest.approx(2.0 + 0.2 * 0.64 / 2)
    # triangle: D < v (ta + td)/2 peaks at sqrt(2 D v / (ta + td))
    vp = (2 * 1000 * 50000 / 0.2) ** 0.5
    assert profile_time(1000, 50000, 100, 100) == pytest.approx(vp * 0.2 / 50000, rel=1e-4)  # vs = 1, not 0
    assert profile_time(1000, 50000, 100, 100) < 1000 / 50000 + 0.1
    assert profile_time(0, 5000, 100, 100) == 0.0
    assert profile_time(5000, 5000, 100, 100, start_speed=9000) == pytest.approx(1.0)  # no ramps


@pytest.mark.parametrize("case", ["params", "params-3-4", "ex-both", "ex-accel-only", "ex-abs", "triangle",
                                  "start-speed"])
def test_move_duration_on_the_virtual_clock_matches_profile_time(case):
    b = make()
    p3, p4, data_ex = 100, 100, None
    if case == "params-3-4":
        set_param(b, 3, 300)
        set_param(b, 4, 50)
        p3, p4 = 300, 50
    if case == "start-speed":
        set_param(b, 2, 2000)
    if case == "params":
        ftype, data, expect = F.MOVE_INC_POS, struct.pack("<iI", 10000, 10000), profile_time(10000, 10000, 100, 100)
    elif case == "params-3-4":
        ftype, data, expect = F.MOVE_ABS_POS, struct.pack("<iI", -7000, 8000), profile_time(7000, 8000, p3, p4)
    elif case == "ex-both":
        # the option's times override params 3/4 (still 100/100)
        ftype, data = F.MOVE_INC_POS_EX, struct.pack("<iI", 9000, 12000) + ex_option(20, 400)
        expect = profile_time(9000, 12000, 20, 400)
        assert abs(expect - profile_time(9000, 12000, p3, p4)) > 0.1
    elif case == "ex-accel-only":
        ftype, data = F.MOVE_INC_POS_EX, struct.pack("<iI", 9000, 12000) + ex_option(acc=350)
        expect = profile_time(9000, 12000, 350, p4)
    elif case == "ex-abs":
        ftype, data = F.MOVE_ABS_POS_EX, struct.pack("<iI", -4000, 6000) + ex_option(250, 30)
        expect = profile_time(4000, 6000, 250, 30)
    elif case == "triangle":
        ftype, data = F.MOVE_INC_POS_EX, struct.pack("<iI", 2000, 50000) + ex_option(150, 60)
        expect = profile_time(2000, 50000, 150, 60)
        assert 2000 < 50000 * (0.15 + 0.06) / 2  # really a triangle
    else:
        ftype, data, expect = F.MOVE_INC_POS, struct.pack("<iI", 6000, 5000), profile_time(6000, 5000, 100, 100, 2000)
    t0 = start(b, DRIVE, ftype, data)
    assert_took(b, DRIVE, t0, expect)
    target = {"params-3-4": -7000, "ex-abs": -4000}.get(case, struct.unpack_from("<i", data)[0])
    assert i32(b, DRIVE, F.GET_COMMAND_POS) == target


def test_ex_time_out_of_range_is_a_data_error():
    b = make()
    for opt in (ex_option(acc=10000), struct.pack("<IHH", 2, 0, 0) + bytes(24)):  # flagged 10000 ms / 0 ms
        assert b.request(DRIVE, F.MOVE_INC_POS_EX, struct.pack("<iI", 100, 1000) + opt)[1] == b"\x81"
    assert b.request(DRIVE, F.MOVE_VELOCITY_EX, velocity_ex(1000, 1, accdec=10000))[1] == b"\x81"
    assert not axis(b) & FF_MOTIONING


def test_velocity_ex_acc_dec_time_and_its_stop():
    b = make()
    start(b, DRIVE, F.MOVE_VELOCITY_EX, velocity_ex(10000, 1, accdec=400))
    run_s(b, 0.2)
    # half way up a 400 ms ramp (params 3/4 would have it at full speed after 100 ms)
    assert i32(b, DRIVE, F.GET_ACTUAL_VEL) == pytest.approx(5000, abs=150)
    run_s(b, 0.3)
    assert i32(b, DRIVE, F.GET_ACTUAL_VEL) == 10000
    t0 = start(b, DRIVE, F.MOVE_STOP)
    lo, hi = until_stopped(b, DRIVE, t0, 0.4)  # MoveStop ramps down with the move's 400 ms
    assert lo is not None and lo <= 0.4 + TOL and hi >= 0.4 - TOL


# --- homing --------------------------------------------------------------------------------


def test_homing_is_a_motion_that_ends_on_the_origin_sensor():
    b = make()
    d = b.drivers[DRIVE]
    set_param(b, 23, 777)  # org_position_set
    assert not drive_inputs(b) & 4  # not at the sensor
    t0 = start(b, DRIVE, F.MOVE_ORIGIN)
    f = axis(b)
    assert f & FF_ORIGIN_RETURNING and f & FF_MOTIONING and not f & FF_ORIGIN_OK
    run_s(b, 0.2)
    assert i32(b, DRIVE, F.GET_ACTUAL_VEL) == 5000  # param 17, + direction (param 21 = 0)
    # fresh drive: the sensor's near edge is origin_pos - width/2 = 2250 pulses away; it
    # runs there at 5000 pps (param 19: 50 ms ramps), then stops in 50 ms
    edge = d.origin_pos - d.origin_width / 2
    expect = profile_time(edge + 5000 * 0.05 / 2, 5000, 50, 50)
    assert 0.2 < expect < 1.0
    assert_took(b, DRIVE, t0, expect)
    inputs, _out, f, cmd, act, err, _vel = all_status(b)
    assert f & FF_ORIGIN_OK and not f & FF_ORIGIN_RETURNING
    assert (cmd, act, err) == (777, 777, 0)
    assert inputs & 4  # the origin input reads active at the sensor
    call(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", 5000, 20000))
    run_s(b, 1.0)
    assert not drive_inputs(b) & 4 and i32(b, DRIVE, F.GET_COMMAND_POS) == 5777
    # a rotary axis: the flag comes round again after a turn (10000 pulses)
    t0 = start(b, DRIVE, F.MOVE_ORIGIN)
    expect = profile_time(d.rev_pulses - 5000 - 5000 * 0.05 / 2 + 5000 * 0.05 / 2, 5000, 50, 50)
    assert_took(b, DRIVE, t0, expect)
    assert axis(b) & FF_ORIGIN_OK and i32(b, DRIVE, F.GET_COMMAND_POS) == 777


def test_homing_direction_minus_and_its_own_acc_dec():
    b = make()
    set_param(b, 21, 1)  # org_dir: -
    set_param(b, 19, 200)
    set_param(b, 17, 8000)
    t0 = start(b, DRIVE, F.MOVE_ORIGIN)
    run_s(b, 0.3)
    assert i32(b, DRIVE, F.GET_ACTUAL_VEL) == -8000
    d = b.drivers[DRIVE]
    # from 0 going -, the next edge is at origin_pos + width/2 - one turn
    dist = d.rev_pulses - (d.origin_pos + d.origin_width / 2)
    assert_took(b, DRIVE, t0, profile_time(dist + 8000 * 0.2 / 2, 8000, 200, 200))
    assert axis(b) & FF_ORIGIN_OK and i32(b, DRIVE, F.GET_COMMAND_POS) == 0
    # its 200 ms stop from 8000 pps runs 800 pulses on: past the 500 pulse flag
    assert not drive_inputs(b) & 4


@pytest.mark.parametrize("stop", [F.MOVE_STOP, F.EMERGENCY_STOP])
def test_a_stop_aborts_homing(stop):
    b = make()
    call(b, DRIVE, F.MOVE_ORIGIN)
    run_s(b, 0.15)
    assert axis(b) & FF_ORIGIN_RETURNING
    call(b, DRIVE, stop)
    run_s(b, 0.1)
    f = axis(b)
    assert not f & (FF_MOTIONING | FF_ORIGIN_RETURNING | FF_ORIGIN_OK)
    assert i32(b, DRIVE, F.GET_COMMAND_POS) < 1000  # stopped short of the sensor, position not reset


# --- faults ---------------------------------------------------------------------------------


def test_no_origin_homing_runs_on_until_a_wired_limit_stops_it():
    b = make(WIRING)
    b.set_fault("no-origin")
    t0 = start(b, DRIVE, F.MOVE_ORIGIN)
    run_s(b, 2.5)  # more than a turn at 5000 pps
    inputs, _o, f, cmd, _a, _e, vel = all_status(b)
    assert f & FF_ORIGIN_RETURNING and f & FF_MOTIONING and vel == 5000 and cmd > 10000
    assert not inputs & 4
    relays(b, on=1 << 0)  # limit+
    run_s(b, 0.2)
    f = axis(b)
    assert f & FF_HW_PLUS and not f & (FF_MOTIONING | FF_ORIGIN_OK | FF_ORIGIN_RETURNING)
    assert b.clock.now - t0 > 2.5e6


def test_dead_origin_input_hides_the_sensor_from_homing():
    b = make()
    b.drivers[DRIVE].set_fault("dead-input", 2)
    call(b, DRIVE, F.MOVE_ORIGIN)
    run_s(b, 1.5)
    assert axis(b) & FF_ORIGIN_RETURNING and not axis(b) & FF_ORIGIN_OK


def test_step_out_loses_the_steps_above_the_threshold():
    b = make()
    b.set_fault("step-out", 20000)  # no wiring: every driver
    call(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", 30000, 40000))
    run_s(b, 0.3)
    e1 = i32(b, DRIVE, F.GET_POS_ERROR)
    run_s(b, 0.2)
    e2 = i32(b, DRIVE, F.GET_POS_ERROR)
    assert 0 < e1 < e2  # growing while above 20000 pps
    run_s(b, 1.0)
    _i, _o, f, cmd, act, err, _v = all_status(b)
    assert not f & FF_MOTIONING and cmd == 30000
    # 100 ms ramps to 40000 pps: 0.65 s above the threshold at full speed (13000 pulses)
    # and 50 ms on each ramp (500 each) -> 14000 lost
    assert err == cmd - act and err == pytest.approx(14000, abs=60)
    assert i32(b, DRIVE, F.GET_ACTUAL_POS) == act
    run_s(b, 0.5)
    assert i32(b, DRIVE, F.GET_POS_ERROR) == err  # it stays
    call(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", 5000, 15000))  # below the threshold
    run_s(b, 1.0)
    assert i32(b, DRIVE, F.GET_POS_ERROR) == err
    assert i32(b, OTHER, F.GET_POS_ERROR) == 0  # it did not move
    b.clear_faults()
    call(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", 30000, 40000))
    run_s(b, 1.5)
    assert i32(b, DRIVE, F.GET_POS_ERROR) == err


@pytest.mark.parametrize("kind", ["inc", "velocity", "homing"])
def test_alarm_mid_move(kind):
    b = make(WIRING)
    b.set_fault("alarm", "4@50" if kind == "inc" else None)  # default: 1 (over-current) at 30 ms
    ms, code = (0.050, 4) if kind == "inc" else (0.030, 1)
    ftype, data = {"inc": (F.MOVE_INC_POS, struct.pack("<iI", 10000, 10000)),
                   "velocity": (F.MOVE_VELOCITY, struct.pack("<IB", 5000, 0)),
                   "homing": (F.MOVE_ORIGIN, b"")}[kind]
    assert not jig_inputs(b) & 2
    t0 = start(b, DRIVE, ftype, data)
    assert_took(b, DRIVE, t0, ms)
    _i, out, f, *_rest = all_status(b)
    assert f & FF_ERROR_ALL and f & FF_STEP_ALARM and not f & (FF_SERVO_ON | FF_ORIGIN_RETURNING)
    assert call(b, DRIVE, F.GET_ALARM_TYPE) == bytes([code])
    assert out & 4 and struct.unpack("<I", call(b, DRIVE, F.GET_IO_OUTPUT))[0] & 4
    assert jig_inputs(b) & 2  # the alarm output reaches the jig through the wiring
    assert b.request(DRIVE, ftype, data)[1] == b"\x85"  # servo off
    # reset, servo on: the fault is still there, the next move fails the same way
    call(b, DRIVE, F.STEP_ALARM_RESET, b"\x01")
    call(b, DRIVE, F.STEP_ALARM_RESET, b"\x00")
    call(b, DRIVE, F.SERVO_ENABLE, b"\x01")
    assert call(b, DRIVE, F.GET_ALARM_TYPE) == b"\x00"
    t0 = start(b, DRIVE, ftype, data)
    assert_took(b, DRIVE, t0, ms)
    assert call(b, DRIVE, F.GET_ALARM_TYPE) == bytes([code])


def test_alarm_after_a_move_ended_is_not_raised():
    b = make()
    b.set_fault("alarm", "2@500")
    call(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", 1000, 20000))
    run_s(b, 1.0)
    assert call(b, DRIVE, F.GET_ALARM_TYPE) == b"\x00" and i32(b, DRIVE, F.GET_COMMAND_POS) == 1000


def test_sluggish_motor_takes_factor_times_the_profile():
    b = make()
    b.set_fault("sluggish", 1.5)
    t0 = start(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", 10000, 10000))
    run_s(b, 0.5)
    assert i32(b, DRIVE, F.GET_ACTUAL_VEL) == pytest.approx(10000 / 1.5, abs=1)
    assert_took(b, DRIVE, t0, 1.5 * profile_time(10000, 10000, 100, 100))
    _i, _o, _f, cmd, act, err, _v = all_status(b)
    assert (cmd, act, err) == (10000, 10000, 0)


def test_param_fault_in_ram_and_rom_until_cleared():
    b = make()
    b.drivers[DRIVE].set_fault("param", "3:250")
    assert struct.unpack("<i", call(b, DRIVE, F.GET_PARAMETER, b"\x03"))[0] == 250
    assert struct.unpack("<i", call(b, DRIVE, F.GET_ROM_PARAMETER, b"\x03"))[0] == 250
    assert struct.unpack("<i", call(b, OTHER, F.GET_PARAMETER, b"\x03"))[0] == 100
    t0 = start(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", 10000, 10000))  # the drive uses it
    assert_took(b, DRIVE, t0, profile_time(10000, 10000, 250, 100))
    b.clear_faults()
    assert struct.unpack("<i", call(b, DRIVE, F.GET_PARAMETER, b"\x03"))[0] == 100
    assert struct.unpack("<i", call(b, DRIVE, F.GET_ROM_PARAMETER, b"\x03"))[0] == 100


def test_fault_names_values_and_clearing():
    b = make()
    d = b.drivers[DRIVE]
    assert parse_fault_spec("3:alarm=4@50") == (3, "alarm", (4, 50.0))
    assert parse_fault_spec("param=3:250") == (None, "param", (3, 250))
    assert parse_fault_spec("no-origin") == (None, "no-origin", True)
    assert parse_fault("step-out") == 20000 and parse_fault("alarm") == (1, 30.0) and parse_fault("sluggish") == 1.5
    for name, value in (("nope", None), ("step-out", 0), ("alarm", "x"), ("alarm", "17"), ("sluggish", 0.5),
                        ("dead-input", 32), ("dead-input", None), ("param", "29:1"), ("param", "3:0"),
                        ("no-origin", 5), ("step-out", True)):
        with pytest.raises(ValueError):
            d.set_fault(name, value)
    for spec in ("step-out=20000", "alarm=4@50", "sluggish=2", "dead-input=26", "dead-input=2", "param=3:250",
                 "no-origin", "late=300", "wrong-id=7", "silent", "garbage", "bad-crc"):
        _s, name, value = parse_fault_spec(spec)
        d.set_fault(name, value)
    assert d.active_faults() == ["step-out=20000", "alarm=4@50", "sluggish=2", "dead-input=2", "dead-input=26",
                                 "param=3:250", "no-origin", "silent", "garbage", "bad-crc", "late=300",
                                 "wrong-id=7"]
    b.clear_faults()
    assert d.active_faults() == [] and d.ram[3] == d.rom[3] == 100
    call(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", 30000, 40000))
    run_s(b, 1.0)
    _i, _o, f, cmd, _a, err, _v = all_status(b)
    assert (cmd, err) == (30000, 0) and not f & FF_ERROR_ALL


def test_set_fault_goes_to_the_wired_drive_else_to_every_driver():
    b = make(WIRING)
    b.set_fault("step-out", 1000)
    assert b.drivers[DRIVE].step_out_pps == 1000 and b.drivers[OTHER].step_out_pps is None
    b.set_fault("sluggish", 2, slave=OTHER)
    assert b.drivers[OTHER].sluggish == 2 and b.drivers[DRIVE].sluggish == 1
    with pytest.raises(ValueError):
        b.set_fault("silent", slave=9)
    b = SimBench(driver_ids=(DRIVE, OTHER), faults=[(None, "no-origin", None), (OTHER, "param", "4:77")])
    assert b.drivers[DRIVE].no_origin and b.drivers[OTHER].no_origin
    assert b.drivers[OTHER].ram[4] == 77 and b.drivers[DRIVE].ram[4] == 100


# --- limits, Stop input, wiring ---------------------------------------------------------------


@pytest.mark.parametrize("method", [0, 1])
def test_limit_plus_relay_stops_the_axis_and_flags_it(method):
    b = make(WIRING)
    set_param(b, 15, method)  # hard_limit_stop_method: 0 at once, 1 decelerating
    set_param(b, 4, 200)
    call(b, DRIVE, F.MOVE_VELOCITY, struct.pack("<IB", 10000, 1))
    run_s(b, 0.5)  # no request in between: the drive catches up when the relay switches
    relays(b, on=1 << 0)
    at_relay = b.drivers[DRIVE].motion.pos
    # the relay switched 0.5 s (+ ~2 ms of frames) after the start: a 100 ms ramp (500
    # pulses) + 0.4 s at 10000 pps; had the drive not caught up first, it would stop at ~0
    assert at_relay == pytest.approx(4500 + 20, abs=30)
    assert drive_inputs(b) & 1
    f = axis(b)
    if method == 0:
        assert not f & FF_MOTIONING
        run_s(b, 0.01)
        assert i32(b, DRIVE, F.GET_COMMAND_POS) == pytest.approx(at_relay, abs=20)
    else:
        assert f & FF_MOTIONING and f & FF_SLOW_STOP and f & FF_DECEL
        run_s(b, 0.25)
        # decelerating from 10000 pps in param 4's 200 ms: 1000 pulses more
        assert i32(b, DRIVE, F.GET_COMMAND_POS) == pytest.approx(at_relay + 1000, abs=40)
    inputs, _o, f, *_r = all_status(b)
    assert f & FF_HW_PLUS and not f & FF_MOTIONING and inputs & 1
    # a move in + is stopped again; away from the limit (-) is free
    call(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", 1000, 10000))
    run_s(b, 0.3)
    assert axis(b) & FF_HW_PLUS and i32(b, DRIVE, F.GET_COMMAND_POS) < at_relay + 1100
    call(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", -1000, 10000))
    run_s(b, 0.5)
    f = axis(b)
    assert not f & (FF_HW_PLUS | FF_MOTIONING)
    relays(b, off=1 << 0)
    assert not drive_inputs(b) & 1


def test_limit_minus_relay_and_the_stop_input():
    b = make(WIRING)
    relays(b, on=1 << 1)  # limit- active: only moves in - stop
    call(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", 2000, 20000))
    run_s(b, 0.5)
    assert i32(b, DRIVE, F.GET_COMMAND_POS) == 2000
    call(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", -5000, 20000))
    run_s(b, 0.5)
    assert axis(b) & FF_HW_MINUS and i32(b, DRIVE, F.GET_COMMAND_POS) > 1000
    relays(b, off=1 << 1)
    # Stop (input 13) acts as MoveStop: decelerating, no limit flag
    call(b, DRIVE, F.MOVE_VELOCITY, struct.pack("<IB", 8000, 1))
    run_s(b, 0.3)
    t0 = b.clock.now
    relays(b, on=1 << 2)
    f = axis(b)
    assert f & FF_SLOW_STOP and not f & (FF_HW_PLUS | FF_HW_MINUS)
    b.drivers[DRIVE].record_requests = True
    b.drivers[DRIVE].received = []
    lo, hi = until_stopped(b, DRIVE, t0, 0.1)  # param 4: 100 ms
    assert lo is not None and lo <= 0.1 + TOL and hi >= 0.1 - TOL
    # while Stop is active a move stops at once; an Ex move that ignores the stop input runs
    call(b, DRIVE, F.MOVE_VELOCITY, struct.pack("<IB", 8000, 1))
    run_s(b, 0.2)
    assert not axis(b) & FF_MOTIONING
    call(b, DRIVE, F.MOVE_VELOCITY_EX, velocity_ex(8000, 1, ignore_stop=True))
    run_s(b, 0.2)
    assert axis(b) & FF_MOTIONING and i32(b, DRIVE, F.GET_ACTUAL_VEL) == 8000
    call(b, DRIVE, F.MOVE_STOP)


def test_sense_wiring_and_dead_input():
    b = make(WIRING)
    assert jig_inputs(b) == 0
    call(b, DRIVE, F.SET_IO_OUTPUT, struct.pack("<II", 1 << 15, 0))  # user out 0
    assert jig_inputs(b) == 1 << 0
    call(b, DRIVE, F.MOVE_INC_POS, struct.pack("<iI", 20000, 20000))
    assert jig_inputs(b) == 1 << 0 | 1 << 2  # run/stop while moving
    run_s(b, 1.5)
    assert jig_inputs(b) == 1 << 0
    call(b, OTHER, F.SET_IO_OUTPUT, struct.pack("<II", 1 << 15, 0))  # the unwired drive: nothing
    call(b, DRIVE, F.SET_IO_OUTPUT, struct.pack("<II", 0, 1 << 15))
    assert jig_inputs(b) == 0
    relays(b, on=1 << 3)
    assert drive_inputs(b) == 1 << 26 and drive_inputs(b, OTHER) == 0
    b.set_fault("dead-input", 26)
    assert drive_inputs(b) == 0
    relays(b, off=1 << 3)
    relays(b, on=1 << 3)
    assert drive_inputs(b) == 0  # a broken wire never changes
    call(b, DRIVE, F.SET_IO_INPUT, struct.pack("<II", 1 << 26, 0))
    assert drive_inputs(b) == 1 << 26  # SetIOInput is no wire: it still sets the bit
    b.clear_faults()
    call(b, DRIVE, F.SET_IO_INPUT, struct.pack("<II", 0, 1 << 26))
    assert drive_inputs(b) == 1 << 26  # the relay again


def test_wiring_from_a_file_and_bad_bench_wiring(tmp_path):
    p = tmp_path / "plan.toml"
    p.write_text('[drive]\nslave = 3\n[wiring]\n[[wiring.relay]]\nrelay = 5\ndrive_input = 26\n')
    b = SimBench(driver_ids=(DRIVE, OTHER), wiring=str(p))
    assert b.wired_slave == OTHER
    relays(b, on=1 << 5)
    assert drive_inputs(b, OTHER) == 1 << 26 and drive_inputs(b, DRIVE) == 0
    assert SimBench(driver_ids=(DRIVE, OTHER), wiring=Wiring()).wired_slave == DRIVE  # the first driver
    with pytest.raises(ValueError, match="wiring.slave 9 is not a driver"):
        SimBench(driver_ids=(DRIVE, OTHER), wiring=Wiring(slave=9))
    with pytest.raises(ValueError, match="direct=True"):
        SimBench(driver_ids=(DRIVE,), direct=True, wiring=Wiring())


# --- the wiring parser ------------------------------------------------------------------------


def test_parse_wiring_values_and_helpers():
    w = parse_wiring(WIRING, "w.toml")
    assert w.slave == DRIVE and w.source == "w.toml"
    assert w.relays[0] == (0, 0, "limit+") and w.relays[3] == (3, 26, "user in 0")
    assert w.senses == ((0, 15, "user out 0"), (1, 2, "alarm"), (2, 3, "run/stop"))
    assert w.drive_inputs(0b1011) == 1 << 0 | 1 << 1 | 1 << 26
    assert w.drive_inputs(1 << 7) == 0
    assert w.jig_inputs(1 << 15 | 1 << 3 | 1 << 4) == 0b101
    assert w.drive_input_mask == 1 | 2 | 1 << 13 | 1 << 26 and w.jig_input_mask == 0b111
    w = parse_wiring({"relay": [{"relay": 1, "drive_input": 2}]}, default_slave=4)
    assert w.slave == 4 and w.relays == ((1, 2, ""),) and w.senses == ()
    assert parse_wiring({}).slave is None


@pytest.mark.parametrize("table,msg", [
    ({"slave": 2, "relays": []}, "plan.toml: wiring.relays: unknown key (known: slave, node, relay, sense)"),
    ({"relay": [{"relay": 0, "drive_inptu": 1}]}, "plan.toml: wiring.relay[0].drive_inptu: unknown key"),
    ({"relay": [{"relay": 0, "drive_input": 0}, {"relay": 1, "drive_input": "x"}]},
     "plan.toml: wiring.relay[1].drive_input: expected an integer 0..31, got 'x'"),
    ({"relay": [{"relay": 16, "drive_input": 0}]},
     "plan.toml: wiring.relay[0].relay: expected an integer 0..15, got 16"),
    ({"sense": [{"jig_input": 0, "drive_output": 32}]},
     "plan.toml: wiring.sense[0].drive_output: expected an integer 0..31, got 32"),
    ({"sense": [{"jig_input": True, "drive_output": 3}]},
     "wiring.sense[0].jig_input: expected an integer 0..15, got True"),
    ({"relay": [{"relay": 1.0, "drive_input": 0}]}, "wiring.relay[0].relay: expected an integer 0..15, got 1.0"),
    ({"relay": [{"relay": 1}]}, "wiring.relay[0].drive_input: missing"),
    ({"relay": [{"relay": 1, "drive_input": 0, "name": 5}]}, "wiring.relay[0].name: expected a string, got 5"),
    ({"relay": {"relay": 1, "drive_input": 0}},
     "wiring.relay: expected an array of tables ([[wiring.relay]]), got a table"),
    ({"slave": 16}, "wiring.slave: expected an integer 0..15, got 16"),
    ({"relay": [{"relay": 1, "drive_input": 0}, {"relay": 1, "drive_input": 2}]},
     "wiring.relay[1].relay: relay 1 is already wired in wiring.relay[0]"),
    ({"relay": [{"relay": 1, "drive_input": 0, "name": "a"}, {"relay": 2, "drive_input": 2, "name": "a"}]},
     "wiring.relay[1].name: name 'a' is already used by wiring.relay[0]"),
])
def test_parse_wiring_errors_name_the_file_and_the_key(table, msg):
    with pytest.raises(WiringError) as exc:
        parse_wiring(table, "plan.toml")
    assert msg in str(exc.value)
    assert isinstance(exc.value, ValueError) and str(exc.value).startswith("plan.toml: wiring")


def test_the_parser_checks_against_wiring_schema():
    """Every integer key of the schema accepts its bounds and refuses one beyond them."""
    base = {"wiring.relay": {"relay": 0, "drive_input": 0}, "wiring.sense": {"jig_input": 0, "drive_output": 0}}
    for section, fields in WIRING_SCHEMA.items():
        for f in fields:
            if f.kind != "integer":
                continue
            for value, ok in ((f.lo, True), (f.hi, True), (f.lo - 1, False), (f.hi + 1, False)):
                if section == "wiring":
                    table = {f.key: value}
                else:
                    key = section.split(".")[1]
                    table = {key: [dict(base[section], **{f.key: value})]}
                if ok:
                    parse_wiring(table)
                else:
                    with pytest.raises(WiringError, match="%d..%d" % (f.lo, f.hi)):
                        parse_wiring(table)
    keys = {f.key for f in WIRING_SCHEMA["wiring.relay"]}
    assert keys == {"relay", "drive_input", "name"}


def test_load_wiring_files(tmp_path):
    p = tmp_path / "plan.toml"
    p.write_text('[plan]\nname = "x"\n[drive]\nslave = 5\n[wiring]\n[[wiring.sense]]\njig_input = 3\n'
                 'drive_output = 15\nname = "out0"\n')
    w = load_wiring(p)
    assert w.slave == 5 and w.senses == ((3, 15, "out0"),) and w.source == str(p)
    p.write_text('[wiring]\nslave = 2\n[drive]\nslave = 5\n')
    assert load_wiring(p).slave == 2  # the wiring's own slave wins
    for text, msg in (("[drive]\nslave = 2\n", "no [wiring] table"), ("[wiring\n", "not valid TOML"),
                      ("[drive]\nslave = 'a'\n[wiring]\n", "drive.slave: expected an integer 0..15"),
                      ("[wiring]\n[[wiring.relay]]\nrelay = 0\ndrive_input = 'x'\n",
                       "wiring.relay[0].drive_input: expected an integer 0..31, got 'x'")):
        p.write_text(text)
        with pytest.raises(WiringError, match=msg.replace("[", r"\[")) as exc:
            load_wiring(p)
        assert str(exc.value).startswith(str(p) + ": ")
    with pytest.raises(WiringError, match="cannot read"):
        load_wiring(tmp_path / "missing.toml")


# --- the command line ----------------------------------------------------------------------------


@pytest.mark.parametrize("argv,msg", [
    (["--fault", "3:alarm=x"], "--fault 3:alarm=x: alarm: expected CODE or CODE@MS"),
    (["--fault", "bogus"], "unknown fault 'bogus'"),
    (["--fault", "9:silent"], "--fault 9:silent: no driver 9"),
    (["--fault", "param=3:0"], "parameter 3 must be 1..9999, got 0"),
    (["--fault", "step-out=fast"], "step-out: expected a speed in pps > 0, got 'fast'"),
    (["--wiring", "/nonexistent/plan.toml"], "--wiring: /nonexistent/plan.toml: cannot read it"),
    (["--wiring", "BAD"], "wiring.relay[0].drive_input: expected an integer 0..31, got 'x'"),
    (["--wiring", "SLAVE9"], "wiring.slave 9 is not one of the --drivers (2,3)"),
])
def test_cli_bad_fault_or_wiring_is_one_line_and_exit_2(argv, msg, capsys, tmp_path):
    files = {"BAD": "[wiring]\n[[wiring.relay]]\nrelay = 0\ndrive_input = 'x'\n", "SLAVE9": "[wiring]\nslave = 9\n"}
    if argv[-1] in files:
        p = tmp_path / "w.toml"
        p.write_text(files[argv[-1]])
        argv = argv[:-1] + [str(p)]
    assert sim_main.main(argv + ["--no-pty", "--no-demo", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert msg in err and err.startswith("error: ") and err.count("\n") == 1


def test_cli_prints_the_wiring_and_the_faults(capsys, tmp_path):
    p = tmp_path / "w.toml"
    p.write_text('[wiring]\nslave = 3\n[[wiring.relay]]\nrelay = 0\ndrive_input = 0\nname = "limit+"\n'
                 '[[wiring.sense]]\njig_input = 1\ndrive_output = 15\n')
    rc = sim_main.main(["--wiring", str(p), "--fault", "step-out=20000", "--fault", "2:alarm=4@50",
                        "--fault", "param=3:250", "--no-pty", "--no-demo", "--duration", "0.1"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "wiring (%s): drive 3" % p in out
    assert "jig relay 0 -> drive input 0 (limit+)" in out and "drive output 15 -> jig input 1" in out
    assert "faults: driver 2: alarm=4@50; driver 3: step-out=20000, param=3:250" in out


def test_cli_exit_code_2_without_traceback_in_a_process():
    proc = subprocess.run([sys.executable, "-m", "motorjig.sim", "--fault", "sluggish=0"], capture_output=True,
                          text=True, env=SUBPROCESS_ENV, timeout=60)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip() == "error: --fault sluggish=0: sluggish: expected a factor >= 1, got 0"
    assert "--fault SPEC" in subprocess.run([sys.executable, "-m", "motorjig.sim", "--help"], capture_output=True,
                                            text=True, env=SUBPROCESS_ENV, timeout=60).stdout


# --- the real-time bench -------------------------------------------------------------------------


def test_real_time_bench_wiring_homing_and_faults():
    with Bench(driver_ids=(DRIVE, OTHER), pty=False, servo_on=True, wiring=parse_wiring(WIRING),
               faults=[(OTHER, "alarm", "4@30")]) as bench, Master(bench.tcp_url, timeout=0.5) as m:
        m.set_io_output(JIG, set_mask=1 << 3)
        assert m.get_io_input(DRIVE) & 1 << 26
        m.set_io_output(DRIVE, set_mask=1 << 15)
        assert m.get_io_input(JIG) & 1
        m.move_origin(DRIVE)
        assert m.get_axis_status(DRIVE).origin_returning
        st = m.wait_motion_done(DRIVE, timeout=5)
        assert st.origin_ok and m.get_io_input(DRIVE) & 4
        m.move_velocity(OTHER, 5000, 1)
        m.wait_motion_done(OTHER, timeout=5)
        assert m.get_alarm_type(OTHER).code == 4 and m.get_axis_status(OTHER).step_alarm
