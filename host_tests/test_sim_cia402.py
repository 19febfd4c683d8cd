"""The simulated CiA 402 drive on the simulated CAN bus, driven by a small master made
of raw frames (the test's ``Master``), on the virtual clock: NMT, heartbeat, SDO,
PDOs, EMCY, the power state machine's table, moves, homing, faults, LSS; and its EDS.

Times are where the master sees them: the end of a frame on the wire.
"""

import configparser
import logging
import struct

import pytest
from canopen.objectdictionary import import_od

from motorjig.can import EDS_PATH
from motorjig.sim import cia402 as C
from motorjig.sim import drive402 as D
from motorjig.sim.axis import profile_time, ramp_ms
from motorjig.sim.canbus import CanBus
from motorjig.sim.clock import VirtualClock

NID = 5
MS = 1000.0


class Abort(Exception):
    def __init__(self, code):
        super().__init__("SDO abort 0x%08X" % code)
        self.code = code


class Master:
    """A CANopen master in raw frames: what it sent (with the time it left the wire) and received."""

    def __init__(self, clock, bus):
        self.clock = clock
        self.rx = []  # (t_us, can_id, rtr, data)
        self.tx_done = []  # (t_us, can_id, data)
        self.node = bus.add_node("master", self._rx, self._tx)

    def _rx(self, t, can_id, ext, rtr, data):
        self.rx.append((t, can_id, rtr, bytes(data)))

    def _tx(self, t, ok):
        f = self.node.done
        self.tx_done.append((t, f.can_id, f.data))

    def send(self, cob, data=b"", rtr=False):
        self.node.transmit(cob, False, rtr, bytes(data))

    def frames(self, cob, since=0.0):
        return [(t, d) for t, c, _r, d in self.rx if c == cob and t > since]

    def wait(self, cob, limit_ms=100.0, since=None, pred=None):
        """The first frame on ``cob`` at or after ``since`` (default: now) matching pred."""
        since = self.clock.now if since is None else since

        def found():
            return [f for f in self.frames(cob, since) if pred is None or pred(f[1])]

        self.clock.run_while(lambda: not found(), limit_ms * MS)
        got = found()
        assert got, "no frame on 0x%03X within %g ms" % (cob, limit_ms)
        return got[0]

    def run(self, ms):
        self.clock.advance(ms * MS)

    # --- NMT and SDO
    def nmt(self, cmd, nid=NID):
        self.send(0x000, [cmd, nid])
        self.run(2)

    def sdo(self, req, nid=NID, limit_ms=100.0):
        since = self.clock.now
        self.send(0x600 + nid, req + bytes(8 - len(req)))
        return self.wait(0x580 + nid, limit_ms, since)[1]

    def upload(self, index, sub=0, nid=NID):
        r = self.sdo(struct.pack("<BHB", 0x40, index, sub), nid)
        if r[0] == 0x80:
            raise Abort(struct.unpack_from("<I", r, 4)[0])
        assert struct.unpack_from("<HB", r, 1) == (index, sub)
        if r[0] & 0x02:  # expedited
            return r[4 : 8 - (r[0] >> 2 & 3)]
        size = struct.unpack_from("<I", r, 4)[0]
        out, toggle = b"", 0
        while True:
            r = self.sdo(bytes([0x60 | toggle << 4]), nid)
            if r[0] == 0x80:
                raise Abort(struct.unpack_from("<I", r, 4)[0])
            assert r[0] >> 5 == 0 and (r[0] >> 4 & 1) == toggle
            out += r[1 : 8 - (r[0] >> 1 & 7)]
            toggle ^= 1
            if r[0] & 1:
                assert len(out) == size
                return out

    def download(self, index, sub, data, nid=NID, segmented=False):
        if not segmented and len(data) <= 4:
            n = 4 - len(data)
            r = self.sdo(struct.pack("<BHB", 0x23 | n << 2, index, sub) + data, nid)
            if r[0] == 0x80:
                raise Abort(struct.unpack_from("<I", r, 4)[0])
            assert r[:4] == struct.pack("<BHB", 0x60, index, sub)
            return
        r = self.sdo(struct.pack("<BHBI", 0x21, index, sub, len(data)), nid)
        if r[0] == 0x80:
            raise Abort(struct.unpack_from("<I", r, 4)[0])
        toggle = 0
        for i in range(0, len(data), 7):
            chunk = data[i : i + 7]
            last = i + 7 >= len(data)
            r = self.sdo(bytes([toggle << 4 | (7 - len(chunk)) << 1 | last]) + chunk, nid)
            if r[0] == 0x80:
                raise Abort(struct.unpack_from("<I", r, 4)[0])
            assert r[0] == 0x20 | toggle << 4
            toggle ^= 1

    def get(self, index, sub=0, fmt="<I", nid=NID):
        return struct.unpack(fmt, self.upload(index, sub, nid))[0]

    def set(self, index, sub, fmt, value, nid=NID):
        self.download(index, sub, struct.pack(fmt, value), nid)


