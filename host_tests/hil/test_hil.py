"""Hardware-in-the-loop: a real jig (and optionally a real driver) over RS-485.

Skipped unless ``--port`` is given (see conftest.py). Each test leaves the jig as it
found it (parameters restored and saved back).
"""

import subprocess
import sys
import time

import pytest

from jig import diag, frame
from jig import params as P
from jig.frame import get_i32, get_u32

MOTIONING = 1 << 27  # GetAxisStatus flag bit: axis moving


def counters(hil):
    data = hil.request(hil.slave, diag.READ_COUNTERS)
    assert data is not None, "no reply to ReadCounters"
    return diag.decode_counters(data)


def get_param(hil, num, rom=False):
    data = hil.request(hil.slave, frame.GET_ROM_PARAMETER if rom else frame.GET_PARAMETER, bytes([num]), timeout=0.6)
    assert data is not None and data[0] == 0 and len(data) == 5, data
    return get_i32(data, 1)


def set_param(hil, num, value):
    data = hil.request(hil.slave, frame.SET_PARAMETER, bytes([num]) + (value & 0xFFFFFFFF).to_bytes(4, "little"))
    assert data == b"\x00", data


def save(hil):
    data = hil.request(hil.slave, frame.SAVE_ALL_PARAMETERS, timeout=5.0)  # flash erase takes time
    assert data == b"\x00", data


def restart(hil):
    """Restart the jig through its USB REPL; False if no --usb was given."""
    if not hil.usb:
        return False
    subprocess.run([sys.executable, "-m", "mpremote", "connect", hil.usb, "reset"], check=True, timeout=30)
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline:
        if hil.request(hil.slave, frame.GET_SLAVE_INFO) is not None:
            return True
        time.sleep(0.2)
    pytest.fail("the jig did not answer within 15 s of a restart")


def test_get_slave_info(hil):
    data = hil.request(hil.slave, frame.GET_SLAVE_INFO)
    assert data is not None, "no reply to GetSlaveInfo"
    assert data[0] == frame.STATUS_OK
    assert data[1] == diag.SLAVE_TYPE
    assert data[2:].split(b"\x00")[0].startswith(diag.NAME)


def test_parameter_round_trip_with_save_and_restart(hil):
    num = P.P_REPLY_TIMEOUT_MS
    old = get_param(hil, num)
    new = old + 1 if old < P.TABLE[num][4] else old - 1
    try:
        set_param(hil, num, new)
        assert get_param(hil, num) == new
        assert get_param(hil, num, rom=True) == old  # not saved yet
        save(hil)
        assert get_param(hil, num, rom=True) == new
        if restart(hil):  # without --usb the ROM read above is the persistence check
            assert get_param(hil, num) == new
    finally:
        set_param(hil, num, old)
        save(hil)
    assert get_param(hil, num, rom=True) == old


def test_out_of_range_parameter_refused(hil):
    data = hil.request(hil.slave, frame.SET_PARAMETER, bytes([P.P_REPLY_TIMEOUT_MS]) + (0).to_bytes(4, "little"))
    assert data == bytes([frame.STATUS_DATA_ERROR])


def test_forward_status_reads(hil):
    if hil.driver is None:
        pytest.skip("give --driver-id of a driver on the jig's driver bus")
    before = counters(hil)
    for _ in range(20):
        data = hil.request(hil.driver, frame.GET_AXIS_STATUS)
        assert data is not None and data[0] == 0 and len(data) == 5
        data = hil.request(hil.driver, frame.GET_ALL_STATUS)
        assert data is not None and data[0] == 0
    after = counters(hil)
    assert after["replies"] - before["replies"] >= 40
    assert after["timeouts"] == before["timeouts"]


def test_short_move(hil):
    if hil.driver is None or not hil.allow_move:
        pytest.skip("give --driver-id and --allow-move to let a driver turn 100 pulses")
    d = hil.driver
    start = hil.request(d, frame.GET_COMMAND_POS)
    assert start is not None and start[0] == 0
    assert hil.request(d, frame.SERVO_ENABLE, b"\x01", timeout=0.6) == b"\x00"
    try:
        reply = hil.request(d, frame.MOVE_INC_POS, (100).to_bytes(4, "little") + (1000).to_bytes(4, "little"))
        assert reply == b"\x00"
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            st = hil.request(d, frame.GET_AXIS_STATUS)
            assert st is not None and st[0] == 0
            if not get_u32(st, 1) & MOTIONING:
                break
            time.sleep(0.05)
        else:
            pytest.fail("the move did not finish within 5 s")
        end = hil.request(d, frame.GET_COMMAND_POS)
        assert get_i32(end, 1) - get_i32(start, 1) == 100
    finally:
        hil.request(d, frame.MOVE_STOP)
        hil.request(d, frame.SERVO_ENABLE, b"\x00", timeout=0.6)


def test_counters_count_requests_and_reset(hil):
    assert hil.request(hil.slave, diag.RESET_COUNTERS) == b"\x00"
    for _ in range(5):
        assert hil.request(hil.slave, frame.GET_SLAVE_INFO) is not None
    c = counters(hil)
    assert c["up_frames_in"] >= 6  # five requests + this ReadCounters
    assert c["local_requests"] >= 6
    assert c["up_crc_errors"] == 0 and c["up_rx_overflows"] == 0


def test_recovery_after_garbage_burst(hil):
    before = counters(hil)
    junk = bytearray()
    x = 1
    for _ in range(600):
        x = (x * 1103515245 + 12345) & 0x7FFFFFFF
        junk.append((x >> 16) & 0xFF)
    junk += b"\xaa\xcc\x01\x01"  # a truncated frame at the end
    hil.send_raw(bytes(junk))
    time.sleep(0.05)
    data = hil.request(hil.slave, frame.GET_SLAVE_INFO)
    assert data is not None and data[0] == 0, "no answer right after a garbage burst"
    after = counters(hil)
    errors = sum(after["up_" + n] - before["up_" + n] for n in ("noise", "stuff_errors", "crc_errors", "timeouts", "resyncs", "short", "overlong"))
    assert errors > 0
