"""The jig's CAN port (jig.canport) on the bench's CAN bus: SLCAN in and out, the bus both ways.

The rig is the real App on bridge_probe's in-memory RS-485 HAL plus the bench's CAN
parts: ``SimCan`` (machine.CAN, its IRQ handler called as a hard IRQ) on a
``CanBus`` with another node ("peer") that sends frames and records what it hears,
and ``SimSlcanPort`` as the third CDC port whose host side the tests feed.
"""

import struct

import pytest

import bridge_probe
from jig import counters as K
from jig import diag
from jig import frame as F
from jig import params as P
from jig import slcan as S
from jig.app import CAN_IDLE_PARK, SLOW_US, App
from jig.canport import CAN_DEFER_US, CAN_POLL_US, STALL_US
from jig.parser import FrameParser
from motorjig.sim.canbus import CanBus
from motorjig.sim.canhal import SimCan, SimSlcanPort
from motorjig.sim.clock import VirtualClock

BEL = b"\x07"


class CanHal(bridge_probe.Hal):
    """bridge_probe's HAL on a virtual clock, with the CAN port: one SimCan, opened
    and closed as the board's machine.CAN(1) is."""

    def __init__(self, clock, bus, fs=None):
        super().__init__()
        self.clock = clock
        self.bus = bus
        self.slcan = SimSlcanPort(clock)
        self.can = None
        if fs is not None:
            self.fs = fs

    def ticks_us(self):
        return self.clock.ticks_us()

    def can_open(self, bitrate, listen_only):
        if self.can is None:
            self.can = SimCan(self.bus)
        self.can.init(bitrate, mode=SimCan.MODE_SILENT if listen_only else SimCan.MODE_NORMAL)
        self.can.set_filters(None)
        return self.can

    def can_close(self, can):
        can.deinit()


class Rig:
    def __init__(self, bitrate=500000, params=None, fastpath=None):
        self.clock = VirtualClock()
        self.bus = CanBus(self.clock, bitrate)
        self.heard = []  # (t, id, ext, rtr, data) the peer received
        self.peer = self.bus.add_node("peer", on_frame=self._heard)
        fs = None
        if params:
            fs = bridge_probe.MemFS()
            pr = P.Params(fs, "/p")
            for num, value in params.items():
                assert pr.set(num, value)
            assert pr.save()
        self.hal = CanHal(self.clock, self.bus, fs)
        self.app = App(self.hal, fastpath)
        self.port = self.hal.slcan
        self.port.host_open()

    def _heard(self, t, can_id, ext, rtr, data):
        self.heard.append((t, can_id, ext, rtr, bytes(data)))

    def run(self, us, step=50):
        end = self.clock.now + us
        while self.clock.now < end:
            self.app.poll()
            self.clock.advance(step)

    def say(self, text, us=15000):
        """Host -> jig; returns what the host got back meanwhile."""
        self.port.host_send(text)
        self.run(us)
        return self.port.host_read()

    def counters(self):
        return dict(zip(diag.CAN_WIRE_NAMES, self.app.can.counter_values([0] * diag.N_CAN_WIRE)))

    def ask(self, ftype, data=b""):
        """A local request on the PC bus; the reply's data (status first)."""
        up = self.hal.up
        up.out_n = 0
        wire = F.encode(1, ftype, data)
        up.rx.write(bytearray(wire), len(wire), self.hal.ticks_us())
        self.run(2000)
        p = FrameParser(False)
        p.feed(bytes(up.out[: up.out_n]))
        assert p.ready, "no reply to 0x%02X" % ftype
        return bytes(p.body[p.data_start:p.data_end])


def lines(text):
    return text.split(b"\r")


# --- the session: open, close, bitrate --------------------------------------------------
def test_python_cans_opening_sequence_opens_at_the_bitrate_asked():
    r = Rig()
    # what python-can's slcan interface sends: C, S5, an empty line (no data bitrate), O
    got = r.say(b"C\rS5\r\rO\r")
    assert got == BEL + b"\r\r"  # C while closed is refused; S5 and O are OK; the empty line is ignored
    assert r.app.can.is_open == 1 and r.hal.can.bitrate == 250000 and r.app.can.bitrate == 250000
    c = r.counters()
    assert c["can_open"] == 1 and c["can_bitrate"] == 250000 and c["can_state"] == SimCan.STATE_ACTIVE


def test_bitrate_and_open_only_while_closed_close_only_while_open():
    r = Rig()
    assert r.say(b"S9\r") == BEL  # python-can's S9 (83.3 k) is not one of S0..S8
    assert r.say(b"S8\rO\r") == b"\r\r"
    assert r.hal.can.bitrate == 1000000
    assert r.say(b"S6\rO\rL\r") == BEL * 3  # open: no bitrate change, no second open
    assert r.hal.can.bitrate == 1000000
    assert r.say(b"C\rC\r") == b"\r" + BEL
    assert r.app.can.is_open == 0 and r.hal.can.bitrate is None  # deinit
    assert r.say(b"s4E3C\r") == BEL  # BTR registers: not done by this adapter


