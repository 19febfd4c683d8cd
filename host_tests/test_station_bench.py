"""MotorJig Station end to end: plans run through the real firmware on the real-time bench.

A healthy drive passes `smoke` and `ezi-step-eol` in Ver6 and Ver8; every fault a real
drive has makes `ezi-step-eol` fail at the step meant to catch it, on the right
measurement, and leaves the axis stopped and the servo off; a drive of the wrong
variant is refused before anything moves; a lost connection and Ctrl-C end the run
as errors with the record still written.
"""

import glob
import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from motorjig import cli
from motorjig.master import Master
from motorjig.sim import Bench
from motorjig.station import load_plan, run_plan
from motorjig.wiring import load_wiring

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SMOKE = os.path.join(ROOT, "plans", "smoke.toml")
EOL = os.path.join(ROOT, "plans", "ezi-step-eol.toml")
JIGCTL = os.path.join(os.path.dirname(sys.executable), "jigctl")
DRIVE = 2


def bench(ver8=False, wiring=True, **kw):
    return Bench(driver_ids=(DRIVE,), baud=115200, pty=False, jig_ver8=ver8,
                 ver8_drivers=(DRIVE,) if ver8 else (), wiring=load_wiring(EOL) if wiring else None, **kw)


def run(plan_path, url, tmp_path, **kw):
    kw.setdefault("confirm", lambda message: True)
    ctx = run_plan(load_plan(plan_path), url, out_dir=str(tmp_path), out=None, timeout_ms=300, **kw)
    return ctx, ctx.record


def phase(record, name):
    return next(p for p in record["phases"] if p["name"] == name)


def failed_phases(record):
    return [p for p in record["phases"] if p["outcome"] != "PASS"]


def failed_measurements(ph):
    return {n for n, m in ph["measurements"].items() if m["outcome"] != "PASS"}


def axis_state(url):
    with Master(url, timeout=0.3) as m:
        return m.get_axis_status(DRIVE)


@pytest.mark.parametrize("ver8", [False, True], ids=["ver6", "ver8"])
def test_smoke_passes_through_the_jig(tmp_path, ver8):
    with bench(ver8, wiring=False) as b:
        ctx, rec = run(SMOKE, b.tcp_url, tmp_path)
    assert rec["outcome"] == "PASS", failed_phases(rec)
    assert rec["metadata"]["drive"]["protocol"] == (8 if ver8 else 6)
    assert [p["name"] for p in rec["phases"]] == ["preflight", "identify", "servo", "out", "back", "servo_off"]
    out = phase(rec, "out")["measurements"]
    assert out["position_error"]["measured_value"] == 0
    assert 0.85 <= out["duration_ratio"]["measured_value"] <= 1.15
    for ext in ("json", "xml", "html"):
        assert os.path.exists(ctx.files[ext])


@pytest.mark.parametrize("ver8", [False, True], ids=["ver6", "ver8"])
def test_the_eol_plan_passes_on_a_healthy_drive(tmp_path, ver8):
    with bench(ver8) as b:
        ctx, rec = run(EOL, b.tcp_url, tmp_path, serial="SN-OK-1", operator="ci")
        st = axis_state(b.tcp_url)
    assert rec["outcome"] == "PASS", [(p["name"], failed_measurements(p)) for p in failed_phases(rec)]
    assert rec["dut_id"] == "SN-OK-1" and rec["metadata"]["operator"] == "ci"
    names = [p["name"] for p in rec["phases"]]
    for name in ("move_speed_5000", "move_speed_20000", "move_speed_50000", "home", "io", "limit-sensor",
                 "stop-response", "emergency_stop", "bus-health", "servo_off"):
        assert name in names
    assert not st.servo_on  # the plan's last step


FAULTS = [
    # (fault, value, the step that must catch it, measurements that must fail there)
    ("step-out", 20000, "move_speed_50000", {"following_error", "position_error"}),
    ("alarm", "1@30", "move_speed_5000", {"alarm"}),
    ("sluggish", 1.5, "move_speed_5000", {"duration_ratio"}),
    ("param", "3:250", "parameters", {"ram_axis_acc_time", "rom_axis_acc_time"}),
    ("no-origin", None, "home", {"origin_ok"}),
    ("dead-input", 26, "io", {"relay_2_on"}),
]


