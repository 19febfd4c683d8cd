"""MotorJig Station on an EtherCAT CiA 402 servo: plans run by SOEM (pysoem) against the bench's EtherCAT line.

The bench's simulated servos behind their veth interface (``ecat_bench``, its own process) and the
simulated jig for the PC port; the station as a user runs it: a healthy servo passes `ecat-smoke`
and `ecat-eol` (CSP moves at 1 ms, sampled every cycle), each injected fault fails `ecat-eol` at
its step, a lost frame makes a move ERROR (the measurement's), never FAIL, a servo that refuses OP
ends the run ERROR with its AL status code, and `--check` refuses a bad EtherCAT plan with file,
line and key. Root only (a network namespace); skipped, saying so, without it.
"""

import os
import subprocess
import sys

import pytest

from motorjig.sim import Bench
from motorjig.station import load_plan, run_plan

pytest.importorskip("pysoem")
if os.geteuid() != 0:
    pytest.skip("the EtherCAT bench needs root (a network namespace and raw sockets)", allow_module_level=True)

from test_ecat_pysoem import Bench as EcatBench  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SMOKE = os.path.join(ROOT, "plans", "ecat-smoke.toml")
EOL = os.path.join(ROOT, "plans", "ecat-eol.toml")


@pytest.fixture(scope="module")
def line():
    ecat = EcatBench(1, "s%d" % os.getpid())
    jig = Bench(driver_ids=(2,), pty=False)
    jig.start()
    try:
        yield jig, ecat
    finally:
        jig.stop()
        ecat.stop()


def run(line, tmp_path, plan_path=SMOKE, tries=2):
    """The run's record. A run the station could not judge because this busy PC sent cycles late
    (ERROR, 'cannot be judged') is run once more: that is the PC's lateness, not the drive's."""
    jig, ecat = line
    for _ in range(tries):
        ecat.cmd("power-cycle")
        plan = load_plan(plan_path)
        plan.sample_rate_min = 20.0
        ctx = run_plan(plan, jig.tcp_url, ecat_ifname=ecat.ifname, out_dir=str(tmp_path), out=None,
                       timeout_ms=300, confirm=lambda message: True)
        rec = ctx.record
        late = rec["outcome"] == "ERROR" and "cycle" in " ".join(d["description"] for d in rec["outcome_details"])
        if not late:
            return rec
    return rec


def failed(record):
    return {p["name"]: {n for n, m in p["measurements"].items() if m["outcome"] != "PASS"}
            for p in record["phases"] if p["outcome"] != "PASS"}


def state(ecat):
    return ecat.cmd("state 0")


def test_a_healthy_servo_passes_the_smoke_plan_its_record_naming_it_by_its_sii(line, tmp_path):
    rec = run(line, tmp_path)
    assert rec["outcome"] == "PASS", (failed(rec), rec["outcome_details"])
    drive = rec["metadata"]["drive"]
    assert drive["protocol"] == "ethercat" and drive["name"] == "MotorJig ECAT servo"
    assert (drive["vendor_id"], drive["product_code"]) == (0x4D4A4947, 0x402)
    assert rec["dut_id"].startswith("ecat-00000402-")
    assert rec["metadata"]["safety_net"]["armed"] is False  # the slave's watchdog is the net
    assert rec["metadata"]["sampling"]["dated_by"] == "distributed clock"
    out = next(p for p in rec["phases"] if p["name"] == "out")["measurements"]
    assert out["samples"]["measured_value"] >= 400  # one a cycle over a ~0.55 s move
    assert ", SWITCH ON DISABLED," in state(line[1])  # the run ends with the drive disabled


