"""MotorJig Station on a CiA 402 drive: plans run through the jig's SLCAN port on the real-time bench.

The bench's simulated CiA 402 drive (node 5) behind the simulated jig, the station as a user
runs it: a healthy drive passes `cia402-smoke`, its moves traced by TPDOs dated by the jig's
clock; an overcurrent fault mid-move fails the move with the EMCY named and leaves the drive
with its operation disabled; Ctrl-C and SIGTERM on `jigctl test` end the run ABORTED with
the drive disabled; the jig's CAN safety stop is armed for the run and put back after it.
"""

import os
import signal
import subprocess
import sys
import time

import pytest

from motorjig.master import Master
from motorjig.sim import Bench
from motorjig.station import load_plan, run_plan

from jig.params import P_CAN_SAFETY
from test_station_signals import safety_params, stats_twice

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SMOKE = os.path.join(ROOT, "plans", "cia402-smoke.toml")
EOL = os.path.join(ROOT, "plans", "cia402-eol.toml")
JIGCTL = os.path.join(os.path.dirname(sys.executable), "jigctl")
NODE = 5
LONG_PLAN = ('[plan]\nname = "long402"\nversion = "1"\n[drive]\nprotocol = "cia402"\nnode_id = 5\n'
             '[[steps]]\nkind = "servo"\n[[steps]]\nkind = "move"\nname = "long_move"\n'
             'distance = 400000\nspeed = 20000\naccel = 500000\ndecel = 500000\n')


def bench(**kw):
    return Bench(driver_ids=(2,), can_nodes=(NODE,), can_bitrate=500000, pty=False, **kw)


def eol_bench():
    return bench(wiring=load_plan(EOL).wiring)


def run(b, tmp_path, plan_path=SMOKE, **kw):
    plan = load_plan(plan_path)
    # The bench runs in real time in this process on a shared, busy machine: a stall of the
    # process is a gap in the trace (the step would end ERROR, rightly). The trace's rate is
    # make bench's business; here a floor of 20 Hz (gaps up to 200 ms) lets the verdicts show.
    plan.sample_rate_min = 20.0
    ctx = run_plan(plan, b.tcp_url, can_port=b.slcan_url, out_dir=str(tmp_path), out=None,
                   timeout_ms=300, confirm=lambda message: True, **kw)
    return ctx.record


def phase(record, name):
    return next(p for p in record["phases"] if p["name"] == name)


def failed(record):
    return {p["name"]: {n for n, m in p["measurements"].items() if m["outcome"] != "PASS"}
            for p in record["phases"] if p["outcome"] != "PASS"}


def node(b):
    return b.sim.can_nodes[NODE]


def operation_disabled(b):
    """True when the simulated drive's operation is not enabled (statusword bit 2 clear) and it stands still."""
    nd = node(b)
    return not nd.statusword() & 0x04 and not nd.motion.moving


def test_frames_are_dated_by_the_jigs_slcan_timestamps_unwrapped_past_60_s():
    from motorjig.station.drive_cia402 import StampedSlcanBus

    bus = StampedSlcanBus(channel="loop://", bitrate=500000, sleep_after_open=0)  # what it writes comes back
    try:
        bus.serialPortOrig.write(b"t705105EA5F\rt7051050010\rT000005851AA0064\rr7050000A\rt705105\r")
        got = []
        while len(got) < 5:
            msg = bus.recv(1.0)
            assert msg is not None, got
            got.append((msg.arbitration_id, round(msg.timestamp, 3)))
    finally:
        bus.shutdown()
    # 59 999 ms, then the field wraps: 60.016 s; extended and remote frames carry it too;
    # a line without a timestamp keeps python-can's own (this PC's) time
    assert got[:4] == [(0x705, 59.999), (0x705, 60.016), (0x585, 60.1), (0x705, 60.01)]
    assert got[4][1] > 1e9


