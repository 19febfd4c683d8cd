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
def test_cut_through_hops_are_one_byte_time_with_no_cpu(baud):
    """A frame goes on from its first byte, both ways: the AA that can start a header
    is sent on as soon as it is in, and the rest follows through the transmit FIFO.
    The other bus is taken (DE up) at that byte's start bit (the line watch), so the
    DE pre-delay (10 us) runs while the byte arrives: with an infinitely fast CPU each
    hop is the byte's own wire time -- the least a UART bridge can do -- and the
    polling rate is within 95 % of a direct line at every baud rate (ticks are whole
    µs: at 921 600 baud up to 1 µs of pre-delay may be waited on). Without the line
    watch the pre-delay comes after the byte (at 921 600 baud, where a byte lasts
    10.85 us, that was 93.8 %)."""
    d = bench_bridge.polling_rate(baud, direct=True, n=5)
    j = bench_bridge.polling_rate(baud, forward_mode=P.CUT_THROUGH, n=5, cpu_model=(0.0, 0.0))
    bt = 10e6 / baud
    pre = 10.0
    # (what is left of the pre-delay is reckoned in whole-µs ticks: up to 1 µs more
    # where the pre-delay is nearly a byte time)
    assert bt - 1e-6 <= j["req_hop_us"] <= bt + 1.0
    assert bt - 1e-6 <= j["rep_hop_us"] <= bt + 1.0
    assert j["rate"] / d["rate"] >= 0.95
    before = bench_bridge.polling_rate(baud, forward_mode=P.CUT_THROUGH, n=5, cpu_model=(0.0, 0.0),
                                       line_watch=False)
    assert before["req_hop_us"] == pytest.approx(bt + pre, abs=0.5)
    assert before["rep_hop_us"] == pytest.approx(bt + pre, abs=0.5)
    assert before["req_pre_left_us"] == pytest.approx(pre, abs=0.01)
    assert before["rate"] < j["rate"]


@pytest.mark.parametrize("baud", (460800, 921600))
def test_the_line_watch_hides_the_pre_delay_behind_the_first_byte_with_the_m7_model(baud):
    """With the jig's CPU modelled (the M7 figures of `make test-qemu`: an idle pass
    before a start bit is seen, then the pass that reads the byte) the pre-delay is
    over before the byte's pass is done: what is left of a hop is the byte and that
    pass, and the polling rate is >= 95 % of a direct line (issue 26)."""
    model = bench_bridge.JIG_CPU_MODEL
    d = bench_bridge.polling_rate(baud, direct=True, n=5)
    j = bench_bridge.polling_rate(baud, forward_mode=P.CUT_THROUGH, n=5, cpu_model=model)
    bt = 10e6 / baud
    assert j["req_pre_left_us"] == j["rep_pre_left_us"] == 0
    assert j["req_hop_us"] == pytest.approx(bt + model[0] + model[1], abs=0.01)
    assert j["rep_hop_us"] == pytest.approx(bt + model[0] + model[1], abs=0.01)
    assert j["rate"] / d["rate"] >= 0.95


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


# --- DE up early: at the AA's start bit (the line watch), or at the AA --------------------
def _de_log(b, bus_name):
    node = b.hal.down.node if bus_name == "down" else b.hal.up.node
    return list(node.de_log)


def _segments(bus):
    segs = []
    bus.monitor = lambda seg, data: segs.append((seg.node.name, seg.t0, seg.end, bytes(data)))
    return segs


@pytest.mark.parametrize("watch", (True, False))
@pytest.mark.parametrize("baud", (115200, 921600))
def test_the_aa_goes_on_at_once_after_the_pre_delay(baud, watch):
    """The PC's AA takes the driver bus as soon as its start bit is seen (the line
    watch: DE up half a bit into it), the AA goes on once it is in and the whole
    pre-delay has passed, the CC and the rest follow as they come: the frame leaves
    one byte time after it began -- no more -- and whole. Without the line watch
    DE goes up when the AA is in, and the pre-delay adds to the hop."""
    b = SimBench(driver_ids=(2,), baud=baud, turnaround_us=100.0, line_watch=watch)
    pre = b.app.params.get(P.P_DE_PRE_US)
    assert pre == 10
    segs = _segments(b.down_bus)
    pc_end = b.send(b.encode(2, F.GET_ALL_STATUS))
    b.run_for(2000.0 + 20 * b.down_bus.bt)
    jig = [s for s in segs if s[0] == "jig-down"]
    assert b"".join(s[3] for s in jig) == b.encode(2, F.GET_ALL_STATUS)
    assert jig[0][3] == b"\xaa"  # the AA on its own: it did not wait for the CC
    first_bit = jig[0][1]
    bt = b.down_bus.bt
    pc_first_bit = pc_end - 8 * bt
    rises = [t for t, v in b.hal.down.node.de_log if v == 1 and t <= first_bit]
    assert rises and first_bit - rises[-1] >= pre - 1e-6  # the transceiver had its pre-delay
    if watch:
        assert rises[-1] == pytest.approx(pc_first_bit + bt / 20, abs=1e-6)  # half a bit in
        assert bt - 1e-6 <= first_bit - pc_first_bit <= bt + 1.0  # pre-delay < a byte (ticks: whole µs)
    else:
        assert rises[-1] == pytest.approx(pc_first_bit + bt, abs=1e-6)
        assert first_bit - pc_first_bit == pytest.approx(bt + pre, abs=0.01)


