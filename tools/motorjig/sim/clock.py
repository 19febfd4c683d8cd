"""Event scheduler for the virtual bench: a virtual clock for tests, real time for use.

Times are float microseconds. ``VirtualClock`` jumps from event to event, so a
simulated minute takes as long as the Python work in it. ``PacedClock`` follows
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


class PacedClock(VirtualClock):
    """Event time paced by the wall clock, for the real-time bench.

    ``now`` is simulated time (µs since creation). Events run in time order, each
    at its own time, and never before the wall clock reaches it; when the host has
    stalled (a GC pause, a loaded machine), the clock catches up event by event
    without sleeping. Using the wall clock itself as ``now`` would move every
    deadline forward during a stall: the jig's 50 ms reply timeout would fire while
    the simulated drive's 0.3 ms turnaround was still pending. ``pump`` runs on
    every pass (the bench pulls the pty/TCP bytes with it).
    """

    def __init__(self, start_us=0.0):
        super().__init__(start_us)
        self._t0 = time.monotonic() - start_us / 1e6
        self.pump = None
        # How far the simulation has fallen behind the wall clock (µs), now and at worst: a
        # loaded host (the bench needs about half a core at 115 200 baud with a trace
        # running) makes it lag, and every request from outside then waits that long
        # in addition, since its bytes reach the bus at their wall time. A PC timeout
        # shorter than the lag reads as a deaf jig: tell the two apart with these.
        self.lag_us = 0.0
        self.max_lag_us = 0.0

    def wall(self):
        return (time.monotonic() - self._t0) * 1e6

    def run_until(self, t):
        while True:
            if self.pump is not None:
                self.pump()
            wall = self.wall()
            # Everything due up to t, but never ahead of the wall clock.
            VirtualClock.run_until(self, t if t < wall else wall)
            lag = self.wall() - self.now  # (after the events: one may have stalled the host)
            self.lag_us = lag if lag > 0.0 else 0.0
            if lag > self.max_lag_us:
                self.max_lag_us = lag
            if wall >= t:
                return
            nxt = self.next_time()
            if nxt is None or nxt > t:
                nxt = t
            if nxt > wall:
                time.sleep(min(nxt - wall, 1000.0) / 1e6)

    def run_while(self, pred, limit_us):
        end = self.now + limit_us
        while pred():
            if self.now >= end:
                return not pred()
            self.run_until(min(end, self.now + 500.0))
        return True
