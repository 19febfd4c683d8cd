"""Fixed-size byte ring buffer between a UART receive interrupt and the main loop.

One writer (the interrupt handler) and one reader (the main loop): the writer only
moves ``head``, the reader only moves ``tail``, so no lock is needed. ``write``
and ``read_into`` copy in at most two runs and allocate nothing, so ``write`` may
run in a hard interrupt. Bytes that do not fit are dropped and counted in
``overflows``; nothing is lost silently. ``t_last`` holds the tick (µs) of the last
write, so the parser can time inter-byte gaps from when bytes arrived rather than
from when the main loop got round to them.
"""

from jig import mem


class RingBuffer:
    def __init__(self, size):
        if size < 2 or size & (size - 1):
            raise ValueError("size must be a power of two")
        self.buf = bytearray(size)
        self.mask = size - 1
        self.head = 0  # next write position
        self.tail = 0  # next read position
        self.overflows = 0
        self.t_last = 0

    def capacity(self):
        return self.mask  # one slot stays empty to tell full from empty

    def any(self):
        return (self.head - self.tail) & self.mask

    def free(self):
        return self.mask - ((self.head - self.tail) & self.mask)

    def write(self, src, n, now=0):
        """Append src[0:n]; returns how many bytes fitted (the rest are counted)."""
        room = self.mask - ((self.head - self.tail) & self.mask)
        if n > room:
            self.overflows += n - room
            n = room
        head = self.head
        first = self.mask + 1 - head
        if first > n:
            first = n
        mem.copy(self.buf, head, src, 0, first)
        if n > first:
            mem.copy(self.buf, 0, src, first, n - first)
        self.head = (head + n) & self.mask
        self.t_last = now
        return n

    def put(self, byte, now=0):
        """Append one byte; False (and counted) if the buffer is full."""
        nxt = (self.head + 1) & self.mask
        if nxt == self.tail:
            self.overflows += 1
            return False
        self.buf[self.head] = byte
        self.head = nxt
        self.t_last = now
        return True

    def read_into(self, dst, limit=-1):
        """Move up to min(len(dst), limit) bytes into dst[0:]; returns the count."""
        n = (self.head - self.tail) & self.mask
        room = len(dst)
        if 0 <= limit < room:
            room = limit  # a limit never lets the copy run past the end of dst
        if n > room:
            n = room
        tail = self.tail
        first = self.mask + 1 - tail
        if first > n:
            first = n
        mem.copy(dst, 0, self.buf, tail, first)
        if n > first:
            mem.copy(dst, first, self.buf, 0, n - first)
        self.tail = (tail + n) & self.mask
        return n

    def clear(self):
        self.tail = self.head
