"""DE/RE timing on the virtual timeline, hardware-DE mode, echo discard."""

import pytest

from jig import frame as F
from jig import params as P
from jig.ringbuf import RingBuffer
from jig.rs485 import Rs485, wire_time_us
from motorjig.sim import SimBench

EPS = 1e-6


class Tap:
    def __init__(self, bus):
        self.segs = []
        bus.monitor = lambda seg, data: self.segs.append((seg.node.name, seg.t0, seg.end, bytes(data)))

    def by(self, name):
        """(name, start, end, bytes) per frame a node sent: the pieces of a frame cut
        through (one write per piece, DE held between them) are joined."""
        out = []
        for seg in self.segs:
            if seg[0] != name:
                continue
            if out and not out[-1][3].endswith(b"\xaa\xee"):
                n, t0, _t1, d = out[-1]
                out[-1] = (n, t0, seg[2], d + seg[3])
            else:
                out.append(seg)
        return out


def check_de(node, seg_start, seg_end, pre_us, before):
    """DE up >= pre_us before the first start bit, down after the last stop bit and before `before`."""
    rises = [t for t, v in node.de_log if v == 1 and t <= seg_start + EPS]
    falls = [t for t, v in node.de_log if v == 0 and t >= seg_start]
    assert rises, "DE never rose before the transmission"
    assert rises[-1] <= seg_start - pre_us + EPS
    assert falls, "DE never fell"
    assert falls[0] >= seg_end - EPS  # not before the last stop bit has left
    assert falls[0] < before  # released before the other side starts talking
    return rises[-1], falls[0]


MODES = pytest.mark.parametrize("mode", [P.CUT_THROUGH, P.STORE_AND_FORWARD], ids=["cut", "saf"])


@MODES
@pytest.mark.parametrize("baud", P.BAUD_RATES)
def test_de_timing_every_baud(baud, mode):
    b = SimBench(driver_ids=(2,), baud=baud, turnaround_us=50.0, jig_params={P.P_FORWARD_MODE: mode})
    down, up = Tap(b.down_bus), Tap(b.up_bus)
    pre = b.app.params.get(P.P_DE_PRE_US)
    wire, r = b.request(2, F.GET_COMMAND_POS, timeout_us=500000.0)
    assert r is not None
    (_n, j0, j1, sent), = down.by("jig-down")
    assert sent == F.encode(2, F.GET_COMMAND_POS)
    assert abs((j1 - j0) - len(sent) * 10e6 / baud) < 1e-3  # 10 bits per byte at this baud
    (_n, d0, _d1, _reply), = down.by("driver-2")
    check_de(b.hal.down.node, j0, j1, pre, d0)
    # relay upstream: the PC's next request may follow right away
    (_n, u0, u1, relayed), = up.by("jig-up")
    assert relayed == wire
    check_de(b.hal.up.node, u0, u1, pre, u1 + 10e6 / baud)
    (_n, p0, p1, _req), = up.by("pc")
    bt = 10e6 / baud
    if mode == P.STORE_AND_FORWARD:
        # the jig adds at most the pre-delay + one byte time over store-and-forward
        assert j0 - p1 <= pre + bt
        assert u0 - _d1 <= pre + bt
    else:
        # cut through: the request starts out once AA CC id are in, the reply once
        # AA CC id type are (the virtual timeline charges no CPU time)
        assert j0 - (p0 + 3 * bt) <= pre + EPS
        assert u0 - (d0 + 4 * bt) <= pre + EPS


@MODES
@pytest.mark.parametrize("baud", (9600, 115200, 921600))
def test_de_delays_from_parameters(baud, mode):
    b = SimBench(driver_ids=(2,), baud=baud, turnaround_us=2000.0, jig_params={P.P_FORWARD_MODE: mode})
    assert b.request(1, F.SET_PARAMETER, bytes([P.P_DE_PRE_US]) + (250).to_bytes(4, "little"))[1] == b"\x00"
    assert b.request(1, F.SET_PARAMETER, bytes([P.P_DE_POST_US]) + (100).to_bytes(4, "little"))[1] == b"\x00"
    down = Tap(b.down_bus)
    assert b.request(2, F.GET_AXIS_STATUS, timeout_us=500000.0)[1] is not None
    (_n, j0, j1, _s), = down.by("jig-down")
    (_n, d0, _d1, _r), = down.by("driver-2")
    rise, fall = check_de(b.hal.down.node, j0, j1, 250, d0)
    assert fall >= j1 + 100 - EPS


