"""Frame encoding with stuffing, the protocol constants, and little-endian fields."""

import random

import pytest

from jig import crc, frame

# (slave, type, data, wire) from the worked examples of the protocol notes (§3.1).
DOC_WIRE = [
    (1, 0x01, "", "AA CC 01 01 C1 E0 AA EE"),
    (0, 0x01, "", "AA CC 00 01 C0 70 AA EE"),
    (1, 0x40, "", "AA CC 01 40 01 D0 AA EE"),
    (1, 0x43, "", "AA CC 01 43 41 D1 AA EE"),
    (1, 0x31, "", "AA CC 01 31 C1 F4 AA EE"),
    (0, 0x2A, "01", "AA CC 00 2A 01 AF 60 AA EE"),
    (1, 0x2C, "01", "AA CC 01 2C 01 FD 00 AA EE"),
    (1, 0x13, "01", "AA CC 01 13 01 EC F0 AA EE"),
    (1, 0x12, "01 A0 86 01 00", "AA CC 01 12 01 A0 86 01 00 F7 0B AA EE"),
    (0, 0x35, "10 27 00 00 88 13 00 00", "AA CC 00 35 10 27 00 00 88 13 00 00 97 3D AA EE"),
    (1, 0x34, "18 FC FF FF 20 4E 00 00", "AA CC 01 34 18 FC FF FF 20 4E 00 00 10 6A AA EE"),
    (1, 0x37, "88 13 00 00 01", "AA CC 01 37 88 13 00 00 01 2A DC AA EE"),
    (1, 0x58, "01", "AA CC 01 58 01 DA 00 AA EE"),
    (1, 0x64, "05 00", "AA CC 01 64 05 00 43 57 AA EE"),
    (99, 0x3B, "", "AA CC 63 3B 68 93 AA EE"),
    (2, 0x50, "AA 00 00 00", "AA CC 02 50 AA AA 00 00 00 E0 2D AA EE"),
    (4, 0x26, "", "AA CC 04 26 82 AA AA AA EE"),
    (1, 0x31, "00", "AA CC 01 31 00 35 90 AA EE"),
    (0, 0x2A, "00", "AA CC 00 2A 00 6E A0 AA EE"),
    (1, 0x40, "00 00 00 00 08", "AA CC 01 40 00 00 00 00 08 04 C6 AA EE"),
    (1, 0x51, "00 18 FC FF FF", "AA CC 01 51 00 18 FC FF FF C1 61 AA EE"),
    (1, 0x53, "00 AA AA 00 00", "AA CC 01 53 00 AA AA AA AA 00 00 06 5B AA EE"),
    (1, 0x2E, "00 03", "AA CC 01 2E 00 03 21 D0 AA EE"),
    (1, 0x01, "00 14 41 42 43 00", "AA CC 01 01 00 14 41 42 43 00 24 1C AA EE"),
    (1, 0x35, "85", "AA CC 01 35 85 F6 F3 AA EE"),
]


@pytest.mark.parametrize("slave,ftype,data,wire", DOC_WIRE)
def test_encode_worked_examples(slave, ftype, data, wire):
    assert frame.encode(slave, ftype, bytes.fromhex(data)) == bytes.fromhex(wire)


def unstuff(wire):
    """Independent reference decoder for one well-formed frame."""
    assert wire[:2] == b"\xaa\xcc" and wire[-2:] == b"\xaa\xee"
    inner = wire[2:-2]
    out = bytearray()
    i = 0
    while i < len(inner):
        if inner[i] == 0xAA:
            assert inner[i + 1] == 0xAA, "lone 0xAA inside an encoded frame"
            i += 1
        out.append(inner[i])
        i += 1
    return bytes(out)


def test_encode_stuffs_every_aa_and_crc_checks_out():
    rng = random.Random(3)
    for _ in range(500):
        n = rng.randrange(0, frame.MAX_DATA + 1)
        data = bytes(rng.choice((0xAA, 0xAA, 0xCC, 0xEE, rng.randrange(256))) for _ in range(n))
        slave, ftype = rng.randrange(256), rng.randrange(256)
        sync = rng.choice((-1, rng.randrange(256)))
        wire = frame.encode(slave, ftype, data, sync)
        body = unstuff(wire)
        head = bytes([slave, ftype]) if sync < 0 else bytes([slave, sync, ftype])
        assert body[:-2] == head + data
        assert crc.crc16(body) == 0
        assert len(wire) == 4 + len(body) + body.count(0xAA)
        assert len(wire) <= frame.MAX_WIRE


