"""The CANopen ecosystem's own tools through the jig's SLCAN port, used as a user would.

A real-time bench with two simulated CiA 402 drives (node ids 5 and 6) behind the
simulated jig; the PC side is python-can (``can.Bus(interface="slcan")``), python-canopen
(``Network``, its scanner, ``BaseNode402``) and ``python -m can.logger``, unchanged,
on the bench's SLCAN port (its TCP URL, and its pty for python-can), exactly as they
would open a board's third USB serial port. Nothing here is MotorJig code except the
bench itself and the EDS the drives are described by.
"""

import os
import signal
import subprocess
import sys
import time

import can
import canopen
import pytest

from motorjig.can import EDS_PATH
from motorjig.sim import Bench

NODES = (5, 6)
BITRATE = 500000
OPEN = dict(interface="slcan", bitrate=BITRATE, sleep_after_open=0.05)
SDO_TIMEOUT = 1.0  # s: the bench runs in real time on a shared, busy machine
VENDOR = 0x4D4A4947  # the EDS's 0x1018:1
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def bench():
    with Bench(driver_ids=(2,), can_nodes=NODES, can_bitrate=BITRATE) as b:
        yield b


@pytest.fixture
def network(bench):
    net = canopen.Network()
    net.connect(channel=bench.slcan_url, **OPEN)
    try:
        yield net
    finally:
        net.disconnect()


def remote(network, node_id, cls=canopen.RemoteNode):
    node = cls(node_id, EDS_PATH)
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT
    return node


def until(fn, timeout=5.0, step=0.01):
    """fn()'s first true value within timeout seconds (else its last value)."""
    end = time.monotonic() + timeout
    while True:
        value = fn()
        if value or time.monotonic() >= end:
            return value
        time.sleep(step)


def sdo_upload(bus, node_id, index, sub, timeout=5.0):
    """The expedited SDO upload response to a request sent as a raw frame, as a python-can user writes it."""
    request = can.Message(arbitration_id=0x600 + node_id, is_extended_id=False,
                          data=[0x40, index & 0xFF, index >> 8, sub, 0, 0, 0, 0])
    bus.send(request)
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        msg = bus.recv(0.1)
        if msg is not None and msg.arbitration_id == 0x580 + node_id and bytes(msg.data[1:4]) == bytes(request.data[1:4]):
            return msg
    return None


def test_python_can_sends_and_receives(bench):
    python_can_session(bench.slcan_url)


def python_can_session(channel):
    with can.Bus(channel=channel, **OPEN) as bus:
        version = bus.get_version(2.0)
        assert version != (None, None)  # the jig answers V like any SLCAN adapter
        for node_id in NODES:
            msg = sdo_upload(bus, node_id, 0x1018, 1)  # identity: vendor id
            assert msg is not None, "node %d did not answer" % node_id
            assert msg.data[0] == 0x43 and msg.dlc == 8 and not msg.is_extended_id
            assert int.from_bytes(msg.data[4:8], "little") == VENDOR
        msg = sdo_upload(bus, 5, 0x2FFF, 0)  # an object the node does not have: an abort frame
        assert msg.data[0] == 0x80 and int.from_bytes(msg.data[4:8], "little") == 0x06020000


def test_python_canopen_scanner_finds_the_nodes(network):
    network.scanner.reset()
    network.scanner.search()
    assert until(lambda: sorted(network.scanner.nodes) == list(NODES)), network.scanner.nodes
    time.sleep(0.2)  # and no one else answers
    assert sorted(network.scanner.nodes) == list(NODES)


def test_sdo_by_the_eds_names(network):
    node = remote(network, 6)
    assert node.sdo["Device type"].raw & 0xFFFF == 402
    assert node.sdo["Manufacturer device name"].raw == "MotorJig CiA 402 drive (sim)"  # segmented upload
    assert node.sdo["Identity object"]["Vendor-ID"].raw == VENDOR
    node.sdo["Profile velocity"].raw = 12345
    assert node.sdo["Profile velocity"].raw == 12345
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo["Statusword"].raw = 1  # python-canopen sends it; the node refuses
    assert exc.value.code == 0x06010002