@pytest.mark.parametrize("fault,value,step,measurements", FAULTS, ids=[f[0] for f in FAULTS])
def test_each_fault_fails_the_eol_plan_at_its_step(tmp_path, fault, value, step, measurements):
    with bench() as b:
        b.sim.drivers[DRIVE].set_fault(fault, value)
        ctx, rec = run(EOL, b.tcp_url, tmp_path)
        time.sleep(0.05)
        st = axis_state(b.tcp_url)
    assert rec["outcome"] == "FAIL"
    bad = failed_phases(rec)
    assert bad[0]["name"] == step, [(p["name"], failed_measurements(p)) for p in bad]
    assert measurements <= failed_measurements(bad[0])
    assert rec["phases"][-1]["name"] == step  # stop_on_fail: nothing ran after it
    assert not st.motioning and not st.servo_on, st
    with open(ctx.files["xml"]) as f:
        xml = f.read()
    assert sorted(measurements)[0] in xml  # the JUnit failure names the measurement


def test_a_ver8_plan_on_a_ver6_drive_is_refused_before_anything_moves(tmp_path, capsys):
    plan = tmp_path / "v8.toml"
    with open(SMOKE) as f:
        plan.write_text(f.read().replace("protocol = [6, 8]", "protocol = 8"))
    with bench(wiring=False) as b:
        rc = cli.main(["test", "--check", str(plan), "--port", b.tcp_url])
        err = capsys.readouterr().err
        assert rc == 2 and "the plan is for a Ver8 drive, but slave 2 answers as Ver6" in err
        ctx, rec = run(str(plan), b.tcp_url, tmp_path)
        drive = b.sim.drivers[DRIVE]
        assert not drive.servo_on and drive.motion.pos == 0
    assert rec["outcome"] == "ERROR"
    assert [p["name"] for p in rec["phases"]] == ["preflight"]
    assert "answers as Ver6" in rec["outcome_details"][0]["description"]


def test_a_connection_lost_mid_run_ends_it_as_error_with_the_record(tmp_path):
    b = bench()
    b.start()
    threading.Timer(1.2, b.stop).start()  # during move_speed_5000 (2.1 s)
    try:
        ctx, rec = run(EOL, b.tcp_url, tmp_path)
    finally:
        b.stop()
    assert rec["outcome"] == "ERROR"
    last = rec["phases"][-1]
    assert last["name"] == "move_speed_5000" and last["outcome"] == "ERROR"
    assert phase(rec, "identify")["outcome"] == "PASS"
    with open(ctx.files["json"]) as f:
        assert json.load(f)["outcome"] == "ERROR"


