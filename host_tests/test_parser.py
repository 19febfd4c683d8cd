"""FrameParser unit behaviour: the table itself, the feed contract, timeouts, limits."""

import os

import pytest

from jig import crc, frame, parser
from jig.parser import BODY, ESCAPE, HEADER, HUNT, FrameParser

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def feed_all(p, data, now=None):
    frames = []
    i = 0
    while i < len(data):
        i = p.feed(data, i, len(data), now)
        if p.ready:
            frames.append(bytes(p.body[: p.body_len]))
    return frames


def test_table_is_complete_and_consistent():
    n_states, n_classes = len(parser.STATE_NAMES), len(parser.CLASS_NAMES)
    assert len(parser.TRANSITIONS) == n_states
    for row in parser.TRANSITIONS:
        assert len(row) == n_classes
        for action, nxt in row:
            assert 0 <= action < len(parser.ACTION_NAMES) and 0 <= nxt < n_states
    # The bulk path skips/copies runs of non-0xAA bytes in HUNT and BODY with one find:
    # that is only right while the table says those bytes are noise/stored and stay.
    for c in (parser.C_HEADER, parser.C_TAIL, parser.C_OTHER):
        assert parser.TRANSITIONS[HUNT][c] == (parser.A_NOISE, HUNT)
        assert parser.TRANSITIONS[BODY][c] == (parser.A_STORE, BODY)
    assert parser.TRANSITIONS[HUNT][parser.C_STUFF][1] == HEADER
    assert parser.TRANSITIONS[BODY][parser.C_STUFF][1] == ESCAPE


def test_byte_classes():
    classes = [parser.byte_class(b) for b in range(256)]
    assert classes[0xAA] == parser.C_STUFF and classes[0xCC] == parser.C_HEADER
    assert classes[0xEE] == parser.C_TAIL
    assert classes.count(parser.C_OTHER) == 253


def test_generated_state_doc_is_committed_and_current():
    import gen_parser_doc  # tools/docgen is on the path (conftest)
    with open(os.path.join(ROOT, "docs", "parser-states.md"), encoding="utf-8") as f:
        assert f.read() == gen_parser_doc.render(), "run: python tools/docgen/gen_parser_doc.py"


def test_feed_stops_after_each_good_frame():
    a = frame.encode(1, 0x40)
    b = frame.encode(2, 0x51, b"\x00\x18\xfc\xff\xff")
    data = b"\x00" + a + b + b"\x11"
    p = FrameParser()
    i = p.feed(data)
    assert p.ready and i == 1 + len(a)
    assert (p.slave, p.sync, p.ftype, p.data_start, p.data_end) == (1, -1, 0x40, 2, 2)
    i = p.feed(data, i)
    assert p.ready and i == 1 + len(a) + len(b)
    assert (p.slave, p.ftype) == (2, 0x51)
    assert bytes(p.body[p.data_start : p.data_end]) == b"\x00\x18\xfc\xff\xff"
    dst = bytearray(300)
    assert p.copy_frame(dst, 3) == p.body_len == 9
    assert bytes(dst[3:12]) == bytes(p.body[:9])
    assert p.feed(data, i) == len(data) and not p.ready
    assert p.good == 2 and p.noise == 2


def test_ver8_fields():
    p = FrameParser(ver8=True)
    p.feed(frame.encode(3, 0x01, b"\x00\x14AB\x00", sync=0xAA))
    assert p.ready
    assert (p.slave, p.sync, p.ftype, p.data_start, p.data_end) == (3, 0xAA, 0x01, 3, 8)


def test_poll_without_data_does_not_keep_a_partial_frame_alive():
    p = FrameParser(interbyte_timeout_us=5000)
    p.feed(b"\xaa\xcc\x01\x40", now=0)
    for t in (2000, 4000):  # the main loop polls with nothing new
        p.feed(b"", now=t)
        assert p.in_frame()
    p.feed(b"", now=5001)
    assert not p.in_frame() and p.timeouts == 1


def test_check_timeout_and_wraparound():
    p = FrameParser(interbyte_timeout_us=1000)
    t0 = 0x3FFFFF00  # just before the tick counter wraps
    p.feed(b"\xaa\xcc\x01", now=t0)
    assert not p.check_timeout((t0 + 1000) & 0x3FFFFFFF)
    assert p.check_timeout((t0 + 1001) & 0x3FFFFFFF)
    assert p.timeouts == 1 and p.state == HUNT
    assert not p.check_timeout(t0 + 10**6)  # nothing pending: nothing to drop
    p.feed(b"\xaa", now=0)  # a lone 0xAA that times out is noise
    assert p.check_timeout(2000) and p.noise == 1 and p.timeouts == 1


def test_reset_keeps_counters():
    p = FrameParser()
    p.feed(b"\x00\xaa\xcc\x01\x01")
    p.reset()
    assert p.state == HUNT and p.body_len == 0 and p.noise == 1
    assert feed_all(p, b"\xc1\xe0\xaa\xee") == []  # the tail alone is not a frame


