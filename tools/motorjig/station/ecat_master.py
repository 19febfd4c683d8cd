"""The EtherCAT master of a station's run, in a process of its own: SOEM (pysoem), the cycle, CSP, SDOs.

``EcatMaster`` opens the line (scan, PDO layout read by SDO, map, distributed clocks with SYNC0
at the cycle, SAFE-OP, OP), runs the process-data cycle in a thread (``cycle_s``, 1 ms by
default) and serves the station's requests between cycles: object access by CoE SDO (typed by
the drive's object dictionary), the controlword, CSP moves along the station's trapezoid (one
target a cycle), homing through mode 6. Each sample is dated by the distributed clock (the
reference slave's system time), so a busy PC does not move a sample's date; every cycle's own
timing is counted (frames lost, working counters short, cycles sent late, the period).

It runs in its own process (``serve``, started by ``drive_ecat.EcatDrive``) because a 1 ms cycle
cannot share a Python interpreter with the station's engine: a busy thread there holds the
interpreter for milliseconds. When the station's process dies (its pipe closes), the master
quick-stops and disables the drive, takes the line to INIT and stops; when both die, the
frames stop and the slave's process-data watchdog stops the drive.
"""

import gc
import os
import struct
import threading
import time

from motorjig.can import cia301, power402
from motorjig.errors import JigError, PortError
from motorjig.station.drive import Emcy, SdoRefused, cia301_identity

MODE_HOMING, MODE_CSP = 6, 8
SW_FAULT = 0x0008
STATE_TIMEOUT_S = 1.0
OP_TIMEOUT_S = 3.0
LATE_FACTOR = 1.5  # a cycle sent this many periods after the last one came late
# how long a cycle waits for its frame: a late answer is a late cycle (judged by its budget), not a
# lost frame; SOEM's own 2 ms would count a busy PC's scheduling as the bus losing frames
RECEIVE_TIMEOUT_US = 5000
OUT_NEEDED = ((0x6040, 0), (0x607A, 0))  # the objects the process data must carry
IN_NEEDED = ((0x6041, 0), (0x6064, 0))
STRUCTS = {8: "b", 16: "h", 32: "i"}
HIST_US = 10  # the period histogram's bin, µs
HIST_BINS = 5000  # up to 50 ms; longer ones go in the last
NICE = -15  # the cycle thread's niceness, when the system lets us (root)


def trapezoid(distance, speed, accel, decel):
    """(times, fn(t) -> position from 0) of a trapezoid (or triangle) move of ``distance`` counts."""
    d = abs(distance)
    sign = 1 if distance >= 0 else -1
    v, a, b = float(speed), float(accel), float(decel)
    ta, tb = v / a, v / b
    if a * ta * ta / 2 + b * tb * tb / 2 > d:  # never reaches the speed: a triangle
        v = (2 * d * a * b / (a + b)) ** 0.5
        ta, tb = v / a, v / b
    da, db = a * ta * ta / 2, b * tb * tb / 2
    tc = (d - da - db) / v if v else 0.0
    total = ta + tc + tb

    def at(t):
        if t <= 0:
            return 0.0
        if t < ta:
            return sign * a * t * t / 2
        if t < ta + tc:
            return sign * (da + v * (t - ta))
        if t < total:
            r = total - t
            return sign * (d - b * r * r / 2)
        return float(distance)

    return total, at


