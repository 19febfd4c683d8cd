"""The station's samplers: what they date, and when they refuse to judge a drive.

A recorded trace is fed to ``JigTrace`` the way the jig hands it over (chunks that may
hold seconds of samples after the standstill, a PC that reads late); the checks that
turn a step into ERROR are tried with gaps and thin traces. The jig's own sampler
end to end is in test_trace.py and test_station_bench.py.
"""

import pytest

from motorjig.master import AxisStatus, TraceSample, TransactionTime
from motorjig.station.sampling import JigTrace, UntrustedMeasurement, trace_period_us

MOTIONING = 1 << 27  # the axis flag (names.AXIS_FLAG_BITS["motioning"])


def samples(period_us, n_still, n_moving, n_after, speed=5000):
    out, pos, t = [], 0, 0
    for i in range(n_still + n_moving + n_after):
        moving = n_still <= i < n_still + n_moving
        if moving:
            pos += speed * period_us // 1000000
        out.append(TraceSample(t, pos, pos, speed if moving else 0, AxisStatus(MOTIONING if moving else 0)))
        t += period_us
    return out


class FakeJigMaster:
    """What JigTrace asks of a Master: the jig's trace in chunks, its record of the move command."""

    def __init__(self, chunks, move_tick):
        self.chunks = list(chunks)
        self._trace = {"raw": 0, "t": 0}
        self.move_tick = move_tick
        self.stopped = False

    def trace_start(self, slave, period_us, jig=1):
        return 4096

    def trace_read(self, jig=1):
        got = self.chunks.pop(0) if self.chunks else []
        if got:
            self._trace = {"raw": got[-1].t_us, "t": got[-1].t_us}
        return got

    def trace_stop(self, jig=1):
        self.stopped = True
        return {"state": "off", "lost": 0, "skipped": 0, "failed": 0}

    def variant(self, slave):
        return 6

    def trace_time_us(self, tick):
        return self._trace["t"] + (tick - self._trace["raw"])  # (no tick wrap in these traces)

    def transaction_times(self, jig=1):
        return [TransactionTime(2, 0x35, self.move_tick, self.move_tick + 900, 900)]


def test_the_move_ends_at_the_first_standstill_sample_even_in_a_late_chunk():
    """The PC read late: one chunk holds the whole move and 3 s of standstill after it."""
    trace = samples(5000, 4, 400, 600)
    m = FakeJigMaster([trace[:2], trace[2:]], move_tick=12000)
    jt = JigTrace(jig=1, period_us=5000)
    jt.begin(m, 2)
    jt.mark("move", 0x35)
    jt.sent(m, 2, "move")
    assert jt.until_stopped(m, 2, 5.0)
    jt.end(m)
    assert jt.time_of("move") == pytest.approx(0.012)
    assert jt.t_stop == pytest.approx(404 * 0.005)  # the first sample at standstill
    assert jt.rows[-1][0] == pytest.approx(1003 * 0.005)  # the chunk went on for 3 s
    jt.check(jt.time_of("move"), jt.t_stop, 100.0)  # 200 Hz, no gap: trusted
    assert m.stopped


def test_a_stop_ends_at_the_first_standstill_even_when_every_later_sample_is_still():
    """The axis was seen moving before the stop; the next chunk read holds only samples after the
    stop, all at standstill (the jig read in chunks, several slots' drives sampled in turn): the
    stop ends at its first sample, not settle_s later (it was a false stop_time FAIL of 51 ms)."""
    trace = samples(4000, 0, 50, 40)  # moving until 0.2 s, still from then on
    m = FakeJigMaster([trace[:50], trace[50:]], move_tick=199500)  # the stop, 0.5 ms before standstill
    m.transaction_times = lambda jig=1: [TransactionTime(2, 0x31, 199500, 199600, 100)]  # EmergencyStop
    jt = JigTrace(jig=1, period_us=4000)
    jt.begin(m, 2)
    while len(jt.rows) < 50:
        jt.more(m, 2)
    jt.mark("stop", 0x31)
    jt.sent(m, 2, "stop")
    assert jt.until_stopped(m, 2, 5.0)
    assert jt.t_stop - jt.time_of("stop") == pytest.approx(0.0005)


def test_a_command_the_jig_has_no_record_of_cannot_be_dated():
    m = FakeJigMaster([samples(5000, 2, 0, 0)], move_tick=0)
    m.transaction_times = lambda jig=1: [TransactionTime(3, 0x35, 100, 900, 800)]  # another slave's
    jt = JigTrace(jig=1, period_us=5000)
    jt.begin(m, 2)
    jt.mark("move", 0x35)
    with pytest.raises(UntrustedMeasurement, match="no record of move"):
        jt.sent(m, 2, "move")


def _trace_with(ts):
    jt = JigTrace(jig=1, period_us=5000)
    for t in ts:
        jt.rows.append([t, 0, 0, 0])
    return jt


def test_a_gap_is_an_untrusted_measurement_not_a_judgement():
    ts = [i * 0.005 for i in range(100)]
    ts = ts[:50] + [t + 0.045 for t in ts[50:]]  # one 50 ms gap
    with pytest.raises(UntrustedMeasurement, match="gap of 50 ms"):
        _trace_with(ts).check(0.0, ts[-1], 100.0)
    _trace_with([i * 0.005 for i in range(100)]).check(0.0, 0.495, 100.0)


def test_a_rate_below_the_floor_is_untrusted_only_over_ten_periods():
    thin = [i * 0.015 for i in range(40)]  # 67 Hz, no gap over 40 ms
    with pytest.raises(UntrustedMeasurement, match="sampled at 67 Hz, below the plan's floor of 100 Hz"):
        _trace_with(thin).check(0.0, thin[-1], 100.0)
    short = [0.0, 0.015, 0.03, 0.045]  # an emergency stop's few samples: too short a stretch for a rate
    _trace_with(short).check(0.0, 0.045, 100.0)


def test_samples_that_share_one_time_give_no_rate_and_no_division_by_zero():
    """A stop of about 2 ms: its two samples carry the same jig time (issue 31: ERROR "float
    division by zero" on a healthy drive). Too short a stretch for a rate: judged by its gaps."""
    same = [0.010, 0.010]
    n, rate, gap = _trace_with(same).stats(0.009, 0.011)
    assert (n, rate) == (2, 0.0) and gap == pytest.approx(0.001)
    _trace_with(same).check(0.009, 0.011, 100.0)


@pytest.mark.parametrize("baud,period", [(115200, 4750), (921600, 1000), (9600, 51500)])
def test_the_jig_samples_at_one_transaction_of_its_driver_bus(baud, period):
    assert trace_period_us(baud) == period
