"""The simulated bus itself: wire time, DE gating, collisions, echo."""

from motorjig.sim import Bus, VirtualClock


def make(baud=115200):
    clock = VirtualClock(0.0)
    bus = Bus(clock, baud)
    got = {}

    def rx(name):
        got[name] = []
        return lambda data, t: got[name].append((t, bytes(data)))

    a = bus.add_node("a", rx("a"))
    b = bus.add_node("b", rx("b"), auto_de=True)
    return clock, bus, a, b, got


def test_wire_time_and_delivery():
    clock, bus, a, b, got = make(9600)
    a.set_de(1)
    end = a.transmit(b"\x01\x02\x03")
    assert abs(end - 3 * 10e6 / 9600) < 1e-6
    clock.run_until(end - 1)
    assert got["b"] == []
    clock.run_until(end)
    assert got["b"] == [(end, b"\x01\x02\x03")] and got["a"] == []


def test_bytes_sent_with_de_low_are_lost():
    clock, bus, a, b, got = make()
    bt = bus.bt
    a.transmit(b"ABCD")  # DE never raised
    clock.run_until(1000)
    assert got["b"] == [] and bus.lost == 4
    # DE raised late (during byte 0) and dropped early (during byte 3)
    t0 = clock.now
    a.transmit(b"ABCD")
    clock.run_until(t0 + 0.5 * bt)
    a.set_de(1)
    clock.run_until(t0 + 3.5 * bt)
    a.set_de(0)
    clock.run_until(t0 + 10 * bt)
    assert got["b"][-1][1] == b"BC"


def test_collisions_corrupt_both_talkers():
    clock, bus, a, b, got = make()
    c = bus.add_node("c", auto_de=True)
    a.set_de(1)
    a.transmit(b"\x10\x11\x12\x13\x14\x15")
    clock.run_until(2 * bus.bt)
    c.transmit(b"\x20\x21")  # overlaps bytes 2..3 of a's segment
    clock.run_until(100 * bus.bt)
    short, data = [d for _t, d in got["b"]]  # c's segment ends first
    assert data[:2] == b"\x10\x11" and data[4:] == b"\x14\x15"
    assert data[2] != 0x12 and data[3] != 0x13
    assert short[0] != 0x20 and short[1] != 0x21
    assert bus.collisions == 4


def test_echo_only_when_enabled():
    clock, bus, a, b, got = make()
    a.echo = True
    a.set_de(1)
    a.transmit(b"xy")
    clock.run_until(1000)
    assert got["a"] == got["b"] and got["a"][0][1] == b"xy"


def test_segments_of_one_node_queue_back_to_back():
    clock, bus, a, b, got = make()
    e1 = b.transmit(b"12")
    e2 = b.transmit(b"34")
    assert abs(e2 - e1 - 2 * bus.bt) < 1e-6
    clock.run_until(e2)
    assert [d for _t, d in got["a"]] == [b"12", b"34"] and bus.collisions == 0



def test_corrupt_flips_one_bit_so_the_crc_fails():
    from jig import frame as F
    from jig.parser import FrameParser
    from motorjig.sim.link import flip_for_crc

    clock, bus, a, b, got = make()
    frame = F.encode(2, 0x51, b"\x00\xaa\x00\x00\x00")  # a stuffed AA AA inside
    b.corrupt(1)
    b.transmit(frame)
    b.transmit(frame)
    clock.run_until(clock.now + 10000.0)
    (t1, bad), (t2, good) = got["a"]
    assert good == frame and len(bad) == len(frame) and bus.corrupted == 1 and b.corrupt_next == 0
    assert sum(x != y for x, y in zip(bad, frame)) == 1
    p = FrameParser()
    p.feed(bad)
    assert not p.ready and p.crc_errors == 1 and p.stuff_errors == 0
    # frames full of stuffed bytes, one with 0xAA in its CRC: still a CRC error, never a framing error
    crc_aa = next(F.encode(3, 0x13, bytes([i])) for i in range(256)
                  if 0xAA in F.encode(3, 0x13, bytes([i]))[-4:-2])
    for data in (F.encode(1, 0x01, b"\xaa" * 5), F.encode(0xAA, 0xAA, b"\xab\xaa"), crc_aa):
        q = FrameParser()
        q.feed(flip_for_crc(data))
        assert (q.crc_errors, q.stuff_errors, q.good) == (1, 0, 0)


