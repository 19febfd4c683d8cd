"""A jig runs for weeks: nothing may depend on the clock being young.

The issue: the real-time bench (`python -m motorjig.sim`, `jigctl gui --bench`) died
after 35 min 47 s, 2**31 µs of its clock, with "signed integer is greater than
maximum": the simulated PC adapter and drives handed the bench's absolute time (µs
since the bench started) to ``jig.parser.FrameParser`` as ``now``, whose state is a
32-bit signed array. The parser takes ticks (wrapping at 2**30, like MicroPython's
``ticks_us``); the jig's own ports always gave it ticks.

* the bench in virtual time, capture on, past 2**31 µs and four 2**30 wraps (2**32
  too), with requests through the jig (local and forwarded) answered all along,
  the capture records stamped with the ticks of the bench's clock;
"""

import pytest

from jig import frame as F
from motorjig.sim import SimBench
from motorjig.sim.bench import VIRTUAL_START_US
from test_capture_bench import body, records

WRAP = 1 << 30  # MicroPython's ticks period on a 32-bit port
MASK = WRAP - 1


def tick(t):
    return int(t) & MASK


def _check_stamp(rec, t_before, t_after):
    """A capture record's end lies on the bench's clock between the two instants (as ticks)."""
    assert 0 <= rec.t_end <= MASK and 0 <= rec.t_first <= MASK
    assert (rec.t_end - tick(t_before)) & MASK <= t_after - t_before + 1, (rec, t_before, t_after)


@pytest.mark.parametrize("fastpath", [False, True], ids=["portable", "fastpath"])
def test_bench_runs_past_2_31_us_and_four_tick_wraps(fastpath):
    b = SimBench(driver_ids=(2, 3), fastpath=fastpath)
    assert b.clock.now == VIRTUAL_START_US < WRAP
    assert b.capture_start()
    b.capture_read()
    end = 4 * WRAP + 3e6  # past 2**30, 2**31, 3 * 2**30 and 2**32 µs
    # Requests every 20 s, and back to back for 20 ms around every wrap.
    marks = [k * WRAP for k in range(1, 5)]
    asked = 0
    while b.clock.now < end:
        near = any(-10000.0 <= b.clock.now - m <= 10000.0 for m in marks)
        for slave, ftype in ((2, F.GET_AXIS_STATUS), (1, F.GET_SLAVE_INFO), (3, F.GET_COMMAND_POS)):
            t0 = b.clock.now
            req = b.encode(slave, ftype)
            wire, data = b.request(slave, ftype)
            assert data is not None and data[0] == 0, "no answer from %d at %.0f µs" % (slave, b.clock.now)
            asked += 1
            recs = [r for r in records(b.capture_read()) if r.type < 4 and r.data == body(req)]
            assert len(recs) == (2 if slave != 1 else 1), recs  # received (and passed on)
            for r in recs:
                _check_stamp(r, t0, b.clock.now)
        if near:
            continue
        nxt = min([m - 10000.0 for m in marks if m - 10000.0 > b.clock.now] + [b.clock.now + 20e6])
        b.run_for(nxt - b.clock.now)
    c = b.counters
    assert c["forwards"] == c["replies"] == 2 * asked // 3 and c["timeouts"] == 0 and c["local_requests"] == asked // 3
    assert c["capture_lost"] == 0 and c["up_crc_errors"] == c["down_crc_errors"] == 0
    assert b.clock.now > 4 * WRAP and asked > 3 * 160
