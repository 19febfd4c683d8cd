"""Plans for CiA 402 drives: `[drive] protocol = "cia402"` loads with the EDS's object dictionary,
plans written before it still load as Plus-R plans, and every kind of bad CiA 402 plan is refused
by `jigctl test --check` with one sentence naming the file, the line and the key -- before
anything touches the bus."""

import os

import pytest

from motorjig.can import EDS_PATH, paramset402
from motorjig.can import objects as O
from motorjig.station import plan as P
from motorjig.station import kinds, schema
from test_station_plans import GOOD as GOOD_PLUSR
from test_station_plans import PLANS, ROOT, check, refused, write

GOOD = GOOD_PLUSR.replace("slave = 2\n", 'protocol = "cia402"\nnode_id = 5\n')  # the same plan on a CiA 402 node

PARAMS_STEP = '\n[[steps]]\nkind = "parameters"\nfile = "set.toml"\nmode = "%s"\n'


def with_set(tmp_path, objects, mode="verify"):
    (tmp_path / "set.toml").write_text("[objects]\n" + objects)
    return GOOD + PARAMS_STEP % mode


# --- what loads ------------------------------------------------------------------
@pytest.mark.parametrize("name", ["cia402-smoke.toml", "cia402-eol.toml"])
def test_shipped_cia402_plans_check_out(capsys, name):
    rc, out, err = check(capsys, os.path.join(PLANS, name))
    assert rc == 0, err
    assert "is valid" in out


def test_a_cia402_plan_carries_its_drive_and_the_eds_object_dictionary():
    plan = P.load_plan(os.path.join(PLANS, "cia402-eol.toml"))
    d = plan.drive
    assert (d.protocol, d.node_id, d.bitrate, d.eds, d.jig_id) == ("cia402", 5, 500000, EDS_PATH, 1)
    assert d.od[0x6041].name == "Statusword" and 0x6099 in d.od
    moves = [s for s in plan.steps if s.name.startswith("move_speed_")]
    assert [s.args["speed"] for s in moves] == [5000, 20000, 50000]
    assert all(s.args["accel"] == 500000 for s in moves)
    ps = next(s for s in plan.steps if s.kind == "parameters").paramset
    assert isinstance(ps, paramset402.ParamSet402)
    assert ps.values[(0x6065, 0)] == 1000 and ps.values[(0x6099, 1)] == 5000
    assert ps.drive["product_code"] == 0x402
    assert plan.wiring.node == 5 and [r[1] for r in plan.wiring.relays] == [1, 0, 16]
    assert d.describe() == "CAN node 5, 500000 bit/s, motorjig-cia402.eds"
    assert d.as_dict() == {"protocol": "cia402", "node_id": 5, "bitrate": 500000, "eds": "motorjig-cia402.eds",
                           "jig_id": 1}


def test_the_golden_set_is_the_simulated_drives_defaults():
    """cia402-eol verifies what a healthy bench drive has: every golden value is the EDS default."""
    od = O.load_eds(EDS_PATH)
    ps = paramset402.load(os.path.join(PLANS, "cia402-golden.toml"), od, writable=True)
    for e in ps.entries:
        assert e.var.default == e.value, e.label


def test_old_plans_protocol_numbers_load_as_plusr_variants(tmp_path):
    plusr = GOOD.replace('protocol = "cia402"\nnode_id = 5', "slave = 2\nprotocol = [8, 6]")
    d = P.load_plan(write(tmp_path, plusr)).drive
    assert (d.protocol, d.variants, d.slave) == ("plusr", (6, 8), 2)
    assert d.describe() == "slave 2, Ver6/Ver8, type 20"
    d = P.load_plan(write(tmp_path, plusr.replace("protocol = [8, 6]", 'protocol = "plusr"\nvariant = 8'))).drive
    assert (d.protocol, d.variants) == ("plusr", (8,))
    d = P.load_plan(write(tmp_path, plusr.replace("protocol = [8, 6]\n", ""))).drive
    assert (d.protocol, d.variants) == ("plusr", (6,))


def test_the_hash_covers_the_eds(tmp_path):
    eds = tmp_path / "drive.eds"
    eds.write_bytes(open(EDS_PATH, "rb").read())
    text = GOOD.replace("node_id = 5", 'node_id = 5\neds = "drive.eds"')
    first = P.load_plan(write(tmp_path, text)).hash
    eds.write_bytes(open(EDS_PATH, "rb").read().replace(b"DefaultValue=1000", b"DefaultValue=999", 1))
    assert P.load_plan(write(tmp_path, text)).hash != first


