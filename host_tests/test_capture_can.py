"""The CAN bus in the jig's recording (record format 2): jig.capture.Capture.can_frame,
read by jigstream, shown by the text view, written as the third pcapng interface
(LINKTYPE_CAN_SOCKETCAN), filtered by ``jigctl capture --jig --bus``, and dissected by
tshark's own CANopen dissector next to the Plus-R buses.

The firmware's records are made by calling ``app.capture.can_frame`` on a bench's
app with its CAN port (every kind of frame, as the CAN port does from its main-loop
pass), and by a bench session in which the host talks CANopen through the jig's
SLCAN port to a simulated CiA 402 drive; the SocketCAN bytes expected in the pcapng
are written here from the link type's definition, not from
``motorjig.capture.pcapng``.
"""

import io
import json
import os
import shutil
import struct
import subprocess

import pytest

from test_capture_jig_support import EPOCH_US, JigServer, can, frame, hello, raw, read_all
from test_capture_support import LUA, jigctl, needs_tshark, parse_pcapng, run_tshark

from jig import capture as C
from jig import frame as F
from jig import native
from jig import params as P
from jig.params import BAUD_RATES

from motorjig.capture import jigstream as J
from motorjig.capture import pcapng
from motorjig.capture import record as R
from motorjig.capture.textview import TextView, canopen_name
from motorjig.sim import SimBench
from motorjig.sim.cia402 import Cia402Node

EXT, RTR = R.CAN_EXT, R.CAN_RTR
#: (identifier, flags, DLC, data): standard, extended, remote requests, every length 0..8
FRAMES = [(0x123, 0, n, bytes(range(0xA0, 0xA0 + n))) for n in range(9)] + [
    (0x000, 0, 2, b"\x01\x05"),  # NMT start node 5
    (0x7FF, 0, 1, b"\xaa"),  # the highest standard identifier
    (0x18FF50E5, EXT, 3, b"\x01\x02\x03"),
    (0x1FFFFFFF, EXT, 8, b"\xff" * 8),  # the highest extended one
    (0x00000000, EXT, 0, b""),  # extended zero is not standard zero
    (0x705, RTR, 1, b""),  # a remote request asks for DLC bytes and carries none
    (0x080, RTR, 0, b""),
    (0x1ABCDEF0, EXT | RTR, 8, b""),
]
BITRATE = 250000


def recording(bitrate=BITRATE, **kw):
    """A bench whose jig has a CAN port at ``bitrate`` (0: no CAN bus, so no CAN port),
    recording from now on."""
    if bitrate:  # the bus's bitrate, and the jig's CAN port's (parameter 14)
        b = SimBench(can=True, can_bitrate=bitrate, jig_params={P.P_CAN_BITRATE: bitrate}, **kw)
    else:
        b = SimBench(**kw)
    assert (b.app.can is not None) == bool(bitrate)
    b.app.set_capture(1, b.hal.ticks_us())
    b.t_hello = int(b.clock.now)
    return b, bitrate


def record_frames(b, frames=FRAMES, step_us=250):
    """Every frame once received (to_bus 0) and once sent (1), step_us apart; returns
    [(bench time of the record, to_bus, frame)]."""
    out = []
    for to_bus in (0, 1):
        for fr in frames:
            b.run_for(step_us)
            can_id, flags, dlc, data = fr
            payload = bytearray(8)
            payload[:len(data)] = data
            # data as the CAN port holds it: a view of its frame buffer, dlc bytes long (or any, for RTR)
            assert b.app.capture.can_frame(b.hal.ticks_us(), can_id, flags, dlc, memoryview(payload)[:max(dlc, 1)],
                                           to_bus) == 1
            out.append((int(b.clock.now), to_bus, fr))
    return out


