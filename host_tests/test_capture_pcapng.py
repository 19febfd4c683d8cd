"""The pcapng writer, read back by the tests' own reader (written from the specification):
block types and lengths, interfaces, timestamps, bytes, comments, flags, rotation."""

import os
import re
import struct

import pytest

from test_capture_support import (CAPTURES, EPOCH_US, capture_records, load, needs_tshark, parse_pcapng,
                                  read_blocks, run_tshark, write_pcapng)

from jig import frame as F
from motorjig.capture import pcapng
from motorjig.capture import record as R


@pytest.mark.parametrize("path", CAPTURES, ids=os.path.basename)
def test_capture_file_layout(path, tmp_path):
    recs, rest = capture_records(load(path))
    recs += rest
    out = write_pcapng(str(tmp_path / "c.pcapng"), recs)
    data = open(out, "rb").read()
    kinds = [b.kind for b in read_blocks(data)]
    assert kinds == [0x0A0D0D0A, 1] + [6] * len(recs)
    f = parse_pcapng(data)
    assert f["shb"][4].decode().startswith("MotorJig jigctl capture")
    (iface,) = f["interfaces"]
    assert iface["linktype"] == 147 and iface["snaplen"] == 0
    assert iface["options"][2] == b"pc" and iface["options"][3] == b"PC bus, 115200 baud"
    assert iface["options"][9] == b"\x06"  # µs
    assert struct.unpack("<Q", iface["options"][8]) == (115200,)
    for rec, pkt in zip(recs, f["packets"]):
        assert pkt["interface"] == 0 and pkt["t_us"] == rec.t_us
        assert pkt["data"] == rec.data and pkt["caplen"] == pkt["origlen"] == len(rec.data)
        assert pkt["comments"] == [R.comment(rec.verdict)]
        assert pkt["flags"] == (pcapng.VERDICT_FLAGS[rec.verdict] if rec.verdict in pcapng.VERDICT_FLAGS else None)


def test_two_buses_and_directions(tmp_path):
    buses = [R.pc_bus(115200, "jig"), R.driver_bus(921600, "jig")]
    wire = F.encode(2, F.GET_AXIS_STATUS)
    recs = [R.Record(0, EPOCH_US + 1, R.DIR_INBOUND, wire, R.GOOD),
            R.Record(1, EPOCH_US + 2, R.DIR_OUTBOUND, wire, R.GOOD),
            R.Record(1, (1 << 32) + 5, R.DIR_INBOUND, b"\xaa\xcc\x02", R.TIMEOUT)]
    f = parse_pcapng(open(write_pcapng(str(tmp_path / "two.pcapng"), recs, buses), "rb").read())
    assert [i["linktype"] for i in f["interfaces"]] == [147, 148]
    assert [i["options"][2] for i in f["interfaces"]] == [b"pc", b"drivers"]
    assert f["interfaces"][1]["options"][3] == b"driver bus, 921600 baud, jig"
    assert [(p["interface"], p["flags"]) for p in f["packets"]] == [
        (0, 1), (1, 2), (1, 1 | pcapng.FLAG_INTERFRAME_GAP)]
    assert f["packets"][2]["t_us"] == (1 << 32) + 5


def test_a_record_for_a_missing_bus_is_refused(tmp_path):
    with open(str(tmp_path / "x.pcapng"), "wb") as f:
        w = pcapng.Writer(f, [R.pc_bus(9600)])
        with pytest.raises(ValueError):
            w.write(R.Record(1, 0, 0, b"\x00", R.NOISE))


