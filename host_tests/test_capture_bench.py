"""The jig's recording of both buses on the virtual bench (issue 19).

The bench's capture port (``SimHAL.capture``): the HAL contract (never blocks,
takes what fits in a USB CDC's 1 KB transmit buffer, nothing while closed), the
record stream the real firmware writes to it with the bench's virtual-time ticks,
a closed port (the jig's ring fills and counts lost records), and the real-time
``Bench`` serving the stream on its own TCP port and pty to one reader at a time.
The records are read here by the test's own reader of the documented format
(firmware/jig/capture.py), not by the host tools.
"""

import os
import select
import socket
import struct
import time

import pytest
import serial

from jig import frame as F
from jig.capture import CS_LOST_TOTAL
from motorjig.sim import Bench, SimBench
from motorjig.sim import __main__ as sim_main
from motorjig.sim.hal import CDC_TX_SIZE
from test_capture_support import dissect, installed, needs_tshark  # noqa: F401 (installed: a fixture)

MASK = 0x3FFFFFFF
HELLO, LOST, CLOCK = 0x10, 0x11, 0x12
PC_IN, PC_OUT, DRV_IN, DRV_OUT = 0, 1, 2, 3
PASSED = 4  # | the channel it came in on: received and passed on to the other bus (cut through)


class Rec(tuple):
    """(type, verdict, t_first, t_end, data, passed) of one record (passed: half of a
    passed-on frame's record)."""

    type = property(lambda self: self[0])
    verdict = property(lambda self: self[1])
    t_first = property(lambda self: self[2])
    t_end = property(lambda self: self[3])
    data = property(lambda self: self[4])
    passed = property(lambda self: self[5])


def records(stream, whole=True):
    """The records of a capture stream: 0xA5, type, verdict, n, u32 t_first, u32 t_end, (a frame
    passed on: u32 t_first, u32 t_end on the other bus,) n bytes. A passed-on frame comes back as
    two records, received and sent. whole: the stream must end at a record's end."""
    out = []
    i = 0
    while i + 12 <= len(stream):
        assert stream[i] == 0xA5, "no record mark at offset %d: %s" % (i, stream[i:i + 16].hex(" "))
        typ, verdict, n = stream[i + 1], stream[i + 2], stream[i + 3]
        head = 20 if typ in (PASSED | PC_IN, PASSED | DRV_IN) else 12
        if i + head + n > len(stream):
            break
        data = bytes(stream[i + head:i + head + n])
        t0, t1 = struct.unpack_from("<II", stream, i + 4)
        if head == 20:
            ch = typ & 3
            u0, u1 = struct.unpack_from("<II", stream, i + 12)
            out.append(Rec((ch, verdict, t0, t1, data, True)))
            out.append(Rec((ch ^ 3, verdict, u0, u1, data, True)))
        else:
            out.append(Rec((typ, verdict, t0, t1, data, False)))
        i += head + n
    if whole:
        assert i == len(stream), "%d bytes after the last whole record" % (len(stream) - i)
    return out


def body(wire):
    """The unstuffed body (CRC included) of one frame's wire bytes."""
    assert wire[:2] == b"\xaa\xcc" and wire[-2:] == b"\xaa\xee"
    return wire[2:-2].replace(b"\xaa\xaa", b"\xaa")


def frames(recs):
    return [r for r in recs if r.type < 4]


# --- the port ------------------------------------------------------------------------
def test_port_takes_nothing_while_closed_and_what_fits_when_open():
    b = SimBench(driver_ids=(2,))
    port = b.capture
    assert not port.is_open and port.write(b"x" * 10) == 0  # no host: a closed CDC port takes nothing
    port.host_send(b"S")
    assert port.any() == 0  # nobody can send on a closed port either
    port.host_open()
    assert port.write(bytes(1000)) == 1000
    assert port.write(memoryview(bytes(range(100)))) == CDC_TX_SIZE - 1000  # what fits, at once
    assert port.write(b"y") == 0
    assert port.host_read() == b""  # nothing before the next USB frame
    b.run_for(1000.0)  # one 1 ms frame
    got = port.host_read()
    assert got == bytes(1000) + bytes(range(24))
    assert port.write(b"z" * 5) == 5
    port.host_close()  # the host closes: the buffer's bytes go with it
    assert port.write(b"w") == 0
    b.run_for(5000.0)
    assert port.host_read() == b""
    port.host_open()
    port.host_send(b"SX")
    assert port.any() == 2
    buf = bytearray(1)
    assert port.readinto(buf) == 1 and buf == b"S" and port.any() == 1
    buf = bytearray(4)
    assert port.readinto(buf) == 1 and buf[0:1] == b"X" and port.readinto(buf) == 0


