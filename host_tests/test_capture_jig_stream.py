"""The jig's record stream read by motorjig.capture.jigstream: every record type, ticks
unwrapped across the 2**30 wrap, lost and noise reports, losing step and finding it
again, any chunking; then streams the real firmware recorded on the bench (both
loops), with lost records from a ring that filled up.

Streams are built from the documented format (test_capture_jig_support.raw), so
the reader is checked against docs/capture.md; the bench streams check both
against jig.capture.
"""

import struct

import pytest

from test_capture_jig_support import (EPOCH_US, PERIOD, BenchCapture, body, clock, fill_ring, frame, hello, lost,
                                      noise, passed, raw, read_all, scenario)

from jig import capture as C
from jig import frame as F

from motorjig.capture import jigstream as J
from motorjig.capture import record as R
from motorjig.capture.textview import TextView

CHAR = 10e6 / 115200  # µs per character at 115200 baud
REQ = body(2, F.GET_AXIS_STATUS)
REP = body(2, F.GET_AXIS_STATUS, b"\x00" + struct.pack("<I", 0x08000000))


def test_format_constants_agree_with_the_firmware():
    assert (J.MARK, J.VERSION, J.HEADER_LEN) == (C.MARK, C.VERSION, C.HEADER_LEN)
    assert (J.T_HELLO, J.T_LOST, J.T_CLOCK, J.T_NOISE) == (C.T_HELLO, C.T_LOST, C.T_CLOCK, C.T_NOISE)
    assert (J.T_CAN_IN, J.T_CAN_OUT, J.CAN_HEAD) == (C.T_CAN_IN, C.T_CAN_OUT, C.CAN_HEAD)
    assert (R.CAN_EXT, R.CAN_RTR) == (C.CAN_EXT, C.CAN_RTR) and J.VERSION == 2
    for name in ("GOOD", "BAD_CRC", "BAD_STUFFING", "SHORT", "OVERLONG", "TIMEOUT", "RESYNC"):
        assert getattr(R, name) == getattr(C, "V_" + name), name
    assert R.LOST not in R.VERDICT_COUNTER and R.LOST not in range(9)  # new, and none of the old codes moved


def test_hello_sets_the_buses_and_the_jig():
    recs, js = read_all(hello(t=1000, protocol=1, forward=1, slave=4, up=230400, down=57600, interbyte=3000,
                              ring=8192, name=b"MotorJig bridge 0.2"))
    assert recs == []
    h = js.hello
    assert (h["version"], h["protocol"], h["variant"], h["forward_mode"], h["slave_id"]) == (2, 1, "Ver8", 1, 4)
    assert (h["up_baud"], h["down_baud"], h["interbyte_timeout_us"], h["ring_size"]) == (230400, 57600, 3000, 8192)
    assert h["name"] == "MotorJig bridge 0.2" and h["tick"] == 1000 and h["can_bitrate"] == 0
    pc, drivers = js.buses()  # no CAN port: two buses
    assert (pc.name, pc.baud, pc.description) == ("pc", 230400, "PC bus, 230400 baud, jig test")
    assert (drivers.name, drivers.baud, drivers.description) == ("drivers", 57600, "driver bus, 57600 baud, jig test")
    assert "store-and-forward" in js.description() and "Ver8" in js.description()


