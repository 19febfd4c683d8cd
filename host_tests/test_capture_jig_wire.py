"""The jig's records against the wire: the real firmware on the bench records both buses,
a listen-only tap on each bus hears every byte, and the two must agree.

* Bytes: every record's rebuilt wire bytes against the records the firmware's parser
  (``jig.parser`` through ``motorjig.capture.framer``) cuts from what the tap heard,
  for every verdict; the jig's noise counts against the noise bytes.
* Times: every whole frame's start and end against the tap's (the bench's CPU is
  infinitely fast, so a received frame's read is its arrival), across the tick wrap.
* Wireshark: the stream written as pcapng and dissected by tshark with plusr.lua:
  requests paired to replies on both buses, ``plusr.turnaround`` (the simulated
  drives answer 300 µs after a request's end), the jig's verdicts, lost records.
"""

import struct

import pytest

from test_capture_jig_support import EPOCH_US, BenchCapture, fill_ring, scenario
from test_capture_support import dissect, needs_tshark, num, one, parse_pcapng, run_tshark

from jig import frame as F
from jig import params as P

from motorjig.capture import pcapng
from motorjig.capture import record as R
from motorjig.capture.framer import Framer
from motorjig.sim.link import flip_for_crc

WHOLE = (R.GOOD, R.BAD_CRC, R.SHORT)
DE_PRE_US = P.TABLE[P.P_DE_PRE_US][5]  # its default
#: the dissector's plusr.problem for each verdict of a jig record
PROBLEM = {R.GOOD: 0, R.BAD_CRC: 1, R.BAD_STUFFING: 2, R.SHORT: 3, R.OVERLONG: 4, R.NOISE: 7, R.TIMEOUT: 9,
           R.RESYNC: 9, R.LOST: 10}
EXPERT = {R.BAD_CRC: "plusr.crc.bad", R.BAD_STUFFING: "plusr.bad_stuffing", R.SHORT: "plusr.short",
          R.OVERLONG: "plusr.overlong", R.NOISE: "plusr.no_header", R.TIMEOUT: "plusr.no_tail",
          R.RESYNC: "plusr.no_tail", R.LOST: "plusr.lost.records"}


def broken(cap):
    """The PC sends one frame of every verdict (and the good ones are answered)."""
    b = cap.bench
    sends = [
        F.encode(2, F.GET_AXIS_STATUS),  # good, and its reply
        flip_for_crc(F.encode(3, F.GET_AXIS_STATUS)),  # bad CRC
        bytes.fromhex("AA CC 02 AA EE"),  # short
        bytes.fromhex("AA CC 02 51 AA 11"),  # 0xAA then 0x11: stuffing error
        b"\xaa\xcc" + b"\x02" * 300 + b"\xaa\xee",  # overlong, then noise
        bytes.fromhex("AA CC 02 51"),  # silence: timeout
        bytes.fromhex("AA CC 03 40") + F.encode(3, F.GET_AXIS_STATUS),  # a new header: resync, then good
    ]
    for wire in sends:
        b.send(wire)
        cap.run(30000)
    return cap


def host_records(cap, bus):
    """What the firmware's parser makes of the tap's bytes (the Framer, the jig's settings)."""
    fr = Framer(bus=bus, byte_us=(cap.bench.up_bus if bus == 0 else cap.bench.down_bus).bt,
                interbyte_timeout_us=5000, ver8=False)
    out = []
    for t, data in cap.taps[bus]:
        out += fr.feed(data, EPOCH_US + t)
    out += fr.check_timeout(EPOCH_US + cap.bench.clock.now) + fr.flush()
    return out


def same_bytes(jig, host):
    """The jig keeps neither the byte after a stuffing error's 0xAA nor the one that overflowed."""
    if jig.verdict != host.verdict:
        return False
    if jig.verdict in (R.BAD_STUFFING, R.OVERLONG):
        return jig.data == host.data[:-1]
    return jig.data == host.data


