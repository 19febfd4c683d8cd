"""Captured SLCAN streams: load one, replay it through SlcanReader, compare with its sidecar.

A capture is two text files in host_tests/captures/slcan/ (docs in README there):

``NAME.slcan``, the bytes the host wrote, one write a line::

    # comment
    @0 C\\rS6\\r            # at 0 µs: these bytes (escapes: \\r \\n \\t \\\\ \\xNN; no raw blanks)
    @1500 O\\r
    end 2500000            # optional: at this time the main loop calls gap(now)

``NAME.expect``, what the reader must make of them, in order::

    S 6                    # a good line: letter, fields (frames: id hex, DLC, data hex)
    t 605 8 4000100000000000
    bad missing_cr         # a refused line: its kind (ERR_NAMES)
    counts lines=12 missing_cr=1   # the final counters; every kind not named is 0

Shared by pytest (CPython) and by the replay on the WebAssembly MicroPython VM, so
it only uses what both have (no f-strings, no bytes.hex, no dataclasses).
"""

from jig.compat import TICKS_PERIOD, ticks_add
from jig.slcan import EV_BAD, EV_CMD, ERR_NAMES, SlcanReader, encode_frame

# The replay clock starts just before the tick counter wraps, so every gap also
# exercises the wrap-around of the tick arithmetic.
T0 = TICKS_PERIOD - 3000
_HEX = "0123456789ABCDEF"


class CaptureError(Exception):
    pass


class Capture:
    def __init__(self, name):
        self.name = name
        self.bursts = []  # [time_us, bytes]
        self.end = -1  # >= 0: gap(end) is called after the last burst
        self.expect = []  # event strings
        self.counts = None  # dict name -> value

    def stream(self):
        out = bytearray()
        for _t, data in self.bursts:
            out.extend(data)
        return bytes(out)


def _strip_comment(line):
    k = line.find("#")
    return (line if k < 0 else line[:k]).strip()


def unescape(text, where):
    out = bytearray()
    i = 0
    n = len(text)
    while i < n:
        c = text[i]
        if c != "\\":
            out.append(ord(c))
            i += 1
            continue
        if i + 1 >= n:
            raise CaptureError("%s: a lone backslash at the end" % where)
        e = text[i + 1]
        if e == "r":
            out.append(13)
        elif e == "n":
            out.append(10)
        elif e == "t":
            out.append(9)
        elif e == "\\":
            out.append(92)
        elif e == "x":
            try:
                out.append(int(text[i + 2:i + 4], 16))
            except ValueError:
                raise CaptureError("%s: bad \\x escape" % where)
            i += 2
        else:
            raise CaptureError("%s: unknown escape \\%s" % (where, e))
        i += 2
    return bytes(out)


def load(path, expect_path=None):
    """Load NAME.slcan and its sidecar NAME.expect."""
    if expect_path is None:
        expect_path = path[:path.rfind(".")] + ".expect"
    cap = Capture(path[path.rfind("/") + 1:])
    with open(path) as f:
        lines = f.read().split("\n")
    last = -1
    for no, raw in enumerate(lines):
        where = "%s:%d" % (cap.name, no + 1)
        # A comment starts at ' #' (a '#' in the bytes is written \x23).
        line = raw.strip()
        if not line or line[0] == "#":
            continue
        parts = line.split()
        if len(parts) > 2 and parts[2][0] != "#":
            raise CaptureError("%s: blanks in the bytes (write \\x20)" % where)
        head = parts[0]
        if head == "end":
            cap.end = int(parts[1])
            continue
        if head[0] != "@" or len(parts) < 2:
            raise CaptureError("%s: expected '@TIME BYTES' or 'end TIME'" % where)
        t = int(head[1:])
        if t < last:
            raise CaptureError("%s: time goes backwards" % where)
        last = t
        cap.bursts.append([t, unescape(parts[1], where)])
    with open(expect_path) as f:
        lines = f.read().split("\n")
    for no, raw in enumerate(lines):
        line = _strip_comment(raw)
        if not line:
            continue
        parts = line.split()
        if parts[0] == "counts":
            cap.counts = {}
            for item in parts[1:]:
                k = item.find("=")
                name = item[:k]
                if name != "lines" and name not in ERR_NAMES:
                    raise CaptureError("%s.expect:%d: unknown counter %s" % (cap.name, no + 1, name))
                cap.counts[name] = int(item[k + 1:])
        else:
            cap.expect.append(" ".join(parts))
    if cap.counts is None:
        raise CaptureError("%s: the sidecar has no counts line" % cap.name)
    return cap


def _hex(value, digits):
    s = ""
    for k in range(digits - 1, -1, -1):
        s += _HEX[(value >> (4 * k)) & 15]
    return s


