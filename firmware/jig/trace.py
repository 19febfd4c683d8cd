"""The jig samples its drives itself: GetAllStatus at a fixed period, on the jig's clock.

The sampler polls a *set* of drivers in turn, one GetAllStatus (0x43) per period --
through ``Bridge.request``, like the bus scan and the safety stop: the reply comes
back to this client and never reaches the PC -- and keeps one 20-byte sample per
answer in a ring, tagged with its drive's id::

    u32 t        jig tick (µs, 30-bit wrapping, as ticks_us) at which the jig began
                 sending the request (DE up); the drive reads its state one request
                 wire time later (plus its own processing time: a constant)
    i32 command  command position        } copied byte for byte from the reply:
    i32 actual   actual position         } no integer is built, nothing allocated
    i32 velocity actual velocity         }
    u32 flags    axis status flags       }

The period is per request: with N drives in the set each is polled every N periods
(round robin in id order, the next one after the drive polled last). Two ways in:

* StartTrace (0xF5) with 6 data bytes, as before the set existed: the set is that
  one drive, the ring emptied, the figures 0 (a restart).
* StartTrace with a 7th byte, 1 (*join*): the drive joins the set while the others
  keep sampling (their samples, the ring and the grid of slots untouched); the
  sampler starts if it was off. StopTrace (0xF6) with one byte, the drive (*leave*):
  it leaves, the others go on; the last one leaving stops the sampler. StopTrace
  without data stops it all.

The station reads the ring in chunks with ReadTrace (0xF7), each read naming the
index it wants next (what the last reply said): the samples before it are released,
so a read repeated after a lost reply returns the same samples. Without its 4th byte
a chunk holds 12 untagged samples at most (5 + 12 x 20 = 245 data bytes), with it (1)
11 samples each after its drive's id (5 + 11 x 21 = 236). GetTraceStatus (0xF8) with
a drive's id gives that drive's figures since its join. Layouts in ``jig.diag`` and
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

Each drive is polled in its own variant: the framing its StartTrace named, Ver6 or
Ver8, or the jig's protocol first and the other after an answer that is a bare
error (a frame-type error, as the safety stop does). Ver6 replies carry 32 data
bytes, Ver8 ones 36 (64-bit inputs) or 32; both are read by their length.

The ring (``RING`` samples, 80 KB, and their ids, 4 KB) is allocated at the first
StartTrace and kept: nothing is allocated per sample or per read afterwards. A full
ring keeps what it has and counts the samples it cannot keep (``lost``, also per
drive).
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
CHUNK_TAGGED = const(11)  # samples per tagged ReadTrace reply at most (each after its drive's id)
PIECE = const(16)  # bytes of the ReadTrace reply written at a time (the USART's FIFO)
MIN_PERIOD_US = const(100)
MAX_PERIOD_US = const(1000000)
MAX_DRIVES = const(14)  # drives in the set at most
_SEQ_MASK = const(0xFFFF)
_RX_CHUNK = const(256)  # app.RX_CHUNK
_TICKS_MASK = const(0x3FFFFFFF)
_TICKS_HALF = const(0x20000000)

# StartTrace flags: the framing of the requests to the drive
FRAMING_DETECT = const(0)  # the jig's protocol, the other one after a bare error reply
FRAMING_VER6 = const(1)
FRAMING_VER8 = const(2)

OP_JOIN = const(1)  # StartTrace's 7th byte: the drive joins the set
FORMAT_TAGGED = const(1)  # ReadTrace's 4th byte: each sample after its drive's id

OFF = const(0)
RUNNING = const(1)

# Trace.ts: the sampler's state, one integer array
T_ON = const(0)
T_SLAVE = const(1)  # the drive polled last (its request may be out)
T_PERIOD = const(2)  # µs, per request
T_NEXT = const(3)  # tick of the next slot
T_HEAD = const(4)  # sequence number of the next sample written (u16)
T_TAIL = const(5)  # sequence number of the oldest sample kept (u16)
T_TAKEN = const(6)  # samples stored
T_SKIPPED = const(7)  # slots passed over (the bus was busy past the next slot)
T_LOST = const(8)  # samples the full ring could not keep
T_FAILED = const(9)  # requests without a good GetAllStatus reply (timeout, error, aborted)
T_WAITING = const(10)  # 1: our request is out
T_FRAMING = const(11)  # FRAMING_* of the request out
T_VER8 = const(12)  # the framing of the request out: 1 Ver8, 0 Ver6
T_T_REQ = const(13)  # tick of the request out
T_TIMEOUT_MS = const(14)
T_STALE = const(15)  # 1: the request out belongs to a trace since restarted: its answer is not kept
T_SET = const(16)  # bit k: drive k is in the set
T_COUNT = const(17)  # drives in the set
T_ONLY = const(18)  # the drive, when the set holds one (-1: several or none): no search per slot
T_SIZE = const(19)

_GET_ALL_STATUS = const(0x43)
_STATUS_OK = const(0)
_STATUS_DATA_ERROR = const(0x81)
_STATUS_FRAME_ERROR = const(0x82)
_BROADCAST_ID = const(99)
# The longest GetAllStatus reply on the wire, stuffing aside: AA CC id sync 43 St 36 CRC AA EE
_REPLY_WIRE_BYTES = const(45)

STATUS_LEN = const(26)  # the status block: u8 state, u8 slave, 5 x u32, 2 x u16
DRIVE_STATUS_LEN = const(30)  # a drive's: u8 state, u8 slave, u32 set, 5 x u32, 2 x u16
JOIN_REPLY_LEN = const(16)  # St, u16 ring, u32 tick, u8 started, u16 oldest, u16 next, u32 set


class Trace:
    def __init__(self, app):
        self.app = app
        self.bridge = app.bridge
        self.ts = array("i", bytes(4 * T_SIZE))
        self.ring = None  # allocated at the first StartTrace
        self.tags = None  # the drive of each sample in the ring (with it)
        # per drive id: the framing asked for, the framing of its next request (1 Ver8),
        # its figures since it joined (skipped: the sampler's count at its join while it
        # is in the set, its own count after it left)
        self.d_framing = bytearray(SEEN_IDS)
        self.d_ver8 = bytearray(SEEN_IDS)
        self.d_taken = array("i", bytes(4 * SEEN_IDS))
        self.d_lost = array("i", bytes(4 * SEEN_IDS))
        self.d_failed = array("i", bytes(4 * SEEN_IDS))
        self.d_skipped = array("i", bytes(4 * SEEN_IDS))
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
        """0xF5 StartTrace: u8 slave, u32 period µs, u8 flags -> St, u16 ring size, u32 tick
        (a restart with that drive alone); with a 7th byte 1 the drive joins the set ->
        St, u16 ring size, u32 tick, u8 started, u16 oldest index, u16 next index, u32 set."""
        n = p.st[S_N] - 2 - o  # data bytes
        if n != 6 and n != 7:
            out[0] = _STATUS_FRAME_ERROR
            return 1
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
        ts = self.ts
        join = n == 7
        if join and (d[o + 6] != OP_JOIN or (ts[T_ON] and not ts[T_SET] & (1 << slave)
                                              and ts[T_COUNT] >= MAX_DRIVES)):
            return 1
        if self.ring is None:
            try:
                self.ring = bytearray(RING * SAMPLE)
                self.tags = bytearray(RING)
            except MemoryError:
                self.ring = None
                return 1
        now = self._ticks()
        started = 0
        if not join or not ts[T_ON]:
            started = 1
            self._drop_all()  # (first: their figures stay as they were)
            ts[T_STALE] = ts[T_WAITING]
            ts[T_SLAVE] = slave
            ts[T_NEXT] = now
            ts[T_HEAD] = 0
            ts[T_TAIL] = 0
            ts[T_TAKEN] = 0
            ts[T_SKIPPED] = 0
            ts[T_LOST] = 0
            ts[T_FAILED] = 0
        ts[T_PERIOD] = period  # (a join's period is the sampler's from its next slot)
        # the wait for a reply: the scan's, plus the longest reply's wire time
        ts[T_TIMEOUT_MS] = app.params.ram[P_SCAN_TIMEOUT_MS] + (_REPLY_WIRE_BYTES * 10000) // app.params.ram[P_DOWN_BAUD] + 1
        self._join(slave, flags)
        if started:
            ts[T_ON] = RUNNING
            app.due[0] = now  # the first sample at the next pass
        out[0] = _STATUS_OK
        put_u16(out, 1, RING)
        put_u32(out, 3, now)
        if not join:
            return 7
        out[7] = started
        put_u16(out, 8, ts[T_TAIL])
        put_u16(out, 10, ts[T_HEAD])
        put_u32(out, 12, ts[T_SET])
        return JOIN_REPLY_LEN

    def _join(self, slave, flags):
        """The drive joins the set (again: its figures start over; nothing else changes)."""
        ts = self.ts
        bit = 1 << slave
        if not ts[T_SET] & bit:
            ts[T_SET] |= bit
            ts[T_COUNT] += 1
            self._only()
        self.d_framing[slave] = flags
        if flags == FRAMING_DETECT:
            self.d_ver8[slave] = 1 if self.bridge.ver8 else 0
        else:
            self.d_ver8[slave] = 1 if flags == FRAMING_VER8 else 0
        self.d_taken[slave] = 0
        self.d_lost[slave] = 0
        self.d_failed[slave] = 0
        self.d_skipped[slave] = ts[T_SKIPPED]

    def _leave(self, slave):
        """The drive leaves the set; its figures stay as they are until it joins again."""
        ts = self.ts
        bit = 1 << slave
        if ts[T_SET] & bit:
            ts[T_SET] &= ~bit
            ts[T_COUNT] -= 1
            self.d_skipped[slave] = ts[T_SKIPPED] - self.d_skipped[slave]
            self._only()

    def _only(self):
        ts = self.ts
        i = -1
        if ts[T_COUNT] == 1:
            i = 0
            while not ts[T_SET] & (1 << i):
                i += 1
        ts[T_ONLY] = i

    def _drop_all(self):
        for i in range(SEEN_IDS):
            self._leave(i)

    def stop(self, p, d, o, out):
        """0xF6 StopTrace: -> St, the status block (the samples stay readable). With one
        byte, a drive: it leaves the set (the last one stops the sampler) -> St, its
        status block."""
        n = p.st[S_N] - 2 - o
        if n == 0:
            self._drop_all()
            self._off()
            return self.status(p, d, o, out)
        if n != 1:
            out[0] = _STATUS_FRAME_ERROR
            return 1
        slave = d[o]
        if slave >= SEEN_IDS:
            out[0] = _STATUS_DATA_ERROR
            return 1
        self._leave(slave)  # (a repeated leave changes nothing: its figures again)
        if not self.ts[T_COUNT]:
            self._off()
        return self._drive_status(slave, out)

    def _off(self):
        self.ts[T_ON] = OFF
        self.bridge.bs[B_WAKE] = 0  # (else every relay's end would still ask for a slow pass)

    def status(self, p, d, o, out):
        """0xF8 GetTraceStatus: -> St, u8 state, u8 slave, u32 period, taken, skipped, lost,
        failed, u16 oldest index kept, u16 next index written. With one byte, a drive: ->
        St, u8 state, u8 slave, u32 set, u32 period, and that drive's figures since its
        join (taken, skipped, lost, failed), u16 oldest, u16 next."""
        n = p.st[S_N] - 2 - o
        if n == 1:
            if d[o] >= SEEN_IDS:
                out[0] = _STATUS_DATA_ERROR
                return 1
            return self._drive_status(d[o], out)
        if n != 0:
            out[0] = _STATUS_FRAME_ERROR
            return 1
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

    def _drive_status(self, slave, out):
        ts = self.ts
        skipped = self.d_skipped[slave]
        if ts[T_SET] & (1 << slave):
            skipped = ts[T_SKIPPED] - skipped
        out[0] = _STATUS_OK
        out[1] = ts[T_ON]
        out[2] = slave
        put_u32(out, 3, ts[T_SET])
        put_u32(out, 7, ts[T_PERIOD])
        put_u32(out, 11, self.d_taken[slave])
        put_u32(out, 15, skipped)
        put_u32(out, 19, self.d_lost[slave])
        put_u32(out, 23, self.d_failed[slave])
        put_u16(out, 27, ts[T_TAIL])
        put_u16(out, 29, ts[T_HEAD])
        return 1 + DRIVE_STATUS_LEN

    def read(self, p, d, o, out):
        """0xF7 ReadTrace: u16 from, u8 max n (0: as many as fit) [, u8 1: tagged] -> St, u8
        state, u16 next, u8 n, n x sample (tagged: n x (u8 drive, sample)). Sent here, in
        pieces, with the sampler's slots kept between them; returns handlers.DEFERRED
        (-1): the reply has gone."""
        nd = p.st[S_N] - 2 - o
        if nd != 3 and nd != 4:
            out[0] = _STATUS_FRAME_ERROR
            return 1
        ts = self.ts
        frm = d[o] | (d[o + 1] << 8)
        want = d[o + 2]
        tagged = nd == 4
        tail = ts[T_TAIL]
        held = (ts[T_HEAD] - tail) & _SEQ_MASK
        ahead = (frm - tail) & _SEQ_MASK
        if ahead > held or self.ring is None or (tagged and d[o + 3] != FORMAT_TAGGED):
            out[0] = _STATUS_DATA_ERROR  # not a sample the ring holds or will hold next
            return 1
        ts[T_TAIL] = frm  # the samples before it are read: released
        n = held - ahead
        most = CHUNK_TAGGED if tagged else CHUNK
        if want == 0 or want > most:
            want = most
        if n > want:
            n = want
        out[0] = _STATUS_OK
        out[1] = ts[T_ON]
        put_u16(out, 2, (frm + n) & _SEQ_MASK)
        out[4] = n
        ring = self.ring
        tags = self.tags
        k = 5
        for i in range(n):
            j = (frm + i) & _RING_MASK
            if tagged:
                out[k] = tags[j]
                k += 1
            mem.copy(out, k, ring, j * SAMPLE, SAMPLE)
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

    def _next_drive(self):
        """The drive of the next slot: the first in the set after the one polled last
        (-1: the set is empty)."""
        members = self.ts[T_SET]
        if not members:
            return -1
        i = self.ts[T_SLAVE] + 1
        rest = members >> i  # the members after it
        if not rest:
            i = 0  # (round again from the lowest)
            rest = members
        while not rest & 1:
            rest >>= 1
            i += 1
        return i

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
        slave = ts[T_ONLY]
        if slave < 0:
            slave = self._next_drive()
            if slave < 0:
                return
        ver8 = self.d_ver8[slave]
        ts[T_VER8] = ver8
        ts[T_FRAMING] = self.d_framing[slave]
        if b.request(self, slave, _GET_ALL_STATUS, self.empty, 0, ts[T_TIMEOUT_MS], ver8, True):
            ts[T_SLAVE] = slave
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
        slave = ts[T_SLAVE]
        if ts[T_STALE] or not ts[T_ON] or not ts[T_SET] & (1 << slave):
            ts[T_STALE] = 0
            return  # restarted, stopped, or its drive left meanwhile: not kept
        body = p.body
        n = p.st[S_N]
        h = 3 if ts[T_VER8] else 2  # id, [sync], type
        dl = n - h - 3  # data bytes after the status
        if (body[0] != slave or body[h - 1] != _GET_ALL_STATUS or body[h] != _STATUS_OK
                or (dl != 32 and dl != 36)):
            ts[T_FAILED] += 1
            self.d_failed[slave] += 1
            if ts[T_FRAMING] == FRAMING_DETECT and n <= 6:
                self.d_ver8[slave] ^= 1  # a bare error: a drive of the other variant
            return
        head = ts[T_HEAD]
        if ((head - ts[T_TAIL]) & _SEQ_MASK) >= RING:
            ts[T_LOST] += 1
            self.d_lost[slave] += 1
            return
        ring = self.ring
        j = head & _RING_MASK
        self.tags[j] = slave
        off = j * SAMPLE
        put_u32(ring, off, ts[T_T_REQ])
        base = h + 1 + dl - 28  # after the inputs (4 or 8 bytes): outputs, flags, cmd, act, err, vel, pt
        mem.copy(ring, off + 4, body, base + 8, 8)  # command, actual
        mem.copy(ring, off + 12, body, base + 20, 4)  # velocity
        mem.copy(ring, off + 16, body, base + 4, 4)  # flags
        ts[T_HEAD] = (head + 1) & _SEQ_MASK
        ts[T_TAKEN] += 1
        self.d_taken[slave] += 1

    def on_timeout(self):
        ts = self.ts
        ts[T_WAITING] = 0
        self._next_slot()
        slave = ts[T_SLAVE]
        if ts[T_STALE] or not ts[T_ON] or not ts[T_SET] & (1 << slave):
            ts[T_STALE] = 0
            return
        ts[T_FAILED] += 1
        self.d_failed[slave] += 1

    on_abort = on_timeout