@pytest.mark.parametrize("fastpath", [False, True], ids=["portable", "fastpath"])
def test_wire_bytes_of_every_verdict_are_what_the_parser_saw(fastpath):
    cap = broken(BenchCapture(fastpath=fastpath))
    recs, js = cap.records()
    assert {r.verdict for r in recs} >= {R.GOOD, R.BAD_CRC, R.SHORT, R.BAD_STUFFING, R.OVERLONG, R.TIMEOUT, R.RESYNC,
                                         R.NOISE}
    # The PC bus: the jig's parser heard exactly what the tap heard (the jig's own replies
    # are its records too), so the records agree one to one.
    mine = sorted((r for r in recs if r.bus == 0 and r.count is None), key=lambda r: r.t_first_us)
    host = [r for r in host_records(cap, 0) if r.verdict != R.NOISE]
    assert len(mine) == len(host)
    for m, h in zip(mine, host):
        assert same_bytes(m, h), (m, h)
    host_noise = sum(len(r.data) for r in host_records(cap, 0) if r.verdict == R.NOISE)
    assert js.noise[0] == host_noise == 48  # the 46 bytes after the overflow, and the AA EE
    # The driver bus: whatever the jig sent or received is on it, in order (what it passed on
    # of a broken frame may be cut differently by a listener: it skips what it must).
    mine = sorted((r for r in recs if r.bus == 1 and r.count is None), key=lambda r: r.t_first_us)
    host = iter(host_records(cap, 1))
    for m in mine:
        assert any(same_bytes(m, h) for h in host), m


def _locate(wire, data, near):
    """(start, end) of the occurrence of data among the tap's bytes nearest to ``near``."""
    stream = bytes(b for b, _s, _e in wire)
    best = None
    i = stream.find(data)
    while i >= 0:
        start, end = wire[i][1], wire[i + len(data) - 1][2]
        if best is None or abs(start - near) < abs(best[0] - near):
            best = (start, end)
        i = stream.find(data, i + 1)
    assert best is not None, data.hex(" ")
    return best


@pytest.mark.parametrize("fastpath", [False, True], ids=["portable", "fastpath"])
def test_times_are_the_wire_times(fastpath):
    cap = scenario(BenchCapture(fastpath=fastpath))
    recs, _js = cap.records()
    checked = 0
    for r in recs:
        if r.verdict not in WHOLE:
            continue
        start, end = _locate(cap.wire(r.bus), r.data, r.t_first_us - EPOCH_US)
        # ticks are whole µs of the bench's clock; the start of a received frame is computed
        assert abs(r.t_us - EPOCH_US - end) <= 2, (r, start, end)
        if r.direction == R.DIR_INBOUND:
            assert abs(r.t_first_us - EPOCH_US - start) <= 2, (r, start, end)
        else:
            # handed to the transmitter; a frame sent whole starts after DE's pre-delay
            # (de_pre_us, 10 µs), one passed on from its header while its CC arrived
            assert -2 <= start - (r.t_first_us - EPOCH_US) <= DE_PRE_US + 2, (r, start, end)
        checked += 1
    assert checked >= 20 and max(r.t_us for r in recs) - EPOCH_US > (1 << 30)  # past the tick wrap


def _pcapng(cap, path):
    recs, js = cap.records()
    with open(path, "wb") as f:
        w = pcapng.Writer(f, js.buses("bench"), hardware=js.description())
        for r in recs:
            w.write(r)
    return recs, js


def test_pcapng_of_the_jig_records(tmp_path):
    path = str(tmp_path / "jig.pcapng")
    recs, js = _pcapng(scenario(BenchCapture()), path)
    f = parse_pcapng(open(path, "rb").read())
    assert [i["linktype"] for i in f["interfaces"]] == [147, 148]
    assert [i["options"][3].decode() for i in f["interfaces"]] == [
        "PC bus, 115200 baud, jig bench", "driver bus, 115200 baud, jig bench"]
    assert f["shb"][2].decode().startswith("MotorJig bridge 0.1 (record format 2")
    for rec, p in zip(recs, f["packets"]):
        assert (p["interface"], p["t_us"], p["data"]) == (rec.bus, rec.t_us, rec.data)
        assert p["comments"][0] == R.comment(rec.verdict)
        if rec.count is not None:
            assert p["comments"][1] == "jig: " + R.count_text(rec) and p["data"] == b""
        else:
            assert p["comments"][1].startswith("start: %d us before the end" % (rec.t_us - rec.t_first_us))
        assert (p["flags"] or 0) & 3 == rec.direction


