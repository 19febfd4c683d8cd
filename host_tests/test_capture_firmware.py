"""The jig's own recording of both buses (jig.capture): records, ring, lost records, switching.

The records are read here by a parser of the test's own (the documented layout,
firmware/jig/capture.py), not by jigctl's, so the two are checked against each
other by the format, not against themselves. Bench tests run on both main loops
(conftest's ``jig_loop``: the portable loop and jig.fastpath.pump).
"""

import random
import struct
from array import array

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jig import capture as C
from jig import fastpath, frame, native, parser
from jig import params as P
from motorjig.capture import record as R
from motorjig.sim import SimBench

NAMES = {C.CH_PC_IN: "pc_in", C.CH_PC_OUT: "pc_out", C.CH_DRV_IN: "drv_in", C.CH_DRV_OUT: "drv_out",
         C.T_HELLO: "hello", C.T_LOST: "lost", C.T_CLOCK: "clock",
         C.T_NOISE | C.CH_PC_IN: "pc_noise", C.T_NOISE | C.CH_DRV_IN: "drv_noise"}


def parse(stream):
    """[(name, verdict, data, t_first, t_end)] of a record stream; asserts it is whole.
    A frame passed on (types 4, 6) is listed as what it was on each bus: received,
    then sent on the other."""
    out = []
    i = 0
    while i < len(stream):
        assert stream[i] == C.MARK, "record %d at byte %d: no mark" % (len(out), i)
        typ, verdict, n, t0, t1 = struct.unpack_from("<BBBII", stream, i + 1)
        hlen = 20 if typ in (C.T_PC_PASSED, C.T_DRV_PASSED) else 12
        data = bytes(stream[i + hlen:i + hlen + n])
        assert len(data) == n, "truncated record"
        if hlen == 20:
            t2, t3 = struct.unpack_from("<II", stream, i + 12)
            out.append((NAMES[typ & 3], verdict, data, t0, t1))
            out.append((NAMES[(typ & 3) ^ 3], verdict, data, t2, t3))
        else:
            out.append((NAMES[typ], verdict, data, t0, t1))
        i += hlen + n
    return out


def records(b, drop_hello=True):
    recs = parse(b.app.capture.drain_to(bytearray()))
    if drop_hello:
        assert recs[0][0] == "hello"
        recs = recs[1:]
    return [r for r in recs if r[0] != "clock"]


def body(wire):
    """The body of a whole frame on the wire (header, tail and stuffing off)."""
    return bytes(wire[2:-2]).replace(b"\xaa\xaa", b"\xaa")


def bench(**kw):
    kw.setdefault("jig_params", {})[P.P_CAPTURE] = 1
    return SimBench(**kw)