def test_a_parameter_set_may_name_objects(tmp_path):
    text = with_set(tmp_path, '"Profile velocity" = 20000\n"0x6099:Speed during search for zero" = 500\n'
                              '"0x607D:02" = 100000\n"0x6065:0" = 10\n')
    ps = P.load_plan(write(tmp_path, text)).steps[-1].paramset
    assert ps.values == {(0x6081, 0): 20000, (0x6099, 2): 500, (0x607D, 2): 100000, (0x6065, 0): 10}


def test_a_parameter_set_round_trips_through_its_text(tmp_path):
    od = O.load_eds(EDS_PATH)
    objs = paramset402.default_objects(od)
    values = [(i, s, v, (v.default or 0) + 1 if O.type_info(v)[2] == "uint" and i != 0x60FE else v.default)
              for i, s, v in objs]
    path = tmp_path / "set.toml"
    path.write_text(paramset402.dumps(values, 5, {"device_type": 0x20192, "vendor_id": None}, "drive"))
    ps = paramset402.load(str(path), od, writable=True)
    assert ps.values == {(i, s): v for i, s, _, v in values}
    assert ps.drive == {"device_type": 0x20192}
    assert (0x6040, 0) not in ps.values and (0x6041, 0) not in ps.values  # commands and status: not settings


# --- what --check refuses ----------------------------------------------------------
def test_an_object_not_in_the_eds(capsys, tmp_path):
    refused(capsys, tmp_path, with_set(tmp_path, '"0x6081" = 1\n"0x6999" = 5\n'), 3, "objects.0x6999",
            ["0x6999 is not an object in motorjig-cia402.eds"], path=tmp_path / "set.toml")


def test_a_sub_index_not_in_the_eds(capsys, tmp_path):
    refused(capsys, tmp_path, with_set(tmp_path, '"0x6099:03" = 5\n'), 2, "objects.0x6099:03",
            ["has no sub-index 3"], path=tmp_path / "set.toml")


def test_a_read_only_object_in_apply(capsys, tmp_path):
    refused(capsys, tmp_path, with_set(tmp_path, '"0x6065" = 1000\n"Statusword" = 7\n', "apply"), 3,
            "objects.Statusword", ["0x6041:00 Statusword is read-only", "cannot be written"],
            path=tmp_path / "set.toml")


def test_a_read_only_object_may_be_verified(tmp_path):
    ps = P.load_plan(write(tmp_path, with_set(tmp_path, '"0x2000" = 10000\n'))).steps[-1].paramset
    assert ps.values == {(0x2000, 0): 10000}


def test_a_value_of_the_wrong_type(capsys, tmp_path):
    refused(capsys, tmp_path, with_set(tmp_path, '"0x6065" = "1000"\n'), 2, "objects.0x6065",
            ["expected an integer (UNSIGNED32)", "'1000'"], path=tmp_path / "set.toml")


def test_a_value_out_of_the_types_range(capsys, tmp_path):
    refused(capsys, tmp_path, with_set(tmp_path, '"0x6098" = 200\n'), 2, "objects.0x6098",
            ["200 is out of range for INTEGER8: -128..127"], path=tmp_path / "set.toml")


def test_a_value_out_of_the_eds_limits(capsys, tmp_path):
    refused(capsys, tmp_path, with_set(tmp_path, '"0x6083" = 0\n'), 2, "objects.0x6083",
            ["0 is out of range", "1..4294967295"], path=tmp_path / "set.toml")


def test_a_step_value_out_of_the_eds_limits(capsys, tmp_path):
    eds = tmp_path / "drive.eds"
    eds.write_text(open(EDS_PATH).read().replace("[6081]\n", "[6081]\nHighLimit=100000\n"))
    text = GOOD.replace("node_id = 5", 'node_id = 5\neds = "drive.eds"').replace(
        "speed = 5000", "speed = [5000, 200000]")
    refused(capsys, tmp_path, text, 17, "steps[1].speed[1]", ["200000 is outside 0x6081 Profile velocity's limits",
                                                               "0..100000"])


def test_a_step_object_the_eds_lacks(capsys, tmp_path):
    eds = tmp_path / "drive.eds"
    eds.write_text(open(EDS_PATH).read().replace("[6098]\n", "[5098]\n").replace("6098=", "5098="))
    text = GOOD.replace("node_id = 5", 'node_id = 5\neds = "drive.eds"') + '\n[[steps]]\nkind = "home"\nmethod = 19\n'
    refused(capsys, tmp_path, text, 21, "steps[2].method", ["0x6098 is not an object in drive.eds"])


