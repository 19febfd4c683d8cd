"""jig.native, the viper source, run as plain Python: the same results as the portable code.

On the board these functions are machine code (the emulated Cortex-M7 checks that
in ``make test-qemu``); here the shims of ``jig.compat`` run the very same source.
"""

from array import array

from hypothesis import given, settings
from hypothesis import strategies as st

from jig import compat, crc, frame, native, parser


def test_constants_mirror_the_parser():
    """viper folds only its own module's constants: they must equal jig.parser's."""
    for name in ("HUNT", "HEADER", "A_NOISE", "A_NOISE2", "A_START", "A_STORE", "A_LITERAL", "A_RESYNC", "A_END",
                 "A_STUFF_ERROR", "EV_FRAME", "EV_HEAD", "EV_DROP", "S_STATE", "S_N", "S_EVENT", "S_T_LAST",
                 "S_TIMEOUT", "S_BYTE_US", "S_LIMIT", "S_MIN_LEN", "S_HEAD_AT", "S_STOP_DROP", "S_GOOD", "S_NOISE",
                 "S_STUFF_ERRORS", "S_CRC_ERRORS", "S_SHORT", "S_OVERLONG", "S_TIMEOUTS", "S_RESYNCS", "S_WHY"):
        assert getattr(native, "_" + name) == getattr(parser, name), name
    assert native._CRC_AT * 2 == 1024 and len(parser.TABLES) == 1024 + 512


def test_the_source_is_what_compat_loads():
    assert compat.native_source() is native
    assert compat.NATIVE is None  # CPython runs the portable paths by default


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=frame.MAX_DATA), st.integers(0, 255), st.integers(-1, 255), st.integers(0, 255))
def test_put_body_and_stuff_match_the_portable_encoder(data, slave, sync, ftype):
    body_a = bytearray(frame.MAX_BODY)
    body_b = bytearray(frame.MAX_BODY)
    if sync >= 0 and len(data) == frame.MAX_DATA:
        data = data[:-1]
    n_a = frame.build_body(body_a, slave, ftype, data, 0, -1, sync)  # portable on CPython
    n_b = native.put_body(body_b, slave, sync, ftype, data, len(data), crc.TABLE)
    assert n_a == n_b and body_a[:n_a] == body_b[:n_b]
    out_a = bytearray(frame.MAX_WIRE)
    out_b = bytearray(frame.MAX_WIRE)
    assert frame.stuff_into(out_a, body_a, n_a) == native.stuff(out_b, body_a, n_a)
    assert out_a == out_b


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300), st.integers(0, 0xFFFF))
def test_crc_and_copy(data, init):
    buf = bytearray(data)
    assert native.crc16(buf, 0, len(buf), init, crc.TABLE) == crc.crc16_table(buf, 0, len(buf), init)
    dst = bytearray(len(buf) + 3)
    native.copy(dst, 3, buf, 0, len(buf))
    assert dst[3:] == buf


def test_ptr_shims_write_through():
    a = array("i", [0, 0, 0])
    compat.ptr32(a)[1] += 7
    b = bytearray(4)
    compat.ptr16(b)[1] = 0xABCD
    assert a[1] == 7 and b == b"\x00\x00\xcd\xab"