def test_every_channel_and_its_times():
    t = 5000
    stream = hello(t) + b"".join([
        frame(C.CH_PC_IN, REQ, t + 100, t + 600),  # received from the PC
        frame(C.CH_DRV_OUT, REQ, t + 180, t + 880),  # sent to the drives
        frame(C.CH_DRV_IN, REP, t + 1300, t + 2200),  # received from a drive
        frame(C.CH_PC_OUT, REP, t + 1400, t + 2500),  # sent to the PC
    ])
    recs, _js = read_all(stream)
    assert [(r.bus, r.direction) for r in recs] == [(0, R.DIR_INBOUND), (1, R.DIR_OUTBOUND), (1, R.DIR_INBOUND),
                                                     (0, R.DIR_OUTBOUND)]
    wire_req, wire_rep = F.encode(2, F.GET_AXIS_STATUS), F.encode(2, F.GET_AXIS_STATUS, REP[2:-2])
    assert [r.data for r in recs] == [wire_req, wire_req, wire_rep, wire_rep]
    assert all(r.verdict == R.GOOD and r.count is None for r in recs)
    # the hello's tick is the host time at which it came; everything else follows the jig's clock
    assert [r.t_us - EPOCH_US for r in recs] == [600, 880, 2200, 2500]
    # sent: the first tick is the start; received: the earlier of one character before the
    # read that brought the header and the end less the frame's length in characters
    in_pc = min(100 - CHAR, 600 - len(wire_req) * CHAR)
    in_drv = min(1300 - CHAR, 2200 - len(wire_rep) * CHAR)
    assert [r.t_first_us - EPOCH_US for r in recs] == [round(in_pc), 180, round(in_drv), 1400]


def test_a_frame_passed_on_is_one_record_per_bus():
    """Cut through, a frame goes on from its header: one record with both buses' ticks."""
    t = 7000
    stream = hello(t) + passed(C.CH_PC_IN, REQ, t + 100, t + 600, t + 180, t + 780) + passed(
        C.CH_DRV_IN, REP, t + 1300, t + 2200, t + 1400, t + 2300, R.BAD_CRC)
    recs, _js = read_all(stream)
    wire_req, wire_rep = F.encode(2, F.GET_AXIS_STATUS), F.encode(2, F.GET_AXIS_STATUS, REP[2:-2])
    assert [(r.bus, r.direction, r.data, r.verdict) for r in recs] == [
        (0, R.DIR_INBOUND, wire_req, R.GOOD), (1, R.DIR_OUTBOUND, wire_req, R.GOOD),
        (1, R.DIR_INBOUND, wire_rep, R.BAD_CRC), (0, R.DIR_OUTBOUND, wire_rep, R.BAD_CRC)]
    assert [r.t_us - EPOCH_US for r in recs] == [600, 780, 2200, 2300]
    assert [r.t_first_us - EPOCH_US for r in recs] == [
        round(min(100 - CHAR, 600 - len(wire_req) * CHAR)), 180, round(min(1300 - CHAR, 2200 - len(wire_rep) * CHAR)),
        1400]
    # a passed record cut anywhere still reads the same
    assert read_all(stream, step=1)[0] == recs


def test_received_frame_read_in_one_late_chunk_starts_a_frame_length_before_its_end():
    """t_first = t_end (one read brought the whole frame): the start is the length back."""
    recs, _js = read_all(hello(0) + frame(C.CH_PC_IN, REQ, 9000, 9000))
    assert recs[0].t_us - recs[0].t_first_us == round(len(recs[0].data) * CHAR)


def test_each_bus_has_its_own_character_time():
    recs, _js = read_all(hello(0, up=9600, down=921600) + frame(C.CH_PC_IN, REQ, 50000, 50000) +
                         frame(C.CH_DRV_IN, REQ, 60000, 60000))
    n = len(recs[0].data)
    assert recs[0].t_us - recs[0].t_first_us == round(n * 10e6 / 9600)
    assert recs[1].t_us - recs[1].t_first_us == round(n * 10e6 / 921600)


@pytest.mark.parametrize("verdict, tail", [
    (R.GOOD, b"\xaa\xee"), (R.BAD_CRC, b"\xaa\xee"), (R.SHORT, b"\xaa\xee"), (R.BAD_STUFFING, b"\xaa"),
    (R.OVERLONG, b""), (R.TIMEOUT, b""), (R.RESYNC, b""),
])
def test_wire_bytes_per_verdict(verdict, tail):
    b = bytes([0x02, 0xAA, 0x51, 0xAA, 0x10])  # two 0xAA: doubled on the wire
    assert J.wire_bytes(b, verdict) == b"\xaa\xcc\x02\xaa\xaa\x51\xaa\xaa\x10" + tail
    recs, _js = read_all(hello(0) + frame(C.CH_DRV_IN, b, 10, 500, verdict))
    assert recs[0].data == J.wire_bytes(b, verdict) and recs[0].verdict == verdict