def bench(node_id=NID, **kw):
    clock = VirtualClock()
    bus = CanBus(clock, 500000)
    master = Master(clock, bus)
    node = C.Cia402Node(clock, bus, node_id, **kw)
    clock.advance(5 * MS)  # boot-up
    return clock, bus, master, node


def sw(master):
    return master.get(0x6041, 0, "<H")


def state_of(word):
    for name, (mask, value) in D.STATES.items():
        if word & mask == value:
            return name
    return None


# --- the EDS ----------------------------------------------------------------------------------------
def test_eds_loads_with_canopen_without_a_warning(caplog):
    with caplog.at_level(logging.DEBUG, logger="canopen"):
        od = import_od(EDS_PATH, 7)
    assert [r for r in caplog.records if r.levelno >= logging.WARNING] == []
    assert od[0x1000].default & 0xFFFF == 402
    assert od[0x1800][1].default == 0x187 and od[0x1403][1].default == 0x507
    info = od.device_information
    assert info.LSS_supported and info.nr_of_RXPDO == 4 and info.nr_of_TXPDO == 4
    assert 500000 in info.allowed_baudrates and 1000000 in info.allowed_baudrates


def test_eds_describes_every_object_completely():
    eds = configparser.RawConfigParser()
    eds.optionxform = str
    eds.read(EDS_PATH)
    for section in ("FileInfo", "DeviceInfo", "DummyUsage", "MandatoryObjects", "OptionalObjects",
                    "ManufacturerObjects"):
        assert eds.has_section(section), section
    listed = set()
    for section in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        n = eds.getint(section, "SupportedObjects")
        listed |= {int(eds.get(section, str(i)), 16) for i in range(1, n + 1)}
    objects = {int(s, 16) for s in eds.sections() if len(s) == 4}
    assert listed == objects
    for idx in (0x1000, 0x1001, 0x1003, 0x1008, 0x1009, 0x100A, 0x1010, 0x1011, 0x1017, 0x1018, 0x603F, 0x6040,
                0x6041, 0x605A, 0x6060, 0x6061, 0x6062, 0x6064, 0x6065, 0x6066, 0x6067, 0x6068, 0x606C, 0x607A,
                0x607C, 0x607D, 0x6081, 0x6083, 0x6084, 0x6085, 0x6098, 0x6099, 0x609A, 0x60F4, 0x60FD, 0x60FE,
                0x6502):
        assert idx in objects, hex(idx)
    for s in eds.sections():
        if len(s) == 4 or "sub" in s:
            obj_type = int(eds.get(s, "ObjectType"), 0)
            if obj_type == 7:
                for key in ("ParameterName", "DataType", "AccessType", "DefaultValue", "PDOMapping"):
                    assert eds.has_option(s, key), (s, key)
            else:
                assert eds.has_option(s, "SubNumber"), s


