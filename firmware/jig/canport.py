"""The jig's CAN port: FDCAN1 as an SLCAN adapter on the third USB CDC port.

``CanPort(app)`` (``app.can``) owns the SLCAN session the host runs on ``hal.slcan``
(python-can's ``slcan`` interface, ``slcand``, CANable-style tools): ``Sn`` picks the
bitrate while closed, ``O`` / ``L`` open the controller (``hal.can_open``) normal or
listen-only, ``C`` closes it, ``t``/``T``/``r``/``R`` send a frame, ``F`` / ``V`` /
``N`` / ``Zn`` answer status, version, serial and switch the 4-digit ms timestamps.
CR is OK, BEL refused (a bad line, a command in the wrong state, a full queue).

Receive: the controller's hard IRQ handler (``_irq``) moves each frame with
``recv`` into a preallocated ring of ``RX_FRAMES`` frames (id, flags, DLC, tick, 8
data bytes each) -- nothing allocated; a frame the ring cannot hold is counted as
lost. The ring becomes ``t``/``T``/``r``/``R`` lines for the host, and every frame
goes to the recorder (``app.capture.can_frame``), in the port's own pass (``serve``).
The port's ``write`` never blocks: lines it does not take wait in the ring.

The port's own pass: while the port is open the main loop calls ``serve`` every
``CAN_POLL_US`` (its tick in ``app.due[1]``; the first frame into an empty ring
pulls it to now): the host's lines in, frames both ways -- at most
``IN_PER_SERVE`` bytes from the host and ``RX_PER_SERVE`` frames to it a pass, and
none of the slow pass's work; with nothing to do the main loop (or the pump) only
looks at its queues and calls one ``any()``, not ``serve``. On the board the host's
bytes cannot wake the loop (``USB_VCP.irq`` is a soft callback, which never runs
inside the machine-code pump), so this period is what a host line waits for at
most: less than a frame time at 1 Mbit/s (47-135 µs) -- while the bridge is idle.
The pass runs in the bridge's idle time: while a Plus-R transaction is in flight (a
reply awaited, a frame coming in or passed on) it waits, at most ``CAN_DEFER_US``
past its tick (``App.bridge_idle``); the ring and the USB port hold what comes
meanwhile. Open, the port's traffic is this pass's only. The slow pass (``poll``),
which may run inside a transaction, does the rest: the controller's state, the
SLCAN session's line timeout, the safety stop; closed, the host's commands wait
for it.

Send: frame lines go into a FIFO of ``TX_FRAMES``. ``machine.CAN``'s transmit
queue is a priority queue by id, so to keep the host's order at most one frame is
in the controller at a time; the TX IRQ sends the next (copied into a staging
buffer, passed as a preallocated memoryview of its length). A host that sends
faster than the bus is held off, not refused: its bytes are read only as the FIFO
has room for the frame lines they could hold, the rest wait in the USB port (see
``_read``; BEL only after ``STALL_US`` of a full FIFO with nothing sent).
Completed frames are counted and recorded in the port's pass, with the tick of
their TX interrupt (received frames: the tick the RX interrupt put them in the ring).

Bus-off is seen by ``state()`` in the slow pass and restarted after parameter 17
``can_bus_off_restart_ms`` (0: it stays off until the host closes and opens). The
CAN safety stop (parameter 18, ``jig.safety.CanSafety``) acts on silence from the
host while the port is open. Counters in ``counters.CAN_NAMES`` order (0xFA
ReadCanCounters).

While the port is closed and its host silent the slow pass costs one ``any()``
and the main loop nothing more; the main loop's hot path never sees the CAN port.
"""

from array import array

from jig import counters as K
from jig import params as P
from jig import slcan as S
from jig.compat import const, ticks_add, ticks_diff
from jig.mem import copy
from jig.safety import CanSafety

