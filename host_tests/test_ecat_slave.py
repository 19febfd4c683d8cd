"""The simulated EtherCAT slaves on the bench's virtual clock, frame by frame (no root, no network).

What SOEM relies on is checked in test_ecat_pysoem.py against the running bench; here each rule is
pinned down on its own: addressing and working counters, the SII and its EEPROM interface, the
AL state machine's refusals, the mailbox and CoE SDO transfers (expedited, normal, segmented,
aborts), logical process data through the FMMUs, the watchdog, and garbage that never wedges.
"""

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motorjig.ecat import esi, frame as F, sii
from motorjig.sim.clock import VirtualClock
from motorjig.sim.ecat_bus import Segment
from motorjig.sim.ecat_servo import ESI_PATH, EcatServo

DEVICE = esi.read(ESI_PATH)[0]


def line(n=2):
    clock = VirtualClock()
    servos = [EcatServo(clock, k, clock_offset_ns=k * 1000) for k in range(n)]
    return clock, servos, Segment(servos)


def send(seg, *datagrams):
    out = seg.process(F.build(list(datagrams)))
    return F.parse(out)


def dg(cmd, adp=0, ado=0, data=b"", n=None, logical=None):
    return F.Datagram(cmd, adp, ado, data if n is None else bytes(n), logical=logical)


def test_broadcast_read_counts_the_slaves_and_auto_increment_addresses_one():
    _c, _s, seg = line(3)
    (d,) = send(seg, dg("BRD", ado=0x0000, n=2))
    assert d.wkc == 3 and d.adp == 3
    (d,) = send(seg, dg("APWR", adp=0xFFFF, ado=0x0010, data=struct.pack("<H", 0x1002)))  # position 1
    assert d.wkc == 1
    (d,) = send(seg, dg("FPRD", adp=0x1002, ado=0x0010, n=2))
    assert d.wkc == 1 and struct.unpack("<H", d.data)[0] == 0x1002
    (d,) = send(seg, dg("FPRD", adp=0x1003, ado=0x0010, n=2))
    assert d.wkc == 0  # nobody has that address


def test_read_only_registers_keep_their_value_and_read_write_counts_three():
    _c, _s, seg = line(1)
    (d,) = send(seg, dg("APWR", ado=0x0000, data=b"\x55\x55"))  # the ESC type: read only
    assert d.wkc == 1
    (d,) = send(seg, dg("APRD", ado=0x0000, n=1))
    assert d.data[0] == 0xC8
    (d,) = send(seg, dg("APRW", ado=0x0010, data=struct.pack("<H", 7)))
    assert d.wkc == 3 and struct.unpack("<H", d.data)[0] == 0  # the old value comes back


def eeprom_read(seg, word):
    send(seg, dg("APWR", ado=0x0502, data=struct.pack("<HI", 0x0100, word)))
    (d,) = send(seg, dg("APRD", ado=0x0508, n=8))
    return bytes(d.data)


def test_the_sii_is_read_through_the_eeprom_registers_as_the_esi_says():
    _c, servos, seg = line(1)
    (d,) = send(seg, dg("APRD", ado=0x0502, n=2))
    assert struct.unpack("<H", d.data)[0] & 0x0040  # 8 bytes a read
    ident = eeprom_read(seg, 0x08)
    assert struct.unpack("<II", ident) == (DEVICE.vendor_id, DEVICE.product_code)
    image = b"".join(eeprom_read(seg, w) for w in range(0, 1024, 4))
    assert image == bytes(servos[0].esc.sii)
    assert sii.fields(image)["checksum_ok"] and sii.device_name(image) == "MotorJig ECAT servo"
    kinds = [k for k, _d in sii.categories(image)]
    assert kinds == [sii.CAT_STRINGS, sii.CAT_GENERAL, sii.CAT_FMMU, sii.CAT_SYNCM, sii.CAT_TXPDO, sii.CAT_RXPDO]


def test_the_sii_checksum_is_the_specifications_crc8():
    assert sii.crc8(bytes.fromhex("0501440A00000000") + bytes(6)) == sii.image(DEVICE)[14]
    assert sii.crc8(b"") == 0xFF


def set_mailbox(seg, ok=True):
    rx, tx = esi.sm_of(DEVICE, "MBoxOut")[1], esi.sm_of(DEVICE, "MBoxIn")[1]
    send(seg, dg("APWR", ado=0x0800, data=struct.pack("<HHBBBB", rx.start, rx.size if ok else 64, 0x26, 0, 1, 0)))
    send(seg, dg("APWR", ado=0x0808, data=struct.pack("<HHBBBB", tx.start, tx.size, 0x22, 0, 1, 0)))


def al(seg, state):
    send(seg, dg("APWR", ado=0x0120, data=struct.pack("<H", state)))
    (d,) = send(seg, dg("APRD", ado=0x0130, n=6))
    status, _r, code = struct.unpack("<HHH", d.data)
    return status, code


