"""The state and actions behind the MotorJig Desk page, without any web code.

One ``BusSession`` per server owns the one ``Master`` and is shared by every
browser tab. Every bus access goes through ``_bus`` under one lock, so only one
request is on the line at a time; the background poller (axis status for the
panel and the plot) takes the lock only when nothing else holds it, so it pauses
while a command runs. Long jobs (scan, motion test, parameter table) take the
lock once per request, so STOP and EMERGENCY STOP get onto the line between two
of their requests.

Every failure the operator can cause or meet reaches the page as ``UserError``
with one sentence; a port that fails while in use switches the session to the
``lost`` state ("connection lost ... Reconnect").

A test-plan run (the Test tab) needs the port for itself: ``lend_port`` closes the
Master (the poller and every command then wait with a sentence, state ``lent``) and
``take_port_back`` opens it again, so one program part owns the port at a time.
With ``read_only`` every method that would send something to the bus is refused;
only the poller reads, and a lost connection is opened again (Reconnect, or by
itself every few seconds): watching is not moving.

Ver6 or Ver8 is detected per slave as ``jigctl scan`` does it (``Master(ver8=None)``)
unless the operator forces one framing; the scan rows carry each slave's variant.
The jig (slave 1, or the id that answered as the jig) is never an axis.
"""

import collections
import csv
import datetime
import functools
import io
import threading
import time
from types import SimpleNamespace

from jig import diag as D
from jig import frame as F
from jig.parser import FrameParser

from motorjig import names as N
from motorjig import safetynotice
from motorjig.commands import _motion_cycles  # the very moves and checks of `jigctl motion-test`
from motorjig.decode import Decoder
from motorjig.errors import JigError, MotionRefusedError, PortError
from motorjig.master import BAUD_RATES, AxisStatus, Frame, Master

from motorjig.desk import forms
from motorjig.desk.axes import DeskAxis

#: parser counters that mean a broken frame arrived, and how the log names them
LINE_ERRORS = (("crc_errors", "frame with a bad CRC"), ("stuff_errors", "bad escape sequence"),
               ("short", "frame too short"), ("overlong", "frame too long"),
               ("timeouts", "frame cut off (inter-byte timeout)"))

LogEntry = collections.namedtuple("LogEntry", "seq t kind text")
LogEntry.__doc__ = "One log line: kind is tx, rx, error, info or line (a broken frame on the line)."

Sample = collections.namedtuple("Sample", "t command_pos actual_pos actual_vel")


class UserError(Exception):
    """Something the operator must be told in one sentence (never a traceback)."""


class Aborted(JigError):
    """STOP or EMERGENCY STOP was pressed while a job was running."""


#: what the page says brings an axis back after EMERGENCY STOP (the drive latches it)
ESTOP_RECOVERY = ("EMERGENCY STOP is latched in the drive: it refuses every move (0x85) until the servo is "
                  "switched off and on again (Servo OFF, then Servo ON). ALARM RESET and STOP AXIS do not clear it.")

#: the move fields' values before the operator has typed any (those of the seed program)
MOVE_DEFAULTS = {"target": "300000", "speed": "50000", "acc": "1000", "dec": "10"}

#: the move buttons (kind, sign): ABS, INC and DEC (INC of the field's distance the other way)
MOVES = {("abs", 1): "Move ABS", ("inc", 1): "Move INC", ("inc", -1): "Move DEC"}

#: how often a read-only Desk tries to open a lost connection again by itself (seconds)
RECONNECT_EVERY = 2.0


def protocol_name(ver8):
    """The Ver6/Ver8 setting in words: None detects each slave's variant."""
    return "auto" if ver8 is None else "Ver8" if ver8 else "Ver6"


def command(what):
    """Mark a session method that sends something to the bus: refused in a read-only Desk."""
    def wrap(fn):
        @functools.wraps(fn)
        def call(self, *args, **kw):
            if self.read_only:
                raise UserError("%s refused: this Desk is read-only (--read-only): it shows the status and the "
                                "runs and sends nothing to the bus" % what)
            return fn(self, *args, **kw)
        return call
    return wrap


def wire_frame(wire):
    """(Frame, None) for complete wire bytes, or (None, why) when they are not a good frame."""
    p = FrameParser()
    p.feed(bytes(wire))
    if p.ready:
        return Frame(p.slave, p.sync, p.ftype, bytes(p.body[p.data_start:p.data_end]),
                     bytes(p.body[:p.body_len]), time.time()), None
    for name, text in LINE_ERRORS:
        if getattr(p, name, 0):
            return None, text
    return None, "not a complete frame"


class SessionAxis(DeskAxis):
    """The bus session (the jig's PC port: the selected axis, a motion test, a scan, a test run) as
    one of the Desk's axes (``axes.DeskAxis``). A run gets the PC port through ``lend_port``."""

    title = "the bus"

    def __init__(self, session):
        self.session = session

    def present(self):
        return self.session.state not in ("disconnected", "lost")

    def stop(self, emergency):
        s = self.session
        return s.emergency_stop() if emergency else s.stop_axis()

    def status(self):
        return self.session.state