# --- streaming delivery (a UART receiver sees each byte as its stop bit ends) -------------


def make_stream(baud=9600, chunk=1):
    clock = VirtualClock(0.0)
    bus = Bus(clock, baud, chunk=chunk)
    got = {"s": [], "w": []}
    a = bus.add_node("a")
    s = bus.add_node("s", lambda data, t: got["s"].append((t, bytes(data))), stream=True)
    w = bus.add_node("w", lambda data, t: got["w"].append((t, bytes(data))))  # whole segments
    return clock, bus, a, s, w, got


def close(x, y):
    return abs(x - y) < 1e-6


def test_streaming_node_gets_each_byte_when_its_stop_bit_ends():
    clock, bus, a, s, w, got = make_stream()
    bt = bus.bt
    a.set_de(1)
    end = a.transmit(b"\x01\x02\x03")
    clock.run_until(bt * 1.5)
    assert got["s"] == [(bt, b"\x01")] and got["w"] == []  # byte 1 is still on the wire
    clock.run_until(end)
    assert [d for _t, d in got["s"]] == [b"\x01", b"\x02", b"\x03"]
    assert all(close(t, (i + 1) * bt) for i, (t, _d) in enumerate(got["s"]))
    assert got["w"] == [(end, b"\x01\x02\x03")]  # non-streaming nodes: whole segment at its end


def test_streaming_in_chunks_of_k_bytes():
    clock, bus, a, s, w, got = make_stream(chunk=2)
    bt = bus.bt
    a.set_de(1)
    a.transmit(b"\x01\x02\x03\x04\x05")
    clock.run_until(10 * bt)
    assert [d for _t, d in got["s"]] == [b"\x01\x02", b"\x03\x04", b"\x05"]
    assert [round(t / bt, 6) for t, _d in got["s"]] == [2, 4, 5]


def test_streamed_bytes_sent_with_de_low_are_lost_one_by_one():
    clock, bus, a, s, w, got = make_stream()
    bt = bus.bt
    a.transmit(b"ABCD")
    clock.run_until(0.5 * bt)
    a.set_de(1)  # during byte A: A is lost
    clock.run_until(3.5 * bt)
    a.set_de(0)  # during byte D: D is lost
    clock.run_until(10 * bt)
    assert [(round(t / bt, 6), d) for t, d in got["s"]] == [(2, b"B"), (3, b"C")]
    assert got["w"][0][1] == b"BC" and bus.lost == 2


def test_streamed_collision_garbles_only_the_overlapping_bytes_when_they_arrive():
    clock, bus, a, s, w, got = make_stream()
    bt = bus.bt
    c = bus.add_node("c", auto_de=True)
    a.set_de(1)
    a.transmit(b"\x10\x11\x12\x13\x14\x15")
    clock.run_until(1.5 * bt)
    assert got["s"] == [(bt, b"\x10")]
    clock.run_until(2 * bt)
    c.transmit(b"\x20\x21")  # overlaps bytes 2..3 of a's segment
    clock.run_until(100 * bt)
    from_a = [d for t, d in got["s"] if len(d) == 1]
    assert from_a[:2] == [b"\x10", b"\x11"] and from_a[-2:] == [b"\x14", b"\x15"]
    assert b"\x12" not in from_a and b"\x13" not in from_a and b"\x20" not in from_a
    assert bus.collisions == 4
    # the whole-segment receiver sees the same bytes (c's segment first: it ends first)
    assert sorted(b"".join(d for _t, d in got["s"])) == sorted(b"".join(d for _t, d in got["w"]))


