"""The CiA 402 power state machine the station runs (motorjig.can.power402): the statusword
decoding, the transitions against the standard's, the shortest paths, agreement with the
bench's simulated drive (its table, and every path run on it over SDO frames on the
simulated bus) and with python-canopen's names; the generated docs/cia402-states.md.
"""

import itertools
import os
import struct
import sys

import pytest
from canopen.profiles.p402 import State402

from motorjig.can import power402 as P
from motorjig.sim import cia402 as C
from motorjig.sim import drive402 as D
from motorjig.sim.canbus import CanBus
from motorjig.sim.clock import VirtualClock

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tools"))
try:
    import gen_cia402_doc
finally:
    sys.path.pop(0)

NR, SOD, RDY, SO, OE, QSA, FRA, FLT = (P.NOT_READY, P.SWITCH_ON_DISABLED, P.READY, P.SWITCHED_ON,
                                       P.OPERATION_ENABLED, P.QUICK_STOP_ACTIVE, P.FAULT_REACTION, P.FAULT)

# CiA 402's transitions, written out from the standard (canopen-notes.md): commanded ones
# as (number, from, to, controlword), automatic ones as (number, from, to).
STANDARD_COMMANDED = {
    (2, SOD, RDY, 0x06), (3, RDY, SO, 0x07), (4, SO, OE, 0x0F), (5, OE, SO, 0x07), (6, SO, RDY, 0x06),
    (7, RDY, SOD, 0x00), (7, RDY, SOD, 0x02), (8, OE, RDY, 0x06), (9, OE, SOD, 0x00), (10, SO, SOD, 0x00),
    (10, SO, SOD, 0x02), (11, OE, QSA, 0x02), (12, QSA, SOD, 0x00), (15, FLT, SOD, 0x80), (16, QSA, OE, 0x0F),
}
STANDARD_AUTOMATIC = {(1, NR, SOD), (12, QSA, SOD), (14, FRA, FLT)}
STANDARD_AUTOMATIC |= {(13, s, FRA) for s in (NR, SOD, RDY, SO, OE, QSA)}  # 13: from every state but the fault ones
COMMANDED_STATES = (SOD, RDY, SO, OE, QSA, FLT)  # the states a path can start from
TARGETS = (SOD, RDY, SO, OE, QSA)  # the states a path can lead to


# --- the statusword -----------------------------------------------------------------------------
def test_states_are_the_standards_eight_with_their_masks():
    assert [(n, m, v) for n, m, v in P.STATES] == [
        (NR, 0x4F, 0x00), (SOD, 0x4F, 0x40), (RDY, 0x6F, 0x21), (SO, 0x6F, 0x23),
        (OE, 0x6F, 0x27), (QSA, 0x6F, 0x07), (FRA, 0x4F, 0x0F), (FLT, 0x4F, 0x08)]
    assert P.STATE_NAMES == tuple(n for n, _m, _v in P.STATES)


@pytest.mark.parametrize("name,mask,value", P.STATES, ids=[s[0] for s in P.STATES])
def test_every_state_decodes_whatever_the_bits_outside_its_mask(name, mask, value):
    free = [b for b in range(16) if not mask >> b & 1]
    words = [value | sum(1 << b for b, on in zip(free, bits) if on)
             for bits in itertools.product((0, 1), repeat=len(free))]
    assert len(words) == 1 << len(free) and max(words) > 0xFF00  # high bits set too
    assert {P.state_of(w) for w in words} == {name}


def test_decoding_is_unique_and_leaves_the_standards_holes_undecoded():
    seen = {}
    for w in range(0x10000):
        matches = [n for n, m, v in P.STATES if w & m == v]
        assert len(matches) <= 1, hex(w)
        assert P.state_of(w) == (matches[0] if matches else None)
        seen[P.state_of(w)] = seen.get(P.state_of(w), 0) + 1
    assert set(seen) == set(P.STATE_NAMES) | {None}
    assert P.state_of(0x0001) is None and P.state_of(0x0027 | 0x0040) is None  # no such patterns
    assert P.state_of(0x1637) == OE and P.state_of(0x0250) == SOD and P.state_of(0x0218) == FLT


