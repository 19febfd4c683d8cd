"""Measurements of the frame parser that are run inside a MicroPython VM.

Used by host_tests/test_micropython_vm.py and tools/bench/bench_parser.py through
host_tests/wasm/run_vm.mjs, which puts this file, capture_format.py, the firmware
package and the captures on the WebAssembly VM's filesystem. Everything here is
MicroPython-compatible and also runs under CPython (where ``gc.mem_alloc`` is
missing, so only the replay and throughput parts apply).

* ``print_reports(paths)``: the capture replay report of capture_format, for the
  frame-by-frame comparison with CPython;
* ``alloc_per_frame(...)``: heap growth with the collector disabled while a stream
  is parsed over and over, after a warm-up (goal: 0 bytes per frame);
* ``heap_growth(fn, *args)``: that measurement for any call (host_tests/slcan_replay.py
  uses it too);
* ``throughput(...)``: bytes and frames per second of the parser on a stream.
"""

import gc
import time

import capture_format
from jig.compat import ticks_add
from jig.frame import MAX_BODY
from jig.parser import FrameParser

def print_reports(paths, every_split=True):
    for path in paths:
        for line in capture_format.report(capture_format.load(path), every_split):
            print(line)


def load_bursts(paths):
    """All captures of one protocol mode as one list of [time, bytes] bursts.

    Each capture's timeline is shifted to start after the previous one plus a long
    silence, so partial frames at a capture's end time out as they do in the file.
    """
    caps = [capture_format.load(path) for path in paths]
    return join_bursts([(cap.bursts, cap.end_gap) for cap in caps], 100000)


def join_bursts(timelines, silence):
    """One list of [time, bytes] bursts from (bursts, end) timelines, each after the previous
    one's last burst (or its end, if later) plus ``silence``; returns (bursts, span)."""
    bursts = []
    clock = 0
    for part, end in timelines:
        last = 0
        for t, data in part:
            bursts.append([clock + t, bytes(data)])
            last = t
        if end > last:
            last = end
        clock += last + silence
    return bursts, clock


def _run(p, bursts, span, rounds, chunk, dst):
    """Feed the bursts ``rounds`` times in pieces of ``chunk`` bytes; no allocation."""
    base = 0
    frames = 0
    for _ in range(rounds):
        for burst in bursts:
            data = burst[1]
            now = ticks_add(base, burst[0])  # C arithmetic: no big ints near the wrap
            n = len(data)
            i = 0
            while i < n:
                e = i + chunk
                if e > n:
                    e = n
                while i < e:
                    i = p.feed(data, i, e, now)
                    if p.ready:
                        p.copy_frame(dst)
                        frames += 1
        base = ticks_add(base, span)
    return frames


def alloc_per_frame(bursts, span, ver8=False, bulk=True, chunk=64, rounds=20, parser_class=FrameParser):
    """(bytes allocated, frames parsed) over ``rounds`` replays after a warm-up.

    Everything the measurement touches is a local or already exists, so the only
    thing that can allocate between the two readings is the parser.
    """
    p = parser_class(ver8, 5000, bulk, 1)  # byte_us=1: the timing estimate runs too
    dst = bytearray(MAX_BODY)
    _run(p, bursts, span, 2, chunk, dst)
    return heap_growth(_run, p, bursts, span, rounds, chunk, dst)


def heap_growth(fn, *args):
    """(bytes allocated, fn's result) while ``fn(*args)`` runs with the collector off.

    Warm up first: what exists before the first reading does not count.
    """
    gc.collect()
    gc.disable()
    try:
        a0 = gc.mem_alloc()
        result = fn(*args)
        a1 = gc.mem_alloc()
    finally:
        gc.enable()
    return a1 - a0, result


def print_alloc(paths_v6, paths_v8, rounds=20):
    """One line per configuration: 'alloc <label> <bytes> <frames>'."""
    for ver8, paths in ((False, paths_v6), (True, paths_v8)):
        if not paths:
            continue
        bursts, span = load_bursts(paths)
        for bulk in (True, False):
            for chunk in (1, 7, 64, 4096):
                grew, frames = alloc_per_frame(bursts, span, ver8, bulk, chunk, rounds)
                label = "%s,%s,chunk%d" % ("ver8" if ver8 else "ver6", "bulk" if bulk else "table", chunk)
                print("alloc %s %d %d" % (label, grew, frames))


def throughput(data, chunk=256, bulk=True, min_ms=1500):
    """(bytes/s, frames/s, frames per pass) parsing data repeatedly for >= min_ms."""
    p = FrameParser(False, 5000, bulk)
    dst = bytearray(MAX_BODY)
    bursts = [[0, data]]
    per_pass = _run(p, bursts, 100000, 1, chunk, dst)
    passes = 0
    t0 = time.ticks_ms()
    while True:
        _run(p, bursts, 100000, 1, chunk, dst)
        passes += 1
        dt = time.ticks_diff(time.ticks_ms(), t0)
        if dt >= min_ms:
            break
    return len(data) * passes * 1000 // dt, per_pass * passes * 1000 // dt, per_pass
