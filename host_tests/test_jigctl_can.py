"""``jigctl can``: every subcommand against the bench's SLCAN port, every refusal in one sentence.

The first half needs no CAN bench: the CiA 301 names, the EDS lookups and value parsing,
the dump's lines, and the input refusals (which come before any port is opened), plus
ports that are not SLCAN ports (the bench's Plus-R port, its capture port, an echoing
port like a REPL). The second half runs ``cli.main`` against a real-time
``Bench(can_nodes=(5, 6))`` through the jig's SLCAN port, as test_cli_bench.py does
for the RS-485 commands.
"""

import json
import os
import struct

import can
import pytest

from motorjig import cli
from motorjig.can import EDS_PATH, cia301
from motorjig.can import objects as O
from motorjig.can.dump import FrameText
from motorjig.commands import UsageError

NODES = (5, 6)
TIMEOUT_MS = 500  # SDO answers: generous, the bench runs in real time on a shared machine


@pytest.fixture(scope="module")
def od():
    return O.load_eds(EDS_PATH)


class Run:
    """cli.main with captured output; asserts the exit status, and one sentence for refusals."""

    def __init__(self, capsys, port=None):
        self.capsys = capsys
        self.port = port

    def __call__(self, *argv, code=0):
        self.capsys.readouterr()
        head = ["--port", self.port] if self.port else []
        rc = cli.main(head + ["--timeout", str(TIMEOUT_MS)] + [str(a) for a in argv])
        self.out, self.err = self.capsys.readouterr()
        assert rc == code, (argv, rc, self.out, self.err)
        if code not in (0, 1):
            lines = [ln for ln in self.err.splitlines() if ln.strip()]
            assert len(lines) == 1 and lines[0].startswith("jigctl: ") and lines[0].endswith((".", "?")), self.err
            assert "Traceback" not in self.err
        return self.out

    def json(self, *argv, code=0):
        return json.loads(self(*argv, "--json", code=code))


# --- names ---------------------------------------------------------------------------
def test_abort_codes_and_emcy_codes_are_named():
    assert cia301.abort_text(0x06020000) == "0x06020000 object does not exist in the object dictionary"
    assert cia301.abort_text(0x06010002) == "0x06010002 attempt to write a read only object"
    assert cia301.abort_text(0x12345678) == "0x12345678 unknown abort code"
    assert cia301.emcy_name(0x8611) == "following error"
    assert cia301.emcy_name(0x2310) == "continuous over current"
    assert cia301.emcy_name(0x4281) == "device temperature"  # by its class
    assert cia301.emcy_name(0x5ABC) == "device hardware"
    assert cia301.profile_name(0x00020192) == "CiA 402 drives and motion control"
    assert cia301.profile_name(0x1F5) == "profile 501"


def test_frames_are_described_by_cob_id():
    d = cia301.describe_frame
    assert d(0x000, b"\x01\x05") == "NMT start node 5"
    assert d(0x000, b"\x81\x00") == "NMT reset node all nodes"
    assert d(0x705, b"\x05") == "heartbeat node 5: operational"
    assert d(0x706, b"\x00") == "heartbeat node 6: boot-up"
    assert d(0x705, b"\x7f") == "heartbeat node 5: pre-operational"
    assert d(0x085, bytes([0x11, 0x86, 0x01, 0, 0, 0, 0, 0])) == \
        "EMCY node 5: 0x8611 following error, error register 0x01"
    assert d(0x605, bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0])) == "SDO request node 5: upload 0x6041:00"
    assert d(0x585, bytes([0x4B, 0x41, 0x60, 0, 0x37, 0x02, 0, 0])) == "SDO response node 5: 0x6041:00 = 0x0237"
    assert d(0x585, bytes([0x80, 0xFF, 0x2F, 0]) + struct.pack("<I", 0x06020000)) == \
        "SDO response node 5: abort 0x2FFF:00: 0x06020000 object does not exist in the object dictionary"
    assert d(0x605, bytes([0x2B, 0x40, 0x60, 0, 0x0F, 0, 0, 0])) == "SDO request node 5: download 0x6040:00 = 0x000F"
    assert d(0x585, bytes([0x60, 0x40, 0x60, 0, 0, 0, 0, 0])) == "SDO response node 5: download 0x6040:00 done"
    assert d(0x185, b"\x37\x02\x01") == "TPDO1 node 5"
    assert d(0x080, b"") == "SYNC"
    assert d(0x7E5, bytes([0x51] + [0] * 7)) == "LSS master fast scan"
    assert d(0x123, b"\x01", ext=True) == ""
    assert d(0x7FF, b"") == ""


