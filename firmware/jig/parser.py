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

In HUNT and BODY the table's self-loops (noise / store) cover every byte except
0xAA, so runs up to the next 0xAA are handled with one ``find`` and one copy; the
byte after that 0xAA goes through the table (flattened into ``STEP`` at import).
The ``bulk=False`` option runs every byte through the table instead; the host
tests check that both give identical results, and that the self-loops the bulk
path relies on are what the table says.

Nothing is allocated per frame: the body lives in a preallocated buffer and a
completed frame is described by integer attributes (see ``feed``).
"""

from jig.compat import IS_MICROPYTHON, const, ticks_add, ticks_diff
from jig.crc import crc16
from jig.mem import copy
from jig.frame import MAX_BODY

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


def byte_class(b):
    if b == 0xAA:
        return C_STUFF
    if b == 0xCC:
        return C_HEADER
    if b == 0xEE:
        return C_TAIL
    return C_OTHER


def _flatten(table):
    """TRANSITIONS as one lookup per byte: STEP[state << 8 | byte] = action << 2 | next
    (two bits of state: at most four states)."""
    step = bytearray(len(table) << 8)
    for s in range(len(table)):
        for b in range(256):
            action, nxt = table[s][byte_class(b)]
            step[(s << 8) | b] = (action << 2) | nxt
    return bytes(step)


STEP = _flatten(TRANSITIONS)

# A slice allocates on MicroPython (so the firmware copies with jig.mem.copy); on
# CPython, slice assignment is the fastest copy and saves a call per run.
SLICES = not IS_MICROPYTHON

DEFAULT_INTERBYTE_TIMEOUT_US = const(5000)

# Shortest body in either layout: id, one byte (Ver6 type / Ver8 sync), CRC.
MIN_BODY = const(4)

# Counter names, in the order ``counters()`` reports them.
COUNTER_NAMES = ("good", "noise", "stuff_errors", "crc_errors", "short", "overlong", "timeouts", "resyncs")


class FrameParser:
    """Incremental Plus-R frame parser.

    ``feed`` consumes bytes until it has completed one good frame or used up the
    input, and returns the offset it stopped at. When ``ready`` is true after a
    call, the frame is described by:

    * ``body`` / ``body_len``: the unstuffed frame, id to CRC (``body_len`` includes
      the two CRC bytes);
    * ``slave``, ``sync`` (-1 in Ver6), ``ftype``;
    * ``data_start`` / ``data_end``: the data field within ``body``; in Ver8 a
      4-byte body (a Ver6 frame without data) gives ``data_end == data_start - 1``
      and ``ftype`` is then its first CRC byte.

    The frame stays valid until the next ``feed`` call.
    """

    def __init__(self, ver8=False, interbyte_timeout_us=DEFAULT_INTERBYTE_TIMEOUT_US, bulk=True, byte_us=0):
        self.ver8 = ver8
        self.interbyte_timeout_us = interbyte_timeout_us
        # Time of one character on the line (10 bits / baud), or 0: see feed().
        self.byte_us = byte_us
        self.bulk = bulk
        # Longest body accepted: id, [sync], type, MAX_DATA data bytes, CRC.
        self.max_body = MAX_BODY if ver8 else MAX_BODY - 1
        self.head = 3 if ver8 else 2  # id, [sync], type
        self.body = bytearray(MAX_BODY)
        self.body_len = 0
        self.state = HUNT
        self.t_last = 0
        self.ready = False
        self.slave = 0
        self.sync = -1
        self.ftype = 0
        self.data_start = self.head
        self.data_end = 0
        self.reset_counters()

    def reset_counters(self):
        self.good = 0
        self.noise = 0
        self.stuff_errors = 0
        self.crc_errors = 0
        self.short = 0
        self.overlong = 0
        self.timeouts = 0
        self.resyncs = 0

    def counters(self, out=None):
        """Counter values in COUNTER_NAMES order: a new tuple, or written into
        ``out`` (a list or array of 8) without allocating."""
        if out is None:
            return (self.good, self.noise, self.stuff_errors, self.crc_errors,
                    self.short, self.overlong, self.timeouts, self.resyncs)
        out[0] = self.good
        out[1] = self.noise
        out[2] = self.stuff_errors
        out[3] = self.crc_errors
        out[4] = self.short
        out[5] = self.overlong
        out[6] = self.timeouts
        out[7] = self.resyncs
        return out

    def reset(self):
        """Forget any partial frame (counters are kept)."""
        self.state = HUNT
        self.body_len = 0
        self.ready = False

    @property
    def errors(self):
        return self.stuff_errors + self.crc_errors + self.short + self.overlong + self.timeouts + self.resyncs

    def in_frame(self):
        return self.state == BODY or self.state == ESCAPE

    def check_timeout(self, now):
        """Drop a partial frame whose last byte came more than the timeout before now."""
        if self.state != HUNT and ticks_diff(now, self.t_last) > self.interbyte_timeout_us:
            if self.state == HEADER:
                self.noise += 1  # the lone 0xAA
            else:
                self.timeouts += 1
            self.state = HUNT
            self.body_len = 0
            return True
        return False

    def feed(self, data, start=0, end=-1, now=None):
        """Consume data[start:end] (bytes or bytearray); ``now`` (µs) is the tick at
        which its last byte arrived (e.g. RingBuffer.t_last), or None for no timing.

        A partial frame is dropped when the line was silent for longer than the
        inter-byte timeout before these bytes. With ``byte_us`` set, the silence is
        measured up to the earliest time the first of them can have arrived;
        without it, up to ``now``, so a chunk holding more than timeout/byte-time
        bytes of continuous traffic would look like a gap.

        Returns the offset after the last byte consumed: ``end``, or the byte after
        the tail of a good frame, in which case ``ready`` is true. Call again from
        that offset for the rest.
        """
        if end < 0:
            end = len(data)
        self.ready = False
        if now is not None:
            if self.state != HUNT:
                t = now
                if self.byte_us and end - start > 1:
                    # The first byte came at least (count - 1) character times
                    # before the last: judge the gap from there, so a main loop
                    # that drains a long burst late does not see a silent line.
                    t = ticks_add(now, -(end - start - 1) * self.byte_us)
                self.check_timeout(t)
            if end > start:
                # The time of the last byte, not of the last call: polling with no
                # data must not keep a stale partial frame alive.
                self.t_last = now
        # Hot loop: state and body length live in locals and are written back at
        # every exit. After a find, the byte that follows the 0xAA goes through the
        # table in the same pass, so a plain frame takes two passes.
        state = self.state
        n = self.body_len
        body = self.body
        limit = self.max_body
        bulk = self.bulk
        i = start
        while i < end:
            if bulk:
                if state == BODY:
                    # TRANSITIONS: every byte but 0xAA is stored and stays in BODY.
                    j = data.find(b"\xaa", i, end)
                    if j < 0:
                        j = end
                    if j > i:
                        run = j - i
                        if run > limit - n:
                            # As byte by byte: the byte that overflows ends the
                            # frame, the rest of the run is noise.
                            self.noise += run - (limit - n) - 1
                            self.overlong += 1
                            n = 0
                            state = HUNT
                            i = j
                            continue
                        if SLICES:
                            body[n : n + run] = data[i:j]
                        else:
                            copy(body, n, data, i, run)
                        n += run
                    state = ESCAPE  # TRANSITIONS[BODY][0xAA]
                    i = j + 1
                    if i >= end:
                        if j == end:
                            state = BODY  # the run ended with the input, not at a 0xAA
                        break
                elif state == HUNT:
                    # TRANSITIONS: every byte but 0xAA is noise and stays in HUNT.
                    j = data.find(b"\xaa", i, end)
                    if j < 0:
                        self.noise += end - i
                        break
                    if j > i:
                        self.noise += j - i
                    state = HEADER  # TRANSITIONS[HUNT][0xAA]
                    i = j + 1
                    if i == end:
                        break
            # One byte through the table (flattened into STEP).
            b = data[i]
            i += 1
            code = STEP[(state << 8) | b]
            state = code & 3
            action = code >> 2
            if action == A_STORE or action == A_LITERAL:  # the byte is the 0xAA for a literal
                if n >= limit:
                    self.overlong += 1
                    n = 0
                    state = HUNT
                else:
                    body[n] = b
                    n += 1
            elif action == A_START:
                n = 0
            elif action == A_END:
                # Check and publish the frame (inline: this runs once per frame).
                head = self.head
                if n < MIN_BODY:
                    self.short += 1
                elif crc16(body, 0, n):
                    self.crc_errors += 1
                else:
                    self.slave = body[0]
                    if head == 3:
                        self.sync = body[1]
                    self.ftype = body[head - 1]
                    self.data_end = n - 2
                    self.good += 1
                    self.ready = True
                    self.state = state
                    self.body_len = n
                    return i
            elif action == A_NOISE:
                self.noise += 1
            elif action == A_NOISE2:
                self.noise += 2
            elif action == A_RESYNC:
                self.resyncs += 1
                n = 0
            elif action == A_STUFF_ERROR:
                self.stuff_errors += 1
                n = 0
        self.state = state
        self.body_len = n
        return end

    def copy_frame(self, dst, dst_off=0):
        """Copy the current unstuffed frame (id to CRC) into dst; returns its length."""
        copy(dst, dst_off, self.body, 0, self.body_len)
        return self.body_len
