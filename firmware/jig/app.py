"""Wires the jig together and runs its main loop, on any HAL.

``App(hal)`` builds the two RS-485 ports, their parsers, the bridge, the local
handlers, the bus scanner, the safety stop and the CAN port (``jig.canport``,
where the HAL has one) from the parameter table, and
``poll()`` does one pass of the main loop: bytes waiting on the driver bus, then on
the PC bus, go through their parser into the bridge (which acts on every event:
a routing decision, a complete frame, a dropped one). Everything with a time in
it -- the inter-byte and reply timeouts, the scan, the safety stop, the watchdog,
the heartbeat -- runs in the *slow pass*, only when the tick reaches ``due[0]``:
the earliest time any of them needs attention (at least every ``SLOW_US``; the
bridge moves it earlier for a reply deadline and for the inter-byte timeout of a
frame it is cutting through). An idle pass is two ``any()`` calls, a tick and a
compare. ``run()`` loops forever (the board's main.py calls it). On the board, cut
through, the passes themselves run as machine code in ``jig.fastpath.pump``
(docs/bridge.md, "The machine-code hot path"); elsewhere in the portable loop here.

While the CAN port is open (``due[2]`` = 1) it has a pass of its own at the tick
``due[1]``, every ``canport.CAN_POLL_US``: nothing of the slow pass's work, so the
host's frames reach the bus within a fraction of a frame time without the slow
pass's cost. It runs in the bridge's idle time (``bridge_idle``): while a Plus-R
transaction is in flight it waits, at most ``canport.CAN_DEFER_US`` past its tick. The loop (and the pump, which returns for ``due[1]`` as for
``due[0]``) looks at the port's queues itself -- array compares and one ``any()``,
no call -- and calls ``CanPort.serve`` (the host's SLCAN lines in, frames both
ways) only when one of them has something in it.

The HAL (docs/hal.md; implemented by ``jig.board`` and by the virtual bench)::

    hal.ticks_us() -> int           wrapping µs ticks (time.ticks_us semantics)
    hal.sleep_us(us)                short blocking wait (DE delays)
    hal.up, hal.down                the PC-bus and driver-bus ports, each:
        .baud                       int, 8N1
        .any() -> int               received bytes waiting
        .readinto(buf, n) -> int    move up to n bytes into buf[0:], non-blocking
        .overflows                  RX overruns detected (bytes lost, buffer full)
        .write(buf, off, n)         send buf[off:off+n]; returns after the last stop bit
        .queue(buf, off, n)         optional: queue for the transmitter, return at once
        .drain()                    with queue: return after the last stop bit queued
        .tx_blocks                  True if write returns after transmit-complete
        .de(v)                      DE pin (1 = drive the bus); /RE tied to it or .re(v)
        .hw_de(on, pre16, post16)   USART hardware DE on/off -> True if supported
    hal.set_outputs(mask) / hal.get_outputs() / hal.get_inputs()   jig I/O, bits 0..15
    hal.heartbeat(on)               heartbeat LED
    hal.wdt_feed()                  watchdog
    hal.fs                          .read_into(path, buf) .write(path, buf, n)
                                    .rename(src, dst) .remove(path)
    hal.param_path                  parameter file path
    hal.can_open(bitrate, listen_only) -> machine.CAN-like object or None   optional:
    hal.can_close(can)              the CAN port (FDCAN1); hal.slcan its SLCAN CDC port

Ports are opened by the HAL at the baud rates the app asks for: the app calls
``hal.open(up_baud, down_baud)`` once after loading the parameters (baud rates
take effect at restart).
"""

from array import array

from jig import counters as K
from jig import parser as _parser
from jig import params as P
from jig.bridge import ARM_BYTES, Bridge, arm_overdue
from jig.canport import CAN_DEFER_US, CAN_POLL_US, CanPort
from jig.capture import QUIET_US, Capture
from jig.compat import NATIVE, const, ticks_add, ticks_diff
from jig.frame import MAX_BODY
from jig.handlers import Handlers
from jig.rs485 import Rs485
from jig.safety import SafetyLease, SafetyStop
from jig.scan import Scanner
from jig.trace import Trace

