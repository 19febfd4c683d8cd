"""Viper (native machine code) versions of the per-byte loops: the frame scanner, CRC, copy.

On the board these run as machine code (``compat.load_native``; the stm32 port has a
native emitter, the WebAssembly build does not). Under CPython the very same source
runs as plain Python through the stand-ins in ``jig.compat`` (the decorator does
nothing, ``ptr8``/``ptr16``/``ptr32`` give indexable views), so the host tests check
it against the portable engines; the emulated Cortex-M7 checks the machine code.

Viper has no bounds checks: the callers guarantee the ranges (``st`` has
``parser.S_SIZE`` entries, ``body`` ``frame.MAX_BODY`` bytes, ``tables`` is
``parser.TABLES``). The constants below mirror ``jig.parser`` (viper can only fold
constants of its own module); a host test checks they agree.
"""

try:
    import micropython
except ImportError:  # CPython: run the source as plain Python
    from jig.compat import micropython_shim as micropython
from jig.compat import const, ptr8, ptr16, ptr32  # noqa: F401 (casts under viper)

_HUNT = const(0)
_HEADER = const(1)
_A_NOISE = const(1)
_A_NOISE2 = const(2)
_A_START = const(3)
_A_STORE = const(4)
_A_LITERAL = const(5)
_A_RESYNC = const(6)
_A_END = const(7)
_A_STUFF_ERROR = const(8)
_EV_FRAME = const(1)
_EV_HEAD = const(2)
_EV_DROP = const(3)
_EV_START = const(4)
_S_STATE = const(0)
_S_N = const(1)
_S_EVENT = const(2)
_S_T_LAST = const(3)
_S_TIMEOUT = const(4)
_S_BYTE_US = const(5)
_S_LIMIT = const(6)
_S_MIN_LEN = const(7)
_S_HEAD_AT = const(8)
_S_STOP_DROP = const(9)
_S_GOOD = const(12)
_S_NOISE = const(13)
_S_STUFF_ERRORS = const(14)
_S_CRC_ERRORS = const(15)
_S_SHORT = const(16)
_S_OVERLONG = const(17)
_S_TIMEOUTS = const(18)
_S_RESYNCS = const(19)
_S_WHY = const(20)
_S_START_EV = const(21)
_S_DROP_N = const(22)
_CRC_AT = const(512)  # the CRC table's first u16 in tables
_MASK = const(0x3FFFFFFF)
_HALF = const(0x20000000)