def test_ctrl_c_ends_with_an_emergency_stop_and_servo_off(tmp_path):
    plan = tmp_path / "long.toml"
    plan.write_text('[plan]\nname = "long"\nversion = "1"\n[drive]\nslave = 2\n'
                    '[[steps]]\nkind = "servo"\n[[steps]]\nkind = "move"\ndistance = 200000\nspeed = 5000\ntimeout_s = 60\n')
    with bench(wiring=False) as b:
        p = subprocess.Popen([JIGCTL, "test", str(plan), "--port", b.tcp_url, "--yes", "--out", str(tmp_path)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 20
        while not b.sim.drivers[DRIVE].motion.moving and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=30)
        drive = b.sim.drivers[DRIVE]
        assert not drive.motion.moving and drive.estop and not drive.servo_on, (out, err)
    assert p.returncode == 2, (out, err)
    assert "Traceback" not in err
    records = glob.glob(str(tmp_path / "long_*.json"))
    with open(records[0]) as f:
        assert json.load(f)["outcome"] == "ABORTED"


def test_a_prompt_without_a_terminal_or_yes_is_an_error(tmp_path):
    with bench() as b:
        ctx, rec = run(EOL, b.tcp_url, tmp_path, confirm=None)
    assert rec["outcome"] == "ERROR"
    assert rec["phases"][-1]["name"] == "prompt"
    assert "--yes" in rec["phases"][-1]["result"]["phase_result"] or "--yes" in json.dumps(rec["outcome_details"])


def test_jigctl_test_prints_a_line_per_step_and_exits_1_on_a_failure(tmp_path):
    with bench() as b:
        b.sim.drivers[DRIVE].set_fault("param", "3:250")
        p = subprocess.run([JIGCTL, "test", EOL, "--port", b.tcp_url, "--yes", "--out", str(tmp_path),
                            "--serial", "SN7"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 1, p.stderr
    lines = p.stdout.splitlines()
    assert any(ln.startswith("[ 1/") and "prompt" in ln and "PASS" in ln for ln in lines), p.stdout
    assert any("parameters" in ln and "FAIL" in ln for ln in lines), p.stdout
    assert any("ram_axis_acc_time = 250 (x == 100)" in ln for ln in lines), p.stdout
    assert any(ln.startswith("FAIL  ezi-step-eol  dut SN7") for ln in lines), p.stdout
    assert any(ln.startswith("  html ") and ln.endswith(".html") for ln in lines), p.stdout


def test_jigctl_test_with_a_wrong_port_is_one_sentence(tmp_path):
    p = subprocess.run([JIGCTL, "test", SMOKE, "--port", "/dev/ttyNOPE0", "--yes", "--out", str(tmp_path)],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    assert p.stderr.startswith("jigctl: ") and len(p.stderr.strip().splitlines()) == 1 and "ttyNOPE0" in p.stderr


def test_param_dump_and_load_through_the_jig(tmp_path, capsys):
    path = tmp_path / "set.toml"
    with bench(wiring=False) as b:
        assert cli.main(["--port", b.tcp_url, "param", "dump", str(path)]) == 0
        text = path.read_text()
        assert "axis_acc_time = 100" in text
        path.write_text(text.replace("axis_acc_time = 100", "axis_acc_time = 321"))
        assert cli.main(["--port", b.tcp_url, "param", "load", str(path), "--save"]) == 0
        drive = b.sim.drivers[DRIVE]
        assert drive.ram[3] == 321 and drive.rom[3] == 321
        path.write_text(text.replace("axis_acc_time = 100", "axis_jerk = 1"))
        capsys.readouterr()
        assert cli.main(["--port", b.tcp_url, "param", "load", str(path)]) == 2
        assert "axis_jerk: the drive has no such parameter" in capsys.readouterr().err


def test_the_plug_and_phases_in_a_users_own_openhtf_script(tmp_path):
    """The example of docs/station.md: our plug and phases beside the user's own phase."""
    import openhtf as htf
    from openhtf.util import configuration

    from motorjig.station import MotorJigPlug, RunContext, build_phase

    records = []
    with bench(wiring=False) as b:
        configuration.CONF.load(motorjig_port=b.tcp_url, motorjig_slave=2)

        @htf.measures(htf.Measurement("supply_voltage").in_range(23.0, 25.0))
        def supply(test):
            test.measurements.supply_voltage = 24.1

        @htf.plug(bus=MotorJigPlug)
        def servo_on(test, bus):
            bus.master.servo_enable(bus.slave, True)

        plan = load_plan(SMOKE)
        ctx = RunContext(plan)
        test = htf.Test(supply, servo_on, *[build_phase(s, plan, ctx) for s in plan.steps if s.kind == "move"])
        test.add_output_callbacks(records.append)
        test.execute(test_start=lambda: "SN1234")
    rec = records[0]
    assert rec.outcome.name == "PASS" and rec.dut_id == "SN1234"
    assert [p.name for p in rec.phases][-3:] == ["servo_on", "out", "back"]


def test_a_parameters_step_in_apply_mode_writes_saves_and_verifies(tmp_path):
    (tmp_path / "golden.toml").write_text("[drive]\nslave_type = 20\n[parameters]\naxis_acc_time = 222\n"
                                          "org_speed = 7000\n")
    plan = tmp_path / "apply.toml"
    plan.write_text('[plan]\nname = "apply"\nversion = "1"\n[drive]\nslave = 2\n'
                    '[[steps]]\nkind = "parameters"\nmode = "apply"\nfile = "golden.toml"\n')
    with bench(wiring=False) as b:
        ctx, rec = run(str(plan), b.tcp_url, tmp_path)
        drive = b.sim.drivers[DRIVE]
        assert (drive.ram[3], drive.rom[3], drive.ram[17], drive.rom[17]) == (222, 222, 7000, 7000)
    assert rec["outcome"] == "PASS"
    ms = phase(rec, "parameters")["measurements"]
    assert set(ms) == {"ram_axis_acc_time", "rom_axis_acc_time", "ram_org_speed", "rom_org_speed"}
    assert ms["rom_org_speed"]["measured_value"] == 7000


def test_making_safe_goes_on_when_the_stop_is_refused():
    """MoveStop answered with an error status: EmergencyStop and servo off are still sent."""
    from motorjig.station.plug import make_safe

    with bench(wiring=False) as b:
        drive = b.sim.drivers[DRIVE]
        with Master(b.tcp_url, timeout=0.3) as m:
            m.servo_enable(DRIVE, True)
            m.move_velocity(DRIVE, 5000, 1)
            drive.force(0x85, frames=1)  # the next request (MoveStop) is refused
            problems = make_safe(m, DRIVE)
            st = m.get_axis_status(DRIVE)
    assert len(problems) == 1 and problems[0].startswith("MoveStop")
    assert not st.motioning and not st.servo_on and st.emergency_stop


def test_a_refused_drive_keeps_the_operators_serial(tmp_path):
    plan = tmp_path / "servo.toml"
    plan.write_text('[plan]\nname = "t"\nversion = "1"\n[drive]\nslave = 2\nslave_type = 1\n'
                    '[[steps]]\nkind = "servo"\n')
    with bench(wiring=False) as b:
        ctx, rec = run(str(plan), b.tcp_url, tmp_path, serial="SN77")
    assert rec["outcome"] == "ERROR" and rec["dut_id"] == "SN77"
    assert "slave type 1" in rec["outcome_details"][0]["description"]


def test_an_unwritable_out_folder_is_refused_before_anything_moves(tmp_path):
    (tmp_path / "file").write_text("")
    with bench(wiring=False) as b:
        p = subprocess.run([JIGCTL, "test", SMOKE, "--port", b.tcp_url, "--yes", "--db", "none",
                            "--out", str(tmp_path / "file" / "x")], capture_output=True, text=True, timeout=60)
        assert b.sim.drivers[DRIVE].requests == 0
    assert p.returncode == 2 and p.stderr.startswith("jigctl: cannot use ") and "Traceback" not in p.stderr


def test_a_report_that_cannot_be_written_leaves_the_verdict_and_the_stored_run(tmp_path, monkeypatch):
    from motorjig.station import report

    def broken(record):
        raise RuntimeError("disk full")

    monkeypatch.setattr(report, "html_report", broken)
    with bench(wiring=False) as b:
        ctx, rec = run(SMOKE, b.tcp_url, tmp_path, db=str(tmp_path / "r.sqlite"))
    assert rec["outcome"] == "PASS" and ctx.run_id == 1
    assert "html" not in ctx.files and os.path.exists(ctx.files["json"])
    assert "disk full" in ctx.write_errors[0]


def test_an_io_step_that_errors_leaves_no_relay_on(tmp_path):
    plan = tmp_path / "io.toml"
    with open(EOL) as f:
        eol = f.read()
    plan.write_text(eol[: eol.index("[[steps]]")] + '[[steps]]\nkind = "io"\n')
    with bench() as b:
        drive = b.sim.drivers[DRIVE]

        def on_event(ev):  # the drive refuses its first request of the io step
            if ev.get("event") == "step" and ev["state"] == "running":
                drive.force(0x85, frames=1)

        ctx, rec = run(str(plan), b.tcp_url, tmp_path, on_event=on_event)
        assert b.sim.hal.outputs == 0
    assert rec["outcome"] == "ERROR" and rec["phases"][-1]["name"] == "io"


def test_an_abort_before_the_first_step_moves_nothing(tmp_path):
    with bench(wiring=False) as b:
        ctx, rec = run(SMOKE, b.tcp_url, tmp_path, on_start=lambda c: c.abort())
        drive = b.sim.drivers[DRIVE]
        assert drive.motion.pos == 0 and not drive.servo_on
    assert rec["outcome"] in ("ERROR", "ABORTED") and [p["name"] for p in rec["phases"]] == ["preflight"]
