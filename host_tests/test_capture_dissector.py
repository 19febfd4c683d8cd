"""The Plus-R Lua dissector in tshark: every capture file, pairing and times, broken frames,
filters, and its tables against the project's Python tables.

Each capture of host_tests/captures is cut into records by the framer, written as
pcapng and dissected by tshark with ``-X lua_script:plusr.lua``: no Lua error, the
good frames are the ones the capture file states (bodies and CRCs), the
dissector's own verdict on every record matches the parser's, Ver6/Ver8 is read
the way ``motorjig.capture.variant`` reads it, and the decoded values match
``motorjig.decode`` and, for the worked examples of the protocol notes, the
values written down here by hand.
"""

import os
import struct

import pytest

from test_capture_support import (CAPTURES, EPOCH_US, LUA, body_of, capture_records, dissect, fields, load,
                                  needs_tshark, num, one, run_tshark, write_pcapng)

from motorjig import names as N
from motorjig.capture import luagen
from motorjig.capture import record as R
from motorjig.capture.variant import VariantReader
from motorjig.decode import Decoder
from jig import frame as F

#: the dissector's plusr.problem for each verdict of the recording parser
PROBLEM_OF_VERDICT = {R.GOOD: 0, R.BAD_CRC: 1, R.BAD_STUFFING: 2, R.SHORT: 3, R.OVERLONG: 4, R.NOISE: 7,
                      R.TIMEOUT: 9, R.RESYNC: 9, R.UNFINISHED: 9}
EXPERT_OF_VERDICT = {R.BAD_CRC: "plusr.crc.bad", R.BAD_STUFFING: "plusr.bad_stuffing", R.SHORT: "plusr.short",
                     R.OVERLONG: "plusr.overlong", R.NOISE: "plusr.no_header", R.TIMEOUT: "plusr.no_tail",
                     R.RESYNC: "plusr.no_tail", R.UNFINISHED: "plusr.no_tail"}
#: decode.py's field names -> the dissector's
VALUE_FIELDS = {"command_pos": "plusr.cmd_pos", "actual_pos": "plusr.act_pos", "pos_error": "plusr.pos_error",
                "actual_vel": "plusr.velocity", "position": "plusr.position", "speed": "plusr.speed",
                "slave_type": "plusr.slave_type", "version": "plusr.version", "pt_number": "plusr.pt_number"}
#: frame types whose one i32 reply decode.py calls "value", and the dissector's field for it
VALUE_OF_TYPE = {F.GET_COMMAND_POS: "plusr.cmd_pos", F.GET_ACTUAL_POS: "plusr.act_pos",
                 F.GET_POS_ERROR: "plusr.pos_error", F.GET_ACTUAL_VEL: "plusr.velocity",
                 F.GET_PARAMETER: "plusr.value", F.GET_ROM_PARAMETER: "plusr.value"}


def test_generated_tables_are_current():
    with open(LUA, encoding="utf-8") as f:
        _before, block, _after = luagen.split(f.read())
    assert block == luagen.render(), "plusr.lua's tables are stale: python -m motorjig.capture.luagen --write"


def test_luagen_check_reports_a_stale_file(tmp_path, capsys):
    with open(LUA, encoding="utf-8") as f:
        text = f.read()
    stale = tmp_path / "plusr.lua"
    stale.write_text(text.replace('"GetSlaveInfo"', '"GetSlaveInformation"', 1), encoding="utf-8")
    assert luagen.main(["--check", str(stale)]) == 1
    assert luagen.main(["--write", str(stale)]) == 0
    assert stale.read_text(encoding="utf-8") == text
    assert luagen.main(["--check", str(stale)]) == 0
    capsys.readouterr()


