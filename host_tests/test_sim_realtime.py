"""The interactive bench: Bench API, pty and TCP, the pyserial example, the CLI."""

import os
import subprocess
import sys
import time

import pytest
import serial

from jig import frame as F
from jig.parser import FrameParser
from motorjig.sim import Bench
from bench_fixtures import bench_process

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXAMPLE = os.path.join(ROOT, "tools", "examples", "pyserial_scan_move.py")
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.join(ROOT, "firmware"), os.path.join(ROOT, "tools")]))


def read_frame(ser, limit_s=2.0):
    """The next frame's body from ser, as soon as it is complete (None after limit_s)."""
    p = FrameParser()
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        chunk = ser.read(ser.in_waiting or 1)
        i = 0
        while i < len(chunk):
            i = p.feed(chunk, i)
            if p.ready:
                return bytes(p.body[: p.body_len])
    return None


@pytest.fixture(scope="module")
def bench():
    with Bench(driver_ids=(2, 3), baud=115200) as b:
        yield b


def test_bench_tcp_and_pty(bench):
    assert bench.tcp_url.startswith("socket://127.0.0.1:")
    assert bench.pty_path and os.path.exists(bench.pty_path)
    for url in (bench.tcp_url, bench.pty_path):
        with serial.serial_for_url(url, baudrate=115200, timeout=0.05) as s:
            s.write(F.encode(1, F.GET_SLAVE_INFO))
            body = read_frame(s)
            assert body is not None and body[:3] == b"\x01\x01\x00"
            s.write(F.encode(3, F.GET_COMMAND_POS))
            body = read_frame(s)
            assert body is not None and body[:3] == b"\x03\x51\x00"


@pytest.fixture(scope="module")
def bench_urls():
    with bench_process() as urls:
        yield urls


@pytest.mark.parametrize("which", ["tcp", "pty"])
def test_pyserial_example_scans_and_moves(bench_urls, which):
    url = bench_urls[which]
    r = subprocess.run([sys.executable, EXAMPLE, url, "2"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "found ids: [1, 2, 3]" in r.stdout
    pos = int(r.stdout.strip().splitlines()[-1].split()[-1])
    assert pos % 4000 == 0 and pos > 0


def test_cli_help_and_bad_args():
    r = subprocess.run([sys.executable, "-m", "motorjig.sim", "--help"], capture_output=True, text=True, env=ENV, timeout=30)
    assert r.returncode == 0 and "--tcp-port" in r.stdout and "--duration" in r.stdout
    r = subprocess.run([sys.executable, "-m", "motorjig.sim", "--drivers", "2,x"], capture_output=True, text=True, env=ENV, timeout=30)
    assert r.returncode != 0 and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "motorjig.sim", "--baud", "1234", "--duration", "0.1"], capture_output=True, text=True, env=ENV, timeout=30)
    assert r.returncode != 0 and "Traceback" not in r.stderr and "baud" in r.stderr


def test_cli_demo_runs_bounded():
    r = subprocess.run([sys.executable, "-m", "motorjig.sim", "--duration", "0.2", "--drivers", "2,5"],
                       capture_output=True, text=True, env=ENV, timeout=60)
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "pty: /dev/" in out and "tcp: socket://127.0.0.1:" in out
    assert "id  1: Ver6  MotorJig bridge (type 200)" in out and "id  5: Ver6  Ezi-STEP Plus-R ST (type 20)" in out
    assert "servo on id 2" in out and "move id 2" in out
    assert "pos  10000" in out


def test_cli_port_in_use_is_a_clean_error():
    import socket

    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen(1)
        port = blocker.getsockname()[1]
        r = subprocess.run([sys.executable, "-m", "motorjig.sim", "--tcp-port", str(port), "--no-demo", "--duration", "0.1"],
                           capture_output=True, text=True, env=ENV, timeout=30)
    assert r.returncode == 1 and "cannot start the bench" in r.stderr and "Traceback" not in r.stderr


def test_paced_clock_runs_stalled_events_at_their_own_times():
    """A host stall must not let a later deadline overtake an earlier event's follow-up."""
    import time

    from motorjig.sim.clock import PacedClock

    clock = PacedClock()
    seen = []
    t0 = clock.now

    def slow_event():
        time.sleep(0.06)  # the host stalls for 60 ms while this event runs
        seen.append(("slow", clock.now))
        clock.after(300.0, lambda: seen.append(("reply", clock.now)))

    clock.at(t0 + 100.0, slow_event)
    clock.at(t0 + 50000.0, lambda: seen.append(("deadline", clock.now)))
    clock.run_until(t0 + 70000.0)
    assert [name for name, _ in seen] == ["slow", "reply", "deadline"]
    assert seen[0][1] == t0 + 100.0 and seen[1][1] == t0 + 400.0 and seen[2][1] == t0 + 50000.0
    assert clock.now == t0 + 70000.0 and clock.wall() >= clock.now  # never ahead of the wall clock