class EcatMaster:
    """The master of one drive's line (see the module's docstring): runs in the cycle's process."""

    def __init__(self, ifname, position, od, cycle_s, samples, shared):
        self.ifname, self.position_on_line, self.od, self.period = ifname, position, od, cycle_s
        self.label = "slave %d" % position
        self.master = self.slave = None
        self.emcys = []
        # (t, statusword, actual, velocity, following error, the target sent, a profile running), to the station
        self.samples = samples
        self.shared = shared  # statusword, position, velocity, following error, inputs, bus time, cycles
        self.tracing = False
        self.ready = False
        self.sw = self.pos = self.vel = self.ferr = self.din = 0
        self.sw_log = []  # (t, statusword) on every change
        self.cycles = self.frames_lost = self.wkc_errors = self.late_cycles = 0
        self.late_max_ms = 0.0
        self.late_ms_total = 0.0  # what the late cycles lost in all, ms
        self.periods = [0] * HIST_BINS  # how many periods fell in each HIST_US-wide bin (the last: longer)
        self.period_max_ms = 0.0
        self.t_bus = None  # the bus's time of the last cycle, s
        self.bus_seconds = 0.0
        self.identity = {}
        self._cw = 0
        self._mode = MODE_CSP
        self._target = 0  # the demand the cycle sends (CSP)
        self._profile = None  # (start, t0 cycles, total s, at)
        self._sent = threading.Condition()
        self._cycle_no = 0
        self._run = False
        self._thread = None
        self._lock = threading.RLock()  # one SDO conversation at a time

    # --- the bus ------------------------------------------------------------------------------------
    def open(self):
        """Scan the line, map the process data, start the cycle and take the slaves to OP. PortError /
        JigError with the reason (no slave, the plan's position not on the line, OP refused)."""
        import pysoem

        pysoem.settings.always_release_gil = True  # the cycle thread runs while an SDO waits
        m = self.master = pysoem.Master()
        try:
            m.open(self.ifname)
        except Exception as exc:
            self.master = None
            raise PortError("cannot open the EtherCAT interface %s: %s (run as root; `ip link` lists the "
                            "interfaces)" % (self.ifname, exc)) from None
        n = m.config_init()
        if n <= 0:
            raise JigError("no EtherCAT slave answered on %s: is the drive's cable in (or the bench started with "
                           "python -m motorjig.sim --ecat-slaves N)?" % self.ifname)
        if self.position_on_line >= n:
            raise JigError("the plan's slave position %d is not on the line: %d slave%s answered on %s"
                           % (self.position_on_line, n, "" if n == 1 else "s", self.ifname))
        s = self.slave = m.slaves[self.position_on_line]
        self.identity = {"name": s.name, "vendor_id": s.man, "product_code": s.id, "revision": s.rev}
        s.add_emergency_callback(self._on_emcy)
        self.out_map = self._layout(0x1C12)
        self.in_map = self._layout(0x1C13)
        for key in OUT_NEEDED:
            if key not in self.out_map:
                raise JigError("slave %d's process data lacks 0x%04X:%02X (RxPDO, 0x1C12): map it to test the drive "
                               "in cyclic synchronous position" % ((self.position_on_line,) + key))
        for key in IN_NEEDED:
            if key not in self.in_map:
                raise JigError("slave %d's process data lacks 0x%04X:%02X (TxPDO, 0x1C13): map it"
                               % ((self.position_on_line,) + key))
        m.config_map()
        self.dc = bool(m.config_dc())
        if self.dc:
            for sl in m.slaves:
                sl.dc_sync(True, int(self.period * 1e9))
        if m.state_check(pysoem.SAFEOP_STATE, 50000) != pysoem.SAFEOP_STATE:
            raise JigError("the slaves did not reach SAFE-OP: %s" % self._al_text())
        self.out_size, self.in_size = len(s.output), len(s.input)
        self._run = True
        self._thread = threading.Thread(target=self._cycle_loop, name="ecat-cycle", daemon=True)
        self.realtime = False
        self._thread.start()
        self._wait_cycles(3)
        self._target = self.pos
        m.state = pysoem.OP_STATE
        m.write_state()
        deadline = time.monotonic() + OP_TIMEOUT_S
        while m.state_check(pysoem.OP_STATE, 20000) != pysoem.OP_STATE:
            if time.monotonic() > deadline:
                raise JigError("slave %d did not go to OP: %s" % (self.position_on_line, self._al_text()))
        self.ready = True

    def _al_text(self):
        self.master.read_state()
        import pysoem

        return "; ".join("slave %d %s, AL status 0x%04X %s" % (
            i, {1: "INIT", 2: "PRE-OP", 4: "SAFE-OP", 8: "OP"}.get(sl.state & 0x0F, hex(sl.state)), sl.al_status,
            pysoem.al_status_code_to_string(sl.al_status)) for i, sl in enumerate(self.master.slaves))

    def _layout(self, assign):
        """{(index, sub): (byte offset, bits)} of the PDOs assigned in ``assign`` (by SDO, in PRE-OP)."""
        out, offset = {}, 0
        for i in range(1, self._sdo_read(assign, 0, 1) + 1):
            pdo = self._sdo_read(assign, i, 2)
            for j in range(1, self._sdo_read(pdo, 0, 1) + 1):
                e = self._sdo_read(pdo, j, 4)
                index, sub, bits = e >> 16, e >> 8 & 0xFF, e & 0xFF
                if index:
                    out[(index, sub)] = (offset // 8, bits)
                offset += bits
        return out

    def _sdo_read(self, index, sub, size):
        raw = self.slave.sdo_read(index, sub)
        return int.from_bytes(raw[:size], "little")

    # --- the cycle (its own thread) -------------------------------------------------------------
    def _pack(self, buf, key, value):
        where = self.out_map.get(key)
        if where is not None:
            offset, bits = where
            struct.pack_into("<" + STRUCTS[bits].upper(), buf, offset, int(value) & ((1 << bits) - 1))

    def _unpack(self, raw, key, signed=True):
        where = self.in_map.get(key)
        if where is None:
            return None
        offset, bits = where
        fmt = STRUCTS[bits]
        return struct.unpack_from("<" + (fmt if signed else fmt.upper()), raw, offset)[0]

    def _outputs(self):
        buf = bytearray(self.out_size)
        self._pack(buf, (0x6040, 0), self._cw & 0xFFFF)
        self._pack(buf, (0x607A, 0), int(self._target))
        self._pack(buf, (0x6060, 0), self._mode)
        return bytes(buf)

    def _cycle_loop(self):
        self.realtime = _realtime()
        gc.freeze()  # what exists now is never scanned again: shorter collections in the cycle's process
        m, s = self.master, self.slave
        period = self.period
        t_next = time.perf_counter()
        t_last = None
        while self._run:
            prof = self._profile
            if prof is not None:
                start, k0, total, at = prof
                t = (self._cycle_no - k0) * period
                self._target = int(round(start + at(t)))
                if t >= total:
                    self._profile = None
            s.output = self._outputs()
            now = time.perf_counter()
            if t_last is not None:
                gap = (now - t_last) * 1000.0
                self.periods[min(HIST_BINS - 1, int(gap * 1000.0 / HIST_US))] += 1
                if gap > self.period_max_ms:
                    self.period_max_ms = gap
                if gap > LATE_FACTOR * period * 1000.0:
                    self.late_cycles += 1
                    self.late_max_ms = max(self.late_max_ms, gap - period * 1000.0)
                    self.late_ms_total += gap - period * 1000.0
            t_last = now
            m.send_processdata()
            wkc = m.receive_processdata(max(RECEIVE_TIMEOUT_US, int(period * 3e6)))
            self.cycles += 1
            if wkc <= 0:
                self.frames_lost += 1
            elif wkc != m.expected_wkc:
                self.wkc_errors += 1
            else:
                self._take_inputs(bytes(s.input), m.dc_time / 1e9 if self.dc else now)
            with self._sent:
                self._cycle_no += 1
                self._sent.notify_all()
            t_next += period
            wait = t_next - time.perf_counter()
            if wait < -period:  # far behind (a stalled PC): start afresh, the lateness was counted
                t_next = time.perf_counter()
            elif wait > 0:
                if wait > 0.0003:
                    time.sleep(wait - 0.0003)
                while time.perf_counter() < t_next:
                    pass

    def _take_inputs(self, raw, t):
        sw = self._unpack(raw, (0x6041, 0), signed=False)
        self.pos = self._unpack(raw, (0x6064, 0))
        vel = self._unpack(raw, (0x606C, 0))
        ferr = self._unpack(raw, (0x60F4, 0))
        din = self._unpack(raw, (0x60FD, 0), signed=False)
        self.vel = vel if vel is not None else 0
        self.ferr = ferr if ferr is not None else 0
        self.din = din
        if sw != self.sw or not self.sw_log:
            self.sw_log.append((t, sw))
        self.sw = sw
        self.t_bus = t
        sh = self.shared
        sh[0], sh[1], sh[2], sh[3], sh[4], sh[5], sh[6] = sw, self.pos, self.vel, self.ferr, din or 0, t, self.cycles
        if self.tracing:
            self.samples.put((t, sw, self.pos, self.vel, self.ferr, int(self._target), self._profile is not None))

    def _wait_cycles(self, n=1):
        """Until ``n`` more cycles went out (the last outputs are on the bus); the bus's time then."""
        with self._sent:
            target = self._cycle_no + n
            deadline = time.monotonic() + max(1.0, 20 * n * self.period)
            while self._cycle_no < target and self._run:
                if not self._sent.wait(max(0.0, deadline - time.monotonic())):
                    raise JigError("the EtherCAT cycle stopped: no frame went out on %s" % self.ifname)
        return self.t_bus

    def _on_emcy(self, e):
        self.emcys.append(Emcy(self.t_bus, e.error_code, e.error_reg))

    # --- object access by SDO ---------------------------------------------------------------------
    def _var(self, index, sub):
        obj = self.od.get(index) if hasattr(self.od, "get") else None
        if obj is None:
            return None
        try:
            return obj if not hasattr(obj, "subindices") else obj[sub]
        except KeyError:
            return None

    def read(self, index, sub=0):
        t0 = time.monotonic()
        import pysoem

        try:
            with self._lock:
                raw = self.slave.sdo_read(index, sub)
        except pysoem.SdoError as exc:
            raise SdoRefused("slave %d refused the SDO read of 0x%04X:%02X: abort %s" % (
                self.position_on_line, index, sub, cia301.abort_text(exc.abort_code)), exc.abort_code) from None
        except (pysoem.WkcError, pysoem.PacketError, pysoem.MailboxError) as exc:
            raise JigError("slave %d did not answer the SDO read of 0x%04X:%02X (%s)"
                           % (self.position_on_line, index, sub, type(exc).__name__)) from None
        finally:
            self.bus_seconds += time.monotonic() - t0
        var = self._var(index, sub)
        return var.decode_raw(raw) if var is not None else int.from_bytes(raw, "little")

    def write(self, index, sub, value):
        t0 = time.monotonic()
        import pysoem

        var = self._var(index, sub)
        if var is None:
            raise JigError("0x%04X:%02X is not in the drive's object dictionary: its type is unknown" % (index, sub))
        try:
            with self._lock:
                self.slave.sdo_write(index, sub, var.encode_raw(value))
        except pysoem.SdoError as exc:
            raise SdoRefused("slave %d refused the SDO write of 0x%04X:%02X = %r: abort %s" % (
                self.position_on_line, index, sub, value, cia301.abort_text(exc.abort_code)), exc.abort_code) from None
        except (pysoem.WkcError, pysoem.PacketError, pysoem.MailboxError) as exc:
            raise JigError("slave %d did not answer the SDO write of 0x%04X:%02X (%s)"
                           % (self.position_on_line, index, sub, type(exc).__name__)) from None
        finally:
            self.bus_seconds += time.monotonic() - t0
        return self.t_bus

    # --- what the steps use --------------------------------------------------------------------------
    def identify(self):
        return cia301_identity(self.read)

    def line(self):
        """Every slave of the line: position, name, identity, AL state and status code."""
        self.master.read_state()
        return [{"position": i, "name": sl.name, "vendor": "0x%08X" % sl.man, "product": "0x%08X" % sl.id,
                 "revision": "0x%08X" % sl.rev, "state": {1: "INIT", 2: "PRE-OP", 4: "SAFE-OP", 8: "OP"}.get(
                     sl.state & 0x0F, "0x%02X" % sl.state) + (" + error" if sl.state & 0x10 else ""),
                 "al_status": "0x%04X" % sl.al_status} for i, sl in enumerate(self.master.slaves)]

    def emcy_list(self):
        return [(e.t, e.code, e.register) for e in self.emcys]

    def info(self):
        """What the station keeps of the line once it is in OP."""
        return {"identity": self.identity, "dc": self.dc, "period": self.period}

    def sync(self, on):
        """Sampling on or off (the cycle runs either way)."""
        self.tracing = on

    def controlword(self, value):
        """The controlword from the next cycle on; the bus's time of that cycle."""
        self._cw = value
        return self._wait_cycles(1)

    def read_statusword(self):
        return self.sw

    def state(self):
        return power402.state_of(self.sw)

    def go(self, target):
        done = []
        now = self.state()
        if now == power402.FAULT_REACTION:
            now = self._wait_state(power402.FAULT, 0)[0]
        option = self.read(0x605A) if target == power402.OPERATION_ENABLED and now == power402.QUICK_STOP_ACTIVE else None
        for cw, expected in power402.path(now, target, option):
            if expected == power402.OPERATION_ENABLED:
                self._profile = None
                self._target = self.pos  # CSP: the demand starts where the shaft is
                self._mode = MODE_CSP
            n0 = len(self.sw_log)
            t_cmd = self.controlword(cw)
            state, t = self._wait_state(expected, n0)
            if state != expected:
                raise JigError("slave %d: controlword 0x%04X did not take it to %s (it is in %s)"
                               % (self.position_on_line, cw, expected, state))
            done.append((cw, expected, max(0.0, round(t - t_cmd, 4)) if t is not None and t_cmd is not None else None))
        return done

    def _wait_state(self, expected, n0):
        deadline = time.monotonic() + STATE_TIMEOUT_S
        while True:
            for t, sw in self.sw_log[n0:]:
                if power402.state_of(sw) == expected:
                    return expected, t
            if time.monotonic() > deadline:
                return self.state(), None
            self._wait_cycles(1)

    def enable(self, on):
        steps = self.go(power402.OPERATION_ENABLED if on else power402.SWITCH_ON_DISABLED)
        return {"state": self.state(), "transitions": steps}

    def fault_reset(self):
        if self.state() in (power402.FAULT, power402.FAULT_REACTION):
            return self.go(power402.SWITCH_ON_DISABLED)
        return []

    def fault(self):
        return self.read(0x603F) if self.sw & SW_FAULT else 0

    def position(self):
        return self.pos

    def move(self, target, speed, accel=None, decel=None, relative=False):
        """A CSP move to ``target``: the station's trapezoid, one target a cycle; the bus's time of its
        first cycle."""
        # the drive's profile objects get the step's values, as a profile move writes them on CAN: its halt
        # and the station's halt ramp then use the deceleration of the moves before
        if accel is not None:
            self.write(0x6083, 0, accel)
        if decel is not None:
            self.write(0x6084, 0, decel)
        acc = accel or self.read(0x6083)
        dec = decel or self.read(0x6084)
        start = self._target
        if relative:
            target += start
        total, at = trapezoid(target - start, speed, acc, dec)
        self._mode = MODE_CSP
        if self._cw & 0x0100:
            self._cw &= ~0x0100  # no halt
        with self._sent:
            self._profile = (start, self._cycle_no + 1, total, at)
        return self._wait_cycles(1)

    def halt(self):
        """Stop the motion along the deceleration 0x6084 (the station owns the CSP trajectory)."""
        dec = self.read(0x6084)
        v = self.vel
        d = v * abs(v) / (2.0 * dec) if dec else 0.0
        start = self._target
        total, at = trapezoid(int(round(d)), max(1, abs(v)), 10 ** 12, dec) if d else (0.0, lambda t: 0.0)
        with self._sent:
            self._profile = (start, self._cycle_no + 1, total, at) if d else None
        return self._wait_cycles(1)

    def quick_stop(self):
        self._profile = None
        self._target = self.pos
        return self.controlword(power402.COMMANDS[power402.QUICK_STOP])

    def wait_target_reached(self, timeout):
        """In CSP the drive has no target of its own: reached once the profile is done, the shaft within
        the position window 0x6067 of the last target and no following error (bit 13)."""
        window = self.read(0x6067)
        deadline = time.monotonic() + timeout
        while True:
            if self._profile is None and abs(self._target - self.pos) <= window and not self.sw & 0x2000:
                return True
            if time.monotonic() > deadline:
                return False
            self._wait_cycles(1)

    def home(self, method, speed_switch=None, speed_zero=None, accel=None):
        self.write(0x6098, 0, method)
        if speed_switch is not None:
            self.write(0x6099, 1, speed_switch)
        if speed_zero is not None:
            self.write(0x6099, 2, speed_zero)
        if accel is not None:
            self.write(0x609A, 0, accel)
        self._profile = None
        self._mode = MODE_HOMING
        self.controlword(0x0F)
        self._wait_cycles(2)
        return self.controlword(0x1F)

    def inputs(self):
        return self.din if self.din is not None else self.read(0x60FD)

    def bus_health(self):
        median, p99 = self._percentile(0.5), self._percentile(0.99)
        return {"realtime": self.realtime, "cycles": self.cycles, "frames_lost": self.frames_lost,
                "wkc_errors": self.wkc_errors,
                "late_cycles": self.late_cycles, "late_max_ms": round(self.late_max_ms, 3),
                "late_ms_total": round(self.late_ms_total, 3),
                "period_median_ms": median, "period_p99_ms": p99, "period_max_ms": round(self.period_max_ms, 4),
                "cycle_ms": self.period * 1000.0}

    def _percentile(self, q):
        """The period (ms, to the histogram's bin) that a share ``q`` of all periods stayed within."""
        n = sum(self.periods)
        if not n:
            return 0.0
        seen, want = 0, q * n
        for i, count in enumerate(self.periods):
            seen += count
            if seen >= want:
                return round((i + 1) * HIST_US / 1000.0, 4)
        return round(self.period_max_ms, 4)

    def make_safe(self, emergency=False):
        """Quick stop, then disable voltage, through the process data; each tried whatever the other did."""
        problems = []
        self._profile = None
        self._target = self.pos
        for what, cw in (("quick stop", power402.COMMANDS[power402.QUICK_STOP]),
                         ("disable voltage", power402.COMMANDS[power402.DISABLE_VOLTAGE])):
            try:
                self.controlword(cw)
                self._wait_cycles(5)
            except Exception as exc:
                problems.append("%s: %s" % (what, exc))
        return problems

    def close(self):
        """Disable the drive, take the line to INIT (its slaves' mailboxes and outputs off), stop the
        cycle, close the interface."""
        m = self.master
        if m is None:
            return
        try:
            if self._run:
                self._profile = None
                self._cw = power402.COMMANDS[power402.DISABLE_VOLTAGE]
                self._wait_cycles(5)
        except JigError:
            pass
        import pysoem

        self._run = False
        if self._thread is not None:
            self._thread.join(2.0)
        try:
            m.state = pysoem.INIT_STATE
            m.write_state()
        except Exception:
            pass
        m.close()
        self.master = None


def _realtime():
    """The calling thread ahead of the PC's ordinary work when allowed (root: nice -15), not on a
    real-time class: SOEM spins while it waits for a frame, and a real-time spinner would starve the
    kernel's own packet work on its core (frames then come back milliseconds late)."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), NICE)
        return True
    except (AttributeError, PermissionError, OSError):
        return False


def _error(exc):
    return ("error", type(exc).__name__, str(exc), getattr(exc, "code", None))


def serve(conn, samples, shared, ifname, position, eds, cycle_s):
    """The master process: open the line, answer ``(method, args)`` requests on ``conn`` until
    ``close`` or the station's process is gone (then make the drive safe first)."""
    import sys

    from motorjig.station.kind_cia402 import object_dictionary

    # The cycle thread waits for the interpreter whenever this process's other thread (the requests)
    # runs Python: hand it over every 0.2 ms, not every 5.
    sys.setswitchinterval(0.0002)
    m = EcatMaster(ifname, position, object_dictionary(eds), cycle_s, samples, shared)
    try:
        m.open()
    except Exception as exc:
        conn.send(_error(exc))
        m.close()
        return
    conn.send(("ok", m.info()))
    while True:
        try:
            name, args = conn.recv()
        except (EOFError, OSError):  # the station's process died: the drive is made safe, the line closed
            m.make_safe(True)
            m.close()
            return
        if name == "close":
            m.close()
            conn.send(("ok", None))
            return
        try:
            conn.send(("ok", getattr(m, name)(*args)))
        except Exception as exc:
            conn.send(_error(exc))
