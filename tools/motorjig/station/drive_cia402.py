"""A CiA 402 drive on the jig's CAN port as a station ``Drive``, through python-canopen.

``Cia402Drive(url, node_id, bitrate, od, master=None, jig_id=1)``; ``open()`` checks the
SLCAN port (``motorjig.can.port.probe``), opens python-can's slcan bus on it with the jig's
timestamps on (below), adds the node as a python-canopen ``BaseNode402`` and prepares it:
NMT pre-operational, the trace TPDOs mapped, the heartbeat on, NMT operational. The
protocol work is python-canopen's (SDO, PDO maps, NMT, EMCY); this module only decides
what to send when. The power state machine it runs is the table of
``motorjig.can.power402`` (``path``/``state_of``), each transition timed.

**Dates.** Every frame the jig receives is dated by the jig's ms clock: the SLCAN ``Z1``
timestamp (docs/can.md). python-can's slcan interface reads the line and stamps the
frame with this PC's time, ignoring the jig's field, so ``StampedSlcanBus`` (a subclass,
two small overrides) sends ``Z1`` when it opens the channel and puts the jig's time,
unwrapped past its 60 s wrap, into ``msg.timestamp``: the TPDO samples and the replies
to the station's own commands are dated on one clock that a busy PC cannot move. A
command is dated by its SDO reply (the drive's answer, ``sdo_stamp``), 1 ms resolution.

**The trace** (``TRACE_TPDOS``): TPDO1 statusword on change (every state change and
handshake bit, dated); TPDO2 statusword + position actual 0x6064 and TPDO3 velocity
actual 0x606C + following error actual 0x60F4, sampled by the drive itself every
``sync_period(bitrate)`` (2 ms at 1 Mbit/s and 500 kbit/s, where the frames fill 15 % / 30 %
of the bus): event-driven (transmission type 254, event timer = inhibit time = the period)
by default, or on a SYNC the station sends at that period (``on_sync=True``). The drive's
own timer is the default because a SYNC sent by this PC is as regular as this PC: on the
shared bench machine the SYNC trace came at 276 Hz with gaps where the drive-timed one came
at 500.0 Hz (cia402-smoke's moves, same load). A sample is a TPDO3 with the last TPDO2
(on SYNC: the same SYNC's); demand = actual + following error. The TPDOs are decoded here
with ``struct`` (the maps are python-canopen's, set with ``PdoMap.save``): 1 000 frames a
second through its per-variable decoding would cost this PC more than the bus costs the drive.

**EMCY**: every EMCY the node sends is kept (``emcys``: time, code, register, text named
by ``motorjig.can.cia301``); a step that sees one with a non-zero code fails with it.
"""

import logging
import queue
import struct
import threading
import time

import can
import canopen
from can.interfaces.slcan import slcanBus

from motorjig.can import cia301, power402
from motorjig.can import port as canport
from motorjig.errors import JigError, PortError
from motorjig.station.drive import Drive, Emcy, SdoRefused, cia301_identity

_LOG = logging.getLogger(__name__)

HEARTBEAT_MS = 100  # the drive's 0x1017 during a run (bus-health judges its regularity)
SDO_TIMEOUT_S = 2.0  # a drive answers in ms; the real-time bench on a shared machine has stalled ~1 s
RESET_COMM_WAIT_S = 1.0  # a node's boot-up after "reset communication" (the bench's: ~50 ms)
STATE_TIMEOUT_S = 2.0  # a power state transition must be made within this
_FRAME_BITS = 300  # SYNC + TPDO2 (6 bytes) + TPDO3 (8 bytes) with stuffing, about
_LOAD = 0.3  # the share of the bus the trace may use
# Each sample costs this PC three SLCAN lines (and the real-time bench its whole CAN path in
# Python): 2 ms (500 Hz, the goal at 1 Mbit/s) is the shortest period used.
PERIOD_MIN_S = 0.002