def test_nothing_is_recorded_until_the_host_asks():
    b = SimBench(driver_ids=(2,))
    b.request(2, F.GET_COMMAND_POS)
    assert not b.app.capture.on and b.capture.taken == 0
    b.capture.host_open()
    b.run_for(50000.0)
    assert b.capture_read() == b""  # open, but no S: the jig records nothing


# --- the stream ----------------------------------------------------------------------
def test_a_transaction_is_four_records_stamped_with_the_bench_clock():
    b = SimBench(driver_ids=(2, 3))
    assert b.capture_start()
    req = b.encode(2, F.GET_COMMAND_POS)
    t_req_end = b.send(req)
    b.run_for(5000.0)
    reply = b.pc.frames[-1][1]
    recs = records(b.capture_read())
    assert recs[0].type == HELLO and recs[0].data[0] == 2  # format version 2 first
    assert b"MotorJig bridge" in recs[0].data
    got = frames(recs)
    assert [r.type for r in got] == [PC_IN, DRV_OUT, DRV_IN, PC_OUT]
    assert all(r.verdict == 0 for r in got)
    assert got[0].data == got[1].data == body(req)  # forwarded unchanged
    assert got[2].data == got[3].data == body(reply)  # relayed unchanged
    bt = b.up_bus.bt  # one character time
    # The ticks are the bench's virtual clock (which crosses the 2**30 wrap in every test).
    assert got[0].t_end == int(t_req_end) & MASK
    for r in got:
        assert (r.t_end - r.t_first) & MASK < len(F.encode(2, F.GET_COMMAND_POS, bytes(5))) * bt + 1
    # cut through: the jig's copy ends a character after the PC's frame (its AA went on at
    # once: the jig must have a byte before it can send it; DE went up at its start bit, so
    # the pre-delay, 10 us < a character, ran while it arrived)
    assert b.app.params.ram[6] < bt  # (6: de_pre_us)
    assert abs(((got[1].t_end - got[0].t_end) & MASK) - bt) <= 1
    d = b.drivers[2]
    answer = (got[2].t_first - got[1].t_end) & MASK  # request sent .. reply's header read
    assert d.turnaround_us <= answer <= d.turnaround_us + 2 * bt + 1


def test_a_closed_port_fills_the_ring_and_the_stream_says_what_was_lost():
    b = SimBench(driver_ids=(2,))
    assert b.capture_start()
    b.capture_read()
    b.capture.host_close()  # e.g. the reader went away
    n = 400  # 53 bytes of records each: more than the 16 KB ring holds
    for _ in range(n):
        wire, data = b.request(2, F.GET_COMMAND_POS)
        assert data == b"\x00" + bytes(4)  # recording never stalls the bridge
    lost = b.app.capture.cs[CS_LOST_TOTAL]
    assert lost > 0 and b.app.capture.on
    b.capture.host_open()  # a reader again, without S: the ring as it was, then the loss
    recs = records(b.capture_read())
    assert LOST not in [r.type for r in recs]  # said with the next record that fits
    b.request(2, F.GET_COMMAND_POS)
    recs += records(b.capture_read())
    kept = frames(recs)  # cut through: one ring record per frame passed on, both buses in it
    assert all(r.passed for r in kept) and len(kept) // 2 + lost == 2 * (n + 1)
    losts = [r for r in recs if r.type == LOST]
    assert len(losts) == 1 and struct.unpack("<I", losts[0].data)[0] == lost
    i = recs.index(losts[0])
    assert [r.type for r in recs[i + 1:] if r.type < 4] == [PC_IN, DRV_OUT, DRV_IN, PC_OUT]


def test_s_while_recording_starts_afresh():
    """A new reader after one that went away without X: its S empties the ring and a
    hello comes first (jig.capture's S command)."""
    b = SimBench(driver_ids=(2,))
    assert b.capture_start()
    b.capture.host_close()
    b.request(2, F.GET_COMMAND_POS)
    b.capture.host_open()
    b.capture.host_send(b"S")
    b.run_for(20000.0)
    b.request(2, F.GET_COMMAND_POS)
    recs = records(b.capture_read())
    assert recs[0].type == HELLO and len(frames(recs)) == 4