def event(r):
    """The reader's event as a sidecar line."""
    if r.ev == EV_BAD:
        return "bad " + ERR_NAMES[r.err]
    c = chr(r.cmd)
    if c in "tTrR":
        s = c + " " + _hex(r.can_id, 8 if r.ext else 3) + " " + str(r.dlc)
        if not r.rtr and r.dlc:
            s += " "
            for k in range(r.dlc):
                s += _hex(r.data[k], 2)
        return s
    if c in "SZ":
        return c + " " + str(r.arg)
    if c == "s":
        return "s " + _hex(r.arg, 4)
    return c


def counts_of(r):
    d = {"lines": r.lines}
    for k in range(len(ERR_NAMES)):
        d[ERR_NAMES[k]] = r.counts[k]
    return d


def replay(cap, cut=-1, bytewise=False, reader_class=SlcanReader):
    """Feed the capture burst by burst at its times (each burst in one call, cut in
    two at stream offset ``cut``, or byte by byte) to a new ``reader_class()`` (an
    engine's reader, slcan.reader_class); returns (events, counters)."""
    r = reader_class()
    events = []
    offset = 0
    for t, data in cap.bursts:
        now = ticks_add(T0, t)
        if r.gap(now):  # the main loop's slow pass before the bytes
            events.append(event(r))
        n = len(data)
        if bytewise:
            stops = list(range(1, n + 1))
        elif offset < cut < offset + n:
            stops = [cut - offset, n]
        else:
            stops = [n]
        i = 0
        for stop in stops:
            while i < stop:
                i = r.feed(data, i, stop, now)
                if r.ev == EV_CMD or r.ev == EV_BAD:
                    events.append(event(r))
        offset += n
    if cap.end >= 0 and r.gap(ticks_add(T0, cap.end)):
        events.append(event(r))
    return events, counts_of(r)


def check(cap, events, counts):
    """A list of differences from the sidecar (empty: as expected)."""
    problems = []
    if events != cap.expect:
        for k in range(max(len(events), len(cap.expect))):
            got = events[k] if k < len(events) else "(nothing)"
            want = cap.expect[k] if k < len(cap.expect) else "(nothing)"
            if got != want:
                problems.append("event %d: got %s, expected %s" % (k, got, want))
                break
    for name in counts:
        want = cap.counts.get(name, 0)
        if counts[name] != want:
            problems.append("%s: %d, expected %d" % (name, counts[name], want))
    return problems


def report(cap, every_split=False, reader_class=SlcanReader):
    """Lines that say what the replay gave: the events, the counters, whether the
    other feeding strategies agree and the sidecar is met."""
    events, counts = replay(cap, reader_class=reader_class)
    out = ["capture " + cap.name]
    for e in events:
        out.append("  " + e)
    out.append("  counts " + " ".join("%s=%d" % (k, counts[k]) for k in sorted(counts)))
    same = replay(cap, bytewise=True, reader_class=reader_class) == (events, counts)
    if every_split:
        for cut in range(len(cap.stream()) + 1):
            if replay(cap, cut=cut, reader_class=reader_class) != (events, counts):
                same = False
                break
    out.append("  strategies " + ("all same" if same else "differ"))
    problems = check(cap, events, counts)
    out.append("  check " + ("ok" if not problems else "; ".join(problems)))
    return out


# --- allocation probe (MicroPython: gc.mem_alloc) -----------------------------------

def _run(r, bursts, span, rounds, chunk, out):
    """Feed the bursts ``rounds`` times in pieces of ``chunk`` bytes (0: whole bursts),
    write every frame read back as a line with encode_frame; returns the lines read."""
    base = T0
    count = 0
    for _ in range(rounds):
        for burst in bursts:
            now = ticks_add(base, burst[0])  # C arithmetic: no big ints near the wrap
            if r.gap(now):
                count += 1
            data = burst[1]
            n = len(data)
            step = chunk if chunk else n
            i = 0
            while i < n:
                e = i + step
                if e > n:
                    e = n
                while i < e:
                    i = r.feed(data, i, e, now)
                    if r.ev == EV_CMD:
                        count += 1
                        if r.cmd == 0x74 or r.cmd == 0x54 or r.cmd == 0x72 or r.cmd == 0x52:
                            encode_frame(out, 0, r.can_id, r.ext, r.rtr, r.data, r.dlc, now >> 10)
                    elif r.ev == EV_BAD:
                        count += 1
        base = ticks_add(base, span)
    return count


def alloc_per_line(caps, chunk=0, rounds=5, reader_class=SlcanReader):
    """(bytes allocated, lines read) over ``rounds`` replays after a warm-up, with the
    collector off: everything the loop touches exists before the first reading."""
    from vm_probe import heap_growth, join_bursts  # on the VM's /lib beside this file

    # the captures one after the other, with a silence longer than the line timeout between
    bursts, span = join_bursts([(cap.bursts, cap.end) for cap in caps], 2000000)
    r = reader_class()
    out = bytearray(32)
    _run(r, bursts, span, 2, chunk, out)
    return heap_growth(_run, r, bursts, span, rounds, chunk, out)
