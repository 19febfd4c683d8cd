"""The Desk's recording of both buses: the jig's capture port, started and stopped from the page.

The jig records every frame it receives or sends on the PC bus and the driver bus
(``jig.capture``) and streams the records over its capture port: the board's
second USB CDC port (``jigctl gui --capture-port /dev/ttyACM1``), or the virtual
bench's capture TCP port (``--bench`` knows it). ``DeskCapture`` is one per Desk
server, shared by every browser tab like the bus session: ``start()`` opens the
port and sends ``S`` (``motorjig.capture.jigport.JigCapture``: the jig empties its
ring and sends its hello first), a thread reads the record stream
(``motorjig.capture.jigstream.JigStream``) into memory, ``stop()`` sends ``X`` and
closes the port, ``pcapng()`` is the pcapng file of what was recorded (the writer
of ``jigctl capture``: one interface per bus) at any time, while recording too.

Start replaces the previous recording; ``unsaved`` says when that would lose one
nobody downloaded (the page asks first). The Desk keeps the newest ``keep`` records; older ones are dropped and counted.
Without a capture port every action is refused with the sentence ``unavailable``
says, and the page shows it beside the greyed-out controls. Every failure is one
sentence (``UserError``); a port that fails while recording ends the recording
with the reason in ``error``, the records read until then kept.
"""

import collections
import io
import threading
import time

from motorjig.capture import pcapng
from motorjig.capture import record as R
from motorjig.errors import JigError

from motorjig.desk.session import UserError

KEEP = 100000  # records kept in memory, the newest (about 20 MB)
PORT_FREE_WAIT_S = 5.0  # the longest a Start waits for the last recording's port to close
NO_PORT = ("no capture port: start the Desk with --capture-port PORT (the jig's second USB port, e.g. "
           "/dev/ttyACM1), or with --bench")