def test_cia402_smoke_passes_traced_by_tpdos_dated_by_the_jig(tmp_path):
    with bench() as b:
        rec = run(b, tmp_path)
        with Master(b.tcp_url, timeout=0.3) as m:
            can_safety = m.get_parameter(1, P_CAN_SAFETY)
        assert operation_disabled(b)
    assert rec["outcome"] == "PASS", failed(rec)
    assert [p["name"] for p in rec["phases"]] == ["preflight", "identify", "servo_on", "out", "back", "servo_off"]
    assert rec["metadata"]["drive"]["protocol"] == "cia402" and rec["metadata"]["drive"]["node_id"] == NODE
    assert rec["metadata"]["sampling"] == {"by": "drive", "period_us": 2000, "dated_by": "jig"}
    assert rec["metadata"]["safety_net"]["armed"]
    assert can_safety == 0  # the CAN safety stop was the run's only: put back
    out = phase(rec, "out")["measurements"]
    assert out["position_error"]["measured_value"] == 0
    assert 0.9 <= out["duration_ratio"]["measured_value"] <= 1.1
    assert out["emcy"]["measured_value"] == "none"
    assert phase(rec, "servo_on")["measurements"]["state"]["measured_value"] == "OPERATION ENABLED"


def test_an_overcurrent_mid_move_fails_the_move_with_the_emcy_named_and_disables_the_drive(tmp_path):
    with bench() as b:
        b.sim.set_fault("can:overcurrent", 30, NODE)
        rec = run(b, tmp_path)
        assert operation_disabled(b)
    assert rec["outcome"] == "FAIL"
    assert list(failed(rec)) == ["out"]  # stop_on_fail: nothing after it ran
    out = phase(rec, "out")["measurements"]
    assert "0x2310" in out["emcy"]["measured_value"] and out["emcy"]["outcome"] == "FAIL"
    assert out["fault"]["measured_value"] == 0x2310 and out["fault"]["outcome"] == "FAIL"
    assert out["target_reached"]["measured_value"] is False


def test_cia402_eol_passes_on_a_healthy_drive(tmp_path):
    with eol_bench() as b:
        rec = run(b, tmp_path, EOL)
        assert operation_disabled(b)
    assert rec["outcome"] == "PASS", failed(rec)
    names = [p["name"] for p in rec["phases"]]
    assert names[1:5] == ["identify", "parameters", "alarm-reset", "servo_on"]
    assert {"home", "io", "limit-sensor", "quick_stop", "halt", "bus-health"} <= set(names)
    health = phase(rec, "bus-health")["measurements"]
    assert health["heartbeats"]["measured_value"] if "heartbeats" in health else True
    assert health["emcy"]["measured_value"] == 0 and health["lost_frames"]["measured_value"] == 0
    servo = [p for p in rec["phases"] if "transition_time_max" in p["measurements"]]
    assert servo and all(p["measurements"]["transition_time_max"]["measured_value"] >= 0 for p in servo)  # a time


# fault -> (the step that must catch it, the measurements that must fail there)
EOL_FAULTS = {
    "following-error": ("move_speed_50000", {"emcy", "fault", "following_error", "position_error", "target_reached"}),
    "overcurrent": ("move_speed_5000", {"emcy", "fault", "position_error", "target_reached"}),
    "sluggish": ("move_speed_5000", {"duration_ratio"}),
    "no-origin": ("home", {"homing_attained"}),
    "missed-heartbeat": ("bus-health", {"heartbeat_jitter"}),
    "dead-input": ("io", {"relay_2_on"}),
    "param": ("parameters", {"x6065_00"}),  # following error window off its golden value
    "sdo-abort": ("parameters", {"x6065_00"}),  # a node that aborts the read of one object
}
# the value each fault is set with (None: the fault's default)
EOL_FAULT_VALUES = {"dead-input": 16, "param": "0x6065=500", "sdo-abort": "0x06040047@0x6065"}


@pytest.mark.parametrize("fault", list(EOL_FAULTS))
def test_each_fault_fails_cia402_eol_at_its_step_and_leaves_the_drive_disabled(tmp_path, fault):
    step, measurements = EOL_FAULTS[fault]
    with eol_bench() as b:
        b.sim.set_fault("can:" + fault, EOL_FAULT_VALUES.get(fault), NODE)
        rec = run(b, tmp_path, EOL)
        assert operation_disabled(b), node(b).state
    assert rec["outcome"] == "FAIL", failed(rec)
    got = failed(rec)
    assert list(got) == [step], got
    assert measurements <= got[step], got


