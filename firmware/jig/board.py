"""The STM32H7_JIG board: the HAL of ``jig.app`` (docs/hal.md) on real hardware.

``Board`` opens the two RS-485 ports (``jig.uartport``, the one other module that
touches the hardware modules), drives the relays, reads the inputs and the SAFE
button, lights the LEDs and keeps the watchdog. Housekeeping -- the traffic and
error LEDs, the receive-overflow check, clearing the crash streak after a clean
minute -- runs from ``wdt_feed``, which the app calls from its slow pass (every
few ms), never per byte.

The boot helpers main.py uses that need the hardware live here too: the flash
block device, the SAFE button pin, the reset cause. The pure parts of boot are in
``jig.flashfs`` (mount/format), ``jig.safeboot`` (the decision) and
``jig.crashlog`` (the crash log text).

Pin maps are data (``PROFILES``): the jig itself, and a NUCLEO-H743ZI running
stock MicroPython (``tools/flash.py deploy``), whose UART3 is the ST-LINK REPL.

The CAN port: FDCAN1 (PD1 TX / PD0 RX, AF9, on both profiles as upstream's
NUCLEO_H743ZI board has it; the image names it "FDCAN1" in mpconfigboard.h) through
``machine.CAN`` (``can_open`` / ``can_close``), and the third USB CDC port
(``slcan``) where the host speaks SLCAN to it (``jig.canport``). Either is None where
the build lacks it (no ``machine.CAN``, fewer CDC ports): the bridge runs without.
"""

import os

import machine
import micropython

from jig import crashlog, flashfs
from jig.compat import const, sleep_us, ticks_add, ticks_diff, ticks_ms, ticks_us
from jig.params import FileFS
from jig.safeboot import CLEAN_RUN_MS
from jig.uartport import UartPort

WDT_MS = const(8000)  # > the worst-case flash sector erase of a parameter save
HOUSEKEEP_MS = const(10)  # at most this often, from wdt_feed
TRAFFIC_LED_MS = const(40)  # the traffic LED stays on this long after the last burst
ERROR_LED_MS = const(1000)  # and the error LED after a receive overflow

PARAM_PATH = flashfs.FLASH_MOUNT + "/jigparams.bin"

