"""Issue 10: FASTECH's own host library finds every slave and its variant through the jig.

Two views of the vendor library's connect sequence on a mixed bus (the jig, a Ver6
drive at id 2, a Ver8 drive at id 3):

* The captures 26 (jig in Ver6 mode) and 27 (Ver8 mode) hold the exact probe
  sequence as the PC sees it. test_captures.py replays them through the parser;
  here every request of a capture goes through the real firmware on the bench and
  the jig must answer exactly the reply the capture states -- or nothing where the
  capture has none.
* ``VendorStyleMaster`` implements the detection procedure from the issue's text,
  independently of ``motorjig.master`` (own CRC, stuffing and reading of the
  bytes): on every combination of jig protocol and driver variants it must find
  each id with the right variant, and GetCommandPos / GetAllStatus / a move must
  work for each slave; a late reply with an old sync number must never reach the
  PC as the answer to a newer request.
"""

import os
import struct

import pytest

import capture_format as cf
from jig import params as P
from motorjig.sim import SimBench

HERE = os.path.dirname(os.path.abspath(__file__))
CAPTURES = {False: "26_vendor_probe_mixed_bus_ver6_jig.cap", True: "27_vendor_probe_mixed_bus_ver8_jig.cap"}


# --- the protocol, written again from the protocol notes (not jig.frame / jig.crc) -------
def crc16(data):
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def wire_of(body_without_crc):
    c = crc16(body_without_crc)
    body = bytes(body_without_crc) + bytes([c & 0xFF, c >> 8])
    return b"\xaa\xcc" + body.replace(b"\xaa", b"\xaa\xaa") + b"\xaa\xee"


def body_of(wire):
    """The unstuffed body (CRC included) of one frame's wire bytes; None if not one good frame."""
    if wire is None or wire[:2] != b"\xaa\xcc" or wire[-2:] != b"\xaa\xee":
        return None
    body = wire[2:-2].replace(b"\xaa\xaa", b"\xaa")
    return body if len(body) >= 4 and crc16(body) == 0 else None


# --- captures through the bridge ---------------------------------------------------------
@pytest.mark.parametrize("jig_ver8", [False, True], ids=["jig-ver6", "jig-ver8"])
def test_vendor_probe_capture_through_the_bridge(jig_ver8):
    cap = cf.load(os.path.join(HERE, "captures", CAPTURES[jig_ver8]))
    frames = [bytes(body) for body, _crc in cap.frames]
    bench = SimBench(driver_ids=(2, 3), jig_ver8=jig_ver8, ver8_drivers=(3,))
    pairs = 0
    k = 0
    while k < len(frames):
        req = frames[k]
        assert len(req) <= 3, "the captures hold requests without data and their replies"
        want = frames[k + 1] if k + 1 < len(frames) and len(frames[k + 1]) > 3 else None
        got = bench.transact(wire_of(req), timeout_us=100000.0)
        if want is None:
            assert got is None, "id %d must stay silent" % req[0]
        else:
            assert got == wire_of(want), "reply to %s" % req.hex(" ")
            pairs += 1
        if req[0] in bench.drivers:  # forwarded unchanged, whatever the driver's variant
            assert bench.drivers[req[0]].last_request[:-2] == req
        k += 2 if want is not None else 1
    assert pairs == (6 + (1 if jig_ver8 else 0) + 3)
    c = bench.counters
    assert c["stale_drops"] == 0 and c["timeouts"] == 2 * 13  # the absent ids, both rounds


