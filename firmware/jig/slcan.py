"""SLCAN (Lawicel ASCII) lines in, commands out; CAN frames out as SLCAN lines.

The host (python-can's ``slcan`` interface, Linux's ``slcand``, CANable-style
tools) speaks to the jig's third USB CDC port in lines ending in CR. ``SlcanReader``
reads them with the state machine below, and ``encode_frame``
writes a received CAN frame as the ``t``/``T``/``r``/``R`` line the host expects.

The table is the machine (``docs/slcan-states.md`` is generated from it by
``tools/docgen/gen_slcan_doc.py``): every byte is classified, and (state, byte class)
gives an action and the next state. The counted fields (the id's 3 or 8 hex
digits, 2 per data byte, the 4 of ``sXXYY``) stay in their state until the last
digit, then go where the table says.

Recovery: every fault costs exactly its own line and is counted by kind
(``ERR_NAMES``, ``counts``):

* a fault found inside a line sends the reader to SKIP, which drops bytes up to
  the CR; the CR ends the refused line (``EV_BAD``, the host gets BEL). A line
  longer than the longest valid one (``MAX_LINE``) is refused as ``overlong``
  whatever else is wrong with it;
* a fault found at the CR (too few digits, a missing DLC or argument) refuses the
  line there;
* a command letter where no hex digit can belong (``t``, ``O``, ... -- but ``C``
  and ``F`` are hex digits inside an id or data) means the previous line lost its
  CR: that line is refused as ``missing_cr`` and the letter starts the next line
  (it is read again in START);
* a partial line older than ``LINE_TIMEOUT_US`` is dropped by ``gap(now)`` (and
  by ``feed`` before new bytes), as ``missing_cr`` (or the fault already found).

After a refused line the reader is in START for the byte after the CR. A CR
alone (python-can sends one after ``Sn``) and an LF in START (CRLF line ends) are
ignored. Nothing is allocated in ``feed``, ``gap`` or ``encode_frame``: ids up to
0x1FFFFFFF, arguments and timestamps are small integers on MicroPython, the data
goes into the preallocated ``data``.

Two engines run this one table and must agree byte for byte, state for state
(host_tests/test_slcan.py feeds random and mutated streams through both):

* ``viper``: ``jig.slcanfast.feed``, machine code, the default where the port has
  a native emitter (the board: a 22-byte ``t`` line with 8 data bytes is read in
  ~4 000 instructions, where the table engine as bytecode took ~55 000). It runs
  the counted fields' self-loops (hex digits of the id and the data) as runs
  without the table, every other byte through it. Under CPython its source runs
  as plain Python (``reader_class("viper")``) for the host tests.
* ``table``: ``scan_py``, every byte through the table; ``TableReader``, the
  default on CPython and on MicroPython builds without a native emitter (the
  WebAssembly VM).

Everything that changes while a line is read lives in one integer array ``st``
(indices ``S_*``), the line's fields are stored on the reader when it ends.
"""

from array import array

from jig.compat import IS_MICROPYTHON, const, ticks_diff

# CAN bitrates of S0..S8 (python-can's table: S7 = 750 k; its S9 = 83.3 k is refused).
SLCAN_BITRATES = (10000, 20000, 50000, 100000, 125000, 250000, 500000, 750000, 1000000)

# Longest valid line without its CR: T, 8 id digits, DLC, 16 data digits.
MAX_LINE = const(26)
# A partial line whose last byte is older than this is dropped (the host lost its CR).
LINE_TIMEOUT_US = const(1000000)

# States
START = const(0)  # at the start of a line
ID = const(1)  # t/T/r/R: the id's hex digits (3 or 8)
DLC = const(2)  # the DLC digit 0..8
DATA = const(3)  # two hex digits per data byte
FRAME_END = const(4)  # a complete frame line: only CR belongs
ARG_S = const(5)  # S: the bitrate digit 0..8
ARG_Z = const(6)  # Z: timestamps 0/1
BTR = const(7)  # s: four hex digits (SJA1000 BTR0 BTR1)
BTR_END = const(8)  # sXXYY complete: only CR belongs
END = const(9)  # a complete command (O L C F V N, Sn, Zn): only CR belongs
SKIP = const(10)  # a refused line: drop bytes up to the CR
STATE_NAMES = ("START", "ID", "DLC", "DATA", "FRAME_END", "ARG_S", "ARG_Z", "BTR", "BTR_END", "END", "SKIP")

