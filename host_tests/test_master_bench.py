"""Every Master method against the virtual bench (real jig firmware + simulated drives),
once over the bench's pseudo-terminal and once over its TCP port.

Faults come from the bench's fault switches: the simulated drive's (``silent``,
``bad_crc``, ``force`` a status such as 0xAA) and the PC link's (``corrupt_to_pc``:
a bit flipped in the jig's next reply). Set-up shared with test_cli_bench.py is in
bench_fixtures.py.
"""

import os
import re
import threading

import pytest

from bench_fixtures import DRIVE, OTHER, TIMEOUT, bench, eventually, port  # noqa: F401 (fixtures)
from jig import frame as F
from motorjig import errors as E
from motorjig.master import AxisStatus, Master, MotionStatus
from motorjig.sim import Bench

JIG = 1
ABSENT = 9
FAST = 200000  # pps


@pytest.fixture
def m(port):
    with Master(port, timeout=TIMEOUT) as master:
        # First contact (variant detection) up front, so the tests below count only
        # the requests they make themselves.
        assert [master.variant(i) for i in (JIG, DRIVE, OTHER)] == [6, 6, 6]
        yield master


def drive(bench, slave=DRIVE):
    return bench.sim.drivers[slave]


def test_connection_and_discovery(bench, m):
    assert m.is_open
    assert m.is_slave_exist(DRIVE) and m.is_slave_exist(JIG)
    assert not m.is_slave_exist(ABSENT, timeout=0.1)
    found = m.scan(range(0, 5), timeout=TIMEOUT)  # one try per id: the present ones must answer
    assert sorted(found) == [JIG, DRIVE, OTHER]
    assert found[DRIVE].type == 20 and found[JIG].type_name == "MotorJig bridge"
    assert m.open() is m  # already open: no-op
    m.close()
    assert not m.is_open
    m.connect()
    assert m.get_slave_info(DRIVE).type_name == "Ezi-STEP Plus-R ST"


def test_info(m):
    info = m.get_slave_info(DRIVE)
    assert info.type == 20 and "sim" in info.version
    assert m.get_motor_info(DRIVE).text
    assert m.get_firmware_info(DRIVE) >= 0


def test_parameters(m):
    m.set_parameter(DRIVE, 1, 123456)
    assert m.get_parameter(DRIVE, 1) == 123456
    assert m.get_rom_parameter(DRIVE, 1) != 123456
    m.save_all_parameters(DRIVE)
    assert m.get_rom_parameter(DRIVE, 1) == 123456
    m.set_parameter(DRIVE, 1, 500000)
    m.save_all_parameters(DRIVE)
    with pytest.raises(E.DataError):
        m.set_parameter(DRIVE, 3, 0)  # accel time 0 ms is out of range
    # the jig's own table on slave 1
    m.set_parameter(JIG, 11, 30)
    assert m.get_parameter(JIG, 11) == 30
    m.set_parameter(JIG, 11, 20)


def test_io(m):
    m.set_io_output(DRIVE, 1 << 15, 0)
    assert m.get_io_output(DRIVE) & (1 << 15)
    m.set_io_output(DRIVE, 0, 1 << 15)
    assert not m.get_io_output(DRIVE) & (1 << 15)
    m.set_io_input(DRIVE, 1 << 26, 0)
    assert m.get_io_input(DRIVE) & (1 << 26)
    m.set_io_input(DRIVE, 0, 1 << 26)
    assert not m.get_io_input(DRIVE) & (1 << 26)
    m.set_io_assign_map(DRIVE, 5, 1 << 13, 1)
    a = m.get_io_assign_map(DRIVE, 5)
    assert (a.mask, a.level) == (1 << 13, 1)
    assert m.io_assign_map_read_rom(DRIVE) == 0


def test_positions(m):
    m.set_command_pos(DRIVE, 170)  # 0xAA: stuffed on the wire
    assert m.get_command_pos(DRIVE) == 170
    m.set_actual_pos(DRIVE, 150)
    assert m.get_actual_pos(DRIVE) == 150
    assert m.get_pos_error(DRIVE) == 20
    assert m.get_actual_vel(DRIVE) == 0
    m.clear_position(DRIVE)
    assert m.get_command_pos(DRIVE) == 0 and m.get_actual_pos(DRIVE) == 0