# --- the transitions and paths ------------------------------------------------------------------
def test_transitions_are_the_standards():
    commanded = {(t.number, t.source, t.target, t.controlword) for t in P.TRANSITIONS if t.command is not None}
    automatic = {(t.number, t.source, t.target) for t in P.TRANSITIONS if t.command is None}
    assert commanded == STANDARD_COMMANDED
    assert automatic == STANDARD_AUTOMATIC
    assert len(P.TRANSITIONS) == len(commanded) + len(automatic)  # no row twice
    assert all(t.controlword is None for t in P.TRANSITIONS if t.command is None)
    assert all(P.COMMANDS[t.command] == t.controlword for t in P.TRANSITIONS if t.command is not None)
    assert sorted({t.number for t in P.TRANSITIONS}) == list(range(1, 17))
    assert [t.number for t in P.TRANSITIONS] == sorted(t.number for t in P.TRANSITIONS)
    assert P.COMMANDS == {"SHUTDOWN": 0x06, "SWITCH ON": 0x07, "ENABLE OPERATION": 0x0F, "DISABLE VOLTAGE": 0x00,
                          "QUICK STOP": 0x02, "DISABLE OPERATION": 0x07, "FAULT RESET": 0x80}


def _reachable(a, k, option):
    """States k standard transitions (any, commanded) from a."""
    edges = {(f, t) for n, f, t, _cw in STANDARD_COMMANDED if n != 16 or option in range(5, 9)}
    states = {a}
    for _ in range(k):
        states = {t for s in states for f, t in edges if f == s}
    return states


@pytest.mark.parametrize("option", [None, 2, 6])
@pytest.mark.parametrize("a,b", list(itertools.product(COMMANDED_STATES, TARGETS)))
def test_every_path_is_a_shortest_chain_of_the_standards_transitions(a, b, option):
    steps = P.path(a, b, quick_stop_option=option)
    state, transitions = a, 0
    for cw, expected in steps:
        if expected == state:  # the only step that is no transition: bit 7 low before a fault reset
            assert state == FLT and cw == P.FAULT_RESET_ARM and not cw & 0x80
            continue
        assert (cw, expected) in {(c, t) for _n, f, t, c in STANDARD_COMMANDED if f == state}
        number = [n for n, f, t, c in STANDARD_COMMANDED if (f, t, c) == (state, expected, cw)][0]
        assert number != 16 or option in range(5, 9)
        if number == 15:
            assert steps[steps.index((cw, expected)) - 1] == (P.FAULT_RESET_ARM, FLT)
        state, transitions = expected, transitions + 1
    assert state == b
    assert all(b not in _reachable(a, k, option) for k in range(transitions))  # none shorter
    assert [t.target for t in P.route(a, b, option)] == [s for _cw, s in steps if (_cw, s) != (P.FAULT_RESET_ARM, FLT)]


def test_the_paths_a_station_uses_most():
    assert P.path(SOD, OE) == [(0x06, RDY), (0x07, SO), (0x0F, OE)]
    assert P.path(OE, SOD) == [(0x00, SOD)]
    assert P.path(FLT, OE) == [(0x00, FLT), (0x80, SOD), (0x06, RDY), (0x07, SO), (0x0F, OE)]
    assert P.path(QSA, OE) == [(0x00, SOD), (0x06, RDY), (0x07, SO), (0x0F, OE)]
    assert P.path(QSA, OE, quick_stop_option=5) == [(0x0F, OE)]
    assert P.path(OE, OE) == [] and P.path(FLT, FLT) == []
    assert [t.number for t in P.route(FLT, OE)] == [15, 2, 3, 4]


@pytest.mark.parametrize("a,b,why", [
    (NR, SOD, "by itself: transition 1"), (FRA, SOD, "by itself: transition 14"), (OE, FLT, "only the drive"),
    (SOD, FRA, "only the drive"), (SOD, NR, "only the drive"), ("ENABLED", OE, "unknown CiA 402 state"),
])
def test_states_only_the_drive_enters_or_leaves_have_no_path(a, b, why):
    with pytest.raises(ValueError, match=why):
        P.path(a, b)


# --- the simulated drive ----------------------------------------------------------------------------
def _sim_command(cw, previous):
    """The command the simulated drive reads in a controlword (its own table, COMMANDS)."""
    if cw & D.CW_FAULT_RESET and not previous & D.CW_FAULT_RESET:
        return D.FAULT_RESET
    return next((name for name, mask, value in D.COMMANDS if cw & mask == value), None)