# --- format and the two put engines -------------------------------------------------
def test_constants_agree_across_the_modules_that_share_them():
    assert (native._CS_ON, native._CS_HEAD, native._CS_TAIL, native._CS_MASK, native._CS_LOST, native._CS_LOST_T0,
            native._CS_LOST_T1, native._CS_T_LAST, native._CS_START, native._CS_TOTAL, native._CS_LOST_TOTAL) == (
        C.CS_ON, C.CS_HEAD, C.CS_TAIL, C.CS_MASK, C.CS_LOST, C.CS_LOST_T0, C.CS_LOST_T1, C.CS_T_LAST, C.CS_START,
        C.CS_TOTAL, C.CS_LOST_TOTAL)
    assert (native._CAP_MARK, native._CAP_HEADER, native._CAP_LOST, native._CAP_PASSED_HEADER, native._CAP_PASSED,
            native._CS_T_IN) == (C.MARK, C.HEADER_LEN, C.T_LOST, C.PASSED_HEADER_LEN, C.T_PASSED, C.CS_T_IN)
    assert (fastpath._CS_T_IN, fastpath._T_PC_PASSED, fastpath._T_DRV_PASSED) == (C.CS_T_IN, C.T_PC_PASSED,
                                                                                   C.T_DRV_PASSED)
    assert (fastpath._CS_ON, fastpath._CS_START, fastpath._CH_PC_IN, fastpath._CH_PC_OUT, fastpath._CH_DRV_IN,
            fastpath._CH_DRV_OUT, fastpath._STUB >> 8) == (C.CS_ON, C.CS_START, C.CH_PC_IN, C.CH_PC_OUT,
                                                            C.CH_DRV_IN, C.CH_DRV_OUT, C.V_SHORT)
    assert native._S_DROP_N == parser.S_DROP_N
    from jig import bridge

    folded = [n for n in vars(bridge) if n.startswith(("_CS_", "_CH_", "_V_", "_T_")) or n == "_QUIET_US"]
    assert len(folded) == 19
    for name in folded:
        assert getattr(bridge, name) == getattr(C, name[1:]), name
    assert (C._S_NOISE, C._S_T_LAST) == (parser.S_NOISE, parser.S_T_LAST)
    # the verdict codes are motorjig.capture.record's (jigctl, pcapng, dissector)
    assert (C.V_GOOD, C.V_BAD_CRC, C.V_BAD_STUFFING, C.V_SHORT, C.V_OVERLONG, C.V_TIMEOUT, C.V_RESYNC) == (
        R.GOOD, R.BAD_CRC, R.BAD_STUFFING, R.SHORT, R.OVERLONG, R.TIMEOUT, R.RESYNC)
    assert P.TABLE[P.P_CAPTURE][1:] == ("capture", "0=off 1=record both buses", 0, 1, 0, P.IMMEDIATE)


def _state(size):
    cs = array("i", bytes(4 * C.CS_SIZE))
    cs[C.CS_MASK] = size - 1
    cs[C.CS_ON] = 1
    for k in range(4):
        cs[C.CS_START + k] = -1
    return cs, bytearray(size)


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([0, 1, 2, 3, 4, 6, 0x12, 0x20, 0x22]), st.integers(0, 6),
                          st.integers(0, 40), st.integers(-1, (1 << 30) - 1), st.integers(0, (1 << 30) - 1),
                          st.integers(0, 70)), max_size=30),
       st.sampled_from([64, 128, 256]))
def test_the_machine_code_put_is_the_python_put(ops, size):
    """Same records, same lost counts, same ring bytes, whatever the port takes between."""
    a = _state(size)
    b = _state(size)
    src = bytes(range(40))
    for typ, verdict, n, t_start, t1, take in ops:
        for cs, ring in (a, b):
            if typ < 8:
                cs[C.CS_START + (typ & 3)] = t_start
                cs[C.CS_START + ((typ & 3) ^ 3)] = t_start // 2 if t_start % 3 else -1
                cs[C.CS_T_IN] = t1 // 3
            cs[C.CS_TAIL] = (cs[C.CS_TAIL] + min(take, (cs[C.CS_HEAD] - cs[C.CS_TAIL]) & cs[C.CS_MASK])) & cs[C.CS_MASK]
        ra = C.put_py(a[0], a[1], typ | verdict << 8, src, n, t1)
        rb = native.cap_put(b[0], b[1], typ | verdict << 8, src, n, t1)
        assert ra == rb
        assert list(a[0]) == list(b[0])
        assert a[1] == b[1]


def test_a_full_ring_counts_lost_records_and_says_so_before_the_next_one():
    cs, ring = _state(64)
    frame_body = bytes(10)
    assert C.put_py(cs, ring, C.CH_PC_IN, frame_body, 10, 100) == 1  # 22 bytes
    assert C.put_py(cs, ring, C.CH_PC_IN, frame_body, 10, 200) == 1  # 44
    assert C.put_py(cs, ring, C.CH_PC_IN, frame_body, 10, 300) == 0  # 66 > 63: lost
    assert C.put_py(cs, ring, C.CH_PC_IN, frame_body, 10, 400) == 0
    assert (cs[C.CS_LOST], cs[C.CS_LOST_T0], cs[C.CS_LOST_T1], cs[C.CS_LOST_TOTAL]) == (2, 300, 400, 2)
    out = bytearray()
    for _ in range(44):  # the port takes both records
        out.append(ring[cs[C.CS_TAIL]])
        cs[C.CS_TAIL] = (cs[C.CS_TAIL] + 1) & 63
    assert C.put_py(cs, ring, C.CH_DRV_IN, b"\x02\x03", 2, 500) == 1
    while cs[C.CS_TAIL] != cs[C.CS_HEAD]:
        out.append(ring[cs[C.CS_TAIL]])
        cs[C.CS_TAIL] = (cs[C.CS_TAIL] + 1) & 63
    recs = parse(out)
    assert [r[0] for r in recs] == ["pc_in", "pc_in", "lost", "drv_in"]
    assert recs[2][2] == struct.pack("<I", 2) and recs[2][3:] == (300, 400)
    assert cs[C.CS_LOST] == 0 and cs[C.CS_TOTAL] == 3


