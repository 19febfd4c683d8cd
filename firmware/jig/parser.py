"""Bytes in, checked frames out: the receive state machine with per-state recovery.

States and what each byte class does in them (this table is the machine; the code
below only runs it, and ``docs/parser-states.md`` is generated from it)::

    state    | 0xAA               | 0xCC               | 0xEE             | other
    ---------+--------------------+--------------------+------------------+-----------------
    HUNT     | -> HEADER          | noise              | noise            | noise
    HEADER   | noise, stay        | start -> BODY      | noise2 -> HUNT   | noise2 -> HUNT
    BODY     | -> ESCAPE          | store              | store            | store
    ESCAPE   | literal AA -> BODY | resync -> BODY     | end -> HUNT      | stuff error -> HUNT

* ``AA CC`` anywhere restarts a frame; ``AA AA`` inside a frame is one 0xAA, so
  ``AA AA CC`` inside a frame is data, never a header.
* A completed frame is checked: shorter than MIN_BODY (id, one more byte, CRC),
  or a CRC that does not come out to 0, is dropped and counted.
* Ver8 accepts a 4-byte body too, as a Ver8 drive does: it CRC-checks the whole
  body and reads id / sync / type from its first three bytes, so the Ver6-format
  GetCommandPos probe ``id 51 crcL crcH`` parses as sync 0x51, type crcL and a
  data length of -1 (``data_end == data_start - 1``), which marks it for a
  frame-type error reply. A body longer than the protocol allows
  (id, [sync], type, MAX_DATA data bytes, CRC: 253 bytes in Ver6, 254 in Ver8) is
  dropped as soon as it overflows, and the parser hunts for the next header.
* A gap longer than the inter-byte timeout inside a frame drops the partial frame,
  so a truncated frame cannot swallow the start of the next one. The gap is
  measured from the ``now`` of the last call that brought bytes, so polling with
  no data does not keep a partial frame alive.

Three engines run this one table and must agree byte for byte (the host tests and
the emulated Cortex-M7 check it):

* ``viper``: ``jig.native.scan``, one byte at a time in machine code; the default
  where the port has a native emitter (the board). The same source runs as plain
  Python under CPython through the shims in ``jig.compat``.
* ``bulk``: ``scan_py`` below. In HUNT and BODY the table's self-loops cover every
  byte but 0xAA, so runs up to the next 0xAA take one ``find`` and one copy; the
  default on CPython and on MicroPython builds without a native emitter.
* ``table``: ``scan_py`` with the runs switched off, every byte through the table.

Everything that changes while bytes are parsed -- state, body length, counters,
the event that ended a call, the time of the last byte -- lives in one integer
array ``st`` (indices ``S_*``), never in instance attributes: on MicroPython an
attribute store costs several times an array store, and the viper engine can
only reach integers and buffers. Nothing is allocated per frame.

``feed`` returns at the first *event* (``S_EVENT``): ``EV_FRAME``, a good frame is
in ``body``; if asked for at construction, ``EV_START``, a header (AA CC) has
started a frame (cut-through forwarding starts passing it on), ``EV_HEAD``, the
first ``head_at`` body bytes of a frame are known (it routes on them) and
``EV_DROP``, the frame being received ended without being good (bad CRC, too
short, stuffing error, overflow, a new header, an inter-byte timeout); or
``EV_NONE`` when the input is used up.
"""

from array import array

from jig import crc as _crc
from jig.compat import IS_MICROPYTHON, NATIVE, const, ticks_add, ticks_diff
from jig.frame import MAX_BODY
from jig.mem import copy

# A slice allocates on MicroPython (so the firmware copies with jig.mem.copy); on
# CPython, slice assignment is the fastest copy and saves a call per run.
SLICES = not IS_MICROPYTHON

# States
HUNT = const(0)
HEADER = const(1)
BODY = const(2)
ESCAPE = const(3)
STATE_NAMES = ("HUNT", "HEADER", "BODY", "ESCAPE")