def test_base_node_402_profile_position_move(network):
    node = remote(network, 5, canopen.BaseNode402)
    node.TIMEOUT_SWITCH_STATE_FINAL = 5.0  # the bench is real time on a busy machine
    node.TIMEOUT_SWITCH_STATE_SINGLE = 2.0
    node.TIMEOUT_SWITCH_OP_MODE = 2.0
    node.nmt.state = "PRE-OPERATIONAL"
    node.setup_402_state_machine()  # reads the node's PDO configuration by SDO
    node.nmt.state = "OPERATIONAL"
    node.sdo["Profile acceleration"].raw = 200000
    node.sdo["Profile deceleration"].raw = 200000
    node.sdo["Profile velocity"].raw = 50000
    node.op_mode = "PROFILED POSITION"
    assert node.sdo["Modes of operation display"].raw == 1
    node.state = "OPERATION ENABLED"
    assert node.state == "OPERATION ENABLED"
    assert node.sdo["Statusword"].raw & 0x6F == 0x27

    start = node.sdo["Position actual value"].raw
    target = start + 20000
    node.sdo["Target position"].raw = target
    node.controlword = 0x1F  # enable operation + new set-point
    assert until(lambda: node.sdo["Statusword"].raw & (1 << 12)), "no set-point acknowledge"
    node.controlword = 0x0F
    assert until(lambda: node.sdo["Statusword"].raw & (1 << 10), timeout=10.0), "target not reached"
    assert node.sdo["Position actual value"].raw == target  # read back by SDO

    tpdo = node.tpdo[2]  # statusword + position actual value, on SYNC (transmission type 1)
    assert tpdo.enabled and [v.index for v in tpdo] == [0x6041, 0x6064]
    got = []
    tpdo.add_callback(lambda m: got.append(m["Position actual value"].raw))
    network.sync.transmit()
    assert until(lambda: got), "no TPDO2 after SYNC"
    assert got[-1] == target  # ... and by PDO
    assert tpdo["Statusword"].raw & (1 << 10)

    node.state = "SWITCH ON DISABLED"
    assert node.state == "SWITCH ON DISABLED"


def test_can_logger_records_the_heartbeats(bench, tmp_path):
    with canopen.Network() as net:  # heartbeat of node 5 on, as a user would by SDO
        net.connect(channel=bench.slcan_url, **OPEN)
        remote(net, 5).sdo["Producer heartbeat time"].raw = 50
    path = str(tmp_path / "bus.asc")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.join(ROOT, "firmware"), os.path.join(ROOT, "tools")]))
    proc = subprocess.Popen([sys.executable, "-m", "can.logger", "-i", "slcan", "-c", bench.slcan_url,
                             "-b", str(BITRATE), "-f", path, "--bus-kwargs", "sleep_after_open=0.05"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert until(lambda: os.path.exists(path) and os.path.getsize(path) > 200 or proc.poll() is not None,
                     timeout=15.0)
        time.sleep(1.0)  # some 20 heartbeats
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    frames = list(can.LogReader(path))
    beats = [m for m in frames if m.arbitration_id == 0x705]
    assert len(beats) >= 5, (len(frames), err)
    assert all(m.dlc == 1 and m.data[0] in (0x05, 0x7F, 0x04) for m in beats)
    with canopen.Network() as net:
        net.connect(channel=bench.slcan_url, **OPEN)
        remote(net, 5).sdo["Producer heartbeat time"].raw = 0


def test_python_can_on_the_pty(bench):
    # Last in this module: the bench sees the pty closed a moment after python-can closes
    # it, and turns away a TCP client that comes in that moment (one host at a time).
    python_can_session(bench.slcan_pty_path)
