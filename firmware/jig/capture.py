"""The jig's recording of its buses: a ring of records, streamed in the slow pass.

With parameter 13 ``capture`` = 1 (or a ``S`` on the capture port) the bridge writes
one *record* into a preallocated ring for every frame and every dropped fragment
it receives or sends on either Plus-R bus, and the CAN port (``jig.canport``) one
for every CAN frame it receives from or sends onto the CAN bus; the main loop's slow pass moves the ring to the
capture port (the board's second USB CDC port, the bench's TCP port / pty) as far
as the port takes it, never waiting. A full ring drops new records and counts
them; the next record that fits is preceded by a ``lost`` record. So recording
never stalls the bridge, and the host always knows what it did not get.

A record, little-endian (the format is versioned by the ``hello`` record that
starts every stream; docs/capture.md, "The jig's record stream")::

    0  u8   0xA5 (mark)
    1  u8   type: 0..3 a frame on channel (bit 1: 0 PC bus, 1 driver bus;
            bit 0: 0 received by the jig, 1 sent by it); 4 / 6 a frame received
            on the PC / driver bus and passed on to the other (cut through: the
            same bytes on both); 0x10 hello, 0x11 lost, 0x12 clock,
            0x20 | channel: noise bytes counted on a receiving channel;
            0x30 a CAN frame received from the CAN bus, 0x31 one the jig sent onto it
    2  u8   verdict (motorjig.capture.record codes: 0 good, 1 bad CRC, ...)
    3  u8   n, data bytes that follow the header
    4  u32  t_first: the jig's µs tick of the first byte (wraps at 2**30)
    8  u32  t_end: of the last byte
    (types 4, 6 only) 12 u32 t_first, 16 u32 t_end on the other bus
    12/20 n data: a frame's body as the parser holds it (id .. CRC, unstuffed);
            for CAN (0x30, 0x31): u32 identifier, u8 flags (bit 0 extended, bit 1
            RTR), u8 DLC, then the data bytes (DLC of them, none for RTR)

Times: a received frame ends at the tick at which the main loop read the chunk
holding its last byte (on the board within a pass of its stop bit) and starts at
the tick of the read that brought its header (cut through; store-and-forward and a
frame that began with a resync have only the end, and give it twice: the host
dates the first byte back by the frame's wire time). A sent frame starts at the
tick its header was handed to the transmitter and ends when its last stop bit had
gone. A CAN frame has one tick, given by the CAN port, as t_first and t_end. ``put`` is machine code on the board
(``jig.native.cap_put``) and the same logic in Python elsewhere (``put_py``); the
host tests compare the two.
"""

from array import array

from jig.compat import NATIVE, const, ticks_diff
from jig.mem import copy

MARK = const(0xA5)
VERSION = const(2)  # 2: CAN records, the CAN bitrate in the hello
HEADER_LEN = const(12)
PASSED_HEADER_LEN = const(20)  # + t_first and t_end on the other bus

# Record types
CH_PC_IN = const(0)  # received from the PC
CH_PC_OUT = const(1)  # sent to the PC
CH_DRV_IN = const(2)  # received from the drives
CH_DRV_OUT = const(3)  # sent to the drives
T_PASSED = const(4)  # | in channel: received and passed on to the other bus (cut through)
T_PC_PASSED = const(4)  # a PC frame passed on to the drives
T_DRV_PASSED = const(6)  # a driver frame passed on to the PC
T_HELLO = const(0x10)
T_LOST = const(0x11)
T_CLOCK = const(0x12)
T_NOISE = const(0x20)  # | channel
T_CAN = const(0x30)  # | 1: sent onto the CAN bus by the jig; | 0: received from it
T_CAN_IN = const(0x30)
T_CAN_OUT = const(0x31)

# A CAN record's data: u32 identifier, u8 flags, u8 DLC, data
CAN_EXT = const(1)  # flags: 29-bit identifier
CAN_RTR = const(2)  # flags: remote request (no data bytes)
CAN_HEAD = const(6)

# Verdicts (motorjig.capture.record's codes; a host test checks they agree)
V_GOOD = const(0)
V_BAD_CRC = const(1)
V_BAD_STUFFING = const(2)
V_SHORT = const(3)
V_OVERLONG = const(4)
V_TIMEOUT = const(5)
V_RESYNC = const(6)