# Byte classes
C_STUFF = const(0)  # 0xAA
C_HEADER = const(1)  # 0xCC
C_TAIL = const(2)  # 0xEE
C_OTHER = const(3)
CLASS_NAMES = ("0xAA", "0xCC", "0xEE", "other")

# Actions
A_NONE = const(0)  # remember the 0xAA, nothing else
A_NOISE = const(1)  # one byte discarded outside a frame
A_NOISE2 = const(2)  # the pending 0xAA and this byte discarded
A_START = const(3)  # header complete: empty the body
A_STORE = const(4)  # append this byte
A_LITERAL = const(5)  # append one 0xAA (from AA AA)
A_RESYNC = const(6)  # header inside a frame: drop the partial frame, start anew
A_END = const(7)  # tail: check and deliver the frame
A_STUFF_ERROR = const(8)  # 0xAA followed by a byte that is not AA/CC/EE
ACTION_NAMES = ("-", "noise", "noise x2", "start", "store", "literal AA", "resync", "end", "stuffing error")

# TRANSITIONS[state][byte class] = (action, next state)
TRANSITIONS = (
    # HUNT
    ((A_NONE, HEADER), (A_NOISE, HUNT), (A_NOISE, HUNT), (A_NOISE, HUNT)),
    # HEADER
    ((A_NOISE, HEADER), (A_START, BODY), (A_NOISE2, HUNT), (A_NOISE2, HUNT)),
    # BODY
    ((A_NONE, ESCAPE), (A_STORE, BODY), (A_STORE, BODY), (A_STORE, BODY)),
    # ESCAPE
    ((A_LITERAL, BODY), (A_RESYNC, BODY), (A_END, HUNT), (A_STUFF_ERROR, HUNT)),
)

# Events: why feed() returned
EV_NONE = const(0)  # the input is used up
EV_FRAME = const(1)  # a good frame is in body
EV_HEAD = const(2)  # the first head_at body bytes of a frame are known
EV_DROP = const(3)  # the frame being received ended without being good
EV_START = const(4)  # a header (AA CC) has started a frame
EVENT_NAMES = ("none", "frame", "head", "drop", "start")

# Indices into FrameParser.st (the engines' whole state)
S_STATE = const(0)
S_N = const(1)  # body bytes so far
S_EVENT = const(2)
S_T_LAST = const(3)  # tick of the last byte
S_TIMEOUT = const(4)  # inter-byte timeout, µs
S_BYTE_US = const(5)  # one character time, µs (0: not known)
S_LIMIT = const(6)  # longest body
S_MIN_LEN = const(7)  # shortest good body
S_HEAD_AT = const(8)  # body length that raises EV_HEAD (0: never)
S_STOP_DROP = const(9)  # 1: return EV_DROP when a frame is dropped
S_BULK = const(10)  # scan_py: 1 = runs with find, 0 = every byte through the table
S_HEAD = const(11)  # id, [sync], type: 2 in Ver6, 3 in Ver8
S_GOOD = const(12)  # counters, in COUNTER_NAMES order
S_NOISE = const(13)
S_STUFF_ERRORS = const(14)
S_CRC_ERRORS = const(15)
S_SHORT = const(16)
S_OVERLONG = const(17)
S_TIMEOUTS = const(18)
S_RESYNCS = const(19)
S_WHY = const(20)  # after EV_DROP: the action that dropped the frame (0: inter-byte timeout)
S_START_EV = const(21)  # 1: return EV_START when a header starts a frame
S_DROP_N = const(22)  # after EV_DROP: body bytes of the dropped frame (in body[0:])
S_SIZE = const(23)

# Counter names, in the order ``counters()`` reports them.
COUNTER_NAMES = ("good", "noise", "stuff_errors", "crc_errors", "short", "overlong", "timeouts", "resyncs")

DEFAULT_INTERBYTE_TIMEOUT_US = const(5000)

# Shortest body in either layout: id, one byte (Ver6 type / Ver8 sync), CRC.
MIN_BODY = const(4)


def byte_class(b):
    if b == 0xAA:
        return C_STUFF
    if b == 0xCC:
        return C_HEADER
    if b == 0xEE:
        return C_TAIL
    return C_OTHER