def test_rotation_keeps_the_newest_files(tmp_path):
    path = str(tmp_path / "bus.pcapng")
    w = pcapng.RotatingWriter(path, [R.pc_bus(115200)], max_size=1024, files=2)
    frame = bytes.fromhex("AA CC 01 01 C1 E0 AA EE")
    for i in range(100):
        w.write(R.Record(0, EPOCH_US + i, R.DIR_UNKNOWN, frame, R.GOOD))
    w.close()
    assert w.index > 3
    names = sorted(os.listdir(str(tmp_path)))
    assert names == [os.path.basename(n) for n in w.written]
    assert [re.fullmatch(r"bus_(\d{5})_\d{14}\.pcapng", n).group(1) for n in names] == [
        "%05d" % (w.index - 1), "%05d" % w.index]
    times = []
    for name in names:
        data = open(str(tmp_path / name), "rb").read()
        assert len(data) <= 1024
        f = parse_pcapng(data)
        assert len(f["interfaces"]) == 1
        times += [p["t_us"] - EPOCH_US for p in f["packets"]]
    assert times == list(range(100 - len(times), 100))


def test_a_second_run_goes_on_numbering_and_keeps_the_first_run_s_files(tmp_path):
    path = str(tmp_path / "bus.pcapng")
    frame = bytes.fromhex("AA CC 01 01 C1 E0 AA EE")
    runs = []
    for run in range(2):
        w = pcapng.RotatingWriter(path, [R.pc_bus(115200)], max_size=1024, files=3)
        for i in range(60):
            w.write(R.Record(0, EPOCH_US + i, R.DIR_UNKNOWN, frame, R.GOOD))
        w.close()
        runs.append(list(w.written))
    first, second = runs
    assert len(first) == len(second) == 3
    number = lambda n: int(os.path.basename(n).split("_")[1])  # noqa: E731
    assert min(map(number, second)) > max(map(number, first))  # after the first run's highest
    assert [number(n) for n in second] == list(range(number(second[0]), number(second[0]) + 3))
    assert sorted(os.listdir(str(tmp_path))) == sorted(os.path.basename(n) for n in first + second)
    (tmp_path / "bus_00900.pcapng").write_bytes(b"")  # an old-style name counts too
    assert pcapng.highest_ring_index(path) == 900
    assert pcapng.highest_ring_index(str(tmp_path / "other.pcapng")) == 0


def test_rotation_never_splits_a_packet(tmp_path):
    path = str(tmp_path / "big.pcapng")
    w = pcapng.RotatingWriter(path, [R.pc_bus(115200)], max_size=1024)
    for i in range(3):
        w.write(R.Record(0, i, R.DIR_UNKNOWN, b"\x00" * 2000, R.NOISE))
    w.close()
    assert [len(parse_pcapng(open(n, "rb").read())["packets"]) for n in w.written] == [1, 1, 1]


@needs_tshark
def test_tshark_reads_rotated_files_and_interfaces(tmp_path):
    path = str(tmp_path / "bus.pcapng")
    w = pcapng.RotatingWriter(path, [R.pc_bus(115200), R.driver_bus(115200)], max_size=2000)
    for i in range(40):
        w.write(R.Record(i % 2, EPOCH_US + 1000 * i, R.DIR_INBOUND, F.encode(2, F.GET_AXIS_STATUS), R.GOOD))
    w.close()
    total = 0
    for name in w.written:
        res = run_tshark(["-r", name, "-T", "fields", "-e", "frame.interface_name", "-e", "frame.interface_description",
                          "-e", "frame.time_epoch", "-e", "plusr.kind"])
        assert res.returncode == 0, res.stderr
        rows = [line.split("\t") for line in res.stdout.splitlines()]
        total += len(rows)
        for name_, desc, _t, kind in rows:
            assert (name_, desc, kind) in (("pc", "PC bus, 115200 baud", "0"), ("drivers", "driver bus, 115200 baud", "1"))
    assert total == 40


def test_flush_each_flushes_the_header(tmp_path):
    """A pipe (-w -, an extcap's fifo) gets the section and interface headers at once,
    before any packet: a quiet bus must not leave the reader waiting for them."""
    path = str(tmp_path / "h.pcapng")
    with open(path, "wb") as f:  # buffered: nothing reaches the file unless flushed
        w = pcapng.Writer(f, [R.make_bus("pc", 115200, "x"), R.make_bus("drivers", 115200, "x")], flush_each=True)
        got = parse_pcapng(open(path, "rb").read())
        assert len(got["interfaces"]) == 2 and got["packets"] == [] and os.path.getsize(path) == w.size
