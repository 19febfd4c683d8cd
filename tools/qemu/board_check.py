"""jig.board on real MicroPython with stand-in machine/stm modules (qemu suite part).

The qemu port has no UART or Pin for the jig, so small fakes replace ``machine``
and ``stm`` in ``sys.modules`` before ``jig.board`` is imported. What this checks
that the CPython host tests cannot:

* the receive-idle handler runs with the heap locked (``micropython.heap_lock``,
  exactly the state of a hard interrupt handler): any allocation would raise;
* its cost in instructions per burst on the emulated Cortex-M7;
* the DE register arithmetic with MicroPython's integers (addresses above 2**30
  are big ints there);
* crash-log text formatting with MicroPython's ``sys.print_exception``.

The fakes themselves allocate nothing per call (preallocated buffers, viper copy).
"""

import sys

import micropython

from jig.compat import ticks_diff, ticks_us
from memrx import MemRx


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
    IRQ_RXIDLE = 16
    last = None

    def __init__(self, uart_id, **kw):
        MemRx.__init__(self)
        self.handler = None
        _UART.last = self

    def irq(self, handler, trigger, hard=False):
        self.handler = handler

    def write(self, buf, off, n):
        return n


class _Mem32:
    def __init__(self):
        self.regs = {}

    def __getitem__(self, addr):
        return self.regs.get(addr, 0)

    def __setitem__(self, addr, value):
        self.regs[addr] = value & 0xFFFFFFFF


class _Namespace:
    """Stands in for a module (MicroPython cannot instantiate the module type)."""


def _fake_modules():
    machine = _Namespace()
    machine.Pin = _Pin
    machine.UART = _UART
    machine.disable_irq = lambda: 0
    machine.enable_irq = lambda s: None
    stm = _Namespace()
    stm.mem32 = _Mem32()
    stm.USART2 = 0x40004400
    stm.USART3 = 0x40004800
    stm.USART_CR1 = 0
    stm.USART_CR3 = 8
    stm.USART_ISR = 0x1C
    return machine, stm


def run(result, fail, instr):
    saved = {}
    for name in ("machine", "stm", "jig.board"):
        saved[name] = sys.modules.get(name)
    machine, stm = _fake_modules()
    sys.modules["machine"] = machine
    sys.modules["stm"] = stm
    sys.modules.pop("jig.board", None)
    try:
        from jig import board

        _check(board, machine, stm, result, fail, instr)
    finally:
        for name, mod in saved.items():
            if mod is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = mod


def _check(board, machine, stm, result, fail, instr):
    led = _Pin("LED_TRAFFIC", _Pin.OUT, value=0)
    port = board.Port((2, "UP_TX", "UP_RX", "UP_DE", 7), 115200, led)
    uart = _UART.last
    burst = bytearray(b"\xaa\xcc\x02\x40\x00\x00\x00\x00\x08\x04\xc6\xaa\xee" * 2)
    handler = uart.handler
    handler(uart)  # first call outside the lock (nothing to warm up, but fair)
    port.ring.clear()
    rounds = 50
    t0 = ticks_us()
    micropython.heap_lock()
    err = None
    try:
        for _ in range(rounds):
            uart.load(burst, len(burst))
            handler(uart)
            port.ring.clear()
    except MemoryError as e:
        err = e
    finally:
        micropython.heap_unlock()
    dt = ticks_diff(ticks_us(), t0)
    if err is not None:
        fail("board: the RX idle handler allocated with the heap locked (as in a hard IRQ)")
        return
    uart.load(burst, len(burst))
    handler(uart)
    out = bytearray(64)
    n = port.readinto(out, 64)
    if n != len(burst) or out[0:n] != burst or led.level != 1:
        fail("board: RX idle handler moved %d of %d bytes" % (n, len(burst)))
    result("board RX idle IRQ handler (heap locked, fake UART): %d instructions per %d-byte burst, no allocation"
           % (instr(dt) // rounds, len(burst)))

    # Hardware DE on MicroPython integers.
    base = stm.USART2
    stm.mem32.regs[base] = 0x2000000D
    stm.mem32.regs[base + 0x1C] = 0x40  # ISR.TC: the transmitter is idle
    if not port.hw_de(True, 5, 3):
        fail("board: hw_de refused with stm present")
    cr1 = stm.mem32.regs[base]
    cr3 = stm.mem32.regs[base + 8]
    if cr1 != (0x2000000D | (5 << 21) | (3 << 16)) or cr3 != (1 << 14):
        fail("board: DE registers CR1=0x%08x CR3=0x%08x" % (cr1, cr3))
    else:
        result("board DE registers on MicroPython ints: CR1=0x%08x CR3=0x%08x" % (cr1, cr3))

    # Crash-log text with MicroPython's traceback printer.
    try:
        raise ValueError("qemu check")
    except ValueError as e:
        text = board.format_crash_log((2, 1, 0), "ValueError: qemu check", board.exception_text(e), (("forwards", 3),))
    counts = board.parse_crash_counts(text)
    if counts != (2, 1, 0) or "ValueError: qemu check" not in text or "forwards=3" not in text:
        fail("board: crash log text %r" % text)
    if board.decide_boot(True, 0) != board.MODE_SAFE_BUTTON or board.decide_boot(False, 5) == board.MODE_BRIDGE:
        fail("board: safe-boot decision")