def test_stop_ends_the_recording():
    b = SimBench(driver_ids=(2,))
    b.capture_start()
    b.request(2, F.GET_COMMAND_POS)
    recs = records(b.capture_stop())
    assert len(frames(recs)) == 4 and not b.app.capture.on
    b.request(2, F.GET_COMMAND_POS)
    b.run_for(50000.0)
    assert b.capture_read() == b""


# --- the real-time bench ------------------------------------------------------------------
def read_records(recv, want, timeout=5.0):
    """Bytes from recv() until the records of the stream include ``want`` frame records."""
    data = b""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        chunk = recv()
        if chunk:
            data += chunk
            if len(frames(records(data, whole=False))) >= want:
                return records(data, whole=False)
    raise AssertionError("only %d bytes of records within %g s" % (len(data), timeout))


def ask(ser, slave, ftype):
    ser.write(F.encode(slave, ftype))
    out = b""
    end = time.monotonic() + 2.0
    while not out.endswith(b"\xaa\xee") and time.monotonic() < end:
        out += ser.read(64)
    assert out.endswith(b"\xaa\xee"), "no reply from slave %d" % slave
    return out


def wait_until(pred, timeout=3.0, what="condition"):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return
        time.sleep(0.02)
    raise AssertionError("timed out waiting for " + what)


@pytest.fixture(scope="module")
def bench():
    with Bench(driver_ids=(2, 3)) as b:
        yield b


def tcp_reader(url):
    host, port = url[len("socket://"):].rsplit(":", 1)
    s = socket.create_connection((host, int(port)), timeout=2.0)
    s.settimeout(0.2)
    return s


def recv_or_empty(sock):
    try:
        return sock.recv(65536)
    except socket.timeout:
        return None


def test_bench_serves_the_stream_to_one_tcp_reader_at_a_time(bench):
    assert bench.capture_url.startswith("socket://127.0.0.1:") and bench.capture_url != bench.tcp_url
    first = tcp_reader(bench.capture_url)
    wait_until(lambda: bench.sim.capture.is_open, what="the port opened by the reader")
    second = tcp_reader(bench.capture_url)
    second.settimeout(3.0)
    assert second.recv(100) == b""  # closed at once: one reader at a time
    second.close()
    first.sendall(b"S")
    wait_until(lambda: bench.sim.app.capture.on, what="S read by the jig (its slow pass: within 10 ms)")
    with serial.serial_for_url(bench.tcp_url, timeout=0.1) as pc:
        reply = ask(pc, 2, F.GET_COMMAND_POS)
        recs = read_records(lambda: recv_or_empty(first), 4)
    assert recs[0].type == HELLO
    got = frames(recs)
    assert [r.type for r in got[:4]] == [PC_IN, DRV_OUT, DRV_IN, PC_OUT]
    assert got[0].data == body(F.encode(2, F.GET_COMMAND_POS)) and got[3].data == body(reply)
    first.close()  # the reader leaves: the port is closed, the jig records into its ring
    wait_until(lambda: not bench.sim.capture.is_open, what="the port closed with the reader")
    assert bench.sim.app.capture.on
    again = tcp_reader(bench.capture_url)  # the next reader is welcome
    wait_until(lambda: bench.sim.capture.is_open, what="a reader again")
    again.sendall(b"X")
    wait_until(lambda: not bench.sim.app.capture.on, what="X stops the recording")
    again.close()
    wait_until(lambda: not bench.sim.capture.is_open, what="closed")


def test_bench_serves_the_stream_on_a_pty(bench):
    path = bench.capture_pty_path
    assert path and os.path.exists(path) and path != bench.pty_path
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        wait_until(lambda: bench.sim.capture.is_open, what="the pty opened")
        sock = tcp_reader(bench.capture_url)  # the pty is the reader now: a TCP client is refused
        sock.settimeout(3.0)
        assert sock.recv(100) == b""
        sock.close()
        os.write(fd, b"S")
        wait_until(lambda: bench.sim.app.capture.on, what="S read by the jig")

        def from_pty():
            r, _, _ = select.select([fd], [], [], 0.2)
            return os.read(fd, 65536) if r else None

        with serial.serial_for_url(bench.tcp_url, timeout=0.1) as pc:
            ask(pc, 3, F.GET_COMMAND_POS)
            recs = read_records(from_pty, 4)
        assert recs[0].type == HELLO
        assert [r.type for r in frames(recs)[:4]] == [PC_IN, DRV_OUT, DRV_IN, PC_OUT]
        os.write(fd, b"X")
        wait_until(lambda: not bench.sim.app.capture.on, what="X stops the recording")
    finally:
        os.close(fd)
    wait_until(lambda: not bench.sim.capture.is_open, what="the pty closed")