RX_FRAMES = const(256)  # the RX ring (a power of two): ~30 ms of a 1 Mbit/s bus full of 8-byte frames
TX_FRAMES = const(64)  # the host's frames waiting for the bus (a power of two)
STAGE = const(256)  # bytes of SLCAN lines / answers handed to the port per write
LINE_MAX = const(31)  # "T" + 8 id + 1 dlc + 16 data + 4 stamp + CR
LINE_MIN = const(6)  # the shortest frame line: "t" + 3 id + DLC + CR
IN_CHUNK = const(64)  # bytes read from the host per readinto
IN_PER_POLL = const(512)  # at most this many a slow pass
# The port's own pass does a bounded piece of work, so that an RS-485 frame arriving
# meanwhile waits for little more than one host line and a few frames: at most
IN_PER_SERVE = const(32)  # bytes from the host (a frame line and a bit: > 14 000 lines/s)
RX_PER_SERVE = const(4)  # and frames to the host a pass (40 000 frames/s: more than a CAN bus carries)
OUT_PER_POLL = const(2048)  # bytes of lines handed to the port a pass, at most
CAN_POLL_US = const(100)  # while open the port's own pass (serve) comes this often
# ... but not inside the bridge's work: while a Plus-R transaction is in flight (a reply
# awaited, a frame being received or passed on) the port's pass waits for the bridge's
# idle time, at most this long past its due tick (app.due[1]); then it runs anyway
CAN_DEFER_US = const(1000)
STALL_US = const(250000)  # a full TX FIFO that sent nothing this long: the host's frames are refused again
ANSWER_US = const(1000)  # closed with answers the port has not taken: the slow pass this often
WATCH_US = const(10000)  # the controller's state and error counters are read this often
_NOT_OFF = const(-1)  # CanPort.t_bus_off: not bus-off
_RECOVERING = const(-2)  # ... restarted, waiting to be back on the bus
STAMP_PERIOD_MS = const(60000)  # SLCAN timestamps count ms 0..59999

# SLCAN's version and serial answers ("V" + hardware + software version, "N" + 4 digits)
VERSION_LINE = b"V1013\r"
SERIAL_DEFAULT = b"NMJ01\r"

# Status flags byte of the F command (Lawicel)
F_RX_FULL = const(0x01)
F_TX_FULL = const(0x02)
F_WARNING = const(0x04)
F_OVERRUN = const(0x08)
F_PASSIVE = const(0x20)
F_BUS_ERROR = const(0x80)

# machine.CAN constants (class attributes there; these are their values in v1.28)
_IRQ_TX = const(1)
_IRQ_RX = const(2)
_IRQ_TX_FAILED = const(4)
_IRQ_STATE = const(8)
_FLAG_RTR = const(1)
_FLAG_EXT_ID = const(2)
_RECV_ERR_OVERRUN = const(2)
_STATE_STOPPED = const(0)
_STATE_WARNING = const(2)
_STATE_PASSIVE = const(3)
_STATE_BUS_OFF = const(4)

# Indices into CanPort.rs (the RX ring's state; the IRQ writes HEAD)
RS_HEAD = const(0)
RS_TAIL = const(1)
RS_STATE_EV = const(2)  # 1: the IRQ saw IRQ_STATE (the slow pass looks at the state)
# ... and CanPort.ts (the TX FIFO: the slow pass writes HEAD and REC, the IRQ DONE)
TS_HEAD = const(0)  # next free entry
TS_TAIL = const(1)  # next entry to hand to the controller
TS_DONE = const(2)  # next entry whose transmission has not ended
TS_REC = const(3)  # next ended entry not yet counted / recorded
TS_BUSY = const(4)  # 1: one entry is in the controller
TS_HOLD = const(5)  # 1: the IRQ sends nothing (bus-off)

# The counters the interrupts and the port's pass count, as local constants (a
# module's const() is not folded into another module: K.CC_RX is a lookup at run
# time); host_tests/test_canport.py checks they are counters.CC_*.
_CC_RX = const(0)
_CC_TX = const(1)
_CC_RX_LOST = const(2)
_CC_RX_OVERRUNS = const(3)
_CC_TX_FAILED = const(4)
_CC_LINES = const(17)

# slcan's reader events (S.EV_CMD would be a lookup at run time; the test checks them)
_EV_CMD = const(1)
_EV_BAD = const(2)

_RX_MASK = const(255)  # RX_FRAMES - 1
_TICKS_MASK = const(0x3FFFFFFF)  # (ticks_diff inline: the interrupt calls nothing it need not)
_TICKS_HALF = const(0x20000000)
_TX_MASK = const(63)  # TX_FRAMES - 1

CAN_COUNTER_NAMES = K.CAN_NAMES

_CR = const(13)
_BEL = const(7)
_HEX = b"0123456789ABCDEF"


