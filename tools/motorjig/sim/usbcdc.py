"""A USB CDC port of the board as the bench sees it: the device's transmit buffer, the host's
1 ms frames, the host opening and closing the port (the jig's capture port, its SLCAN port)."""

CDC_TX_SIZE = 1024  # MicroPython stm32's USB CDC transmit buffer (USBD_CDC_TX_DATA_SIZE)
USB_FRAME_US = 1000  # full-speed USB: the host polls the IN endpoint once per 1 ms frame
USB_FRAME_BYTES = 1024  # what one frame moves at most (the CDC sends its buffer per frame)


class SimCapturePort:
    """The jig's capture port on the bench: a USB CDC port as ``jig.capture`` sees it.

    Device side (the firmware, HAL contract): ``any()`` bytes the host sent and the
    jig has not read, ``readinto(buf)`` non-blocking into buf[0:], ``write(buf)`` the
    bytes it took now: as many as fit into the ``tx_size``-byte transmit buffer, 0
    while no host has the port open. Never blocks.

    Host side (the bench): ``host_open()`` / ``host_close()`` (a closed port drops
    what its transmit buffer held, or with ``keep_on_close`` keeps it for the next
    host to open the port, as the board's CDC does; what the host sent before
    closing has reached the device and is still read, so ``X`` then close stops the
    recording),
    ``host_send(data)`` (commands: b"S", b"X"), ``host_read()`` (what the host has
    received since the last call). Once per USB frame (``frame_us``) the host takes
    up to ``frame_bytes`` from the transmit buffer; ``sink`` (fn(bytes) -> bytes
    accepted), when set, receives them instead of ``host_read`` (the real-time bench
    hands them to its TCP client or pty, whose own buffer then pushes back). Runs on
    the bench's clock; not thread-safe.
    """

    def __init__(self, clock, tx_size=CDC_TX_SIZE, frame_us=USB_FRAME_US, frame_bytes=USB_FRAME_BYTES,
                 keep_on_close=False):
        self.clock = clock
        self.keep_on_close = keep_on_close
        self.tx_size = tx_size
        self.frame_us = frame_us
        self.frame_bytes = frame_bytes
        self.tx = bytearray()  # the device's transmit buffer
        self.rx = bytearray()  # from the host, not yet read by the jig
        self.received = bytearray()  # what the host has taken (sink None)
        self.sink = None
        self.is_open = False
        self.taken = 0  # bytes the jig handed over, ever
        self.refused = 0  # write calls that took nothing
        self._frame_due = None  # the time of the scheduled USB frame, if any
        self.cpu_us_per_write = 0.0  # the jig's CPU time per write that takes bytes (SimHAL.cpu_model)

    # --- the jig's side -------------------------------------------------------------
    def any(self):
        return len(self.rx)

    def readinto(self, buf):
        n = min(len(buf), len(self.rx))
        if n:
            buf[0:n] = self.rx[0:n]
            del self.rx[0:n]
        return n

    def write(self, buf):
        room = self.tx_size - len(self.tx) if self.is_open else 0
        n = min(len(buf), room)
        if n <= 0:
            self.refused += 1
            return 0
        if self.cpu_us_per_write:
            self.clock.run_until(self.clock.now + self.cpu_us_per_write)  # (SimHAL.cpu_model)
        self.tx += bytes(buf[0:n])
        self.taken += n
        self._schedule()
        return n

    # --- the host's side --------------------------------------------------------------
    def host_open(self):
        self.is_open = True
        self._schedule()

    def host_close(self):
        self.is_open = False
        if not self.keep_on_close:
            self.tx = bytearray()

    def host_send(self, data):
        """Bytes from the host to the jig (read in its slow pass); dropped while closed."""
        if self.is_open:
            self.rx += bytes(data)

    def host_read(self):
        data = bytes(self.received)
        self.received = bytearray()
        return data

    @property
    def busy(self):
        """True while the transmit buffer holds bytes the host has not taken."""
        return bool(self.tx)

    def _schedule(self):
        if self._frame_due is not None or not self.tx or not self.is_open:
            return
        f = self.frame_us
        t = (self.clock.now // f + 1) * f
        self._frame_due = t
        self.clock.at(t, self._frame)

    def _frame(self):
        self._frame_due = None
        if not self.is_open or not self.tx:
            return
        chunk = bytes(self.tx[0:self.frame_bytes])
        if self.sink is None:
            self.received += chunk
            n = len(chunk)
        else:
            n = self.sink(chunk) or 0
        if n:
            del self.tx[0:n]
        self._schedule()
