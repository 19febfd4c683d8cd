"""The CAN side of the bench: SimHAL's CAN port, SimBench's CAN bus and nodes, the
direct SLCAN adapter, CAN faults, and the real-time Bench serving the SLCAN port."""

import os
import select
import socket
import time

import pytest

from motorjig.sim.bench import Bench, SimBench
from motorjig.sim.canhal import SLCAN_RATES, SimCan, SimSlcanPort


class SdoNode:
    """A small CANopen-like node for these tests: answers an expedited SDO upload of
    0x1000 with 0x00020192 and counts its faults; boot-up on start."""

    def __init__(self, clock, bus, node_id):
        self.node_id = node_id
        self.node = bus.add_node("node%d" % node_id, self.on_frame)
        self.faults = {}
        self.node.transmit(0x700 + node_id, False, False, b"\x00")  # boot-up

    def on_frame(self, t, can_id, ext, rtr, data):
        if can_id == 0x600 + self.node_id and data[:4] == b"\x40\x00\x10\x00" and "silent" not in self.faults:
            self.node.transmit(0x580 + self.node_id, False, False, b"\x43\x00\x10\x00\x92\x01\x02\x00")

    def set_fault(self, name, value):
        self.faults[name] = value

    def clear_faults(self):
        self.faults = {}


def test_a_bench_without_can_has_no_can_port():
    b = SimBench(driver_ids=(2,))
    assert b.can_bus is None and b.can_nodes == {} and b.slcan is None
    assert not hasattr(b.hal, "can_open") and b.hal.slcan is None


def test_can_nodes_and_the_jigs_can_port():
    b = SimBench(driver_ids=(2,), can_nodes=(5, 6), can_bitrate=1000000, can_node_factory=SdoNode)
    assert b.can_bus.bitrate == 1000000 and sorted(b.can_nodes) == [5, 6]
    assert isinstance(b.slcan, SimSlcanPort) and b.slcan is b.hal.slcan
    can = b.hal.can_open(1000000, False)
    assert isinstance(can, SimCan) and can.state() == can.STATE_ACTIVE
    assert b.hal.can_open(1000000, True) is can  # one FDCAN1, opened again
    b.hal.can_close(can)
    can = b.hal.can_open(1000000, False)
    can.send(0x605, b"\x40\x00\x10\x00\x00\x00\x00\x00")
    b.run_for(2000)
    got = []
    while (r := can.recv()) is not None:
        got.append((r[0], bytes(r[1])))
    assert (0x585, b"\x43\x00\x10\x00\x92\x01\x02\x00") in got
    b.hal.can_close(can)
    assert can.state() == can.STATE_STOPPED


@pytest.mark.parametrize("bad, msg", [
    (dict(can_nodes=(0,)), "out of range"), (dict(can_nodes=(128,)), "out of range"),
    (dict(can_nodes=(5, 5)), "twice"), (dict(can_nodes=(5,), can_bitrate=400000), "SLCAN bitrate"),
])
def test_bad_can_settings_are_refused(bad, msg):
    with pytest.raises(ValueError, match=msg):
        SimBench(driver_ids=(2,), can_node_factory=SdoNode, **bad)


def test_can_faults_go_to_the_nodes_and_plus_r_faults_stay():
    b = SimBench(driver_ids=(2,), can_nodes=(5, 6), can_node_factory=SdoNode)
    b.set_fault("can:silent", 1, 5)
    assert b.can_nodes[5].faults == {"silent": 1} and b.can_nodes[6].faults == {}
    b.set_fault("can:heartbeat", 100)
    assert b.can_nodes[6].faults == {"heartbeat": 100}
    with pytest.raises(ValueError, match="no CAN node 7"):
        b.set_fault("can:silent", 1, 7)
    b.set_fault("step-out", 2000, 2)  # a Plus-R fault as before
    assert b.drivers[2].active_faults()
    b.clear_faults()
    assert b.can_nodes[5].faults == {} and not b.drivers[2].active_faults()


