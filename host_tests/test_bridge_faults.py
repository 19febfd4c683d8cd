"""Bridge behaviour under faults, on the virtual bench (real firmware, virtual time)."""

import struct

from jig import frame as F
from jig import params as P
from jig.bridge import B_FWD, B_STATE
from motorjig.sim import SimBench

GCP = F.GET_COMMAND_POS


def make(**kw):
    kw.setdefault("driver_ids", (2, 3))
    return SimBench(**kw)


def test_silent_driver_times_out_like_an_empty_address():
    b = make()
    b.drivers[2].silent = True
    assert b.request(2, GCP) == (None, None)
    assert b.counters["timeouts"] == 1 and b.counters["replies"] == 0
    _w, r = b.request(3, GCP)
    assert r == b"\x00" + bytes(4)
    assert b.pc.raw == b.pc.frames[0][1]  # nothing else ever reached the PC


def test_garbage_answer_is_not_relayed():
    b = make()
    b.drivers[2].garbage = True
    assert b.request(2, GCP) == (None, None)
    c = b.counters
    assert c["timeouts"] == 1 and c["replies"] == 0 and c["up_frames_out"] == 0
    assert c["down_noise"] + c["down_crc_errors"] + c["down_stuff_errors"] + c["down_short"] > 0
    assert b.pc.raw == b""


def test_bad_crc_reply_dropped_store_and_forward():
    b = make(jig_params={P.P_FORWARD_MODE: P.STORE_AND_FORWARD})
    b.drivers[2].bad_crc = True
    assert b.request(2, GCP) == (None, None)
    assert b.counters["down_crc_errors"] == 1 and b.pc.raw == b""


def test_bad_crc_reply_passed_on_cut_through_like_a_wire():
    """The reply matched from its first bytes and was already on its way: the PC gets
    it as a direct line would give it, and its own CRC check rejects it."""
    b = make()
    b.drivers[2].bad_crc = True
    assert b.request(2, GCP) == (None, None)
    c = b.counters
    assert c["down_crc_errors"] == 1 and c["relay_corrupt"] == 1 and c["replies"] == 0
    assert b.pc.parser.crc_errors == 1 and b.pc.frames == []
    assert not b.hal.up.node.de  # the relay ended cleanly
    b.drivers[2].bad_crc = False
    _w, r = b.request(2, GCP)  # and the next one is fine
    assert r == b"\x00" + bytes(4)
    c = b.counters
    assert c["forwards"] == 2 == c["replies"] + c["relay_corrupt"]


def test_pc_sends_with_gaps_mid_frame_cut_through():
    """Pieces with short gaps are passed on with DE held; a gap longer than the
    inter-byte timeout ends the transmission cleanly and is counted."""
    b = make()
    wire = F.encode(2, F.MOVE_INC_POS, struct.pack("<iI", 1000, 500))
    t = b.send(wire[:5])
    b.clock.run_until(t + 2000.0)  # under the 5 ms inter-byte timeout
    t = b.send(wire[5:11])
    b.clock.run_until(t + 1000.0)
    t = b.send(wire[11:])
    b.run_for(20000.0)
    assert len(b.pc.frames) == 1 and b.drivers[2].requests == 1
    node = b.hal.down.node
    assert [v for _t, v in node.de_log[-2:]] == [1, 0]  # one DE pulse for the whole frame
    c = b.counters
    assert c["replies"] == 1 and c["cut_truncated"] == 0
    # now a PC that stops mid-frame for good
    t = b.send(wire[:7])
    b.run_for(30000.0)
    c = b.counters
    assert c["cut_truncated"] == 1 and c["unawaited"] == 1 and not node.de
    assert b.drivers[2].requests == 1 and len(b.pc.frames) == 1
    assert c["forwards"] == c["replies"] + c["timeouts"] + c["aborts"] + c["unawaited"] + c["relay_corrupt"]


def test_driver_garbage_mid_relay_reaches_the_pc_as_a_broken_frame():
    b = make()
    d = b.drivers[2]
    reply = F.encode(2, GCP, b"\x00\x01\x02\x03\x04")
    d.silent = True
    t = b.send(F.encode(2, GCP))
    b.clock.run_until(t + 300.0)
    b.down_bus.inject(reply[:6] + b"\x13\x37" + reply[8:])  # garbage in the middle of the answer
    b.run_for(60000.0)
    c = b.counters
    assert c["relay_corrupt"] == 1 and c["replies"] == 0 and b.pc.frames == []
    assert b.pc.parser.crc_errors == 1
    d.silent = False
    assert b.request(2, GCP)[1] == b"\x00" + bytes(4)


def test_wrong_id_reply_dropped_store_and_forward():
    b = make(jig_params={P.P_FORWARD_MODE: P.STORE_AND_FORWARD})
    b.drivers[2].wrong_id = 5
    assert b.request(2, GCP) == (None, None)
    c = b.counters
    assert c["stale_drops"] == 1 and c["timeouts"] == 1 and b.pc.raw == b""