def test_the_al_state_machine_refuses_with_the_codes_a_slave_gives():
    _c, _s, seg = line(1)
    assert al(seg, 8) == (0x11, 0x0011)  # INIT -> OP: invalid requested state change, error shown
    assert al(seg, 2) == (0x11, 0x0011)  # not acknowledged: ignored
    set_mailbox(seg, ok=False)
    assert al(seg, 2 | 0x10) == (0x11, 0x0016)  # invalid mailbox configuration
    set_mailbox(seg)
    assert al(seg, 2 | 0x10) == (0x02, 0)
    assert al(seg, 4) == (0x12, 0x001D)  # no process-data sync managers: invalid output configuration
    assert al(seg, 3 | 0x10) == (0x12, 0x0013)  # BOOT is not supported
    assert al(seg, 0x0F | 0x10) == (0x12, 0x0012)  # unknown state
    assert al(seg, 1 | 0x10) == (0x01, 0)


def mailbox(seg, coe_body, counter=1):
    rx, tx = esi.sm_of(DEVICE, "MBoxOut")[1], esi.sm_of(DEVICE, "MBoxIn")[1]
    msg = struct.pack("<HHBB", len(coe_body), 0, 0, 3 | counter << 4) + coe_body
    (d,) = send(seg, dg("APWR", ado=rx.start, data=msg.ljust(rx.size, b"\x00")))
    assert d.wkc == 1
    (d,) = send(seg, dg("APRD", ado=0x080D, n=1))
    assert d.data[0] & 0x08  # the reply is waiting
    (d,) = send(seg, dg("APRD", ado=tx.start, n=tx.size))
    assert d.wkc == 1
    length = struct.unpack_from("<H", d.data, 0)[0]
    return bytes(d.data[6:6 + length])


def sdo(cmd, index, sub, data=b""):
    return struct.pack("<HBHB", 2 << 12, cmd, index, sub) + data.ljust(4, b"\x00")


def preop():
    clock, servos, seg = line(1)
    set_mailbox(seg)
    assert al(seg, 2) == (0x02, 0)
    return clock, servos[0], seg


def test_coe_sdo_expedited_normal_and_abort():
    _c, servo, seg = preop()
    reply = mailbox(seg, sdo(0x40, 0x6081, 0))
    assert reply[2] == 0x43 and struct.unpack_from("<I", reply, 6)[0] == servo.read(0x6081)  # expedited
    reply = mailbox(seg, sdo(0x40, 0x1008, 0))
    size = struct.unpack_from("<I", reply, 6)[0]
    assert reply[2] == 0x41 and reply[10:10 + size].decode() == servo.read(0x1008)  # normal
    reply = mailbox(seg, sdo(0x23, 0x6081, 0, struct.pack("<I", 4321)))
    assert reply[2] == 0x60 and servo.read(0x6081) == 4321
    reply = mailbox(seg, sdo(0x40, 0x2345, 0))
    assert struct.unpack_from("<H", reply, 0)[0] >> 12 == 2 and reply[2] == 0x80  # an abort is an SDO request
    assert struct.unpack_from("<I", reply, 6)[0] == 0x06020000
    reply = mailbox(seg, sdo(0x50, 0x1C12, 0))  # complete access: not offered
    assert struct.unpack_from("<I", reply, 6)[0] == 0x06010000


def test_coe_segmented_upload_when_the_mailbox_is_too_small():
    _c, servo, seg = preop()
    servo.sdo.room = 8  # as a slave with a tiny mailbox would
    servo.sdo.segment_room = 10
    text = servo.read(0x1008)
    reply = mailbox(seg, sdo(0x40, 0x1008, 0))
    got = reply[10:18]
    toggle = 0
    for counter in range(2, 10):
        reply = mailbox(seg, struct.pack("<HB", 2 << 12, 0x60 | toggle << 4) + bytes(7), counter % 7 + 1)
        chunk = reply[3:]
        if reply[2] & 1:
            got += chunk[:len(text) - len(got)]
            break
        got += chunk
        toggle ^= 1
    assert got.decode() == text