def test_direct_adapter_answers_slcan_and_a_node_replies():
    b = SimBench(direct=True, driver_ids=(2,), can_nodes=(5,), can_node_factory=SdoNode)
    assert b.hal is None and b.can_adapter is not None
    b.slcan_send(b"S6\rO\r")
    # the node's boot-up had nobody to acknowledge it: it is retried until the adapter is on
    assert b.slcan_read(3) == b"\r\rt705100\r"
    b.slcan_send(b"V\rt60584000100000000000\r")
    assert b.slcan_read(3) == b"V1013\r\rt58584300100092010200\r"
    b.slcan_send(b"t6059\r")  # a DLC that does not match: refused
    assert b.slcan_read(1) == b"\a"


def test_direct_adapter_timestamps_and_remote_frames():
    b = SimBench(direct=True, driver_ids=(2,), can_nodes=(5,), can_node_factory=SdoNode)
    b.slcan_send(b"Z1\rO\rr7052\r")
    out = b.slcan_read(3)
    assert out.startswith(b"\r\r\r")
    boot = [x for x in out.split(b"\r") if x.startswith(b"t705")]
    assert len(boot) == 1 and len(boot[0]) == len(b"t705100") + 4  # a 4-digit ms stamp


def test_the_same_host_helpers_on_a_jig_bench_need_the_jigs_port():
    b = SimBench(driver_ids=(2,), can_nodes=(5,), can_node_factory=SdoNode)
    port = b.slcan
    assert not port.is_open
    b.slcan_send(b"V\r")
    assert port.is_open
    b.slcan_close()
    assert not port.is_open


# --- real time: the SLCAN port on TCP and a pty -------------------------------------------

def _read_until(sock, want, timeout=5.0):
    end = time.monotonic() + timeout
    got = b""
    while time.monotonic() < end and got.count(b"\r") + got.count(b"\a") < want:
        r, _, _ = select.select([sock], [], [], 0.1)
        if r:
            data = sock.recv(4096)
            if not data:
                break
            got += data
    return got


def test_realtime_bench_serves_the_slcan_port_one_host_at_a_time():
    with Bench(driver_ids=(2,), can_nodes=(5,), can_node_factory=SdoNode, direct_can=True) as bench:
        assert bench.slcan_url.startswith("socket://127.0.0.1:")
        assert bench.slcan_pty_path and os.path.exists(bench.slcan_pty_path)
        host, port = bench.slcan_url[len("socket://"):].split(":")
        a = socket.create_connection((host, int(port)), timeout=5)
        try:
            a.sendall(b"S6\rO\rt60584000100000000000\r")
            got = _read_until(a, 5)  # 3 OKs, the node's boot-up, the SDO reply
            assert got.startswith(b"\r\r\r") and b"t58584300100092010200\r" in got
            b2 = socket.create_connection((host, int(port)), timeout=5)
            try:
                b2.settimeout(5)
                assert b2.recv(100) == b""  # a second host is turned away
            finally:
                b2.close()
        finally:
            a.close()


def test_realtime_slcan_pty():
    with Bench(driver_ids=(2,), can_nodes=(5,), can_node_factory=SdoNode, direct_can=True) as bench:
        fd = os.open(bench.slcan_pty_path, os.O_RDWR | os.O_NOCTTY)
        try:
            os.write(fd, b"S6\rO\rV\r")
            end = time.monotonic() + 5
            got = b""
            while time.monotonic() < end and b"V" not in got:
                r, _, _ = select.select([fd], [], [], 0.1)
                if r:
                    got += os.read(fd, 4096)
            assert got.startswith(b"\r\r") and b"V1013\r" in got
        finally:
            os.close(fd)


# --- python -m motorjig.sim: the CAN options ------------------------------------------------

