"""Sampling an axis during a step, and whether the samples can be trusted.

Two samplers with one interface, chosen per run (``new_trace``):

* ``JigTrace`` -- the jig samples the axis itself (StartTrace/ReadTrace, docs/bridge.md):
  GetAllStatus at a fixed period, each sample dated by the jig's µs clock, and the PC's
  own commands to that drive (the move, the stop) and the jig's relay switchings dated
  by the same clock as they happened on the bus. Nothing a busy PC does moves a date:
  the PC only reads the samples later, in chunks. The slots that share one Master share
  the jig's sampler through its ``tracehub.TraceHub``: each moving step's drive joins the
  jig's set and gets its own samples; with N drives moving each is sampled every N periods.
* ``PcTrace`` -- the station polls GetAllStatus itself and dates each sample with its own
  clock at the middle of the round trip (a bus without a MotorJig, or a jig whose
  firmware has no sampler). A busy PC delays replies and leaves gaps.

Both keep ``rows`` ``[t, command, actual, velocity]`` (t in seconds from the first
sample), ``last`` (the last sample: ``command_pos``, ``actual_pos``, ``actual_vel``,
``axis``), ``peak_error``, and the instants of the step's commands (``mark`` /
``time_of``). ``check(floor_hz)`` raises ``UntrustedMeasurement`` when the samples cannot
judge the drive: a gap, a rate below the plan's floor, samples the jig lost, a command
the jig did not see go out -- the step then ends ERROR with that reason, never FAIL.
"""

import logging
import time

from motorjig.errors import JigError
from motorjig.station import tracehub

_LOG = logging.getLogger(__name__)

# GetAllStatus on the driver bus: the request and its 32-byte reply, framed (Ver6, no stuffing).
_STATUS_TRANSACTION_BYTES = 8 + 41
_DRIVE_TURNAROUND_US = 300  # what a Plus-R drive takes to answer, about; the jig's own handling inside it


class UntrustedMeasurement(Exception):
    """The step's samples cannot judge the drive (a gap, too few, a command not dated): the step
    ends ERROR with this sentence, not FAIL."""