def test_the_stubs_are_short_frames():
    recs, _js = read_all(hello(0) + frame(C.CH_DRV_OUT, b"\x01", 10, 450, R.SHORT) +
                         frame(C.CH_PC_OUT, b"\x02\xaa", 20, 620, R.SHORT))
    assert [r.data for r in recs] == [bytes.fromhex("AA CC 01 AA EE"), bytes.fromhex("AA CC 02 AA AA AA EE")]


def test_lost_noise_and_clock_records():
    stream = hello(0) + lost(3, 100, 900) + noise(C.CH_PC_IN, 5, 1000) + clock(1001000) + noise(C.CH_DRV_IN, 2, 1002000)
    stream += lost(1, 1003000, 1003000)
    recs, js = read_all(stream)
    assert [(r.bus, r.verdict, r.count, r.data) for r in recs] == [
        (0, R.LOST, 3, b""), (0, R.NOISE, 5, b""), (1, R.NOISE, 2, b""), (0, R.LOST, 1, b"")]
    assert recs[0].t_first_us - EPOCH_US == 100 and recs[0].t_us - EPOCH_US == 900
    assert [r.direction for r in recs] == [R.DIR_UNKNOWN, R.DIR_INBOUND, R.DIR_INBOUND, R.DIR_UNKNOWN]
    assert recs[2].t_us - EPOCH_US == 1002000
    assert (js.lost, js.noise, js.clocks) == (4, [5, 2], 1)
    assert R.count_text(recs[0]) == "3 records lost (the jig's capture ring was full)"
    assert R.count_text(recs[3]) == "1 record lost (the jig's capture ring was full)"
    assert R.count_text(recs[1]) == "5 bytes outside any frame (counted by the jig's parser, not recorded)"
    view = TextView(js.buses())
    assert "lost      3 records lost" in view.line(recs[0])
    assert view.as_dict(recs[1])["count"] == 5 and view.as_dict(recs[0])["t_first"] == (EPOCH_US + 100) / 1e6


def test_ticks_unwrap_across_the_wrap():
    t = PERIOD - 2000  # 2 ms before the wrap
    stream = hello(t) + frame(C.CH_PC_IN, REQ, t + 1000, t + 1500) + frame(C.CH_PC_OUT, REP, t + 1900, t + 2900)
    stream += frame(C.CH_PC_IN, REQ, t + 5000, t + 5600)  # all past the wrap: small ticks
    recs, _js = read_all(stream)
    assert [r.t_us - EPOCH_US for r in recs] == [1500, 2900, 5600]
    assert recs[1].t_first_us - EPOCH_US == 1900  # its first tick before the wrap, its end after


def test_an_hour_with_clock_records_keeps_counting():
    """Ticks wrap every 17.9 minutes; a clock record a second apart (here: every 60 s)
    keeps every step under half a period."""
    stream = hello(0)
    for k in range(1, 61):
        stream += clock(k * 60000000)
    stream += frame(C.CH_DRV_OUT, REQ, 3600000000 + 10, 3600000000 + 700)
    recs, js = read_all(stream)
    assert recs[0].t_us - EPOCH_US == 3600000700 and js.clocks == 60


def test_records_slightly_older_than_the_latest_keep_their_place():
    """A noise or lost record carries the tick of its bytes, earlier than the record before."""
    stream = hello(0) + frame(C.CH_PC_IN, REQ, 5000, 5600) + noise(C.CH_PC_IN, 1, 4000) + frame(
        C.CH_PC_IN, REQ, 7000, 7600)
    recs, _js = read_all(stream)
    assert [r.t_us - EPOCH_US for r in recs] == [5600, 4000, 7600]


