"""The jig's sampler (jig.trace) on bridge_probe's in-memory rig, one sample at a time.

Runs under CPython, on the WebAssembly MicroPython VM (host_tests/test_trace.py:
heap bytes per sample with the collector off) and frozen into the qemu build
(tools/firmware/qemu/qemu_suite.py). ``TraceRig.sample_once`` is one slot: the clock moves
to the slot, a pass sends the GetAllStatus request, the drive's reply comes in, a
pass stores the sample. ``SetRig`` samples a set of drives (StartTrace's join) and
reads tagged chunks.
"""


from jig import frame
from jig.trace import T_NEXT, T_SLAVE

import bridge_probe

MASK = 0x3FFFFFFF
SLAVE = 2
PERIOD_US = 1000


def all_status_reply(slave, sync=-1, inputs64=False):
    """A GetAllStatus reply: inputs, outputs, flags, command 1000, actual 999, error 1,
    velocity 5000, PT 0 (Ver8 with 64-bit inputs: 36 data bytes)."""
    d = bytearray(1 + (36 if inputs64 else 32))
    w = 8 if inputs64 else 4
    frame.put_u32(d, 1, 0x11)
    frame.put_u32(d, 1 + w, 0x22)
    frame.put_u32(d, 1 + w + 4, 0x08000000)  # moving
    frame.put_u32(d, 1 + w + 8, 1000)
    frame.put_u32(d, 1 + w + 12, 999)
    frame.put_u32(d, 1 + w + 16, 1)
    frame.put_u32(d, 1 + w + 20, 5000)
    return bytearray(frame.encode(slave, frame.GET_ALL_STATUS, bytes(d), sync))


class TraceRig(bridge_probe.Rig):
    def __init__(self, period_us=PERIOD_US):
        bridge_probe.Rig.__init__(self)
        # drive 2 answers once through the bridge: the jig has seen it
        self.req = bytearray(frame.encode(SLAVE, frame.GET_AXIS_STATUS))
        self.reply = bytearray(frame.encode(SLAVE, frame.GET_AXIS_STATUS, b"\x00\x00\x00\x00\x08"))
        self.forward_once()
        self.status = all_status_reply(SLAVE)
        data = bytearray(6)
        data[0] = SLAVE
        frame.put_u32(data, 1, period_us)
        data[5] = 1  # Ver6
        self.local_once(bytearray(frame.encode(1, 0xF5, bytes(data))))
        self.read_req = bytearray(frame.encode(1, 0xF7, b"\x00\x00\x00"))
        self.trace = self.app.trace

    def sample_once(self):
        """One slot: the request goes out, the reply comes in and is stored."""
        hal = self.hal
        hal.t = self.trace.ts[T_NEXT]
        self.app.poll()  # the slow pass is due: the request goes out
        self._in(hal.down, self.status)
        self.app.poll()  # the reply: stored

    def read_once(self):
        """ReadTrace from index 0: the first 12 samples again (a read releases only the
        samples before the index it names, so the ring keeps them)."""
        self.local_once(self.read_req)


def sample_alloc(n=200):
    """Heap bytes allocated over n samples after a warm-up (gc.mem_alloc: MicroPython),
    and whether every sample was stored."""
    r = TraceRig()
    for _ in range(20):
        r.sample_once()
    used = bridge_probe.heap_used(r.sample_once, n)
    return used, r.trace.ts[6] == n + 20  # T_TAKEN


def read_alloc(n=100):
    """Heap bytes allocated over n ReadTrace requests answered (12 samples each, the
    reply written in pieces), and whether every reply went out."""
    r = TraceRig()
    for _ in range(30):
        r.sample_once()
    for _ in range(10):
        r.read_once()
    w0 = r.hal.up.writes
    used = bridge_probe.heap_used(r.read_once, n)
    return used, r.hal.up.writes - w0 == n


def times_alloc(n=100):
    """Heap bytes allocated over n ReadTransactionTimes requests answered while the trace
    runs (a long local reply: written in pieces, the sampler's slots between them), and
    whether every reply went out."""
    r = TraceRig()
    for _ in range(5):
        r.sample_once()
    req = bytearray(frame.encode(1, 0xF9))
    v = r.app.counters.v
    for _ in range(10):
        r.local_once(req)
    out0 = v[1]  # C_UP_OUT
    used = bridge_probe.heap_used(lambda: r.local_once(req), n)
    return used, v[1] - out0 == n


class SetRig(TraceRig):
    """Drives 2, 3 and 4 in the sampler's set (each joining: StartTrace's 7th byte), each
    answering its own GetAllStatus; ReadTrace reads tagged chunks."""

    IDS = (2, 3, 4)

    def __init__(self, period_us=PERIOD_US):
        bridge_probe.Rig.__init__(self)
        self.replies = {}
        for slave in self.IDS:  # each answers once through the bridge: the jig has seen it
            self.req = bytearray(frame.encode(slave, frame.GET_AXIS_STATUS))
            self.reply = bytearray(frame.encode(slave, frame.GET_AXIS_STATUS, b"\x00\x00\x00\x00\x08"))
            self.forward_once()
            self.replies[slave] = all_status_reply(slave)
        for slave in self.IDS:
            data = bytearray(7)
            data[0] = slave
            frame.put_u32(data, 1, period_us)
            data[5] = 1  # Ver6
            data[6] = 1  # join
            self.local_once(bytearray(frame.encode(1, 0xF5, bytes(data))))
        self.read_req = bytearray(frame.encode(1, 0xF7, b"\x00\x00\x00\x01"))
        self.trace = self.app.trace

    def sample_once(self):
        """One slot: the request to the next drive of the set goes out, its reply comes in."""
        hal = self.hal
        hal.t = self.trace.ts[T_NEXT]
        self.app.poll()
        self._in(hal.down, self.replies[self.trace.ts[T_SLAVE]])
        self.app.poll()


def set_sample_alloc(n=200):
    """Heap bytes allocated over n samples of a set of three drives, and whether every
    sample was stored, each drive's a third of them."""
    r = SetRig()
    for _ in range(21):
        r.sample_once()
    used = bridge_probe.heap_used(r.sample_once, n - n % 3)
    tr = r.trace
    k = (n - n % 3 + 21) // 3
    return used, tr.ts[6] == n - n % 3 + 21 and all(tr.d_taken[i] == k for i in SetRig.IDS)


def tagged_read_alloc(n=100):
    """Heap bytes allocated over n tagged ReadTrace requests answered (11 samples each),
    and whether every reply went out."""
    r = SetRig()
    for _ in range(30):
        r.sample_once()
    for _ in range(10):
        r.read_once()
    w0 = r.hal.up.writes
    used = bridge_probe.heap_used(r.read_once, n)
    return used, r.hal.up.writes - w0 == n
