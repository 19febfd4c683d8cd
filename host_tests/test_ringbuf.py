"""RingBuffer: FIFO order across the wrap, overflow counted, bulk reads, t_last."""

import random
from collections import deque

import pytest

from jig.ringbuf import RingBuffer


def test_size_must_be_a_power_of_two():
    for bad in (0, 1, 3, 100):
        with pytest.raises(ValueError):
            RingBuffer(bad)
    assert RingBuffer(16).capacity() == 15


def test_write_read_wraps_and_keeps_order():
    r = RingBuffer(8)
    out = bytearray(8)
    assert r.write(b"abcde", 5, now=10) == 5 and r.t_last == 10
    assert r.read_into(out, 3) == 3 and out[:3] == b"abc"
    assert r.write(b"fghij", 5, now=20) == 5  # wraps around the end
    assert r.any() == 7 and r.free() == 0
    assert r.read_into(out) == 7 and out[:7] == b"defghij"
    assert r.any() == 0 and r.overflows == 0


def test_overflow_is_counted_not_silent():
    r = RingBuffer(8)
    assert r.write(b"0123456789", 10) == 7
    assert r.overflows == 3
    assert not r.put(0x41) and r.overflows == 4
    out = bytearray(16)
    assert r.read_into(out) == 7 and out[:7] == b"0123456"


def test_put_and_clear():
    r = RingBuffer(4)
    assert r.put(1, now=5) and r.put(2) and r.put(3)
    assert not r.put(4)
    assert r.any() == 3
    r.clear()
    assert r.any() == 0 and r.free() == 3


def test_write_of_part_of_a_buffer_and_read_limits():
    r = RingBuffer(16)
    src = bytearray(b"xyz----")
    assert r.write(src, 3) == 3
    out = bytearray(2)
    # a limit larger than dst never writes past dst (that would corrupt memory on the board)
    assert r.read_into(out, 10) == 2 and out == b"xy" and len(out) == 2
    assert r.read_into(out, 0) == 0
    assert r.read_into(out) == 1 and out[:1] == b"z"


def test_against_a_model():
    rng = random.Random(42)
    r = RingBuffer(64)
    model = deque()
    dropped = 0
    out = bytearray(100)
    for step in range(5000):
        if rng.random() < 0.5:
            n = rng.randrange(0, 40)
            data = bytes(rng.randrange(256) for _ in range(n))
            fit = min(n, 63 - len(model))
            assert r.write(data, n, now=step) == fit
            model.extend(data[:fit])
            dropped += n - fit
        elif rng.random() < 0.2:
            b = rng.randrange(256)
            ok = r.put(b, now=step)
            assert ok == (len(model) < 63)
            if ok:
                model.append(b)
            else:
                dropped += 1
        else:
            limit = rng.choice((-1, rng.randrange(0, 50)))
            n = r.read_into(out, limit)
            want = min(len(model), 100 if limit < 0 else limit)
            assert n == want
            assert bytes(out[:n]) == bytes(model.popleft() for _ in range(n))
        assert r.any() == len(model) and r.free() == 63 - len(model)
        assert r.overflows == dropped