def test_paced_clock_reports_how_far_it_lags_the_wall_clock():
    """A simulation that falls behind the wall clock (a loaded host) delays every request
    from outside by the lag: its bytes reach the bus at their wall time. A PC whose timeout
    is shorter reads that as a deaf jig (a ReadTrace with 300 ms, the sim 300 ms late);
    the clock says how late it is, now and at worst, so the two can be told apart."""
    import time

    from motorjig.sim.clock import PacedClock

    clock = PacedClock()
    t0 = clock.now
    clock.run_until(t0 + 2000.0)
    assert clock.max_lag_us < 20000.0
    clock.at(t0 + 3000.0, lambda: time.sleep(0.08))  # the host stalls 80 ms in an event
    clock.at(t0 + 3100.0, lambda: None)
    clock.run_until(t0 + 3100.0)
    assert clock.lag_us >= 70000.0 and clock.max_lag_us >= 70000.0
    clock.run_until(clock.wall() + 2000.0)  # caught up: no lag now, the worst one kept
    assert clock.lag_us < 20000.0 and clock.max_lag_us >= 70000.0


def test_a_host_stall_during_a_drive_turnaround_is_no_jig_timeout(bench, monkeypatch):
    """The bench thread frozen for 80 ms (> the jig's 50 ms reply timeout) right when a
    drive answers: on the bench's timeline nothing happened, the reply is relayed."""
    import time

    from motorjig.master import Master

    d = bench.sim.drivers[2]
    real = d._send_reply

    def stalled(*args):
        time.sleep(0.08)  # what a garbage collection or a busy machine does to the thread
        return real(*args)

    monkeypatch.setattr(d, "_send_reply", stalled)
    with Master(bench.tcp_url, timeout=0.5, retries=0) as m:
        m.reset_counters(1)
        for _ in range(3):
            assert m.get_command_pos(2) == d._positions()[0]
        assert m.read_counters(1)["timeouts"] == 0


def test_a_pty_nobody_reads_does_not_stop_the_bench_for_tcp_clients():
    """Every reply also goes to the pty; with nobody reading it, its buffer fills after
    ~20 KB. The bench must go on answering its TCP clients (it blocked there once)."""
    with Bench(driver_ids=(2,), baud=921600, pty=True) as b:
        with serial.serial_for_url(b.tcp_url, baudrate=921600, timeout=0.05) as s:
            req = F.encode(1, F.GET_SLAVE_INFO)  # a 30-byte reply
            n_ok = 0
            for _ in range(1200):  # ~36 KB of replies, more than the pty holds
                s.write(req)
                body = read_frame(s)
                if body is None or body[:3] != b"\x01\x01\x00":
                    break  # (the bench stopped answering: no point waiting 2 s 1 000 times)
                n_ok += 1
            assert n_ok == 1200
        # a reader who opens the pty now gets fresh replies, not a backlog of stale ones
        with serial.serial_for_url(b.pty_path, baudrate=921600, timeout=0.05) as p:
            p.reset_input_buffer()
            p.write(F.encode(2, F.GET_COMMAND_POS))
            body = read_frame(p)
            assert body is not None and body[:3] == b"\x02\x51\x00"


def test_a_simulation_stuck_at_stop_keeps_its_ptys_until_it_ends():
    """stop() waits 2 s for the threads; a simulation still inside a pass may write to the
    PC pty afterwards, so its descriptors stay open until it ends (closed then, not
    earlier: a closed number would be reused by the next file this process opens)."""
    import threading

    b = Bench(driver_ids=(2,)).start()
    inside, release = threading.Event(), threading.Event()
    pump = b.sim.clock.pump

    def stuck_pump():
        inside.set()
        release.wait(20)
        pump()

    b.sim.clock.pump = stuck_pump
    assert inside.wait(5)
    fds = (b._master, b._slave, b._cap_pty)
    t = time.monotonic()
    b.stop()
    assert time.monotonic() - t >= 1.9  # it waited for the stuck thread, then returned
    for fd in fds:
        os.fstat(fd)  # still open
    release.set()
    end = time.monotonic() + 5
    while b._master is not None and time.monotonic() < end:
        time.sleep(0.01)
    assert (b._master, b._slave, b._cap_pty) == (None, None, None)  # closed by the thread as it ended
    with pytest.raises(OSError):
        os.fstat(fds[0])


def test_stop_closes_the_ptys_of_a_bench_that_ended_normally():
    b = Bench(driver_ids=(2,)).start()
    fds = (b._master, b._slave, b._cap_pty)
    b.stop()
    assert (b._master, b._slave, b._cap_pty) == (None, None, None)
    for fd in fds:
        with pytest.raises(OSError):
            os.fstat(fd)
