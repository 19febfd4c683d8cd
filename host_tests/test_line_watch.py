"""The line watch (issue 26): cut through, a frame's first start bit takes the other
bus (DE up) while the byte arrives, so the DE pre-delay is over by the time its AA
can go on. Every way that can leave DE up for nothing must let the bus go: a byte
that is no AA, a start bit that never became a byte, a frame for the jig itself.
Run on both main loops (the portable one and jig.fastpath.pump's source)."""

import pytest

from jig import bridge as B
from jig import params as P
from jig import frame as F
from motorjig.sim import SimBench

BAUD = 115200


def _bench(**kw):
    b = SimBench(driver_ids=(2,), baud=BAUD, turnaround_us=100.0, **kw)
    b.run_for(1000.0)
    return b


def _jig_segments(bus):
    segs = []
    bus.monitor = lambda seg, data: segs.append((seg.node.name, bytes(data)))
    return segs


def _rises(node, since=0.0):
    return [t for t, v in node.de_log if v == 1 and t >= since]


@pytest.fixture(params=["portable", "fastpath"])
def jig_loop(request):
    from motorjig.sim import bench

    old = bench.DEFAULT_FASTPATH
    bench.DEFAULT_FASTPATH = request.param == "fastpath"
    yield request.param
    bench.DEFAULT_FASTPATH = old


def test_a_byte_that_is_no_aa_lets_the_driver_bus_go_when_it_is_in(jig_loop):
    b = _bench()
    down = b.hal.down.node
    segs = _jig_segments(b.down_bus)
    n0 = len(down.de_log)
    end = b.send(b"\x11")
    b.run_for(500.0)
    bt = b.down_bus.bt
    log = down.de_log[n0:]
    assert [v for _t, v in log] == [1, 0]  # up at its start bit, down when it was in
    assert log[0][0] == pytest.approx(end - bt + bt / 20, abs=1e-6)
    assert end <= log[1][0] < end + 50
    assert [d for name, d in segs if name == "jig-down"] == []  # nothing was sent
    _w, r = b.request(2, F.GET_ALL_STATUS)
    assert r is not None and r[0] == 0


def test_a_stream_of_noise_takes_the_bus_once_not_per_byte(jig_loop):
    """Only a byte after a byte time of silence can be a frame's first: the bytes of a
    stream of noise that follow it are not watched."""
    b = _bench()
    down = b.hal.down.node
    n0 = len(down.de_log)
    noise = bytes((0x11 + 7 * i) & 0x7F for i in range(60))  # no AA in it
    b.send(noise)
    b.run_for(60 * b.down_bus.bt + 2000.0)
    assert [v for _t, v in down.de_log[n0:]] == [1, 0]
    assert not down.de


class _Glitch:
    """An ISR whose BUSY shows for ``span`` us from ``t0``, with no byte behind it (a
    start bit that the USART then rejected as noise)."""

    def __init__(self, clock, t0, span):
        self.clock = clock
        self.t0 = t0
        self.span = span

    def __getitem__(self, i):
        now = self.clock.now
        return B.ISR_BUSY if self.t0 <= now < self.t0 + self.span else 0


def _glitch(b, port, span=3.0):
    t0 = b.clock.now + 10.0
    port.isr = _Glitch(b.clock, t0, span)
    if b.app.bridge.up_isr is not None:  # (the portable loop holds the ports' ISRs)
        b.app.bridge.up_isr = b.hal.up.isr
        b.app.bridge.down_isr = b.hal.down.isr
    if b.app.pump is not None:
        from jig import fastpath

        b.app.pump_ctx = fastpath.context(b.app)
    b.clock.at(t0 + span / 2, b.hal.on_rx)  # the loop's idle pass sees it
    return t0