# --- NMT, heartbeat --------------------------------------------------------------------------------
def test_boot_up_then_heartbeat_at_its_period():
    clock, bus, master, node = bench(heartbeat_ms=100)
    boot = master.frames(0x705, -1)
    assert boot and boot[0][1] == b"\x00"
    master.run(1000)
    beats = master.frames(0x705, -1)[1:]
    assert [d for _t, d in beats] == [b"\x7f"] * 10
    gaps = {round(b[0] - a[0]) for a, b in zip(beats, beats[1:])}
    assert gaps == {100000}
    master.set(0x1017, 0, "<H", 20)
    t0 = clock.now
    master.run(200)
    assert 9 <= len(master.frames(0x705, t0)) <= 10
    node.set_fault("missed-heartbeat")
    t1 = clock.now
    master.run(200)
    assert master.frames(0x705, t1) == []
    node.clear_faults()
    master.run(100)
    assert master.frames(0x705, clock.now - 100 * MS)


def test_nmt_states_gate_sdo_and_pdos():
    clock, bus, master, node = bench(heartbeat_ms=50)
    assert node.nmt_state == "PRE-OPERATIONAL"
    assert master.get(0x1000) == 0x00020192  # SDO in pre-operational
    t = clock.now
    master.send(0x080)
    master.run(5)
    assert master.frames(0x285, t) == []  # no PDO before operational
    master.nmt(0x01)
    assert node.nmt_state == "OPERATIONAL"
    assert master.wait(0x705, 60)[1] == b"\x05"
    t = clock.now
    master.send(0x080)
    assert master.wait(0x285, 5, t)  # TPDO2 on every SYNC
    master.nmt(0x02)
    assert master.wait(0x705, 60)[1] == b"\x04"
    t = clock.now
    master.send(0x605, struct.pack("<BHB4x", 0x40, 0x1000, 0))
    master.send(0x080)
    master.run(10)
    assert master.frames(0x585, t) == [] and master.frames(0x285, t) == []
    master.nmt(0x80)
    assert master.wait(0x705, 60)[1] == b"\x7f"


def test_reset_node_and_reset_communication():
    clock, bus, master, node = bench()
    master.set(0x6081, 0, "<I", 777)
    master.set(0x1017, 0, "<H", 30)
    t = clock.now
    master.nmt(0x82)  # reset communication: communication objects only
    assert master.wait(0x705, 5, t)[1] == b"\x00"
    assert master.get(0x1017, 0, "<H") == 0 and master.get(0x6081) == 777
    t = clock.now
    master.nmt(0x81, 0)  # reset node, to all nodes
    assert master.wait(0x705, 5, t)[1] == b"\x00"
    assert master.get(0x6081) == 10000


def test_store_and_restore_parameters():
    clock, bus, master, node = bench()
    master.set(0x6081, 0, "<I", 4321)
    with pytest.raises(Abort) as e:
        master.set(0x1010, 1, "<I", 0x12345678)
    assert e.value.code == D.ABORT_STORE
    master.download(0x1010, 1, b"save")
    master.nmt(0x81)
    assert master.get(0x6081) == 4321
    master.download(0x1011, 1, b"load")
    assert master.get(0x6081) == 4321  # restored defaults take effect at the next reset
    master.nmt(0x81)
    assert master.get(0x6081) == 10000


# --- SDO ----------------------------------------------------------------------------------------------
def test_sdo_expedited_upload_and_download():
    clock, bus, master, node = bench()
    r = master.sdo(struct.pack("<BHB", 0x40, 0x1000, 0))
    assert r == bytes([0x43, 0x00, 0x10, 0x00]) + struct.pack("<I", 0x00020192)
    r = master.sdo(struct.pack("<BHB", 0x40, 0x6060, 0))
    assert r[0] == 0x4F and r[4] == 1  # one byte: n = 3
    master.set(0x6083, 0, "<I", 250000)
    assert master.get(0x6083) == 250000
    assert master.get(0x1018, 4) == D.SERIAL_BASE + NID
    master.set(0x607A, 0, "<i", -12345)
    assert master.get(0x607A, 0, "<i") == -12345


def test_sdo_segmented_upload_of_the_device_name_and_segmented_download():
    clock, bus, master, node = bench()
    t = clock.now
    assert master.upload(0x1008) == b"MotorJig CiA 402 drive (sim)"
    replies = master.frames(0x585, t)
    assert replies[0][1][0] == 0x41 and struct.unpack_from("<I", replies[0][1], 4)[0] == 28
    toggles = [d[0] >> 4 & 1 for _t, d in replies[1:]]
    assert toggles == [0, 1, 0, 1] and replies[-1][1][0] & 1
    master.download(0x6081, 0, struct.pack("<I", 31337), segmented=True)
    assert master.get(0x6081) == 31337
    assert master.upload(0x100A) == b"motorjig-cia402 1.0"


