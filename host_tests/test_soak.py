"""Soak: 100 000 PC transactions through the jig in virtual time, faults injected at random.

Every transaction checks what the PC got against what actually happened on the
driver bus; at the end the jig's counters must reconcile exactly.
"""

import random
import struct

from jig import frame as F
from motorjig.sim import SimBench

N_TRANSACTIONS = 100000
DRIVERS = (2, 3, 5)
ABSENT = (4, 9)
TIMEOUT_US = 50000.0  # jig reply_timeout_ms default
PC_WAIT_US = 60000.0

REQUESTS = (
    (F.GET_AXIS_STATUS, b""),
    (F.GET_COMMAND_POS, b""),
    (F.GET_ALL_STATUS, b""),
    (F.GET_PARAMETER, b"\x03"),
    # 0xAA in the data exercises stuffing; on the jig, parameter 7 is de_post_us
    (F.SET_PARAMETER, b"\x07" + struct.pack("<i", 0xAA)),
    (F.GET_SLAVE_INFO, b""),
    (F.SET_COMMAND_POS, struct.pack("<i", -0x55AA)),
    (F.GET_IO_INPUT, b""),
)


def run_soak(n, seed, ver8=False, stream_chunk=1):
    rng = random.Random(seed)
    bench = SimBench(driver_ids=DRIVERS, record=False, ver8=ver8, stream_chunk=stream_chunk)
    drivers = bench.drivers
    # What the drivers put on the wire in the current transaction (as delivered).
    driver_wire = []
    bench.down_bus.monitor = lambda seg, data: driver_wire.append(data) if seg.node.name.startswith("driver") else None
    stats = dict(ok=0, local=0, absent=0, faulted=0, broadcast=0, lost=0, wrong=0, dup=0, faults=0)
    pc = bench.pc
    for k in range(n):
        for d in drivers.values():
            d.silent = d.garbage = d.bad_crc = False
            d.late_us = 0.0
            d.wrong_id = None
        r = rng.random()
        if r < 0.03:
            slave = bench.jig_id
        elif r < 0.05:
            slave = rng.choice(ABSENT)
        elif r < 0.06:
            slave = F.BROADCAST_ID
        else:
            slave = rng.choice(DRIVERS)
        ftype, data = REQUESTS[rng.randrange(len(REQUESTS))]
        if slave == F.BROADCAST_ID:
            ftype, data = F.ALL_MOVE_STOP, b""
        wire = bench.encode(slave, ftype, data)
        fault = None
        if slave in drivers and rng.random() < 0.05:
            fault = rng.choice(("silent", "garbage", "late", "wrong_id", "bad_crc", "noise_up", "noise_down", "truncated", "retry"))
            stats["faults"] += 1
            d = drivers[slave]
            if fault == "silent":
                d.silent = True
            elif fault == "garbage":
                d.garbage = True
            elif fault == "late":
                d.late_us = TIMEOUT_US + 5000.0
            elif fault == "wrong_id":
                d.wrong_id = rng.choice(ABSENT)
            elif fault == "bad_crc":
                d.bad_crc = True
            elif fault == "retry":
                d.late_us = 8000.0  # slow answer: the PC re-sends after 3 ms
        n_frames = len(pc.frames)
        del driver_wire[:]
        if fault == "truncated":
            bench.send(wire[: rng.randrange(2, len(wire) - 1)])
            bench.run_for(20000.0)  # longer than the inter-byte timeout
        if fault == "noise_up":
            bench.up_bus.inject(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 12))))
            bench.run_for(5000.0)
        t_end = bench.send(wire)
        if fault == "noise_down":
            # noise on the driver bus while the driver answers: may destroy the reply
            bench.down_bus.inject(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 12))),
                                  t=t_end + rng.uniform(0, 2000.0))
        if fault == "retry":
            bench.clock.run_until(t_end + 3000.0)
            t_end = bench.send(wire)
        if slave == F.BROADCAST_ID:
            bench.run_for(3000.0)
        else:
            bench.clock.run_while(lambda: len(pc.frames) == n_frames, t_end - bench.clock.now + PC_WAIT_US)
        got = pc.frames[n_frames:]
        if fault == "late":
            bench.run_for(10000.0)  # let the late reply arrive (it must be dropped)
            got = pc.frames[n_frames:]
        if fault == "retry":
            bench.run_for(15000.0)  # the second answer must be dropped
            got = pc.frames[n_frames:]
        # checks
        for _t, w in got:
            body = w[2:-2].replace(b"\xaa\xaa", b"\xaa")
            p_id, p_type = body[0], body[2 if ver8 else 1]
            if p_id != slave or p_type != ftype:
                stats["wrong"] += 1
            if ver8 and body[1] != wire[3]:  # the reply to *this* request (sync)
                stats["wrong"] += 1
            if slave in drivers and w not in driver_wire:  # relayed unchanged
                stats["wrong"] += 1
        if slave == F.BROADCAST_ID:
            stats["broadcast"] += 1
            if got:
                stats["wrong"] += 1
            continue
        if slave in ABSENT:
            stats["absent"] += 1
            if got:
                stats["wrong"] += 1
            continue
        if len(got) > 1:
            stats["dup"] += 1
        if slave == bench.jig_id:
            stats["local"] += 1
            if len(got) != 1:
                stats["lost"] += 1
            continue
        if fault is None or fault == "retry":
            if len(got) != 1:
                stats["lost"] += 1
            stats["ok"] += 1
        else:
            stats["faulted"] += 1
            if fault in ("silent", "garbage", "late", "wrong_id", "bad_crc") and got:
                stats["wrong"] += 1
    bench.run_for(100000.0)
    return bench, stats


def test_soak_100k_transactions_with_faults():
    # The jig gets the bytes 4 at a time (each byte on its own is the ver8 soak's and
    # the e2e tests' job): a wake-up per byte would make this run 4x longer.
    bench, s = run_soak(N_TRANSACTIONS, seed=20261122, stream_chunk=4)
    c = bench.counters
    assert s["wrong"] == 0 and s["dup"] == 0 and s["lost"] == 0, s
    assert s["faults"] > 3000  # the faults really happened
    # conservation: every forwarded request ended exactly one way
    assert c["forwards"] == c["replies"] + c["timeouts"] + c["aborts"]
    assert c["up_frames_in"] == c["local_requests"] + c["forwards"] + c["broadcasts"]
    assert c["up_frames_out"] == c["replies"] + c["local_requests"] == len(bench.pc.frames)
    assert c["broadcasts"] == s["broadcast"]
    assert c["local_requests"] == s["local"]
    # faults were seen by the jig where they should be
    assert c["timeouts"] >= s["absent"]
    assert c["stale_drops"] > 0 and c["aborts"] > 0 and c["down_crc_errors"] > 0
    assert c["up_timeouts"] + c["up_resyncs"] > 0


def test_soak_ver8_sync_numbers():
    """Ver8: every reply the PC gets carries the sync number of its own request."""
    bench, s = run_soak(10000, seed=8, ver8=True)
    c = bench.counters
    assert s["wrong"] == 0 and s["dup"] == 0 and s["lost"] == 0, s
    assert c["forwards"] == c["replies"] + c["timeouts"] + c["aborts"]
    assert c["up_frames_out"] == c["replies"] + c["local_requests"] == len(bench.pc.frames)
