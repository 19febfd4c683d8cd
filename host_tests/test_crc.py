"""CRC-16 of the Plus-R protocol: table against a bitwise reference, known values,
the worked examples of the protocol notes, and the viper loop's logic."""

import random
import sys
import types

import pytest

from jig import compat, crc

# (unstuffed body, CRC) from the worked examples of the protocol notes (§3.1).
DOC_EXAMPLES = [
    ("01 01", 0xE0C1), ("00 01", 0x70C0), ("01 40", 0xD001), ("01 43", 0xD141),
    ("01 31", 0xF4C1), ("00 2A 01", 0x60AF), ("01 2C 01", 0x00FD), ("01 13 01", 0xF0EC),
    ("01 12 01 A0 86 01 00", 0x0BF7), ("00 35 10 27 00 00 88 13 00 00", 0x3D97),
    ("01 34 18 FC FF FF 20 4E 00 00", 0x6A10), ("01 37 88 13 00 00 01", 0xDC2A),
    ("01 58 01", 0x00DA), ("01 64 05 00", 0x5743), ("63 3B", 0x9368),
    ("02 50 AA 00 00 00", 0x2DE0), ("04 26", 0xAA82),
    ("01 31 00", 0x9035), ("00 2A 00", 0xA06E), ("01 40 00 00 00 00 08", 0xC604),
    ("01 51 00 18 FC FF FF", 0x61C1), ("01 53 00 AA AA 00 00", 0x5B06),
    ("01 2E 00 03", 0xD021), ("01 01 00 14 41 42 43 00", 0x1C24), ("01 35 85", 0xF3F6),
]


def crc16_bitwise(data, crc_value=0xFFFF):
    """Reference: the bit-at-a-time definition (reflected poly 0xA001)."""
    for b in data:
        crc_value ^= b
        for _ in range(8):
            crc_value = (crc_value >> 1) ^ 0xA001 if crc_value & 1 else crc_value >> 1
    return crc_value


def test_check_value_of_crc16_modbus():
    assert crc.crc16(b"123456789") == 0x4B37
    assert crc.crc16_table(b"123456789") == 0x4B37


def test_table_entries_from_the_notes():
    assert len(crc.TABLE) == 256
    assert crc.TABLE[0] == 0 and crc.TABLE[1] == 0xC0C1
    assert crc.TABLE[0x80] == 0xA001 and crc.TABLE[0xFF] == 0x4040


@pytest.mark.parametrize("body,value", DOC_EXAMPLES)
def test_worked_examples(body, value):
    data = bytes.fromhex(body)
    assert crc.crc16(data) == value
    # Running the CRC over the body and its CRC (low byte first) gives 0.
    assert crc.crc16(data + bytes([value & 0xFF, value >> 8])) == 0


def test_table_equals_bitwise_reference_on_random_inputs():
    rng = random.Random(1234)
    for n in list(range(0, 40)) + [255, 256, 600]:
        data = bytes(rng.randrange(256) for _ in range(n))
        assert crc.crc16_table(data) == crc16_bitwise(data)
    for b in range(256):  # every byte value from a non-trivial start value
        assert crc.update_byte(0x1234, b) == crc16_bitwise(bytes([b]), 0x1234)


def test_start_end_and_chaining():
    rng = random.Random(7)
    data = bytearray(rng.randrange(256) for _ in range(100))
    whole = crc.crc16(data)
    assert crc.crc16(data, 0, len(data)) == whole
    assert crc.crc16(data, 0, -1) == whole
    for cut in (0, 1, 37, 99, 100):
        part = crc.crc16(data, 0, cut)
        assert crc.crc16(data, cut, len(data), part) == whole
    assert crc.crc16(data, 10, 20) == crc16_bitwise(data[10:20])
    assert crc.crc16(data, 5, 5) == 0xFFFF
    running = crc.INIT
    for b in data:
        running = crc.update_byte(running, b)
    assert running == whole


def test_cpython_pair_path_equals_table_path():
    # CPython has no viper; crc16 there takes two bytes per step (crc.py). It must
    # agree with the portable table loop for every length, offset and start value.
    assert compat.NATIVE is None
    assert crc.crc16 is not crc.crc16_table
    rng = random.Random(17)
    data = bytearray(rng.randrange(256) for _ in range(300))
    for _ in range(2000):
        start = rng.randrange(0, 300)
        end = rng.randrange(start, 301)
        init = rng.choice((0xFFFF, 0, rng.randrange(0x10000)))
        assert crc.crc16(data, start, end, init) == crc.crc16_table(data, start, end, init)
    assert crc.crc16(bytes(data)) == crc.crc16_table(data)
    long = bytes(rng.randrange(256) for _ in range(1001))
    for n in (253, 254, 255, 256, 508, 509, 1000, 1001):
        assert crc.crc16(long, 0, n) == crc.crc16_table(long, 0, n)
        assert crc.crc16(long, 1001 - n) == crc.crc16_table(long, 1001 - n)
    assert crc.crc16(memoryview(data), 3, 250) == crc.crc16_table(data, 3, 250)


def _load_viper_source_as_python():
    """native.py run as plain Python: viper decorator = identity, ptr8/ptr16 = the object.

    This checks the *logic* of the viper loops against the table version under CPython.
    The native code itself is checked in QEMU (make test-qemu, issue 4); the WebAssembly
    VM rejects viper, so it cannot be checked there.
    """
    fake = types.ModuleType("micropython")
    fake.viper = lambda f: f
    saved = sys.modules.get("micropython")
    sys.modules["micropython"] = fake
    try:
        import jig

        with open(jig.__path__[0] + "/native.py") as f:
            source = f.read()
        ns = {"__name__": "native_as_python", "ptr8": lambda b: b, "ptr16": lambda t: t}
        exec(compile(source, "native.py", "exec"), ns)
    finally:
        if saved is None:
            del sys.modules["micropython"]
        else:
            sys.modules["micropython"] = saved
    return ns


def test_viper_crc_loop_logic_matches_table():
    native = _load_viper_source_as_python()
    rng = random.Random(99)
    for n in (0, 1, 2, 5, 64, 254):
        data = bytearray(rng.randrange(256) for _ in range(n + 4))
        for start, end in ((0, n), (2, n + 2), (4, n + 4)):
            assert native["crc16"](data, start, end, 0xFFFF, crc.TABLE) == crc.crc16_table(data, start, end)


def test_viper_copy_loop_logic_matches_slices():
    native = _load_viper_source_as_python()
    src = bytes(range(200))
    for doff, soff, n in ((0, 0, 0), (0, 0, 200), (10, 3, 50), (199, 0, 1)):
        dst = bytearray(200)
        native["copy"](dst, doff, src, soff, n)
        want = bytearray(200)
        want[doff : doff + n] = src[soff : soff + n]
        assert dst == want
