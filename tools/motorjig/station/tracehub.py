"""The jig's sampler shared by every slot that talks through one Master (multi-up, issue 34).

Several slots test their drives at once, each OpenHTF run in a thread of its own, all
through one ``plug.TimedMaster``. The jig has one sampler, which polls a *set* of drives
in turn (docs/bridge.md, "The jig's own sampler"); the hub owns it for all of them:

* ``join(slave, period_us)`` adds a slot's drive to the jig's set; the others keep
  sampling. ``take(slave)`` returns that drive's samples since its last take: it reads
  the jig's ring for everyone (tagged ReadTrace) and keeps the other drives' samples for
  their own takes. ``leave(slave)`` takes the drive out and returns its figures since it
  joined (the last one out stops the jig's sampler).
* Times: the hub unfolds the jig's 30-bit ticks once for all; a drive's samples and the
  instants of its commands (``time_us``) are µs since its own join, as a single drive's
  were since StartTrace.
* One lock: a take reads for every slot while the others wait for it, and then finds its
  samples already read. Requests go through the Master, whose own lock serialises them.
  The ring is read at most once a sampler period for one drive, and at most every
  ``READ_PERIODS`` periods with several (19 ms at 115 200 baud, 4 ms at 921 600), however many
  slots ask (each slot asks again
  after half its own drive's interval): every PC frame that reaches the jig as a slot falls
  due delays that slot (the PC goes first), and at 115 200 baud a transaction fills 4.56 ms
  of the 4.75 ms period, so delays pile up into skipped slots (read once a period, about 5 %
  of them on the real-time bench at 115 200 baud; at 921 600 baud none).

A jig whose firmware samples one drive only (it answers GetTraceStatus for one drive
0x82) is used the way it always was (StartTrace / ReadTrace / StopTrace), by one slot at a
time: ``claim`` gives the sampler to the first slot whose moving step begins, until that
step ends; the moving steps of the other slots meanwhile are sampled by this PC
(``sampling.new_trace`` gives them a ``PcTrace``, and their traces say so).
"""

import threading
import time

from jig import diag as D
from jig import frame as F
from jig.compat import ticks_diff
from motorjig.errors import BadReplyError, JigError, StatusError
from motorjig.master import AxisStatus, TraceSample

_HUBS_LOCK = threading.Lock()
READ_PERIODS = 4  # while several drives are sampled, the ring is read at most every this many periods


def hub_for(master, jig=1):
    """The hub of the jig ``jig`` behind ``master`` (one per Master and jig, made at the first call)."""
    with _HUBS_LOCK:
        hubs = master.__dict__.setdefault("_trace_hubs", {})
        hub = hubs.get(jig)
        if hub is None:
            hub = hubs[jig] = TraceHub(master, jig)
        return hub


class _Member:
    __slots__ = ("t0", "samples")

    def __init__(self, t0):
        self.t0 = t0  # its join on the hub's time base, µs
        self.samples = []  # read for it, not taken yet


