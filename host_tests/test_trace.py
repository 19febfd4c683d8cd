"""The jig's own sampler (jig.trace, frames 0xF5-0xF8) on the virtual bench, in virtual time.

Every bench test runs on both main loops (the portable one and jig.fastpath.pump's
source as Python), like the bridge suites. Sample times are the jig's ticks; the
"grid" is the StartTrace reply's tick plus whole periods.
"""

import os
import shutil
import struct
import subprocess

import pytest

from jig import diag as D
from jig import frame as F
from jig import trace as T
from motorjig.master import Master, TraceSample
from motorjig.sim import SimBench

import trace_probe

HERE = os.path.dirname(os.path.abspath(__file__))
MASK = 0x3FFFFFFF


@pytest.fixture(params=["portable", "fastpath"])
def fast(request):
    return request.param == "fastpath"


def start(b, slave, period_us, framing=1):
    _w, d = b.request(1, D.START_TRACE, struct.pack("<BIB", slave, period_us, framing))
    return d


def started(b, slave, period_us, framing=1):
    d = start(b, slave, period_us, framing)
    assert d is not None and d[0] == 0, d
    size, t0 = D.decode_trace_start(d)
    assert size == T.RING
    return t0


def read_all(b, frm=0):
    """Every sample the ring holds from index frm on, chunk by chunk; (samples, next)."""
    out = []
    while True:
        _w, d = b.request(1, D.READ_TRACE, struct.pack("<HB", frm, 0))
        assert d is not None and d[0] == 0, d
        _state, frm, s = D.decode_trace_chunk(d)
        out += s
        if len(s) < D.TRACE_CHUNK:
            return out, frm


def status(b):
    _w, d = b.request(1, D.GET_TRACE_STATUS)
    return D.decode_trace_status(d)


def offsets(samples, t0, period):
    """Each sample's tick minus its slot on the grid t0 + k * period (the nearest slot
    not after it), in µs."""
    out = []
    for s in samples:
        d = (s[0] - t0) & MASK
        out.append(d % period)
    return out


def known(b, *ids):
    """The PC talks to each drive once through the jig: the jig has seen them answer."""
    for i in ids:
        assert b.request(i, F.GET_SLAVE_INFO)[1][0] == 0


@pytest.mark.parametrize("baud, period", [(115200, 6000), (921600, 1000)])
def test_samples_at_the_period_on_the_jigs_clock(fast, baud, period):
    b = SimBench(driver_ids=(2,), baud=baud, servo_on=True, turnaround_us=100.0, fastpath=fast)
    known(b, 2)
    t_start = b.clock.now
    t0 = started(b, 2, period)
    b.run_for(600000.0)
    _w, d = b.request(1, D.STOP_TRACE)
    st = D.decode_trace_status(d)
    elapsed = b.clock.now - t_start
    samples, _ = read_all(b)
    assert st["failed"] == 0 and st["lost"] == 0 and st["skipped"] == 0
    assert len(samples) == st["taken"] and abs(st["taken"] - elapsed / period) <= 2
    # every slot's request goes out at the slot's own tick, to the µs, except the first
    # (it waits for the StartTrace reply) and the one the StopTrace request delayed
    offs = offsets(samples, t0, period)
    late = [o for o in offs[1:] if o > 0]
    assert len(late) <= 1 and max(late, default=0) < period // 2
    gaps = [(b_[0] - a[0]) & MASK for a, b_ in zip(samples, samples[1:])]
    assert sum(1 for g in gaps if g != period) <= 4


def test_wrap_of_the_jig_clock_and_full_drive_values(fast):
    """A trace across the 2**30 µs tick wrap (the bench starts 3 s before it) and a
    moving drive: positions rise, the flags say moving, the command matches the drive."""
    b = SimBench(driver_ids=(2,), baud=921600, servo_on=True, fastpath=fast)
    known(b, 2)
    assert b.request(2, F.SET_PARAMETER, bytes([3]) + struct.pack("<i", 5))[1][0] == 0  # short ramps
    assert b.request(2, F.SET_PARAMETER, bytes([4]) + struct.pack("<i", 5))[1][0] == 0
    started(b, 2, 2000)
    b.run_for(2.6e6)
    assert b.request(2, F.MOVE_INC_POS, struct.pack("<iI", 40000, 50000))[1][0] == 0
    b.run_for(1.2e6)
    samples, _ = read_all(b)
    ticks = [s[0] for s in samples]
    assert any(ticks[i + 1] < ticks[i] for i in range(len(ticks) - 1))  # the wrap is inside
    moving = [s for s in samples if s[4] & (1 << 27)]
    assert len(moving) > 100
    cmd = [s[1] for s in moving]
    assert cmd == sorted(cmd) and cmd[-1] > cmd[0]
    assert all(s[3] > 0 for s in moving[5:-5])  # velocity while moving
    assert samples[-1][1] == 40000 and samples[-1][2] == 40000 and not samples[-1][4] & (1 << 27)