def test_version_serial_status_and_timestamps():
    r = Rig()
    assert r.say(b"V\rN\rF\r") == b"V1013\rNMJ01\rF00\r"
    assert r.say(b"Z1\rZ2\rO\r") == b"\r" + BEL + b"\r"
    r.peer.transmit(0x123, False, False, b"\x01")
    got = r.say(b"", 3000)
    assert len(got) == len(b"t123101SSSS\r") and got.startswith(b"t12310") and got.endswith(b"\r")
    stamp = int(got[7:11], 16)
    assert 0 <= stamp < 60000


def test_the_serial_number_comes_from_the_boards_unique_id():
    r = Rig()
    r.hal.unique_id = lambda: b"\x12\x34\x56\x78\x9a\xbc\xde\xf0\x11\x22\x33\x44"
    from jig.canport import CanPort

    line = CanPort._serial_line(r.hal)
    assert len(line) == 6 and line[:1] == b"N" and line[-1:] == b"\r" and line != b"NMJ01\r"
    int(line[1:5], 16)


# --- frames both ways -------------------------------------------------------------------
def test_frames_from_the_bus_reach_the_host_as_slcan_lines():
    r = Rig()
    r.say(b"O\r")
    r.peer.transmit(0x18FF00AA, True, False, bytes(range(1, 9)))
    r.clock.advance(1000)
    r.peer.transmit(0x123, False, True, b"\x00\x00\x00")
    r.clock.advance(1000)
    r.peer.transmit(0x7FF, False, False, b"")
    got = r.say(b"", 5000)
    assert lines(got) == [b"T18FF00AA80102030405060708", b"r1233", b"t7FF0", b""]
    c = r.counters()
    assert c["can_rx_frames"] == 3 and c["can_rx_lost"] == 0 and c["can_tx_frames"] == 0


def test_frames_from_the_host_reach_the_bus_with_cr_on_accept():
    r = Rig()
    r.say(b"O\r")
    assert r.say(b"t12340102030A\rT1234567821122\rr7FF3\rR000000010\r") == b"\r" * 4
    assert [h[1:] for h in r.heard] == [(0x123, False, False, b"\x01\x02\x03\x0A"),
                                         (0x12345678, True, False, b"\x11\x22"),
                                         (0x7FF, False, True, b"\x00\x00\x00"),
                                         (0x1, True, True, b"")]
    assert r.counters()["can_tx_frames"] == 4


def test_the_hosts_order_is_kept_under_load():
    """machine.CAN's queue sends the lowest id first; one frame in the controller at
    a time keeps the host's order, falling ids and repeated ones alike."""
    r = Rig()
    r.say(b"O\r")
    ids = [0x700 - 16 * k for k in range(40)] + [0x100] * 5 + [0x080, 0x7F0]
    text = b"".join(b"t%03X2%02X%02X\r" % (i, k, k) for k, i in enumerate(ids))
    got = r.say(text, 60000)
    assert got == b"\r" * len(ids)
    assert [h[1] for h in r.heard] == ids
    assert [h[4][0] for h in r.heard] == list(range(len(ids)))


def test_a_burst_faster_than_the_bus_waits_for_the_fifo_and_every_frame_goes_out():
    """python-canopen's scanner sends 127 SDO requests at once: the jig reads the host's
    bytes only as the TX FIFO has room for the lines they could hold, the rest wait in
    the USB port (which holds the host off), and nothing is refused (python-can ignores
    BEL: a refused request is a node unseen). The shortest lines (6 bytes: t, id, DLC 0,
    CR) are the case the bound is for; falling ids check the order is the host's."""
    r = Rig(bitrate=125000)
    r.say(b"S4\rO\r")
    short = [b"t%03X0\r" % (0x7FF - k) for k in range(200)]
    sdo = [b"t%03X84000100000000000\r" % (0x600 + n) for n in range(1, 128)]  # the scanner's requests
    text = b"".join(short + sdo)
    r.port.host_send(text)
    assert len(text) > 3 * r.port.rx_size  # more than the USB port holds: the host is held off
    got = b""
    for _ in range(40):
        got += r.say(b"", 20000)
        if len(got) >= len(short) + len(sdo):
            break
    assert got == b"\r" * (len(short) + len(sdo))
    r.run(100000)  # the FIFO's last frames
    ids = [h[1] for h in r.heard]
    assert ids == [0x7FF - k for k in range(200)] + [0x600 + n for n in range(1, 128)]
    c = r.counters()
    assert c["can_tx_refused"] == 0 and c["can_tx_frames"] == len(ids)
    assert int(r.say(b"F\r")[1:3], 16) & 0x02  # the FIFO was full (latched until read)
    assert r.say(b"F\r") == b"F00\r"


