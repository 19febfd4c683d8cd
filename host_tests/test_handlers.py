"""Frames for the jig's own id, answered locally (through the bench: the PC's view)."""

import struct

import pytest

from jig import diag
from jig import frame as F
from jig import params as P
from motorjig.sim import SimBench


@pytest.fixture
def b():
    return SimBench(driver_ids=(2, 3))


def ask(b, ftype, data=b"", slave=None):
    wire, r = b.request(b.jig_id if slave is None else slave, ftype, data)
    assert wire is not None, "no reply to 0x%02X" % ftype
    return r


def test_discovery_frames_have_documented_lengths(b):
    assert ask(b, F.GET_COMMAND_POS) == b"\x00" + bytes(4)
    assert ask(b, F.GET_AXIS_STATUS) == b"\x00" + bytes(4)
    assert ask(b, F.GET_ALL_STATUS) == b"\x00" + bytes(32)
    info = ask(b, F.GET_SLAVE_INFO)
    assert info[:2] == bytes([0, diag.SLAVE_TYPE]) and info[-1] == 0
    assert info[2:-1] == diag.NAME + b" " + diag.VERSION
    assert b.counters["forwards"] == 0  # nothing went to the drivers


def test_vendor_style_probe_of_ids_0_to_15(b):
    """Like the vendor library at connect: GetCommandPos to every id, exact length."""
    answered = []
    for i in range(16):
        wire, r = b.request(i, F.GET_COMMAND_POS, timeout_us=100000.0)
        if r is not None:
            assert len(r) == 5 and r[0] == 0
            answered.append(i)
    assert answered == [1, 2, 3]


def test_unknown_type_and_bad_length(b):
    assert ask(b, 0x77) == bytes([F.STATUS_FRAME_TYPE_ERROR])
    assert ask(b, F.GET_SLAVE_INFO, b"\x00") == bytes([F.STATUS_FRAME_ERROR])
    assert ask(b, F.SET_PARAMETER, b"\x01\x00") == bytes([F.STATUS_FRAME_ERROR])
    assert ask(b, F.SET_IO_OUTPUT, bytes(7)) == bytes([F.STATUS_FRAME_ERROR])
    assert b.counters["local_errors"] == 4


def test_parameters_get_set_rom_save(b):
    assert ask(b, F.GET_PARAMETER, bytes([P.P_REPLY_TIMEOUT_MS])) == b"\x00" + struct.pack("<i", 50)
    assert ask(b, F.SET_PARAMETER, bytes([P.P_REPLY_TIMEOUT_MS]) + struct.pack("<i", 120)) == b"\x00"
    assert ask(b, F.GET_PARAMETER, bytes([P.P_REPLY_TIMEOUT_MS])) == b"\x00" + struct.pack("<i", 120)
    assert ask(b, F.GET_ROM_PARAMETER, bytes([P.P_REPLY_TIMEOUT_MS])) == b"\x00" + struct.pack("<i", 50)
    # out of range, unknown number
    assert ask(b, F.SET_PARAMETER, bytes([P.P_REPLY_TIMEOUT_MS]) + struct.pack("<i", 0)) == b"\x81"
    assert ask(b, F.SET_PARAMETER, bytes([P.P_UP_BAUD]) + struct.pack("<i", 12345)) == b"\x81"
    assert ask(b, F.SET_PARAMETER, bytes([200]) + struct.pack("<i", 1)) == b"\x81"
    assert ask(b, F.GET_PARAMETER, bytes([P.COUNT])) == b"\x81"
    assert ask(b, F.GET_ROM_PARAMETER, bytes([P.COUNT])) == b"\x81"
    assert ask(b, F.SAVE_ALL_PARAMETERS) == b"\x00"
    assert ask(b, F.GET_ROM_PARAMETER, bytes([P.P_REPLY_TIMEOUT_MS])) == b"\x00" + struct.pack("<i", 120)
    assert b.counters["param_saves"] == 1
    # immediate: the new timeout is used at once
    assert b.app.bridge.params.ram[P.P_REPLY_TIMEOUT_MS] == 120


def test_saved_parameters_survive_restart_and_restart_params_apply():
    b = SimBench(driver_ids=(2,))
    assert ask(b, F.SET_PARAMETER, bytes([P.P_DOWN_BAUD]) + struct.pack("<i", 460800)) == b"\x00"
    assert b.down_bus.baud == 115200  # takes effect at restart
    assert ask(b, F.SAVE_ALL_PARAMETERS) == b"\x00"
    b2 = SimBench(driver_ids=(2,), fs=b.fs)
    assert b2.down_bus.baud == 460800 and b2.app.params.get(P.P_DOWN_BAUD) == 460800
    assert b2.counters["param_errors"] == 0