def test_byte_by_byte_gives_the_same_records():
    cap = scenario(BenchCapture())
    whole, js1 = cap.records()
    bytewise, js2 = cap.records(step=1)
    odd, _js = cap.records(step=7)
    assert whole == bytewise == odd and len(whole) > 20
    assert (js1.lost, js1.noise, js1.clocks) == (js2.lost, js2.noise, js2.clocks)


def test_a_stream_must_start_with_a_hello():
    with pytest.raises(J.StreamError) as exc:
        read_all(b"\x00\x01" + hello(0) + frame(C.CH_PC_IN, REQ, 10, 600))
    assert "does not start with the jig's hello record (first bytes 00 01 A5 10)" in str(exc.value)
    assert "Traceback" not in str(exc.value) and len(str(exc.value).splitlines()) == 1
    # the rest of that chunk was read: the hello was found again, and its frame came
    assert [r.data for r in exc.value.records] == [F.encode(2, F.GET_AXIS_STATUS)]


def test_without_strict_start_what_comes_before_the_hello_is_skipped():
    leftover = frame(C.CH_PC_IN, REQ, 10, 600)[5:]  # the end of an earlier recording
    recs, js = read_all(leftover + hello(0) + frame(C.CH_PC_IN, REQ, 10, 600), strict_start=False)
    assert len(recs) == 1 and js.skipped == len(leftover)


def test_resync_after_garbage():
    good = frame(C.CH_PC_IN, REQ, 100, 700)
    stream = hello(0) + good + b"\x13\x37garbage" + good + hello(50000) + good + frame(C.CH_PC_OUT, REP, 900, 1900)
    js = J.JigStream("socket://x")
    with pytest.raises(J.StreamError) as exc:
        js.feed(stream, EPOCH_US)
    msg = str(exc.value)
    assert msg == "the stream from socket://x is out of step: 0x13 where a record's mark 0xA5 should be"
    assert exc.value.offset == len(hello(0) + good)
    recs = exc.value.records
    # before the garbage: one frame; the frame after it is skipped; after the next hello, two
    assert len(recs) == 3 and [r.direction for r in recs] == [R.DIR_INBOUND, R.DIR_INBOUND, R.DIR_OUTBOUND]
    assert js.in_step and js.hellos == 2
    # the second hello's tick agrees with the host's clock within a second: the jig's
    # timeline goes on (ticks 100..700 are before that hello, and stay where they were)
    assert recs[1].t_us - EPOCH_US == 700 and recs[2].t_us - EPOCH_US == 1900
    assert len(js.feed(good, EPOCH_US)) == 1  # in step from there on


def test_losing_step_in_a_later_chunk_raises_once():
    js = J.JigStream()
    js.feed(hello(0), EPOCH_US)
    assert len(js.feed(frame(C.CH_PC_IN, REQ, 10, 500), EPOCH_US)) == 1
    with pytest.raises(J.StreamError):
        js.feed(raw(0x33, 0, b"", 1, 1), EPOCH_US)  # a type that does not exist
    assert not js.in_step
    assert js.feed(frame(C.CH_PC_IN, REQ, 10, 500), EPOCH_US) == []  # still hunting, quietly
    assert len(js.feed(hello(600) + frame(C.CH_PC_IN, REQ, 700, 900), EPOCH_US)) == 1


@pytest.mark.parametrize("bad, text", [
    (raw(0x01, 9, REQ, 1, 2), "a frame record with verdict 9"),
    (raw(0x11, 0, b"\x01\x00", 1, 1), "a record of type 0x11 with 2 bytes (4)"),
    (raw(0x12, 0, b"\x00", 1, 1), "a clock record with 1 bytes"),
    (raw(0x40, 0, b"", 1, 1), "unknown record type 0x40"),
    (struct.pack("<BBBBII", 0xA5, 0, 0, 0, PERIOD + 5, 0), "past the jig's 2**30 period"),
    (struct.pack("<BBBBIIII", 0xA5, 4, 0, len(REQ), 1, 2, PERIOD + 3, 4) + REQ, "past the jig's 2**30 period"),
    (raw(0x05, 0, REQ, 1, 2), "unknown record type 0x05"),
])
def test_what_loses_step(bad, text):
    with pytest.raises(J.StreamError) as exc:
        read_all(hello(0) + bad)
    assert text in str(exc.value)


