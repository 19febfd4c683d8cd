"""Shared helpers of the tests of the jig's record stream (no tests here): records built
byte by byte from the format, a stream recorded by the real firmware on the virtual
bench with every byte of both buses tapped, and a loopback server that plays a stream
as the jig's capture port does (S starts it, X stops it).

The record builder is written from the format in docs/capture.md, not from
``jig.capture``, so a test that feeds its output to ``JigStream`` checks the reader
against the documented format; the bench streams check it against the firmware.
"""

import socket
import struct
import threading
import time

from test_capture_support import body_of

from jig import frame as F

from motorjig.capture import record as R
from motorjig.capture.jigstream import JigStream
from motorjig.sim.bench import SimBench
from motorjig.sim.link import flip_for_crc

#: 2026-01-01 00:00:00 UTC in µs
EPOCH_US = 1767225600 * 1000000
PERIOD = 1 << 30


# --- records from the format -----------------------------------------------------------
def raw(typ, verdict=0, data=b"", t0=0, t1=None):
    """One record's bytes: A5, type, verdict, n, t_first, t_end, data."""
    t1 = t0 if t1 is None else t1
    return struct.pack("<BBBBII", 0xA5, typ, verdict, len(data), t0 % PERIOD, t1 % PERIOD) + bytes(data)


def hello(t=0, protocol=0, forward=0, slave=1, up=115200, down=115200, interbyte=5000, ring=16384,
          name=b"MotorJig bridge 0.1", version=2, can=0):
    """A hello record; format 2 carries the CAN bitrate (0: no CAN port) before the name,
    format 1 has none."""
    data = struct.pack("<BBBBIIII", version, protocol, forward, slave, up, down, interbyte, ring)
    if version >= 2:
        data += struct.pack("<I", can)
    return raw(0x10, 0, data + name, t, t)


def can(to_bus, can_id, data=b"", t=0, ext=False, rtr=False, dlc=None):
    """A CAN record: type 0x30 | to_bus; u32 identifier, u8 flags (1 extended, 2 RTR),
    u8 DLC, the data bytes (none for RTR)."""
    dlc = len(data) if dlc is None else dlc
    flags = (1 if ext else 0) | (2 if rtr else 0)
    return raw(0x30 | to_bus, 0, struct.pack("<IBB", can_id, flags, dlc) + (b"" if rtr else bytes(data)), t, t)


def lost(n, t0, t1):
    return raw(0x11, 0, struct.pack("<I", n), t0, t1)


def clock(t):
    return raw(0x12, 0, b"", t, t)


def noise(channel, n, t):
    return raw(0x20 | channel, 0, struct.pack("<I", n), t, t)


def frame(channel, body, t0, t1, verdict=R.GOOD):
    return raw(channel, verdict, body, t0, t1)


def passed(into, body, t0, t1, o0, o1, verdict=R.GOOD):
    """A frame received on channel ``into`` (0 the PC bus, 2 the driver bus) and passed on
    to the other bus (cut through): type 4 | into, its ticks there, then those on the other."""
    return struct.pack("<BBBBIIII", 0xA5, 4 | into, verdict, len(body), t0 % PERIOD, t1 % PERIOD, o0 % PERIOD,
                       o1 % PERIOD) + bytes(body)


def body(slave, ftype, data=b""):
    """A frame's body (id, type, data, CRC) as the jig's parser holds it."""
    return body_of(F.encode(slave, ftype, bytes(data)))


def read_all(stream, host_us=EPOCH_US, step=0, **kw):
    """Records of a whole stream (step > 0: fed in pieces of that size) and the reader."""
    js = JigStream("test", **kw)
    recs = []
    pieces = [stream] if step <= 0 else [stream[i:i + step] for i in range(0, len(stream), step)]
    for piece in pieces:
        recs += js.feed(piece, host_us)
    return recs, js