def _tables():
    """TRANSITIONS as one lookup per byte, STEP[state << 8 | byte] = action << 2 | next
    (bytes 0..1023), followed by the CRC table as little-endian u16 (bytes 1024..1535):
    the two tables every engine reads, in one buffer the viper engine can index."""
    t = bytearray(1024 + 512)
    for s in range(len(TRANSITIONS)):
        for b in range(256):
            action, nxt = TRANSITIONS[s][byte_class(b)]
            t[(s << 8) | b] = (action << 2) | nxt
    for i in range(256):
        c = _crc.TABLE[i]
        t[1024 + 2 * i] = c & 0xFF
        t[1025 + 2 * i] = c >> 8
    return t


TABLES = _tables()
STEP = bytes(TABLES[0:1024])


def scan_py(st, data, start, end, body, tables, now):
    """The bulk and table engines (``st[S_BULK]``): same contract as jig.native.scan.

    Consumes data[start:end] until an event; returns the offset after the last byte
    consumed and leaves the event in st[S_EVENT]. ``now`` is the tick of the last of
    these bytes, or -1 for no timing.
    """
    ev = EV_NONE
    state = st[S_STATE]
    n = st[S_N]
    if now >= 0:
        if state != HUNT:
            t = now
            count = end - start
            if st[S_BYTE_US] and count > 1:
                # The first byte came at least (count - 1) character times before the
                # last: judge the gap from there, so a main loop that drains a long
                # burst late does not see a silent line.
                t = ticks_add(now, -(count - 1) * st[S_BYTE_US])
            if ticks_diff(t, st[S_T_LAST]) > st[S_TIMEOUT]:
                if state == HEADER:
                    st[S_NOISE] += 1  # the lone 0xAA
                else:
                    st[S_TIMEOUTS] += 1
                    if st[S_STOP_DROP]:
                        ev = EV_DROP
                        st[S_WHY] = 0
                        st[S_DROP_N] = n
                state = HUNT
                st[S_STATE] = HUNT
                if ev:
                    st[S_EVENT] = ev
                    return start
        if end > start:
            st[S_T_LAST] = now
    limit = st[S_LIMIT]
    head_at = st[S_HEAD_AT]
    stop_drop = st[S_STOP_DROP]
    start_ev = st[S_START_EV]
    bulk = st[S_BULK]
    step = STEP
    i = start
    while i < end:
        if bulk:
            if state == BODY:
                # TRANSITIONS: every byte but 0xAA is stored and stays in BODY.
                j = data.find(b"\xaa", i, end)
                if j < 0:
                    j = end
                if n < head_at and j - i >= head_at - n:
                    j = i + head_at - n  # stop the run where the head is complete
                if j > i:
                    run = j - i
                    if run > limit - n:
                        # As byte by byte: the body fills up, the byte that overflows
                        # ends the frame (the rest of the run is noise, counted in HUNT).
                        if SLICES:
                            body[n:limit] = data[i:i + limit - n]
                        else:
                            copy(body, n, data, i, limit - n)
                        i += limit - n + 1
                        st[S_OVERLONG] += 1
                        n = 0
                        state = HUNT
                        if stop_drop:
                            ev = EV_DROP
                            st[S_WHY] = A_STORE
                            st[S_DROP_N] = limit
                            break
                        continue
                    if SLICES:
                        body[n : n + run] = data[i:j]
                    else:
                        copy(body, n, data, i, run)
                    n += run
                    i = j
                    if n == head_at:
                        ev = EV_HEAD
                        break
                    if i >= end:  # else the run stopped at a 0xAA
                        break
                state = ESCAPE  # TRANSITIONS[BODY][0xAA]
                i += 1
                if i >= end:
                    break
            elif state == HUNT:
                # TRANSITIONS: every byte but 0xAA is noise and stays in HUNT.
                j = data.find(b"\xaa", i, end)
                if j < 0:
                    st[S_NOISE] += end - i
                    i = end
                    break
                if j > i:
                    st[S_NOISE] += j - i
                state = HEADER  # TRANSITIONS[HUNT][0xAA]
                i = j + 1
                if i == end:
                    break
        # One byte through the table.
        b = data[i]
        i += 1
        code = step[(state << 8) | b]
        state = code & 3
        action = code >> 2
        if action == A_STORE or action == A_LITERAL:  # the byte is the 0xAA for a literal
            if n >= limit:
                st[S_OVERLONG] += 1
                n = 0
                state = HUNT
                if stop_drop:
                    ev = EV_DROP
                    st[S_WHY] = A_STORE
                    st[S_DROP_N] = limit
                    break
            else:
                body[n] = b
                n += 1
                if n == head_at:
                    ev = EV_HEAD
                    break
        elif action == A_START:
            n = 0
            if start_ev:
                ev = EV_START
                break
        elif action == A_END:
            if n < st[S_MIN_LEN]:
                st[S_SHORT] += 1
            elif _crc.crc16(body, 0, n):
                st[S_CRC_ERRORS] += 1
            else:
                st[S_GOOD] += 1
                ev = EV_FRAME
                break
            if stop_drop:
                ev = EV_DROP
                st[S_WHY] = A_END
                st[S_DROP_N] = n
                break
        elif action == A_NOISE:
            st[S_NOISE] += 1
        elif action == A_NOISE2:
            st[S_NOISE] += 2
        elif action == A_RESYNC:
            st[S_RESYNCS] += 1
            if stop_drop:
                ev = EV_DROP
                st[S_WHY] = A_RESYNC
                st[S_DROP_N] = n
                n = 0
                break
            n = 0
        elif action == A_STUFF_ERROR:
            st[S_STUFF_ERRORS] += 1
            if stop_drop:
                ev = EV_DROP
                st[S_WHY] = A_STUFF_ERROR
                st[S_DROP_N] = n
                break
    st[S_STATE] = state
    st[S_N] = n
    st[S_EVENT] = ev
    return i


