"""The SLCAN line reader and frame-line encoder (jig.slcan).

* the table: complete, every CR back to START, the STEP bytes are the table, the
  generated docs/slcan-states.md is current;
* the captured streams (host_tests/captures/slcan) give their expected commands and
  errors fed whole, cut in two at every offset, and byte by byte; capture 01 is what
  python-can writes today;
* the feed/gap contract: one line per call, the letter of a missing-CR line left for
  the next, the line timeout (with the tick wrap), reset;
* hypothesis: random bytes and mutated good streams never raise, every
  CR-terminated line is accounted for exactly once, any chunking gives the same
  result, good lines after a refused one are read, and every line agrees with an
  independent reference of the grammar;
* encode_frame: exact lines, and round trips through python-can's own slcan line
  parsing and writing (python-can's slcan bus on a loop:// serial port);
* the two engines (jig.slcanfast's viper source run as plain Python, and the table
  engine): the contract tests and the captures run on both; hypothesis feeds random
  and mutated streams, cut anywhere, timed across the line timeout and the tick
  wrap, through both and compares offsets, events, fields, counts and the partial
  line after every call; the viper constants mirror jig.slcan's; the runs of hex
  digits it reads without the table are the table's self-loops; the viper encoder
  writes the portable one's lines. (tools/firmware/slcan_qemu.py runs the machine code.)
"""

import glob
import os
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import slcan_replay as sr
from jig import slcan
from jig.compat import TICKS_PERIOD
from jig.slcan import (ERR_NAMES, EV_BAD, EV_CMD, EV_NONE, LINE_TIMEOUT_US, MAX_LINE, S_STATE, SKIP, START,
                       SlcanReader, encode_frame)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CAPTURES = sorted(glob.glob(os.path.join(ROOT, "host_tests", "captures", "slcan", "*.slcan")))
ENGINES = ("table", "viper")
SETTINGS = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(params=ENGINES)
def Reader(request):
    """The reader class of each engine (viper: jig.slcanfast's source as plain Python)."""
    return slcan.reader_class(request.param)


def feed_all(r, data, now=-1, chunk=None):
    """Every event of data fed in pieces of ``chunk`` bytes (None: whole)."""
    events = []
    n = len(data)
    step = chunk or max(n, 1)
    for a in range(0, n, step):
        b = min(a + step, n)
        i = a
        while i < b:
            i = r.feed(data, i, b, now)
            if r.ev != EV_NONE:
                events.append(sr.event(r))
    return events


def err_count(r, name):
    return r.counts[ERR_NAMES.index(name)]


# --- the table ---------------------------------------------------------------------

def test_table_is_complete_and_consistent():
    n_states, n_classes = len(slcan.STATE_NAMES), len(slcan.CLASS_NAMES)
    assert len(slcan.TRANSITIONS) == n_states
    for s, row in enumerate(slcan.TRANSITIONS):
        assert len(row) == n_classes
        for action, nxt in row:
            assert 0 <= action < len(slcan.ACTION_NAMES) and 0 <= nxt < n_states
        # Every CR ends the line: the next byte is read in START, whatever came before.
        assert row[slcan.K_CR][1] == START, slcan.STATE_NAMES[s]
        # A missing-CR line leaves its letter for START; START must never do that (no loop).
        for action, nxt in row:
            if action == slcan.A_E_MISSING_CR:
                assert s != START and nxt == START
    # SKIP's self-loop covers every byte but CR (the fast path relies on it).
    for c in range(n_classes):
        if c != slcan.K_CR:
            assert slcan.TRANSITIONS[SKIP][c] == (slcan.A_NONE, SKIP)
    # Error actions are A_ERR + their ERR_NAMES index.
    assert [slcan.A_E_UNKNOWN, slcan.A_E_HEX, slcan.A_E_DLC, slcan.A_E_ARG, slcan.A_E_SHORT, slcan.A_E_MISSING_CR] == [
        slcan.A_ERR + k for k in (slcan.ERR_UNKNOWN, slcan.ERR_HEX, slcan.ERR_DLC, slcan.ERR_ARG, slcan.ERR_SHORT,
                                  slcan.ERR_MISSING_CR)]


def test_step_bytes_are_the_table():
    for s, row in enumerate(slcan.TRANSITIONS):
        for b in range(256):
            action, nxt = row[slcan.byte_class(b)]
            assert slcan.STEP[(s << 8) | b] == (action << 4) | nxt
    for b in range(256):
        c = chr(b)
        if c in "0123456789abcdefABCDEF":
            assert slcan.HEXVAL[b] == int(c, 16)


