"""Captured byte streams: load a capture file, replay it through FrameParser, check it.

The format (see docs/captures.md) is line based and meant to be written by hand::

    # anything after '#' is a comment
    mode ver8              # optional: ver6 (default) or ver8
    timeout 5000           # optional: inter-byte timeout of the parser in µs
    AA CC 01 01 C1 E0 AA EE   # bytes on the wire, hex pairs; 'XX*N' repeats a byte N times
    gap 6000               # N µs of silence before the next bytes (at the end: the line goes quiet)
    frame 01 01 crc E0C1   # an expected frame, in order: unstuffed id [sync] type data;
                           # 'crc XXXX' optionally checks the CRC value too
    + 00 14                # a '+' line continues the frame line above (long frames)
    counters good=1 noise=0   # expected final counters; every counter not named must be 0

This module is shared by pytest (CPython) and by the replay on the WebAssembly
MicroPython VM (host_tests/wasm/run_vm.mjs with vm_probe.py), so it only uses what
both have: no f-strings, no dataclasses, no bytes.hex. Run it as a script for a
helper that prints the wire bytes of a frame, or checks captures
(``python host_tests/capture_format.py --help``).
"""

try:
    import jig  # noqa: F401
except ImportError:  # run as a script from a checkout without the venv
    import os
    import sys

    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "firmware"))

from jig.compat import TICKS_PERIOD
from jig.parser import COUNTER_NAMES, FrameParser

# The clock of a replay starts just before the tick counter wraps, so every gap in a
# capture also exercises wrap-around of the tick arithmetic.
T0 = TICKS_PERIOD - 3000


class CaptureError(Exception):
    pass


class Capture:
    """A parsed capture: bursts of bytes with their arrival times, and the expectations."""

    def __init__(self, name):
        self.name = name
        self.ver8 = False
        self.timeout_us = -1  # -1: the parser's default
        self.bursts = []  # [time_us, bytearray]; consecutive byte lines share a burst
        self.end_gap = -1  # >= 0: time after the last burst at which the line is checked
        self.frames = []  # expected: (body bytes without CRC, crc or -1)
        self.counters = None  # dict name -> value

    def stream(self):
        out = bytearray()
        for _t, data in self.bursts:
            out.extend(data)
        return bytes(out)


def _hex_bytes(tokens, where):
    out = bytearray()
    for tok in tokens:
        count = 1
        star = tok.find("*")
        if star >= 0:
            try:
                count = int(tok[star + 1 :])
            except ValueError:
                raise CaptureError("%s: bad repeat count in %r" % (where, tok))
            tok = tok[:star]
        if len(tok) != 2:
            raise CaptureError("%s: %r is not a hex byte" % (where, tok))
        try:
            value = int(tok, 16)
        except ValueError:
            raise CaptureError("%s: %r is not a hex byte" % (where, tok))
        for _ in range(count):
            out.append(value)
    return out


def parse(text, name="capture"):
    cap = Capture(name)
    now = 0
    pending_gap = True  # the first byte line starts a burst
    lineno = 0
    last_key = ""
    pending_frames = []  # [where, tokens]: frame lines, with their '+' continuations
    for raw in text.split("\n"):
        lineno += 1
        where = "%s:%d" % (name, lineno)
        hash_at = raw.find("#")
        line = raw if hash_at < 0 else raw[:hash_at]
        tokens = line.split()
        if not tokens:
            continue
        key = tokens[0].lower()
        args = tokens[1:]
        if key == "+" and last_key not in ("frame", "+"):
            raise CaptureError("%s: a '+' line continues the frame line right above it" % where)
        last_key = key
        if key == "mode":
            if len(args) != 1 or args[0] not in ("ver6", "ver8"):
                raise CaptureError("%s: mode must be ver6 or ver8" % where)
            cap.ver8 = args[0] == "ver8"
        elif key == "timeout":
            cap.timeout_us = _int_arg(args, where)
        elif key == "gap":
            now += _int_arg(args, where)
            pending_gap = True
            cap.end_gap = now
        elif key == "frame":
            pending_frames.append([where, args])
        elif key == "+":
            pending_frames[-1][1] = pending_frames[-1][1] + args
        elif key == "counters":
            if cap.counters is not None:
                raise CaptureError("%s: more than one counters line" % where)
            cap.counters = {}
            for arg in args:
                eq = arg.find("=")
                cname = arg[:eq]
                if eq < 0 or cname not in COUNTER_NAMES:
                    raise CaptureError("%s: %r is not name=value with a counter name of %s" % (where, arg, COUNTER_NAMES))
                cap.counters[cname] = _int_arg([arg[eq + 1 :]], where)
        else:
            data = _hex_bytes(tokens, where)
            if pending_gap or not cap.bursts:
                cap.bursts.append([now, bytearray()])
                pending_gap = False
                cap.end_gap = -1
            cap.bursts[-1][1].extend(data)
    for where, args in pending_frames:
        cap.frames.append(_expected_frame(cap, args, where))
    if cap.counters is None:
        raise CaptureError("%s: no counters line (every capture states the counters it must yield)" % name)
    if cap.counters.get("good", 0) != len(cap.frames):
        raise CaptureError("%s: counters good=%d but %d frame lines" % (name, cap.counters.get("good", 0), len(cap.frames)))
    if not cap.bursts:
        raise CaptureError("%s: no bytes" % name)
    return cap


