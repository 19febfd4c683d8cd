"""The virtual bench: PC, jig and drivers on two simulated RS-485 buses.

``SimBench`` wires it up on a virtual clock (tests drive it step by step);
``Bench`` runs the same thing in real time on a background thread and exposes
the PC side as a pseudo-terminal and a TCP port, for any pyserial program::

    from motorjig.sim import Bench
    with Bench(driver_ids=(2, 3), baud=115200) as bench:
        serial.serial_for_url(bench.tcp_url)      # or bench.pty_path

Each simulated driver speaks Ver6 or Ver8 on its own (``ver8_drivers``), and the
jig's protocol setting is chosen apart from them (``jig_ver8``), so mixed buses
can be built; ``ver8`` alone keeps the old meaning (everything Ver8).

The jig is the real firmware (``jig.app.App``) on ``SimHAL``; its main loop is
polled whenever bytes reach one of its ports and whenever ``App.wait_us`` says a
deadline is due.

``wiring`` (a ``motorjig.wiring.Wiring`` or a TOML file with a ``[wiring]`` table)
connects the jig's relays to one drive's inputs and that drive's outputs to the
jig's inputs, evaluated whenever either side reads them: a Plus-R drive's (its
``slave``) or a CAN node's (its ``node``: the relays drive 0x60FD's bits, 0x60FE:1's
bits reach the jig's inputs); ``faults`` and ``set_fault`` make drives fail
(``SimDriver.set_fault``, ``can:NAME``: the CAN node's).

The jig's capture port (``jig.capture``: its recording of both buses) is
``SimHAL.capture``; ``SimBench.capture_start`` / ``capture_read`` / ``capture_stop``
are the host's side of it. ``Bench`` serves it on a TCP port of its own
(``capture_url``) and a pseudo-terminal (``capture_pty_path``): one reader at a
time; while none is attached the port is closed (it takes nothing, and the jig's
ring fills and counts what it loses, as on the board with the port not opened).

In real time the bench runs on ``PacedClock``: simulated time follows the wall
clock but never jumps over a pending event, so a stall of the host (a garbage
collection, a busy machine) delays the whole simulated world alike instead of
letting the jig's reply timeout expire before a simulated drive had its turn.

``can_nodes`` adds a CAN bus (``canbus.CanBus``) with simulated CANopen nodes; the
jig's HAL then has its CAN port (``hal.can_open``, ``hal.slcan``) and the host's side
of the SLCAN port is ``SimBench.slcan_send`` / ``slcan_read``; ``Bench`` serves it on
``slcan_url`` and ``slcan_pty_path`` like the capture port (``HostPort``).
``direct``/``direct_can`` put a plain SLCAN adapter on the bus instead of the jig.
"""

import os
import queue
import select
import socket
import termios
import threading

from jig import frame as F
from jig import params as P
from jig.app import App
from jig.parser import FrameParser

from ..wiring import Wiring, load_wiring
from .canbus import CanBus
from .canhal import SLCAN_RATES, DirectSlcanAdapter
from .clock import TICKS_MASK, PacedClock, VirtualClock
from .cpumodel import CpuModel
from .driver import SimDriver
from . import kinds as sim_kinds
from .hal import SimFS, SimHAL
from .link import Bus

# Start the virtual clock 3 s before the 2**30 µs tick wrap, so every test also
# crosses the wrap that MicroPython's ticks_us has every ~18 minutes.
VIRTUAL_START_US = float((1 << 30) - 3000000)
# The real-time bench (Bench: python -m motorjig.sim, jigctl gui --bench) starts there
# too, so a wrap bug shows within seconds of starting it, not after 17.9 min (or, with
# a clock from 0, after 35.8 min at 2**31 µs). This environment variable sets another
# start (µs), to check a moment of a long run without waiting for it.
REALTIME_START_ENV = "MOTORJIG_SIM_START_US"


def realtime_start_us():
    """Where the real-time bench's clock starts: ``$MOTORJIG_SIM_START_US`` if set,
    else VIRTUAL_START_US. ValueError for a value that is not a time ≥ 0."""
    text = os.environ.get(REALTIME_START_ENV, "").strip()
    if not text:
        return VIRTUAL_START_US
    try:
        value = float(int(text, 0))
    except ValueError:
        raise ValueError("%s=%r: expected whole µs, e.g. %d" % (REALTIME_START_ENV, text, (1 << 31) - 2000000)) from None
    if value < 0:
        raise ValueError("%s=%r: the clock starts at 0 µs or later" % (REALTIME_START_ENV, text))
    return value


# The jig's main loop on the bench: None as on a board without a native emitter (the
# portable loop, on CPython), True for jig.fastpath's source run as Python (the host
# tests run the bridge suites both ways: conftest.py).
DEFAULT_FASTPATH = None

