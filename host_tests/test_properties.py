"""Property tests (hypothesis) of the frame parser.

The parser is compared with a plain byte-by-byte reference written straight from the
protocol notes (no table, no bulk path), and checked for: encode->parse round trips,
arbitrary input never raising or yielding a frame with a bad CRC, valid frames
surviving garbage around them, and independence from how the input is chunked.
"""

from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from jig import crc, frame
from jig.parser import COUNTER_NAMES, FrameParser

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# Bytes biased towards the delimiter values, where the interesting cases are.
special_byte = st.one_of(st.sampled_from([0xAA, 0xAA, 0xCC, 0xEE]), st.integers(0, 255))
garbage = st.lists(special_byte, max_size=40).map(bytes)
# Long runs without 0xAA reach the body limit (overlong frames, the bulk copy's edge).
long_run = st.tuples(st.integers(0, 255).filter(lambda b: b != 0xAA), st.integers(200, 600)).map(
    lambda t: bytes([t[0]]) * t[1])
mixed_input = st.lists(st.one_of(garbage, garbage, long_run), max_size=6).map(b"".join)


def reference_parse(data, ver8=False):
    """Independent receiver: returns ([(end offset, body incl. CRC)], counters dict)."""
    max_body = frame.MAX_BODY if ver8 else frame.MAX_BODY - 1
    min_body = 4  # id, one byte, CRC in both layouts (Ver8: the Ver6 probe's shape)
    c = dict.fromkeys(COUNTER_NAMES, 0)
    frames = []
    state = "hunt"
    body = bytearray()

    def append(b):
        nonlocal state
        if len(body) >= max_body:
            c["overlong"] += 1
            state = "hunt"
        else:
            body.append(b)

    for pos, b in enumerate(data):
        if state == "hunt":
            if b == 0xAA:
                state = "header"
            else:
                c["noise"] += 1
        elif state == "header":
            if b == 0xCC:
                body = bytearray()
                state = "body"
            elif b == 0xAA:
                c["noise"] += 1
            else:
                c["noise"] += 2
                state = "hunt"
        elif state == "body":
            if b == 0xAA:
                state = "escape"
            else:
                append(b)
        else:  # escape
            if b == 0xAA:
                state = "body"
                append(0xAA)
            elif b == 0xCC:
                c["resyncs"] += 1
                body = bytearray()
                state = "body"
            elif b == 0xEE:
                state = "hunt"
                if len(body) < min_body:
                    c["short"] += 1
                elif crc.crc16(body) != 0:
                    c["crc_errors"] += 1
                else:
                    c["good"] += 1
                    frames.append((pos + 1, bytes(body)))
            else:
                c["stuff_errors"] += 1
                state = "hunt"
    return frames, tuple(c[name] for name in COUNTER_NAMES), state


def run(data, ver8=False, bulk=True, cuts=(), times=None, timeout=5000):
    """Feed data cut at the given offsets; times[k] is the arrival time of piece k."""
    p = FrameParser(ver8, timeout, bulk)
    frames = []
    bounds = sorted(set(c for c in cuts if 0 < c < len(data))) + [len(data)]
    lo = 0
    for k, hi in enumerate(bounds):
        now = None if times is None else times[k]
        i = lo
        while True:
            i = p.feed(data, i, hi, now)
            if p.ready:
                body = bytes(p.body[: p.body_len])
                assert crc.crc16(body) == 0
                head = 3 if ver8 else 2
                assert p.data_start == head and p.data_end == p.body_len - 2
                assert p.slave == body[0] and p.ftype == body[head - 1]
                assert p.sync == (body[1] if ver8 else -1)
                frames.append((i, body))
            if i >= hi:
                break
        lo = hi
    return frames, p.counters()


@SETTINGS
@given(slave=st.integers(0, 255), ftype=st.integers(0, 255),
       data=st.lists(special_byte, max_size=frame.MAX_DATA).map(bytes),
       sync=st.one_of(st.just(-1), st.integers(0, 255)), cut=st.integers(0, 600))
def test_encode_parse_round_trip(slave, ftype, data, sync, cut):
    wire = frame.encode(slave, ftype, data, sync)
    ver8 = sync >= 0
    for bulk in (True, False):
        frames, counters = run(wire, ver8, bulk, cuts=(cut,))
        assert len(frames) == 1 and frames[0][0] == len(wire)
        body = frames[0][1]
        head = bytes([slave, ftype]) if not ver8 else bytes([slave, sync, ftype])
        assert body[:-2] == head + data
        assert counters == (1, 0, 0, 0, 0, 0, 0, 0)