def _engine(name):
    if name == "viper":
        if NATIVE is not None:
            return NATIVE.scan
        from jig import compat

        return compat.native_source().scan  # the viper source as plain Python
    return scan_py


class FrameParser:
    """Incremental Plus-R frame parser.

    ``feed`` consumes bytes until an event or the end of the input and returns the
    offset it stopped at. When ``ready`` is true after a call, the frame is in
    ``body[0:body_len]`` (id to CRC, unstuffed), with ``slave``, ``sync`` (-1 in
    Ver6), ``ftype`` and the data field ``body[data_start:data_end]``. The frame stays
    valid until the next ``feed`` call.

    ``engine``: "viper", "bulk" or "table" (default: viper where the port has a
    native emitter, else bulk; ``bulk=False`` is the old spelling of "table").
    ``head_at``/``stop_drop``/``start_ev`` switch on the EV_HEAD/EV_DROP/EV_START
    events.
    """

    def __init__(self, ver8=False, interbyte_timeout_us=DEFAULT_INTERBYTE_TIMEOUT_US, bulk=True, byte_us=0,
                 engine=None, head_at=0, stop_drop=False, start_ev=False):
        if engine is None:
            engine = "table" if not bulk else ("viper" if NATIVE is not None else "bulk")
        self.engine = engine
        self.scan = _engine(engine)
        self.ver8 = ver8
        self.body = bytearray(MAX_BODY)
        st = array("i", bytes(4 * S_SIZE))
        head = 3 if ver8 else 2
        st[S_HEAD] = head
        st[S_TIMEOUT] = interbyte_timeout_us
        st[S_BYTE_US] = byte_us
        # Longest body accepted: id, [sync], type, MAX_DATA data bytes, CRC.
        st[S_LIMIT] = MAX_BODY if ver8 else MAX_BODY - 1
        st[S_MIN_LEN] = MIN_BODY
        st[S_HEAD_AT] = head_at
        st[S_STOP_DROP] = 1 if stop_drop else 0
        st[S_START_EV] = 1 if start_ev else 0
        st[S_BULK] = 0 if engine == "table" else 1
        self.st = st

    # --- the contract --------------------------------------------------------------
    def feed(self, data, start=0, end=-1, now=None):
        """Consume data[start:end] (bytes or bytearray); ``now`` (µs) is the tick at
        which its last byte arrived, or None for no timing.

        A partial frame is dropped when the line was silent for longer than the
        inter-byte timeout before these bytes. With ``byte_us`` set, the silence is
        measured up to the earliest time the first of them can have arrived;
        without it, up to ``now``.

        Returns the offset after the last byte consumed: ``end``, or the byte after
        the event (``event``). Call again from that offset for the rest.
        """
        if end < 0:
            end = len(data)
        return self.scan(self.st, data, start, end, self.body, TABLES, -1 if now is None else now)

    def check_timeout(self, now):
        """Drop a partial frame whose last byte came more than the timeout before now."""
        st = self.st
        before = st[S_TIMEOUTS] + st[S_NOISE]
        self.scan(st, self.body, 0, 0, self.body, TABLES, now)
        return st[S_TIMEOUTS] + st[S_NOISE] != before

    def reset(self):
        """Forget any partial frame (counters are kept)."""
        self.st[S_STATE] = HUNT
        self.st[S_N] = 0
        self.st[S_EVENT] = EV_NONE

    def reset_counters(self):
        for i in range(S_GOOD, S_GOOD + len(COUNTER_NAMES)):
            self.st[i] = 0

    def counters(self, out=None):
        """Counter values in COUNTER_NAMES order: a new tuple, or written into
        ``out`` (a list or array of 8) without allocating."""
        if out is None:
            return tuple(self.counters([0] * len(COUNTER_NAMES)))
        st = self.st  # (no closure here: a captured local would allocate a cell per call)
        for i in range(len(COUNTER_NAMES)):
            out[i] = st[S_GOOD + i]
        return out

    def in_frame(self):
        s = self.st[S_STATE]
        return s == BODY or s == ESCAPE

    def copy_frame(self, dst, dst_off=0):
        """Copy the current unstuffed frame (id to CRC) into dst; returns its length."""
        n = self.st[S_N]
        copy(dst, dst_off, self.body, 0, n)
        return n

    # --- read-only views of st and body (host code, tests, local handlers) ---------
    @property
    def ready(self):
        return self.st[S_EVENT] == EV_FRAME

    @property
    def max_body(self):
        return self.st[S_LIMIT]

    @max_body.setter
    def max_body(self, n):
        """A reader that keeps whole frames, never fields, takes the longer Ver8 body
        whatever its own layout (a mixed Ver6/Ver8 bus)."""
        self.st[S_LIMIT] = n

    @property
    def slave(self):
        return self.body[0]

    @property
    def sync(self):
        return self.body[1] if self.st[S_HEAD] == 3 else -1

    @property
    def ftype(self):
        return self.body[self.st[S_HEAD] - 1]

    @property
    def data_start(self):
        return self.st[S_HEAD]

    @property
    def data_end(self):
        return self.st[S_N] - 2

    @property
    def interbyte_timeout_us(self):
        return self.st[S_TIMEOUT]

    @interbyte_timeout_us.setter
    def interbyte_timeout_us(self, us):
        self.st[S_TIMEOUT] = us

    @property
    def errors(self):
        st = self.st
        return (st[S_STUFF_ERRORS] + st[S_CRC_ERRORS] + st[S_SHORT] + st[S_OVERLONG]
                + st[S_TIMEOUTS] + st[S_RESYNCS])


def _field(index):
    """A read-only property for st[index]."""
    return property(lambda self: self.st[index])


for _name, _index in (("event", S_EVENT), ("state", S_STATE), ("body_len", S_N), ("t_last", S_T_LAST),
                      ("head", S_HEAD), ("byte_us", S_BYTE_US)):
    setattr(FrameParser, _name, _field(_index))
for _i, _name in enumerate(COUNTER_NAMES):
    setattr(FrameParser, _name, _field(S_GOOD + _i))