RX_CHUNK = const(256)
HEARTBEAT_US = const(500000)
SLOW_US = const(10000)  # the slow pass runs at least this often
CAN_IDLE_PARK = const(1000000)  # wait_us: an idle CAN port's next pass parked this far on (a multiple of CAN_POLL_US)
TICKS_MASK = const(0x3FFFFFFF)
TICKS_HALF = const(0x20000000)
# jig.canport's ring and FIFO indices (its consts are not folded here): CanPort.rs ...
_RS_HEAD = const(0)
_RS_TAIL = const(1)
# ... and CanPort.ts
_TS_HEAD = const(0)
_TS_TAIL = const(1)
_TS_DONE = const(2)
_TS_REC = const(3)
_TS_BUSY = const(4)
# jig.bridge's state array (Bridge.bs)
_B_STATE = const(0)
_B_FWD = const(1)
_B_REL = const(3)
PARSER_COUNTERS = len(_parser.COUNTER_NAMES)  # per parser, in counter_values


def _fastpath_module(use):
    """jig.fastpath where it runs as machine code (a port with a native emitter);
    ``use=True`` loads its source as plain Python elsewhere (CPython: the host tests'
    parity runs), ``use=False`` never."""
    if use is False:
        return None
    if NATIVE is None and not use:
        return None  # (the WebAssembly VM cannot even compile it)
    from jig import fastpath

    return fastpath


