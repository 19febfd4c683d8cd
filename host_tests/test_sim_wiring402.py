"""The jig's I/O wired to a CiA 402 drive on the bench, as to a Plus-R drive: the jig's
relays (the real firmware's SetIOOutput) drive the node's digital inputs 0x60FD, its
digital outputs 0x60FE:1 reach the jig's inputs (GetIOInput); a limit switch
asserted through a relay during a move stops it (statusword bit 11), the home switch
wired to a relay is the one homing uses. The node is driven by the raw-frame master
of test_sim_cia402 on the bench's CAN bus; the CAN faults of issue 25 each with their
observable effect, and a faulted drive can always be left with operation disabled.
"""

import struct

import pytest
from test_sim_cia402 import MS, NID, Abort, Master, state_of

from jig import frame as F
from motorjig.sim import cia402 as C
from motorjig.sim import drive402 as D
from motorjig.sim.__main__ import check_setup, main, parse_args
from motorjig.sim.axis import profile_time, ramp_ms
from motorjig.sim.bench import SimBench
from motorjig.wiring import Wiring, WiringError, load_wiring, parse_wiring

JIG = 1
PLUSR = 2
RELAY_LIMIT_MINUS, RELAY_LIMIT_PLUS, RELAY_HOME, RELAY_USER = 0, 1, 2, 3
WIRING = {
    "node": NID,
    "relay": [
        {"relay": RELAY_LIMIT_MINUS, "drive_input": 0, "name": "limit-"},
        {"relay": RELAY_LIMIT_PLUS, "drive_input": 1, "name": "limit+"},
        {"relay": RELAY_HOME, "drive_input": 2, "name": "home"},
        {"relay": RELAY_USER, "drive_input": 16, "name": "user in 0"},
    ],
    "sense": [
        {"jig_input": 0, "drive_output": 16, "name": "user out 0"},
        {"jig_input": 1, "drive_output": 17, "name": "user out 1"},
    ],
}


def bench(wiring=WIRING, **kw):
    b = SimBench(driver_ids=(PLUSR,), can_nodes=(NID, 6), wiring=parse_wiring(wiring, "w.toml"), **kw)
    master = Master(b.clock, b.can_bus)
    b.run_for(5 * MS)  # boot-up
    master.nmt(0x01)
    return b, master, b.can_nodes[NID]


def call(b, slave, ftype, data=b""):
    _w, r = b.request(slave, ftype, data)
    assert r is not None and r[0] == 0, "0x%02X -> %r" % (ftype, r)
    return r[1:]


def relays(b, on=0, off=0):
    call(b, JIG, F.SET_IO_OUTPUT, struct.pack("<II", on, off))


def jig_inputs(b):
    return struct.unpack("<H", call(b, JIG, F.GET_IO_INPUT)[:2])[0]


def sw(master):
    return master.get(0x6041, 0, "<H")


def cw(master, word, mode=1):
    master.send(0x200 + NID, struct.pack("<Hb", word, mode))
    master.run(2)


def enable(master, mode=1):
    for word in (0x06, 0x07, 0x0F):
        cw(master, word, mode)


def start_move(master, target, speed=10000):
    master.set(0x6081, 0, "<I", speed)
    master.set(0x607A, 0, "<i", target)
    cw(master, 0x1F)
    cw(master, 0x0F)


# --- the wiring table ---------------------------------------------------------------------------------
def test_node_key_of_the_wiring_table():
    w = parse_wiring(WIRING, "w.toml")
    assert w.node == NID and w.slave is None and w.drive == "CAN node 5"
    assert w.drive_inputs(1 << RELAY_LIMIT_PLUS | 1 << RELAY_USER) == 1 << 1 | 1 << 16
    assert w.jig_inputs(1 << 17) == 1 << 1
    assert "node=5" in repr(w)
    # the plan's [drive] gives the default: node_id for a CiA 402 plan, slave for a Plus-R one
    assert parse_wiring({}, default_slave=2, default_node=7).node == 7
    assert parse_wiring({"slave": 3}, default_node=7).slave == 3  # the table's own choice wins
    assert parse_wiring({"slave": 3}, default_node=7).node is None
    with pytest.raises(WiringError, match="w.toml: wiring.node: a wiring connects one drive"):
        parse_wiring({"slave": 2, "node": 5}, "w.toml")
    for bad in (0, 128, "5"):
        with pytest.raises(WiringError, match="wiring.node: expected an integer 1..127"):
            parse_wiring({"node": bad}, "w.toml")
    with pytest.raises(ValueError, match="not both"):
        Wiring(slave=2, node=5)