def test_byte_classes():
    cls = [slcan.byte_class(b) for b in range(256)]
    assert [b for b in range(256) if cls[b] == slcan.K_CF] == [ord("C"), ord("F")]
    assert sorted(chr(b) for b in range(256) if cls[b] == slcan.K_FRAME) == sorted("tTrR")
    assert sorted(chr(b) for b in range(256) if cls[b] == slcan.K_HEX) == sorted("ABDEabcdef")
    assert cls.count(slcan.K_OTHER) == 256 - 2 - 10 - 10 - 2 - 4 - 4 - 3


def test_generated_state_doc_is_committed_and_current():
    import gen_slcan_doc  # tools/docgen is on the path (conftest)
    with open(os.path.join(ROOT, "docs", "slcan-states.md"), encoding="utf-8") as f:
        assert f.read() == gen_slcan_doc.render(), "run: python tools/docgen/gen_slcan_doc.py"


def test_bitrates_are_pythoncans_s0_to_s8():
    from can.interfaces.slcan import slcanBus

    table = {cmd: rate for rate, cmd in slcanBus._BITRATES.items()}
    assert slcan.SLCAN_BITRATES == tuple(table["S%d" % k] for k in range(9))


# --- captured streams --------------------------------------------------------------

def test_there_are_captures_of_every_kind():
    assert len(CAPTURES) >= 9
    seen = set()
    for path in CAPTURES:
        cap = sr.load(path)
        seen.update(name for name, value in cap.counts.items() if value)
        seen.update(e.split()[0] for e in cap.expect)
    assert set(ERR_NAMES) <= seen
    assert set("tTrROLCSsFVNZ") <= seen


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("path", CAPTURES, ids=[os.path.basename(p) for p in CAPTURES])
def test_capture_whole_halved_and_bytewise(path, engine):
    cap = sr.load(path)
    cls = slcan.reader_class(engine)
    events, counts = sr.replay(cap, reader_class=cls)
    assert sr.check(cap, events, counts) == []
    assert sr.replay(cap, bytewise=True, reader_class=cls) == (events, counts)
    for cut in range(len(cap.stream()) + 1):
        assert sr.replay(cap, cut=cut, reader_class=cls) == (events, counts), "cut at %d" % cut


def test_capture_01_is_what_python_can_writes():
    """python-can's slcan bus on a loop:// port: the bytes it writes, write by write."""
    import can
    import can.interfaces.slcan as mod
    from serial.urlhandler.protocol_loop import Serial as LoopSerial

    writes = []

    class Recording(LoopSerial):
        def write(self, data):
            writes.append(bytes(data))
            return super().write(data)

    def open_recording(url, **kwargs):
        return Recording(url, **kwargs)

    old = mod.serial.serial_for_url
    mod.serial.serial_for_url = open_recording
    try:
        bus = can.Bus(interface="slcan", channel="loop://", bitrate=500000, sleep_after_open=0)
        for msg in (can.Message(arbitration_id=0, data=[0x82, 0], is_extended_id=False),
                    can.Message(arbitration_id=0x605, data=[0x40, 0, 0x10, 0, 0, 0, 0, 0], is_extended_id=False),
                    can.Message(arbitration_id=0x1ABCDEF, data=[0xDE, 0xAD], is_extended_id=True),
                    can.Message(arbitration_id=0x705, is_remote_frame=True, dlc=1, is_extended_id=False),
                    can.Message(arbitration_id=0x12345678, is_remote_frame=True, dlc=0, is_extended_id=True),
                    can.Message(arbitration_id=0x80, data=[], is_extended_id=False)):
            bus.send(msg)
        for ask in (bus.get_version, bus.get_serial_number):
            try:
                ask(0.01)  # the loop port answers with the request itself: not parseable
            except ValueError:
                pass
        bus.shutdown()
    finally:
        mod.serial.serial_for_url = old
    cap = sr.load(CAPTURES[0])
    assert [bytes(data) for _t, data in cap.bursts] == writes


# --- the feed and gap contract -----------------------------------------------------