def test_counters_and_errors():
    p = FrameParser()
    stream = (b"\x00"  # noise
              + b"\xaa\xcc\x01\x01\xc1\xe1\xaa\xee"  # bad CRC
              + b"\xaa\xcc\x01\xaa\x01"  # stuffing error
              + b"\xaa\xcc\x01\xaa\xee"  # short
              + b"\xaa\xcc\x01\xaa\xcc" + frame.encode(1, 1)[2:])  # resync, then good
    assert len(feed_all(p, stream)) == 1
    assert p.counters() == (1, 1, 1, 1, 1, 0, 0, 1)
    assert dict(zip(parser.COUNTER_NAMES, p.counters()))["crc_errors"] == 1
    out = [0] * 8
    assert p.counters(out) is out and out == list(p.counters())
    assert p.errors == 4
    p.reset_counters()
    assert p.counters() == (0,) * 8


def raw_frame(body_len_without_crc, ver8=False):
    """Wire bytes of a valid frame with the given number of body bytes before the CRC."""
    head = 3 if ver8 else 2
    data = bytes((i * 7) & 0xFF for i in range(body_len_without_crc - head))
    b = bytes([1, 9, 0x12] if ver8 else [1, 0x12]) + data
    c = crc.crc16(b)
    b += bytes([c & 0xFF, c >> 8])
    return b"\xaa\xcc" + b.replace(b"\xaa", b"\xaa\xaa") + b"\xaa\xee"


@pytest.mark.parametrize("bulk", [True, False])
def test_length_limits_per_mode(bulk):
    # Ver6: id, type, 249 data bytes, CRC = 253 body bytes is the longest allowed.
    p = FrameParser(bulk=bulk)
    assert len(feed_all(p, raw_frame(251))) == 1
    assert feed_all(p, raw_frame(252)) == [] and p.overlong == 1
    # Ver8 has the sync byte too: 254.
    p = FrameParser(ver8=True, bulk=bulk)
    assert len(feed_all(p, raw_frame(252, True))) == 1
    assert feed_all(p, raw_frame(253, True)) == [] and p.overlong == 1
    # shortest in both modes: id, one byte, CRC. A Ver8 drive CRC-checks such a
    # body whole and reads id / sync / type from its first three bytes, so the
    # type is the first CRC byte and the data length is -1.
    assert len(feed_all(FrameParser(bulk=bulk), raw_frame(2))) == 1
    p = FrameParser(ver8=True, bulk=bulk)
    assert feed_all(p, b"\xaa\xcc\x01\x51\xaa\xee") == [] and p.short == 1
    probe = frame.encode(5, frame.GET_COMMAND_POS)  # AA CC 05 51 crcL crcH AA EE
    p.feed(probe)
    assert p.ready and p.body_len == 4
    assert (p.slave, p.sync, p.ftype) == (5, 0x51, probe[4])
    assert p.data_end - p.data_start == -1


def test_bulk_and_table_paths_agree_on_a_mixed_stream():
    import random

    rng = random.Random(11)
    parts = []
    for _ in range(300):
        r = rng.random()
        if r < 0.6:
            parts.append(frame.encode(rng.randrange(16), rng.randrange(256),
                                      bytes(rng.choice((0xAA, 0xCC, rng.randrange(256))) for _ in range(rng.randrange(30)))))
        elif r < 0.8:
            parts.append(bytes(rng.choice((0xAA, 0xCC, 0xEE, rng.randrange(256))) for _ in range(rng.randrange(8))))
        else:
            parts.append(bytes(rng.randrange(256) for _ in range(rng.randrange(400))))
    data = b"".join(parts)
    results = []
    for bulk in (True, False):
        p = FrameParser(bulk=bulk)
        results.append((feed_all(p, data), p.counters()))
    assert results[0] == results[1]
    assert results[0][1][0] > 100


def test_late_drain_of_a_long_burst_is_not_a_gap_with_byte_us():
    # 115200 baud: 86.8 us per character. A main loop that drains every 20 ms gets
    # ~230 bytes of continuous traffic per read; the last byte's time then lies
    # 20 ms after the previous read's, but the line was never silent.
    frames = b"".join(frame.encode(1, 0x43, bytes(range(40))) for _ in range(12))
    chunks = [frames[k : k + 230] for k in range(0, len(frames), 230)]
    for byte_us, want_good, want_timeouts in ((87, 12, 0), (0, None, None)):
        p = FrameParser(interbyte_timeout_us=5000, byte_us=byte_us)
        t = 0
        for chunk in chunks:
            t += len(chunk) * 87
            i = 0
            while i < len(chunk):
                i = p.feed(chunk, i, len(chunk), t)
        if want_good is not None:
            assert (p.good, p.timeouts) == (want_good, want_timeouts)
        else:
            assert p.timeouts > 0  # without byte_us the late reads look like gaps
    # a real silence is still seen with byte_us set
    p = FrameParser(interbyte_timeout_us=5000, byte_us=87)
    p.feed(b"\xaa\xcc\x01\x43", now=1000)
    tail = frame.encode(1, 0x43)[4:]
    p.feed(tail, now=1000 + 6000 + len(tail) * 87)
    assert p.timeouts == 1 and p.good == 0