def test_a_lone_aa_from_the_pc_takes_the_driver_bus_only_until_the_parser_gives_it_up():
    """A wire would pass the AA on, and so does the jig; no header follows, so the bus
    is let go after the inter-byte timeout, and a frame after it is understood (an AA
    before a header is noise to the drives' parsers)."""
    b = SimBench(driver_ids=(2,), baud=115200, turnaround_us=100.0)
    timeout = b.app.params.get(P.P_INTERBYTE_US)
    segs = _segments(b.down_bus)
    end = b.send(b"\xaa")  # then silence
    b.run_for(3 * timeout)
    log = b.hal.down.node.de_log
    assert [v for _t, v in log][-2:] == [1, 0]
    up_t, down_t = log[-2][0], log[-1][0]
    assert end - b.down_bus.bt < up_t < end + 100  # at the AA (its start bit)
    assert timeout <= down_t - end <= timeout + 1100  # the parser's inter-byte timeout (+ one slow pass)
    assert [s[3] for s in segs if s[0] == "jig-down"] == [b"\xaa"]  # the AA, nothing else
    # the bus works as before afterwards
    _w, r = b.request(2, F.GET_ALL_STATUS)
    assert r is not None and r[0] == 0


def test_an_aa_not_followed_by_cc_gives_the_bus_back_at_the_next_byte():
    b = SimBench(driver_ids=(2,), baud=115200, turnaround_us=100.0)
    segs = _segments(b.down_bus)
    end = b.send(b"\xaa")
    b.run_for(end - b.clock.now + 20.0)
    assert b.hal.down.node.de  # up at the AA
    end = b.send(b"\x11")
    b.run_for(500.0)
    assert not b.hal.down.node.de
    fall = b.hal.down.node.de_log[-1][0]
    assert end <= fall < end + 100
    assert [s[3] for s in segs if s[0] == "jig-down"] == [b"\xaa"]
    _w, r = b.request(2, F.GET_ALL_STATUS)
    assert r is not None and r[0] == 0


def test_no_early_de_on_the_driver_bus_while_a_reply_is_awaited():
    """A reply may start any moment then: a lone AA from the PC must not take the bus."""
    b = SimBench(driver_ids=(2,), baud=115200, turnaround_us=5000.0)  # a slow drive
    b.send(b.encode(2, F.GET_ALL_STATUS))
    b.run_for(1500.0)  # forwarded; the reply is awaited
    n_edges = len(b.hal.down.node.de_log)
    assert not b.hal.down.node.de
    end = b.send(b"\xaa")
    b.run_for(end - b.clock.now + 200.0)
    assert len(b.hal.down.node.de_log) == n_edges and not b.hal.down.node.de
    b.run_for(20000.0)
    assert b.counters["replies"] == 1  # the wait went on; the reply reached the PC


@pytest.mark.parametrize("watch", (True, False))
def test_early_de_on_the_pc_bus_for_a_reply(watch):
    """The driver's AA while its reply is awaited takes the PC bus and goes on at once:
    the relay leaves one byte time after the reply began (the line watch: DE up at
    the AA's start bit; without it, one byte time and the pre-delay), with DE up the
    whole pre-delay before it."""
    b = SimBench(driver_ids=(2,), baud=921600, turnaround_us=100.0, line_watch=watch)
    up = _segments(b.up_bus)
    down = _segments(b.down_bus)
    _w, r = b.request(2, F.GET_ALL_STATUS)
    assert r is not None and r[0] == 0
    drive_first_bit = [s for s in down if s[0] == "driver-2"][0][1]
    first_bit = [s for s in up if s[0] == "jig-up"][0][1]
    pre = b.app.params.get(P.P_DE_PRE_US)
    lag = first_bit - drive_first_bit - b.up_bus.bt
    if watch:
        assert -1e-6 <= lag <= 1.0  # (the rest of the pre-delay in whole-µs ticks)
    else:
        assert lag == pytest.approx(pre, abs=0.01)
    rises = [t for t, v in b.hal.up.node.de_log if v == 1 and t <= first_bit]
    assert first_bit - rises[-1] >= pre - 1e-6


@pytest.mark.parametrize("baud", (460800, 921600))
def test_the_slow_pass_falls_in_the_drives_turnaround_not_inside_a_frame(baud):
    """The slow pass (18 920 instructions in the model, 47 us) inside a frame being passed
    on stalls the copy: the transmitter runs dry. A forwarded request's end 3 ms or more
    after the last slow pass asks for it then, while the drive thinks, so no hop of a
    fast poller is longer than the others (before: every fourth request at 460 800 baud
    lost 20-36 us)."""
    j = bench_bridge.polling_rate(baud, n=40)
    assert j["req_hop_max_us"] - j["req_hop_min_us"] < 1.0
    assert j["rep_hop_max_us"] - j["rep_hop_min_us"] < 1.0
    assert j["jig_cpu_us"] > 40 * 47  # (the slow passes ran: their CPU is in the model)
