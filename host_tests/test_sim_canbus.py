"""The bench's CAN bus (motorjig.sim.canbus) and the jig's CAN controller on it
(motorjig.sim.canhal.SimCan): frame time, arbitration, ACK, fault confinement,
RX FIFO, listen-only, and machine.CAN's API semantics."""

import pytest

from motorjig.sim.canbus import (STATE_ACTIVE, STATE_BUS_OFF, STATE_PASSIVE, STATE_WARNING, CanBus,
                                 arbitration_key, frame_bits)
from motorjig.sim.canhal import RX_FIFO_LEN, SimCan, SimSlcanPort
from motorjig.sim.clock import VirtualClock


class Rec:
    """A node's received frames and transmissions done."""

    def __init__(self):
        self.frames = []
        self.done = []

    def on_frame(self, t, can_id, ext, rtr, data):
        self.frames.append((t, can_id, ext, rtr, data))

    def on_tx_done(self, t, ok):
        self.done.append((t, ok))


def bus_with(n, bitrate=500000, listen_only=()):
    clock = VirtualClock(1000.0)
    bus = CanBus(clock, bitrate)
    recs = [Rec() for _ in range(n)]
    nodes = [bus.add_node("n%d" % i, r.on_frame, r.on_tx_done, listen_only=i in listen_only)
             for i, r in enumerate(recs)]
    return clock, bus, nodes, recs


# --- frame time -----------------------------------------------------------------------

def test_frame_bits_worst_case_stuffing():
    assert frame_bits(False, False, 8) == 135
    assert frame_bits(False, False, 0) == 55  # 34 + 8 stuff + 10 + 3
    assert frame_bits(True, False, 8) == 160
    assert frame_bits(True, False, 0) == 80
    assert frame_bits(False, True, 8) == frame_bits(False, False, 0)  # a remote frame has no data


@pytest.mark.parametrize("bitrate, us", [(500000, 270.0), (1000000, 135.0)])
def test_frame_time_on_the_wire(bitrate, us):
    clock, bus, nodes, recs = bus_with(2, bitrate)
    t0 = clock.now
    nodes[0].transmit(0x181, False, False, bytes(range(8)))
    clock.advance(10000)
    (t, can_id, ext, rtr, data), = recs[1].frames
    assert (can_id, ext, rtr, data) == (0x181, False, False, bytes(range(8)))
    assert t == pytest.approx(t0 + us - 3 * 1e6 / bitrate)  # delivered at the end of EOF
    assert recs[0].done == [(t, True)] and recs[0].frames == []  # the sender does not hear itself
    assert bus.load(t0, t0 + us) == pytest.approx(1.0)
    assert bus.load(t0, t0 + 2 * us) == pytest.approx(0.5)
    assert bus.busy_us == pytest.approx(us)


def test_back_to_back_frames_fill_the_bus():
    clock, bus, nodes, recs = bus_with(2, 1000000)
    t0 = clock.now
    for i in range(10):
        nodes[0].transmit(0x200, False, False, b"\x00" * 8)
    clock.advance(5000)
    times = [f[0] for f in recs[1].frames]
    assert len(times) == 10
    assert [b - a for a, b in zip(times, times[1:])] == pytest.approx([135.0] * 9)
    assert bus.load(t0, t0 + 1350.0) == pytest.approx(1.0)


# --- arbitration ----------------------------------------------------------------------

def test_lowest_id_wins_among_frames_pending_when_the_bus_goes_idle():
    clock, bus, nodes, recs = bus_with(4)
    nodes[0].transmit(0x700, False, False, b"\x05")  # starts at once on the idle bus
    clock.advance(1)
    nodes[1].transmit(0x300, False, False, b"")
    nodes[2].transmit(0x080, False, False, b"")
    nodes[0].transmit(0x100, False, False, b"")
    nodes[1].transmit(0x081, False, False, b"")
    clock.advance(10000)
    assert [f[1] for f in recs[3].frames] == [0x700, 0x080, 0x081, 0x100, 0x300]


