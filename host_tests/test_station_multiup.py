"""Multi-up: one station tests several drives at once, each slot its own run, verdict and records.

On the real-time bench (the jig's firmware in this process, jigctl in its own process as a
user starts it): four Ezi-STEP drives in a 4-up fixture, two healthy, one that steps out, one
that raises an alarm, give two PASS and two FAIL at their own steps, four records and four
database rows, and the healthy slots measure what a drive tested alone measures, each sampled
by the jig. At 115 200 baud four moving slots get fewer samples than the plan's floor: ERROR,
never FAIL. Every ending
with four axes moving leaves them all still: SIGINT, SIGTERM, SIGKILL (the jig's safety
stop). Slots that would fight over a drive, a relay or an input are refused before anything
moves.
"""

import glob
import json
import os
import signal
import subprocess
import sys
import time

import pytest

from motorjig.master import Master
from motorjig.sim import Bench
from motorjig.station import load_plan, run_plan
from motorjig.station import slots as SL

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EOL = os.path.join(ROOT, "plans", "ezi-step-eol.toml")
FOUR_UP = os.path.join(ROOT, "plans", "multiup", "ezi-step-4up.toml")
JIGCTL = os.path.join(os.path.dirname(sys.executable), "jigctl")
DRIVES = (2, 3, 4, 5)
LONG_PLAN = ('[plan]\nname = "long"\nversion = "1"\n[drive]\nslave = 2\n'
             '[[steps]]\nkind = "servo"\n[[steps]]\nkind = "move"\nname = "long_move"\n'
             'distance = 200000\nspeed = 5000\ntimeout_s = 60\n')


def four_up_bench():
    """At 921 600 baud: the jig's sampler gives each of four moving drives 250 samples/s (at 115 200
    baud about 53, under the plan's floor of 100: their moving steps would be ERROR, not judged)."""
    wirings = [s.plan.wiring for s in SL.load_slots(FOUR_UP, EOL)]
    return Bench(driver_ids=DRIVES, baud=921600, pty=False, wiring=wirings)


def jigctl_test(plan, slots, url, tmp_path, *extra, **kw):
    args = [JIGCTL, "test", plan, "--slots", slots, "--port", url, "--yes", "--out", str(tmp_path),
            "--db", str(tmp_path / "results.sqlite")] + list(extra)
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def the_records(tmp_path, pattern):
    out = {}
    for path in glob.glob(str(tmp_path / pattern)):
        with open(path) as f:
            rec = json.load(f)
        out[rec["metadata"]["slot"]] = rec
    return out


def stored(tmp_path):
    from motorjig.station.store import open_store

    with open_store(str(tmp_path / "results.sqlite")) as st:
        return sorted(r["verdict"] for r in st.runs())


def failed(rec):
    return [(p["name"], sorted(n for n, m in p["measurements"].items() if m["outcome"] != "PASS"))
            for p in rec["phases"] if p["outcome"] != "PASS"]


def still(url, drives=DRIVES):
    """Each drive as a second connection reads it: (moving, velocity)."""
    with Master(url, timeout=0.5) as m:
        return {s: (m.get_all_status(s).axis.motioning, m.get_all_status(s).actual_vel) for s in drives}


def test_four_slots_two_healthy_two_faulty_each_judged_alone(tmp_path):
    alone = tmp_path / "alone"
    with four_up_bench() as b:
        ctx = run_plan(load_plan(EOL, wiring=None), b.tcp_url, out_dir=str(alone), out=None, timeout_ms=300,
                       confirm=lambda m: True, serial="ALONE")
        single = ctx.record
        b.sim.drivers[4].set_fault("step-out", 20000)
        b.sim.drivers[5].set_fault("alarm", "1@30")
        p = jigctl_test(EOL, FOUR_UP, b.tcp_url, tmp_path)
        out, err = p.communicate(timeout=240)
        axes = still(b.tcp_url)
    assert single["outcome"] == "PASS", failed(single)
    assert p.returncode == 1, (out, err)  # some failed, none unjudged
    assert "Traceback" not in err
    assert "FAIL: 2 of 4 slots passed" in out, out
    recs = the_records(tmp_path, "ezi-step-eol_*.json")
    assert sorted(recs) == ["1", "2", "3", "4"]
    verdicts = {k: r["outcome"] for k, r in recs.items()}
    assert verdicts == {"1": "PASS", "2": "PASS", "3": "FAIL", "4": "FAIL"}, {k: failed(r) for k, r in recs.items()}
    assert failed(recs["3"])[0][0] == "move_speed_50000"
    assert {"following_error", "position_error"} <= set(failed(recs["3"])[0][1])
    assert failed(recs["4"])[0] == ("move_speed_5000", ["alarm"]) or "alarm" in failed(recs["4"])[0][1]
    assert {r["metadata"]["drive"]["slave"] for r in recs.values()} == set(DRIVES)
    assert stored(tmp_path) == ["FAIL", "FAIL", "PASS", "PASS"]
    for name in ("1", "2"):  # the healthy slots measure what the drive measured alone
        for ph in recs[name]["phases"]:
            one = next(p for p in single["phases"] if p["name"] == ph["name"])
            assert len(ph["measurements"]) == len(one["measurements"])  # (the io step names its slot's relays)
            for m, v in ph["measurements"].items():
                assert v["outcome"] == "PASS" == one["measurements"].get(m, v)["outcome"], (name, ph["name"], m)
            if ph["name"].startswith("move_speed"):
                got, ref = (x["measurements"]["duration_ratio"]["measured_value"] for x in (ph, one))
                assert abs(got - ref) <= 0.05, (name, ph["name"], got, ref)
                assert ph["measurements"]["position_error"]["measured_value"] == 0
        sampling = recs[name]["metadata"]["sampling"]
        assert sampling["by"] == "jig", sampling
    assert all(not moving and vel == 0 for moving, vel in axes.values()), axes


