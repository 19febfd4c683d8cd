"""The CAN port's figures on the emulated Cortex-M7 (issue 24, "Measured"), for qemu_suite.

Frozen into the qemu build beside qemu_suite, which calls ``run(result, fail, prices)``
after its bridge figures. The jig's App runs on qemu_suite's memory HAL (``MemHal``,
the UART ports in C) plus the CAN port's hardware as C models of the qemu build
(tools/firmware/qemu/cmodules/memcan):

* ``memcan.CAN`` -- machine.CAN on FDCAN1: recv/send/irq().flags()/state()/
  get_counters() do the Python-facing and the controller work the board's C does
  (argument parsing, buffer protocol, message RAM, TX buffer scan, a real mp_irq
  object) on registers in RAM; the interrupt runs as the board's does: an ISR model
  calls the handler through MicroPython's own hard-IRQ dispatch (``mp_irq_handler``).
  Its instructions stay in the figures: they are the estimate of the board's. The
  rig's part of each bus call (putting the frame into the controller, the call
  from Python) is measured and taken out.
* ``memcan.Vcp`` -- the SLCAN port (``pyb.USB_VCP(2)``): its any/readinto/write are
  counted, their stand-in cost taken out and priced as qemu_suite prices the UART's
  (board_check: ``any`` / ``readinto`` / ``write`` C methods), as the capture port's
  USB write is priced by a C stream method.

Printed (``RESULT can ...``), heap locked (any allocation fails the probe):

1. a CAN frame received -> SLCAN line out: the RX interrupt (ISR, handler, recv into
   the ring), ``CanPort.poll`` turning it into a line written to the port, and the
   whole slow pass the frame asks for (``App._slow``); a burst of 16 frames;
2. an SLCAN frame line in -> frame queued: ``CanPort.poll`` reading the line, queueing
   the frame and handing it to the controller (``send``), the CR answer; the TX
   interrupt; the next poll counting it;
3. the Plus-R bridge (cut-through, ``jig.fastpath.pump``): forwarded transaction, local
   GetSlaveInfo, idle pass, with the HAL calls at the board's prices, without a CAN
   port, with the port closed, open and idle, and open and busy (a frame received
   and a host line waiting in every transaction; once with the slow pass the frame
   asks for held off, once with everything in).

Under CPython (host tests: ``run(..., quick=True)``) Python stand-ins replace the C
models and the figures mean nothing.
"""

import gc
from array import array

import qemu_suite as Q
from jig import compat
from jig.compat import ticks_diff, ticks_us

try:
    import memcan  # in the qemu build only (tools/firmware/qemu/cmodules/memcan)
except ImportError:
    memcan = None

V_ANY = 0
V_READ = 1
V_WRITE = 2
V_LOAD = 3
VCP_CALLS = array("i", [0, 0, 0, 0])

RX_ID = 0x181  # a TPDO1 of node 1, 8 bytes
RX_DATA = b"\x11\x22\x33\x44\x55\x66\x77\x88"
RX_LINE = b"t18181122334455667788\r"
TX_LINE = b"t60582B40600002000000\r"  # an SDO upload request to node 5
OPEN_LINE = b"O\r"


# --- Python stand-ins, for CPython only -------------------------------------------------------
class PyIrq:
    def __init__(self, can):
        self.can = can

    def flags(self):
        c = self.can
        f = 2 if c.fifo else 0
        if c.done:
            c.done = 0
            f |= 1
        return f