def test_load_wiring_takes_a_cia402_plans_node_id(tmp_path):
    p = tmp_path / "plan.toml"
    p.write_text('[drive]\nprotocol = "cia402"\nnode_id = 9\nslave = 2\n[wiring]\n'
                 '[[wiring.relay]]\nrelay = 1\ndrive_input = 1\n')
    w = load_wiring(p)
    assert w.node == 9 and w.slave is None
    p.write_text('[drive]\nprotocol = "cia402"\nnode_id = 200\n[wiring]\n')
    with pytest.raises(WiringError, match="drive.node_id: expected an integer 1..127"):
        load_wiring(p)
    p.write_text('[drive]\nslave = 3\n[wiring]\n')  # a Plus-R plan as before
    assert load_wiring(p).slave == 3 and load_wiring(p).node is None


@pytest.mark.parametrize("plan", ["cia402-eol.toml"])
def test_the_shipped_cia402_plans_wiring_works_on_the_bench(plan):
    """--wiring plans/cia402-eol.toml: every relay reaches the 0x60FD bit it names, every
    0x60FE:1 bit the jig input it names."""
    from pathlib import Path

    w = load_wiring(Path(__file__).resolve().parent.parent / "plans" / plan)
    assert w.node == 5 and w.relays and w.senses
    b = SimBench(driver_ids=(PLUSR,), can_nodes=(5,), wiring=w)
    master = Master(b.clock, b.can_bus)
    b.run_for(5 * MS)
    node = b.can_nodes[5]
    for relay, bit, _name in w.relays:
        relays(b, on=1 << relay)
        assert master.get(0x60FD) & w.drive_input_mask == 1 << bit
        relays(b, off=1 << relay)
    for k, bit, _name in w.senses:
        master.set(0x60FE, 1, "<I", 1 << bit)
        assert jig_inputs(b) == 1 << k
    assert node.digital_inputs() & w.drive_input_mask == 0


def test_a_bench_refuses_a_wiring_to_a_node_it_does_not_have():
    with pytest.raises(ValueError, match="wiring.node 9 is not a CiA 402 node on this bench"):
        SimBench(driver_ids=(PLUSR,), can_nodes=(NID,), wiring=Wiring(node=9))
    with pytest.raises(ValueError, match="CAN nodes: none"):
        SimBench(driver_ids=(PLUSR,), wiring=Wiring(node=9))


# --- relays -> 0x60FD, 0x60FE:1 -> jig inputs ------------------------------------------------------------
def test_relays_drive_the_nodes_digital_inputs_and_its_outputs_reach_the_jig():
    b, master, node = bench()
    assert b.wired_node == NID and b.wired_slave is None
    assert master.get(0x60FD) & (1 | 2 | 1 << 16) == 0
    t = b.clock.now
    relays(b, on=1 << RELAY_USER)
    assert master.get(0x60FD) & 1 << 16
    # TPDO4 (0x60FD, 0x603F; on change) tells the master without being asked
    got = [struct.unpack_from("<I", d)[0] for _t, d in master.frames(0x480 + NID, t)]
    assert got and got[-1] & 1 << 16
    relays(b, on=1 << RELAY_LIMIT_MINUS | 1 << RELAY_LIMIT_PLUS, off=1 << RELAY_USER)
    assert master.get(0x60FD) & (1 | 2 | 1 << 16) == 0b11
    assert b.can_nodes[6].digital_inputs() == 0  # the other node is not wired
    relays(b, off=0b11)
    # outputs: 0x60FE:1 by SDO and by RPDO4, masked by 0x60FE:2
    assert jig_inputs(b) == 0
    master.set(0x60FE, 1, "<I", 1 << 16)
    assert jig_inputs(b) == 1 << 0
    master.send(0x500 + NID, struct.pack("<I", 1 << 16 | 1 << 17))
    master.run(2)
    assert jig_inputs(b) == 0b11
    master.set(0x60FE, 2, "<I", ~(1 << 17) & 0xFFFFFFFF)
    assert jig_inputs(b) == 0b01
    assert node.out_bits() == 1 << 16