@pytest.mark.parametrize("argv, msg", [
    (["--can-nodes", "0"], "CAN node ids must be 1..127, got 0"),
    (["--can-nodes", "5,128"], "CAN node ids must be 1..127, got 128"),
    (["--can-nodes", "5,x"], "expected CANopen node ids"),
    (["--can-nodes", "5", "--can-bitrate", "400000"], "the CAN bitrate must be one of the SLCAN rates"),
])
def test_cli_refuses_bad_can_options_in_one_sentence(argv, msg, capsys):
    from motorjig.sim.__main__ import main

    with pytest.raises(SystemExit) as exc:
        main(argv + ["--no-demo", "--duration", "0.1"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert msg in err and "Traceback" not in err


@pytest.mark.parametrize("argv, msg", [
    (["--fault", "can:5:silent"], "a CAN fault needs --can-nodes"),
    (["--can-nodes", "5", "--fault", "can:6:silent"], "no CAN node 6 (--can-nodes 5)"),
    (["--can-nodes", "5", "--fault", "can:x:silent"], "'x' is not a CAN node id"),
    (["--can-nodes", "5", "--slcan-port", "7000", "--tcp-port", "7000"], "--tcp-port and --slcan-port must differ"),
    (["--can-nodes", "5", "--fault", "can:5:no-such-fault"], "unknown fault 'no-such-fault'"),
    (["--can-nodes", "5", "--fault", "can:5:dead-input=40"], "dead-input"),
])
def test_cli_refuses_bad_can_faults(argv, msg, capsys):
    from motorjig.sim.__main__ import main

    assert main(argv + ["--no-demo", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert msg in err and err.count("\n") == 1


def test_cli_help_tells_the_can_options(capsys):
    from motorjig.sim.__main__ import main

    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert "--can-nodes" in out and "--can-bitrate" in out and "--slcan-port" in out and "can:[ID:]NAME" in out
    assert "can:following-error=PPS" in out and "can:missed-heartbeat" in out


def test_cli_prints_the_slcan_port(capsys):
    from motorjig.sim.__main__ import main

    assert main(["--can-nodes", "5,6", "--no-demo", "--duration", "0.3", "--fault", "can:6:missed-heartbeat"]) == 0
    out = capsys.readouterr().out
    assert "CAN bus: 500000 bit/s, CiA 402 nodes 5, 6" in out
    assert "slcan: socket://127.0.0.1:" in out and "slcan pty: /dev/" in out
    assert "CAN node 6: missed-heartbeat" in out


# --- end to end through the jig's firmware (jig.canport) -------------------------------------

def test_slcan_through_the_jig_reaches_a_node_and_its_reply_comes_back():
    b = SimBench(driver_ids=(2,), can_nodes=(5,), can_node_factory=SdoNode)
    b.slcan_send(b"S6\rO\r")
    assert b.slcan_read(3) == b"\r\rt705100\r"  # the boot-up, acknowledged once the jig opened
    assert b.hal.can.state() == SimCan.STATE_ACTIVE and b.hal.can.bitrate == 500000
    b.slcan_send(b"t60584000100000000000\r")
    assert b.slcan_read(2) == b"\rt58584300100092010200\r"
    assert b.can_bus.frames == 3  # boot-up, request, reply
    b.slcan_send(b"C\r")
    assert b.slcan_read(1) == b"\r" and b.hal.can.state() == SimCan.STATE_STOPPED


def test_python_can_through_the_jig_on_the_realtime_bench():
    can = pytest.importorskip("can")
    with Bench(driver_ids=(2,), can_nodes=(5,), can_node_factory=SdoNode, pty=False) as bench:
        bus = can.Bus(interface="slcan", channel=bench.slcan_url, bitrate=500000, sleep_after_open=0)
        try:
            bus.send(can.Message(arbitration_id=0x605, data=b"\x40\x00\x10\x00\x00\x00\x00\x00",
                                 is_extended_id=False))
            got = []
            end = time.monotonic() + 5
            while time.monotonic() < end:
                m = bus.recv(0.5)
                if m is not None:
                    got.append((m.arbitration_id, bytes(m.data)))
                    if m.arbitration_id == 0x585:
                        break
            assert (0x585, b"\x43\x00\x10\x00\x92\x01\x02\x00") in got
        finally:
            bus.shutdown()


def test_cia402_nodes_answer_through_the_jig():
    b = SimBench(driver_ids=(2,), can_nodes=(5, 6))  # the default node: cia402.Cia402Node
    b.slcan_send(b"S6\rO\r")
    assert b.slcan_read(2) == b"\r\r"  # (the nodes booted meanwhile, acknowledging each other)
    b.slcan_send(b"t00028100\r")  # NMT reset node, all: their boot-ups again
    assert sorted(b.slcan_read(3).split(b"\r")) == [b"", b"", b"t705100", b"t706100"]
    b.slcan_send(b"t60684000100000000000\r")
    out = b.slcan_read(2)
    assert out.startswith(b"\rt5868430010") and out.endswith(b"\r")  # 0x1000 device type, 4 bytes
    assert out[len(b"\rt5868430010") + 2:][:4] == b"9201"  # low 16 bits: profile 402


# --- the same full-speed USB on both adapters; the jig against the direct adapter ------------

def test_the_slcan_ports_host_bytes_come_in_usb_frames():
    from motorjig.sim.canhal import CDC_RX_SIZE
    from motorjig.sim.clock import VirtualClock

    clock = VirtualClock()
    port = SimSlcanPort(clock)
    arrived = []
    port.on_host_data = lambda: arrived.append((clock.now, len(port.rx)))
    port.host_open()
    clock.advance(250)
    port.host_send(b"V\r")
    assert port.any() == 0  # not before the next USB frame
    clock.advance(749)
    assert port.any() == 0
    clock.advance(1)
    assert port.any() == 2 and arrived == [(1000, 2)]
    port.readinto(bytearray(2))
    port.host_send(bytes(3000))  # more than a frame moves, and than the device's buffer holds
    clock.advance(10000)
    assert port.any() == CDC_RX_SIZE and len(port.host_out) == 3000 - CDC_RX_SIZE  # the rest NAKed
    port.readinto(bytearray(CDC_RX_SIZE))
    clock.advance(5000)
    assert port.any() == CDC_RX_SIZE and len(port.host_out) == 3000 - 2 * CDC_RX_SIZE


def _sdo_round_trips(direct, bitrate, offsets):
    """(host line sent -> its frame's end on the bus, host line sent -> reply line in) for
    an SDO upload at each offset into a USB frame."""
    b = SimBench(driver_ids=(2,), can_nodes=(5,), can_node_factory=SdoNode, can_bitrate=bitrate,
                 direct_can=direct)
    port = b.slcan
    b.slcan_send(b"S%d\rO\r" % SLCAN_RATES.index(bitrate))
    b.slcan_read(3)
    ends = []
    b.can_bus.monitor = lambda t, f, kind: ends.append(t) if f.can_id == 0x605 else None
    got = []
    port.sink = lambda chunk: got.append((b.clock.now, bytes(chunk))) or len(chunk)
    out = []
    for off in offsets:
        b.run_for(5000 - b.clock.now % 1000 + off)
        t0 = b.clock.now
        del got[:], ends[:]
        port.host_send(b"t60584000100000000000\r")
        b.clock.run_while(lambda: not any(b"t585" in c for _, c in got), 20000)
        out.append((ends[0] - t0, [t for t, c in got if b"t585" in c][0] - t0))
    return out


def test_through_the_jig_an_sdo_upload_takes_what_it_takes_on_the_direct_adapter():
    """Both adapters on the same full-speed USB: the jig's line reaches the bus within
    CAN_POLL_US of the direct adapter's, and an idle bus's SDO round trip is the same."""
    from jig.canport import CAN_POLL_US

    offsets = [0, 90, 333, 500, 777, 999]
    for bitrate in (500000, 1000000):
        jig = _sdo_round_trips(False, bitrate, offsets)
        ref = _sdo_round_trips(True, bitrate, offsets)
        for (bus_j, rt_j), (bus_d, rt_d) in zip(jig, ref):
            assert bus_d <= bus_j <= bus_d + CAN_POLL_US
            assert rt_j == rt_d