class BusSession:
    """Connection, selected axis, polled status, history, log and jobs of one Desk server."""

    def __init__(self, poll_interval=0.05, history_seconds=120.0, log_size=3000, timeout=0.1,
                 master_factory=Master, read_only=False):
        self.read_only = read_only
        self.desk_axis = SessionAxis(self)  # what the page's STOP sees of it
        self.poll_interval = poll_interval
        self.timeout = timeout
        self.history_seconds = history_seconds
        self.master_factory = master_factory
        self.master = None
        self.state = "disconnected"  # connected, lost, lent (to a test run)
        self.lent_to = ""  # who has the port while lent
        self._lent_abort = None  # called by STOP / EMERGENCY STOP while lent
        self.move_fields = dict(MOVE_DEFAULTS)  # the last values moved with (as typed), for every tab
        self.last_move = ("abs", 1)  # the last move button used: what Enter repeats, in every tab
        self.move_seq = 0  # bumped by every move sent, so every tab takes its fields again
        self.url = ""
        self.baud = 115200
        self.ver8 = None  # None: each slave's Ver6/Ver8 detected; True/False: one framing forced
        self.lost_reason = ""
        self.safety_notice = ""  # what the jig's safety stop did before this Desk connected (the header says it)
        self._next_reconnect = 0.0
        self.slaves = {}  # id -> {"id", "type", "type_name", "version", "jig", "variant"}
        self.scan_progress = None  # (id being probed, last id) while a scan runs
        self.axis = None
        self.status = None  # last AllStatus of the axis, or None
        self.status_time = 0.0
        self.status_error = ""
        self.polls = 0
        self.history = collections.deque()
        self.log_polls = False
        self.motion_test = {"running": False, "moves": [], "summary": ""}
        self._log = collections.deque(maxlen=log_size)
        self._seq = 0
        self._lock = threading.RLock()  # the bus: one request on the line at a time
        self._log_lock = threading.Lock()
        self._abort = threading.Event()
        self._polling = False
        self._jog_gen = 0  # bumped by every jog release
        self._seen_errors = {}
        self._decoder = Decoder()
        self._stop = threading.Event()
        self._poller = None
        self.viewers = 0

    # --- log ---------------------------------------------------------------------------
    def log(self, kind, text):
        with self._log_lock:
            self._seq += 1
            self._log.append(LogEntry(self._seq, time.time(), kind, text))

    def log_since(self, seq):
        with self._log_lock:
            return [e for e in self._log if e.seq > seq]

    def clear_log(self):
        with self._log_lock:
            self._log.clear()

    def log_text(self):
        with self._log_lock:
            entries = list(self._log)
        return "".join("%s  %-5s %s\n" % (stamp(e.t), e.kind.upper(), e.text) for e in entries)

    def _trace(self, direction, item):
        if self._polling and not self.log_polls:
            return
        if direction == "tx":
            fr, why = wire_frame(item)
            text = self._decoder.describe(fr, _kind(fr)) if fr is not None else "(%s)" % why
            self.log("tx", "%s   [wire %s]" % (text, bytes(item).hex(" ")))
        else:  # what the master receives is a reply: the bus master sends every request
            self.log("rx", "%s   [body %s]" % (self._decoder.describe(item, "reply"), item.body.hex(" ")))

    def _note_line_errors(self):
        p = self.master.parser if self.master is not None else None
        if p is None:
            return
        for name, text in LINE_ERRORS:
            now = getattr(p, name, 0)
            n = now - self._seen_errors.get(name, 0)
            if n > 0:
                self.log("line", "received %d %s%s" % (n, text, "s" if n > 1 else ""))
            self._seen_errors[name] = now

    # --- connection --------------------------------------------------------------------
    @property
    def connected(self):
        return self.state == "connected"

    @command("Connect")
    def connect(self, url, baud=115200, ver8=None):
        """Open the port and look for the jig; returns a sentence saying what answered.
        ver8: None detects each slave's variant (as jigctl does), True/False force one."""
        return self._open(url, baud, ver8)

    def _open(self, url, baud=115200, ver8=None):
        self._not_lent()
        url = str(url or "").strip()
        if not url:
            raise UserError("choose a serial port or type a pyserial URL (socket://host:port)")
        baud = forms.number(baud, "baud rate")
        if baud not in BAUD_RATES:
            raise UserError("baud rate %d is not one the drives support (%s)" % (
                baud, ", ".join(map(str, BAUD_RATES))))
        self._close(quiet=True)
        with self._lock:
            try:
                m = self.master_factory(url, baud=baud, ver8=ver8, trace=self._trace, timeout=self.timeout)
            except PortError as exc:
                raise UserError(str(exc)) from None
            self.master, self.url, self.baud, self.ver8 = m, url, baud, ver8
            self._seen_errors = {name: getattr(m.parser, name, 0) for name, _ in LINE_ERRORS}
            self.state = "connected"
            self.lost_reason = ""
            self.status = None
            self.history.clear()
            self.log("info", "connected to %s at %d baud (%s)" % (
                url, baud, "Ver6/Ver8 detected per slave" if ver8 is None else protocol_name(ver8)))
            try:
                alive = any(m.is_slave_exist(i) for i in (1, 2, 3))
            except PortError as exc:
                self._lose(exc)
                raise UserError(self.lost_message()) from None
            # What a killed run left behind, said once (the jig forgets it when asked: a read-only
            # Desk leaves it to whoever connects to act)
            notice = safetynotice.take(m, self.jig_id()) if alive and not self.read_only else None
        if notice:
            self.safety_notice = notice
            self.log("warning", "note: " + notice)
        if not alive:
            msg = ("connected to %s, but nothing answers on the bus (silent port: check the baud rate, the "
                   "Ver6/Ver8 setting (now %s: the protocol choice beside the baud rate), the wiring and that "
                   "the jig is powered)%s" % (
                       url, "auto, each slave's variant detected" if ver8 is None else protocol_name(ver8),
                       "" if self.read_only else "; press Scan to look again"))
            self.log("error", msg)
            return msg
        # a read-only Desk refuses Scan (it sends nothing): it watches the axis the page shows
        return "connected to %s%s" % (url, "" if self.read_only else "; press Scan to find the slaves")

    @command("Disconnect")
    def disconnect(self, quiet=False):
        self._not_lent()
        self._close(quiet)

    def _close(self, quiet=False):
        self._abort.set()
        with self._lock:
            m, self.master = self.master, None
            if m is not None:
                m.close()
                if not quiet:
                    self.log("info", "disconnected from %s" % self.url)
            if self.state == "connected" or not quiet:
                self.state = "disconnected"
            self.status = None
        self._abort.clear()

    def reconnect(self):
        """Open the last connection again (allowed read-only too: it sends nothing that moves)."""
        if not self.url:
            raise UserError("nothing to reconnect to: connect first")
        msg = self._open(self.url, self.baud, self.ver8)
        if self.read_only and not self.slaves and self.connected:  # it never got to its first scan
            self._scan(1, F.MAX_SLAVE_ID)
        return msg

    def watch(self, url, baud=115200, ver8=None, why=""):
        """A read-only Desk whose port did not open at start: remember it as lost, so it
        connects by itself once the port answers."""
        self.url, self.baud, self.ver8 = str(url), baud, ver8
        self.state, self.lost_reason = "lost", str(why) or "the port did not open"

    def _auto_reconnect(self):
        """Read-only: a lost connection is tried again every RECONNECT_EVERY seconds."""
        if not self.read_only or self.state != "lost" or not self.url:
            return
        now = time.monotonic()
        if now < self._next_reconnect:
            return
        self._next_reconnect = now + RECONNECT_EVERY
        try:
            self.reconnect()
        except UserError:
            if self.state != "connected":
                self.state = "lost"  # still lost; the banner keeps the first reason

    def _lose(self, exc):
        self.state = "lost"
        self.lost_reason = str(exc)
        if self.master is not None:
            try:
                self.master.close()
            except Exception:
                pass
        self.master = None
        self.status = None
        self.log("error", self.lost_message())

    def lost_message(self):
        return "connection lost: %s. Check the cable or the bench, then press Reconnect." % (
            self.lost_reason.rstrip("."))

    def _not_lent(self):
        if self.state == "lent":
            raise UserError("the port is with %s: wait until it ends, or press Abort" % self.lent_to)

    def lend_port(self, who, abort):
        """Close the Master so ``who`` (a test run) can open the port itself; returns (url, baud).

        Until ``take_port_back`` the poller pauses and every command is refused with a
        sentence; STOP and EMERGENCY STOP call ``abort`` instead.
        """
        if self.read_only:
            raise UserError("a test run refused: this Desk is read-only (--read-only)")
        if self.motion_test["running"]:
            raise UserError("a motion test is running: stop it first")
        if self.scan_progress is not None:
            raise UserError("a scan is running: wait for it to end")
        with self._lock:
            self._not_lent()
            if self.state == "lost":
                raise UserError(self.lost_message())
            if self.master is None:
                raise UserError("not connected: connect to the bus first (Connect & bus)")
            m, self.master = self.master, None
            try:
                m.close()
            except Exception:
                pass
            self.state, self.lent_to, self._lent_abort = "lent", who, abort
            self.status = None
            self.log("info", "port %s handed to %s" % (self.url, who))
        return self.url, self.baud

    def take_port_back(self):
        """Open the port again after a test run; returns a sentence."""
        with self._lock:
            if self.state != "lent":
                return ""
            who = self.lent_to
            self.lent_to, self._lent_abort = "", None
            try:
                m = self.master_factory(self.url, baud=self.baud, ver8=self.ver8, trace=self._trace,
                                        timeout=self.timeout)
            except PortError as exc:
                self.state = "lost"
                self.lost_reason = "after %s: %s" % (who, exc)
                self.log("error", self.lost_message())
                return self.lost_message()
            self.master = m
            self._seen_errors = {name: getattr(m.parser, name, 0) for name, _ in LINE_ERRORS}
            self.state = "connected"
            self.log("info", "port %s back from %s" % (self.url, who))
            return "connected to %s again" % self.url

    def _bus(self, fn, *args, polling=False, watch=False):
        """Run fn(master, *args) with the bus to ourselves; failures become UserError.
        Read-only, only the poller's reads and a scan (watch: the caller checked) pass."""
        if self.read_only and not (polling or watch):
            raise UserError("refused: this Desk is read-only (--read-only)")
        with self._lock:
            self._not_lent()
            if self.state == "lost":
                raise UserError(self.lost_message())
            if self.master is None:
                raise UserError("not connected: choose a port and press Connect")
            self._polling = polling
            try:
                return fn(self.master, *args)
            except PortError as exc:
                self._lose(exc)
                raise UserError(self.lost_message()) from None
            except MotionRefusedError as exc:
                flags = AxisStatus(self.status.axis).flags if self.status is not None else ()
                if "emergency_stop" in flags:
                    raise UserError("%s. %s" % (exc, ESTOP_RECOVERY)) from None
                raise UserError(str(exc)) from None
            except (JigError, ValueError) as exc:
                raise UserError(str(exc)) from None
            finally:
                self._polling = False
                self._note_line_errors()

    # --- bus scan ------------------------------------------------------------------------
    @staticmethod
    def _row(i, info, variant=None):
        """A scan row; variant: 6 or 8 (detected, or the forced framing), None when unknown."""
        if info is None:
            return {"id": i, "type": None, "type_name": "answered with an error", "version": "", "jig": False,
                    "variant": variant}
        return {"id": i, "type": info.type, "type_name": info.type_name, "version": info.version,
                "jig": info.type == D.SLAVE_TYPE, "variant": variant}

    def _variant(self, m, slave):
        """slave's variant as the Master knows it (6 or 8), or None."""
        if m.ver8 is not None:
            return 8 if m.ver8 else 6
        return m.variants.get(slave)

    @command("Scan")
    def scan(self, first=0, last=F.MAX_SLAVE_ID):
        """GetSlaveInfo to every id (one request per lock hold), each slave in its own
        variant (detected, as `jigctl scan`); returns the rows found."""
        return self._scan(first, last)

    def _scan(self, first=0, last=F.MAX_SLAVE_ID):
        first, last = forms.slave_id(first, "first id"), forms.slave_id(last, "last id")
        found = {}
        self._abort.clear()
        try:
            for i in range(first, last + 1):
                if self._abort.is_set():
                    raise UserError("scan stopped at id %d" % i)
                self.scan_progress = (i, last)
                res = self._bus(lambda m, i=i: {sid: (info, self._variant(m, sid))
                                                for sid, info in m.scan(ids=(i,)).items()}, watch=True)
                for sid, (info, variant) in res.items():
                    found[sid] = self._row(sid, info, variant)
        finally:
            self.scan_progress = None
        self.slaves = found
        self.log("info", "scan: %d slave(s) found: %s" % (len(found), ", ".join(
            "%d %s%s" % (r["id"], r["type_name"], " (Ver%d)" % r["variant"] if r["variant"] else "")
            for r in found.values()) or "none"))
        self._pick_driver()
        return list(found.values())

    @command("Scan via jig")
    def scan_via_jig(self):
        """The jig's own bus scan (0xF2/0xF3), then GetSlaveInfo to what it found."""
        jig = self.jig_id()
        res = self._bus(lambda m: m.jig_bus_scan(jig, timeout=5.0))

        def info(sid):
            return self._bus(lambda m: (m.get_slave_info(sid), self._variant(m, sid)))

        found = {jig: self._row(jig, *info(jig))}
        for sid in sorted(res.types):
            if sid != jig:
                found[sid] = self._row(sid, *info(sid))
        self.slaves = found
        self.log("info", "scan via jig: ids %s answered on the driver bus" % (
            ", ".join(map(str, sorted(res.types))) or "none"))
        self._pick_driver()
        return list(found.values())

    def jig_id(self):
        for r in self.slaves.values():
            if r["jig"]:
                return r["id"]
        return 1

    def is_jig(self, slave):
        """The jig: slave 1 (its id on every bench and board) or the id that answered as the jig."""
        row = self.slaves.get(slave)
        return slave == 1 or slave == self.jig_id() or bool(row and row["jig"])

    def drivers(self):
        """The scan rows that may be an axis (never the jig), in id order."""
        return [r for r in self.slaves.values() if not self.is_jig(r["id"])]

    def _pick_driver(self):
        """Keep the axis if it is still a driver on the bus, else the first driver that told its type."""
        ids = [r["id"] for r in self.drivers()]
        if self.axis not in ids:
            typed = [r["id"] for r in self.drivers() if r["type"] is not None]
            self.axis = (typed or ids or [None])[0]
            self.status = None
            self.history.clear()

    def variant_of(self, slave):
        """6 or 8 for a slave whose variant is known (scan, or the forced framing), else None."""
        if self.ver8 is not None:
            return 8 if self.ver8 else 6
        row = self.slaves.get(slave)
        if row and row.get("variant"):
            return row["variant"]
        m = self.master
        return m.variants.get(slave) if m is not None else None

    def select_axis(self, slave):
        """Choose the axis to show and work with (read-only too: watching is not moving);
        the jig is refused."""
        slave = forms.slave_id(slave)
        if self.is_jig(slave):
            raise UserError("slave %d is the jig, not a motor driver: pick a driver (the jig's parameters "
                            "and I/O: type its id in those tabs)" % slave)
        if slave != self.axis:
            self.axis = slave
            self.status = None
            self.history.clear()
        return slave

    def axis_is_jig(self):
        return self.axis is not None and self.is_jig(self.axis)

    def axis_is_servo(self):
        row = self.slaves.get(self.axis)
        return bool(row and row["type"] in N.SERVO_TYPES)

    def _need_axis(self):
        if self.axis is None:
            raise UserError("no axis selected: scan the bus and pick a driver")
        return self.axis

    def _need_driver(self):
        a = self._need_axis()
        if self.axis_is_jig():
            raise UserError("slave %d is the jig, not a motor driver: pick a driver" % a)
        return a

    # --- polling ------------------------------------------------------------------------------
    def start(self):
        if self._poller is None:
            self._poller = threading.Thread(target=self._poll_loop, name="desk-poller", daemon=True)
            self._poller.start()
        return self

    def stop(self):
        self._stop.set()
        if self._poller is not None:
            self._poller.join(2.0)
            self._poller = None
        abort = self._lent_abort
        if abort is not None:  # the server stops during a test run: end it safely
            abort()
        self._close(quiet=True)

    def _poll_loop(self):
        while not self._stop.wait(self.poll_interval):
            self._auto_reconnect()
            self.poll_once()

    def poll_once(self):
        """One status read of the selected axis, unless a command holds the bus; True when read."""
        a = self.axis
        if not self.connected or a is None or self.viewers <= 0 and self._poller is not None:
            return False
        if not self._lock.acquire(blocking=False):
            return False  # a command is on the line: polling waits
        try:
            st = self._bus(lambda m: m.get_all_status(a), polling=True)
        except UserError as exc:
            self.status_error = str(exc)
            return False
        finally:
            self._lock.release()
        if a != self.axis:
            return False
        now = time.time()
        self.status, self.status_time, self.status_error = st, now, ""
        self.polls += 1
        self.history.append(Sample(now, st.command_pos, st.actual_pos, st.actual_vel))
        while self.history and self.history[0].t < now - self.history_seconds:
            self.history.popleft()
        return True

    def status_view(self):
        """The axis panel's content as plain values (None when nothing was read yet)."""
        st = self.status
        if st is None:
            return None
        axis = AxisStatus(st.axis)
        jig = self.axis_is_jig()
        return {
            "command_pos": st.command_pos, "actual_pos": st.actual_pos, "pos_error": st.pos_error,
            "actual_vel": st.actual_vel, "flags": set(axis.flags), "errors": set(axis.errors),
            "inputs": N.bit_names(st.inputs, () if jig else N.INPUT_BITS),
            "outputs": N.bit_names(st.outputs, () if jig else N.OUTPUT_BITS),
            "age": time.time() - self.status_time,
        }

    def poll_rate(self):
        """Status reads per second over the last two seconds (what the axis panel refreshes at)."""
        rows = list(self.history)
        if len(rows) < 2:
            return 0.0
        recent = [r.t for r in rows if r.t >= rows[-1].t - 2.0]
        span = recent[-1] - recent[0]
        return (len(recent) - 1) / span if span > 0 else 0.0

    def history_rows(self, seconds=None):
        rows = list(self.history)
        if seconds and rows:
            rows = [r for r in rows if r.t >= rows[-1].t - seconds]
        return rows

    def history_csv(self):
        """The plot's samples: local ISO time, seconds from the first sample, the slave."""
        out = io.StringIO()
        w = csv.writer(out)
        w.writerow(["time", "t_s", "slave", "command_pos", "actual_pos", "actual_vel_pps"])
        rows = list(self.history)
        t0 = rows[0].t if rows else 0.0
        for r in rows:
            when = datetime.datetime.fromtimestamp(r.t).astimezone().isoformat(timespec="milliseconds")
            w.writerow([when, "%.3f" % (r.t - t0), self.axis, r.command_pos, r.actual_pos, r.actual_vel])
        return out.getvalue()

    # --- drive control and motion ---------------------------------------------------------------
    @command("Servo on/off")
    def servo(self, on):
        a = self._need_driver()
        self._bus(lambda m: m.servo_enable(a, bool(on)))
        return "slave %d: servo %s" % (a, "on" if on else "off")

    @command("Servo off and on")
    def recover_estop(self):
        """Servo off, then on: what clears a drive's latched emergency stop."""
        a = self._need_driver()
        self._bus(lambda m: m.servo_enable(a, False))
        self._bus(lambda m: m.servo_enable(a, True))
        self.log("info", "slave %d: servo off and on again (clears the emergency stop)" % a)
        return "slave %d: servo off and on again" % a

    @command("Alarm reset")
    def alarm_reset(self):
        a = self._need_driver()
        servo = self.axis_is_servo()
        self._bus(lambda m: m.alarm_reset(a, servo=servo))
        return "slave %d: alarm reset sent" % a

    @command("STOP AXIS")
    def stop_axis(self):
        """Decelerating stop of the selected axis; also ends a running job (a test run: Abort)."""
        if self._abort_lent():
            return "test run aborted: emergency stop and servo off"
        self._abort.set()
        a = self._need_driver()
        self._bus(lambda m: m.move_stop(a))
        self.log("info", "STOP AXIS sent to slave %d" % a)
        return "slave %d: stop" % a

    def _abort_lent(self):
        abort = self._lent_abort if self.state == "lent" else None
        if abort is None:
            return False
        self.log("info", "STOP / EMERGENCY STOP during %s: aborting it" % self.lent_to)
        abort()
        return True

    @command("EMERGENCY STOP")
    def emergency_stop(self):
        """EMERGENCY STOP: broadcast to every axis, then to the selected one with a reply."""
        if self._abort_lent():
            return "test run aborted: emergency stop and servo off"
        self._abort.set()
        a = self.axis if self.axis is not None and not self.axis_is_jig() else None

        def both(m):
            m.all_emergency_stop()
            if a is not None:
                m.emergency_stop(a)

        self._bus(both)
        self.log("info", "EMERGENCY STOP sent to all axes%s" % ("" if a is None else " and slave %d" % a))
        return "EMERGENCY STOP sent"

    @command("Move")
    def move(self, kind, target, speed, accel="", decel="", sign=1):
        """Move absolute ('abs') or incremental ('inc'); acc/dec times use the EX frames.
        sign -1 is Move DEC: a button named for a direction moves that way only, so it moves
        down by the distance's magnitude whatever its sign (-5000 and 5000 alike). The
        fields are kept as typed with the button used, so every tab (and a reload) shows
        the very field, sign and Enter button of the move that was sent."""
        a = self._need_driver()
        if (kind, 1 if sign >= 0 else -1) not in MOVES:
            raise UserError("unknown move %r" % kind)
        sign = 1 if sign >= 0 else -1
        fields = {"target": str(target), "speed": str(speed), "acc": str(accel or ""), "dec": str(decel or "")}
        target = forms.position(target, "position" if kind == "abs" else "distance")
        if sign < 0:
            target = forms.position(-abs(target), "distance")
        speed = forms.speed(speed)
        acc, dec = forms.accel(accel, "acceleration time"), forms.accel(decel, "deceleration time")
        with self._log_lock:
            self.move_fields, self.last_move = fields, (kind, sign)
            self.move_seq += 1
        self._abort.clear()
        if kind == "abs":
            fn = (lambda m: m.move_abs_ex(a, target, speed, acc, dec)) if acc or dec else \
                (lambda m: m.move_abs(a, target, speed))
        elif kind == "inc":
            fn = (lambda m: m.move_inc_ex(a, target, speed, acc, dec)) if acc or dec else \
                (lambda m: m.move_inc(a, target, speed))
        else:
            raise UserError("unknown move %r" % kind)
        self._bus(fn)
        return "slave %d: move %s %d at %d pps" % (a, kind, target, speed)

    @command("Jog")
    def jog(self, direction, speed):
        """Start jogging (press); a release that reaches the bus first cancels it."""
        a = self._need_driver()
        speed = forms.speed(speed, "jog speed")
        gen = self._jog_gen

        def start(m):
            if self._jog_gen == gen:
                m.move_velocity(a, speed, 1 if direction > 0 else 0)

        self._bus(start)
        return "slave %d: jog %s" % (a, "+" if direction > 0 else "-")

    @command("Jog")
    def jog_release(self):
        self._jog_gen += 1
        a = self._need_driver()
        self._bus(lambda m: m.move_stop(a))
        return "slave %d: jog released" % a

    @command("Home")
    def home(self):
        a = self._need_driver()
        self._bus(lambda m: m.move_origin(a))
        return "slave %d: origin search started" % a

    @command("Move to limit")
    def to_limit(self, direction, speed):
        a = self._need_driver()
        speed = forms.speed(speed)
        self._bus(lambda m: m.move_to_limit(a, speed, 1 if direction > 0 else 0))
        return "slave %d: to limit %s" % (a, "+" if direction > 0 else "-")

    @command("Clear position")
    def clear_position(self):
        a = self._need_driver()
        self._bus(lambda m: m.clear_position(a))
        return "slave %d: position cleared" % a

    # --- motion test (the checks of `jigctl motion-test`) ------------------------------------------
    @command("The motion test")
    def run_motion_test(self, cycles, distance, speed, move_timeout=30.0):
        """Out-and-back cycles with per-move pass/fail; blocks until done (run it in a thread).
        It ends at the first lost connection, or at STOP / EMERGENCY STOP."""
        a = self._need_driver()
        args = SimpleNamespace(cycles=forms.number(cycles, "cycles", 1, 1000),
                               distance=forms.distance(distance),
                               speed=forms.speed(speed), move_timeout=move_timeout, json=True,
                               stop_on_fail=False)
        moves = []
        with self._log_lock:  # two tabs pressing Start at once: one test runs
            if self.motion_test["running"]:
                raise UserError("a motion test is already running")
            self.motion_test = {"running": True, "moves": moves, "summary": "running"}
        self._abort.clear()
        self.log("info", "motion test: %d cycles of +/-%d at %d pps on slave %d" % (
            args.cycles, args.distance, args.speed, a))
        try:
            _motion_cycles(args, _JobMaster(self, args), a, moves)
        finally:
            passed = sum(1 for r in moves if r["ok"])
            why = (" (connection lost)" if self.state == "lost" else " (stopped)" if self._abort.is_set()
                   else "")
            summary = "%d of %d moves passed%s" % (passed, len(moves), why)
            verdict = "PASS" if passed == len(moves) == 2 * args.cycles else "FAIL"
            self.motion_test = {"running": False, "moves": moves, "summary": "%s: %s" % (verdict, summary)}
            self.log("info", "motion test %s: %s" % (verdict, summary))
        return self.motion_test["summary"]

    # --- parameters ---------------------------------------------------------------------------------
    def param_table(self, slave=None):
        slave = self.axis if slave is None else slave
        if slave is not None and self.is_jig(slave):
            return "jig", N.jig_params()
        return "drive", N.STEP_PARAMS

    @command("Reading the parameters")
    def read_params(self, slave=None):
        """Every parameter's RAM and ROM value (one request per lock hold)."""
        slave = self._need_axis() if slave is None else forms.slave_id(slave)
        which, table = self.param_table(slave)
        rows = []
        for p in table:
            ram = self._optional(lambda m: m.get_parameter(slave, p.number))
            rom = self._optional(lambda m: m.get_rom_parameter(slave, p.number))
            full = (p.min, p.max) == forms.I32
            rows.append({"number": p.number, "name": p.name, "unit": p.unit,
                         "range": "unconfirmed" if full else "%s..%s" % (p.min, p.max),
                         "ram": "-" if ram is None else ram, "rom": "-" if rom is None else rom,
                         "effect": p.effect or "", "meaning": p.meaning or ""})
        return which, rows

    def _optional(self, fn):
        try:
            return self._bus(fn)
        except UserError:
            if self.state == "lost":
                raise
            return None

    @command("Writing a parameter")
    def write_param(self, slave, key, value):
        slave = forms.slave_id(slave)
        which, table = self.param_table(slave)
        p = N.find_param(table, str(key).strip())
        if p is None:
            raise UserError("no parameter %r in the %s table" % (key, which))
        value = forms.number(value, "value of %s" % p.name)
        try:
            p.check(value)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        self._bus(lambda m: m.set_parameter(slave, p.number, value))
        back = self._bus(lambda m: m.get_parameter(slave, p.number))
        self.log("info", "slave %d parameter %d %s = %d (RAM)" % (slave, p.number, p.name, back))
        return back

    @command("Saving the parameters")
    def save_params(self, slave):
        slave = forms.slave_id(slave)
        self._bus(lambda m: m.save_all_parameters(slave))
        self.log("info", "slave %d: parameters saved to ROM" % slave)
        return "slave %d: parameters saved to ROM" % slave

    # --- I/O ----------------------------------------------------------------------------------------
    @command("Reading the I/O")
    def io_bits(self, slave=None):
        """(input rows, output rows) of (bit, name, on) for the drive's or the jig's I/O."""
        slave = self._need_axis() if slave is None else slave
        jig = self.param_table(slave)[0] == "jig"
        inputs = self._bus(lambda m: m.get_io_input(slave))
        outputs = self._bus(lambda m: m.get_io_output(slave))
        if jig:
            in_names = [(b, "in%d" % b) for b in range(16)]
            out_names = [(b, "out%d" % b) for b in range(16)]
        else:
            in_names = [(r[0], r[1]) for r in N.INPUT_BITS]
            out_names = [(r[0], r[1]) for r in N.OUTPUT_BITS]
        return ([(b, n, bool(inputs >> b & 1)) for b, n in in_names],
                [(b, n, bool(outputs >> b & 1)) for b, n in out_names])

    @command("Switching an output")
    def set_output(self, slave, bit, on):
        mask = 1 << forms.number(bit, "output bit", 0, 31)
        self._bus(lambda m: m.set_io_output(slave, mask if on else 0, 0 if on else mask))
        return "slave %d output bit %d %s" % (slave, bit, "on" if on else "off")

    # --- jig diagnostics ----------------------------------------------------------------------------
    @command("Reading the counters")
    def counters(self):
        jig = self.jig_id()
        return self._bus(lambda m: m.read_counters(jig))

    @command("Resetting the counters")
    def reset_counters(self):
        jig = self.jig_id()
        self._bus(lambda m: m.reset_counters(jig))
        self.log("info", "jig counters reset")
        return "jig counters reset"

    @command("Reading the crash log")
    def crash_log(self):
        jig = self.jig_id()
        return self._bus(lambda m: m.read_crash_log(jig)) or "no crash recorded (or none kept here)"

    @command("Reading the bus-scan result")
    def bus_scan_result(self):
        jig = self.jig_id()
        res = self._bus(lambda m: m.get_bus_scan_result(jig))
        return "%s: %s" % (res.state, ", ".join("id %d type %d" % kv for kv in sorted(res.types.items())) or "no ids")

    # --- raw frames -----------------------------------------------------------------------------------
    @command("Sending a raw frame")
    def send_raw(self, slave, ftype, data_hex="", corrupt=False, wire_hex="", timeout=None):
        """Send one frame (or wire bytes as typed) and log every frame that comes back."""
        timeout = self.timeout if timeout is None else timeout
        if str(wire_hex or "").strip():
            wire = forms.hex_bytes(wire_hex, "wire bytes")
            want = None
        else:
            slave = forms.slave_id(slave)
            ftype = forms.hex_byte(ftype, "frame type")
            data = forms.hex_bytes(data_hex, "data")
            if len(data) > F.MAX_DATA:
                raise UserError("too much data for one frame (at most %d bytes)" % F.MAX_DATA)
            want = (slave, ftype)

        def exchange(m):
            nonlocal wire
            if want is not None:  # in the slave's own variant as known (no probe of ours on the line)
                known = m.variants
                if m.ver8 is not None:
                    v8 = bool(m.ver8)
                elif slave == F.BROADCAST_ID:
                    v8 = 8 in known.values()
                else:
                    v8 = known.get(slave) == 8
                    if slave not in known:
                        self.log("info", "slave %d's Ver6/Ver8 variant is not known yet (Scan detects it): "
                                         "framed as Ver6" % slave)
                wire = F.encode(slave, ftype, data, m.next_sync(slave) if v8 else -1)
            if corrupt:
                wire = forms.corrupt_crc(wire)
            fr, why = wire_frame(wire)
            if fr is None:
                self.log("tx", "(%s: the receiver will drop it)   [wire %s]" % (why, wire.hex(" ")))
            m.discard_input()
            saved, m.trace = m.trace, None
            try:
                m.write(wire)
            finally:
                m.trace = saved
            if fr is not None:
                self.log("tx", "%s   [wire %s]" % (self._decoder.describe(fr, _kind(fr)), wire.hex(" ")))
            end = time.monotonic() + timeout
            got = 0
            while True:
                left = end - time.monotonic()
                if left <= 0:
                    break
                r = m.read_frame(left)
                if r is None:
                    break
                got += 1
                if want is None or (r.slave, r.ftype) == want:
                    break
            return got

        got = self._bus(exchange)
        if not got:
            self.log("info", "no frame came back within %d ms" % round(timeout * 1000))
            return "sent; no frame came back"
        return "sent; %d frame(s) received" % got


