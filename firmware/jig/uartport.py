"""One half-duplex RS-485 port on an STM32 USART: the HAL port of docs/hal.md.

Receive path: MicroPython's UART driver puts every received byte into the port's
receive ring (``machine.UART(..., rxbuf=RXBUF)``) from the USART RX interrupt, in
C, as the byte arrives; the main loop asks ``any()`` and drains the ring with
``readinto``. So bytes are visible to the main loop while a frame is still
arriving (what cut-through forwarding needs), and there is no Python interrupt
handler at all.

``any``, ``readinto`` and ``write`` are the UART's own bound methods, stored on
the port once: a call costs what the C method costs, with no Python frame in
between and nothing allocated. Their contract (docs/hal.md):

* ``readinto(buf, n)`` must only be asked for bytes already waiting
  (``n <= any()``): the UART's read returns at once then. Asked for more it waits
  for them, up to one character timeout (>= 2 ms) after the last byte that came.
* ``write(buf, n)`` / ``write(buf, off, n)`` returns after the last stop bit
  (stm32 waits for transmit-complete).

Transmit path for a frame passed on in pieces: ``queue`` puts bytes straight into
the USART's 16-byte transmit FIFO (the stm32 port enables it on the H7) and
returns; it waits only while the FIFO is full. ``drain`` waits for
transmit-complete (ISR.TC: FIFO empty and the last stop bit sent). Both are viper,
on the USART's ISR/TDR registers: MicroPython's UART has no non-blocking write,
and its ``write`` waits for TC after every call, so the CPU and the line would
take turns. ``jig.rs485`` drains before DE drops, so ``write`` (which with
timeout 0 refuses when the FIFO is full) always finds the FIFO empty.

A full ring loses bytes silently (the driver stops reading the USART, whose
16-byte FIFO then overruns). ``housekeep`` -- run by the board every few ms,
never on the hot path -- counts each time the ring is found full (what that can
and cannot see is in docs/board.md) and reports traffic for the LED.

Driver enable: the DE pin is the pin whose alternate function is the USART's
RTS/DE output. In software mode it is a plain output that ``jig.rs485`` raises
and drops around ``write``; ``hw_de`` hands it to the USART (CR3.DEM, DEAT/DEDT
in CR1, RM0433 "RS485 driver enable"). The register arithmetic is pure and
unit-tested on the host.
"""

import machine

try:
    import micropython
except ImportError:  # CPython (host tests): the viper source as plain Python
    from jig.compat import micropython_shim as micropython

try:
    import stm
except ImportError:  # a port without the stm module: software DE only
    stm = None

from jig.compat import const, ptr8, ptr32, ticks_diff, ticks_ms  # noqa: F401 (ptrN: viper casts)

# --- USART registers (RM0433, chapter USART/UART: "RS485 driver enable" and the
# descriptions of USART_CR1, USART_CR3, USART_ISR and USART_ICR). DEM/DEP and
# DEAT/DEDT may only be written while CR1.UE = 0. Times are in 1/16 bit
# (oversampling by 16).
USART_CR1_UE = const(1 << 0)  # USART enable
USART_CR1_DEDT_SHIFT = const(16)  # DEDT[4:0], bits 20:16: DE de-assertion time
USART_CR1_DEAT_SHIFT = const(21)  # DEAT[4:0], bits 25:21: DE assertion time
USART_CR1_DEDT_MASK = const(0x1F << 16)
USART_CR1_DEAT_MASK = const(0x1F << 21)
USART_CR3_DEM = const(1 << 14)  # driver enable mode: DE on the RTS pin
USART_CR3_DEP = const(1 << 15)  # DE polarity: 0 = active high
USART_ISR_IDLE = const(1 << 4)  # an idle line was seen after received bytes
USART_ISR_TC = const(1 << 6)  # transmission complete
USART_ISR_TXFNF = const(1 << 7)  # transmit FIFO not full (TXE with the FIFO off)
USART_TDR_WORDS_AFTER_ISR = const(3)  # TDR at 0x28, ISR at 0x1C
# Bounds on the transmit waits, in polls of ISR (a few cycles each at 400 MHz): a
# byte takes ~1 ms at 9 600 baud, the whole FIFO ~18 ms. They end a wait only if
# the USART stopped sending; the watchdog would not catch a hang shorter than its period.
TX_FIFO_SPINS = const(1 << 20)
TX_DRAIN_SPINS = const(1 << 23)
USART_ICR_IDLECF = const(1 << 4)  # write 1: clear ISR.IDLE
USART_ICR_OFFSET = const(0x20)  # where the stm module has no USART_ICR name
DE_TIME_MAX = const(31)