def test_frames_named_from_the_eds(od):
    text = FrameText(od)

    def meaning(can_id, data):
        return text.meaning(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))

    assert meaning(0x605, bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0])) == "SDO request node 5: upload 0x6041:00 Statusword"
    assert meaning(0x585, bytes([0x4B, 0x41, 0x60, 0, 0x37, 0x02, 0, 0])) == \
        "SDO response node 5: 0x6041:00 Statusword = 567 (0x0237)"
    # TPDO2 by the EDS's default mapping: statusword (16 bits), position actual value (32 bits)
    assert meaning(0x286, struct.pack("<Hi", 0x0637, -1000)) == \
        "TPDO2 node 6: Statusword=1591 (0x0637), Position actual value=-1000"
    assert meaning(0x286, b"\x01") == "TPDO2 node 6"  # too short for its mapping: not guessed
    line = text.line(can.Message(timestamp=10.5, arbitration_id=0x705, data=b"\x05", is_extended_id=False), 10.0)
    assert line.startswith("(   0.500000)  slcan       705   [1]  05 ") and line.endswith("heartbeat node 5: operational")


# --- the EDS ----------------------------------------------------------------------------
def test_objects_by_number_name_and_sub_name(od):
    t = O.find(od, "0x6041", "eds")
    assert (t.index, t.sub, t.var.name) == (0x6041, 0, "Statusword")
    assert O.find(od, "statusword", "eds").index == 0x6041
    assert O.find(od, "24641", "eds").index == 0x6041
    t = O.find(od, "0x1018:2", "eds")
    assert (t.sub, t.label) == (2, "0x1018:02 Identity object.Product code")
    t = O.find(od, "Identity object:Serial number", "eds")
    assert (t.index, t.sub) == (0x1018, 4)
    t = O.find(od, "0x1018", "eds")
    assert t.var is None and t.container.name == "Identity object"
    assert O.find(od, "0x2FFF:3", "eds", force=True).var is None


@pytest.mark.parametrize("text, message", [
    ("0x2FFF", "0x2FFF is not an object in eds"),
    ("NoSuchThing", "'NoSuchThing' is not the name of an object in eds"),
    ("0x1018:7", "0x1018 Identity object has no sub-index 7 in eds"),
    ("0x6041:1", "0x6041 Statusword is a single value: it has no sub-index 1"),
    ("0x10000", "index 0x10000 is not 0..0xFFFF"),
    ("0x1018:300", "sub-index 300 is not 0..255"),
    (":1", "is not an object"),
])
def test_unknown_objects_are_refused(od, text, message):
    with pytest.raises(UsageError, match=message.replace("(", r"\(").replace(")", r"\)")):
        O.find(od, text, "eds")


def test_values_are_parsed_by_type_and_range(od):
    def parse(obj, text, force=False):
        t = O.find(od, obj, "eds")
        return O.parse_value(t.var, text, t.label, force=force)

    assert parse("0x607A", "-1000") == -1000
    assert parse("0x607A", "0x7FFF_FFFF") == 0x7FFFFFFF
    assert parse("0x6040", "0x000F") == 15
    assert parse("0x6060", "-1") == -1
    assert parse("0x1010:1", "save") == 0x65766173
    assert parse("0x1011:1", "load") == 0x64616F6C
    with pytest.raises(UsageError, match="is not a value for 0x607A:00 Target position .INTEGER32: a whole number."):
        parse("0x607A", "ten")
    with pytest.raises(UsageError, match="2147483648 is out of range for 0x607A:00 Target position"):
        parse("0x607A", "2147483648")
    with pytest.raises(UsageError, match="-1 is out of range for 0x6040:00 Controlword: 0..65535"):
        parse("0x6040", "-1")
    with pytest.raises(UsageError, match="0 is out of range for 0x6083:00 Profile acceleration: 1..4294967295"):
        parse("0x6083", "0")  # the EDS's LowLimit
    assert parse("0x6083", "0", force=True) == 0  # --force: only the type's own range
    with pytest.raises(UsageError, match="1.5"):
        parse("0x6060", "1.5")


