"""The jig's CAN hardware on the bench: ``SimCan`` (machine.CAN) and ``SimSlcanPort``.

``SimCan`` has exactly the API of MicroPython v1.28's ``machine.CAN`` on the stm32
FDCAN (the constants, ``init``/``deinit``, ``set_filters``, ``send``, ``recv``,
``irq``, ``state``, ``get_counters``, ``restart``, ``cancel_send``) on a node of a
``canbus.CanBus``. What it does as the port does (extmod/machine_can.c and
ports/stm32/machine_can.c):

* ``send`` puts the frame into the first free of ``TX_QUEUE_LEN`` transmit buffers
  and returns its index, or None when all are taken or when a frame with the same
  numeric id (standard or extended alike) is queued and ``FLAG_UNORDERED`` is not
  given; the bus sends the queued frames by priority (lowest id first), not in
  the order queued. OSError when not initialised or bus-off; a listen-only
  controller (``MODE_SILENT``) takes the frame but never sends it, as FDCAN's bus
  monitoring mode. ValueError for an id out of range, OverflowError for more than
  8 bytes; with ``FLAG_RTR`` the data's length is the DLC.
* Received frames go into an RX FIFO of ``RX_FIFO_LEN`` (64) frames once
  ``set_filters`` has been called (``None``: all; ``()``: none; or (id, mask,
  flags) filters). A full FIFO sets ``RECV_ERR_FULL``, a frame lost to it
  ``RECV_ERR_OVERRUN`` (and counts an overrun); ``recv`` reports and clears both.
* ``recv(lst)``: lst = [0, memoryview(bytearray(8)), 0, 0]. MicroPython resizes
  the memoryview in lst[1] in place; a CPython memoryview cannot be resized, so
  the bench writes the data into the buffer lst[1] views (``lst[1].obj``, from
  its start) and puts ``memoryview(buffer)[:dlc]`` into lst[1]: read lst[1] after
  each call, never keep the old view. A remote frame's data is DLC zero bytes.
* ``irq(handler, trigger, hard)``: the handler is called synchronously, as a hard
  IRQ, with the SimCan as argument, on a frame stored in the FIFO (IRQ_RX), a
  transmission finished (IRQ_TX) and a more severe error state (IRQ_STATE: warning
  from active, passive, bus-off). ``irq().flags()`` as on stm32: IRQ_STATE once per
  change, IRQ_RX while the FIFO holds frames, and one finished transmission per
  call (``index << IRQ_TX_IDX_SHIFT | IRQ_TX [| IRQ_TX_FAILED]``); call it until it
  returns 0. With IRQ_TX triggered, a transmit buffer is free again only once
  ``flags()`` has reported it.
* ``restart`` cancels every queued frame (no IRQ_TX for them), zeroes the state
  entry counters and overruns, and leaves bus-off after 128 x 11 bit times.
  ``init`` at another bitrate than the bus's: a controller that cannot talk to
  the others (its frames are errors: it goes bus-off).

``on_event`` (the bench's "wake the main loop") is called after each interrupt.

``SimSlcanPort`` is the jig's third USB CDC port, where the host speaks SLCAN: the
same device and host sides as ``hal.SimCapturePort`` (``any``/``readinto``/
``write`` that takes what fits now, never blocks and takes nothing while the host
has the port closed; ``host_open``/``host_send``/``host_read``/``host_close``).
Full-speed USB both ways: the host takes the transmit buffer once per 1 ms USB
frame, and what it sends reaches the device in the next frame (up to
``USB_FRAME_BYTES`` a frame, and no more than the device's ``CDC_RX_SIZE``-byte
receive buffer has room for: the host's OUT packets are NAKed meanwhile). Bytes
arriving from the host call ``on_host_data`` (the bench wakes the jig).
"""

import errno

from .canbus import STATE_ACTIVE, STATE_BUS_OFF, STATE_PASSIVE, STATE_WARNING
from .usbcdc import CDC_TX_SIZE, SimCapturePort

RX_FIFO_LEN = 64  # FDCAN's RX FIFO 0 as MicroPython configures it on the H7
CDC_RX_SIZE = 1024  # MicroPython stm32's USB CDC receive buffer (MICROPY_HW_USB_CDC_RX_DATA_SIZE)