def test_status_words(m):
    st = m.get_axis_status(DRIVE)
    assert isinstance(st, AxisStatus) and st.servo_on and not st.motioning
    io = m.get_io_axis_status(DRIVE)
    assert io.axis == st
    ms = m.get_motion_status(DRIVE)
    assert isinstance(ms, MotionStatus) and ms.command_pos == 0
    al = m.get_all_status(DRIVE)
    assert al.axis.servo_on and al.command_pos == 0 and al.actual_vel == 0


def test_moves_and_waiting(m):
    m.move_inc(DRIVE, 3000, FAST)
    assert m.get_axis_status(DRIVE).motioning
    st = m.wait_motion_done(DRIVE, timeout=5)
    assert not st.errors and m.get_command_pos(DRIVE) == 3000
    m.move_abs(DRIVE, -2000, FAST)
    m.wait_motion_done(DRIVE, timeout=5)
    assert m.get_command_pos(DRIVE) == -2000
    m.move_inc_ex(DRIVE, 1000, FAST, accel_ms=5, decel_ms=5)
    m.wait_motion_done(DRIVE, timeout=5)
    m.move_abs_ex(DRIVE, 0, FAST)
    m.wait_motion_done(DRIVE, timeout=5)
    assert m.get_command_pos(DRIVE) == 0
    m.move_origin(DRIVE)
    st = m.wait_motion_done(DRIVE, timeout=5)
    assert st.origin_ok


def test_velocity_overrides_pause_and_stops(m):
    m.move_velocity(DRIVE, 20000, 1)
    assert m.get_axis_status(DRIVE).motioning
    m.velocity_override(DRIVE, 40000)
    m.move_pause(DRIVE, True)
    assert m.get_axis_status(DRIVE).motion_pause
    m.move_pause(DRIVE, False)
    m.move_stop(DRIVE)
    m.wait_motion_done(DRIVE, timeout=5)
    m.move_inc(DRIVE, 100000, 20000)
    m.position_abs_override(DRIVE, 3000)
    m.position_inc_override(DRIVE, 500)
    m.wait_motion_done(DRIVE, timeout=5)
    assert m.get_command_pos(DRIVE) == 3500
    m.move_velocity_ex(DRIVE, 20000, 0, accdec_ms=5)
    assert m.get_axis_status(DRIVE).motioning
    m.emergency_stop(DRIVE)
    st = m.get_axis_status(DRIVE)
    assert st.emergency_stop and not st.motioning


def test_limit_move(bench, m):
    drive(bench).limit_plus = 400
    try:
        m.move_to_limit(DRIVE, FAST, 1)
        st = m.wait_motion_done(DRIVE, timeout=5)
        assert st.hw_limit_plus and m.get_command_pos(DRIVE) == 400
    finally:
        drive(bench).limit_plus = None


def test_alarms(bench, m):
    drive(bench).inject_alarm(3)
    assert m.get_alarm_type(DRIVE).name == "step-out"
    assert m.get_axis_status(DRIVE).step_alarm
    with pytest.raises(E.ServoOnRefusedError) as exc:
        m.servo_enable(DRIVE, True)
    assert exc.value.status == 0x87
    m.step_alarm_reset(DRIVE, True)
    m.step_alarm_reset(DRIVE, False)
    assert m.get_alarm_type(DRIVE).code == 0
    drive(bench).inject_alarm(1)
    m.servo_alarm_reset(DRIVE)
    assert m.get_alarm_type(DRIVE).code == 0
    drive(bench).inject_alarm(2)
    m.alarm_reset(DRIVE)  # STEP: assert + release
    assert m.get_alarm_type(DRIVE).code == 0