def test_values_of_other_types(od):
    var = od[0x1008]  # VISIBLE_STRING
    assert O.parse_value(var, "hello", "x") == "hello"
    with pytest.raises(UsageError, match="only ASCII"):
        O.parse_value(var, "héllo", "x")
    real = type(var)("real", 0x2100)
    real.data_type = 0x8  # REAL32
    assert O.parse_value(real, "1.25", "x") == 1.25
    with pytest.raises(UsageError, match="does not fit"):
        O.parse_value(real, "1e300", "x")
    with pytest.raises(UsageError, match="NaN"):
        O.parse_value(real, "nan", "x")
    flag = type(var)("flag", 0x2101)
    flag.data_type = 0x1  # BOOLEAN
    assert O.parse_value(flag, "on", "x") is True and O.parse_value(flag, "0", "x") is False
    with pytest.raises(UsageError, match="0/1, true/false or on/off"):
        O.parse_value(flag, "maybe", "x")
    blob = type(var)("blob", 0x2102)
    blob.data_type = 0xF  # DOMAIN
    assert O.parse_value(blob, "01 02 0a", "x") == b"\x01\x02\x0a"
    assert O.parse_value(blob, "0x01020A", "x") == b"\x01\x02\x0a"
    with pytest.raises(UsageError, match="hex bytes"):
        O.parse_value(blob, "zz", "x")
    assert O.show(od[0x6041], 0x237) == "567 (0x0237)"
    assert O.show(od[0x607A], -5) == "-5"
    assert O.show(var, "abc") == "'abc'"


# --- refusals before any port is opened -------------------------------------------------
@pytest.mark.parametrize("argv, message", [
    (["sdo", "read", "0", "0x6041"], "node id must be 1..127, not '0'"),
    (["sdo", "read", "128", "0x6041"], "node id must be 1..127, not '128'"),
    (["sdo", "read", "five", "0x6041"], "node id must be 1..127, not 'five'"),
    (["nmt", "200", "start"], "node id must be 1..127 or all, not '200'"),
    (["sdo", "read", "5", "0x2FFF"], "0x2FFF is not an object in motorjig-cia402.eds"),
    (["sdo", "read", "5", "NoSuchObject"], "'NoSuchObject' is not the name of an object"),
    (["sdo", "write", "5", "0x607A", "ten"], "'ten' is not a value for 0x607A:00 Target position (INTEGER32"),
    (["sdo", "write", "5", "0x6040", "70000"], "70000 is out of range for 0x6040:00 Controlword: 0..65535"),
    (["sdo", "write", "5", "0x6041", "1"], "0x6041:00 Statusword is read-only"),
    (["sdo", "write", "5", "0x1018", "1"], "0x1018 Identity object has sub-indexes: give one"),
    (["sdo", "read", "5", "0x2001"], "0x2001:00 Set position actual is write-only"),
    (["--eds", "/no/such.eds", "sdo", "read", "5", "0x6041"], "the EDS /no/such.eds does not exist"),
    (["nmt", "5", "go"], "NMT command must be one of start, stop, preop, reset, reset-comm, not 'go'"),
    (["--bitrate", "12345", "scan"], "--bitrate must be one of 10000"),
    (["scan", "--bitrate", "fast"], "--bitrate must be one of 10000"),
    (["dump", "--count", "0"], "--count must be at least 1"),
    (["dump", "--duration", "-1"], "--duration must be a number of seconds"),
    (["dump", "--log", "frames.pcap"], "give a file ending in .asc, .blf, .csv"),
    (["dump", "--log", "/no/such/dir/x.asc"], "cannot write /no/such/dir/x.asc"),
    (["lss", "set-id", "0"], "node id must be 1..127 (or 255: unconfigured), not '0'"),
    (["lss", "set-bitrate", "750000"], "LSS bitrate must be one of the CiA table's"),
    (["lss", "store", "--identity", "1,2,3"], "--identity must be four numbers"),
    (["lss", "fast-scan", "--lss-timeout", "0"], "--lss-timeout must be at least 1 ms"),
])
def test_bad_input_is_refused_in_one_sentence(capsys, monkeypatch, argv, message):
    monkeypatch.delenv("JIGCTL_CAN_PORT", raising=False)
    run = Run(capsys, "socket://127.0.0.1:1")  # never opened: the input is checked first
    run("can", *argv, code=2)
    assert message in run.err


