"""Received bytes held in a preallocated buffer, for board_check's stand-in UART.

board_check's Python fake of machine.UART reads from it: ``load`` puts bytes on the
line, ``any``/``readinto`` behave like a UART's. (The bridge benchmark's HAL port
is C: tools/firmware/qemu/cmodules/memport.) Nothing allocates per call (board_check reads
with the heap locked). The methods do the work themselves rather than call one another: their
cost is part of the instruction counts the suite reports.
"""

from jig import mem


class MemRx:
    def __init__(self, size=512):
        self.rx = bytearray(size)
        self.rx_n = 0
        self.rx_pos = 0

    def load(self, data, n, off=0):
        """Make data[off:off + n] the bytes waiting to be read (anything unread is dropped)."""
        mem.copy(self.rx, 0, data, off, n)
        self.rx_n = n
        self.rx_pos = 0

    def any(self):
        return self.rx_n - self.rx_pos

    def readinto(self, buf, n):
        k = self.rx_n - self.rx_pos
        if k > n:
            k = n
        mem.copy(buf, 0, self.rx, self.rx_pos, k)
        self.rx_pos += k
        return k