def _expected_frame(cap, args, where):
    crc = -1
    if len(args) >= 2 and args[-2].lower() == "crc":
        try:
            crc = int(args[-1], 16)
        except ValueError:
            raise CaptureError("%s: bad crc %r" % (where, args[-1]))
        args = args[:-2]
    body = _hex_bytes(args, where)
    if len(body) < 2:
        raise CaptureError("%s: an expected frame needs at least id and type (Ver8: id and sync)" % where)
    return (bytes(body), crc)


def _int_arg(args, where):
    if len(args) != 1:
        raise CaptureError("%s: expected one number" % where)
    try:
        value = int(args[0])
    except ValueError:
        raise CaptureError("%s: %r is not a number" % (where, args[0]))
    if value < 0:
        raise CaptureError("%s: negative number" % where)
    return value


def load(path):
    with open(path) as f:
        text = f.read()
    slash = path.rfind("/")
    return parse(text, path[slash + 1 :])


def hexstr(buf, start=0, end=-1):
    if end < 0:
        end = len(buf)
    return " ".join(["%02X" % buf[i] for i in range(start, end)])


def make_parser(cap, engine="bulk"):
    if cap.timeout_us >= 0:
        return FrameParser(cap.ver8, cap.timeout_us, engine=engine)
    return FrameParser(cap.ver8, engine=engine)


def engines():
    """The parser engines this runtime has: bulk and table everywhere, viper where
    jig.native loads (machine code on the board, plain Python under CPython)."""
    out = ["bulk", "table"]
    try:
        FrameParser(engine="viper")
        out.append("viper")
    except Exception:  # the WebAssembly VM cannot compile viper
        pass
    return out


def replay(cap, step=0, split=-1, engine="bulk"):
    """Feed a capture and return (frames, counters).

    Each burst is fed at its own arrival time. ``step`` > 0 cuts every burst into
    pieces of that many bytes; ``split`` >= 0 additionally cuts the stream at that
    byte offset. Each frame is reported as a tuple (body hex incl. CRC, slave, sync,
    ftype, data_start, data_end, stream offset just after its tail).
    """
    p = make_parser(cap, engine)
    frames = []
    base = 0
    for t, data in cap.bursts:
        now = (T0 + t) % TICKS_PERIOD
        n = len(data)
        cuts = []
        if step > 0:
            cuts = list(range(step, n, step))
        if base < split < base + n:
            cuts.append(split - base)
            cuts.sort()
        cuts.append(n)
        lo = 0
        for hi in cuts:
            i = lo
            while True:
                i = p.feed(data, i, hi, now)
                if p.ready:
                    frames.append((hexstr(p.body, 0, p.body_len), p.slave, p.sync, p.ftype,
                                   p.data_start, p.data_end, base + i))
                if i >= hi:
                    break
            lo = hi
        base += n
    if cap.end_gap >= 0:
        p.check_timeout((T0 + cap.end_gap) % TICKS_PERIOD)
    return frames, p.counters()


def strategies(cap, every_split=True):
    """(label, kwargs) of every way a capture is fed; all must give the same result."""
    n = len(cap.stream())
    out = []
    for engine in engines():
        suffix = "" if engine == "bulk" else "," + engine
        out.append(("whole" + suffix, {"engine": engine}))
        out.append(("bytewise" + suffix, {"step": 1, "engine": engine}))
        out.append(("step7" + suffix, {"step": 7, "engine": engine}))
        if every_split:
            for k in range(1, n):
                out.append(("split%d%s" % (k, suffix), {"split": k, "engine": engine}))
    return out


