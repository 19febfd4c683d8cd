"""The simulated HAL the real firmware (``jig.app.App``) runs on in the bench.

Implements docs/hal.md: two UART-like ports on simulated buses (receive ring
buffers filled as bytes arrive, ``write`` that blocks on the virtual timeline until
the last stop bit has left, ``queue``/``drain`` for a transmitter that sends
queued bytes while the CPU goes on), DE pins that record every transition with its time
stamp, LEDs/relays/buttons as integers, a watchdog counter and an in-memory
filesystem that can lose power in the middle of a write.

The ports are streaming receivers on their buses (see ``link``): bytes reach the
ring buffer one chunk at a time while a frame is still arriving, as the UART
interrupt would put them there. ``SimHAL.cpu_model`` (a ``cpumodel.CpuModel``, or a
tuple of its figures) charges the jig's CPU time on the virtual timeline: the first read that returns bytes in a main-loop pass advances
the clock by the per-pass cost, and every read by the per-byte cost times the
bytes it returned, so whatever the pass does with them (forwarding, answering)
happens that much later; each slow pass costs its share where it feeds the
watchdog, and each write that hands records to the capture port its own; an idle
pass is how late the loop sees a start bit (``SimIsr``: the USART's BUSY flag,
which the pump watches while idle). Bytes keep arriving meanwhile. Default
(``CpuModel()``): the CPU is infinitely fast.

The jig's I/O can be wired to a simulated drive (``SimBench(wiring=...)``):
``input_source`` adds bits to what ``get_inputs`` returns, computed when it is
read, and ``output_hooks`` run before the outputs (relays) change, so a drive
wired to them first catches up to the present with the relays as they were.

``SimHAL.capture`` is the jig's capture port (the board's second USB CDC port,
``jig.capture``): a device transmit buffer of ``CDC_TX_SIZE`` bytes that takes what
fits and nothing while no host has the port open, emptied by the host once per 1 ms
USB frame; the host's side (open, close, commands, what it has read) is for the
bench (``SimCapturePort``).

With a CAN bus (``SimHAL(can_bus=...)``) the HAL has the jig's CAN port
(docs/hal.md): ``can_open(bitrate, listen_only)`` (re)starts the one FDCAN1
controller, a ``canhal.SimCan`` on that bus, with ``set_filters(None)`` done, and
returns it; ``can_close(can)`` stops it; ``slcan`` is the third USB CDC port
(``canhal.SimSlcanPort``). Frames received, transmissions done and the host's
bytes on ``slcan`` wake the main loop like UART bytes do. Without a CAN bus the
HAL has no ``can_open`` attribute at all and ``slcan`` is None (a board without
the port, as old HALs).
"""

from jig.bridge import ISR_BUSY
from jig.ringbuf import RingBuffer
from .cpumodel import CpuModel
from .usbcdc import CDC_TX_SIZE, USB_FRAME_BYTES, USB_FRAME_US, SimCapturePort  # noqa: F401 (the HAL's ports)


class PowerLoss(Exception):
    """Raised by SimFS when the simulated supply fails during a write."""


class SimFS:
    """In-memory files. ``fail_after`` = n: the write that would pass byte n dies there."""

    def __init__(self):
        self.files = {}
        self.fail_after = None
        self.written = 0  # bytes written since fail_after was set
        self.replace_ok = True  # False: rename onto an existing file fails (FAT-like)

    def read_into(self, path, buf):
        data = self.files.get(path)
        if data is None:
            return -1
        n = min(len(data), len(buf))
        buf[0:n] = data[0:n]
        return n

    def _budget(self, n):
        if self.fail_after is None:
            return n
        left = self.fail_after - self.written
        return max(0, min(n, left))

    def write(self, path, buf, n):
        k = self._budget(n)
        self.files[path] = bytes(buf[0:k])
        self.written += k
        if k < n:
            raise PowerLoss()
        if self.fail_after is not None and self.written >= self.fail_after:
            raise PowerLoss()

    def rename(self, src, dst):
        if src not in self.files:
            raise OSError(2, "no such file")
        if dst in self.files and not self.replace_ok:
            raise OSError(17, "exists")
        self.files[dst] = self.files.pop(src)

    def remove(self, path):
        self.files.pop(path, None)