class CanPort:
    def __init__(self, app):
        self.app = app
        hal = app.hal
        self.hal = hal
        self.port = getattr(hal, "slcan", None)
        self.params = app.params
        pr = app.params.ram
        self.bitrate = pr[P.P_CAN_BITRATE]  # the session's (Sn changes it while closed)
        self.is_open = 0
        self.listen = 0
        self.state = _STATE_STOPPED
        self.can = None
        self.stamps = 0  # Z1: 4-digit ms timestamps on the lines to the host
        self.due = app.due
        self._ticks = hal.ticks_us
        self.cv = array("i", bytes(4 * K.CAN_COUNT))
        self.flags = 0  # F's latched status bits (cleared when read)
        self.lines = 0  # good SLCAN lines since the port was opened
        self.t_host = 0  # tick of the last good line
        self.seen = bytearray(16)  # CANopen node ids heard on the bus (boot-up, heartbeat, SDO reply)
        self.reader = S.SlcanReader()
        self.base_err = [0] * len(S.ERR_NAMES)
        self.t_bus_off = _NOT_OFF  # tick the controller was found bus-off, or _NOT_OFF / _RECOVERING
        self.t_watch = 0  # tick of the last look at the controller's state
        self.base_hw = [0, 0, 0]  # the controller's warning/passive/bus-off entry counts last seen
        self.hw = [0] * 8  # get_counters' list
        # RX ring, filled by the IRQ
        self.rs = array("i", [0, 0, 0])
        self.rx_id = array("i", bytes(4 * RX_FRAMES))
        self.rx_tick = array("i", bytes(4 * RX_FRAMES))
        self.rx_fl = bytearray(RX_FRAMES)  # bit 0 extended, bit 1 remote (SLCAN's meaning)
        self.rx_dlc = bytearray(RX_FRAMES)
        self.rx_data = bytearray(8 * RX_FRAMES)
        self._rxl = [0, memoryview(bytearray(8)), 0, 0]
        # TX FIFO; entries are kept until counted (TS_REC) so the recorder gets their data
        self.ts = array("i", [0, 0, 0, 0, 0, 0])
        self.tx_id = array("i", bytes(4 * TX_FRAMES))
        self.tx_tick = array("i", bytes(4 * TX_FRAMES))
        self.tx_fl = bytearray(TX_FRAMES)
        self.tx_dlc = bytearray(TX_FRAMES)
        self.tx_ok = bytearray(TX_FRAMES)
        self.tx_data = bytearray(8 * TX_FRAMES)
        self.txb = bytearray(8)  # the frame being handed to the controller
        mv = memoryview(self.txb)
        self.txv = [mv[0:k] for k in range(9)]
        self.mflags = bytearray(4)  # SLCAN flags -> machine.CAN flags (set at open)
        self.frame = bytearray(8)  # one frame's data for the encoder and the recorder
        # the host side: input chunk, output stage with one view per length
        self.inb = bytearray(IN_CHUNK)
        mv = memoryview(self.inb)
        self.inv = [mv[0:k] for k in range(IN_CHUNK + 1)]
        self.out = bytearray(STAGE)
        self.out_n = 0
        mv = memoryview(self.out)
        self.outv = [mv[0:k] for k in range(STAGE + 1)]
        self.serial = self._serial_line(hal)
        # the ms clock of the timestamps: t_ms at tick t_ref
        self.t_ref = self._ticks()
        self.t_ms = 0
        self._irq_cb = self._irq  # bound once: the controller keeps it
        # The host's bytes wake the port's pass at once where the port can say so
        # (pyb.USB_VCP.irq: a soft callback, scheduled between bytecodes -- the main
        # loop's idle pass pays nothing for it, and it cannot run inside the pump);
        # else they wait for the next one (open: CAN_POLL_US; closed: the slow pass).
        irq = getattr(self.port, "irq", None)
        if irq is not None:
            try:
                irq(self._host_data)
            except (TypeError, ValueError, OSError):
                pass
        self._irqo = None
        cap = getattr(app, "capture", None)
        self.record = getattr(cap, "can_frame", None)  # (does nothing while not recording ...
        self.rec_on = getattr(cap, "cs", None) or bytearray(1)  # ... [0]: CS_ON, so it is called only while it does)
        self.lost_seen = 0  # rx lost + overruns at the last look (F's overrun bits)
        self.t_full = -1  # tick the TX FIFO was found full with the host's bytes waiting (-1: not full)
        self.safety = CanSafety(self, app.params, app.counters, getattr(app, "lease", None))

    def _host_data(self, _port):
        due = self.due
        t = self._ticks()
        if not self.is_open:
            due[0] = t  # (closed: commands are read by the slow pass)
        elif (due[1] - t) & _TICKS_MASK < _TICKS_HALF:
            due[1] = t  # (a pass already due keeps its tick: the bound on its wait counts from it)

    @staticmethod
    def _serial_line(hal):
        """"N" + 4 hex digits folded from the board's unique id, or NMJ01."""
        fn = getattr(hal, "unique_id", None)
        uid = None
        if fn is not None:
            try:
                uid = fn()
            except Exception:
                uid = None
        if not uid:
            return SERIAL_DEFAULT
        v = 0
        for b in uid:
            v = ((v << 5) ^ (v >> 11) ^ b) & 0xFFFF
        out = bytearray(b"N0000\r")
        for i in range(4):
            out[4 - i] = _HEX[(v >> (4 * i)) & 15]
        return bytes(out)

    # --- the controller's interrupt (hard: nothing allocated) ----------------------------
    def _irq(self, can):
        irqo = self._irqo
        if irqo is None:
            irqo = can.irq()
        while True:
            f = irqo.flags()
            if not f:
                return
            if f & _IRQ_RX:
                self._rx(can)
            if f & _IRQ_TX and self.ts[TS_BUSY]:
                self._tx_end(f)
            if f & _IRQ_STATE:
                self.rs[RS_STATE_EV] = 1
                self.due[0] = self._ticks()

    def _rx(self, can):
        lst = self._rxl
        rs = self.rs
        cv = self.cv
        data = self.rx_data
        ticks = self._ticks  # (a bound method made once: can.recv here would allocate one)
        while can.recv(lst) is not None:
            cv[_CC_RX] += 1
            if lst[3] & _RECV_ERR_OVERRUN:
                cv[_CC_RX_OVERRUNS] += 1
            head = rs[RS_HEAD]
            nxt = (head + 1) & _RX_MASK
            tail = rs[RS_TAIL]
            if nxt == tail:
                cv[_CC_RX_LOST] += 1
                continue
            self.rx_id[head] = lst[0]
            fl = lst[2]
            self.rx_fl[head] = (1 if fl & _FLAG_EXT_ID else 0) | (2 if fl & _FLAG_RTR else 0)
            mv = lst[1]
            n = len(mv)
            self.rx_dlc[head] = n
            copy(data, head << 3, mv, 0, n)
            t = ticks()
            self.rx_tick[head] = t
            rs[RS_HEAD] = nxt
            if head == tail:
                due = self.due
                if (due[1] - t) & _TICKS_MASK < _TICKS_HALF:
                    due[1] = t  # the port's own pass next (one already due, deferred, keeps its tick)

    def _tx_end(self, f):
        ts = self.ts
        if not ts[TS_BUSY]:
            return
        k = ts[TS_DONE]
        self.tx_ok[k] = 0 if f & _IRQ_TX_FAILED else 1
        self.tx_tick[k] = self._ticks()
        ts[TS_DONE] = (k + 1) & _TX_MASK
        ts[TS_BUSY] = 0
        if ts[TS_TAIL] != ts[TS_HEAD] and not ts[TS_HOLD]:
            self._send_next()

    def _send_next(self):
        """Hand the FIFO's next frame to the controller (only while none is in it)."""
        ts = self.ts
        k = ts[TS_TAIL]
        n = self.tx_dlc[k]
        copy(self.txb, 0, self.tx_data, k << 3, n)
        ts[TS_TAIL] = (k + 1) & _TX_MASK
        ts[TS_BUSY] = 1
        r = -1
        try:
            r = self.can.send(self.tx_id[k], self.txv[n], self.mflags[self.tx_fl[k]])
        except Exception:  # OSError: bus-off or stopped; the frame is lost
            self.tx_ok[k] = 0
            ts[TS_DONE] = (k + 1) & _TX_MASK
            ts[TS_BUSY] = 0
            return
        if r is None:  # the controller's queue is full: again later
            ts[TS_TAIL] = k
            ts[TS_BUSY] = 0

    # --- the slow pass -----------------------------------------------------------------
    def wait_us(self, now):
        """µs until the port needs the slow pass again (-1: no need of its own). Open,
        the port's traffic is its own pass's (``serve``); the slow pass only for the
        safety stop (and its usual period: the controller's state)."""
        if not self.is_open:
            return ANSWER_US if self.out_n else -1  # (answers the port has not taken yet)
        return self.safety.wait_us(now)

    def serve(self, now):
        """The port's own pass while open (``app.due[1]``): the controller's finished
        frames counted, the host's lines in, the ring's frames out (a bounded piece of
        each; the rest in the next pass); nothing more. The main loop calls it only
        when one of them has something waiting."""
        ts = self.ts
        if ts[TS_REC] != ts[TS_DONE]:
            self._tx_count()  # (first: the entries it frees are room for the host's frames)
        if self.out_n:
            self._flush()
        if self.port.any():
            self._read(now, IN_PER_SERVE)
        rs = self.rs
        if rs[RS_TAIL] != rs[RS_HEAD]:
            self._rx_out(RX_PER_SERVE)
        if not ts[TS_BUSY] and ts[TS_TAIL] != ts[TS_HEAD]:
            self._kick()  # (the controller's queue was full)
        if self.out_n:
            self._flush()

    def pending(self):
        """True if ``serve`` has something to do now (a simulation skips its idle passes)."""
        if self.out_n:
            return True
        port = self.port
        if port is not None and port.any():
            return True
        rs = self.rs
        ts = self.ts
        return rs[RS_TAIL] != rs[RS_HEAD] or ts[TS_REC] != ts[TS_DONE] or (
            not ts[TS_BUSY] and not ts[TS_HOLD] and ts[TS_TAIL] != ts[TS_HEAD])

    def poll(self, now):
        """The slow pass's part. Closed: read and answer the host. Open: the timestamps'
        clock, the controller's state, the host's line timeout, the safety stop; the
        traffic (the host's lines, the ring, the FIFO) is the port's own pass's
        (``serve``), which waits for the bridge's idle time -- the slow pass may run
        inside a Plus-R transaction (while the drive thinks), where it must not."""
        port = self.port
        if port is None:
            return
        if not self.is_open:
            if not self.out_n and not port.any():
                return  # closed and idle: one any() a slow pass
            self._clock(now)
            self._flush()
            if self.reader.gap(now) and self.out_n < STAGE:
                self._put(_BEL)  # a partial line that never got its CR
            self._read(now)
            self._flush()
            return
        self._clock(now)
        self._watch(now)
        if self.reader.gap(now) and self.out_n < STAGE:
            self._put(_BEL)  # (serve hands it to the port: App._slow shows it in due[3])
        self.safety.poll(now)

    def _clock(self, now):
        d = ticks_diff(now, self.t_ref)
        if d >= 1000:
            self.t_ms = (self.t_ms + d // 1000) % STAMP_PERIOD_MS
            self.t_ref = ticks_add(self.t_ref, d - d % 1000)

    def _watch(self, now):
        """The controller's state and error counters (every WATCH_US, and at once after
        an IRQ_STATE); bus-off recovery."""
        rs = self.rs
        if not rs[RS_STATE_EV] and ticks_diff(now, self.t_watch) < WATCH_US:
            return
        rs[RS_STATE_EV] = 0
        self.t_watch = now
        can = self.can
        st = can.state()
        self.state = st
        hw = can.get_counters(self.hw)
        cv = self.cv
        base = self.base_hw
        for i in range(3):  # warning, passive, bus-off entries (restart() zeroes them)
            x = hw[2 + i]
            if x is None:
                continue
            if x < base[i]:
                base[i] = 0
            cv[K.CC_WARNINGS + i] += x - base[i]
            base[i] = x
        if st >= _STATE_WARNING:
            self.flags |= F_WARNING
        if st >= _STATE_PASSIVE:
            self.flags |= F_PASSIVE
        if st != _STATE_BUS_OFF:
            if self.t_bus_off != _NOT_OFF:  # back on the bus (after a restart's recovery)
                self.t_bus_off = _NOT_OFF
                self.ts[TS_HOLD] = 0
                self.t_full = -1
            return
        self.flags |= F_BUS_ERROR
        if self.t_bus_off == _RECOVERING:
            return  # restarted: the controller waits for 128 x 11 recessive bits
        if self.t_bus_off == _NOT_OFF:
            self.t_bus_off = now
            self.ts[TS_HOLD] = 1
        ms = self.params.ram[P.P_CAN_BUS_OFF_RESTART_MS]
        if ms and ticks_diff(now, self.t_bus_off) >= ms * 1000:
            can.restart()
            cv[K.CC_RESTARTS] += 1
            for i in range(3):
                base[i] = 0
            self._cancel_in_flight()
            self.t_bus_off = _RECOVERING

    def _cancel_in_flight(self):
        """After restart()/deinit: the frame in the controller is gone, with no IRQ."""
        ts = self.ts
        if ts[TS_BUSY]:
            k = ts[TS_DONE]
            self.tx_ok[k] = 0
            ts[TS_DONE] = (k + 1) & _TX_MASK
            ts[TS_BUSY] = 0

    def _kick(self):
        ts = self.ts
        if not ts[TS_BUSY] and not ts[TS_HOLD] and ts[TS_TAIL] != ts[TS_HEAD]:
            self._send_next()

    def _tx_count(self):
        """Count (and record) the frames whose transmission has ended."""
        ts = self.ts
        cv = self.cv
        record = self.record if self.rec_on[0] else None
        tx_ok = self.tx_ok
        k = ts[TS_REC]
        done = ts[TS_DONE]
        while k != done:
            if tx_ok[k]:
                cv[_CC_TX] += 1
                if record is not None:
                    copy(self.frame, 0, self.tx_data, k << 3, 8)
                    record(self.tx_tick[k], self.tx_id[k], self.tx_fl[k], self.tx_dlc[k], self.frame, 1)
            else:
                cv[_CC_TX_FAILED] += 1
            k = (k + 1) & _TX_MASK
            ts[TS_REC] = k
            done = ts[TS_DONE]  # (the TX interrupt may have ended another)

    def queue_frame(self, can_id, ext, rtr, data, dlc):
        """Put one frame into the TX FIFO (data[0:dlc]); False if it is full."""
        ts = self.ts
        h = ts[TS_HEAD]
        nxt = (h + 1) & _TX_MASK
        if nxt == ts[TS_REC]:
            return False
        self.tx_id[h] = can_id
        self.tx_fl[h] = ext | (rtr << 1)
        self.tx_dlc[h] = dlc
        copy(self.tx_data, h << 3, data, 0, dlc)
        ts[TS_HEAD] = nxt
        if not ts[TS_BUSY] and not ts[TS_HOLD]:  # (_kick, inline)
            self._send_next()
        return True

    # --- the host's side ---------------------------------------------------------------
    def _flush(self):
        """Hand the stage to the port as far as it takes it now."""
        n = self.out_n
        if not n:
            return
        w = self.port.write(self.outv[n])
        if not w:
            return
        if w < n:
            copy(self.out, 0, self.out, w, n - w)
        self.out_n = n - w

    def _put(self, b):
        self.out[self.out_n] = b
        self.out_n += 1

    def _put_line(self, s):
        o = self.out_n
        for i in range(len(s)):
            self.out[o + i] = s[i]
        self.out_n = o + len(s)

    def _read(self, now, most=IN_PER_POLL):
        """Read the host's lines and act on them; an answer for each line must fit the
        stage (at most 3 bytes of answer a byte of input: "V" CR -> "V1013" CR).

        Push back: while frames can be queued, no more bytes are read than could
        complete a frame line for each free TX FIFO entry (LINE_MIN bytes an entry:
        a partial line needs at least one more byte, every other line all of its
        own). The rest wait in the USB port, which holds the host off when its
        buffer is full (the stm32 CDC stops acknowledging OUT packets): a host that
        sends faster than the bus waits instead of losing frames to BEL. Only a
        FIFO that has been full for STALL_US with nothing sent (no other node
        acknowledges) lets the host's frames be refused again, so that its later
        commands (C) still get through."""
        port = self.port
        r = self.reader
        ts = self.ts
        buf = self.inb
        inv = self.inv
        frames = self.is_open and not self.listen
        got = 0
        while got < most:
            k = (STAGE - self.out_n) // 3
            if k > IN_CHUNK:
                k = IN_CHUNK
            if k > most - got:
                k = most - got
            if frames and not ts[TS_HOLD]:
                room = ((ts[TS_REC] - ts[TS_HEAD] - 1) & _TX_MASK) * LINE_MIN
                if room:
                    self.t_full = -1
                    if room < k:
                        k = room
                elif port.any():
                    self.flags |= F_TX_FULL
                    if self.t_full < 0:
                        self.t_full = now
                        return
                    if ticks_diff(now, self.t_full) < STALL_US:
                        return
            if k <= 0 or not port.any():
                return
            n = port.readinto(inv[k])
            if not n:
                return
            got += n
            i = 0
            while i < n:
                i = r.feed(buf, i, n, now)
                ev = r.ev
                if ev == _EV_CMD:
                    c = r.cmd
                    if (c == 0x74 or c == 0x54) and frames:  # t T on an open port: the frame path, inline
                        self._frame_line(r, now)
                    else:
                        self._command(r, now)
                        frames = self.is_open and not self.listen  # (it may have opened or closed the port)
                elif ev == _EV_BAD:
                    self._put(_BEL)

    def _frame_line(self, r, now):
        """A t/T line on an open port (not listen-only): ``_command``'s frame case
        without its dispatch (the line the host sends most)."""
        cv = self.cv
        cv[_CC_LINES] += 1
        o = self.out_n
        if self.ts[TS_HOLD]:
            self.out[o] = _BEL
        elif self.queue_frame(r.can_id, r.ext, 0, r.data, r.dlc):
            self.out[o] = _CR
        else:
            cv[K.CC_TX_REFUSED] += 1
            self.flags |= F_TX_FULL
            self.out[o] = _BEL
        self.out_n = o + 1
        self.lines += 1
        self.t_host = now

    def _command(self, r, now):
        c = r.cmd
        self.cv[_CC_LINES] += 1
        if c == 0x74 or c == 0x54 or c == 0x72 or c == 0x52:  # t T r R
            if not self.is_open or self.listen or self.ts[TS_HOLD]:
                self._put(_BEL)
            elif self.queue_frame(r.can_id, r.ext, r.rtr, r.data, r.dlc):
                self._put(_CR)
            else:
                self.cv[K.CC_TX_REFUSED] += 1
                self.flags |= F_TX_FULL
                self._put(_BEL)
        elif c == 0x4F or c == 0x4C:  # O L
            if self.is_open or not self.open(1 if c == 0x4C else self.params.ram[P.P_CAN_LISTEN_ONLY]):
                self._put(_BEL)
            else:
                self._put(_CR)
        elif c == 0x43:  # C
            if self.is_open:
                self.close()
                self._put(_CR)
            else:
                self._put(_BEL)
        elif c == 0x53:  # S
            if self.is_open or r.arg < 0 or r.arg >= len(S.SLCAN_BITRATES):
                self._put(_BEL)
            else:
                b = S.SLCAN_BITRATES[r.arg]
                if b != self.bitrate:
                    self.bitrate = b
                    cap = getattr(self.app, "capture", None)
                    if cap is not None:
                        cap.hello(now)  # the recording's hello carries the CAN bitrate
                self._put(_CR)
        elif c == 0x46:  # F
            self._status_line()
        elif c == 0x56:  # V
            self._put_line(VERSION_LINE)
        elif c == 0x4E:  # N
            self._put_line(self.serial)
        elif c == 0x5A:  # Z
            if r.arg == 0 or r.arg == 1:
                self.stamps = r.arg
                self._put(_CR)
            else:
                self._put(_BEL)
        else:  # s (BTR registers) and anything else the jig does not do
            self._put(_BEL)
        self.lines += 1  # (after an O: it counts for the safety stop's silence)
        self.t_host = now

    def _status_line(self):
        f = self.flags
        if self.is_open:
            st = self.state
            if st >= _STATE_WARNING:
                f |= F_WARNING
            if st >= _STATE_PASSIVE:
                f |= F_PASSIVE
            if st == _STATE_BUS_OFF:
                f |= F_BUS_ERROR
            ts = self.ts
            if ((ts[TS_HEAD] + 1) & _TX_MASK) == ts[TS_REC]:
                f |= F_TX_FULL
        self.flags = 0
        self._put(0x46)
        self._put(_HEX[f >> 4])
        self._put(_HEX[f & 15])
        self._put(_CR)

    def _rx_out(self, most=RX_FRAMES):
        """Frames from the ring to the host (and the recorder), as the port takes them;
        at most ``most`` of them."""
        rs = self.rs
        cv = self.cv
        record = self.record if self.rec_on[0] else None
        frame = self.frame
        lost = cv[_CC_RX_LOST] + cv[_CC_RX_OVERRUNS]
        if lost != self.lost_seen:
            self.lost_seen = lost
            self.flags |= F_RX_FULL | F_OVERRUN
        rx_id = self.rx_id
        rx_fl = self.rx_fl
        rx_dlc = self.rx_dlc
        rx_data = self.rx_data
        out = self.out
        seen = self.seen
        encode = S.encode_frame
        stamps = self.stamps
        sent = 0
        o = self.out_n
        k = rs[RS_TAIL]
        while k != rs[RS_HEAD] and most > 0:
            most -= 1
            if STAGE - o < LINE_MAX:
                self.out_n = o
                self._flush()
                sent += o - self.out_n
                o = self.out_n
                if STAGE - o < LINE_MAX or sent >= OUT_PER_POLL:
                    return
            can_id = rx_id[k]
            fl = rx_fl[k]
            dlc = rx_dlc[k]
            copy(frame, 0, rx_data, k << 3, dlc)
            if fl == 0 and 0x581 <= can_id <= 0x77F:  # (_note_node, inline)
                if can_id >= 0x701:
                    n = can_id - 0x700
                    seen[n >> 3] |= 1 << (n & 7)
                elif can_id <= 0x5FF:
                    n = can_id - 0x580
                    seen[n >> 3] |= 1 << (n & 7)
            stamp = -1
            if record is not None or stamps:
                t = self.rx_tick[k]
                if record is not None:
                    record(t, can_id, fl, dlc, frame, 0)
                if stamps:
                    stamp = (self.t_ms + ticks_diff(t, self.t_ref) // 1000) % STAMP_PERIOD_MS
            o = encode(out, o, can_id, fl & 1, fl >> 1, frame, dlc, stamp)
            k = (k + 1) & _RX_MASK
            rs[RS_TAIL] = k
            self.out_n = o

    def _note_node(self, can_id):
        """A CANopen node's boot-up/heartbeat (0x701..0x77F) or SDO reply (0x581..0x5FF)."""
        if 0x701 <= can_id <= 0x77F:
            n = can_id - 0x700
        elif 0x581 <= can_id <= 0x5FF:
            n = can_id - 0x580
        else:
            return
        self.seen[n >> 3] |= 1 << (n & 7)

    # --- open / close ------------------------------------------------------------------
    def open(self, listen_only):
        """Open the controller at the session's bitrate; False if the HAL cannot."""
        fn = getattr(self.hal, "can_open", None)
        if fn is None:
            return False
        can = fn(self.bitrate, 1 if listen_only else 0)
        if can is None:
            return False
        rs = self.rs
        rs[RS_HEAD] = rs[RS_TAIL] = 0
        ts = self.ts
        for i in range(6):
            ts[i] = 0
        m = self.mflags
        m[0] = 0
        m[1] = can.FLAG_EXT_ID
        m[2] = can.FLAG_RTR
        m[3] = can.FLAG_EXT_ID | can.FLAG_RTR
        for i in range(3):
            self.base_hw[i] = 0
        self.t_bus_off = _NOT_OFF
        self.t_full = -1
        self.can = can
        self.listen = 1 if listen_only else 0
        self.lines = 0
        self.is_open = 1
        self.state = can.state()
        self.rs[RS_STATE_EV] = 1
        self.due[1] = self._ticks()  # the port's own passes from now on
        self.due[2] = 1  # (the main loop and the pump watch due[1] while it is set)
        self._irqo = None
        self._irqo = can.irq(self._irq_cb, trigger=can.IRQ_RX | can.IRQ_TX | can.IRQ_STATE, hard=True)
        self.safety.reset()
        return True

    def tx_idle(self):
        """True when every frame queued has ended its transmission."""
        return self.ts[TS_DONE] == self.ts[TS_HEAD]

    def end_session(self):
        """The safety stop ends a dead host's session: closed, and the lines it had not been
        given are dropped too (the next host gets nothing from before it)."""
        self.close()
        self.out_n = 0

    def close(self):
        """Close the controller; what the ring and the FIFO held is dropped."""
        can = self.can
        self.is_open = 0
        self.due[2] = 0  # no pass of its own
        self.state = _STATE_STOPPED
        if can is not None:
            self._tx_count()
            fn = getattr(self.hal, "can_close", None)
            if fn is not None:
                fn(can)
            else:
                can.deinit()
        self.can = None
        self._irqo = None
        self.rs[RS_HEAD] = self.rs[RS_TAIL] = 0
        ts = self.ts
        for i in range(6):
            ts[i] = 0
        self.t_bus_off = _NOT_OFF
        self.safety.reset()

    # --- counters ----------------------------------------------------------------------
    def counter_values(self, out):
        """The CAN counters in counters.CAN_NAMES order into out (a list); returns out."""
        cv = self.cv
        cv[K.CC_STATE] = self.state
        cv[K.CC_OPEN] = self.is_open
        cv[K.CC_LISTEN] = self.listen
        cv[K.CC_BITRATE] = self.bitrate
        cv[K.CC_TEC] = cv[K.CC_REC] = 0
        if self.is_open:
            hw = self.can.get_counters(self.hw)
            cv[K.CC_TEC] = hw[0] or 0
            cv[K.CC_REC] = hw[1] or 0
        for i in range(K.CAN_COUNT):
            out[i] = cv[i]
        counts = self.reader.counts
        base = self.base_err
        for i in range(len(base)):
            out[K.CAN_COUNT + i] = counts[i] - base[i]
        return out

    def reset_counters(self):
        cv = self.cv
        for i in range(K.CAN_COUNT):
            cv[i] = 0
        self.lost_seen = 0
        counts = self.reader.counts
        for i in range(len(self.base_err)):
            self.base_err[i] = counts[i]