@pytest.mark.parametrize("baud, period", [(115200, 6000), (921600, 1000)])
def test_pc_requests_during_a_move_are_answered(fast, baud, period):
    """The PC's move, status polls, trace reads and the stop all answered while the jig
    samples: PC frames that come while the sampler's request is out are held and sent
    whole after its reply (no collision on the driver bus), and the sampler keeps its
    period (a slot waits for the PC's transaction; at most a few are skipped)."""
    b = SimBench(driver_ids=(2, 3), baud=baud, servo_on=True, turnaround_us=100.0, fastpath=fast)
    for d in b.drivers.values():
        d.record_requests = True
    known(b, 2, 3)
    t0 = started(b, 2, period)
    assert b.request(2, F.MOVE_VELOCITY, struct.pack("<IB", 20000, 1))[1] == b"\x00"
    samples = []
    frm = 0
    answered = 0
    t_begin = b.clock.now
    pc = ((2, F.GET_AXIS_STATUS), (3, F.GET_ALL_STATUS), (2, F.GET_COMMAND_POS))
    for i in range(90):
        slave, ftype = pc[i % 3]
        _w, d = b.request(slave, ftype)
        assert d is not None and d[0] == 0, (i, slave, ftype)
        answered += 1
        if i % 5 == 0:
            s, frm = read_all(b, frm)
            samples += s
        b.run_for(float(period) * 1.3)
    assert b.request(2, F.MOVE_STOP)[1] == b"\x00"
    assert F.MOVE_STOP in [ft for _t, ft in b.drivers[2].received[-3:]]  # (the sampler's polls go on)
    duration = b.clock.now - t_begin
    b.run_for(50000.0)
    s, frm = read_all(b, frm)
    samples += s
    st = status(b)
    c = b.counters
    assert b.down_bus.collisions == 0 and b.up_bus.collisions == 0
    assert c["stale_drops"] == 0 and c["timeouts"] == 0 and c["aborts"] == 0
    assert st["failed"] == 0 and st["lost"] == 0
    # the sampler kept (nearly) every slot in the PC's busy traffic
    expected = (duration + 50000.0) / period
    assert st["taken"] >= 0.85 * expected, (st, expected)
    assert st["skipped"] <= 0.15 * expected
    # each sample within one PC round trip of its slot
    rt = 2 * (20 + 45) * 10e6 / baud + 300
    assert max(offsets(samples[1:], t0, period)) < min(rt, period), max(offsets(samples[1:], t0, period))
    vel_moving = [x for x in samples if x[4] & (1 << 27)]
    assert len(vel_moving) > 10
    pos = [x[1] for x in vel_moving]
    assert pos == sorted(pos)


def test_ver8_drive_on_a_mixed_bus(fast):
    """A Ver6 jig, a Ver6 and a Ver8 drive: the Ver8 drive is sampled in its own framing,
    forced (2) or found (0: the jig's Ver6 first, Ver8 after its frame-type error)."""
    b = SimBench(driver_ids=(2, 3), ver8_drivers=(3,), servo_on=True, baud=921600, fastpath=fast)
    known(b, 2, 3)
    for framing, failed in ((2, 0), (0, 1)):
        started(b, 3, 1000, framing)
        b.run_for(100000.0)
        st = status(b)
        samples, _ = read_all(b)
        assert st["failed"] == failed and st["slave"] == 3
        assert len(samples) >= 95 - failed
        assert all(s[1] == 0 and s[2] == 0 for s in samples)
        assert samples[-1][4] == b.drivers[3].flags()
    # and a Ver8 jig sampling its Ver6 drive (framing 0: Ver8 first, Ver6 after the error)
    b = SimBench(driver_ids=(2,), jig_ver8=True, ver8_drivers=(), servo_on=True, baud=921600, fastpath=fast)
    known(b, 2)
    started(b, 2, 1000, 0)
    b.run_for(50000.0)
    st = status(b)
    assert st["failed"] == 1 and st["taken"] >= 45