# Pin maps. Ports: (UART id, TX, RX, DE pin, DE alternate function); "echo_free":
# /RE is tied to DE on both transceivers, so a port hears no echo of its own
# transmission. Inputs are (pin, active level, pull); outputs (relays) are active
# high. LEDs: heartbeat, traffic, error, active level.
PROFILES = (
    (
        "STM32H7_JIG",
        {
            "up": (2, "UP_TX", "UP_RX", "UP_DE", 7),  # J2 "PC": USART2, PD4 = USART2_DE (AF7)
            "down": (3, "DN_TX", "DN_RX", "DN_DE", 7),  # J3 "DRIVERS": USART3, PD12 = USART3_DE (AF7)
            "echo_free": True,
            "leds": ("LED_HB", "LED_TRAFFIC", "LED_ERR", 1),
            "safe": ("BTN_SAFE", 0, "up"),
            "inputs": (("IN1", 0, "up"), ("IN2", 0, "up"), ("IN3", 0, "up"), ("IN4", 0, "up"), ("BTN_SAFE", 0, "up")),
            "outputs": ("RLY1", "RLY2", "RLY3", "RLY4"),
            "can": 1,  # J4 "CAN": FDCAN1, PD1 TX / PD0 RX (AF9), 3.3 V transceiver
        },
    ),
    (
        "NUCLEO_H743ZI",
        {
            "up": (2, "PD5", "PD6", "PD4", 7),  # CN9: USART2, PD4 = USART2_DE (AF7)
            "down": (6, "PC6", "PC7", "PG8", 7),  # CN7/CN12: USART6, PG8 = USART6_DE (AF7)
            "echo_free": False,  # whatever transceiver is wired on: echo is checked for
            "leds": ("PB0", "PB7", "PB14", 1),  # green, blue, red
            "safe": ("PC13", 1, None),  # blue USER button, pressed = high
            "inputs": (("PC13", 1, None),),
            "outputs": (),
            "can": 1,  # FDCAN1 on PD1 TX / PD0 RX (CN9), a 3.3 V transceiver wired on
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


def input_pin(name, pull):
    if pull == "up":
        return machine.Pin(name, machine.Pin.IN, machine.Pin.PULL_UP)
    return machine.Pin(name, machine.Pin.IN)


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
            self.inputs.append(input_pin(pin_name, pull))
            self.input_active.append(active)
        self.out_mask = 0
        self.up = None
        self.down = None
        self.wdt = None
        self.t_start = ticks_ms()
        # Uptime past ticks_ms' range: ticks_diff spans +-2**29 ms (6.2 days) and a jig
        # runs for weeks. The housekeeping moves whole seconds into up_s (a small int
        # for 34 years, so nothing is allocated); t_up is the tick they were counted to.
        self.up_s = 0
        self.t_up = self.t_start
        self.t_house = self.t_start
        self.t_traffic = self.t_start
        self.traffic_on = False
        self.t_error = 0
        self.error_on = False
        self.seen_overflows = 0
        self.streak_cleared = False
        self.capture = self._usb_port(1)
        self.slcan = self._usb_port(2)

    def open(self, up_baud, down_baud):
        """Open both ports at the given baud rates (called once by jig.app.App)."""
        p = self.profile
        self.up = UartPort(p["up"], up_baud, p["echo_free"])
        self.down = UartPort(p["down"], down_baud, p["echo_free"])

    # the capture and SLCAN ports ------------------------------------------------------
    def _usb_port(self, index):
        """A USB CDC port after the REPL (jigusb.py selects three): 1 is the HAL's
        ``capture``, 2 its ``slcan``. ``USB_VCP(index)`` with CTS flow control, so a
        write takes only what fits in its buffer and nothing while no PC has the
        port open -- it never blocks the bridge. None where the build has fewer CDC
        ports or no pyb module."""
        try:
            import pyb

            vcp = pyb.USB_VCP(index)
            vcp.init(flow=pyb.USB_VCP.CTS)
            return vcp
        except (ImportError, AttributeError, ValueError, OSError, TypeError):
            return None

    # the CAN port ------------------------------------------------------------------------
    def can_open(self, bitrate, listen_only):
        """FDCAN1 at bitrate, normal or listen-only (MODE_SILENT), receiving every
        frame; None where the build has no machine.CAN or refuses the bitrate."""
        cls = getattr(machine, "CAN", None)
        index = self.profile.get("can")
        if cls is None or index is None:
            return None
        try:
            can = cls(index, bitrate, mode=cls.MODE_SILENT if listen_only else cls.MODE_NORMAL)
            can.set_filters(None)  # (v1.28: None = receive every frame)
        except (ValueError, OSError, TypeError):
            return None
        return can

    def can_close(self, can):
        try:
            can.deinit()
        except OSError:
            pass

    def unique_id(self):
        """The MCU's 96-bit unique id (the SLCAN serial number is folded from it)."""
        return machine.unique_id()

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

    def traffic_led(self, on):
        self.led_traffic.value(self.led_on if on else 1 - self.led_on)

    # watchdog and housekeeping ------------------------------------------------------
    def wdt_feed(self):
        """Feed the watchdog (started on the first call) and run the housekeeping.

        Called by the app's slow pass, at least every few ms and not per byte.
        """
        if self.wdt is None:
            self.wdt = machine.WDT(timeout=WDT_MS)
        self.wdt.feed()
        now = ticks_ms()
        if ticks_diff(now, self.t_house) < HOUSEKEEP_MS:
            return
        self.t_house = now
        self.housekeep(now)

    def housekeep(self, now):
        """LEDs, overflow counts, the crash streak and the uptime; allocates nothing."""
        d = ticks_diff(now, self.t_up)
        if d >= 1000:
            self.up_s += d // 1000
            self.t_up = ticks_add(self.t_up, d - d % 1000)
        up = self.up
        down = self.down
        if up is None:
            return
        # Both ports are asked every time: each call clears that port's idle flag.
        seen_up = up.housekeep()
        seen_down = down.housekeep()
        if seen_up or seen_down:
            self.t_traffic = now
            if not self.traffic_on:
                self.traffic_on = True
                self.traffic_led(True)
        elif self.traffic_on and ticks_diff(now, self.t_traffic) > TRAFFIC_LED_MS:
            self.traffic_on = False
            self.traffic_led(False)
        ovf = up.overflows + down.overflows
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
            crashlog.clear_crash_streak()

    def uptime_ms(self):
        """ms since the HAL was made (main.py starts the bridge right after), right
        after weeks too (for the crash log; may allocate: a long int past 12.4 days)."""
        return self.up_s * 1000 + ticks_diff(ticks_ms(), self.t_up)

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
        return crashlog.crash_summary()


# --- boot helpers that need the hardware (main.py) ------------------------------------
def early_boot():
    """First thing main.py does: room for IRQ exception reports, flash mounted.

    Returns what jig.flashfs.mount_flash returns ("mounted", "formatted", "none").
    """
    micropython.alloc_emergency_exception_buf(100)  # the Ctrl-C watchdog timer is a hard IRQ
    if flashfs.is_mounted():
        return "mounted"
    return flashfs.mount_flash(flash_device())


def flash_device():
    """The internal flash after the firmware as a block device, or None."""
    try:
        import pyb

        return pyb.Flash(start=0)
    except (ImportError, AttributeError, TypeError, ValueError, OSError):
        return None


def safe_button(name=None):
    """(pin, active level) of the SAFE button, for jig.safeboot.button_held."""
    _, prof = profile_for(machine_name() if name is None else name)
    pin_name, active, pull = prof["safe"]
    return input_pin(pin_name, pull), active


def watchdog_reset_happened():
    """True if the last reset was the watchdog's."""
    try:
        return machine.reset_cause() == machine.WDT_RESET
    except AttributeError:
        return False
