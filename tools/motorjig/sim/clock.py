"""Event scheduler for the virtual bench: a virtual clock for tests, real time for use.

Times are float microseconds. ``VirtualClock`` jumps from event to event, so a
simulated minute takes as long as the Python work in it. ``RealClock`` follows
``time.monotonic`` and sleeps between events; its ``pump`` hook runs on every
turn (the interactive bench uses it to pull bytes from the pty/TCP threads).
``ticks_us`` gives firmware-style wrapping ticks (2**30 period, like MicroPython).
"""

import heapq
import itertools
import time

TICKS_MASK = 0x3FFFFFFF


class VirtualClock:
    def __init__(self, start_us=0.0):
        self.now = float(start_us)
        self._heap = []
        self._seq = itertools.count()

    def ticks_us(self):
        return int(self.now) & TICKS_MASK

    def at(self, t, fn, *args):
        """Run fn(*args) at time t (µs); never before now."""
        if t < self.now:
            t = self.now
        heapq.heappush(self._heap, (t, next(self._seq), fn, args))

    def after(self, dt, fn, *args):
        self.at(self.now + dt, fn, *args)

    def next_time(self):
        return self._heap[0][0] if self._heap else None

    def run_until(self, t):
        """Run every event due up to t, then set now = t (if later)."""
        heap = self._heap
        while heap and heap[0][0] <= t:
            et, _, fn, args = heapq.heappop(heap)
            if et > self.now:
                self.now = et
            fn(*args)
        if t > self.now:
            self.now = t

    def advance(self, dt):
        self.run_until(self.now + dt)

    def run_while(self, pred, limit_us):
        """Run events while pred() is true, up to now + limit_us. Returns not pred()."""
        end = self.now + limit_us
        heap = self._heap
        while pred():
            if not heap or heap[0][0] > end:
                self.run_until(end)
                return not pred()
            et, _, fn, args = heapq.heappop(heap)
            if et > self.now:
                self.now = et
            fn(*args)
        return True


class RealClock(VirtualClock):
    """Same interface, following the wall clock; ``now`` is µs since creation."""

    def __init__(self, start_us=0.0):
        super().__init__(start_us)
        self._t0 = time.monotonic() - start_us / 1e6
        self.pump = None

    @property
    def now(self):
        return (time.monotonic() - self._t0) * 1e6

    @now.setter
    def now(self, value):
        pass  # real time cannot be set

    def run_until(self, t):
        heap = self._heap
        while True:
            if self.pump is not None:
                self.pump()
            now = self.now
            while heap and heap[0][0] <= now:
                _, _, fn, args = heapq.heappop(heap)
                fn(*args)
            if now >= t:
                return
            nxt = heap[0][0] if heap else t
            wait = min(nxt, t) - now
            if wait > 0:
                time.sleep(min(wait, 1000.0) / 1e6)

    def run_while(self, pred, limit_us):
        end = self.now + limit_us
        while pred():
            if self.now >= end:
                return not pred()
            self.run_until(min(end, self.now + 500.0))
        return True
