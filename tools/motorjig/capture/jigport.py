"""The jig's capture port: start its recording, read its record stream, stop it.

``JigCapture(url)`` opens the capture port (the board's second USB CDC port,
``/dev/ttyACM1``, or any pyserial URL such as the virtual bench's
``socket://127.0.0.1:N``); ``start()`` sends ``X`` (the jig stops a recording that is
on -- parameter ``capture`` = 1, or a reader that went away without ``X`` -- as an
``S`` alone does not restart one), reads and discards what comes until
``QUIET_S`` of silence (at most ``DRAIN_MAX_S``: what an earlier recording left in
the pipe, the board's CDC keeping its transmit buffer when its reader goes away,
old hellos included), then sends ``S`` (the jig empties its ring and sends a hello
record first) and waits for that hello, so a port that is not the jig's capture
port is told within ``HELLO_WAIT_S``; a connection the port closes at once is
another reader attached (one reader at a time). ``run(sinks)`` hands every record
(``jigstream.JigStream``; only those ``keep`` keeps, when set) to the sinks until a duration or count is reached,
``stop()`` is called or ``alive()`` turns false, or nothing at all has come for
``SILENCE_S`` (the jig sends a clock record at least every second while it
records: it has stopped, ``STOPPED_MSG``); ``close()`` sends ``X`` (recording
off) and closes the port. Failures are ``PortError``s (one sentence); a stream out
of step, or a recording the jig ended, is ``jigstream.StreamError``, a kind of it,
raised after the records read before the fault went to the sinks.
"""

import time

import serial

from motorjig.capture.jigstream import JigStream, StreamError
from motorjig.capture.sniff import open_port, read_waiting
from motorjig.errors import PortError

CMD_START = b"S"
CMD_STOP = b"X"
QUIET_S = 0.05  # after X: this long without bytes, the old stream has all come
DRAIN_MAX_S = 1.0  # ... but no longer than this (a port that never stops talking)
SILENCE_S = 3.0  # while recording: this long without a byte, the jig has stopped
STOPPED_MSG = "the jig stopped recording (parameter 13 capture = 0, or a reset)"
ANOTHER_READER = "%s closed the connection at once: another reader is attached (one reader at a time)"
HELLO_WAIT_S = 2.0  # the jig answers S within a slow pass (10 ms); USB and the OS add a little


class JigCapture:
    """One recording from the jig's capture port (see the module docstring)."""

    def __init__(self, url, clock=None, port=None, monotonic=time.monotonic):
        self.url = url
        self._monotonic = monotonic
        self.port = port if port is not None else self._open(url)
        self.stream = JigStream(url, clock, strict_start=False)
        self.records = 0  # records handed to the sinks
        self.keep = None  # a predicate on Records: only those it keeps go to the sinks and count (None: all)
        self._pending = []  # records that came with the hello
        self._stop = False
        self._started = False

    @staticmethod
    def _open(url):
        """The port (a CDC port has no baud); a server that resets the connection while
        it is being opened is another reader's, as one that closes it at the first read."""
        try:
            return open_port(url, 115200)
        except PortError as exc:
            if "reset by peer" in str(exc).lower():
                raise PortError(ANOTHER_READER % url) from None
            raise

    @property
    def bytes(self):
        return self.stream.bytes

    def stop(self):
        self._stop = True

    def _write(self, data, starting=False):
        try:
            self.port.write(data)
            self.port.flush()
        except (serial.SerialException, OSError) as exc:
            raise self._failed(exc, "writing to", starting) from None

    def _read(self, starting=False):
        try:
            return read_waiting(self.port)
        except (serial.SerialException, OSError) as exc:
            raise self._failed(exc, "reading from", starting) from None

    def _failed(self, exc, doing, starting):
        """The PortError of a failed read or write ("another reader" while starting)."""
        if starting and self._closed_at_once(exc):
            return PortError(ANOTHER_READER % self.url)
        return PortError("%s %s failed: %s" % (doing, self.url, exc))

    @staticmethod
    def _closed_at_once(exc):
        """True if a read failed as a connection the other end closed (EOF, reset)."""
        if isinstance(exc, (ConnectionResetError, ConnectionAbortedError, BrokenPipeError)):
            return True
        text = str(exc).lower()
        return "disconnected" in text or "reset by peer" in text or "broken pipe" in text

    def _drain(self, quiet=QUIET_S, limit=DRAIN_MAX_S):
        """Read and discard until quiet seconds without bytes (at most limit seconds)."""
        now = self._monotonic()
        end = now + limit
        last = now
        while now < end and now - last < quiet:
            if self._read(starting=True):
                last = self._monotonic()
            now = self._monotonic()

    def start(self, wait=HELLO_WAIT_S):
        """Recording on afresh (X, what comes discarded, S) and its hello read; returns
        the hello (a dict)."""
        try:
            self.port.reset_input_buffer()  # what an earlier recording left
        except (serial.SerialException, OSError, AttributeError):
            pass
        self._write(CMD_STOP, starting=True)
        self._started = True
        self._drain()  # the rest of an earlier recording, in the port's buffers
        self._write(CMD_START, starting=True)
        end = self._monotonic() + wait
        while self.stream.hello is None:
            if self._monotonic() >= end:
                got = self.stream.bytes
                if got:
                    why = "(%d bytes of something else came)" % got
                else:
                    why = "(nothing came), or another program is reading it"
                raise PortError("%s is not a MotorJig capture port: no hello record in %g s %s" % (
                    self.url, wait, why))
            data = self._read(starting=True)
            if data:
                self._pending += self.stream.feed(data, self.stream.clock.now_us())
        return self.stream.hello

    def _out(self, recs, sinks, count=None):
        """recs (those ``keep`` keeps) to the sinks, only as many as keep the total within
        count (None: all)."""
        if self.keep is not None:
            recs = [r for r in recs if self.keep(r)]
        if count is not None:
            recs = recs[:max(0, count - self.records)]
        for rec in recs:
            self.records += 1
            for sink in sinks:
                sink(rec)

    def run(self, sinks, duration=None, count=None, alive=None):
        """Records to the sinks (callables taking a Record) until duration seconds,
        count records, stop(), ``alive()`` false (checked at every read) or a failure."""
        now = self._monotonic()
        end = None if duration is None else now + duration
        last = now  # when a byte last came
        pending, self._pending = self._pending, []
        self._out(pending, sinks, count)
        while not self._stop and (alive is None or alive()):
            now = self._monotonic()
            if end is not None and now >= end:
                break
            if count is not None and self.records >= count:
                break
            data = self._read()
            if not data:
                if self._monotonic() - last > SILENCE_S:
                    raise StreamError(STOPPED_MSG, (), self.stream.bytes)
                continue
            last = self._monotonic()
            try:
                recs = self.stream.feed(data, self.stream.clock.now_us())
            except StreamError as exc:
                self._out(exc.records, sinks)
                raise
            self._out(recs, sinks, count)

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
