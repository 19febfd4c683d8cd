"""Drive kinds are plug-ins: a kind defined here, in the test, runs through the station's engine.

``LoopbackKind`` is a fourth drive kind that lives only in this file: a drive simulated in
memory, one plan key, two step kinds of its own. Registered in the table of kinds, a plan that
names it passes ``jigctl test --check`` and runs through the station's engine (pre-flight, the
steps, the teardown) to its JSON, JUnit and HTML records, with no module outside this file
knowing it. And the generic modules name no kind: ``kind-leaks`` counts what is left.
"""

import json
import os
import subprocess

import pytest

from motorjig import cli
from motorjig.sim import Bench
from motorjig.station import kinds, load_plan, run_plan
from motorjig.station import schema as S
from motorjig.station.drive import Drive

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class LoopbackDrive(Drive):
    """An axis in memory: it moves where it is told at once."""

    protocol = "loopback"
    emergency_words = "loop stop"

    def __init__(self, axis):
        self.label = "loop axis %d" % axis
        self.position = 0
        self.enabled = False
        self.closed = False

    def identify(self):
        return {"name": "loopback drive"}

    def enable(self, on):
        self.enabled = bool(on)
        return {"state": "on" if on else "off", "transitions": []}

    def make_safe(self, emergency=False):
        self.enabled = False
        return []

    def close(self):
        self.closed = True


class PlanDrive:
    protocol = "loopback"

    def __init__(self, axis, jig_id):
        self.axis, self.jig_id = axis, jig_id

    def as_dict(self):
        return {"protocol": self.protocol, "axis": self.axis, "jig_id": self.jig_id}

    def describe(self):
        return "loop axis %d" % self.axis


def measures_hop(step, plan):
    from openhtf import Measurement

    return [Measurement("position").equals(step.args["to"]), Measurement("enabled").equals(True)]


def run_hop(test, bus, step, ctx):
    d = bus.drive
    d.enable(True)
    d.position = step.args["to"]
    test.measurements["position"] = d.position
    test.measurements["enabled"] = d.enabled


class LoopbackKind(kinds.DriveKind):
    name = "loopback"
    title = "loopback"
    drive_keys = (S.key("axis", "int", 1, "the loop axis", lo=1, hi=4),)
    step_kinds = (S.Kind("hop", "jump to a position", (S.key("to", "int", S.REQUIRED, "where", lo=0, hi=1000),),
                         ("position", "enabled")),)
    emergency_words = "loop stop"
    opened = []

    def plan_drive(self, ck, v, plan_dir):
        return PlanDrive(v["axis"], v["jig_id"]), b""

    def open_drive(self, plug):
        d = LoopbackDrive(1)
        self.opened.append(d)
        return d

    def step_functions(self, step, plan):
        return measures_hop(step, plan), run_hop

    def preflight(self, test, bus, plan, serial, ctx):
        test.test_record.metadata["drive"] = plan.drive.as_dict()
        if not serial:
            test.dut_id = "loop-%d" % plan.drive.axis


PLAN = '[plan]\nname = "loop"\nversion = "1"\n[drive]\nprotocol = "loopback"\naxis = 2\n' \
       '[[steps]]\nkind = "hop"\nto = 7\n[[steps]]\nkind = "hop"\nname = "far"\nto = 900\n'


@pytest.fixture
def loopback():
    kind = kinds.register(LoopbackKind())
    yield kind
    kinds.unregister(kind.name)


def test_a_kind_registered_from_outside_passes_check_and_refuses_what_it_lacks(loopback, tmp_path, capsys):
    plan = tmp_path / "loop.toml"
    plan.write_text(PLAN)
    assert cli.main(["test", "--check", str(plan)]) == 0
    assert "is valid: 2 steps (hop, far)" in capsys.readouterr().out
    plan.write_text(PLAN.replace('kind = "hop"\nto = 7', 'kind = "move"\ndistance = 7'))
    assert cli.main(["test", "--check", str(plan)]) == 2
    err = capsys.readouterr().err
    assert "a loopback drive has no step kind 'move'" in err and "this plan's kinds: hop" in err
    plan.write_text(PLAN.replace("axis = 2", "axis = 9"))
    assert cli.main(["test", "--check", str(plan)]) == 2
    assert "drive.axis" in capsys.readouterr().err


