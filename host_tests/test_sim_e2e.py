"""End to end through the virtual bench: PC -> jig (real firmware) -> simulated drives.

Every frame type of the protocol notes, sent to a driver id, must arrive at the
driver byte-for-byte as the PC sent it, and the driver's reply must reach the PC
byte-for-byte with the documented layout.
"""

import struct

import pytest

from jig import diag
from jig import frame as F
from jig.params import P_FORWARD_MODE
from motorjig.sim import SimBench

# Reply data lengths from the protocol notes (§5), status byte included.
# None = variable (a NUL-terminated string follows a type byte).
DOC_REPLY_LEN = {
    0x01: None, 0x05: None, 0x07: 2, 0x10: 1, 0x11: 5, 0x12: 1, 0x13: 5,
    0x20: 1, 0x21: 1, 0x22: 5, 0x23: 5, 0x24: 1, 0x25: 6, 0x26: 2, 0x27: 1, 0x28: 2,
    0x2A: 1, 0x2B: 1, 0x2C: 1, 0x2E: 2,
    0x31: 1, 0x32: 1, 0x33: 1, 0x34: 1, 0x35: 1, 0x36: 1, 0x37: 1, 0x38: 1, 0x39: 1, 0x3A: 1,
    0x40: 5, 0x41: 13, 0x42: 21, 0x43: 33,
    0x50: 1, 0x51: 5, 0x52: 1, 0x53: 5, 0x54: 5, 0x55: 5, 0x56: 1, 0x58: 1,
    0x60: 65, 0x61: 2, 0x62: 2, 0x63: 2, 0x64: 1, 0x65: 33, 0x68: 1, 0x69: 2,
    0x6A: 5, 0x6B: 1, 0x6C: 9, 0x78: 1, 0x79: 2, 0x80: 1, 0x81: 1, 0x82: 1,
}

# Request data for each type (documented lengths; 0xAA bytes included here and there).
REQUEST_DATA = {
    0x11: b"\x01", 0x12: b"\x03" + struct.pack("<i", 0xAA), 0x13: b"\x01",
    0x20: struct.pack("<II", 0x8000, 0), 0x21: struct.pack("<II", 0x01, 0),
    0x24: struct.pack("<BIB", 12, 0x8000, 1), 0x25: b"\x0c",
    0x27: struct.pack("<BiIIBI", 0, 0, 100, 10, 0, 0),
    0x2A: b"\x01", 0x2C: b"\x00",
    0x34: struct.pack("<iI", 170, 5000), 0x35: struct.pack("<iI", -170, 5000),
    0x36: struct.pack("<IB", 1000, 1), 0x37: struct.pack("<IB", 1000, 1),
    0x38: struct.pack("<i", 0), 0x39: struct.pack("<i", 0), 0x3A: struct.pack("<I", 900),
    0x50: struct.pack("<i", 0xAAAA), 0x52: struct.pack("<i", 0xAAAA), 0x58: b"\x00",
    0x60: struct.pack("<H", 3), 0x61: struct.pack("<H", 3) + bytes(range(0xA0, 0xE0)),
    0x64: struct.pack("<H", 3), 0x68: b"\x00\x03\x00",
    0x6A: struct.pack("<HH", 3, 4), 0x6B: struct.pack("<HHi", 3, 4, 7),
    0x6C: struct.pack("<I", 0), 0x78: bytes(26),
    0x80: struct.pack("<iI", 100, 1000) + bytes(32), 0x81: struct.pack("<iI", 100, 1000) + bytes(32),
    0x82: struct.pack("<IB", 1000, 1) + bytes(32),
}


class Tap:
    """Records what each node put on a bus (bytes actually delivered)."""

    def __init__(self, bus):
        self.segs = []
        bus.monitor = lambda seg, data: self.segs.append((seg.node.name, bytes(data)))

    def by(self, name):
        """What the node sent, one item per frame (a jig cutting a frame through
        sends it in pieces: those are joined)."""
        out = []
        for n, d in self.segs:
            if n != name:
                continue
            if out and not out[-1].endswith(b"\xaa\xee"):
                out[-1] += d
            else:
                out.append(d)
        return out

    def clear(self):
        self.segs.clear()


@pytest.fixture(params=[0, 1], ids=["cut-through", "store-and-forward"])
def bench(request):
    b = SimBench(driver_ids=(2, 3), servo_on=True, jig_params={P_FORWARD_MODE: request.param})
    b.down_tap = Tap(b.down_bus)
    b.up_tap = Tap(b.up_bus)
    return b