def test_the_simulated_drives_states_are_these():
    assert D.STATES == {n: (m, v) for n, m, v in P.STATES}
    assert (D.NOT_READY, D.SWITCH_ON_DISABLED, D.READY, D.SWITCHED_ON, D.OPERATION_ENABLED, D.QUICK_STOP_ACTIVE,
            D.FAULT_REACTION, D.FAULT) == P.STATE_NAMES


def test_the_simulated_drives_table_is_this_one():
    # every row of the drive's table is one of ours (its "3+4": 0x0F in READY goes on to OPERATION ENABLED)
    for (source, command), (target, label) in D.TRANSITIONS.items():
        if label == "3+4":
            assert [t.number for t in P.route(source, target)] == [3, 4]
            assert _sim_command(P.COMMANDS["ENABLE OPERATION"], 0) == command
            continue
        rows = [t for t in P.TRANSITIONS if (t.number, t.source, t.target) == (int(label), source, target)
                and t.command is not None and _sim_command(t.controlword, 0) == command]
        assert rows, (source, command, target, label)
    # and every commanded row of ours is in the drive's table
    for t in P.TRANSITIONS:
        if t.command is not None:
            assert D.TRANSITIONS[(t.source, _sim_command(t.controlword, 0))] == (t.target, str(t.number)), t


class SdoMaster:
    """Raw SDO frames to one node on the simulated bus: expedited download and upload."""

    def __init__(self, clock, bus, node_id):
        self.clock, self.node_id, self.rx = clock, node_id, []
        self.can = bus.add_node("master", lambda t, cid, ext, rtr, data: self.rx.append((cid, bytes(data))))

    def _request(self, data):
        self.rx.clear()
        self.can.transmit(0x600 + self.node_id, False, False, data)
        self.clock.run_while(lambda: not any(cid == 0x580 + self.node_id for cid, _d in self.rx), 100_000)
        reply = [d for cid, d in self.rx if cid == 0x580 + self.node_id]
        assert reply, "no SDO answer"
        assert reply[0][0] != 0x80, "SDO abort 0x%08X" % struct.unpack_from("<I", reply[0], 4)[0]
        return reply[0]

    def write_u16(self, index, sub, value):
        assert self._request(struct.pack("<BHBHxx", 0x2B, index, sub, value))[0] == 0x60

    def write_i16(self, index, sub, value):
        assert self._request(struct.pack("<BHBhxx", 0x2B, index, sub, value))[0] == 0x60

    def read_u16(self, index, sub=0):
        r = self._request(struct.pack("<BHBxxxx", 0x40, index, sub))
        assert r[0] == 0x4B and struct.unpack_from("<HB", r, 1) == (index, sub)
        return struct.unpack_from("<H", r, 4)[0]


def drive(quick_stop_option):
    clock = VirtualClock()
    bus = CanBus(clock, 500000)
    master = SdoMaster(clock, bus, 5)
    node = C.Cia402Node(clock, bus, 5)
    clock.advance(5000)  # boot-up
    master.write_i16(0x605A, 0, quick_stop_option)
    return clock, master, node


def run_path(master, a, b, option):
    """Writes the controlwords of path(a, b); the state each statusword shows after each."""
    shown = []
    for cw, _expected in P.path(a, b, quick_stop_option=option):
        master.write_u16(0x6040, 0, cw)
        shown.append(P.state_of(master.read_u16(0x6041)))
    return shown


# with 0x605A 2 the drive does not hold QUICK STOP ACTIVE: no path starts there
RUNS = [(o, a, b) for o in (2, 6) for a, b in itertools.product(COMMANDED_STATES, TARGETS)
        if not (a == QSA and o not in P.HOLDS_QUICK_STOP)]