# Byte classes
K_CR = const(0)
K_LF = const(1)
K_01 = const(2)  # '0' '1'
K_28 = const(3)  # '2'..'8'
K_9 = const(4)  # '9'
K_HEX = const(5)  # hex letters that are no command: A B D E a..f
K_CF = const(6)  # 'C' 'F': commands, and hex digits where a hex digit belongs
K_FRAME = const(7)  # t T r R
K_SIMPLE = const(8)  # O L V N
K_S = const(9)  # 'S'
K_Z = const(10)  # 'Z'
K_BTR = const(11)  # 's'
K_OTHER = const(12)
CLASS_NAMES = ("CR", "LF", "0-1", "2-8", "9", "A B D E a-f", "C F", "t T r R", "O L V N", "S", "Z", "s", "other")

# Errors: index into counts, in ERR_NAMES order.
ERR_UNKNOWN = const(0)  # not a command letter at the start of a line
ERR_HEX = const(1)  # a character that is not a (hex) digit where one belongs
ERR_DLC = const(2)  # the data digits do not match the DLC (too few, too many), DLC > 8
ERR_ARG = const(3)  # S not 0..8, Z not 0/1, s not 4 hex digits; anything after O L C F V N
ERR_SHORT = const(4)  # a frame line ends inside its id or before its DLC
ERR_MISSING_CR = const(5)  # a new command letter, or silence, before the line's CR
ERR_ID = const(6)  # standard id > 0x7FF, extended id > 0x1FFFFFFF
ERR_OVERLONG = const(7)  # longer than MAX_LINE
ERR_NAMES = ("unknown", "hex", "dlc", "argument", "short", "missing_cr", "id_range", "overlong")

# Actions
A_NONE = const(0)  # nothing (an ignored byte, a byte of a refused line)
A_CMD = const(1)  # a command letter: remember it
A_FRAME = const(2)  # t T r R: remember it, extended/RTR, start the id
A_ID = const(3)  # an id digit (the first one checks the range)
A_DLC = const(4)  # the DLC: data digits follow unless RTR or 0
A_DATA = const(5)  # a data digit
A_ARG = const(6)  # the S/Z digit
A_BTR = const(7)  # a BTR digit
A_DONE = const(8)  # CR ends a good line: EV_CMD
A_REFUSE = const(9)  # CR ends a refused line: EV_BAD
A_ERR = const(10)  # A_ERR + ERR_x: the line is refused as ERR_x
A_E_UNKNOWN = const(10)
A_E_HEX = const(11)
A_E_DLC = const(12)
A_E_ARG = const(13)
A_E_SHORT = const(14)
A_E_MISSING_CR = const(15)  # the byte is read again in START
ACTION_NAMES = ("-", "command", "frame", "id digit", "DLC", "data digit", "argument", "BTR digit", "done",
                "refuse", "unknown", "bad hex", "bad DLC", "bad argument", "short", "missing CR")
# Actions that read a counted field: they stay in their state until its last digit.
COUNTED = (A_ID, A_DATA, A_BTR)

_SKIP_HEX = (A_E_HEX, SKIP)
_SKIP_ARG = (A_E_ARG, SKIP)
_LOST_CR = (A_E_MISSING_CR, START)

