"""The jig's CAN port in its steady state, for heap measurements in the MicroPython VM.

Used by host_tests/test_canport.py through host_tests/wasm/run_vm.mjs (the real
MicroPython VM). The App runs on bridge_probe's in-memory HAL plus ``ProbeCan``, a
minimal stand-in for machine.CAN that calls the port's IRQ handler at once (as the
controller's hard IRQ would) and allocates nothing itself, and ``ProbeSlcan``, a
host side that takes every line. Everything here is MicroPython-compatible and
also runs under CPython (where ``gc.mem_alloc`` is missing: -1).

* ``rx_alloc(n)``: heap bytes over n frames received -> SLCAN line to the host;
* ``tx_alloc(n)``: ... over n SLCAN frame lines from the host -> frame sent, its
  TX interrupt, counted;
* ``idle_alloc(n)``: ... over n main-loop passes with the port closed and idle;
* ``open_idle_alloc(n)``: ... over n of the open port's own passes with nothing to do.
Each returns (bytes, ok) where ok says the frames went where they should.
"""

import bridge_probe
from bridge_probe import MASK
from bridge_probe import heap_used as _heap_used
from jig.app import App


def heap_used(fn, n, warm=20):
    """bridge_probe.heap_used after ``warm`` calls (the first pass through a path may
    intern or grow something once)."""
    for _ in range(warm):
        fn()
    return _heap_used(fn, n)


class ProbeCan:
    """machine.CAN as jig.canport uses it; one frame in each direction at a time."""

    FLAG_RTR = 1
    FLAG_EXT_ID = 2
    IRQ_TX = 1
    IRQ_RX = 2
    IRQ_TX_FAILED = 4
    IRQ_STATE = 8
    STATE_ACTIVE = 1

    def __init__(self):
        self.buf = bytearray(8)
        mv = memoryview(self.buf)
        self.views = [mv[0:k] for k in range(9)]
        self.handler = None
        self.rx_id = 0
        self.rx_n = 0
        self.rx_pending = 0
        self.tx_pending = 0
        self.tx_done = 0
        self.sent = 0
        self.last_id = 0
        self.last_len = 0

    def irq(self, handler=None, trigger=0, hard=False):
        if handler is not None:
            self.handler = handler
        return self

    def flags(self):
        f = 0
        if self.rx_pending:
            f |= 2
        if self.tx_done:
            self.tx_done = 0
            f |= 1
        return f

    def recv(self, lst):
        if not self.rx_pending:
            return None
        self.rx_pending = 0
        lst[0] = self.rx_id
        lst[1] = self.views[self.rx_n]
        lst[2] = 0
        lst[3] = 0
        return lst

    def send(self, can_id, data, flags=0):
        self.tx_pending = 1
        self.sent += 1
        self.last_id = can_id
        self.last_len = len(data)
        return 0

    def state(self):
        return 1

    def get_counters(self, lst):
        for i in range(8):
            lst[i] = 0
        return lst

    def restart(self):
        pass

    def deinit(self):
        pass

    # the bus's side
    def frame_in(self, can_id, n):
        for i in range(n):
            self.buf[i] = 0x11 * (i + 1)
        self.rx_id = can_id
        self.rx_n = n
        self.rx_pending = 1
        self.handler(self)

    def frame_out(self):
        if self.tx_pending:
            self.tx_pending = 0
            self.tx_done = 1
            self.handler(self)


class ProbeSlcan:
    """The host's side of the SLCAN port: feeds one preallocated line, takes every byte."""

    def __init__(self):
        self.line = bytearray(32)
        self.n = 0
        self.off = 0
        self.taken = 0

    def give(self, text):
        for i in range(len(text)):
            self.line[i] = text[i]
        self.n = len(text)
        self.off = 0

    def again(self):
        self.off = 0

    def any(self):
        return self.n - self.off

    def readinto(self, buf):
        k = self.n - self.off
        if k > len(buf):
            k = len(buf)
        for i in range(k):
            buf[i] = self.line[self.off + i]
        self.off += k
        return k

    def write(self, buf):
        self.taken += len(buf)
        return len(buf)


class CanHal(bridge_probe.Hal):
    def __init__(self):
        super().__init__()
        self.slcan = ProbeSlcan()
        self.can = ProbeCan()

    def can_open(self, bitrate, listen_only):
        return self.can

    def can_close(self, can):
        can.deinit()


class CanRig:
    def __init__(self, open_it=True):
        self.hal = CanHal()
        self.app = App(self.hal)
        if open_it:
            self.hal.slcan.give(b"O\r")
            self.step(20000)
            self.hal.slcan.n = 0

    def step(self, us):
        hal = self.hal
        hal.t = (hal.t + us) & MASK
        self.app.poll()


def rx_alloc(n=200):
    r = CanRig()
    can = r.hal.can
    port = r.hal.slcan
    t0 = port.taken

    def one():
        can.frame_in(0x181, 8)  # the IRQ: into the ring, the slow pass due now
        r.step(10)  # the slow pass: the line out

    used = heap_used(one, n)
    line = len(b"t18181122334455667788\r")
    return used, port.taken - t0 == (n + 20) * line and r.app.can.cv[0] == n + 20


def tx_alloc(n=200):
    r = CanRig()
    can = r.hal.can
    port = r.hal.slcan
    port.give(b"t60582B40600002000000\r")

    def one():
        port.again()
        r.step(1000)  # the line read, queued, handed to the controller
        can.frame_out()  # its TX interrupt
        r.step(1000)  # counted

    used = heap_used(one, n)
    return used, can.sent == n + 20 and can.last_id == 0x605 and can.last_len == 8 and r.app.can.cv[1] == n + 20


def idle_alloc(n=2000):
    r = CanRig(open_it=False)

    def one():
        r.step(20)

    used = heap_used(one, n)
    return used, r.app.can.is_open == 0


def open_idle_alloc(n=2000):
    r = CanRig()
    due = r.app.due
    passes = [0]

    def one():
        t = due[1]
        r.step(100)  # CAN_POLL_US: the port's own pass, nothing to do
        if due[1] != t:
            passes[0] += 1

    used = heap_used(one, n)
    return used, r.app.can.is_open == 1 and passes[0] >= n
