"""Machine code (viper) for the SLCAN reader and the SLCAN frame-line encoder.

``feed`` is ``jig.slcan.SlcanReader.feed`` where the port has a native emitter:
the reader's table (``slcan.TABLES``: the STEP bytes, then the hex digits'
values) over a buffer until a line ends, with the partial line in the reader's
integer array ``st`` (indices ``slcan.S_*``) and the fields of a line that ended
stored on the reader -- the contract of ``slcan.TableReader.feed``. The hex
digits of the id and the data (the table's self-loops in ID and DATA) go in runs,
two data digits at a time; every other byte goes through the table. One call
does a whole line: a call from Python costs more than the work on its bytes.
``encode_frame`` is ``slcan.encode_py``.

The WebAssembly build rejects viper and runs the portable functions
(``slcan._load_fast``). Under CPython the very same source runs as plain Python
through the stand-ins of ``jig.compat``, so the host tests check it against the
portable engine byte for byte; the emulated Cortex-M7 runs the machine code.

Viper has no bounds checks: the reader's arrays have their sizes (``st``
``slcan.S_SIZE`` words, ``counts`` one per ``slcan.ERR_NAMES``, ``data`` 8 bytes)
and ``out`` has room for 31 bytes at ``off``. The constants below mirror
``jig.slcan`` (viper folds only its own module's constants); a host test checks
they agree.
"""

try:
    import micropython
except ImportError:  # CPython: run the source as plain Python
    from jig.compat import micropython_shim as micropython
from jig.compat import const, ptr8, ptr32  # noqa: F401 (casts under viper)

_START = const(0)
_ID = const(1)
_DLC = const(2)
_DATA = const(3)
_FRAME_END = const(4)
_BTR = const(7)
_SKIP = const(10)

_A_NONE = const(0)
_A_CMD = const(1)
_A_FRAME = const(2)
_A_ID = const(3)
_A_DLC = const(4)
_A_DATA = const(5)
_A_ARG = const(6)
_A_BTR = const(7)
_A_DONE = const(8)
_A_REFUSE = const(9)
_A_ERR = const(10)

_ERR_UNKNOWN = const(0)
_ERR_MISSING_CR = const(5)
_ERR_ID = const(6)
_ERR_OVERLONG = const(7)

_EV_CMD = const(1)
_EV_BAD = const(2)

_S_STATE = const(0)
_S_N = const(1)
_S_NEED = const(2)
_S_POS = const(3)
_S_ACC = const(4)
_S_EV = const(5)
_S_ERR = const(6)
_S_CMD = const(7)
_S_ID = const(8)
_S_EXT = const(9)
_S_RTR = const(10)
_S_DLC = const(11)
_S_ARG = const(12)
_S_LINES = const(13)
_S_T_LAST = const(14)
_S_TIMEOUT = const(15)

_HEX_AT = const(2816)  # HEXVAL's first byte in tables (11 states x 256)
_MAX_LINE = const(26)
_MASK = const(0x3FFFFFFF)
_HALF = const(0x20000000)