def test_feed_stops_after_each_line_and_fills_the_fields(Reader):
    r = Reader()
    data = b"t1232CAFE\rT1ABCDEF01r7FF8\rS5\rs0A1b\rZ1\r"
    i = r.feed(data, 0, len(data), -1)
    assert (r.ev, i) == (EV_CMD, 10)
    assert (chr(r.cmd), r.can_id, r.ext, r.rtr, r.dlc, bytes(r.data[:2])) == ("t", 0x123, 0, 0, 2, b"\xca\xfe")
    # T1ABCDEF0 1 then 'r': a letter where the data byte belongs, so the line lost its CR.
    i = r.feed(data, i, len(data), -1)
    assert r.ev == EV_BAD and ERR_NAMES[r.err] == "missing_cr" and data[i:i + 1] == b"r"
    i = r.feed(data, i, len(data), -1)
    assert r.ev == EV_CMD and (chr(r.cmd), r.can_id, r.ext, r.rtr, r.dlc) == ("r", 0x7FF, 0, 1, 8)
    i = r.feed(data, i, len(data), -1)
    assert (chr(r.cmd), r.arg) == ("S", 5)
    i = r.feed(data, i, len(data), -1)
    assert (chr(r.cmd), r.arg) == ("s", 0x0A1B)
    i = r.feed(data, i, len(data), -1)
    assert (chr(r.cmd), r.arg, i) == ("Z", 1, len(data))
    assert r.feed(data, i, len(data), -1) == len(data) and r.ev == EV_NONE
    assert r.lines == 5 and r.refused_lines() == 1


def test_a_refused_line_answers_at_its_cr_and_the_next_byte_starts_afresh(Reader):
    r = Reader()
    data = b"t12G4567\rO\r"
    i = r.feed(data, 0, 4, -1)  # the fault is found at 'G' ...
    assert r.ev == EV_NONE and r.st[S_STATE] == SKIP and i == 4
    i = r.feed(data, i, len(data), -1)  # ... and answered at the CR
    assert r.ev == EV_BAD and ERR_NAMES[r.err] == "hex" and i == 9 and r.st[S_STATE] == START
    r.feed(data, i, len(data), -1)
    assert r.ev == EV_CMD and chr(r.cmd) == "O"


def test_extended_ids_never_grow_past_29_bits(Reader):
    # The first of 8 digits decides the range: nothing bigger than 0x1FFFFFFF is ever
    # accumulated (a MicroPython small int holds 30 bits).
    for line, kind in ((b"T1FFFFFFF0\r", None), (b"T2000000000\r", "id_range"), (b"t7FF0\r", None),
                       (b"t8000\r", "id_range"), (b"tF000\r", "id_range")):
        r = Reader()
        ev = feed_all(r, line)
        assert ev == (["bad " + kind] if kind else [sr.event(r)])
        if not kind:
            assert r.can_id in (0x1FFFFFFF, 0x7FF)


def test_overlong_is_decided_by_length_alone(Reader):
    r = Reader()
    assert feed_all(r, b"x" * MAX_LINE + b"\r") == ["bad unknown"]
    assert feed_all(r, b"x" * (MAX_LINE + 1) + b"\r") == ["bad overlong"]
    assert feed_all(r, b"T1FFFFFFF8" + b"A" * 16 + b"\r") == ["T 1FFFFFFF 8 " + "AA" * 8]
    assert feed_all(r, b"T1FFFFFFF8" + b"A" * 17 + b"\r") == ["bad overlong"]
    # across calls: the length counts on while skipping
    assert feed_all(r, b"?" + b"z" * 500 + b"\rV\r", chunk=7) == ["bad overlong", "V"]


def test_gap_drops_a_stale_partial_line_across_the_tick_wrap(Reader):
    r = Reader()
    t0 = TICKS_PERIOD - 100
    assert r.feed(b"t123", 0, 4, t0) == 4 and r.ev == EV_NONE
    assert r.gap((t0 + LINE_TIMEOUT_US) % TICKS_PERIOD) == 0
    assert r.gap((t0 + LINE_TIMEOUT_US + 1) % TICKS_PERIOD) == 1
    assert r.ev == EV_BAD and ERR_NAMES[r.err] == "missing_cr" and r.st[S_STATE] == START
    assert r.gap(t0 + 10 * LINE_TIMEOUT_US) == 0  # nothing pending: nothing to drop
    assert r.refused_lines() == 1