@needs_tshark
def test_tshark_pairs_both_buses_and_gives_the_turnaround(tmp_path):
    path = str(tmp_path / "jig.pcapng")
    recs, _js = _pcapng(scenario(BenchCapture(turnaround_us=300.0)), path)
    p = dissect(path)
    assert len(p) == len(recs)
    replies = 0
    for i, (rec, x) in enumerate(zip(recs, p)):
        where = "packet %d %s" % (i + 1, rec)
        assert num(x, "plusr.problem") == PROBLEM[rec.verdict], where
        assert one(x, "plusr.verdict") == R.verdict_name(rec.verdict), where
        if rec.verdict != R.GOOD:
            assert EXPERT[rec.verdict] in x, where
            continue
        kind = num(x, "plusr.kind")
        requests_in = rec.bus == 0  # the jig: a slave on the PC bus, the master on the driver bus
        assert kind == (0 if (rec.direction == R.DIR_INBOUND) == requests_in else 1), where
        if kind != 1:
            continue
        req_no = num(x, "plusr.request_in")
        assert req_no is not None, where
        req = recs[req_no - 1]
        assert req.bus == rec.bus and req.direction != rec.direction, where
        assert num(p[req_no - 1], "plusr.response_in") == i + 1, where
        assert round(float(one(x, "plusr.time")) * 1e6) == rec.t_us - req.t_us, where
        turn = round(float(one(x, "plusr.turnaround")) * 1e6)
        assert turn == rec.t_first_us - req.t_us, where
        if rec.bus == 1:
            assert abs(turn - 300) <= 2, where  # the simulated drive's turnaround
        replies += 1
    # the four answered by a drive with a good frame, on both buses; the jig's own on the PC bus
    assert replies == 2 * 4 + 1
    bad = [x for x in p if num(x, "plusr.problem") == 1]
    assert sorted(one(x, "frame.interface_name") for x in bad) == ["drivers", "drivers", "pc", "pc"]
    rows = run_tshark(["-r", path, "-2", "-T", "fields", "-e", "frame.number", "-Y",
                       "plusr.turnaround > 0.0005 && frame.interface_name == \"drivers\""]).stdout.split()
    assert rows == []  # the drives are quick


@needs_tshark
def test_tshark_names_every_verdict_of_the_jig(tmp_path):
    path = str(tmp_path / "broken.pcapng")
    recs, _js = _pcapng(broken(BenchCapture()), path)
    p = dissect(path)
    seen = set()
    for rec, x in zip(recs, p):
        assert num(x, "plusr.problem") == PROBLEM[rec.verdict], rec
        if rec.verdict != R.GOOD:
            assert EXPERT[rec.verdict] in x, rec
        seen.add(rec.verdict)
    assert seen >= {R.GOOD, R.BAD_CRC, R.SHORT, R.BAD_STUFFING, R.OVERLONG, R.TIMEOUT, R.RESYNC, R.NOISE}
    noise = [x for x in p if num(x, "plusr.problem") == 7]
    # reported as the slow pass finds them (the overlong frame's rest arrives over 4 ms)
    assert sum(num(x, "plusr.noise_bytes") for x in noise) == 48 and all(
        num(x, "plusr.noise_bytes") > 0 for x in noise)
    msgs = [m for x in p for m in x.get("expert_messages", [])]
    assert any("the jig keeps the body up to its limit" in m for m in msgs)
    assert any("the jig keeps the body only" in m for m in msgs)
    assert any("inter-byte timeout" in m for m in msgs)


@needs_tshark
def test_tshark_reports_lost_records(tmp_path):
    cap = BenchCapture()
    fill_ring(cap)
    cap.drain()
    cap.bench.request(2, F.SET_PARAMETER, struct.pack("<Bi", 1, 5000))
    cap.drain()
    path = str(tmp_path / "lost.pcapng")
    recs, js = _pcapng(cap, path)
    p = dissect(path)
    lost = [(i, x) for i, x in enumerate(p) if "plusr.lost" in x]
    assert len(lost) == 1 and recs[lost[0][0]].verdict == R.LOST
    x = lost[0][1]
    assert num(x, "plusr.lost") == js.lost > 0 and num(x, "plusr.problem") == 10
    assert "plusr.lost.records" in x
    warn = run_tshark(["-r", path, "-q", "-z", "expert,warn"]).stdout
    assert "The jig lost %d records here" % js.lost in warn