class SimIsr:
    """A port's USART ISR as the pump reads it (``isr[0]``): only BUSY (bit 16, a
    byte is being received) is modelled, set from the start bit of a transmission
    on the bus until its end, as the main loop sees it: ``SimPort.busy_delay``
    after the start bit (the USART confirms a start bit in half a bit; an idle pass
    of the loop may be under way)."""

    BUSY = ISR_BUSY

    def __init__(self, port):
        self.port = port

    def __getitem__(self, i):
        if i != 0:
            raise IndexError("SimIsr: only the ISR word (0) is modelled")
        p = self.port
        return self.BUSY if p.bus.receiving(p.node, p.busy_delay) else 0


class SimPort:
    """One jig UART + RS-485 transceiver on a simulated bus."""

    def __init__(self, hal, bus, name, rxsize=4096, echo=False, line_watch=True):
        self.hal = hal
        self.bus = bus
        self.node = bus.add_node(name, self._rx, echo=echo, record=hal.record, stream=True)
        self.ring = RingBuffer(rxsize)
        self.baud = bus.baud
        self.tx_blocks = True
        self.echo_free = not echo  # a receiver that hears our own transmission: echo
        # The jig's transceivers have /RE tied to DE: while the port drives its bus it hears
        # nobody (an echo port models a receiver that stays on)
        self.node.deaf_with_de = not echo
        self.t_last = 0
        self.writes = []  # (t_start, t_end, bytes) of every write, if hal.record
        # The USART's ISR.BUSY (SimIsr): the main loop sees a start bit half a bit after
        # it began plus an idle pass (SimHAL.cpu_model's fifth figure), and is woken then.
        self.isr = SimIsr(self) if line_watch else None
        self.busy_delay = 0.5e6 / self.baud + hal.us_per_idle_pass
        if line_watch:
            self.node.on_start = self._start

    @property
    def overflows(self):
        return self.ring.overflows

    def any(self):
        return self.ring.any()

    def readinto(self, buf, n):
        got = self.ring.read_into(buf, n)
        if got:
            self.hal.charge_cpu(got)
        return got

    def write(self, buf, off, n):
        clock = self.hal.clock
        if self.node.tx_until > clock.now:
            # stm32's UART.write (timeout 0) may refuse or interleave behind queued
            # bytes: the firmware drains first (jig.rs485), and the bench holds it to that.
            raise RuntimeError("%s: write while queued bytes are still going out" % self.node.name)
        self._transmit(buf, off, n)
        clock.run_until(self.node.tx_until)  # like stm32 UART.write: returns after transmit-complete

    def queue(self, buf, off, n):
        """Queue buf[off:off + n] for the transmitter and return at once (the USART's
        transmit FIFO; the bus sends each piece after the one before it)."""
        self._transmit(buf, off, n)
        return n

    def drain(self):
        """Return after the last stop bit of everything queued."""
        clock = self.hal.clock
        if self.node.tx_until > clock.now:
            clock.run_until(self.node.tx_until)
        return 0

    def _transmit(self, buf, off, n):
        data = bytes(buf[off : off + n])
        t0 = self.hal.clock.now
        end = self.bus.transmit(self.node, data)
        if self.hal.record:
            self.writes.append((max(t0, end - self.bus.bt * n), end, data))

    def de(self, v):
        self.node.set_de(v)

    def hw_de(self, on, pre16, post16):
        bit_us = 1e6 / self.baud
        self.node.hw_de = bool(on)
        self.node.hw_pre_us = pre16 * bit_us / 16
        self.node.hw_post_us = post16 * bit_us / 16
        return True

    def _start(self, seg):
        self.hal.clock.at(seg.t0 + self.busy_delay, self.hal.on_rx)

    def _rx(self, data, t):
        self.ring.write(data, len(data), int(t) & 0x3FFFFFFF)
        self.t_last = int(t) & 0x3FFFFFFF
        self.hal.on_rx()


