"""jig.fastpath.pump (the board's machine-code hot path) against the portable main loop.

Its source runs here as plain Python through jig.compat's shims. The bridge suites
already run on both loops (conftest.py: ``jig_loop``); here the two loops get the
same random traffic on two identical benches and must put the same bytes on both
buses at the same virtual times, with the same DE edges, the same counters and the
same capture records (jig.capture), byte for byte.
"""

from hypothesis import given, settings
from hypothesis import strategies as st

import ast
import os

from jig import app, bridge, counters, fastpath, frame, native, params, parser
from jig import diag
from motorjig.sim import SimBench

GOOD_TYPES = (frame.GET_SLAVE_INFO, frame.GET_AXIS_STATUS, frame.GET_COMMAND_POS, frame.GET_ALL_STATUS,
              diag.READ_COUNTERS)


def test_constants_mirror_the_modules_they_come_from():
    """viper folds only its own module's constants: each must equal its source's."""
    sources = {
        "RX_CHUNK": app, "EV_FRAME": parser, "EV_HEAD": parser, "EV_START": parser, "S_N": parser,
        "S_STATE": parser, "HEADER": parser, "IDLE": bridge,
        "S_EVENT": parser, "AWAIT_PC": bridge, "AWAIT_INT": bridge, "E_PC_LOCAL": bridge, "E_PC_FORWARD": bridge,
        "E_PC_BROADCAST": bridge, "E_REPLY": bridge, "N_EVENTS": bridge, "F_ABORT": bridge, "SEEN_IDS": bridge,
        "STATUS_FRAME_TYPE_ERROR": frame, "STATUS_DATA_ERROR": frame, "STATUS_FRAME_ERROR": frame,
        "P_SLAVE_ID": params, "P_REPLY_TIMEOUT_MS": params, "P_INTERBYTE_US": params, "P_DE_PRE_US": params,
        "P_DE_POST_US": params, "TA_SUM": counters, "TA_BASE": counters, "EV_DROP": parser, "HUNT": parser,
        "CRC_AT": native, "SLOW_AHEAD_US": bridge, "ISR_BUSY": bridge, "ARM_BYTES": bridge,
    }
    for name in vars(parser):
        if name.startswith(("S_", "A_")):
            sources[name] = parser
    names = [n[1:] for n in vars(fastpath) if n.startswith("_") and n[1:2].isupper()]
    checked = 0
    for name in names:
        if name.startswith(("B_", "C_")):
            src = bridge if name.startswith("B_") else counters
        elif name in sources:
            src = sources[name]
        else:
            continue
        attr = name if hasattr(src, name) else "_" + name
        assert getattr(fastpath, "_" + name) == getattr(src, attr), name
        checked += 1
    assert checked >= 77
    assert bridge.ISR_BUSY == 1 << 16  # RM0433, USART_ISR.BUSY
    assert fastpath._MASK == app.TICKS_MASK and fastpath._HALF == app.TICKS_HALF
    uart = _uartport_constants()  # (jig.uartport imports machine: read from its source)
    assert fastpath._ISR_TXFNF == uart["USART_ISR_TXFNF"] and fastpath._TDR == uart["USART_TDR_WORDS_AFTER_ISR"]
    assert fastpath._TX_FIFO_SPINS == uart["TX_FIFO_SPINS"]
    from jig import canport

    assert fastpath._CAN_POLL_US == canport.CAN_POLL_US
    assert fastpath._CAN_DEFER_US == canport.CAN_DEFER_US
    for name in ("RS_HEAD", "RS_TAIL", "TS_HEAD", "TS_TAIL", "TS_DONE", "TS_REC", "TS_BUSY"):
        assert getattr(fastpath, "_" + name) == getattr(canport, name) == getattr(app, "_" + name), name


