"""The jig samples an axis itself: GetAllStatus at a fixed period, on the jig's clock.

StartTrace (0xF5) names a driver and a period; from then on the jig sends that
driver a GetAllStatus (0x43) once per period through ``Bridge.request`` -- like the
bus scan and the safety stop, the reply comes back to this client and never reaches
the PC -- and keeps one 20-byte sample per answer in a ring::

    u32 t        jig tick (µs, 30-bit wrapping, as ticks_us) at which the jig began
                 sending the request (DE up); the drive reads its state one request
                 wire time later (plus its own processing time: a constant)
    i32 command  command position        } copied byte for byte from the reply:
    i32 actual   actual position         } no integer is built, nothing allocated
    i32 velocity actual velocity         }
    u32 flags    axis status flags       }

The station reads the ring in chunks with ReadTrace (0xF7), 12 samples a reply at
most (5 + 12 x 20 = 245 data bytes), each read naming the index it wants next
(what the last reply said): the samples before it are released, so a read repeated
after a lost reply returns the same samples. Layouts in ``jig.diag`` and
docs/diagnostics.md.

Interleaving with the PC (docs/bridge.md, "The jig's own sampler"):

* A slot waits while the PC's own request is on the driver bus or awaited (the PC
  goes first); a slot that falls due while the bridge is busy is taken the moment it
  is free (the bridge then asks for the slow pass: ``B_WAKE``). A slot taken later
  than one period after its time skips the slots in between (``skipped``); every
  sample carries the tick it was really taken at.
* While the sampler's request is out, a PC frame for the driver bus is *held* (not
  passed on cut through, not aborting the request, which would make the two collide
  on the driver bus) and sent whole the moment the sample's reply is in or its wait
  times out (``Bridge.request(..., hold=True)``).
* The ReadTrace reply is sent to the PC in 16-byte pieces (the USART's FIFO), and a
  slot that falls due meanwhile sends its request on the driver bus between two
  pieces: reading the trace while it runs does not stall the sampler for the
  reply's wire time (22 ms at 115 200 baud).

The drive is polled in its own variant: flags of StartTrace choose Ver6 or Ver8
framing, or the jig's protocol first and the other after an answer that is a bare
error (a frame-type error, as the safety stop does). Ver6 replies carry 32 data
bytes, Ver8 ones 36 (64-bit inputs) or 32; both are read by their length.

The ring (``RING`` samples, 80 KB) is allocated at the first StartTrace and kept:
nothing is allocated per sample or per read afterwards. A full ring keeps what it
has and counts the samples it cannot keep (``lost``).
"""

from array import array

from jig import frame, mem
from jig.bridge import B_T_PC, B_WAKE, SEEN_IDS
from jig.compat import const, ticks_add, ticks_diff
from jig.frame import put_u16, put_u32
from jig.params import P_DOWN_BAUD, P_SCAN_TIMEOUT_MS, P_SLAVE_ID
from jig.parser import HUNT, S_N, S_STATE

RING = const(4096)  # samples (a power of two: an index is a u16 sequence number)
_RING_MASK = const(4095)
SAMPLE = const(20)  # bytes per sample
CHUNK = const(12)  # samples per ReadTrace reply at most
PIECE = const(16)  # bytes of the ReadTrace reply written at a time (the USART's FIFO)
MIN_PERIOD_US = const(100)
MAX_PERIOD_US = const(1000000)
_SEQ_MASK = const(0xFFFF)
_RX_CHUNK = const(256)  # app.RX_CHUNK
_TICKS_MASK = const(0x3FFFFFFF)
_TICKS_HALF = const(0x20000000)

# StartTrace flags: the framing of the requests to the drive
FRAMING_DETECT = const(0)  # the jig's protocol, the other one after a bare error reply
FRAMING_VER6 = const(1)
FRAMING_VER8 = const(2)

OFF = const(0)
RUNNING = const(1)

