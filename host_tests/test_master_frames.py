"""Bus-master behaviour that needs no slave: wire bytes, retry policy, Ver8 sync numbers.

The port is pyserial's ``loop://``: every byte written comes straight back, so the
master hears only the echo of its own request -- which it skips (``echo=True``) --
and then times out. The ``trace`` hook shows exactly what went on the wire.
"""

import pytest

from jig import frame as F
from jig.parser import FrameParser
from motorjig import errors as E
from motorjig import names as N
from motorjig.master import AxisStatus, Master, pack

# Worked examples from the protocol notes (§3.1): request -> wire bytes.
EXAMPLES = [
    (lambda m: m.get_slave_info(1), "AA CC 01 01 C1 E0 AA EE"),
    (lambda m: m.get_axis_status(1), "AA CC 01 40 01 D0 AA EE"),
    (lambda m: m.get_all_status(1), "AA CC 01 43 41 D1 AA EE"),
    (lambda m: m.move_stop(1), "AA CC 01 31 C1 F4 AA EE"),
    (lambda m: m.servo_enable(0, True), "AA CC 00 2A 01 AF 60 AA EE"),
    (lambda m: m.step_alarm_reset(1, True), "AA CC 01 2C 01 FD 00 AA EE"),
    (lambda m: m.get_parameter(1, 1), "AA CC 01 13 01 EC F0 AA EE"),
    (lambda m: m.set_parameter(1, 1, 100000), "AA CC 01 12 01 A0 86 01 00 F7 0B AA EE"),
    (lambda m: m.move_inc(0, 10000, 5000), "AA CC 00 35 10 27 00 00 88 13 00 00 97 3D AA EE"),
    (lambda m: m.move_abs(1, -1000, 20000), "AA CC 01 34 18 FC FF FF 20 4E 00 00 10 6A AA EE"),
    (lambda m: m.move_velocity(1, 5000, 1), "AA CC 01 37 88 13 00 00 01 2A DC AA EE"),
    (lambda m: m.move_pause(1, True), "AA CC 01 58 01 DA 00 AA EE"),
    (lambda m: m.pos_table_run_item(1, 5), "AA CC 01 64 05 00 43 57 AA EE"),
    (lambda m: m.set_command_pos(2, 170), "AA CC 02 50 AA AA 00 00 00 E0 2D AA EE"),
    (lambda m: m.io_assign_map_read_rom(4), "AA CC 04 26 82 AA AA AA EE"),
]


def loop_master(**kw):
    sent = []

    def trace(direction, item):
        if direction == "tx":
            sent.append(item)

    kw.setdefault("timeout", 0.01)
    kw.setdefault("ver8", False)  # Ver6 framing, no detection probe (nothing answers)
    m = Master("loop://", trace=trace, echo=True, **kw)
    return m, sent


@pytest.mark.parametrize("call,wire", EXAMPLES)
def test_request_bytes_match_the_protocol_examples(call, wire):
    m, sent = loop_master(retries=0)
    with m, pytest.raises(E.NoReplyError):
        call(m)  # only our own echo comes back: skipped, then timeout
    assert sent == [bytes.fromhex(wire)]


def test_broadcast_all_move_stop_needs_no_reply():
    m, sent = loop_master()
    with m:
        m.all_move_stop()
    assert sent == [bytes.fromhex("AA CC 63 3B 68 93 AA EE")]


def test_idempotent_requests_are_retried_motion_starts_are_not():
    m, sent = loop_master(retries=2)
    with m:
        with pytest.raises(E.NoReplyError):
            m.get_axis_status(2)
        assert len(sent) == 3
        sent.clear()
        for start in (lambda: m.move_inc(2, 100, 1000), lambda: m.move_abs(2, 100, 1000),
                      lambda: m.move_velocity(2, 100, 1), lambda: m.move_origin(2),
                      lambda: m.move_to_limit(2, 100, 0), lambda: m.position_inc_override(2, 5)):
            with pytest.raises(E.NoReplyError):
                start()
            assert len(sent) == 1
            sent.clear()
        with pytest.raises(E.NoReplyError):
            m.move_stop(2)
        assert len(sent) == 3