def test_a_bus_that_takes_nothing_refuses_the_hosts_frames_after_stall_us():
    """Alone on the bus (no node acknowledges) the first frame is sent again and again:
    after STALL_US with a full FIFO and nothing sent the host's frames are refused
    (BEL, counted) again, so its later commands reach the jig (it can close)."""
    r = Rig()
    r.bus.remove_node(r.peer)
    r.say(b"O\r")
    r.port.host_send(b"t12388877665544332211\r" * 100 + b"C\r")
    r.run(STALL_US // 2)
    assert r.app.can.is_open and r.port.host_read() == b"\r" * 63  # the FIFO's 63 entries, the rest wait
    r.run(STALL_US)
    got = r.port.host_read()
    assert got == BEL * 37 + b"\r" and r.app.can.is_open == 0
    assert r.counters()["can_tx_refused"] == 37


def test_bel_for_bad_lines_and_frames_in_the_wrong_state():
    r = Rig()
    assert r.say(b"t1230\r") == BEL  # closed
    assert r.say(b"X\rt12G0\rt1231\rt8000\r") == BEL * 4  # unknown, bad hex, DLC without data, id range
    r.say(b"L\r")
    assert r.say(b"t1230\r") == BEL  # listen-only sends nothing
    assert r.heard == []
    c = r.counters()
    assert c["can_listen_only"] == 1 and c["slcan_unknown"] == 1 and c["slcan_id_range"] == 1
    assert sum(c["slcan_" + n] for n in S.ERR_NAMES) == 4


def test_parameter_listen_only_makes_o_open_listen_only():
    r = Rig(params={P.P_CAN_LISTEN_ONLY: 1, P.P_CAN_BITRATE: 125000})
    assert r.say(b"O\r") == b"\r"
    assert r.hal.can.mode == SimCan.MODE_SILENT and r.hal.can.bitrate == 125000
    assert r.say(b"t1230\r") == BEL


def test_ring_overflow_is_counted_and_the_rest_delivered():
    """The host stops reading: lines wait in the ring, what it cannot hold is lost and counted."""
    r = Rig(bitrate=1000000)
    r.say(b"S8\rO\r")
    r.port.host_close()  # the PC's program stops reading (the SLCAN channel stays open)
    for k in range(400):
        r.peer.transmit(0x100 + (k & 0xFF), False, False, b"\x00")
    r.run(60000)
    c = r.counters()
    assert c["can_rx_frames"] == 400 and c["can_rx_lost"] > 0
    r.port.host_open()
    got = r.say(b"", 20000)
    delivered = got.count(b"\r")
    assert delivered + c["can_rx_lost"] == 400
    assert r.counters()["can_rx_lost"] == c["can_rx_lost"]


# --- bus-off ----------------------------------------------------------------------------
def test_bus_off_is_restarted_after_the_parameters_time():
    r = Rig(params={P.P_CAN_BUS_OFF_RESTART_MS: 50})
    r.say(b"O\r")
    r.bus.inject_errors(32)  # TEC += 8 per error frame: 256 = bus-off
    assert r.say(b"t1230\r", 20000) == b"\r"
    assert r.app.can.state == SimCan.STATE_BUS_OFF
    assert r.say(b"t1231AA\r", 3000) == BEL  # refused while bus-off (a USB frame each way)
    r.run(60000)
    c = r.counters()
    assert c["can_bus_off_entries"] == 1 and c["can_bus_off_restarts"] == 1 and c["can_tx_failed"] == 1
    assert r.app.can.state == SimCan.STATE_ACTIVE
    assert r.say(b"t1232BBCC\r", 5000) == b"\r"
    assert r.heard[-1][1:] == (0x123, False, False, b"\xBB\xCC")
    r.run(300000)  # (the 128 x 11 bit recovery is not a second bus-off)
    c = r.counters()
    assert c["can_bus_off_entries"] == 1 and c["can_bus_off_restarts"] == 1 and c["can_state"] == SimCan.STATE_ACTIVE


def test_bus_off_stays_until_the_host_closes_and_opens_with_restart_0():
    r = Rig(params={P.P_CAN_BUS_OFF_RESTART_MS: 0})
    r.say(b"O\r")
    r.bus.inject_errors(32)
    r.say(b"t1230\r", 20000)
    r.run(500000)
    assert r.app.can.state == SimCan.STATE_BUS_OFF and r.counters()["can_bus_off_restarts"] == 0
    f = r.say(b"F\r")
    assert int(f[1:3], 16) & 0x80
    assert r.say(b"C\rO\rt1231AA\r", 5000) == b"\r\r\r"
    assert r.app.can.state == SimCan.STATE_ACTIVE and r.heard[-1][1:] == (0x123, False, False, b"\xAA")


# --- the safety stop on CAN silence -------------------------------------------------------
def test_safety_nmt_stop_all_on_host_silence_once():
    r = Rig(params={P.P_SAFETY_TIMEOUT_MS: 100, P.P_CAN_SAFETY: 1})
    r.say(b"O\rt1230\r")
    n0 = len(r.heard)  # (the lines came at t = 0, now is 15 ms)
    r.run(80000)
    assert len(r.heard) == n0  # not yet
    r.run(30000)
    assert [h[1:] for h in r.heard[n0:]] == [(0x000, False, False, b"\x02\x00")]
    r.run(500000)
    assert len(r.heard) == n0 + 1  # once, until the host speaks again
    assert r.counters()["can_safety_stops"] == 1
    assert r.app.counters.v[K.C_SAFETY_STOPS] == 1
    assert r.app.can.is_open == 0  # the dead host's session ended with the stop
    r.say(b"F\r")  # (closed: the status flags answer, nothing is armed)
    r.run(150000)
    assert len(r.heard) == n0 + 1
    r.say(b"O\rt1230\r")  # a window saved to flash is a setting: the next session is watched too
    r.run(150000)
    assert [h[1:] for h in r.heard[n0 + 1:]] == [(0x123, False, False, b""), (0x000, False, False, b"\x02\x00")]


def test_safety_quick_stop_to_every_node_seen():
    r = Rig(params={P.P_SAFETY_TIMEOUT_MS: 100, P.P_CAN_SAFETY: 2})
    r.say(b"O\r")
    r.peer.transmit(0x705, False, False, b"\x05")  # heartbeat of node 5
    r.peer.transmit(0x77F, False, False, b"\x00")  # boot-up of node 127
    r.peer.transmit(0x587, False, False, b"\x60\x40\x60\x00\x00\x00\x00\x00")  # SDO reply of node 7
    r.peer.transmit(0x185, False, False, b"\x01")  # a PDO: says nothing about node ids
    r.run(150000)
    got = [h[1:] for h in r.heard]
    sdo = b"\x2B\x40\x60\x00\x02\x00\x00\x00"
    assert got == [(0x605, False, False, sdo), (0x607, False, False, sdo), (0x67F, False, False, sdo)]
    assert r.counters()["can_safety_stops"] == 1


def lease(r, window_ms=100, can_safety=2):
    """Arm the safety net as a run does: in RAM only (ask = SetParameter on the PC bus)."""
    for num, value in ((P.P_SAFETY_ACTION, 2), (P.P_CAN_SAFETY, can_safety), (P.P_SAFETY_TIMEOUT_MS, window_ms)):
        assert r.ask(F.SET_PARAMETER, bytes([num]) + struct.pack("<i", value)) == b"\x00"


def test_a_leased_quick_stop_then_resets_the_nodes_communication_and_lets_go():
    """A run's lease: quick stop to each node seen, then NMT reset communication to each (its
    PDO timers and heartbeat back to power-on: a quiet bus), then parameters 9, 10, 18 back to
    their saved values; a new session's silence stops nothing."""
    r = Rig()
    r.say(b"O\r")
    r.peer.transmit(0x705, False, False, b"\x05")
    r.peer.transmit(0x706, False, False, b"\x05")
    lease(r)
    r.say(b"t1230\r")
    r.run(400000)
    got = [h[1:] for h in r.heard if h[1] != 0x123]
    sdo = b"\x2B\x40\x60\x00\x02\x00\x00\x00"
    assert got == [(0x605, False, False, sdo), (0x606, False, False, sdo),
                   (0x000, False, False, b"\x82\x05"), (0x000, False, False, b"\x82\x06")]
    resets = [h[0] for h in r.heard if h[1] == 0]
    quick = [h[0] for h in r.heard if h[1] == 0x606]
    assert resets[0] - quick[0] >= 100000 - 1000  # the drive had time to act on the quick stop
    assert [r.app.params.get(n) for n in (P.P_SAFETY_TIMEOUT_MS, P.P_SAFETY_ACTION, P.P_CAN_SAFETY)] == [0, 0, 0]
    n = diag.decode_safety_notice(r.ask(diag.TAKE_SAFETY_NOTICE))
    assert n["can"] and n["nodes"] == [5, 6] and n["ids"] == []
    assert r.counters()["can_safety_stops"] == 1
    assert r.app.can.is_open == 0 and r.port.host_read() == b""  # the dead session ended, nothing kept for the next
    heard = len(r.heard)
    r.say(b"O\rt1230\r")  # the next user's session, then silence
    r.run(2000000)
    assert len(r.heard) == heard + 1  # its own frame only


def test_the_pc_ports_silence_fires_the_can_ports_stop_too():
    """One lease: the run's master fell silent on the PC bus first (its CAN keep-alive still
    going): the CAN nodes are stopped at once too, not a window later or never."""
    r = Rig()
    r.say(b"O\r")
    r.peer.transmit(0x705, False, False, b"\x05")
    lease(r, window_ms=300)
    for _ in range(8):  # the CAN side stays alive; the PC bus fell silent at the lease's last frame
        r.say(b"t1230\r", 60000)
    got = [h[1] for h in r.heard if h[1] != 0x123]
    assert got[:1] == [0x605] and r.app.counters.v[K.C_SAFETY_STOPS] == 2  # both watches fired once


def test_no_safety_stop_when_off_or_listen_only():
    r = Rig(params={P.P_SAFETY_TIMEOUT_MS: 100, P.P_CAN_SAFETY: 0})
    r.say(b"O\r")
    r.run(300000)
    assert r.heard == []
    r = Rig(params={P.P_SAFETY_TIMEOUT_MS: 100, P.P_CAN_SAFETY: 1})
    r.say(b"L\r")
    r.run(300000)
    assert r.heard == [] and r.counters()["can_safety_stops"] == 0


# --- diagnostics, parameters, old HALs ------------------------------------------------------
def test_read_can_counters_decoded_and_reset_by_reset_counters():
    r = Rig()
    r.say(b"O\rt1230\rX\r")
    r.peer.transmit(0x181, False, False, b"\x01")
    r.run(5000)
    c = diag.decode_can_counters(r.ask(diag.READ_CAN_COUNTERS))
    assert list(c) == list(diag.CAN_WIRE_NAMES)
    assert c["can_rx_frames"] == 1 and c["can_tx_frames"] == 1 and c["slcan_unknown"] == 1
    assert c["slcan_lines"] == 2 and c["can_open"] == 1 and c["can_bitrate"] == 500000
    assert r.ask(diag.RESET_COUNTERS) == b"\x00"
    c = diag.decode_can_counters(r.ask(diag.READ_CAN_COUNTERS))
    assert c["can_rx_frames"] == 0 and c["slcan_unknown"] == 0 and c["can_open"] == 1  # states stay
    # ReadCounters is unchanged: its reply stays under the data limit
    counters = diag.decode_counters(r.ask(diag.READ_COUNTERS))
    assert list(counters) == list(diag.WIRE_NAMES)
    assert 2 + 4 * (diag.N_WIRE) <= F.MAX_DATA and 2 + 4 * diag.N_CAN_WIRE <= F.MAX_DATA


def test_the_ports_local_counter_constants_are_the_counters_modules():
    from jig import canport

    for name in ("CC_RX", "CC_TX", "CC_RX_LOST", "CC_RX_OVERRUNS", "CC_TX_FAILED", "CC_LINES"):
        assert getattr(canport, "_" + name) == getattr(K, name), name
    assert canport._EV_CMD == S.EV_CMD and canport._EV_BAD == S.EV_BAD


def test_can_counter_names_cover_the_slcan_error_kinds_and_are_documented():
    assert diag.CAN_WIRE_NAMES[-len(S.ERR_NAMES):] == tuple("slcan_" + n for n in S.ERR_NAMES)
    assert len(set(diag.CAN_WIRE_NAMES)) == diag.N_CAN_WIRE
    assert not set(diag.CAN_WIRE_NAMES) & set(diag.WIRE_NAMES)
    import os

    doc = open(os.path.join(os.path.dirname(__file__), "..", "docs", "diagnostics.md")).read()
    for name in diag.CAN_WIRE_NAMES:
        assert "`%s`" % name in doc, name


def test_a_parameter_file_from_before_the_can_parameters_loads():
    fs = bridge_probe.MemFS()
    old = b"MJP1" + bytes([14]) + struct.pack("<14i", 1, 115200, 921600, 50, 5000, 0, 10, 0, 0, 250, 1, 20, 1, 0)
    from jig.crc import crc16

    old += struct.pack("<H", crc16(old, 0, len(old)))
    fs.files["/p"] = old
    pr = P.Params(fs, "/p")
    assert pr.load()
    assert pr.ram[P.P_DOWN_BAUD] == 921600 and pr.ram[P.P_SAFETY_TIMEOUT_MS] == 250
    assert pr.ram[P.P_CAN_BITRATE:] == [500000, 0, 1, 100, 0]  # the new ones at their defaults
    assert pr.save()  # and saved again with all of them
    assert len(fs.files["/p"]) == P.FILE_SIZE and fs.files["/p"][4] == P.COUNT


def test_can_bitrate_parameter_takes_slcan_rates_only():
    pr = P.Params()
    assert pr.set(P.P_CAN_BITRATE, 125000) and pr.set(P.P_CAN_BITRATE, 750000)
    assert not pr.set(P.P_CAN_BITRATE, 83333) and not pr.set(P.P_CAN_BITRATE, 2000000)
    assert P.CAN_BITRATES == S.SLCAN_BITRATES


def test_the_app_runs_unchanged_on_a_hal_without_can():
    rig = bridge_probe.Rig()
    assert rig.app.can is None
    for _ in range(5):
        rig.forward_once()
    assert rig.hal.up.writes == 5
    rig.hal.up.out_n = 0
    rig.local_once(bytearray(F.encode(1, diag.READ_CAN_COUNTERS)))
    p = FrameParser(False)
    p.feed(bytes(rig.hal.up.out[: rig.hal.up.out_n]))
    assert p.ready and diag.decode_can_counters(bytes(p.body[p.data_start:p.data_end])) == {}


class WakingSlcanPort(SimSlcanPort):
    """The SLCAN port with pyb.USB_VCP's ``irq(handler)``: the handler runs (soft) when
    the host's bytes arrive."""

    handler = None

    def irq(self, handler=None, trigger=1, hard=False):
        self.handler = handler

    def _arrived(self):
        super()._arrived()
        if self.handler is not None:
            self.handler(self)


def test_host_bytes_wake_the_slow_pass_where_the_port_can_say_so():
    for cls, within in ((SimSlcanPort, False), (WakingSlcanPort, True)):
        r = Rig()
        r.hal.slcan = r.port = cls(r.clock)
        from jig.canport import CanPort

        r.app.can = CanPort(r.app)
        r.port.host_open()
        r.run(3000)  # between two slow passes (every 10 ms while closed)
        assert (r.say(b"V\r", 2000) == b"V1013\r") is within


# --- the port's own pass (due[1]): the host's lines reach the bus within CAN_POLL_US ------------
def _count_port_passes(r):
    """The ticks of the port's own passes (each asks the host's port for bytes once,
    serve only when something waits) and of the slow passes."""
    passes, slows = [], []
    real_any, real_slow = r.app._can_any, r.app._slow
    r.app._can_any = lambda: passes.append(r.app.hal.ticks_us()) or real_any()
    r.app._slow = lambda now: slows.append(now) or real_slow(now)
    return passes, slows


def _count_passes(r):
    serves, slows = [], []
    real_serve, real_slow = r.app._can_serve, r.app._slow
    r.app._can_serve = lambda now: serves.append(now) or real_serve(now)
    r.app._slow = lambda now: slows.append(now) or real_slow(now)
    return serves, slows


def test_open_the_ports_own_pass_comes_every_can_poll_us_and_the_slow_pass_keeps_its_period():
    r = Rig()
    r.say(b"O\r")
    passes, slows = _count_port_passes(r)
    serves, _ = _count_passes(r)
    r.run(100000, step=5)  # the board's loop: a pass every 5 µs
    gaps = [b - a for a, b in zip(passes, passes[1:])]
    assert len(passes) >= 100000 // CAN_POLL_US - 2 and max(gaps) <= CAN_POLL_US + 5
    assert len(slows) <= 100000 // SLOW_US + 2  # open and idle: no more slow passes than closed
    assert serves == []  # nothing to do: the loop looked, serve was not called
    r.say(b"C\r")
    passes[:] = []
    r.run(50000, step=5)
    assert passes == []  # closed: no pass of its own


def test_a_host_line_reaches_the_bus_within_can_poll_us_of_its_usb_frame():
    """On the virtual timeline: a line the host sends at any moment reaches the jig in
    the next 1 ms USB frame, and its frame is on the bus at most CAN_POLL_US later."""
    r = Rig()
    r.say(b"O\r")
    r.peer.transmit(0x181, False, False, b"\x01")  # its IRQ sets the phase of the port's passes
    r.run(1237, step=5)
    usb = r.port.frame_us
    frame = r.bus.frame_us(False, False, 8) - 3 * r.bus.bit_us  # start of frame to end of EOF
    late = []
    for k in range(23):
        r.run(usb + 37 * k % usb, step=5)
        t_send = r.clock.now
        arrive = (t_send // usb + 1) * usb
        n0 = len(r.heard)
        r.port.host_send(b"t12388877665544332211\r")
        r.run(2 * usb + 2 * frame, step=5)
        assert len(r.heard) == n0 + 1
        late.append(r.heard[-1][0] - frame - arrive)  # from the USB frame to the start on the bus
    assert min(late) >= 0 and max(late) <= CAN_POLL_US + 5
    assert max(late) > 0  # (the pass's own period, not the USB frame, decides)


def test_a_frame_from_the_bus_goes_to_the_host_in_the_next_usb_frame():
    r = Rig()
    r.say(b"O\r")
    r.run(333, step=5)
    r.peer.transmit(0x181, False, False, b"\x01\x02")
    r.run(r.bus.frame_us(False, False, 2), step=5)  # the frame ends; the IRQ pulls due[1] to now
    assert r.app.can.cv[K.CC_RX] == 1 and r.port.tx == bytearray(b"t18120102\r")  # at once, not a period on
    assert r.say(b"", 1000) == b"t18120102\r"


def test_a_simulation_skips_the_idle_ports_passes_on_their_grid():
    """App.wait_us (the bench's scheduler) wakes the loop for the port's pass only when
    it has work, and then at the tick of its grid the board's loop would have used."""
    r = Rig()
    r.say(b"O\r")
    app = r.app
    t0 = app.due[1]
    w = app.wait_us()
    assert 0 < w <= SLOW_US  # only the slow pass's
    parked = app.due[1]
    assert (parked - t0) % CAN_POLL_US == 0 and parked - r.clock.ticks_us() >= CAN_IDLE_PARK
    r.clock.advance(1234)
    r.port.rx += b"t1230\r"  # the host's line arrives between two of the port's passes
    app.poll()
    assert r.heard == [] and app.wait_us() == CAN_POLL_US - 1234 % CAN_POLL_US
    r.clock.advance(app.wait_us())
    app.poll()
    r.clock.advance(1000)
    assert [h[1] for h in r.heard] == [0x123] and (app.due[1] - t0) % CAN_POLL_US == 0
    assert CAN_IDLE_PARK % CAN_POLL_US == 0


def test_the_pump_serves_the_ports_own_pass_while_the_port_is_open():
    r = Rig(fastpath=True)
    app = r.app
    if app.pump is None:
        pytest.skip("this rig's ports do not take the pump")
    calls = []
    real = app.pump
    app.pump = None
    r.say(b"O\r")
    assert app.due[2] == 1

    def pump(ctx, k):
        calls.append(k)
        return real(ctx, k)

    app.pump = pump
    app.run(1)  # (the port's pass the say left due)
    del calls[:]
    app.run(157)  # the clock stands still: the passes all in one call
    assert calls == [157]
    serves, _ = _count_passes(r)
    for _ in range(20):
        r.clock.advance(CAN_POLL_US)
        t = app.due[1]
        app.run(50)
        assert app.due[1] == (t + CAN_POLL_US) & 0x3FFFFFFF  # the port's pass came, a period on
    assert serves == []  # (nothing to do: the pump moved due[1] itself)
    lines = app.can.lines
    r.port.host_send(b"t1231AA\r")
    for _ in range(20):  # (the bytes come in the next USB frame)
        r.clock.advance(CAN_POLL_US)
        app.run(50)
    assert serves and app.can.lines == lines + 1  # a host line (then its TX end): served from the pump's return
    r.say(b"C\r")
    assert app.due[2] == 0
    del calls[:]
    app.due[1] = app.hal.ticks_us()  # (stale: closed, the pump does not look at it)
    app.run(150)
    assert calls == [150]  # closed: the pump as before


@pytest.mark.parametrize("fastpath", [False, True])
def test_the_ports_pass_waits_for_the_bridges_idle_time_at_most_can_defer_us(fastpath):
    """A frame from the bus while a Plus-R transaction is in flight goes to the host after
    the reply has been relayed, not between request and reply; with no reply coming, no
    later than CAN_DEFER_US after the pass fell due (the portable loop and the pump)."""
    r = Rig(fastpath=fastpath)
    app = r.app
    if fastpath and app.pump is None:
        pytest.skip("this rig's ports do not take the pump")
    r.say(b"O\r")
    up = r.hal.up
    down = r.hal.down
    bs = app.bridge.bs
    frame_us = r.bus.frame_us(False, False, 2)
    for reply in (True, False):
        up.out_n = 0
        req = F.encode(2, F.GET_AXIS_STATUS)
        up.rx.write(bytearray(req), len(req), r.hal.ticks_us())
        r.run(100, step=5)
        assert bs[0] == 1  # AWAIT_PC: the request went to the drivers
        r.peer.transmit(0x181, False, False, b"\x01\x02")
        r.run(frame_us, step=5)
        t_due = app.due[1]
        assert app.can.cv[K.CC_RX] >= 1 and app.can.rs[0] != app.can.rs[1]  # in the ring, not served
        if reply:
            r.run(300, step=5)
            assert r.port.tx == b""  # the transaction in flight: the port's pass waits
            rep = F.encode(2, F.GET_AXIS_STATUS, b"\x00\x00\x00\x00\x08")
            down.rx.write(bytearray(rep), len(rep), r.hal.ticks_us())
            r.run(20, step=5)
            assert bs[0] == 0 and up.out_n == len(rep)  # relayed ...
            assert r.port.tx == b"t18120102\r"  # ... and the port's pass came at once after it
        else:
            r.run(CAN_DEFER_US - 10 - (r.hal.ticks_us() - t_due), step=5)
            assert bs[0] == 1 and r.port.tx == b""
            r.run(20, step=5)
            assert bs[0] == 1 and r.port.tx == b"t18120102\r"  # waited CAN_DEFER_US, not the reply timeout
        r.port.host_read()
        r.run(60000)  # (the reply's timeout)


def test_closed_and_idle_the_port_costs_the_slow_pass_one_any():
    r = Rig()
    calls = []
    real_any = r.port.any
    r.port.any = lambda: calls.append(1) or real_any()
    r.run(100000)
    passes = len(calls)
    assert 0 < passes <= 100000 // 10000 + 2  # one a slow pass, and the slow pass no more often


def test_the_recorder_gets_can_frames_both_ways():
    r = Rig()
    if not hasattr(r.app.capture, "can_frame"):
        pytest.skip("jig.capture has no CAN records yet")
    r.app.set_capture(1, r.hal.ticks_us())
    total0 = r.app.capture.cs[12]  # CS_TOTAL
    r.say(b"O\rt1230\r")
    r.peer.transmit(0x181, False, False, b"\x01")
    r.run(5000)
    assert r.app.capture.cs[12] - total0 == 2


def test_a_new_bitrate_is_reported_by_a_hello_record():
    """docs/capture.md: the hello carries the CAN bitrate, so Sn that changes it writes
    a new hello while recording (and the same bitrate again writes none)."""
    from jig import capture as C

    r = Rig()
    r.app.set_capture(1, r.hal.ticks_us())
    cap = r.app.capture
    cs, ring = cap.cs, cap.ring
    total0, head0 = cs[C.CS_TOTAL], cs[C.CS_HEAD]
    assert r.say(b"S4\r") == b"\r"
    assert cs[C.CS_TOTAL] - total0 == 1 and ring[(head0 + 1) & cs[C.CS_MASK]] == C.T_HELLO
    assert r.say(b"S4\r") == b"\r" and cs[C.CS_TOTAL] - total0 == 1
    assert r.app.can.bitrate == 125000


def test_jigctl_stats_prints_a_can_port_block():
    from motorjig.commands import can_block

    r = Rig(params={P.P_CAN_TERMINATION: 0})
    r.say(b"S4\rL\r")
    can = diag.decode_can_counters(r.ask(diag.READ_CAN_COUNTERS))
    text = "\n".join(can_block(can, r.app.params.ram[P.P_CAN_TERMINATION]))
    assert text.startswith("CAN port: open, listen-only, error active, 125000 bit/s, TEC 0, REC 0")
    assert "leave J4-TERM open" in text and "can_rx_frames" in text and "slcan_lines" in text
    r.say(b"C\r")
    can = diag.decode_can_counters(r.ask(diag.READ_CAN_COUNTERS))
    assert can_block(can, 1)[0] == "CAN port: closed, 125000 bit/s"
    assert "fit J4-TERM" in can_block(can, 1)[1]


# --- no allocation: the steady state in the MicroPython VM --------------------------------
def test_no_heap_per_frame_either_way_on_micropython():
    """A frame from the bus to the host, a line from the host to the bus (with its TX
    interrupt), idle passes with the port closed and the open port's own idle passes
    allocate nothing on MicroPython
    (the WebAssembly VM: the IRQ handler runs synchronously there, as a hard IRQ must:
    with no allocation)."""
    import os
    import shutil
    import subprocess

    here = os.path.dirname(os.path.abspath(__file__))
    pkg = os.path.join(here, "wasm", "node_modules", "@micropython", "micropython-webassembly-pyscript")
    if shutil.which("node") is None or not os.path.isdir(pkg):
        pytest.skip("node or the MicroPython WebAssembly package is missing (tools/setup.sh)")
    code = ("import sys\nsys.path.append('/data')\nimport can_probe as c\n"
            "print(c.rx_alloc(300))\nprint(c.tx_alloc(300))\nprint(c.idle_alloc(2000))\n"
            "print(c.open_idle_alloc(2000))\n"
            "print(c.heap_used(lambda: bytearray(16), 10) > 0)\nprint(sys.implementation.name)\n")
    r = subprocess.run(["node", os.path.join(here, "wasm", "run_vm.mjs"),
                        "--file", "bridge_probe.py=" + os.path.join(here, "bridge_probe.py"),
                        "--file", "can_probe.py=" + os.path.join(here, "can_probe.py"), code],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["(0,", "True)"] * 4 + ["True", "micropython"]


def test_can_probe_under_cpython():
    import can_probe

    assert can_probe.rx_alloc(20)[1] and can_probe.tx_alloc(20)[1] and can_probe.idle_alloc(50)[1]
    assert can_probe.open_idle_alloc(50)[1]


def test_the_ports_own_pass_does_a_bounded_piece_of_work():
    """One pass moves at most RX_PER_SERVE frames to the host and reads at most
    IN_PER_SERVE bytes from it (an RS-485 frame behind it waits for no more); the
    rest goes in the next passes, none lost."""
    from jig.canport import IN_PER_SERVE, RX_PER_SERVE

    r = Rig()
    r.say(b"O\r")
    can = r.app.can
    rs = can.rs
    for k in range(10):
        r.peer.transmit(0x100 + k, False, False, b"\x00")
    r.clock.advance(5000)  # on the bus, into the ring: no pass meanwhile
    assert (rs[0] - rs[1]) & 255 == 10
    can.serve(r.app.hal.ticks_us())
    assert (rs[0] - rs[1]) & 255 == 10 - RX_PER_SERVE
    lines = b"".join(b"t%03X10%d\r" % (0x200 + k, k) for k in range(10))  # 8 bytes a line
    r.port.host_send(lines)
    r.clock.advance(2000)  # (in the next USB frame)
    n = can.lines
    can.serve(r.app.hal.ticks_us())
    assert 0 < can.lines - n <= IN_PER_SERVE // 8
    r.run(20000)
    assert rs[0] == rs[1] and can.lines - n == 10
    assert len(r.heard) == 10 and r.port.host_read().count(b"\r") >= 20
