"""jig.uartport and jig.board on real MicroPython with stand-in machine/stm modules.

Part of the qemu suite. The qemu port has no UART or Pin for the jig, so small
fakes replace ``machine`` and ``stm`` in ``sys.modules`` before the board
modules are imported. What this checks that the CPython host tests cannot:

* the port's ``any()``, ``readinto()`` and ``write()`` -- the calls the main loop
  makes -- run with the heap locked (``micropython.heap_lock``): any allocation
  would raise; and what one call costs in instructions on the emulated
  Cortex-M7. Two stand-in UARTs: one written in Python (MemRx, its own body
  counts), and one whose methods are C stream methods of ``io.BytesIO``, bound
  to the port exactly as ``machine.UART``'s are on the board: that figure is
  the nearer estimate of the board's (the board's C bodies do about as little);
* the board's housekeeping (traffic LED from the USART idle flag, overflow
  check, error LED) with the heap locked, and its cost per pass;
* the port's transmit FIFO calls (``queue``/``drain``: viper on the USART's
  ISR/TDR) compiled for the M7 and run against a register block in RAM: bytes
  land in TDR, a full FIFO or a stopped transmitter ends the wait, nothing
  allocates, and what a call costs;
* the DE register arithmetic with MicroPython's integers (addresses above 2**30
  are big ints there);
* crash-log text formatting with MicroPython's ``sys.print_exception``, and the
  safe-boot decision.
"""

import io
import sys

import micropython

from jig.compat import ticks_diff, ticks_ms, ticks_us
from memrx import MemRx

CALLS = 500  # per timed loop: 1 instruction per call resolution (1 µs = 1 000)
CHUNK = 8  # bytes per readinto / write call


class _Pin:
    OUT = 1
    IN = 0
    ALT = 2
    PULL_UP = 1

    def __init__(self, name, mode=0, pull=None, value=None, alt=None):
        self.name = name
        self.mode = mode
        self.alt = alt
        self.level = 0 if value is None else value

    def init(self, mode=0, pull=None, value=None, alt=None):
        self.mode = mode
        self.alt = alt
        if value is not None:
            self.level = value

    def value(self, v=None):
        if v is None:
            return self.level
        self.level = v


class _UART(MemRx):
    """machine.UART stand-in written in Python (nothing allocates per call)."""

    last = None
    make_c = False  # the next UART made gets C stream methods (see _use_c_methods)

    def __init__(self, uart_id, **kw):
        MemRx.__init__(self)
        self.kw = kw
        self.irqs = 0
        if _UART.make_c:
            _use_c_methods(self)
        _UART.last = self

    def irq(self, *args, **kw):
        self.irqs += 1

    def write(self, buf, off, n):
        return n


def _use_c_methods(uart):
    """any/readinto/write as C methods of io.BytesIO, as instance attributes: the
    port binds them like machine.UART's own. The receive stream holds enough
    bytes for every timed read; the transmit stream is overwritten in place."""
    rx = io.BytesIO(bytes(CALLS * CHUNK * 2))
    tx = io.BytesIO(bytearray(CALLS * CHUNK * 2))
    tx.write(b"\x00")  # first write copies the initial buffer: outside the lock
    tx.seek(0)
    uart.any = rx.tell  # a C method without arguments returning a small int
    uart.readinto = rx.readinto
    uart.write = tx.write
    uart.c_rx = rx
    uart.c_tx = tx


class _Namespace:
    """Stands in for a module (MicroPython cannot instantiate the module type)."""


def _fake_modules():
    machine = _Namespace()
    machine.Pin = _Pin
    machine.UART = _UART
    stm = _Namespace()
    stm.USART2 = 0x40004400
    stm.USART3 = 0x40004800
    stm.USART_CR1 = 0
    stm.USART_CR3 = 8
    stm.USART_ISR = 0x1C
    stm.USART_ICR = 0x20
    # stm.mem32 as a dict keyed by address: indexing is C, as on the board, and
    # every register exists before the heap is locked (a new key would allocate).
    # The addresses are above 2**30: big ints here, as on the board.
    stm.mem32 = {}
    for base in (stm.USART2, stm.USART3):
        for off in (stm.USART_CR1, stm.USART_CR3, stm.USART_ISR, stm.USART_ICR):
            stm.mem32[base + off] = 0
    return machine, stm


def run(result, fail, instr):
    """Run the checks; return what the board's HAL calls cost (instructions per call:
    any, readinto, write, queue of 1 byte, queue of CHUNK bytes, CHUNK, drain) where
    measured, else None."""
    saved = {}
    names = ("machine", "stm", "jig.uartport", "jig.board")
    for name in names:
        saved[name] = sys.modules.get(name)
    machine, stm = _fake_modules()
    sys.modules["machine"] = machine
    sys.modules["stm"] = stm
    sys.modules.pop("jig.uartport", None)
    sys.modules.pop("jig.board", None)
    try:
        from jig import board, crashlog, safeboot, uartport

        return _check(uartport, board, crashlog, safeboot, stm, result, fail, instr)
    finally:
        for name, mod in saved.items():
            if mod is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = mod