PTY_READER = "pty"  # Bench: the capture reader is the pty


class PcPort:
    """The PC's RS-485 adapter (automatic direction) on the upstream bus."""

    def __init__(self, bench, bus, ver8=False):
        self.bench = bench
        self.node = bus.add_node("pc", self._rx, auto_de=True, record=False)
        # Only finds good frames (wire bytes are kept, never fields): any layout.
        # byte_us: see SimDriver.
        self.parser = FrameParser(ver8, byte_us=max(1, int(bus.bt)))
        self.parser.max_body = F.MAX_BODY
        self.raw = bytearray()  # every byte received, in order
        self.frames = []  # (time µs, wire bytes of a good frame)
        self.listeners = []  # fn(data) called with raw bytes (pty/TCP)
        self.keep = True  # False: only pass bytes to the listeners (long interactive runs)

    def send(self, data, t0=None):
        """Transmit data at t0 (default: now); returns the end of its last stop bit."""
        return self.node.bus.transmit(self.node, data, t0)

    def _rx(self, data, t):
        for fn in self.listeners:
            fn(data)
        if not self.keep:
            return
        self.raw += data
        p = self.parser
        i = 0
        n = len(data)
        now = int(t) & TICKS_MASK  # ticks, as the jig's parser gets them: its state is 32-bit
        while i < n:
            j = p.feed(data, i, n, now)
            if p.ready:
                # wire bytes of the frame = re-stuffed body (stuffing is canonical)
                out = bytearray(F.MAX_WIRE)
                m = F.stuff_into(out, p.body, p.body_len)
                self.frames.append((t, bytes(out[:m])))
            i = j

    def clear(self):
        self.raw = bytearray()
        self.frames = []


class JigRunner:
    """Runs App.poll on the bench clock: on input, and at the app's deadlines."""

    def __init__(self, clock, hal, fastpath=None):
        self.clock = clock
        self.hal = hal
        hal.rx_callback = self.wake
        self.app = App(hal, fastpath)
        self.in_poll = False
        self.t_next = None
        self.polls = 0
        self.t_last_run = None
        self.same_instant = 0
        self.missed = False  # a wake came while a poll ran (a start bit seen during a slow pass)
        self._reschedule()

    def wake(self):
        self._schedule(self.clock.now)

    def _schedule(self, t):
        if self.t_next is not None and self.t_next <= t:
            return
        self.t_next = t
        self.clock.at(t, self._run, t)

    def _run(self, t):
        if t != self.t_next:
            return  # superseded by an earlier poll
        self.t_next = None
        if self.in_poll:
            self.missed = True  # the running poll reschedules when it returns, at once
            return
        self.in_poll = True
        try:
            self.hal.begin_pass()
            self.app.poll()
            self.polls += 1
        finally:
            self.in_poll = False
        self._reschedule()

    def _reschedule(self):
        w = self.app.wait_us()
        if self.missed:
            # The board's loop runs on after a long pass and would see what woke us then
            # (a start bit: the line watch): an idle pass now.
            self.missed = False
            w = 0
        if w < 0:
            return
        # Bytes that came in while the poll was blocked in a write are handled at once
        # (as the board's loop would); a 1 µs step only guards against a poll that
        # makes no progress at the same instant again and again.
        if w == 0 and self.clock.now == self.t_last_run:
            self.same_instant += 1
            if self.same_instant > 100:
                w = 1
        else:
            self.same_instant = 0
        self.t_last_run = self.clock.now
        self._schedule(self.clock.now + w)