@needs_tshark
def test_wireshark_sees_the_python_names():
    """What tshark loaded (value strings, bit masks) is what the Python tables say."""
    res = run_tshark_report("values")
    values = {}
    for line in res.splitlines():
        parts = line.split("\t")
        if len(parts) == 4 and parts[0] == "V" and parts[1].startswith("plusr."):
            values.setdefault(parts[1], {})[int(parts[2], 0)] = parts[3]
    assert values["plusr.type"] == N.FRAME_NAMES
    assert values["plusr.status"] == N.STATUS_NAMES
    assert values["plusr.slave_type"] == N.SLAVE_TYPES
    assert values["plusr.alarm"] == N.ALARM_NAMES
    masks = {}
    for line in run_tshark_report("fields").splitlines():
        parts = line.split("\t")
        if len(parts) >= 7 and parts[0] == "F" and parts[2].startswith("plusr."):
            masks[parts[2]] = (parts[1], int(parts[6], 16))
    for bit, name, meaning in N.AXIS_FLAGS:
        assert masks["plusr.flags." + name] == (meaning, 1 << bit)
    for table, prefix in ((N.INPUT_BITS, "plusr.in."), (N.OUTPUT_BITS, "plusr.out.")):
        for bit, name in table:
            assert masks[prefix + name][1] == 1 << bit
    from jig import diag as D

    for name in D.WIRE_NAMES:
        assert "plusr.jig." + name in masks


