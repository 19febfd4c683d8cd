"""The jig's sampler with a set of drives (jig.trace: StartTrace's join, StopTrace's leave,
tagged ReadTrace) on the virtual bench, in virtual time, on both main loops.

One GetAllStatus per period, the drives of the set in turn: each of N drives gets a
sample every N periods. A drive joins or leaves while the others keep sampling: their
samples go on without a restart, a gap or a loss. The single-drive frames of before the
set (6-byte StartTrace, 3-byte ReadTrace, StopTrace without data) work as they did.
"""

import struct

import pytest

from jig import diag as D
from jig import frame as F
from jig import trace as T
from motorjig.sim import SimBench

import trace_probe

MASK = 0x3FFFFFFF
REFUSED = b"\x81"


@pytest.fixture(params=["portable", "fastpath"])
def fast(request):
    return request.param == "fastpath"


def known(b, *ids):
    for i in ids:
        assert b.request(i, F.GET_SLAVE_INFO)[1][0] == 0


def join(b, slave, period_us, framing=1, op=T.OP_JOIN):
    _w, d = b.request(1, D.START_TRACE, struct.pack("<BIBB", slave, period_us, framing, op))
    return d


def joined(b, slave, period_us, framing=1):
    d = join(b, slave, period_us, framing)
    assert d is not None and d[0] == 0, d
    return D.decode_trace_join(d)


def leave(b, slave):
    _w, d = b.request(1, D.STOP_TRACE, bytes([slave]))
    return D.decode_trace_drive_status(d)


def drive_status(b, slave):
    return D.decode_trace_drive_status(b.request(1, D.GET_TRACE_STATUS, bytes([slave]))[1])


def status(b):
    return D.decode_trace_status(b.request(1, D.GET_TRACE_STATUS)[1])


def read_tagged(b, frm):
    """Every sample from index frm on, tagged; (samples, next)."""
    out = []
    while True:
        _w, d = b.request(1, D.READ_TRACE, struct.pack("<HBB", frm, 0, D.TRACE_TAGGED))
        assert d is not None and d[0] == 0, d
        _state, frm, s = D.decode_trace_chunk_tagged(d)
        out += s
        if len(s) < D.TRACE_CHUNK_TAGGED:
            return out, frm


def by_drive(samples):
    out = {}
    for s in samples:
        out.setdefault(s[0], []).append(s[1:])
    return out


def gaps(rows):
    return [(b_[0] - a[0]) & MASK for a, b_ in zip(rows, rows[1:])]


def test_drives_join_and_leave_while_the_others_keep_sampling(fast):
    """2 samples alone, 3 and 4 join later, 3 leaves, 4 leaves, 2 leaves last (the sampler
    stops). Every sample is tagged with the drive that answered it (each drive is at its
    own position); each drive is polled every N periods while N are in the set; drive 2's
    samples run through every change without a gap, a loss or a restart of the indexes."""
    period = 1000
    b = SimBench(driver_ids=(2, 3, 4), baud=921600, servo_on=True, turnaround_us=100.0, fastpath=fast)
    known(b, 2, 3, 4)
    for slave, pos in ((2, 2000), (3, 3000), (4, 4000)):  # a drive's position tells its samples
        assert b.request(slave, F.SET_COMMAND_POS, struct.pack("<i", pos))[1][0] == 0
        assert b.request(slave, F.SET_ACTUAL_POS, struct.pack("<i", pos))[1][0] == 0
    j2 = joined(b, 2, period)
    assert j2["started"] and j2["first"] == 0 and j2["next"] == 0 and j2["set"] == [2] and j2["ring"] == T.RING
    samples, frm = [], 0
    b.run_for(40000.0)
    j3 = joined(b, 3, period)
    assert not j3["started"] and j3["set"] == [2, 3] and j3["next"] > 30  # drive 2's samples kept
    b.run_for(40000.0)
    j4 = joined(b, 4, period)
    assert j4["set"] == [2, 3, 4]
    b.run_for(60000.0)
    s, frm = read_tagged(b, frm)  # a read while they run releases nothing unread
    samples += s
    b.run_for(30000.0)
    st3 = leave(b, 3)
    assert st3["slave"] == 3 and st3["set"] == [2, 4] and st3["state"] == "running"
    assert st3["lost"] == 0 and st3["failed"] == 0 and st3["taken"] >= 45  # (40 ms of 2, 90 ms of 3 drives, the reads)
    t_leave3 = b.hal.ticks_us()
    b.run_for(40000.0)
    again = leave(b, 3)  # a repeated leave (a retry after a lost reply): the same figures
    assert [again[k] for k in ("taken", "skipped", "lost", "failed")] == [st3[k] for k in ("taken", "skipped", "lost", "failed")]
    st4 = leave(b, 4)
    assert st4["set"] == [2]
    b.run_for(20000.0)
    st2 = leave(b, 2)
    assert st2["state"] == "off" and st2["set"] == []
    b.run_for(20000.0)
    s, frm = read_tagged(b, frm)
    samples += s
    st = status(b)
    assert st["state"] == "off" and st["lost"] == 0 and st["failed"] == 0
    assert len(samples) == st["taken"] == st2["taken"] + st3["taken"] + st4["taken"] and frm == st["taken"]
    per = by_drive(samples)
    assert sorted(per) == [2, 3, 4]
    for slave, rows in per.items():
        assert all(r[1] == 1000 * slave and r[2] == 1000 * slave for r in rows), slave  # its own values only
    assert len(per[2]) == st2["taken"] and len(per[3]) == st3["taken"] and len(per[4]) == st4["taken"]
    # drive 2: one sample a period alone, every 2 with 3, every 3 with 3 and 4: no gap beyond that
    g2 = gaps(per[2])
    assert max(g2) <= 3 * period + 200
    assert g2.count(period) >= 30 and g2.count(2 * period) >= 30 and g2.count(3 * period) >= 15
    # each drive every N periods while N are in the set; none of 3's after it left
    assert all(2 * period - 300 <= g <= 3 * period + 300 for g in gaps(per[3]))  # (± a slot the PC's read moved)
    assert all(((r[0] - t_leave3) & MASK) > (1 << 29) for r in per[3])  # (every tick before the leave)
    # the ring's indexes ran on through every join and leave: one sequence, one sample a period
    # (a slot the PC's request delayed a little), none skipped
    ticks = [r[1] for r in samples]
    assert all(0 < (b_ - a) & MASK < 2 * period for a, b_ in zip(ticks, ticks[1:])) and st["skipped"] == 0