ABORT_CASES = {
    "no object": (lambda m: m.get(0x2345), D.ABORT_NO_OBJECT),
    "no sub-index": (lambda m: m.get(0x1018, 9), D.ABORT_NO_SUBINDEX),
    "read-only": (lambda m: m.set(0x6041, 0, "<H", 1), D.ABORT_READ_ONLY),
    "const": (lambda m: m.download(0x1008, 0, b"x"), D.ABORT_READ_ONLY),
    "write-only": (lambda m: m.get(0x2001), D.ABORT_WRITE_ONLY),
    "length": (lambda m: m.set(0x6081, 0, "<H", 5), D.ABORT_LENGTH),
    "segmented length": (lambda m: m.download(0x6081, 0, b"12345678", segmented=True), D.ABORT_LENGTH),
    "value": (lambda m: m.set(0x6060, 0, "<b", 2), D.ABORT_VALUE),
    "value too high": (lambda m: m.set(0x1600, 0, "<B", 9), D.ABORT_VALUE_HIGH),
    "block upload": (lambda m: m.sdo(struct.pack("<BHB", 0xA0, 0x1008, 0)), D.ABORT_COMMAND),
    "block download": (lambda m: m.sdo(struct.pack("<BHB", 0xC2, 0x6081, 0)), D.ABORT_COMMAND),
    "segment without transfer": (lambda m: m.sdo(b"\x60"), D.ABORT_COMMAND),
}


@pytest.mark.parametrize("case", list(ABORT_CASES))
def test_sdo_aborts_with_the_cia301_code(case):
    clock, bus, master, node = bench()
    fn, code = ABORT_CASES[case]
    try:
        r = fn(master)
    except Abort as e:
        assert e.code == code
    else:  # the raw requests
        assert r[0] == 0x80 and struct.unpack_from("<I", r, 4)[0] == code


def test_sdo_toggle_bit_and_timeout_aborts():
    clock, bus, master, node = bench()
    master.sdo(struct.pack("<BHB", 0x40, 0x1008, 0))
    r = master.sdo(b"\x70")  # toggle 1 first: not alternated
    assert r[0] == 0x80 and struct.unpack_from("<I", r, 4)[0] == D.ABORT_TOGGLE
    r = master.sdo(struct.pack("<BHB", 0x40, 0x1008, 0))
    assert r[0] == 0x41
    r = master.wait(0x585, 1500, pred=lambda d: d[0] == 0x80)[1]  # the client went silent
    assert struct.unpack_from("<HBI", r, 1) == (0x1008, 0, D.ABORT_TIMEOUT)


def test_sdo_abort_fault_answers_every_request_with_its_code():
    clock, bus, master, node = bench()
    node.set_fault("sdo-abort", "0x08000021")
    with pytest.raises(Abort) as e:
        master.get(0x1000)
    assert e.value.code == 0x08000021
    node.clear_faults()
    assert master.get(0x1000) == 0x00020192


# --- PDOs ------------------------------------------------------------------------------------------------
def remap_tpdo(master, n, trans_type, entries, event_ms=None):
    """As python-canopen's PdoMap.save does: disable, settings, count 0, entries, count, enable."""
    cob = 0x180 + 0x100 * n + NID
    master.set(0x1800 + n, 1, "<I", cob | 0x80000000)
    master.set(0x1800 + n, 2, "<B", trans_type)
    if event_ms is not None:
        master.set(0x1800 + n, 5, "<H", event_ms)
    master.set(0x1A00 + n, 0, "<B", 0)
    for i, e in enumerate(entries, 1):
        master.set(0x1A00 + n, i, "<I", e)
    master.set(0x1A00 + n, 0, "<B", len(entries))
    master.set(0x1800 + n, 1, "<I", cob)