# Indices into Capture.cs (shared with jig.native.cap_put and jig.fastpath)
CS_ON = const(0)  # 1: recording
CS_HEAD = const(1)  # ring write offset
CS_TAIL = const(2)  # ring read offset (what the port has taken)
CS_MASK = const(3)  # ring size - 1 (a power of two)
CS_LOST = const(4)  # records dropped since the last lost record
CS_LOST_T0 = const(5)  # tick of the first of them
CS_LOST_T1 = const(6)  # ... and of the last
CS_T_LAST = const(7)  # tick of the last record written
CS_START = const(8)  # 8..11: tick of the first byte of the frame in progress, per channel
CS_TOTAL = const(12)  # records written since boot (wraps)
CS_LOST_TOTAL = const(13)  # records lost since boot
CS_T_IN = const(14)  # end of a frame passed on, on the bus it came from (for put)
CS_NEXT = const(15)  # tick before which the bridge asks for no stream window
CS_SIZE = const(16)

RING_SIZE = const(16384)
CLOCK_US = const(1000000)  # a clock record after this long without one (the host unwraps ticks)
STREAM_MAX = const(1024)  # bytes handed to the port per slow pass, at most (its buffer's size)
STREAM_US = const(4000)  # the bridge asks for a stream window at most this often
QUIET_US = const(2000)  # a PC bus silent this long is a window too
STAGE = const(256)  # bytes a write (the CDC's transmit buffer holds 1 KB)

_TICKS_MASK = const(0x3FFFFFFF)
_S_NOISE = const(13)  # jig.parser's (const() takes no imported name)
_S_T_LAST = const(3)

CMD_START = const(0x53)  # "S"
CMD_STOP = const(0x58)  # "X"


def put_py(cs, ring, kind, body, n, t1):
    """Append one record (type | verdict << 8 in ``kind``, data body[0:n], last byte
    at tick t1); 0 if the ring is full (the record is counted as lost), else 1.

    A frame's first tick is ``cs[CS_START + channel]``, which the bridge sets where
    the frame starts (its header read, or handed to the transmitter); it is used
    once (reset to -1), and the end stands in where none was set. A frame passed on
    (type ``T_PASSED | in channel``) ended on its own bus at ``cs[CS_T_IN]`` and on
    the other at t1."""
    if not cs[CS_ON]:
        return 0
    typ = kind & 0xFF
    t_in = t1
    hlen = HEADER_LEN
    if typ < 8:
        if typ & T_PASSED:
            t_in = cs[CS_T_IN]
            hlen = PASSED_HEADER_LEN
        ch = typ & 3
        t0 = cs[CS_START + ch]
        cs[CS_START + ch] = -1
        if t0 < 0:
            t0 = t_in
    else:
        t0 = t1
    mask = cs[CS_MASK]
    head = cs[CS_HEAD]
    need = hlen + n
    lost = cs[CS_LOST]
    if lost:
        need += HEADER_LEN + 4
    if ((head - cs[CS_TAIL]) & mask) + need > mask:
        if lost == 0:
            cs[CS_LOST_T0] = t1
        cs[CS_LOST] = lost + 1
        cs[CS_LOST_T1] = t1
        cs[CS_LOST_TOTAL] += 1
        return 0
    if lost:
        head = _header(ring, mask, head, T_LOST, 4, cs[CS_LOST_T0], cs[CS_LOST_T1])
        head = _u32(ring, mask, head, lost)
        cs[CS_LOST] = 0
    head = _header(ring, mask, head, kind, n, t0, t_in)
    if hlen == PASSED_HEADER_LEN:
        out = (typ & 3) ^ 3  # the other bus, sent
        t = cs[CS_START + out]
        cs[CS_START + out] = -1
        head = _u32(ring, mask, head, t if t >= 0 else t1)
        head = _u32(ring, mask, head, t1)
    for i in range(n):
        ring[head] = body[i]
        head = (head + 1) & mask
    cs[CS_HEAD] = head
    cs[CS_T_LAST] = t1
    cs[CS_TOTAL] += 1
    return 1


def _u32(ring, mask, head, v):
    for k in range(4):
        ring[head] = (v >> (8 * k)) & 0xFF
        head = (head + 1) & mask
    return head


def _header(ring, mask, head, kind, n, t0, t1):
    ring[head] = MARK
    ring[(head + 1) & mask] = kind & 0xFF
    ring[(head + 2) & mask] = (kind >> 8) & 0xFF
    ring[(head + 3) & mask] = n
    head = _u32(ring, mask, (head + 4) & mask, t0)
    return _u32(ring, mask, head, t1)


def _put_engine():
    if NATIVE is not None:
        return NATIVE.cap_put
    return put_py