def test_a_node_that_does_not_answer_ends_the_run_as_an_error_saying_so(tmp_path):
    plan = tmp_path / "node7.toml"
    with open(SMOKE) as f:
        plan.write_text(f.read().replace("node_id = 5", "node_id = 7"))
    with bench() as b:
        rec = run(b, tmp_path, str(plan))
    assert rec["outcome"] == "ERROR"
    assert any("node 7 does not answer" in d["description"] for d in rec["outcome_details"]), rec["outcome_details"]


def test_a_refused_parameter_read_shows_the_abort_on_the_console_and_in_the_html(tmp_path):
    lines = []
    with eol_bench() as b:
        b.sim.set_fault("can:sdo-abort", "0x06040047@0x6065", NODE)
        plan = load_plan(EOL)
        plan.sample_rate_min = 20.0
        ctx = run_plan(plan, b.tcp_url, can_port=b.slcan_url, out_dir=str(tmp_path), out=lines.append,
                       timeout_ms=300, confirm=lambda message: True)
    console = "\n".join(str(x) for x in lines)
    assert "x6065_00 = unset: refused by the drive: SDO abort 0x06040047 general internal incompatibility" in console
    with open(ctx.files["html"]) as f:
        html = f.read()
    assert "not measured: refused by the drive: SDO abort 0x06040047 general internal incompatibility" in html


def test_a_node_that_aborts_every_sdo_is_said_to_answer_with_its_abort_not_to_be_silent(tmp_path):
    with bench() as b:
        b.sim.set_fault("can:sdo-abort", "0x08000000", NODE)
        rec = run(b, tmp_path)
    assert rec["outcome"] == "ERROR"
    text = " ".join(d["description"] for d in rec["outcome_details"])
    assert "node 5 answers" in text and "abort 0x08000000 general error" in text.lower(), text
    assert "does not answer" not in text and "cable" not in text