def test_a_healthy_servo_passes_the_eol_plan(line, tmp_path):
    rec = run(line, tmp_path, EOL)
    assert rec["outcome"] == "PASS", (failed(rec), rec["outcome_details"])
    names = [p["name"] for p in rec["phases"]]
    assert {"ten_turns", "home", "quick_stop", "halt", "bus-health"} <= set(names)
    health = next(p for p in rec["phases"] if p["name"] == "bus-health")["measurements"]
    assert health["frames_lost"]["measured_value"] == 0 and health["emcy"]["measured_value"] == 0


# fault -> (its value, the step that must catch it, the measurements that must fail there)
EOL_FAULTS = {
    "following-error": ("30000", "move_speed_50000", {"emcy", "fault", "following_error", "position_error",
                                                      "target_reached"}),
    "overcurrent": (None, "move_speed_5000", {"emcy", "fault", "position_error", "target_reached"}),
    "no-origin": (None, "home", {"homing_attained"}),
    "param": ("0x6065=500", "parameters", {"x6065_00"}),
    "sdo-abort": ("0x06040047@0x6065", "parameters", {"x6065_00"}),
}


@pytest.mark.parametrize("fault", list(EOL_FAULTS))
def test_each_fault_fails_ecat_eol_at_its_step_and_leaves_the_drive_disabled(line, tmp_path, fault):
    value, step, measurements = EOL_FAULTS[fault]
    jig, ecat = line

    def run_faulted():
        ecat.cmd("power-cycle")
        ecat.cmd("fault 0:%s%s" % (fault, "" if value is None else "=" + value))
        plan = load_plan(EOL)
        plan.sample_rate_min = 20.0
        return run_plan(plan, jig.tcp_url, ecat_ifname=ecat.ifname, out_dir=str(tmp_path), out=None, timeout_ms=300,
                        confirm=lambda message: True).record

    rec = run_faulted()
    if rec["outcome"] == "ERROR":  # this PC sent cycles late: once more
        rec = run_faulted()
    assert rec["outcome"] == "FAIL", (failed(rec), rec["outcome_details"])
    got = failed(rec)
    assert list(got) == [step], got
    assert measurements <= got[step], got
    said = state(ecat)
    assert "OPERATION ENABLED" not in said, said


def test_lost_frames_make_a_move_an_error_of_the_measurement_never_a_fail(line, tmp_path):
    jig, ecat = line
    ecat.cmd("power-cycle")
    ecat.cmd("fault 0:lost-frames=40")
    plan = load_plan(SMOKE)
    ctx = run_plan(plan, jig.tcp_url, ecat_ifname=ecat.ifname, out_dir=str(tmp_path), out=None, timeout_ms=300,
                   confirm=lambda message: True)
    rec = ctx.record
    assert rec["outcome"] == "ERROR", failed(rec)
    text = " ".join(d["description"] for d in rec["outcome_details"])
    # a lost process-data frame during a move, or a lost mailbox frame during an SDO: either way the
    # run could not judge the drive and says why
    assert ("cannot be judged" in text and "frame" in text) or "did not answer the SDO" in text, text
    assert not any(p["outcome"] == "FAIL" for p in rec["phases"])


def test_a_servo_that_refuses_op_ends_the_run_as_an_error_with_its_al_code(line, tmp_path):
    jig, ecat = line
    ecat.cmd("power-cycle")
    ecat.cmd("fault 0:refuse-op=0x001A")
    rec = run_plan(load_plan(SMOKE), jig.tcp_url, ecat_ifname=ecat.ifname, out_dir=str(tmp_path), out=None,
                   timeout_ms=300, confirm=lambda message: True).record
    assert rec["outcome"] == "ERROR"
    text = " ".join(d["description"] for d in rec["outcome_details"])
    assert "did not go to OP" in text and "0x001A" in text, text


def jigctl(*args):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(os.path.join(ROOT, d) for d in ("firmware", "tools")))
    return subprocess.run([sys.executable, "-m", "motorjig.cli"] + list(args), capture_output=True, text=True,
                          env=env, cwd=ROOT)