# Trace.ts: the sampler's state, one integer array
T_ON = const(0)
T_SLAVE = const(1)
T_PERIOD = const(2)  # µs
T_NEXT = const(3)  # tick of the next slot
T_HEAD = const(4)  # sequence number of the next sample written (u16)
T_TAIL = const(5)  # sequence number of the oldest sample kept (u16)
T_TAKEN = const(6)  # samples stored
T_SKIPPED = const(7)  # slots passed over (the bus was busy past the next slot)
T_LOST = const(8)  # samples the full ring could not keep
T_FAILED = const(9)  # requests without a good GetAllStatus reply (timeout, error, aborted)
T_WAITING = const(10)  # 1: our request is out
T_FRAMING = const(11)  # FRAMING_*
T_VER8 = const(12)  # the framing of the next request: 1 Ver8, 0 Ver6
T_T_REQ = const(13)  # tick of the request out
T_TIMEOUT_MS = const(14)
T_STALE = const(15)  # 1: the request out belongs to a trace since restarted: its answer is not kept
T_SIZE = const(16)

_GET_ALL_STATUS = const(0x43)
_STATUS_OK = const(0)
_STATUS_DATA_ERROR = const(0x81)
_BROADCAST_ID = const(99)
# The longest GetAllStatus reply on the wire, stuffing aside: AA CC id sync 43 St 36 CRC AA EE
_REPLY_WIRE_BYTES = const(45)

STATUS_LEN = const(26)  # the status block: u8 state, u8 slave, 5 x u32, 2 x u16


