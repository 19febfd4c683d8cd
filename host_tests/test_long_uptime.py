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
* the firmware in a real MicroPython VM (the WebAssembly build) on a HAL clock
  that goes through five 2**30 wraps: every transaction answered, the capture
  stamps its ticks, and no heap allocation near a wrap (a tick plus a delay
  computed as ``(t + d) & mask`` is a heap-allocated long int on a 32-bit port
  for the d µs before each wrap, once per forwarded request);
* the real-time bench starts a few seconds before a tick wrap, as the virtual
  bench does, and survives the instant it used to die at (started just before it);
* the board's crash log gives the bridge's uptime right after weeks (it took
  ``ticks_diff(ticks_ms(), t0)``, which spans +-2**29 ms: 6.2 days).
"""

import os
import shutil
import subprocess
import time

import pytest

from jig import frame as F
from motorjig.sim import Bench, SimBench
from motorjig.sim.bench import REALTIME_START_ENV, VIRTUAL_START_US
from test_board import FakePin, fakes, load_main  # noqa: F401 (fakes: a fixture)
from test_capture_bench import body, records

HERE = os.path.dirname(os.path.abspath(__file__))
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


# --- the firmware in MicroPython --------------------------------------------------------

RUN_VM = os.path.join(HERE, "wasm", "run_vm.mjs")
PKG = os.path.join(HERE, "wasm", "node_modules", "@micropython", "micropython-webassembly-pyscript")

VM_CODE = r"""
import gc, sys, time
import bridge_probe as bp
from jig.capture import CS_T_LAST, CS_TOTAL
MASK = 0x3FFFFFFF
ticks_add = time.ticks_add  # C arithmetic: the probe itself makes no long ints near the wrap
ticks_diff = time.ticks_diff

class Rig(bp.Rig):
    def _in(self, port, wire):
        hal = self.hal
        hal.t = ticks_add(hal.t, 50)
        port.rx.write(wire, len(wire), hal.t)

class Hal(bp.Hal):
    def sleep_us(self, us):
        self.t = ticks_add(self.t, us)

bp.Hal = Hal
r = Rig(capture=True)
hal = r.hal
app = r.app
cs = app.capture.cs
up = hal.up

def slow(us):
    hal.t = ticks_add(hal.t, us)
    app.poll()

def same(buf, n, want):
    # buf[0:n] == want without a slice (a slice is a new object on the heap)
    if n != len(want):
        return False
    for i in range(n):
        if buf[i] != want[i]:
            return False
    return True

def pair():
    # a forwarded request and its reply, a local request; both answered, stamped now
    w = up.writes
    r.forward_once()
    ok = up.writes == w + 1 and same(up.out, up.out_n, r.reply)
    ok = ok and cs[CS_T_LAST] == hal.t
    r.local_once()
    ok = ok and up.writes == w + 2 and cs[CS_T_LAST] == hal.t
    return ok

def around_wrap():
    # transactions from 80 ms before the wrap to 80 ms after, a slow pass now and then
    # (the capture stream goes out, the deadlines are looked at); in a function: a new
    # global name would grow the module's dictionary on the heap
    gc.collect()
    gc.disable()
    a0 = gc.mem_alloc()
    ok = True
    n = 0
    t_start = hal.t
    while ticks_diff(hal.t, t_start) < 160000:
        ok = pair() and ok
        n += 1
        if n % 8 == 0:
            slow(2000)
    grew = gc.mem_alloc() - a0
    gc.enable()
    return n, grew, ok

hal.t = 12345
for _ in range(30):
    pair()
slow(20000)
total0 = cs[CS_TOTAL]
for k in range(5):
    # idle up to 80 ms before the wrap, in steps the main loop follows (< 2**29)
    while hal.t < MASK - 80000:
        step = MASK - 80000 - hal.t
        slow(step if step < (1 << 27) else (1 << 27))
    n, grew, ok = around_wrap()
    print("wrap", k, hal.t, n, grew, ok)
    slow(20000)
c = app.counters.as_dict()
print("counters", c["forwards"], c["replies"], c["timeouts"], c["local_requests"], c["capture_lost"],
      cs[CS_TOTAL] - total0, hal.capture.taken, app.capture.pending())