def test_position_table(m):
    item = bytearray(64)
    F.put_i32(item, 0, 1500)
    F.put_u32(item, 8, FAST)
    F.put_u16(item, 16, 3)  # ABS normal
    assert m.pos_table_write_item(DRIVE, 7, item)
    assert m.pos_table_read_item(DRIVE, 7) == bytes(item)
    assert m.pos_table_write_rom(DRIVE)
    assert m.pos_table_read_rom(DRIVE)
    m.pos_table_run_item(DRIVE, 7)
    m.wait_motion_done(DRIVE, timeout=5)
    assert m.get_command_pos(DRIVE) == 1500
    with pytest.raises(ValueError):
        m.pos_table_write_item(DRIVE, 7, b"short")


def test_broadcast_moves(m):
    m.all_move_inc(2000, FAST)
    for s in (DRIVE, OTHER):
        m.wait_motion_done(s, timeout=5)
        assert m.get_command_pos(s) == 2000
    m.all_move_abs(-500, FAST)
    for s in (DRIVE, OTHER):
        m.wait_motion_done(s, timeout=5)
        assert m.get_command_pos(s) == -500
    m.all_move_origin()
    for s in (DRIVE, OTHER):  # homing is a motion now: the search takes its time
        assert m.get_axis_status(s).origin_returning
    for s in (DRIVE, OTHER):
        assert m.wait_motion_done(s, timeout=5).origin_ok
    m.all_move_inc(1000000, 20000)
    m.all_move_stop()
    m.all_emergency_stop()
    for s in (DRIVE, OTHER):
        assert m.get_axis_status(s).emergency_stop


def test_jig_extensions(m):
    m.reset_counters(JIG)
    m.get_command_pos(DRIVE)
    c = m.read_counters(JIG)
    assert c["forwards"] >= 1 and c["replies"] >= 1 and "up_crc_errors" in c
    m.start_bus_scan(JIG)
    assert m.get_bus_scan_result(JIG).state in ("running", "done")
    res = m.jig_bus_scan(JIG)
    assert res.state == "done" and res.types == {DRIVE: 20, OTHER: 20}
    assert m.can_counters(JIG) == {}  # this bench has no CAN bus: the jig answers n = 0 (test_canport: with one)
    assert m.take_safety_notice(JIG) is None  # no safety stop fired (test_safety: one that did)


def test_crash_log(bench, monkeypatch, m):
    assert m.read_crash_log(JIG) == ""  # the bench's HAL has no crash_summary()
    text = "crashes=2 consecutive=1 wdt_resets=0; last: MemoryError: memory allocation failed"
    monkeypatch.setattr(bench.sim.hal, "crash_summary", lambda: text, raising=False)
    assert m.read_crash_log(JIG) == text
    with pytest.raises(E.FrameTypeError):  # a drive does not know the jig's frame
        m.read_crash_log(DRIVE)


def test_low_level(m):
    fr = m.request(DRIVE, F.GET_AXIS_STATUS)
    assert (fr.slave, fr.ftype, fr.data[0]) == (DRIVE, F.GET_AXIS_STATUS, 0) and len(fr.data) == 5
    assert len(m.call(DRIVE, F.GET_ALL_STATUS)) == 32
    m.broadcast(F.ALL_MOVE_STOP)
    m.discard_input()
    m.write(F.encode(DRIVE, F.GET_COMMAND_POS))
    fr = m.read_frame(TIMEOUT)
    assert fr is not None and fr.ftype == F.GET_COMMAND_POS
    assert list(m.frames(0.05)) == []
    assert m.next_sync(DRIVE) >= 0


# --- error paths ----------------------------------------------------------------
def test_no_reply_from_an_absent_or_silent_slave(bench, m):
    m.timeout = 0.15
    with pytest.raises(E.NoReplyError) as exc:
        m.get_axis_status(ABSENT)
    assert "no reply from slave 9 to GetAxisStatus within 150 ms" in str(exc.value)
    assert m.variant(OTHER) == 6  # detected at first contact, before it falls silent
    drive(bench, OTHER).silent = True
    try:
        n0 = drive(bench, OTHER).requests
        with pytest.raises(E.NoReplyError):
            m.get_command_pos(OTHER)
        assert eventually(lambda: drive(bench, OTHER).requests - n0, 1 + m.retries) == 1 + m.retries  # retried
        n0 = drive(bench, OTHER).requests
        with pytest.raises(E.NoReplyError):
            m.move_inc(OTHER, 100, 1000)
        assert eventually(lambda: drive(bench, OTHER).requests - n0, 1) == 1  # motion starts are not
    finally:
        drive(bench, OTHER).silent = False