def test_frame_written_in_pieces_with_de_held():
    clock, bus, a, s, w, got = make_stream()
    bt = bus.bt
    a.set_de(1)
    e1 = a.transmit(b"AB")
    clock.run_until(e1 + 3 * bt)  # the rest has not arrived yet: the line idles, DE stays high
    e2 = a.transmit(b"CD")
    clock.run_until(e2)
    a.set_de(0)
    clock.run_until(e2 + 10 * bt)
    assert b"".join(d for _t, d in got["s"]) == b"ABCD" and bus.lost == 0
    assert [round(t / bt, 6) for t, _d in got["s"]] == [1, 2, 6, 7]
    assert [d for _t, d in got["w"]] == [b"AB", b"CD"]
    assert [v for _t, v in a.de_log] == [1, 0]
    # DE dropped between two pieces: the second one never reaches the line
    a.set_de(1)
    e3 = a.transmit(b"EF")
    clock.run_until(e3)
    a.set_de(0)
    a.transmit(b"GH")
    clock.run_until(clock.now + 10 * bt)
    assert b"".join(d for _t, d in got["s"]).endswith(b"EF") and bus.lost == 2


def test_collision_across_pieces():
    clock, bus, a, s, w, got = make_stream()
    bt = bus.bt
    c = bus.add_node("c", auto_de=True)
    a.set_de(1)
    e1 = a.transmit(b"\x01\x02")
    clock.run_until(e1 + bt)
    c.transmit(b"\x30\x31")  # from the gap into the second piece's first byte
    clock.run_until(e1 + 2 * bt)
    e2 = a.transmit(b"\x03\x04")
    clock.run_until(e2 + 10 * bt)
    a.set_de(0)
    (_t1, piece1), (_tc, from_c), (_t2, piece2) = got["w"]  # in order of their ends
    assert piece1 == b"\x01\x02" and piece2[1:] == b"\x04" and piece2[0] != 0x03
    assert from_c[0] == 0x30 and from_c[1] != 0x31  # c's first byte went out in the gap
    assert bus.collisions == 2  # a's byte 3 and c's second byte


def test_corrupt_frame_sent_in_one_byte_pieces_fails_its_crc():
    from jig import frame as F
    from jig.parser import FrameParser

    clock, bus, a, s, w, got = make_stream(baud=115200)
    frame = F.encode(2, 0x51, b"\x00\xaa\x00\x00\x00")
    a.corrupt(1)
    a.set_de(1)
    for i in range(len(frame)):
        clock.run_until(a.transmit(frame[i:i + 1]))
    a.set_de(0)
    clock.run_until(clock.now + 1000.0)
    bad = b"".join(d for _t, d in got["s"])
    assert len(bad) == len(frame) and sum(x != y for x, y in zip(bad, frame)) == 1
    assert bus.corrupted == 1 and a.corrupt_next == 0
    p = FrameParser()
    p.feed(bad)
    assert (p.crc_errors, p.stuff_errors, p.good) == (1, 0, 0)


def test_one_event_per_segment_when_no_streaming_node_hears_it():
    clock, bus, a, s, w, got = make_stream()
    s.transmit(b"0123456789")  # the streaming node is the sender and has no echo
    assert len(clock._heap) == 1
    a.transmit(b"0123456789")  # s hears this one: the events come one byte at a time
    assert len(clock._heap) == 2
    clock.run_until(1e6)
    assert len(got["s"]) == 0 and bus.lost == 20  # nobody raised DE


def test_corrupt_counts_frames_not_pieces():
    """corrupt(2) on a frame sent byte by byte flips one bit in it and one in the next frame."""
    from jig import frame as F
    from jig.parser import FrameParser

    clock, bus, a, s, w, got = make_stream(baud=115200)
    frames = [F.encode(2, 0x51, bytes([i, 0xAA, 0xAA])) for i in range(3)]
    a.corrupt(2)
    a.set_de(1)
    for fr in frames:
        for i in range(len(fr)):
            clock.run_until(a.transmit(fr[i:i + 1]))
    a.set_de(0)
    clock.run_until(clock.now + 1000.0)
    p = FrameParser()
    p.feed(b"".join(d for _t, d in got["s"]))
    assert (p.crc_errors, p.stuff_errors, p.good) == (2, 0, 1) and bus.corrupted == 2
    # whole frames, one segment each: one bit in each of the next n
    a.corrupt(1)
    a.set_de(1)
    for fr in frames[:2]:
        clock.run_until(a.transmit(fr))
    a.set_de(0)
    clock.run_until(clock.now + 1000.0)
    q = FrameParser()
    q.feed(b"".join(d for _t, d in got["w"][-2:]))
    assert (q.crc_errors, q.good) == (1, 1) and bus.corrupted == 3