def test_ver8_jig_and_ver8_drive_with_64_bit_inputs(fast):
    b = SimBench(driver_ids=(2,), ver8=True, servo_on=True, baud=921600, fastpath=fast)
    known(b, 2)
    started(b, 2, 1000, 2)
    b.request(2, F.MOVE_INC_POS, struct.pack("<iI", 3000, 30000))
    b.run_for(300000.0)
    samples, _ = read_all(b)
    assert status(b)["failed"] == 0
    assert samples[-1][1] == 3000 and samples[-1][2] == 3000


def test_a_full_ring_counts_what_it_loses(fast, monkeypatch):
    monkeypatch.setattr(T, "RING", 64)
    monkeypatch.setattr(T, "_RING_MASK", 63)
    b = SimBench(driver_ids=(2,), baud=921600, servo_on=True, fastpath=fast)
    known(b, 2)
    d = start(b, 2, 1000)
    assert D.decode_trace_start(d)[0] == 64
    b.run_for(100000.0)
    st = status(b)
    assert st["taken"] == 64 and st["lost"] >= 30 and st["state"] == "running"
    _w, d = b.request(1, D.READ_TRACE, struct.pack("<HB", 0, 0))
    _state, nxt, first = D.decode_trace_chunk(d)
    assert nxt == 12 and len(first) == 12
    # naming index 12 releases the first 12: the ring takes 12 samples again, no more
    _w, d = b.request(1, D.READ_TRACE, struct.pack("<HB", nxt, 0))
    b.run_for(30000.0)
    _w, d = b.request(1, D.STOP_TRACE)
    st2 = D.decode_trace_status(d)
    assert st2["taken"] == 76 and st2["first"] == 12 and st2["next"] == 76 and st2["lost"] > st["lost"]
    samples, nxt = read_all(b, 12)
    assert len(samples) == 64 and nxt == 76
    assert ((samples[-1][0] - samples[51][0]) & MASK) > 30000  # the last 12 came after the release


def test_read_again_returns_the_same_samples_and_stop_keeps_them(fast):
    b = SimBench(driver_ids=(2,), baud=921600, servo_on=True, fastpath=fast)
    known(b, 2)
    started(b, 2, 1000)
    b.run_for(30000.0)
    w1, d1 = b.request(1, D.READ_TRACE, struct.pack("<HB", 0, 5))
    w2, d2 = b.request(1, D.READ_TRACE, struct.pack("<HB", 0, 5))  # a retry after a lost reply
    assert d1 == d2 and D.decode_trace_chunk(d1)[1] == 5 and len(D.decode_trace_chunk(d1)[2]) == 5
    _w, d = b.request(1, D.STOP_TRACE)
    st = D.decode_trace_status(d)
    assert st["state"] == "off" and st["taken"] >= 25
    b.run_for(30000.0)
    assert status(b)["taken"] == st["taken"]  # stopped
    samples, nxt = read_all(b, 5)
    assert len(samples) == st["taken"] - 5 and nxt == st["taken"]
    assert D.decode_trace_chunk(b.request(1, D.READ_TRACE, struct.pack("<HB", nxt, 0))[1])[0] == "off"


def test_bad_requests_are_refused(fast):
    b = SimBench(driver_ids=(2, 3), baud=115200, fastpath=fast)
    known(b, 2)
    refused = b"\x81"
    assert start(b, 9, 1000) == refused  # no driver there
    assert start(b, 3, 1000) == refused  # a driver the jig has not seen answer yet
    assert start(b, 1, 1000) == refused  # the jig itself
    assert start(b, 99, 1000) == refused  # broadcast
    assert start(b, 40, 1000) == refused  # not a driver id
    assert start(b, 2, 0) == refused  # period 0
    assert start(b, 2, 50) == refused and start(b, 2, 2000000) == refused
    assert start(b, 2, 1000, 3) == refused  # no such framing
    assert b.request(1, D.START_TRACE, b"\x02\xe8\x03")[1] == b"\x82"  # wrong length
    assert b.request(1, D.READ_TRACE, struct.pack("<HB", 0, 0))[1] == refused  # never started: no ring
    assert status(b)["state"] == "off" and b.counters["int_requests"] == 0
    started(b, 2, 5000)
    b.run_for(20000.0)
    assert b.request(1, D.READ_TRACE, struct.pack("<HB", 100, 0))[1] == refused  # not taken yet
    known(b, 3)
    started(b, 3, 5000)  # now it is known; a new StartTrace restarts
    assert status(b)["slave"] == 3


