"""The STM32H7_JIG hardware: the only module that imports machine, pyb and stm.

``Board`` implements the HAL of ``jig.app`` (docs/hal.md): two RS-485 ports on
USARTs, the jig's relays, inputs and LEDs, the watchdog and the parameter file on
the littlefs flash filesystem. The module also holds the boot-time pieces
main.py uses: mounting (and on a blank board formatting) the flash, the safe-boot
decision and the crash log.

Receive path, per port: the USART interrupt fills MicroPython's UART buffer
(``rxbuf``, sized for several maximum frames); at the end of every burst the
``IRQ_RXIDLE`` hard interrupt moves those bytes into a ``jig.ringbuf.RingBuffer``
with the arrival tick. The handler allocates nothing: it reads into one
preallocated scratch buffer through bound methods made once in ``__init__``. A
long burst without any idle gap is pumped from the main loop (``any``) with
interrupts off, so the UART buffer cannot fill unseen.

Driver enable: the DE pin of each port is the pin whose alternate function is the
USART's RTS/DE output, so the USART can drive DE itself (``hw_de``); otherwise the
pin is a plain output that ``jig.rs485`` raises and drops around ``write`` (which
on stm32 returns only after the last stop bit). /RE is tied to DE on the board.

Pin maps are data (``PROFILES``): the jig itself, and a NUCLEO-H743ZI running
stock MicroPython (``tools/flash.py deploy``), whose UART3 is the ST-LINK REPL.
"""

import os
import sys

import machine
import micropython

try:
    import stm
except ImportError:  # a port without the stm module: software DE only
    stm = None

from jig.compat import const, sleep_ms, sleep_us, ticks_diff, ticks_ms, ticks_us
from jig.params import FileFS
from jig.ringbuf import RingBuffer

# --- USART registers for RS-485 driver enable ----------------------------------------
# RM0433 (STM32H742/743/750/753 reference manual), chapter "Universal synchronous
# receiver transmitter (USART)/UART": functional description "RS485 driver enable"
# and the register descriptions of USART_CR1 and USART_CR3. DEM/DEP and DEAT/DEDT
# may only be written while CR1.UE = 0. Times are in 1/16 bit (oversampling by 16).
USART_CR1_UE = const(1 << 0)  # USART enable
USART_CR1_DEDT_SHIFT = const(16)  # DEDT[4:0], bits 20:16: DE de-assertion time
USART_CR1_DEAT_SHIFT = const(21)  # DEAT[4:0], bits 25:21: DE assertion time
USART_CR1_DEDT_MASK = const(0x1F << 16)
USART_CR1_DEAT_MASK = const(0x1F << 21)
USART_CR3_DEM = const(1 << 14)  # driver enable mode: DE on the RTS pin
USART_CR3_DEP = const(1 << 15)  # DE polarity: 0 = active high
USART_ISR_TC = const(1 << 6)  # transmission complete
DE_TIME_MAX = const(31)

RXBUF = const(4096)  # machine.UART buffer: 8 maximum frames on the wire
RING_SIZE = const(4096)  # jig.ringbuf between the IRQ and the main loop (power of 2)
SCRATCH = const(256)  # bytes moved per readinto in the IRQ handler
PUMP_AT = const(2048)  # UART buffer fill at which the main loop moves bytes itself
# write() waits at most this long for the transmitter to accept the first byte (it is
# idle after the previous write, which returned at transmit-complete). Reads never
# wait: the IRQ handler asks for exactly the bytes already buffered. timeout_char=0
# lets MicroPython apply its minimum (one character time + 2 ms) between bytes.
UART_TIMEOUT_MS = const(5)

WDT_MS = const(8000)  # > the worst-case flash sector erase of a parameter save
HOUSEKEEP_MS = const(10)
TRAFFIC_LED_MS = const(40)
ERROR_LED_MS = const(1000)
CLEAN_RUN_MS = const(60000)  # bridge uptime after which a crash streak is over
SAFE_AFTER_CRASHES = const(3)  # consecutive crashes that force safe boot