# --- the real firmware on the bench ------------------------------------------------------
class BenchCapture:
    """The jig's record stream of a scenario on SimBench, with both buses tapped.

    ``taps[bus]``: (end of the delivery's last stop bit in µs, bytes) as a listen-only
    node on that bus got them (bus 0 the PC bus, 1 the driver bus); ``t_hello``: the
    bench time of the hello (its tick, unwrapped), so ``records()`` puts the jig's
    times on the bench's timeline (+ EPOCH_US)."""

    def __init__(self, fastpath=None, **kw):
        self.bench = b = SimBench(fastpath=fastpath, **kw)
        self.taps = {0: [], 1: []}
        for bus, link in ((0, b.up_bus), (1, b.down_bus)):
            link.add_node("tap%d" % bus, on_rx=lambda d, t, bus=bus: self.taps[bus].append((t, bytes(d))))
        self.t_hello = int(b.clock.now)
        b.app.set_capture(1, b.hal.ticks_us())
        self.stream = bytearray()

    def drain(self):
        """Take what the jig's ring holds (the bench's capture port is not opened)."""
        self.bench.app.capture.drain_to(self.stream)

    def run(self, us):
        self.bench.run_for(us)
        self.drain()

    def records(self, step=0):
        recs, js = read_all(bytes(self.stream), EPOCH_US + self.t_hello, step)
        return recs, js

    def wire(self, bus):
        """[(byte, start µs, end µs)] of every byte on a bus, in order."""
        bt = (self.bench.up_bus if bus == 0 else self.bench.down_bus).bt
        out = []
        for t, data in self.taps[bus]:
            for k, b in enumerate(data):
                end = t - (len(data) - 1 - k) * bt
                out.append((b, end - bt, end))
        return out


def fill_ring(cap, limit=3000):
    """Round trips with nobody emptying the jig's ring until it has dropped a few records;
    returns how many it dropped."""
    from jig.capture import CS_LOST

    b = cap.bench
    for _ in range(limit):
        b.request(2, F.GET_COMMAND_POS)
        if b.app.capture.cs[CS_LOST] > 3:
            return b.app.capture.cs[CS_LOST]
    raise AssertionError("the ring did not fill in %d round trips" % limit)


def scenario(cap):
    """A few transactions through the jig on both buses, each kind of trouble once:
    requests forwarded to drives 2 and 3 and answered, one answered by the jig itself
    (its stub on the driver bus), a request with a flipped CRC bit (bad CRC on both
    buses, no reply), a drive's reply with a bad CRC (on both buses too), noise from
    the PC, and a silence across the jig's 2**30 µs tick wrap (clock records)."""
    b = cap.bench
    b.request(2, F.GET_COMMAND_POS)
    b.request(1, F.GET_SLAVE_INFO)
    b.request(3, F.GET_AXIS_STATUS)
    cap.run(20000)
    b.send(flip_for_crc(b.encode(3, F.GET_AXIS_STATUS)))
    cap.run(30000)
    b.set_fault("bad-crc", None, 2)
    b.request(2, F.GET_ACTUAL_POS, timeout_us=30000)
    b.clear_faults()
    cap.run(30000)
    b.send(b"\x11\x22\x33")
    cap.run(30000)
    cap.run(3200000)  # past the tick wrap (the bench starts 3 s before it)
    b.request(3, F.SET_PARAMETER, struct.pack("<Bi", 1, 100000))
    b.request(2, F.GET_COMMAND_POS)
    cap.run(20000)
    return cap


# --- a loopback capture port ----------------------------------------------------------------
class JigServer:
    """A loopback TCP server that behaves as the jig's capture port for one client:
    on S it sends ``before`` (what an earlier recording left in the pipeline), then
    ``stream`` in pieces of ``chunk`` bytes ``gap`` s apart; an X after that stops it
    (``stopped``). ``commands`` is every byte the client sent, in order."""

    def __init__(self, stream, before=b"", chunk=512, gap=0.0, answer=True):
        self.stream = bytes(stream)
        self.before = bytes(before)
        self.chunk = chunk
        self.gap = gap
        self.answer = answer
        self.commands = bytearray()
        self.started = threading.Event()
        self.stopped = threading.Event()
        self.sent_all = threading.Event()
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.url = "socket://127.0.0.1:%d" % self.sock.getsockname()[1]
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        try:
            conn, _ = self.sock.accept()
        except OSError:
            return
        with conn:
            conn.settimeout(0.05)
            sending = None
            pos = 0
            while not self._closed.is_set():
                try:
                    got = conn.recv(64)
                    if not got:
                        return
                    self.commands += got
                    for c in got:  # in order: jigctl sends X, S to start afresh
                        if c == 0x53 and self.answer and not self.started.is_set():
                            self.started.set()
                            sending = self.before + self.stream
                        elif c == 0x58 and self.started.is_set():
                            self.stopped.set()
                            sending = None
                except socket.timeout:
                    pass
                except OSError:
                    return
                if sending is not None and pos < len(sending):
                    try:
                        conn.sendall(sending[pos:pos + self.chunk])
                    except OSError:
                        return
                    pos += self.chunk
                    if pos >= len(sending):
                        self.sent_all.set()
                    if self.gap:
                        time.sleep(self.gap)

    def close(self):
        self._closed.set()
        self.sock.close()
        self._thread.join(5)