def socketcan(can_id, flags, dlc, data):
    """LINKTYPE_CAN_SOCKETCAN (tcpdump.org): identifier word big-endian (bit 31 EFF, bit 30
    RTR), payload length, FD flags, two reserved bytes, the data (8 bytes in a CAN_MTU frame)."""
    word = can_id | (0x80000000 if flags & EXT else 0) | (0x40000000 if flags & RTR else 0)
    return struct.pack(">IBBBB", word, dlc, 0, 0, 0) + bytes(data).ljust(8, b"\0")


def drain(b):
    return bytes(b.app.capture.drain_to(bytearray()))


# --- the firmware's records -------------------------------------------------------------------
def test_can_records_as_documented_in_both_engines():
    streams = []
    for engine in (C.put_py, native.cap_put):
        b, _bitrate = recording()
        b.app.capture.put = engine
        made = record_frames(b)
        stream = drain(b)
        streams.append(stream)
        i = 12 + stream[3]  # after the hello
        for _t, to_bus, (can_id, flags, dlc, data) in made:
            mark, typ, verdict, n, t0, t1 = struct.unpack_from("<BBBBII", stream, i)
            assert (mark, typ, verdict, t0) == (0xA5, 0x30 | to_bus, 0, t1)
            assert stream[i + 12:i + 12 + n] == struct.pack("<IBB", can_id, flags, dlc) + data
            i += 12 + n
        assert i == len(stream)
    assert streams[0][streams[0][3] + 12:] == streams[1][streams[1][3] + 12:]


def test_nothing_while_not_recording_and_a_full_ring_counts_lost():
    b, _bitrate = recording()
    cap = b.app.capture
    cap.stop()
    assert cap.can_frame(b.hal.ticks_us(), 0x705, 0, 1, b"\x05", 0) == 0 and cap.pending() == 0
    cap.start(b.hal.ticks_us())
    drain(b)
    n = 0
    while cap.can_frame(b.hal.ticks_us(), 0x185, 0, 8, bytes(8), 0):
        n += 1
    assert n == (C.RING_SIZE - 1) // (12 + 6 + 8) and cap.cs[C.CS_LOST] == 1
    cap.drain_to(bytearray())
    assert cap.can_frame(b.hal.ticks_us(), 0x185, 0, 0, b"", 1) == 1
    stream = drain(b)
    assert stream[1] == C.T_LOST and struct.unpack_from("<I", stream, 12)[0] == 1 and stream[17] == 0x31


def test_a_dlc_above_8_is_8_bytes():
    b, _bitrate = recording()
    drain(b)
    b.app.capture.can_frame(b.hal.ticks_us(), 0x205, 0, 15, bytes(range(8)), 1)
    stream = drain(b)
    assert stream[3] == 14 and stream[12:] == struct.pack("<IBB", 0x205, 0, 8) + bytes(range(8))


def test_the_hello_gives_the_can_bitrate_after_format_1s_fields():
    """Format 2's hello keeps format 1's first 20 bytes (so a format-1 reader knows it for a
    hello and refuses it by its version byte), then the CAN bitrate, then the name."""
    for bitrate in (BITRATE, 1000000, 0):
        b, got = recording(bitrate)
        data = drain(b)[12:]
        version, protocol, forward, slave, up, down, interbyte, ring, rate = struct.unpack_from("<BBBBIIIII", data)
        assert (version, protocol, forward, slave, interbyte, ring) == (2, 0, 0, 1, 5000, C.RING_SIZE)
        assert up in BAUD_RATES and down in BAUD_RATES and rate == got
        assert data[24:] == b"MotorJig bridge 0.1"