def test_pdo_remap_then_sync_driven_tpdo_content():
    clock, bus, master, node = bench()
    # mapping refused while the PDO is valid, a non-mappable object, too long a PDO
    with pytest.raises(Abort) as e:
        master.set(0x1A02, 0, "<B", 0)
    assert e.value.code == D.ABORT_UNSUPPORTED
    master.set(0x1802, 1, "<I", 0x80000000 | 0x385)
    master.set(0x1A02, 0, "<B", 0)
    with pytest.raises(Abort) as e:
        master.set(0x1A02, 1, "<I", 0x10080008)
    assert e.value.code == D.ABORT_NOT_MAPPABLE
    for i in (1, 2, 3):
        master.set(0x1A02, i, "<I", 0x60640020)
    with pytest.raises(Abort) as e:
        master.set(0x1A02, 0, "<B", 3)
    assert e.value.code == D.ABORT_PDO_LENGTH
    remap_tpdo(master, 2, 2, [0x60640020, 0x60410010, 0x60610008])  # every 2nd SYNC
    node.motion.pos = 4242.0
    master.nmt(0x01)
    t = clock.now
    for _ in range(4):
        master.send(0x080)
        master.run(5)
    got = master.frames(0x385, t)
    assert len(got) == 2
    assert got[0][1] == struct.pack("<iHb", 4242, 0x0240, 1)  # switch on disabled, remote
    assert master.frames(0x285, t) and len(master.frames(0x285, t)) == 4


def test_event_driven_tpdo_event_timer_and_inhibit_time():
    clock, bus, master, node = bench()
    remap_tpdo(master, 3, 255, [0x60640020], event_ms=100)
    master.nmt(0x01)
    t = clock.now
    master.run(1000)
    got = master.frames(0x485, t)
    assert 10 <= len(got) <= 11
    assert {round((b[0] - a[0]) / MS) for a, b in zip(got, got[1:])} == {100}
    # inhibit: a move changes the position every ms; TPDO4 at most every 10 ms
    master.set(0x1803, 1, "<I", 0x80000485)
    master.set(0x1803, 3, "<H", 100)  # 100 x 100 µs
    master.set(0x1803, 5, "<H", 0)
    master.set(0x1803, 1, "<I", 0x485)
    enable(master)
    t = clock.now
    move(master, 5000)
    master.run(300)
    got = master.frames(0x485, t)
    gaps = [b[0] - a[0] for a, b in zip(got, got[1:])]
    assert len(got) > 10 and min(gaps) >= 10 * MS - 1


def rpdo1(master, cw, mode=1):
    master.send(0x200 + NID, struct.pack("<Hb", cw, mode))
    master.run(2)


def enable(master, mode=1):
    """RPDO1 controlword + mode to OPERATION ENABLED (the node operational)."""
    master.nmt(0x01)
    for cw in (0x06, 0x07, 0x0F):
        rpdo1(master, cw, mode)


def move(master, target, cw=0x0F):
    master.set(0x607A, 0, "<i", target)
    rpdo1(master, cw | 0x10)
    rpdo1(master, cw)


def test_rpdo_controlword_drives_the_state_machine_and_tpdo1_shows_it():
    clock, bus, master, node = bench()
    master.nmt(0x01)
    t = clock.now
    rpdo1(master, 0x06)
    assert node.state == D.READY
    last = master.frames(0x185, t)[-1][1]
    assert struct.unpack("<Hb", last) == (0x0221, 1)
    rpdo1(master, 0x07)
    rpdo1(master, 0x0F, 3)
    assert node.state == D.OPERATION_ENABLED and master.get(0x6061, 0, "<b") == 3
    last = master.frames(0x185, t)[-1][1]
    assert struct.unpack("<Hb", last)[0] & 0x6F == 0x27 and last[2] == 3


# --- the power state machine ------------------------------------------------------------------------
CW = {"DISABLE VOLTAGE": 0x00, "QUICK STOP": 0x02, "SHUTDOWN": 0x06, "SWITCH ON": 0x07, "ENABLE OPERATION": 0x0F,
      D.FAULT_RESET: 0x80}
