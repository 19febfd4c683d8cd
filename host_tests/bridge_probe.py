"""The jig's App on a minimal in-memory HAL, for measurements under CPython and MicroPython.

Used by host_tests/test_bridge_vm.py (through host_tests/wasm/run_vm.mjs: the
real MicroPython VM) and by tools/bench/bench_bridge.py. Nothing here allocates in the
steady state either, so heap growth measured with the collector disabled is the
firmware's own.

* ``forward_alloc(n)`` / ``local_alloc(n)``: heap bytes allocated over n forwarded
  (request forwarded + reply relayed) or local transactions after a warm-up; the
  goal is 0. ``gc.mem_alloc`` exists on MicroPython only.
* ``Rig``: the App plus helpers to push one transaction through it.
"""

import gc

from jig import frame, mem
from jig.counters import C_INT_REQUESTS
from jig.app import App
from jig.ringbuf import RingBuffer

MASK = 0x3FFFFFFF


class Port:
    def __init__(self):
        self.baud = 115200
        self.rx = RingBuffer(1024)
        self.t_last = 0
        self.overflows = 0
        self.tx_blocks = True
        self.echo_free = True  # like the jig's transceivers: /RE tied to DE
        self.out = bytearray(frame.MAX_WIRE)
        self.out_n = 0
        self.writes = 0

    def any(self):
        return self.rx.any()

    def readinto(self, buf, n):
        return self.rx.read_into(buf, n)

    def write(self, buf, off, n):
        # A frame cut through comes in pieces: collect them; ``writes`` counts frames.
        if n >= 2 and buf[off] == 0xAA and buf[off + 1] == 0xCC:
            self.out_n = 0
        mem.copy(self.out, self.out_n, buf, off, n)
        self.out_n += n
        if self.out_n >= 4 and self.out[self.out_n - 2] == 0xAA and self.out[self.out_n - 1] == 0xEE:
            self.writes += 1

    def de(self, v):
        pass

    def hw_de(self, on, pre16, post16):
        return False


class MemFS:
    """``hal.fs`` in memory, for a rig whose parameters are not the defaults."""

    def __init__(self):
        self.files = {}

    def read_into(self, path, buf):
        data = self.files.get(path)
        if data is None:
            return -1
        n = min(len(data), len(buf))
        buf[0:n] = data[0:n]
        return n

    def write(self, path, buf, n):
        self.files[path] = bytes(buf[0:n])

    def rename(self, src, dst):
        self.files[dst] = self.files.pop(src)

    def remove(self, path):
        self.files.pop(path, None)


class NoFS:
    def read_into(self, path, buf):
        return -1

    def write(self, path, buf, n):
        pass

    def rename(self, a, b):
        pass

    def remove(self, path):
        pass


class CapturePort:
    """``hal.capture`` that takes everything (a PC reading the capture port fast)."""

    def __init__(self):
        self.taken = 0
        self.writes = 0

    def any(self):
        return 0

    def readinto(self, buf):
        return 0

    def write(self, buf):
        self.taken += len(buf)
        self.writes += 1
        return len(buf)


class Hal:
    def __init__(self):
        self.t = 0
        self.capture = CapturePort()
        self.fs = NoFS()
        self.param_path = "/p"
        self.outputs = 0
        self.up = None
        self.down = None

    def open(self, up_baud, down_baud):
        self.up = Port()
        self.down = Port()

    def ticks_us(self):
        return self.t

    def sleep_us(self, us):
        self.t = (self.t + us) & MASK

    def set_outputs(self, m):
        self.outputs = m

    def get_outputs(self):
        return self.outputs

    def get_inputs(self):
        return 0

    def heartbeat(self, on):
        pass

    def wdt_feed(self):
        pass


class Rig:
    def __init__(self, capture=False):
        self.hal = Hal()
        self.app = App(self.hal)
        if capture:
            self.app.set_capture(1, self.hal.t)
        self.req = bytearray(frame.encode(2, frame.GET_AXIS_STATUS))
        self.reply = bytearray(frame.encode(2, frame.GET_AXIS_STATUS, b"\x00\x00\x00\x00\x08"))
        self.local = bytearray(frame.encode(1, frame.GET_COMMAND_POS))
        self.counters = bytearray(frame.encode(1, 0xF0))

    def _in(self, port, wire):
        hal = self.hal
        hal.t = (hal.t + 50) & MASK
        port.rx.write(wire, len(wire), hal.t)
        port.t_last = hal.t

    def forward_once(self):
        """PC request in, poll (forwarded), driver reply in, poll (relayed)."""
        hal = self.hal
        self._in(hal.up, self.req)
        self.app.poll()
        self._in(hal.down, self.reply)
        self.app.poll()

    def local_once(self, wire=None):
        self._in(self.hal.up, self.local if wire is None else wire)
        self.app.poll()


def _measure(fn, n):
    for _ in range(20):
        fn()
    gc.collect()
    gc.disable()
    try:
        a0 = gc.mem_alloc()
        for _ in range(n):
            fn()
        a1 = gc.mem_alloc()
    finally:
        gc.enable()
    return a1 - a0


def forward_alloc(n=200, capture=False):
    """With capture: the slow pass runs after every transaction (streaming the records)
    and ``ok`` also asks that both records of each (request and reply, each passed
    on) reached the capture port."""
    r = Rig(capture)
    fn = r.forward_once
    if capture:
        def fn():
            r.forward_once()
            r.hal.t = (r.hal.t + 20000) & MASK  # past every deadline: the slow pass runs
            r.app.poll()
    used = _measure(fn, n)
    ok = r.hal.up.writes == n + 20 and r.hal.up.out[0:r.hal.up.out_n] == r.reply
    if capture:
        ok = ok and r.app.capture.cs[12] == 2 * (n + 20) + 1 and r.app.capture.pending() == 0  # CS_TOTAL: + hello
    return used, ok


def local_alloc(n=200, counters=False, capture=False):
    r = Rig(capture)
    wire = r.counters if counters else r.local
    used = _measure(lambda: r.local_once(wire), n)
    return used, r.hal.up.writes == n + 20


def scan_all_absent():
    """StartBusScan with no driver answering: 16 probes, each timing out; returns
    (probes sent, scan state, heap bytes used by the 16 probes or -1 on CPython)."""
    r = Rig()
    r.local_once(bytearray(frame.encode(1, 0xF2)))
    hal = r.hal

    def pass_30ms():
        hal.t = (hal.t + 30000) & MASK
        r.app.poll()

    used = heap_used(pass_30ms, 40)
    return r.app.counters.v[C_INT_REQUESTS], r.app.scanner.state, used


def heap_used(fn, n):
    """Heap bytes allocated by n calls of fn, the collector off meanwhile (gc.mem_alloc:
    MicroPython only; -1 on CPython, where fn still runs n times)."""
    gc.collect()
    has_mem = hasattr(gc, "mem_alloc")
    if has_mem:
        gc.disable()
        a0 = gc.mem_alloc()
    for _ in range(n):
        fn()
    used = gc.mem_alloc() - a0 if has_mem else -1
    if has_mem:
        gc.enable()
    return used
