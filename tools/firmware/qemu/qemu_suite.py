"""Checks and figures for the firmware on an emulated Cortex-M7 (MicroPython qemu port).

Frozen into MicroPython's ``qemu`` port (board MPS2_AN500: Cortex-M7 with
double-precision FPU) together with the ``jig`` package by tools/firmware/test_qemu.sh,
which runs ``import qemu_suite; qemu_suite.main()`` in qemu-system-arm with
``-icount shift=0``: one instruction takes exactly 1 ns of virtual time, so a
``ticks_us`` difference times 1 000 is an instruction count.

1. capture replay: every capture of host_tests/captures through the frozen
   parser, compared line by line with the report CPython produced for it;
2. CRC parity: the viper CRC and copy (jig.native, which must load here) against
   the table CRC and a plain loop, on pseudo-random buffers;
3. jig.board / jig.uartport on real MicroPython with stand-in machine/stm
   modules: the port's any/readinto/write/queue/drain and the board's
   housekeeping with the heap locked, and their instruction cost (board_check);
4. figures: instructions per byte for the CRC and the parser, and per forwarded
   transaction (PC request -> driver -> reply relayed) through ``jig.app.App``
   on a HAL whose ports are memory buffers (``memport``, a C module of the qemu
   build: its calls cost a few hundred instructions, always the same, and are
   taken out), plus heap bytes allocated in steady state (expected 0); then the
   same with the HAL calls priced at what board_check measured for the board's;
5. one sample of the jig's own trace (jig.trace): request built and sent, reply
   parsed and stored, heap locked, at the board's prices (``bench_trace``).

Lines starting with ``RESULT`` are the summary the shell script prints; a line
starting with ``FAIL`` makes it exit non-zero. The module also runs under CPython
(``main(quick=True)``) so the host tests keep it working; figures there mean
nothing.
"""

import gc
import sys
from array import array

from jig import compat, crc, frame, mem, parser
from jig.counters import C_DOWN_OUT as K_DOWN_OUT
from jig.counters import C_UP_OUT as K_UP_OUT
from jig.compat import ticks_diff, ticks_us

try:
    import qemu_captures
except ImportError:
    qemu_captures = None

try:
    import capture_format
except ImportError:
    capture_format = None

import bridge_probe  # host_tests' in-memory rig (also used on the WebAssembly VM)

try:
    import memport  # the HAL port in C: in the qemu build only (tools/firmware/qemu/cmodules/memport)
except ImportError:
    memport = None

INSTR_PER_US = 1000  # qemu -icount shift=0: 1 instruction = 1 ns
failures = []


def fail(msg):
    failures.append(msg)
    print("FAIL " + msg)


def result(msg):
    print("RESULT " + msg)


def instr(us):
    return us * INSTR_PER_US


def alloc_bytes():
    try:
        return gc.mem_alloc()
    except AttributeError:
        return 0


# --- 1. capture replay ---------------------------------------------------------------
def minimal_replay():
    """Without the capture files: the protocol notes' examples, fed byte by byte."""
    examples = (
        (b"\xaa\xcc\x01\x01\xc1\xe0\xaa\xee", b"\x01\x01"),
        (b"\xaa\xcc\x02\x50\xaa\xaa\x00\x00\x00\xe0\x2d\xaa\xee", b"\x02\x50\xaa\x00\x00\x00"),
        (b"\xaa\xcc\x04\x26\x82\xaa\xaa\xaa\xee", b"\x04\x26"),
    )
    p = parser.FrameParser()
    ok = 0
    for wire, body in examples:
        got = None
        for i in range(len(wire)):
            p.feed(wire, i, i + 1, 0)
            if p.ready:
                got = bytes(p.body[0 : p.body_len - 2])
        if got == body:
            ok += 1
        else:
            fail("minimal replay: %r gave %r" % (wire, got))
    return ok, len(examples)


def replay_captures():
    if qemu_captures is None or capture_format is None or not qemu_captures.CAPTURES:
        ok, n = minimal_replay()
        result("capture replay: capture files not frozen in; minimal replay %d/%d ok" % (ok, n))
        return
    ok = 0
    for name, text, expected in qemu_captures.CAPTURES:
        try:
            cap = capture_format.parse(text, name)
            lines = capture_format.report(cap, False)
        except Exception as e:  # report it, keep going
            fail("capture %s raised %s: %s" % (name, type(e).__name__, e))
            continue
        got = "\n".join(lines)
        if got == expected:
            ok += 1
        else:
            exp_lines = expected.split("\n")
            for k in range(max(len(lines), len(exp_lines))):
                a = lines[k] if k < len(lines) else "<none>"
                b = exp_lines[k] if k < len(exp_lines) else "<none>"
                if a != b:
                    fail("capture %s line %d: MicroPython %r, CPython %r" % (name, k, a, b))
                    break
    n = len(qemu_captures.CAPTURES)
    result("capture replay: %d/%d captures give CPython's report line for line" % (ok, n))
    if ok != n:
        fail("capture replay: %d of %d captures differ" % (n - ok, n))


# --- 2. viper vs table -------------------------------------------------------------------
class Lcg:
    def __init__(self, seed):
        self.x = seed

    def next(self):
        self.x = (self.x * 1103515245 + 12345) & 0x3FFFFFFF
        return self.x >> 8