def test_no_port_given(capsys, monkeypatch):
    monkeypatch.delenv("JIGCTL_CAN_PORT", raising=False)
    monkeypatch.delenv("JIGCTL_PORT", raising=False)
    run = Run(capsys)
    run("can", "scan", code=2)
    assert "give --port PORT" in run.err and "$JIGCTL_CAN_PORT" in run.err


def test_help_everywhere(capsys):
    for argv in (["can", "--help"], ["can", "scan", "--help"], ["can", "nmt", "--help"], ["can", "sdo", "--help"],
                 ["can", "sdo", "read", "--help"], ["can", "sdo", "write", "--help"], ["can", "dump", "--help"],
                 ["can", "lss", "--help"], ["can", "lss", "fast-scan", "--help"], ["can", "lss", "set-id", "--help"],
                 ["can", "lss", "set-bitrate", "--help"], ["can", "lss", "store", "--help"]):
        assert cli.main(argv) == 0, argv
        out = capsys.readouterr().out
        assert "usage: jigctl can" in out and "--bitrate" in out, argv
    assert cli.main(["can"]) == 2  # a CAN subcommand is required
    assert "CAN_COMMAND" in capsys.readouterr().err


# --- ports that are not SLCAN ports --------------------------------------------------------
def test_an_echoing_port_is_not_an_slcan_port(capsys):
    run = Run(capsys, "loop://")  # answers what it is sent, as a REPL echoes
    run("can", "scan", code=3)
    assert run.err.startswith("jigctl: loop:// is not an SLCAN port: it answered b'V\\r' to V")


def test_missing_ports_are_refused(capsys):
    run = Run(capsys, "/dev/does-not-exist")
    run("can", "sdo", "read", 5, "0x6041", code=3)
    assert "port /dev/does-not-exist does not exist" in run.err
    run = Run(capsys, "socket://127.0.0.1:1")
    run("can", "dump", "--count", 1, code=3)
    assert "connection refused" in run.err


# --- against the bench ------------------------------------------------------------------
VENDOR = 0x4D4A4947  # the EDS's 0x1018:1
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.join(ROOT, "firmware"), os.path.join(ROOT, "tools")]))


@pytest.fixture(scope="module")
def bench():
    from motorjig.sim import Bench

    with Bench(driver_ids=(2,), can_nodes=NODES, can_bitrate=500000) as b:
        yield b


@pytest.fixture
def run(capsys, bench):
    return Run(capsys, bench.slcan_url)


def test_scan(run, bench):
    rows = run.json("can", "scan")
    assert [r["node"] for r in rows] == list(NODES)
    r = rows[0]
    assert r["profile"] == "CiA 402 drives and motion control" and r["device_type"] & 0xFFFF == 402
    assert r["name"] == "MotorJig CiA 402 drive (sim)"
    assert (r["vendor"], r["product"], r["revision"]) == (VENDOR, 0x402, 0x00010000)
    assert rows[0]["serial"] != rows[1]["serial"]
    text = run("can", "scan", "--wait", "0.3")
    assert "node   5  CiA 402 drives and motion control (0x1000 = 0x%08X)" % r["device_type"] in text
    assert "name 'MotorJig CiA 402 drive (sim)'" in text and "vendor 0x4D4A4947" in text