def test_bus_scan_and_safety_stop_still_work_beside_a_trace(fast):
    b = SimBench(driver_ids=(2, 3), baud=921600, servo_on=True, fastpath=fast)
    known(b, 2)
    started(b, 2, 2000)
    assert b.request(1, D.START_BUS_SCAN)[1] == b"\x00"
    b.run_for(1.5e6)
    state, ids = D.decode_scan(b.request(1, D.GET_BUS_SCAN_RESULT)[1])
    assert state == "done" and sorted(ids) == [2, 3]
    assert status(b)["failed"] == 0


def test_master_methods_unfold_the_clock():
    """Master.trace_* on canned replies: ticks that wrap are unfolded."""
    m = Master("loop://", open=False)
    replies = []

    class Fr:
        def __init__(self, data):
            self.data = data

    def fake(slave, ftype, data=b"", **kw):
        return Fr(replies.pop(0))

    m.request = fake
    m.variant = lambda slave: 6
    replies.append(b"\x00" + struct.pack("<HI", 4096, MASK - 1500))
    assert m.trace_start(2, 1000) == 4096
    chunk = [struct.pack("<Iiiii", (MASK - 1500 + 1000 * k) & MASK, k, k, 7, 1 << 27) for k in range(12)]
    replies.append(b"\x00\x01" + struct.pack("<HB", 12, 12) + b"".join(chunk))
    replies.append(b"\x00\x01" + struct.pack("<HB", 13, 1) + struct.pack("<Iiiii", (MASK - 1500 + 12000) & MASK, 12, 12, 7, 0))
    got = m.trace_read()
    assert [s.t_us for s in got] == [1000 * k for k in range(13)]
    assert isinstance(got[0], TraceSample) and got[0].axis.motioning and not got[-1].axis.motioning
    assert m._trace["next"] == 13