@pytest.mark.parametrize("baud", P.BAUD_RATES)
def test_hardware_de_mode(baud):
    b = SimBench(driver_ids=(2,), baud=baud, turnaround_us=50.0,
                 jig_params={P.P_DE_MODE: 1, P.P_FORWARD_MODE: P.STORE_AND_FORWARD})
    assert b.app.down.hw and b.app.up.hw
    down = Tap(b.down_bus)
    assert b.request(2, F.GET_COMMAND_POS, timeout_us=500000.0)[1] is not None
    (_n, j0, j1, _s), = down.by("jig-down")
    (_n, d0, _d1, _r), = down.by("driver-2")
    lead = min(10.0, 31 / 16 * 1e6 / baud)  # DEAT is 5 bits of 1/16 bit time
    check_de(b.hal.down.node, j0, j1, lead - 1e-3, d0)


def test_hardware_de_is_not_used_cut_through():
    """The USART drops DE when its transmitter runs empty between the pieces of a
    frame cut through, so there the jig keeps software DE."""
    b = SimBench(driver_ids=(2,), jig_params={P.P_DE_MODE: 1})
    assert not b.app.down.hw and not b.app.up.hw
    assert b.request(2, F.GET_COMMAND_POS)[1] is not None


def test_wire_time():
    assert wire_time_us(1, 115200) == 87
    assert wire_time_us(10, 9600) == 10417
    assert wire_time_us(0, 9600) == 0


class FakePort:
    """A port whose receiver hears what it sends (echo), plus scripted incoming bytes."""

    def __init__(self, echo=True, tx_blocks=True):
        self.baud = 115200
        self.rx = RingBuffer(256)
        self.echo = echo
        self.tx_blocks = tx_blocks
        self.t_last = 0
        self.overflows = 0
        self.log = []
        self.sent = b""

    def any(self):
        return self.rx.any()

    def readinto(self, buf, n):
        return self.rx.read_into(buf, n)

    def write(self, buf, off, n):
        self.log.append(("write", n))
        self.sent += bytes(buf[off : off + n])
        if self.echo:
            self.rx.write(bytes(buf[off : off + n]), n)

    def de(self, v):
        self.log.append(("de", v))


class FakeHal:
    def __init__(self):
        self.t = 0
        self.sleeps = []

    def ticks_us(self):
        return self.t

    def sleep_us(self, us):
        self.sleeps.append(us)
        self.t += us


def test_echo_skipped_after_bytes_already_waiting():
    hal, port = FakeHal(), FakePort()
    rs = Rs485(hal, port, pre_us=5, post_us=3)
    port.rx.write(b"ABC", 3)  # arrived before we transmit: must be kept
    rs.send(b"\xaa\xcc\x01\x02", 4)
    port.rx.write(b"XYZ", 3)  # arrives afterwards: kept
    buf = bytearray(64)
    n = rs.read_into(buf, 64)
    assert bytes(buf[:n]) == b"ABCXYZ"
    assert rs.echo_bytes == 4
    assert port.log == [("de", 0), ("de", 1), ("write", 4), ("de", 0)]
    assert hal.sleeps == [5, 3]


def test_echo_skipped_across_small_reads():
    hal, port = FakeHal(), FakePort()
    rs = Rs485(hal, port)
    port.rx.write(b"AB", 2)
    rs.send(b"12345", 5)
    port.rx.write(b"C", 1)
    buf = bytearray(64)
    out = b""
    for _ in range(10):
        n = rs.read_into(buf, 1)
        out += bytes(buf[:n])
    assert out == b"ABC" and rs.echo_bytes == 5


def test_non_blocking_write_waits_the_wire_time():
    hal, port = FakeHal(), FakePort(echo=False, tx_blocks=False)
    rs = Rs485(hal, port, pre_us=0, post_us=0)
    rs.send(b"x" * 10, 10)
    assert hal.sleeps == [wire_time_us(10, 115200)]
    assert port.log[-1] == ("de", 0)


def test_hw_de_hook_receives_sixteenths():
    hal, port = FakeHal(), FakePort(echo=False)
    calls = []
    port.hw_de = lambda on, pre, post: calls.append((on, pre, post)) or True
    rs = Rs485(hal, port, pre_us=10, post_us=1000, hw_de=True)
    assert rs.hw and calls[-1] == (True, 19, 31)
    rs.send(b"ab", 2)
    assert ("de", 1) not in port.log  # the USART drives DE
    port2 = FakePort(echo=False)  # no hook: software DE
    assert not Rs485(hal, port2, hw_de=True).hw


def test_separate_re_pin_follows_de():
    hal, port = FakeHal(), FakePort(echo=False)
    port.re = lambda v: port.log.append(("re", v))
    rs = Rs485(hal, port, pre_us=0, post_us=0)
    port.log.clear()
    rs.send(b"ab", 2)
    assert port.log == [("re", 1), ("de", 1), ("write", 2), ("de", 0), ("re", 0)]