def test_logical_process_data_through_the_fmmus_counts_one_for_inputs_and_two_for_outputs():
    clock, servo, seg = preop()
    out_size, in_size = servo.pdo_sizes()
    o, i = esi.sm_of(DEVICE, "Outputs")[1], esi.sm_of(DEVICE, "Inputs")[1]
    send(seg, dg("APWR", ado=0x0810, data=struct.pack("<HHBBBB", o.start, out_size, 0x64, 0, 1, 0)))
    send(seg, dg("APWR", ado=0x0818, data=struct.pack("<HHBBBB", i.start, in_size, 0x20, 0, 1, 0)))
    send(seg, dg("APWR", ado=0x0600, data=struct.pack("<IHBBHBBB3x", 0x10000, out_size, 0, 7, o.start, 0, 2, 1)))
    send(seg, dg("APWR", ado=0x0610, data=struct.pack("<IHBBHBBB3x", 0x10000 + out_size, in_size, 0, 7, i.start,
                                                      0, 1, 1)))
    assert al(seg, 4) == (0x04, 0)
    assert al(seg, 8) == (0x08, 0)
    (d,) = send(seg, dg("LRW", data=struct.pack("<HiiB", 0x06, 0, 0, 8).ljust(out_size + in_size, b"\x00"),
                        logical=0x10000))
    assert d.wkc == 3
    sw = struct.unpack_from("<H", d.data, out_size)[0]
    assert sw & 0x4F == 0x40  # SWITCH ON DISABLED: read before the shutdown command acted
    (d,) = send(seg, dg("LRD", n=out_size + in_size, logical=0x10000))
    assert d.wkc == 1 and struct.unpack_from("<H", d.data, out_size)[0] & 0x6F == 0x21  # READY TO SWITCH ON


def test_the_watchdog_drops_to_safeop_and_the_drive_faults_when_outputs_stop():
    clock, servo, seg = preop()
    out_size, in_size = servo.pdo_sizes()
    o, i = esi.sm_of(DEVICE, "Outputs")[1], esi.sm_of(DEVICE, "Inputs")[1]
    send(seg, dg("APWR", ado=0x0810, data=struct.pack("<HHBBBB", o.start, out_size, 0x64, 0, 1, 0)))
    send(seg, dg("APWR", ado=0x0818, data=struct.pack("<HHBBBB", i.start, in_size, 0x20, 0, 1, 0)))
    al(seg, 4)
    al(seg, 8)
    for cw in (0x06, 0x07, 0x0F):
        send(seg, dg("APWR", ado=o.start, data=struct.pack("<HiiB", cw, 0, 5000, 9).ljust(out_size, b"\x00")))
        clock.advance(1000)
    assert servo.velocity_actual() == 5000
    clock.advance(150000)  # 150 ms without outputs: past the 100 ms watchdog
    (d,) = send(seg, dg("APRD", ado=0x0130, n=6))
    assert struct.unpack_from("<HHH", d.data) == (0x14, 0, 0x001B)
    assert servo.state == "FAULT" and servo.velocity_actual() == 0 and servo.emcys[-1][1] == 0x8130


def test_a_link_down_ends_the_line_before_the_slave_and_lost_frames_come_back_as_none():
    _c, servos, seg = line(3)
    servos[1].set_fault("link-down")
    (d,) = send(seg, dg("BRD", n=2))
    assert d.wkc == 1
    (d,) = send(seg, dg("APRD", ado=0x0110, n=2))
    assert struct.unpack("<H", d.data)[0] & 0x0C00 == 0x0400  # port 1 closed
    servos[1].clear_faults()
    servos[2].set_fault("lost-frames", 2)
    assert [seg.process(F.build([dg("BRD", n=2)])) is None for _ in range(4)].count(True) == 0  # only in OP
    servos[2].esc.set_al_status(8, False, 0)  # as if the master had taken it to OP
    assert [seg.process(F.build([dg("BRD", n=2)])) is None for _ in range(4)].count(True) == 2


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_garbage_never_wedges_the_segment(raw):
    _c, _s, seg = line(2)
    frame = b"\xff" * 6 + b"\x02" * 6 + b"\x88\xa4" + raw
    seg.process(frame)  # answered or dropped, never an exception
    (d,) = send(seg, dg("BRD", n=2))
    assert d.wkc == 2


def test_an_unknown_fault_or_a_bad_value_is_one_sentence():
    _c, servos, _seg = line(1)
    with pytest.raises(ValueError, match="unknown fault 'nope'"):
        servos[0].set_fault("nope")
    with pytest.raises(ValueError, match="refuse-op: expected an AL status code"):
        servos[0].set_fault("refuse-op", "x")


def test_without_root_the_bench_says_what_to_run_in_one_sentence(monkeypatch, capsys):
    from motorjig.sim import ecat_bench
    from motorjig.sim.ecat_bus import Wire

    monkeypatch.setattr("os.geteuid", lambda: 1000)
    why = Wire.check_permissions()
    assert why.startswith("the EtherCAT bench makes a network namespace") and "run it as root" in why
    assert ecat_bench.main(["--slaves", "2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "run it as root (sudo)" in err and "Traceback" not in err


@pytest.mark.parametrize("argv, said", [
    (["--slaves", "0"], "--slaves must be 1..64, got 0"),
    (["--fault", "5:overcurrent"], "--fault: slave position 5 is not on the bus (0..1)"),
    (["--fault", "x:overcurrent"], "is not a slave position"),
    (["--fault", "refuse-op=abc"], "refuse-op: expected an AL status code"),
])
def test_bad_bench_options_are_one_sentence(argv, said, capsys):
    from motorjig.sim import ecat_bench

    assert ecat_bench.main(argv) == 2
    err = capsys.readouterr().err
    assert said in err and err.count("\n") == 1
