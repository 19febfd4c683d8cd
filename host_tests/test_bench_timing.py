"""The bench's timing options: a PC wired directly to the drivers, the polling-rate
measurement of `make bench`, and the model of the jig's CPU time (issue 8)."""

import pytest

import bench_bridge
from jig import frame as F
from jig import params as P
from motorjig.sim import SimBench


def test_direct_bench_talks_to_the_driver_with_no_jig():
    b = SimBench(direct=True, driver_ids=(2,), baud=115200, turnaround_us=300.0)
    assert b.app is None and b.up_bus is b.down_bus
    _w, info = b.request(2, F.GET_SLAVE_INFO)
    assert info is not None and info[0] == 0 and b"Ezi-STEP" in info
    end = b.send(b.encode(2, F.GET_ALL_STATUS))
    n0 = len(b.pc.frames)
    b.run_for(100000.0)
    (t, wire), = b.pc.frames[n0:]
    assert wire[2] == 2 and wire[3] == F.GET_ALL_STATUS
    # nothing in the line: the reply ends a turnaround plus its own wire time after the request
    assert t - end == pytest.approx(300.0 + len(wire) * b.down_bus.bt, abs=1e-6)
    assert b.request(1, F.GET_SLAVE_INFO) == (None, None)  # no jig at id 1


@pytest.mark.parametrize("baud", (9600, 115200, 921600))
def test_direct_polling_rate_matches_the_wire_time_model(baud):
    d = bench_bridge.polling_rate(baud, direct=True, n=10)
    model = bench_bridge.direct_period_us(d["req_bytes"], d["rep_bytes"], baud)
    assert d["req_bytes"] == 8 and d["rep_bytes"] > 30
    assert d["period_us"] == pytest.approx(model, rel=0.01)
    assert d["rate"] == pytest.approx(1e6 / model, rel=0.01)


@pytest.mark.parametrize("mode", (P.CUT_THROUGH, P.STORE_AND_FORWARD))
@pytest.mark.parametrize("cpu_model", ((0.0, 0.0), (30.0, 2.0)))
def test_polling_through_the_jig_is_consistent_with_its_hops(mode, cpu_model):
    baud = 57600
    d = bench_bridge.polling_rate(baud, direct=True, n=5)
    j = bench_bridge.polling_rate(baud, forward_mode=mode, n=5, cpu_model=cpu_model)
    assert j["rep_bytes"] == d["rep_bytes"]
    # the jig's hops are all it adds to a direct poll; a jig is never faster than a wire
    assert j["period_us"] == pytest.approx(d["period_us"] + j["req_hop_us"] + j["rep_hop_us"], rel=0.01)
    assert 0 < j["rate"] < d["rate"]
    assert 0 <= j["req_hop_min_us"] <= j["req_hop_us"] <= j["req_hop_max_us"]
    assert 0 <= j["rep_hop_min_us"] <= j["rep_hop_us"] <= j["rep_hop_max_us"]
    if mode == P.STORE_AND_FORWARD:
        # a whole frame's wire time, DE pre-delay, then the CPU of the pass that read the last byte
        pre = 10.0
        cpu = cpu_model[0] + cpu_model[1]
        bt = 10e6 / baud
        assert j["req_hop_us"] == pytest.approx(j["req_bytes"] * bt + pre + cpu, abs=1.0)
        assert j["rep_hop_us"] == pytest.approx(j["rep_bytes"] * bt + pre + cpu, abs=1.0)


@pytest.mark.parametrize("baud", (9600, 115200, 921600))
def test_cut_through_hops_are_two_byte_times_with_no_cpu(baud):
    """A frame goes on from its header, both ways: with an infinitely fast CPU each
    hop is the two header bytes' wire time plus the DE pre-delay, and the polling
    rate is within the 90 % of a direct line that issue 8 asks for."""
    d = bench_bridge.polling_rate(baud, direct=True, n=5)
    j = bench_bridge.polling_rate(baud, forward_mode=P.CUT_THROUGH, n=5, cpu_model=(0.0, 0.0))
    bt = 10e6 / baud
    pre = 10.0
    assert j["req_hop_us"] == pytest.approx(2 * bt + pre, abs=0.5)
    assert j["rep_hop_us"] == pytest.approx(2 * bt + pre, abs=0.5)
    assert j["rate"] / d["rate"] >= 0.90


def reply_end(cpu_model, slave, mode=P.STORE_AND_FORWARD):
    b = SimBench(driver_ids=(2,), baud=115200, cpu_model=cpu_model, jig_params={P.P_FORWARD_MODE: mode})
    b.run_for(1000.0)
    end = b.send(b.encode(slave, F.GET_SLAVE_INFO))
    n0 = len(b.pc.frames)
    b.run_for(100000.0)
    (t, _wire), = b.pc.frames[n0:]
    return t - end, b.hal.cpu_us


def test_cpu_model_delays_a_local_reply_by_the_pass_that_read_the_last_byte():
    base, cpu0 = reply_end((0.0, 0.0), 1)
    slow, cpu = reply_end((20.0, 1.5), 1)
    assert cpu0 == 0
    # one byte per pass (21.5 µs < 86.8 µs byte time): each of the 8 request bytes is charged
    assert cpu == pytest.approx(8 * 21.5)
    assert slow - base == pytest.approx(21.5, abs=1e-3)


def test_cpu_model_delays_each_hop_of_a_forwarded_transaction():
    base, _ = reply_end((0.0, 0.0), 2)
    slow, _ = reply_end((20.0, 1.5), 2)
    assert slow - base == pytest.approx(2 * 21.5, abs=1e-3)


def test_cpu_slower_than_the_bytes_batches_them_and_still_answers():
    base, _ = reply_end((0.0, 0.0), 1)
    slow, cpu = reply_end((200.0, 0.0), 1)  # a pass takes longer than 2 byte times
    assert slow - base >= 200.0
    assert cpu < 8 * 200.0  # bytes that arrived during a pass were read together


def test_bad_options_are_refused():
    with pytest.raises(ValueError):
        SimBench(cpu_model=(-1.0, 0.0))
    with pytest.raises(ValueError):
        SimBench(direct=True, cpu_model=(10.0, 0.0))  # no jig to be slow
    with pytest.raises(ValueError):
        SimBench(direct=True, jig_params={12: 1})
    with pytest.raises(ValueError):
        SimBench(stream_chunk=0)


def test_jig_port_can_send_a_frame_in_pieces_with_de_held():
    """What a cut-through jig does: DE up, the frame written as it arrives, DE down."""
    b = SimBench(driver_ids=(2,), baud=115200)
    b.run_for(1000.0)
    port = b.hal.down
    frame = F.encode(2, F.GET_SLAVE_INFO)
    port.de(1)
    t0 = b.clock.now
    for i in range(len(frame)):
        port.write(frame, i, 1)  # blocks until its stop bit has left
        assert b.clock.now == pytest.approx(t0 + (i + 1) * b.down_bus.bt + i * 30.0)
        b.run_for(30.0)  # the next byte is late: the line idles, DE stays high
    port.de(0)
    b.run_for(20000.0)
    d = b.drivers[2]
    assert d.requests == 1 and d.replies == 1 and b.down_bus.lost == 0
    assert [v for _t, v in port.node.de_log[-2:]] == [1, 0]
