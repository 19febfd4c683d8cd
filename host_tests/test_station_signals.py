"""Every way a station run ends stops the axis: signals, a closed terminal, `timeout`, SIGKILL.

`jigctl test` runs a long move on the real-time bench (the firmware in this process's
Bench, the station in its own process, as a user starts it) and is ended mid-move. For
each catchable ending the run is ABORTED with its cause named, exit 2, the drive stands
still with its servo off (read through a second connection), and the JSON, JUnit XML,
HTML report and database row exist. SIGKILL cannot be caught: the jig's master-silence
safety stop, which the station arms for the run, stops the drive within the window.
"""

import fcntl
import glob
import json
import os
import signal
import subprocess
import sys
import termios
import time

import pytest

from motorjig.master import Master
from motorjig.sim import Bench

from jig import frame as F

JIGCTL = os.path.join(os.path.dirname(sys.executable), "jigctl")
DRIVE = 2
LONG_PLAN = ('[plan]\nname = "long"\nversion = "1"\n[drive]\nslave = 2\n'
             '[[steps]]\nkind = "servo"\n[[steps]]\nkind = "move"\nname = "long_move"\n'
             'distance = 200000\nspeed = 5000\ntimeout_s = 60\n')


def long_plan(tmp_path, text=LONG_PLAN):
    plan = tmp_path / "long.toml"
    plan.write_text(text)
    return str(plan)


def wait_until_moving(b, proc, timeout=30.0):
    deadline = time.monotonic() + timeout
    while not b.sim.drivers[DRIVE].motion.moving:
        assert proc.poll() is None, "jigctl test ended before the move: %s" % (proc.communicate(),)
        assert time.monotonic() < deadline, "the move never started"
        time.sleep(0.05)
    time.sleep(0.3)  # well into the move


def drive_state(url):
    """The drive as a second connection reads it: (moving, servo on, velocity)."""
    with Master(url, timeout=0.3) as m:
        st = m.get_all_status(DRIVE)
        return st.axis.motioning, st.axis.servo_on, st.actual_vel


def on_its_own_terminal():
    """preexec_fn: the child leads a session of its own, with the pty on its stdin as its terminal
    (closing that terminal then sends it SIGHUP, as closing a terminal window does)."""
    os.setsid()
    fcntl.ioctl(0, termios.TIOCSCTTY, 0)


def records(tmp_path):
    found = {ext: glob.glob(str(tmp_path / ("long_*." + ext))) for ext in ("json", "xml", "html")}
    assert all(len(v) == 1 for v in found.values()), found
    with open(found["json"][0]) as f:
        return json.load(f), found


def stored_outcomes(db):
    from motorjig.station.store import open_store

    with open_store(db) as st:
        return [r["verdict"] for r in st.runs()]


def start(b, tmp_path, extra=(), cmd=(), plan=LONG_PLAN, **kw):
    db = str(tmp_path / "results.sqlite")
    args = list(cmd) + [JIGCTL, "test", long_plan(tmp_path, plan), "--port", b.tcp_url, "--yes", "--out", str(tmp_path),
                        "--db", db] + list(extra)
    return subprocess.Popen(args, **kw), db


class bench(Bench):
    """The real-time bench with one drive that keeps the (time, frame type) of what it receives."""

    def __init__(self):
        super().__init__(driver_ids=(DRIVE,), baud=115200, pty=False)

    def __enter__(self):
        super().__enter__()
        self.sim.drivers[DRIVE].record_requests = True
        return self


def check_safe_and_recorded(b, tmp_path, db, cause):
    moving, servo_on, vel = drive_state(b.tcp_url)
    assert not moving and not servo_on and vel == 0
    record, files = records(tmp_path)
    assert record["outcome"] == "ABORTED"
    assert record["outcome_details"][0]["description"].startswith(cause), record["outcome_details"]
    assert record["metadata"]["end_cause"].startswith(cause)
    assert stored_outcomes(db) == ["ABORTED"]
    with open(files["xml"][0]) as f:
        assert cause in f.read()
    return record