def test_feed_drops_the_stale_line_before_new_bytes(Reader):
    r = Reader(line_timeout_us=5000)
    r.feed(b"t0F01", 0, 5, 0)
    data = b"C\r"
    i = r.feed(data, 0, 2, 5001)  # nothing consumed: the stale line is refused first
    assert (i, r.ev, ERR_NAMES[r.err]) == (0, EV_BAD, "missing_cr")
    r.feed(data, i, 2, 5001)
    assert r.ev == EV_CMD and chr(r.cmd) == "C"
    # within the timeout the same bytes continue the line: C is its last hex digit
    r.feed(b"t0F01", 0, 5, 10000)
    r.feed(b"C\r", 0, 2, 15000)
    assert r.ev == EV_BAD and ERR_NAMES[r.err] == "dlc"


def test_a_refused_line_that_goes_quiet_counts_its_first_fault(Reader):
    r = Reader(line_timeout_us=1000)
    r.feed(b"Z7", 0, 2, 0)
    assert r.gap(2000) and ERR_NAMES[r.err] == "argument" and err_count(r, "argument") == 1
    assert err_count(r, "missing_cr") == 0


def test_reset_forgets_the_partial_line_and_keeps_counters(Reader):
    r = Reader()
    feed_all(r, b"?\rt12")
    r.reset()
    assert r.st[S_STATE] == START and feed_all(r, b"4\rO\r") == ["bad unknown", "O"] and r.refused_lines() == 2


# --- properties ----------------------------------------------------------------------

HEXD = "0123456789ABCDEFabcdef"


def reference(seg):
    """An independent reading of one line (no CR): the event string it must give, or
    None when it is no valid SLCAN line. Written from the Lawicel grammar."""
    s = seg.decode("latin-1")
    if not s:
        return None
    c, rest = s[0], s[1:]

    def is_hex(x):
        return all(ch in HEXD for ch in x)

    if c in "tTrR":
        width = 3 if c in "tr" else 8
        ident, rest = rest[:width], rest[width:]
        if len(ident) != width or not is_hex(ident) or int(ident, 16) > (0x7FF if width == 3 else 0x1FFFFFFF):
            return None
        if not rest or rest[0] not in "012345678":
            return None
        dlc, rest = int(rest[0]), rest[1:]
        want = 0 if c in "rR" else 2 * dlc
        if len(rest) != want or not is_hex(rest):
            return None
        out = "%s %0*X %d" % (c, width, int(ident, 16), dlc)
        return out + (" " + rest.upper() if rest else "")
    if c == "S" and len(rest) == 1 and rest in "012345678":
        return "S " + rest
    if c == "Z" and len(rest) == 1 and rest in "01":
        return "Z " + rest
    if c == "s" and len(rest) == 4 and is_hex(rest):
        return "s " + rest.upper()
    if c in "OLCFVN" and not rest:
        return c
    return None


RESYNC_LETTERS = set(b"tTrROLCFVNSZs")


def segments(data):
    """CR-terminated lines of data, leading LFs dropped (ignored in START), empty ones out."""
    parts = data.split(b"\r")[:-1]
    return [p.lstrip(b"\n") for p in parts if p.lstrip(b"\n")]


def run_lines(data):
    """Events per CR-terminated line, fed whole: [(segment, [events])]."""
    r = SlcanReader()
    out = []
    for seg_raw in data.split(b"\r")[:-1]:
        out.append((seg_raw.lstrip(b"\n"), feed_all(r, seg_raw + b"\r")))
    return r, out


good_line = st.one_of(
    st.builds(lambda i, d: b"t%03X%d%s\r" % (i, len(d), d.hex().upper().encode()),
              st.integers(0, 0x7FF), st.binary(max_size=8)),
    st.builds(lambda i, d: b"T%08X%d%s\r" % (i, len(d), d.hex().encode()),
              st.integers(0, 0x1FFFFFFF), st.binary(max_size=8)),
    st.builds(lambda i, n: b"r%03X%d\r" % (i, n), st.integers(0, 0x7FF), st.integers(0, 8)),
    st.builds(lambda i, n: b"R%08X%d\r" % (i, n), st.integers(0, 0x1FFFFFFF), st.integers(0, 8)),
    st.sampled_from([b"O\r", b"L\r", b"C\r", b"F\r", b"V\r", b"N\r", b"Z0\r", b"Z1\r", b"\r", b"\n", b"s031C\r"]),
    st.integers(0, 8).map(lambda k: b"S%d\r" % k),
)
good_stream = st.lists(good_line, max_size=12).map(b"".join)
special = st.sampled_from(list(b"\r\r\n0189AFCcftTrRsSZOLVNx \x07\xff"))
noise = st.lists(st.one_of(special, st.integers(0, 255)), max_size=60).map(bytes)