def test_standard_beats_extended_and_data_beats_remote():
    # same 11-bit base 0x123: standard data, standard remote, extended (base 0x123)
    k_std = arbitration_key(0x123, False, False)
    k_rtr = arbitration_key(0x123, False, True)
    k_ext = arbitration_key(0x123 << 18, True, False)
    assert k_std < k_rtr < k_ext
    assert arbitration_key(0x122 << 18 | 0x3FFFF, True, False) < k_std  # the base decides first
    clock, bus, nodes, recs = bus_with(4)
    nodes[0].transmit(0x7FF, False, False, b"")  # occupies the bus
    clock.advance(1)
    nodes[1].transmit(0x123 << 18, True, False, b"")
    nodes[2].transmit(0x123, False, True, b"\x00" * 4)
    nodes[0].transmit(0x123, False, False, b"\x01")
    clock.advance(10000)
    got = [(f[1], f[2], f[3]) for f in recs[3].frames[1:]]
    assert got == [(0x123, False, False), (0x123, False, True), (0x123 << 18, True, False)]
    assert recs[3].frames[2][4] == bytes(4)  # a remote frame: DLC zero bytes


def test_equal_ids_of_one_node_go_in_queue_order():
    clock, bus, nodes, recs = bus_with(2)
    for i in range(5):
        nodes[0].transmit(0x600, False, False, bytes([i]))
    clock.advance(10000)
    assert [f[4] for f in recs[1].frames] == [bytes([i]) for i in range(5)]


# --- ACK, error frames, fault confinement -----------------------------------------------

def test_a_frame_nobody_acknowledges_is_retried_and_the_sender_goes_error_passive():
    clock, bus, nodes, recs = bus_with(2, listen_only=(1,))
    nodes[0].transmit(0x181, False, False, b"\x01\x02")
    clock.advance(20000)
    assert recs[1].frames == [] and recs[0].done == []  # never delivered, never done
    assert bus.ack_errors > 16
    # 16 ACK errors bring TEC to 128; a passive transmitter's ACK error does not count
    assert nodes[0].tec == 128 and nodes[0].state == STATE_PASSIVE
    assert nodes[0].passive_entries == 1 and nodes[0].warning_entries == 1


def test_the_ack_comes_as_soon_as_a_second_node_is_there_and_tec_counts_down():
    clock, bus, nodes, recs = bus_with(2)
    nodes[1].online = False
    nodes[0].transmit(0x181, False, False, b"\x01")
    clock.advance(1500)
    tec = nodes[0].tec
    assert tec > 0 and recs[1].frames == []
    nodes[1].online = True
    clock.advance(2000)
    assert len(recs[1].frames) == 1 and recs[0].done[0][1] is True
    assert nodes[0].tec == tec - 1


def test_injected_errors_count_on_every_node_and_the_frame_comes_again():
    clock, bus, nodes, recs = bus_with(3)
    bus.inject_errors(3)
    nodes[0].transmit(0x205, False, False, b"\xAA" * 8)
    clock.advance(10000)
    assert [f[1] for f in recs[1].frames] == [0x205]  # once, after three error frames
    assert bus.error_frames == 3
    assert nodes[0].tec == 3 * 8 - 1
    assert nodes[1].rec == 3 - 1 and nodes[2].rec == 3 - 1


def test_bus_off_at_256_and_restart_after_recovery():
    clock, bus, nodes, recs = bus_with(2)
    states = []
    nodes[0].on_state = lambda t, s: states.append(s)
    bus.inject_errors(32)
    nodes[0].transmit(0x181, False, False, b"\x01")
    clock.advance(100000)
    assert nodes[0].tec == 256 and nodes[0].state == STATE_BUS_OFF
    assert states == [STATE_WARNING, STATE_PASSIVE, STATE_BUS_OFF]
    assert nodes[0].bus_off_entries == 1 and recs[1].frames == []
    # the receiver counted the 32 error frames (REC 32: still error active)
    assert nodes[1].rec == 32 and nodes[1].state == STATE_ACTIVE
    nodes[0].restart()
    clock.advance(128 * 11 * 2.0 - 1)
    assert nodes[0].state == STATE_BUS_OFF
    clock.advance(2000)
    assert nodes[0].state == STATE_ACTIVE and nodes[0].tec == 0
    assert [f[1] for f in recs[1].frames] == [0x181]  # its queued frame went out after recovery