# TRANSITIONS[state][byte class] = (action, next state)
TRANSITIONS = (
    # START:  CR, LF  |  0-1, 2-8, 9  |  A B D E a-f, C F, t T r R, O L V N  |  S, Z, s, other
    ((A_NONE, START), (A_NONE, START),
     (A_E_UNKNOWN, SKIP), (A_E_UNKNOWN, SKIP), (A_E_UNKNOWN, SKIP),
     (A_E_UNKNOWN, SKIP), (A_CMD, END), (A_FRAME, ID), (A_CMD, END),
     (A_CMD, ARG_S), (A_CMD, ARG_Z), (A_CMD, BTR), (A_E_UNKNOWN, SKIP)),
    # ID
    ((A_E_SHORT, START), _SKIP_HEX,
     (A_ID, DLC), (A_ID, DLC), (A_ID, DLC),
     (A_ID, DLC), (A_ID, DLC), _LOST_CR, _LOST_CR,
     _LOST_CR, _LOST_CR, _LOST_CR, _SKIP_HEX),
    # DLC
    ((A_E_SHORT, START), _SKIP_HEX,
     (A_DLC, DATA), (A_DLC, DATA), (A_E_DLC, SKIP),
     (A_E_DLC, SKIP), _LOST_CR, _LOST_CR, _LOST_CR,
     _LOST_CR, _LOST_CR, _LOST_CR, _SKIP_HEX),
    # DATA
    ((A_E_DLC, START), _SKIP_HEX,
     (A_DATA, FRAME_END), (A_DATA, FRAME_END), (A_DATA, FRAME_END),
     (A_DATA, FRAME_END), (A_DATA, FRAME_END), _LOST_CR, _LOST_CR,
     _LOST_CR, _LOST_CR, _LOST_CR, _SKIP_HEX),
    # FRAME_END
    ((A_DONE, START), _SKIP_HEX,
     (A_E_DLC, SKIP), (A_E_DLC, SKIP), (A_E_DLC, SKIP),
     (A_E_DLC, SKIP), (A_E_DLC, SKIP), _LOST_CR, _LOST_CR,
     _LOST_CR, _LOST_CR, _LOST_CR, _SKIP_HEX),
    # ARG_S
    ((A_E_ARG, START), _SKIP_ARG,
     (A_ARG, END), (A_ARG, END), _SKIP_ARG,
     _SKIP_ARG, _LOST_CR, _LOST_CR, _LOST_CR,
     _LOST_CR, _LOST_CR, _LOST_CR, _SKIP_ARG),
    # ARG_Z
    ((A_E_ARG, START), _SKIP_ARG,
     (A_ARG, END), _SKIP_ARG, _SKIP_ARG,
     _SKIP_ARG, _LOST_CR, _LOST_CR, _LOST_CR,
     _LOST_CR, _LOST_CR, _LOST_CR, _SKIP_ARG),
    # BTR
    ((A_E_ARG, START), _SKIP_ARG,
     (A_BTR, BTR_END), (A_BTR, BTR_END), (A_BTR, BTR_END),
     (A_BTR, BTR_END), (A_BTR, BTR_END), _LOST_CR, _LOST_CR,
     _LOST_CR, _LOST_CR, _LOST_CR, _SKIP_ARG),
    # BTR_END
    ((A_DONE, START), _SKIP_ARG,
     _SKIP_ARG, _SKIP_ARG, _SKIP_ARG,
     _SKIP_ARG, _SKIP_ARG, _LOST_CR, _LOST_CR,
     _LOST_CR, _LOST_CR, _LOST_CR, _SKIP_ARG),
    # END
    ((A_DONE, START), _SKIP_ARG,
     _SKIP_ARG, _SKIP_ARG, _SKIP_ARG,
     _SKIP_ARG, _LOST_CR, _LOST_CR, _LOST_CR,
     _LOST_CR, _LOST_CR, _LOST_CR, _SKIP_ARG),
    # SKIP
    ((A_REFUSE, START), (A_NONE, SKIP),
     (A_NONE, SKIP), (A_NONE, SKIP), (A_NONE, SKIP),
     (A_NONE, SKIP), (A_NONE, SKIP), (A_NONE, SKIP), (A_NONE, SKIP),
     (A_NONE, SKIP), (A_NONE, SKIP), (A_NONE, SKIP), (A_NONE, SKIP)),
)

# Events: why feed() returned
EV_NONE = const(0)  # the input is used up, no line ended
EV_CMD = const(1)  # a good line: cmd and its fields
EV_BAD = const(2)  # a refused line: err (answer BEL)
EVENT_NAMES = ("none", "cmd", "bad")

_HEX_DIGITS = b"0123456789ABCDEF"


def byte_class(b):
    if b == 13:
        return K_CR
    if b == 10:
        return K_LF
    if 0x30 <= b <= 0x31:
        return K_01
    if 0x32 <= b <= 0x38:
        return K_28
    if b == 0x39:
        return K_9
    if b == 0x43 or b == 0x46:  # C F
        return K_CF
    if 0x41 <= b <= 0x46 or 0x61 <= b <= 0x66:
        return K_HEX
    if b == 0x74 or b == 0x54 or b == 0x72 or b == 0x52:  # t T r R
        return K_FRAME
    if b == 0x4F or b == 0x4C or b == 0x56 or b == 0x4E:  # O L V N
        return K_SIMPLE
    if b == 0x53:
        return K_S
    if b == 0x5A:
        return K_Z
    if b == 0x73:
        return K_BTR
    return K_OTHER