def long_bench(baud=921600):
    return Bench(driver_ids=DRIVES, baud=baud, pty=False)


def wait_all_moving(b, proc, timeout=30.0):
    deadline = time.monotonic() + timeout
    while not all(b.sim.drivers[s].motion.moving for s in DRIVES):
        assert proc.poll() is None, "jigctl test ended before the moves: %s" % (proc.communicate(),)
        assert time.monotonic() < deadline, "not every axis started to move"
        time.sleep(0.05)
    time.sleep(0.3)


@pytest.mark.parametrize("sig,cause", [(signal.SIGINT, "interrupted by SIGINT"),
                                       (signal.SIGTERM, "terminated by SIGTERM")], ids=["SIGINT", "SIGTERM"])
def test_a_signal_with_four_axes_moving_stops_them_all(tmp_path, sig, cause):
    plan = tmp_path / "long.toml"
    plan.write_text(LONG_PLAN)
    with long_bench() as b:
        p = jigctl_test(str(plan), "2,3,4,5", b.tcp_url, tmp_path)
        wait_all_moving(b, p)
        p.send_signal(sig)
        out, err = p.communicate(timeout=60)
        axes = still(b.tcp_url)
        with Master(b.tcp_url, timeout=0.3) as m:
            window = m.get_parameter(1, 9)
    assert p.returncode == 2, (out, err)
    assert "Traceback" not in err and "Traceback" not in out
    assert all(not moving and vel == 0 for moving, vel in axes.values()), axes
    recs = the_records(tmp_path, "long_*.json")
    assert sorted(recs) == ["1", "2", "3", "4"]
    for rec in recs.values():
        assert rec["outcome"] == "ABORTED"
        assert rec["metadata"]["end_cause"].startswith(cause)
    assert stored(tmp_path) == ["ABORTED"] * 4
    assert window == 0  # the slots' one safety net is off again


def test_sigkill_with_four_axes_moving_the_jig_stops_them_all(tmp_path):
    plan = tmp_path / "long.toml"
    plan.write_text(LONG_PLAN)
    with long_bench() as b:
        p = jigctl_test(str(plan), "2,3,4,5", b.tcp_url, tmp_path, "--safety-window", "500")
        wait_all_moving(b, p)
        p.kill()
        p.wait(timeout=10)
        deadline = time.monotonic() + 5
        while any(b.sim.drivers[s].motion.moving for s in DRIVES) and time.monotonic() < deadline:
            time.sleep(0.02)
        moving = {s: b.sim.drivers[s].motion.moving for s in DRIVES}
        stops = b.sim.counters["safety_stops"]
    assert not any(moving.values()), "axes still moving 5 s after SIGKILL: %s" % moving
    assert stops == 1  # one stop of the jig's, for every drive it has seen


LONG_402 = ('[plan]\nname = "long402"\nversion = "1"\n[drive]\nprotocol = "cia402"\nnode_id = 5\n'
            '[[steps]]\nkind = "servo"\n[[steps]]\nkind = "move"\nname = "long_move"\n'
            'distance = 400000\nspeed = 20000\naccel = 500000\ndecel = 500000\n')