def sync_period(bitrate, sharing=1):
    """The SYNC period (s) of a trace at ``bitrate``: the three frames of a sample in 30 % of the
    bus, rounded up to 0.5 ms, at least PERIOD_MIN_S (2 ms at 1 Mbit/s and 500 kbit/s, 4 ms at 250 kbit/s).
    ``sharing`` drives tracing on one bus at once (multi-up slots) share those 30 %: 8 ms each for
    four at 500 kbit/s (at 2 ms each they would fill the bus and starve the SDOs)."""
    period = _FRAME_BITS * max(1, sharing) / (_LOAD * bitrate)
    return max(PERIOD_MIN_S, -(-period // 0.0005) * 0.0005)


# TPDO number -> (transmission type, [(index, sub)]): see the module's doc
TRACE_TPDOS = {
    1: (255, [(0x6041, 0)]),
    2: (1, [(0x6041, 0), (0x6064, 0)]),
    3: (1, [(0x606C, 0), (0x60F4, 0)]),
}

# statusword bits
SW_FAULT = 1 << 3
SW_WARNING = 1 << 7
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
SW_ACK = 1 << 12  # profile position: set-point acknowledge; homing: homing attained
SW_ERROR = 1 << 13  # profile position: following error; homing: homing error
# controlword bits
CW_NEW_SETPOINT = 1 << 4
CW_IMMEDIATE = 1 << 5
CW_RELATIVE = 1 << 6
CW_HALT = 1 << 8

MODE_PROFILE_POSITION = 1
MODE_HOMING = 6


class StampedSlcanBus(slcanBus):
    """python-can's slcan bus with the jig's receive timestamps (``Z1``) as ``msg.timestamp``,
    seconds on the jig's clock; sends are serialised (the SYNC thread and python-canopen's)."""

    def __init__(self, *a, **kw):
        self._line = None
        self._ms_last = None
        self._ms_base = 0
        self.unstamped = 0  # frames that came without the jig's timestamp (dated by this PC)
        self._send_lock = threading.Lock()
        super().__init__(*a, **kw)

    def open(self, require_node=True):
        self._write("Z1")
        super().open()

    def _read(self, timeout):
        self._line = line = super()._read(timeout)
        return line

    def _recv_internal(self, timeout):
        self._line = None
        msg, filtered = super()._recv_internal(timeout)
        if msg is not None:
            stamp = _stamp_ms(self._line) if self._line else None
            if stamp is not None:
                if self._ms_last is not None and stamp < self._ms_last - 30000:
                    self._ms_base += 60000  # the jig's field wraps at 60 000 ms
                self._ms_last = stamp
                msg.timestamp = (self._ms_base + stamp) / 1000.0
            else:
                self.unstamped += 1
        return msg, filtered

    def send(self, msg, timeout=None):
        with self._send_lock:
            super().send(msg, timeout)


def _stamp_ms(line):
    """The 4-hex-digit ms timestamp at the end of an SLCAN frame line (its CR may end it), or None."""
    line = line.rstrip("\r")
    kind = line[:1]
    try:
        if kind and kind in "tr":
            n = 5 + (2 * int(line[4]) if kind == "t" else 0)
        elif kind and kind in "TR":
            n = 10 + (2 * int(line[9]) if kind == "T" else 0)
        else:
            return None
        return int(line[n:n + 4], 16) if len(line) == n + 4 else None
    except (ValueError, IndexError):
        return None


class Cia402Drive(Drive):
    protocol = "cia402"
    emergency_words = "quick stop, disable voltage"

    def __init__(self, url, node_id, bitrate, od, master=None, jig_id=1, period=None, on_sync=False, links=None):
        self.url, self.node_id, self.bitrate, self.od = url, node_id, bitrate, od
        self.links = links  # the slots' shared connections (station.slots.Links): one CAN network per port
        self.master, self.jig_id = master, jig_id
        self.label = "node %d" % node_id
        self.network = self.node = None
        self.emcys = []
        self.heartbeats = []  # jig times of the node's heartbeats
        self.t_opened = None  # jig time the heartbeat was switched on
        self.ready = False  # the node answered and is prepared (connect_node)
        self._booted = threading.Event()  # the node's boot-up came (after close's reset communication)
        self.bus_seconds = 0.0  # time spent waiting for SDO replies (the run's split: motion, bus, engine)
        self.sdo_stamp = None  # jig time of the node's last SDO reply
        self.statusword = None  # the last one a TPDO brought
        self.sw_log = []  # (t, statusword) of TPDO1 (every change)
        self.samples = queue.SimpleQueue()  # (t, statusword, actual, velocity, following error)
        self._tpdo2 = None
        self.period = period or sync_period(bitrate)
        self.event_driven = not on_sync
        self._sync_task = None
        self.tracing = False
        self._timers_on = False
        self._mode = None
        self._lock = threading.RLock()  # one SDO conversation at a time (steps, the safety net)
        self.last_sent = time.monotonic()

    # --- the connection ---------------------------------------------------------------------
    def open(self, require_node=True):
        """Open the port and prepare the node (see the module's doc); PortError / JigError if the
        port is not the jig's SLCAN port or the node does not answer."""
        if self.links is not None:  # several slots' nodes on one port: one network, opened by the first
            self.network = self.links.take(("can", self.url), self._open_network)
        else:
            self.network = self._open_network()
        n = self.node_id
        node = self.node = canopen.BaseNode402(n, self.od)
        self.network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        node.emcy.add_callback(self._on_emcy)
        self.network.subscribe(0x700 + n, self._on_heartbeat)
        self.network.subscribe(0x580 + n, self._on_sdo_reply)
        self.network.subscribe(0x180 + n, self._on_tpdo1)
        self.network.subscribe(0x280 + n, self._on_tpdo2)
        self.network.subscribe(0x380 + n, self._on_tpdo3)
        if require_node:
            self.connect_node()

    def _open_network(self):
        canport.probe(self.url)
        try:
            bus = StampedSlcanBus(channel=self.url, bitrate=self.bitrate, sleep_after_open=canport.SLEEP_AFTER_OPEN_S)
        except (can.CanError, OSError, ValueError) as exc:
            raise PortError("cannot open %s as an SLCAN port: %s" % (self.url, exc)) from None
        network = canopen.Network(bus)
        network.NOTIFIER_CYCLE = canport.NOTIFIER_CYCLE_S
        network.connect()
        return network

    def connect_node(self, wait_s=0.0):
        """The node answers at its id (asked again for up to ``wait_s``: a node just given its id
        boots first); then it is prepared for the run. JigError if it does not."""
        deadline = time.monotonic() + wait_s
        while True:
            try:
                self.read(0x1000)
                break
            except SdoRefused as exc:  # it answered: not the cable, the node's own refusal
                raise JigError("node %d answers on %s but refused the SDO read of 0x1000 (device type) with abort "
                               "%s: the station cannot prepare it"
                               % (self.node_id, self.url, cia301.abort_text(exc.code))) from None
            except JigError:
                if time.monotonic() >= deadline:
                    raise JigError("node %d does not answer on %s at %d bit/s (no SDO reply to 0x1000): check the "
                                   "cable, --can-port, [drive] node_id and bitrate"
                                   % (self.node_id, self.url, self.bitrate)) from None
                time.sleep(0.05)
        self._prepare()
        self.ready = True

    def _prepare(self):
        node = self.node
        with self._lock:
            node.nmt.send_command(0x80)  # pre-operational: PDO maps may change
            for number, (trans_type, objects) in TRACE_TPDOS.items():
                pdo = node.tpdo[number]
                pdo.clear()
                for index, sub in objects:
                    pdo.add_variable(index, sub)
                pdo.cob_id = (0x80 + 0x100 * number) + self.node_id
                pdo.trans_type = trans_type
                if number != 1 and self.event_driven:
                    pdo.trans_type = 254
                    pdo.inhibit_time = int(round(self.period * 10000))  # 100 us units
                    pdo.event_timer = 0  # on while a step traces (sync): no stream between steps
                else:
                    pdo.inhibit_time = 0 if trans_type >= 254 else None
                    pdo.event_timer = 0 if trans_type >= 254 else None
                pdo.enabled = True
                pdo.save()
            self.t_opened = self.write(0x1017, 0, HEARTBEAT_MS)  # heartbeats due from here
            node.nmt.send_command(0x01)  # operational: the PDOs run
            self.last_sent = time.monotonic()

    def close(self):
        """Leave the node as the run found it, then close: NMT "reset communication" puts its
        communication objects (the trace's PDO maps and event timers, the run's 0x1017) back to
        their power-on values and leaves it PRE-OPERATIONAL, so the bus is quiet for the next
        user (the jig's safety stop does the same when this PC dies)."""
        self._stop_sync()
        if self.ready and self.node is not None and self.network is not None:
            try:
                self._booted.clear()
                with self._lock:
                    self.node.nmt.send_command(0x82)
                # its boot-up says it was done (closing the channel at once could drop the frame)
                if not self._booted.wait(RESET_COMM_WAIT_S):
                    _LOG.error("node %d did not boot up after the reset of its communication", self.node_id)
            except (can.CanError, OSError, ValueError) as exc:
                _LOG.error("resetting node %d's communication failed: %s", self.node_id, exc)
        net, self.network = self.network, None
        if net is None:
            return
        if self.links is None:
            _disconnect(net)
            return
        n = self.node_id  # the network stays the other slots': only this node's callbacks leave it
        for can_id, callback in ((0x700 + n, self._on_heartbeat), (0x580 + n, self._on_sdo_reply),
                                 (0x180 + n, self._on_tpdo1), (0x280 + n, self._on_tpdo2),
                                 (0x380 + n, self._on_tpdo3)):
            try:
                net.unsubscribe(can_id, callback)
            except (KeyError, ValueError):
                pass
        if n in net:
            del net[n]
        self.links.give_back(("can", self.url), _disconnect)

    # --- frames in (python-canopen's notifier thread) ----------------------------------------
    def _on_emcy(self, entry):
        self.emcys.append(Emcy(entry.timestamp, entry.code, entry.register))

    def _on_heartbeat(self, can_id, data, t):
        if data and data[0] != 0:  # a boot-up is not a heartbeat
            self.heartbeats.append(t)
        elif data:
            self._booted.set()

    def _on_sdo_reply(self, can_id, data, t):
        self.sdo_stamp = t

    def _on_tpdo1(self, can_id, data, t):
        if len(data) >= 2:
            sw = data[0] | data[1] << 8
            self.statusword = sw
            self.sw_log.append((t, sw))

    def _on_tpdo2(self, can_id, data, t):
        if len(data) >= 6:
            sw, pos = struct.unpack_from("<Hi", data)
            self.statusword = sw
            self._tpdo2 = (t, sw, pos)

    def _on_tpdo3(self, can_id, data, t):
        got = self._tpdo2
        if not self.tracing:
            return
        if not self.event_driven:
            self._tpdo2 = None
        if got is not None and len(data) >= 8:
            vel, ferr = struct.unpack_from("<ii", data)
            self.samples.put((got[0], got[1], got[2], vel, ferr))

    # --- SDO ----------------------------------------------------------------------------------
    def read(self, index, sub=0):
        """An object's value by SDO (JigError naming the abort or the silence)."""
        with self._lock:
            t0 = self.last_sent = time.monotonic()
            try:
                obj = self.node.sdo[index]
                return (obj[sub] if not isinstance(obj, canopen.sdo.SdoVariable) else obj).raw
            except canopen.SdoAbortedError as exc:
                raise SdoRefused("node %d refused to read 0x%04X:%02X: %s" % (
                    self.node_id, index, sub, cia301.abort_text(exc.code)), exc.code) from None
            except (canopen.SdoCommunicationError, can.CanError, OSError) as exc:
                raise JigError("node %d, reading 0x%04X:%02X: %s" % (self.node_id, index, sub, exc)) from None
            finally:
                self.bus_seconds += time.monotonic() - t0

    def write(self, index, sub, value):
        """Write an object by SDO; returns the jig's time of the drive's reply."""
        with self._lock:
            t0 = self.last_sent = time.monotonic()
            try:
                obj = self.node.sdo[index]
                (obj[sub] if not isinstance(obj, canopen.sdo.SdoVariable) else obj).raw = value
            except canopen.SdoAbortedError as exc:
                raise JigError("node %d refused 0x%04X:%02X = %r: %s" % (
                    self.node_id, index, sub, value, cia301.abort_text(exc.code))) from None
            except (canopen.SdoCommunicationError, can.CanError, OSError) as exc:
                raise JigError("node %d, writing 0x%04X:%02X: %s" % (self.node_id, index, sub, exc)) from None
            finally:
                self.bus_seconds += time.monotonic() - t0
            return self.sdo_stamp

    def controlword(self, value):
        """Write 0x6040; the jig's time of the drive's reply (the command's instant)."""
        return self.write(0x6040, 0, value)

    def read_statusword(self):
        return self.read(0x6041)

    def sync(self, on):
        """Start (on) or stop tracing: samples are kept (``samples``) only while on. Event-driven,
        the drive's event timers of TPDO2/3 run only then (between steps they would only queue
        frames before the station's SDO replies); on SYNC, the station's SYNC runs only then."""
        self.tracing = on
        if self.event_driven:
            if self._timers_on != on:
                ms = int(round(self.period * 1000)) if on else 0
                for comm in (0x1801, 0x1802):  # TPDO2, TPDO3 communication: sub 5 event timer
                    self.write(comm, 5, ms)
                self._timers_on = on
        elif on and self._sync_task is None:
            self._sync_task = self.network.bus.send_periodic(
                can.Message(arbitration_id=0x080, is_extended_id=False, data=b""), self.period)
        elif not on:
            self._stop_sync()

    def _stop_sync(self):
        self.tracing = False
        task, self._sync_task = self._sync_task, None
        if task is not None:
            try:
                task.stop()
            except (can.CanError, OSError):
                pass

    def keep_alive(self):
        """One SYNC: the jig's CAN safety stop sees the host alive (the safety net's heartbeat)."""
        if self.network is not None and self._sync_task is None:
            self.network.sync.transmit()

    # --- the drive interface --------------------------------------------------------------
    def identify(self):
        return cia301_identity(self.read)

    def state(self):
        return power402.state_of(self.read_statusword())

    def go(self, target):
        """Take the power state machine to ``target`` along ``power402.path``; returns
        [(controlword, state, seconds)] each transition took, from the drive's reply to the
        controlword to the first statusword showing the state, on the jig's clock."""
        done = []
        now = self.state()
        if now == power402.FAULT_REACTION:
            now = self._wait_state(power402.FAULT, time.monotonic() + STATE_TIMEOUT_S, 0)[0]
        option = self.read(0x605A) if target == power402.OPERATION_ENABLED and now == power402.QUICK_STOP_ACTIVE else None
        for cw, expected in power402.path(now, target, option):
            n0 = len(self.sw_log)
            t_cmd = self.controlword(cw)
            state, t = self._wait_state(expected, time.monotonic() + STATE_TIMEOUT_S, n0)
            if state != expected:
                raise JigError("node %d: controlword 0x%04X did not take it to %s (it is in %s)"
                               % (self.node_id, cw, expected, state))
            # A drive that shows the state in its TPDO before it answers the SDO (the same ms, or the
            # reply queued behind the PDO) took no measurable time: 0, never a negative time.
            done.append((cw, expected, max(0.0, round(t - t_cmd, 4)) if t is not None and t_cmd is not None else None))
        return done

    def _wait_state(self, expected, deadline, n0=None):
        """(state, jig time TPDO1 first showed it after sw_log[n0], or None) once the drive shows
        ``expected`` (asked by SDO when TPDO1 is slow) or the deadline passed."""
        n0 = len(self.sw_log) if n0 is None else n0
        seen_by_sdo = None
        while True:
            for t, sw in self.sw_log[n0:]:
                if power402.state_of(sw) == expected:
                    return expected, t
            now = time.monotonic()
            if seen_by_sdo is None:
                state = self.state()
                if state == expected:
                    seen_by_sdo = now  # its TPDO1 is on the way: a moment to date it
                elif now > deadline:
                    return state, None
            elif now - seen_by_sdo > 0.1:
                return expected, None
            time.sleep(0.002)

    def enable(self, on):
        target = power402.OPERATION_ENABLED if on else power402.SWITCH_ON_DISABLED
        steps = self.go(target)
        if on:
            self._mode = None  # enabling sets the demand to the actual position
        return {"state": self.state(), "transitions": steps}

    def fault_reset(self):
        state = self.state()
        if state in (power402.FAULT, power402.FAULT_REACTION):
            return self.go(power402.SWITCH_ON_DISABLED)
        return []

    def fault(self):
        """0x603F error code when the drive is in FAULT (0: no fault)."""
        sw = self.read_statusword()
        return self.read(0x603F) if sw & SW_FAULT else 0

    def set_mode(self, mode):
        if self._mode != mode:
            self.write(0x6060, 0, mode)
            deadline = time.monotonic() + STATE_TIMEOUT_S
            while self.read(0x6061) != mode:
                if time.monotonic() > deadline:
                    raise JigError("node %d did not take mode of operation %d" % (self.node_id, mode))
                time.sleep(0.002)
            self._mode = mode

    def position(self):
        return self.read(0x6064)

    def move(self, target, speed, accel=None, decel=None, relative=False):
        """A profile position move (the new-set-point handshake); returns the jig time of the
        drive's reply to the controlword that started it."""
        self.set_mode(MODE_PROFILE_POSITION)
        self.write(0x6081, 0, speed)
        if accel is not None:
            self.write(0x6083, 0, accel)
        if decel is not None:
            self.write(0x6084, 0, decel)
        self.write(0x607A, 0, target)
        base = 0x0F | (CW_RELATIVE if relative else 0) | CW_IMMEDIATE
        self.controlword(base)  # bit 4 low first: the next write is its rising edge
        t = self.controlword(base | CW_NEW_SETPOINT)
        self._handshake(SW_ACK, True)
        self.controlword(base)
        return t

    def _handshake(self, bit, value, timeout=STATE_TIMEOUT_S):
        deadline = time.monotonic() + timeout
        while bool(self.read_statusword() & bit) != value:
            if time.monotonic() > deadline:
                raise JigError("node %d did not acknowledge the set-point (statusword bit 12)" % self.node_id)
            time.sleep(0.001)

    def home(self, method, speed_switch=None, speed_zero=None, accel=None):
        """Start a homing (mode 6); returns the jig time of the start."""
        self.set_mode(MODE_HOMING)
        self.write(0x6098, 0, method)
        if speed_switch is not None:
            self.write(0x6099, 1, speed_switch)
        if speed_zero is not None:
            self.write(0x6099, 2, speed_zero)
        if accel is not None:
            self.write(0x609A, 0, accel)
        self.controlword(0x0F)
        return self.controlword(0x1F)

    def quick_stop(self):
        return self.controlword(power402.COMMANDS[power402.QUICK_STOP])

    def halt(self):
        return self.controlword(0x0F | CW_HALT | CW_IMMEDIATE)

    def inputs(self):
        return self.read(0x60FD)

    def lss_configure(self, factory_node_id=0xFF):
        """CiA 305: find the drive at its factory node id (255: unconfigured, by LSS fast scan; else
        by its identity 0x1018 read there), give it this drive's node id and bitrate, store them
        and switch every node back to waiting, where it boots with its new id. Returns its
        identity (vendor, product, revision, serial), or None when no node was found."""
        from motorjig.can.cancmd import LSS_BIT_TIMING

        lss = self.network.lss
        with self._lock:
            self.last_sent = time.monotonic()
            if factory_node_id == 0xFF:
                found, ids = lss.fast_scan()
                if not found:
                    return None
            else:
                factory = canopen.RemoteNode(factory_node_id, self.od)
                self.network.add_node(factory)
                factory.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
                try:
                    ids = [factory.sdo[0x1018][sub].raw for sub in (1, 2, 3, 4)]
                except (canopen.SdoAbortedError, canopen.SdoCommunicationError):
                    return None
                finally:
                    del self.network[factory_node_id]
                if not lss.send_switch_state_selective(*ids):
                    return None
            lss.configure_node_id(self.node_id)
            lss.configure_bit_timing(LSS_BIT_TIMING[self.bitrate])
            lss.store_configuration()
            lss.send_switch_state_global(lss.WAITING_STATE)
        return tuple(ids)

    def new_trace(self, ctx, step):
        """The trace a moving step samples this drive with: its TPDOs on the station's SYNC, dated by the jig."""
        from motorjig.station.sampling_cia402 import Cia402Trace

        return Cia402Trace(ctx, step)

    def wait_target_reached(self, timeout):
        """True once the statusword (by SDO) shows target reached (bit 10) within ``timeout`` s (0x6068
        may delay it)."""
        deadline = time.monotonic() + timeout
        while not self.read_statusword() & SW_TARGET_REACHED:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.005)
        return True

    def unstamped(self):
        """Frames received without the jig's timestamp (their time is this PC's, not the bus's)."""
        bus = getattr(self.network, "bus", None)
        return getattr(bus, "unstamped", 0)

    def bus_health(self):
        counters = {}
        if self.master is not None:
            try:
                counters = self.master.can_counters(self.jig_id)
            except JigError:
                counters = {}
        return counters

    def make_safe(self, emergency=False):
        """Quick stop, then disable voltage (SWITCH ON DISABLED), each tried whatever the other did."""
        problems = []
        self._stop_sync()
        for what, cw in (("quick stop", power402.COMMANDS[power402.QUICK_STOP]),
                         ("disable voltage", power402.COMMANDS[power402.DISABLE_VOLTAGE])):
            try:
                self.controlword(cw)
            except Exception as exc:  # a dead node or a closed port: try the next action anyway
                problems.append("%s: %s" % (what, exc))
        return problems


def _disconnect(network):
    try:
        network.disconnect()
    except (can.CanError, OSError, ValueError):
        pass


def make_safe_on(url, node_id, bitrate, od):
    """Quick stop + disable voltage on a connection of its own (after an abort whose plug is gone);
    the problems met, as texts."""
    d = Cia402Drive(url, node_id, bitrate, od)
    try:
        canport.probe(url)
        d.network = canopen.Network(StampedSlcanBus(channel=url, bitrate=bitrate,
                                                   sleep_after_open=canport.SLEEP_AFTER_OPEN_S))
        d.network.NOTIFIER_CYCLE = canport.NOTIFIER_CYCLE_S
        d.network.connect()
        d.node = canopen.BaseNode402(node_id, od)
        d.network.add_node(d.node)
        d.node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        return d.make_safe(emergency=True)
    except Exception as exc:  # the port cannot be opened any more: the record says how the run ended
        return ["%s" % exc]
    finally:
        d.close()