def crc_parity(cases=300):
    native = compat.NATIVE
    if compat.IS_MICROPYTHON and native is None:
        fail("jig.native (viper) did not load on this port")
        return
    if crc.crc16(b"123456789") != 0x4B37 or crc.crc16_table(b"123456789") != 0x4B37:
        fail("CRC check value of b'123456789' is not 0x4B37")
    rnd = Lcg(12345)
    bad = 0
    for k in range(cases):
        n = rnd.next() % 300
        buf = bytearray(n)
        for i in range(n):
            buf[i] = rnd.next() & 0xFF
        start = rnd.next() % (n + 1)
        end = start + rnd.next() % (n - start + 1)
        init = rnd.next() & 0xFFFF
        if crc.crc16(buf, start, end, init) != crc.crc16_table(buf, start, end, init):
            bad += 1
        dst = bytearray(n + 8)
        ref = bytearray(n + 8)
        off = rnd.next() % 8
        mem.copy(dst, off, buf, start, end - start)
        for i in range(end - start):
            ref[off + i] = buf[start + i]
        if dst != ref:
            bad += 1
    path = "viper" if native is not None else "table only (no native emitter)"
    result("crc/copy parity (%s vs table/loop): %d cases, %d mismatches" % (path, cases, bad))
    if bad:
        fail("viper CRC/copy differ from the portable versions in %d cases" % bad)


# --- 3. figures ------------------------------------------------------------------------------
def timed(fn, *args):
    gc.collect()
    t0 = ticks_us()
    fn(*args)
    return ticks_diff(ticks_us(), t0)