class Capture:
    """The ring, its state array ``cs`` and the streaming to ``port``.

    ``port`` (the HAL's ``capture``, or None): ``any()`` -> bytes waiting from the
    host, ``readinto(buf)`` -> count, ``write(buf)`` -> bytes taken (0 or None when
    it takes nothing now; it must never block).
    """

    def __init__(self, app, port=None, size=RING_SIZE):
        self.app = app
        self.port = port
        self.ring = bytearray(size)
        cs = array("i", bytes(4 * CS_SIZE))
        cs[CS_MASK] = size - 1
        self.cs = cs
        self.put = _put_engine()
        self.info = bytearray(48)  # the hello record's data
        self.can_body = bytearray(CAN_HEAD + 8)  # a CAN record's data
        self.stage = bytearray(STAGE)
        # One view per length, made once: port.write takes a whole buffer, and a slice
        # of a memoryview allocates on MicroPython.
        mv = memoryview(self.stage)
        self.views = [mv[0:k] for k in range(STAGE + 1)]
        self.cmd = bytearray(1)
        self.noise_seen = array("i", [0, 0])  # noise counts of the two parsers, last reported
        self.up_st = self.down_st = None  # the parsers' state arrays (from start on)

    @property
    def on(self):
        return self.cs[CS_ON] != 0

    # --- switching ----------------------------------------------------------------
    def start(self, now):
        """Recording on: the ring emptied, a hello record first."""
        cs = self.cs
        cs[CS_HEAD] = cs[CS_TAIL] = 0
        cs[CS_LOST] = 0
        for k in range(4):
            cs[CS_START + k] = -1
        cs[CS_ON] = 1
        app = self.app
        self.up_st = app.up_parser.st
        self.down_st = app.down_parser.st
        self.noise_seen[0] = self.up_st[_S_NOISE]
        self.noise_seen[1] = self.down_st[_S_NOISE]
        self.hello(now)

    def hello(self, now):
        """A hello record: the stream's version and how the jig runs (again after an
        immediate parameter change that it reports, and after the CAN port's bitrate
        changed: the CAN port calls it then; nothing while not recording)."""
        n = self._hello_data()
        self.put(self.cs, self.ring, T_HELLO, self.info, n, now)

    def can_frame(self, t, can_id, flags, dlc, data, to_bus):
        """A CAN frame's record (the CAN port calls it from the main loop, not from its
        interrupt): ``flags`` bit 0 extended, bit 1 RTR; ``data[0:dlc]`` its bytes;
        ``to_bus`` 1 if the jig sent it onto the CAN bus, 0 if it received it; ``t``
        its tick. Nothing while not recording; 0 if the ring is full (counted as
        lost), else 1. No allocation."""
        cs = self.cs
        if not cs[CS_ON]:
            return 0
        d = self.can_body
        d[0] = can_id & 0xFF
        d[1] = (can_id >> 8) & 0xFF
        d[2] = (can_id >> 16) & 0xFF
        d[3] = (can_id >> 24) & 0x1F
        d[4] = flags & (CAN_EXT | CAN_RTR)
        if dlc > 8:
            dlc = 8  # (DLC 9..15 of classic CAN: 8 bytes)
        d[5] = dlc
        n = 0 if flags & CAN_RTR else dlc
        for i in range(n):
            d[CAN_HEAD + i] = data[i]
        return self.put(cs, self.ring, T_CAN | (1 if to_bus else 0), d, CAN_HEAD + n, t & _TICKS_MASK)

    def stop(self):
        """Recording off; what is in the ring is dropped."""
        cs = self.cs
        cs[CS_ON] = 0
        cs[CS_HEAD] = cs[CS_TAIL] = 0
        cs[CS_LOST] = 0

    def set(self, on, now):
        if on and not self.cs[CS_ON]:
            self.start(now)
        elif not on and self.cs[CS_ON]:
            self.stop()

    def _hello_data(self):
        from jig import params as P
        from jig.frame import put_u32

        app = self.app
        pr = app.params.ram
        d = self.info
        d[0] = VERSION
        # protocol, forward mode and baud rates as the jig booted with them (changed in
        # RAM they apply from the next boot); the id and timeout as they are now
        d[1] = 1 if app.ver8 else 0
        d[2] = P.CUT_THROUGH if app.cut else P.STORE_AND_FORWARD
        d[3] = pr[P.P_SLAVE_ID]
        put_u32(d, 4, app.up_baud)
        put_u32(d, 8, app.down_baud)
        put_u32(d, 12, pr[P.P_INTERBYTE_US])
        put_u32(d, 16, len(self.ring))
        can = getattr(app, "can", None)  # the CAN port (0: the jig has none)
        put_u32(d, 20, can.bitrate if can is not None else 0)
        name = b"MotorJig bridge 0.1"
        d[24:24 + len(name)] = name
        return 24 + len(name)

    # --- the slow pass ----------------------------------------------------------------
    def slow(self, now, bridge=None):
        """Commands from the host, noise and clock records, and as much of the ring as
        the port takes. Returns 0 if the ring still holds bytes the port is taking
        (the app comes back sooner), else -1.

        The records go out in a *window* (``bridge.stream_window``; always without a
        bridge), when a stall of the main loop costs the bridge nothing: a forwarded
        request waits for its reply (the drive is thinking: the bridge asks for a slow
        pass then, ``CS_NEXT``), or the PC bus has been silent for QUIET_US. A ring
        half full goes out anyway."""
        port = self.port
        if port is not None and port.any():
            self._command(now)
        cs = self.cs
        if not cs[CS_ON]:
            return -1
        seen = self.noise_seen
        st = self.up_st
        if st[_S_NOISE] != seen[0]:
            self._noise(0, CH_PC_IN, st)
        st = self.down_st
        if st[_S_NOISE] != seen[1]:
            self._noise(1, CH_DRV_IN, st)
        if ticks_diff(now, cs[CS_T_LAST]) >= CLOCK_US:
            if self._fits(0):
                self.put(cs, self.ring, T_CLOCK, self.stage, 0, now)
            else:
                cs[CS_T_LAST] = now  # (a full ring is no news: the next lost record says it)
        if port is None or cs[CS_HEAD] == cs[CS_TAIL]:
            return -1
        if (bridge is not None and ((cs[CS_HEAD] - cs[CS_TAIL]) & cs[CS_MASK]) < (cs[CS_MASK] >> 1)
                and not bridge.stream_window(now)):
            return -1  # the next window, or the next slow pass
        # now + STREAM_US, in small ints only (a long int near the tick wrap: jig.bridge)
        cs[CS_NEXT] = ((now - _TICKS_MASK) + (STREAM_US - 1)) & _TICKS_MASK
        return 0 if self._stream() else -1

    def _command(self, now):
        if self.port.readinto(self.cmd):
            c = self.cmd[0]
            if c == CMD_START:
                if self.cs[CS_ON]:
                    self.start(now)  # a new reader: a fresh stream, from a hello
                else:
                    self.app.set_capture(1, now)
            elif c == CMD_STOP:
                self.app.set_capture(0, now)

    def _fits(self, n):
        """True if a record of n data bytes (and a pending lost record) fits the ring:
        the slow pass's own records wait for room rather than count as lost."""
        cs = self.cs
        need = HEADER_LEN + n + (HEADER_LEN + 4 if cs[CS_LOST] else 0)
        return ((cs[CS_HEAD] - cs[CS_TAIL]) & cs[CS_MASK]) + need <= cs[CS_MASK]

    def _noise(self, k, ch, st):
        """A noise record: the bytes the parser st counted outside frames since the last
        (they add up in the parser while the ring has no room)."""
        if not self._fits(4):
            return
        n = st[_S_NOISE] - self.noise_seen[k]
        d = self.stage
        d[0] = n & 0xFF
        d[1] = (n >> 8) & 0xFF
        d[2] = (n >> 16) & 0xFF
        d[3] = (n >> 24) & 0xFF
        if self.put(self.cs, self.ring, T_NOISE | ch, d, 4, st[_S_T_LAST]):
            self.noise_seen[k] = st[_S_NOISE]

    def _stream(self):
        """Hand the port what it takes (STAGE bytes a write, STREAM_MAX a pass);
        True if the ring still holds bytes after that."""
        cs = self.cs
        ring = self.ring
        stage = self.stage
        mask = cs[CS_MASK]
        port = self.port  # (port.write(...) is a method call; a bound method kept would allocate)
        sent = 0
        while sent < STREAM_MAX:
            tail = cs[CS_TAIL]
            left = (cs[CS_HEAD] - tail) & mask
            if left == 0:
                return False
            k = left if left < STAGE else STAGE
            first = mask + 1 - tail  # bytes up to the ring's end
            if first >= k:
                copy(stage, 0, ring, tail, k)
            else:
                copy(stage, 0, ring, tail, first)
                copy(stage, first, ring, 0, k - first)
            w = port.write(self.views[k])
            if not w:
                return False  # the port takes nothing now (full, or not open): back to the slow pace
            cs[CS_TAIL] = (tail + w) & mask
            sent += w
        return cs[CS_HEAD] != cs[CS_TAIL]

    def pending(self):
        """Bytes in the ring not yet taken by the port."""
        cs = self.cs
        return (cs[CS_HEAD] - cs[CS_TAIL]) & cs[CS_MASK]

    def drain_to(self, out):
        """Test and bench helper: move everything in the ring into ``out`` (a bytearray)."""
        cs = self.cs
        mask = cs[CS_MASK]
        while cs[CS_HEAD] != cs[CS_TAIL]:
            out.append(self.ring[cs[CS_TAIL]])
            cs[CS_TAIL] = (cs[CS_TAIL] + 1) & mask
        return out
