"""One half-duplex RS-485 port: DE/RE timing around a transmission, echo discard.

``send`` raises DE, waits the pre-delay, writes, makes sure the last stop bit has
left the shift register (the HAL's ``write`` returns after transmit-complete, or
we wait the computed wire time), waits the post-delay and releases DE. A frame
that is passed on as it arrives (cut-through) is sent as ``begin``, any number of
``part`` calls and ``finish``: DE stays up from the first byte to the last stop
bit of the last part. On a plain port the bus may be taken early
(``raise_early``: the bridge does it when a byte that can start a header, an AA,
arrives on the other bus): DE up, the pre-delay, and that AA goes on at once, as
on a wire; the ``begin`` that follows sends its header from the CC, and
``drop_early`` lets the bus go if no header followed (the line then carried a lone
AA, as a wire would have). The bus may be taken earlier still, when that byte's
start bit is seen on the other bus (``arm``: DE up, nothing sent): the pre-delay
then runs while the byte arrives, and whoever takes the bus next (``raise_early``,
``begin``) waits only for what is left of it; ``disarm`` lets it go if no AA came.
Where the port can queue bytes for its transmitter
(``port.queue``/``port.drain``: the USART's transmit FIFO on the board), the
pieces of such a frame are queued and the CPU goes on while they go out;
``finish`` drains the transmitter before DE drops. So DE is never dropped with
bytes still queued, and a whole-frame ``write`` always finds the transmitter
empty. In hardware-DE mode the USART drives DE itself (set up
through ``port.hw_de``) and only writes happen here; the USART drops DE whenever
its transmitter runs empty, so the app uses hardware DE only in store-and-forward
mode, where every frame is one write.

A separate /RE pin (``port.re``, if the board has one) is driven with DE: the
receiver is switched off while we drive the bus and back on after DE drops.
Bytes heard on our own port while we transmit anyway (a transceiver whose
receiver stays enabled) are echo: they are discarded from the receive stream and
counted. A port that declares ``echo_free`` (receiver off whenever DE is up, as
/RE tied to DE on the jig) skips that bookkeeping.
"""

from array import array

from jig import mem
from jig.compat import const, ticks_diff

BITS_PER_BYTE = const(10)  # 8N1: start + 8 data + stop
_AA = b"\xaa"  # the header's first byte, sent ahead of the rest (raise_early)


def wire_time_us(nbytes, baud):
    """Time nbytes take on the wire at baud, in µs (rounded up)."""
    return (nbytes * BITS_PER_BYTE * 1000000 + baud - 1) // baud


def _nothing_queued():
    """``drain`` of a port whose writes return after the last stop bit."""
    return 0