@pytest.mark.parametrize("sig,cause", [(signal.SIGINT, "interrupted by SIGINT"),
                                       (signal.SIGTERM, "terminated by SIGTERM"),
                                       (signal.SIGHUP, "terminated by SIGHUP")],
                         ids=["SIGINT", "SIGTERM", "SIGHUP"])
def test_a_signal_mid_move_stops_the_axis_and_writes_every_record(tmp_path, sig, cause):
    with bench() as b:
        p, db = start(b, tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        wait_until_moving(b, p)
        p.send_signal(sig)
        out, err = p.communicate(timeout=60)
        assert p.returncode == 2, (out, err)
        assert "Traceback" not in err and "Traceback" not in out
        assert cause in out and "ABORTED" in out, out
        d = b.sim.drivers[DRIVE]
        estops = [t for t, ft in d.received if ft == F.EMERGENCY_STOP]
        assert estops, "no EmergencyStop reached the drive"
        check_safe_and_recorded(b, tmp_path, db, cause)
        # the jig's safety stop was armed for the run and is off again
        with Master(b.tcp_url, timeout=0.3) as m:
            assert m.get_parameter(1, 9) == 0


def test_timeout_ends_the_run_like_sigterm(tmp_path):
    """`timeout 20 jigctl test ...` (20 s: time enough to start on a busy machine; the move takes 40 s):
    timeout's SIGTERM (its own exit status is 124)."""
    with bench() as b:
        p, db = start(b, tmp_path, cmd=("timeout", "20"), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out, err = p.communicate(timeout=60)
        print(out, err)
        assert p.returncode == 124
        assert b.sim.drivers[DRIVE].motion.pos > 0, "the move had not started when timeout struck: too slow a bench"
        check_safe_and_recorded(b, tmp_path, db, "terminated by SIGTERM")


def test_a_closed_terminal_ends_the_run_like_sighup(tmp_path):
    """jigctl on a pty as its controlling terminal; the terminal goes away (the kernel's SIGHUP,
    and EIO on every later write): the run ends as after SIGHUP, nothing hangs."""
    master, slave = os.openpty()

    with bench() as b:
        p, db = start(b, tmp_path, stdin=slave, stdout=slave, stderr=slave, preexec_fn=on_its_own_terminal)
        os.close(slave)
        try:
            wait_until_moving(b, p)
        finally:
            os.close(master)  # the terminal is gone: SIGHUP to its session
        assert p.wait(timeout=60) == 2
        check_safe_and_recorded(b, tmp_path, db, "terminated by SIGHUP")


@pytest.mark.parametrize("on_end,servo_off", [("stop-servo-off", True), ("none", False)])
def test_sigkill_mid_move_the_jig_stops_the_axis_within_the_window(tmp_path, on_end, servo_off):
    """Nothing in jigctl runs after SIGKILL: the jig's safety stop, armed by the station for the run,
    stops the drive when the PC has been silent for the window (and switches the servo off when
    the plan's on_end says so). Measured on the bench's clock: the stop reaches the drive
    between window and window + 100 ms after the PC's last frame."""
    window_ms = 500
    plan_text = LONG_PLAN.replace('version = "1"\n', 'version = "1"\non_end = "%s"\n' % on_end)
    with bench() as b:
        before = safety_params(b.tcp_url)
        p, db = start(b, tmp_path, extra=("--safety-window", str(window_ms)), plan=plan_text,
                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        wait_until_moving(b, p)
        p.kill()
        p.wait(timeout=10)
        t_kill = b.sim.clock.now
        d = b.sim.drivers[DRIVE]
        deadline = time.monotonic() + 5
        while d.motion.moving and time.monotonic() < deadline:
            time.sleep(0.02)  # no bus traffic meanwhile: any request would be the PC speaking again
        assert not d.motion.moving, "the axis still moves 5 s after SIGKILL"
        time.sleep(0.3)  # the servo-off follows the stop's reply
        t_last_pc = b.sim.pc.node.tx_until
        stops = [t for t, ft in d.received if ft == F.EMERGENCY_STOP and t > t_last_pc]
        assert len(stops) == 1
        silence_ms = (stops[0] - t_last_pc) / 1000.0
        print("silence before the stop: %.1f ms; kill to stop: %.1f ms" % (silence_ms, (stops[0] - t_kill) / 1000.0))
        assert window_ms <= silence_ms <= window_ms + 100, silence_ms
        assert stops[0] - t_kill <= (window_ms + 100) * 1000.0
        offs = [t for t, ft in d.received if ft == F.SERVO_ENABLE and t > stops[0]]
        assert bool(offs) == servo_off, d.received[-6:]
        assert d.servo_on != servo_off
        assert b.sim.counters["safety_stops"] == 1
        moving, servo_on, vel = drive_state(b.tcp_url)  # a second connection, now that talking is harmless
        assert not moving and vel == 0 and servo_on != servo_off
        check_the_next_user_finds_the_bus_as_before(b, before, servo_on=not servo_off)
    assert not glob.glob(str(tmp_path / "long_*.json"))  # SIGKILL: no record, as the docs say


SAFETY_PARAMS = (9, 10, 18)  # safety_timeout_ms, safety_action, can_safety


def safety_params(url):
    with Master(url, timeout=0.3) as m:
        return [m.get_parameter(1, n) for n in SAFETY_PARAMS]


def stats_twice(url):
    """``jigctl stats`` twice in a row: (the first's, the second's) output -- a notice is said once."""
    runs = [subprocess.run([JIGCTL, "--port", url, "stats"], capture_output=True, text=True, timeout=60)
            for _ in range(2)]
    assert all(r.returncode == 0 for r in runs), [r.stderr for r in runs]
    return runs[0].stdout, runs[1].stdout


def check_the_next_user_finds_the_bus_as_before(b, before, servo_on):
    """After the jig's stop the lease is let go: the parameters read back as before the run, the
    next jigctl is told once what happened, and a move of its own followed by silence is not
    stopped by a window nobody asked for."""
    assert safety_params(b.tcp_url) == before
    first, again = stats_twice(b.tcp_url)
    assert "note: the jig stopped drive 2 after the run's master went silent at" in first, first
    assert "note:" not in again  # said once
    if servo_on:
        with Master(b.tcp_url, timeout=0.3) as m:
            m.servo_enable(DRIVE, True)  # (out of the EmergencyStop)
            m.move_velocity(DRIVE, 2000, 1)
        time.sleep(1.5)  # silence, longer than the run's window
        moving, _, _ = drive_state(b.tcp_url)
        assert moving, "a window nobody asked for stopped the next user's move"
        with Master(b.tcp_url, timeout=0.3) as m:
            m.move_stop(DRIVE)


def test_ctrl_c_at_an_operator_prompt_ends_the_run_at_once(tmp_path):
    """The prompt waits on the terminal; Ctrl-C there ends the run within seconds (it waited for the
    operator's next Enter before), ABORTED, the records written."""
    plan = LONG_PLAN.replace('[[steps]]\nkind = "servo"\n',
                             '[[steps]]\nkind = "prompt"\nmessage = "fit the motor"\n[[steps]]\nkind = "servo"\n', 1)
    master, slave = os.openpty()

    with bench() as b:
        db = str(tmp_path / "results.sqlite")
        p = subprocess.Popen([JIGCTL, "test", long_plan(tmp_path, plan), "--port", b.tcp_url, "--out", str(tmp_path),
                              "--db", db], stdin=slave, stdout=slave, stderr=slave, preexec_fn=on_its_own_terminal)
        os.close(slave)
        seen = b""
        deadline = time.monotonic() + 60
        try:
            while b"press Enter when done" not in seen:
                assert time.monotonic() < deadline and p.poll() is None, seen
                try:
                    seen += os.read(master, 4096)
                except OSError:
                    break
            p.send_signal(signal.SIGINT)
            t0 = time.monotonic()
            rc = p.wait(timeout=20)
            assert time.monotonic() - t0 < 5
        finally:
            os.close(master)
        assert rc == 2
        assert b.sim.drivers[DRIVE].motion.pos == 0
    record, _ = records(tmp_path)
    assert record["outcome"] == "ABORTED"
    assert record["outcome_details"][0] == {"code": "SIGINT", "description": "interrupted by SIGINT (Ctrl-C)"}