def long_run_moving(b, tmp_path, *extra):
    """`jigctl test` of LONG_PLAN on bench b in a process of its own, returned once node 5 moves."""
    plan = tmp_path / "long402.toml"
    plan.write_text(LONG_PLAN)
    p = subprocess.Popen([JIGCTL, "test", str(plan), "--port", b.tcp_url, "--can-port", b.slcan_url,
                          "--out", str(tmp_path), "--db", "none", "--yes", *extra],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not node(b).motion.moving:
            assert p.poll() is None, "jigctl test ended before the move: %s" % (p.communicate(),)
            assert time.monotonic() < deadline, "the move never started"
            time.sleep(0.05)
    except BaseException:
        p.kill()
        raise
    time.sleep(0.3)
    return p


def wait_operation_disabled(b, within_s=5.0):
    deadline = time.monotonic() + within_s
    while not operation_disabled(b) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert operation_disabled(b), node(b).state


def frames_a_quiet_session_sees(url, seconds=3.0):
    """A fresh python-can session on the jig's SLCAN port that sends nothing: what it receives."""
    import can

    got = []
    with can.Bus(interface="slcan", channel=url, bitrate=500000) as bus:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            msg = bus.recv(timeout=0.2)
            if msg is not None:
                got.append(msg)
    return got


def test_sigkill_mid_move_the_jig_stops_the_drive_then_leaves_a_quiet_bus_as_before(tmp_path):
    """What no handler catches: the jig's CAN safety stop (can_safety = 2, armed for the run) sends
    the quick stop after the --safety-window of silence on its SLCAN port, then resets the nodes'
    communication (the run's 2 ms TPDOs and its heartbeat stop) and lets its safety net go: the
    parameters read back as before the run, the next python-can session quiet for 3 s sees no
    frame it did not cause, and the next jigctl is told once."""
    with Bench(driver_ids=(2,), can_nodes=(NODE, 6), can_bitrate=500000, pty=False) as b:
        before = safety_params(b.tcp_url)
        p = long_run_moving(b, tmp_path, "--safety-window", "500")
        try:
            p.kill()
            p.communicate(timeout=30)
        finally:
            if p.poll() is None:
                p.kill()
        wait_operation_disabled(b)
        time.sleep(0.5)  # the resets of communication follow the quick stops
        with Master(b.tcp_url, timeout=0.3) as m:
            assert m.can_counters(1)["can_safety_stops"] == 1
        assert safety_params(b.tcp_url) == before
        assert frames_a_quiet_session_sees(b.slcan_url) == []
        assert operation_disabled(b)
        first, again = stats_twice(b.tcp_url)
    assert "note: the jig stopped CAN node 5 after the run's master went silent at" in first, first  # (6: never heard)
    assert "note:" not in again


LSS_PLAN = ('[plan]\nname = "lss402"\nversion = "1"\n[drive]\nprotocol = "cia402"\nnode_id = 5\n'
            '[[steps]]\nkind = "lss"\n[[steps]]\nkind = "identify"\n[[steps]]\nkind = "servo"\n'
            '[[steps]]\nkind = "move"\ndistance = 5000\nspeed = 20000\naccel = 500000\ndecel = 500000\n'
            '[[steps]]\nkind = "servo"\nname = "servo_off"\non = false\n')


def unconfigure(b):
    """Node 5 as a drive fresh from its box: LSS node id 255, stored (it answers LSS only)."""
    import canopen

    with canopen.Network() as net:
        net.connect(channel=b.slcan_url, interface="slcan", bitrate=500000, sleep_after_open=0.05)
        net.lss.send_switch_state_global(net.lss.CONFIGURATION_STATE)
        net.lss.configure_node_id(255)
        net.lss.store_configuration()
        net.lss.send_switch_state_global(net.lss.WAITING_STATE)
        net.nmt.send_command(0x81)  # reset node: it comes back with the stored id (none)
        deadline = time.monotonic() + 5
        while node(b).node_id != 255 and time.monotonic() < deadline:
            time.sleep(0.05)


def test_an_lss_step_gives_an_unconfigured_drive_the_plans_node_id_and_the_run_goes_on(tmp_path):
    plan = tmp_path / "lss402.toml"
    plan.write_text(LSS_PLAN)
    with bench() as b:
        unconfigure(b)
        assert node(b).node_id == 255
        rec = run(b, tmp_path, str(plan))
        assert node(b).node_id == NODE
    assert rec["outcome"] == "PASS", failed(rec)
    lss = phase(rec, "lss")["measurements"]
    assert lss["found"]["measured_value"] is True and lss["node_id"]["measured_value"] == NODE
    assert lss["serial"]["measured_value"] == "%08X" % rec["metadata"]["drive"]["serial"]
    assert rec["dut_id"].startswith("node5-")


def test_a_plan_for_a_cia402_drive_needs_the_can_port(tmp_path):
    p = subprocess.run([JIGCTL, "test", SMOKE, "--port", "socket://127.0.0.1:9", "--db", "none", "--out",
                        str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    assert "--can-port" in p.stderr and "Traceback" not in p.stderr


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_signal_mid_move_leaves_the_drive_disabled(tmp_path, sig):
    with bench() as b:
        p = long_run_moving(b, tmp_path)
        try:
            p.send_signal(sig)
            out, err = p.communicate(timeout=60)
        finally:
            if p.poll() is None:
                p.kill()
        wait_operation_disabled(b)
        # the run's heartbeat and trace PDOs are gone with it: communication reset, PRE-OPERATIONAL
        deadline = time.monotonic() + 5
        while not (node(b).values[(0x1017, 0)] == 0 and node(b).nmt == 0x7F) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert node(b).values[(0x1017, 0)] == 0 and node(b).nmt == 0x7F, (node(b).values[(0x1017, 0)], node(b).nmt)
    assert p.returncode == 2, (out, err)
    assert "ABORTED" in out and "Traceback" not in err
    assert "stopping the axis (quick stop, disable voltage)" in out and "EmergencyStop" not in out  # its words