def test_nothing_is_written_while_recording_is_off():
    cs, ring = _state(64)
    cs[C.CS_ON] = 0
    assert C.put_py(cs, ring, C.CH_PC_IN, b"\x01", 1, 5) == 0
    assert native.cap_put(cs, ring, C.CH_PC_IN, b"\x01", 1, 5) == 0
    assert cs[C.CS_HEAD] == 0 and cs[C.CS_LOST_TOTAL] == 0


# --- what the bridge records, on both loops -----------------------------------------
def test_off_by_default_and_the_hello_says_how_the_jig_is_set():
    b = SimBench()
    assert not b.app.capture.on and b.app.params.ram[P.P_CAPTURE] == 0
    b.transact(frame.encode(2, frame.GET_COMMAND_POS))
    assert b.app.capture.pending() == 0
    b = bench(ver8=True, baud=230400, down_baud=57600)
    name, verdict, data, t0, t1 = parse(b.app.capture.drain_to(bytearray()))[0]
    assert name == "hello" and t0 == t1
    version, proto, mode, jig_id, up, down, ibt, ring = struct.unpack_from("<BBBBIIII", data)
    assert (version, proto, mode, jig_id, up, down, ibt, ring) == (C.VERSION, 1, 0, 1, 230400, 57600, 5000,
                                                                    C.RING_SIZE)
    assert data[20:24] == bytes(4)  # the CAN bitrate: no CAN port on this bench (format 2)
    assert data[24:] == b"MotorJig bridge 0.1"


def test_a_forwarded_transaction_is_four_records_in_wire_order():
    b = bench()
    req = frame.encode(2, frame.GET_COMMAND_POS)
    reply = b.transact(req)
    recs = records(b)
    assert [(r[0], r[1]) for r in recs] == [("pc_in", 0), ("drv_out", 0), ("drv_in", 0), ("pc_out", 0)]
    assert recs[0][2] == recs[1][2] == body(req)
    assert recs[2][2] == recs[3][2] == body(reply)
    t = [(r[3], r[4]) for r in recs]
    char = 10e6 / 115200
    # cut through: the copy starts while the request is still arriving (its AA goes on at
    # once: after the received frame's start as the host computes it, before the read that
    # brought its header), ends after it
    assert min(t[0][0] - char, t[0][1] - len(req) * char) <= t[1][0] < t[0][1] <= t[1][1]
    assert t[1][1] - t[1][0] == pytest.approx(len(req) * char, abs=char)  # the AA at once, then as they come
    # the drive's turnaround (300 µs on this bench) lies between request and reply
    assert t[2][0] - t[1][1] >= 300 - char
    assert min(t[2][0] - char, t[2][1] - len(reply) * char) <= t[3][0] < t[2][1] <= t[3][1]


def test_a_local_frame_is_recorded_with_the_stub_on_the_driver_bus_and_the_reply():
    b = bench()
    req = frame.encode(1, frame.GET_SLAVE_INFO)
    reply = b.transact(req)
    recs = records(b)
    assert [(r[0], r[1]) for r in recs] == [("drv_out", R.SHORT), ("pc_in", 0), ("pc_out", 0)]
    assert recs[0][2] == b"\x01"  # AA CC 01 AA EE
    assert recs[1][2] == body(req) and recs[2][2] == body(reply)


