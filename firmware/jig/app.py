"""Wires the jig together and runs its main loop, on any HAL.

``App(hal)`` builds the two RS-485 ports, their parsers, the bridge, the local
handlers, the bus scanner and the safety stop from the parameter table, and
``poll()`` does one pass of the main loop: drain the driver bus and the PC bus into
their parsers, hand complete frames to the bridge, time out the pending wait, give
the scan and the safety stop a turn, feed the watchdog, blink the heartbeat.
``run()`` loops forever (the board's main.py calls it).

The HAL (docs/hal.md; implemented by ``jig.board`` and by the virtual bench)::

    hal.ticks_us() -> int           wrapping µs ticks (time.ticks_us semantics)
    hal.sleep_us(us)                short blocking wait (DE delays)
    hal.up, hal.down                the PC-bus and driver-bus ports, each:
        .baud                       int, 8N1
        .any() -> int               received bytes waiting
        .readinto(buf, n) -> int    move up to n bytes into buf[0:], non-blocking
        .t_last                     tick of the last received byte (IRQ time stamp)
        .overflows                  RX bytes dropped, buffer full
        .write(buf, n)              send buf[0:n]; returns after the last stop bit
        .tx_blocks                  True if write returns after transmit-complete
        .de(v)                      DE pin (1 = drive the bus); /RE tied to it or .re(v)
        .hw_de(on, pre16, post16)   USART hardware DE on/off -> True if supported
    hal.set_outputs(mask) / hal.get_outputs() / hal.get_inputs()   jig I/O, bits 0..15
    hal.heartbeat(on)               heartbeat LED
    hal.wdt_feed()                  watchdog
    hal.fs                          .read_into(path, buf) .write(path, buf, n)
                                    .rename(src, dst) .remove(path)
    hal.param_path                  parameter file path

Ports are opened by the HAL at the baud rates the app asks for: the app calls
``hal.open(up_baud, down_baud)`` once after loading the parameters (baud rates
take effect at restart).
"""

from jig import counters as K
from jig import parser as _parser
from jig import params as P
from jig.bridge import Bridge
from jig.compat import const, ticks_diff
from jig.frame import MAX_BODY
from jig.handlers import Handlers
from jig.rs485 import Rs485
from jig.safety import SafetyStop
from jig.scan import Scanner

RX_CHUNK = const(256)
HEARTBEAT_US = const(500000)
PARSER_COUNTERS = len(_parser.COUNTER_NAMES)  # per parser, in counter_values


