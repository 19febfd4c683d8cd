"""Listening on a bus: a pyserial port read with host timestamps, framed into records.

``open_port`` opens a listen-only USB-RS-485 adapter (or any pyserial URL:
``socket://`` to a bench or a test's server); ``Sniffer.run`` reads whatever
arrives, stamps each chunk with the host's clock when ``read`` returned it, and
hands the records the ``Framer`` cuts to every sink, until a duration or count
is reached, ``stop()`` is called, or the port fails.

Precision: the time is when the host got the chunk, not when the bytes were on
the wire. A USB adapter holds received bytes until its buffer fills or its
latency timer runs out (FTDI: 16 ms by default, 1 ms at the lowest; CP210x and
CH340 a few ms), then the OS scheduler adds its share; frames inside one chunk
are spaced one character time apart backwards from the chunk's time. The clock
is the host's wall clock at start, advanced by its monotonic clock (µs).
"""

import time

import serial

from motorjig.capture.framer import Framer, char_time_us
from motorjig.errors import PortError

READ_SLICE = 0.05  # s: the longest a read blocks, so timeouts and stop() are seen
DEFAULT_INTERBYTE_MS = 20.0  # longer than a USB adapter's usual hold-back (see docs/capture.md)


def open_port(url, baud):
    try:
        port = serial.serial_for_url(url, baudrate=baud, timeout=READ_SLICE, do_not_open=True)
        port.open()
    except (serial.SerialException, OSError, ValueError) as exc:
        raise PortError("cannot open %s: %s" % (url, exc)) from None
    return port



def read_waiting(port):
    """One byte (waiting up to the port's timeout), then whatever else is waiting."""
    data = port.read(1)
    if data:
        n = port.in_waiting
        if n:
            data += port.read(n)
    return data

class HostClock:
    """µs since the Unix epoch: wall clock at start, then the monotonic clock."""

    def __init__(self):
        self._wall0 = time.time_ns() // 1000
        self._mono0 = time.monotonic_ns()

    def now_us(self):
        return self._wall0 + (time.monotonic_ns() - self._mono0) // 1000


class Sniffer:
    """Reads one port into records for the sinks (callables taking a Record)."""

    def __init__(self, port, url, baud, bus=0, interbyte_timeout_ms=DEFAULT_INTERBYTE_MS, ver8=None, clock=None):
        self.port = port
        self.url = url
        self.framer = Framer(bus=bus, byte_us=char_time_us(baud),
                             interbyte_timeout_us=int(interbyte_timeout_ms * 1000), ver8=ver8)
        self.clock = clock or HostClock()
        self.records = 0
        self.bytes = 0
        self._stop = False

    def stop(self):
        self._stop = True

    def _read(self):
        try:
            return read_waiting(self.port)
        except (serial.SerialException, OSError) as exc:
            raise PortError("reading from %s failed: %s" % (self.url, exc)) from None

    def _out(self, recs, sinks):
        for rec in recs:
            self.records += 1
            for sink in sinks:
                sink(rec)

    def run(self, sinks, duration=None, count=None, alive=None):
        """Until duration seconds passed, count records were made, stop(), ``alive()``
        turned false (checked at every read) or a port error; then call finish() (also
        after Ctrl-C) for a frame left open."""
        end = None if duration is None else time.monotonic() + duration
        while not self._stop and (alive is None or alive()):
            if end is not None and time.monotonic() >= end:
                break
            if count is not None and self.records >= count:
                break
            data = self._read()
            t = self.clock.now_us()
            if data:
                self.bytes += len(data)
                self._out(self.framer.feed(data, t), sinks)
            else:
                self._out(self.framer.check_timeout(t), sinks)

    def finish(self, sinks):
        """What the line left unfinished, as a last record."""
        self._out(self.framer.flush(), sinks)
