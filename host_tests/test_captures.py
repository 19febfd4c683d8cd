"""Replay every capture under host_tests/captures through the parser.

Each capture is fed whole, byte by byte, in 7-byte pieces and split at every byte
position, each with the bulk path and with the table-only path (bulk=False); all
must give the frames and counters the capture states.
"""

import glob
import os

import pytest

import capture_format as cf

HERE = os.path.dirname(os.path.abspath(__file__))
CAPTURES = sorted(glob.glob(os.path.join(HERE, "captures", "*.cap")))


def test_there_are_enough_captures():
    assert len(CAPTURES) >= 20


@pytest.mark.parametrize("path", CAPTURES, ids=os.path.basename)
def test_capture(path):
    cap = cf.load(path)
    whole = cf.replay(cap)
    assert cf.check(cap, whole) == []
    for label, kw in cf.strategies(cap, every_split=True):
        assert cf.replay(cap, **kw) == whole, label


def test_coverage_of_the_issue_list():
    """The captures between them exercise every error class and both modes."""
    totals = dict.fromkeys(cf.COUNTER_NAMES, 0)
    ver8 = gaps = 0
    for path in CAPTURES:
        cap = cf.load(path)
        for name, value in cap.counters.items():
            totals[name] += value
        ver8 += cap.ver8
        gaps += len(cap.bursts) > 1
    assert all(totals.values()), totals
    assert ver8 and gaps


def parse(text):
    return cf.parse(text, "t")


def test_format_basics():
    cap = parse("""
        # comment
        AA CC 01 01 C1 E0 AA EE   # trailing comment
        00*3
        gap 7000
        aa cc 01 40 01 d0 aa ee
        frame 01 01 crc E0C1
        frame 01
        + 40
        counters good=2 noise=3
    """)
    assert [(t, bytes(d)) for t, d in cap.bursts] == [
        (0, bytes.fromhex("AA CC 01 01 C1 E0 AA EE 00 00 00")),
        (7000, bytes.fromhex("AA CC 01 40 01 D0 AA EE")),
    ]
    assert cap.frames == [(b"\x01\x01", 0xE0C1), (b"\x01\x40", -1)]
    assert cap.counters == {"good": 2, "noise": 3} and cap.end_gap == -1
    assert cf.check(cap, cf.replay(cap)) == []


def test_trailing_gap_checks_the_timeout():
    cap = parse("AA CC 01\ngap 6000\ncounters timeouts=1")
    assert cap.end_gap == 6000
    assert cf.check(cap, cf.replay(cap)) == []
    cap = parse("AA CC 01\ncounters")
    assert cf.check(cap, cf.replay(cap)) == []  # no trailing gap: still pending


def test_check_reports_every_difference():
    cap = parse("AA CC 01 01 C1 E0 AA EE\nframe 01 02 crc E0C2\ncounters good=1 noise=1")
    problems = cf.check(cap, cf.replay(cap))
    assert len(problems) == 3
    assert "frame 0 is 01 01" in problems[0] and "CRC" in problems[1] and "noise" in problems[2]


@pytest.mark.parametrize("text,msg", [
    ("AA ZZ\ncounters", "not a hex byte"),
    ("AAA\ncounters", "not a hex byte"),
    ("AA*x\ncounters", "repeat"),
    ("AA CC", "no counters"),
    ("AA\ncounters good=1", "frame lines"),
    ("AA\ncounters bogus=1", "counter name"),
    ("AA\ncounters\ncounters", "more than one"),
    ("mode ver7\nAA\ncounters", "ver6 or ver8"),
    ("gap -5\nAA\ncounters", "negative"),
    ("gap 1.5\nAA\ncounters", "not a number"),
    ("+ 01\nAA\ncounters", "continues"),
    ("AA\nframe 01\ncounters good=1", "at least id and type"),
    ("counters", "no bytes"),
])
def test_format_errors_name_the_problem(text, msg):
    with pytest.raises(cf.CaptureError, match=msg):
        parse(text)


def test_encode_helper_prints_the_wire_bytes(capsys):
    assert cf._main(["x", "encode", "04", "26"]) == 0
    out = capsys.readouterr().out.split("\n")
    assert out[0] == "# crc AA82" and out[1] == "AA CC 04 26 82 AA AA AA EE"
    assert cf._main(["x", "encode", "01"]) == 2
    assert "error:" in capsys.readouterr().out