def test_a_start_bit_that_never_becomes_a_byte_lets_the_bus_go_within_two_byte_times(jig_loop):
    b = _bench()
    down = b.hal.down.node
    n0 = len(down.de_log)
    t0 = _glitch(b, b.hal.up)
    b.run_for(20.0)
    assert down.de  # taken at the start bit
    b.run_for(20000.0)
    log = down.de_log[n0:]
    assert [v for _t, v in log] == [1, 0]
    held = log[1][0] - log[0][0]
    limit = B.ARM_BYTES * (10000000 // BAUD)
    assert limit < held <= limit + 1000 + 1  # after two byte times, by the next pass at the latest
    assert b.app.down.early[1] == -1
    _w, r = b.request(2, F.GET_ALL_STATUS)  # the bridge works as before
    assert r is not None and r[0] == 0
    assert t0 < log[0][0]


def test_a_glitch_on_the_driver_bus_while_a_reply_is_awaited_lets_the_pc_bus_go(jig_loop):
    b = SimBench(driver_ids=(2,), baud=BAUD, turnaround_us=20000.0)  # a slow drive
    b.run_for(1000.0)
    up = b.hal.up.node
    b.send(b.encode(2, F.GET_ALL_STATUS))
    b.run_for(2000.0)  # forwarded; the reply is awaited
    n0 = len(up.de_log)
    _glitch(b, b.hal.down)
    b.run_for(5000.0)
    assert [v for _t, v in up.de_log[n0:]] == [1, 0]
    b.run_for(30000.0)
    assert b.counters["replies"] == 1  # the real reply came later and was relayed
    assert b.pc.frames and b.pc.frames[-1][1][2] == 2


def test_a_frame_for_the_jig_after_a_watched_start_bit_is_answered_and_the_bus_let_go(jig_loop):
    b = _bench()
    down = b.hal.down.node
    segs = _jig_segments(b.down_bus)
    n0 = len(down.de_log)
    _w, info = b.request(1, F.GET_SLAVE_INFO)
    assert info is not None and b"MotorJig" in info
    assert [v for _t, v in down.de_log[n0:]] == [1, 0]
    assert not down.de
    assert [d for name, d in segs if name == "jig-down"] == [b"\xaa", b"\xcc", b"\x01", b"\xaa\xee"]  # the stub


def test_the_driver_bus_is_not_watched_while_a_reply_is_awaited_nor_store_and_forward(jig_loop):
    """A reply may start any moment while it is awaited: a PC byte then must not take
    the driver bus. Store-and-forward passes on only whole frames: nothing is watched."""
    b = SimBench(driver_ids=(2,), baud=BAUD, turnaround_us=5000.0)
    b.send(b.encode(2, F.GET_ALL_STATUS))
    b.run_for(1500.0)
    n0 = len(b.hal.down.node.de_log)
    b.send(b"\x11")
    b.run_for(500.0)
    assert len(b.hal.down.node.de_log) == n0
    sf = SimBench(driver_ids=(2,), baud=BAUD, turnaround_us=100.0,
                  jig_params={P.P_FORWARD_MODE: P.STORE_AND_FORWARD})
    sf.run_for(1000.0)
    assert sf.app.bridge.up_isr is None and sf.app.pump is None
    n0 = len(sf.hal.down.node.de_log)
    end = sf.send(sf.encode(2, F.GET_ALL_STATUS))
    sf.run_for(100.0)
    assert len(sf.hal.down.node.de_log) == n0  # nothing until the frame is whole
    sf.run_for(20000.0)
    assert _rises(sf.hal.down.node)[-1] >= end


def test_the_jigs_own_request_takes_an_armed_bus_and_keeps_its_pre_delay(jig_loop):
    """The bus scan sends on a driver bus that a PC start bit has armed: its request
    waits what is left of the pre-delay (DE is up already), and DE goes down after it."""
    b = _bench()
    down = b.hal.down.node
    segs = []
    b.down_bus.monitor = lambda seg, data: segs.append((seg.node.name, seg.t0, bytes(data)))
    _glitch(b, b.hal.up, span=1.0)
    b.run_for(15.0)
    assert down.de and b.app.down.early[1] >= 0
    t_arm = down.t_rise
    ok = b.app.bridge.request(_Client(), 3, F.GET_SLAVE_INFO, b"", 0, 20)
    assert ok
    b.run_for(30000.0)
    mine = [(t, d) for name, t, d in segs if name == "jig-down"]
    assert mine and mine[0][0] - t_arm >= b.app.params.get(P.P_DE_PRE_US) - 1e-6
    assert not down.de and b.app.down.early[1] == -1


class _Client:
    def on_reply(self, p):
        pass

    def on_timeout(self):
        pass

    def on_abort(self):
        pass


def test_the_pc_bus_is_blind_only_while_armed_and_hears_a_frame_after_it(jig_loop):
    """While the PC bus is armed for an answer its receiver is off (/RE tied to DE, as the
    bench models it). A start bit on the driver bus that never becomes a byte lets it go
    after two byte times; a PC frame after that is heard whole and goes on (it aborts the
    wait for the slow drive's answer)."""
    b = SimBench(driver_ids=(2, 3), baud=BAUD, turnaround_us=20000.0)  # slow drives
    b.run_for(1000.0)
    b.send(b.encode(2, F.GET_ALL_STATUS))
    b.run_for(2000.0)  # forwarded; the answer is awaited
    up = b.hal.up.node
    n0 = len(up.de_log)
    t0 = _glitch(b, b.hal.down)
    b.run_for(20.0)
    assert up.de  # armed: the PC bus is driven, its receiver off
    b.clock.run_until(t0 + B.ARM_BYTES * b.up_bus.bt + 30.0)
    assert not up.de and [v for _t, v in up.de_log[n0:]] == [1, 0]
    segs = _jig_segments(b.down_bus)
    req = b.encode(3, F.GET_COMMAND_POS)
    b.send(req)
    b.run_for(3000.0)
    assert b"".join(d for name, d in segs if name == "jig-down") == req  # heard whole, passed on
    assert b.counters["aborts"] == 1


def test_no_arming_of_the_pc_bus_while_the_pc_talks(jig_loop):
    """A start bit on the driver bus while the PC's own line is busy (the PC talking over
    its wait) must not take the PC bus: the jig would talk over the PC and hear nothing."""
    b = SimBench(driver_ids=(2, 3), baud=BAUD, turnaround_us=20000.0)
    b.run_for(1000.0)
    b.send(b.encode(2, F.GET_ALL_STATUS))
    b.run_for(2000.0)
    up = b.hal.up.node
    n0 = len(up.de_log)
    req = b.encode(3, F.GET_COMMAND_POS)
    end = b.send(req)
    t_first = end - len(req) * b.up_bus.bt
    port = b.hal.down
    port.isr = _Glitch(b.clock, t_first + 5.0, 20.0)  # within the PC's first byte
    b.app.bridge.down_isr = port.isr if b.app.bridge.down_isr is not None else None
    if b.app.pump is not None:
        from jig import fastpath

        b.app.pump_ctx = fastpath.context(b.app)
    b.clock.at(t_first + 10.0, b.hal.on_rx)
    b.run_for(end - b.clock.now + 3000.0)
    assert up.de_log[n0:] == []  # the PC bus was never taken
    assert b.counters["aborts"] == 1 and b.counters["forwards"] == 2
