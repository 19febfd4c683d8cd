"""The simulated Ezi-STEP Plus-R drive on its own (no jig)."""

import struct

from jig import frame as F
from motorjig.sim import Bus, SimDriver, VirtualClock
from motorjig.sim.driver import FF_ACCEL, FF_CONST, FF_DECEL, FF_ERROR_ALL, FF_INPOSITION, FF_MOTIONING


def make(**kw):
    clock = VirtualClock(0.0)
    bus = Bus(clock, 115200)
    return clock, SimDriver(clock, bus, 2, **kw)


def test_trapezoid_profile_phases_and_final_position():
    clock, d = make(servo_on=True)
    assert d.handle(F.MOVE_INC_POS, struct.pack("<iI", 10000, 10000)) == b"\x00"
    phases = []
    last = -1
    for _ in range(2000):
        clock.advance(1000.0)
        f = d.flags()
        for bit, name in ((FF_ACCEL, "acc"), (FF_CONST, "const"), (FF_DECEL, "dec")):
            if f & bit and (not phases or phases[-1] != name):
                phases.append(name)
        pos = d._positions()[0]
        assert pos >= last
        last = pos
        if not f & FF_MOTIONING:
            break
    assert phases == ["acc", "const", "dec"]
    assert d._positions()[0] == 10000 and d.flags() & FF_INPOSITION
    # 10000 pulses at 10000 pps with 100 ms ramps: about 1.1 s
    assert 1.0e6 < clock.now < 1.25e6


def test_refusals_and_alarm():
    clock, d = make()
    assert d.handle(F.MOVE_ABS_POS, struct.pack("<iI", 100, 1000)) == bytes([F.STATUS_MOTION_REFUSED])
    assert d.handle(F.SERVO_ENABLE, b"\x01") == b"\x00"
    d.inject_alarm(3)
    assert d.flags() & FF_ERROR_ALL
    assert d.handle(F.GET_ALARM_TYPE, b"") == b"\x00\x03"
    assert d.handle(F.SERVO_ENABLE, b"\x01") == bytes([F.STATUS_SERVO_ON_ALARM])
    d.handle(F.STEP_ALARM_RESET, b"\x01")
    d.handle(F.STEP_ALARM_RESET, b"\x00")
    assert d.handle(F.GET_ALARM_TYPE, b"") == b"\x00\x00"
    assert d.handle(F.SERVO_ENABLE, b"\x01") == b"\x00"


def test_parameters_ram_rom():
    clock, d = make()
    assert d.handle(F.SET_PARAMETER, b"\x03" + struct.pack("<i", 250)) == b"\x00"
    assert d.handle(F.GET_PARAMETER, b"\x03") == b"\x00" + struct.pack("<i", 250)
    assert d.handle(F.GET_ROM_PARAMETER, b"\x03") == b"\x00" + struct.pack("<i", 100)
    assert d.handle(F.SAVE_ALL_PARAMETERS, b"") == b"\x00"
    assert d.handle(F.GET_ROM_PARAMETER, b"\x03") == b"\x00" + struct.pack("<i", 250)
    assert d.handle(F.SET_PARAMETER, b"\x03" + struct.pack("<i", 0)) == bytes([F.STATUS_DATA_ERROR])
    assert d.handle(F.GET_PARAMETER, b"\x1d") == bytes([F.STATUS_DATA_ERROR])


def test_limit_sensor_stops_motion():
    clock, d = make(servo_on=True)
    d.limit_plus = 500
    d.handle(F.MOVE_VELOCITY, struct.pack("<IB", 5000, 1))
    clock.advance(1e6)
    f = d.flags()
    assert not f & FF_MOTIONING and f & 0x2 and d._positions()[0] == 500


def test_velocity_mode_and_stop():
    clock, d = make(servo_on=True)
    d.handle(F.MOVE_VELOCITY, struct.pack("<IB", 4000, 0))
    clock.advance(500000.0)
    assert d._positions()[3] == -4000
    d.handle(F.MOVE_STOP, b"")
    clock.advance(300000.0)
    assert not d.flags() & FF_MOTIONING and d._positions()[0] < 0


def test_forced_status_for_n_frames_then_normal_replies():
    from motorjig.sim import SimBench

    b = SimBench(driver_ids=(2,), servo_on=True)
    d = b.drivers[2]
    d.force(F.STATUS_CRC_ERROR, frames=2)
    assert b.request(2, F.GET_COMMAND_POS)[1] == bytes([F.STATUS_CRC_ERROR])
    # a forced request is not executed: the drive did not start this move
    assert b.request(2, F.MOVE_INC_POS, struct.pack("<iI", 1000, 5000))[1] == bytes([F.STATUS_CRC_ERROR])
    assert not d.flags() & FF_MOTIONING and d.force_status is None
    assert b.request(2, F.GET_COMMAND_POS)[1] == b"\x00" + bytes(4)
    d.force(0x85)  # until cleared
    for _ in range(3):
        assert b.request(2, F.GET_AXIS_STATUS)[1] == b"\x85"
    wire = b.encode(F.BROADCAST_ID, F.ALL_EMERGENCY_STOP)  # broadcasts are executed as usual
    b.run_for(b.send(wire) - b.clock.now + 2000.0)
    assert d.estop and d.force_status == 0x85
    d.clear_faults()
    assert b.request(2, F.GET_AXIS_STATUS)[1][0] == 0 and d.requests == 8  # the broadcast too
