"""The jig's capture port: start its recording, read its record stream, stop it.

``JigCapture(url)`` opens the capture port (the board's second USB CDC port,
``/dev/ttyACM1``, or any pyserial URL such as the virtual bench's
``socket://127.0.0.1:N``); ``start()`` sends ``X`` then ``S`` (the jig empties its
ring and sends a hello record first; the ``X`` first makes a jig that is already
recording -- parameter ``capture`` = 1, or a reader that went away without ``X`` --
start afresh, as an ``S`` alone does not restart a recording) and waits for that
hello, skipping what an earlier recording left in the pipe, so a port that is not
the jig's capture port is told within ``HELLO_WAIT_S``; ``run(sinks)`` hands every
record (``jigstream.JigStream``) to the sinks until a duration or count is
reached, ``stop()`` is called or ``alive()`` turns false; ``close()`` sends ``X``
(recording off) and closes the port. Failures are ``PortError``s (one sentence);
a stream out of step is ``jigstream.StreamError``, a kind of it, raised after
the records read before the fault went to the sinks.
"""

import time

import serial

from motorjig.capture.jigstream import JigStream, StreamError
from motorjig.capture.sniff import open_port
from motorjig.errors import PortError

CMD_START = b"S"
CMD_STOP = b"X"
CMD_RESTART = CMD_STOP + CMD_START  # the jig reads one command per slow pass: X, then S
HELLO_WAIT_S = 2.0  # the jig answers S within a slow pass (10 ms); USB and the OS add a little


class JigCapture:
    """One recording from the jig's capture port (see the module docstring)."""

    def __init__(self, url, clock=None, port=None):
        self.url = url
        self.port = port if port is not None else open_port(url, 115200)  # (a CDC port has no baud)
        self.stream = JigStream(url, clock, strict_start=False)
        self.records = 0
        self._pending = []  # records that came with the hello
        self._stop = False
        self._started = False

    @property
    def bytes(self):
        return self.stream.bytes

    def stop(self):
        self._stop = True

    def _write(self, data):
        try:
            self.port.write(data)
            self.port.flush()
        except (serial.SerialException, OSError) as exc:
            raise PortError("writing to %s failed: %s" % (self.url, exc)) from None

    def _read(self):
        try:
            data = self.port.read(1)
            if data:
                n = self.port.in_waiting
                if n:
                    data += self.port.read(n)
            return data
        except (serial.SerialException, OSError) as exc:
            raise PortError("reading from %s failed: %s" % (self.url, exc)) from None

    def start(self, wait=HELLO_WAIT_S):
        """Recording on afresh (X, S) and its hello read; returns the hello (a dict)."""
        try:
            self.port.reset_input_buffer()  # what an earlier recording left
        except (serial.SerialException, OSError, AttributeError):
            pass
        self._write(CMD_RESTART)
        self._started = True
        end = time.monotonic() + wait
        while self.stream.hello is None:
            if time.monotonic() >= end:
                got = self.stream.bytes
                raise PortError("%s is not a MotorJig capture port: no hello record in %g s (%s)" % (
                    self.url, wait, "%d bytes of something else came" % got if got else "nothing came"))
            data = self._read()
            if data:
                self._pending += self.stream.feed(data, self.stream.clock.now_us())
        return self.stream.hello

    def _out(self, recs, sinks):
        for rec in recs:
            self.records += 1
            for sink in sinks:
                sink(rec)

    def run(self, sinks, duration=None, count=None, alive=None):
        """Records to the sinks (callables taking a Record) until duration seconds,
        count records, stop(), ``alive()`` false (checked at every read) or a failure."""
        end = None if duration is None else time.monotonic() + duration
        pending, self._pending = self._pending, []
        self._out(pending[:None if count is None else max(0, count - self.records)], sinks)
        while not self._stop and (alive is None or alive()):
            if end is not None and time.monotonic() >= end:
                break
            if count is not None and self.records >= count:
                break
            data = self._read()
            if not data:
                continue
            try:
                recs = self.stream.feed(data, self.stream.clock.now_us())
            except StreamError as exc:
                self._out(exc.records, sinks)
                raise
            if count is not None:
                recs = recs[:max(0, count - self.records)]
            self._out(recs, sinks)

    def close(self):
        """Recording off (X), port closed; never raises."""
        try:
            if self._started:
                self.port.write(CMD_STOP)
                self.port.flush()
        except Exception:  # the port is gone: the jig stops streaming to nobody anyway
            pass
        try:
            self.port.close()
        except Exception:
            pass
