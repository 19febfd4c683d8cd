"""CRC-16 of the Plus-R protocol: reflected polynomial 0xA001, initial 0xFFFF.

This is the CRC-16/MODBUS algorithm (check value of b"123456789" is 0x4B37). It
covers the unstuffed slave id, frame type and data; it is sent low byte first, and
running it over a whole frame body including its CRC gives 0.
"""

from array import array

from jig.compat import NATIVE, const

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

else:
    crc16 = crc16_table
