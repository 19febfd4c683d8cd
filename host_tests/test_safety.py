"""Master-silence safety stop: opt-in, once per silence, only to drivers seen."""

import struct

from jig import frame as F
from jig import params as P
from motorjig.sim import SimBench


def setup(action=0, timeout_ms=200):
    b = SimBench(driver_ids=(2, 3, 4), servo_on=True)
    for d in b.drivers.values():
        d.record_requests = True
    data = bytes([P.P_SAFETY_TIMEOUT_MS]) + struct.pack("<i", timeout_ms)
    assert b.request(1, F.SET_PARAMETER, data)[1] == b"\x00"
    assert b.request(1, F.SET_PARAMETER, bytes([P.P_SAFETY_ACTION]) + struct.pack("<i", action))[1] == b"\x00"
    return b


def stops(d):
    return [t for t, ft in d.received if ft in (F.MOVE_STOP, F.EMERGENCY_STOP)]


def test_off_by_default():
    b = SimBench(driver_ids=(2,), servo_on=True)
    b.request(2, F.MOVE_VELOCITY, struct.pack("<IB", 1000, 1))
    b.run_for(5e6)
    assert b.counters["safety_stops"] == 0 and b.counters["int_requests"] == 0
    assert b.drivers[2].motion.moving


def test_silence_stops_seen_drivers_once():
    b = setup(action=0, timeout_ms=200)
    for i in (2, 3):
        assert b.request(i, F.MOVE_VELOCITY, struct.pack("<IB", 2000, 1))[1] == b"\x00"
    t_last = b.pc.node.tx_until  # end of the PC's last frame
    b.run_for(150000.0)
    assert b.counters["safety_stops"] == 0
    b.run_for(2e6)
    c = b.counters
    assert c["safety_stops"] == 1
    for i in (2, 3):
        s = stops(b.drivers[i])
        assert len(s) == 1 and s[0] - t_last >= 200000.0
        assert b.drivers[i].received[-1][1] == F.MOVE_STOP
        assert not b.drivers[i].flags() & (1 << 27)  # decelerated to a stop
    assert stops(b.drivers[4]) == []  # never seen: not addressed
    assert c["int_requests"] == 2 and c["int_replies"] == 2
    assert b.pc.frames[-1][1][3] == F.MOVE_VELOCITY  # nothing reached the PC
    # a lease (set in RAM, as a run does): let go once it fired, the window back to its saved 0
    assert get_param(b, P.P_SAFETY_TIMEOUT_MS) == 0 and get_param(b, P.P_SAFETY_ACTION) == 0
    b.request(2, F.GET_AXIS_STATUS)
    b.run_for(1e6)
    assert b.counters["safety_stops"] == 1 and len(stops(b.drivers[2])) == 1


def get_param(b, num):
    return struct.unpack("<i", b.request(1, F.GET_PARAMETER, bytes([num]))[1][1:5])[0]


def test_a_window_saved_to_flash_is_a_setting_it_stays_and_fires_again():
    b = setup(action=1, timeout_ms=200)
    assert b.request(1, F.SAVE_ALL_PARAMETERS)[1] == b"\x00"
    assert b.request(2, F.MOVE_VELOCITY, struct.pack("<IB", 2000, 1))[1] == b"\x00"
    b.run_for(1e6)
    assert b.counters["safety_stops"] == 1 and get_param(b, P.P_SAFETY_TIMEOUT_MS) == 200
    b.request(2, F.GET_AXIS_STATUS)  # talks again, goes silent again: fires again
    b.run_for(1e6)
    assert b.counters["safety_stops"] == 2 and len(stops(b.drivers[2])) == 2


def take_notice(b):
    from jig import diag as D

    return D.decode_safety_notice(b.request(1, D.TAKE_SAFETY_NOTICE)[1])


def test_the_jig_keeps_a_notice_of_the_stop_until_a_pc_takes_it():
    b = setup(action=2, timeout_ms=200)
    assert take_notice(b) is None
    for i in (2, 3):
        assert b.request(i, F.MOVE_VELOCITY, struct.pack("<IB", 2000, 1))[1] == b"\x00"
    t_last = b.pc.node.tx_until  # end of the PC's last frame: the stop 200 ms later
    b.run_for(3.5e6)
    n = take_notice(b)
    assert n["ids"] == [2, 3] and n["pc_bus"] and not n["can"] and n["nodes"] == []
    assert abs(n["ms_ago"] - ((b.clock.now - t_last) / 1000 - 200)) < 30
    assert take_notice(b) is None  # taken: said once