def test_a_wired_home_switch_replaces_the_drives_own():
    b, master, node = bench()
    node.mech = node.origin_pos  # on the flag: not connected, the wire is
    assert not master.get(0x60FD) & D.IN_HOME
    relays(b, on=1 << RELAY_HOME)
    assert master.get(0x60FD) & D.IN_HOME


def test_homing_stops_at_the_home_switch_relay():
    b, master, node = bench()
    master.set(0x6098, 0, "<b", 19)
    master.set(0x6099, 1, "<I", 5000)
    master.set(0x607C, 0, "<i", 100)
    enable(master, 6)
    cw(master, 0x1F, 6)
    master.run(300)
    assert node.homing == "search" and node.motion.moving  # the flag is not wired: nothing yet
    relays(b, on=1 << RELAY_HOME)
    master.wait(0x180 + NID, 500, pred=lambda d: d[1] & 0x14 == 0x14)  # attained + target reached
    assert node.homing == "attained" and master.get(0x6064, 0, "<i") == 100


@pytest.mark.parametrize("relay, target, bit", [(RELAY_LIMIT_PLUS, 200000, 1), (RELAY_LIMIT_MINUS, -200000, 0)])
def test_a_limit_switch_during_a_move_stops_it_with_internal_limit_active(relay, target, bit):
    b, master, node = bench()
    enable(master)
    master.set(0x6085, 0, "<I", 200000)
    start_move(master, target)
    master.run(300)
    assert node.motion.moving and not sw(master) & D.SW_INTERNAL_LIMIT
    relays(b, on=1 << relay)
    t_relay = b.clock.now
    t, d = master.wait(0x180 + NID, 200, pred=lambda d: d[1] & 0x04)  # stopped: bit 10
    word = struct.unpack_from("<H", d)[0]
    assert word & D.SW_INTERNAL_LIMIT and word & 0x6F == 0x27  # still OPERATION ENABLED, bit 11
    assert (t - t_relay) / MS < ramp_ms(10000, 200000) + 5  # within the quick stop ramp (50 ms) + a step
    assert master.get(0x60FD) & 1 << bit
    stopped = master.get(0x6064, 0, "<i")
    assert abs(stopped) < 200000 and not node.motion.moving and node.state == D.OPERATION_ENABLED
    # a new set-point towards the limit does not move; away from it does, and bit 11 goes with the switch
    start_move(master, target)
    master.run(50)
    assert abs(master.get(0x6064, 0, "<i") - stopped) <= 1
    start_move(master, 0)
    master.run(50)
    assert abs(master.get(0x6064, 0, "<i")) < abs(stopped)
    relays(b, off=1 << relay)
    assert not sw(master) & D.SW_INTERNAL_LIMIT


def test_a_limit_switch_ends_a_homing_in_the_homing_error():
    b, master, node = bench()
    master.set(0x6098, 0, "<b", 19)  # positive direction
    enable(master, 6)
    cw(master, 0x1F, 6)
    master.run(20)
    relays(b, on=1 << RELAY_LIMIT_PLUS)
    master.wait(0x180 + NID, 500, pred=lambda d: d[1] & 0x20)  # bit 13 homing error
    assert node.homing == "error"


def test_profile_velocity_held_by_a_limit_switch():
    b, master, node = bench()
    relays(b, on=1 << RELAY_LIMIT_PLUS)
    enable(master, 3)
    master.set(0x60FF, 0, "<i", 5000)
    master.run(100)
    assert not node.motion.moving and sw(master) & D.SW_INTERNAL_LIMIT
    master.set(0x60FF, 0, "<i", -5000)
    master.run(100)
    assert master.get(0x606C, 0, "<i") == -5000


def test_the_plus_r_wiring_is_untouched_by_can_nodes():
    w = parse_wiring({"relay": [{"relay": 0, "drive_input": 26}]}, default_slave=PLUSR)
    b = SimBench(driver_ids=(PLUSR,), can_nodes=(NID,), wiring=w)
    assert b.wired_slave == PLUSR and b.wired_node is None
    relays(b, on=1)
    assert struct.unpack("<I", call(b, PLUSR, F.GET_IO_INPUT))[0] == 1 << 26
    assert b.can_nodes[NID].digital_inputs() & 1 << 26 == 0