def _uartport_constants():
    path = os.path.join(os.path.dirname(parser.__file__), "uartport.py")
    out = {}
    for node in ast.parse(open(path).read()).body:
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call) and getattr(node.value.func, "id", "") == "const":
            out[node.targets[0].id] = eval(compile(ast.Expression(node.value.args[0]), path, "eval"))
    return out
    assert fastpath._STUFF == frame.STUFF and fastpath._BROADCAST_ID == frame.BROADCAST_ID
    assert fastpath._CC == frame.HEADER2


def test_the_board_runs_the_pump_only_where_it_applies():
    assert SimBench(fastpath=True).runner.app.pump is fastpath.pump
    assert SimBench().runner.app.pump is None  # CPython: the portable loop unless asked
    sf = SimBench(fastpath=True, jig_params={params.P_FORWARD_MODE: params.STORE_AND_FORWARD})
    assert sf.runner.app.pump is None  # store-and-forward is the portable loop's
    echo = SimBench(fastpath=True, echo_up=True)
    assert echo.runner.app.pump is None  # a port that hears its own echo is not plain


class FifoRegs:
    """A USART's ISR..TDR as the pump sees them, for a port of the bench: the transmit
    FIFO never full, each byte written to TDR queued on the port, as the USART would
    send it (jig.compat.ptr32 indexes an object that is no buffer as memory)."""

    def __init__(self, port):
        self.port = port
        self.written = 0

    def __getitem__(self, k):
        assert k == 0  # ISR
        return fastpath._ISR_TXFNF

    def __setitem__(self, k, value):
        assert k == fastpath._TDR and 0 <= value <= 0xFF
        self.written += 1
        self.port.queue(bytes([value]), 0, 1)


class Run:
    """One bench, everything it puts on the wire recorded with its time. ``regs``: the
    pump writes the bytes it passes on into the ports' FIFO registers (FifoRegs), as on
    the board, instead of calling their ``queue``."""

    def __init__(self, fast, chunk, faults, regs=False):
        # Recording both buses on (jig.capture): its records are compared too.
        self.b = SimBench(driver_ids=(2, 3), fastpath=fast, stream_chunk=chunk, jig_params={params.P_CAPTURE: 1})
        self.regs = []
        if regs:
            a = self.b.app
            for port in (self.b.hal.up, self.b.hal.down):
                port.regs = FifoRegs(port)
                self.regs.append(port.regs)
            a.pump_ctx = fastpath.context(a)
        for slave, fault in faults:
            setattr(self.b.drivers[slave], fault, True)
        self.down = []
        self.b.down_bus.add_node("spy", lambda data, t: self.down.append((t, bytes(data))), record=False)

    def play(self, steps):
        b = self.b
        for wire, gap_us in steps:
            b.run_for(gap_us)
            end = b.pc.send(wire)
            b.run_for(max(0.0, end - b.clock.now))
        b.run_for(300000)
        hal = b.hal
        return (b.pc.raw, b.pc.frames, self.down, hal.up.node.de_log, hal.down.node.de_log, b.counters,
                bytes(b.app.capture.drain_to(bytearray())))


def _step(kind, slave, ftype, cut, gap):
    wire = frame.encode(slave, ftype, bytes(range(ftype % 7)) if ftype == frame.SET_PARAMETER else b"")
    if kind == "bad_crc":
        wire = wire[:-3] + bytes([wire[-3] ^ 0x01]) + wire[-2:]
    elif kind == "cut":
        wire = wire[: max(1, min(cut, len(wire) - 1))]
    elif kind == "garbage":
        wire = bytes([(ftype * 37 + i * 11) & 0xFF for i in range(cut)])
    return wire, gap


steps_strategy = st.lists(
    st.builds(_step, st.sampled_from(["good", "good", "good", "bad_crc", "cut", "garbage"]),
              st.sampled_from([1, 2, 3, 5, 99]), st.sampled_from(GOOD_TYPES + (frame.SET_PARAMETER,)),
              st.integers(1, 12), st.sampled_from([0, 50, 400, 3000, 20000])),
    min_size=1, max_size=8)