def test_sigkill_with_two_plusr_and_two_cia402_axes_moving_the_jig_stops_them_all(tmp_path):
    """Slots of two kinds at once, killed mid-move: the jig's safety lease stops the Plus-R drives
    (EmergencyStop) and the CAN nodes (quick stop) it has seen."""
    (tmp_path / "long.toml").write_text(LONG_PLAN)
    (tmp_path / "long402.toml").write_text(LONG_402)
    slots = write(tmp_path, "mixed.toml", '[[slot]]\nslave = 2\n[[slot]]\nslave = 3\n'
                                          '[[slot]]\nplan = "long402.toml"\nnode_id = 5\n'
                                          '[[slot]]\nplan = "long402.toml"\nnode_id = 6\n')
    with Bench(driver_ids=(2, 3), can_nodes=(5, 6), can_bitrate=500000, baud=921600, pty=False) as b:
        axes = [b.sim.drivers[2], b.sim.drivers[3], b.sim.can_nodes[5], b.sim.can_nodes[6]]
        p = jigctl_test(str(tmp_path / "long.toml"), slots, b.tcp_url, tmp_path, "--can-port", b.slcan_url,
                        "--safety-window", "500")
        deadline = time.monotonic() + 60
        while not all(a.motion.moving for a in axes):
            assert p.poll() is None, "jigctl test ended before the moves: %s" % (p.communicate(),)
            assert time.monotonic() < deadline, "not every axis started to move"
            time.sleep(0.05)
        time.sleep(0.3)
        p.kill()
        p.wait(timeout=10)
        deadline = time.monotonic() + 5
        while any(a.motion.moving for a in axes) and time.monotonic() < deadline:
            time.sleep(0.02)
        moving = [a.motion.moving for a in axes]
        with Master(b.tcp_url, timeout=0.5) as m:
            stops, can_stops = m.read_counters(1)["safety_stops"], m.can_counters(1)["can_safety_stops"]
    assert moving == [False] * 4, "axes still moving 5 s after SIGKILL: %s" % moving
    # one lease: each port's watch stopped once (safety_stops counts both, can_safety_stops the CAN one)
    assert stops == 2 and can_stops == 1, (stops, can_stops)


def test_slots_the_jigs_sampler_cannot_serve_at_the_plans_floor_are_refused(tmp_path):
    """Four moving slots at 115 200 baud would get about 53 samples/s each, under the plan's 100:
    refused with one sentence before anything moves."""
    plan = tmp_path / "long.toml"
    plan.write_text(LONG_PLAN)
    with long_bench(115200) as b:
        p = jigctl_test(str(plan), "2,3,4,5", b.tcp_url, tmp_path)
        out, err = p.communicate(timeout=60)
        moved = [s for s in DRIVES if b.sim.drivers[s].motion.pos != 0]
    assert p.returncode == 2, (out, err)
    assert "4 slots moving at once get at most 53 samples/s each" in err and "nothing was moved" in err, err
    assert "Traceback" not in err and not moved
    assert not glob.glob(str(tmp_path / "long_*.json"))


def test_an_exception_in_one_slots_engine_leaves_the_others_to_finish(tmp_path, monkeypatch):
    from motorjig.station import runner

    plan = tmp_path / "short.toml"
    plan.write_text(LONG_PLAN.replace("distance = 200000", "distance = 2000"))
    slots = SL.load_slots("2,3", str(plan))
    build = runner.build_test

    def broken_for_slot_2(plan, ctx, operator=None, plug=None):
        if ctx.slot == "2":
            raise RuntimeError("a bug in the engine")
        return build(plan, ctx, operator, plug)

    monkeypatch.setattr(runner, "build_test", broken_for_slot_2)
    with Bench(driver_ids=(2, 3), baud=921600, pty=False) as b:
        run = SL.SlotRun(slots, b.tcp_url, out_dir=str(tmp_path), out=None, confirm=lambda m: True, timeout_ms=300)
        ctxs = run.run()
        axes = still(b.tcp_url, (2, 3))
    assert ctxs["1"].record["outcome"] == "PASS"
    assert "2" not in ctxs or ctxs["2"].record is None
    assert run.errors["2"] == "RuntimeError: a bug in the engine"
    verdicts = [SL.summary(s, ctxs.get(s.name), run.errors.get(s.name))["verdict"] for s in slots]
    assert verdicts == ["PASS", "ERROR"] and SL.exit_code(verdicts) == 2
    assert all(not moving for moving, _ in axes.values())


