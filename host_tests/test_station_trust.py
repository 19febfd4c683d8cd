"""What a user tripped over with `jigctl test`, each checked as they met it.

A jig of one protocol variant serving a drive of the other; `--check` catching, before
anything moves, a prompt nobody can answer and a speed above the drive's maximum;
`--json` answering in JSON when the plan is missing; a run without `$USER`.
"""

import json
import os
import subprocess
import sys

import pytest

from motorjig.master import Master
from motorjig.sim import Bench
from motorjig.station import load_plan, run_plan

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SMOKE = os.path.join(ROOT, "plans", "smoke.toml")
EOL = os.path.join(ROOT, "plans", "ezi-step-eol.toml")
JIGCTL = os.path.join(os.path.dirname(sys.executable), "jigctl")
DRIVE = 2


def jigctl(*args, env=None, stdin=subprocess.DEVNULL):
    return subprocess.run([JIGCTL] + list(args), capture_output=True, text=True, timeout=120, env=env, stdin=stdin)


@pytest.mark.parametrize("jig_ver8,drive_ver8", [(False, True), (True, False)], ids=["jig6-drive8", "jig8-drive6"])
def test_a_jig_and_a_drive_of_different_variants_run_the_smoke_plan(tmp_path, jig_ver8, drive_ver8):
    """The station talks to the jig (ResetCounters, its safety stop) in the jig's variant and to
    the drive in the drive's: before, the run ended ERROR at the jig's first frame."""
    with Bench(driver_ids=(DRIVE,), baud=115200, pty=False, jig_ver8=jig_ver8,
               ver8_drivers=(DRIVE,) if drive_ver8 else ()) as b:
        p = jigctl("test", "--check", SMOKE, "--port", b.tcp_url)
        assert p.returncode == 0, p.stderr
        ctx = run_plan(load_plan(SMOKE), b.tcp_url, out_dir=str(tmp_path), out=None, timeout_ms=300,
                       confirm=lambda m: True)
        rec = ctx.record
        assert rec["outcome"] == "PASS", (rec["outcome_details"], [(p["name"], p["outcome"]) for p in rec["phases"]])
        assert rec["metadata"]["drive"]["protocol"] == (8 if drive_ver8 else 6)
        assert rec["metadata"]["safety_net"]["armed"] is True
        with Master(b.tcp_url, timeout=0.3) as m:
            assert m.variant(1) == (8 if jig_ver8 else 6)
            assert m.get_parameter(1, 9) == 0  # disarmed again


def test_check_notes_a_prompt_nobody_could_answer_but_needs_no_terminal(tmp_path):
    """EOL's first step is a prompt: no terminal (stdin is not one) and no --yes. A check moves
    nothing and asks nothing: it passes (the README's `jigctl test --check plans/ezi-step-eol.toml`
    in a CI job) and notes what the run will need."""
    p = jigctl("test", "--check", EOL)
    assert p.returncode == 0, p.stderr
    assert "is valid" in p.stdout
    assert p.stderr.startswith("jigctl: note: step prompt asks the operator to confirm") and "--yes" in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1
    ok = jigctl("test", "--check", EOL, "--yes")
    assert ok.returncode == 0 and ok.stderr == ""
    with Bench(driver_ids=(DRIVE,), baud=115200, pty=False) as b:  # the drive read too: the note stays
        p = jigctl("test", "--check", EOL, "--port", b.tcp_url)
    assert p.returncode == 0 and "the drive is the plan's" in p.stdout, p.stderr
    assert p.stderr.startswith("jigctl: note: step prompt asks the operator to confirm"), p.stderr


def test_a_run_with_a_prompt_and_no_terminal_moves_nothing(tmp_path):
    with Bench(driver_ids=(DRIVE,), baud=115200, pty=False) as b:
        p = jigctl("test", EOL, "--port", b.tcp_url, "--out", str(tmp_path), "--db", "none")
        assert p.returncode == 2 and "--yes" in p.stderr
        d = b.sim.drivers[DRIVE]
        assert not d.servo_on and d.motion.pos == 0
        assert b.sim.counters["up_frames_in"] == 0  # the bus was not even asked
    assert not list(tmp_path.iterdir())


def test_check_with_the_port_refuses_a_speed_above_the_drives_maximum(tmp_path):
    plan = tmp_path / "fast.toml"
    with open(SMOKE) as f:
        plan.write_text(f.read().replace("speed = 20000", "speed = 400000", 1))
    with Bench(driver_ids=(DRIVE,), baud=115200, pty=False) as b:
        with Master(b.tcp_url, timeout=0.3) as m:
            m.set_parameter(DRIVE, 1, 300000)  # axis_max_speed
        p = jigctl("test", "--check", str(plan), "--port", b.tcp_url)
        assert p.returncode == 2
        assert "step out moves at 400000 pps, above slave 2's axis_max_speed (parameter 1) of 300000" in p.stderr
        assert jigctl("test", "--check", str(plan)).returncode == 0  # without the drive: nothing to compare
        ctx = run_plan(load_plan(str(plan)), b.tcp_url, out_dir=str(tmp_path), out=None, timeout_ms=300,
                       confirm=lambda m: True)
        assert ctx.record["outcome"] == "ERROR"
        assert "axis_max_speed" in ctx.record["outcome_details"][0]["description"]
        assert b.sim.drivers[DRIVE].motion.pos == 0 and not b.sim.drivers[DRIVE].servo_on