@settings(max_examples=60, deadline=None)
@given(steps_strategy, st.sampled_from([1, 3, 64]),
       st.lists(st.tuples(st.sampled_from([2, 3]), st.sampled_from(["bad_crc", "silent"])), max_size=1))
def test_the_pump_does_on_the_wire_what_the_portable_loop_does(steps, chunk, faults):
    portable = Run(False, chunk, faults).play(steps)
    pumped = Run(True, chunk, faults).play(steps)
    names = ("PC bytes", "PC frames", "driver bus", "PC-side DE", "driver-side DE", "counters", "capture records")
    for name, a, b in zip(names, portable, pumped):
        assert a == b, name


def test_a_local_frame_after_a_long_burst_scans_only_what_was_read():
    """A local reply's length is no read count: the bytes after a local frame in the
    receive buffer are stale (a regression the differential test above also guards)."""
    steps = [(frame.encode(2, frame.SET_PARAMETER, bytes(40)), 0), (frame.encode(1, frame.GET_SLAVE_INFO), 5000),
             (frame.encode(1, frame.GET_SLAVE_INFO), 5000)]
    portable = Run(False, 64, ()).play(steps)
    pumped = Run(True, 64, ()).play(steps)
    assert pumped == portable
    c = pumped[5]  # the counters
    assert c["up_noise"] == 0 and c["local_requests"] == 2 and c["up_frames_out"] == 3  # (2 local + the drive's answer)


def _per_byte(segments, bt):
    """(end of each byte's stop bit, byte) from (end of a piece, its bytes)."""
    return sorted((round(t - (len(data) - 1 - i) * bt, 3), data[i]) for t, data in segments for i in range(len(data)))


# Gaps long enough for every answer: the bench's bus corrupts whole pieces that collide,
# so a collision would tell pieces of one byte from longer ones.
quiet_steps = st.lists(
    st.builds(_step, st.sampled_from(["good", "good", "bad_crc", "cut", "garbage"]), st.sampled_from([1, 2, 3, 5, 99]),
              st.sampled_from(GOOD_TYPES + (frame.SET_PARAMETER,)), st.integers(1, 12), st.just(20000)),
    min_size=1, max_size=6)


@settings(max_examples=30, deadline=None)
@given(quiet_steps, st.sampled_from([1, 3, 64]))
def test_the_fifo_filled_through_its_registers_sends_what_the_queue_calls_send(steps, chunk):
    """On the board the pump writes the bytes it passes on into TDR itself; the pieces
    then reach the line byte by byte instead of as one queued piece: the same bytes at
    the same times."""
    called = Run(True, chunk, ())
    a = called.play(steps)
    written = Run(True, chunk, (), regs=True)
    b = written.play(steps)
    if any(w[:2] == b"\xaa\xcc" and len(w) > 3 for w, _gap in steps):  # a frame's id at least went on
        assert sum(r.written for r in written.regs) > 0
    bt = written.b.down_bus.bt
    # (The capture records are left out: their ticks are whole µs of times that sum the
    # bytes' wire times in another order, and may differ in the last µs.)
    for name, x, y in zip(("PC bytes", "PC frames", "driver bus", "PC-side DE", "driver-side DE", "counters"), a, b):
        if name == "driver bus":
            x, y = _per_byte(x, bt), _per_byte(y, bt)
        assert _same(x, y), name  # (a time summed over other pieces: equal but for the float's last bits)


def _same(x, y):
    """x == y, floats within 1 ns (rounding both to the ns can split a pair that sits on
    a rounding boundary, as times of 1/16 µs do)."""
    if isinstance(x, float) or isinstance(y, float):
        return isinstance(x, (int, float)) and isinstance(y, (int, float)) and abs(x - y) < 1e-3
    if isinstance(x, (list, tuple)) and isinstance(y, (list, tuple)):
        return len(x) == len(y) and all(_same(a, b) for a, b in zip(x, y))
    return x == y