def test_scan_at_the_wrong_bitrate_finds_nothing(run):
    run("can", "--bitrate", "250000", "scan", "--wait", "0.3", code=4)
    assert "no node answered on socket://" in run.err and "at 250000 bit/s" in run.err


def test_sdo_read_and_write(run):
    d = run.json("can", "sdo", "read", 5, "0x1018:1")
    assert (d["index"], d["subindex"], d["name"], d["type"], d["value"]) == (0x1018, 1, "Identity object.Vendor-ID",
                                                                            "UNSIGNED32", VENDOR)
    text = run("can", "sdo", "read", 5, "Identity object")  # a record: every sub-index
    assert "node 5 0x1018:00 Identity object.Highest sub-index supported = 4 (0x04)" in text
    assert "node 5 0x1018:01 Identity object.Vendor-ID = %d (0x%08X)" % (VENDOR, VENDOR) in text
    assert len(text.splitlines()) == 5
    assert "= 'MotorJig CiA 402 drive (sim)'" in run("can", "sdo", "read", 5, "Manufacturer device name")  # segmented
    assert run("can", "sdo", "write", 6, "Profile velocity", "0x5BA0").strip() == \
        "node 6 0x6081:00 Profile velocity := 23456 (0x00005BA0)"
    assert run.json("can", "sdo", "read", 6, "0x6081")["value"] == 23456
    run("can", "sdo", "write", 6, "0x607A", "-1000")
    assert run.json("can", "sdo", "read", 6, "Target position")["value"] == -1000
    run("can", "sdo", "write", 6, "0x607A", "0")
    # --force: objects the EDS lacks go untyped, as hex bytes (the node decides); the others stay typed
    assert run.json("can", "sdo", "read", 6, "0x6081", "--force")["value"] == 23456
    run("can", "sdo", "write", 6, "0x6081", "10000", "--force")
    assert run.json("can", "sdo", "read", 6, "0x6081")["value"] == 10000
    run("can", "sdo", "write", 6, "0x2FFF:1", "10 27 00 00", "--force", code=5)
    assert "node 6 aborted the write of 0x2FFF:01: 0x06020000 object does not exist" in run.err


def test_sdo_refusals_from_the_node_and_silence(run):
    run("can", "sdo", "read", 5, "0x2FFF", "--force", code=5)
    assert run.err == ("jigctl: node 5 aborted the read of 0x2FFF:00: 0x06020000 object does not exist in the "
                       "object dictionary.\n")
    run("can", "sdo", "write", 5, "0x6041", 1, "--force", code=5)
    assert "0x06010002 attempt to write a read only object" in run.err
    run("can", "sdo", "read", 5, "0x1018:9", "--force", code=5)
    assert "0x06090011 sub-index does not exist" in run.err
    run("can", "sdo", "read", 7, "0x6041", code=4)  # no node 7
    assert run.err.startswith("jigctl: node 7 did not answer the read of 0x6041:00 Statusword")


def test_a_silent_node_is_one_sentence_in_a_process_of_its_own(bench):
    """python-canopen logs the transfer it gives up ("Transfer aborted by client with code
    0x05040000") before our sentence: jigctl says it once."""
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-m", "motorjig.cli", "can", "--port", bench.slcan_url, "sdo", "read", "7",
                        "0x6041"], capture_output=True, text=True, timeout=60, env=ENV)
    assert p.returncode == 4
    assert p.stderr.startswith("jigctl: node 7 did not answer the read of 0x6041:00") and p.stderr.count("\n") == 1
    assert "Transfer aborted" not in p.stderr


def _heartbeats(run, ms):
    for n in NODES:
        run("can", "sdo", "write", n, "0x1017", ms)