class SimCanIrq:
    """What ``SimCan.irq()`` returns."""

    def __init__(self, can):
        self._can = can

    def flags(self):
        return self._can._irq_flags()

    def trigger(self, new=None):
        if new is not None:
            self._can._trigger = new
        return self._can._trigger


class SimCan:
    FLAG_RTR = 1
    FLAG_EXT_ID = 2
    FLAG_UNORDERED = 16
    IRQ_TX = 1
    IRQ_RX = 2
    IRQ_TX_FAILED = 4
    IRQ_STATE = 8
    IRQ_TX_IDX_SHIFT = 16
    IRQ_TX_IDX_MASK = 0xFF
    STATE_STOPPED = 0
    STATE_ACTIVE = STATE_ACTIVE
    STATE_WARNING = STATE_WARNING
    STATE_PASSIVE = STATE_PASSIVE
    STATE_BUS_OFF = STATE_BUS_OFF
    MODE_NORMAL = 0
    MODE_SLEEP = 1
    MODE_LOOPBACK = 2
    MODE_SILENT = 3
    MODE_SILENT_LOOPBACK = 4
    RECV_ERR_FULL = 1
    RECV_ERR_OVERRUN = 2
    TX_QUEUE_LEN = 16
    FILTERS_MAX = 28

    def __init__(self, bus, bitrate=None, mode=0, sample_point=75, name="jig-can", rx_fifo=RX_FIFO_LEN):
        self.bus = bus
        self.node = bus.add_node(name, self._on_frame, self._on_tx_done)
        self.node.on_state = self._on_state
        self.node.online = False
        self.rx_fifo_len = rx_fifo
        self.on_event = None
        self.bitrate = None
        self.mode = None
        self._handler = None
        self._trigger = 0
        self._irq = None
        self._slots = [None] * self.TX_QUEUE_LEN  # (id, TxFrame or None) per transmit buffer
        self._done = []  # (index, ok) finished, not yet reported by flags()
        self._fifo = []
        self._rx_err = 0
        self._filters = ()  # () receives nothing until set_filters
        self._state_irq = False
        self._counts = [0, 0, 0, 0]  # warning, passive, bus-off entries, rx overruns
        self._prev_state = STATE_ACTIVE
        self.sent = self.received = 0
        if bitrate is not None:
            self.init(bitrate, mode, sample_point)

    # --- configuration ----------------------------------------------------------------
    def init(self, bitrate, mode=0, sample_point=75, sjw=1, tseg1=None, tseg2=None):
        if mode in (self.MODE_LOOPBACK, self.MODE_SILENT_LOOPBACK):
            raise ValueError("the bench's CAN has no loopback modes")
        if mode not in (self.MODE_NORMAL, self.MODE_SLEEP, self.MODE_SILENT):
            raise ValueError("invalid mode")
        if self.bitrate is not None:
            self.deinit()
        self.bitrate = int(bitrate)
        self.mode = mode
        node = self.node
        node.reset()
        node.bitrate = self.bitrate
        node.listen_only = mode == self.MODE_SILENT
        node.online = mode != self.MODE_SLEEP
        self._slots = [None] * self.TX_QUEUE_LEN
        self._done = []
        self._fifo = []
        self._rx_err = 0
        self._filters = ()
        self._state_irq = False
        self._counts = [0, 0, 0, 0]
        self._prev_state = STATE_ACTIVE

    def deinit(self):
        """Stop: queued frames and received ones dropped, no IRQs."""
        if self.bitrate is None:
            return
        self.node.cancel()
        self.node.online = False
        self.node.recovering = False
        self.bitrate = None
        self._slots = [None] * self.TX_QUEUE_LEN
        self._done = []
        self._fifo = []

    def set_filters(self, filters):
        self._check()
        if filters is None:
            self._filters = None
            return
        out = []
        for f in filters:
            can_id, mask, flags = f[0], f[1], f[2]
            limit = 1 << 29 if flags & self.FLAG_EXT_ID else 1 << 11
            if not (0 <= can_id < limit and 0 <= mask < limit):
                raise ValueError("invalid id")
            out.append((can_id, mask, bool(flags & self.FLAG_EXT_ID)))
        if len(out) > self.FILTERS_MAX:
            raise ValueError("too many filters")
        self._filters = tuple(out)

    def _check(self):
        if self.bitrate is None:
            raise OSError(errno.EINVAL, "CAN not initialised")

    # --- transmit ----------------------------------------------------------------------
    def send(self, can_id, data, flags=0):
        self._check()
        if len(data) > 8:
            raise OverflowError("data too long")
        ext = bool(flags & self.FLAG_EXT_ID)
        if not 0 <= can_id < (1 << 29 if ext else 1 << 11):
            raise ValueError("invalid id")
        if self.node.state == STATE_BUS_OFF:
            raise OSError(errno.EIO, "CAN bus off")
        free = -1
        for i, slot in enumerate(self._slots):
            if slot is None:
                if free < 0:
                    free = i
            elif slot[0] == can_id and not flags & self.FLAG_UNORDERED:
                return None
        if free < 0:
            return None
        rtr = bool(flags & self.FLAG_RTR)
        if self.node.listen_only or not self.node.online:
            frame = None  # bus monitoring / sleep: the request stays pending
        else:
            frame = self.node.transmit(can_id, ext, rtr, bytes(data))
            frame.tag = free
        self._slots[free] = (can_id, frame)
        return free

    def cancel_send(self, index):
        self._check()
        if not 0 <= index < self.TX_QUEUE_LEN:
            raise IndexError(index)
        slot = self._slots[index]
        if slot is None or (slot[1] is not None and slot[1] not in self.node.pending):
            return False
        if slot[1] is not None and not self.node.cancel(slot[1]):
            return False  # on the wire now: it completes
        self._finish(index, False)
        return True

    def _on_tx_done(self, t, ok):
        self.sent += 1
        self._finish(self.node.done.tag, ok)

    def _finish(self, index, ok):
        if self._trigger & self.IRQ_TX and self._handler is not None:
            self._done.append((index, ok))
            self._call()
        else:
            self._slots[index] = None
            self._event()

    # --- receive -----------------------------------------------------------------------
    def _accepts(self, can_id, ext):
        filters = self._filters
        if filters is None:
            return True
        for fid, mask, fext in filters:
            if fext == ext and (can_id & mask) == (fid & mask):
                return True
        return False

    def _on_frame(self, t, can_id, ext, rtr, data):
        if self.bitrate is None or not self._accepts(can_id, ext):
            return
        fifo = self._fifo
        if len(fifo) >= self.rx_fifo_len:
            self._rx_err |= self.RECV_ERR_OVERRUN
            self._counts[3] += 1
            return
        fifo.append((can_id, (self.FLAG_EXT_ID if ext else 0) | (self.FLAG_RTR if rtr else 0), data))
        self.received += 1
        if len(fifo) == self.rx_fifo_len:
            self._rx_err |= self.RECV_ERR_FULL
        if self._trigger & self.IRQ_RX and self._handler is not None:
            self._call()
        else:
            self._event()

    def recv(self, lst=None):
        self._check()
        if lst is not None and not isinstance(lst[1], memoryview):
            raise TypeError("recv: lst[1] must be a memoryview")
        if not self._fifo:
            return None
        can_id, flags, data = self._fifo.pop(0)
        if lst is None:
            lst = [0, memoryview(bytearray(8)), 0, 0]
        buf = lst[1].obj
        view = memoryview(buf)[: len(data)]
        view[:] = data
        lst[0] = can_id
        lst[1] = view
        lst[2] = flags
        lst[3] = self._rx_err
        self._rx_err = 0
        return lst

    # --- state and counters -------------------------------------------------------------
    def state(self):
        if self.bitrate is None:
            return self.STATE_STOPPED
        return self.node.state

    def _on_state(self, t, state):
        prev, self._prev_state = self._prev_state, state
        if state <= prev:
            return  # back to a milder state: no interrupt
        c = self._counts
        if state == STATE_BUS_OFF:
            c[2] += 1
        elif state == STATE_PASSIVE:
            c[1] += 1
        elif state == STATE_WARNING and prev == STATE_ACTIVE:
            c[0] += 1
        if self._trigger & self.IRQ_STATE and self._handler is not None:
            self._state_irq = True
            self._call()
        else:
            self._event()

    def get_counters(self, lst=None):
        if lst is None:
            lst = [0] * 8
        node = self.node
        pending = 0
        for slot in self._slots:
            if slot is not None and (slot[1] is None or slot[1] in node.pending):
                pending += 1
        lst[0] = node.tec
        lst[1] = node.rec
        lst[2], lst[3], lst[4] = self._counts[0], self._counts[1], self._counts[2]
        lst[5] = pending
        lst[6] = len(self._fifo)
        lst[7] = self._counts[3]
        return lst

    def restart(self):
        """Leave bus-off (after 128 x 11 bit times); queued frames cancelled, no IRQ_TX."""
        self._check()
        self.node.cancel()
        self._slots = [None] * self.TX_QUEUE_LEN
        self._done = []
        self._state_irq = False
        self._counts = [0, 0, 0, 0]
        self.node.restart()
        if self.node.state != STATE_BUS_OFF:
            self._prev_state = self.node.state

    # --- interrupts ---------------------------------------------------------------------
    def irq(self, handler=None, trigger=0, hard=False):
        if self._irq is None:
            self._irq = SimCanIrq(self)
        if handler is not None or trigger:
            self._handler = handler
            self._trigger = trigger
        return self._irq

    def _irq_flags(self):
        flags = 0
        trig = self._trigger
        if trig & self.IRQ_STATE and self._state_irq:
            flags |= self.IRQ_STATE
            self._state_irq = False
        if trig & self.IRQ_RX and self._fifo:
            flags |= self.IRQ_RX
        if trig & self.IRQ_TX and self._done:
            index, ok = self._done.pop(0)
            self._slots[index] = None
            flags |= (index << self.IRQ_TX_IDX_SHIFT) | self.IRQ_TX
            if not ok:
                flags |= self.IRQ_TX_FAILED
        return flags

    def _call(self):
        self._handler(self)
        self._event()

    def _event(self):
        if self.on_event is not None:
            self.on_event()