class DeskCapture:
    """Start, stop and download the jig's recording (see the module docstring).

    ``url``: the capture port (a device or a pyserial URL), or None: then
    ``unavailable`` says why (``why``, default ``NO_PORT``). ``opener``:
    fn(url) -> an object with JigCapture's start/run/stop/close and ``stream``
    (default: ``JigCapture``).
    """

    def __init__(self, url=None, why=None, keep=KEEP, opener=None):
        self.url = url or None
        self.unavailable = None if self.url else (why or NO_PORT)
        self.keep = keep
        self._opener = opener
        self._lock = threading.Lock()
        self._records = collections.deque(maxlen=keep)
        self._cap = None
        self._thread = None
        self.state = "idle"  # recording, stopped
        self.error = ""
        self.dropped = 0  # the oldest records, beyond keep
        self.total = 0  # records read since start
        self.per_bus = [0, 0]  # frame records per bus
        self.lost = 0  # records the jig reported lost (its ring was full)
        self.hello = None  # the jig's hello (a dict) of this recording
        self.description = ""  # one line about the jig, for the file's header
        self.buses = None
        self.started = None  # time.time() at start and at stop
        self.ended = None
        self.downloaded = False  # the finished recording was downloaded
        self._generation = 0  # recordings started
        self._port_free = threading.Event()  # no recording holds the port (or is closing it)
        self._port_free.set()

    @property
    def recording(self):
        return self.state == "recording"

    # --- start / stop ----------------------------------------------------------------------
    def start(self):
        """Open the capture port, S, wait for the jig's hello, read in a thread; returns a sentence."""
        if self.unavailable:
            raise UserError("recording is not available: %s" % self.unavailable)
        with self._lock:
            if self.state in ("recording", "starting"):
                raise UserError("already recording: press STOP RECORDING first")
            self.state = "starting"
        # The last recording may still be closing its port (a Stop, or one that ended by
        # itself): its X would stop the jig recording for this new start.
        if not self._port_free.wait(PORT_FREE_WAIT_S):
            self._start_failed()
            raise UserError("the last recording's port did not close within %g s: try again" % PORT_FREE_WAIT_S)
        try:
            cap = self._open()
            try:
                hello = cap.start()
            except Exception:
                cap.close()
                raise
        except JigError as exc:
            self._start_failed()
            raise UserError(str(exc).rstrip(".")) from None
        except Exception:
            self._start_failed()
            raise
        with self._lock:
            self._cap = cap
            self._records.clear()
            self.dropped = self.total = self.lost = 0
            self.per_bus = [0, 0]
            self.error = ""
            self.hello = hello
            self.description = cap.stream.description()
            self.buses = cap.stream.buses()
            self.started, self.ended = time.time(), None
            self.downloaded = False
            self._generation += 1
            self._port_free.clear()
            self.state = "recording"
            self._thread = threading.Thread(target=self._read, args=(cap,), name="desk-capture", daemon=True)
            thread = self._thread
        thread.start()
        return "recording both buses from %s (%s)" % (self.url, self.description)

    def _start_failed(self):
        with self._lock:
            self.state = "stopped" if self.total else "idle"

    def _open(self):
        if self._opener is not None:
            return self._opener(self.url)
        from motorjig.capture.jigport import JigCapture

        return JigCapture(self.url)

    def _read(self, cap):
        error = ""
        try:
            cap.run([self._add])
        except JigError as exc:
            error = "recording ended: %s" % str(exc).rstrip(".")
        except Exception as exc:  # a bug: one sentence on the page, never a traceback
            error = "recording ended: internal error (%s: %s)" % (type(exc).__name__, exc)
        finally:
            with self._lock:
                if error and self._cap is cap:  # not an error of a recording already stopped
                    self.error = error
                if self._cap is cap and self.state == "recording":
                    self.state = "stopped"
                    self.ended = time.time()
                    self._cap = None
                    closing = True
                else:
                    closing = False
            if closing:  # ended by itself (a failure): X and close here
                try:
                    cap.close()
                finally:
                    self._port_free.set()

    def _add(self, rec):
        with self._lock:
            if len(self._records) == self.keep:
                self.dropped += 1
            self._records.append(rec)
            self.total += 1
            if rec.verdict == R.LOST:
                self.lost += rec.count or 0
            elif rec.data and 0 <= rec.bus < 2:
                self.per_bus[rec.bus] += 1

    def stop(self):
        """X, the port closed; the records stay for the download. Returns a sentence."""
        if self.unavailable:
            raise UserError("recording is not available: %s" % self.unavailable)
        with self._lock:
            cap, self._cap = self._cap, None
            if cap is None:
                if self.error:
                    return self.error
                raise UserError("not recording: press Start first")
            self.state = "stopped"
            self.ended = time.time()
        try:
            cap.stop()
            thread = self._thread
            if thread is not None:
                thread.join(2.0)
            cap.close()
        finally:
            self._port_free.set()
        return "recording stopped: %s" % self.summary()

    def close(self):
        """The Desk stops: a recording in progress is stopped (X), quietly."""
        if self._cap is not None:
            try:
                self.stop()
            except UserError:
                pass

    # --- what was recorded ----------------------------------------------------------------
    def records(self):
        with self._lock:
            return list(self._records)

    def summary(self):
        """One line: what has been recorded so far."""
        if self.unavailable:
            return self.unavailable
        if self.state == "idle" and not self.total:
            return "nothing recorded yet: Start records both buses through the jig (%s)" % self.url
        with self._lock:
            total, pc, drv, lost, dropped = self.total, self.per_bus[0], self.per_bus[1], self.lost, self.dropped
        span = ((self.ended or time.time()) - self.started) if self.started else 0.0
        parts = ["%d records in %.1f s: %d frames on the PC bus, %d on the driver bus" % (total, span, pc, drv)]
        if lost:
            parts.append("the jig lost %d (its ring was full)" % lost)
        if dropped:
            parts.append("the oldest %d not kept (the Desk keeps the newest %d)" % (dropped, self.keep))
        text = "; ".join(parts)
        if self.state == "recording":
            return "recording: " + text
        return text + (" (%s)" % self.error if self.error else "")

    @property
    def unsaved(self):
        """A finished recording with records that has not been downloaded since it ended
        (a new Start would replace it)."""
        return self.state == "stopped" and self.total > 0 and not self.downloaded

    def pcapng(self):
        """The pcapng file (bytes) of the records kept: one interface per bus."""
        if self.unavailable:
            raise UserError("recording is not available: %s" % self.unavailable)
        if self.buses is None:
            raise UserError("nothing recorded yet: press Start recording, let the bus work, then STOP RECORDING")
        with self._lock:
            finished = self.state == "stopped"
            generation = self._generation
        out = io.BytesIO()
        w = pcapng.Writer(out, self.buses, hardware=self.description or None)
        for rec in self.records():
            w.write(rec)
        with self._lock:
            # A download while recording leaves out what comes next; one that took so long
            # that a new recording began is not that recording's download.
            if finished and generation == self._generation:
                self.downloaded = True
        return out.getvalue()

    def file_name(self):
        t = self.started or time.time()
        return time.strftime("motorjig-capture-%Y%m%d-%H%M%S.pcapng", time.localtime(t))


__all__ = ["DeskCapture", "KEEP", "NO_PORT"]