@micropython.viper
def scan(st, data, start: int, end: int, body, tables, now: int) -> int:
    """jig.parser's table, one byte at a time: the contract of parser.scan_py."""
    s = ptr32(st)
    d = ptr8(data)
    b = ptr8(body)
    step = ptr8(tables)
    crct = ptr16(tables)
    ev = 0
    state = s[_S_STATE]
    n = s[_S_N]
    if now >= 0:
        if state != _HUNT:
            t = now
            count = end - start
            if s[_S_BYTE_US] != 0 and count > 1:
                t = (now - (count - 1) * s[_S_BYTE_US]) & _MASK
            if ((t - s[_S_T_LAST] + _HALF) & _MASK) - _HALF > s[_S_TIMEOUT]:
                if state == _HEADER:
                    s[_S_NOISE] += 1
                else:
                    s[_S_TIMEOUTS] += 1
                    if s[_S_STOP_DROP] != 0:
                        ev = _EV_DROP
                        s[_S_WHY] = 0
                        s[_S_DROP_N] = n
                state = _HUNT
                s[_S_STATE] = _HUNT
                if ev != 0:
                    s[_S_EVENT] = ev
                    return start
        if end > start:
            s[_S_T_LAST] = now
    limit = s[_S_LIMIT]
    head_at = s[_S_HEAD_AT]
    stop_drop = s[_S_STOP_DROP]
    start_ev = s[_S_START_EV]
    i = start
    while i < end:
        c = d[i]
        i += 1
        code = step[(state << 8) | c]
        state = code & 3
        a = code >> 2
        if a == _A_STORE or a == _A_LITERAL:
            if n >= limit:
                s[_S_OVERLONG] += 1
                n = 0
                state = _HUNT
                if stop_drop != 0:
                    ev = _EV_DROP
                    s[_S_WHY] = _A_STORE
                    s[_S_DROP_N] = limit
                    break
            else:
                b[n] = c
                n += 1
                if n == head_at:
                    ev = _EV_HEAD
                    break
        elif a == _A_START:
            n = 0
            if start_ev != 0:
                ev = _EV_START
                break
        elif a == _A_END:
            if n < s[_S_MIN_LEN]:
                s[_S_SHORT] += 1
            else:
                crc = 0xFFFF
                k = 0
                while k < n:
                    crc = (crc >> 8) ^ crct[_CRC_AT + ((crc ^ b[k]) & 0xFF)]
                    k += 1
                if crc != 0:
                    s[_S_CRC_ERRORS] += 1
                else:
                    s[_S_GOOD] += 1
                    ev = _EV_FRAME
                    break
            if stop_drop != 0:
                ev = _EV_DROP
                s[_S_WHY] = _A_END
                s[_S_DROP_N] = n
                break
        elif a == _A_NOISE:
            s[_S_NOISE] += 1
        elif a == _A_NOISE2:
            s[_S_NOISE] += 2
        elif a == _A_RESYNC:
            s[_S_RESYNCS] += 1
            if stop_drop != 0:
                ev = _EV_DROP
                s[_S_WHY] = _A_RESYNC
                s[_S_DROP_N] = n
                n = 0
                break
            n = 0
        elif a == _A_STUFF_ERROR:
            s[_S_STUFF_ERRORS] += 1
            if stop_drop != 0:
                ev = _EV_DROP
                s[_S_WHY] = _A_STUFF_ERROR
                s[_S_DROP_N] = n
                break
    s[_S_STATE] = state
    s[_S_N] = n
    s[_S_EVENT] = ev
    return i


@micropython.viper
def crc16(buf, start: int, end: int, crc: int, table) -> int:
    p = ptr8(buf)
    t = ptr16(table)
    i = start
    while i < end:
        crc = (crc >> 8) ^ t[(crc ^ p[i]) & 0xFF]
        i += 1
    return crc


@micropython.viper
def copy(dst, dst_off: int, src, src_off: int, n: int):
    d = ptr8(dst)
    s = ptr8(src)
    i = 0
    while i < n:
        d[dst_off + i] = s[src_off + i]
        i += 1


@micropython.viper
def put_body(body, slave: int, sync: int, ftype: int, data, n: int, table) -> int:
    """frame.build_body for data[0:n]: id, [sync] (if >= 0), type, data, CRC; returns
    the body length."""
    b = ptr8(body)
    d = ptr8(data)
    t = ptr16(table)
    b[0] = slave
    k = 1
    if sync >= 0:
        b[1] = sync
        k = 2
    b[k] = ftype
    k += 1
    i = 0
    while i < n:
        b[k + i] = d[i]
        i += 1
    k += n
    crc = 0xFFFF
    i = 0
    while i < k:
        crc = (crc >> 8) ^ t[(crc ^ b[i]) & 0xFF]
        i += 1
    b[k] = crc & 0xFF
    b[k + 1] = (crc >> 8) & 0xFF
    return k + 2


@micropython.viper
def stuff(out, body, n: int) -> int:
    """frame.stuff_into at offset 0: header, body[0:n] with every 0xAA doubled, tail."""
    o = ptr8(out)
    b = ptr8(body)
    o[0] = 0xAA
    o[1] = 0xCC
    k = 2
    i = 0
    while i < n:
        c = b[i]
        o[k] = c
        k += 1
        if c == 0xAA:
            o[k] = c
            k += 1
        i += 1
    o[k] = 0xAA
    o[k + 1] = 0xEE
    return k + 2