def test_python_m_motorjig_sim_prints_the_capture_port(capsys):
    port = sim_main.parse_args(["--capture-port", "0"]).capture_port
    assert port == 0
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    free = s.getsockname()[1]
    s.close()
    rc = sim_main.main(["--no-demo", "--duration", "0.1", "--capture-port", str(free)])
    out = capsys.readouterr().out
    assert rc == 0
    assert "  capture: socket://127.0.0.1:%d\n" % free in out
    assert "  capture pty: /dev/pts/" in out
    rc = sim_main.main(["--no-demo", "--no-pty", "--duration", "0.1"])
    out = capsys.readouterr().out
    assert rc == 0 and "  capture: socket://127.0.0.1:" in out and "capture pty" not in out


def test_capture_port_options_and_errors(capsys):
    with pytest.raises(SystemExit):
        sim_main.parse_args(["--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "--capture-port N" in help_text and "capture stream" in help_text
    assert sim_main.main(["--capture-port", "70000"]) == 2
    assert capsys.readouterr().err == "error: --capture-port must be 0..65535\n"
    assert sim_main.main(["--capture-port", "5123", "--tcp-port", "5123"]) == 2
    assert capsys.readouterr().err == "error: --tcp-port and --capture-port must differ\n"
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    try:
        rc = sim_main.main(["--no-demo", "--no-pty", "--duration", "0.1", "--capture-port",
                            str(busy.getsockname()[1])])
    finally:
        busy.close()
    err = capsys.readouterr().err
    assert rc == 1 and err.startswith("error: cannot start the bench: ") and err.count("\n") == 1


# --- end to end: a bench session recorded by the jig, read by tshark with the dissector -----------
ABSENT = {0} | set(range(4, 16))  # the bench has the jig (1) and drives 2 and 3
EPOCH_US = 1767225600 * 1000000  # 2026-01-01: where the file's times start


class Session:
    """A vendor-style session on the virtual bench, recorded through the jig."""


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from test_vendor_probe import VendorStyleMaster, wire_of

    from motorjig.capture import pcapng
    from motorjig.capture.jigstream import JigStream

    b = SimBench(driver_ids=(2, 3))
    s = Session()
    s.bench = b
    s.sent = []  # every frame the PC sent, as wire bytes
    pc_send = b.pc.send

    def send(data, t0=None):
        s.sent.append(bytes(data))
        return pc_send(data, t0)

    b.pc.send = send
    s.driver_bus = []  # (start, bytes) of everything on the driver bus
    b.down_bus.monitor = lambda seg, data: s.driver_bus.append((seg.t0, bytes(data)))
    assert b.capture_start()
    m = VendorStyleMaster(b)
    # The FASTECH library's connect: GetCommandPos probes to 0..15 twice, then GetSlaveInfo to every id.
    assert m.connect() == {1: 6, 2: 6, 3: 6}
    s.infos = {i: m.request(i, F.GET_SLAVE_INFO) for i in range(16)}
    assert {i for i, r in s.infos.items() if r is not None} == {1, 2, 3}
    assert m.request(2, 0x2A, b"\x01") == b"\x00"  # ServoEnable
    assert m.request(2, 0x35, struct.pack("<iI", 1500, 50000)) == b"\x00"  # MoveIncPos
    b.run_for(200000.0)
    assert struct.unpack_from("<i", m.request(2, 0x51), 1)[0] == 1500  # arrived
    assert m.request(3, 0x34, struct.pack("<iI", -800, 40000)) == b"\x85"  # a move refused: servo off
    for num in (0, 3, 4):  # parameters of a drive and of the jig
        assert m.request(2, 0x13, bytes([num]))[0] == 0
    assert m.request(1, 0x13, bytes([3])) == b"\x00" + struct.pack("<i", 50)  # the jig's reply_timeout_ms
    # Faults: a request with a bad CRC from the PC (the jig drops it, no driver answers) ...
    bad = bytearray(wire_of(bytes([2, 0x51])))
    bad[-3] ^= 0x01
    s.bad_request = bytes(bad)
    assert b.transact(s.bad_request, 60000.0) is None
    # ... a drive whose reply fails its CRC (relayed as it came: the PC's CRC check rejects it) ...
    b.drivers[3].bad_crc = True
    assert m.request(3, 0x51, timeout_us=80000.0) is None
    b.drivers[3].bad_crc = False
    # ... and the jig's reply corrupted on its way to the PC (the jig recorded what it sent).
    b.corrupt_to_pc(1)
    assert m.request(2, 0x51) is None
    s.stream = b.capture_stop()
    js = JigStream("bench")
    s.records = js.feed(s.stream, host_us=EPOCH_US)
    s.jig = js
    s.path = str(tmp_path_factory.mktemp("capture") / "bench.pcapng")
    with open(s.path, "wb") as f:
        w = pcapng.Writer(f, js.buses(), hardware=js.description())
        for rec in s.records:
            w.write(rec)
    return s


def test_the_stream_is_the_session(session):
    """Nothing lost; the PC-bus records are the PC's frames; the driver-bus records, in
    the order they started, are every byte the driver bus carried."""
    from motorjig.capture import record as R

    s = session
    js = s.jig
    assert js.hellos == 1 and js.lost == 0 and js.noise == [0, 0] and js.skipped == 0
    pc_in = [r.data for r in s.records if r.bus == 0 and r.direction == R.DIR_INBOUND]
    assert pc_in == s.sent  # every request as the PC sent it, the bad-CRC one too
    pc_out = b"".join(r.data for r in s.records if r.bus == 0 and r.direction == R.DIR_OUTBOUND)
    got = bytes(s.bench.pc.raw)  # what reached the PC: one bit of the last reply flipped on the way
    assert len(pc_out) == len(got)
    diff = [i for i in range(len(got)) if got[i] != pc_out[i]]
    assert len(diff) == 1 and bin(got[diff[0]] ^ pc_out[diff[0]]).count("1") == 1
    assert diff[0] >= len(got) - 13  # in the last reply (GetCommandPos: 13 bytes)
    drivers = sorted((r.t_first_us, r.data) for r in s.records if r.bus == 1)
    assert b"".join(d for _t, d in drivers) == b"".join(d for _t, d in sorted(s.driver_bus))


@needs_tshark
def test_tshark_pairs_every_request_and_marks_the_faults(session):
    s = session
    packets = dissect(s.path)
    assert len(packets) == len(s.records)

    def get(p, name):
        v = p.get(name)
        return v[0] if v else None

    by_number = {int(get(p, "frame.number")): p for p in packets}
    seen_absent = set()
    replies = {"pc": [], "drivers": []}
    for p in packets:
        bus = get(p, "frame.interface_name")
        kind = get(p, "plusr.kind")
        sid = get(p, "plusr.id")
        good = get(p, "plusr.verdict") == "good"
        if kind in ("0", "1"):  # the jig is a slave on the PC bus and the master on the driver bus
            inbound = (kind == "0") == (bus == "pc")
            assert get(p, "frame.packet_flags_direction") == ("0x00000001" if inbound else "0x00000002")
        if kind == "0":  # a request
            if int(sid) in ABSENT:
                seen_absent.add(int(sid))
                assert get(p, "plusr.response_in") is None, "id %s is not on the bench" % sid
                continue
            if get(p, "plusr.response_in") is None:
                # unanswered: the request whose reply came with a bad CRC (drive 3, GetCommandPos)
                assert (sid, get(p, "plusr.type")) == ("3", "0x51"), "request %s unanswered" % get(p, "frame.number")
                continue
            reply = by_number[int(get(p, "plusr.response_in"))]
            assert get(reply, "plusr.request_in") == get(p, "frame.number")
            assert get(reply, "frame.interface_name") == bus and get(reply, "plusr.id") == sid
        elif kind == "1":
            replies[bus].append((sid, get(p, "plusr.type"), get(p, "plusr.status")))
            assert get(p, "plusr.request_in") is not None
        else:
            assert not good, "packet %s is neither request nor reply" % get(p, "frame.number")
    assert seen_absent == ABSENT
    # A reply for every good frame the PC got, and the one corrupted on its way (the jig sent it good)
    assert len(replies["pc"]) == len(s.bench.pc.frames) + 1
    # Every drive's reply went on to the PC; the jig answered its own id (probe, GetSlaveInfo, GetParameter)
    assert replies["drivers"] == [r for r in replies["pc"] if r[0] != "1"]
    assert [r for r in replies["pc"] if r[0] == "1"] == [("1", "0x51", "0x00"), ("1", "0x01", "0x00"),
                                                         ("1", "0x13", "0x00")]
    assert ("3", "0x34", "0x85") in replies["pc"]  # the refused move, paired like any reply

    # The driver-bus response time: the simulated drive's own turnaround, within one character time
    turnaround = s.bench.drivers[2].turnaround_us
    char = s.bench.down_bus.bt
    times = [float(get(p, "plusr.turnaround")) * 1e6 for p in packets
             if get(p, "frame.interface_name") == "drivers" and get(p, "plusr.kind") == "1"]
    assert len(times) == len(replies["drivers"])
    assert all(abs(t - turnaround) <= char for t in times), times

    # The faults, as the jig's parser judged them and as the dissector sees them
    bad = [p for p in packets if get(p, "plusr.verdict") == "bad_crc"]
    assert [(get(p, "frame.interface_name"), get(p, "plusr.id")) for p in bad] == [
        ("pc", "2"), ("drivers", "2"), ("drivers", "3"), ("pc", "3")]
    for p in bad:
        assert get(p, "plusr.crc.status") == "0" and "plusr.crc.bad" in p
        assert get(p, "frame.packet_flags_crc_error") == "1"
        assert any(m.startswith("CRC mismatch") for m in p["expert_messages"])
    assert int(get(bad[0], "frame.cap_len")) == len(s.bad_request)
    assert int(get(bad[0], "plusr.crc"), 16) == struct.unpack("<H", body(s.bad_request)[-2:])[0]


@needs_tshark
def test_tshark_records_a_real_time_bench_through_the_jig_extcap(installed, bench):
    """tshark -i motorjig-jig on the bench's capture port while a PC talks to the bench."""
    import subprocess

    from test_capture_support import TSHARK

    listed = subprocess.run([TSHARK, "-D"], capture_output=True, text=True, timeout=60,
                            env=dict({k: v for k, v in os.environ.items() if k != "XDG_CONFIG_HOME"},
                                     HOME=str(installed)))
    assert "motorjig-jig" in listed.stdout, listed.stderr
    env = {k: v for k, v in os.environ.items() if k != "XDG_CONFIG_HOME"}
    env["HOME"] = str(installed)
    wait_until(lambda: not bench.sim.capture.is_open, what="no other reader")
    proc = subprocess.Popen([TSHARK, "-i", "motorjig-jig", "-o", "extcap.motorjig_jig.port:" + bench.capture_url,
                             "-c", "8", "-a", "duration:40", "-T", "fields", "-E", "separator=\t",
                             "-e", "frame.interface_name", "-e", "plusr.id", "-e", "plusr.type", "-e", "plusr.kind",
                             "-e", "plusr.turnaround", "-e", "frame.packet_flags_direction"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        wait_until(lambda: bench.sim.app.capture.on or proc.poll() is not None, 30,
                   "the extcap started the jig's recording")
        assert proc.poll() is None, proc.stderr.read()
        with serial.serial_for_url(bench.tcp_url, timeout=0.1) as pc:
            ask(pc, 2, F.GET_COMMAND_POS)
            ask(pc, 3, F.GET_AXIS_STATUS)
        out, err = proc.communicate(timeout=40)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "Lua" not in err.replace('Running as user "root"', ""), err
    rows = [line.split("\t") for line in out.splitlines()]
    assert [r[:4] for r in rows] == [
        ["pc", "2", "0x51", "0"], ["drivers", "2", "0x51", "0"], ["drivers", "2", "0x51", "1"],
        ["pc", "2", "0x51", "1"], ["pc", "3", "0x40", "0"], ["drivers", "3", "0x40", "0"],
        ["drivers", "3", "0x40", "1"], ["pc", "3", "0x40", "1"]]
    turnaround = bench.sim.drivers[2].turnaround_us
    char = bench.sim.down_bus.bt
    for r in (rows[2], rows[6]):  # the bench's clock is paced, not virtual: the same µs all the same
        assert abs(float(r[4]) * 1e6 - turnaround) <= char, r
    assert [r[5] for r in rows] == ["0x00000001", "0x00000002", "0x00000001", "0x00000002"] * 2
    # tshark stopped the extcap: its X ended the recording and the port is closed again
    wait_until(lambda: not bench.sim.app.capture.on and not bench.sim.capture.is_open, 10,
               "the recording stopped with the capture")