# --- an independent vendor-style master --------------------------------------------------
class VendorStyleMaster:
    """The detection procedure as issue 10 describes the vendor library, on SimBench."""

    def __init__(self, bench):
        self.bench = bench
        self.variant = {}  # id -> 6 / 8
        self.sync = {}  # id -> last sync number sent

    def _ask(self, wire, timeout_us=100000.0):
        return body_of(self.bench.transact(wire, timeout_us))

    def connect(self):
        """Ver6-format GetCommandPos probe to 0..15, twice ~100 ms apart; classify."""
        for _round in range(2):
            for i in range(16):
                if i in self.variant:
                    continue
                probe = bytes([i, 0x51])
                crc_lo = crc16(probe) & 0xFF
                r = self._ask(wire_of(probe))
                if r is None or r[0] != i or r[1] != 0x51:
                    continue
                if len(r) == 2 + 1 + 4 + 2 and r[2] == 0:
                    self.variant[i] = 6  # a normal Ver6 GetCommandPos reply
                elif len(r) == 4 + 2 and r[2] == crc_lo and r[3] == 0x80:
                    # Ver8-layout frame-type error: then the Ver8 probe, sync 0xF1
                    self.sync[i] = 0xF0
                    if self.request(i, 0x51) is not None:
                        self.variant[i] = 8
            self.bench.run_for(100000.0)
        return dict(self.variant)

    def request(self, slave, ftype, data=b"", timeout_us=100000.0):
        """Reply data (status first) or None; Ver8: the next sync, which must be echoed."""
        if self.variant.get(slave) == 8 or slave in self.sync and slave not in self.variant:
            s = self.sync[slave] = (self.sync[slave] + 1) & 0xFF
            r = self._ask(wire_of(bytes([slave, s, ftype]) + data), timeout_us)
            if r is None or r[:3] != bytes([slave, s, ftype]) or len(r) < 6:
                return None
            return r[3:-2]
        r = self._ask(wire_of(bytes([slave, ftype]) + data), timeout_us)
        if r is None or r[:2] != bytes([slave, ftype]) or len(r) < 5:
            return None
        return r[2:-2]


COMBOS = [(jig, drv) for jig in (False, True) for drv in ((), (2,), (3,), (2, 3))]


@pytest.mark.parametrize("jig_ver8,ver8_drivers", COMBOS,
                         ids=["jig%d-v8drivers%s" % (8 if j else 6, "".join(map(str, d)) or "none") for j, d in COMBOS])
@pytest.mark.parametrize("mode", [P.CUT_THROUGH, P.STORE_AND_FORWARD], ids=["cut", "saf"])
def test_vendor_detection_finds_every_slave_with_its_variant(jig_ver8, ver8_drivers, mode):
    bench = SimBench(driver_ids=(2, 3), jig_ver8=jig_ver8, ver8_drivers=ver8_drivers,
                     jig_params={P.P_FORWARD_MODE: mode})
    m = VendorStyleMaster(bench)
    assert m.connect() == {1: 8 if jig_ver8 else 6, 2: 8 if 2 in ver8_drivers else 6,
                           3: 8 if 3 in ver8_drivers else 6}


@pytest.mark.parametrize("mode", [P.CUT_THROUGH, P.STORE_AND_FORWARD], ids=["cut", "saf"])
@pytest.mark.parametrize("jig_ver8", [False, True], ids=["jig-ver6", "jig-ver8"])
def test_vendor_style_session_on_a_mixed_bus(jig_ver8, mode):
    bench = SimBench(driver_ids=(2, 3), jig_ver8=jig_ver8, ver8_drivers=(3,), jig_params={P.P_FORWARD_MODE: mode})
    m = VendorStyleMaster(bench)
    assert m.connect() == {1: 8 if jig_ver8 else 6, 2: 6, 3: 8}
    assert m.sync[3] == 0xF1 and (not jig_ver8 or m.sync[1] == 0xF1)  # the Ver8 probe used 0xF1
    in_bytes = {6: 4, 8: 8}  # Ver8 widens the input word of GetAllStatus to 64 bits
    for s in (1, 2, 3):
        assert m.request(s, 0x51) == b"\x00" + bytes(4)  # GetCommandPos
        st = m.request(s, 0x43)  # GetAllStatus
        assert st is not None and st[0] == 0
        assert len(st) == 1 + (in_bytes[m.variant[s]] if s != 1 else 4) + 28
    for s in (2, 3):
        assert m.request(s, 0x2A, b"\x01") == b"\x00"  # ServoEnable
        assert m.request(s, 0x35, struct.pack("<iI", 1500, 50000)) == b"\x00"  # MoveIncPos
    bench.run_for(500000.0)
    for s in (2, 3):
        st = m.request(s, 0x43)
        w = in_bytes[m.variant[s]]
        flags, cmd = struct.unpack_from("<Ii", st, 1 + w + 4)
        assert cmd == 1500 and not flags & (1 << 27)  # arrived, not moving
    assert m.sync[3] == 0xF1 + 5  # one sync number per request to that slave (5 after the probe)