def test_a_node_at_another_bitrate_goes_bus_off():
    clock, bus, nodes, recs = bus_with(2)
    nodes[0].bitrate = 250000
    nodes[0].transmit(0x181, False, False, b"\x01")
    nodes[1].transmit(0x182, False, False, b"\x02")
    clock.advance(100000)
    assert nodes[0].state == STATE_BUS_OFF and recs[1].frames == []
    assert recs[0].frames == []  # nor does it hear the others
    assert recs[1].done == [] and nodes[1].state == STATE_PASSIVE  # and nobody acks the other one


def test_listen_only_receives_but_neither_acks_nor_sends():
    clock, bus, nodes, recs = bus_with(3, listen_only=(2,))
    nodes[0].transmit(0x181, False, False, b"\x01")
    clock.advance(1000)
    assert [f[1] for f in recs[2].frames] == [0x181]
    with pytest.raises(ValueError):
        nodes[2].transmit(0x100, False, False, b"")


# --- SimCan: machine.CAN's API ------------------------------------------------------------

def can_bench(bitrate=500000, mode=0):
    clock = VirtualClock(1000.0)
    bus = CanBus(clock, bitrate)
    peer = Rec()
    pnode = bus.add_node("peer", peer.on_frame, peer.on_tx_done)
    can = SimCan(bus, bitrate, mode)
    return clock, bus, can, pnode, peer


def test_send_is_a_priority_queue_and_refuses_an_equal_id():
    clock, bus, can, pnode, peer = can_bench()
    assert can.send(0x700, b"\x00") == 0
    clock.advance(1)  # on the wire now (queued at the same instant, the others would have competed)
    assert can.send(0x300, b"\x01") == 1
    assert can.send(0x300, b"\x02") is None  # equal id queued: order not guaranteed
    assert can.send(0x300, b"\x02", can.FLAG_UNORDERED) == 2
    assert can.send(0x100, b"\x03") == 3
    assert can.send(0x300, b"", can.FLAG_EXT_ID) is None  # same numeric id, as on stm32
    clock.advance(10000)
    assert [f[1] for f in peer.frames] == [0x700, 0x100, 0x300, 0x300]
    assert [f[4] for f in peer.frames[2:]] == [b"\x01", b"\x02"]
    assert can.get_counters()[5] == 0


def test_the_transmit_queue_has_tx_queue_len_buffers():
    clock, bus, can, pnode, peer = can_bench()
    idx = [can.send(0x100 + i, b"") for i in range(SimCan.TX_QUEUE_LEN)]
    assert idx == list(range(SimCan.TX_QUEUE_LEN))
    assert can.send(0x200, b"") is None
    assert can.get_counters()[5] == SimCan.TX_QUEUE_LEN
    clock.advance(200)  # the first frame has gone: its buffer is free
    assert can.send(0x200, b"") == 0


def test_send_checks_like_machine_can():
    clock, bus, can, pnode, peer = can_bench()
    with pytest.raises(OverflowError):
        can.send(0x100, bytes(9))
    with pytest.raises(ValueError):
        can.send(0x800, b"")
    assert can.send(0x1FFFFFFF, b"", can.FLAG_EXT_ID) == 0
    can.deinit()
    assert can.state() == can.STATE_STOPPED
    with pytest.raises(OSError):
        can.send(0x100, b"")