@SETTINGS
@given(data=st.one_of(st.lists(special_byte, max_size=600).map(bytes), mixed_input), ver8=st.booleans(),
       cuts=st.lists(st.integers(0, 600), max_size=8))
def test_arbitrary_bytes_match_the_reference(data, ver8, cuts):
    want_frames, want_counters, _ = reference_parse(data, ver8)
    for bulk in (True, False):
        got = run(data, ver8, bulk, cuts)  # run() asserts every frame's CRC is good
        assert got == (want_frames, want_counters)


# A stream of valid frames with garbage before, between and after them.
frames_and_garbage = st.lists(
    st.tuples(garbage,
              st.tuples(st.integers(0, 15), st.integers(0, 255),
                        st.lists(special_byte, max_size=30).map(bytes))),
    min_size=1, max_size=8)


def build(pairs, tail):
    stream = bytearray()
    ends = []
    starts = []
    for junk, (slave, ftype, data) in pairs:
        stream += junk
        starts.append(len(stream))
        stream += frame.encode(slave, ftype, data)
        ends.append(len(stream))
    stream += tail
    return bytes(stream), starts, ends


@SETTINGS
@given(pairs=frames_and_garbage, tail=garbage, cuts=st.lists(st.integers(0, 400), max_size=6))
def test_frames_survive_garbage_they_do_not_overlap(pairs, tail, cuts):
    stream, starts, ends = build(pairs, tail)
    frames, _ = run(stream, cuts=cuts)
    got = dict(frames)
    for k, (start, end) in enumerate(zip(starts, ends)):
        # The garbage overlaps a frame only when it leaves the receiver inside a frame
        # right after an odd 0xAA: the frame's own header 0xAA then reads as "AA AA",
        # a literal, and the frame becomes data of the broken one. In any other state
        # (idle, after a lone 0xAA, or inside a frame) the frame's AA CC starts it.
        state_before = reference_parse(stream[:start])[2]
        if state_before != "escape":
            assert got.get(end) == stream_body(pairs[k][1]), "frame %d lost (state %s)" % (k, state_before)
    # No frame is ever reported that ends strictly inside one of ours: inside a frame
    # an odd 0xAA followed by 0xEE only occurs at its tail, whatever came before.
    for end, _body in frames:
        assert not any(s < end < e for s, e in zip(starts, ends))


def stream_body(triple):
    slave, ftype, data = triple
    b = bytes([slave, ftype]) + data
    c = crc.crc16(b)
    return b + bytes([c & 0xFF, c >> 8])


@SETTINGS
@given(pairs=frames_and_garbage, tail=garbage)
def test_garbage_without_aa_never_costs_a_frame(pairs, tail):
    pairs = [(junk.replace(b"\xaa", b"\x55"), f) for junk, f in pairs]
    stream, _, ends = build(pairs, tail.replace(b"\xaa", b"\x55"))
    frames, counters = run(stream)
    assert [e for e, _ in frames] == ends
    assert counters[0] == len(pairs)


@SETTINGS
@given(pairs=frames_and_garbage, tail=garbage)
@example(pairs=[(b"\xaa", (0, 0, b"")), (b"", (0, 0, b"")), (b"\xaa\xcc\xaa", (0, 0, b""))], tail=b"")
def test_a_timeout_gap_before_each_frame_saves_it_from_any_garbage(pairs, tail):
    stream, starts, ends = build(pairs, tail)
    # The stream is cut at each frame start; piece k (frame k-1 and the garbage after
    # it) arrives 6 ms after piece k-1, so the line is silent longer than the timeout
    # right before every frame.
    times = [6000 * k for k in range(len(starts) + 1)]
    frames, _ = run(stream, cuts=starts, times=times)
    got = dict(frames)
    for k, end in enumerate(ends):
        assert got.get(end) == stream_body(pairs[k][1])


@SETTINGS
@given(pairs=frames_and_garbage, tail=garbage, cuts=st.lists(st.integers(0, 400), max_size=20))
def test_chunking_does_not_change_anything(pairs, tail, cuts):
    stream, _, _ = build(pairs, tail)
    whole = run(stream)
    assert run(stream, cuts=cuts) == whole
    assert run(stream, bulk=False, cuts=cuts) == whole
    assert run(stream, cuts=range(len(stream))) == whole