# --- the CAN faults of issue 25, each with what it shows -------------------------------------------------
def test_following_error_faults_when_0x6065_and_0x6066_say():
    b, master, node = bench()
    b.set_fault("can:following-error", 5000, NID)
    master.set(0x6065, 0, "<I", 4000)  # a wider window: it takes longer
    master.set(0x6066, 0, "<H", 50)
    enable(master)
    t = b.clock.now
    start_move(master, 200000, 20000)
    t_emcy, d = master.wait(0x80 + NID, 3000, t)
    assert struct.unpack_from("<H", d)[0] == D.EMCY_FOLLOWING_ERROR
    # lost 15 000 counts/s: past 4000 counts after ~0.27 s of the move, + 50 ms; not before
    first_bit13 = next(tt for tt, dd in master.frames(0x180 + NID, t) if struct.unpack_from("<H", dd)[0] & D.SW_BIT13)
    assert (t_emcy - first_bit13) / MS == pytest.approx(50, abs=3)
    master.run(200)
    assert state_of(sw(master)) == D.FAULT


def test_following_error_inside_the_window_is_no_fault():
    b, master, node = bench()
    b.set_fault("can:step-out", 9000, NID)
    master.set(0x6065, 0, "<I", 0xFFFFFFFF)  # the check off
    enable(master)
    start_move(master, 20000)
    master.run(3000)
    assert node.state == D.OPERATION_ENABLED and master.get(0x60F4, 0, "<i") > 1000 and not node.emcys


def test_overcurrent_mid_move():
    b, master, node = bench()
    b.set_fault("can:overcurrent", 40)  # the wired node
    enable(master)
    t = b.clock.now
    start_move(master, 50000)
    _t, d = master.wait(0x80 + NID, 500, t)
    assert struct.unpack_from("<HB", d) == (D.EMCY_OVERCURRENT, D.ERR_GENERIC | D.ERR_CURRENT)
    master.run(100)
    assert node.state == D.FAULT and not node.motion.moving and not b.can_nodes[6].emcys


def test_sluggish():
    b, master, node = bench()
    b.set_fault("can:sluggish", 1.5, NID)
    enable(master)
    t = b.clock.now
    start_move(master, 10000)
    t_done, _ = master.wait(0x180 + NID, 5000, t, pred=lambda d: d[1] & 0x04)
    expect = 1.5 * profile_time(10000, 10000, ramp_ms(10000, 100000), ramp_ms(10000, 100000))
    assert (t_done - t) / 1e6 > expect - 0.01


def test_dead_input_hides_a_wired_relay():
    b, master, node = bench()
    b.set_fault("can:dead-input", 16, NID)
    relays(b, on=1 << RELAY_USER | 1 << RELAY_LIMIT_PLUS)
    assert master.get(0x60FD) & (1 << 16 | 2) == 2
    b.clear_faults()
    assert master.get(0x60FD) & 1 << 16


def test_param_fault_puts_an_object_off_its_golden_value():
    b, master, node = bench()
    assert master.get(0x6065) == 1000
    b.set_fault("can:param", "0x6065:0=4321", NID)
    assert master.get(0x6065) == 4321
    assert node.active_faults() == ["param=0x6065:00=4321"]
    master.nmt(0x81)  # a reset node keeps it: the stored value is off too
    master.run(5)
    assert master.get(0x6065) == 4321
    b.clear_faults()
    assert master.get(0x6065) == 1000
    master.nmt(0x81)
    master.run(5)
    assert master.get(0x6065) == 1000
    # the drive uses it: profile velocity 0x6081 off makes a move slower
    b.set_fault("can:param", ((0x6081, 0), 5000), NID)
    master.nmt(0x01)
    enable(master)
    master.set(0x607A, 0, "<i", 5000)
    cw(master, 0x1F)
    master.run(300)
    assert master.get(0x606C, 0, "<i") == 5000