def test_bad_frames_are_recorded_with_the_parser_verdict_on_both_buses():
    b = bench()
    good = frame.encode(2, frame.GET_COMMAND_POS)
    bad_crc = good[:-3] + bytes([good[-3] ^ 1]) + good[-2:]
    b.pc.send(bad_crc)
    b.run_for(20000)
    b.pc.send(b"\xaa\xcc\x02\xaa\x11\x22")  # stuffing error
    b.run_for(20000)
    b.pc.send(b"\xaa\xcc\x02\x51\x00")  # then silence: timeout
    b.run_for(20000)
    recs = [r for r in records(b) if r[0] in ("pc_in", "drv_out")]
    got = [(r[0], R.verdict_name(r[1]), r[2]) for r in recs]
    assert got[:2] == [("pc_in", "bad_crc", body(bad_crc)), ("drv_out", "bad_crc", body(bad_crc))]
    assert got[2:4] == [("pc_in", "bad_stuffing", b"\x02"), ("drv_out", "bad_stuffing", b"\x02")]
    assert got[4:6] == [("pc_in", "timeout", b"\x02\x51\x00"), ("drv_out", "timeout", b"\x02\x51\x00")]
    # a frame cut by silence ended with its last byte, not when the silence was noticed
    t_last = recs[4][4]
    assert recs[4][3] <= t_last < recs[4][3] + 1000


def test_store_and_forward_records_drops_too():
    b = bench(jig_params={P.P_FORWARD_MODE: P.STORE_AND_FORWARD})
    good = frame.encode(2, frame.GET_COMMAND_POS)
    b.pc.send(good[:-3] + bytes([good[-3] ^ 1]) + good[-2:])
    b.run_for(20000)
    reply = b.transact(good)
    recs = records(b)
    assert [(r[0], R.verdict_name(r[1])) for r in recs] == [
        ("pc_in", "bad_crc"), ("pc_in", "good"), ("drv_out", "good"), ("drv_in", "good"), ("pc_out", "good")]
    assert recs[4][2] == body(reply)
    b.transact(good)  # recording on did not change what the bridge does
    assert b.counters["forwards"] == 2 and b.counters["replies"] == 2 and b.counters["cut_corrupt"] == 0


def test_the_parameter_switches_recording_at_once_and_the_reply_says_so():
    b = SimBench()
    set_on = frame.encode(1, frame.SET_PARAMETER, bytes([P.P_CAPTURE]) + struct.pack("<i", 1))
    assert b.transact(set_on)[4] == 0  # AA CC 01 12 status: OK
    assert b.app.capture.on
    b.transact(frame.encode(2, frame.GET_COMMAND_POS))
    recs = parse(b.app.capture.drain_to(bytearray()))
    assert recs[0][0] == "hello"
    assert [r[0] for r in recs[1:] if r[0] != "clock"] == ["pc_in", "drv_out", "drv_in", "pc_out"]
    off = frame.encode(1, frame.SET_PARAMETER, bytes([P.P_CAPTURE]) + struct.pack("<i", 0))
    b.transact(off)
    assert not b.app.capture.on
    b.transact(frame.encode(2, frame.GET_COMMAND_POS))
    assert b.app.capture.pending() == 0


class HostEnd:
    """The HAL's capture port as the contract has it (docs/hal.md): a PC on the other
    end that sends commands and takes ``room`` bytes a write."""

    def __init__(self, room=10 ** 9):
        self.room = room
        self.cmds = bytearray()
        self.got = bytearray()

    def any(self):
        return len(self.cmds)

    def readinto(self, buf):
        n = min(len(buf), len(self.cmds))
        buf[0:n] = self.cmds[0:n]
        del self.cmds[0:n]
        return n

    def write(self, buf):
        n = min(len(buf), self.room)
        self.got += bytes(buf[0:n])
        return n