class SimBench:
    """PC + jig + drivers on a virtual clock (``realtime=True``: on the wall clock).

    ``direct=True``: no jig; the PC's adapter is on the driver bus with the same
    drivers (to measure what the jig costs). ``stream_chunk``: bytes per delivery
    to the jig's ports while a frame arrives (see ``link``). ``cpu_model``: the jig's
    CPU time on the virtual timeline (a ``CpuModel`` or a tuple of its figures, see
    ``cpumodel``); default none (an infinitely fast CPU). ``wiring``: the jig's I/O
    wired to a drive (a ``Wiring`` or a TOML file; its slave, else the first driver).
    ``faults``: (slave or None, name, value) each, as ``set_fault``.
    ``line_watch=False``: the jig's ports show no USART ISR (``hal.SimIsr``), so it
    takes a bus at a frame's first byte, not at its start bit (the bench's "before").
    """

    def __init__(self, driver_ids=(2, 3), baud=None, down_baud=None, ver8=False, realtime=False,
                 jig_params=None, fs=None, turnaround_us=300.0, rxsize=4096, echo_up=False,
                 echo_down=False, record=True, servo_on=False, start_us=None, jig_ver8=None,
                 ver8_drivers=None, direct=False, stream_chunk=1, cpu_model=None, fastpath=None,
                 wiring=None, faults=(), can_nodes=(), can_bitrate=500000, can_node_factory=None, can=None,
                 direct_can=False, line_watch=True):
        """``ver8``: the default variant of the jig and every driver. ``jig_ver8``
        (None: ``ver8``) sets the jig's protocol parameter; ``ver8_drivers`` (None:
        every driver follows ``ver8``) lists the ids of the Ver8 drivers, all others
        are Ver6.

        The CAN side (``can_nodes``: CANopen node ids; ``can`` True: a CAN bus even
        without nodes): ``can_bus`` at ``can_bitrate``, ``can_nodes`` {id: node} made by
        ``can_node_factory(clock, bus, node_id)`` (default: ``sim.kinds``' CAN node), the
        jig's HAL with ``can_open`` and its SLCAN port ``slcan``. ``direct`` or
        ``direct_can``: the host's SLCAN port is a ``DirectSlcanAdapter`` on the bus
        instead of the jig's (``can_adapter``; the jig, if any, then has no CAN)."""
        if realtime:
            self.clock = PacedClock(realtime_start_us() if start_us is None else start_us)
        else:
            self.clock = VirtualClock(VIRTUAL_START_US if start_us is None else start_us)
        self.t_started = self.clock.now  # (a bus's load over the bench's life: its busy_us over now - this)
        fresh = fs is None
        settings = dict(jig_params or {})
        if baud is not None:
            settings.setdefault(P.P_UP_BAUD, baud)
        if down_baud is not None or baud is not None:
            settings.setdefault(P.P_DOWN_BAUD, down_baud or baud)
        if jig_ver8 is None:
            jig_ver8 = ver8
        if jig_ver8:
            settings.setdefault(P.P_PROTOCOL, 1)
        if ver8_drivers is None:
            ver8_drivers = tuple(driver_ids) if ver8 else ()
        ver8_drivers = frozenset(ver8_drivers)
        unknown = ver8_drivers - set(driver_ids)
        if unknown:
            raise ValueError("ver8_drivers %s are not among the driver ids" % sorted(unknown))
        baud = baud or 115200
        down_baud = down_baud or baud
        self.direct = direct
        self.down_bus = Bus(self.clock, down_baud, "down", stream_chunk)
        # direct: the PC's adapter sits on the driver bus itself, no jig in the line.
        self.up_bus = self.down_bus if direct else Bus(self.clock, baud, "up", stream_chunk)
        self.ver8 = ver8
        self.jig_ver8 = bool(jig_ver8)
        self.pc = PcPort(self, self.up_bus, ver8)
        self.drivers = {}
        for i in driver_ids:
            self.drivers[i] = SimDriver(self.clock, self.down_bus, i, turnaround_us, i in ver8_drivers,
                                        servo_on=servo_on)
        self._sync = 0
        self.wiring = None  # the first wiring (the bench's only one unless a multi-up fixture)
        self.wired_slave = None
        self._input_sources = []
        self.wirings = []  # every fixture position's wiring
        self.wired_node = None
        self._make_can(can_nodes, can_bitrate, can_node_factory, bool(can) or direct_can, direct or direct_can)
        if direct:
            if jig_params or not CpuModel.of(cpu_model).off or wiring is not None:
                raise ValueError("direct=True has no jig: jig_params, cpu_model and wiring do not apply")
            self.fs = fs
            self.hal = self.runner = self.app = None
            for slave, name, value in faults:
                self.set_fault(name, value, slave)
            return
        self.fs = fs if fs is not None else SimFS()
        self.hal = SimHAL(self.clock, self.up_bus, self.down_bus, self.fs, rxsize=rxsize,
                          echo_up=echo_up, echo_down=echo_down, record=record, cpu_model=cpu_model,
                          can_bus=None if self.can_adapter is not None else self.can_bus, line_watch=line_watch)
        if settings or fresh:
            self.write_params(settings)
        self.runner = JigRunner(self.clock, self.hal, DEFAULT_FASTPATH if fastpath is None else fastpath)
        self.app = self.runner.app
        self._sync = 0
        if wiring is not None:
            self._connect(wiring)
        for slave, name, value in faults:
            self.set_fault(name, value, slave)

    def _make_can(self, node_ids, bitrate, factory, want, direct):
        self.can_bus = None
        self.can_nodes = {}
        self.can_adapter = None
        self._slcan_got = bytearray()
        node_ids = tuple(node_ids)
        if not (node_ids or want):
            return
        if bitrate not in SLCAN_RATES:
            raise ValueError("can_bitrate %r is not an SLCAN bitrate (%s)" % (bitrate, " ".join(map(str, SLCAN_RATES))))
        for i in node_ids:
            if not 1 <= i <= 127:
                raise ValueError("CAN node id %r out of range 1..127" % (i,))
        if len(set(node_ids)) != len(node_ids):
            raise ValueError("a CAN node id is given twice: %s" % ",".join(map(str, node_ids)))
        self.can_bus = CanBus(self.clock, bitrate)
        if factory is None:
            factory = sim_kinds.can_node
        for i in node_ids:
            self.can_nodes[i] = factory(self.clock, self.can_bus, i)
        if direct:
            self.can_adapter = DirectSlcanAdapter(self.clock, self.can_bus)

    def _connect(self, wiring):
        """Wire the jig's relays to the drive's inputs and its outputs to the jig's inputs; a list
        of wirings wires each slot of a multi-up fixture to its own drive (their relays and inputs
        apart: ``station.slots`` refuses slots that share one)."""
        if isinstance(wiring, (list, tuple)):
            for w in wiring:
                self._connect(w)
            return
        if not isinstance(wiring, Wiring):
            wiring = load_wiring(wiring)
        self.wirings.append(wiring)
        if wiring.node is not None:
            self._connect_node(wiring)
            return
        slave = wiring.slave if wiring.slave is not None else next(iter(self.drivers))
        if slave not in self.drivers:
            raise ValueError("%s: wiring.slave %d is not a driver on this bench (drivers: %s)"
                             % (wiring.source, slave, ", ".join(str(i) for i in self.drivers)))
        drive = self.drivers[slave]
        hal = self.hal
        drive.connect_inputs(lambda: wiring.drive_inputs(hal.outputs), wiring.drive_input_mask)
        self._add_input_source(lambda: wiring.jig_inputs(drive.out_bits()))
        hal.output_hooks.append(drive.update)  # the drive's past ran with the relays as they were
        if self.wiring is None:
            self.wiring = wiring
            self.wired_slave = slave

    def _add_input_source(self, source):
        """The jig's inputs: what every wired drive's outputs set on them."""
        self._input_sources.append(source)
        sources = self._input_sources
        if len(sources) == 1:
            self.hal.input_source = source
        else:
            self.hal.input_source = lambda: _or_all(sources)

    def _connect_node(self, wiring):
        """The same wiring to CAN node ``wiring.node``: relays -> its digital inputs 0x60FD,
        its digital outputs 0x60FE:1 -> the jig's inputs."""
        node = self.can_nodes.get(wiring.node)
        if node is None or not hasattr(node, "connect_inputs"):
            raise ValueError("%s: wiring.node %d is not a CiA 402 node on this bench (CAN nodes: %s)"
                             % (wiring.source, wiring.node, ", ".join(str(i) for i in self.can_nodes) or "none"))
        hal = self.hal
        node.connect_inputs(lambda: wiring.drive_inputs(hal.outputs), wiring.drive_input_mask)
        self._add_input_source(lambda: wiring.jig_inputs(node.out_bits()))

        def relays_change():
            node.update()  # the node's past ran with the relays as they were
            self.clock.after(0.0, node.inputs_changed)  # once they have changed: limits, TPDOs

        hal.output_hooks.append(relays_change)
        if self.wiring is None:
            self.wiring = wiring
            self.wired_node = wiring.node

    def write_params(self, settings):
        """Store a parameter file (as SaveAllParameters would) for the next boot."""
        pr = P.Params(self.fs, self.hal.param_path)
        pr.load()
        for num, value in settings.items():
            if not pr.set(num, value):
                raise ValueError("jig parameter %d: %r not allowed" % (num, value))
        pr.save()

    @property
    def jig_id(self):
        return self.app.params.ram[P.P_SLAVE_ID]

    @property
    def counters(self):
        vals = self.app.counter_values([0] * len(DIAG_NAMES))
        return dict(zip(DIAG_NAMES, vals))

    # --- faults --------------------------------------------------------------------
    def clear_faults(self):
        """Switch off every injected fault: the drives' switches, corruption to the PC,
        the CAN nodes' faults."""
        for d in self.drivers.values():
            d.clear_faults()
        for nd in self.can_nodes.values():
            if hasattr(nd, "clear_faults"):
                nd.clear_faults()
        if self.hal is not None:
            self.hal.up.node.corrupt(0)

    def set_fault(self, name, value=None, slave=None):
        """``SimDriver.set_fault`` on driver ``slave``; None: the wired drive, else every driver.
        A name ``can:NAME`` goes to the CAN node ``slave`` (None: the wired node, else every
        CAN node) as the node's ``set_fault(NAME, value)``."""
        if name.startswith(CAN_FAULT_PREFIX):
            name = name[len(CAN_FAULT_PREFIX):]
            if slave is not None:
                if slave not in self.can_nodes:
                    raise ValueError("no CAN node %d on this bench (CAN nodes: %s)"
                                     % (slave, ", ".join(str(i) for i in self.can_nodes) or "none"))
                targets = [self.can_nodes[slave]]
            elif self.wired_node is not None:
                targets = [self.can_nodes[self.wired_node]]
            else:
                targets = list(self.can_nodes.values())
                if not targets:
                    raise ValueError("no CAN nodes on this bench for the fault can:%s" % name)
            for nd in targets:
                nd.set_fault(name, value)
            return
        if slave is not None:
            if slave not in self.drivers:
                raise ValueError("no driver %d on this bench (drivers: %s)"
                                 % (slave, ", ".join(str(i) for i in self.drivers)))
            targets = [self.drivers[slave]]
        elif self.wired_slave is not None:
            targets = [self.drivers[self.wired_slave]]
        else:
            targets = list(self.drivers.values())
        for d in targets:
            d.set_fault(name, value)

    def corrupt_to_pc(self, frames=1):
        """Flip a bit in each of the next ``frames`` transmissions of the jig to the PC
        (the PC sees a CRC error; see ``link.flip_for_crc``)."""
        self.hal.up.node.corrupt(frames)

    # --- the capture port (jig.capture) ---------------------------------------------
    @property
    def capture(self):
        """The jig's capture port (``hal.SimCapturePort``); the host's side is ``host_*``."""
        return self.hal.capture

    def capture_start(self, timeout_us=50000.0):
        """Open the capture port as a host would, send ``X`` and ``S`` (the jig starts
        only from off: so a recording already on starts afresh too) and run until the
        jig records (its slow pass reads one command a pass: within 20 ms). True if it
        does; the stream then starts with a hello."""
        port = self.hal.capture
        port.host_open()
        port.host_send(b"XS")
        return self.clock.run_while(lambda: port.rx or not self.app.capture.on, timeout_us)

    def capture_read(self, drain=True, limit_us=200000.0):
        """The capture stream's bytes the host has received since the last read. With
        ``drain`` the bench first runs until everything recorded so far has reached the
        host (the jig's ring and the port's buffer empty; at most ``limit_us``)."""
        port = self.hal.capture
        if drain and port.is_open:
            cap = self.app.capture
            self.clock.run_while(lambda: cap.pending() or port.busy, limit_us)
        return port.host_read()

    def capture_stop(self, drain=True, close=False, timeout_us=50000.0):
        """Send ``X`` (after draining, see ``capture_read``) and run until the jig has
        stopped recording; returns what the host received before the stop. ``close``:
        the host closes the port afterwards."""
        port = self.hal.capture
        data = self.capture_read(drain)
        port.host_send(b"X")
        self.clock.run_while(lambda: port.rx or self.app.capture.on, timeout_us)
        data += port.host_read()
        if close:
            port.host_close()
        return data

    # --- the SLCAN port (the jig's third USB CDC port, or the direct adapter's) -------------
    @property
    def slcan(self):
        """The host's SLCAN port (``canhal.SimSlcanPort``): the jig's, or the direct
        adapter's on a direct bench; None without a CAN bus."""
        if self.can_adapter is not None:
            return self.can_adapter.port
        return None if self.hal is None else self.hal.slcan

    def slcan_send(self, data):
        """The host sends SLCAN bytes (the port is opened first if it is not)."""
        port = self.slcan
        if port is None:
            raise ValueError("this bench has no CAN bus (SimBench(can_nodes=...) or can=True)")
        if not port.is_open:
            port.host_open()
        port.host_send(data)

    def slcan_read(self, replies=0, limit_us=100000.0):
        """What the host has received on the SLCAN port since the last read. Runs the
        clock until at least ``replies`` answers (each ending in CR or BEL) have come in
        and nothing the jig already has is still on its way (at most ``limit_us``)."""
        port = self.slcan
        got = self._slcan_got

        def waiting():
            got.extend(port.host_read())
            return got.count(13) + got.count(7) < replies or port.rx or port.busy

        self.clock.run_while(waiting, limit_us)
        got.extend(port.host_read())
        data = bytes(got)
        del got[:]
        return data

    def slcan_close(self):
        if self.slcan is not None:
            self.slcan.host_close()

    # --- running -----------------------------------------------------------------
    def run_for(self, us):
        self.clock.run_until(self.clock.now + us)

    def variant_ver8(self, slave):
        """True if slave speaks Ver8 on this bench: the jig's protocol for the jig's
        id, the driver's own variant, else the bench default ``ver8``."""
        if self.app is not None and slave == self.jig_id:  # (a direct bench has no jig)
            return self.jig_ver8
        d = self.drivers.get(slave)
        return self.ver8 if d is None else d.ver8

    @property
    def variants(self):
        """{id: 6 or 8} for the jig and every driver."""
        out = {self.jig_id: 8 if self.jig_ver8 else 6}
        for i, d in sorted(self.drivers.items()):
            out[i] = 8 if d.ver8 else 6
        return out

    def encode(self, slave, ftype, data=b"", ver8=None):
        """Wire bytes of a request in slave's variant (``ver8`` overrides); Ver8 takes
        the next number of one bench-wide sync counter."""
        if ver8 is None:
            ver8 = self.variant_ver8(slave)
        sync = -1
        if ver8:
            sync = self._sync
            self._sync = (self._sync + 1) & 0xFF
        return F.encode(slave, ftype, bytes(data), sync)

    def send(self, wire):
        """PC transmits raw bytes now; returns the time the last stop bit ends."""
        return self.pc.send(wire)

    def transact(self, wire, timeout_us=100000.0):
        """Send wire bytes from the PC; return the first frame the PC gets (or None)."""
        n0 = len(self.pc.frames)
        end = self.pc.send(wire)
        deadline_from = end
        self.clock.run_while(lambda: len(self.pc.frames) == n0, (deadline_from - self.clock.now) + timeout_us)
        if len(self.pc.frames) > n0:
            return self.pc.frames[n0][1]
        return None

    def request(self, slave, ftype, data=b"", timeout_us=100000.0):
        """Encode, send, wait: returns (reply wire bytes, reply data incl. status) or (None, None)."""
        ver8 = self.variant_ver8(slave)
        wire = self.transact(self.encode(slave, ftype, data, ver8), timeout_us)
        if wire is None:
            return None, None
        p = FrameParser(ver8)
        p.feed(wire)
        if not p.ready:
            return wire, None
        return wire, bytes(p.body[p.data_start : p.data_end])