def test_late_reply_with_an_old_sync_never_answers_a_newer_request():
    """The Ver8 drive answers late; the PC gives up and asks again (next sync). The
    jig drops the late answer to the old request and relays only the new one."""
    bench = SimBench(driver_ids=(2, 3), jig_ver8=True, ver8_drivers=(3,))
    m = VendorStyleMaster(bench)
    m.connect()
    d = bench.drivers[3]
    d.late_us = 20000.0  # answers 20 ms late (the jig waits 50 ms)
    old = m.sync[3] = (m.sync[3] + 1) & 0xFF
    n0 = len(bench.pc.frames)
    bench.send(wire_of(bytes([3, old, 0x51])))  # GetCommandPos, then the PC gives up after 5 ms
    bench.run_for(5000.0)
    d.motion.pos = 777.0  # the newer request is answered with a different position
    # The old answer (position 0) comes while the jig awaits the new one: it has the
    # same id and frame type, only its sync number tells it apart.
    assert m.request(3, 0x51, timeout_us=60000.0) == b"\x00" + struct.pack("<i", 777)
    bench.run_for(100000.0)  # the late answer to the old request has come and gone
    got = [body_of(w) for _t, w in bench.pc.frames[n0:]]
    assert [b[1] for b in got] == [m.sync[3]]  # only the reply carrying the new sync
    assert bench.counters["stale_drops"] == 1 and bench.counters["aborts"] == 1


@pytest.mark.parametrize("jig_ver8", [False, True], ids=["jig-ver6", "jig-ver8"])
def test_jig_bus_scan_finds_drivers_of_both_variants(jig_ver8):
    """The jig's own scan speaks its protocol; a driver of the other variant answers
    with a frame-type error: found, its type unknown (0)."""
    bench = SimBench(driver_ids=(2, 3), jig_ver8=jig_ver8, ver8_drivers=(3,))
    m = VendorStyleMaster(bench)
    m.connect()
    assert m.request(1, 0xF2) == b"\x00"  # StartBusScan
    bench.run_for(1000000.0)
    r = m.request(1, 0xF3)  # GetBusScanResult: St, state, u16 bitmap, 16 types
    assert r[1] == 2 and struct.unpack_from("<H", r, 2)[0] == (1 << 2) | (1 << 3)
    types = r[4:20]
    assert (types[2], types[3]) == ((0, 20) if jig_ver8 else (20, 0))


def test_jig_own_ver8_syncs_are_no_frame_type_of_a_ver6_drive():
    """A Ver8 jig's scan reaches a Ver6 drive too, which reads the sync byte as its
    frame type: over many scans no sync may be a type (e.g. 0x2A ServoEnable, whose
    data byte would be GetSlaveInfo's 0x01: servo on)."""
    from motorjig.master import REQUEST_LEN

    bench = SimBench(driver_ids=(2,), jig_ver8=True, ver8_drivers=())
    m = VendorStyleMaster(bench)
    m.connect()
    seen = []
    bench.down_bus.monitor = lambda seg, data: seen.append(bytes(data)) if seg.node.name == "jig-down" else None
    for _ in range(20):  # 320 probes: more than every byte value
        assert m.request(1, 0xF2) == b"\x00"
        bench.run_for(1000000.0)
    syncs = {body_of(w)[1] for w in seen if body_of(w) is not None}
    assert len(syncs) >= 40 and not syncs & (set(REQUEST_LEN) | set(range(0x84, 0xB4)))
    assert not bench.drivers[2].servo_on and not bench.drivers[2].alarm_reset_held