VM_CODE = """
import sys
sys.path.append('/data')
from bridge_probe import heap_used
from jig import capture as C
cap = C.Capture(None, None, 1024)
cap.cs[C.CS_ON] = 1
mv = memoryview(bytearray(8))
views = [mv[0:k] for k in range(9)]
def emptied(can_id, flags, dlc, view, to_bus):
    def one():
        cap.can_frame(1000, can_id, flags, dlc, view, to_bus)
        cap.cs[C.CS_TAIL] = cap.cs[C.CS_HEAD]
    return one
for one in (emptied(0x705, 0, 8, views[8], 0), emptied(0x1FFFFFFF, 1, 3, views[3], 1),
            emptied(0x1ABCDEF0, 3, 8, views[0], 1)):
    for _ in range(20):
        one()
    print(heap_used(one, 500))
def full():
    cap.can_frame(1000, 0x185, 0, 8, views[8], 0)
for _ in range(200):
    full()
print(cap.cs[C.CS_LOST] > 0, heap_used(full, 500))
print(sys.implementation.name)
"""


def test_can_frame_allocates_nothing_in_the_micropython_vm():
    """Standard, extended and RTR frames into the ring, and into a full one (counted lost):
    0 heap bytes each over 500 calls, in the real MicroPython VM (its portable engine)."""
    here = os.path.dirname(os.path.abspath(__file__))
    pkg = os.path.join(here, "wasm", "node_modules", "@micropython", "micropython-webassembly-pyscript")
    if shutil.which("node") is None or not os.path.isdir(pkg):
        pytest.skip("node or the MicroPython WebAssembly package is missing (tools/setup.sh)")
    r = subprocess.run(["node", os.path.join(here, "wasm", "run_vm.mjs"),
                        "--file", "bridge_probe.py=" + os.path.join(here, "bridge_probe.py"), VM_CODE],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["0", "0", "0", "True", "0", "micropython"]


# --- read back: Record, text, pcapng ----------------------------------------------------------
@pytest.mark.parametrize("step", [0, 1, 7])
def test_round_trip_firmware_to_record_to_pcapng(step):
    b, bitrate = recording()
    made = record_frames(b)
    recs, js = read_all(drain(b), EPOCH_US + b.t_hello, step)
    assert js.has_can and js.can_frames == len(made) == len(recs)
    for rec, (t, to_bus, (can_id, flags, dlc, data)) in zip(recs, made):
        assert rec.is_can and (rec.bus, rec.can_id, rec.can_flags, rec.can_dlc, rec.data) == (
            R.CAN_BUS, can_id, flags, dlc, data)
        assert rec.direction == (R.DIR_OUTBOUND if to_bus else R.DIR_INBOUND) and rec.verdict == R.GOOD
        assert rec.t_us == EPOCH_US + t
    buses = js.buses()
    assert [x.name for x in buses] == ["pc", "drivers", "can"]
    assert (buses[2].baud, buses[2].description) == (bitrate, "CAN bus, %d bit/s, jig test" % bitrate)
    out = io.BytesIO()
    w = pcapng.Writer(out, buses, hardware=js.description())
    for rec in recs:
        w.write(rec)
    f = parse_pcapng(out.getvalue())
    assert f["shb"][2].decode().endswith(", CAN bus %d bit/s" % bitrate)
    can_if = f["interfaces"][2]
    assert [i["linktype"] for i in f["interfaces"]] == [147, 148, 227]
    assert can_if["options"][2] == b"can" and can_if["options"][9] == b"\x06"
    assert struct.unpack("<Q", can_if["options"][8])[0] == bitrate
    assert len(f["packets"]) == len(made)
    for p, (t, to_bus, fr) in zip(f["packets"], made):
        assert (p["interface"], p["t_us"], p["caplen"], p["origlen"]) == (2, EPOCH_US + t, 16, 16)
        assert p["data"] == socketcan(*fr) and p["comments"] == [] and p["flags"] == (2 if to_bus else 1)


def test_without_a_can_port_a_capture_keeps_two_interfaces():
    b, _bitrate = recording(0)
    b.transact(F.encode(2, F.GET_COMMAND_POS))
    recs, js = read_all(drain(b), EPOCH_US + b.t_hello)
    assert not js.has_can and len(js.buses()) == 2 and "CAN" not in js.description()
    assert recs and all(not r.is_can for r in recs)


def test_the_live_view_prints_can_frames_like_candump():
    recs, js = read_all(hello(0, can=BITRATE) + b"".join([
        can(0, 0x705, b"\x05", 100), can(1, 0x000, b"\x01\x05", 200), can(1, 0x605, b"\x40\x41\x60\x00" + bytes(4), 300),
        can(0, 0x585, b"\x4b\x41\x60\x00\x37\x06\x00\x00", 400), can(0, 0x185, b"\x37\x06", 500),
        can(0, 0x085, b"\x10\x81\x11" + bytes(5), 600), can(1, 0x705, t=700, rtr=True, dlc=1),
        can(0, 0x18FF50E5, b"\x01\x02\x03", 800, ext=True), can(0, 0x7E4, b"\x50", 900)]))
    view = TextView(js.buses())
    lines = [view.line(r)[17:] for r in recs]  # after the time
    assert lines == [
        "can     in   705   [1]  05                          heartbeat node 5: operational",
        "can     out  000   [2]  01 05                       NMT start node 5",
        "can     out  605   [8]  40 41 60 00 00 00 00 00     SDO request node 5",
        "can     in   585   [8]  4B 41 60 00 37 06 00 00     SDO response node 5",
        "can     in   185   [2]  37 06                       TPDO1 node 5",
        "can     in   085   [8]  10 81 11 00 00 00 00 00     EMCY node 5",
        "can     out  705   [1]  remote request              heartbeat node 5",
        "can     in   18FF50E5   [3]  01 02 03",
        "can     in   7E4   [1]  50                          LSS response",
    ]
    d = view.as_dict(recs[7])
    assert d == {"t": (EPOCH_US + 800) / 1e6, "bus": "can", "dir": "in", "id": 0x18FF50E5, "ext": True, "rtr": False,
                 "dlc": 3, "data": "01 02 03"}
    assert view.as_dict(recs[0])["canopen"] == "heartbeat node 5: operational"
    assert canopen_name(0x000, 0, b"\x82\x00") == "NMT reset communication all nodes"
    assert canopen_name(0x080, 0, b"") == "SYNC" and canopen_name(0x700, 0, b"\x00") == ""


# --- versions and losing step -----------------------------------------------------------------
def test_format_3_is_refused_in_one_sentence():
    b, _bitrate = recording()
    stream = bytearray(drain(b))
    stream[12] = 3  # the hello's version byte
    with pytest.raises(J.StreamError) as exc:
        read_all(bytes(stream))
    assert str(exc.value) == ("the stream from test speaks record format 3; this jigctl reads formats 1 and 2 "
                              "(update motorjig)")


@pytest.mark.parametrize("bad, text", [
    (can(0, 0x800, b"\x01"), "a CAN record with identifier 0x800"),
    (can(0, 0x20000000, b"", ext=True), "a CAN record with identifier 0x20000000"),
    (can(0, 0x100, bytes(8), dlc=9), "a CAN record with flags 0x00 and DLC 9"),
    (raw(0x30, 0, struct.pack("<IBB", 0x100, 4, 0)), "a CAN record with flags 0x04 and DLC 0"),
    (can(0, 0x100, b"\x01\x02", dlc=3), "a CAN record of 8 bytes for DLC 3"),
    (raw(0x31, 0, struct.pack("<IBB", 0x100, RTR, 1) + b"\x01"), "a CAN record of 7 bytes for DLC 1"),
    (raw(0x31, 0, b"\x00" * 5), "a CAN record of 5 bytes (6 to 14)"),
    (raw(0x30, 1, struct.pack("<IBB", 0x100, 0, 0)), "a CAN record with verdict 1"),
    (raw(0x32, 0, struct.pack("<IBB", 0x100, 0, 0)), "unknown record type 0x32"),
])
def test_what_loses_step_on_the_can_channel(bad, text):
    with pytest.raises(J.StreamError) as exc:
        read_all(hello(0, can=BITRATE) + bad)
    assert text in str(exc.value)


def test_can_records_need_format_2_and_a_can_port():
    with pytest.raises(J.StreamError) as exc:
        read_all(hello(0, version=1) + can(0, 0x705, b"\x05"))
    assert "unknown record type 0x30" in str(exc.value)
    with pytest.raises(J.StreamError) as exc:
        read_all(hello(0, can=0) + can(0, 0x705, b"\x05"))
    assert "a CAN record from a jig whose hello says it has no CAN port" in str(exc.value)


# --- jigctl capture --jig, and tshark -----------------------------------------------------------
def bench_session():
    """A bench session through the jig: Plus-R transactions on both buses while the host,
    on the jig's SLCAN port, opens the CAN port and talks CANopen to a simulated CiA 402
    drive (node 5, heartbeat every 200 ms): NMT start, an SDO upload of 0x1000 (request
    and response), the drive's TPDOs as it goes operational, its EMCY on a fault, its
    heartbeats."""
    b = SimBench(can_nodes=(5,), can_bitrate=500000,
                 can_node_factory=lambda clock, bus, i: Cia402Node(clock, bus, i, heartbeat_ms=200))
    b.app.set_capture(1, b.hal.ticks_us())
    b.transact(F.encode(2, F.GET_COMMAND_POS))
    b.slcan_send(b"O\r")
    assert b.slcan_read(1).startswith(b"\r")
    b.slcan_send(b"t00020105\r")  # NMT start node 5
    b.transact(F.encode(1, F.GET_SLAVE_INFO))
    b.slcan_send(b"t60584000100000000000\r")  # SDO upload 0x1000:00 (device type)
    b.slcan_read(2)
    b.transact(F.encode(3, F.GET_AXIS_STATUS))
    b.run_for(250000)
    b.can_nodes[5].fault(0x2310, 0x02)  # overcurrent: EMCY
    b.run_for(250000)
    return drain(b)


@pytest.fixture(scope="module")
def session():
    return bench_session()


def _capture(session, tmp_path, *args):
    recs, _js = read_all(session)
    srv = JigServer(session)
    out = str(tmp_path / ("jig%d.pcapng" % len(args)))
    try:
        res = jigctl("capture", "--jig", srv.url, "-w", out, "--json", "--duration", "30", *args)
    finally:
        srv.close()
    assert res.returncode == 0 and "Traceback" not in res.stderr.decode(), res.stderr
    return recs, out, [json.loads(line) for line in res.stdout.decode().splitlines()]


def test_jigctl_capture_writes_the_can_bus_as_a_third_interface(session, tmp_path):
    recs, out, lines = _capture(session, tmp_path, "--count", str(len(read_all(session)[0])))
    summary = lines.pop()["summary"]
    n_can = sum(r.is_can for r in recs)
    assert n_can >= 8 and summary["verdicts"]["can"] == summary["can_frames"] == n_can
    assert summary["jig"]["can_bitrate"] == 500000
    assert [(d["bus"], d.get("id")) for d in lines] == [(("pc", "drivers", "can")[r.bus], r.can_id) for r in recs]
    with open(out, "rb") as f:
        p = parse_pcapng(f.read())
    assert [i["linktype"] for i in p["interfaces"]] == [147, 148, 227]
    assert [x["interface"] for x in p["packets"]] == [r.bus for r in recs]


def test_bus_keeps_the_buses_named(session, tmp_path):
    recs, _js = read_all(session)
    can_recs = [r for r in recs if r.is_can]
    recs, out, lines = _capture(session, tmp_path, "--bus", "can", "--count", str(len(can_recs)))
    summary = lines.pop()["summary"]
    assert summary["records"] == len(can_recs)
    assert [(d["bus"], d["dir"], d["id"], d["data"]) for d in lines] == [
        ("can", R.DIRECTION_NAMES[r.direction], r.can_id, r.data.hex(" ")) for r in can_recs]
    with open(out, "rb") as f:
        p = parse_pcapng(f.read())
    assert len(p["interfaces"]) == 3 and [x["interface"] for x in p["packets"]] == [2] * len(can_recs)
    plusr = [r for r in recs if not r.is_can]
    _recs, _out, lines = _capture(session, tmp_path, "--bus", "pc,drivers", "--count", str(len(plusr)))
    assert [(d["bus"], d["wire"]) for d in lines[:-1]] == [(("pc", "drivers")[r.bus], r.data.hex(" ")) for r in plusr]


def test_bus_can_refused_without_a_can_port():
    srv = JigServer(hello(0) + frame(C.CH_PC_IN, b"\x02\x51\xc1\x2c", 10, 600))
    try:
        res = jigctl("capture", "--jig", srv.url, "--bus", "can", "--duration", "5")
    finally:
        srv.close()
    err = res.stderr.decode().strip()
    assert res.returncode == 2 and "Traceback" not in err
    assert err == "jigctl: --bus can: the jig at %s has no CAN port (its hello gives no CAN bitrate)." % srv.url


@needs_tshark
def test_tshark_reads_canopen_on_the_can_interface_and_plusr_as_before(session, tmp_path):
    recs, out, _lines = _capture(session, tmp_path, "--count", str(len(read_all(session)[0])))
    names = ["frame.interface_name", "_ws.col.Protocol", "canopen.function_code", "canopen.node_id", "_ws.col.Info",
             "plusr.id", "plusr.type", "plusr.kind", "plusr.problem"]
    args = ["-r", out, "-2", "-d", "can.subdissector,canopen", "-T", "fields", "-E", "separator=\t",
            "-E", "occurrence=f"] + [a for n in names for a in ("-e", n)]
    res = run_tshark(args)
    assert res.returncode == 0 and "Lua" not in res.stderr.replace('Running as user "root"', ""), res.stderr
    rows = [dict(zip(names, line.split("\t"))) for line in res.stdout.splitlines()]
    assert len(rows) == len(recs)
    can_rows = [r for r in rows if r["frame.interface_name"] == "can"]
    assert len(can_rows) == sum(r.is_can for r in recs)
    assert {r["_ws.col.Protocol"] for r in can_rows} == {"CANopen"}
    infos = [r["_ws.col.Info"] for r in can_rows]
    for name in ("NMT: Start remote node [0x5]", "Default-SDO (rx): Initiate upload request",
                 "Default-SDO (tx): Initiate upload response", "PDO1 (tx)", "EMCY", "NMT Error Control: Boot-up [0x5]",
                 "NMT Error Control: Operational [0x5]"):
        assert any(i.startswith(name) for i in infos), (name, infos)
    assert infos.index("EMCY") > [i.startswith("NMT: Start") for i in infos].index(True)
    assert {r["canopen.node_id"] for r in can_rows if not r["_ws.col.Info"].startswith("NMT:")} == {"0x00000005"}
    # the Plus-R interfaces: what the same records without the CAN bus dissect to
    plain = str(tmp_path / "plain.pcapng")
    with open(plain, "wb") as f:
        w = pcapng.Writer(f, read_all(session)[1].buses()[:2])
        for rec in recs:
            if not rec.is_can:
                w.write(rec)
    res2 = run_tshark(["-r", plain] + args[2:])
    assert res2.returncode == 0, res2.stderr
    before = [dict(zip(names, line.split("\t"))) for line in res2.stdout.splitlines()]
    plusr_rows = [r for r in rows if r["frame.interface_name"] != "can"]
    assert len(plusr_rows) == len(before) and {r["_ws.col.Protocol"] for r in before} == {"Plus-R"}
    strip = ("frame.interface_name", "plusr.id", "plusr.type", "plusr.kind", "plusr.problem", "_ws.col.Info")
    assert [[r[k] for k in strip] for r in plusr_rows] == [[r[k] for k in strip] for r in before]
    assert LUA.endswith("plusr.lua")