def test_reply_with_bad_crc_on_the_driver_bus(bench, m):
    # The jig checks the driver's reply and drops it, so the PC sees a timeout; a
    # bench that relayed it would give ReplyCRCError. Either way: CommError, retried.
    d = drive(bench)
    d.bad_crc = True
    m.timeout = 0.15
    try:
        n0 = d.requests
        with pytest.raises(E.CommError):
            m.get_command_pos(DRIVE)
        assert eventually(lambda: d.requests - n0, 1 + m.retries) == 1 + m.retries
    finally:
        d.bad_crc = False


def test_refused_move_0x85(m):
    m.servo_enable(DRIVE, False)
    with pytest.raises(E.MotionRefusedError) as exc:
        m.move_inc(DRIVE, 1000, FAST)
    assert exc.value.status == 0x85 and "slave 2" in str(exc.value)
    m.servo_enable(DRIVE, True)
    m.move_velocity(DRIVE, 10000, 1)
    with pytest.raises(E.MotionRefusedError):  # already moving
        m.move_abs(DRIVE, 0, FAST)
    m.move_stop(DRIVE)


def test_crc_error_status_0xaa(bench, m):
    d = drive(bench)
    d.force(F.STATUS_CRC_ERROR, frames=1)
    n0 = d.requests
    assert m.get_command_pos(DRIVE) == 0  # read: re-sent after the 0xAA status
    assert d.requests - n0 == 2 and d.force_status is None  # the forced answer was used up
    d.force(F.STATUS_CRC_ERROR, frames=1)
    n0 = d.requests
    with pytest.raises(E.RequestCRCError) as exc:  # motion start: reported, not re-sent
        m.move_inc(DRIVE, 1000, FAST)
    assert exc.value.status == 0xAA and "slave 2" in str(exc.value)
    assert eventually(lambda: d.requests - n0, 1) == 1
    assert not m.get_axis_status(DRIVE).motioning  # a drive that saw garbage did not move
    d.force(F.STATUS_CRC_ERROR)  # until cleared: every attempt gets 0xAA
    try:
        n0 = d.requests
        with pytest.raises(E.RequestCRCError):
            m.get_command_pos(DRIVE)
        assert d.requests - n0 == 1 + m.retries
    finally:
        d.force(None)
    assert m.get_command_pos(DRIVE) == 0


def test_corrupted_reply_on_the_pc_link(bench, m):
    """A bit flipped in the jig's reply on its way to the PC: ReplyCRCError, retried."""
    d = drive(bench)
    crc0 = m.parser.crc_errors
    bench.sim.corrupt_to_pc(1)
    n0 = d.requests
    assert m.get_command_pos(DRIVE) == 0  # the first reply fails its CRC; the re-sent one is good
    assert d.requests - n0 == 2 and m.parser.crc_errors - crc0 == 1
    bench.sim.corrupt_to_pc(1 + m.retries)
    n0 = d.requests
    with pytest.raises(E.ReplyCRCError) as exc:
        m.get_axis_status(DRIVE)
    assert "failed its CRC" in str(exc.value) and d.requests - n0 == 1 + m.retries
    # a motion start whose reply is lost is not re-sent: the drive did start moving
    bench.sim.corrupt_to_pc(1)
    n0 = d.requests
    with pytest.raises(E.ReplyCRCError):
        m.move_inc(DRIVE, 1000, FAST)
    assert d.requests - n0 == 1
    m.wait_motion_done(DRIVE, timeout=5)
    assert m.get_command_pos(DRIVE) == 1000
    # the jig's own replies travel the same link
    bench.sim.corrupt_to_pc(1)
    assert m.read_crash_log(JIG) == ""  # retried once, then the bench HAL's "no crash log"