def test_slow_frames_get_the_vendor_timeout_multipliers():
    m, _ = loop_master(timeout=0.002, retries=0)
    with m:
        for call, ms in ((m.save_all_parameters, 10), (m.clear_position, 30),
                         (m.pos_table_write_rom, 40), (m.get_command_pos, 2)):
            with pytest.raises(E.NoReplyError) as exc:
                call(3)
            assert "within %d ms" % ms in str(exc.value)
        with pytest.raises(E.NoReplyError) as exc:
            m.servo_enable(3, True)
        assert "within 10 ms" in str(exc.value)


def test_ver8_sync_numbers_per_slave_and_broadcast():
    m, sent = loop_master(ver8=True, retries=0)
    p = FrameParser(ver8=True)

    def syncs():
        out = []
        for wire in sent:
            p.feed(wire)
            assert p.ready
            out.append((p.slave, p.sync, p.ftype))
        sent.clear()
        return out

    with m:
        for slave in (2, 2, 3, 2):
            with pytest.raises(E.NoReplyError):
                m.get_command_pos(slave)
        got = syncs()
        assert [g[0] for g in got] == [2, 2, 3, 2]
        assert [g[1] for g in got] == [0xF1, 0xF2, 0xF1, 0xF3]
        assert all(g[2] == F.GET_COMMAND_POS for g in got)
        m.all_move_stop()
        (b,) = syncs()
        assert b[0] == F.BROADCAST_ID and b[1] not in (0xF1, 0xF2, 0xF3)
        # every counter continues from the broadcast's number
        with pytest.raises(E.NoReplyError):
            m.get_command_pos(3)
        assert syncs()[0][1] == (b[1] + 1) & 0xFF


def test_pack_rejects_values_that_do_not_fit():
    assert pack(("i32", -1)) == b"\xff\xff\xff\xff"
    for bad in (("u8", 256), ("u16", -1), ("i32", 2 ** 31), ("u32", -1)):
        with pytest.raises(ValueError):
            pack(bad)
    m, sent = loop_master()
    with m:
        with pytest.raises(ValueError):
            m.move_inc(2, 2 ** 31, 100)
        with pytest.raises(ValueError):
            m.get_axis_status(16)
    assert sent == []


def test_axis_status_flags_by_name():
    st = AxisStatus(0x08000000 | 1 << 20 | 1 << 10 | 1 << 5)
    assert st.motioning and st.servo_on and st.step_out and not st.emergency_stop
    assert st.flags == ["bit5", "step_out", "servo_on", "motioning"]
    assert st.errors == ["step_out"]
    with pytest.raises(AttributeError):
        st.no_such_flag


def test_status_codes_map_to_exception_classes():
    assert isinstance(E.status_error(0x85, 2, 0x35, "MoveIncPos"), E.MotionRefusedError)
    assert isinstance(E.status_error(0xAA), E.RequestCRCError)
    assert isinstance(E.status_error(0x88), E.ServoOnRefusedError)
    assert isinstance(E.status_error(0x42), E.UnknownStatusError)
    msg = str(E.status_error(0x85, 2, 0x35, "MoveIncPos"))
    assert "slave 2" in msg and "MoveIncPos" in msg and "0x85" in msg
    for code in (0x80, 0x81, 0x82, 0x85, 0x86, 0x87, 0x88, 0x89, 0x8A, 0x8B, 0xAA):
        assert type(E.status_error(code)) is not E.UnknownStatusError
        assert N.status_name(code) != "status_0x%02X" % code