def test_json_errors_are_json(tmp_path):
    p = jigctl("--json", "test", str(tmp_path / "nope.toml"))
    assert p.returncode == 2
    doc = json.loads(p.stdout)
    assert doc["verdict"] == "ERROR" and "nope.toml" in doc["error"]


def test_without_user_the_operator_is_the_login_name_or_unknown(monkeypatch):
    import getpass
    import pwd

    from motorjig.testcmd import default_operator

    monkeypatch.delenv("USER", raising=False)
    monkeypatch.delenv("LOGNAME", raising=False)
    assert default_operator() == pwd.getpwuid(os.getuid()).pw_name  # a service's own account

    def no_user():
        raise KeyError("getpwuid(): uid not found: 12345")  # a container's uid without a passwd entry

    monkeypatch.setattr(getpass, "getuser", no_user)
    assert default_operator() == "unknown"
    monkeypatch.setenv("USER", "anna")
    assert default_operator() == "anna"


def test_a_pc_that_stalls_past_the_safety_window_makes_the_step_an_error_not_a_fail(tmp_path, monkeypatch):
    """This PC hangs for 1 s inside a request mid-move (the heartbeat waits behind it): the jig's
    safety stop rightly stops the axis, and the step that was measuring ends ERROR, naming the
    stop, instead of failing a good drive on a move the PC cut short."""
    from motorjig.station import plug

    plan = tmp_path / "long.toml"
    plan.write_text('[plan]\nname = "long"\nversion = "1"\n[drive]\nslave = 2\n'
                    '[[steps]]\nkind = "servo"\n[[steps]]\nkind = "move"\nname = "long_move"\n'
                    'distance = 20000\nspeed = 5000\nposition_error_max = 0\n')
    calls = {"n": 0}
    request = plug.TimedMaster.request

    def stalling(self, slave, ftype, *a, **kw):
        if slave == DRIVE or ftype == 0xF7:
            calls["n"] += 1
            if calls["n"] == 40:
                with self.lock:
                    import time
                    time.sleep(1.0)
        return request(self, slave, ftype, *a, **kw)

    monkeypatch.setattr(plug.TimedMaster, "request", stalling)
    with Bench(driver_ids=(DRIVE,), baud=115200, pty=False) as b:
        ctx = run_plan(load_plan(str(plan)), b.tcp_url, out_dir=str(tmp_path), out=None, timeout_ms=300,
                       confirm=lambda m: True, safety_window_ms=300)
        assert b.sim.counters["safety_stops"] >= 1
    rec = ctx.record
    assert rec["outcome"] == "ERROR", [(p["name"], p["outcome"]) for p in rec["phases"]]
    last = rec["phases"][-1]
    assert last["name"] == "long_move" and last["outcome"] == "ERROR"
    assert "the jig's safety stop fired during the step" in json.dumps(rec)


@pytest.mark.parametrize("late_us,verdict", [(0, "PASS"), (4000, "FAIL")])
def test_bus_health_judges_the_drives_response_on_the_jigs_clock(tmp_path, late_us, verdict):
    """A drive that answers 4 ms late fails drive_response_max (the jig timed it, request's end to
    reply's end); a healthy one passes, and this PC's round trip is only reported."""
    plan = tmp_path / "bus.toml"
    plan.write_text('[plan]\nname = "bus"\nversion = "1"\n[drive]\nslave = 2\n'
                    '[[steps]]\nkind = "bus-health"\nturnaround_max_us = 100000\ndrive_response_max_us = 6000\n')
    with Bench(driver_ids=(DRIVE,), baud=115200, pty=False) as b:
        if late_us:
            b.sim.drivers[DRIVE].set_fault("late", late_us)
        ctx = run_plan(load_plan(str(plan)), b.tcp_url, out_dir=str(tmp_path), out=None, timeout_ms=300,
                       confirm=lambda m: True)
    rec = ctx.record
    assert rec["outcome"] == verdict, rec["outcome_details"]
    ms = rec["phases"][-1]["measurements"]
    response = ms["drive_response_max"]["measured_value"]
    assert 3600 < response < 4500 + late_us  # the reply's 3.6 ms on the wire + the drive's turnaround (+ late)
    assert ms["roundtrip_max"]["outcome"] == "PASS" and not ms["roundtrip_max"].get("validators")