@pytest.mark.parametrize("node", [0, 128])
def test_a_node_id_out_of_range(capsys, tmp_path, node):
    refused(capsys, tmp_path, GOOD.replace("node_id = 5", "node_id = %d" % node), 7, "drive.node_id",
            ["must be between 1 and 127", repr(node)])


def test_a_missing_node_id(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("node_id = 5\n", ""), 5, "drive", ["needs the key 'node_id'"])


def test_a_bitrate_the_slcan_port_cannot_set(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("node_id = 5", "node_id = 5\nbitrate = 400000"), 8, "drive.bitrate",
            ["expected one of", "500000", "400000"])


def test_a_missing_eds(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("node_id = 5", 'node_id = 5\neds = "nowhere.eds"'), 8, "drive.eds",
            ["nowhere.eds does not exist"])


def test_a_step_kind_the_protocol_does_not_have(capsys, tmp_path):
    plusr = GOOD.replace('protocol = "cia402"\nnode_id = 5', "slave = 2")
    refused(capsys, tmp_path, plusr + '\n[[steps]]\nkind = "lss"\n', 18, "steps[2].kind",
            ["a Plus-R drive has no step kind 'lss'", 'protocol = "cia402"'])


def test_a_plusr_key_in_a_cia402_step(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("speed = 5000", "speed = 5000\naccel_ms = 50"), 17, "steps[1].accel_ms",
            ["unknown key in a move step", "did you mean 'accel'?"])


def test_a_plusr_drive_key_in_a_cia402_plan(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace("node_id = 5", "node_id = 5\nslave = 2"), 8, "drive.slave",
            ['a key of protocol = "plusr" drives', 'protocol = "cia402"'])


def test_variants_given_twice(capsys, tmp_path):
    plusr = GOOD.replace('protocol = "cia402"\nnode_id = 5', "slave = 2\nprotocol = 6\nvariant = 8")
    refused(capsys, tmp_path, plusr, 8, "drive.variant", ["the variants are given twice"])


def test_a_protocol_that_is_neither(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD.replace('"cia402"', '"canopen"'), 6, "drive.protocol",
            ['"plusr" or "cia402" or "ethercat", 6, 8 or [6, 8]', "'canopen'"])


def test_a_fixture_wired_to_another_node(capsys, tmp_path):
    text = GOOD + '\n[wiring]\nnode = 6\n[[wiring.relay]]\nrelay = 0\ndrive_input = 1\n'
    refused(capsys, tmp_path, text, 19, "wiring.node", ["wired to CAN node 6", "tests CAN node 5"])


def test_a_limit_step_on_a_relay_wired_to_no_limit_input(capsys, tmp_path):
    text = GOOD + ('\n[wiring]\n[[wiring.relay]]\nrelay = 0\ndrive_input = 16\nname = "in"\n'
                   '\n[[steps]]\nkind = "limit-sensor"\nrelay = "in"\n')
    refused(capsys, tmp_path, text, 26, "steps[2].relay", ["not a limit input", "0x60FD bit 0 negative"])


def test_a_move_that_cannot_end_within_its_timeout(capsys, tmp_path):
    text = GOOD.replace("distance = 1000", "distance = 100000\ntimeout_s = 5").replace("speed = 5000",
                                                                                      "speed = [50000, 10000]")
    refused(capsys, tmp_path, text, 16, "steps[1].timeout_s", ["takes at least 10 s (distance / speed)",
                                                               "timeout_s = 5"])


def test_a_duration_limit_above_the_timeout(capsys, tmp_path):
    text = GOOD + '\n[[steps]]\nkind = "home"\nduration_s = [0.1, 20]\ntimeout_s = 10\n'
    refused(capsys, tmp_path, text, 20, "steps[2].duration_s", ["upper limit 20 s is above timeout_s = 10"])


@pytest.mark.parametrize("node", [0, 128, 254])
def test_an_lss_factory_node_id_that_is_none(capsys, tmp_path, node):
    text = GOOD + '\n[[steps]]\nkind = "lss"\nfactory_node_id = %d\n' % node
    refused(capsys, tmp_path, text, 20, "steps[2].factory_node_id", [str(node)])


LSS_FIRST = GOOD.replace("[[steps]]", '[[steps]]\nkind = "lss"\n\n[[steps]]', 1)


