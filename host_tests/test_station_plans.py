"""Plan files: the shipped plans load, and every kind of bad plan is refused by `jigctl test --check`
with a message that names the file, the line and the key -- before anything touches the bus."""

import os
import re

import pytest

from motorjig import cli, paramset
from motorjig.station import plan as P
from motorjig.station import schema
from motorjig.station.schema_plusr import KINDS as PLUSR_KINDS
from motorjig.station.schema_plusr import STEP_KINDS as PLUSR_STEP_KINDS

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PLANS = os.path.join(ROOT, "plans")

GOOD = """\
[plan]
name = "t"
version = "1"

[drive]
slave = 2

[[steps]]
kind = "servo"
on = true

[[steps]]
kind = "move"
distance = 1000
speed = 5000
"""


def check(capsys, path, *extra):
    capsys.readouterr()
    rc = cli.main(["test", "--check", str(path)] + list(extra))
    out, err = capsys.readouterr()
    return rc, out, err


def write(tmp_path, text, name="plan.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def refused(capsys, tmp_path, text, line, key, words, path=None):
    """--check exits 2 with one sentence: file:line: key: ... words ... (file: the plan, or ``path``;
    test_station_plan402 uses it too)."""
    plan = write(tmp_path, text)
    rc, out, err = check(capsys, plan)
    assert rc == 2, (out, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    prefix = "jigctl: %s%s: " % (path or plan, ":%d" % line if line else "")
    assert err.startswith(prefix), (prefix, err)
    if key:
        assert err[len(prefix):].startswith(key + ": "), err
    for w in words:
        assert w in err, (w, err)
    return err


@pytest.mark.parametrize("name", ["smoke.toml", "ezi-step-eol.toml"])
def test_shipped_plans_check_out(capsys, name):
    rc, out, err = check(capsys, os.path.join(PLANS, name), "--yes")  # --yes: the eol plan has a prompt
    assert rc == 0, err
    assert "is valid" in out


def test_the_eol_plan_expands_its_sweep_into_three_moves():
    plan = P.load_plan(os.path.join(PLANS, "ezi-step-eol.toml"))
    moves = [s for s in plan.steps if s.kind == "move" and s.index == 5]
    assert [s.args["speed"] for s in moves] == [5000, 20000, 50000]
    assert [s.name for s in moves] == ["move_speed_5000", "move_speed_20000", "move_speed_50000"]
    assert len({s.name for s in plan.steps}) == len(plan.steps)
    assert plan.drive.protocol == "plusr" and plan.drive.variants == (6, 8)
    assert re.fullmatch(r"[0-9a-f]{64}", plan.hash)


def test_repeat_gives_numbered_steps(tmp_path):
    plan = P.load_plan(write(tmp_path, GOOD.replace('on = true', 'on = true\nrepeat = 3')))
    assert [s.name for s in plan.steps] == ["servo_1", "servo_2", "servo_3", "move"]


def test_the_hash_covers_the_parameter_set(tmp_path):
    (tmp_path / "golden.toml").write_text("[parameters]\naxis_acc_time = 100\n")
    text = GOOD + '\n[[steps]]\nkind = "parameters"\nfile = "golden.toml"\n'
    first = P.load_plan(write(tmp_path, text)).hash
    (tmp_path / "golden.toml").write_text("[parameters]\naxis_acc_time = 101\n")
    assert P.load_plan(write(tmp_path, text)).hash != first


def test_unknown_step_kind(capsys, tmp_path):
    err = refused(capsys, tmp_path, GOOD.replace('kind = "servo"', 'kind = "sevro"'), 9, "steps[0].kind",
                  ["unknown step kind 'sevro'", "did you mean 'servo'"])
    assert "limit-sensor" in err  # the known kinds are listed


def test_missing_key(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("speed = 5000\n", ""), 12, "steps[1]",
            ["a move step needs the key 'speed'"])


def test_misspelled_key(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("speed = 5000", "sped = 5000"), 15, "steps[1].sped",
            ["unknown key", "did you mean 'speed'"])


def test_misspelled_table(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("[drive]", "[drvie]"), 5, "drvie", ["unknown table", "'drive'"])


def test_value_of_the_wrong_type(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("speed = 5000", 'speed = "fast"'), 15, "steps[1].speed",
            ["expected an integer", "'fast'"])


def test_value_out_of_range(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("speed = 5000", "speed = 9000000"), 15, "steps[1].speed",
            ["must be between 1 and 2500000, not 9000000"])


@pytest.mark.parametrize("key, value, words", [
    ("following_error_max", "-1", "must be ≥ 0, not -1"),
    ("duration_tolerance", "-0.5", "must be between 0 and 10, not -0.5"),
    ("timeout_s", "0.01", "must be between 0.1 and 3600, not 0.01"),
    ("accel_ms", "0", "must be between 1 and 9999, not 0"),
])
def test_every_range_message_reads_as_a_sentence(capsys, tmp_path, key, value, words):
    err = refused(capsys, tmp_path, GOOD.replace("speed = 5000", "speed = 5000\n%s = %s" % (key, value)), 16,
                  "steps[1].%s" % key, [words])
    assert "outside" not in err and "..." not in err


def test_every_bounded_key_of_the_schema_has_a_readable_range_message(tmp_path):
    """Each key with a lower or upper bound, given a value just outside it, says 'must be ..., not V'."""
    tables = [("plan", schema.PLAN_KEYS), ("drive", schema.DRIVE_KEYS)]
    tables += [("steps", schema.COMMON_STEP_KEYS + kind.keys) for kind in PLUSR_STEP_KINDS]
    checked = 0
    for table, keys in tables:
        for k in keys:
            if k.type not in ("int", "num") or (k.lo is None and k.hi is None):
                continue
            bad = k.lo - 1 if k.lo is not None else k.hi + 1
            ck = P._Checker("p.toml", None)
            ck.error = lambda keypath, message: P.PlanError("p.toml", None, P.dotted(keypath), message)
            with pytest.raises(P.PlanError) as e:
                ck.value(bad, k, (table, 0, k.name) if table == "steps" else (table, k.name))
            assert e.value.message == "must be %s, not %r" % (P.bounds_text(k.lo, k.hi), bad)
            checked += 1
    assert checked > 20


@pytest.mark.parametrize("key", ["name_pattern", "motor_pattern"])
def test_an_invalid_regular_expression_is_refused_before_anything_moves(capsys, tmp_path, key):
    text = GOOD + '\n[[steps]]\nkind = "identify"\n%s = "Ezi-(STEP"\n' % key
    refused(capsys, tmp_path, text, 19, "steps[2].%s" % key,
            ["'Ezi-(STEP' is not a valid regular expression", "missing ), unterminated subpattern"])


def test_two_steps_of_the_same_name_are_refused_naming_both(capsys, tmp_path):
    text = GOOD.replace('distance = 1000', 'distance = 1000\nname = "m"') + \
        '\n[[steps]]\nkind = "move"\nname = "m"\ndistance = -1000\nspeed = 5000\n'
    refused(capsys, tmp_path, text, 20, "steps[2].name",
            ["two steps are named 'm'", "steps[1] (line 15) and steps[2]"])


def test_a_name_given_to_a_step_must_not_be_taken_by_another(capsys, tmp_path):
    # the second servo is numbered (servo_2); a step given that very name is refused
    text = GOOD + '\n[[steps]]\nkind = "servo"\non = false\n\n[[steps]]\nkind = "servo"\nname = "servo_2"\n'
    refused(capsys, tmp_path, text, 23, "steps[3].name", ["two steps are named 'servo_2'", "steps[2] (line 17)"])
    # a step named like a repeated step's run
    text = GOOD.replace("on = true", 'on = true\nname = "s"\nrepeat = 2') + '\n[[steps]]\nkind = "servo"\nname = "s_2"\n'
    refused(capsys, tmp_path, text, 21, "steps[2].name", ["two steps are named 's_2'", "steps[0] (line 11)"])


def test_unnamed_steps_of_one_kind_are_numbered(tmp_path):
    text = GOOD + '\n[[steps]]\nkind = "servo"\non = false\n'
    assert [s.name for s in P.load_plan(write(tmp_path, text)).steps] == ["servo", "move", "servo_2"]


def test_a_move_of_distance_zero(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("distance = 1000", "distance = 0"), 14, "steps[1].distance",
            ["distance 0"])


def test_not_toml_at_all(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("[[steps]]\nkind", "[[steps]\nkind", 1), 8, "", ["not valid TOML"])


def test_a_missing_file(capsys, tmp_path):
    rc, out, err = check(capsys, tmp_path / "nope.toml")
    assert rc == 2 and "nope.toml: cannot read" in err and "Traceback" not in err


def test_a_parameter_the_drive_does_not_have(capsys, tmp_path):
    (tmp_path / "golden.toml").write_text("[parameters]\naxis_acc_time = 100\naxis_jerk = 5\n")
    path = write(tmp_path, GOOD + '\n[[steps]]\nkind = "parameters"\nfile = "golden.toml"\n')
    rc, out, err = check(capsys, path)
    assert rc == 2
    assert err.startswith("jigctl: %s:3: parameters.axis_jerk: the drive has no such parameter" % (tmp_path / "golden.toml"))


def test_a_parameter_number_the_drive_does_not_have(capsys, tmp_path):
    (tmp_path / "golden.toml").write_text("[parameters]\n40 = 1\n")
    path = write(tmp_path, GOOD + '\n[[steps]]\nkind = "parameters"\nfile = "golden.toml"\n')
    rc, out, err = check(capsys, path)
    assert rc == 2 and ":2: parameters.40: the drive has no such parameter" in err


def test_a_parameter_value_out_of_range(capsys, tmp_path):
    (tmp_path / "golden.toml").write_text("[parameters]\naxis_acc_time = 0\n")
    path = write(tmp_path, GOOD + '\n[[steps]]\nkind = "parameters"\nfile = "golden.toml"\n')
    rc, out, err = check(capsys, path)
    assert rc == 2 and ":2: parameters.axis_acc_time: parameter 3 (axis_acc_time) must be between 1 and 9999" in err


def test_a_missing_parameter_set(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD + '\n[[steps]]\nkind = "parameters"\nfile = "gone.toml"\n', 19,
            "steps[2].file", ["gone.toml not found"])


def test_a_limit_step_on_a_relay_that_is_not_wired(capsys, tmp_path):
    text = GOOD + ('\n[[wiring.relay]]\nrelay = 0\ndrive_input = 0\nname = "limit+"\n'
                   '\n[[steps]]\nkind = "limit-sensor"\nrelay = "limit-"\n')
    refused(capsys, tmp_path, text, 24, "steps[2].relay", ["'limit-' is not in the plan's [wiring]", "0 (limit+)"])


def test_a_bad_wiring_entry(capsys, tmp_path):
    text = GOOD + '\n[[wiring.relay]]\nrelay = 0\ndrive_input = "x"\n'
    refused(capsys, tmp_path, text, 19, "wiring.relay[0].drive_input", ["expected an integer", "'x'"])


def test_a_protocol_that_is_neither(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("slave = 2", "slave = 2\nprotocol = 7"), 7, "drive.protocol",
            ["6, 8 or [6, 8]"])


def test_the_jig_is_not_a_drive(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("slave = 2", "slave = 1"), 6, "drive.slave", ["the jig"])


def test_the_docs_reference_is_the_schema():
    """docs/station.md's plan reference is generated from the schema the loader checks against."""
    from motorjig.sim import doctables

    with open(os.path.join(ROOT, "docs", "station.md")) as f:
        text = f.read()
    assert doctables.expected("docs/station.md", text) == text, "python -m motorjig.sim.doctables --write"
    for kind in PLUSR_KINDS:
        assert '`kind = "%s"`' % kind in text


def test_param_set_files_round_trip(tmp_path):
    values = {1: 400000, 3: 250, 13: -5000}
    path = tmp_path / "set.toml"
    path.write_text(paramset.dumps(values, slave=2, slave_type=20))
    ps = paramset.load(str(path))
    assert ps.values == values and ps.slave_type == 20


def test_a_parameter_set_of_another_drive_type(capsys, tmp_path):
    (tmp_path / "golden.toml").write_text("[drive]\nslave_type = 1\n[parameters]\naxis_acc_time = 100\n")
    refused(capsys, tmp_path, GOOD + '\n[[steps]]\nkind = "parameters"\nfile = "golden.toml"\n', 19,
            "steps[2].file", ["parameter set of slave type 1", "type 20"])


def test_a_fixture_wired_to_another_slave(capsys, tmp_path):
    text = GOOD + '\n[wiring]\nslave = 3\n[[wiring.relay]]\nrelay = 0\ndrive_input = 0\n'
    refused(capsys, tmp_path, text, 18, "wiring.slave", ["wired to slave 3", "tests slave 2"])


def test_an_io_step_checks_the_relays_it_names_by_number_or_name(tmp_path):
    from motorjig.station import phases

    with open(os.path.join(PLANS, "ezi-step-eol.toml")) as f:
        eol = f.read()
    text = eol[: eol.index("[[steps]]")] + '[[steps]]\nkind = "io"\nrelays = ["user-in-0", 0]\nsenses = [1]\n'
    plan = P.load_plan(write(tmp_path, text))
    names = [m.name for m in phases.measures_io(plan.steps[0], plan)]
    assert names == ["relay_2_on", "relay_2_off", "relay_0_on", "relay_0_off", "sense_1_on", "sense_1_off"]


def test_the_documented_measurements_are_the_ones_each_step_declares(tmp_path):
    """The reference's 'Measurements:' line of every kind lists every measurement its phase declares."""
    from motorjig.station import phases

    with open(os.path.join(PLANS, "ezi-step-eol.toml")) as f:
        eol = f.read()
    wiring = eol[eol.index("[[wiring.relay]]"):eol.index("[[steps]]")] if "[[wiring.relay]]" in eol else ""
    (tmp_path / "golden.toml").write_text("[parameters]\naxis_acc_time = 100\n")
    steps = {
        "identify": 'motor_pattern = "."', "parameters": 'file = "golden.toml"', "servo": "", "alarm-reset": "",
        "move": "distance = 100\nspeed = 100\nduration_tolerance = 0.1", "home": "", "io": "",
        "limit-sensor": 'relay = "limit+"', "stop-response": "", "bus-health": "", "prompt": 'message = "m"'}
    assert set(steps) == set(PLUSR_KINDS)
    text = GOOD[: GOOD.index("[[steps]]")] + wiring + "".join(
        '\n[[steps]]\nkind = "%s"\n%s\n' % (k, v) for k, v in steps.items())
    plan = P.load_plan(write(tmp_path, text))
    for step in plan.steps:
        declared = [m.name for m in getattr(phases, "measures_" + step.kind.replace("-", "_"))(step, plan)]
        documented = PLUSR_KINDS[step.kind].measurements
        if step.kind == "parameters":
            assert declared == ["ram_axis_acc_time", "rom_axis_acc_time"]
        elif step.kind == "io":
            assert {re.sub(r"_\d+_", "_<n>_", n) for n in declared} == set(documented)
        else:
            assert declared == list(documented), step.kind