class App:
    def __init__(self, hal):
        self.hal = hal
        self.counters = K.Counters()
        self.params = P.Params(getattr(hal, "fs", None), getattr(hal, "param_path", None))
        if not self.params.load():
            self.counters.v[K.C_PARAM_ERRORS] += 1
        pr = self.params.ram
        hal.open(pr[P.P_UP_BAUD], pr[P.P_DOWN_BAUD])
        ver8 = pr[P.P_PROTOCOL] == 1
        hw = pr[P.P_DE_MODE] == 1
        self.up = Rs485(hal, hal.up, pr[P.P_DE_PRE_US], pr[P.P_DE_POST_US], hw)
        self.down = Rs485(hal, hal.down, pr[P.P_DE_PRE_US], pr[P.P_DE_POST_US], hw)
        # byte_us (one character time) lets the parser judge a gap from when a
        # late-drained burst began, not from its last byte.
        self.up_parser = _parser.FrameParser(ver8, pr[P.P_INTERBYTE_US], True, 10000000 // pr[P.P_UP_BAUD])
        self.down_parser = _parser.FrameParser(ver8, pr[P.P_INTERBYTE_US], True, 10000000 // pr[P.P_DOWN_BAUD])
        # The bridge reads driver frames layout-free (mixed Ver6/Ver8 bus): allow the
        # longer Ver8 body whatever the jig's own protocol.
        self.down_parser.max_body = MAX_BODY
        self.handlers = Handlers(self)
        self.bridge = Bridge(hal, self.up, self.down, self.handlers, self.params, self.counters, ver8)
        self.scanner = Scanner(self.bridge, self.params)
        self.safety = SafetyStop(self.bridge, self.params, self.counters)
        self.up_rx = bytearray(RX_CHUNK)
        self.down_rx = bytearray(RX_CHUNK)
        self._pc_scratch = [0] * PARSER_COUNTERS  # one parser's counters, for counter_values
        self._on_pc = self.bridge.on_pc_frame
        self._on_down = self.bridge.on_down_frame
        self.base_echo = 0
        self.base_up_ovf = hal.up.overflows
        self.base_down_ovf = hal.down.overflows
        self.t_beat = hal.ticks_us()
        self.beat = False

    # --- parameters --------------------------------------------------------------
    def apply_params(self):
        """Apply the 'immediate' parameters after a SetParameter."""
        pr = self.params.ram
        self.up.pre_us = self.down.pre_us = pr[P.P_DE_PRE_US]
        self.up.post_us = self.down.post_us = pr[P.P_DE_POST_US]
        self.up_parser.interbyte_timeout_us = pr[P.P_INTERBYTE_US]
        self.down_parser.interbyte_timeout_us = pr[P.P_INTERBYTE_US]

    def save_params(self):
        ok = self.params.save()
        if ok:
            self.counters.v[K.C_PARAM_SAVES] += 1
        return ok

    # --- counters ------------------------------------------------------------------
    def _sync_counters(self):
        v = self.counters.v
        v[K.C_ECHO] = self.up.echo_bytes + self.down.echo_bytes - self.base_echo
        v[K.C_UP_OVERFLOWS] = self.hal.up.overflows - self.base_up_ovf
        v[K.C_DOWN_OVERFLOWS] = self.hal.down.overflows - self.base_down_ovf

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

    # --- main loop -----------------------------------------------------------------
    def _drain(self, rs, port, p, buf, on_frame):
        n = rs.read_into(buf, RX_CHUNK)
        if n == 0:
            return False
        t = port.t_last
        i = 0
        while i < n:
            i = p.feed(buf, i, n, t)
            if p.ready:
                on_frame(p, t)
        return True

    def poll(self):
        """One pass of the main loop."""
        hal = self.hal
        now = hal.ticks_us()
        # Driver bus first: a reply already in must be relayed before a new PC
        # request aborts its wait.
        if not self._drain(self.down, hal.down, self.down_parser, self.down_rx, self._on_down):
            self.down_parser.check_timeout(now)
        if not self._drain(self.up, hal.up, self.up_parser, self.up_rx, self._on_pc):
            self.up_parser.check_timeout(now)
        now = hal.ticks_us()
        self.bridge.poll(now)
        self.scanner.poll(now)
        self.safety.poll(now)
        hal.wdt_feed()
        if ticks_diff(now, self.t_beat) >= HEARTBEAT_US:
            self.t_beat = now
            self.beat = not self.beat
            hal.heartbeat(self.beat)

    def wait_us(self):
        """µs until the app next needs a poll without new input (-1: only on input).

        Lets a simulation (or a board that sleeps) skip idle loop passes.
        """
        hal = self.hal
        if hal.up.any() or hal.down.any() or self.scanner.pending():
            return 0
        now = hal.ticks_us()
        best = ticks_diff(self.t_beat, now) + HEARTBEAT_US
        w = self.bridge.wait_us(now)
        if 0 <= w < best:
            best = w
        w = self.safety.wait_us(now)
        if 0 <= w < best:
            best = w
        w = self._gap_wait(self.up_parser, now)
        if w < best:
            best = w
        w = self._gap_wait(self.down_parser, now)
        if w < best:
            best = w
        return best if best > 0 else 0

    def _gap_wait(self, p, now):
        if p.state == _parser.HUNT:
            return HEARTBEAT_US
        return p.interbyte_timeout_us - ticks_diff(now, p.t_last) + 1

    def run(self):
        while True:
            self.poll()
