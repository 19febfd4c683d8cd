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