CAN_FAULT_PREFIX = "can:"  # SimBench.set_fault / --fault: a fault of a CAN node


def _diag_names():
    from jig.diag import WIRE_NAMES

    return WIRE_NAMES


DIAG_NAMES = _diag_names()


class HostPort:
    """One of the jig's USB CDC ports (``SimCapturePort``-like: the capture port, the
    SLCAN port) served to one host at a time on a TCP port and a pseudo-terminal.

    A TCP client that connects while another host is attached is closed at once;
    the pty counts as attached while a program holds it open and no TCP client is. A
    host that goes away closes the port (``host_close``). ``pump`` runs in the
    simulation thread; ``accept_loop`` in a thread of its own.
    """

    def __init__(self, name, port, tcp_port=0, pty=True):
        self.name = name
        self.port = port
        self.tcp_port = tcp_port
        self.want_pty = pty
        self.url = None
        self.pty_path = None
        self.pty = None  # the pty's master fd
        self._server = None
        self._poll = None
        self._new = queue.Queue()  # accepted connections, for the simulation thread
        self.reader = None  # the attached host: a socket, PTY_READER or None

    def open(self):
        self.port.sink = self.sink
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind(("127.0.0.1", self.tcp_port))
        self._server.listen(2)
        self._server.settimeout(0.2)
        self.url = "socket://127.0.0.1:%d" % self._server.getsockname()[1]
        if self.want_pty:
            import tty

            master, slave = os.openpty()
            tty.setraw(slave)  # kept by the pty for whoever opens it next
            self.pty_path = os.ttyname(slave)
            # Not kept open here: the master then reports POLLHUP while no program has the
            # pty open, which is how the bench tells an opened port from a closed one.
            os.close(slave)
            os.set_blocking(master, False)
            self.pty = master
            self._poll = select.poll()
            self._poll.register(master, select.POLLIN)

    def accept_loop(self, stop):
        while not stop.is_set():
            try:
                conn, _ = self._server.accept()
            except (socket.timeout, OSError):
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._new.put(conn)

    def close(self):
        """The server and the attached TCP host (the pty's fd: ``close_pty``)."""
        if self._server is not None:
            self._server.close()
        if self.reader is not None and self.reader is not PTY_READER:
            self.reader.close()
        self.reader = None
        while not self._new.empty():
            self._new.get_nowait().close()

    def close_pty(self):
        fd, self.pty = self.pty, None
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass

    def pump(self):
        """Hosts coming and going, their bytes to the jig."""
        port = self.port
        while True:
            try:
                conn = self._new.get_nowait()
            except queue.Empty:
                break
            if self.reader is not None:
                conn.close()  # one host at a time
                continue
            conn.setblocking(False)
            self._attach(conn)
        reader = self.reader
        if reader is not None and reader is not PTY_READER:
            try:
                data = reader.recv(4096)
            except (BlockingIOError, InterruptedError):
                data = None
            except OSError:
                data = b""
            if data == b"":
                self._detach()
            elif data:
                port.host_send(data)
        if self.pty is None:
            return
        events = 0
        for _, ev in self._poll.poll(0):
            events |= ev
        hup = events & (select.POLLHUP | select.POLLERR)
        if reader is None and not hup:
            self._attach(PTY_READER)
        elif reader is PTY_READER and hup:
            self._detach()
        if events & select.POLLIN and not hup:
            try:
                data = os.read(self.pty, 4096)
            except OSError:
                data = b""
            if data and self.reader is PTY_READER:  # else: a second host, ignored
                port.host_send(data)

    def _attach(self, reader):
        self.reader = reader
        self.port.host_open()

    def _detach(self):
        reader, self.reader = self.reader, None
        if reader is PTY_READER:
            try:
                termios.tcflush(self.pty, termios.TCIOFLUSH)  # the next host gets no stale bytes
            except (OSError, termios.error):
                pass
        elif reader is not None:
            try:
                reader.close()
            except OSError:
                pass
        self.port.host_close()

    def sink(self, data):
        """What the host takes now of one USB frame's bytes (never blocks)."""
        reader = self.reader
        if reader is None:
            return 0
        try:
            if reader is PTY_READER:
                return os.write(self.pty, data)
            return reader.send(data)
        except (BlockingIOError, InterruptedError):
            return 0
        except OSError:
            self._detach()
            return 0