@micropython.viper
def feed(self, buf, i: int, n: int, now: int) -> int:
    """SlcanReader.feed in machine code: slcan.scan_py's work on the reader's st,
    then the fields of a line that ended stored on the reader (as TableReader.feed)."""
    s = ptr32(self.st)
    state = s[_S_STATE]
    if now >= 0:
        if state != _START and ((now - s[_S_T_LAST] + _HALF) & _MASK) - _HALF > s[_S_TIMEOUT]:
            if state != _SKIP:
                s[_S_ERR] = _ERR_MISSING_CR
            err = s[_S_ERR]
            c = ptr32(self.counts)
            c[err] += 1
            s[_S_STATE] = _START
            s[_S_EV] = _EV_BAD
            self.ev = _EV_BAD
            self.err = err
            self.cmd = s[_S_CMD]
            return i
        if n > i:
            s[_S_T_LAST] = now & _MASK
    b = ptr8(buf)
    t = ptr8(self.tables)
    nn = s[_S_N]
    need = s[_S_NEED]
    pos = s[_S_POS]
    acc = s[_S_ACC]
    ev = 0
    while i < n:
        # The counted fields' self-loops first (TRANSITIONS: in ID and DATA a hex digit
        # stays until the field's last one, then ID -> DLC, DATA -> FRAME_END): whole
        # runs of digits without the table; anything else goes through it below.
        if state == _DATA:
            if nn & 1 == 0:
                e = i + need - nn
                if e > n:
                    e = n - ((n - i) & 1)
                d = ptr8(self.data)
                k = nn >> 1
                j = i
                while j < e:
                    hi = t[_HEX_AT + b[j]]
                    lo = t[_HEX_AT + b[j + 1]]
                    if (hi | lo) > 15:
                        break
                    d[k] = (hi << 4) | lo
                    k += 1
                    j += 2
                nn = k << 1
                pos += j - i
                i = j
                if nn == need:
                    state = _FRAME_END
                if i >= n:
                    break
        elif state == _ID:
            top = 1
            if need == 3:
                top = 7
            if nn != 0 or t[_HEX_AT + b[i]] <= top:  # (a first digit out of range: below)
                while nn < need and i < n:
                    v = t[_HEX_AT + b[i]]
                    if v > 15:
                        break
                    acc = (acc << 4) | v
                    nn += 1
                    i += 1
                    pos += 1
                if nn == need:
                    s[_S_ID] = acc
                    state = _DLC
                if i >= n:
                    break
        elif state == _SKIP:
            # TRANSITIONS: every byte but CR is dropped and stays in SKIP.
            while i < n and b[i] != 13:
                i += 1
                pos += 1
            if pos > _MAX_LINE:
                s[_S_ERR] = _ERR_OVERLONG
            if i >= n:
                break
        # One byte through the table.
        ch = b[i]
        i += 1
        pos += 1
        code = t[(state << 8) | ch]
        action = code >> 4
        state = code & 15
        if action == _A_DATA:
            v = t[_HEX_AT + ch]
            d = ptr8(self.data)
            k = nn >> 1
            if nn & 1:
                d[k] = d[k] | v
            else:
                d[k] = v << 4
            nn += 1
            if nn < need:
                state = _DATA
        elif action == _A_ID:
            v = t[_HEX_AT + ch]
            if nn == 0:
                top = 1
                if need == 3:
                    top = 7
                if v > top:
                    s[_S_ERR] = _ERR_ID
                    state = _SKIP
                    continue
            acc = (acc << 4) | v
            nn += 1
            if nn < need:
                state = _ID
            else:
                s[_S_ID] = acc
        elif action == _A_DONE:
            s[_S_LINES] += 1
            ev = _EV_CMD
            break
        elif action == _A_NONE:
            pass
        elif action == _A_FRAME:
            s[_S_CMD] = ch
            ext = 0
            if ch == 0x54 or ch == 0x52:  # T R
                ext = 1
            rtr = 0
            if ch == 0x72 or ch == 0x52:  # r R
                rtr = 1
            s[_S_EXT] = ext
            s[_S_RTR] = rtr
            need = 3
            if ext:
                need = 8
            nn = 0
            acc = 0
            pos = 1
        elif action == _A_DLC:
            dlc = ch - 0x30
            s[_S_DLC] = dlc
            nn = 0
            need = dlc << 1
            if s[_S_RTR] or dlc == 0:
                state = _FRAME_END
        elif action == _A_CMD:
            s[_S_CMD] = ch
            s[_S_ARG] = 0
            nn = 0
            need = 4
            acc = 0
            pos = 1
        elif action == _A_ARG:
            s[_S_ARG] = ch - 0x30
        elif action == _A_BTR:
            acc = (acc << 4) | t[_HEX_AT + ch]
            nn += 1
            if nn < need:
                state = _BTR
            else:
                s[_S_ARG] = acc
        elif action == _A_REFUSE:
            c = ptr32(self.counts)
            c[s[_S_ERR]] += 1
            ev = _EV_BAD
            break
        else:  # _A_ERR + ERR_x
            err = action - _A_ERR
            s[_S_ERR] = err
            if err == _ERR_UNKNOWN:
                s[_S_CMD] = ch
                pos = 1
            if state == _START:  # found at the CR, or the CR is missing: refused now
                if err == _ERR_MISSING_CR:
                    i -= 1  # the letter starts the next line
                c = ptr32(self.counts)
                c[err] += 1
                ev = _EV_BAD
                break
    s[_S_STATE] = state
    s[_S_N] = nn
    s[_S_NEED] = need
    s[_S_POS] = pos
    s[_S_ACC] = acc
    s[_S_EV] = ev
    self.ev = ev
    if ev == _EV_CMD:
        self.cmd = s[_S_CMD]
        self.can_id = s[_S_ID]
        self.ext = s[_S_EXT]
        self.rtr = s[_S_RTR]
        self.dlc = s[_S_DLC]
        self.arg = s[_S_ARG]
        self.lines = s[_S_LINES]
    elif ev == _EV_BAD:
        self.err = s[_S_ERR]
        self.cmd = s[_S_CMD]
    return i


@micropython.viper
def encode_frame(out, off: int, can_id: int, ext: int, rtr: int, data, dlc: int, stamp_ms: int) -> int:
    """slcan.encode_py: a received frame as an SLCAN line in out at off; returns the end."""
    o = ptr8(out)
    h = ptr8(b"0123456789ABCDEF")
    if ext:
        o[off] = 0x54  # T
        if rtr:
            o[off] = 0x52  # R
        shift = 28
    else:
        o[off] = 0x74  # t
        if rtr:
            o[off] = 0x72  # r
        shift = 8
    off += 1
    while shift >= 0:
        o[off] = h[(can_id >> shift) & 15]
        off += 1
        shift -= 4
    o[off] = 0x30 + dlc
    off += 1
    if not rtr:
        d = ptr8(data)
        k = 0
        while k < dlc:
            v = d[k]
            o[off] = h[v >> 4]
            o[off + 1] = h[v & 15]
            off += 2
            k += 1
    if stamp_ms >= 0:
        ms = stamp_ms % 60000
        o[off] = h[ms >> 12]
        o[off + 1] = h[(ms >> 8) & 15]
        o[off + 2] = h[(ms >> 4) & 15]
        o[off + 3] = h[ms & 15]
        off += 4
    o[off] = 13
    return off + 1