def test_master_on_the_real_time_bench():
    import time

    from motorjig.sim import Bench

    with Bench(driver_ids=(2,), baud=115200) as bench:
        # (generous: on a loaded host the real-time bench falls behind the wall clock)
        with Master(bench.tcp_url, timeout=2.0) as m:
            m.servo_enable(2, True)
            assert m.trace_start(2, 10000) == T.RING
            m.move_inc(2, 5000, 20000)
            time.sleep(0.4)
            s1 = m.trace_read()
            time.sleep(0.2)
            s2 = m.trace_read()
            st = m.trace_stop()
            s3 = m.trace_read()
    samples = s1 + s2 + s3
    assert st["state"] == "off" and st["failed"] == 0
    assert len(samples) == st["taken"] >= 40
    t = [s.t_us for s in samples]
    assert t == sorted(t)
    gaps = [b_ - a for a, b_ in zip(t, t[1:])]
    assert sorted(gaps)[len(gaps) // 2] == 10000  # the jig's period, whatever the host's load


def test_probe_under_cpython():
    used, ok = trace_probe.sample_alloc(30)
    assert ok
    used, ok = trace_probe.read_alloc(10)
    assert ok
    used, ok = trace_probe.times_alloc(10)
    assert ok


def test_zero_heap_bytes_per_sample_on_micropython():
    run_vm = os.path.join(HERE, "wasm", "run_vm.mjs")
    pkg = os.path.join(HERE, "wasm", "node_modules", "@micropython", "micropython-webassembly-pyscript")
    if shutil.which("node") is None or not os.path.isdir(pkg):
        pytest.skip("node or the MicroPython WebAssembly package is missing (tools/setup.sh)")
    code = ("import sys\nsys.path.append('/data')\nimport trace_probe as t\n"
            "print(t.sample_alloc(300))\nprint(t.read_alloc(50))\nprint(sys.implementation.name)\n"
            "print(t.times_alloc(50))\n")
    r = subprocess.run(["node", run_vm, "--file", "bridge_probe.py=" + os.path.join(HERE, "bridge_probe.py"),
                        "--file", "trace_probe.py=" + os.path.join(HERE, "trace_probe.py"), code],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.split("\n")
    assert lines[2] == "micropython"
    assert lines[0] == "(0, True)" and lines[1] == "(0, True)", r.stdout
    assert lines[3] == "(0, True)", r.stdout  # a long local reply sent in pieces while the trace runs


@pytest.mark.parametrize("mode", [0, 1])
def test_transaction_times_on_the_jigs_clock(fast, mode):
    """ReadTransactionTimes: per forwarded request the tick its last stop bit left on the
    driver bus and the tick the reply's last byte came in, as the bus saw them; a
    request without a reply has none; the last 16 are kept, oldest first."""
    from jig import params as P

    b = SimBench(driver_ids=(2, 3), baud=115200, fastpath=fast, jig_params={P.P_FORWARD_MODE: mode})
    segs = []
    b.down_bus.monitor = lambda seg, data: segs.append((seg.node.name, seg.end, bytes(data)))
    want = []
    for i in range(20):
        slave = (2, 3, 9)[i % 3]
        segs.clear()
        _w, d = b.request(slave, F.GET_AXIS_STATUS, timeout_us=200000.0)
        req_end = [t for name, t, _d in segs if name == "jig-down"][-1]
        rep = [t for name, t, _d in segs if name.startswith("driver")]
        want.append((slave, F.GET_AXIS_STATUS, int(req_end) & MASK, int(rep[-1]) & MASK if rep else None))
        assert (d is None) == (slave == 9)
    _w, d = b.request(1, D.READ_TRANSACTION_TIMES)
    got = D.decode_transaction_times(d)
    assert len(got) == 16
    assert got == want[-16:]


def test_master_transaction_times():
    m = Master("loop://", open=False)

    class Fr:
        data = b"\x00\x02" + struct.pack("<BBII", 2, 0x40, MASK - 10, 990) + struct.pack("<BBIi", 9, 0x40, 5000, -1)

    m.request = lambda *a, **k: Fr()
    rows = m.transaction_times()
    assert rows[0].round_trip_us == 1001 and rows[0].slave == 2 and rows[1].reply_end is None
    assert rows[1].round_trip_us is None


def test_store_and_forward_with_hardware_de(fast):
    """Store-and-forward with the USART's hardware DE (no transmit queue for the pieces):
    the ReadTrace reply goes out whole; the sampler and the PC's frames work as cut through."""
    from jig import params as P

    b = SimBench(driver_ids=(2,), baud=921600, servo_on=True, fastpath=fast,
                 jig_params={P.P_FORWARD_MODE: P.STORE_AND_FORWARD, P.P_DE_MODE: 1})
    known(b, 2)
    started(b, 2, 1000)
    for _ in range(20):
        assert b.request(2, F.GET_AXIS_STATUS)[1][0] == 0
        b.run_for(1500.0)
    b.run_for(20000.0)
    samples, _ = read_all(b)
    st = status(b)
    assert st["failed"] == 0 and len(samples) >= st["taken"] - 2 and st["taken"] >= 40
    assert b.down_bus.collisions == 0


def test_master_trace_start_makes_the_jig_see_the_drive_first():
    """A variant known from before the jig's reset: StartTrace is refused (0x81), the
    Master asks the drive once through the jig and starts again."""
    from motorjig import errors as E

    m = Master("loop://", open=False)
    m.variant = lambda slave: 6
    calls = []

    class Fr:
        def __init__(self, data):
            self.data = data

    def fake(slave, ftype, data=b"", **kw):
        calls.append((slave, ftype))
        if ftype == D.START_TRACE and len(calls) == 1:
            raise E.status_error(0x81, 1, ftype, "StartTrace")
        if ftype == D.START_TRACE:
            return Fr(b"\x00" + struct.pack("<HI", 4096, 5))
        return Fr(b"\x00\x00\x00\x00\x00")

    m.request = fake
    assert m.trace_start(2, 1000) == 4096
    assert calls == [(1, D.START_TRACE), (2, F.GET_AXIS_STATUS), (1, D.START_TRACE)]


def test_master_trace_read_skips_a_late_reply_to_an_earlier_read():
    m = Master("loop://", open=False)
    m.variant = lambda slave: 6
    replies = [b"\x00" + struct.pack("<HI", 4096, 0)]

    class Fr:
        def __init__(self, data):
            self.data = data

    def chunk(frm, n):
        return b"\x00\x01" + struct.pack("<HB", frm + n, n) + b"".join(
            struct.pack("<Iiiii", 1000 * (frm + k), frm + k, 0, 0, 0) for k in range(n))

    m.request = lambda *a, **k: Fr(replies.pop(0))
    m.trace_start(2, 1000)
    # the reply to the read from 0, then a late copy of it (answering the read from 12)
    replies += [chunk(0, 12), chunk(0, 12), chunk(12, 3)]
    got = m.trace_read()
    assert [s.command_pos for s in got] == list(range(15))


def test_stop_leaves_no_wake_behind(fast):
    """A slot that waits for the PC sets the bridge's wake flag; StopTrace clears it, so
    the forwarded transactions after a trace ask for no extra slow pass."""
    from jig.bridge import AWAIT_PC, B_STATE, B_WAKE, IDLE

    b = SimBench(driver_ids=(2,), baud=921600, servo_on=True, fastpath=fast)
    known(b, 2)
    started(b, 2, 1000)
    b.run_for(20000.0)
    tr = b.app.trace
    b.clock.run_while(lambda: tr.ts[T.T_WAITING], 5000.0)
    bs = b.app.bridge.bs
    bs[B_STATE] = AWAIT_PC  # the PC's request is out when the slot falls due
    now = b.hal.ticks_us()
    tr.ts[T.T_NEXT] = now
    tr.poll(now)
    assert bs[B_WAKE] == 1 and not tr.ts[T.T_WAITING]
    # StopTrace ends the PC's wait (a new PC frame aborts it): no relay's end clears the flag
    assert b.request(1, D.STOP_TRACE)[1][0] == 0
    assert bs[B_STATE] == IDLE and bs[B_WAKE] == 0
    polls = b.hal.wdt_feeds
    for _ in range(10):
        assert b.request(2, F.GET_AXIS_STATUS)[1][0] == 0
    assert b.hal.wdt_feeds - polls <= 2  # no slow pass per transaction


def test_long_local_replies_leave_no_sample_unanswered(fast):
    """A long local reply written whole (ReadTransactionTimes: 162 data bytes, 15 ms at
    115 200 baud; ReadCounters) left the driver bus unread meanwhile: the
    rest of a sample's reply, read after it, looked to the parser like a silence longer
    than the inter-byte timeout, and a good reply was dropped (down_timeouts,
    down_noise), the sample unanswered, a gap of the sample's timeout in the trace (the
    station read 25-45 ms gaps). While the sampler runs, such replies go out in pieces
    with the driver bus read between them, as ReadTrace's does."""
    import random

    from jig import handlers as H

    assert H._T_WAITING == T.T_WAITING and T.T_ON == 0
    b = SimBench(driver_ids=(2,), baud=115200, servo_on=True, fastpath=fast)
    known(b, 2)
    for _ in range(4):
        assert b.request(2, F.GET_AXIS_STATUS)[1][0] == 0  # (ReadTransactionTimes: 16 rows)
    started(b, 2, 4750)
    assert b.request(2, F.MOVE_VELOCITY, struct.pack("<IB", 20000, 1))[1] == b"\x00"
    rng = random.Random(7)
    frm = 0
    long_replies = (D.READ_TRANSACTION_TIMES, D.READ_COUNTERS, F.GET_SLAVE_INFO, D.GET_TRACE_STATUS)
    assert H.PACED_MIN < 2 + 16 * 10 and H.PACED_MIN < 2 + 4 * D.N_WIRE  # these two go in pieces
    for i in range(120):
        b.run_for(rng.random() * 4750.0)
        _w, d = b.request(1, long_replies[i % 4])
        assert d is not None and d[0] == 0, i
        if i % 10 == 9:
            _s, frm = read_all(b, frm)
    assert b.request(2, F.MOVE_STOP)[1] == b"\x00"
    st = status(b)
    c = b.counters
    assert c["down_timeouts"] == 0 and c["down_noise"] == 0 and c["int_timeouts"] == 0, c
    assert st["failed"] == 0, st
    assert b.down_bus.collisions == 0 and b.up_bus.collisions == 0