def test_nmt(run):
    _heartbeats(run, 50)
    try:
        text = run("can", "nmt", 5, "stop")
        assert text.splitlines()[0] == "NMT stop sent to node 5" and "node 5: " in text and text.rstrip().endswith("stopped (heartbeat)")
        run("can", "sdo", "read", 5, "0x6041", code=4)  # a stopped node does no SDO
        d = run.json("can", "nmt", "all", "start")
        assert d == {"command": "start", "node": "all", "heard": {"5": "operational", "6": "operational"}}
        d = run.json("can", "nmt", 6, "preop")
        assert d["heard"] == {"6": "pre-operational"}
        text = run("can", "nmt", 6, "reset")  # boots, and comes back with the heartbeat off (0x1017's default)
        assert "boot-up (heartbeat)" in text and "node 6: " in text  # a heartbeat on its way may come first
        assert run.json("can", "sdo", "read", 6, "0x1017")["value"] == 0
        text = run("can", "nmt", 6, "start", "--wait", "0.3")
        assert "nothing heard from node 6 within 0.3 s to confirm it" in text
    finally:
        _heartbeats(run, 0)
        run("can", "nmt", "all", "preop", "--wait", "0")


def test_dump_lines_json_and_log(run, tmp_path):
    _heartbeats(run, 20)
    try:
        text = run("can", "--eds", EDS_PATH, "dump", "--count", 4)
        lines = text.splitlines()
        assert len(lines) == 4 and all("slcan" in ln and "heartbeat node " in ln for ln in lines), text
        assert "[1]  7F" in lines[0] and lines[0].endswith("pre-operational")
        assert run.err == "4 frames\n"
        rows = [json.loads(ln) for ln in run("can", "dump", "--count", 2, "--json").splitlines()]
        assert len(rows) == 2 and rows[0]["id"] in (0x705, 0x706) and rows[0]["data"] == "7f"
        log = str(tmp_path / "bus.asc")
        run("can", "dump", "--duration", 0.5, "--log", log)
        assert run.err.endswith("logged to %s\n" % log)
        frames = list(can.LogReader(log))
        assert len(frames) >= 5 and {m.arbitration_id for m in frames} == {0x705, 0x706}
    finally:
        _heartbeats(run, 0)
    run("can", "dump", "--duration", 0.3)  # a quiet bus: no frame, no error
    assert run.out == "" and run.err == "0 frames\n"


def test_dump_names_pdos_from_the_eds(run):
    run("can", "sdo", "write", 5, "0x1800:5", 100)  # TPDO1 every 100 ms (event timer)
    try:
        run("can", "nmt", 5, "start", "--wait", 0)
        lines = run("can", "--eds", EDS_PATH, "dump", "--count", 2).splitlines()
        assert len(lines) == 2 and all(" 185   [3]  " in ln for ln in lines), lines
        assert "TPDO1 node 5: Statusword=" in lines[0] and lines[0].endswith("Modes of operation display=1")
        plain = run("can", "dump", "--count", 1).splitlines()  # without --eds: the PDO, not its contents
        assert plain[0].endswith("TPDO1 node 5")
    finally:
        run("can", "nmt", 5, "reset")  # the communication parameters back to the EDS's defaults


def test_dump_ends_cleanly_on_ctrl_c(bench, tmp_path):
    import signal
    import subprocess
    import sys

    log = str(tmp_path / "bus.csv")
    p = subprocess.Popen([sys.executable, "-m", "motorjig.cli", "--port", bench.slcan_url, "can", "dump", "--log", log],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        import time

        end = time.monotonic() + 20
        while not os.path.exists(log) and time.monotonic() < end:
            time.sleep(0.02)
        time.sleep(0.3)
    finally:
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=20)
    assert p.returncode == 0, err
    assert err.endswith("frames logged to %s\n" % log) and "Traceback" not in err
    assert open(log).readline().startswith("timestamp,arbitration_id")


