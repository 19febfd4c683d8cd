"""MotorJig Desk's logic without a browser: BusSession and the input checks, against the
real-time virtual bench in this process (the page only shows what these return)."""

import socket
import threading
import time

import pytest

from jig import frame as F
from jig.parser import FrameParser
from motorjig.desk import forms
from motorjig.desk.session import BusSession, UserError, wire_frame
from motorjig.master import Master
from motorjig.sim import Bench

TIMEOUT = 0.5  # generous: the bench runs in real time on a shared machine


@pytest.fixture(scope="module")
def bench():
    with Bench(driver_ids=(2, 3), baud=115200, pty=False) as b:
        yield b


@pytest.fixture
def s(bench):
    session = BusSession(timeout=TIMEOUT)
    session.connect(bench.tcp_url)
    session.scan(1, 3)
    yield session
    session.stop()


def poll_until(s, pred, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        s.poll_once()
        if s.status is not None and pred(s.status):
            return s.status
        time.sleep(0.02)
    raise AssertionError("the polled status never got there: %r" % (s.status,))


# --- input checks ---------------------------------------------------------------------------------
def test_numbers_from_fields():
    assert forms.number("1_000", "x") == 1000 and forms.number("0x10", "x") == 16 and forms.number(7.0, "x") == 7
    assert forms.number("", "x", blank=5) == 5
    for bad, msg in (("", "x is empty"), ("1.5", "not a whole number"), ("abc", "not a whole number"),
                     (7.5, "whole number")):
        with pytest.raises(forms.InputError, match=msg):
            forms.number(bad, "x")
    with pytest.raises(forms.InputError, match="speed must be 1..2500000, not 0"):
        forms.speed("0")
    with pytest.raises(forms.InputError, match="position must be -2147483648..2147483647"):
        forms.position(str(2 ** 31))
    assert forms.accel("", "accel") is None and forms.accel("250", "accel") == 250
    with pytest.raises(forms.InputError):
        forms.accel("10000", "accel")
    assert forms.hex_bytes("0x1, 40 aa", "d") == b"\x01\x40\xaa" and forms.hex_bytes("", "d") == b""
    with pytest.raises(forms.InputError, match="not hex bytes"):
        forms.hex_bytes("0g", "d")


def test_corrupt_crc_breaks_exactly_the_crc_of_every_frame():
    """All ids x frame types x a few payloads, including CRCs whose high byte is stuffed (0xAA)."""
    stuffed = 0
    for slave in range(16):
        for ftype in range(256):
            for data in (b"", bytes((ftype,)), b"\xaa\x00\x55"):
                wire = F.encode(slave, ftype, data)
                stuffed += wire[-4:-2] == b"\xaa\xaa"
                assert wire_frame(wire)[0] is not None
                fr, why = wire_frame(forms.corrupt_crc(wire))
                assert fr is None and why == "frame with a bad CRC", (slave, ftype, data, why)
    assert stuffed > 0  # the stuffed case was really exercised


# --- connection ----------------------------------------------------------------------------------------
def test_connect_errors_are_sentences(bench):
    s = BusSession(timeout=TIMEOUT)
    with pytest.raises(UserError, match="choose a serial port"):
        s.connect("  ")
    with pytest.raises(UserError, match="baud rate 12345 is not one the drives support"):
        s.connect(bench.tcp_url, 12345)
    free = socket.socket()
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()
    with pytest.raises(UserError, match="connection refused"):
        s.connect("socket://127.0.0.1:%d" % port)
    with pytest.raises(UserError, match="does not exist"):
        s.connect("/dev/ttyDOES-NOT-EXIST")
    assert s.state == "disconnected"
    with pytest.raises(UserError, match="not connected"):
        s.scan()


def test_a_busy_port_is_reported():
    with Bench(driver_ids=(2,), baud=115200, pty=True) as b:
        other = Master(b.pty_path)  # another program holds the port
        s = BusSession(timeout=TIMEOUT)
        try:
            with pytest.raises(UserError, match=r"port /dev/\S+ is busy \(another program has it open\)"):
                s.connect(b.pty_path)
        finally:
            other.close()
        assert s.connect(b.pty_path).startswith("connected to /dev/")
        s.stop()


def test_a_silent_port_is_reported():
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    try:
        s = BusSession(timeout=0.05)
        msg = s.connect("socket://127.0.0.1:%d" % server.getsockname()[1])
        assert "nothing answers on the bus" in msg and s.connected
        assert "silent port" in s.log_text()
        s.stop()
    finally:
        server.close()


def test_scan_finds_the_jig_and_both_drivers_and_picks_the_first_driver(s):
    assert sorted(s.slaves) == [1, 2, 3]
    assert s.slaves[1]["jig"] and s.slaves[1]["type"] == 200
    assert not s.slaves[2]["jig"] and s.slaves[2]["type_name"] == "Ezi-STEP Plus-R ST"
    assert s.axis == 2 and s.jig_id() == 1
    assert s.scan_progress is None
    assert ("scan: 3 slave(s) found: 1 MotorJig bridge (Ver6), 2 Ezi-STEP Plus-R ST (Ver6), 3 Ezi-STEP Plus-R ST "
            "(Ver6)") in s.log_text()


def test_scan_via_jig(s):
    rows = s.scan_via_jig()
    assert sorted(r["id"] for r in rows) == [1, 2, 3]
    assert "scan via jig: ids 2, 3 answered" in s.log_text()


# --- axis, motion, plot history -------------------------------------------------------------------------
def test_move_inc_is_polled_into_status_and_history(s):
    s.select_axis(3)
    s.servo(True)
    s.clear_position()
    s.history.clear()
    assert s.move("inc", "10000", "40000") == "slave 3: move inc 10000 at 40000 pps"
    st = poll_until(s, lambda st: st.actual_pos == 10000 and not st.axis >> 27 & 1)
    view = s.status_view()
    assert view["command_pos"] == 10000 and "servo_on" in view["flags"] and not view["errors"]
    rows = s.history_rows()
    assert rows[-1].actual_pos == 10000 and any(0 < r.actual_pos < 10000 for r in rows)
    assert any(r.actual_vel > 0 for r in rows)
    csv = s.history_csv().splitlines()
    assert csv[0] == "time,t_s,slave,command_pos,actual_pos,actual_vel_pps" and csv[-1].endswith(",3,10000,10000,0")
    first = csv[1].split(",")
    assert first[1] == "0.000" and first[0][10] == "T" and first[0][-6] in "+-"  # local ISO time with its offset
    assert len(csv) == len(rows) + 1


def test_move_with_accel_uses_the_ex_frame(s):
    s.select_axis(2)
    s.servo(True)
    s.clear_position()
    s.clear_log()
    s.move("abs", "-500", "40000", accel="20", decel="")
    poll_until(s, lambda st: st.command_pos == -500)
    assert "MoveAbsPosEx(0x%02X)" % F.MOVE_ABS_POS_EX in s.log_text()


def test_bad_input_sends_nothing(s):
    s.clear_log()
    for call, msg in ((lambda: s.move("inc", "10", "0"), "speed must be"),
                      (lambda: s.move("abs", "x", "100"), "not a whole number"),
                      (lambda: s.jog(1, "-5"), "jog speed must be"),
                      (lambda: s.write_param(2, "axis_acc_time", "10000"), "between 1 and 9999"),
                      (lambda: s.write_param(2, "no_such", "1"), "no parameter 'no_such'"),
                      (lambda: s.send_raw("16", "0x40"), "slave id must be 0..15")):
        with pytest.raises((UserError, forms.InputError), match=msg):
            call()
    assert "TX" not in s.log_text()


def test_the_jig_is_not_an_axis(s):
    s.select_axis(2)
    with pytest.raises(UserError, match="slave 1 is the jig, not a motor driver"):
        s.select_axis(1)
    assert s.axis == 2 and [r["id"] for r in s.drivers()] == [2, 3]
    assert s.param_table(1)[0] == "jig" and s.param_table()[0] == "drive"


def test_a_mixed_bus_is_scanned_in_each_slaves_variant():
    """A Ver8 jig, drive 2 Ver6, drive 3 Ver8 (`python -m motorjig.sim --drivers 2,3:v8 --jig-protocol 8`):
    detected per slave as `jigctl scan` does; the jig is never the axis; both drives answer."""
    with Bench(driver_ids=(2, 3), baud=115200, pty=False, jig_ver8=True, ver8_drivers=(3,)) as b:
        s = BusSession(timeout=TIMEOUT)
        try:
            s.connect(b.tcp_url)
            rows = {r["id"]: r for r in s.scan(1, 3)}
            assert [(i, r["type_name"], r["variant"], r["jig"]) for i, r in sorted(rows.items())] == [
                (1, "MotorJig bridge", 8, True), (2, "Ezi-STEP Plus-R ST", 6, False),
                (3, "Ezi-STEP Plus-R ST", 8, False)]
            assert s.axis == 2 and s.variant_of(3) == 8
            for axis in (3, 2):
                s.select_axis(axis)
                s.servo(True)
                s.clear_position()
                s.move("inc", "1000", "40000")
                poll_until(s, lambda st: st.command_pos == 1000)
            assert s.send_raw(3, "40") == "sent; 1 frame(s) received"  # framed in slave 3's Ver8
            assert s.counters()  # the Ver8 jig answers too
            s.connect(b.tcp_url, ver8=True)  # forced Ver8: only the Ver8 slaves answer
            assert sorted(r["id"] for r in s.scan(1, 3)) == [1, 3] and s.axis == 3
        finally:
            s.stop()


def test_move_dec_keeps_the_distance_as_typed_and_its_button(s):
    """What every tab and a reload show is the field, sign and Enter button of the move sent."""
    s.select_axis(2)
    s.servo(True)
    s.clear_position()
    seq = s.move_seq
    assert s.move("inc", "5000", "40000", sign=-1) == "slave 2: move inc -5000 at 40000 pps"
    poll_until(s, lambda st: st.command_pos == -5000)
    assert s.move_fields == {"target": "5000", "speed": "40000", "acc": "", "dec": ""}
    assert s.last_move == ("inc", -1) and s.move_seq == seq + 1
    with pytest.raises(forms.InputError):  # refused before anything is sent: the last move stays
        s.move("abs", "1", "0")
    assert s.last_move == ("inc", -1) and s.move_seq == seq + 1


def test_move_dec_never_moves_up_whatever_the_fields_sign(s):
    """Issue 31: MOVE DEC with -5000 in the field moved the axis up by 5000."""
    s.select_axis(2)
    s.servo(True)
    s.clear_position()
    assert s.move("inc", "-5000", "40000", sign=-1) == "slave 2: move inc -5000 at 40000 pps"
    poll_until(s, lambda st: st.command_pos == -5000)
    assert s.move_fields["target"] == "-5000"  # kept as typed


def test_emergency_stop_ends_a_running_motion_test(s):
    s.select_axis(2)
    s.servo(True)
    result = {}
    t = threading.Thread(target=lambda: result.setdefault("summary", s.run_motion_test(50, 20000, 5000)))
    t.start()
    poll_until(s, lambda st: st.axis >> 27 & 1)  # moving
    s.emergency_stop()
    t.join(10)
    assert not t.is_alive()
    assert result["summary"].startswith("FAIL") and result["summary"].endswith("(stopped)")
    assert len(s.motion_test["moves"]) < 100
    st = poll_until(s, lambda st: not st.axis >> 27 & 1)
    assert st.axis >> 16 & 1  # emergency_stop flag
    s.alarm_reset()


def test_motion_test_passes(s):
    s.select_axis(2)
    s.servo(True)
    assert s.run_motion_test(2, 3000, 40000) == "PASS: 4 of 4 moves passed"
    assert [m["distance"] for m in s.motion_test["moves"]] == [3000, -3000, 3000, -3000]


def test_polling_waits_while_a_command_holds_the_bus(s):
    """The poller never interleaves with a command: it skips while the lock is held."""
    polls = s.polls
    with s._lock:
        done = []
        t = threading.Thread(target=lambda: done.append(s.poll_once()))
        t.start()
        t.join(2)
        assert done == [False]
    assert s.poll_once() and s.polls == polls + 1


def test_many_threads_share_one_connection(s):
    """Commands from several 'tabs' and the poller at once: every reply matches its request."""
    s.select_axis(2)
    errors = []

    def tab(n):
        try:
            for _ in range(15):
                assert s.param_table(2)[0] == "drive"
                s._bus(lambda m: m.get_parameter(2, 3))
                s.poll_once()
        except Exception as exc:  # collected, asserted below
            errors.append(exc)

    threads = [threading.Thread(target=tab, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert errors == []
    assert s.master.parser.crc_errors == 0


# --- parameters, I/O, diagnostics, raw ---------------------------------------------------------------------
def test_parameter_round_trip_and_rom(s):
    which, rows = s.read_params(2)
    assert which == "drive" and len(rows) == 29
    row3 = rows[3]
    assert row3["name"] == "axis_acc_time" and row3["range"] == "1..9999"
    assert s.write_param(2, "3", "321") == 321
    assert dict((r["number"], r) for r in s.read_params(2)[1])[3]["ram"] == 321
    which, jig_rows = s.read_params(1)
    assert which == "jig" and jig_rows[3]["name"] == "reply_timeout_ms"
    s.write_param(2, "axis_acc_time", 5)


def test_outputs_and_inputs(s):
    ins, outs = s.io_bits(2)
    assert [n for _, n, _ in ins][:3] == ["limit_plus", "limit_minus", "origin"]
    s.set_output(2, 15, True)  # user_out0
    assert dict((n, on) for _, n, on in s.io_bits(2)[1])["user_out0"]
    s.set_output(2, 15, False)
    assert not dict((n, on) for _, n, on in s.io_bits(2)[1])["user_out0"]
    jig_in, jig_out = s.io_bits(1)
    assert [n for _, n, _ in jig_out][:2] == ["out0", "out1"]


def test_jig_diagnostics(s):
    c = s.counters()
    assert c["up_frames_in"] > 0 and "up_crc_errors" in c
    s.reset_counters()
    assert s.counters()["local_errors"] == 0
    assert "no crash recorded" in s.crash_log()
    s.scan_via_jig()
    assert s.bus_scan_result().startswith("done: id 2 type 20, id 3 type 20")


def test_raw_frames_are_logged_decoded_and_a_bad_crc_as_such(s, bench):
    s.clear_log()
    assert s.send_raw("2", "0x40") == "sent; 1 frame(s) received"
    log = s.log_text()
    assert "TX    request   id 2  GetAxisStatus(0x40)" in log and "RX    reply     id 2  GetAxisStatus(0x40)" in log
    crc_before = s.counters()["up_crc_errors"]
    s.clear_log()
    assert s.send_raw("1", "0x01", corrupt=True) == "sent; no frame came back"
    log = s.log_text()
    assert "(frame with a bad CRC: the receiver will drop it)" in log and "no frame came back within 500 ms" in log
    assert s.counters()["up_crc_errors"] == crc_before + 1  # and the jig counted it
    # A reply that arrives broken is logged as a line error.
    s.clear_log()
    bench.sim.corrupt_to_pc(1)
    s.send_raw("1", "0x01")
    assert "received 1 frame with a bad CRC" in s.log_text()
    # Wire bytes as typed go out unchanged.
    s.clear_log()
    wire = F.encode(2, F.GET_AXIS_STATUS, b"")
    s.send_raw("", "", wire_hex=wire.hex(" "))
    assert "[wire %s]" % wire.hex(" ") in s.log_text()


def test_the_log_keeps_order_and_can_be_read_incrementally(s):
    s.clear_log()
    s.log("info", "one")
    first = s.log_since(0)
    s.log("info", "two")
    assert [e.text for e in s.log_since(first[-1].seq)] == ["two"]
    assert s.log_text().splitlines()[-1].endswith("INFO  two")


def test_bench_gone_means_connection_lost(bench):
    with Bench(driver_ids=(2,), baud=115200, pty=False) as b2:
        s = BusSession(timeout=TIMEOUT)
        s.connect(b2.tcp_url)
        s.select_axis(2)
        assert s.poll_once()
    # b2 is stopped: its socket is closed
    end = time.monotonic() + 5
    while s.state != "lost" and time.monotonic() < end:
        s.poll_once()
        time.sleep(0.05)
    assert s.state == "lost"
    assert s.lost_message().startswith("connection lost: ") and "Reconnect" in s.lost_message()
    with pytest.raises(UserError, match="connection lost"):
        s.servo(True)
    with pytest.raises(UserError, match="connection refused"):
        s.reconnect()
    s.stop()


def test_frame_parser_agrees_with_wire_frame():
    wire = F.encode(2, F.MOVE_INC_POS, b"\x10\x27\x00\x00\x88\x13\x00\x00")
    fr, why = wire_frame(wire)
    p = FrameParser()
    p.feed(wire)
    assert why is None and fr.slave == 2 and fr.ftype == F.MOVE_INC_POS and fr.data == bytes(p.body[p.data_start:p.data_end])
    assert wire_frame(wire[:-2]) == (None, "not a complete frame")


def test_a_jog_released_before_it_reached_the_bus_never_starts(s):
    s.select_axis(2)
    s.servo(True)
    with s._lock:  # the press waits for the bus; the release comes first
        gen_before = s._jog_gen
        t = threading.Thread(target=s.jog, args=(1, "3000"))
        t.start()
        time.sleep(0.1)
        s._jog_gen += 1  # what jog_release does before it queues its stop
    t.join(5)
    assert s._jog_gen == gen_before + 1
    time.sleep(0.2)
    st = poll_until(s, lambda st: True)
    assert not st.axis >> 27 & 1  # not moving
    s.jog(1, "3000")
    poll_until(s, lambda st: st.axis >> 27 & 1)
    s.jog_release()
    poll_until(s, lambda st: not st.axis >> 27 & 1)


def test_the_poller_runs_only_while_a_page_is_open(s):
    s.select_axis(2)
    s.start()
    time.sleep(0.3)
    assert s.viewers == 0 and s.polls == 0
    s.viewers = 1
    end = time.monotonic() + 5
    while s.polls < 5 and time.monotonic() < end:
        time.sleep(0.05)
    assert s.polls >= 5 and s.status is not None
    s.viewers = 0
    time.sleep(0.2)
    polls = s.polls
    time.sleep(0.3)
    assert s.polls == polls


def test_one_motion_test_at_a_time_and_stop_ends_it(s):
    s.select_axis(3)
    s.servo(True)
    t = threading.Thread(target=s.run_motion_test, args=(50, 20000, 5000))
    t.start()
    end = time.monotonic() + 5
    while not s.motion_test["running"] and time.monotonic() < end:
        time.sleep(0.01)
    with pytest.raises(UserError, match="a motion test is already running"):
        s.run_motion_test(1, 100, 1000)
    s.stop_axis()
    t.join(15)
    assert not t.is_alive() and s.motion_test["summary"].endswith("(stopped)")


# --- read-only, lending the port, the decoder's pairing ----------------------------------------------------
def test_a_read_only_session_polls_and_refuses_everything_else(s):
    s.read_only = True
    try:
        assert s.poll_once()
        for what, fn in (("Move", lambda: s.move("inc", 100, 1000)), ("Servo on/off", lambda: s.servo(True)),
                         ("EMERGENCY STOP", s.emergency_stop), ("STOP AXIS", s.stop_axis),
                         ("Sending a raw frame", lambda: s.send_raw("2", "40")),
                         ("Writing a parameter", lambda: s.write_param(2, 3, 100)),
                         ("The motion test", lambda: s.run_motion_test(1, 100, 1000)),
                         ("Connect", lambda: s.connect("socket://127.0.0.1:1")), ("Scan", s.scan)):
            with pytest.raises(UserError, match="^%s refused: this Desk is read-only" % what):
                fn()
        with pytest.raises(UserError, match="read-only"):
            s.lend_port("a test run", lambda: None)
        with pytest.raises(UserError, match="read-only"):  # the bus itself refuses too
            s._bus(lambda m: m.servo_enable(2, True))
        assert s.select_axis(3) == 3 and s.poll_once() and s.status_view() is not None  # watching another axis
        assert s.reconnect().startswith("connected to ") and s.connected  # opening the port sends no move
        assert s.axis == 3 and s.poll_once()
    finally:
        s.read_only = False


def test_a_read_only_session_reconnects_by_itself():
    from desk_browser import free_port

    port = free_port()
    b = Bench(driver_ids=(2,), baud=115200, pty=False, tcp_port=port).start()
    s = BusSession(timeout=TIMEOUT, poll_interval=0.02)
    try:
        s.connect(b.tcp_url)
        s.scan(1, 2)
        s.read_only = True
        s.viewers = 1
        s.start()
        b.stop()
        end = time.monotonic() + 5
        while s.state != "lost" and time.monotonic() < end:
            time.sleep(0.05)
        assert s.state == "lost"
        b = Bench(driver_ids=(2,), baud=115200, pty=False, tcp_port=port).start()
        end = time.monotonic() + 10
        while not (s.connected and s.status is not None) and time.monotonic() < end:
            time.sleep(0.05)
        assert s.connected and s.status is not None and s.axis == 2
    finally:
        s.stop()
        b.stop()


def test_the_desk_says_once_what_the_jigs_safety_stop_did_before_it_connected():
    """Issue 31: after a killed run the Desk's header tells the next user what the jig stopped."""
    with Bench(driver_ids=(2,), baud=115200, pty=False) as b:
        with Master(b.tcp_url, timeout=0.3) as m:  # a run's lease, then its master falls silent
            m.set_parameter(1, 10, 1)
            m.set_parameter(1, 9, 200)
            m.servo_enable(2, True)
            m.move_velocity(2, 2000, 1)
        time.sleep(1.0)
        s = BusSession(timeout=TIMEOUT, poll_interval=0.02)
        try:
            s.connect(b.tcp_url)
            assert s.safety_notice.startswith("the jig stopped drive 2 after the run's master went silent at")
            assert any("note: the jig stopped drive 2" in line for line in s.log_text().splitlines())
            s.safety_notice = ""
            s.connect(b.tcp_url)
            assert s.safety_notice == ""  # said once
        finally:
            s.stop()


def test_a_read_only_desks_reconnect_does_not_send_the_user_to_scan():
    """Issue 31: its reconnect toast said "press Scan to find the slaves", which it refuses."""
    with Bench(driver_ids=(2,), baud=115200, pty=False) as b:
        s = BusSession(timeout=TIMEOUT, poll_interval=0.02)
        try:
            assert "press Scan" in s.connect(b.tcp_url)
            s.read_only = True
            said = s.reconnect()
            assert said.startswith("connected to %s" % b.tcp_url) and "Scan" not in said, said
        finally:
            s.stop()


def test_a_read_only_desk_whose_port_did_not_open_connects_once_it_does():
    from desk_browser import free_port

    port = free_port()
    s = BusSession(timeout=TIMEOUT, poll_interval=0.02)
    s.read_only = True
    s.watch("socket://127.0.0.1:%d" % port, 115200, None, "connection refused")
    assert s.state == "lost"
    s.viewers = 1
    s.start()
    try:
        with Bench(driver_ids=(2, 3), baud=115200, pty=False, tcp_port=port):
            end = time.monotonic() + 15
            while not (s.connected and s.status is not None) and time.monotonic() < end:
                time.sleep(0.05)
            assert s.connected and sorted(s.slaves) == [1, 2, 3] and s.axis == 2  # scanned once, as at start
    finally:
        s.stop()


def test_lending_the_port_pauses_everything_and_stop_aborts_the_borrower(s, bench):
    aborted = []
    url, baud = s.lend_port("the test run (smoke)", lambda: aborted.append(1))
    try:
        assert (url, baud) == (bench.tcp_url, 115200) and s.state == "lent" and s.master is None
        assert not s.poll_once()
        with pytest.raises(UserError, match=r"the port is with the test run \(smoke\): wait until it ends"):
            s.servo(True)
        with pytest.raises(UserError, match="the port is with"):
            s.connect(bench.tcp_url)
        assert s.emergency_stop() == "test run aborted: emergency stop and servo off" and aborted == [1]
        assert s.stop_axis().startswith("test run aborted") and aborted == [1, 1]
    finally:
        assert s.take_port_back() == "connected to %s again" % bench.tcp_url
    assert s.state == "connected" and s.poll_once()
    log = s.log_text()
    assert "port %s handed to the test run (smoke)" % bench.tcp_url in log and "back from the test run" in log


def test_the_decoder_pairs_a_sniffed_reply_with_its_request():
    from motorjig.decode import PAIR_SECONDS, Decoder
    from motorjig.master import Frame

    def fr(slave, ftype, data, t, sync=-1):
        return Frame(slave, sync, ftype, bytes(data), b"", t)

    dec = Decoder()
    # ServoEnable off and its reply are the same bytes: the first is the request, the second its reply
    assert dec.classify(fr(2, F.SERVO_ENABLE, b"\x00", 1.0)) == "request"
    assert dec.classify(fr(2, F.SERVO_ENABLE, b"\x00", 1.002)) == "reply"
    # a known direction is remembered: the master's own request pairs with what comes back
    dec.as_dict(fr(3, F.SERVO_ENABLE, b"\x00", 2.0), "request")
    assert dec.classify(fr(3, F.SERVO_ENABLE, b"\x00", 2.003)) == "reply"
    # a request that got no answer does not make a much later frame its reply
    assert dec.classify(fr(4, F.SERVO_ENABLE, b"\x00", 3.0)) == "request"
    assert dec.classify(fr(4, F.SERVO_ENABLE, b"\x00", 3.0 + PAIR_SECONDS + 1)) == "request"
    # Ver8: the reply carries its request's sync number
    assert dec.classify(fr(5, F.SERVO_ENABLE, b"\x00", 4.0, sync=0xF3)) == "request"
    assert dec.classify(fr(5, F.SERVO_ENABLE, b"\x00", 4.001, sync=0xF4)) == "request"
    assert dec.classify(fr(5, F.SERVO_ENABLE, b"\x00", 4.002, sync=0xF4)) == "reply"
    # a reply whose request was not seen is still told by its shape
    assert Decoder().classify(fr(2, F.MOVE_INC_POS, b"\x85", 5.0)) == "reply"


def test_frame_types_are_hex_and_a_motion_test_distance_is_not_0():
    assert [forms.hex_byte(t, "frame type") for t in ("40", "2A", "0x40", "0X2a", " f ", "ff")] == \
        [0x40, 0x2A, 0x40, 0x2A, 0x0F, 0xFF]
    for bad in ("", "140", "0x", "zz", "4 0", "-1"):
        with pytest.raises(forms.InputError, match="frame type"):
            forms.hex_byte(bad, "frame type")
    assert forms.distance("-2000") == -2000
    with pytest.raises(forms.InputError, match="distance must not be 0"):
        forms.distance("0")


def test_the_test_tabs_station_lists_plans_serves_run_files_and_counts_todays_yield(tmp_path):
    import json
    import os

    from motorjig.desk.testrun import Station

    plans = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "plans")
    st = Station(BusSession(), plans_dir=plans, out_dir=str(tmp_path))
    names = [e.file for e in st.plans()]
    assert "smoke.toml" in names and "ezi-step-eol.toml" in names
    assert "ezi-step-golden.toml" not in names  # a parameter set, not a plan
    now = time.time() * 1000
    for i, (dut, verdict) in enumerate((("A", "FAIL"), ("A", "PASS"), ("B", "PASS"), ("C", "ABORTED"))):
        record = {"start_time_millis": now + i, "end_time_millis": now + i + 500, "outcome": verdict,
                  "dut_id": dut, "station_id": "s", "metadata": {"test_name": "smoke", "operator": "anna"},
                  "phases": [{"name": "out", "outcome": "FAIL" if verdict == "FAIL" else "PASS"}]}
        (tmp_path / ("smoke_%s_%d.json" % (dut, i))).write_text(json.dumps(record))
    (tmp_path / "smoke_A_1.html").write_text("<html>report</html>")
    y = st.yield_today("smoke")
    assert (y["runs"], y["PASS"], y["FAIL"], y["ABORTED"], y["duts"], y["first_pass"]) == (4, 2, 1, 1, 3, 1)
    assert y["yield_pct"] == 33.3 and st.yield_today("other")["runs"] == 0
    rows = st.recent_runs()
    assert [r["dut"] for r in rows] == ["C", "B", "A", "A"] and rows[3]["failed"] == "out"
    assert rows[2]["report"] == "/runs/smoke_A_1.html" and rows[3]["report"] == ""
    assert st.file_path("smoke_A_1.html") == str(tmp_path / "smoke_A_1.html")
    for bad in ("../smoke_A_1.html", "x/smoke_A_1.html", ".smoke.html", "smoke_A_1.toml", "missing.html"):
        assert st.file_path(bad) is None, bad
    with pytest.raises(UserError, match="a plan is a .toml file"):
        st.add_upload("plan.txt", b"")
    assert st.add_upload("../up.toml", b"[parameters]\n").startswith("up.toml kept beside the uploaded plans")
    assert os.listdir(st.upload_dir) == ["up.toml"]  # a path in the name is dropped: it stays in the folder


# --- the Test tab's station on the engine (no browser) ---------------------------------------------
SERVO_PLAN = """\
[plan]
name = "quick"
version = "1.0"

[drive]
slave = 2
protocol = [6, 8]
slave_type = 20

[[steps]]
kind = "servo"
on = true

[[steps]]
kind = "servo"
name = "servo_off"
on = false
"""

LONG_MOVE_PLAN = """\
[plan]
name = "long-move"
version = "1.0"

[drive]
slave = 2
protocol = [6, 8]
slave_type = 20

[[steps]]
kind = "servo"
on = true

[[steps]]
kind = "move"
name = "long"
mode = "inc"
distance = 200000
speed = 5000
timeout_s = 60
"""

GOLDEN = """\
[drive]
slave_type = 20

[parameters]
axis_acc_time = %d
"""

PARAMS_PLAN = """\
[plan]
name = "params"
version = "1.0"

[drive]
slave = 2
protocol = [6, 8]
slave_type = 20

[[steps]]
kind = "parameters"
mode = "verify"
file = "golden.toml"
memory = "ram"
"""


def wait_for(pred, timeout, what):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = pred()
        if got:
            return got
        time.sleep(0.02)
    raise AssertionError("never happened: " + what)


def station_on(tmp_path, url, plans, **kw):
    """A connected BusSession and a Station whose plans folder holds ``plans`` ({file: text})."""
    from motorjig.desk.testrun import Station

    folder = tmp_path / "plans"
    folder.mkdir(exist_ok=True)
    for name, text in plans.items():
        (folder / name).write_text(text)
    session = BusSession(timeout=TIMEOUT)
    session.connect(url)
    return session, Station(session, plans_dir=str(folder), out_dir=str(tmp_path / "out"), **kw)


def earlier_today_ms(ago_ms):
    """A time ago_ms before now in ms, but never before today's local midnight (a test
    that counts today's runs, run just after midnight, would date them yesterday)."""
    import datetime

    now = time.time()
    midnight = datetime.datetime.combine(datetime.date.fromtimestamp(now), datetime.time()).timestamp()
    return int(max(now * 1000 - ago_ms, midnight * 1000 + 1))


def stored_record(dut, station, start_ms, verdict="PASS", plan="smoke"):
    return {"dut_id": dut, "station_id": station, "start_time_millis": start_ms, "end_time_millis": start_ms + 500,
            "outcome": verdict, "metadata": {"test_name": plan, "test_version": "1.0", "operator": "anna"},
            "phases": [{"name": "out", "outcome": verdict, "start_time_millis": start_ms,
                        "end_time_millis": start_ms + 500, "measurements": {}}]}


@pytest.fixture
def bench_process():
    """A bench in a process of its own (drive 2): the Desk's shutdown path is not helped by ours."""
    import desk_browser as B

    proc, url = B.start_bench("2", "--duration", "60")
    try:
        yield url
    finally:
        B.stop(proc)


def test_stopping_the_desk_during_a_move_waits_until_the_axis_stands_with_the_servo_off(tmp_path, bench_process):
    from motorjig.desk import server

    session, st = station_on(tmp_path, bench_process, {"long-move.toml": LONG_MOVE_PLAN}, station="desk-stop")
    st.start(str(tmp_path / "plans" / "long-move.toml"), "SN-STOP")
    run = st.run
    wait_for(lambda: len(run.samples_of("long")) > 10, 20, "the long move running")
    assert run.samples_of("long")[-1][3] != 0  # moving (the samples' velocity)
    server.stop_desk(session, st)  # what the server's shutdown runs, before the process exits
    assert run.verdict == "ABORTED" and not st._worker.is_alive()
    with Master(bench_process, timeout=TIMEOUT) as m:
        first = m.get_all_status(2)
        time.sleep(0.2)
        again = m.get_all_status(2)
    flags = set(first.axis.flags)
    assert "motioning" not in flags and "servo_on" not in flags, flags
    assert again.actual_pos == first.actual_pos and 0 < first.actual_pos < 200000


def test_a_second_run_starts_right_after_the_verdict(tmp_path, bench):
    session, st = station_on(tmp_path, bench.tcp_url, {"quick.toml": SERVO_PLAN})
    slow_open = session.master_factory

    def slow(*a, **kw):  # a port that takes its time to open again (a USB adapter, a busy machine)
        m = slow_open(*a, **kw)
        time.sleep(0.5)
        return m

    session.master_factory = slow
    try:
        key = str(tmp_path / "plans" / "quick.toml")
        for serial in ("SN-Q1", "SN-Q2"):
            st.start(key, serial)  # the second: as soon as the first's verdict is shown
            run = st.run
            assert wait_for(lambda: run.verdict, 20, "the verdict of %s" % serial) == "PASS", run.details
            assert session.state == "connected"
    finally:
        session.stop()


def test_a_changed_parameter_set_is_read_again(tmp_path):
    import os

    session = BusSession()
    golden = tmp_path / "plans" / "golden.toml"
    golden.parent.mkdir()
    golden.write_text(GOLDEN % 100)
    (tmp_path / "plans" / "params.toml").write_text(PARAMS_PLAN)
    from motorjig.desk.testrun import Station

    st = Station(session, plans_dir=str(tmp_path / "plans"), out_dir=str(tmp_path / "out"))
    key = str(tmp_path / "plans" / "params.toml")
    before = st.find_plan(key)
    assert before.plan.paramsets[str(golden)].values[3] == 100
    assert st.find_plan(key) is before  # unchanged files: not read again
    golden.write_text(GOLDEN % 250)
    later = os.stat(golden).st_mtime + 5
    os.utime(golden, (later, later))  # the edit, whatever the file system's clock resolution
    after = st.find_plan(key)
    assert after.plan.paramsets[str(golden)].values[3] == 250
    assert after.plan.hash != before.plan.hash
    golden.unlink()  # gone: the plan does not load any more, and says why
    assert "golden.toml" in st.find_plan(key).error
    golden.write_text(GOLDEN % 100)  # back: it loads again
    assert st.find_plan(key).plan.hash == before.plan.hash


def test_the_recent_runs_are_this_stations_on_a_shared_database(tmp_path):
    from motorjig.desk.testrun import Station
    from motorjig.station.store import open_store

    now = earlier_today_ms(600000)
    mine = [stored_record("M%d" % k, "desk-1", now + k, "FAIL" if k == 0 else "PASS") for k in range(3)]
    others = [stored_record("O%d" % k, "line-%d" % (k % 4), now + 1000 + k) for k in range(250)]
    with open_store(str(tmp_path / "line.sqlite")) as store:
        store.add_runs(mine + others)  # the other stations' runs are newer than all of ours
        st = Station(BusSession(), plans_dir=str(tmp_path), out_dir=str(tmp_path / "out"), station="desk-1",
                     store=store)
        rows = st.recent_runs()
        assert [r["dut"] for r in rows] == ["M2", "M1", "M0"] and st.records_error == ""
        assert rows[2]["verdict"] == "FAIL" and rows[2]["failed"] == "out"
        y = st.yield_today("smoke")
        assert (y["runs"], y["duts"], y["PASS"], y["FAIL"]) == (3, 3, 2, 1)


def test_a_stored_report_is_served_only_from_the_output_folder(tmp_path):
    import os

    from motorjig.desk.testrun import Station
    from motorjig.station.store import open_store

    out = tmp_path / "out"
    out.mkdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (out / "good.html").write_text("<html>report</html>")
    (out / "record.json").write_text("{}")
    (elsewhere / "secret.html").write_text("<html>not the Desk's</html>")
    os.symlink(str(elsewhere / "secret.html"), str(out / "link.html"))
    (tmp_path / "secret.txt").write_text("a key")
    files = {"good": str(out / "good.html"), "json": str(out / "record.json"),
             "outside": str(elsewhere / "secret.html"), "link": str(out / "link.html"),
             "up": str(out / ".." / "secret.txt"), "dotdot": str(out / ".." / "elsewhere" / "secret.html")}
    now = int(time.time() * 1000)
    with open_store(str(tmp_path / "r.sqlite")) as store:
        ids = {k: store.add_run(stored_record(k, "desk-1", now + i), {"html": path})
               for i, (k, path) in enumerate(files.items())}
        st = Station(BusSession(), plans_dir=str(tmp_path), out_dir=str(out), station="desk-1", store=store)
        assert st.report_path(ids["good"]) == str(out / "good.html")
        for bad in ("json", "outside", "link", "up", "dotdot"):
            assert st.report_path(ids[bad]) is None, bad
        assert st.report_path(999) is None and st.report_path("x") is None
        reports = {r["dut"]: r["report"] for r in st.recent_runs()}
        assert reports["good"] == "/report/%d" % ids["good"] and reports["outside"] == ""


# --- multi-up: the Test tab's slots (--slots) ---------------------------------------------------------
PROMPT_PLAN = """\
[plan]
name = "put-in"
version = "1.0"

[drive]
slave = 2
protocol = [6, 8]
slave_type = 20

[[steps]]
kind = "prompt"
message = "Put the drive in its nest, then confirm"

[[steps]]
kind = "servo"
on = true

[[steps]]
kind = "servo"
name = "servo_off"
on = false
"""


def answer_prompts(st, multi, count):
    """Answer ``count`` prompts of the slots' runs as they come; returns their messages."""
    messages, last = [], None
    for _ in range(count):
        prompt = wait_for(lambda: (lambda p: p if p is not None and p["id"] != last else None)(multi.prompt()), 20,
                          "a slot's prompt")
        messages.append(prompt["message"])
        last = prompt["id"]
        assert st.answer(prompt["id"], True) == "confirmed"
    return messages


def test_the_slots_run_at_once_each_with_its_prompt_serial_verdict_and_records(tmp_path, bench):
    from motorjig.station.store import open_store

    store = open_store(str(tmp_path / "results.sqlite"))
    session, st = station_on(tmp_path, bench.tcp_url, {"put-in.toml": PROMPT_PLAN}, slots="2,3", station="desk-mu",
                             store=store)
    try:
        key = str(tmp_path / "plans" / "put-in.toml")
        slots, why = st.slots(key)
        assert [s.describe() for s in slots] == ["slot 1 (slave 2)", "slot 2 (slave 3)"] and why == ""
        with pytest.raises(UserError, match=r"slot 2 \(slave 3\): serial number 'S 2'"):
            st.start_slots(key, {"1": "SN-MU-1", "2": "S 2"})
        assert session.state == "connected"  # refused before the port was lent
        assert st.start_slots(key, {"1": "SN-MU-1", "2": "SN-MU-2"}) == "test put-in started in 2 slots"
        multi = st.run
        messages = answer_prompts(st, multi, 2)
        assert sorted(messages) == ["slot 1 (slave 2): Put the drive in its nest, then confirm",
                                    "slot 2 (slave 3): Put the drive in its nest, then confirm"]
        wait_for(lambda: not multi.running, 30, "both verdicts")
        assert {n: (r.verdict, r.dut_id) for n, r in multi.runs.items()} == {
            "1": ("PASS", "SN-MU-1"), "2": ("PASS", "SN-MU-2")}, [r.details for r in multi.runs.values()]
        assert multi.verdict == "PASS" and session.state == "connected"
        assert [r["state"] for r in multi.runs["2"].snapshot()["steps"]] == ["pass"] * 4
        # the records name their slot; the runs list is filtered by it
        rows = wait_for(lambda: st.recent_runs() if len(st.recent_runs()) == 2 else None, 5, "two records")
        assert sorted((r["slot"], r["dut"]) for r in rows) == [("1", "SN-MU-1"), ("2", "SN-MU-2")]
        assert [r["dut"] for r in st.recent_runs(slot="2")] == ["SN-MU-2"] and st.recent_runs(slot="9") == []
        assert st.run_slots(key) == ["1", "2"]
        # one slot alone: the other keeps its last run
        assert st.start_slots(key, {"2": "SN-MU-3"}, only="2") == "test put-in started in slot 2"
        again = st.run
        assert list(again.runs) == ["2"]
        assert answer_prompts(st, again, 1) == ["slot 2 (slave 3): Put the drive in its nest, then confirm"]
        wait_for(lambda: not again.running, 30, "slot 2's verdict")
        assert again.runs["2"].verdict == "PASS" and st.slot_runs["1"] is multi.runs["1"]
        assert st.slot_runs["2"] is again.runs["2"]
        assert [r["dut"] for r in st.recent_runs(slot="2")] == ["SN-MU-3", "SN-MU-2"]
        assert st.records_error == ""
    finally:
        session.stop()
        store.close()


def test_abort_stops_every_slot(tmp_path, bench):
    # sampled by the PC: the jig samples one axis at a time (both slots move at once here)
    plan = LONG_MOVE_PLAN.replace('version = "1.0"\n', 'version = "1.0"\nsampling = "pc"\n', 1)
    session, st = station_on(tmp_path, bench.tcp_url, {"long-move.toml": plan}, slots="2,3",
                             station="desk-mu-abort")
    try:
        key = str(tmp_path / "plans" / "long-move.toml")
        st.start_slots(key, {})
        multi = st.run
        for name in ("1", "2"):
            wait_for(lambda: len(multi.runs[name].samples_of("long")) > 5, 20, "slot %s moving" % name)
        assert session.emergency_stop() == "test run aborted: emergency stop and servo off"  # the header's
        wait_for(lambda: not multi.running, 20, "the verdicts")
        assert [r.verdict for r in multi.runs.values()] == ["ABORTED", "ABORTED"]
        assert multi.verdict == "ERROR"  # neither PASS nor FAIL: nobody could judge them
        for run in multi.runs.values():
            assert {r["name"]: r["state"] for r in run.snapshot()["steps"]}["long"] == "aborted"
        for slave in (2, 3):
            drive = bench.sim.drivers[slave]
            assert not drive.servo_on and drive.estop, slave
        assert session.state == "connected"
    finally:
        session.stop()


def test_a_slots_file_names_its_slots_and_a_missing_serial_is_asked_for(tmp_path):
    import os

    from motorjig.desk.testrun import Station

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    spec = tmp_path / "two-up.toml"
    spec.write_text('[[slot]]\nname = "A1"\nslave = 4\nserial = "ask"\nwiring = "%s"\n\n'
                    '[[slot]]\nname = "A2"\nslave = 5\nwiring = "%s"\n'
                    % tuple(os.path.join(root, "plans", "multiup", "fixture-%d.toml" % i) for i in (1, 2)))
    st = Station(BusSession(), plans_dir=os.path.join(root, "plans"), out_dir=str(tmp_path / "out"),
                 slots=str(spec))
    key = os.path.join(root, "plans", "ezi-step-eol.toml")
    slots, why = st.slots(key)
    assert why == "" and [s.describe() for s in slots] == ["slot A1 (slave 4)", "slot A2 (slave 5)"]
    assert st.slots(key)[0] is slots  # unchanged files: not read again
    with pytest.raises(UserError, match=r"slot A1 \(slave 4\): scan or type its serial number"):
        st.start_slots(key, {"A2": "SN-2"})
    spec.write_text('[[slot]]\nslave = 4\n\n[[slot]]\nslave = 4\n')
    later = os.stat(spec).st_mtime + 5
    os.utime(spec, (later, later))
    slots, why = st.slots(key)
    assert slots == [] and "one drive" in why