@pytest.mark.parametrize("edit, said", [
    (("position = 0 ", "position = -1 "), "drive.position"),
    (("cycle_ms = 1.0", "cycle_ms = 0.1"), "drive.cycle_ms"),
    (("position = 0 ", "position = 0\nesi = \"nowhere.xml\" "), "drive.esi"),
    (('kind = "identify"', 'kind = "lss"'), "lss"),
])
def test_check_refuses_a_bad_ethercat_plan_with_file_line_and_key(tmp_path, edit, said):
    with open(SMOKE) as f:
        text = f.read()
    assert edit[0] in text
    path = tmp_path / "bad.toml"
    path.write_text(text.replace(edit[0], edit[1], 1))
    r = jigctl("test", str(path), "--check")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert str(path) in r.stderr and said in r.stderr, r.stderr


def test_a_run_without_the_interface_or_with_a_wrong_one_is_refused_in_one_sentence(tmp_path, line):
    jig, _ecat = line
    r = jigctl("test", SMOKE, "--port", jig.tcp_url, "--db", "none", "--out", str(tmp_path))
    assert r.returncode == 2 and "give this PC's network interface on the EtherCAT line with --ecat-ifname" in r.stderr
    r = jigctl("test", SMOKE, "--port", jig.tcp_url, "--ecat-ifname", "nosuch0", "--db", "none", "--out",
               str(tmp_path))
    assert r.returncode == 2 and "no network interface named nosuch0" in r.stderr and "Traceback" not in r.stderr


LONG_PLAN = ('[plan]\nname = "long-ecat"\nversion = "1"\n[drive]\nprotocol = "ethercat"\nposition = 0\n'
             '[[steps]]\nkind = "servo"\n[[steps]]\nkind = "move"\nname = "long_move"\n'
             'distance = 600000\nspeed = 20000\naccel = 500000\ndecel = 500000\n')


def start_long_run(line, tmp_path):
    """`jigctl test` of a 30 s move in a session of its own; returns once the shaft turns."""
    import time

    jig, ecat = line
    ecat.cmd("power-cycle")
    plan = tmp_path / "long.toml"
    plan.write_text(LONG_PLAN)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(os.path.join(ROOT, d) for d in ("firmware", "tools")))
    proc = subprocess.Popen([sys.executable, "-m", "motorjig.cli", "test", str(plan), "--port", jig.tcp_url,
                             "--ecat-ifname", ecat.ifname, "--db", "none", "--out", str(tmp_path), "--yes"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT,
                            start_new_session=True)
    deadline = time.monotonic() + 30
    while "velocity 20000" not in ecat.cmd("state 0"):
        assert time.monotonic() < deadline and proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    return proc


def wait_for(ecat, text, seconds):
    import time

    deadline = time.monotonic() + seconds
    while True:
        said = ecat.cmd("state 0")
        if text in said:
            return said
        assert time.monotonic() < deadline, said
        time.sleep(0.01)


def test_sigterm_mid_move_ends_the_run_aborted_with_the_drive_stopped_and_disabled(line, tmp_path):
    import glob
    import json
    import signal

    proc = start_long_run(line, tmp_path)
    os.kill(proc.pid, signal.SIGTERM)
    proc.wait(30)
    said = wait_for(line[1], ", velocity 0,", 5)
    assert "OPERATION ENABLED" not in said, said
    (path,) = glob.glob(str(tmp_path / "long-ecat_*.json"))
    with open(path) as f:
        assert json.load(f)["outcome"] == "ABORTED"


def test_sigkill_of_jigctl_leaves_its_master_to_stop_and_disable_the_drive(line, tmp_path):
    import signal

    proc = start_long_run(line, tmp_path)
    os.kill(proc.pid, signal.SIGKILL)  # the station's process only: its master process sees its pipe close
    said = wait_for(line[1], "SWITCH ON DISABLED", 5)
    assert ", velocity 0," in said
    wait_for(line[1], "0: AL 0x01,", 5)  # and took the line to INIT


def test_sigkill_of_everything_leaves_the_slaves_watchdog_to_stop_the_drive(line, tmp_path):
    import signal
    import time

    proc = start_long_run(line, tmp_path)
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGKILL)  # jigctl and its master process: no frame goes out any more
    said = wait_for(line[1], "FAULT", 2)
    took = time.monotonic() - t0
    assert ", velocity 0," in said and "AL 0x14" in said, said  # SAFE-OP with the error bit
    assert took < 1.0, took  # the watchdog is 100 ms


