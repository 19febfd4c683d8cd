"""Viper (native machine code) versions of the two per-byte loops: CRC and byte copy.

Imported only on MicroPython, through ``compat.load_native``, and only where the
port has a native emitter (the stm32 port does; the WebAssembly build does not).
``crc`` and ``mem`` fall back to portable code when this module cannot load, and
the host tests check that both paths give the same results.
"""

import micropython


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