FLASH_MOUNT = "/flash"
PARAM_PATH = "/flash/jigparams.bin"
CRASH_PATH = "/flash/crash.txt"

MODE_BRIDGE = "bridge"
MODE_SAFE_BUTTON = "safe: SAFE button held at reset"
MODE_SAFE_CRASHES = "safe: the bridge crashed %d times in a row"

# Pin maps. Ports: (UART id, TX, RX, DE pin, DE alternate function). Inputs are
# (pin, active level, pull); outputs (relays) are active high. LEDs: heartbeat,
# traffic, error, active level.
PROFILES = (
    (
        "STM32H7_JIG",
        {
            "up": (2, "UP_TX", "UP_RX", "UP_DE", 7),  # J2 "PC": USART2, PD4 = USART2_DE (AF7)
            "down": (3, "DN_TX", "DN_RX", "DN_DE", 7),  # J3 "DRIVERS": USART3, PD12 = USART3_DE (AF7)
            "leds": ("LED_HB", "LED_TRAFFIC", "LED_ERR", 1),
            "safe": ("BTN_SAFE", 0, "up"),
            "inputs": (("IN1", 0, "up"), ("IN2", 0, "up"), ("IN3", 0, "up"), ("IN4", 0, "up"), ("BTN_SAFE", 0, "up")),
            "outputs": ("RLY1", "RLY2", "RLY3", "RLY4"),
        },
    ),
    (
        "NUCLEO_H743ZI",
        {
            "up": (2, "PD5", "PD6", "PD4", 7),  # CN9: USART2, PD4 = USART2_DE (AF7)
            "down": (6, "PC6", "PC7", "PG8", 7),  # CN7/CN12: USART6, PG8 = USART6_DE (AF7)
            "leds": ("PB0", "PB7", "PB14", 1),  # green, blue, red
            "safe": ("PC13", 1, None),  # blue USER button, pressed = high
            "inputs": (("PC13", 1, None),),
            "outputs": (),
        },
    ),
)


def machine_name():
    try:
        return os.uname().machine
    except (AttributeError, OSError):
        return ""


def profile_for(name):
    """The pin map whose key occurs in the machine name (the jig's map if none does)."""
    for key, prof in PROFILES:
        if key in name:
            return key, prof
    return PROFILES[0]


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


# --- one RS-485 port -----------------------------------------------------------------
class Port:
    """One half-duplex RS-485 port on a USART: the HAL port of docs/hal.md."""

    def __init__(self, spec, baud, traffic_led=None):
        uart_id, tx, rx, de_name, de_af = spec
        self.uart_id = uart_id
        self.baud = baud
        self.tx_blocks = True  # stm32 UART.write returns after transmit-complete
        self.hw = False
        self.de_name = de_name
        self.de_af = de_af
        self.base = usart_base(uart_id)
        self.ring = RingBuffer(RING_SIZE)
        self.de_pin = machine.Pin(de_name, machine.Pin.OUT, value=0)
        self.uart = machine.UART(
            uart_id, baudrate=baud, bits=8, parity=None, stop=1, rxbuf=RXBUF, timeout=UART_TIMEOUT_MS, timeout_char=0
        )
        self.pumps = 0  # bursts moved by the main loop instead of the IRQ
        self._scratch = bytearray(SCRATCH)
        # Bound methods made once: creating one per call would allocate in the IRQ.
        self._uart_any = self.uart.any
        self._uart_readinto = self.uart.readinto
        self._uart_write = self.uart.write
        self._ring_write = self.ring.write
        self._ring_read = self.ring.read_into
        self._de_value = self.de_pin.value
        self._led = traffic_led.value if traffic_led is not None else None
        self._irq = self._on_rx_idle
        self.uart.irq(self._irq, machine.UART.IRQ_RXIDLE, hard=True)

    def _on_rx_idle(self, _uart):
        """Hard IRQ at the end of a receive burst: UART buffer -> ring, no allocation."""
        now = ticks_us()
        scratch = self._scratch
        n = self._uart_any()
        while n > 0:
            k = self._uart_readinto(scratch, n if n < SCRATCH else SCRATCH)
            if not k:
                break
            self._ring_write(scratch, k, now)
            n -= k
        if self._led is not None:
            self._led(1)

    # HAL port interface ------------------------------------------------------------
    @property
    def t_last(self):
        return self.ring.t_last

    @property
    def overflows(self):
        return self.ring.overflows

    def any(self):
        if self._uart_any() >= PUMP_AT:
            # A burst long enough to half-fill the UART buffer without an idle gap.
            state = machine.disable_irq()
            try:
                self._on_rx_idle(None)
            finally:
                machine.enable_irq(state)
            self.pumps += 1
        return self.ring.any()

    def readinto(self, buf, n):
        return self._ring_read(buf, n)

    def write(self, buf, off, n):
        self._uart_write(buf, off, n)

    def de(self, v):
        if not self.hw:
            self._de_value(v)

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