def test_irq_flags_tell_what_fired():
    clock, bus, can, pnode, peer = can_bench()
    can.set_filters(None)
    seen = []
    lst = [0, memoryview(bytearray(8)), 0, 0]

    def handler(c):
        while True:
            f = c.irq().flags()
            if not f:
                break
            if f & c.IRQ_RX:
                while c.recv(lst) is not None:
                    seen.append(("rx", lst[0], bytes(lst[1]), lst[2]))
            if f & c.IRQ_TX:
                seen.append(("tx", (f >> c.IRQ_TX_IDX_SHIFT) & c.IRQ_TX_IDX_MASK, bool(f & c.IRQ_TX_FAILED)))
            if f & c.IRQ_STATE:
                seen.append(("state", c.state()))

    irq = can.irq(handler, can.IRQ_RX | can.IRQ_TX | can.IRQ_STATE, hard=True)
    assert can.irq() is irq and irq.trigger() == can.IRQ_RX | can.IRQ_TX | can.IRQ_STATE
    i = can.send(0x601, b"\x40\x00\x10\x00")
    pnode.transmit(0x581, False, False, b"\x43\x00\x10\x00\x92\x01\x02\x00")
    pnode.transmit(0x1234567, True, True, b"\x00\x00")
    clock.advance(5000)
    assert ("tx", i, False) in seen
    assert ("rx", 0x581, b"\x43\x00\x10\x00\x92\x01\x02\x00", 0) in seen
    assert ("rx", 0x1234567, b"\x00\x00", can.FLAG_EXT_ID | can.FLAG_RTR) in seen
    # a cancelled frame: IRQ_TX with IRQ_TX_FAILED
    pnode.online = False  # nobody acks: the frame keeps trying
    j = can.send(0x602, b"\x01")
    clock.advance(100)
    k = can.send(0x603, b"\x02")
    assert can.cancel_send(k) is True
    assert ("tx", k, True) in seen
    assert can.cancel_send(k) is False
    # errors: warning, then passive (IRQ_STATE each)
    clock.advance(20000)
    assert ("state", can.STATE_WARNING) in seen and ("state", can.STATE_PASSIVE) in seen
    assert can.get_counters()[2:5] == [1, 1, 0]
    assert j is not None


def test_tx_buffer_is_free_only_once_flags_reported_it():
    clock, bus, can, pnode, peer = can_bench()
    calls = []
    can.irq(lambda c: calls.append(1), can.IRQ_TX)  # a handler that does not call flags()
    assert can.send(0x100, b"") == 0
    clock.advance(1000)
    assert calls and can.send(0x101, b"") == 1  # buffer 0 still taken
    assert can.irq().flags() == (0 << 16) | can.IRQ_TX
    assert can.send(0x102, b"") == 0


def test_recv_resizes_the_view_and_needs_set_filters():
    clock, bus, can, pnode, peer = can_bench()
    pnode.transmit(0x181, False, False, b"\x01\x02\x03")
    clock.advance(1000)
    assert can.recv() is None  # nothing received before set_filters
    can.set_filters(None)
    pnode.transmit(0x181, False, False, b"\x01\x02\x03")
    pnode.transmit(0x182, False, False, b"")
    clock.advance(1000)
    buf = bytearray(8)
    lst = [0, memoryview(buf), 0, 0]
    assert can.recv(lst) is lst
    assert lst[0] == 0x181 and bytes(lst[1]) == b"\x01\x02\x03" and lst[1].obj is buf
    assert buf[:3] == b"\x01\x02\x03"
    assert can.recv(lst) is lst and len(lst[1]) == 0 and lst[1].obj is buf
    assert can.recv(lst) is None
    with pytest.raises(TypeError):
        can.recv([0, bytearray(8), 0, 0])


def test_filters_select_ids():
    clock, bus, can, pnode, peer = can_bench()
    can.set_filters([(0x580, 0x780, 0), (0x50700, 0x1FFFFFFF, can.FLAG_EXT_ID)])
    for cid, ext in ((0x585, False), (0x185, False), (0x50700, True), (0x580, True)):
        pnode.transmit(cid, ext, False, b"")
    clock.advance(2000)
    got = []
    while (r := can.recv()) is not None:
        got.append((r[0], r[2]))
    assert got == [(0x50700, can.FLAG_EXT_ID), (0x585, 0)]  # (0x50700's 11-bit base is 0x001)