PATH = {  # controlwords from SWITCH ON DISABLED to a state
    D.SWITCH_ON_DISABLED: (),
    D.READY: (0x06,),
    D.SWITCHED_ON: (0x06, 0x07),
    D.OPERATION_ENABLED: (0x06, 0x07, 0x0F),
    D.QUICK_STOP_ACTIVE: (0x06, 0x07, 0x0F, 0x02),
}


@pytest.mark.parametrize("step", sorted(D.TRANSITIONS, key=lambda k: int(D.TRANSITIONS[k][1].split("+")[0])),
                         ids=lambda k: "%s-%s" % k)
def test_every_transition_of_the_power_state_machine(step):
    clock, bus, master, node = bench()
    start, command = step
    new, label = D.TRANSITIONS[step]
    master.set(0x605A, 0, "<h", 6)  # quick stop, then stay in QUICK STOP ACTIVE (for 16)
    if start == D.FAULT:
        for cw in PATH[D.OPERATION_ENABLED]:
            master.set(0x6040, 0, "<H", cw)
        node.fault(D.EMCY_OVERCURRENT, D.ERR_CURRENT)
    else:
        for cw in PATH[start]:
            master.set(0x6040, 0, "<H", cw)
    assert state_of(sw(master)) == start
    master.set(0x6040, 0, "<H", CW[command])
    word = sw(master)
    assert state_of(word) == new
    mask, value = D.STATES[new]
    assert word & mask == value
    assert node.transitions[-1][1] == label


def test_commands_outside_the_table_change_nothing():
    clock, bus, master, node = bench()
    for cw in (0x0F, 0x07, 0x80):  # enable / switch on from SWITCH ON DISABLED; fault reset without a fault
        master.set(0x6040, 0, "<H", cw)
        assert state_of(sw(master)) == D.SWITCH_ON_DISABLED
    master.set(0x6040, 0, "<H", 0x06)
    master.set(0x6040, 0, "<H", 0x0F)  # 3+4
    assert state_of(sw(master)) == D.OPERATION_ENABLED


def test_quick_stop_ramps_down_then_switch_on_disabled():
    clock, bus, master, node = bench()
    enable(master)
    master.set(0x6081, 0, "<I", 20000)
    move(master, 100000)
    master.run(500)
    assert node.motion.moving
    rpdo1(master, 0x02)  # 0x605A = 2: quick stop deceleration 0x6085, then switch on disabled
    assert node.state == D.QUICK_STOP_ACTIVE and node.motion.moving
    master.run(30)
    assert node.state == D.SWITCH_ON_DISABLED and not node.motion.moving
    assert [lab for _t, lab in node.transitions[-2:]] == ["11", "12"]


# --- motion ---------------------------------------------------------------------------------------------
def test_profile_position_move_handshake_target_reached_and_duration():
    clock, bus, master, node = bench()
    enable(master)
    master.set(0x6081, 0, "<I", 10000)
    master.set(0x6083, 0, "<I", 50000)
    master.set(0x6084, 0, "<I", 40000)
    master.set(0x607A, 0, "<i", 20000)
    t = clock.now
    rpdo1(master, 0x1F)
    t_cmd = [tt for tt, cob, d in master.tx_done if cob == 0x205 and d[0] == 0x1F][-1]
    words = [struct.unpack_from("<H", d)[0] for _t, d in master.frames(0x185, t)]
    assert words[-1] & D.SW_BIT12 and not words[-1] & D.SW_TARGET_REACHED  # set-point acknowledged, moving
    rpdo1(master, 0x0F)
    assert not master.frames(0x185, clock.now - 2 * MS)[-1][1][1] & 0x10  # acknowledge cleared with bit 4
    t_done, d = master.wait(0x185, 5000, pred=lambda d: d[1] & 0x04)  # bit 10
    expect = profile_time(20000, 10000, ramp_ms(10000, 50000), ramp_ms(10000, 40000))
    assert (t_done - t_cmd) / 1e6 == pytest.approx(expect, abs=0.003)
    word = struct.unpack_from("<H", d)[0]
    assert word & 0x6F == 0x27 and not word & D.SW_BIT13 and not word & D.SW_BIT12
    assert master.get(0x6064, 0, "<i") == 20000 and master.get(0x60F4, 0, "<i") == 0
    t = clock.now
    master.send(0x080)
    assert struct.unpack("<Hi", master.wait(0x285, 5, t)[1])[1] == 20000
    move(master, -5000, 0x4F)  # relative to the last target
    master.wait(0x185, 5000, pred=lambda d: d[1] & 0x04)
    assert master.get(0x6064, 0, "<i") == 15000