def test_worst_case_wire_length():
    wire = frame.encode(0xAA, 0xAA, b"\xaa" * frame.MAX_DATA, 0xAA)
    assert len(wire) >= 4 + 2 * (frame.MAX_BODY - 2)
    assert len(wire) <= frame.MAX_WIRE


def test_encode_into_and_offsets():
    out = bytearray(frame.MAX_WIRE + 10)
    body = bytearray(frame.MAX_BODY)
    n = frame.encode_into(out, body, 2, 0x50, b"\xaa\x00\x00\x00")
    assert bytes(out[:n]) == bytes.fromhex("AA CC 02 50 AA AA 00 00 00 E0 2D AA EE")
    # build_body with a data window, and stuff_into at an offset
    src = b"xx\xaa\x00\x00\x00yy"
    blen = frame.build_body(body, 2, 0x50, src, 2, 6)
    assert bytes(body[:blen]) == bytes.fromhex("02 50 AA 00 00 00 E0 2D")
    end = frame.stuff_into(out, body, blen, 5)
    assert bytes(out[5:end]) == bytes.fromhex("AA CC 02 50 AA AA 00 00 00 E0 2D AA EE")


def test_ver8_layout():
    wire = frame.encode(1, 0x01, b"", 0xF0)
    body = unstuff(wire)
    assert body[:3] == b"\x01\xf0\x01" and crc.crc16(body) == 0


def test_data_too_long_is_refused():
    with pytest.raises(ValueError):
        frame.encode(1, 0x12, bytes(frame.MAX_DATA + 1))
    assert len(unstuff(frame.encode(1, 0x12, bytes(frame.MAX_DATA)))) == 2 + frame.MAX_DATA + 2


def test_limits_are_consistent():
    assert frame.MAX_DATA == 249  # 248 payload bytes + the status byte of a reply
    assert frame.MAX_BODY == 1 + 1 + 1 + frame.MAX_DATA + 2  # Ver8: id, sync, type, data, CRC
    assert frame.MAX_WIRE == 2 + 2 * frame.MAX_BODY + 2
    assert frame.BROADCAST_ID == 99


def test_codes_from_the_notes():
    assert (frame.GET_SLAVE_INFO, frame.MOVE_STOP, frame.GET_AXIS_STATUS) == (0x01, 0x31, 0x40)
    assert (frame.GET_COMMAND_POS, frame.IO_ASSIGN_MAP_READ_ROM, frame.ALL_MOVE_STOP) == (0x51, 0x26, 0x3B)
    assert (frame.STATUS_OK, frame.STATUS_FRAME_TYPE_ERROR, frame.STATUS_MOTION_REFUSED) == (0, 0x80, 0x85)
    assert frame.STATUS_CRC_ERROR == 0xAA
    # no two frame-type constants share a code
    names = [n for n in dir(frame) if n.isupper() and not n.startswith(("STATUS_", "MAX_"))]
    types_ = {n: getattr(frame, n) for n in names if n not in ("STUFF", "HEADER2", "TAIL2", "BROADCAST_ID")}
    assert len(set(types_.values())) == len(types_)


def test_little_endian_fields():
    buf = bytearray(8)
    for value in (0, 1, 0x7FFFFFFF, -1, -1000, -(2**31), 43690):
        frame.put_i32(buf, 2, value)
        assert frame.get_i32(buf, 2) == value
        assert frame.get_u32(buf, 2) == value & 0xFFFFFFFF
    frame.put_i32(buf, 0, -1000)
    assert bytes(buf[:4]) == bytes.fromhex("18 FC FF FF")
    frame.put_u16(buf, 5, 0xBEEF)
    assert bytes(buf[5:7]) == b"\xef\xbe" and frame.get_u16(buf, 5) == 0xBEEF