# Indices into the reader's st: the partial line and the fields as the engines find
# them, in one integer array (the viper engine reaches it through one pointer).
S_STATE = const(0)
S_N = const(1)  # digits read in the counted field
S_NEED = const(2)  # digits it needs
S_POS = const(3)  # the line's length so far
S_ACC = const(4)  # the value being accumulated (id, BTR)
S_EV = const(5)  # why the engine returned (EV_*)
S_ERR = const(6)  # the fault found in the line (ERR_*)
S_CMD = const(7)  # the line's command byte
S_ID = const(8)
S_EXT = const(9)
S_RTR = const(10)
S_DLC = const(11)
S_ARG = const(12)
S_LINES = const(13)  # good lines
S_T_LAST = const(14)  # tick (µs) of the last call that brought bytes
S_TIMEOUT = const(15)  # line timeout, µs
S_SIZE = const(16)

_TICKS_MASK = const(0x3FFFFFFF)
# HEXVAL's first byte in TABLES, after the STEP bytes of the 11 states.
HEX_AT = const(2816)


def _tables():
    """STEP[state << 8 | byte] = action << 4 | next state (bytes 0..2815), then
    HEXVAL[byte] = the hex digit's value, 0xFF for a byte that is none (bytes
    2816..3071): the tables every engine reads, in one buffer the viper engine can
    index."""
    t = bytearray(HEX_AT + 256)
    for s in range(len(TRANSITIONS)):
        for b in range(256):
            action, nxt = TRANSITIONS[s][byte_class(b)]
            t[(s << 8) | b] = (action << 4) | nxt
    for b in range(256):
        t[HEX_AT + b] = 0xFF
    for v in range(16):
        t[HEX_AT + _HEX_DIGITS[v]] = v
        t[HEX_AT + b"0123456789abcdef"[v]] = v
    return t


TABLES = _tables()
STEP = memoryview(TABLES)[0:HEX_AT]
HEXVAL = memoryview(TABLES)[HEX_AT:HEX_AT + 256]