def test_a_kind_registered_from_outside_runs_through_the_engine_to_its_records(loopback, tmp_path):
    plan_path = tmp_path / "loop.toml"
    plan_path.write_text(PLAN)
    plan = load_plan(str(plan_path))
    with Bench(driver_ids=(2,), baud=115200, pty=False) as b:  # the jig: the engine's plug opens its PC port
        ctx = run_plan(plan, b.tcp_url, out_dir=str(tmp_path), out=None, confirm=lambda m: True, timeout_ms=300,
                       safety_window_ms=0)
    rec = ctx.record
    assert rec["outcome"] == "PASS", rec.get("outcome_details")
    assert rec["dut_id"] == "loop-2" and rec["metadata"]["drive"] == {"protocol": "loopback", "axis": 2, "jig_id": 1}
    assert [p["name"] for p in rec["phases"]][-2:] == ["hop", "far"]
    assert rec["phases"][-1]["measurements"]["position"]["measured_value"] == 900
    assert set(ctx.files) >= {"json", "xml", "html"}
    with open(ctx.files["json"]) as f:
        assert json.load(f)["dut_id"] == "loop-2"
    assert loopback.opened and loopback.opened[-1].closed  # the plug's teardown closed it


def test_a_kind_registered_from_outside_runs_from_the_desks_test_tab(loopback, tmp_path):
    """The Desk's Test tab (its Station, as the page drives it) lists the plan and runs it."""
    import time

    from motorjig.desk.session import BusSession
    from motorjig.desk.testrun import Station

    (tmp_path / "plans").mkdir()
    (tmp_path / "plans" / "loop.toml").write_text(PLAN)
    with Bench(driver_ids=(2,), baud=115200, pty=False) as b:
        session = BusSession(timeout=0.3)
        try:
            session.connect(b.tcp_url)
            station = Station(session, plans_dir=str(tmp_path / "plans"), out_dir=str(tmp_path / "results"))
            entry = next(e for e in station.plans() if e.plan is not None and e.plan.name == "loop")
            station.start(entry.path, serial="LOOP-1")
            deadline = time.monotonic() + 60
            while station.running and time.monotonic() < deadline:
                time.sleep(0.1)
            run = station.run
        finally:
            session.stop()
    assert run.verdict == "PASS", run.snapshot()
    records = [f.name for f in (tmp_path / "results").iterdir()]
    assert any(f.startswith("loop_LOOP-1_") and f.endswith(".json") for f in records), records


def test_the_generic_modules_name_no_drive_kind():
    """``kind-leaks`` (../shared/tools) lists the lines of the station, Desk, bench and CLI modules
    that name a drive kind outside the kinds' own files and the tables of kinds: none."""
    tool = os.path.join(os.path.dirname(ROOT), "shared", "tools", "kind-leaks")
    if not os.path.exists(tool):
        pytest.skip("no kind-leaks tool beside the project")
    out = subprocess.run(["bash", tool], capture_output=True, text=True, cwd=ROOT, timeout=60).stdout
    n = int(out.strip().splitlines()[-1].split()[1])
    assert n <= LEAKS_LEFT, out


LEAKS_LEFT = 0
GENERIC = ("station/plan.py", "station/plug.py", "station/runner.py", "station/phases.py", "station/schema.py",
           "station/sampling.py", "station/store.py", "station/report.py", "station/junit.py", "desk/page.py",
           "desk/session.py", "desk/testrun.py", "desk/server.py", "sim/bench.py", "sim/hal.py", "testcmd.py",
           "wiring.py", "resultscmd.py")


@pytest.mark.parametrize("rel", GENERIC)
def test_no_generic_module_names_a_kind_or_its_client(rel):
    """The same rule for the modules kind-leaks skips by its path (testcmd, the Desk's testrun): no
    code line names a kind or a kind's client class; comments and prose may say "CiA 402"."""
    import re

    pattern = re.compile(r"plusr|PlusR|cia402|Cia402|CIA402|ethercat|modbus|PlusRDrive|Cia402Drive|canopen\.")
    with open(os.path.join(ROOT, "tools", "motorjig", rel)) as f:
        hits = [line for line in f if pattern.search(line) and not line.lstrip().startswith("#")]
    assert not hits, hits