def test_another_record_format_is_refused():
    with pytest.raises(J.StreamError) as exc:
        read_all(hello(0, version=3, can=500000))
    assert str(exc.value) == ("the stream from test speaks record format 3; this jigctl reads formats 1 and 2 "
                              "(update motorjig)")


def test_record_format_1_is_still_read():
    """An older firmware (no CAN, no CAN bitrate in the hello) with this jigctl."""
    recs, js = read_all(hello(0, version=1, name=b"MotorJig bridge 0.1") + frame(C.CH_PC_IN, REQ, 10, 600))
    assert js.hello["version"] == 1 and js.hello["can_bitrate"] == 0 and js.hello["name"] == "MotorJig bridge 0.1"
    assert [r.data for r in recs] == [J.wire_bytes(REQ, R.GOOD)] and len(js.buses()) == 2


def test_a_later_hello_with_an_agreeing_clock_keeps_the_timeline():
    """Recording restarted (S again): same clock, so no new anchor and no jump."""
    js = J.JigStream()
    js.feed(hello(1000), EPOCH_US)
    js.feed(frame(C.CH_PC_IN, REQ, 1500, 2000), EPOCH_US + 1005)
    # 3 s later the host gets a hello 3 s on, 2 ms late (USB): the jig's clock is kept
    js.feed(hello(3001000), EPOCH_US + 3002000)
    recs = js.feed(frame(C.CH_PC_IN, REQ, 3001500, 3002000), EPOCH_US + 3003000)
    assert recs[0].t_us - EPOCH_US == 3001000 and js.hellos == 2


def test_a_later_hello_with_another_clock_anchors_anew():
    """The jig restarted (its ticks began again): the host's clock decides."""
    js = J.JigStream()
    js.feed(hello(500000000), EPOCH_US)
    js.feed(hello(200), EPOCH_US + 60000000)
    recs = js.feed(frame(C.CH_PC_IN, REQ, 300, 900), EPOCH_US + 60001000)
    assert recs[0].t_us - EPOCH_US == 60000700


@pytest.mark.parametrize("fastpath", [False, True], ids=["portable", "fastpath"])
def test_the_firmware_stream_on_the_bench(fastpath):
    cap = scenario(BenchCapture(fastpath=fastpath))
    recs, js = cap.records()
    assert js.hello["name"] == "MotorJig bridge 0.1" and js.hello["slave_id"] == 1 and js.clocks >= 3
    verdicts = [(r.bus, r.direction, r.verdict) for r in recs]
    # the corrupted request and the corrupted reply: bad CRC on both buses each
    assert verdicts.count((0, R.DIR_INBOUND, R.BAD_CRC)) == 1 and verdicts.count((1, R.DIR_OUTBOUND, R.BAD_CRC)) == 1
    assert verdicts.count((1, R.DIR_INBOUND, R.BAD_CRC)) == 1 and verdicts.count((0, R.DIR_OUTBOUND, R.BAD_CRC)) == 1
    assert (1, R.DIR_OUTBOUND, R.SHORT) in verdicts  # the stub for the jig's own id
    assert [r.count for r in recs if r.verdict == R.NOISE] == [3] and js.noise == [3, 0]
    assert js.lost == 0
    times = [r.t_us for r in recs if r.count is None]
    assert times == sorted(times) and times[-1] - times[0] > 3000000  # in order, across the wrap
    assert all(r.t_first_us <= r.t_us for r in recs if r.t_first_us is not None)