def test_the_jigs_own_frames_are_named():
    """Every frame of the jig's own (jig.diag, 0xF0-0xF9) has its name: an error about a
    trace read says ReadTrace, not Frame0xF7."""
    from jig import diag as D

    assert {t: N.frame_name(t) for t in range(0xF5, 0xFA)} == {
        D.START_TRACE: "StartTrace", D.STOP_TRACE: "StopTrace", D.READ_TRACE: "ReadTrace",
        D.GET_TRACE_STATUS: "GetTraceStatus", D.READ_TRANSACTION_TIMES: "ReadTransactionTimes"}
    for t in range(0xF0, 0xFA):
        assert not N.frame_name(t).startswith("Frame0x"), hex(t)
    m, _sent = loop_master(retries=0)
    with pytest.raises(E.NoReplyError) as ei:
        m.trace_status(1)
    assert "GetTraceStatus" in str(ei.value)


def test_names_cover_the_tables():
    assert N.frame_name(0x43) == "GetAllStatus" and N.frame_name(0xF0) == "ReadCounters"
    assert [p.number for p in N.STEP_PARAMS] == list(range(29))
    jig = N.jig_params()
    assert N.find_param(jig, "up_baud").number == 1
    with pytest.raises(ValueError):
        N.find_param(jig, "up_baud").check(12345)  # not a baud rate, though inside min..max
    with pytest.raises(ValueError):
        N.find_param(N.STEP_PARAMS, 3).check(0)
    assert N.bit_value(N.bit_names(0x8005, N.OUTPUT_BITS), N.OUTPUT_BITS) == 0x8005


def answering_master(*replies, **kw):
    """A loop:// master that, right after each request, hears the given wire frames."""
    kw.setdefault("ver8", False)
    m = Master("loop://", timeout=kw.pop("timeout", 0.02), echo=True, **kw)
    queue = list(replies)
    sent = []

    def trace(direction, item):
        if direction == "tx" and len(sent) < 100:
            sent.append(item)
            if queue:
                m._serial.write(queue.pop(0))

    m.trace = trace
    return m, sent


def test_reply_matching_skips_other_slaves_and_types():
    other_slave = F.encode(3, F.GET_COMMAND_POS, b"\x00\x01\x00\x00\x00")
    other_type = F.encode(2, F.GET_ACTUAL_POS, b"\x00\x02\x00\x00\x00")
    mine = F.encode(2, F.GET_COMMAND_POS, b"\x00\x18\xfc\xff\xff")  # -1000
    m, sent = answering_master(other_slave + other_type + mine)
    with m:
        assert m.get_command_pos(2) == -1000
    assert len(sent) == 1


def test_reply_with_bad_crc_raises_reply_crc_error_after_retries():
    good = bytearray(F.encode(2, F.GET_COMMAND_POS, b"\x00\x01\x00\x00\x00"))
    good[-3] ^= 0x01  # CRC high byte
    m, sent = answering_master(bytes(good), bytes(good), bytes(good), retries=2)
    with m, pytest.raises(E.ReplyCRCError) as exc:
        m.get_command_pos(2)
    assert len(sent) == 3 and "CRC" in str(exc.value)


def test_retry_after_crc_then_good_reply():
    bad = bytearray(F.encode(2, F.GET_COMMAND_POS, b"\x00\x07\x00\x00\x00"))
    bad[-3] ^= 0x01
    good = F.encode(2, F.GET_COMMAND_POS, b"\x00\x07\x00\x00\x00")
    m, sent = answering_master(bytes(bad), good, retries=2)
    with m:
        assert m.get_command_pos(2) == 7
    assert len(sent) == 2


def test_reply_of_wrong_length_is_a_bad_reply():
    m, _ = answering_master(F.encode(2, F.GET_AXIS_STATUS, b"\x00\x01\x02"))
    with m, pytest.raises(E.BadReplyError) as exc:
        m.get_axis_status(2)
    assert "2 data bytes, expected 4" in str(exc.value)