def scan_py(st, buf, i, n, data, counts, tables, now):
    """The portable engine (``table``): the contract of jig.slcanfast.scan.

    Runs the table over buf[i:n] until a line ends or the input is used up and
    returns the offset after the last byte consumed (a ``missing_cr`` line leaves
    the letter that ended it unconsumed); st[S_EV] says why it returned. The
    fields go to st, the data bytes to ``data``, a refused line's count to
    ``counts``. ``now`` (µs, or -1 for no timing) first drops a partial line whose
    last bytes came more than st[S_TIMEOUT] earlier (then nothing is consumed).
    """
    st[S_EV] = EV_NONE
    state = st[S_STATE]
    if now >= 0:
        if state != START and ticks_diff(now, st[S_T_LAST]) > st[S_TIMEOUT]:
            if state != SKIP:
                st[S_ERR] = ERR_MISSING_CR
            counts[st[S_ERR]] += 1
            st[S_STATE] = START
            st[S_EV] = EV_BAD
            return i
        if n > i:
            st[S_T_LAST] = now & _TICKS_MASK
    nn = st[S_N]
    need = st[S_NEED]
    pos = st[S_POS]
    acc = st[S_ACC]
    ev = EV_NONE
    while i < n:
        if state == SKIP:
            # TRANSITIONS: every byte but CR is dropped and stays in SKIP.
            while i < n and buf[i] != 13:
                i += 1
                pos += 1
            if pos > MAX_LINE:
                st[S_ERR] = ERR_OVERLONG
            if i >= n:
                break
        b = buf[i]
        i += 1
        pos += 1
        code = tables[(state << 8) | b]
        action = code >> 4
        state = code & 15
        if action == A_DATA:
            v = tables[HEX_AT + b]
            if nn & 1:
                data[nn >> 1] |= v
            else:
                data[nn >> 1] = v << 4
            nn += 1
            if nn < need:
                state = DATA
        elif action == A_ID:
            v = tables[HEX_AT + b]
            if nn == 0 and v > (7 if need == 3 else 1):
                st[S_ERR] = ERR_ID
                state = SKIP
                continue
            acc = (acc << 4) | v
            nn += 1
            if nn < need:
                state = ID
            else:
                st[S_ID] = acc
        elif action == A_DONE:
            st[S_LINES] += 1
            ev = EV_CMD
            break
        elif action == A_NONE:
            pass
        elif action == A_FRAME:
            st[S_CMD] = b
            ext = 1 if (b == 0x54 or b == 0x52) else 0  # T R
            st[S_EXT] = ext
            st[S_RTR] = 1 if (b == 0x72 or b == 0x52) else 0  # r R
            need = 8 if ext else 3
            nn = 0
            acc = 0
            pos = 1
        elif action == A_DLC:
            dlc = b - 0x30
            st[S_DLC] = dlc
            nn = 0
            need = dlc << 1
            if st[S_RTR] or dlc == 0:
                state = FRAME_END
        elif action == A_CMD:
            st[S_CMD] = b
            st[S_ARG] = 0
            nn = 0
            need = 4
            acc = 0
            pos = 1
        elif action == A_ARG:
            st[S_ARG] = b - 0x30
        elif action == A_BTR:
            acc = (acc << 4) | tables[HEX_AT + b]
            nn += 1
            if nn < need:
                state = BTR
            else:
                st[S_ARG] = acc
        elif action == A_REFUSE:
            counts[st[S_ERR]] += 1
            ev = EV_BAD
            break
        else:  # A_ERR + ERR_x
            err = action - A_ERR
            st[S_ERR] = err
            if err == ERR_UNKNOWN:
                st[S_CMD] = b
                pos = 1
            if state == START:  # found at the CR, or the CR is missing: refused now
                if err == ERR_MISSING_CR:
                    i -= 1  # the letter starts the next line
                counts[err] += 1
                ev = EV_BAD
                break
    st[S_STATE] = state
    st[S_N] = nn
    st[S_NEED] = need
    st[S_POS] = pos
    st[S_ACC] = acc
    st[S_EV] = ev
    return i


def encode_py(out, off, can_id, ext, rtr, data, dlc, stamp_ms):
    """The portable encode_frame (the contract of jig.slcanfast.encode_frame)."""
    h = _HEX_DIGITS
    if ext:
        out[off] = 0x52 if rtr else 0x54  # R T
        shift = 28
    else:
        out[off] = 0x72 if rtr else 0x74  # r t
        shift = 8
    off += 1
    while shift >= 0:
        out[off] = h[(can_id >> shift) & 15]
        off += 1
        shift -= 4
    out[off] = 0x30 + dlc
    off += 1
    if not rtr:
        for k in range(dlc):
            v = data[k]
            out[off] = h[v >> 4]
            out[off + 1] = h[v & 15]
            off += 2
    if stamp_ms >= 0:
        s = stamp_ms % 60000
        out[off] = h[s >> 12]
        out[off + 1] = h[(s >> 8) & 15]
        out[off + 2] = h[(s >> 4) & 15]
        out[off + 3] = h[s & 15]
        off += 4
    out[off] = 13
    return off + 1


def _load_fast():
    """jig.slcanfast as machine code, or None where it cannot run as such (CPython;
    the WebAssembly build rejects viper at compile time)."""
    if not IS_MICROPYTHON:
        return None
    try:
        from jig import slcanfast

        return slcanfast
    except Exception:  # SyntaxError/ViperTypeError/ImportError: no native emitter here
        return None


FAST = _load_fast()