class Trace:
    def __init__(self, app):
        self.app = app
        self.bridge = app.bridge
        self.ts = array("i", bytes(4 * T_SIZE))
        self.ring = None  # allocated at the first StartTrace
        self.empty = bytearray(1)
        # The ReadTrace reply's own body and wire buffers (a sample request sent between
        # its pieces uses the bridge's).
        self.rbody = bytearray(frame.MAX_BODY)
        self.rwire = bytearray(frame.MAX_WIRE)
        self._ticks = app.hal.ticks_us
        self.up_st = app.up_parser.st  # a PC frame arriving goes first
        self.byte_us = 10000000 // app.up_baud + 1

    # --- the frames (handlers.Handlers calls these) --------------------------------
    def start(self, p, d, o, out):
        """0xF5 StartTrace: u8 slave, u32 period µs, u8 flags -> St, u16 ring size, u32 tick."""
        app = self.app
        slave = d[o]
        period = frame.get_i32(d, o + 1)
        flags = d[o + 5]
        known = self.bridge.seen() | app.scanner.found
        out[0] = _STATUS_DATA_ERROR
        if (slave == app.params.ram[P_SLAVE_ID] or slave == _BROADCAST_ID or slave >= SEEN_IDS
                or not known & (1 << slave)):
            return 1  # not a driver the jig has seen answer
        if period < MIN_PERIOD_US or period > MAX_PERIOD_US or flags > FRAMING_VER8:
            return 1
        if self.ring is None:
            try:
                self.ring = bytearray(RING * SAMPLE)
            except MemoryError:
                return 1
        ts = self.ts
        now = self._ticks()
        ts[T_STALE] = ts[T_WAITING]
        ts[T_SLAVE] = slave
        ts[T_PERIOD] = period
        ts[T_NEXT] = now
        ts[T_HEAD] = 0
        ts[T_TAIL] = 0
        ts[T_TAKEN] = 0
        ts[T_SKIPPED] = 0
        ts[T_LOST] = 0
        ts[T_FAILED] = 0
        ts[T_FRAMING] = flags
        if flags == FRAMING_DETECT:
            ts[T_VER8] = 1 if self.bridge.ver8 else 0
        else:
            ts[T_VER8] = 1 if flags == FRAMING_VER8 else 0
        # the wait for a reply: the scan's, plus the longest reply's wire time
        ts[T_TIMEOUT_MS] = app.params.ram[P_SCAN_TIMEOUT_MS] + (_REPLY_WIRE_BYTES * 10000) // app.params.ram[P_DOWN_BAUD] + 1
        ts[T_ON] = RUNNING
        app.due[0] = now  # the first sample at the next pass
        out[0] = _STATUS_OK
        put_u16(out, 1, RING)
        put_u32(out, 3, now)
        return 7

    def stop(self, p, d, o, out):
        """0xF6 StopTrace: -> St, the status block (the samples stay readable)."""
        self.ts[T_ON] = OFF
        self.bridge.bs[B_WAKE] = 0  # (else every relay's end would still ask for a slow pass)
        return self.status(p, d, o, out)

    def status(self, p, d, o, out):
        """0xF8 GetTraceStatus: -> St, u8 state, u8 slave, u32 period, taken, skipped, lost,
        failed, u16 oldest index kept, u16 next index written."""
        ts = self.ts
        out[0] = _STATUS_OK
        out[1] = ts[T_ON]
        out[2] = ts[T_SLAVE]
        put_u32(out, 3, ts[T_PERIOD])
        put_u32(out, 7, ts[T_TAKEN])
        put_u32(out, 11, ts[T_SKIPPED])
        put_u32(out, 15, ts[T_LOST])
        put_u32(out, 19, ts[T_FAILED])
        put_u16(out, 23, ts[T_TAIL])
        put_u16(out, 25, ts[T_HEAD])
        return 1 + STATUS_LEN

    def read(self, p, d, o, out):
        """0xF7 ReadTrace: u16 from, u8 max n (0: as many as fit) -> St, u8 state, u16 next,
        u8 n, n x sample. Sent here, in pieces, with the sampler's slots kept between
        them; returns handlers.DEFERRED (-1): the reply has gone."""
        ts = self.ts
        frm = d[o] | (d[o + 1] << 8)
        want = d[o + 2]
        tail = ts[T_TAIL]
        held = (ts[T_HEAD] - tail) & _SEQ_MASK
        ahead = (frm - tail) & _SEQ_MASK
        if ahead > held or self.ring is None:
            out[0] = _STATUS_DATA_ERROR  # not a sample the ring holds or will hold next
            return 1
        ts[T_TAIL] = frm  # the samples before it are read: released
        n = held - ahead
        if want == 0 or want > CHUNK:
            want = CHUNK
        if n > want:
            n = want
        out[0] = _STATUS_OK
        out[1] = ts[T_ON]
        put_u16(out, 2, (frm + n) & _SEQ_MASK)
        out[4] = n
        ring = self.ring
        k = 5
        for i in range(n):
            mem.copy(out, k, ring, ((frm + i) & _RING_MASK) * SAMPLE, SAMPLE)
            k += SAMPLE
        return self.reply(p, o, out, k)

    def reply(self, p, o, out, k):
        """Send the jig's reply out[0:k] to request p (its type at body[o - 1]) in pieces,
        the sampler's slots kept between them (``between``); returns handlers.DEFERRED
        (-1): the reply has gone. ReadTrace's reply goes this way, and while the sampler
        runs or its request is out, every other long local reply (``Handlers._long``): one
        written whole (ReadTransactionTimes: 15 ms at 115 200 baud) left the driver bus
        unread meanwhile, and the rest of a sample's reply, read after it, looked like
        a silence longer than the inter-byte timeout to the parser: a good reply dropped
        (down_timeouts, down_noise), the sample unanswered and a gap of its timeout."""
        body = p.body
        sync = body[1] if o == 3 else -1
        b = self.bridge
        b.local_reply_paced(body[0], body[o - 1], sync, out, k, b.bs[B_T_PC], self.rbody, self.rwire, self)
        return -1

    # --- the sampler ---------------------------------------------------------------
    def between(self):
        """Called between the pieces of a reply to the PC: the driver bus's bytes are
        read (our sample's reply among them) and a slot due goes out now."""
        ts = self.ts
        if ts[T_WAITING]:
            # (also after a StopTrace: the reply still coming must be read as it comes)
            if self.bridge.held_n:
                return  # (its release would relay a reply onto the PC bus we are writing)
            app = self.app
            k = app._down_any()
            if k:
                k = app._down_read(app.down_rx, k if k < _RX_CHUNK else _RX_CHUNK)
                if k:
                    app._down_bytes(app.down_parser, app.down_rx, k, self._ticks())
            if ts[T_WAITING]:
                return
        if not ts[T_ON]:
            return
        now = self._ticks()
        if ticks_diff(now, ts[T_NEXT]) >= 0:
            self.poll(now)

    def poll(self, now):
        """Slow pass: send the request of a slot that is due, if the driver bus is free."""
        ts = self.ts
        if not ts[T_ON] or ts[T_WAITING]:
            return
        nxt = ts[T_NEXT]
        late = ticks_diff(now, nxt)
        if late < 0:
            return
        b = self.bridge
        if b.busy():
            b.bs[B_WAKE] = 1  # the bridge asks for the slow pass once it is free
            return
        b.bs[B_WAKE] = 0
        if self.up_st[S_STATE] != HUNT:
            return  # a PC frame is arriving: it goes first (wait_us looks again a byte later)
        per = ts[T_PERIOD]
        if late >= per:
            k = late // per
            ts[T_SKIPPED] += k
            nxt = ticks_add(nxt, k * per)
        ts[T_NEXT] = ticks_add(nxt, per)
        if b.request(self, ts[T_SLAVE], _GET_ALL_STATUS, self.empty, 0, ts[T_TIMEOUT_MS], ts[T_VER8], True):
            ts[T_WAITING] = 1
            ts[T_T_REQ] = b.down.t_tx_start

    def wait_us(self, now):
        """µs until the next slot (-1: not running, our request is out, or the slot is
        due and the bridge is busy: it wakes the slow pass when it is free)."""
        ts = self.ts
        if not ts[T_ON] or ts[T_WAITING]:
            return -1
        d = ticks_diff(ts[T_NEXT], now)
        if d > 0:
            return d
        if self.bridge.busy():
            return -1
        return self.byte_us if self.up_st[S_STATE] != HUNT else 0

    def _next_slot(self):
        """Our request is done: the slow pass must run by the next slot (the bridge does
        not ask for one after a reply to a request sent with ``hold``)."""
        t = self.ts[T_NEXT]
        due = self.app.due
        if (t - due[0]) & _TICKS_MASK >= _TICKS_HALF:  # t comes before due[0]
            due[0] = t

    def on_reply(self, p):
        ts = self.ts
        ts[T_WAITING] = 0
        self._next_slot()
        if not ts[T_ON] or ts[T_STALE]:
            ts[T_STALE] = 0
            return  # stopped or restarted meanwhile: StopTrace's figures are the final ones
        body = p.body
        n = p.st[S_N]
        h = 3 if ts[T_VER8] else 2  # id, [sync], type
        dl = n - h - 3  # data bytes after the status
        if (body[0] != ts[T_SLAVE] or body[h - 1] != _GET_ALL_STATUS or body[h] != _STATUS_OK
                or (dl != 32 and dl != 36)):
            ts[T_FAILED] += 1
            if ts[T_FRAMING] == FRAMING_DETECT and n <= 6:
                ts[T_VER8] ^= 1  # a bare error: a drive of the other variant
            return
        head = ts[T_HEAD]
        if ((head - ts[T_TAIL]) & _SEQ_MASK) >= RING:
            ts[T_LOST] += 1
            return
        ring = self.ring
        off = (head & _RING_MASK) * SAMPLE
        put_u32(ring, off, ts[T_T_REQ])
        base = h + 1 + dl - 28  # after the inputs (4 or 8 bytes): outputs, flags, cmd, act, err, vel, pt
        mem.copy(ring, off + 4, body, base + 8, 8)  # command, actual
        mem.copy(ring, off + 12, body, base + 20, 4)  # velocity
        mem.copy(ring, off + 16, body, base + 4, 4)  # flags
        ts[T_HEAD] = (head + 1) & _SEQ_MASK
        ts[T_TAKEN] += 1

    def on_timeout(self):
        ts = self.ts
        ts[T_WAITING] = 0
        self._next_slot()
        if ts[T_STALE]:
            ts[T_STALE] = 0
        elif ts[T_ON]:
            ts[T_FAILED] += 1

    on_abort = on_timeout