# The receive ring: 4 KB is about eight maximum frames on the wire, 44 ms of
# continuous traffic at 921 600 baud and 355 ms at 115 200 before it is full.
RXBUF = const(4096)
# machine.UART read timeout for the first byte: 0, so a read with nothing waiting
# returns None at once. (Between bytes MicroPython enforces at least one
# character time + 2 ms; only a read asked for more than any() waits for that.)
# The first byte of a write waits for a free transmitter with the same timeout:
# the transmitter is always free then, as every write returned at transmit-complete.
UART_TIMEOUT_MS = const(0)


# --- DE register arithmetic (pure: unit-tested on the host) ---------------------------
def de_times_16ths(pre16, post16):
    """Clamp DE assertion/de-assertion times to the 5-bit register fields."""
    if pre16 < 0:
        pre16 = 0
    if post16 < 0:
        post16 = 0
    return min(pre16, DE_TIME_MAX), min(post16, DE_TIME_MAX)


def cr1_with_de_times(cr1, pre16, post16):
    """CR1 with DEAT = pre16 and DEDT = post16 (other bits kept)."""
    pre16, post16 = de_times_16ths(pre16, post16)
    cr1 &= ~(USART_CR1_DEAT_MASK | USART_CR1_DEDT_MASK)
    return cr1 | (pre16 << USART_CR1_DEAT_SHIFT) | (post16 << USART_CR1_DEDT_SHIFT)


def cr3_with_de(cr3, on):
    """CR3 with driver-enable mode on/off, DE active high (DEP = 0)."""
    cr3 &= ~USART_CR3_DEP
    if on:
        return cr3 | USART_CR3_DEM
    return cr3 & ~USART_CR3_DEM


def usart_base(uart_id):
    """Base address of USARTn / UARTn from the stm module, or None."""
    if stm is None or not hasattr(stm, "mem32"):
        return None
    for name in ("USART%d" % uart_id, "UART%d" % uart_id):
        base = getattr(stm, name, None)
        if base is not None:
            return base
    return None


