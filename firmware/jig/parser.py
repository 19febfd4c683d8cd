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
* A completed frame is checked: shorter than id+type+CRC, or a CRC that does not
  come out to 0, is dropped and counted. A body longer than MAX_BODY is dropped
  as soon as it overflows and the parser hunts for the next header.
* A gap longer than the inter-byte timeout inside a frame drops the partial frame,
  so a truncated frame cannot swallow the start of the next one.

In HUNT and BODY the table's self-loops (noise / store) cover every byte except
0xAA, so runs up to the next 0xAA are handled with one ``find`` and one copy. The
``bulk=False`` option runs every byte through the table instead; the host tests
check that both give identical results.

Nothing is allocated per frame: the body lives in a preallocated buffer and a
completed frame is described by integer attributes (see ``feed``).
"""

from jig import crc as _crc
from jig import mem
from jig.compat import const, ticks_diff
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


DEFAULT_INTERBYTE_TIMEOUT_US = const(5000)

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
    * ``data_start`` / ``data_end``: the data field within ``body``.

    The frame stays valid until the next ``feed`` call.
    """

    def __init__(self, ver8=False, interbyte_timeout_us=DEFAULT_INTERBYTE_TIMEOUT_US, bulk=True):
        self.ver8 = ver8
        self.interbyte_timeout_us = interbyte_timeout_us
        self.bulk = bulk
        self.body = bytearray(MAX_BODY)
        self.body_len = 0
        self.state = HUNT
        self.t_last = 0
        self.ready = False
        self.slave = 0
        self.sync = -1
        self.ftype = 0
        self.data_start = 0
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
        """Counter values in COUNTER_NAMES order (into ``out`` if given)."""
        values = (self.good, self.noise, self.stuff_errors, self.crc_errors,
                  self.short, self.overlong, self.timeouts, self.resyncs)
        if out is None:
            return values
        for i in range(len(values)):
            out[i] = values[i]
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
        """Consume data[start:end] (bytes or bytearray) received at tick ``now`` (µs).

        Returns the offset after the last byte consumed: ``end``, or the byte after
        the tail of a good frame, in which case ``ready`` is true. Call again from
        that offset for the rest.
        """
        if end < 0:
            end = len(data)
        self.ready = False
        if now is not None:
            self.check_timeout(now)
            self.t_last = now
        i = start
        bulk = self.bulk
        while i < end:
            state = self.state
            if bulk and state == BODY:
                j = data.find(b"\xaa", i, end)
                if j < 0:
                    j = end
                n = j - i
                if n:
                    room = MAX_BODY - self.body_len
                    if n > room:
                        # Same accounting as byte by byte: the byte that overflows
                        # ends the frame, the rest of the run is noise.
                        self.noise += n - room - 1
                        self._overlong()
                        i = j
                        continue
                    mem.copy(self.body, self.body_len, data, i, n)
                    self.body_len += n
                if j == end:
                    return end
                self.state = ESCAPE
                i = j + 1
            elif bulk and state == HUNT:
                j = data.find(b"\xaa", i, end)
                if j < 0:
                    self.noise += end - i
                    return end
                self.noise += j - i
                self.state = HEADER
                i = j + 1
            else:
                b = data[i]
                i += 1
                if self._step(b):
                    return i
        return end

    def _step(self, b):
        """Run one byte through TRANSITIONS; True when it completed a good frame."""
        action, self.state = TRANSITIONS[self.state][byte_class(b)]
        if action == A_STORE or action == A_LITERAL:
            if self.body_len >= MAX_BODY:
                self._overlong()
            else:
                self.body[self.body_len] = b
                self.body_len += 1
        elif action == A_NOISE:
            self.noise += 1
        elif action == A_NOISE2:
            self.noise += 2
        elif action == A_START:
            self.body_len = 0
        elif action == A_RESYNC:
            self.resyncs += 1
            self.body_len = 0
        elif action == A_END:
            return self._finish()
        elif action == A_STUFF_ERROR:
            self.stuff_errors += 1
            self.body_len = 0
        return False

    def _overlong(self):
        self.overlong += 1
        self.body_len = 0
        self.state = HUNT

    def _finish(self):
        n = self.body_len
        head = 3 if self.ver8 else 2
        if n < head + 2:
            self.short += 1
            return False
        if _crc.crc16(self.body, 0, n) != 0:
            self.crc_errors += 1
            return False
        body = self.body
        self.slave = body[0]
        if self.ver8:
            self.sync = body[1]
            self.ftype = body[2]
        else:
            self.sync = -1
            self.ftype = body[1]
        self.data_start = head
        self.data_end = n - 2
        self.good += 1
        self.ready = True
        return True

    def copy_frame(self, dst, dst_off=0):
        """Copy the current unstuffed frame (id to CRC) into dst; returns its length."""
        mem.copy(dst, dst_off, self.body, 0, self.body_len)
        return self.body_len