def test_lss_moves_a_node_through_unconfigured_and_back(run):
    ident = run.json("can", "scan")[1]  # node 6
    address = "%d,%d,%d,%d" % (ident["vendor"], ident["product"], ident["revision"], ident["serial"])
    run("can", "lss", "fast-scan", code=4)  # every node has an id
    assert "no unconfigured node answered the LSS fast scan" in run.err
    # node 6 -> unconfigured (255), stored, then a reset makes it so
    text = run("can", "lss", "set-id", 255, "--identity", address, "--store")
    assert "node id 255 configured" in text and "configuration stored" in text
    run("can", "nmt", 6, "reset", "--wait", 0.5)
    assert [r["node"] for r in run.json("can", "scan")] == [5]
    d = run.json("can", "lss", "fast-scan")
    assert d["identity"] == {"vendor": ident["vendor"], "product": ident["product"], "revision": ident["revision"],
                             "serial": ident["serial"]}
    d = run.json("can", "lss", "inquire")
    assert d["node_id"] == 255 and d["identity"]["serial"] == ident["serial"]
    text = run("can", "lss", "set-id", 6, "--store")  # then back to waiting: it boots as node 6
    assert "every node switched back to LSS waiting state" in text
    rows = run.json("can", "scan")
    assert [r["node"] for r in rows] == list(NODES)
    # refusals: no node in configuration state; an identity no node has; a bit timing the node does not do
    run("can", "lss", "set-id", 9, code=4)
    assert "no node answered the LSS configure node id" in run.err
    run("can", "lss", "store", "--identity", "1,2,3,4", code=4)
    assert "no node has the LSS address 1,2,3,4" in run.err
    run("can", "lss", "set-bitrate", 100000, "--identity", address, code=5)
    assert run.err.startswith("jigctl: the node refused the LSS configure bit timing")
    text = run("can", "lss", "set-bitrate", 250000, "--identity", address)
    assert "bitrate 250000 bit/s configured (table index 3)" in text


# --- sdo dump / load: a node's settings as a CiA 402 parameter-set file ----------------------
@pytest.mark.parametrize("argv, message", [
    (["sdo", "dump", "0"], "node id must be 1..127, not '0'"),
    (["sdo", "dump", "5", "--objects", "0x2001"], "0x2001:00 Set position actual is write-only"),
    (["sdo", "dump", "5", "--objects", "0x6081,,0x6083"], "an empty entry in the object list"),
    (["sdo", "dump", "5", "--objects", "0x6099:3"], "0x6099 Homing speeds has no sub-index 3"),
    (["sdo", "dump", "5", "--objects", "0x2FFF"], "0x2FFF is not an object in motorjig-cia402.eds"),
    (["sdo", "load", "5", "/no/such/set.toml"], "/no/such/set.toml: cannot read"),
])
def test_sdo_dump_and_load_refuse_bad_input_in_one_sentence(capsys, monkeypatch, argv, message):
    monkeypatch.delenv("JIGCTL_CAN_PORT", raising=False)
    run = Run(capsys, "socket://127.0.0.1:1")  # never opened: the input is checked first
    run("can", *argv, code=2)
    assert message in run.err


def test_sdo_dump_and_load_help(capsys):
    for action, own in (("dump", "--objects LIST"), ("load", "--store")):
        assert cli.main(["can", "sdo", action, "--help"]) == 0
        out = capsys.readouterr().out
        assert "usage: jigctl can sdo %s" % action in out and "--bitrate" in out and own in out, action


@pytest.mark.parametrize("text, message", [
    ('[objects]\n"0x6041" = 1\n', "set.toml:2: objects.0x6041: 0x6041:00 Statusword is read-only"),
    ('[objects]\n"0x6065" = -1\n', "set.toml:2: objects.0x6065: 0x6065:00 Following error window: -1 is out of "
                                   "range for UNSIGNED32"),
    ('[objects]\n"0x6065" = true\n', "set.toml:2: objects.0x6065: 0x6065:00 Following error window: expected an "
                                     "integer"),
    ('[drive]\nslave_type = 20\n[objects]\n"0x6065" = 1\n', "set.toml:2: drive.slave_type: unknown key"),
    ('[parameters]\naxis_acc_time = 100\n', "set.toml:1: parameters: unknown table"),
])
def test_sdo_load_checks_the_file_before_the_port(capsys, monkeypatch, tmp_path, text, message):
    monkeypatch.delenv("JIGCTL_CAN_PORT", raising=False)
    (tmp_path / "set.toml").write_text(text)
    run = Run(capsys, "socket://127.0.0.1:1")
    run("can", "sdo", "load", 5, tmp_path / "set.toml", code=2)
    assert message in run.err