def test_start_and_stop_from_the_capture_port_and_a_stream_that_arrives_whole():
    b = SimBench()
    port = HostEnd(room=7)  # an odd size: records split across writes
    b.app.capture.port = port
    port.cmds += b"S"
    b.run_for(20000)
    assert b.app.capture.on and b.app.params.ram[P.P_CAPTURE] == 1
    for slave in (2, 3, 2):
        b.transact(frame.encode(slave, frame.GET_COMMAND_POS))
    b.run_for(50000)
    recs = parse(port.got)
    assert recs[0][0] == "hello"
    assert [r[0] for r in recs[1:] if r[0] != "clock"] == ["pc_in", "drv_out", "drv_in", "pc_out"] * 3
    assert b.app.capture.pending() == 0
    # a second S (a new reader) starts the stream afresh: the ring emptied, a hello first
    b.transact(frame.encode(2, frame.GET_COMMAND_POS))
    port.room = 0
    b.transact(frame.encode(2, frame.GET_COMMAND_POS))
    assert b.app.capture.pending() > 0
    port.room = 7
    port.got = bytearray()
    port.cmds += b"S"
    b.run_for(20000)
    assert [r[0] for r in parse(port.got)] == ["hello"]
    port.cmds += b"X"
    b.run_for(20000)
    assert not b.app.capture.on and b.app.params.ram[P.P_CAPTURE] == 0


def test_a_port_nobody_reads_fills_the_ring_and_the_next_reader_learns_how_much_was_lost():
    b = bench()
    cap = b.app.capture
    port = HostEnd(room=0)
    cap.port = port
    req = frame.encode(2, frame.GET_COMMAND_POS)
    n = 0
    while cap.cs[C.CS_LOST] == 0:
        b.transact(req)
        n += 1
        assert n < 2000
    for _ in range(3):
        b.transact(req)
    lost = cap.cs[C.CS_LOST]
    assert lost >= 6  # three transactions, two records each (a frame passed on is one), at least
    assert b.counters["replies"] == n + 3  # the bridge did not notice
    port.room = 10 ** 9
    b.run_for(20000)
    b.transact(req)
    for _ in range(100):  # the whole ring reaches the port, a slow pass at a time
        b.run_for(20000)
        if cap.pending() == 0:
            break
    recs = parse(port.got)
    names = [r[0] for r in recs]
    k = names.index("lost")
    assert struct.unpack("<I", recs[k][2])[0] == lost
    assert names[k + 1:] == ["pc_in", "drv_out", "drv_in", "pc_out"]


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["good", "bad_crc", "cut", "garbage", "local", "resync", "long"]),
                          st.sampled_from([0, 300, 8000])), min_size=1, max_size=10),
       st.sampled_from([1, 5, 64]))
def test_the_records_add_up_to_the_parsers_own_counters(steps, chunk):
    """Every frame and fragment a parser counted is one record with that verdict (noise
    in bytes): nothing recorded twice, nothing left out."""
    b = bench(stream_chunk=chunk)
    good = frame.encode(2, frame.GET_COMMAND_POS)
    rnd = random.Random(len(steps) * 7 + chunk)
    for kind, gap in steps:
        wire = {
            "good": good, "local": frame.encode(1, frame.GET_AXIS_STATUS),
            "bad_crc": good[:-3] + bytes([good[-3] ^ 4]) + good[-2:], "cut": good[:5],
            "garbage": bytes(rnd.randrange(256) for _ in range(9)), "resync": good[:5] + good,
            "long": b"\xaa\xcc" + bytes(300) + b"\xaa\xee",
        }[kind]
        end = b.pc.send(wire)  # (when its last byte will have gone)
        b.run_for(max(0.0, end - b.clock.now) + gap + 20000)
    recs = records(b)
    p = b.app.up_parser
    counted = {}
    for name, verdict, data, _t0, _t1 in recs:
        if name == "pc_in":
            counted[verdict] = counted.get(verdict, 0) + 1
        elif name == "pc_noise":
            counted[R.NOISE] = counted.get(R.NOISE, 0) + struct.unpack("<I", data)[0]
    want = {R.COUNTER_VERDICT[c]: v for c, v in zip(parser.COUNTER_NAMES, p.counters()) if v}
    assert counted == want