class SimHAL:
    def __init__(self, clock, up_bus, down_bus, fs=None, param_path="/flash/jigparams.bin",
                 rxsize=4096, echo_up=False, echo_down=False, record=True, cpu_model=(0.0, 0.0),
                 capture_tx=CDC_TX_SIZE, can_bus=None, line_watch=True):
        self.clock = clock
        self.up_bus = up_bus
        self.down_bus = down_bus
        self.fs = fs if fs is not None else SimFS()
        self.param_path = param_path
        self.rxsize = rxsize
        self.echo_up = echo_up
        self.echo_down = echo_down
        self.record = record
        self.outputs = 0
        self.inputs = 0  # buttons; tests set it
        self.input_source = None  # fn() -> more input bits, read when the inputs are (the wiring)
        self.output_hooks = []  # fn() called before the outputs change
        self.wdt_feeds = 0
        self.beats = 0
        self.up = None
        self.down = None
        self.rx_callback = None  # the bench's "wake the main loop"
        model = CpuModel.of(cpu_model)
        self.cpu_model = model
        self.us_per_pass, self.us_per_byte, self.us_per_slow_pass = model.pass_us, model.byte_us, model.slow_pass_us
        self.us_per_idle_pass = model.idle_pass_us
        us_per_write = model.capture_write_us
        self.pass_charged = True  # set False by the bench at the start of each pass
        self.cpu_us = 0.0  # CPU time charged so far
        self.capture = SimCapturePort(clock, capture_tx)  # jig.capture's port (the second USB CDC)
        self.capture.cpu_us_per_write = us_per_write
        self.can_bus = can_bus
        self.line_watch = line_watch  # the ports show their USART's ISR.BUSY (SimIsr)
        self.can = None  # the FDCAN1 controller once opened (canhal.SimCan)
        self.slcan = None
        if can_bus is not None:
            from .canhal import SimSlcanPort

            self.slcan = SimSlcanPort(clock, capture_tx)  # the third USB CDC port
            self.slcan.cpu_us_per_write = us_per_write
            self.slcan.on_host_data = self.on_rx
            self.can_open = self._can_open
            self.can_close = self._can_close

    def _can_open(self, bitrate, listen_only):
        from .canhal import SimCan

        if self.can is None:
            self.can = SimCan(self.can_bus, name="jig-can")
            self.can.on_event = self.on_rx
        mode = SimCan.MODE_SILENT if listen_only else SimCan.MODE_NORMAL
        self.can.init(bitrate, mode)
        self.can.set_filters(None)
        return self.can

    def _can_close(self, can):
        can.deinit()

    def open(self, up_baud, down_baud):
        self.up_bus.set_baud(up_baud)
        self.down_bus.set_baud(down_baud)
        self.up = SimPort(self, self.up_bus, "jig-up", self.rxsize, self.echo_up, self.line_watch)
        self.down = SimPort(self, self.down_bus, "jig-down", self.rxsize, self.echo_down, self.line_watch)

    def ticks_us(self):
        return self.clock.ticks_us()

    def sleep_us(self, us):
        self.clock.run_until(self.clock.now + us)

    def set_outputs(self, mask):
        for fn in self.output_hooks:
            fn()
        self.outputs = mask

    def get_outputs(self):
        return self.outputs

    def get_inputs(self):
        if self.input_source is None:
            return self.inputs
        return self.inputs | self.input_source()

    def heartbeat(self, on):
        self.beats += 1

    def wdt_feed(self):
        """The app feeds the watchdog once per slow pass: the slow pass's CPU time."""
        self.wdt_feeds += 1
        if self.us_per_slow_pass:
            self.cpu_us += self.us_per_slow_pass
            self.clock.run_until(self.clock.now + self.us_per_slow_pass)

    def begin_pass(self):
        """Called by the bench before each main-loop pass (for ``cpu_model``)."""
        self.pass_charged = False

    def charge_cpu(self, nbytes):
        """The CPU time of handling nbytes just read: the virtual clock moves on."""
        dt = nbytes * self.us_per_byte
        if not self.pass_charged:
            self.pass_charged = True
            dt += self.us_per_pass
        if dt > 0:
            self.cpu_us += dt
            self.clock.run_until(self.clock.now + dt)

    def on_rx(self):
        if self.rx_callback is not None:
            self.rx_callback()
