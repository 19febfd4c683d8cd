"""jig.mem.copy: the MicroPython loop and the CPython slice path copy the same bytes."""

import random

import pytest

from jig import mem


@pytest.mark.parametrize("impl", [mem._copy_loop, mem._copy_slice])
def test_copy_paths_agree(impl):
    rng = random.Random(5)
    for _ in range(300):
        src_len = rng.randrange(0, 300)
        src = bytes(rng.randrange(256) for _ in range(src_len))
        dst_len = rng.randrange(1, 300)
        soff = rng.randrange(0, src_len + 1)
        doff = rng.randrange(0, dst_len)
        n = rng.randrange(0, min(src_len - soff, dst_len - doff) + 1)
        a = bytearray(rng.randrange(256) for _ in range(dst_len))
        b = bytearray(a)
        impl(a, doff, src, soff, n)
        mem._copy_slice(b, doff, src, soff, n)
        assert a == b
        assert len(a) == dst_len  # never grows or shrinks the destination


def test_copy_from_bytearray_into_itself_disjoint():
    buf = bytearray(range(20))
    mem.copy(buf, 10, buf, 0, 5)
    assert buf[10:15] == bytes(range(5))
    assert buf[:10] == bytes(range(10))


def test_cpython_uses_slices():
    assert mem.copy is mem._copy_slice