def test_the_records_of_the_pump_are_the_portable_loops():
    """Same traffic, same records, byte for byte (times included: the bench's clock is
    virtual and both loops take their ticks at the same moments)."""
    steps = [frame.encode(2, frame.GET_COMMAND_POS), frame.encode(1, frame.GET_SLAVE_INFO),
             frame.encode(3, frame.GET_AXIS_STATUS)[:6], frame.encode(99, frame.MOVE_STOP),
             frame.encode(2, frame.GET_ALL_STATUS)]
    streams = []
    for fast in (False, True):
        b = bench(fastpath=fast)
        for wire in steps:
            b.pc.send(wire)
            b.run_for(30000)
        streams.append(bytes(b.app.capture.drain_to(bytearray())))
    assert len(parse(streams[0])) >= 14
    assert streams[0] == streams[1]


class TimedHostEnd(HostEnd):
    """HostEnd that notes the bench time of every write that took bytes."""

    def __init__(self, clock):
        HostEnd.__init__(self)
        self.clock = clock
        self.times = []

    def write(self, buf):
        n = HostEnd.write(self, buf)
        if n:
            self.times.append(self.clock.now)
        return n


def test_records_go_out_while_the_drive_thinks_not_while_the_pc_talks():
    """The stream window: a forwarded request awaiting its reply (the drive's
    turnaround), or a PC bus quiet for QUIET_US; never in the middle of PC traffic
    the bridge must pass on at once."""
    b = bench()
    port = TimedHostEnd(b.clock)
    b.app.capture.port = port
    b.run_for(20000)  # the hello goes (the bus is quiet)
    port.times = []
    # the PC keeps talking to the jig itself, a frame every 500 µs: no window
    local = frame.encode(1, frame.GET_AXIS_STATUS)
    t0 = b.clock.now
    for _ in range(8):
        end = b.pc.send(local)
        b.run_for(max(0.0, end - b.clock.now) + 500)
    assert b.app.capture.pending() > 0 and port.times == []
    # ... then falls silent: out after QUIET_US
    b.run_for(C.QUIET_US + 12000)
    assert b.app.capture.pending() == 0 and port.times and port.times[0] > t0
    # a forwarded request: out in the drive's turnaround, before its reply starts
    port.times = []
    port.got = bytearray()
    b.run_for(C.STREAM_US)
    req = frame.encode(2, frame.GET_COMMAND_POS)
    end = b.pc.send(req)
    reply_start = []
    char = 10e6 / 115200

    def spy(data, t_end):  # the drive's reply comes as one segment, the jig's copy in pieces
        if len(data) > 4 and data[2] == 2:
            reply_start.append(t_end - len(data) * char)

    b.down_bus.add_node("spy", spy, record=False)
    b.run_for(max(0.0, end - b.clock.now) + 5000)
    recs = parse(port.got)
    assert [r[0] for r in recs[:2]] == ["pc_in", "drv_out"]  # the request's record, alone first
    assert len(reply_start) == 1 and port.times[0] < reply_start[0]


def test_a_reply_the_pc_talks_over_is_recorded_as_far_as_it_went_on_the_pc_bus():
    from jig import bridge as B

    b = bench()
    # The jig's transceivers have /RE tied to DE: relaying, it hears nothing from the PC
    # (the bench models that). The firmware still acts on PC bytes that reach it while it
    # relays -- ones in its ring from before DE went up, or a board whose receiver stays
    # on --, so here its PC-side receiver stays on.
    b.hal.up.node.deaf_with_de = False
    sent = []
    b.up_bus.monitor = lambda seg, data: sent.append(bytes(seg.data)) if seg.node.name == "jig-up" else None
    b.pc.send(frame.encode(2, frame.GET_ALL_STATUS))
    b.clock.run_while(lambda: not b.app.bridge.bs[B.B_REL], 50000)
    b.run_for(300)  # a few bytes of the reply relayed to the PC
    b.pc.send(frame.encode(3, frame.GET_COMMAND_POS))  # the PC talks over it
    b.run_for(50000)
    cut = [r for r in records(b) if r[0] == "pc_out"]
    wire = b"".join(sent)
    assert cut[0][1] == R.TIMEOUT and len(cut[0][2]) >= 2
    # what the record holds is what went out: AA CC and the body so far, no tail
    assert wire.startswith(b"\xaa\xcc" + cut[0][2]) and b"\xaa\xee" not in wire[:2 + len(cut[0][2])]