@pytest.mark.parametrize("option,a,b", RUNS)
def test_every_path_runs_on_the_simulated_drive(option, a, b):
    clock, master, node = drive(option)
    assert P.state_of(master.read_u16(0x6041)) == SOD and node.transitions[-1][1] == "0+1"  # 0 and 1 at power-on
    if a == FLT:
        run_path(master, SOD, OE, option)
        master.write_u16(0x6040, 0, 0x80)  # bit 7 left high: the path must lower it first
        node.fault(D.EMCY_OVERCURRENT, D.ERR_CURRENT)
        assert [label for _t, label in node.transitions[-2:]] == ["13", "14"]
    else:
        run_path(master, SOD, a, option)
    assert P.state_of(master.read_u16(0x6041)) == a
    before = len(node.transitions)
    shown = run_path(master, a, b, option)
    expected = [s for _cw, s in P.path(a, b, quick_stop_option=option)]
    if b == QSA and option not in P.HOLDS_QUICK_STOP:
        # a drive at rest ends the quick stop at once: transition 12 follows 11 by itself
        assert shown[:-1] == expected[:-1] and shown[-1] == SOD
        assert [label for _t, label in node.transitions[-2:]] == ["11", "12"]
        return
    assert shown == expected
    labels = [label for _t, label in node.transitions[before:]]
    assert labels == [str(t.number) for t in P.route(a, b, option)]


# --- python-canopen ---------------------------------------------------------------------------------
def test_python_canopens_state_names_and_masks_are_these():
    assert State402.SW_MASK == {n: (m, v) for n, m, v in P.STATES}
    for name in P.STATE_NAMES:  # and it decodes every state as we do
        mask, value = State402.SW_MASK[name]
        assert P.state_of(value | 0x0210) == name


def test_python_canopens_transition_table_agrees():
    automatic = {(t.source, t.target) for t in P.TRANSITIONS if t.command is None}
    for (a, b), cw in State402.TRANSITIONTABLE.items():
        if a == "START":  # its transition 0, power-on
            assert b == NR
        elif (a, b) in automatic and not any(t.source == a and t.target == b and t.command for t in P.TRANSITIONS):
            assert cw == 0
        else:
            assert any((t.source, t.target, t.controlword) == (a, b, cw) for t in P.TRANSITIONS), (a, b, cw)
    commanded = {(t.source, t.target) for t in P.TRANSITIONS if t.command is not None}
    assert commanded <= set(State402.TRANSITIONTABLE)
    assert State402.CW_SWITCH_ON_DISABLED == P.COMMANDS["FAULT RESET"]


# --- the generated document ---------------------------------------------------------------------------
def test_generated_state_doc_is_committed_and_current():
    with open(os.path.join(ROOT, "docs", "cia402-states.md"), encoding="utf-8") as f:
        assert f.read() == gen_cia402_doc.render(), "run: python tools/docgen/gen_cia402_doc.py"


def test_the_statechart_has_an_edge_for_every_transition():
    text = gen_cia402_doc.render()
    chart = text.split("```mermaid\n", 1)[1].split("```", 1)[0]
    edges = {}
    for line in chart.splitlines():
        if "-->" in line and "[*]" not in line:
            ends, label = line.strip().split(": ", 1)
            a, b = ends.split(" --> ")
            edges[(a, b)] = label
    ids = gen_cia402_doc.IDS
    for t in P.TRANSITIONS:
        label = edges[(ids[t.source], ids[t.target])]
        what = "auto" if t.command is None else "%s %02X" % (t.command.lower(), t.controlword)
        assert "%d %s" % (t.number, what) in label or ("%d " % t.number in label and what in label), t
    assert len(edges) == len({(t.source, t.target) for t in P.TRANSITIONS})
    assert all(":" not in label and ";" not in label for label in edges.values())


def test_check_flags_a_stale_or_missing_file_in_one_sentence(tmp_path, capsys):
    out = tmp_path / "states.md"
    assert gen_cia402_doc.main(["--output", str(out)]) == 0
    assert gen_cia402_doc.main(["--check", "--output", str(out)]) == 0
    out.write_text(out.read_text(encoding="utf-8").replace("0x0F", "0x1F"), encoding="utf-8")
    capsys.readouterr()
    assert gen_cia402_doc.main(["--check", "--output", str(out)]) == 1
    assert capsys.readouterr().out.strip().count("\n") == 0
    assert gen_cia402_doc.main(["--check", "--output", str(tmp_path / "none.md")]) == 1
    assert "cannot read" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        gen_cia402_doc.main(["--help"])
    assert e.value.code == 0 and "--check" in capsys.readouterr().out