class TableReader:
    """Incremental SLCAN line reader (see the module docstring and docs/slcan-states.md).

    ``feed(buf, i, n, now)`` consumes buf[i:n] up to the end of one line and returns
    the offset after the last byte consumed; then ``ev`` says what happened. For
    EV_CMD: ``cmd`` (the command's byte), and for frames ``can_id``, ``ext``,
    ``rtr``, ``dlc``, ``data`` (bytearray(8), dlc bytes valid), for S/Z/s ``arg``
    (the digit; the BTR value 0xXXYY). For EV_BAD: ``err`` (index into ERR_NAMES and
    ``counts``; ``refused_lines()`` their sum). ``lines`` counts good lines. The
    fields stay valid until the next ``feed``. The partial line is in the integer
    array ``st`` (``st[S_STATE]``: the table's state).

    This class runs the portable engine (``scan_py``); ``SlcanReader`` is the
    reader of the engine the port can run best (``reader_class``).

    No properties: on MicroPython a class with one makes every attribute store on
    its instances look the class up first (5 times the cost), and ``feed`` stores
    the fields of each line.
    """

    ENGINE = "table"

    def __init__(self, line_timeout_us=LINE_TIMEOUT_US):
        self.st = array("i", bytes(4 * S_SIZE))
        self.st[S_TIMEOUT] = line_timeout_us
        self.counts = array("i", [0] * len(ERR_NAMES))
        self.data = bytearray(8)
        self.tables = TABLES
        self.ev = EV_NONE
        self.err = 0
        self.cmd = 0
        self.can_id = 0
        self.ext = 0
        self.rtr = 0
        self.dlc = 0
        self.arg = 0
        self.lines = 0

    def reset(self):
        """Forget a partial line (counters are kept)."""
        self.st[S_STATE] = START
        self.ev = EV_NONE

    def refused_lines(self):
        """Refused lines, all kinds together."""
        c = self.counts
        total = 0
        for k in range(len(ERR_NAMES)):
            total += c[k]
        return total

    def gap(self, now):
        """Drop a partial line whose last byte came more than st[S_TIMEOUT] µs before
        ``now``: refused (EV_BAD) as missing_cr, or as the fault already found in it.
        Returns 1 if a line was dropped, else 0."""
        st = self.st
        if st[S_STATE] == START or ticks_diff(now, st[S_T_LAST]) <= st[S_TIMEOUT]:
            return 0
        self.feed(_EMPTY, 0, 0, now)  # the engine drops it (both have the same rule)
        return 1

    def feed(self, buf, i, n, now):
        """Consume buf[i:n] until a line ends or the input is used up; ``now`` is the
        tick (µs) the bytes arrived at, or -1 for no timing. Returns the offset after
        the last byte consumed (a ``missing_cr`` line leaves the letter that ended it
        unconsumed)."""
        st = self.st
        i = scan_py(st, buf, i, n, self.data, self.counts, TABLES, now)
        ev = st[S_EV]
        self.ev = ev
        if ev == EV_CMD:
            self.cmd = st[S_CMD]
            self.can_id = st[S_ID]
            self.ext = st[S_EXT]
            self.rtr = st[S_RTR]
            self.dlc = st[S_DLC]
            self.arg = st[S_ARG]
            self.lines = st[S_LINES]
        elif ev == EV_BAD:
            self.err = st[S_ERR]
            self.cmd = st[S_CMD]
        return i


_EMPTY = b""


def _viper_class(fast):
    class ViperReader(TableReader):
        """TableReader with jig.slcanfast.feed as its feed (the same contract)."""

        ENGINE = "viper"
        feed = fast.feed

    return ViperReader


def reader_class(engine=None):
    """The reader class of an engine: "viper" (jig.slcanfast: machine code where the
    port has a native emitter; on CPython its source as plain Python, for the host
    tests) or "table" (``TableReader``); None: the default here (``SlcanReader``)."""
    if engine is None:
        return SlcanReader
    if engine == "table":
        return TableReader
    if engine != "viper":
        raise ValueError("engine: viper or table")
    if FAST is not None:
        return SlcanReader
    if IS_MICROPYTHON:
        raise ValueError("no native emitter here: the table engine only")
    from jig import slcanfast  # CPython: the viper source as plain Python

    return _viper_class(slcanfast)


# The reader the firmware uses: machine code where the port can run it.
SlcanReader = _viper_class(FAST) if FAST is not None else TableReader

# encode_frame(out, off, can_id, ext, rtr, data, dlc, stamp_ms) writes a received
# frame as an SLCAN line into ``out`` at ``off``: t/T/r/R, the id (3 or 8 hex digits),
# the DLC (0..8), the data (not for RTR), a 4-hex-digit timestamp in ms (0..59 999:
# ``stamp_ms % 60000``) if ``stamp_ms >= 0``, CR; returns the offset after the CR (at
# most off + 31) and allocates nothing. Machine code where the port has a native
# emitter, else encode_py.
encode_frame = FAST.encode_frame if FAST is not None else encode_py