def test_port_errors(bench, tmp_path):
    with pytest.raises(E.PortError) as exc:
        Master(str(tmp_path / "nope"))
    assert "does not exist" in str(exc.value)
    with Master(bench.pty_path):
        with pytest.raises(E.PortError) as exc:
            Master(bench.pty_path)
        assert "busy" in str(exc.value)


def test_two_threads_do_not_share_a_master_but_two_masters_share_tcp(bench, monkeypatch):
    # two TCP clients see each other's replies; matching keeps them apart
    monkeypatch.setattr(drive(bench, OTHER), "slave_type", 60)  # tell the two drives' replies apart
    wrong = []
    errors = []

    def worker(slave, want_type, n):
        try:
            with Master(bench.tcp_url, timeout=TIMEOUT) as mm:
                for _ in range(n):
                    got = mm.get_slave_info(slave).type
                    if got != want_type:
                        wrong.append((slave, got))
        except Exception as exc:  # reported below
            errors.append(exc)

    ts = [threading.Thread(target=worker, args=(s, t, 5)) for s, t in ((DRIVE, 20), (OTHER, 60))]
    for t in ts:
        t.start()
    for t in ts:
        t.join(30)
    # Two masters on one half-duplex bus collide: the jig aborts the older wait (a
    # timeout), or a request garbles a reply on the line (a CRC error) -- both are
    # reported as such. A reply taken for the wrong request never is.
    assert wrong == []
    assert all(isinstance(e, (E.NoReplyError, E.ReplyCRCError)) for e in errors), errors


def test_ver8_framing_through_the_jig():
    with Bench(driver_ids=(DRIVE,), baud=115200, ver8=True) as b, Master(b.tcp_url, ver8=True, timeout=TIMEOUT) as mm:
        assert mm.get_slave_info(DRIVE).type == 20
        assert mm.get_slave_info(JIG).type_name == "MotorJig bridge"
        mm.servo_enable(DRIVE, True)
        mm.set_parameter(DRIVE, 3, 5)
        mm.move_inc(DRIVE, 500, FAST)
        mm.wait_motion_done(DRIVE, timeout=5)
        assert mm.get_command_pos(DRIVE) == 500
        # the jig names a Ver8 request by the sync number it went out with
        assert mm.transaction_times(JIG)[-1][:2] == (DRIVE, mm.last_sync(DRIVE))
    with Bench(driver_ids=(DRIVE,), baud=115200) as b, Master(b.tcp_url, ver8=True, retries=0) as mm:
        with pytest.raises(E.NoReplyError):  # a Ver6 bus ignores Ver8 frames
            mm.get_slave_info(DRIVE)


def test_mixed_bus_variants_detected_per_slave():
    """Ver8 jig, a Ver6 and a Ver8 drive: Master finds each variant the vendor way and
    uses it per slave, including Ver8's 64-bit inputs and GetMotionStatus axis flags."""
    with Bench(driver_ids=(DRIVE, OTHER), baud=115200, jig_ver8=True, ver8_drivers=(OTHER,)) as b, \
            Master(b.tcp_url, timeout=TIMEOUT) as mm:
        found = mm.scan(range(0, 5), timeout=TIMEOUT)
        assert sorted(found) == [JIG, DRIVE, OTHER]
        assert mm.variants == {JIG: 8, DRIVE: 6, OTHER: 8}
        assert mm.detect_variant(DRIVE) == 6 and mm.detect_variant(OTHER) == 8
        assert found[OTHER].version.endswith("v8.0") and found[JIG].type_name == "MotorJig bridge"
        for s in (DRIVE, OTHER):
            mm.servo_enable(s, True)
            mm.set_parameter(s, 3, 5)
            mm.set_parameter(s, 4, 5)
            mm.move_inc(s, 300, FAST)
        for s in (DRIVE, OTHER):
            mm.wait_motion_done(s, timeout=5)
            assert mm.get_command_pos(s) == 300 and mm.get_all_status(s).command_pos == 300
        mm.set_io_input(OTHER, 1 << 40, 0)  # a Ver8 input word has 64 bits
        assert mm.get_io_input(OTHER) == 1 << 40
        assert mm.get_all_status(OTHER).inputs == 1 << 40
        assert mm.get_io_axis_status(OTHER).inputs == 1 << 40
        ms8, ms6 = mm.get_motion_status(OTHER), mm.get_motion_status(DRIVE)
        assert ms8.pt_number is None and ms8.axis.servo_on and ms6.axis is None and ms6.pt_number == 0
        # one broadcast per variant: both drives stop their jog
        for s in (DRIVE, OTHER):
            mm.move_velocity(s, 2000, 1)
        mm.all_move_stop()
        for s in (DRIVE, OTHER):
            assert not mm.wait_motion_done(s, timeout=5).motioning