# jig.capture's record layout (a host test checks these agree with it)
_CS_ON = const(0)
_CS_HEAD = const(1)
_CS_TAIL = const(2)
_CS_MASK = const(3)
_CS_LOST = const(4)
_CS_LOST_T0 = const(5)
_CS_LOST_T1 = const(6)
_CS_T_LAST = const(7)
_CS_START = const(8)
_CS_TOTAL = const(12)
_CS_LOST_TOTAL = const(13)
_CS_T_IN = const(14)
_CAP_MARK = const(0xA5)
_CAP_HEADER = const(12)
_CAP_PASSED_HEADER = const(20)
_CAP_PASSED = const(4)
_CAP_LOST = const(0x11)


@micropython.viper
def cap_put(cs, ring, kind: int, body, n: int, t1: int) -> int:
    """jig.capture.put_py: one record into the ring (kind = type | verdict << 8,
    data body[0:n]); 0 if it is full (counted as lost), else 1."""
    c = ptr32(cs)
    if c[_CS_ON] == 0:
        return 0
    typ = kind & 0xFF
    t_in = t1
    hlen = _CAP_HEADER
    t0 = t1
    if typ < 8:
        if typ & _CAP_PASSED:
            t_in = c[_CS_T_IN]
            hlen = _CAP_PASSED_HEADER
        t0 = c[_CS_START + (typ & 3)]
        c[_CS_START + (typ & 3)] = -1
        if t0 < 0:
            t0 = t_in
    mask = c[_CS_MASK]
    head = c[_CS_HEAD]
    need = hlen + n
    lost = c[_CS_LOST]
    if lost != 0:
        need += _CAP_HEADER + 4
    if ((head - c[_CS_TAIL]) & mask) + need > mask:
        if lost == 0:
            c[_CS_LOST_T0] = t1
        c[_CS_LOST] = lost + 1
        c[_CS_LOST_T1] = t1
        c[_CS_LOST_TOTAL] += 1
        return 0
    r = ptr8(ring)
    # Up to five words after the mark: [lost record,] type/verdict/n, times.
    if lost != 0:
        r[head] = _CAP_MARK
        r[(head + 1) & mask] = _CAP_LOST
        r[(head + 2) & mask] = 0
        r[(head + 3) & mask] = 4
        a = c[_CS_LOST_T0]
        z = c[_CS_LOST_T1]
        j = 0
        while j < 4:
            r[(head + 4 + j) & mask] = (a >> (8 * j)) & 0xFF
            r[(head + 8 + j) & mask] = (z >> (8 * j)) & 0xFF
            r[(head + 12 + j) & mask] = (lost >> (8 * j)) & 0xFF
            j += 1
        head = (head + 16) & mask
        c[_CS_LOST] = 0
    r[head] = _CAP_MARK
    r[(head + 1) & mask] = typ
    r[(head + 2) & mask] = (kind >> 8) & 0xFF
    r[(head + 3) & mask] = n
    t2 = t1
    if hlen == _CAP_PASSED_HEADER:
        out = (typ & 3) ^ 3
        t2 = c[_CS_START + out]
        c[_CS_START + out] = -1
        if t2 < 0:
            t2 = t1
    j = 0
    while j < 4:
        sh = 8 * j
        r[(head + 4 + j) & mask] = (t0 >> sh) & 0xFF
        r[(head + 8 + j) & mask] = (t_in >> sh) & 0xFF
        if hlen == _CAP_PASSED_HEADER:
            r[(head + 12 + j) & mask] = (t2 >> sh) & 0xFF
            r[(head + 16 + j) & mask] = (t1 >> sh) & 0xFF
        j += 1
    head = (head + hlen) & mask
    b = ptr8(body)
    j = 0
    if head + n <= mask:  # no wrap inside the data: a plain copy
        while j < n:
            r[head + j] = b[j]
            j += 1
        head += n
    else:
        while j < n:
            r[head] = b[j]
            head = (head + 1) & mask
            j += 1
    c[_CS_HEAD] = head
    c[_CS_T_LAST] = t1
    c[_CS_TOTAL] += 1
    return 1