def test_sdo_dump_and_load_round_trip_through_the_node(run, tmp_path):
    from motorjig.can import paramset402

    text = run("can", "sdo", "dump", 5)
    assert text.startswith("# parameter set of node 5 (MotorJig CiA 402 drive (sim)), ")
    assert "product_code = 0x00000402" in text and '"0x6099:01" = ' in text
    path = tmp_path / "node5.toml"
    path.write_text(text)
    ps = paramset402.load(str(path), O.load_eds(EDS_PATH), writable=True)
    assert {(0x6065, 0), (0x6085, 0), (0x6099, 1), (0x607D, 2)} <= set(ps.values)
    assert (0x6040, 0) not in ps.values and (0x607A, 0) not in ps.values  # orders, not settings
    for (index, sub), value in ps.values.items():
        assert run.json("can", "sdo", "read", 5, "0x%04X:%d" % (index, sub))["value"] == value
    window = ps.values[(0x6065, 0)]
    changed = tmp_path / "changed.toml"
    changed.write_text(text.replace('"0x6065" = %d ' % window, '"0x6065" = %d ' % (window + 234)))
    out = run("can", "sdo", "load", 5, changed, "--store")
    assert out == "node 5: %d objects from %s written and stored (0x1010:01 \"save\")\n" % (len(ps.values), changed)
    run("can", "nmt", 5, "reset", "--wait", 0.5)  # a stored value outlives a reset
    assert run.json("can", "sdo", "read", 5, "0x6065")["value"] == window + 234
    # a set of another drive is refused before anything is written
    other = tmp_path / "other.toml"
    other.write_text(text.replace("product_code = 0x00000402", "product_code = 0x00000403").replace(
        '"0x6065" = %d ' % window, '"0x6065" = 7 '))
    run("can", "sdo", "load", 5, other, code=2)
    assert "is for a drive of product_code 0x00000403, node 5 has 0x00000402 (0x1018:2): nothing was written" in run.err
    assert run.json("can", "sdo", "read", 5, "0x6065")["value"] == window + 234
    d = run.json("can", "sdo", "load", 5, path, "--store")
    assert d == {"node": 5, "file": str(path), "written": len(ps.values), "stored": True}
    run("can", "nmt", 5, "reset", "--wait", 0.5)
    assert run.json("can", "sdo", "read", 5, "0x6065")["value"] == window
    run("can", "nmt", 5, "start", "--wait", 0.5)


def test_sdo_dump_of_a_list_and_as_json(run):
    text = run("can", "sdo", "dump", 5, "--objects", "Homing speeds,0x6065,0x2000")
    body = text[text.index("[objects]"):].splitlines()[1:]
    assert [line.split(" = ")[0] for line in body] == ['"0x2000"', '"0x6065"', '"0x6099:01"', '"0x6099:02"']
    d = run.json("can", "sdo", "dump", 5, "--objects", "0x2000")
    assert d["node"] == 5 and d["drive"]["vendor_id"] == VENDOR
    assert d["objects"] == [{"index": 0x2000, "subindex": 0, "name": "Counts per revolution", "value": 10000}]
    run("can", "sdo", "dump", 9, code=4)
    assert "node 9 did not answer the read of 0x1000:00 Device type" in run.err


def test_over_the_pty(capsys, bench):
    # Last in this module: the bench sees the pty closed a moment after it is, and turns
    # away a TCP client that comes in that moment (one host at a time).
    run = Run(capsys, bench.slcan_pty_path)
    assert [r["node"] for r in run.json("can", "scan", "--wait", "0.3")] == list(NODES)
    assert run.json("can", "sdo", "read", 6, "0x1018:1")["value"] == VENDOR