def test_profile_velocity_reaches_its_speed():
    clock, bus, master, node = bench()
    enable(master, 3)
    master.set(0x60FF, 0, "<i", -8000)
    master.wait(0x185, 1000, pred=lambda d: d[1] & 0x04)
    assert master.get(0x606C, 0, "<i") == -8000
    master.set(0x60FF, 0, "<i", 0)
    master.wait(0x185, 1000, pred=lambda d: d[1] & 0x14 == 0x14)  # target reached, speed 0
    assert not node.motion.moving


def test_homing_finds_the_home_switch_and_sets_the_home_offset():
    clock, bus, master, node = bench()
    master.set(0x6098, 0, "<b", 19)
    master.set(0x607C, 0, "<i", 1234)
    enable(master, 6)
    rpdo1(master, 0x1F, 6)
    assert node.homing == "search"
    t, d = master.wait(0x185, 3000, pred=lambda d: d[1] & 0x14 == 0x14)  # attained + target reached
    assert master.get(0x6064, 0, "<i") == 1234
    assert master.get(0x60FD) & D.IN_HOME
    # the home switch broken: the homing gives up with the homing error
    node.set_fault("no-origin")
    rpdo1(master, 0x0F, 6)
    rpdo1(master, 0x1F, 6)
    master.wait(0x185, 10000, pred=lambda d: d[1] & 0x20)
    assert node.homing == "error"


# --- faults, EMCY ---------------------------------------------------------------------------------------
def test_following_error_fault_sends_emcy_then_fault_reset():
    clock, bus, master, node = bench()
    node.set_fault("step-out", 5000)  # the Plus-R name works too
    enable(master)
    master.set(0x6081, 0, "<I", 20000)
    t = clock.now
    move(master, 100000)
    t_emcy, d = master.wait(0x085, 2000, t)
    code, reg = struct.unpack_from("<HB", d)
    assert code == 0x8611 and reg & D.ERR_GENERIC and len(d) == 8
    master.run(100)
    assert state_of(sw(master)) == D.FAULT and node.transitions[-2][1] == "13"
    assert master.get(0x603F, 0, "<H") == 0x8611 and master.get(0x1001, 0, "<B") == reg
    assert master.get(0x1003, 0, "<B") == 1 and master.get(0x1003, 1) == 0x8611
    node.clear_faults()
    t = clock.now
    rpdo1(master, 0x80)
    assert master.wait(0x085, 10, t)[1] == bytes(8)  # EMCY 0x0000: error reset
    assert state_of(sw(master)) == D.SWITCH_ON_DISABLED
    assert master.get(0x1001, 0, "<B") == 0 and master.get(0x603F, 0, "<H") == 0
    master.set(0x1003, 0, "<B", 0)
    assert master.get(0x1003, 0, "<B") == 0


def test_overcurrent_mid_move():
    clock, bus, master, node = bench()
    node.set_fault("overcurrent", 50)
    enable(master)
    t = clock.now
    move(master, 50000)
    t_start = [tt for tt, cob, d in master.tx_done if cob == 0x205 and d[0] & 0x10][-1]
    t_emcy, d = master.wait(0x085, 500, t)
    assert struct.unpack_from("<HB", d) == (0x2310, D.ERR_GENERIC | D.ERR_CURRENT)
    assert (t_emcy - t_start) / MS == pytest.approx(50, abs=2)
    master.run(100)
    assert node.state == D.FAULT and not node.motion.moving