class Rs485:
    def __init__(self, hal, port, pre_us=10, post_us=0, hw_de=False):
        self.hal = hal
        self.port = port
        self.echo_bytes = 0  # bytes discarded as echo
        self.t_tx_start = 0  # tick when the last ``send`` took the bus
        # early[0]: tick at which DE went up ahead of a frame and its AA was sent
        # (``raise_early``), -1: it did not. early[1]: tick at which DE went up as a
        # byte started on the other bus, nothing sent yet (``arm``), -1: not armed.
        # An array: the machine-code pump (jig.fastpath) shares it.
        self.early = array("i", [-1, -1])
        self._keep = 0  # bytes still to deliver before the echo to skip
        self._skip = 0  # echo bytes still to skip
        self._expect = 0  # bytes in the receive buffer, as last seen (echo bookkeeping)
        self.re = getattr(port, "re", None)  # separate /RE pin, if any
        # A port whose receiver is off while it drives the bus (/RE tied to DE, as on
        # the jig) hears no echo: nothing to count or skip, reads go straight through.
        self.track_echo = not getattr(port, "echo_free", False)
        self.tx_blocks = port.tx_blocks
        # Bound once: these run for every frame.
        self._de = port.de
        self._write = port.write
        self._any = port.any
        self._ticks = hal.ticks_us
        self._sleep = hal.sleep_us
        self.read_into = self._read_skipping_echo if self.track_echo else port.readinto
        port.de(0)
        if self.re is not None:
            self.re(0)
        self.configure(pre_us, post_us, hw_de)

    def configure(self, pre_us, post_us, hw_de):
        """Set DE delays; hardware DE if asked for and the port supports it."""
        self.pre_us = pre_us
        self.post_us = post_us
        want = bool(hw_de)
        hook = getattr(self.port, "hw_de", None)
        baud = self.port.baud
        # DEAT/DEDT are in 1/16 bit time, 5 bits wide (max 31).
        pre16 = min(31, (pre_us * baud * 16 + 999999) // 1000000)
        post16 = min(31, (post_us * baud * 16 + 999999) // 1000000)
        ok = False
        if hook is not None:
            ok = hook(want, pre16, post16)
        self.hw = bool(want and ok)
        # The jig's own port (software DE, /RE tied to DE, a write that returns at
        # transmit-complete) needs none of the checks below: a frame cut through pays
        # only for the calls into the HAL.
        self.plain = not self.hw and not self.track_echo and self.tx_blocks and self.re is None
        # Pieces of a frame go into the transmitter's queue where there is one (only on
        # a plain port: echo bookkeeping needs each piece on the wire before it reads).
        queue = getattr(self.port, "queue", None)
        self.queued = self.plain and queue is not None
        self.raw_part = queue if self.queued else self._write
        self.drain = self.port.drain if self.queued else _nothing_queued
        return self.hw

    def begin(self, buf, off, n):
        """Take the bus (/RE off, DE up, pre-delay: software DE) and transmit the
        first part, buf[off:off + n], a frame's header first. If the bus was taken
        early (``raise_early``), the header's AA has gone: the rest follows at once."""
        if self.plain:
            if self.early[0] >= 0:
                self.early[0] = -1
                if n > 1:
                    self.raw_part(buf, off + 1, n - 1)
                return
            self._take()
            self.raw_part(buf, off, n)
            return
        if self.track_echo:
            self._expect = self._any()  # what is waiting now arrived before we talked
        if not self.hw:
            if self.re is not None:
                self.re(1)
            self._de(1)
        if self.pre_us and not self.hw:
            self._sleep(self.pre_us)
        self.part(buf, off, n)

    def part(self, buf, off, n):
        """Transmit buf[off:off + n] while the bus is ours; returns after its last stop
        bit, or once it is queued on a port that queues (``queued``)."""
        self.raw_part(buf, off, n)
        if not self.tx_blocks:
            self._sleep(wire_time_us(n, self.port.baud))
        if self.track_echo:
            self._note_echo()

    def finish(self):
        """Release the bus after the last part: post-delay, DE down, /RE on."""
        if self.plain:
            self.drain()  # the last stop bit of what is queued
            if self.post_us:
                self._sleep(self.post_us)
            self._de(0)
            return
        if not self.hw:
            if self.post_us:
                self._sleep(self.post_us)
            self._de(0)
            if self.re is not None:
                self.re(0)
        if self.track_echo:
            self._note_echo()

    def _take(self):
        """Plain port: DE up and the pre-delay; if the bus was armed, DE is up already
        and only what is left of the pre-delay is waited."""
        early = self.early
        armed = early[1]
        if armed < 0:
            self._de(1)
            if self.pre_us:
                self._sleep(self.pre_us)
            return
        early[1] = -1
        if self.pre_us:
            # + 1: both ticks are whole µs, so what has passed may be up to 1 µs less
            left = self.pre_us + 1 - ticks_diff(self._ticks(), armed)
            if left > 0:
                self._sleep(left)

    def raise_early(self):
        """Plain port: an AA that may start a header came in on the other bus: take
        this bus (DE up, the pre-delay) and send the AA on now, a byte time before its
        CC can be in; the next ``begin`` sends the header from the CC, or
        ``drop_early`` ends it."""
        early = self.early
        if early[0] < 0:
            early[0] = early[1] if early[1] >= 0 else self._ticks()
            self._take()
            self.raw_part(_AA, 0, 1)

    def arm(self, now):
        """Plain port: a byte is arriving on the other bus (its start bit is seen) where
        a frame's AA would go on at once: DE up now, nothing sent, so the pre-delay
        runs while the byte arrives. ``raise_early``/``begin`` go on from here,
        ``disarm`` ends it."""
        early = self.early
        if early[0] < 0 and early[1] < 0:
            self._de(1)
            early[1] = now

    def disarm(self):
        """The byte seen starting was no AA, or never came: DE down (nothing was sent)."""
        if self.early[1] >= 0:
            self.early[1] = -1
            self._de(0)

    def drop_early(self):
        """No header followed the AA sent early: let the bus go (as ``finish``)."""
        if self.early[0] >= 0:
            self.early[0] = -1
            self.drain()
            if self.post_us:
                self._sleep(self.post_us)
            self._de(0)

    def _note_echo(self):
        """Bytes that came in while we talked are our own echo: skip them when read.
        (A frame sent in pieces may be read from between the pieces: ``_expect``
        follows what is in the receive buffer.)"""
        waiting = self._any()
        echo = waiting - self._expect
        if echo > 0:
            if self._skip == 0:
                self._keep = self._expect
            self._skip += echo
            self.echo_bytes += echo
        self._expect = waiting

    def send(self, buf, n):
        """Transmit buf[0:n] with DE framing; returns when the line is released."""
        self.t_tx_start = self._ticks()
        self.begin(buf, 0, n)
        self.finish()

    def any(self):
        return self._any()

    def _read_skipping_echo(self, buf, n):
        """Received bytes (echo removed) into buf[0:]; returns the count."""
        got = self.port.readinto(buf, n)
        self._expect -= got
        if self._expect < 0:
            self._expect = 0
        if self._skip == 0 or got == 0:
            return got
        k = self._keep
        if k >= got:
            self._keep = k - got
            return got
        self._keep = 0
        d = got - k
        if d > self._skip:
            d = self._skip
        self._skip -= d
        rest = got - k - d
        if rest:
            mem.copy(buf, k, buf, k + d, rest)
        return k + rest