def test_an_exception_in_one_slots_worker_mid_move_stops_its_axis_and_the_others_go_on(tmp_path):
    """A bug in slot 2's code (its event callback raises at the first sample of its axis moving): its step
    ends ERROR with the exception, its axis stops at once; slot 1 moves on to its end and passes."""
    plan = tmp_path / "mid.toml"
    plan.write_text(LONG_PLAN.replace("distance = 200000", "distance = 15000"))
    slots = SL.load_slots("2,3", str(plan))

    def on_event(event):
        if event["slot"] == "2" and event["event"] == "sample" and event["row"][3] != 0:  # (a sample of it moving)
            raise RuntimeError("a bug in slot 2's callback")

    with Bench(driver_ids=(2, 3), baud=921600, pty=False) as b:
        run = SL.SlotRun(slots, b.tcp_url, out_dir=str(tmp_path), out=None, confirm=lambda m: True, timeout_ms=300,
                         on_event=on_event)
        ctxs = run.run()
        time.sleep(0.2)
        axes = still(b.tcp_url, (2, 3))
        positions = {s: b.sim.drivers[s].motion.pos for s in (2, 3)}
    assert ctxs["1"].record["outcome"] == "PASS", failed(ctxs["1"].record)
    rec = ctxs["2"].record
    assert rec["outcome"] == "ERROR" and "a bug in slot 2's callback" in json.dumps(rec["outcome_details"])
    assert positions[2] == 15000 and 0 < positions[3] < 15000, positions
    assert all(not moving and vel == 0 for moving, vel in axes.values()), axes


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


FIXTURE = '[[wiring.relay]]\nrelay = %d\ndrive_input = 0\nname = "limit+"\n'


@pytest.mark.parametrize("slots_text,fixtures,words", [
    ('[[slot]]\nslave = 2\nwiring = "a.toml"\n[[slot]]\nslave = 3\nwiring = "b.toml"\n', (0, 0),
     "both use jig relay 0: a relay or input serves one slot at a time"),
    ('[[slot]]\nslave = 2\n[[slot]]\nslave = 2\n', (), "are one drive"),
    ('[[slot]]\nname = "x"\nslave = 2\n[[slot]]\nname = "x"\nslave = 3\n', (), "two slots are named 'x'"),
    ('[[slot]]\nserial = "A"\n', (), "no drive: give its address"),
    ('[[slot]]\nslave = 1\n', (), "slot 1: "),
    ('[slot]\nslave = 2\n', (), "no slots"),
    ('[[slot]]\nslave = 2\nwiring = "missing.toml"\n', (), "missing.toml"),
], ids=["shared-relay", "one-drive-twice", "names", "no-address", "the-jig", "not-an-array", "no-wiring-file"])
def test_slots_that_would_fight_are_refused(tmp_path, slots_text, fixtures, words):
    plan = write(tmp_path, "p.toml", '[plan]\nname = "p"\nversion = "1"\n[drive]\nslave = 2\n'
                                     '[[steps]]\nkind = "servo"\n')
    for name, relay in zip(("a.toml", "b.toml"), fixtures):
        write(tmp_path, name, FIXTURE % relay)
    with pytest.raises(SL.SlotError) as e:
        SL.load_slots(write(tmp_path, "slots.toml", slots_text), plan)
    assert words in str(e.value), str(e.value)


def test_addresses_for_a_wired_plan_are_refused_and_bad_addresses_said(tmp_path):
    with pytest.raises(SL.SlotError, match=r"uses the jig's relays and inputs \(\[wiring\]\): each slot needs"):
        SL.load_slots("2,3", EOL)
    with pytest.raises(SL.SlotError, match="'two' is neither"):
        SL.load_slots("2,two", os.path.join(ROOT, "plans", "smoke.toml"))
    four = SL.load_slots(FOUR_UP, EOL)
    assert [s.describe() for s in four] == ["slot %d (slave %d)" % (i + 1, i + 2) for i in range(4)]
    assert four[1].plan.wiring.find("relay", "limit+")[0] == 3  # each position its own relays


def test_two_slots_of_a_kind_that_cannot_share_its_port_are_refused():
    with pytest.raises(SL.SlotError, match="two EtherCAT slots on one interface are not supported yet"):
        SL.load_slots("0,1", os.path.join(ROOT, "plans", "ecat-smoke.toml"))
    two = SL.load_slots("5,6", os.path.join(ROOT, "plans", "cia402-smoke.toml"))  # CAN nodes share the port
    assert [s.describe() for s in two] == ["slot 1 (node id 5)", "slot 2 (node id 6)"]


def test_the_exit_status_rule():
    assert SL.exit_code(["PASS", "PASS"]) == 0
    assert SL.exit_code(["PASS", "FAIL"]) == 1
    assert SL.exit_code(["FAIL", "ABORTED"]) == 2
    assert SL.exit_code(["PASS", "ERROR"]) == 2
    assert SL.exit_code([]) == 2
    assert SL.overall(["PASS", "FAIL"]) == "FAIL"


def test_the_cli_refuses_serial_with_slots_and_checks_slots(tmp_path, capsys):
    from motorjig import cli

    assert cli.main(["test", EOL, "--slots", FOUR_UP, "--serial", "X", "--yes", "--port", "socket://127.0.0.1:1"]) == 2
    assert "--serial names one drive" in capsys.readouterr().err
    assert cli.main(["test", EOL, "--slots", FOUR_UP, "--check"]) == 0
    assert "4 slots are valid" in capsys.readouterr().out