class Bench:
    """The bench in real time on a background thread, reachable by pty and TCP.

    The PC bus: ``tcp_url`` (``tcp_port``, 0: a free one) and ``pty_path``. The jig's
    capture stream: ``capture_url`` (``capture_port``) and ``capture_pty_path``
    (none with ``pty=False``). One capture reader at a time: a TCP client that
    connects while another reader is attached is closed at once; the pty is attached
    while a program has it open and no TCP client is. A reader that goes away closes
    the port (``SimCapturePort.host_close``).

    With a CAN bus (``can_nodes=...`` or ``can=True``, see ``SimBench``) the jig's
    SLCAN port (or the direct adapter's) is served the same way: ``slcan_url``
    (``slcan_port``, 0: a free one) and ``slcan_pty_path``.
    """

    def __init__(self, driver_ids=(2, 3), baud=115200, tcp_port=0, pty=True, capture_port=0, slcan_port=0, **kw):
        self.driver_ids = tuple(driver_ids)
        self.baud = baud
        self.tcp_port = tcp_port
        self.capture_port = capture_port
        self.want_pty = pty
        # The line watch (DE up at a start bit) moves DE by a fraction of a byte time, which
        # the wall clock's jitter hides, and its start-bit wakes cost the bench ~15 % more CPU
        # a transaction: the real-time bench takes the bus at a frame's first byte.
        kw.setdefault("line_watch", False)
        self.kw = kw
        self.sim = None
        self.pty_path = None
        self.tcp_url = None
        self._inbox = queue.Queue()
        self._stop = threading.Event()
        self._threads = []
        self._clients = []
        self._lock = threading.Lock()
        self._master = self._slave = None
        self._server = None
        self.error = None
        self.capture_url = None
        self.capture_pty_path = None
        self.slcan_port = slcan_port
        self.slcan_url = None
        self.slcan_pty_path = None
        self._hosts = []  # HostPort: the capture port, the SLCAN port
        self._fd_users = 0  # threads running that use the ptys' descriptors
        self._fds_left = False  # stop() returned while one of them still ran

    # --- lifecycle -----------------------------------------------------------------
    def start(self):
        self.sim = SimBench(self.driver_ids, self.baud, realtime=True, record=False, **self.kw)
        # Bytes from the pty/TCP side enter the bus at the wall-clock time they arrived, which
        # can fall a few µs before the jig's DE drop after the reply they answer (the PC saw
        # that reply end): the real-time bench cannot place that edge to the µs, so its jig
        # ports hear the bus while driving it, as before the bench modelled /RE tied to DE.
        self.sim.hal.up.node.deaf_with_de = self.sim.hal.down.node.deaf_with_de = False
        self.sim.clock.pump = self._pump
        self.sim.pc.listeners.append(self._to_pc)
        self.sim.pc.keep = False
        if self.want_pty:
            self._open_pty()
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind(("127.0.0.1", self.tcp_port))
        self._server.listen(4)
        self._server.settimeout(0.2)
        port = self._server.getsockname()[1]
        self.tcp_url = "socket://127.0.0.1:%d" % port
        cap = HostPort("capture", self.sim.hal.capture, self.capture_port, self.want_pty)
        self._hosts.append(cap)
        cap.open()
        self.capture_url, self.capture_pty_path = cap.url, cap.pty_path
        if self.sim.slcan is not None:
            slc = HostPort("slcan", self.sim.slcan, self.slcan_port, self.want_pty)
            self._hosts.append(slc)
            slc.open()
            self.slcan_url, self.slcan_pty_path = slc.url, slc.pty_path
        self._spawn(self._accept_loop)
        for h in self._hosts:
            self._spawn(h.accept_loop, self._stop)
        self._fd_user_spawn(self._sim_loop)
        return self

    def _spawn(self, fn, *args):
        t = threading.Thread(target=fn, args=args, daemon=True)
        t.start()
        self._threads.append(t)

    def stop(self):
        self._stop.set()
        for t in self._threads:
            t.join(2.0)
        with self._lock:
            # A thread still running (the simulation stuck in a pass) may still use the
            # ptys: their descriptors are closed when the last such thread ends, not here,
            # or it would write into whatever file reuses their numbers.
            self._fds_left = self._fd_users > 0
            if not self._fds_left:
                self._close_fds()
        if self._server is not None:
            self._server.close()
        for h in self._hosts:
            h.close()
        with self._lock:
            for c in self._clients:
                try:
                    c.close()
                except OSError:
                    pass
            self._clients = []

    def _fd_user_spawn(self, fn):
        with self._lock:
            self._fd_users += 1
        self._spawn(fn)

    def _fd_user_ends(self):
        """In a thread that uses the ptys, as it ends: the last one closes what stop() left."""
        with self._lock:
            self._fd_users -= 1
            if self._fds_left and self._fd_users == 0:
                self._fds_left = False
                self._close_fds()

    def _close_fds(self):
        """The ptys' raw descriptors (with the lock held; once)."""
        for h in self._hosts:
            h.close_pty()
        for name in ("_master", "_slave"):
            fd = getattr(self, name)
            setattr(self, name, None)
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
        return False

    # --- pty -----------------------------------------------------------------------
    def _open_pty(self):
        import tty

        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.pty_path = os.ttyname(self._slave)
        # The simulation thread writes the PC's replies here: never block it (nobody may
        # be reading the pty while TCP clients use the bench).
        os.set_blocking(self._master, False)
        self._fd_user_spawn(self._pty_loop)

    def _pty_loop(self):
        fd = self._master
        try:
            while not self._stop.is_set():
                r, _, _ = select.select([fd], [], [], 0.2)
                if r:
                    try:
                        data = os.read(fd, 4096)
                    except OSError:
                        continue
                    if data:
                        self._inbox.put(data)
        finally:
            self._fd_user_ends()

    @property
    def _cap_pty(self):
        """The capture pty's master fd (None once closed)."""
        return self._hosts[0].pty if self._hosts else None

    # --- TCP -----------------------------------------------------------------------
    def _accept_loop(self):
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except (socket.timeout, OSError):
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                self._clients.append(conn)
            self._spawn(self._client_loop, conn)

    def _client_loop(self, conn):
        conn.settimeout(0.2)
        while not self._stop.is_set():
            try:
                data = conn.recv(4096)
            except socket.timeout:
                continue
            except OSError:
                break
            if not data:
                break
            self._inbox.put(data)
        with self._lock:
            if conn in self._clients:
                self._clients.remove(conn)
        try:
            conn.close()
        except OSError:
            pass

    # --- simulation thread -------------------------------------------------------------
    def _pump(self):
        # Bytes from outside reach the bus when they arrived (the wall clock), not at
        # the simulated time the bench is catching up through after a stall: they
        # cannot have been on the wire earlier.
        for h in self._hosts:
            h.pump()
        try:
            while True:
                data = self._inbox.get_nowait()
                self.sim.pc.send(data, self.sim.clock.wall())
        except queue.Empty:
            pass

    def _to_pc(self, data):
        if self._master is not None:
            try:
                os.write(self._master, data)
            except BlockingIOError:
                # The pty's buffer is full: nobody reads it. What it holds is stale (an
                # adapter nobody reads loses it too): drop it, keep the newest.
                try:
                    termios.tcflush(self._slave, termios.TCIFLUSH)
                    os.write(self._master, data)
                except OSError:
                    pass
            except OSError:
                pass
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            try:
                c.sendall(data)
            except OSError:
                pass

    def _sim_loop(self):
        clock = self.sim.clock
        try:
            while not self._stop.is_set():
                clock.run_until(clock.now + 2000.0)
        except Exception as exc:  # reported by the CLI, never a silent death
            self.error = exc
            self._stop.set()
        finally:
            self._fd_user_ends()


def _or_all(sources):
    mask = 0
    for source in sources:
        mask |= source()
    return mask