def test_error_status_reply_raises_its_class_without_length_check():
    m, sent = answering_master(F.encode(1, F.MOVE_INC_POS, b"\x85"))
    with m, pytest.raises(E.MotionRefusedError) as exc:
        m.move_inc(1, 10000, 5000)
    assert exc.value.status == 0x85 and len(sent) == 1
    # the protocol notes' example reply, byte for byte
    assert F.encode(1, F.MOVE_INC_POS, b"\x85") == bytes.fromhex("AA CC 01 35 85 F6 F3 AA EE")


def test_ver8_reply_must_carry_the_request_sync():
    # the counter for slave 2 starts at 0xF0, so the first request uses 0xF1
    stale = F.encode(2, F.GET_COMMAND_POS, b"\x00\x05\x00\x00\x00", sync=0xF0)
    fresh = F.encode(2, F.GET_COMMAND_POS, b"\x00\x06\x00\x00\x00", sync=0xF1)
    m, _ = answering_master(stale + fresh, ver8=True)
    with m:
        assert m.get_command_pos(2) == 6


def test_reply_identical_to_its_request_is_not_taken_for_an_echo():
    # "02 2C 00" is both StepAlarmReset(release) and its OK reply.
    reply = F.encode(2, F.STEP_ALARM_RESET, b"\x00")
    m, sent = answering_master(reply)  # loop:// echoes, so echo=True: skip only the first copy
    with m:
        m.step_alarm_reset(2, False)
    assert sent == [reply]
    m, sent = answering_master()  # no reply at all: the echo alone must not count
    with m, pytest.raises(E.NoReplyError):
        m.step_alarm_reset(2, False)


def test_decoder_reads_ver8_64_bit_inputs_and_motion_flags():
    from motorjig.decode import Decoder
    from motorjig.master import Frame

    dec = Decoder()
    d = b"\x00" + (1 << 40).to_bytes(8, "little") + bytes(28)  # GetAllStatus, 64-bit inputs
    got = dec.as_dict(Frame(3, 0xF2, F.GET_ALL_STATUS, d, b"", 0.0))
    assert got["kind"] == "reply" and got["inputs"] == "0x0000010000000000"
    ms = b"\x00" + bytes(16) + (1 << 20).to_bytes(4, "little")  # GetMotionStatus, Ver8: axis flags last
    assert dec.as_dict(Frame(3, 0xF3, F.GET_MOTION_STATUS, ms, b"", 0.0), "reply")["flags"] == ["servo_on"]
    assert "flags" not in dec.as_dict(Frame(2, -1, F.GET_MOTION_STATUS, ms, b"", 0.0), "reply")


def test_detection_and_broadcast_on_a_mixed_bus():
    """Ver6 reply to the probe -> Ver6; Ver8 frame-type error -> Ver8 probe with sync
    0xF1. A broadcast then goes once per variant, the Ver8 one with a sync in 0xC0..0xEF
    (no frame type a Ver6 drive would act on)."""
    probe3 = F.encode(3, F.GET_COMMAND_POS)
    m, sent = answering_master(
        F.encode(2, F.GET_COMMAND_POS, b"\x00" + bytes(4)),  # Ver6 drive 2
        F.encode(3, probe3[4], b"\x80", sync=0x51),  # Ver8 drive 3: id, 51, crcL, 80
        F.encode(3, F.GET_COMMAND_POS, b"\x00" + bytes(4), sync=0xF1),  # the Ver8 probe's answer
        ver8=None)
    with m:
        assert m.detect_variant(2) == 6 and m.detect_variant(3) == 8 and m.variants == {2: 6, 3: 8}
        assert sent[1] == probe3 and sent[2] == F.encode(3, F.GET_COMMAND_POS, sync=0xF1)
        del sent[:]
        m.all_move_stop()
    p = FrameParser(ver8=True)
    assert sent[0] == F.encode(F.BROADCAST_ID, F.ALL_MOVE_STOP)
    p.feed(sent[1])
    assert p.ready and p.slave == F.BROADCAST_ID and p.ftype == F.ALL_MOVE_STOP and 0xC0 <= p.sync <= 0xEF