@pytest.mark.parametrize("baud, period, n", [(115200, 4750, 4), (921600, 1000, 4), (921600, 1000, 2)])
def test_each_of_n_moving_drives_gets_a_sample_every_n_periods(fast, baud, period, n):
    """N drives moving at once, the PC sending their moves and reading the tagged trace:
    each drive's samples come every N periods (115 200 baud, 4 drives: 19 ms; 921 600: 4 ms),
    and each drive's positions rise with its own move."""
    ids = tuple(range(2, 2 + n))
    b = SimBench(driver_ids=ids, baud=baud, servo_on=True, turnaround_us=100.0, fastpath=fast)
    known(b, *ids)
    for i in ids:
        joined(b, i, period)
    for k, i in enumerate(ids):
        assert b.request(i, F.MOVE_VELOCITY, struct.pack("<IB", 5000 * (k + 1), 1))[1] == b"\x00"
    samples, frm = [], 0
    t0 = b.clock.now
    for _ in range(20):
        b.run_for(25.0 * period)
        s, frm = read_tagged(b, frm)
        samples += s
    elapsed = b.clock.now - t0
    for i in ids:
        assert b.request(i, F.MOVE_STOP)[1] == b"\x00"
    per = by_drive(samples)
    figures = {i: leave(b, i) for i in ids}
    taken = {i: len(per[i]) for i in ids}
    s, frm = read_tagged(b, frm)  # (the samples taken during the stops)
    for i, rows in by_drive(s).items():
        taken[i] += len(rows)
    assert sorted(per) == list(ids)
    for k, i in enumerate(ids):
        rows = per[i]
        rate = len(rows) / (elapsed / 1e6)
        assert rate == pytest.approx(1e6 / (period * n), rel=0.1), (i, rate)
        g = sorted(gaps(rows))
        assert g[len(g) // 2] == n * period  # the median: exactly N periods
        assert max(g) <= (n + 2) * period  # (a slot the PC's move delayed)
        moving = [r for r in rows if r[4] & (1 << 27)]
        assert len(moving) > 0.8 * len(rows)
        assert [r[1] for r in moving] == sorted(r[1] for r in moving)
        st = figures[i]
        assert st["taken"] == taken[i] and st["failed"] == 0 and st["lost"] == 0
    c = b.counters
    assert b.down_bus.collisions == 0 and c["timeouts"] == 0 and c["stale_drops"] == 0


def test_the_single_drive_frames_of_before_still_work(fast):
    """An old station: 6-byte StartTrace (a restart with that drive alone, even over a set),
    3-byte ReadTrace (untagged samples, 12 a chunk), StopTrace without data (everything off)."""
    b = SimBench(driver_ids=(2, 3), baud=921600, servo_on=True, fastpath=fast)
    known(b, 2, 3)
    joined(b, 2, 1000)
    joined(b, 3, 1000)
    b.run_for(20000.0)
    _w, d = b.request(1, D.START_TRACE, struct.pack("<BIB", 3, 2000, 1))
    assert len(d) == 7 and d[0] == 0  # the old reply
    b.run_for(40000.0)
    st = status(b)
    assert st["slave"] == 3 and st["period_us"] == 2000 and st["first"] == 0 and 18 <= st["taken"] <= 21
    assert drive_status(b, 3)["set"] == [3]
    _w, d = b.request(1, D.READ_TRACE, struct.pack("<HB", 0, 0))
    _state, nxt, chunk = D.decode_trace_chunk(d)
    assert nxt == 12 and len(chunk) == 12
    assert all((b_[0] - a[0]) & MASK == 2000 for a, b_ in zip(chunk[1:], chunk[2:]))  # only drive 3, every period
    _w, d = b.request(1, D.STOP_TRACE)
    st = D.decode_trace_status(d)
    assert st["state"] == "off" and drive_status(b, 3)["set"] == []
    # and a join after it all starts a fresh ring
    j = joined(b, 2, 1000)
    assert j["started"] and j["first"] == 0 and j["next"] == 0


def test_mixed_variants_in_one_set(fast):
    """Each drive is polled in its own framing: a Ver6 and a Ver8 drive, forced and found."""
    b = SimBench(driver_ids=(2, 3, 4), ver8_drivers=(3, 4), servo_on=True, baud=921600, fastpath=fast)
    known(b, 2, 3, 4)
    joined(b, 2, 1000, 1)
    joined(b, 3, 1000, 2)
    joined(b, 4, 1000, 0)  # the jig's Ver6 first: one failure, then Ver8
    b.run_for(90000.0)
    s, _ = read_tagged(b, 0)
    per = by_drive(s)
    assert [drive_status(b, i)["failed"] for i in (2, 3, 4)] == [0, 0, 1]
    assert len(per[2]) >= 28 and len(per[3]) >= 28 and len(per[4]) >= 27
    assert per[4][-1][4] == b.drivers[4].flags()


def test_bad_set_requests_are_refused(fast):
    b = SimBench(driver_ids=(2, 3), baud=115200, fastpath=fast)
    known(b, 2)
    assert join(b, 3, 1000) == REFUSED  # not seen
    assert join(b, 2, 1000, op=2) == REFUSED  # no such operation
    assert join(b, 2, 50) == REFUSED
    assert b.request(1, D.START_TRACE, struct.pack("<BIBBB", 2, 1000, 1, 1, 0))[1] == b"\x82"  # too long
    assert b.request(1, D.STOP_TRACE, b"\x02\x00")[1] == b"\x82"
    assert b.request(1, D.STOP_TRACE, bytes([40]))[1] == REFUSED  # not a driver id
    assert b.request(1, D.GET_TRACE_STATUS, b"\x02\x00")[1] == b"\x82"
    assert b.request(1, D.READ_TRACE, struct.pack("<HBBB", 0, 0, 1, 0))[1] == b"\x82"
    joined(b, 2, 5000)
    assert b.request(1, D.READ_TRACE, struct.pack("<HBB", 0, 0, 2))[1] == REFUSED  # no such format
    assert leave(b, 3)["taken"] == 0  # never in the set: its (empty) figures
    assert drive_status(b, 2)["set"] == [2]


def test_at_most_fourteen_drives_in_the_set(fast, monkeypatch):
    """The 15th drive is refused; the others go on."""
    ids = tuple(range(2, 18))
    b = SimBench(driver_ids=ids, baud=921600, servo_on=True, fastpath=fast)
    known(b, *ids)
    for i in ids[:14]:
        joined(b, i, 1000)
    assert join(b, ids[14], 1000) == REFUSED
    assert joined(b, ids[0], 1000)["set"] == list(ids[:14])  # a member joining again is no 15th
    b.run_for(60000.0)
    s, _ = read_tagged(b, 0)
    assert sorted(by_drive(s)) == list(ids[:14])


def test_zero_heap_bytes_per_sample_of_a_set_under_cpython():
    used, ok = trace_probe.set_sample_alloc(30)
    assert ok
    used, ok = trace_probe.tagged_read_alloc(10)
    assert ok


def test_zero_heap_bytes_per_sample_of_a_set_on_micropython():
    import os
    import shutil
    import subprocess

    here = os.path.dirname(os.path.abspath(__file__))
    run_vm = os.path.join(here, "wasm", "run_vm.mjs")
    pkg = os.path.join(here, "wasm", "node_modules", "@micropython", "micropython-webassembly-pyscript")
    if shutil.which("node") is None or not os.path.isdir(pkg):
        pytest.skip("node or the MicroPython WebAssembly package is missing (tools/setup.sh)")
    code = ("import sys\nsys.path.append('/data')\nimport trace_probe as t\n"
            "print(t.set_sample_alloc(300))\nprint(t.tagged_read_alloc(50))\nprint(sys.implementation.name)\n")
    r = subprocess.run(["node", run_vm, "--file", "bridge_probe.py=" + os.path.join(here, "bridge_probe.py"),
                        "--file", "trace_probe.py=" + os.path.join(here, "trace_probe.py"), code],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.split("\n")
    assert lines[2] == "micropython"
    assert lines[0] == "(0, True)" and lines[1] == "(0, True)", r.stdout