def trace_period_us(down_baud):
    """The jig's sampling period for a driver bus at ``down_baud``: one GetAllStatus transaction
    (request, reply, the drive's turnaround), rounded up to 250 µs, at least 1 ms. 4.75 ms
    (210 Hz) at 115 200 baud, 1 ms at 921 600."""
    wire_us = _STATUS_TRANSACTION_BYTES * 10 * 1e6 / down_baud
    period = int(-(-(wire_us + _DRIVE_TURNAROUND_US) // 250) * 250)
    return max(1000, period)


class _Sample:
    """The fields of a sample the steps read, whichever sampler took it."""

    __slots__ = ("command_pos", "actual_pos", "actual_vel", "axis", "pos_error")

    def __init__(self, command_pos, actual_pos, actual_vel, axis):
        self.command_pos, self.actual_pos, self.actual_vel, self.axis = command_pos, actual_pos, actual_vel, axis
        self.pos_error = command_pos - actual_pos


class _Trace:
    source = ""

    def __init__(self, ctx=None, step=None):
        self.ctx, self.step = ctx, step
        self.rows = []
        self.axes = []  # the axis flags of each row
        self.last = None
        self.peak_error = 0
        self.marks = {}  # name -> t (s, on the rows' time base)
        self.t_stop = None  # until_stopped: the first sample at standstill

    def _add(self, t, smp):
        row = [round(t, 4), smp.command_pos, smp.actual_pos, smp.actual_vel]
        self.rows.append(row)
        self.axes.append(smp.axis)
        if self.ctx is not None:
            self.ctx.sample(self.step, row)
        self.peak_error = max(self.peak_error, abs(smp.pos_error))
        self.last = smp

    def until_stopped(self, m, s, timeout_s, settle_s=0.05):
        """Sample until the axis stops (or stops with an alarm); False on timeout. A standstill
        counts once motion was seen, or ``settle_s`` after the last command (a drive may flag a
        start a cycle late). ``t_stop``: the first sample at standstill (the last one on a
        timeout) -- a chunk read from the jig may hold samples after it. An axis already moving
        when this is called (a stop's command) has been seen moving: its first standstill counts,
        even when every sample read from here on is after the stop (a jig read in chunks, several
        slots' drives sampled in turn), instead of ``settle_s`` later (a false stop time)."""
        end = time.monotonic() + timeout_s
        moved = self.last is not None and self.last.axis.motioning
        while True:
            for t, smp in self.more(m, s):
                moved = moved or smp.axis.motioning
                if not smp.axis.motioning and (moved or t - self.t_last_command() >= settle_s):
                    self.t_stop = t
                    return True
            if time.monotonic() > end:
                self.t_stop = self.rows[-1][0] if self.rows else 0.0
                return False

    def sample_until(self, m, s, t_from_command):
        """Sample until ``t_from_command`` seconds after the last command (the step's after_ms)."""
        while not self.rows or self.rows[-1][0] - self.t_last_command() < t_from_command:
            self.more(m, s)

    def t_last_command(self):
        return max(self.marks.values()) if self.marks else 0.0

    def time_of(self, name):
        if name not in self.marks:
            raise UntrustedMeasurement("the %s did not date %s: the step's times cannot be dated" % (self.source, name))
        return self.marks[name]

    def date_by_flag(self, name, flag, after=0.0):
        """Date ``name`` by the first sample after ``after`` whose axis shows ``flag``: halfway from the
        sample before it (the jig cannot see a wire switch at the drive; the drive's flag can)."""
        prev = None
        for row, axis in zip(self.rows, self.axes):
            if row[0] > after and getattr(axis, flag):
                self.marks[name] = row[0] if prev is None else (prev + row[0]) / 2.0
                return
            prev = row[0]

    def position_at(self, t, column=1):
        """The command (column 1) or actual (2) position at time t: the last sample at or before t,
        carried forward at its velocity (a stop goes out while the axis runs at constant speed)."""
        before = [r for r in self.rows if r[0] <= t] or self.rows[:1]
        a = before[-1]
        return a[column] + a[3] * (t - a[0])

    def stats(self, t_from, t_to):
        """(samples, rate Hz, longest gap s) of the samples between two instants."""
        ts = [r[0] for r in self.rows if t_from - 1e-9 <= r[0] <= t_to + 1e-9]
        if len(ts) < 2:
            return len(ts), 0.0, t_to - t_from
        gap = max(b - a for a, b in zip(ts, ts[1:]))
        gap = max(gap, ts[0] - t_from, t_to - ts[-1])
        span = ts[-1] - ts[0]  # 0 when the samples share one time (a stop of a few ms): no rate
        return len(ts), (len(ts) - 1) / span if span > 0 else 0.0, gap

    def check(self, t_from, t_to, floor_hz, what="the move"):
        """UntrustedMeasurement unless the samples between two instants are dense enough to judge
        the drive: no gap longer than 4 periods of ``floor_hz`` (and 20 ms) and, over a stretch of at
        least 10 such periods, a rate at or above ``floor_hz``."""
        n, rate, gap = self.stats(t_from, t_to)
        limit = max(0.02, 4.0 / floor_hz) if floor_hz else 0.05
        if gap > limit:
            raise UntrustedMeasurement(
                "%s's samples have a gap of %.0f ms (%s; at most %.0f ms can judge the drive): the drive "
                "was not judged" % (what, gap * 1000, self.gap_cause(), limit * 1000))
        if floor_hz and t_to - t_from >= 10.0 / floor_hz and rate < floor_hz:  # a rate needs 10 periods
            raise UntrustedMeasurement(
                "%s was sampled at %.0f Hz, below the plan's floor of %.0f Hz (%s): the drive was not judged"
                % (what, rate, floor_hz, self.gap_cause()))

    def begin(self, m, s):
        pass

    def end(self, m):
        pass


class PcTrace(_Trace):
    """The station's own sampling: GetAllStatus, dated at the middle of its round trip on this PC's
    clock; a command is dated just before it is sent."""

    source = "pc"

    def __init__(self, ctx=None, step=None, why=None):
        super().__init__(ctx, step)
        self.t0 = time.monotonic()
        self.why = why  # why this PC samples a step of a run the jig samples (None: the run's choice)

    def gap_cause(self):
        return "this PC's polling: a busy PC or a slow reply"

    def more(self, m, s):
        sent = time.monotonic()
        st = m.get_all_status(s)
        t = (sent + time.monotonic()) / 2.0 - self.t0
        smp = _Sample(st.command_pos, st.actual_pos, st.actual_vel, st.axis)
        self._add(t, smp)
        return [(t, smp)]

    def mark(self, name, ftype=None):
        """Call just before sending the command ``name``."""
        self.marks[name] = time.monotonic() - self.t0

    def sent(self, m, s, name):
        pass  # dated by mark(), just before it went out

    def sent_local(self, name):
        """A jig-local command (a relay) is answered: dated at the middle of its round trip."""
        self.marks[name] = (self.marks[name] + time.monotonic() - self.t0) / 2.0


class JigTrace(_Trace):
    """The jig's own sampling (see the module's doc), through the hub of the Master's jig
    (``tracehub.hub_for``). A command is dated by the jig: ``sent(m, s, name)``, called right
    after the command's reply, finds it among the jig's last forwarded requests
    (ReadTransactionTimes: the drive's id, and its frame type or Ver8 sync number) and keeps
    the jig's tick of its last stop bit leaving on the driver bus, on this drive's time base."""

    source = "jig"

    def __init__(self, ctx=None, step=None, jig=1, period_us=5000, hub=None):
        super().__init__(ctx, step)
        self.jig, self.period_us = jig, period_us
        self.hub = hub
        self.slave = None
        self.status = None

    def gap_cause(self):
        st = self.status or {}
        return "the jig: %d sample slots skipped, %d requests unanswered, %d samples lost" % (
            st.get("skipped", 0), st.get("failed", 0), st.get("lost", 0))

    def begin(self, m, s):
        if self.hub is None:
            self.hub = tracehub.hub_for(m, self.jig)
        if not self.hub.claim(s):
            raise JigError("the jig samples one drive at a time (its firmware has no set of drives) and another "
                           "slot's step has it")
        try:
            self.hub.join(s, self.period_us)
        except BaseException:
            self.hub.release(s)
            raise
        self.slave = s
        while not self.rows:
            self.more(m, s)

    def more(self, m, s):
        out = []
        got = self.hub.take(s)
        for item in got:
            t = item.t_us / 1e6
            smp = _Sample(item.command_pos, item.actual_pos, item.actual_vel, item.axis)
            self._add(t, smp)
            out.append((t, smp))
        if not got:
            time.sleep(self.period_us * self.hub.drives() / 2e6)  # nothing new yet: half this drive's interval
        return out

    def mark(self, name, ftype):
        self._ftype = ftype

    def sent(self, m, s, name):
        """The command ``name`` (the frame type given to ``mark``) has been answered: its instant
        on the jig's clock."""
        b1 = self._ftype if m.variant(s) == 6 else m.last_sync(s)  # Ver8: the sync number it went out with
        for tt in reversed(m.transaction_times(self.jig)):
            if tt.slave == s and tt.b1 == b1:
                self.marks[name] = self.hub.time_us(s, tt.request_end) / 1e6
                return
        raise UntrustedMeasurement("the jig has no record of %s going out to slave %d: the step's times cannot "
                                   "be dated" % (name, s))

    def sent_local(self, name):
        pass  # the jig records only what it forwards: the step dates it by the drive's flags (date_by_flag)

    def end(self, m):
        if self.slave is None:
            return  # never joined
        try:
            self.status = self.hub.leave(self.slave)
        except JigError:
            self.status = None
        if self.status and self.status.get("lost"):
            raise UntrustedMeasurement("the jig lost %d samples (its buffer was full: this PC read too late): the "
                                       "drive was not judged" % self.status["lost"])


def jig_can_trace(m, jig):
    """True when the jig's firmware has the sampler and dates the requests it forwards (GetTraceStatus
    and ReadTransactionTimes answer)."""
    try:
        m.trace_status(jig)
        m.transaction_times(jig)
        return True
    except (JigError, AttributeError):
        return False


def new_trace(bus, ctx, step):
    """The run's sampler for one step: the jig's when it has one (``bus.trace_period_us``). A jig
    whose sampler takes one drive only samples one slot's step at a time: a step that begins
    while another slot's has it is sampled by this PC (the trace says why)."""
    if getattr(bus, "trace_period_us", None):
        hub = tracehub.hub_for(bus.master, bus.jig_id)
        if hub.claim(bus.slave):
            return JigTrace(ctx, step, bus.jig_id, bus.trace_period_us, hub)
        why = ("the jig's firmware samples one drive at a time and another slot's step had it: this PC sampled "
               "this step")
        _LOG.warning("slave %d: %s", bus.slave, why)
        return PcTrace(ctx, step, why)
    return PcTrace(ctx, step)