def test_forward_mode_takes_effect_at_restart():
    """The parsers, DE mode and main loop are built for a mode: a change waits for a restart."""
    assert P.TABLE[P.P_FORWARD_MODE][6] == P.RESTART  # as the parameter tables say
    b = SimBench(driver_ids=(2,))
    assert b.app.bridge.cut_through
    assert ask(b, F.SET_PARAMETER, bytes([P.P_FORWARD_MODE]) + struct.pack("<i", P.STORE_AND_FORWARD)) == b"\x00"
    assert ask(b, F.GET_PARAMETER, bytes([P.P_FORWARD_MODE])) == b"\x00" + struct.pack("<i", P.STORE_AND_FORWARD)
    assert b.app.bridge.cut_through  # the running bridge keeps its mode
    assert ask(b, F.GET_AXIS_STATUS, slave=2)[0] == F.STATUS_OK
    assert ask(b, F.SAVE_ALL_PARAMETERS) == b"\x00"
    b2 = SimBench(driver_ids=(2,), fs=b.fs)
    assert not b2.app.bridge.cut_through and b2.app.pump is None
    assert ask(b2, F.GET_AXIS_STATUS, slave=2)[0] == F.STATUS_OK


def test_corrupt_parameter_file_counted():
    b = SimBench(driver_ids=(2,))
    path = b.hal.param_path
    b.fs.files[path] = b"MJP1" + bytes(10)
    b2 = SimBench(driver_ids=(2,), fs=b.fs)
    assert b2.counters["param_errors"] == 1 and b2.jig_id == 1


def test_changing_the_jig_id_answers_with_the_old_one_first(b):
    wire, r = b.request(1, F.SET_PARAMETER, bytes([P.P_SLAVE_ID]) + struct.pack("<i", 4))
    assert r == b"\x00" and wire[2] == 1
    assert b.request(1, F.GET_COMMAND_POS) == (None, None) or b.drivers.get(1)
    assert ask(b, F.GET_SLAVE_INFO, slave=4)[1] == diag.SLAVE_TYPE


def test_io_outputs_and_inputs(b):
    assert ask(b, F.SET_IO_OUTPUT, struct.pack("<II", 0x0005, 0)) == b"\x00"
    assert b.hal.outputs == 0x0005
    assert ask(b, F.SET_IO_OUTPUT, struct.pack("<II", 0x0100, 0x0001)) == b"\x00"
    assert b.hal.outputs == 0x0104
    assert ask(b, F.GET_IO_OUTPUT) == b"\x00" + struct.pack("<I", 0x0104)
    b.hal.inputs = 0x0003
    assert ask(b, F.GET_IO_INPUT) == b"\x00" + struct.pack("<I", 3)
    # bits above 15 are not the jig's: ignored
    assert ask(b, F.SET_IO_OUTPUT, struct.pack("<II", 0xFFFF0000, 0)) == b"\x00"
    assert b.hal.outputs == 0x0104


def test_counters_read_and_reset(b):
    b.request(2, F.GET_COMMAND_POS)
    b.request(9, F.GET_COMMAND_POS)
    r = ask(b, diag.READ_COUNTERS)
    c = diag.decode_counters(r)
    assert list(c) == list(diag.WIRE_NAMES)
    assert c["forwards"] == 2 and c["replies"] == 1 and c["timeouts"] == 1
    assert c["up_frames_in"] == 3 and c["local_requests"] == 1 and c["up_good"] == 3
    assert len(r) == 2 + 4 * len(diag.WIRE_NAMES) <= F.MAX_DATA
    assert ask(b, diag.RESET_COUNTERS) == b"\x00"
    c = diag.decode_counters(ask(b, diag.READ_COUNTERS))
    assert c["forwards"] == 0 and c["up_frames_in"] == 1 and c["local_requests"] == 1