class _JobMaster:
    """The Master as a long job sees it: each call takes the bus lock on its own, and
    STOP / EMERGENCY STOP end the job between two calls."""

    def __init__(self, session, args):
        self._s = session
        self._args = args

    def __getattr__(self, name):
        def call(*a, **kw):
            if self._s._abort.is_set():
                self._args.stop_on_fail = True
                raise Aborted("stopped by the operator")
            try:
                return self._s._bus(lambda m: getattr(m, name)(*a, **kw))
            except UserError as exc:
                if self._s.state != "connected":  # lost (or lent): no further move can reach the drive
                    self._args.stop_on_fail = True
                raise JigError(str(exc)) from None
        return call

    def wait_motion_done(self, slave, timeout=10.0, poll=0.02):
        # Master's own loop, with each status read going through the lock (above).
        return Master.wait_motion_done(self, slave, timeout, poll)


def _kind(sent):
    return "broadcast" if sent.slave == F.BROADCAST_ID else "request"


def stamp(t):
    return time.strftime("%H:%M:%S", time.localtime(t)) + ".%03d" % int(t % 1 * 1000)


__all__ = ["BusSession", "UserError", "Aborted", "LogEntry", "Sample", "wire_frame", "stamp", "ESTOP_RECOVERY",
           "MOVE_DEFAULTS"]