print(sys.implementation.name)
"""


def test_firmware_through_five_tick_wraps_in_micropython():
    if shutil.which("node") is None or not os.path.isdir(PKG):
        if os.environ.get("CI") == "true":
            pytest.fail("the MicroPython VM is required in CI (tools/setup.sh)")
        pytest.skip("node or the MicroPython WebAssembly package is missing (tools/setup.sh)")
    r = subprocess.run(["node", RUN_VM, "--file", "bridge_probe.py=" + os.path.join(HERE, "bridge_probe.py"),
                        "import sys\nsys.path.append('/data')\n" + VM_CODE],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    lines = r.stdout.splitlines()
    assert lines[-1] == "micropython"
    wraps = [line.split() for line in lines if line.startswith("wrap ")]
    assert len(wraps) == 5
    pairs = 0
    for _, k, t, n, grew, ok in wraps:
        assert ok == "True", "wrap %s: a transaction was not answered or stamped with the tick" % k
        assert int(grew) == 0, "wrap %s: %s heap bytes over %s transactions around the tick wrap" % (k, grew, n)
        assert 0 <= int(t) < 100000  # past the wrap
        pairs += int(n)
    fwd, rep, tmo, local, lost, recorded, taken, pending = map(int, lines[-2].split()[1:])
    assert fwd == rep == local == pairs + 30 and tmo == 0 and lost == 0
    assert recorded >= 3 * pairs and taken > 0 and pending < 2000


# --- the real-time bench ------------------------------------------------------------------

def test_realtime_bench_starts_a_few_seconds_before_a_tick_wrap():
    with Bench(driver_ids=(2,), pty=False) as bench:
        now = bench.sim.clock.now
        assert WRAP - 10e6 < now < WRAP  # the first wrap comes within seconds
        assert bench.sim.hal.ticks_us() == tick(now)


def test_realtime_bench_lives_on_past_2_31_us(monkeypatch):
    """Started 2 s before 2**31 µs (the environment variable the bench reads for such
    checks): the instant where the bench used to stop. Requests every 0.2 s, through
    that instant, all answered."""
    from motorjig.master import Master

    monkeypatch.setenv(REALTIME_START_ENV, str((1 << 31) - 2000000))
    with Bench(driver_ids=(2,), pty=False) as bench:
        assert (1 << 31) - 3e6 < bench.sim.clock.now < 1 << 31
        answers = 0
        with Master(bench.tcp_url, timeout=0.5) as m:
            t_end = time.monotonic() + 4.0
            while time.monotonic() < t_end:
                assert m.get_slave_info(2) is not None and m.get_slave_info(1) is not None
                answers += 1
                time.sleep(0.2)
        assert bench.error is None
        assert bench.sim.clock.now > (1 << 31) + 1e6 and answers >= 10


def test_a_bad_start_time_is_one_line_of_error(monkeypatch, capsys):
    from motorjig.sim import __main__ as sim_main

    monkeypatch.setenv(REALTIME_START_ENV, "soon")
    assert sim_main.main(["--no-pty", "--no-demo", "--duration", "0.1"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: cannot start the bench: MOTORJIG_SIM_START_US='soon'") and "Traceback" not in err


# --- the board's uptime ----------------------------------------------------------------------

def test_the_crash_log_gives_weeks_of_bridge_uptime(fakes, monkeypatch, tmp_path):
    """main.py on the board HAL (fake hardware), ticks_ms starting 5 s before its wrap:
    20 days of bridging (the slow pass feeding the watchdog), then a crash."""
    import jig.compat
    import jig.crashlog
    from jig.app import App

    clock = [MASK - 5000]
    monkeypatch.setattr(fakes.board, "ticks_ms", lambda: clock[0])
    monkeypatch.setattr(jig.compat, "ticks_ms", lambda: clock[0])  # what main.py imports
    FakePin.levels = {"BTN_SAFE": 0}
    mod = load_main(fakes, monkeypatch, tmp_path)
    FakePin.levels = {"BTN_SAFE": 1}
    days = 20
    real_run = App.run

    def run(self, passes=-1):
        real_run(self, 1)
        for _ in range(days * 24):
            clock[0] = (clock[0] + 3600000) & MASK
            self.hal.wdt_feed()  # (the slow pass's: the board's housekeeping runs)
        clock[0] = (clock[0] + 1234) & MASK
        raise RuntimeError("bridge fell over")

    monkeypatch.setattr(App, "run", run)
    assert mod.main() == "crashed"
    log = jig.crashlog.read_crash_log()
    assert "RuntimeError: bridge fell over (after %d ms of bridge uptime)" % (days * 86400000 + 1234) in log, log