class App:
    def __init__(self, hal, fastpath=None):
        """``fastpath``: None runs the cut-through hot path as machine code where it
        can (``jig.fastpath``), True also elsewhere (its source as Python), False
        never (the portable loop)."""
        self.hal = hal
        self.counters = K.Counters()
        self.params = P.Params(getattr(hal, "fs", None), getattr(hal, "param_path", None))
        if not self.params.load():
            self.counters.v[K.C_PARAM_ERRORS] += 1
        pr = self.params.ram
        hal.open(pr[P.P_UP_BAUD], pr[P.P_DOWN_BAUD])
        ver8 = pr[P.P_PROTOCOL] == 1
        cut = pr[P.P_FORWARD_MODE] == P.CUT_THROUGH
        # Hardware DE drops whenever the USART's transmitter runs empty, which cut
        # through happens between the pieces of a frame: there it is software DE.
        hw = pr[P.P_DE_MODE] == 1 and not cut
        self.up = Rs485(hal, hal.up, pr[P.P_DE_PRE_US], pr[P.P_DE_POST_US], hw)
        self.down = Rs485(hal, hal.down, pr[P.P_DE_PRE_US], pr[P.P_DE_POST_US], hw)
        # byte_us (one character time) lets the parser judge a gap from when a
        # late-drained burst began, not from its last byte. Cut through, the parsers
        # stop at each routing decision (EV_HEAD) and at each dropped frame.
        # (a reply matches on its first two body bytes, whatever its layout: bridge.py)
        self.up_parser = _parser.FrameParser(ver8, pr[P.P_INTERBYTE_US], True, 10000000 // pr[P.P_UP_BAUD],
                                             head_at=1 if cut else 0, stop_drop=cut, start_ev=cut)
        self.down_parser = _parser.FrameParser(ver8, pr[P.P_INTERBYTE_US], True, 10000000 // pr[P.P_DOWN_BAUD],
                                               head_at=2 if cut else 0, stop_drop=cut, start_ev=cut)
        # The bridge reads driver frames layout-free (mixed Ver6/Ver8 bus): allow the
        # longer Ver8 body whatever the jig's own protocol.
        self.down_parser.max_body = MAX_BODY
        self.handlers = Handlers(self)
        self.t_beat = hal.ticks_us()
        # due[0]: the tick at which the slow pass must next run (anyone may move it
        # earlier); due[1]: the CAN port's own pass, while it is open (jig.canport),
        # which due[2] says (1: open); due[3]: answers the port has not taken yet (its
        # out_n after its last pass: the pump cannot see CanPort.out_n); due[4]: 1 when the
        # pump returned for the port's pass (it has work and may run now)
        self.due = array("i", [self.t_beat, self.t_beat, 0, 0, 0])
        self.cut = cut
        self.ver8 = ver8  # (how this boot runs: the RESTART parameters may differ in RAM)
        self.up_baud = pr[P.P_UP_BAUD]
        self.down_baud = pr[P.P_DOWN_BAUD]
        # The recording of both buses (parameter capture; the HAL's capture port, if any).
        self.capture = Capture(self, getattr(hal, "capture", None))
        self.bridge = Bridge(hal, self.up, self.down, self.handlers, self.params, self.counters, ver8, cut, self.due,
                             self.capture, self.down_parser)
        self.scanner = Scanner(self.bridge, self.params)
        self.lease = SafetyLease(self.params)  # the run's safety net: the PC port's and the CAN port's watches
        self.safety = SafetyStop(self.bridge, self.params, self.counters, self.lease)
        self._notice = self.lease.notice  # [0]: pending (the slow pass looks without a call)
        self.trace = Trace(self)  # (after the parsers and the bridge: it reads both)
        # The CAN port (an SLCAN adapter on the HAL's third CDC port); None on a HAL
        # without CAN (no can_open): the app runs as before.
        self.can = CanPort(self) if hasattr(hal, "can_open") else None
        self._trace_on = self.trace.ts  # [0] (T_ON): the slow pass calls the sampler only while it runs
        self.up_rx = bytearray(RX_CHUNK)
        self.down_rx = bytearray(RX_CHUNK)
        self._pc_scratch = [0] * PARSER_COUNTERS  # one parser's counters, for counter_values
        # Bound once: the main loop calls these on every pass.
        self._up_any = hal.up.any
        self._down_any = hal.down.any
        self._ticks = hal.ticks_us
        self._up_read = self.up.read_into
        self._down_read = self.down.read_into
        self._up_bytes = self.bridge.up_bytes
        self._down_bytes = self.bridge.down_bytes
        self._can_serve = self._can_any = None  # the CAN port's pass: CanPort.serve, its host port's any
        if self.can is not None:
            self._can_serve = self.can.serve
            if self.can.port is not None:
                self._can_any = self.can.port.any
        self.base_echo = 0
        self.base_up_ovf = hal.up.overflows
        self.base_down_ovf = hal.down.overflows
        self.base_cap = array("i", [0, 0])  # the capture totals at the last counter reset
        self.beat = False
        # The hot path in machine code: cut-through between two plain ports.
        fast = _fastpath_module(fastpath) if cut and self.up.plain and self.down.plain else None
        self.pump = fast.pump if fast is not None else None
        self.pump_ctx = fast.context(self) if fast is not None else None
        if pr[P.P_CAPTURE]:
            self.set_capture(1, self.t_beat)

    def set_capture(self, on, now):
        """Recording of both buses on or off (parameter capture, in RAM). Store-and-
        forward, the parsers then also stop at every dropped frame, to record it."""
        on = 1 if on else 0
        self.params.ram[P.P_CAPTURE] = on
        self.capture.set(on, now)
        drop = 1 if (self.cut or on) else 0
        self.up_parser.st[_parser.S_STOP_DROP] = drop
        self.down_parser.st[_parser.S_STOP_DROP] = drop

    # --- parameters --------------------------------------------------------------
    def apply_params(self):
        """Apply the 'immediate' parameters after a SetParameter."""
        pr = self.params.ram
        self.up.pre_us = self.down.pre_us = pr[P.P_DE_PRE_US]
        self.up.post_us = self.down.post_us = pr[P.P_DE_POST_US]
        self.up_parser.interbyte_timeout_us = pr[P.P_INTERBYTE_US]
        self.down_parser.interbyte_timeout_us = pr[P.P_INTERBYTE_US]
        if (pr[P.P_CAPTURE] != 0) != self.capture.on:
            self.set_capture(pr[P.P_CAPTURE], self._ticks())
        elif self.capture.on:
            self.capture.hello(self._ticks())  # the id or the timeout it reports may have changed

    def save_params(self):
        ok = self.params.save()
        if ok:
            self.counters.v[K.C_PARAM_SAVES] += 1
        return ok

    # --- counters ------------------------------------------------------------------
    def _sync_counters(self):
        self.counters.update_average()
        v = self.counters.v
        v[K.C_ECHO] = self.up.echo_bytes + self.down.echo_bytes - self.base_echo
        v[K.C_UP_OVERFLOWS] = self.hal.up.overflows - self.base_up_ovf
        v[K.C_DOWN_OVERFLOWS] = self.hal.down.overflows - self.base_down_ovf
        cs = self.capture.cs
        v[K.C_CAPTURE_RECORDS] = cs[12] - self.base_cap[0]  # (CS_TOTAL, CS_LOST_TOTAL: since boot)
        v[K.C_CAPTURE_LOST] = cs[13] - self.base_cap[1]

    def counter_values(self, out):
        """All counters in diag.WIRE_NAMES order into out (a list); returns out."""
        self._sync_counters()
        v = self.counters.v
        n = K.COUNT
        for i in range(n):
            out[i] = v[i]
        self._put_parser_counters(self.up_parser, out, n)
        self._put_parser_counters(self.down_parser, out, n + PARSER_COUNTERS)
        return out

    def _put_parser_counters(self, p, out, off):
        s = self._pc_scratch
        p.counters(s)
        for i in range(PARSER_COUNTERS):
            out[off + i] = s[i]

    def reset_counters(self):
        self.counters.reset()
        self.up_parser.reset_counters()
        self.down_parser.reset_counters()
        self.base_echo = self.up.echo_bytes + self.down.echo_bytes
        self.base_up_ovf = self.hal.up.overflows
        self.base_down_ovf = self.hal.down.overflows
        self.base_cap[0] = self.capture.cs[12]
        self.base_cap[1] = self.capture.cs[13]
        if self.can is not None:
            self.can.reset_counters()

    # --- main loop -----------------------------------------------------------------
    def poll(self):
        """One pass of the main loop (``run`` is the loop)."""
        self.run(1)

    def run(self, passes=-1):
        """The main loop, forever (or ``passes`` passes). Every name it uses is a local,
        bound once: an idle pass is two ``any()`` calls, a tick and a compare, and a
        pass with bytes calls only the port's read and the bridge."""
        if self.pump is not None:
            self._run_pump(passes)
            return
        down_any = self._down_any
        up_any = self._up_any
        down_read = self._down_read
        up_read = self._up_read
        down_bytes = self._down_bytes
        up_bytes = self._up_bytes
        down_parser = self.down_parser
        up_parser = self.up_parser
        down_rx = self.down_rx
        up_rx = self.up_rx
        ticks = self._ticks
        due = self.due
        can = self.can
        serve = self._can_serve
        port_any = self._can_any
        bridge = self.bridge
        watch = bridge.watch_lines if bridge.up_isr is not None or bridge.down_isr is not None else None
        up_st = up_parser.st
        down_st = down_parser.st
        rs = ts = None
        if can is not None:
            rs = can.rs
            ts = can.ts
        while passes != 0:
            passes -= 1
            # Driver bus first: a reply already in must be relayed before a new PC
            # request aborts its wait. Ask for no more than is waiting: a UART read
            # asked for more waits for it.
            d = down_any()
            if d:
                n = down_read(down_rx, d if d < RX_CHUNK else RX_CHUNK)
                if n:
                    down_bytes(down_parser, down_rx, n, ticks())
            u = up_any()
            if u:
                n = up_read(up_rx, u if u < RX_CHUNK else RX_CHUNK)
                if n:
                    up_bytes(up_parser, up_rx, n, ticks())
            now = ticks()
            if watch and not d and not u:
                watch(up_st, down_st, now)  # a byte starting: DE up on the other bus now
            if (now - due[0]) & TICKS_MASK < TICKS_HALF:
                self._slow(now)  # (open, the CAN port's traffic is not in it: its own pass may follow)
            if due[2] and (now - due[1]) & TICKS_MASK < TICKS_HALF:
                # the CAN port's own pass, in the bridge's idle time (as the pump): after a pass
                # that read input only once it has waited CAN_DEFER_US (due[1] stays put) ...
                late = (now - due[1]) & TICKS_MASK >= CAN_DEFER_US
                if (d or u) and not late:
                    continue
                # ... serve only if something waits (the interrupts' ring, finished or
                # stalled frames, answers, the host's bytes), and not inside a transaction
                if (rs[_RS_TAIL] != rs[_RS_HEAD] or ts[_TS_REC] != ts[_TS_DONE]
                        or (not ts[_TS_BUSY] and ts[_TS_TAIL] != ts[_TS_HEAD]) or due[3] or port_any()):
                    if not late and not self.bridge_idle():
                        continue
                    serve(now)
                    due[3] = can.out_n
                t = (due[1] + CAN_POLL_US) & TICKS_MASK  # the next a period on, on its grid
                d = (t - now) & TICKS_MASK  # (ticks_add and ticks_diff inline: no calls)
                if d == 0 or d >= TICKS_HALF:  # not after now: a period from now
                    t = (now + CAN_POLL_US) & TICKS_MASK
                due[1] = t

    def _run_pump(self, passes):
        """run() with the passes in jig.fastpath.pump, which returns to run the slow pass
        or, the CAN port open, its own pass (the pump decides, as the portable loop
        would, and says so in due[4]). A CAN pass that falls due as the passes run out
        waits for the next call's pump."""
        pump = self.pump
        ctx = self.pump_ctx
        ticks = self._ticks
        due = self.due
        can = self.can
        serve = self._can_serve
        while True:
            left = pump(ctx, passes)
            if passes > 0:
                passes = left
            now = ticks()
            for_can = due[4]  # (the pump has looked: the port has work and may run now)
            due[4] = 0
            if (now - due[0]) & TICKS_MASK < TICKS_HALF:
                self._slow(now)
            elif for_can:
                serve(now)
                due[3] = can.out_n
                t = (due[1] + CAN_POLL_US) & TICKS_MASK
                d = (t - now) & TICKS_MASK
                if d == 0 or d >= TICKS_HALF:
                    t = (now + CAN_POLL_US) & TICKS_MASK
                due[1] = t
            if passes == 0:
                return

    def bridge_idle(self):
        """True when no Plus-R transaction is in flight: the bridge waits for no reply,
        passes no frame on, and neither parser is inside a frame."""
        bs = self.bridge.bs
        return (not (bs[_B_STATE] or bs[_B_FWD] or bs[_B_REL]) and self.up_parser.st[_parser.S_STATE] == _parser.HUNT
                and self.down_parser.st[_parser.S_STATE] == _parser.HUNT)

    def _slow(self, now):
        """Everything with a time in it; sets the next due tick."""
        bridge = self.bridge
        due = ticks_add(now, SLOW_US)
        due = self._gap(self.down_parser, False, now, due)
        due = self._gap(self.up_parser, True, now, due)
        bridge.poll(now)
        self.scanner.poll(now)
        self.safety.poll(now)
        if self._notice[0]:  # (a safety stop's notice is waiting: its age, in whole seconds)
            self.lease.poll(now)
        tracing = self._trace_on[0]
        if tracing:
            self.trace.poll(now)
        can = self.can
        if can is not None:
            can.poll(now)
            self.due[3] = can.out_n  # (for the port's own pass)
        cap = self.capture
        stream = -1
        if cap.port is not None or cap.cs[0]:  # (CS_ON) commands to read, or records to move
            stream = cap.slow(now, bridge)
        self.hal.wdt_feed()
        if ticks_diff(now, self.t_beat) >= HEARTBEAT_US:
            self.t_beat = now
            self.beat = not self.beat
            self.hal.heartbeat(self.beat)
        due = _earlier(due, now, ticks_diff(self.t_beat, now) + HEARTBEAT_US)
        due = _earlier(due, now, bridge.wait_us(now))
        due = _earlier(due, now, self.safety.wait_us(now))
        if tracing:
            due = _earlier(due, now, self.trace.wait_us(now))
        if can is not None:
            due = _earlier(due, now, can.wait_us(now))
        if stream == 0:
            due = _earlier(due, now, QUIET_US)  # more for the capture port
        if ticks_diff(due, now) <= 0:
            due = ticks_add(now, 1)
        self.due[0] = due

    def _gap(self, p, from_pc, now, due):
        """Drop a partial frame after a silence longer than the inter-byte timeout; let
        the other bus go if a byte seen starting here armed it and never came."""
        st = p.st
        rs = self.down if from_pc else self.up
        if arm_overdue(rs, st, now):
            rs.disarm()  # (idle passes do it first: Bridge.watch_lines)
        if st[_parser.S_STATE] == _parser.HUNT:
            return due
        if self.bridge.gap(p, from_pc, now):
            return due
        return _earlier(due, now, st[_parser.S_TIMEOUT] + 1 - ticks_diff(now, st[_parser.S_T_LAST]))

    def wait_us(self):
        """µs until the app next needs a poll without new input (0: now).

        Lets a simulation (or a board that sleeps) skip idle loop passes. The CAN
        port's own passes count only when it has something to do; an idle port's next
        pass is parked further on its period's grid (``due[1]``), so a host line that
        comes meanwhile waits for the pass the board's loop would have run.
        """
        hal = self.hal
        if hal.up.any() or hal.down.any():
            return 0
        now = hal.ticks_us()
        d = ticks_diff(self.due[0], now)
        # a bus armed by the line watch is let go by an idle pass ARM_BYTES byte times on
        d = _armed_wait(self.down, self.up_parser, now, d)
        d = _armed_wait(self.up, self.down_parser, now, d)
        can = self.can
        if can is not None and can.is_open:
            due = self.due
            w = ticks_diff(due[1], now)
            pending = can.pending()
            if pending and w <= 0:  # due (due[1] stays: a deferred pass's wait counts from it)
                if w > -CAN_DEFER_US and not self.bridge_idle():
                    w += CAN_DEFER_US  # deferred (run): the bridge's own events come sooner
                else:
                    w = 0
                if w < d:
                    d = w
                return d if d > 0 else 0
            if not 0 <= w <= CAN_POLL_US:
                w %= CAN_POLL_US  # the next tick on its grid
            if pending:
                due[1] = ticks_add(now, w)
                if w < d:
                    d = w
            else:
                due[1] = ticks_add(now, w + CAN_IDLE_PARK)
        return d if d > 0 else 0


def _armed_wait(rs, p, now, d):
    """The smaller of d and the µs until an idle pass would let rs go (armed by a
    start bit on p's bus that has not become a byte)."""
    armed = rs.early[1]
    if armed < 0:
        return d
    w = ARM_BYTES * p.st[_parser.S_BYTE_US] + 1 - ticks_diff(now, armed)
    return w if w < d else d


def _earlier(due, now, wait):
    """The earlier of the tick due and now + wait (a wait < 0 means none)."""
    if wait >= 0 and wait < ticks_diff(due, now):
        return ticks_add(now, wait)
    return due