def test_bus_scan_runs_in_background(b):
    b.drivers[3].slave_type = 60
    assert ask(b, diag.START_BUS_SCAN) == b"\x00"
    state, ids = diag.decode_scan(ask(b, diag.GET_BUS_SCAN_RESULT))
    assert state == "running"
    # PC traffic keeps flowing during the scan
    for _ in range(5):
        assert b.request(2, F.GET_AXIS_STATUS)[1] is not None
    for _ in range(100):
        b.run_for(10000.0)
        state, ids = diag.decode_scan(ask(b, diag.GET_BUS_SCAN_RESULT))
        if state == "done":
            break
    assert state == "done" and ids == {2: 20, 3: 60}
    c = b.counters
    assert c["int_requests"] == c["int_replies"] + c["int_timeouts"] + c["int_aborts"]
    assert c["int_replies"] >= 2
    # no reply from the scan ever reached the PC
    assert all(w[3] != F.GET_SLAVE_INFO for _t, w in b.pc.frames)


def test_local_replies_are_fast(b):
    for ftype, data in ((F.GET_SLAVE_INFO, b""), (diag.READ_COUNTERS, b""), (F.SAVE_ALL_PARAMETERS, b"")):
        wire = b.encode(1, ftype, data)
        t_end = b.send(wire)
        n0 = len(b.pc.frames)
        b.clock.run_while(lambda: len(b.pc.frames) == n0, 100000.0)
        t_reply, reply = b.pc.frames[n0]
        reply_time = len(reply) * 10e6 / 115200
        assert t_reply - t_end - reply_time < 100.0  # µs on the virtual timeline


def test_crash_log_empty_without_a_hal_crash_summary(b):
    assert not hasattr(b.hal, "crash_summary")  # the bench's HAL has none
    r = ask(b, diag.READ_CRASH_LOG)
    assert r == b"\x00\x00" and diag.decode_crash_log(r) == ""
    assert ask(b, diag.READ_CRASH_LOG, b"\x00") == bytes([F.STATUS_FRAME_ERROR])


def test_crash_log_text_from_the_hal(b):
    text = "crashes=2 consecutive=1 wdt_resets=0; last: MemoryError: memory allocation failed"
    b.hal.crash_summary = lambda: text
    r = ask(b, diag.READ_CRASH_LOG)
    assert r == b"\x00" + text.encode() + b"\x00" and diag.decode_crash_log(r) == text
    for nothing in ("", None):  # a HAL with a crash log API but no crash recorded
        b.hal.crash_summary = lambda: nothing
        assert ask(b, diag.READ_CRASH_LOG) == b"\x00\x00"


def test_crash_log_is_cut_to_the_frame_and_printable(b):
    b.hal.crash_summary = lambda: "x" * 300
    r = ask(b, diag.READ_CRASH_LOG)
    assert len(r) == F.MAX_DATA == 2 + diag.CRASH_TEXT_MAX and r[1:-1] == b"x" * diag.CRASH_TEXT_MAX
    b.hal.crash_summary = lambda: "t\u00e9\tst\x00!"  # UTF-8 é, a tab and a NUL: each byte becomes '?'
    assert diag.decode_crash_log(ask(b, diag.READ_CRASH_LOG)) == "t???st?!"

    def broken():
        raise OSError(5, "EIO")

    b.hal.crash_summary = broken  # an unreadable log reads as none
    assert ask(b, diag.READ_CRASH_LOG) == b"\x00\x00"


def test_decode_crash_log_rejects_bad_replies():
    for bad in (b"", b"\x00", b"\x81", b"\x00abc", b"\x01abc\x00", b"\x00a\x00b\x00", b"\x00\x07\x00",
                b"\x00" + b"x" * (diag.CRASH_TEXT_MAX + 1) + b"\x00"):
        with pytest.raises(ValueError):
            diag.decode_crash_log(bad)
    assert diag.decode_crash_log(b"\x00ok\x00") == "ok"


@pytest.mark.parametrize("jig_id", [1, 2])
def test_ver8_jig_answers_the_ver6_probe_as_a_ver8_drive_does(jig_id):
    """The vendor library's Ver6-format GetCommandPos probe to a Ver8 jig: frame-type
    error in the Ver8 layout, id / sync=0x51 / type=crcL / 0x80."""
    b = SimBench(driver_ids=(3,), ver8=True, jig_params={P.P_SLAVE_ID: jig_id})
    probe = F.encode(jig_id, F.GET_COMMAND_POS)  # AA CC id 51 crcL crcH AA EE
    reply = b.transact(probe)
    assert reply == F.encode(jig_id, probe[4], b"\x80", sync=0x51)
    assert b.counters["local_errors"] == 1 and b.counters["forwards"] == 0
    # then the Ver8 probe, sync 0xF1 echoed
    reply = b.transact(F.encode(jig_id, F.GET_COMMAND_POS, sync=0xF1))
    assert reply == F.encode(jig_id, F.GET_COMMAND_POS, bytes(5), sync=0xF1)