def test_the_desks_ethercat_link_opens_the_line_moves_stops_and_lends_it_to_a_plans_run(line):
    from motorjig.desk import ecattab
    from motorjig.desk.axes import give_back
    from motorjig.desk.ecatlink import EcatLink
    from motorjig.desk.page import DeskPage
    from motorjig.desk.session import BusSession, UserError
    from motorjig.desk.testrun import Station
    import time

    _jig, ecat = line
    ecat.cmd("power-cycle")
    link = EcatLink()
    with pytest.raises(UserError, match="give the network interface"):
        link.open("")
    with pytest.raises(UserError, match="no network interface named nosuch0"):
        link.open("nosuch0", 0)
    assert "in OP" in link.open(ecat.ifname, 0)
    try:
        assert [s["name"] for s in link.slaves()] == ["MotorJig ECAT servo"] and link.line[0]["state"] == "OP"
        assert link.sdo_read("0x1000").startswith("0x1000:00 = 0x20192")
        with pytest.raises(UserError, match="press Enable first"):
            link.move(1000, 10000)
        assert link.enable() == "slave 0: OPERATION ENABLED"
        target = link.status()["position"] + 5000  # the shaft is where the last test left it
        link.move(target, 20000)
        deadline = time.monotonic() + 5
        while link.status()["position"] != target:
            assert time.monotonic() < deadline, link.status()
            time.sleep(0.02)
        page = DeskPage(BusSession(), extra=[(ecattab, link, None)])
        assert "tab-ecat" in [t[0] for t in page._tab_list()] and link.desk_axis in page._axes()
        assert link.desk_axis.stop(True) == "slave 0: quick stop"  # the header's EMERGENCY STOP
        plan = load_plan(SMOKE)
        station = Station(BusSession(), plans_dir=os.path.join(ROOT, "plans"), out_dir=os.path.join(ROOT, "results"))
        station.axes = [link.desk_axis]
        ports, lent = station._lend_ports(plan)
        assert ports == {"ecat_ifname": ecat.ifname} and link.summary() == "lent to the test run (ecat-smoke)"
        assert ", velocity 0," in ecat.cmd("state 0") and "OPERATION ENABLED" not in ecat.cmd("state 0")
        with pytest.raises(UserError, match="lent to the test run"):
            link.open()
        assert give_back(lent) == [] and link.is_open  # opened again after the run
    finally:
        link.close()
    assert link.status() is None and "0: AL 0x01," in ecat.cmd("state 0")


def test_the_ethercat_hil_tests_pass_against_the_benchs_line(line):
    """host_tests/hil/test_hil_ecat.py, meant for a real drive on a NIC, run against the bench's line as a
    user runs it (so it cannot rot before the first real drive)."""
    _jig, ecat = line
    ecat.cmd("power-cycle")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(os.path.join(ROOT, d) for d in ("firmware", "tools")))
    r = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider",
                        os.path.join(ROOT, "host_tests", "hil", "test_hil_ecat.py"), "--ecat-ifname", ecat.ifname,
                        "--ecat-allow-move", "-rA"], capture_output=True, text=True, timeout=300, env=env, cwd=ROOT)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    lines = out.splitlines()
    assert not [x for x in lines if x.startswith(("SKIPPED", "FAILED", "ERROR"))], out
    assert sum(1 for x in lines if x.startswith("PASSED")) == 3, out