def test_sluggish_motor_takes_longer():
    clock, bus, master, node = bench()
    node.set_fault("sluggish", 2)
    enable(master)
    t = clock.now
    move(master, 10000)
    t_start = [tt for tt, cob, d in master.tx_done if cob == 0x205 and d[0] & 0x10][-1]
    t_done, _d = master.wait(0x185, 5000, t, pred=lambda d: d[1] & 0x04)
    expect = 2 * profile_time(10000, 10000, ramp_ms(10000, 100000), ramp_ms(10000, 100000))
    assert (t_done - t_start) / 1e6 == pytest.approx(expect, abs=0.005)


def test_fault_names_and_values():
    with pytest.raises(ValueError, match="unknown fault"):
        C.parse_fault("nope")
    with pytest.raises(ValueError, match="dead-input"):
        C.parse_fault("dead-input", 40)
    assert C.parse_fault("step-out", "300") == ("following-error", 300)
    clock, bus, master, node = bench()
    node.set_fault("dead-input", 2)
    node.mech = node.origin_pos
    assert not master.get(0x60FD) & D.IN_HOME
    assert node.active_faults() == ["dead-input=2"]


# --- LSS -------------------------------------------------------------------------------------------------
def lss(master, data):
    since = master.clock.now
    master.send(0x7E5, bytes(data) + bytes(8 - len(data)))
    master.run(2)
    got = master.frames(0x7E4, since)
    return got[0][1] if got else None


def fast_scan(master):
    """CiA 305 fast scan, as python-canopen's LssMaster.fast_scan does it."""
    def probe(id_number, bit, sub, nxt):
        return lss(master, struct.pack("<BIBBB", 0x51, id_number, bit, sub, nxt)) is not None

    if not probe(0, 0x80, 0, 0):
        return None
    ids = [0] * 4
    for sub in range(4):
        for bit in range(31, -1, -1):
            if not probe(ids[sub], bit, sub, sub):
                ids[sub] |= 1 << bit
        if not probe(ids[sub], 0, sub, (sub + 1) & 3):
            return None
    return ids


def test_lss_fast_scan_finds_an_unconfigured_node_and_gives_it_an_id():
    clock, bus, master, node = bench()  # node 5, configured
    other = C.Cia402Node(clock, bus, C.UNCONFIGURED, serial=0x0BADCAFE)
    master.run(10)
    assert master.frames(0x7FF, -1) == [] and other.nmt_state == "INITIALISING"  # no boot-up without an id
    assert master.sdo(struct.pack("<BHB", 0x40, 0x1000, 0), NID)  # node 5 answers as usual
    assert lss(master, [0x4C]) == bytes([0x50]) + bytes(7)  # a non-configured node is there
    ids = fast_scan(master)
    assert ids == [0x4D4A4947, 0x402, 0x00010000, 0x0BADCAFE]
    assert other.lss_mode == 1 and node.lss_mode == 0
    assert lss(master, [0x5D]) == struct.pack("<BI3x", 0x5D, 0x0BADCAFE)  # inquire serial
    assert lss(master, [0x11, 9]) == bytes([0x11, 0]) + bytes(6)
    assert lss(master, [0x13, 0, 2]) == bytes([0x13, 0]) + bytes(6)
    assert lss(master, [0x17]) == bytes([0x17, 0]) + bytes(6)
    t = clock.now
    lss(master, [0x04, 0])  # back to waiting: the new id takes effect
    assert master.wait(0x709, 10, t)[1] == b"\x00"
    assert master.get(0x1018, 4, nid=9) == 0x0BADCAFE
    assert master.get(0x1800, 1, nid=9) == 0x189
    assert fast_scan(master) is None  # nobody unconfigured is left


def test_lss_switch_state_selective_and_inquire_node_id():
    clock, bus, master, node = bench()
    ident = (0x4D4A4947, 0x402, 0x00010000, D.SERIAL_BASE + NID)
    for cs, value in zip((0x40, 0x41, 0x42), ident):
        assert lss(master, struct.pack("<BI", cs, value)) is None
    assert lss(master, struct.pack("<BI", 0x43, ident[3])) == bytes([0x44]) + bytes(7)
    assert lss(master, [0x5E]) == bytes([0x5E, NID]) + bytes(6)
    assert lss(master, [0x11, 200]) == bytes([0x11, 1]) + bytes(6)  # out of range