def test_ver6_jig_answers_the_ver6_probe_normally():
    b = SimBench(driver_ids=(3,))
    assert b.transact(F.encode(1, F.GET_COMMAND_POS)) == F.encode(1, F.GET_COMMAND_POS, bytes(5))


def test_ver8_jig_reads_a_ver6_frame_whose_crc_byte_is_a_known_type_as_a_frame_type_error():
    """Ver6 'AA CC 01 04 01 E3 AA EE' read as Ver8 is sync 0x04, type 0x01 (GetSlaveInfo)
    with a data length of -1: still 0x80, never a GetSlaveInfo answer."""
    b = SimBench(driver_ids=(3,), ver8=True)
    wire = F.encode(1, 0x04)
    assert wire == bytes.fromhex("AA CC 01 04 01 E3 AA EE")
    assert b.transact(wire) == F.encode(1, 0x01, b"\x80", sync=0x04)


# --- no shadowing: jig_slave_id never takes an id a driver answers at ------------------
def set_id(b, new_id, slave=None):
    return ask(b, F.SET_PARAMETER, bytes([P.P_SLAVE_ID]) + struct.pack("<i", new_id), slave)


def test_jig_id_of_a_driver_not_seen_yet_is_probed_and_refused(b):
    n0 = b.drivers[2].requests
    assert set_id(b, 2) == b"\x81"
    assert b.drivers[2].requests == n0 + 1  # the jig asked id 2 before answering
    assert b.jig_id == 1
    wire, r = b.request(2, F.GET_SLAVE_INFO)
    assert r[1] == 20  # still the driver's answer, not the jig's
    assert b.counters["int_replies"] == 1


def test_jig_id_of_a_driver_already_relayed_is_refused_without_a_probe(b):
    assert ask(b, F.GET_COMMAND_POS, slave=3)[0] == 0  # relayed: the jig has seen id 3
    n0 = b.drivers[3].requests
    assert set_id(b, 3) == b"\x81"
    assert b.drivers[3].requests == n0 and b.jig_id == 1


def test_jig_id_found_by_the_bus_scan_is_refused_without_a_probe(b):
    assert ask(b, diag.START_BUS_SCAN) == b"\x00"
    b.run_for(500000)
    assert ask(b, diag.GET_BUS_SCAN_RESULT)[1] == diag.SCAN_DONE
    n0 = b.drivers[2].requests
    assert set_id(b, 2) == b"\x81"
    assert b.drivers[2].requests == n0


def test_free_jig_id_is_taken_after_the_probe_times_out(b):
    t0 = b.clock.now
    wire, r = b.request(1, F.SET_PARAMETER, bytes([P.P_SLAVE_ID]) + struct.pack("<i", 5))
    assert r == b"\x00" and wire[2] == 1  # answered from the old id
    assert b.clock.now - t0 >= 20000  # after the probe's scan_timeout_ms
    assert b.jig_id == 5
    assert ask(b, F.GET_SLAVE_INFO, slave=5)[1] == diag.SLAVE_TYPE
    assert b.request(1, F.GET_SLAVE_INFO, timeout_us=30000.0) == (None, None)
    assert set_id(b, 5, slave=5) == b"\x00"  # its own id: nothing to check


def test_pc_frame_for_the_drivers_aborts_the_id_check(b):
    b.send(b.encode(1, F.SET_PARAMETER, bytes([P.P_SLAVE_ID]) + struct.pack("<i", 6)))
    b.run_for(3000)  # the probe is out
    assert ask(b, F.GET_COMMAND_POS, slave=2)[0] == 0
    b.run_for(50000)
    assert b.jig_id == 1 and b.counters["int_aborts"] == 1


@pytest.mark.parametrize("jig_ver8", [False, True])
def test_jig_id_refused_for_a_driver_of_the_other_variant(jig_ver8):
    """The probe goes out in the jig's layout; a driver of the other variant answers
    it with a frame-type error, which still shows that the id is taken."""
    b = SimBench(driver_ids=(2,), jig_ver8=jig_ver8, ver8_drivers=() if jig_ver8 else (2,))
    assert set_id(b, 2) == b"\x81" and b.jig_id == 1