def test_the_ring_fills_and_the_firmware_reports_what_it_lost():
    """A ring nobody empties: the jig counts what does not fit and says so first thing."""
    cap = BenchCapture()
    b = cap.bench
    lost_in_ring = fill_ring(cap)
    assert b.app.capture.pending() > C.RING_SIZE - 100
    cap.drain()
    b.request(2, F.GET_COMMAND_POS)  # the next record that fits brings the lost report
    cap.drain()
    recs, js = cap.records()
    reports = [r for r in recs if r.verdict == R.LOST]
    assert len(reports) == 1 and reports[0].count == js.lost >= lost_in_ring
    assert recs[-5].verdict == R.LOST  # before the four Records of the last round trip
    assert reports[0].t_first_us <= reports[0].t_us


# --- long silences: the host's arrival time picks the wrap count ---------------------------
S = 1000000  # µs per second


def test_a_gap_past_half_a_period_keeps_the_timeline_going_forward():
    """The reader stalled, the ring filled: the next record (a lost one) comes 600 s
    after the hello, more than half the tick period: the host's arrival time says
    which period it is in (not 473.7 s before the hello)."""
    js = J.JigStream()
    js.feed(hello(1000), EPOCH_US)
    recs = js.feed(lost(7, 1000 + 2 * S, 1000 + 600 * S) + frame(C.CH_PC_IN, REQ, 1000 + 600 * S + 100,
                                                                    1000 + 600 * S + 600),
                   EPOCH_US + 600 * S + 5000)
    assert [r.t_us - EPOCH_US for r in recs] == [600 * S, 600 * S + 600]
    assert recs[0].t_first_us - EPOCH_US == 2 * S and recs[0].count == 7
    # and on from there, without the host's help
    recs = js.feed(frame(C.CH_PC_IN, REQ, 1000 + 601 * S, 1000 + 601 * S + 500), EPOCH_US + 600 * S + 5000)
    assert recs[0].t_us - EPOCH_US == 601 * S + 500


def test_a_gap_of_more_than_a_whole_period():
    """30 minutes without a record (more than one wrap): still forward, to the host's time."""
    js = J.JigStream()
    js.feed(hello(0), EPOCH_US)
    t = 1800 * S
    recs = js.feed(frame(C.CH_PC_IN, REQ, t, t + 500), EPOCH_US + t + 20000)
    assert recs[0].t_us - EPOCH_US == t + 500


def test_records_that_waited_long_in_the_ring_are_not_moved_a_period_on():
    """Records 10 minutes old (the ring held them while the reader stalled) stay where
    the jig's clock puts them, though the host gets them 10 minutes later."""
    js = J.JigStream()
    js.feed(hello(0), EPOCH_US)
    recs = js.feed(frame(C.CH_PC_IN, REQ, 10 * S, 10 * S + 500) + clock(11 * S), EPOCH_US + 610 * S)
    assert recs[0].t_us - EPOCH_US == 10 * S + 500


def test_a_lost_records_first_tick_more_than_half_a_period_old():
    """The first record lost 590 s before the lost record's end: placed from its end."""
    js = J.JigStream()
    js.feed(hello(0), EPOCH_US)
    js.feed(clock(599 * S), EPOCH_US + 599 * S + 1000)
    recs = js.feed(lost(3, 10 * S, 600 * S), EPOCH_US + 600 * S + 1000)
    assert recs[0].t_us - EPOCH_US == 600 * S and recs[0].t_first_us - EPOCH_US == 10 * S


def test_a_later_hello_of_another_record_format_is_refused():
    js = J.JigStream()
    js.feed(hello(0) + frame(C.CH_PC_IN, REQ, 10, 500), EPOCH_US)
    with pytest.raises(J.StreamError) as exc:
        js.feed(hello(1000, version=3) + frame(C.CH_PC_IN, REQ, 1100, 1500), EPOCH_US + 1000)
    assert "record format 3; this jigctl reads formats 1 and 2" in str(exc.value)
    assert exc.value.records == [] and js.hellos == 1