# --- timed loops (each call site as the app has it) -----------------------------------
def _loop_empty(n):
    for _ in range(n):
        pass


def _loop_any_attr(port, n):
    for _ in range(n):
        port.any()


def _loop_call0(f, n):
    for _ in range(n):
        f()


def _loop_read(f, buf, n):
    for _ in range(n):
        f(buf, CHUNK)


def _loop_write(f, buf, n):
    for _ in range(n):
        f(buf, 0, CHUNK)


def _loop_write1(f, buf, n):
    for _ in range(n):
        f(buf, 0, 1)


def _loop_housekeep(b, now, n):
    for _ in range(n):
        b.housekeep(now)


def _locked(fn, *args):
    """Instructions fn(*args) took with the heap locked, or -1 if it allocated."""
    micropython.heap_lock()
    try:
        t0 = ticks_us()
        fn(*args)
        dt = ticks_diff(ticks_us(), t0)
    except MemoryError:
        dt = -1
    finally:
        micropython.heap_unlock()
    return dt


def _port_costs(port, rewind, fail, instr, what):
    """Per-call instructions of any() (as port.any() and pre-bound), readinto and
    write on port, loop overhead subtracted; None if something allocated."""
    buf = bytearray(64)
    rewind()
    base = _locked(_loop_empty, CALLS)
    times = (
        _locked(_loop_any_attr, port, CALLS),
        _locked(_loop_call0, port.any, CALLS),
        _locked(_loop_read, port.readinto, buf, CALLS),
        _locked(_loop_write, port.write, buf, CALLS),
    )
    if base < 0 or min(times) < 0:
        fail("board: a port call allocated with the heap locked (%s)" % what)
        return None
    return [instr(t - base) // CALLS for t in times]


def _check(uartport, board, crashlog, safeboot, stm, result, fail, instr):
    prices = None
    # 1. The port calls on a Python stand-in UART.
    port = uartport.UartPort((2, "UP_TX", "UP_RX", "UP_DE", 7), 115200, True)
    uart = port.uart
    if uart.irqs:
        fail("board: the port installed a UART IRQ handler")
    if uart.kw.get("rxbuf") != uartport.RXBUF or uart.kw.get("timeout") != 0:
        fail("board: UART opened with %r" % (uart.kw,))
    burst = bytearray(b"\xaa\xcc\x02\x40\x00\x00\x00\x00\x08\x04\xc6\xaa\xee")
    uart.load(burst, len(burst))
    out = bytearray(64)
    n = port.any()
    got = port.readinto(out, n)
    if n != len(burst) or got != n or out[0:n] != burst:
        fail("board: port read %r of %d waiting bytes" % (got, n))
    uart.rx = bytearray(CALLS * CHUNK)  # every timed read gets CHUNK bytes

    def rewind_py():
        uart.rx_n = CALLS * CHUNK
        uart.rx_pos = 0

    py = _port_costs(port, rewind_py, fail, instr, "Python stand-in UART")
    if py is not None and uart.rx_pos != CALLS * CHUNK:
        fail("board: Python stand-in read %d bytes, expected %d" % (uart.rx_pos, CALLS * CHUNK))

    # 2. The same calls bound to C stream methods, as machine.UART's are.
    _UART.make_c = True
    try:
        cport = uartport.UartPort((3, "DN_TX", "DN_RX", "DN_DE", 7), 115200, True)
    finally:
        _UART.make_c = False
    cu = cport.uart

    def rewind_c():
        cu.c_rx.seek(0)
        cu.c_tx.seek(0)

    c = _port_costs(cport, rewind_c, fail, instr, "C stream methods")
    if c is not None and (cu.c_tx.tell() != CALLS * CHUNK or cu.c_rx.tell() != CALLS * CHUNK):
        fail("board: C-method reads/writes moved %d/%d bytes, expected %d"
             % (cu.c_rx.tell(), cu.c_tx.tell(), CALLS * CHUNK))
    if py is not None and c is not None:
        result("board port calls (heap locked, no allocation), instructions per call -- C-method stand-in "
               "(as machine.UART on the board): port.any() %d, pre-bound any() %d, readinto(buf, %d) %d, "
               "write(buf, 0, %d) %d; Python stand-in UART: %d, %d, %d, %d"
               % (c[0], c[1], CHUNK, c[2], CHUNK, c[3], py[0], py[1], py[2], py[3]))

    # 3. Board housekeeping: traffic LED from the idle flag, overflow check, LEDs;
    # the ports' UARTs have C methods (any() is the position of their rx stream).
    b = board.Board("STM32H7_JIG")
    _UART.make_c = True
    try:
        b.open(115200, 115200)
    finally:
        _UART.make_c = False
    b.streak_cleared = True  # no flash write in this check
    isr = b.up._isr
    icr = b.up._icr
    stm.mem32[isr] = uartport.USART_ISR_IDLE  # a burst ended on the PC bus
    now = ticks_ms()
    b.housekeep(now)
    if b.led_traffic.level != 1 or stm.mem32[icr] != uartport.USART_ICR_IDLECF:
        fail("board: the idle flag did not light the traffic LED / was not cleared")
    b.down.uart.c_rx.seek(uartport.RXBUF)  # the driver-bus ring holds RXBUF bytes: full
    dt = _locked(_loop_housekeep, b, now, 1)
    if dt < 0:
        fail("board: housekeeping allocated with the heap locked")
    elif b.down.overflows != 1 or b.up.overflows != 0 or b.led_err.level != 1:
        fail("board: a full ring gave %d/%d overflows, error LED %d"
             % (b.down.overflows, b.up.overflows, b.led_err.level))
    dt = _locked(_loop_housekeep, b, now, 100)
    if dt < 0:
        fail("board: housekeeping allocated with the heap locked")
    elif b.down.overflows != 1:
        fail("board: a ring that stays full was counted %d times" % b.down.overflows)
    else:
        result("board housekeeping (idle flags, overflow check, LEDs unchanged; C-method UARTs; heap locked): "
               "%d instructions per pass, at most every %d ms from wdt_feed" % (instr(dt) // 100, board.HOUSEKEEP_MS))

    # 4. The transmit FIFO calls on a register block in RAM: word 0 = ISR, word 3 = TDR.
    regs = bytearray(16)
    isr_ok = uartport.USART_ISR_TXFNF | uartport.USART_ISR_TC
    regs[0] = isr_ok
    port.regs = regs
    queue = port.queue
    drain = port.drain
    data = bytearray(b"\xaa\xcc\x02\x40\x08\x04\xaa\xee")
    sent = bytearray()
    for i in range(len(data)):
        if queue(data, i, 1) != 1:
            fail("board: queue refused a byte with room in the FIFO")
        sent.append(regs[12])
    if sent != data:
        fail("board: queue put %r into TDR, expected %r" % (bytes(sent), bytes(data)))
    if drain() != 0:
        fail("board: drain with ISR.TC set did not return 0")
    dq = _locked(_loop_write, queue, data, CALLS)
    dq1 = _locked(_loop_write1, queue, data, CALLS)
    dd = _locked(_loop_call0, drain, CALLS)
    base_loop = _locked(_loop_empty, CALLS)
    if dq < 0 or dq1 < 0 or dd < 0:
        fail("board: queue/drain allocated with the heap locked")
    regs[0] = uartport.USART_ISR_TC  # FIFO full: nothing may go in
    stuck_q = queue(data, 0, 4)
    regs[0] = uartport.USART_ISR_TXFNF  # bytes never finish
    stuck_d = drain()
    if stuck_q != 0 or stuck_d != -1:
        fail("board: a stopped transmitter gave queue %d (expected 0), drain %d (expected -1)"
             % (stuck_q, stuck_d))
    elif dq >= 0 and dq1 >= 0 and dd >= 0:
        q8 = instr(dq - base_loop) // CALLS
        q1 = instr(dq1 - base_loop) // CALLS
        qd = instr(dd - base_loop) // CALLS
        result("board transmit FIFO (viper on ISR/TDR, register block in RAM, heap locked): "
               "queue(buf, 0, 1) %d, queue(buf, 0, %d) %d, drain() %d instructions per call; a full "
               "FIFO / stopped transmitter ends the wait (queue 0, drain -1)" % (q1, CHUNK, q8, qd))
        if c is not None:
            prices = (c[1], c[2], c[3], q1, q8, CHUNK, qd)

    # 5. Hardware DE on MicroPython integers.
    base = stm.USART2
    stm.mem32[base] = 0x2000000D
    stm.mem32[base + 0x1C] = 0x40  # ISR.TC: the transmitter is idle
    if not port.hw_de(True, 5, 3):
        fail("board: hw_de refused with stm present")
    cr1 = stm.mem32[base]
    cr3 = stm.mem32[base + 8]
    if cr1 != (0x2000000D | (5 << 21) | (3 << 16)) or cr3 != (1 << 14):
        fail("board: DE registers CR1=0x%08x CR3=0x%08x" % (cr1, cr3))
    else:
        result("board DE registers on MicroPython ints: CR1=0x%08x CR3=0x%08x" % (cr1, cr3))

    # 6. Crash-log text with MicroPython's traceback printer; the boot decision.
    try:
        raise ValueError("qemu check")
    except ValueError as e:
        text = crashlog.format_crash_log(
            (2, 1, 0), "ValueError: qemu check", crashlog.exception_text(e), (("forwards", 3),)
        )
    counts = crashlog.parse_crash_counts(text)
    if counts != (2, 1, 0) or "ValueError: qemu check" not in text or "forwards=3" not in text:
        fail("board: crash log text %r" % text)
    elif "Traceback" not in text:
        fail("board: no traceback in the crash log text")
    else:
        result("board crash log text with MicroPython's print_exception: %d lines, counts %r"
               % (text.count("\n"), counts))
    if (safeboot.decide_boot(True, 0) != safeboot.MODE_SAFE_BUTTON
            or safeboot.decide_boot(False, 5) == safeboot.MODE_BRIDGE):
        fail("board: safe-boot decision")
    return prices