# --- the board -------------------------------------------------------------------------
class Board:
    """The HAL of jig.app for the STM32H7_JIG board (or a NUCLEO-H743ZI)."""

    def __init__(self, name=None):
        self.name, self.profile = profile_for(machine_name() if name is None else name)
        p = self.profile
        self.ticks_us = ticks_us
        self.sleep_us = sleep_us
        self.fs = FileFS()
        self.param_path = PARAM_PATH
        hb, traffic, err, on = p["leds"]
        self.led_on = on
        self.led_hb = machine.Pin(hb, machine.Pin.OUT, value=1 - on)
        self.led_traffic = machine.Pin(traffic, machine.Pin.OUT, value=1 - on)
        self.led_err = machine.Pin(err, machine.Pin.OUT, value=1 - on)
        self.outputs = [machine.Pin(n, machine.Pin.OUT, value=0) for n in p["outputs"]]
        self.inputs = []
        self.input_active = []
        for pin_name, active, pull in p["inputs"]:
            self.inputs.append(_input_pin(pin_name, pull))
            self.input_active.append(active)
        self.out_mask = 0
        self.up = None
        self.down = None
        self.wdt = None
        self.t_start = ticks_ms()
        self.t_house = self.t_start
        self.t_error = 0
        self.error_on = False
        self.seen_overflows = 0
        self.streak_cleared = False

    def open(self, up_baud, down_baud):
        """Open both ports at the given baud rates (called once by jig.app.App)."""
        p = self.profile
        self.up = Port(p["up"], up_baud, self.led_traffic)
        self.down = Port(p["down"], down_baud, self.led_traffic)

    # jig I/O ------------------------------------------------------------------------
    def set_outputs(self, mask):
        mask &= (1 << len(self.outputs)) - 1
        for k in range(len(self.outputs)):
            self.outputs[k].value((mask >> k) & 1)
        self.out_mask = mask

    def get_outputs(self):
        return self.out_mask

    def get_inputs(self):
        v = 0
        for k in range(len(self.inputs)):
            if self.inputs[k].value() == self.input_active[k]:
                v |= 1 << k
        return v

    def heartbeat(self, on):
        self.led_hb.value(self.led_on if on else 1 - self.led_on)

    def error_led(self, on):
        self.led_err.value(self.led_on if on else 1 - self.led_on)

    # watchdog and per-loop housekeeping --------------------------------------------
    def wdt_feed(self):
        """Feed the watchdog (started on the first call) and run the LED housekeeping."""
        if self.wdt is None:
            self.wdt = machine.WDT(timeout=WDT_MS)
        self.wdt.feed()
        now = ticks_ms()
        if ticks_diff(now, self.t_house) < HOUSEKEEP_MS:
            return
        self.t_house = now
        self._housekeep(now)

    def _housekeep(self, now):
        up = self.up
        down = self.down
        if up is None:
            return
        us = ticks_us()
        if (
            ticks_diff(us, up.ring.t_last) > TRAFFIC_LED_MS * 1000
            and ticks_diff(us, down.ring.t_last) > TRAFFIC_LED_MS * 1000
        ):
            self.led_traffic.value(1 - self.led_on)
        ovf = up.ring.overflows + down.ring.overflows
        if ovf != self.seen_overflows:
            self.seen_overflows = ovf
            self.t_error = now
            self.error_on = True
            self.error_led(True)
        elif self.error_on and ticks_diff(now, self.t_error) > ERROR_LED_MS:
            self.error_on = False
            self.error_led(False)
        if not self.streak_cleared and ticks_diff(now, self.t_start) > CLEAN_RUN_MS:
            self.streak_cleared = True
            clear_crash_streak()

    def keep_watchdog_fed(self):
        """After the bridge stops (Ctrl-C): feed a running watchdog from a timer so the
        REPL stays usable. Returns the timer, or None if the watchdog never started."""
        if self.wdt is None:
            return None
        feed = self.wdt.feed

        def _feed(_t):
            feed()

        return machine.Timer(-1, mode=machine.Timer.PERIODIC, period=WDT_MS // 4, callback=_feed, hard=True)

    def crash_summary(self):
        """One line about recorded crashes (for a diagnostics frame); allocates."""
        return crash_summary()


def _input_pin(name, pull):
    if pull == "up":
        return machine.Pin(name, machine.Pin.IN, machine.Pin.PULL_UP)
    return machine.Pin(name, machine.Pin.IN)


# --- boot ------------------------------------------------------------------------------
def early_boot():
    """First thing main.py does: room for IRQ exception reports, flash mounted."""
    micropython.alloc_emergency_exception_buf(100)
    return mount_flash()


def _mounted(path):
    try:
        os.stat(path)
        return True
    except OSError:
        return False


def mount_flash():
    """Mount littlefs on the internal flash at /flash, formatting a blank/corrupt one.

    Returns "mounted", "formatted" or "none" (no usable flash filesystem).
    """
    if _mounted(FLASH_MOUNT):
        return "mounted"
    try:
        import pyb

        bdev = pyb.Flash(start=0)
    except (ImportError, AttributeError, TypeError, ValueError, OSError):
        return "none"
    result = "mounted"
    try:
        os.mount(os.VfsLfs2(bdev), FLASH_MOUNT)
    except OSError:
        try:
            os.VfsLfs2.mkfs(bdev)
            os.mount(os.VfsLfs2(bdev), FLASH_MOUNT)
        except OSError:
            return "none"  # no filesystem: parameters fall back to defaults
        result = "formatted"
    os.chdir(FLASH_MOUNT)
    for path in (FLASH_MOUNT, FLASH_MOUNT + "/lib"):
        if path not in sys.path:
            sys.path.append(path)
    return result


def safe_button_held(name=None, samples=5):
    """True if the SAFE button is pressed now (debounced over a few ms)."""
    _, prof = profile_for(machine_name() if name is None else name)
    pin_name, active, pull = prof["safe"]
    pin = _input_pin(pin_name, pull)
    sleep_ms(2)  # let the pull-up charge the line
    held = 0
    for _ in range(samples):
        if pin.value() == active:
            held += 1
        sleep_ms(1)
    return held == samples


def decide_boot(button_held, consecutive_crashes):
    """The boot mode: MODE_BRIDGE, or a MODE_SAFE_* reason string."""
    if button_held:
        return MODE_SAFE_BUTTON
    if consecutive_crashes >= SAFE_AFTER_CRASHES:
        return MODE_SAFE_CRASHES % consecutive_crashes
    return MODE_BRIDGE


# --- crash log -------------------------------------------------------------------------
# A small text file in flash: a header line of counts, then the last exception and
# the counters at the time. `mpremote fs cat :/flash/crash.txt` shows it.
CRASH_HEADER = "MotorJig crash log"
CRASH_KEYS = ("crashes", "consecutive", "wdt_resets")


def parse_crash_counts(text):
    """(crashes, consecutive, wdt_resets) from a crash log text (zeros if none)."""
    counts = [0, 0, 0]
    if text:
        for line in text.split("\n")[:4]:
            for part in line.split():
                if "=" in part:
                    k, v = part.split("=", 1)
                    if k in CRASH_KEYS:
                        try:
                            counts[CRASH_KEYS.index(k)] = int(v)
                        except ValueError:
                            pass
    return counts[0], counts[1], counts[2]


def format_crash_log(counts, what, trace, counters=(), uptime_ms=0):
    """The crash log text; counts = (crashes, consecutive, wdt_resets)."""
    lines = [CRASH_HEADER]
    lines.append(" ".join("%s=%d" % (CRASH_KEYS[i], counts[i]) for i in range(3)))
    lines.append("last: %s (after %d ms of bridge uptime)" % (what, uptime_ms))
    if trace:
        lines.append(trace.rstrip("\n"))
    if counters:
        lines.append("counters:")
        for name, value in counters:
            lines.append("  %s=%d" % (name, value))
    return "\n".join(lines) + "\n"


def read_crash_log(path=None):
    try:
        with open(path or CRASH_PATH) as f:
            return f.read()
    except OSError:
        return ""


def _write_text(path, text):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    try:
        os.rename(tmp, path)
    except OSError:
        try:
            os.remove(path)
        except OSError:
            pass
        os.rename(tmp, path)


def exception_text(exc):
    """Traceback text of exc on MicroPython or CPython."""
    try:
        import io

        buf = io.StringIO()
        if hasattr(sys, "print_exception"):
            sys.print_exception(exc, buf)
        else:
            import traceback

            traceback.print_exception(type(exc), exc, exc.__traceback__, file=buf)
        return buf.getvalue()
    except Exception:
        return repr(exc)


def record_crash(exc=None, counters=(), uptime_ms=0, what=None, path=None, wdt=False):
    """Append a crash (an exception, or a watchdog reset) to the log; never raises."""
    path = path or CRASH_PATH
    try:
        crashes, streak, wdt_resets = parse_crash_counts(read_crash_log(path))
        crashes += 1
        streak += 1
        if wdt:
            wdt_resets += 1
        if what is None:
            what = "watchdog reset" if exc is None else "%s: %s" % (type(exc).__name__, exc)
        trace = exception_text(exc) if exc is not None else ""
        _write_text(path, format_crash_log((crashes, streak, wdt_resets), what, trace, counters, uptime_ms))
        return crashes, streak, wdt_resets
    except Exception:
        return None


def clear_crash_streak(path=None):
    """The bridge ran cleanly for a while: zero the consecutive-crash count."""
    path = path or CRASH_PATH
    try:
        text = read_crash_log(path)
        crashes, streak, wdt_resets = parse_crash_counts(text)
        if streak == 0:
            return False
        lines = text.split("\n")
        lines[1] = " ".join("%s=%d" % (k, v) for k, v in zip(CRASH_KEYS, (crashes, 0, wdt_resets)))
        _write_text(path, "\n".join(lines))
        return True
    except Exception:
        return False


def crash_summary(path=None):
    """Header counts and the 'last:' line of the crash log as one short line."""
    text = read_crash_log(path)
    if not text:
        return "no crash recorded"
    lines = text.split("\n")
    return (lines[1] + "; " + lines[2])[:200] if len(lines) > 2 else lines[0]


def watchdog_reset_happened():
    """True if the last reset was the watchdog's."""
    try:
        return machine.reset_cause() == machine.WDT_RESET
    except AttributeError:
        return False