@pytest.mark.parametrize("value, msg", [
    ("0x6065", "INDEX\\[:SUB\\]=VALUE"), ("0x9999=1", "0x9999:00 is not in the EDS"),
    ("0x6065=-1", "0x6065:00 must be 0..4294967295"), ("0x6041=1", "computes"), ("0x1008=1", "not an integer"),
    ("0x6066=70000", "must be 0..65535"), ("0x6065=x", "got .0x6065=x."),
])
def test_param_fault_values_are_checked(value, msg):
    with pytest.raises(ValueError, match=msg):
        C.parse_fault("param", value)


def test_no_origin():
    b, master, node = bench(wiring={"node": NID})  # the drive's own home switch
    b.set_fault("can:no-origin", None, NID)
    master.set(0x6098, 0, "<b", 19)
    master.set(0x6099, 1, "<I", 40000)
    enable(master, 6)
    cw(master, 0x1F, 6)
    master.wait(0x180 + NID, 3000, pred=lambda d: d[1] & 0x20)
    assert node.homing == "error"


def test_missed_heartbeats():
    b, master, node = bench()
    master.set(0x1017, 0, "<H", 100)
    master.run(350)
    t = b.clock.now
    assert len(master.frames(0x700 + NID, t - 350 * MS)) >= 3
    b.set_fault("can:missed-heartbeat", None, NID)
    master.run(500)
    assert master.frames(0x700 + NID, t) == [] and len(master.frames(0x706, t)) == 0  # node 6: no 0x1017
    b.clear_faults()
    master.run(250)
    assert len(master.frames(0x700 + NID, t)) >= 2


def test_sdo_aborts_and_the_pdos_still_disable_it():
    b, master, node = bench()
    enable(master)
    b.set_fault("can:sdo-abort", 0x08000022, NID)
    with pytest.raises(Abort) as exc:
        master.get(0x1000)
    assert exc.value.code == 0x08000022
    cw(master, 0x00)  # the controlword by RPDO1 still gets through
    assert node.state == D.SWITCH_ON_DISABLED


def test_sdo_aborts_for_one_object_only():
    b, master, node = bench()
    b.set_fault("can:sdo-abort", "0x06010002@0x6065", NID)
    assert node.active_faults() == ["sdo-abort=0x06010002@0x6065"]
    with pytest.raises(Abort) as exc:
        master.set(0x6065, 0, "<I", 10)
    assert exc.value.code == 0x06010002
    with pytest.raises(Abort):
        master.get(0x6065)  # reads too
    assert master.get(0x6066, 0, "<H") == 10
    assert master.upload(0x1008).startswith(b"MotorJig")  # a segmented upload of another object
    b.set_fault("can:sdo-abort", "0x08000020@0x1008:0", NID)
    with pytest.raises(Abort) as exc:
        master.upload(0x1008)
    assert exc.value.code == 0x08000020 and master.get(0x6065) == 1000  # the write above was refused
    with pytest.raises(ValueError, match="CODE\\[@INDEX"):
        C.parse_fault("sdo-abort", "0x08000000@x")
    assert C.parse_fault("sdo-abort", "0x08000000@6065:1") == ("sdo-abort", (0x08000000, (0x6065, 1)))


def test_bench_set_fault_without_a_node_id_goes_to_the_wired_node():
    b, master, node = bench()
    b.set_fault("can:sluggish", 2)
    assert node.active_faults() == ["sluggish=2"] and b.can_nodes[6].active_faults() == []


# --- after a fault the drive can be left with operation disabled ---------------------------------------
FAULTING = [("following-error", 5000, D.EMCY_FOLLOWING_ERROR), ("overcurrent", 30, D.EMCY_OVERCURRENT)]


@pytest.mark.parametrize("name, value, code", FAULTING)
def test_a_faulted_drive_ends_with_operation_disabled(name, value, code):
    b, master, node = bench()
    b.set_fault("can:" + name, value, NID)
    enable(master)
    master.set(0x6066, 0, "<H", 10)
    start_move(master, 500000, 20000)
    master.wait(0x80 + NID, 3000, pred=lambda d: struct.unpack_from("<H", d)[0] == code)
    # servo off or on in FAULT REACTION ACTIVE and FAULT: no transition of the table, the
    # reaction ramps down, then FAULT (operation enabled bit 2 clear) until a fault reset
    for word in (0x00, 0x06, 0x07, 0x0F):
        master.set(0x6040, 0, "<H", word)
        assert state_of(sw(master)) in (D.FAULT_REACTION, D.FAULT)
    master.run(200)
    word = sw(master)
    assert state_of(word) == D.FAULT and not word & 0x04 and not node.motion.moving
    # what the station does at the end: fault reset, then disable voltage
    master.set(0x6040, 0, "<H", 0x80)
    master.set(0x6040, 0, "<H", 0x00)
    assert state_of(sw(master)) == D.SWITCH_ON_DISABLED and not node.motion.moving