def test_a_full_ring_counts_only_records_it_dropped_not_its_own_retries():
    b = bench()
    cap = b.app.capture
    cap.port = HostEnd(room=0)  # nobody reads
    req = frame.encode(2, frame.GET_COMMAND_POS)
    while cap.cs[C.CS_LOST] == 0:
        b.transact(req)
    lost = cap.cs[C.CS_LOST]
    b.run_for(5000000)  # 5 s without traffic: clock records are due, and wait for room
    b.pc.send(b"\x00\x11\x22")  # noise: its record waits too
    b.run_for(200000)
    assert cap.cs[C.CS_LOST] == lost and cap.cs[C.CS_LOST_TOTAL] == lost
    feeds = b.hal.wdt_feeds  # one per slow pass
    b.run_for(100000)
    assert b.hal.wdt_feeds - feeds <= 12  # a port that takes nothing is asked at the slow pace (10 ms)


def test_the_hello_says_how_the_jig_runs_not_what_takes_effect_at_the_next_boot():
    b = bench()
    port = HostEnd()
    b.app.capture.port = port
    for num, value in ((P.P_UP_BAUD, 921600), (P.P_PROTOCOL, 1), (P.P_FORWARD_MODE, 1)):  # restart parameters
        assert b.transact(frame.encode(1, frame.SET_PARAMETER, bytes([num]) + struct.pack("<i", value)))[4] == 0
    port.cmds += b"S"  # a new reader
    b.run_for(20000)
    hello = [r for r in parse(port.got) if r[0] == "hello"][-1][2]
    assert struct.unpack_from("<BBBBII", hello) == (C.VERSION, 0, 0, 1, 115200, 115200)
    # an immediate parameter it reports: a new hello with it
    port.got = bytearray()
    b.transact(frame.encode(1, frame.SET_PARAMETER, bytes([P.P_INTERBYTE_US]) + struct.pack("<i", 2500)))
    b.run_for(20000)
    hellos = [r[2] for r in parse(port.got) if r[0] == "hello"]
    assert len(hellos) == 1 and struct.unpack_from("<I", hellos[0], 12)[0] == 2500


def test_the_jigs_counters_report_records_written_and_lost_and_reset_with_the_others():
    b = bench()
    cap = b.app.capture
    cap.port = HostEnd(room=0)
    req = frame.encode(2, frame.GET_COMMAND_POS)
    while cap.cs[C.CS_LOST] == 0:
        b.transact(req)
    b.transact(req)
    c = b.counters  # (ReadCounters' layout: jig.diag.WIRE_NAMES)
    assert c["capture_records"] == cap.cs[C.CS_TOTAL] > 100 and c["capture_lost"] == cap.cs[C.CS_LOST_TOTAL] >= 2
    b.transact(frame.encode(1, 0xF1))  # ResetCounters
    b.transact(req)
    c = b.counters
    # the ring is still full: ResetCounters' own reply (recorded after the reset) and both records of req dropped
    assert c["capture_records"] == 0 and c["capture_lost"] == 3


def test_a_pc_silent_for_longer_than_half_a_tick_period_is_still_a_quiet_bus():
    from jig import bridge as B

    b = bench()
    br = b.app.bridge
    now = b.hal.ticks_us()
    br.bs[B.B_T_PC] = (now - 1000) & 0x3FFFFFFF
    assert not br.stream_window(now)  # the PC just talked
    br.bs[B.B_T_PC] = (now - 3000) & 0x3FFFFFFF
    assert br.stream_window(now)
    br.bs[B.B_T_PC] = (now - 0x20000000 - 5000) & 0x3FFFFFFF  # 9 minutes ago: ticks_diff comes out negative
    assert br.stream_window(now)