class SimSlcanPort(SimCapturePort):
    """The jig's SLCAN port (third USB CDC) on the bench; see ``hal.SimCapturePort``.

    ``host_send`` queues the host's bytes (``host_out``); each 1 ms USB frame moves up
    to ``frame_bytes`` of them into the device's receive buffer of ``rx_size`` bytes,
    then ``on_host_data`` (fn()) runs (the bench wakes the jig). What the host sent
    before closing the port still arrives."""

    def __init__(self, clock, tx_size=CDC_TX_SIZE, rx_size=CDC_RX_SIZE, **kw):
        super().__init__(clock, tx_size, **kw)
        self.rx_size = rx_size
        self.on_host_data = None
        self.host_out = bytearray()  # sent by the host, not yet in a USB frame
        self._out_due = None  # the time of the scheduled OUT frame, if any

    def host_send(self, data):
        """Bytes from the host; they reach the device in the next USB frame(s). Dropped
        while the host has the port closed."""
        if self.is_open and data:
            self.host_out += bytes(data)
            self._schedule_out()

    def _schedule_out(self):
        if self._out_due is not None or not self.host_out:
            return
        f = self.frame_us
        t = (self.clock.now // f + 1) * f
        self._out_due = t
        self.clock.at(t, self._out_frame)

    def _out_frame(self):
        self._out_due = None
        n = min(len(self.host_out), self.frame_bytes, self.rx_size - len(self.rx))
        if n > 0:
            self.rx += self.host_out[:n]
            del self.host_out[:n]
            self._arrived()
        self._schedule_out()

    def _arrived(self):
        if self.on_host_data is not None:
            self.on_host_data()


SLCAN_RATES = (10000, 20000, 50000, 100000, 125000, 250000, 500000, 750000, 1000000)  # S0..S8


class DirectSlcanAdapter:
    """A plain USB SLCAN adapter straight on the CAN bus: the reference the jig is
    measured against (``SimBench(direct=True)`` / ``direct_can=True``).

    A real USB adapter (a CANable's kind) with a CPU that takes no time: a line from
    the host is handled the moment its USB frame brings it, a received frame becomes
    a line at once. Its USB side is a ``SimSlcanPort``, full-speed USB in both
    directions as the jig's port (the host's bytes arrive in the next 1 ms frame,
    lines go to the host once a frame), with a transmit buffer that never fills.
    Frames go out in the order the host sent them (one in the controller at a
    time). Commands: ``Sn``, ``O``, ``L``, ``C``, ``t``/``T``/``r``/``R``, ``Zn``,
    ``V``, ``N``, ``F``; CR = OK, BEL = refused.
    """

    def __init__(self, clock, bus, name="adapter"):
        self.clock = clock
        self.port = SimSlcanPort(clock, tx_size=1 << 24)
        self.port.on_host_data = self._host_data
        self.can = SimCan(bus, name=name)
        self.can.irq(self._irq, SimCan.IRQ_RX | SimCan.IRQ_TX, hard=True)
        self.bitrate = bus.bitrate
        self.stamps = False
        self._line = bytearray()
        self._txq = []  # (id, data, flags) in the host's order
        self._busy = False
        self._lst = [0, memoryview(bytearray(8)), 0, 0]

    def _host_data(self):
        buf = bytearray(self.port.any())
        self.port.readinto(buf)
        for b in buf:
            if b == 13:
                line, self._line = bytes(self._line), bytearray()
                self.port.write(self._command(line))
            elif b != 10:
                self._line.append(b)
        self._pump()

    def _command(self, line):
        ok, bad = b"\r", b"\a"
        can = self.can
        is_open = can.bitrate is not None
        if not line:
            return ok
        c = line[:1]
        try:
            if c in (b"t", b"T", b"r", b"R"):
                if not is_open or can.mode == SimCan.MODE_SILENT:
                    return bad
                ext = c in (b"T", b"R")
                n = 8 if ext else 3
                can_id = int(line[1:1 + n], 16)
                dlc = int(line[1 + n:2 + n], 16)
                if dlc > 8:
                    return bad
                flags = (SimCan.FLAG_EXT_ID if ext else 0)
                if c in (b"r", b"R"):
                    data, flags = bytes(dlc), flags | SimCan.FLAG_RTR
                    if len(line) != 2 + n:
                        return bad
                else:
                    data = bytes.fromhex(line[2 + n:].decode())
                    if len(data) != dlc:
                        return bad
                self._txq.append((can_id, data, flags))
                return ok
            if c == b"S" and len(line) == 2 and not is_open:
                self.bitrate = SLCAN_RATES[int(line[1:2])]
                return ok
            if c in (b"O", b"L") and len(line) == 1 and not is_open:
                can.init(self.bitrate, SimCan.MODE_SILENT if c == b"L" else SimCan.MODE_NORMAL)
                can.set_filters(None)
                return ok
            if c == b"C" and len(line) == 1 and is_open:
                can.deinit()
                self._txq = []
                self._busy = False
                return ok
            if c == b"Z" and len(line) == 2:
                self.stamps = line[1:2] == b"1"
                return ok
            if line == b"V":
                return b"V1013\r"
            if line == b"N":
                return b"NSIM1\r"
            if line == b"F":
                return b"F00\r"
        except (ValueError, IndexError):
            pass
        return bad

    def _pump(self):
        if self._busy or not self._txq or self.can.bitrate is None:
            return
        can_id, data, flags = self._txq[0]
        try:
            idx = self.can.send(can_id, data, flags)
        except OSError:
            self._txq = []
            return
        if idx is not None:
            self._txq.pop(0)
            self._busy = True

    def _irq(self, can):
        lst = self._lst
        while True:
            f = can.irq().flags()
            if not f:
                break
            if f & SimCan.IRQ_TX:
                self._busy = False
            if f & SimCan.IRQ_RX:
                while can.recv(lst) is not None:
                    self.port.write(self._line_of(lst))
        self._pump()

    def _line_of(self, lst):
        can_id, data, flags = lst[0], bytes(lst[1]), lst[2]
        ext = flags & SimCan.FLAG_EXT_ID
        if flags & SimCan.FLAG_RTR:
            head = (b"R%08X%d" if ext else b"r%03X%d") % (can_id, len(data))
        else:
            head = (b"T%08X%d" if ext else b"t%03X%d") % (can_id, len(data)) + data.hex().upper().encode()
        if self.stamps:
            head += b"%04X" % (int(self.clock.now // 1000) % 60000)
        return head + b"\r"
