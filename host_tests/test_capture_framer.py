"""The framer: every capture cut into records by the firmware's parser.

The records of a capture, joined, are its byte stream; their verdicts add up to
the counters the capture file states (noise counted in bytes); the good ones are
the capture's frames; and feeding the bytes one at a time gives the same records
(runs of noise may be cut in other places).
"""

import os

import pytest

from test_capture_support import CAPTURES, EPOCH_US, capture_records, load

from jig.parser import COUNTER_NAMES
from motorjig.capture import record as R
from motorjig.capture.framer import Framer


def _counts(records):
    counts = dict.fromkeys(COUNTER_NAMES, 0)
    for r in records:
        counter = R.VERDICT_COUNTER[r.verdict]
        counts[counter] += len(r.data) if r.verdict == R.NOISE else 1
    return counts


@pytest.mark.parametrize("path", CAPTURES, ids=os.path.basename)
def test_capture_records(path):
    cap = load(path)
    recs, rest = capture_records(cap)
    assert b"".join(r.data for r in recs + rest) == cap.stream()
    assert _counts(recs) == {k: cap.counters.get(k, 0) for k in COUNTER_NAMES}
    assert all(r.verdict in (R.NOISE, R.UNFINISHED) for r in rest)
    assert all(r.data for r in recs + rest)
    times = [r.t_us for r in recs]
    assert times == sorted(times)
    assert recs_without_time(capture_records(cap, step=1)[0]) == recs_without_time(recs)


def recs_without_time(recs):
    """(bytes, verdict) of each record, neighbouring noise joined (a run of noise is cut
    where a chunk ends, so its pieces depend on how the bytes came)."""
    out = []
    for r in recs:
        if out and r.verdict == R.NOISE and out[-1][1] == R.NOISE:
            out[-1] = (out[-1][0] + r.data, R.NOISE)
        else:
            out.append((r.data, r.verdict))
    return out


def test_times_of_frames_in_one_chunk():
    """Frames that arrive in one chunk are spaced one character time apart, backwards."""
    fr = Framer(byte_us=100.0)
    a = bytes.fromhex("AA CC 01 01 C1 E0 AA EE")
    b = bytes.fromhex("AA CC 01 40 01 D0 AA EE")
    recs = fr.feed(a + b"\x00\x00" + b, EPOCH_US)
    assert [(r.verdict, r.t_us - EPOCH_US) for r in recs] == [(R.GOOD, -1000), (R.NOISE, -800), (R.GOOD, 0)]


def test_silence_ends_a_frame_and_a_lone_aa():
    fr = Framer(interbyte_timeout_us=5000)
    assert fr.feed(bytes.fromhex("AA CC 01 40"), 0) == []
    assert fr.check_timeout(4000) == []
    recs = fr.check_timeout(6000)
    assert [(r.data.hex(" "), r.verdict, r.t_us) for r in recs] == [("aa cc 01 40", R.TIMEOUT, 0)]
    assert fr.feed(b"\xaa", 10000) == []  # may start a header
    recs = fr.feed(b"\xcc\x01", 20000)  # ... but the line was silent: the AA is noise alone
    assert [(r.data, r.verdict, r.t_us) for r in recs] == [(b"\xaa", R.NOISE, 10000), (b"\xcc\x01", R.NOISE, 20000)]


def test_resync_keeps_the_new_header():
    fr = Framer()
    recs = fr.feed(bytes.fromhex("AA CC 01 12 AA CC 01 01 C1 E0 AA EE"), 0)
    assert [(r.data.hex(" "), r.verdict) for r in recs] == [
        ("aa cc 01 12", R.RESYNC), ("aa cc 01 01 c1 e0 aa ee", R.GOOD)]


def test_flush_gives_the_unfinished_frame():
    fr = Framer()
    assert fr.feed(bytes.fromhex("00 AA CC 02"), 0)[0].verdict == R.NOISE
    recs = fr.flush()
    assert [(r.data.hex(" "), r.verdict) for r in recs] == [("aa cc 02", R.UNFINISHED)]
    assert fr.flush() == []


def test_mixed_bus_takes_the_longest_ver8_body():
    """ver8=None (a sniffer on a mixed bus) accepts a 254-byte body; Ver6 limits drop it."""
    from jig import frame as F

    wire = F.encode(1, 0x61, bytes(F.MAX_DATA), sync=0xF1)  # 254-byte body
    assert [r.verdict for r in Framer(ver8=None).feed(wire, 0)] == [R.GOOD]
    assert [r.verdict for r in Framer(ver8=False).feed(wire, 0)][0] == R.OVERLONG


def test_verdict_comments():
    assert R.comment(R.BAD_CRC) == "parser: bad_crc (dropped: bad CRC)"
    assert R.comment(R.GOOD).startswith(R.COMMENT_PREFIX)
    assert R.verdict_name(99) == "verdict_99"