def test_emergency_stop_action():
    b = setup(action=1, timeout_ms=100)
    b.request(3, F.MOVE_VELOCITY, struct.pack("<IB", 2000, 0))
    b.run_for(500000.0)
    d = b.drivers[3]
    assert d.received[-1][1] == F.EMERGENCY_STOP and d.estop


def test_traffic_keeps_it_quiet():
    b = setup(timeout_ms=100)
    for _ in range(30):
        b.request(2, F.GET_AXIS_STATUS)
        b.run_for(50000.0)
    assert b.counters["safety_stops"] == 0


def test_mixed_bus_each_driver_executes_one_stop():
    """Ver8 jig (and Ver6 jig), a Ver6 and a Ver8 drive: the stop in the jig's framing
    is refused (0x80) by the driver of the other variant, which then gets it in its
    own framing; the driver of the jig's variant gets exactly one frame."""
    for jig_ver8 in (False, True):
        b = SimBench(driver_ids=(2, 3), servo_on=True, jig_ver8=jig_ver8, ver8_drivers=(3,))
        for d in b.drivers.values():
            d.record_requests = True
        data = bytes([P.P_SAFETY_TIMEOUT_MS]) + struct.pack("<i", 100)
        assert b.request(1, F.SET_PARAMETER, data)[1] == b"\x00"
        for i in (2, 3):
            assert b.request(i, F.MOVE_VELOCITY, struct.pack("<IB", 2000, 1))[1] == b"\x00"
        n = {i: len(b.drivers[i].received) for i in (2, 3)}
        b.run_for(2e6)
        same, other = (3, 2) if jig_ver8 else (2, 3)
        assert len(b.drivers[same].received) - n[same] == 1  # one stop, executed
        assert len(b.drivers[other].received) - n[other] == 2  # refused framing, then its own
        for i in (2, 3):
            assert len(stops(b.drivers[i])) == 1 and not b.drivers[i].flags() & (1 << 27)  # stopped
            assert b.drivers[i].servo_on  # nothing else was executed
        c = b.counters
        assert c["safety_stops"] == 1 and c["int_requests"] == 3 and c["int_replies"] == 3


def servo_offs(d):
    return [t for t, ft in d.received if ft == F.SERVO_ENABLE]


def test_emergency_stop_then_servo_off_action():
    """safety_action 2 (the station's, for a run): each seen driver gets EmergencyStop, then
    ServoEnable(off), in the framing it executed the stop in; a Ver8 drive on a Ver6 jig too."""
    for jig_ver8 in (False, True):
        b = SimBench(driver_ids=(2, 3), servo_on=True, jig_ver8=jig_ver8, ver8_drivers=(3,))
        for d in b.drivers.values():
            d.record_requests = True
        for num, value in ((P.P_SAFETY_TIMEOUT_MS, 100), (P.P_SAFETY_ACTION, 2)):
            assert b.request(1, F.SET_PARAMETER, bytes([num]) + struct.pack("<i", value))[1] == b"\x00"
        for i in (2, 3):
            assert b.request(i, F.MOVE_VELOCITY, struct.pack("<IB", 2000, 1))[1] == b"\x00"
        b.run_for(2e6)
        for i in (2, 3):
            d = b.drivers[i]
            assert len(stops(d)) == 1 and len(servo_offs(d)) == 1, (jig_ver8, i, d.received)
            assert stops(d)[0] < servo_offs(d)[0]
            assert d.received[-1][1] == F.SERVO_ENABLE
            assert not d.servo_on and not d.flags() & (1 << 27)
        assert b.counters["safety_stops"] == 1


def test_servo_off_action_out_of_range_is_refused():
    b = SimBench(driver_ids=(2,))
    st = b.request(1, F.SET_PARAMETER, bytes([P.P_SAFETY_ACTION]) + struct.pack("<i", 3))[1]
    assert st == b"\x81"