def run_tshark_report(what):
    """tshark -G values|fields with the dissector loaded (-G must be the first option)."""
    import subprocess

    from test_capture_support import TSHARK

    res = subprocess.run([TSHARK, "-G", what, "-X", "lua_script:" + LUA], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and "Lua" not in res.stderr.replace('Running as user "root"', ""), res.stderr
    return res.stdout


def _expected_values(d, ftype, kind):
    """(dissector field, value) pairs that decode.py's dict of a frame implies."""
    out = []
    for key, field in VALUE_FIELDS.items():
        if key in d and d[key] != "":  # an empty string has no bytes to show
            out.append((field, d[key]))
    if "value" in d and kind == "reply" and ftype in VALUE_OF_TYPE:
        out.append((VALUE_OF_TYPE[ftype], d["value"]))
    if "param" in d and kind != "reply":
        out.append(("plusr.param", d["param"]))
        if ftype == F.SET_PARAMETER:
            out.append(("plusr.value", d["value"]))
    if "alarm" in d and isinstance(d["alarm"], str):
        out.append(("plusr.alarm", [k for k, v in N.ALARM_NAMES.items() if v == d["alarm"]][0]))
    return out


@needs_tshark
@pytest.mark.parametrize("path", CAPTURES, ids=os.path.basename)
def test_capture_dissects(path, tmp_path):
    cap = load(path)
    recs, rest = capture_records(cap)
    recs += rest
    pcap = write_pcapng(str(tmp_path / "c.pcapng"), recs)
    packets = dissect(pcap)
    assert len(packets) == len(recs)

    good = [r for r in recs if r.verdict == R.GOOD]
    assert [body_of(r.data)[:-2] for r in good] == [b for b, _crc in cap.frames]
    for r, (_b, crc) in zip(good, cap.frames):
        if crc >= 0:
            assert body_of(r.data)[-2:] == bytes((crc & 0xFF, crc >> 8))

    reader = VariantReader()
    decoder = Decoder()
    for i, (rec, p) in enumerate(zip(recs, packets)):
        where = "%s packet %d (%s)" % (cap.name, i + 1, rec.data.hex(" "))
        assert num(p, "plusr.problem") == PROBLEM_OF_VERDICT[rec.verdict], where
        assert one(p, "plusr.verdict") == R.verdict_name(rec.verdict), where
        if rec.verdict != R.GOOD:
            assert EXPERT_OF_VERDICT[rec.verdict] in p, where
            if rec.verdict == R.BAD_CRC:
                assert num(p, "plusr.crc.status") == 0, where
            continue
        body = body_of(rec.data)
        fr = reader.frame(0, body, rec.t_us / 1e6)
        ver8 = fr.sync >= 0
        assert num(p, "plusr.crc.status") == 1, where
        assert num(p, "plusr.id") == fr.slave, where
        assert num(p, "plusr.variant") == (8 if ver8 else 6), where
        assert num(p, "plusr.type") == fr.ftype, where
        assert num(p, "plusr.sync") == (fr.sync if ver8 else None), where
        kind = ("request", "reply", "broadcast")[num(p, "plusr.kind")]
        d = decoder.as_dict(fr)
        # Where the dissector knows more than decode.py: a reply of the wrong length after
        # its request, and a Ver8 drive's answer to the vendor's Ver6 probe.
        if "plusr.bad_length" not in p and "plusr.probe_answer" not in p:
            assert kind == d["kind"], where
        if kind == "reply":
            assert num(p, "plusr.status") == fr.data[0], where
            assert ("plusr.status.error" in p) == (fr.data[0] != 0), where
        if kind != d["kind"]:
            continue
        for field, value in _expected_values(d, fr.ftype, kind):
            got = one(p, field)
            assert got is not None, "%s: no %s" % (where, field)
            assert (got if isinstance(value, str) else int(got, 0)) == value, "%s: %s" % (where, field)
        if "flags" in d:
            assert sorted(n for n in d["flags"]) == sorted(
                k[len("plusr.flags."):] for k, v in p.items() if k.startswith("plusr.flags.") and v == ["1"]
                and k != "plusr.flags.error"), where


def _capture_packets(name, tmp_path, *options):
    path = [c for c in CAPTURES if os.path.basename(c).startswith(name)][0]
    recs, rest = capture_records(load(path))
    return dissect(write_pcapng(str(tmp_path / (name + ".pcapng")), recs + rest), *options)


@needs_tshark
def test_worked_examples_by_hand(tmp_path):
    """Values as the protocol notes write them (not as the Python decoder says)."""
    p = _capture_packets("02_", tmp_path)
    assert [(num(x, "plusr.position"), num(x, "plusr.speed")) for x in p[1:3]] == [(10000, 5000), (-1000, 20000)]
    assert (num(p[0], "plusr.param"), num(p[0], "plusr.value")) == (1, 100000)
    assert (num(p[3], "plusr.speed"), num(p[3], "plusr.direction")) == (5000, 1)
    assert num(p[5], "plusr.item") == 5 and num(p[6], "plusr.kind") == 2  # PosTableRunItem; broadcast
    p = _capture_packets("05_", tmp_path)
    assert [num(x, "plusr.status") for x in (p[0], p[2], p[3])] == [0x00, 0x00, 0x85]
    assert num(p[2], "plusr.alarm") == 3 and "plusr.status.error" in p[3]
    p = _capture_packets("06_", tmp_path)
    assert num(p[0], "plusr.flags") == 0x08000000 and one(p[0], "plusr.flags.motioning") == "1"
    assert num(p[1], "plusr.cmd_pos") == -1000 and num(p[2], "plusr.act_pos") == 43690
    assert num(p[2], "plusr.stuffed") == 2
    p = _capture_packets("07_", tmp_path)
    assert [one(x, "plusr.version", "") for x in p] == [
        "ABC", "Ezi-STEP Plus-R ST", "Ezi-SERVO Plus-R ALL 60i v08.05.028", ""]
    p = _capture_packets("20_", tmp_path)
    assert [(num(x, "plusr.variant"), num(x, "plusr.sync")) for x in p[:4]] == [(8, 0xF0), (8, 0xF0), (8, 0xAA), (8, 0xAA)]
    assert num(p[3], "plusr.act_pos") == 43690
    assert num(p[4], "plusr.variant") == 6  # the 4-byte body: only the Ver6 reading fits
    assert num(p[5], "plusr.variant") == 8  # fits neither: slave 1 was last seen as Ver8


@needs_tshark
def test_preference_forces_the_variant(tmp_path):
    p = _capture_packets("20_", tmp_path, "plusr.variant:ver6")
    assert [num(x, "plusr.variant") for x in p] == [6] * len(p)
    assert num(p[0], "plusr.type") == 0xF0  # GetSlaveInfo with sync F0, read as Ver6: ReadCounters
    p = _capture_packets("25_", tmp_path, "plusr.variant:ver8")
    assert num(p[0], "plusr.variant") == 6  # a 4-byte body has no room for a sync byte
    assert num(p[2], "plusr.variant") == 8


@needs_tshark
def test_vendor_probe_answers_are_paired(tmp_path):
    """The Ver8 drive's frame-type error to the Ver6 probe (id, 0x51, crcL, 0x80) answers it."""
    p = _capture_packets("27_", tmp_path)
    answers = [i for i, x in enumerate(p) if "plusr.probe_answer" in x]
    assert answers, "no probe answer recognised"
    for i in answers:
        assert num(p[i], "plusr.status") == 0x80 and num(p[i], "plusr.sync") == 0x51
        req = num(p[i], "plusr.request_in")
        assert num(p[req - 1], "plusr.type") == 0x51 and num(p[req - 1], "plusr.variant") == 6
        assert num(p[req - 1], "plusr.response_in") == i + 1


# --- pairing and response time on a crafted stream with known times ------------------------
def _frame(slave, ftype, data=b"", sync=-1):
    return F.encode(slave, ftype, bytes(data), sync)


def _crafted():
    t0 = EPOCH_US + 5000000
    ok = b"\x00"
    rows = [  # (µs after t0, wire)
        (0, _frame(2, F.GET_AXIS_STATUS)),
        (1500, _frame(2, F.GET_AXIS_STATUS, ok + struct.pack("<I", 0x08000000))),  # 1.5 ms
        (10000, _frame(3, F.GET_COMMAND_POS)),
        (13500, _frame(3, F.GET_COMMAND_POS, ok + struct.pack("<i", -5))),  # 3.5 ms
        (20000, _frame(4, F.GET_ACTUAL_POS, b"", 0xF1)),  # Ver8
        (22250, _frame(4, F.GET_ACTUAL_POS, ok + struct.pack("<i", 7), 0xF1)),  # 2.25 ms
        (30000, _frame(5, F.MOVE_STOP)),  # never answered
        (40000, _frame(F.BROADCAST_ID, F.ALL_MOVE_STOP)),
        (50000, _frame(2, F.MOVE_INC_POS, struct.pack("<iI", 100, 5000))),
        (52100, _frame(2, F.MOVE_INC_POS, b"\x85")),  # refused, 2.1 ms
        (60000, _frame(6, F.GET_PARAMETER, b"\x01")),
        (60900, _frame(6, F.GET_PARAMETER, ok + struct.pack("<i", 500000))),  # 0.9 ms
    ]
    return [R.Record(0, t0 + dt, R.DIR_UNKNOWN, wire, R.GOOD) for dt, wire in rows]


@needs_tshark
def test_pairing_and_response_time(tmp_path):
    pcap = write_pcapng(str(tmp_path / "pairs.pcapng"), _crafted())
    p = dissect(pcap)
    kinds = [num(x, "plusr.kind") for x in p]
    assert kinds == [0, 1, 0, 1, 0, 1, 0, 2, 0, 1, 0, 1]
    pairs = {i + 1: num(x, "plusr.request_in") for i, x in enumerate(p) if num(x, "plusr.kind") == 1}
    assert pairs == {2: 1, 4: 3, 6: 5, 10: 9, 12: 11}
    for reply, req in pairs.items():
        assert num(p[req - 1], "plusr.response_in") == reply
    times = {i + 1: one(x, "plusr.time") for i, x in enumerate(p) if "plusr.time" in x}
    assert times == {2: "0.001500000", 4: "0.003500000", 6: "0.002250000", 10: "0.002100000", 12: "0.000900000"}
    assert "plusr.response_in" not in p[6]  # MoveStop to 5: no reply
    assert one(p[11], "plusr.param.name") == "axis_max_speed" and num(p[11], "plusr.value") == 500000
    assert num(p[5], "plusr.variant") == 8 and num(p[5], "plusr.act_pos") == 7


@needs_tshark
def test_display_filters(tmp_path):
    pcap = write_pcapng(str(tmp_path / "pairs.pcapng"), _crafted())
    assert [r[0] for r in fields(pcap, ["frame.number"], "plusr.type == 0x51")] == ["3", "4"]
    assert [r[0] for r in fields(pcap, ["frame.number"], "plusr.status != 0")] == ["10"]
    assert [r[0] for r in fields(pcap, ["frame.number"], "plusr.time > 0.002")] == ["4", "6", "10"]
    assert [r[0] for r in fields(pcap, ["frame.number"], "plusr.kind == 0 && !plusr.response_in")] == ["7"]
    assert [r[0] for r in fields(pcap, ["frame.number"], "plusr.flags.motioning")] == ["2"]
    assert [r[0] for r in fields(pcap, ["frame.number"], 'plusr.param.name == "axis_max_speed"')] == ["11", "12"]


@needs_tshark
def test_direction_decides_on_two_buses(tmp_path):
    """The jig's view: PC bus inbound = request, driver bus outbound = request; pairs per bus."""
    t = EPOCH_US
    req, rep = _frame(2, F.GET_AXIS_STATUS), _frame(2, F.GET_AXIS_STATUS, b"\x00" + bytes(4))
    same = _frame(2, F.SERVO_ENABLE, b"\x00")  # ServoEnable off = its own OK reply, byte for byte
    recs = [
        R.Record(0, t + 0, R.DIR_INBOUND, req, R.GOOD),
        R.Record(1, t + 200, R.DIR_OUTBOUND, req, R.GOOD),
        R.Record(1, t + 1700, R.DIR_INBOUND, rep, R.GOOD),
        R.Record(0, t + 1900, R.DIR_OUTBOUND, rep, R.GOOD),
        R.Record(0, t + 5000, R.DIR_INBOUND, same, R.GOOD),
        R.Record(0, t + 6000, R.DIR_OUTBOUND, same, R.GOOD),
    ]
    pcap = write_pcapng(str(tmp_path / "two.pcapng"), recs, [R.pc_bus(115200), R.driver_bus(115200)])
    p = dissect(pcap)
    assert [num(x, "plusr.kind") for x in p] == [0, 0, 1, 1, 0, 1]
    assert [num(x, "plusr.request_in") for x in p] == [None, None, 2, 1, None, 5]
    assert [one(x, "plusr.time") for x in p if "plusr.time" in x] == ["0.001500000", "0.001900000", "0.001000000"]


# --- broken frames ----------------------------------------------------------------------------
@needs_tshark
def test_malformed_frames_carry_expert_info(tmp_path):
    good = _frame(2, F.GET_AXIS_STATUS)
    bad_crc = good[:4] + bytes([good[4] ^ 1]) + good[5:]
    rows = [
        (bad_crc, "plusr.crc.bad", "CRC mismatch"),
        (b"\xaa\xcc\x02\x40\xaa\x01", "plusr.bad_stuffing", "0xAA followed by 0x01"),
        (b"\xaa\xcc\x02\x40\xaa\xee", "plusr.short", "Body of 2 bytes"),
        (good[:-2], "plusr.no_tail", "No tail"),
        (b"\x12\x34", "plusr.no_header", "noise"),
        (good + b"\x00", "plusr.trailing", "after the tail"),
        (_frame(2, F.GET_AXIS_STATUS, b"\x00\x01"), "plusr.bad_length", "expected 4"),
        (b"\xaa\xcc" + b"\x01" * 300, "plusr.overlong", "without a tail"),
    ]
    recs = [R.Record(0, EPOCH_US + 1000 * i, R.DIR_UNKNOWN, w, R.GOOD) for i, (w, _e, _m) in enumerate(rows)]
    p = dissect(write_pcapng(str(tmp_path / "bad.pcapng"), recs))
    for (wire, expert, text), x in zip(rows, p):
        assert expert in x, (wire.hex(" "), expert, x.get("expert_messages"))
        assert any(text in m for m in x.get("expert_messages", [])), (text, x.get("expert_messages"))
    assert one(p[0], "plusr.crc.calculated") is not None
    errors = run_tshark(["-r", str(tmp_path / "bad.pcapng"), "-q", "-z", "expert,error"]).stdout
    for text in ("CRC mismatch", "stuffing error", "Body of 2 bytes", "No tail", "without a tail"):
        assert text in errors, (text, errors)


@needs_tshark
def test_jig_frames_and_status_layouts(tmp_path):
    """The jig's own frames (jig.diag layouts) and the wide status replies, request then reply."""
    from jig import diag as D

    ok = b"\x00"
    counters = [7 * i for i in range(D.N_WIRE)]
    scan_types = bytes([0, D.SLAVE_TYPE, 20, 20] + [0] * 12)
    all_status = struct.pack("<IIIiiiiI", 0x5, 0x8004, 0x08000401, 1000, 990, 10, 5000, 3)
    wide = struct.pack("<QIIiiiiI", (1 << 40) | 1, 0, 0x08000000, -1, -2, 1, -5000, 0)  # Ver8: 64-bit inputs
    pairs = [
        (_frame(1, D.READ_COUNTERS), _frame(1, D.READ_COUNTERS, ok + bytes([D.N_WIRE]) + struct.pack(
            "<%dI" % D.N_WIRE, *counters))),
        (_frame(1, D.GET_BUS_SCAN_RESULT), _frame(1, D.GET_BUS_SCAN_RESULT, ok + bytes([D.SCAN_DONE]) +
                                                  struct.pack("<H", 0b1110) + scan_types)),
        (_frame(1, D.READ_CRASH_LOG), _frame(1, D.READ_CRASH_LOG, ok + b"MemoryError in pump\x00")),
        (_frame(2, F.GET_ALL_STATUS), _frame(2, F.GET_ALL_STATUS, ok + all_status)),
        (_frame(3, F.GET_ALL_STATUS, b"", 0xF2), _frame(3, F.GET_ALL_STATUS, ok + wide, 0xF2)),
        (_frame(2, F.SET_IO_OUTPUT, struct.pack("<II", 1 << 11, 1 << 15)), _frame(2, F.SET_IO_OUTPUT, ok)),
    ]
    recs = []
    for k, (req, rep) in enumerate(pairs):
        recs.append(R.Record(0, EPOCH_US + 10000 * k, R.DIR_UNKNOWN, req, R.GOOD))
        recs.append(R.Record(0, EPOCH_US + 10000 * k + 1000, R.DIR_UNKNOWN, rep, R.GOOD))
    p = dissect(write_pcapng(str(tmp_path / "jig.pcapng"), recs))
    assert [num(x, "plusr.kind") for x in p] == [0, 1] * len(pairs)
    assert [num(p[1], "plusr.jig." + name) for name in D.WIRE_NAMES] == counters
    assert num(p[3], "plusr.jig.scan_state") == D.SCAN_DONE and num(p[3], "plusr.jig.scan_found") == 0b1110
    assert [int(v) for v in p[3]["plusr.jig.scan_type"]] == [D.SLAVE_TYPE, 20, 20]
    assert one(p[5], "plusr.jig.crash_log") == "MemoryError in pump"
    x = p[7]
    assert (num(x, "plusr.inputs"), num(x, "plusr.outputs"), num(x, "plusr.flags")) == (0x5, 0x8004, 0x08000401)
    assert (num(x, "plusr.cmd_pos"), num(x, "plusr.act_pos"), num(x, "plusr.pos_error"), num(x, "plusr.velocity"),
            num(x, "plusr.pt_number")) == (1000, 990, 10, 5000, 3)
    assert one(x, "plusr.in.limit_plus") == "1" and one(x, "plusr.out.user_out0") == "1"
    assert one(x, "plusr.flags.step_out") == "1" and "plusr.flags.error" in x  # an error flag: expert note
    x = p[9]
    assert (num(x, "plusr.variant"), num(x, "plusr.sync"), num(x, "plusr.inputs"), num(x, "plusr.inputs_hi")) == (
        8, 0xF2, 1, 1 << 8)
    assert num(x, "plusr.velocity") == -5000
    assert (num(p[10], "plusr.set_mask"), num(p[10], "plusr.clear_mask")) == (1 << 11, 1 << 15)