class PyCan:
    """memcan.CAN's interface in Python (CPython: the host tests)."""

    FLAG_RTR = 1
    FLAG_EXT_ID = 2
    IRQ_TX = 1
    IRQ_RX = 2
    IRQ_TX_FAILED = 4
    IRQ_STATE = 8

    def __init__(self):
        self.fifo = []
        self.handler = None
        self.irqo = PyIrq(self)
        self.pending = 0
        self.done = 0
        self.sent = 0
        self.last_id = 0
        self.last_len = 0
        self.isr_runs = 0

    def irq(self, handler=None, trigger=0, hard=False):
        if handler is not None:
            self.handler = handler
        return self.irqo

    def recv(self, lst):
        if not self.fifo:
            return None
        can_id, data = self.fifo.pop(0)
        lst[0] = can_id
        lst[1] = memoryview(bytearray(data))
        lst[2] = 0
        lst[3] = 0
        return lst

    def send(self, can_id, data, flags=0):
        self.pending = 1
        self.sent += 1
        self.last_id = can_id
        self.last_len = len(data)
        return 0

    def state(self):
        return 1

    def get_counters(self, lst):
        for i in range(8):
            lst[i] = 0
        return lst

    def set_filters(self, f):
        pass

    def restart(self):
        pass

    def deinit(self):
        pass

    def _isr(self):
        self.isr_runs += 1
        if self.handler is not None:
            self.handler(self)

    def bus_rx(self, can_id, data, n, flags):
        self.fifo.append((can_id, bytes(data[0:n])))
        self._isr()

    def bus_put(self, can_id, data, n, flags):
        self.fifo.append((can_id, bytes(data[0:n])))

    def bus_clear(self):
        self.fifo = []

    def bus_tx_done(self, ok):
        if self.pending:
            self.pending = 0
            self.done = 1
            self._isr()

    def bus_nop(self, x):
        pass


class PyVcp:
    def __init__(self, counts):
        self.counts = counts
        self.rx = b""
        self.pos = 0
        self.taken = 0

    def any(self):
        self.counts[V_ANY] += 1
        return len(self.rx) - self.pos

    def readinto(self, buf):
        self.counts[V_READ] += 1
        k = min(len(buf), len(self.rx) - self.pos)
        buf[0:k] = self.rx[self.pos:self.pos + k]
        self.pos += k
        return k

    def write(self, buf):
        self.counts[V_WRITE] += 1
        self.taken += len(buf)
        return len(buf)

    def load(self, data, n):
        self.counts[V_LOAD] += 1
        self.rx = bytes(data[0:n])
        self.pos = 0

    def again(self):
        self.counts[V_LOAD] += 1
        self.pos = 0


def new_can():
    if memcan is not None:
        return memcan.CAN()
    return PyCan()


def new_vcp():
    if memcan is not None:
        return memcan.Vcp(VCP_CALLS)
    return PyVcp(VCP_CALLS)


_MemHal = Q.MemHal


class CanMemHal(_MemHal):
    """qemu_suite's memory HAL with the board's CAN port: hal.can_open / can_close and
    hal.slcan, as jig.board has them."""

    def __init__(self):
        _MemHal.__init__(self)
        self.slcan = new_vcp()
        self.can = None

    def can_open(self, bitrate, listen_only):
        self.can = new_can()
        self.can.set_filters(None)
        return self.can

    def can_close(self, can):
        can.deinit()


def can_rig(mode, capture=False):
    """qemu_suite.BridgeRig on CanMemHal (BridgeRig makes its own MemHal: the class is
    swapped for the construction only)."""
    saved = Q.MemHal
    Q.MemHal = CanMemHal
    try:
        return Q.BridgeRig(mode, capture)
    finally:
        Q.MemHal = saved


def open_port(rig, fail):
    """The host's O: the port opens the controller (hal.can_open) in a slow pass."""
    app = rig.app
    vcp = rig.hal.slcan
    vcp.load(OPEN_LINE, len(OPEN_LINE))
    app.can.poll(ticks_us())
    if not app.can.is_open or rig.hal.can is None:
        fail("can: O did not open the port")
        return False
    return True


# --- costs of the stand-ins and the rig's calls --------------------------------------------
def _per_call(fn, n):
    t0 = ticks_us()
    fn(n)
    return ticks_diff(ticks_us(), t0)