@st.composite
def mutated(draw):
    data = bytearray(draw(good_stream))
    for _ in range(draw(st.integers(0, 6))):
        kind = draw(st.integers(0, 2))
        pos = draw(st.integers(0, len(data)))
        if kind == 0 and pos < len(data):
            del data[pos]
        elif kind == 1:
            data.insert(pos, draw(st.one_of(special, st.integers(0, 255))))
        elif pos < len(data):
            data[pos] = draw(st.one_of(special, st.integers(0, 255)))
    return bytes(data)


def check_accounting(data):
    r = SlcanReader()
    events = feed_all(r, data)
    # Every CR-terminated non-empty line gives exactly one answer at its CR; a line that
    # lost its CR (missing_cr) is refused on top.
    assert r.lines + r.refused_lines() - err_count(r, "missing_cr") == len(segments(data))
    assert len(events) == r.lines + r.refused_lines()
    assert sum(1 for e in events if not e.startswith("bad")) == r.lines
    return events


@SETTINGS
@given(st.one_of(noise, mutated(), st.lists(st.one_of(noise, good_stream), max_size=4).map(b"".join)))
def test_any_input_is_accounted_for_and_independent_of_chunking(data):
    events = check_accounting(data)
    for chunk in (1, 2, 5, 64):
        assert feed_all(SlcanReader(), data, chunk=chunk) == events


@SETTINGS
@given(mutated())
def test_every_line_agrees_with_the_reference_grammar(data):
    _r, lines = run_lines(data)
    for seg, events in lines:
        if not seg:
            assert events == []
            continue
        want = reference(seg)
        if want is not None:
            assert events == [want], seg
            continue
        assert events[0].startswith("bad"), (seg, events)
        if "bad missing_cr" in events:
            # a command letter inside ended the line and started another (checked in detail
            # by the captures)
            assert any(b in RESYNC_LETTERS for b in seg[1:]), (seg, events)
        else:
            assert len(events) == 1, (seg, events)


@SETTINGS
@given(noise, good_stream)
def test_good_lines_after_a_refused_line_are_read(garbage, good):
    r = SlcanReader()
    feed_all(r, garbage + b"\r")
    assert r.st[S_STATE] == START
    expected = [reference(seg) for seg in segments(good)]
    assert feed_all(r, good) == expected


# --- the two engines ---------------------------------------------------------------

def test_viper_constants_mirror_the_reader():
    """viper folds only its own module's constants: they must equal jig.slcan's."""
    from jig import compat, slcanfast

    names = [k[1:] for k in vars(slcanfast) if k.startswith("_") and k[1:2].isupper() and k[1:] not in ("MASK", "HALF")]
    assert len(names) > 40
    for name in names:
        assert getattr(slcanfast, "_" + name) == getattr(slcan, name), name
    assert slcanfast._MASK == compat.TICKS_PERIOD - 1 and slcanfast._HALF == compat.TICKS_PERIOD // 2
    assert slcan.S_SIZE == max(getattr(slcan, k) for k in dir(slcan) if k.startswith("S_") and k != "S_SIZE") + 1


def test_the_runs_are_the_tables_self_loops():
    """The viper engine reads the id's and the data's hex digits without the table:
    in ID and DATA exactly the bytes with a HEXVAL <= 15 are the field's digits,
    which stay until the last one and then go on to DLC / FRAME_END."""
    for state, action, nxt in ((slcan.ID, slcan.A_ID, slcan.DLC), (slcan.DATA, slcan.A_DATA, slcan.FRAME_END)):
        for b in range(256):
            code = slcan.STEP[(state << 8) | b]
            is_digit = slcan.HEXVAL[b] <= 15
            assert (code >> 4 == action) == is_digit, (slcan.STATE_NAMES[state], b)
            if is_digit:
                assert code & 15 == nxt
            else:
                assert slcan.HEXVAL[b] == 0xFF
    assert action in slcan.COUNTED


def snapshot(r):
    """Everything a reader shows, and its whole partial line."""
    return (r.ev, r.err, r.cmd, r.can_id, r.ext, r.rtr, r.dlc, r.arg, r.lines, tuple(r.st), tuple(r.counts),
            bytes(r.data))