def test_disable_while_the_fault_reaction_ramps_down():
    b, master, node = bench()
    master.set(0x605E, 0, "<h", 1)  # slow down on the profile deceleration
    master.set(0x6084, 0, "<I", 10000)
    enable(master)
    start_move(master, 500000, 20000)
    master.run(1000)
    node.fault(D.EMCY_OVERCURRENT, D.ERR_CURRENT)
    assert node.state == D.FAULT_REACTION and node.motion.moving
    master.set(0x6040, 0, "<H", 0x00)  # the reaction goes on (the drive decides how it stops)
    assert node.state == D.FAULT_REACTION and node.motion.moving
    master.run(2500)
    assert state_of(sw(master)) == D.FAULT and not node.motion.moving
    master.set(0x6040, 0, "<H", 0x80)  # and the station's end: fault reset, disable voltage
    master.set(0x6040, 0, "<H", 0x00)
    assert state_of(sw(master)) == D.SWITCH_ON_DISABLED


@pytest.mark.parametrize("name, value", [("sluggish", 2), ("dead-input", 1), ("no-origin", None),
                                         ("missed-heartbeat", None), ("param", "0x6065=1")])
def test_servo_off_works_with_every_other_fault_on(name, value):
    b, master, node = bench()
    b.set_fault("can:" + name, value, NID)
    enable(master)
    start_move(master, 100000)
    master.run(100)
    master.set(0x6040, 0, "<H", 0x00)
    assert state_of(sw(master)) == D.SWITCH_ON_DISABLED and not node.motion.moving


# --- python -m motorjig.sim --can-nodes 5 --wiring FILE --------------------------------------------------
def test_cli_wires_a_can_node(tmp_path, capsys):
    p = tmp_path / "w.toml"
    p.write_text("[wiring]\nnode = 5\n[[wiring.relay]]\nrelay = 1\ndrive_input = 1\nname = \"limit+\"\n")
    assert main(["--can-nodes", "5", "--wiring", str(p), "--no-demo", "--no-pty", "--duration", "0.2",
                 "--fault", "can:5:param=0x6065=500"]) == 0
    out = capsys.readouterr().out
    assert "CAN node 5 (0x60FD inputs, 0x60FE:1 outputs)" in out and "jig relay 1 -> 0x60FD bit 1 (limit+)" in out
    assert "CAN node 5: param=0x6065:00=500" in out


def test_cli_refuses_a_wiring_to_a_node_not_on_the_bench(tmp_path):
    p = tmp_path / "w.toml"
    p.write_text("[wiring]\nnode = 7\n")
    with pytest.raises(ValueError, match="wiring.node 7 is not one of the --can-nodes \\(5\\)"):
        check_setup(parse_args(["--can-nodes", "5", "--wiring", str(p)]))
    with pytest.raises(ValueError, match="param: 0x9999:00 is not in the EDS"):
        check_setup(parse_args(["--can-nodes", "5", "--fault", "can:5:param=0x9999=1"]))


SPECS = {"following-error": "20000", "overcurrent": "30", "sluggish": "1.5", "dead-input": "16", "no-origin": None,
         "missed-heartbeat": None, "sdo-abort": "0x08000000@0x6065", "param": "0x6065=500"}


def test_every_can_fault_from_the_command_line_reaches_the_node():
    assert set(SPECS) == set(C.FAULTS)
    for name, value in SPECS.items():
        spec = "can:5:%s%s" % (name, "" if value is None else "=" + value)
        _wiring, faults = check_setup(parse_args(["--can-nodes", "5,6", "--fault", spec]))
        assert faults == [(5, "can:" + name, value)]
        b = SimBench(driver_ids=(PLUSR,), can_nodes=(5, 6), faults=faults)
        on = b.can_nodes[5].active_faults()
        assert len(on) == 1 and on[0].startswith(name), (spec, on)
        assert b.can_nodes[6].active_faults() == []
