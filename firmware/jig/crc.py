"""CRC-16 of the Plus-R protocol: reflected polynomial 0xA001, initial 0xFFFF.

This is the CRC-16/MODBUS algorithm (check value of b"123456789" is 0x4B37). It
covers the unstuffed slave id, frame type and data; it is sent low byte first, and
running it over a whole frame body including its CRC gives 0.

``crc16`` picks the fastest path of the platform, all giving the same result as
the portable ``crc16_table``: the viper loop of ``jig.native`` on a MicroPython
port with a native emitter, the table loop on other MicroPython builds, and a
two-bytes-per-step table on CPython (host tools and the virtual bench).
"""

from array import array

from jig.compat import IS_MICROPYTHON, NATIVE, const

POLY = const(0xA001)
INIT = const(0xFFFF)


def _make_table():
    table = array("H", bytes(512))
    for n in range(256):
        c = n
        for _ in range(8):
            c = (c >> 1) ^ POLY if c & 1 else c >> 1
        table[n] = c
    return table


TABLE = _make_table()


def crc16_table(buf, start=0, end=-1, crc=INIT):
    """Portable table-driven CRC over buf[start:end] (end=-1: to the end)."""
    if end < 0:
        end = len(buf)
    t = TABLE
    for i in range(start, end):
        crc = (crc >> 8) ^ t[(crc ^ buf[i]) & 0xFF]
    return crc


def update_byte(crc, byte):
    """Advance a running CRC by one byte."""
    return (crc >> 8) ^ TABLE[(crc ^ byte) & 0xFF]


if NATIVE is not None:

    def crc16(buf, start=0, end=-1, crc=INIT):
        """CRC over buf[start:end] with the viper loop (same result as crc16_table)."""
        if end < 0:
            end = len(buf)
        return NATIVE.crc16(buf, start, end, crc, TABLE)

elif IS_MICROPYTHON:
    crc16 = crc16_table

else:
    # CPython (host tools, virtual bench): per-byte Python work is what costs, so
    # take two bytes per step. After 16 bits a CRC-16 register has shifted out
    # completely, so two steps are one lookup: crc = PAIRS[crc ^ (b0 | b1 << 8)].
    # The 65536-entry table is built on first use (~40 ms). Slicing is fine here.
    from struct import Struct as _Struct

    _pairs = []
    # _words[k] unpacks k little-endian 16-bit words (bodies are at most 254 bytes,
    # longer buffers are done in pieces).
    _words = [_Struct("<%dH" % k) for k in range(128)]

    def _make_pairs():
        t = list(TABLE)
        pairs = [0] * 65536
        for x in range(65536):
            c = (x >> 8) ^ t[x & 0xFF]
            pairs[x] = (c >> 8) ^ t[c & 0xFF]
        return pairs

    def crc16(buf, start=0, end=-1, crc=INIT):
        """CRC over buf[start:end], two bytes per step (same result as crc16_table)."""
        if end < 0:
            end = len(buf)
        if not _pairs:
            _pairs.extend(_make_pairs())
        if (end - start) & 1:
            crc = (crc >> 8) ^ TABLE[(crc ^ buf[start]) & 0xFF]
            start += 1
        pairs = _pairs
        k = (end - start) >> 1
        while k > 127:  # longer than any frame body: in pieces
            for w in _words[127].unpack_from(buf, start):
                crc = pairs[crc ^ w]
            start += 254
            k -= 127
        for w in _words[k].unpack_from(buf, start):
            crc = pairs[crc ^ w]
        return crc