class TraceHub:
    def __init__(self, master, jig):
        self.m, self.jig = master, jig
        self.lock = threading.Lock()
        self.multi = None  # True: the jig samples a set; False: one drive; None: not asked yet
        self.owner = None  # (one drive) the slave whose step has the sampler
        self.members = {}  # slave -> _Member
        self.next = 0  # the ring index to read next
        self.raw, self.t = 0, 0  # the newest tick read and its unfolded µs
        self.period_us = 0  # the sampler's period (the last join's)
        self.t_read = 0.0  # (monotonic) when the last read ended

    def sets(self):
        """True when the jig's firmware samples a set of drives (asked once)."""
        if self.multi is None:
            try:
                self.m.trace_drive_status(0, self.jig)
                self.multi = True
            except StatusError as exc:
                if exc.status != F.STATUS_FRAME_ERROR:
                    raise
                self.multi = False  # a jig from before the set: the request's length is wrong to it
            except AttributeError:
                self.multi = False  # a Master without the set's methods
        return self.multi

    def claim(self, slave):
        """True when slave's step may have the jig sample it: always with a set; with a
        single-drive jig, when no other slot's step has the sampler (it is slave's then,
        until ``leave`` or ``release``)."""
        with self.lock:
            if self.sets():
                return True
            if self.owner in (None, slave):
                self.owner = slave
                return True
            return False

    def release(self, slave):
        """Give up a claim without leaving (the step never joined)."""
        with self.lock:
            if self.owner == slave:
                self.owner = None
            self.members.pop(slave, None)

    def join(self, slave, period_us):
        """Make the jig sample slave (``claim`` first)."""
        with self.lock:
            if not self.sets():
                if self.owner != slave:
                    raise JigError("the jig samples one drive at a time and another slot's step has it")
                self.m.trace_start(slave, period_us, jig=self.jig)
                self.members[slave] = _Member(0)  # (the Master unfolds the single trace's ticks)
                return
            r = self.m.trace_join(slave, period_us, jig=self.jig)
            self.period_us = period_us
            if not self.members:  # none of ours in the ring: read from its oldest sample on
                self.next = r["first"]
                self.raw, self.t = r["tick"], 0
            elif r["started"]:
                self.next = r["first"]  # (the jig lost the others' set: a reset; they see a gap)
            self.members[slave] = _Member(self._unfold(r["tick"]))

    def _unfold(self, tick):
        return self.t + ticks_diff(tick, self.raw)

    def take(self, slave):
        """slave's samples read since its last take (TraceSample, t_us since its join)."""
        with self.lock:
            if not self.multi:
                return self.m.trace_read(self.jig)
            mine = self.members.get(slave)
            if mine is None:
                raise JigError("slave %d's samples were asked for before it joined the jig's trace" % slave)
            if not mine.samples and time.monotonic() - self.t_read >= self._read_interval_s():
                self._read()
                self.t_read = time.monotonic()
            out, mine.samples = mine.samples, []
            return out

    def _read_interval_s(self):
        """How often the ring is read: once a period for one drive (as before the set); with
        several, every READ_PERIODS periods at most, since each read's request, arriving at the jig as
        a slot falls due, delays that slot (the PC goes first) and at 115 200 baud the delays pile
        up into skipped slots (the dates stay the jig's: only the rate suffers)."""
        period = self.period_us / 1e6
        return period if len(self.members) < 2 else READ_PERIODS * period

    def drives(self):
        """The drives sampled now (at least 1): each gets a sample every that many periods."""
        return max(1, len(self.members))

    def _read(self):
        """Every sample the ring holds, chunk by chunk, each to its drive's member."""
        stale = 0
        while True:
            _state, nxt, rows = self.m.trace_read_tagged(self.next, self.jig)
            if (nxt - len(rows)) & 0xFFFF != self.next:
                # A late reply to an earlier read (one that timed out here and was sent again):
                # Ver6 frames carry no sequence number, the from-index tells.
                stale += 1
                if stale > 50:
                    raise BadReplyError("slave %d keeps answering ReadTrace for another index" % self.jig,
                                        self.jig, D.READ_TRACE)
                continue
            for slave, raw, cmd, act, vel, flags in rows:
                t = self._unfold(raw)
                self.raw, self.t = raw, t
                member = self.members.get(slave)
                if member is not None and t >= member.t0:  # (not a sample from before it joined again)
                    member.samples.append(TraceSample(t - member.t0, cmd, act, vel, AxisStatus(flags)))
            self.next = nxt
            if len(rows) < D.TRACE_CHUNK_TAGGED:
                return

    def time_us(self, slave, tick):
        """A jig tick (ReadTransactionTimes') on slave's time base: µs since its join."""
        with self.lock:
            if not self.multi:
                return self.m.trace_time_us(tick)
            return self._unfold(tick) - self.members[slave].t0

    def leave(self, slave):
        """The jig stops sampling slave; its figures since it joined ({taken, skipped, lost,
        failed, ...}). Its samples not taken yet are dropped."""
        with self.lock:
            try:
                if not self.multi:
                    return self.m.trace_stop(self.jig)
                return self.m.trace_leave(slave, self.jig)
            finally:
                self.members.pop(slave, None)
                if self.owner == slave:
                    self.owner = None