class UartPort:
    """One RS-485 port: UART with its receive ring, DE pin, hardware DE."""

    def __init__(self, spec, baud, echo_free=False):
        """spec = (UART id, TX pin, RX pin, DE pin, DE alternate function).

        TX and RX are the UART's own pins (the board definition sets them); they
        are named in the spec for the reader. echo_free: /RE is tied to DE, so the
        receiver is off while the port transmits and hears no echo.
        """
        uart_id, _tx, _rx, de_name, de_af = spec
        self.uart_id = uart_id
        self.baud = baud
        self.tx_blocks = True  # stm32 UART.write returns after transmit-complete
        self.echo_free = echo_free
        self.hw = False
        self.de_name = de_name
        self.de_af = de_af
        self.overflows = 0  # times the receive ring was found full
        self._full = False
        self.de_pin = machine.Pin(de_name, machine.Pin.OUT, value=0)
        self.uart = machine.UART(
            uart_id,
            baudrate=baud,
            bits=8,
            parity=None,
            stop=1,
            rxbuf=RXBUF,
            timeout=UART_TIMEOUT_MS,
            timeout_char=0,
        )
        # The HAL calls, bound once to the C methods (see the module docstring).
        self.any = self.uart.any
        self.readinto = self.uart.readinto
        self.write = self.uart.write
        # DE stays this one bound method in both modes (jig.rs485 binds it once):
        # in hardware mode the pin is in its alternate function, where a write to
        # its output register does not reach the pin.
        self.de = self.de_pin.value
        self.base = usart_base(uart_id)
        # Register addresses computed once: above 2**30 they are big ints on
        # MicroPython, and adding them up would allocate.
        self._isr = None
        self._icr = None
        if self.base is not None:
            self._isr = self.base + stm.USART_ISR
            self._icr = self.base + getattr(stm, "USART_ICR", USART_ICR_OFFSET)
        # queue/drain work on the ISR/TDR registers (``regs``: the ISR's address, or
        # any buffer laid out like ISR..TDR in the tests); without them the port has
        # only the blocking write.
        self.regs = self._isr
        # ``isr``: where the pump watches the line for a start bit (ISR.BUSY, jig.bridge.watch_lines)
        self.isr = self._isr
        if self._isr is None:
            self.queue = None
            self.drain = None

    # --- transmit FIFO (a frame passed on in pieces) --------------------------------
    @micropython.viper
    def queue(self, buf, off: int, n: int) -> int:
        """Put buf[off:off + n] into the transmit FIFO; return once the last byte is
        in it (not sent), the count queued. Waits only while the FIFO is full."""
        reg = ptr32(self.regs)
        src = ptr8(buf)
        i = off
        end = off + n
        while i < end:
            spins = 0
            while (reg[0] & USART_ISR_TXFNF) == 0:
                spins += 1
                if spins > TX_FIFO_SPINS:
                    return i - off  # the transmitter stopped: what went in
            reg[USART_TDR_WORDS_AFTER_ISR] = src[i]
            i += 1
        return n

    @micropython.viper
    def drain(self) -> int:
        """Return after the last stop bit of everything queued (ISR.TC); -1 if the
        transmitter stopped before that."""
        reg = ptr32(self.regs)
        spins = 0
        while (reg[0] & USART_ISR_TC) == 0:
            spins += 1
            if spins > TX_DRAIN_SPINS:
                return -1
        return 0

    # --- housekeeping (the board calls this every few ms, never per byte) --------------
    def housekeep(self):
        """Count a receive overflow; True if bytes arrived since the last call.

        Overflow: a full ring means the bytes after it are being lost (the USART
        FIFO holds 16 more); one count per time it is found full, however long it
        stays so. Traffic (for the LED): the USART sets ISR.IDLE when the line goes
        quiet after a burst and keeps it until it is cleared, so reading and
        clearing it here sees every burst that ended since the last call, however
        fast the main loop drained it; bytes still waiting count too (a burst still
        going on; or no stm module).
        """
        n = self.any()
        full = n >= RXBUF
        if full and not self._full:
            self.overflows += 1
        self._full = full
        isr = self._isr
        if isr is not None and stm.mem32[isr] & USART_ISR_IDLE:
            stm.mem32[self._icr] = USART_ICR_IDLECF
            return True
        return n > 0

    # --- hardware DE ---------------------------------------------------------------
    def hw_de(self, on, pre16, post16):
        """USART hardware DE on/off (DEAT/DEDT in 1/16 bit); False if not possible."""
        base = self.base
        if base is None:
            return False
        mem = stm.mem32
        cr1_addr = base + stm.USART_CR1
        cr3_addr = base + stm.USART_CR3
        isr_addr = base + stm.USART_ISR
        if not on:
            # Pin back to a plain output first so DE never floats high.
            self.de_pin.init(machine.Pin.OUT, value=0)
        t0 = ticks_ms()
        while not mem[isr_addr] & USART_ISR_TC and ticks_diff(ticks_ms(), t0) < 50:
            pass
        cr1 = mem[cr1_addr]
        mem[cr1_addr] = cr1 & ~USART_CR1_UE
        mem[cr3_addr] = cr3_with_de(mem[cr3_addr], on)
        mem[cr1_addr] = cr1_with_de_times(cr1, pre16, post16) | USART_CR1_UE
        if on:
            self.de_pin.init(machine.Pin.ALT, alt=self.de_af)
        self.hw = bool(on)
        return True