@st.composite
def schedule(draw):
    """A stream cut into pieces, each arriving at a time (or -1: no timing) after an
    optional gap() of the main loop; gaps around the 1 ms line timeout."""
    data = draw(st.one_of(noise, mutated(), st.lists(st.one_of(noise, good_stream), max_size=4).map(b"".join)))
    cuts = sorted(set(draw(st.lists(st.integers(0, len(data)), max_size=12))) | {len(data)})
    pieces = []
    a = 0
    for b in cuts:
        delay = draw(st.one_of(st.integers(0, 1200), st.sampled_from([999, 1000, 1001, 5000])))
        pieces.append((a, b, delay, draw(st.booleans()), draw(st.integers(0, 9)) == 0))
        a = b
    return data, pieces


@SETTINGS
@given(schedule())
def test_the_engines_agree_call_for_call(plan):
    """Random and mutated streams, any cuts, line timeouts across the tick wrap: the
    viper engine (its source as plain Python) and the table engine give the same
    offsets, events, fields, counts and partial-line state after every call."""
    data, pieces = plan
    a_r = slcan.reader_class("table")(line_timeout_us=1000)
    b_r = slcan.reader_class("viper")(line_timeout_us=1000)
    assert type(a_r).feed is not type(b_r).feed
    now = TICKS_PERIOD - 3000
    for start, end, delay, call_gap, untimed in pieces:
        now = (now + delay) % TICKS_PERIOD
        t = -1 if untimed else now
        if call_gap:
            assert a_r.gap(now) == b_r.gap(now)
            assert snapshot(a_r) == snapshot(b_r)
        i = start
        while i < end:
            j = a_r.feed(data, i, end, t)
            assert b_r.feed(data, i, end, t) == j
            assert snapshot(a_r) == snapshot(b_r), (data, i, end)
            assert j > i or a_r.ev != EV_NONE  # progress: a line ended or bytes were used
            i = j
    assert a_r.refused_lines() == b_r.refused_lines()


def test_the_engines_agree_on_every_split_of_every_line_kind():
    lines = (b"t18181122334455667788\r", b"T1ABCDEF081122334455667788\r", b"r7FF8\r", b"R000000000\r", b"t0000\r",
             b"s0A1b\r", b"S8\r", b"Z1\r", b"O\r", b"t12G4567\r", b"T2000000000\r", b"t1234aabbccdd\r",
             b"t123811223344556677889\r", b"T1FFFFFFF8" + b"A" * 17 + b"\r", b"t1231Ft123\r", b"\n\r?\r")
    for line in lines:
        for cut in range(len(line) + 1):
            readers = [slcan.reader_class(e)() for e in ENGINES]
            for r in readers:
                r.feed(line, 0, cut, -1)
            assert snapshot(readers[0]) == snapshot(readers[1]), (line, cut)
            i = cut
            while i < len(line):
                j = readers[0].feed(line, i, len(line), -1)
                assert readers[1].feed(line, i, len(line), -1) == j
                assert snapshot(readers[0]) == snapshot(readers[1]), (line, cut, i)
                i = j


def test_default_reader_and_engine_names():
    assert slcan.SlcanReader is slcan.TableReader  # CPython: no native emitter
    assert slcan.reader_class() is slcan.SlcanReader and slcan.reader_class("table") is slcan.TableReader
    assert slcan.reader_class("viper").ENGINE == "viper" and slcan.TableReader.ENGINE == "table"
    assert slcan.encode_frame is slcan.encode_py
    with pytest.raises(ValueError):
        slcan.reader_class("bulk")
    # No properties on the reader (see TableReader): every attribute is a plain one.
    for cls in (slcan.TableReader, slcan.reader_class("viper")):
        assert not [k for c in cls.__mro__ for k, v in vars(c).items() if isinstance(v, property)]


# --- encode_frame ------------------------------------------------------------------