def test_wrong_id_reply_reaches_the_pc_only_as_a_stub_cut_through():
    """Cut through, a frame on the driver bus is relayed from its header while a reply
    is awaited; its first two bytes show it is not the answer, and the PC gets a
    frame too short to be one (AA CC id type AA EE), which no parser accepts."""
    b = make()
    b.drivers[2].wrong_id = 5
    assert b.request(2, GCP) == (None, None)
    c = b.counters
    assert c["stale_drops"] == 1 and c["timeouts"] == 1 and c["replies"] == 0
    assert b.pc.raw == bytes((0xAA, 0xCC, 5, GCP, 0xAA, 0xEE)) and b.pc.frames == []
    assert b.pc.parser.short == 1
    assert b.request(3, GCP)[1] == b"\x00" + bytes(4)  # the next request is answered as ever


def test_late_reply_never_answers_the_next_request():
    b = make()
    d = b.drivers[2]
    d.late_us = 60000.0  # jig reply timeout is 50 ms
    assert b.request(2, GCP, timeout_us=52000.0) == (None, None)
    assert b.counters["timeouts"] == 1
    d.late_us = 0.0
    # next request (another type) goes out while the late reply is still pending
    wire, r = b.request(2, F.GET_AXIS_STATUS)
    assert r is not None and wire[3] == F.GET_AXIS_STATUS
    b.run_for(20000.0)  # the late GetCommandPos reply arrives now
    c = b.counters
    assert c["stale_drops"] == 1 and c["replies"] == 1
    assert [w[3] for _t, w in b.pc.frames] == [F.GET_AXIS_STATUS]
    # and the request after that still gets its own answer
    wire, r = b.request(3, GCP)
    assert wire[2:4] == bytes([3, GCP])
    assert len(b.pc.frames) == 2


def test_late_reply_to_idle_jig_is_dropped():
    b = make()
    b.drivers[2].late_us = 70000.0
    assert b.request(2, GCP, timeout_us=100000.0) == (None, None)
    assert b.counters["stale_drops"] == 1 and b.pc.raw == b""


def test_ver8_same_type_late_reply_is_told_apart_by_sync():
    b = make(ver8=True)
    d = b.drivers[2]
    d.late_us = 55000.0
    b.send(b.encode(2, GCP))  # sync 0, answered at ~56 ms
    b.run_for(53000.0)
    assert b.counters["timeouts"] == 1
    d.late_us = 0.0
    d.motion.pos = 1234.0  # the second answer differs from the first
    wire, r = b.request(2, GCP)  # sync 1; the sync-0 answer arrives while this waits
    assert r == b"\x00" + struct.pack("<i", 1234) and wire[3] == 1
    b.run_for(20000.0)
    assert len(b.pc.frames) == 1 and b.counters["stale_drops"] == 1


def test_truncated_request_then_good_one():
    b = make()
    wire = F.encode(2, GCP)
    b.send(wire[:5])
    b.run_for(20000.0)  # > inter-byte timeout
    _w, r = b.request(2, GCP)
    assert r == b"\x00" + bytes(4)
    assert b.counters["up_timeouts"] == 1 and b.drivers[2].requests == 1


def test_truncated_request_immediately_followed_by_good_one():
    b = make()
    wire = F.encode(2, GCP)
    got = b.transact(wire[:5] + wire)
    assert got is not None and got[2:4] == bytes([2, GCP])
    assert b.counters["up_resyncs"] == 1 and b.drivers[2].requests == 1


def test_noise_bursts_on_both_buses():
    b = make()
    noise = bytes([0x55, 0xAA, 0x01, 0xAA, 0xCC, 0x02, 0x13, 0xFF, 0x00, 0xEE, 0xAA])
    for k in range(20):
        b.up_bus.inject(noise[k % 5 :])
        b.down_bus.inject(noise[: 3 + k % 7])
        b.run_for(20000.0)
        wire, r = b.request(2 + k % 2, GCP)
        assert r == b"\x00" + bytes(4)
    c = b.counters
    assert c["replies"] == 20 and c["timeouts"] == 0
    assert c["up_noise"] > 0 and c["down_noise"] > 0
    # everything the jig sent to the PC is exactly the 20 replies
    assert b"".join(w for _t0, _t1, w in b.hal.up.writes) == b"".join(w for _t, w in b.pc.frames)


def test_pc_retry_while_waiting_gets_one_answer():
    b = make()
    d = b.drivers[2]
    d.late_us = 8000.0
    wire = F.encode(2, GCP)
    t = b.send(wire)
    b.clock.run_until(t + 3000.0)
    b.send(wire)  # the PC gives up waiting and re-sends
    b.run_for(40000.0)
    c = b.counters
    assert c["aborts"] == 1 and c["replies"] == 1 and c["stale_drops"] == 1
    assert len(b.pc.frames) == 1 and d.requests == 2
    assert c["forwards"] == c["replies"] + c["timeouts"] + c["aborts"]


