"""MotorJig Station steps on the bench, for what a user's report found: a move to where the axis
already is judged a duration it never measured, and an operator prompt ended by OpenHTF's
3-minute phase timeout (a TIMEOUT verdict, a traceback) instead of waiting for the operator."""

import os
import time

import pytest
from openhtf.core import phase_executor

from motorjig.sim import Bench
from motorjig.station import load_plan, run_plan
from motorjig.station import phases as PH

DRIVE = 2
HEAD = '[plan]\nname = "t"\nversion = "1"\n[drive]\nslave = 2\n'


def bench():
    return Bench(driver_ids=(DRIVE,), baud=115200, pty=False)


def run(tmp_path, text, **kw):
    path = tmp_path / "plan.toml"
    path.write_text(HEAD + text)
    kw.setdefault("confirm", lambda message: True)
    with bench() as b:
        ctx = run_plan(load_plan(str(path)), b.tcp_url, out_dir=str(tmp_path / "out"), out=None, timeout_ms=300,
                       **kw)
    return ctx, ctx.record


def phase(record, name):
    return next(p for p in record["phases"] if p["name"] == name)


def test_an_abs_move_to_where_the_axis_is_judges_no_duration_ratio(tmp_path):
    """An inc move of 0 is refused by the plan (test_station_plans); an abs move to the position the
    axis is at cannot be known before the run: its duration_ratio is left out (SKIPPED), not 1.0."""
    ctx, rec = run(tmp_path, '[[steps]]\nkind = "servo"\n'
                             '[[steps]]\nkind = "move"\nname = "home_again"\nmode = "abs"\nposition = 0\nspeed = 20000\n'
                             '[[steps]]\nkind = "move"\nname = "out"\nmode = "abs"\nposition = 2000\nspeed = 20000\n')
    assert rec["outcome"] == "PASS"
    m = phase(rec, "home_again")["measurements"]
    assert m["duration_ratio"]["outcome"] == "SKIPPED" and "measured_value" not in m["duration_ratio"]
    assert m["expected_duration"]["measured_value"] == 0 and m["position_error"]["measured_value"] == 0
    assert m["in_position"]["measured_value"] is True
    out = phase(rec, "out")["measurements"]["duration_ratio"]
    assert out["outcome"] == "PASS" and 0.85 <= out["measured_value"] <= 1.15
    with open(ctx.files["xml"]) as f:
        assert "<failure" not in f.read()
    with open(ctx.files["html"]) as f:
        page = f.read()
    assert 'class="meas" data-measurement="duration_ratio" data-outcome="SKIPPED"' in page  # not red


def test_a_prompt_waits_for_the_operator_past_openhtfs_phase_timeout(tmp_path, monkeypatch, capfd):
    monkeypatch.setattr(phase_executor, "DEFAULT_PHASE_TIMEOUT_S", 1.0)  # OpenHTF's is 180 s

    def slow_operator(message):
        end = time.monotonic() + 4.0  # short waits, as the Desk's dialog does
        while time.monotonic() < end:
            time.sleep(0.05)
        return True

    ctx, rec = run(tmp_path, '[[steps]]\nkind = "prompt"\nmessage = "put the motor on"\n'
                             '[[steps]]\nkind = "servo"\non = false\n', confirm=slow_operator)
    assert rec["outcome"] == "PASS", rec["outcome_details"]
    assert phase(rec, "prompt")["measurements"]["confirmed"]["measured_value"] is True
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err and "ThreadTerminationError" not in out + err


def test_every_step_gets_a_phase_timeout_beyond_its_own(tmp_path):
    path = tmp_path / "plan.toml"
    path.write_text(HEAD + '[[steps]]\nkind = "prompt"\nmessage = "m"\n'
                           '[[steps]]\nkind = "move"\ndistance = 10\nspeed = 10\ntimeout_s = 3600\n'
                           '[[steps]]\nkind = "limit-sensor"\nrelay = 0\nafter_ms = 60000\ntimeout_s = 600\n'
                           '[[steps]]\nkind = "servo"\n'
                           '[[wiring.relay]]\nrelay = 0\ndrive_input = 0\n')
    prompt, move, limit, servo = load_plan(str(path)).steps
    assert PH.phase_timeout(prompt) > 365 * 86400  # the operator's time: only Abort or Ctrl-C ends it
    assert PH.phase_timeout(move) == 3660.0  # OpenHTF's 180 s would have cut a long move short
    assert PH.phase_timeout(limit) == 720.0
    assert PH.phase_timeout(servo) == 180.0


if __name__ == "__main__":
    raise SystemExit(pytest.main([os.path.abspath(__file__), "-q"]))