def test_encode_frame_lines():
    out = bytearray(40)
    cases = [
        ((0x123, 0, 0, b"\xde\xad\xbe\xef", 4, -1), b"t1234DEADBEEF\r"),
        ((0x1ABCDEF0, 1, 0, b"\x01\x02", 2, 65000), b"T1ABCDEF0201021388\r"),  # 65000 % 60000 = 0x1388
        ((0x7FF, 0, 1, b"", 8, 0), b"r7FF80000\r"),
        ((0x1FFFFFFF, 1, 1, b"", 0, 59999), b"R1FFFFFFF0EA5F\r"),
        ((0, 0, 0, b"", 0, -1), b"t0000\r"),
        ((0x1FFFFFFF, 1, 0, bytes(range(0xF8, 0x100)), 8, 59999), b"T1FFFFFFF8F8F9FAFBFCFDFEFFEA5F\r"),
    ]
    for args, want in cases:
        end = encode_frame(out, 3, *args)
        assert bytes(out[3:end]) == want
    assert len(cases[-1][1]) == 31  # the longest line encode_frame writes


def test_encoded_lines_read_back(Reader):
    out = bytearray(32)
    r = Reader()
    for can_id, ext, rtr, data in ((0x7FF, 0, 0, b"\x00\x11\x22\x33\x44\x55\x66\x77"), (0x1234567, 1, 0, b"\x80"),
                                   (0x100, 0, 1, b"\x00\x00\x00")):
        end = encode_frame(out, 0, can_id, ext, rtr, data, len(data), -1)
        assert r.feed(out, 0, end, -1) == end and r.ev == EV_CMD
        assert (r.can_id, r.ext, r.rtr, r.dlc) == (can_id, ext, rtr, len(data))
        if not rtr:
            assert bytes(r.data[:r.dlc]) == data


@pytest.fixture
def loop_bus():
    """python-can's own slcan bus on a loop:// serial port: what is written comes back."""
    can = pytest.importorskip("can")
    bus = can.Bus(interface="slcan", channel="loop://", sleep_after_open=0)
    assert bus.recv(0.05) is None  # its own "O\r" comes back: not a frame
    yield bus
    bus.shutdown()


message = st.builds(
    lambda ext, rtr, ident, data, n: (ext, rtr, ident if ext else ident & 0x7FF, b"" if rtr else data,
                                      n if rtr else len(data)),
    st.booleans(), st.booleans(), st.integers(0, 0x1FFFFFFF), st.binary(max_size=8), st.integers(0, 8))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(message, st.one_of(st.just(-1), st.integers(0, 10 ** 7)))
def test_encoded_lines_parse_in_python_can(loop_bus, msg, stamp):
    """Our line, as the jig sends it to the host, through python-can's line parsing."""
    ext, rtr, ident, data, dlc = msg
    out = bytearray(32)
    end = encode_frame(out, 0, ident, ext, rtr, data, dlc, stamp)
    loop_bus.serialPortOrig.write(bytes(out[:end]))
    got = loop_bus.recv(1.0)
    assert got is not None
    assert (got.arbitration_id, got.is_extended_id, got.is_remote_frame, got.dlc) == (ident, ext, rtr, dlc)
    assert bytes(got.data) == (b"" if rtr else data)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(message)
def test_python_can_lines_are_read(loop_bus, msg):
    """python-can's send(), as the host sends to the jig, through our reader."""
    import can

    ext, rtr, ident, data, dlc = msg
    loop_bus.send(can.Message(arbitration_id=ident, is_extended_id=ext, is_remote_frame=rtr, dlc=dlc,
                              data=None if rtr else data))
    port = loop_bus.serialPortOrig
    deadline = time.monotonic() + 1.0
    line = b""
    while not line.endswith(b"\r") and time.monotonic() < deadline:
        line += port.read(port.in_waiting or 1)
    r = SlcanReader()
    assert r.feed(line, 0, len(line), -1) == len(line) and r.ev == EV_CMD
    assert (r.can_id, r.ext, r.rtr, r.dlc) == (ident, int(ext), int(rtr), dlc)
    if not rtr:
        assert bytes(r.data[:dlc]) == data


@settings(max_examples=300, deadline=None)
@given(message, st.one_of(st.just(-1), st.integers(0, 2 ** 30 - 1)), st.integers(0, 9))
def test_the_viper_encoder_writes_the_portable_encoders_lines(msg, stamp, off):
    from jig import slcanfast

    ext, rtr, ident, data, dlc = msg
    a = bytearray(b"\xee" * 48)
    b = bytearray(b"\xee" * 48)
    end = slcan.encode_py(a, off, ident, int(ext), int(rtr), data, dlc, stamp)
    assert slcanfast.encode_frame(b, off, ident, int(ext), int(rtr), data, dlc, stamp) == end
    assert a == b and end - off <= 31