def test_an_lss_step_loads(tmp_path):
    step = P.load_plan(write(tmp_path, LSS_FIRST)).steps[0]
    assert (step.kind, step.args["factory_node_id"]) == ("lss", 255)


def test_an_lss_step_that_is_not_first(capsys, tmp_path):
    """At run time the drive has no node id until the lss step: a step before it finds nothing."""
    refused(capsys, tmp_path, GOOD + '\n[[steps]]\nkind = "lss"\n', 19, "steps[2].kind",
            ["an lss step must be the plan's first"])


def test_a_homing_method_cia402_does_not_define(capsys, tmp_path):
    refused(capsys, tmp_path, GOOD + '\n[[steps]]\nkind = "home"\nmethod = 99\n', 20, "steps[2].method",
            ["99 is no homing method", "1-14, 17-30, 33-35 and 37"])
    P.load_plan(write(tmp_path, GOOD + '\n[[steps]]\nkind = "home"\nmethod = -3\n'))  # the maker's own


def test_a_duration_limit_the_moves_profile_cannot_meet(capsys, tmp_path):
    """A 2 s move (10 000 counts at 5 000 counts/s, ramps of 0.1 s) with duration_s = [0, 0.1]."""
    text = GOOD.replace("distance = 1000", "distance = 10000\naccel = 50000\ndecel = 50000\nduration_s = [0, 0.1]")
    refused(capsys, tmp_path, text, 18, "steps[1].duration_s", ["takes at least 2.1 s", "upper limit 0.1 s"])


def test_a_stop_time_of_nothing(capsys, tmp_path):
    text = GOOD + '\n[[steps]]\nkind = "stop-response"\nstop_time_s = [0, 0]\n'
    refused(capsys, tmp_path, text, 20, "steps[2].stop_time_s", ["upper limit is 0 s", "could never pass"])


# --- the schema and its reference ------------------------------------------------------
def test_every_protocol_has_its_kinds_and_the_docs_show_them():
    assert kinds.BUILTIN == ("plusr", "cia402", "ethercat")
    cia402 = set(schema.kinds("cia402"))
    assert cia402 == set(schema.kinds("plusr")) | {"lss"}
    ethercat = set(schema.kinds("ethercat"))
    assert ethercat == cia402 - {"lss", "io", "limit-sensor"}  # CAN's and the jig wiring's steps are not offered
    with open(os.path.join(ROOT, "docs", "station.md")) as f:
        text = f.read()
    for name, its in (("cia402", cia402), ("ethercat", ethercat)):
        for kind in its - {"prompt"}:
            assert '`kind = "%s"` (%s)' % (kind, name) in text
        assert '#### `protocol = "%s"`' % name in text


def test_the_step_objects_are_in_the_shipped_eds():
    od = O.load_eds(EDS_PATH)
    for k in schema.kinds("cia402").values():
        for key in k.keys:
            if key.obj is not None:
                index, sub = key.obj if isinstance(key.obj, tuple) else (key.obj, 0)
                var = O.find(od, "0x%04X:%d" % (index, sub)).var
                assert var.access_type in ("rw", "rww"), (k.name, key.name)


def test_the_documented_measurements_are_the_ones_each_cia402_step_declares(tmp_path):
    """The reference's 'Measurements:' line of every CiA 402 kind lists what its phase declares (kinds
    the station cannot run on CiA 402 drives yet declare nothing and are left out)."""
    from motorjig.station import phases

    (tmp_path / "set.toml").write_text('[objects]\n"0x6065" = 1000\n')
    steps = {
        "identify": 'vendor_id = 1\nproduct_code = 2\nrevision = 3\nserial_pattern = "."', "servo": "",
        "parameters": 'file = "set.toml"', "alarm-reset": "", "move": "distance = 100\nspeed = 100",
        "home": "", "stop-response": "", "bus-health": "heartbeat_jitter_max_ms = 5"}
    text = GOOD[: GOOD.index("[[steps]]")] + "".join('\n[[steps]]\nkind = "%s"\n%s\n' % kv for kv in steps.items())
    plan = P.load_plan(write(tmp_path, text))
    kinds = schema.kinds("cia402")
    for step in plan.steps:
        declared = [m.name for m in phases._step_functions(step, plan)[0]]
        declared = [n for n in declared if not (n == "emcy" and step.kind != "bus-health")]  # the EMCY rule's
        if step.kind == "parameters":
            assert declared == ["x6065_00"] and kinds["parameters"].measurements == ("x<index>_<sub>",)
        elif declared:
            assert declared == list(kinds[step.kind].measurements), step.kind