def vcp_call_costs():
    """Instructions per call of the SLCAN port stand-in's any, readinto, write (V_* order)."""
    vcp = new_vcp()
    buf = bytearray(64)
    mv = memoryview(buf)[0:22]
    vcp.load(RX_LINE, len(RX_LINE))
    any_ = vcp.any
    readinto = vcp.readinto
    write = vcp.write
    n = 400

    def base(k):
        for _ in range(k):
            pass

    def a(k):
        for _ in range(k):
            any_()

    def r(k):
        for _ in range(k):
            readinto(mv)

    def w(k):
        for _ in range(k):
            write(mv)

    b = _per_call(base, n)
    return [Q.instr(_per_call(f, n) - b) // n for f in (a, r, w)]


def rig_call_costs(can):
    """The rig's share of a frame arriving (bus_put: into the controller, the call from
    Python) and of a finished TX with nothing pending (bus_tx_done: the call), and a
    loaded host line (vcp.load/again), per call."""
    n = 32

    def base(k):
        for _ in range(k):
            pass

    def put(k):
        for _ in range(k):
            can.bus_put(RX_ID, RX_DATA, 8, 0)

    def done(k):
        for _ in range(k):
            can.bus_tx_done(1)

    vcp = new_vcp()

    vcp.load(TX_LINE, len(TX_LINE))

    def load(k):
        for _ in range(k):
            vcp.again()

    b = _per_call(base, n)
    p = _per_call(put, n)
    can.bus_clear()
    d = _per_call(done, n)
    ld = _per_call(load, n)
    return Q.instr(p - b) // n, Q.instr(d - b) // n, Q.instr(ld - b) // n


class Vcpricer:
    """SLCAN port calls: their stand-in cost out, the board's price in."""

    def __init__(self, prices):
        self.costs = vcp_call_costs()
        self.snap = array("i", [0, 0, 0, 0])
        if prices is not None:
            self.board = (prices[0], prices[1], prices[2])  # board_check: any, readinto, write
        else:
            self.board = None

    def start(self):
        for k in range(4):
            self.snap[k] = VCP_CALLS[k]

    def delta(self):
        return [VCP_CALLS[k] - self.snap[k] for k in range(4)]

    def acc(self, dst):
        """dst[k] += the calls since start() (no allocation: heap locked)."""
        for k in range(4):
            dst[k] += VCP_CALLS[k] - self.snap[k]

    def stand_in(self, d):
        return d[V_ANY] * self.costs[0] + d[V_READ] * self.costs[1] + d[V_WRITE] * self.costs[2]

    def on_board(self, d):
        if self.board is None:
            return 0
        return d[V_ANY] * self.board[0] + d[V_READ] * self.board[1] + d[V_WRITE] * self.board[2]


# --- 1 and 2: the port's own figures -------------------------------------------------------------
class Meter:
    """Accumulates timed segments: instructions, the UART stand-in's calls (qemu_suite's
    HAL_CALLS) and the SLCAN port's; nothing allocated between begin() and end()."""

    def __init__(self):
        nh = len(Q.HAL_CALLS)
        self.h0 = array("i", [0] * nh)
        self.h = array("i", [0] * nh)
        self.v0 = array("i", [0, 0, 0, 0])
        self.v = array("i", [0, 0, 0, 0])
        self.t0 = 0
        self.t = 0
        self.n = 0

    def clear(self):
        for k in range(len(self.h)):
            self.h[k] = 0
        for k in range(4):
            self.v[k] = 0
        self.t = self.n = 0

    def begin(self):
        h0 = self.h0
        v0 = self.v0
        for k in range(len(h0)):
            h0[k] = Q.HAL_CALLS[k]
        for k in range(4):
            v0[k] = VCP_CALLS[k]
        self.t0 = ticks_us()

    def end(self):
        t1 = ticks_us()
        self.t += ticks_diff(t1, self.t0)
        h = self.h
        h0 = self.h0
        v = self.v
        v0 = self.v0
        for k in range(len(h)):
            h[k] += Q.HAL_CALLS[k] - h0[k]
        for k in range(4):
            v[k] += VCP_CALLS[k] - v0[k]
        self.n += 1

    def figure(self, costs, vp, prices, tcost, per_call=0):
        """(own, at the board's prices) per segment: the timing, the stand-ins and
        per_call (the rig's share, run()'s set-up) taken out, the board's prices put in."""
        n = self.n or 1
        stand = 0
        for k in range(len(costs)):
            stand += self.h[k] * costs[k]
        own = (Q.instr(self.t) - stand - vp.stand_in(self.v)) / n - tcost - per_call
        board = own
        if prices is not None:
            board = own + (Q.board_hal(self.h, costs, prices) + vp.on_board(self.v)) / n
        return int(own), int(board)


def _timing_cost():
    m = Meter()
    for _ in range(200):
        m.begin()
        m.end()
    return Q.instr(m.t) / m.n


def port_due(app):
    """The tick the app serves the CAN port at: its own (due[1]) where the app has it,
    else the slow pass's."""
    due = app.due
    return 1 if len(due) > 1 else 0


def port_figures(result, fail, prices, n):
    from jig import params

    rig = can_rig(params.CUT_THROUGH)
    app = rig.app
    port = app.can
    if not open_port(rig, fail):
        return None
    can = rig.hal.can
    vcp = rig.hal.slcan
    vp = Vcpricer(prices)
    costs = Q.hal_call_costs()
    put_cost, done_cost, load_cost = rig_call_costs(can)
    tcost = _timing_cost()
    setup = rig.setup_cost()
    run = rig.poll
    slow = app._slow
    bus_rx = can.bus_rx
    tx_done = can.bus_tx_done
    ticks = ticks_us
    due = app.due
    pd = port_due(app)
    data = RX_DATA
    m_rx_irq = Meter()
    m_rx_pass = Meter()
    m_idle = Meter()
    m_port_idle = Meter()
    m_tx_pass = Meter()
    m_tx_irq = Meter()
    m_tx_count = Meter()
    m_slow = Meter()
    for _ in range(3):  # every path once: first-use allocations happen here
        bus_rx(RX_ID, data, 8, 0)
        run(1)
        vcp.load(TX_LINE, len(TX_LINE))
        due[pd] = ticks()
        run(1)
        tx_done(1)
        due[pd] = ticks()
        run(1)
    taken0 = vcp.taken
    sent0 = can.sent
    rx0 = port.cv[0]
    gc.collect()
    m0 = Q.mem_total()
    Q.heap_lock(True)
    try:
        for _ in range(n):
            # a frame received -> its line out: the interrupt, then the pass it asks for
            m_rx_irq.begin()
            bus_rx(RX_ID, data, 8, 0)
            m_rx_irq.end()
            m_rx_pass.begin()
            run(1)
            m_rx_pass.end()
            # a main-loop pass with nothing to do; the port's pass with nothing to do
            m_idle.begin()
            run(1)
            m_idle.end()
            due[pd] = ticks()
            m_port_idle.begin()
            run(1)
            m_port_idle.end()
            # a host line -> frame queued and handed to the controller, in the port's pass
            vcp.load(TX_LINE, len(TX_LINE))
            due[pd] = ticks()
            m_tx_pass.begin()
            run(1)
            m_tx_pass.end()
            m_tx_irq.begin()
            tx_done(1)
            m_tx_irq.end()
            due[pd] = ticks()
            m_tx_count.begin()
            run(1)
            m_tx_count.end()
            # the whole slow pass with the port open and nothing to do
            m_slow.begin()
            slow(ticks())
            m_slow.end()
    except MemoryError:
        Q.heap_lock(False)
        fail("can: the port's steady state allocated with the heap locked")
        return None
    Q.heap_lock(False)
    heap = (Q.mem_total() - m0) // n
    line = len(RX_LINE)
    if vcp.taken - taken0 != n * (line + 1) or can.sent - sent0 != n or port.cv[0] - rx0 != n:
        fail("can: %d bytes to the host, %d frames sent, %d received (expected %d, %d, %d)"
             % (vcp.taken - taken0, can.sent - sent0, port.cv[0] - rx0, n * (line + 1), n, n))
    if heap and compat.IS_MICROPYTHON:
        fail("can: %d heap bytes per round" % heap)

    def fig(m, per_call=0):
        return m.figure(costs, vp, prices, tcost, per_call)

    rx_isr = fig(m_rx_irq, put_cost)[1]
    rx_pass = fig(m_rx_pass, setup)[1]
    idle = fig(m_idle, setup)[1]
    port_idle = fig(m_port_idle, setup)[1]
    tx_pass = fig(m_tx_pass, setup)[1]
    tx_isr = fig(m_tx_irq, done_cost)[1]
    tx_cnt = fig(m_tx_count, setup)[1]
    slow0 = fig(m_slow)[1]
    rx_total = rx_isr + rx_pass - idle
    rx_marg = rx_isr + rx_pass - port_idle
    tx_total = tx_pass - idle + tx_isr + tx_cnt - idle
    tx_marg = tx_pass - port_idle + tx_isr + tx_cnt - port_idle
    kind = "CanPort's own pass (app.due[1])" if pd else "the slow pass (App._slow)"
    result("can stand-ins (taken out): SLCAN port any %d, readinto %d, write %d instructions a call (C), priced "
           "as the UART's at the board's: %s; the rig's part of a frame arriving %d, of a TX end %d; memcan.CAN's "
           "own C (machine.CAN's work on FDCAN registers in RAM, hard-IRQ dispatch) stays in; the port is served "
           "by %s" % (vp.costs[0], vp.costs[1], vp.costs[2],
                      "%d / %d / %d" % vp.board if vp.board else "not measured", put_cost, done_cost, kind))
    result("can frame received -> SLCAN line out (8 data bytes, %d-byte line), at the board's prices: RX interrupt "
           "(ISR, hard-IRQ dispatch, CanPort._irq: flags(), recv() into the ring) %d + the main-loop pass that "
           "serves it %d (an idle pass: %d; the port's pass with nothing to do: %d) = %d beyond an idle pass, "
           "%d beyond the port's pass; heap allocated per round %d bytes (heap locked)"
           % (line, rx_isr, rx_pass, idle, port_idle, rx_total, rx_marg, heap))
    result("can SLCAN line in -> frame queued (%d-byte line, 8 data bytes), at the board's prices: the port's pass "
           "reading it, queueing the frame, send() to the controller and the CR %d + TX interrupt (ISR, dispatch, "
           "CanPort._irq: flags(), _tx_end) %d + the next port pass counting it %d = %d beyond idle passes, %d "
           "beyond the port's passes; whole slow pass, port open, nothing due: %d; heap allocated per round %d "
           "bytes (heap locked)" % (len(TX_LINE), tx_pass, tx_isr, tx_cnt, tx_total, tx_marg, slow0, heap))
    burst(result, fail, rig, vp, costs, prices, put_cost, tcost, setup)
    return rx_total, tx_total


def burst(result, fail, rig, vp, costs, prices, put_cost, tcost, setup, frames=16, rounds=20):
    """16 frames arriving (16 interrupts) before the passes that write their lines (the
    port's own pass takes RX_PER_SERVE of them a pass, where the app has it)."""
    can = rig.hal.can
    vcp = rig.hal.slcan
    bus_rx = can.bus_rx
    app = rig.app
    due = app.due
    pd = port_due(app)
    rs = app.can.rs
    ticks = ticks_us
    run = rig.poll
    m_irq = Meter()
    m_pass = Meter()
    m_idle = Meter()
    taken0 = vcp.taken
    gc.collect()
    Q.heap_lock(True)
    try:
        for _ in range(rounds):
            for _ in range(frames):
                m_irq.begin()
                bus_rx(RX_ID, RX_DATA, 8, 0)
                m_irq.end()
            passes = 0
            while rs[1] != rs[0] and passes < frames:  # (RS_TAIL, RS_HEAD)
                due[pd] = ticks()
                m_pass.begin()
                run(1)
                m_pass.end()
                passes += 1
            m_idle.begin()
            run(1)
            m_idle.end()
    except MemoryError:
        Q.heap_lock(False)
        fail("can: a burst allocated with the heap locked")
        return
    Q.heap_lock(False)
    if vcp.taken - taken0 != rounds * frames * len(RX_LINE):
        fail("can: a burst of %d frames gave %d bytes of lines" % (frames, (vcp.taken - taken0) // rounds))
    isr = m_irq.figure(costs, vp, prices, tcost, put_cost)[1]
    npass = m_pass.n // rounds  # (the passes a burst took)
    pas = m_pass.figure(costs, vp, prices, tcost, setup)[1]
    idle = m_idle.figure(costs, vp, prices, tcost, setup)[1]
    per = (pas - idle) * npass // frames
    result("can burst of %d frames, then the %d passes that serve them: per frame %d (interrupt) + %d (its share of "
           "the passes, %d beyond an idle pass each) = %d instructions at the board's prices; %d port writes "
           "a burst" % (frames, npass, isr, per, pas - idle, isr + per, m_pass.v[V_WRITE] // rounds))


# --- 3: the bridge beside the CAN port -------------------------------------------------------------
def measure(rig, fn, count, costs, prices, vp, rig_share):
    """qemu_suite.measure with the SLCAN port's calls priced too and the rig's CAN calls
    (rig_share instructions per call of fn's unit) taken out: (own, heap, on_board)."""
    fn(3)
    setup = rig.setup_cost()
    rig.fresh()
    gc.collect()
    calls0 = Q.HAL_CALLS[:]
    runs0 = rig.runs
    vp.start()
    m0 = Q.mem_total()
    Q.heap_lock(True)
    try:
        t0 = ticks_us()
        fn(count)
        dt = ticks_diff(ticks_us(), t0)
    except MemoryError:
        Q.heap_lock(False)
        return -1, -1, -1
    Q.heap_lock(False)
    heap = (Q.mem_total() - m0) // count
    d = [Q.HAL_CALLS[k] - calls0[k] for k in range(len(Q.HAL_CALLS))]
    vd = vp.delta()
    hal = 0
    for k in range(len(costs)):
        hal += d[k] * costs[k]
    hal += (rig.runs - runs0) * setup + vp.stand_in(vd) + rig_share * count
    own = (Q.instr(dt) - hal) // count
    on_board = -1
    if prices is not None:
        on_board = own + int(Q.board_hal(d, costs, prices) + vp.on_board(vd)) // count
    return own, heap, on_board


class Busy:
    """Forwarded transactions with the CAN port busy: in every one a frame arrives on
    the CAN bus (its interrupt at the start) and a frame line from the host waits on the
    SLCAN port, the last one's TX ends (its interrupt); ``hold``: the slow pass is held
    off (its tick and the last one's moved on, in the interrupts' window: the pump pulls
    the slow pass into a transaction, while the drive thinks, once 3 ms have passed).

    The port's pass comes in the bridge's idle time (``App.bridge_idle``): ``App.run(2)``
    forwards the request and relays the reply (metered: ``tx``), the port's pass comes
    in the idle pass after them, ``App.run(1)`` (metered: ``port``). Meters, not the
    whole call's time: their own cost is the rig's. ``inside`` counts the transactions
    whose frame was served inside ``App.run(2)`` anyway."""

    def __init__(self, rig, hold, quiet=False):
        """``quiet``: the same probe with no CAN traffic (the port open and idle), its
        baseline."""
        self.rig = rig
        self.hold = hold
        self.quiet = quiet
        self.irq_us = array("i", [0])  # the interrupts' window in the last call (timing included)
        self.tx = Meter()  # the transactions: App.run(2)
        self.port = Meter()  # the idle passes after them, which ran the port's pass
        self.inside = 0

    def forward(self, count):
        rig = self.rig
        app = rig.app
        up = rig.hal.up
        down = rig.hal.down
        can = rig.hal.can
        vcp = rig.hal.slcan
        run = rig.poll
        req = rig.request
        rep = rig.reply
        nq = len(req)
        nr = len(rep)
        due = app.due
        bs = app.bridge.bs
        rs = app.can.rs
        hold = self.hold
        busy = not self.quiet
        w_up = up.c.writes
        w_down = down.c.writes
        irq_us = self.irq_us
        irq_us[0] = 0
        m_tx = self.tx
        m_port = self.port
        m_tx.clear()
        m_port.clear()
        inside = 0
        ticks = ticks_us
        # (the board's loop runs on between probes: the port's tick is current, not one a
        # probe's set-up left behind, which would count as a long wait)
        run(1)
        rig._before()
        for _ in range(count):
            up.load(req, nq, 0, 0)
            down.load(rep, nr, 0, 1)
            t0 = ticks()
            if busy:
                can.bus_tx_done(1)
                can.bus_rx(RX_ID, RX_DATA, 8, 0)
            if hold:  # (in the window: the rig's, taken out with it)
                t = ticks()
                due[0] = (t + 500000) & 0x3FFFFFFF
                bs[14] = t  # (bridge.B_T_SLOW)
            irq_us[0] += ticks_diff(ticks(), t0)
            if busy:
                vcp.again()
            m_tx.begin()
            run(2)
            m_tx.end()
            if busy and rs[1] == rs[0]:  # (RS_TAIL, RS_HEAD) the frame was served inside the transaction
                inside += 1
            m_port.begin()
            run(1)
            m_port.end()
        self.inside = inside
        rig.runs += 2 * count + 1
        rig._done(count, w_up, w_down)


def hold_cost(rig):
    """Instructions of Busy's holding off the slow pass (the rig's, in the interrupts' window)."""
    due = rig.app.due
    bs = rig.app.bridge.bs
    ticks = ticks_us
    n = 200
    t0 = ticks()
    for _ in range(n):
        pass
    t1 = ticks()
    for _ in range(n):
        t = ticks()
        due[0] = (t + 500000) & 0x3FFFFFFF
        bs[14] = t
    t2 = ticks()
    due[0] = ticks()
    return Q.instr(ticks_diff(t2, t1) - ticks_diff(t1, t0)) // n


def settle(rig):
    """The ring and the host's lines served, the slow pass's schedule back to normal."""
    app = rig.app
    rig.hal.slcan.load(TX_LINE, 0)
    for _ in range(4):
        app.can.serve(ticks_us())
    app._slow(ticks_us())


def bridge_figures(result, fail, prices, transactions):
    from jig import params

    costs = Q.hal_call_costs()
    vp = Vcpricer(prices)
    tcost = _timing_cost()
    rows = []
    quiet = {}  # hold: the metered transaction with the port open and idle, at the board's prices
    for name in ("no CAN port in the HAL", "CAN port closed", "CAN port open, idle",
                 "CAN port busy, its slow pass held off", "CAN port busy, everything in"):
        gc.collect()
        if name.startswith("no CAN"):
            rig = Q.BridgeRig(params.CUT_THROUGH)
        else:
            rig = can_rig(params.CUT_THROUGH)
            if "closed" not in name and not open_port(rig, fail):
                return
        if compat.NATIVE is not None and rig.app.pump is None:
            fail("can: the bridge is not on jig.fastpath.pump beside the CAN port")
        share = 0
        fwd_fn = rig.forward
        busy = None
        if "busy" in name:
            can = rig.hal.can
            rx_share, done_share, load_share = rig_call_costs(can)
            share = load_share
            rig.hal.slcan.load(TX_LINE, len(TX_LINE))
            busy = Busy(rig, "held off" in name)
            fwd_fn = busy.forward
        fwd, heap_f, fwd_b = measure(rig, fwd_fn, transactions, costs, prices, vp, share)
        if "idle" in name:  # the busy rows' probe with no CAN traffic: their baseline
            for hold in (True, False):
                q = Busy(rig, hold, quiet=True)
                measure(rig, q.forward, transactions, costs, prices, vp, 0)
                quiet[hold] = q.tx.figure(costs, vp, prices, tcost, rig.setup_cost())[1]
        irq = port = port_b = 0
        if busy is not None:
            # the interrupts apart; the transaction and the port's pass after it as metered
            window = Q.instr(busy.irq_us[0]) / transactions
            irq = int(window - tcost - rx_share - done_share - (hold_cost(rig) if busy.hold else 0))
            setup = rig.setup_cost()
            fwd, fwd_b = busy.tx.figure(costs, vp, prices, tcost, setup)
            win, win_b = busy.port.figure(costs, vp, prices, tcost, setup)
            idle_own, _, idle_on_board = measure(rig, rig.idle, 1000, costs, prices, vp, 0)
            port = win - idle_own
            port_b = win_b - idle_on_board
            if busy.inside and compat.IS_MICROPYTHON:
                fail("can: bridge (%s): the port's pass ran inside %d of %d transactions"
                     % (name, busy.inside, transactions))
        if "busy" in name:
            settle(rig)
        loc, heap_l, loc_b = measure(rig, rig.answer_local, transactions, costs, prices, vp, 0)
        idle, heap_i, idle_b = measure(rig, rig.idle, 1000, costs, prices, vp, 0)
        if rig.stuck:
            fail("can: bridge (%s): a transaction did not complete" % name)
        if min(heap_f, heap_l, heap_i) < 0:
            fail("can: bridge (%s): allocated with the heap locked" % name)
        elif compat.IS_MICROPYTHON and (heap_f or heap_l or heap_i):
            fail("can: bridge (%s): %d/%d/%d heap bytes per call" % (name, heap_f, heap_l, heap_i))
        if "busy" in name and rig.app.can.cv[0] == 0:
            fail("can: bridge (%s): no CAN frame was received" % name)
        rows.append((name, fwd, fwd_b, loc, loc_b, idle, idle_b, irq, port, port_b))
        if "busy" in name:
            settle(rig)
        rig = None
    base = rows[0]
    for name, fwd, fwd_b, loc, loc_b, idle, idle_b, irq, port, port_b in rows:
        what = ""
        if "busy" in name:
            q = quiet.get("held off" in name, 0)
            what = (" (metered; the same probe with the port open and idle: %d, this %s) + the CAN interrupts in it "
                    "(a TX end, a frame received) %d; then, the reply relayed, the port's pass (a host line in, a "
                    "frame out, a TX end counted) %d (board prices %d)" % (q, _pct(fwd_b, q), irq, port, port_b))
        result("can bridge cut-through, %s: forwarded transaction %d (board prices %d, %s)%s, local GetSlaveInfo "
               "%d (%d, %s), idle pass %d (%d, %s) instructions; heap 0" % (
                   name, fwd, fwd_b, _pct(fwd_b, base[2]), what,
                   loc, loc_b, _pct(loc_b, base[4]), idle, idle_b, _pct(idle_b, base[6])))
    if prices is not None:
        worst = max(r[2] for r in rows[1:3])
        worst_pct = max(100.0 * (r[2] - base[2]) / base[2] for r in rows[1:3])
        busy_pct = max(100.0 * (r[2] - quiet.get("held off" in r[0], r[2])) / quiet.get("held off" in r[0], 1)
                       for r in rows[3:])
        result("can goal (issue 24: forwarded transaction <= 25 000 at the board's prices, unchanged within 5 %%): "
               "at most %d (%+.1f %%) beside the CAN port closed or idle; (issue 34: busy within 25 %% of idle) "
               "busy at most %d, %+.1f %% beside the same probe idle (the interrupts apart; the port's pass runs "
               "after the reply, in the bridge's idle time)"
               % (worst, worst_pct, max(r[2] for r in rows[3:]), busy_pct))


def _pct(x, base):
    if base <= 0:
        return "-"
    return "%+.1f %%" % (100.0 * (x - base) / base)


def run(result, fail, prices=None, quick=False):
    """The CAN figures; prices: board_check's (qemu_suite.check_board), None under CPython."""
    if compat.IS_MICROPYTHON and memcan is None:
        fail("can: memcan (tools/firmware/qemu/cmodules/memcan) is not built in")
        return
    port_figures(result, fail, prices, 5 if quick else 200)
    bridge_figures(result, fail, prices, 5 if quick else 200)