def test_turnaround_counters():
    from jig.counters import Counters

    c = Counters()
    for us in (40, 10, 70):
        c.turnaround(us)
    assert (c.get("turnaround_count"), c.get("turnaround_min_us"), c.get("turnaround_avg_us"), c.get("turnaround_max_us")) == (3, 10, 40, 70)
    c.reset()
    assert c.get("turnaround_max_us") == 0 and c.get("turnaround_count") == 0


def test_turnaround_average_restarts_before_its_sum_leaves_the_small_ints():
    from jig.counters import Counters

    c = Counters()
    c.turnaround(0x20000000)
    c.turnaround(0x20000000)  # the sum would pass 2**30 - 1: the average starts over here
    assert c.get("turnaround_avg_us") == 0x20000000
    c.turnaround(0)
    names = ("turnaround_count", "turnaround_min_us", "turnaround_avg_us", "turnaround_max_us")
    assert tuple(c.get(n) for n in names) == (3, 0, 0x10000000, 0x20000000)
    c.reset()
    c.turnaround(6)
    assert tuple(c.get(n) for n in names) == (1, 6, 6, 6)


# --- a transmitter with a queue (the USART FIFO on the board: port.queue/drain) -------
def _queued_bench(baud=921600, cpu_model=(6.5, 2.5)):
    return SimBench(driver_ids=(2,), baud=baud, turnaround_us=100.0, cpu_model=cpu_model,
                    jig_params={P.P_FORWARD_MODE: P.CUT_THROUGH})


def test_cut_through_pieces_are_queued_and_drained_before_de_drops():
    b = _queued_bench()
    assert b.app.down.queued and b.app.up.queued
    down, up = Tap(b.down_bus), Tap(b.up_bus)
    wire, r = b.request(2, F.GET_ALL_STATUS, timeout_us=1e6)
    assert r is not None and r[0] == 0
    (_n, j0, j1, sent), = down.by("jig-down")
    assert sent == F.encode(2, F.GET_ALL_STATUS)
    # Queued pieces follow each other on the wire: the frame takes its own wire time,
    # though the jig's CPU (6.5 us a pass) is slower than a byte time (10.85 us) would
    # allow if it had to wait for each piece to leave before reading the next.
    assert abs((j1 - j0) - len(sent) * 10e6 / 921600) < 1e-3
    check_de(b.hal.down.node, j0, j1, b.app.params.get(P.P_DE_PRE_US), float("inf"))
    (_n, u0, u1, relayed), = up.by("jig-up")
    assert relayed == wire
    assert abs((u1 - u0) - len(wire) * 10e6 / 921600) < 1e-3
    check_de(b.hal.up.node, u0, u1, b.app.params.get(P.P_DE_PRE_US), float("inf"))
    assert b.up_bus.lost == 0 and b.down_bus.lost == 0


def test_hop_latency_does_not_grow_with_the_frame():
    """With the pieces queued, the CPU works while they go out: the jig is one fixed
    delay behind the wire, not one pass per piece."""
    b = _queued_bench()
    down = Tap(b.down_bus)
    pc = Tap(b.up_bus)
    hops = []
    for data in (b"", bytes(40)):  # GetAllStatus (8 bytes on the wire) and a 48-byte SetIO-like frame
        down.segs.clear()
        pc.segs.clear()
        b.request(2, F.GET_ALL_STATUS if not data else F.SET_IO_OUTPUT, data, timeout_us=1e6)
        (_n, _p0, p1, _), = [s for s in pc.by("pc")]
        (_n, _j0, j1, _), = down.by("jig-down")
        hops.append(j1 - p1)
    assert abs(hops[1] - hops[0]) < 1.0, hops


def test_sim_write_refuses_while_queued_bytes_go_out():
    b = _queued_bench(cpu_model=(0.0, 0.0))
    port = b.hal.down
    port.de(1)
    port.queue(b"\xaa\xcc\x02", 0, 3)
    with pytest.raises(RuntimeError):
        port.write(b"\xaa\xee", 0, 2)
    port.drain()
    port.write(b"\xaa\xee", 0, 2)
    port.de(0)


def test_a_port_without_a_queue_writes_each_piece():
    hal, port = FakeHal(), FakePort(echo=False)
    rs = Rs485(hal, port, pre_us=0, post_us=0)
    assert not rs.queued and rs.raw_part == port.write
    rs.begin(b"\xaa\xcc", 0, 2)
    rs.part(b"\x02\x40", 0, 2)
    rs.finish()
    assert port.log[-3:] == [("write", 2), ("write", 2), ("de", 0)]