def check(cap, result):
    """Differences between a replay result and what the capture says; [] if none."""
    frames, counters = result
    problems = []
    if len(frames) != len(cap.frames):
        problems.append("%d frames, expected %d" % (len(frames), len(cap.frames)))
    for k in range(min(len(frames), len(cap.frames))):
        got = frames[k][0]
        body, crc = cap.frames[k]
        want = hexstr(body)
        got_body = got[: len(got) - 6]  # drop " LO HI" of the CRC
        if got_body != want:
            problems.append("frame %d is %s, expected %s" % (k, got_body, want))
        if crc >= 0:
            want_crc = "%02X %02X" % (crc & 0xFF, crc >> 8)
            if got[len(got) - 5 :] != want_crc:
                problems.append("frame %d has CRC bytes %s, expected %s" % (k, got[len(got) - 5 :], want_crc))
    for i in range(len(COUNTER_NAMES)):
        cname = COUNTER_NAMES[i]
        want = cap.counters.get(cname, 0)
        if counters[i] != want:
            problems.append("counter %s=%d, expected %d" % (cname, counters[i], want))
    return problems


def format_result(result):
    frames, counters = result
    lines = []
    for f in frames:
        lines.append("frame %s | slave=%d sync=%d type=%d data=%d:%d end=%d" % f)
    lines.append("counters " + " ".join(["%s=%d" % (COUNTER_NAMES[i], counters[i]) for i in range(len(counters))]))
    return lines


def report(cap, every_split=True):
    """Text lines describing how a capture replays: the frames and counters of the
    whole feed, then one line per feeding strategy (same/differs) and the check.

    Both CPython and the MicroPython VM print this; the test compares them line by line.
    """
    whole = replay(cap)
    lines = ["capture " + cap.name]
    lines.extend(format_result(whole))
    bad = 0
    for label, kw in strategies(cap, every_split):
        other = replay(cap, **kw)
        if other != whole:
            bad += 1
            lines.append("DIFFERS " + label + ": " + " / ".join(format_result(other)))
    lines.append("strategies %s" % ("all same" if bad == 0 else "%d differ" % bad))
    problems = check(cap, whole)
    lines.append("check " + ("ok" if not problems else "; ".join(problems)))
    return lines


def _main(argv):
    import sys

    if len(argv) < 2 or argv[1] in ("-h", "--help"):
        print("usage: capture_format.py encode [--ver8] SLAVE [SYNC] TYPE [DATA...]   (hex bytes)")
        print("       capture_format.py check FILE...")
        print("Prints the wire bytes of a frame (to paste into a capture), or replays captures.")
        return 0
    if argv[1] == "encode":
        from jig import frame

        args = argv[2:]
        ver8 = "--ver8" in args
        args = [a for a in args if a != "--ver8"]
        try:
            values = _hex_bytes(args, "arguments")
        except CaptureError as e:
            print("error: %s" % e)
            return 2
        need = 3 if ver8 else 2
        if len(values) < need:
            print("error: give at least the slave id%s and the frame type" % (", sync" if ver8 else ""))
            return 2
        sync = values[1] if ver8 else -1
        data = bytes(values[need:])
        if len(data) > frame.MAX_DATA:
            print("error: at most %d data bytes" % frame.MAX_DATA)
            return 2
        wire = frame.encode(values[0], values[need - 1], data, sync)
        body = bytearray(frame.MAX_BODY)
        n = frame.build_body(body, values[0], values[need - 1], data, 0, -1, sync)
        print("# crc %02X%02X" % (body[n - 1], body[n - 2]))
        for i in range(0, len(wire), 16):
            print(hexstr(wire, i, min(i + 16, len(wire))))
        return 0
    if argv[1] == "check":
        status = 0
        for path in argv[2:]:
            try:
                cap = load(path)
            except (OSError, CaptureError) as e:
                print("error: %s" % e)
                status = 1
                continue
            for line in report(cap, every_split=False):
                print(line)
        return status
    print("error: unknown command %r (try --help)" % argv[1])
    return 2


if __name__ == "__main__":
    import sys

    try:
        sys.exit(_main(sys.argv))
    except BrokenPipeError:  # output piped into head & co.
        sys.exit(0)