def test_new_local_request_aborts_the_wait():
    b = make()
    b.drivers[2].late_us = 8000.0
    b.send(F.encode(2, GCP))
    b.run_for(3000.0)
    _w, r = b.request(1, GCP)
    assert r == b"\x00" + bytes(4)
    b.run_for(20000.0)
    c = b.counters
    assert c["aborts"] == 1 and c["stale_drops"] == 1 and len(b.pc.frames) == 1


def test_unsolicited_driver_bus_frame_never_reaches_pc():
    b = make()
    b.down_bus.inject(F.encode(7, GCP, b"\x00\x01\x02\x03\x04"))
    b.run_for(10000.0)
    assert b.counters["stale_drops"] == 1 and b.pc.raw == b""


def test_rx_overflow_counted_and_recovered():
    # The jig's ring gets the whole burst at once (stream_chunk larger than the
    # burst), as if the main loop were stalled while it arrived: more than it holds.
    b = make(rxsize=64, stream_chunk=256)
    burst = F.encode(2, F.SET_PARAMETER, b"\x03" + bytes(4)) * 10  # 130 bytes in one go
    b.send(burst)
    b.run_for(50000.0)
    c = b.counters
    assert c["up_rx_overflows"] > 0
    _w, r = b.request(3, GCP)
    assert r == b"\x00" + bytes(4)


def test_echo_on_upstream_port_discarded():
    b = make(echo_up=True)
    sent = 0
    for k in range(5):
        wire, r = b.request(1 + k % 3, GCP)
        assert r == b"\x00" + bytes(4)
        sent += len(wire)
    c = b.counters
    assert c["echo_drops"] == sent
    assert c["up_frames_in"] == 5 and c["up_good"] == 5  # the echo never parsed as a PC frame
    assert c["up_frames_out"] == 5


def test_echo_on_downstream_port_discarded():
    b = make(echo_down=True)
    wire, r = b.request(2, GCP)
    assert r is not None
    c = b.counters
    assert c["echo_drops"] == len(F.encode(2, GCP)) and c["stale_drops"] == 0 and c["down_good"] == 1


def test_absent_ids_are_silent_and_slow_types_wait_longer():
    b = make()
    d = b.drivers[2]
    d.late_us = 200000.0  # SaveAllParameters may take 5 x 50 ms
    _w, r = b.request(2, F.SAVE_ALL_PARAMETERS, timeout_us=300000.0)
    assert r == b"\x00"
    d.late_us = 60000.0  # a normal type is given up after 50 ms
    assert b.request(2, GCP, timeout_us=100000.0) == (None, None)
    c = b.counters
    assert c["replies"] == 1 and c["timeouts"] == 1


def test_no_request_of_the_jig_while_a_broadcast_is_cut_through():
    """A broadcast leaves the bridge IDLE while its bytes are still being passed on:
    the jig's own requests (bus scan, safety stop) must not go out in the middle of it."""
    b = make(stream_chunk=1)
    wire = F.encode(F.BROADCAST_ID, F.ALL_MOVE_STOP)
    t = b.send(wire[:4])
    b.clock.run_until(t + 500.0)
    bridge = b.app.bridge
    assert bridge.bs[B_STATE] == 0 and bridge.bs[B_FWD]  # IDLE, and passing the broadcast on
    assert bridge.busy()
    assert bridge.request(b.app.scanner, 2, F.GET_SLAVE_INFO, bytearray(1), 0, 20) is False
    b.send(wire[4:])
    b.run_for(10000.0)
    assert not bridge.busy() and b.drivers[2].requests == 1 and b.drivers[3].requests == 1
    assert b.counters["int_requests"] == 0 and b.down_bus.collisions == 0


def test_driver_frame_broken_off_before_its_two_bytes_is_not_the_answer():
    """Cut through, a header on the driver bus goes on to the PC at once; if the frame
    breaks off before its id and type are in (a glitch, silence), it was no answer:
    the wait goes on and the real reply, coming later, is relayed."""
    b = make()
    d = b.drivers[2]
    d.late_us = 20000.0
    t = b.send(F.encode(2, GCP))
    b.clock.run_until(t + 300.0)
    b.down_bus.inject(bytes((0xAA, 0xCC, 2)))  # ... and then nothing
    b.run_for(60000.0)
    c = b.counters
    assert c["replies"] == 1 and c["relay_corrupt"] == 0 and c["timeouts"] == 0
    assert [w for _t, w in b.pc.frames] == [F.encode(2, GCP, b"\x00" + bytes(4))]
    assert b.pc.raw.startswith(bytes((0xAA, 0xCC, 2)))  # the broken-off start reached the PC