def test_rx_fifo_overrun():
    clock, bus, can, pnode, peer = can_bench(1000000)
    can.set_filters(None)
    for i in range(RX_FIFO_LEN + 3):
        pnode.transmit(0x180 + (i % 8), False, False, bytes([i & 0xFF]))
    clock.advance(20000)
    c = can.get_counters()
    assert c[6] == RX_FIFO_LEN and c[7] == 3
    r = can.recv()
    assert r[3] == can.RECV_ERR_FULL | can.RECV_ERR_OVERRUN and r[1][0] == 0  # the oldest kept
    assert can.recv()[3] == 0  # flags cleared by the recv that reported them


def test_listen_only_simcan_receives_never_sends_never_acks():
    clock, bus, can, pnode, peer = can_bench(mode=SimCan.MODE_SILENT)
    can.set_filters(None)
    pnode.transmit(0x181, False, False, b"\x01")
    clock.advance(2000)
    assert can.recv() is None  # nobody acked the peer's frame: not valid for anyone
    assert pnode.tec > 0
    other = bus.add_node("other", None)
    clock.advance(2000)
    assert can.recv()[0] == 0x181  # acked by the other node now
    assert can.send(0x100, b"\x01") == 0  # taken, never sent (bus monitoring)
    clock.advance(5000)
    assert peer.frames == [] and can.get_counters()[5] == 1
    assert other is not None


def test_bus_off_send_raises_and_restart_recovers():
    clock, bus, can, pnode, peer = can_bench()
    states = []
    can.irq(lambda c: states.append(c.irq().flags()), can.IRQ_STATE)
    bus.inject_errors(32)
    can.send(0x181, b"\x01")
    clock.advance(100000)
    assert can.state() == can.STATE_BUS_OFF
    assert can.get_counters()[:5] == [256, 0, 1, 1, 1]
    assert states == [can.IRQ_STATE] * 3
    with pytest.raises(OSError):
        can.send(0x181, b"\x01")
    can.restart()
    assert can.get_counters()[2:6] == [0, 0, 0, 0]  # restart zeroes the entry counters, cancels TX
    clock.advance(5000)
    assert can.state() == can.STATE_ACTIVE
    assert can.send(0x181, b"\x02") == 0
    clock.advance(1000)
    assert [f[4] for f in peer.frames] == [b"\x02"]  # the cancelled frame never went out


def test_wrong_bitrate_controller_goes_bus_off():
    clock, bus, can, pnode, peer = can_bench()
    can.init(250000)
    can.send(0x181, b"\x01")
    clock.advance(100000)
    assert can.state() == can.STATE_BUS_OFF and peer.frames == []


# --- the SLCAN port ------------------------------------------------------------------------

def test_slcan_port_takes_what_fits_nothing_while_closed_and_delivers_per_usb_frame():
    clock = VirtualClock(0.0)
    port = SimSlcanPort(clock, tx_size=16)
    woke = []
    port.on_host_data = lambda: woke.append(1)
    assert port.write(b"t1230\r") == 0  # closed: nothing taken
    port.host_send(b"O\r")
    assert port.any() == 0 and woke == []  # dropped while closed
    port.host_open()
    port.host_send(b"S6\rO\r")
    assert woke == [] and port.any() == 0  # the host's bytes wait for the next USB frame
    clock.advance(999)
    assert woke == [] and port.any() == 0
    clock.advance(1)
    assert woke == [1] and port.any() == 5
    buf = bytearray(3)
    assert port.readinto(buf) == 3 and buf == b"S6\r"
    assert port.write(b"t12300\r" * 3) == 16  # what fits
    assert port.host_read() == b""
    clock.advance(1000)
    assert port.host_read() == (b"t12300\r" * 3)[:16]
    port.host_close()
    assert port.write(b"x") == 0