def bench_crc(size=4096, rounds=4):
    buf = bytearray(size)
    for i in range(size):
        buf[i] = (i * 7) & 0xFF

    def run(f):
        for _ in range(rounds):
            f(buf, 0, size)

    nbytes = size * rounds
    t_table = timed(run, crc.crc16_table)
    t_fast = timed(run, crc.crc16)
    result("crc16 table: %d instructions/byte" % (instr(t_table) // nbytes))
    result("crc16 %s: %d instructions/byte" % ("viper" if compat.NATIVE else "table", instr(t_fast) // nbytes))


def traffic(repeat):
    """A realistic byte stream: status polls, replies, a long frame with stuffing."""
    one = bytearray()
    one += frame.encode(2, frame.GET_AXIS_STATUS)
    one += frame.encode(2, frame.GET_AXIS_STATUS, b"\x00\x00\x00\x00\x08")
    one += frame.encode(3, frame.MOVE_INC_POS, b"\x10\x27\x00\x00\x88\x13\x00\x00")
    one += frame.encode(3, frame.MOVE_INC_POS, b"\x00")
    one += frame.encode(2, frame.GET_ACTUAL_POS, b"\x00\xaa\xaa\x00\x00")
    one += frame.encode(2, frame.GET_SLAVE_INFO, b"\x00\x14" + b"Ezi-STEP Plus-R \xaa" * 14)
    per = 6
    out = bytearray()
    for _ in range(repeat):
        out += one
    return out, per * repeat


def bench_parser(repeat=40, chunk=256):
    """The parser as the bridge drives it: scan() straight on the state array."""
    stream, frames = traffic(repeat)
    n = len(stream)
    buf = bytearray(chunk)
    p = parser.FrameParser()
    st = p.st
    scan = p.scan
    body = p.body
    tables = parser.TABLES

    def run():
        pos = 0
        got = 0
        while pos < n:
            k = n - pos if n - pos < chunk else chunk
            mem.copy(buf, 0, stream, pos, k)
            pos += k
            i = 0
            now = ticks_us()
            while i < k:
                i = scan(st, buf, i, k, body, tables, now)
                if st[parser.S_EVENT] == parser.EV_FRAME:
                    got += 1
        return got

    gc.collect()
    a0 = alloc_bytes()
    t0 = ticks_us()
    got = run()
    dt = ticks_diff(ticks_us(), t0)
    a1 = alloc_bytes()
    if got != frames:
        fail("parser benchmark: %d frames of %d" % (got, frames))
    result("parser (%s engine): %d bytes, %d frames: %d instructions/byte, %d instructions/frame, heap +%d bytes"
           % (p.engine, n, frames, instr(dt) // n, instr(dt) // frames, a1 - a0))


# Calls into the stand-in HAL, counted so their own cost can be taken out of the
# figures: what is left is the firmware's. On the emulated M7 the ports are C
# (tools/firmware/qemu/cmodules/memport, as machine.UART and machine.Pin are on the board); the
# counters are one array('i') the C methods add to. Index order: memport.c's K_*.
H_ANY = 0
H_READ = 1
H_WRITE = 2
H_DE = 3
H_SLEEP = 4
H_LOAD = 5  # the rig putting bytes on the line
H_QUEUE = 6
H_DRAIN = 7
H_QBYTES = 8  # not a call: the bytes the queue calls carried
HAL_CALL_NAMES = ("any", "readinto", "write", "de", "sleep_us", "load", "queue", "drain")
ISR_TXFNF = 1 << 7  # jig.uartport.USART_ISR_TXFNF / _TC
ISR_TC = 1 << 6
ISR_BUSY = 1 << 16  # jig.bridge.ISR_BUSY: a byte being received (the line watch)
TDR = 3
HAL_CALLS = array("i", [0] * (len(HAL_CALL_NAMES) + 1))


class PyPort:
    """memport.Port's interface in Python, for CPython (main(quick=True) in the host tests)."""

    def __init__(self, counts):
        self.counts = counts
        self.rx = bytearray(512)
        self.rx_n = 0
        self.rx_pos = 0
        self.hold = 0
        self.most = 0
        self.writes = 0
        self.tx_bytes = 0

    def load(self, data, n, off=0, hold=0):
        self.counts[H_LOAD] += 1
        self.rx[0:n] = data[off:off + n]
        self.rx_n = n
        self.rx_pos = 0
        self.hold = hold

    def trickle(self, k):
        self.most = k

    def _waiting(self):
        k = self.rx_n - self.rx_pos
        return k if self.most == 0 or k < self.most else self.most

    def any(self):
        self.counts[H_ANY] += 1
        if self.hold:
            self.hold -= 1
            return 0
        return self._waiting()

    def readinto(self, buf, n):
        self.counts[H_READ] += 1
        k = 0 if self.hold else min(self._waiting(), n, len(buf))
        buf[0:k] = self.rx[self.rx_pos:self.rx_pos + k]
        self.rx_pos += k
        return k

    def _sent(self, buf, off, n):
        self.tx_bytes += n
        if buf[off + n - 1] == 0xEE:
            self.writes += 1
        return n

    def write(self, buf, off, n):
        self.counts[H_WRITE] += 1
        self._sent(buf, off, n)

    def queue(self, buf, off, n):
        self.counts[H_QUEUE] += 1
        self.counts[H_QBYTES] += n
        return self._sent(buf, off, n)

    def drain(self):
        self.counts[H_DRAIN] += 1
        return 0

    def de(self, v):
        self.counts[H_DE] += 1

    def sleep_us(self, us):
        self.counts[H_SLEEP] += 1  # DE delays are waiting, not work


def new_port():
    if memport is not None:
        return memport.Port(HAL_CALLS)
    if compat.IS_MICROPYTHON:
        fail("memport (tools/firmware/qemu/cmodules/memport) is not built in: the figures would include Python stand-in ports")
    return PyPort(HAL_CALLS)


class MemPort:
    """A HAL port over memory (``c``: the memport.Port doing the work). Its HAL methods
    are the C object's own bound methods, as jig.uartport binds machine.UART's."""

    def __init__(self, baud):
        c = new_port()
        self.c = c
        self.baud = baud
        self.tx_blocks = True
        self.echo_free = True  # like the jig's transceivers: /RE tied to DE
        self.overflows = 0
        self.any = c.any
        self.readinto = c.readinto
        self.write = c.write
        self.queue = c.queue
        self.drain = c.drain
        self.de = c.de
        self.load = c.load
        # The USART's ISR..TDR in RAM, as board_check runs UartPort.queue on: the transmit
        # FIFO never full (TXFNF) and the line idle (TC). jig.fastpath.pump writes the
        # bytes of a frame it passes on into TDR itself, as on the board; only the last
        # byte written stays there (the rig checks it is a tail's EE).
        self.regs = array("i", [ISR_TXFNF | ISR_TC, 0, 0, 0])
        # The pump's line watch reads ISR.BUSY from the same block (jig.uartport: isr = regs):
        # clear (the line idle) unless a probe sets it.
        self.isr = self.regs

    def hw_de(self, on, pre16, post16):
        return False


class MemHal(bridge_probe.Hal):
    """bridge_probe's in-memory HAL on the real clock, with MemPorts."""

    def __init__(self):
        bridge_probe.Hal.__init__(self)
        self.ticks_us = ticks_us
        self.sleep_us = new_port().sleep_us

    def open(self, up_baud, down_baud):
        self.up = MemPort(up_baud)
        self.down = MemPort(down_baud)


def hal_call_costs():
    """Instructions per call of each stand-in HAL method (HAL_CALL_NAMES order), called
    pre-bound from a loop as the firmware calls them."""
    port = new_port()
    buf = bytearray(8)
    data = b"\xaa" * 8
    n = 400

    any_ = port.any
    readinto = port.readinto
    write = port.write
    queue = port.queue
    drain = port.drain
    de = port.de
    sleep = port.sleep_us
    load = port.load

    def loop():
        t0 = ticks_us()
        for _ in range(n):
            pass
        return ticks_diff(ticks_us(), t0)

    def run(k):
        # One loop per method: the loop is the same for all and is subtracted.
        t0 = ticks_us()
        if k == H_ANY:
            for _ in range(n):
                any_()
        elif k == H_READ:
            for _ in range(n):
                readinto(buf, 8)
        elif k == H_WRITE:
            for _ in range(n):
                write(data, 0, 8)
        elif k == H_DE:
            for _ in range(n):
                de(1)
        elif k == H_SLEEP:
            for _ in range(n):
                sleep(1)
        elif k == H_LOAD:
            for _ in range(n):
                load(data, 8, 0, 0)
        elif k == H_QUEUE:
            for _ in range(n):
                queue(data, 0, 8)
        elif k == H_DRAIN:
            for _ in range(n):
                drain()
        return ticks_diff(ticks_us(), t0)

    port.load(data, 8)
    base = loop()
    return [instr(run(k) - base) // n for k in range(len(HAL_CALL_NAMES))]


def mem_total():
    try:
        import micropython

        return micropython.mem_total()
    except (ImportError, AttributeError):
        return 0


def heap_lock(on):
    try:
        import micropython
    except ImportError:
        return
    if on:
        micropython.heap_lock()
    else:
        micropython.heap_unlock()


CAPTURE_SINK = 8192  # bytes the capture port stand-in holds; fresh() rewinds it


class CapturePort:
    """``hal.capture`` whose methods are C, as USB_VCP's are on the board: io.BytesIO's
    write (into a preallocated buffer, so it never grows) and tell (0: no command
    from the host). Its cost is in the figures, as the board's USB write would be."""

    def __init__(self):
        import io

        self.sink = io.BytesIO(bytearray(CAPTURE_SINK))
        self.sink.seek(0)
        self.write = self.sink.write
        self.readinto = self.sink.readinto
        self.any = io.BytesIO().tell

    def taken(self):
        return self.sink.tell()


class BridgeRig:
    """jig.app.App on MemHal in one forwarding mode, with the probes of the issue's table;
    ``capture``: recording both buses (parameter 13) into a CapturePort."""

    def __init__(self, mode, capture=False):
        from jig import params
        from jig.app import App

        self.request = frame.encode(2, frame.GET_AXIS_STATUS)
        self.reply = frame.encode(2, frame.GET_AXIS_STATUS, b"\x00\x00\x00\x00\x08")
        self.local = frame.encode(1, frame.GET_SLAVE_INFO)
        hal = MemHal()
        hal.capture = CapturePort() if capture else None
        fs = bridge_probe.MemFS()
        hal.fs = fs
        pr = params.Params(fs, hal.param_path)
        pr.load()
        pr.set(params.P_FORWARD_MODE, mode)
        pr.set(params.P_CAPTURE, 1 if capture else 0)
        pr.save()
        self.app = App(hal)
        self.hal = hal
        self.stuck = False
        # The board's loop for a given number of passes: App.run(k). Its locals are set
        # up at every call here but once on the board, so measure() takes that set-up
        # out (run(0)) for each call, counted in runs.
        self.poll = self.app.run  # bound once: making a bound method allocates
        self.runs = 0
        self.out0 = array("i", [0, 0])  # the bridge's frames-out counters before a probe

    def fresh(self):
        """Before a measurement: an empty capture ring and port (they must not fill up
        during it, or records would take the cheaper lost path)."""
        if self.hal.capture is not None:
            self.app.capture.start(ticks_us())
            self.hal.capture.sink.seek(0)

    def _done(self, count, w_up, w_down=None):
        """count frames reached the PC bus (and, given w_down, the driver bus): pieces
        ending in a tail that went through the port's calls, or -- for a frame the pump
        passed on through the register block -- as many frames counted by the bridge
        (replies relayed, frames sent on to the drivers) and a tail's EE last in TDR."""
        v = self.app.counters.v
        up = self.hal.up
        down = self.hal.down
        if up.c.writes - w_up != count and (v[K_UP_OUT] - self.out0[0] != count or up.regs[TDR] != 0xEE):
            self.stuck = True
        if w_down is not None and down.c.writes - w_down != count and (
                v[K_DOWN_OUT] - self.out0[1] != count or down.regs[TDR] != 0xEE):
            self.stuck = True

    def _before(self):
        v = self.app.counters.v
        self.out0[0] = v[K_UP_OUT]
        self.out0[1] = v[K_DOWN_OUT]
        self.hal.up.regs[TDR] = 0
        self.hal.down.regs[TDR] = 0

    def forward(self, count):
        """Request as one burst, forwarded in the first pass; reply as one burst (held
        back one any() call: it comes after its request), relayed in the second."""
        self._transaction(count, 0, 1, 2)

    def forward_bytewise(self, count):
        """The same transaction with every byte arriving on its own: one byte a pass,
        the reply's first byte in the pass after the request's last."""
        nq = len(self.request)
        self._transaction(count, 1, nq, nq + len(self.reply))

    def _transaction(self, count, most, hold, passes):
        """count request/reply pairs, each in one App.run(passes): the ports hand out at
        most ``most`` bytes a pass (0: all), the reply shows after ``hold`` any() calls."""
        up = self.hal.up
        down = self.hal.down
        run = self.poll
        req = self.request
        rep = self.reply
        nq = len(req)
        nr = len(rep)
        w_up = up.c.writes
        w_down = down.c.writes
        self._before()
        up.c.trickle(most)
        down.c.trickle(most)
        try:
            for _ in range(count):
                up.load(req, nq, 0, 0)
                down.load(rep, nr, 0, hold)
                run(passes)
        finally:
            up.c.trickle(0)
            down.c.trickle(0)
        self.runs += count
        self._done(count, w_up, w_down)

    def answer_local(self, count):
        up = self.hal.up
        run = self.poll
        wire = self.local
        n = len(wire)
        w_up = up.c.writes
        self._before()
        for _ in range(count):
            up.load(wire, n, 0, 0)
            run(1)
        self.runs += count
        self._done(count, w_up)  # (cut through, a stub went to the driver bus too)

    def idle(self, count):
        self.poll(count)  # the board's loop, nothing arriving
        self.runs += 1

    def watch(self, count, busy):
        """An idle pass with the PC's line busy (its USART's ISR.BUSY: a start bit) or not;
        the bus it arms is let go again by the rig (early[1] = -1, as the loop would)."""
        isr = self.hal.up.regs
        early = self.app.down.early
        run = self.poll
        flags = ISR_TXFNF | ISR_TC
        on = flags | ISR_BUSY if busy else flags
        for _ in range(count):
            isr[0] = on
            run(1)
            isr[0] = flags
            early[1] = -1
        self.runs += count

    def first_byte(self, count, busy):
        """A frame's AA arriving on its own after an idle pass that saw its start bit (busy)
        or not, then a byte that is no CC: the bus is let go (drop_early)."""
        isr = self.hal.up.regs
        up = self.hal.up
        run = self.poll
        flags = ISR_TXFNF | ISR_TC
        on = flags | ISR_BUSY if busy else flags
        aa = b"\xaa"
        noise = b"\x11"
        early = self.app.down.early
        for _ in range(count):
            isr[0] = on
            run(1)
            isr[0] = flags
            # On the board the byte takes a byte time (>= 10.85 us) to arrive after its start
            # bit: the pre-delay has run by then. Here the rig is quicker: date the arming back.
            t = (ticks_us() - 1000) & 0x3FFFFFFF
            if busy:
                early[1] = t
            else:
                early[1] = -1
            up.load(aa, 1, 0, 0)
            run(1)
            up.load(noise, 1, 0, 0)
            run(1)
        self.runs += 3 * count

    def setup_cost(self):
        """Instructions of App.run's set-up (run(0)): on the board it runs once."""
        run = self.poll
        n = 200
        t0 = ticks_us()
        for _ in range(n):
            run(0)
        return instr(ticks_diff(ticks_us(), t0)) // n


def board_hal(d, costs, prices):
    """What HAL calls d (counts, HAL_CALLS layout) cost on the board: any, readinto,
    write, queue (per call and per byte) and drain at board_check's prices, the DE
    pin's value() as the C stand-in's de; sleeps are waiting, loads the rig's."""
    p_any, p_read, p_write, q1, qk, k, p_drain = prices
    per_byte = (qk - q1) / (k - 1)
    return (d[H_ANY] * p_any + d[H_READ] * p_read + d[H_WRITE] * p_write + d[H_DRAIN] * p_drain
            + d[H_DE] * costs[H_DE] + d[H_QUEUE] * q1 + (d[H_QBYTES] - d[H_QUEUE]) * per_byte)


def measure(fn, count, costs, rig=None, prices=None):
    """(firmware instructions per call of fn(1), heap bytes allocated per call, HAL
    calls per call, firmware + HAL calls at the board's prices per call or -1), with
    the heap locked: any allocation raises MemoryError, which is reported as a
    failure. The stand-in HAL's own instructions (``costs``) are taken out."""
    fn(5)  # warm up: first-use allocations happen here
    setup = rig.setup_cost() if rig is not None else 0
    if rig is not None:
        rig.fresh()
    gc.collect()
    calls0 = HAL_CALLS[:]
    runs0 = rig.runs if rig is not None else 0
    m0 = mem_total()
    heap_lock(True)
    try:
        t0 = ticks_us()
        fn(count)
        dt = ticks_diff(ticks_us(), t0)
    except MemoryError:
        heap_lock(False)
        return -1, -1, 0, -1
    heap_lock(False)
    m1 = mem_total()
    d = [HAL_CALLS[k] - calls0[k] for k in range(len(HAL_CALLS))]
    hal = 0
    calls = 0
    for k in range(len(costs)):
        hal += d[k] * costs[k]
        if k != H_LOAD:
            calls += d[k]
    if rig is not None:
        hal += (rig.runs - runs0) * setup
    own = (instr(dt) - hal) // count
    on_board = -1
    if prices is not None:
        on_board = own + int(board_hal(d, costs, prices)) // count
    return own, (m1 - m0) // count, calls // count, on_board


def bench_bridge(transactions=200, prices=None):
    """The issue's probes through jig.app.App in both forwarding modes. prices: the
    board's HAL call costs from board_check (None: not measured, under CPython)."""
    from jig import params

    costs = hal_call_costs()
    slow_off = 0
    result("stand-in HAL instructions per call (C methods, as on the board; taken out below): "
           + ", ".join(["%s %d" % (HAL_CALL_NAMES[k], costs[k]) for k in range(len(costs))]))
    for mode, name, capture in ((params.CUT_THROUGH, "cut-through", False),
                                (params.STORE_AND_FORWARD, "store-and-forward", False),
                                (params.CUT_THROUGH, "cut-through, capture on", True)):
        rig = None
        gc.collect()  # (the last rig's buffers, capture ring included, before the next one's)
        rig = BridgeRig(mode, capture)
        fast = rig.app.pump is not None
        if compat.NATIVE is not None and fast != (mode == params.CUT_THROUGH):
            fail("bridge %s: the main loop is %s (jig.fastpath.pump is for cut-through on plain ports)"
                 % (name, "jig.fastpath.pump" if fast else "the portable loop"))
        rx = len(rig.request) + len(rig.reply)
        per_t, heap_t, calls_t, board_t = measure(rig.forward, transactions, costs, rig, prices)
        per_b, heap_b, calls_b, board_b = measure(rig.forward_bytewise, transactions // 4, costs, rig, prices)
        local, heap_l, calls_l, board_l = measure(rig.answer_local, transactions, costs, rig, prices)
        idle, heap_i, calls_i, board_i = measure(rig.idle, 1000, costs, rig, prices)
        if rig.stuck:
            fail("bridge %s: a transaction did not complete" % name)
        for what, heap in (("forward", heap_t), ("bytewise forward", heap_b), ("local", heap_l), ("idle", heap_i)):
            if heap < 0:
                fail("bridge %s: %s allocated with the heap locked" % (name, what))
            elif heap > 0 and compat.IS_MICROPYTHON:
                fail("bridge %s: %s allocated %d heap bytes per call" % (name, what, heap))
        result("bridge %s (%s): forwarded transaction (%d+%d bytes, two bursts) %d instructions + %d HAL calls; "
               "every byte on its own %d instructions/byte + %d HAL calls; local GetSlaveInfo %d + %d HAL calls; "
               "idle pass %d + %d HAL calls; heap allocated per transaction %d / per idle pass %d bytes (heap locked)"
               % (name, "jig.fastpath.pump" if fast else "portable loop", len(rig.request), len(rig.reply), per_t, calls_t, per_b // rx, calls_b // rx, local, calls_l,
                  idle, calls_i, heap_t, heap_i))
        if prices is not None:
            result("bridge %s with its HAL calls at the board's prices (board_check): forwarded transaction %d, "
                   "a byte on its own %d/byte, local GetSlaveInfo %d, idle pass %d instructions"
                   % (name, board_t, board_b // rx, board_l, board_i))
        if mode == params.CUT_THROUGH and not capture and fast:
            bench_line_watch(rig, transactions, costs, prices, board_i if prices is not None else idle)
        if capture:
            bench_stream(rig, transactions // 4, slow_off)
        elif mode == params.CUT_THROUGH:
            slow_off = slow_pass_cost(rig, transactions // 4)


def bench_line_watch(rig, n, costs, prices, idle):
    """The line watch (jig.bridge.watch_lines, in the pump's idle pass): what an idle pass
    that sees a start bit and raises DE on the other bus costs beyond one that sees
    none, and what that changes for the frame's first byte (its pass reads a tick to
    see what is left of the pre-delay instead of calling DE; no sleep: the pre-delay
    ran meanwhile). Pairs of probes with the same rig code, so their difference is
    the firmware's (HAL calls at the board's prices)."""
    def cost(fn):
        own, heap, _calls, board = measure(fn, n, costs, rig, prices)
        if heap != 0:
            fail("line watch: allocated %d heap bytes with the heap locked" % heap)
        return board if prices is not None else own

    def watch_on(k):
        rig.watch(k, True)

    def watch_off(k):
        rig.watch(k, False)

    def first_on(k):
        rig.first_byte(k, True)

    def first_off(k):
        rig.first_byte(k, False)

    arm = cost(watch_on) - cost(watch_off)
    first = cost(first_on) - cost(first_off) - arm
    if rig.app.down.early[0] >= 0 or rig.app.down.early[1] >= 0:
        fail("line watch: the driver bus was not let go after the probes")
    result("line watch%s: an idle pass that sees a start bit and raises DE %d instructions (an idle pass %d "
           "+ %d); the frame's first byte then costs %+d instructions (a tick read instead of the DE call, "
           "and no sleep: the pre-delay ran meanwhile; heap 0)"
           % (" at the board's prices" if prices is not None else "", idle + arm, idle, arm, first))


def slow_pass_cost(rig, n):
    """Instructions of the app's slow pass with nothing due (App._slow), heap locked."""
    app = rig.app
    gc.collect()
    heap_lock(True)
    try:
        t0 = ticks_us()
        for _ in range(n):
            app._slow(ticks_us())
        dt = ticks_diff(ticks_us(), t0)
    except MemoryError:
        heap_lock(False)
        fail("slow pass: allocated with the heap locked")
        return 0
    heap_lock(False)
    return instr(dt) // n


def bench_stream(rig, n, slow_off):
    """Capture on: what the whole slow pass costs with nothing to stream, and what
    capture's own share (Capture.slow) costs with nothing to stream and streaming one
    forwarded transaction's records to the capture port (heap locked)."""
    cap = rig.app.capture
    rig.fresh()
    cap.drain_to(bytearray())  # (the hello)
    whole = slow_pass_cost(rig, n)
    empty = 0
    total = 0
    moved = 0
    streams = 0
    records = 0
    gc.collect()
    for _ in range(n):
        rig.fresh()
        cap.cs[1] = cap.cs[2] = 0  # CS_HEAD, CS_TAIL: the hello out of the way
        total0 = cap.cs[12]  # CS_TOTAL
        rig.forward(1)
        if cap.pending() == 0:
            continue  # the loop's own slow pass streamed it already: not this probe
        records += cap.cs[12] - total0
        before = rig.hal.capture.taken()
        heap_lock(True)
        try:
            t0 = ticks_us()
            cap.slow(ticks_us())
            t1 = ticks_us()
            cap.slow(ticks_us())  # nothing left to stream
            t2 = ticks_us()
        except MemoryError:
            heap_lock(False)
            fail("capture: streaming allocated with the heap locked")
            return
        heap_lock(False)
        total += ticks_diff(t1, t0)
        empty += ticks_diff(t2, t1)
        moved += rig.hal.capture.taken() - before
        streams += 1
        if cap.pending():
            fail("capture: one transaction's records did not fit one slow pass")
    if streams == 0 or records != 2 * streams:
        fail("capture: a forwarded transaction should leave two records (request and reply, each passed on)")
        return
    result("capture on: whole slow pass with nothing to stream %d instructions (capture off: %d); its "
           "Capture.slow share: nothing to stream %d, streaming one forwarded transaction's 2 records (%d bytes) "
           "to the capture port %d (io.BytesIO.write standing in for USB_VCP.write); heap allocated 0 (heap locked)"
           % (whole, slow_off, instr(empty) // streams, moved // streams, instr(total) // streams))


def _snap(dst):
    for k in range(len(HAL_CALLS)):
        dst[k] = HAL_CALLS[k]


def _hal_diff(before, after, acc):
    for k in range(len(HAL_CALLS)):
        acc[k] += after[k] - before[k]


def bench_trace(n=100, prices=None):
    """One sample of the jig's own trace (jig.trace, StartTrace 0xF5) on BridgeRig's
    cut-through App: the slot's request built and sent (``Trace.poll``, in the slow
    pass) and the drive's GetAllStatus reply read, parsed and stored (one main-loop
    pass, ``App.run(1)``, no slow pass in it), heap locked;
    the stand-in HAL's own instructions taken out, then the HAL calls at the board's
    prices. Also the slow pass with a trace running and nothing due."""
    from jig import params
    from jig.trace import T_NEXT, T_TAKEN

    import trace_probe

    costs = hal_call_costs()
    gc.collect()
    rig = BridgeRig(params.CUT_THROUGH)
    app = rig.app
    slow_off = slow_pass_cost(rig, 50)
    rig.forward(1)  # drive 2 answers through the jig once: it may be traced
    data = bytearray(6)
    data[0] = 2
    frame.put_u32(data, 1, 1000000)  # (a slot only when the probe makes one due)
    data[5] = 1  # Ver6
    start = frame.encode(1, 0xF5, bytes(data))
    up = rig.hal.up
    down = rig.hal.down
    up.load(start, len(start), 0, 0)
    rig.poll(1)
    tr = app.trace
    ts = tr.ts
    if ts[0] != 1:
        fail("trace: StartTrace did not start the sampler")
        return
    reply = trace_probe.all_status_reply(2)
    nr = len(reply)
    run = rig.poll
    setup = rig.setup_cost()
    ticks = ticks_us
    due = app.due

    down.load(reply, nr, 0, 0)  # the answer to the request StartTrace sent at once
    run(1)
    for _ in range(5):
        ts[T_NEXT] = ticks()
        tr.poll(ticks())
        down.load(reply, nr, 0, 0)
        run(1)
    slow_on = slow_pass_cost(rig, 50)  # a trace running, the next slot not due
    b0 = array("i", [0] * len(HAL_CALLS))
    b1 = array("i", [0] * len(HAL_CALLS))
    acc_a = array("i", [0] * len(HAL_CALLS))
    acc_b = array("i", [0] * len(HAL_CALLS))
    taken0 = ts[T_TAKEN]
    dt_a = 0
    dt_b = 0
    gc.collect()
    m0 = mem_total()
    heap_lock(True)
    try:
        for _ in range(n):
            ts[T_NEXT] = ticks()
            _snap(b0)
            t0 = ticks()
            tr.poll(t0)
            t1 = ticks()
            _snap(b1)
            _hal_diff(b0, b1, acc_a)
            dt_a += ticks_diff(t1, t0)
            down.load(reply, nr, 0, 0)
            due[0] = (ticks() + 500000) & 0x3FFFFFFF  # (no slow pass in this pass: it is priced apart)
            _snap(b0)
            t0 = ticks()
            run(1)
            t1 = ticks()
            _snap(b1)
            _hal_diff(b0, b1, acc_b)
            dt_b += ticks_diff(t1, t0)
    except MemoryError:
        heap_lock(False)
        fail("trace: a sample allocated with the heap locked")
        return
    heap_lock(False)
    heap = (mem_total() - m0) // n
    if ts[T_TAKEN] - taken0 != n:
        fail("trace: %d samples stored of %d" % (ts[T_TAKEN] - taken0, n))
    hal_a = 0
    hal_b = 0
    calls_a = 0
    calls_b = 0
    for k in range(len(costs)):
        hal_a += acc_a[k] * costs[k]
        hal_b += acc_b[k] * costs[k]
        if k != H_LOAD:
            calls_a += acc_a[k]
            calls_b += acc_b[k]
    own_a = (instr(dt_a) - hal_a) // n
    own_b = (instr(dt_b) - hal_b) // n - setup
    if heap and compat.IS_MICROPYTHON:
        fail("trace: %d heap bytes per sample" % heap)
    result("trace sample (jig.trace, GetAllStatus %d+%d bytes): request built and sent (Trace.poll) %d instructions + "
           "%d HAL calls; reply read, parsed and stored (a main-loop pass) %d + %d HAL calls; "
           "heap allocated per sample %d bytes (heap locked); slow pass, nothing due: %d with a trace running, "
           "%d without" % (len(frame.encode(2, frame.GET_ALL_STATUS)), nr, own_a, calls_a // n, own_b, calls_b // n,
                           heap, slow_on, slow_off))
    if prices is not None:
        board_a = own_a + int(board_hal(acc_a, costs, prices)) // n
        board_b = own_b + int(board_hal(acc_b, costs, prices)) // n
        result("trace sample with its HAL calls at the board's prices (board_check): request %d + reply %d = %d "
               "instructions a sample; with the slow pass of its slot %d" % (board_a, board_b, board_a + board_b,
                                                                            board_a + board_b + slow_on))


def trace_set_heap(n=90):
    """The sampler with a set of drives (trace_probe.SetRig: three drives joined, tagged
    ReadTrace): n samples and n // 9 tagged reads with the heap locked; none may allocate."""
    import trace_probe

    rig = trace_probe.SetRig()
    tr = rig.trace
    for _ in range(30):
        rig.sample_once()
    rig.read_once()
    taken0 = tr.ts[6]  # T_TAKEN
    w0 = rig.hal.up.writes
    gc.collect()
    heap_lock(True)
    try:
        for i in range(n):
            rig.sample_once()
            if i % 9 == 8:
                rig.read_once()
    except MemoryError:
        heap_lock(False)
        fail("trace set: a sample or a tagged read allocated with the heap locked")
        return
    heap_lock(False)
    if tr.ts[6] - taken0 != n or rig.hal.up.writes - w0 != n // 9:
        fail("trace set: %d samples stored of %d, %d reads answered of %d" % (
            tr.ts[6] - taken0, n, rig.hal.up.writes - w0, n // 9))
    result("trace set of 3 drives (join, round robin, tagged ReadTrace): %d samples and %d tagged reads with the "
           "heap locked, nothing allocated" % (n, n // 9))


def probe_cross_check(n=200):
    """The same figures through host_tests/bridge_probe.Rig, the harness the other
    benchmarks use: a second opinion on the numbers above."""
    rig = bridge_probe.Rig()
    dt = timed(lambda: [rig.forward_once() for _ in range(n)] and None)
    result("bridge_probe.Rig forward (its Python stand-in ports and ring buffers included): %d instructions/transaction" % (instr(dt) // n))
    if compat.IS_MICROPYTHON:
        used, ok = bridge_probe.forward_alloc(n)
        used_l, ok_l = bridge_probe.local_alloc(n, counters=True)
        result("bridge_probe heap: forward +%d bytes, ReadCounters +%d bytes over %d transactions" % (used, used_l, n))
        if not (ok and ok_l):
            fail("bridge_probe: transactions did not complete")
        if used or used_l:
            fail("bridge_probe: %d/%d heap bytes allocated in steady state (expected 0)" % (used, used_l))


def capture_alloc():
    if not compat.IS_MICROPYTHON:
        return 0
    gc.collect()
    used, ok = bridge_probe.forward_alloc(200, capture=True)
    if not ok:
        fail("bridge_probe with capture on: transactions or records missing")
    if used:
        fail("bridge_probe with capture on: %d heap bytes allocated in steady state (expected 0)" % used)
    return used


def check_board():
    """jig.board and jig.uartport with stand-in hardware modules (MicroPython only: see board_check)."""
    if not compat.IS_MICROPYTHON:
        return None
    try:
        import board_check
    except ImportError:
        result("board_check not frozen in: skipped")
        return None
    return board_check.run(result, fail, instr)


def bench_can(prices):
    """The CAN port's figures (issue 24): tools/firmware/qemu/can_suite.py, when frozen in."""
    try:
        import can_suite
    except ImportError:
        result("can_suite not frozen in: skipped")
        return
    can_suite.run(result, fail, prices)


def main(quick=False):
    del failures[:]
    print("qemu_suite on %s (%s)" % (sys.platform, sys.implementation.name))
    replay_captures()
    crc_parity(40 if quick else 300)
    if quick:
        bench_parser(2)
        bench_bridge(5)
        bench_trace(5)
        trace_set_heap(18)
    else:
        bench_crc()
        bench_parser()
        prices = check_board()
        bench_bridge(prices=prices)
        bench_trace(prices=prices)
        trace_set_heap()
        probe_cross_check()
        result("bridge_probe heap with capture on: forward %+d bytes over 200 transactions (records streamed)"
               % capture_alloc())
        bench_can(prices)
    result("%s" % ("all checks passed" if not failures else "%d FAILED" % len(failures)))
    return len(failures)