@pytest.mark.parametrize("ftype", sorted(DOC_REPLY_LEN), ids=lambda t: "0x%02X" % t)
def test_every_frame_type_forwarded_unchanged(bench, ftype):
    data = REQUEST_DATA.get(ftype, b"")
    if ftype in (0x38, 0x39, 0x3A):  # overrides need a running move
        assert bench.drivers[2].handle(F.MOVE_ABS_POS, struct.pack("<iI", 100000, 1000)) == b"\x00"
    wire = F.encode(2, ftype, data)
    reply = bench.transact(wire)
    assert reply is not None, "no reply for 0x%02X" % ftype
    # the driver got exactly the PC's bytes, and the PC got exactly the driver's bytes
    assert bench.down_tap.by("jig-down") == [wire]
    assert bench.down_tap.by("driver-2") == [reply]
    assert bench.up_tap.by("jig-up") == [reply]
    assert bench.drivers[2].requests == 1 and bench.drivers[3].requests == 0
    # documented layout
    body = F.MAX_BODY
    assert reply[:2] == b"\xaa\xcc" and reply[-2:] == b"\xaa\xee"
    unstuffed = reply[2:-2].replace(b"\xaa\xaa", b"\xaa")
    assert unstuffed[0] == 2 and unstuffed[1] == ftype
    rdata = unstuffed[2:-2]
    assert rdata[0] == F.STATUS_OK, "status 0x%02X for 0x%02X" % (rdata[0], ftype)
    want = DOC_REPLY_LEN[ftype]
    if want is None:
        assert rdata[-1] == 0 and len(rdata) >= 3
    else:
        assert len(rdata) == want
    assert len(unstuffed) <= body


def test_unknown_type_and_bad_length_from_driver(bench):
    _w, r = bench.request(2, 0x06)
    assert r == bytes([F.STATUS_FRAME_TYPE_ERROR])
    _w, r = bench.request(2, F.MOVE_ABS_POS, b"\x00\x01")
    assert r == bytes([F.STATUS_FRAME_ERROR])


@pytest.mark.parametrize("ftype", [0x3B, 0x3C, 0x3D, 0x3E, 0x3F])
def test_broadcast_forwarded_no_reply(bench, ftype):
    data = struct.pack("<iI", 1000, 2000) if ftype in (0x3E, 0x3F) else b""
    wire = F.encode(F.BROADCAST_ID, ftype, data)
    assert bench.transact(wire, timeout_us=20000.0) is None
    assert bench.down_tap.by("jig-down") == [wire]
    assert bench.drivers[2].requests == 1 and bench.drivers[3].requests == 1
    assert bench.down_tap.by("driver-2") == [] and bench.up_tap.by("jig-up") == []
    c = bench.counters
    assert c["broadcasts"] == 1 and c["forwards"] == 0 and c["timeouts"] == 0


def test_slave_info_for_jig_and_each_driver(bench):
    _w, r = bench.request(1, F.GET_SLAVE_INFO)
    assert r[0] == 0 and r[1] == diag.SLAVE_TYPE
    assert r[2:].rstrip(b"\x00").startswith(b"MotorJig")
    sent_down = b"".join(bench.down_tap.by("jig-down"))
    if bench.app.params.ram[P_FORWARD_MODE] == 0:
        # cut through, the header went on before the id was known: ended as a stub
        # (a frame too short to be one, which every drive drops)
        assert sent_down == bytes((0xAA, 0xCC, 1, 0xAA, 0xEE))
    else:
        assert sent_down == b""  # answered locally, nothing forwarded
    for i in (2, 3):
        _w, r = bench.request(i, F.GET_SLAVE_INFO)
        assert r[0] == 0 and r[1] == 20 and b"Ezi-STEP" in r
    assert bench.request(4, F.GET_SLAVE_INFO) == (None, None)  # absent id: silence


def test_motion_status_evolves_through_the_jig(bench):
    _w, r = bench.request(3, F.MOVE_INC_POS, struct.pack("<iI", 20000, 10000))
    assert r == b"\x00"
    seen = set()
    positions = []
    for _ in range(40):
        bench.run_for(100000.0)
        _w, r = bench.request(3, F.GET_ALL_STATUS)
        _i, _o, flags, cmd, _act, _err, vel, _pt = struct.unpack("<IIIiiiiI", r[1:])
        positions.append(cmd)
        if flags & (1 << 27):
            seen.add("moving")
        if flags & (1 << 29):
            seen.add("accel")
        if flags & (1 << 31):
            seen.add("const")
        if not flags & (1 << 27) and cmd == 20000:
            seen.add("done")
            assert flags & (1 << 19)  # in position
            break
    assert {"moving", "const", "done"} <= seen
    assert positions == sorted(positions)


def test_ver8_sync_number_matched_and_echoed():
    b = SimBench(driver_ids=(2,), ver8=True)
    for k in range(3):
        wire, r = b.request(2, F.GET_COMMAND_POS)
        assert r == b"\x00" + bytes(4)
        assert wire[3] == k  # sync echoed (body: id, sync, type)
    wire, r = b.request(1, F.GET_COMMAND_POS)
    assert r == b"\x00" + bytes(4) and wire[3] == 3