def test_jig_trace_and_transaction_times(bench, m):
    """The jig samples the drive itself (0xF5-0xF8) while the PC moves it; the jig's clock
    dates the forwarded transactions (0xF9)."""
    import time

    assert m.trace_start(DRIVE, 5000) == 4096
    m.move_inc(DRIVE, 2000, FAST)
    time.sleep(0.3)
    samples = m.trace_read()
    st = m.trace_status()
    assert st["state"] == "running" and st["slave"] == DRIVE and st["period_us"] == 5000
    final = m.trace_stop()
    samples += m.trace_read()
    assert final["state"] == "off" and final["failed"] == 0 and len(samples) == final["taken"] >= 40
    t = [s.t_us for s in samples]
    gaps = sorted(b - a for a, b in zip(t, t[1:]))
    assert gaps[len(gaps) // 2] == 5000  # the jig's period, whatever this host's load
    assert samples[-1].command_pos == 2000 and not samples[-1].axis.motioning
    m.get_axis_status(OTHER)
    rows = m.transaction_times()
    assert rows[-1].slave == OTHER and rows[-1].b1 == F.GET_AXIS_STATUS and 0 < rows[-1].round_trip_us < 50000
    # the move command, dated by the jig on the samples' time base: after the first sample, before motion shows
    move = [r for r in rows if r.slave == DRIVE and r.b1 == F.MOVE_INC_POS][-1]
    t_move = m.trace_time_us(move.request_end)
    first_moving = next(s.t_us for s in samples if s.axis.motioning)
    assert samples[0].t_us <= t_move < first_moving <= t_move + 2 * 5000


def test_jig_trace_of_a_set_of_drives(bench, m):
    """Two drives joined to the jig's sampler (several slots moving): tagged samples of each, taken
    in turn, each drive's own figures, the last one out stops it (the station's tracehub)."""
    import time

    j = m.trace_join(DRIVE, 5000)
    assert j["started"] and j["set"] == [DRIVE]
    j2 = m.trace_join(OTHER, 5000)
    assert not j2["started"] and j2["set"] == [DRIVE, OTHER]
    time.sleep(0.3)
    rows, frm = [], j["first"]
    while True:
        _state, frm, chunk = m.trace_read_tagged(frm)
        rows += chunk
        if not chunk:
            break
    both = m.trace_drive_status(OTHER)
    assert both["state"] == "running" and both["set"] == [DRIVE, OTHER] and both["taken"] >= 20
    tags = [r[0] for r in rows]
    assert set(tags) == {DRIVE, OTHER} and abs(tags.count(DRIVE) - tags.count(OTHER)) <= 3  # in turn
    mine = m.trace_leave(DRIVE)
    assert mine["failed"] == 0 and mine["taken"] >= 20
    assert m.trace_leave(OTHER)["state"] == "off"  # the last one out stopped the sampler


def test_every_public_method_is_exercised():
    src = open(os.path.abspath(__file__)).read()
    called = set(re.findall(r"\bmm?\.(\w+)\(", src))
    public = {n for n in dir(Master) if not n.startswith("_") and callable(getattr(Master, n))}
    assert public - called == set()
