"""The EtherCAT CiA 402 drive the station's steps speak to: SOEM (pysoem) as the master, CSP at the plan's cycle.

``EcatDrive`` is a ``station.drive.Drive`` with the methods the CiA 402 steps use
(``phases_cia402``): object access by CoE SDO (typed by the drive's object dictionary), the
power state machine by the process data's controlword and statusword, and motion in cyclic
synchronous position (mode 8): the station generates the trapezoid itself and sends one target
a cycle, as an EtherCAT master does. Homing uses mode 6 and its handshake, also through the
process data.

The cycle runs in a process of its own (``ecat_master``: the master, SOEM, the cycle thread),
because a 1 ms cycle cannot share an interpreter with the station's engine; this side sends it
each request and reads the samples and the drive's last statusword and position it shares.
Each sample is dated by the bus's distributed clock, so a PC that runs late does not move a
sample's date; a trace whose cycles went out late or whose frames were lost cannot judge the
drive: the step ends ERROR with the reason (``EcatTrace.check``), never FAIL.

The run's endings: ``make_safe`` quick-stops and disables through the process data; ``close``
disables, takes the line to INIT and ends the master's process. When this process dies, the
master makes the drive safe itself; when both die, the frames stop and the slave's
process-data watchdog stops the drive.
"""

import multiprocessing
import threading
import time

from motorjig.can import power402
from motorjig.errors import JigError, PortError
from motorjig.station.drive import Drive, Emcy, SdoRefused
from motorjig.station.sampling import UntrustedMeasurement, _Sample
from motorjig.station.sampling_cia402 import Cia402Trace, _Axis

OPEN_TIMEOUT_S = 30.0
LATE_BUDGET = 0.01  # the share of a step's time its late cycles may lose before the step cannot judge
LATE_BUDGET_MIN_MS = 3.0
CALL_TIMEOUT_S = 30.0
ERRORS = {"SdoRefused": SdoRefused, "PortError": PortError}


class _EcatAxis(_Axis):
    """A sample's flags: ``motioning`` while the shaft turns or the station's profile still runs."""

    __slots__ = ("profiling",)

    def __init__(self, statusword, velocity, profiling):
        super().__init__(statusword, velocity)
        self.profiling = profiling

    @property
    def motioning(self):
        return self.velocity != 0 or self.profiling


class EcatTrace(Cia402Trace):
    """The drive's samples as the cycle took them (one a cycle, dated by the distributed clock). The
    station makes the profile one target a cycle: cycles the PC sent late stretch it in time. A step
    whose cycles lost more than ``LATE_BUDGET`` of its time, or whose frames were lost, cannot judge
    the drive (ERROR with the reason)."""

    def gap_cause(self):
        return "cycles the PC sent late or frames lost on the bus"

    wait_periods = 20  # the cycle's own process fills the queue: allow it a hiccup

    def _sample(self, item):
        """The command is the target the station sent in that cycle, and the axis counts as moving while the
        station's profile runs (a late cycle halts a CSP drive for a moment: not the end of the move)."""
        t, sw, pos, vel, _ferr, target, profiling = item
        return t, _Sample(target, pos, vel, _EcatAxis(sw, vel, profiling))

    def begin(self, d, s=None):
        self.drive = d
        self.h0 = d.bus_health()
        super().begin(d, s)

    def check(self, t0, t1, floor_hz=None, what="the move"):
        h, h0 = self.drive.bus_health(), self.h0
        late = h["late_cycles"] - h0["late_cycles"]
        late_ms = h["late_ms_total"] - h0["late_ms_total"]
        lost = h["frames_lost"] - h0["frames_lost"]
        short = h["wkc_errors"] - h0["wkc_errors"]
        budget_ms = max(LATE_BUDGET_MIN_MS, LATE_BUDGET * (t1 - t0) * 1000.0)
        if lost or short:
            said = []
            if lost:
                said.append("%d frame%s did not come back" % (lost, "" if lost == 1 else "s"))
            if short:
                said.append("%d came back with a working counter short of the expected" % short)
            raise UntrustedMeasurement("%s cannot be judged: %s, so the drive missed targets of the plan's profile"
                                       % (what, " and ".join(said)))
        if late_ms > budget_ms:
            raise UntrustedMeasurement(
                "%s cannot be judged: %d cycle%s went out late, %.1f ms lost in all (the step allows %.1f ms; the "
                "latest %.1f ms late): the drive followed targets that came late, not the plan's profile"
                % (what, late, "" if late == 1 else "s", late_ms, budget_ms, h["late_max_ms"]))
        super().check(t0, t1, floor_hz, what)


class EcatDrive(Drive):
    """The station's side of the line: every request goes to the master's process (``ecat_master``)."""

    protocol = "ethercat"
    emergency_words = "quick stop, disable voltage"

    def __init__(self, ifname, position, eds, cycle_s=0.001):
        self.ifname, self.position_on_line, self.eds, self.period = ifname, position, eds, cycle_s
        self.label = "slave %d" % position
        self.ready = False
        self.bus_seconds = 0.0
        self.identity, self.dc = {}, False
        self._proc = self._conn = None
        self._lock = threading.Lock()
        ctx = multiprocessing.get_context("spawn")  # a clean interpreter: no threads of this one forked
        self._ctx = ctx
        self.samples = ctx.Queue()
        self._shared = ctx.Array("d", 7, lock=False)

    def open(self):
        ctx = self._ctx
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, name="ecat-master", daemon=True, args=(
            child, self.samples, self._shared, self.ifname, self.position_on_line, self.eds, self.period))
        self._proc.start()
        child.close()
        try:
            info = self._reply(OPEN_TIMEOUT_S, "open the EtherCAT line")
        except BaseException:
            self._ended()  # the master's process ends after saying why it could not open the line
            raise
        self.identity, self.dc = info["identity"], info["dc"]
        self.ready = True

    def _reply(self, timeout, what):
        if not self._conn.poll(timeout):
            raise JigError("the EtherCAT master did not %s within %g s" % (what, timeout))
        try:
            got = self._conn.recv()
        except (EOFError, OSError):
            raise JigError("the EtherCAT master's process ended (exit %s)" % self._proc.exitcode) from None
        if got[0] == "ok":
            return got[1]
        _, kind, message, code = got
        if kind == "SdoRefused":
            raise SdoRefused(message, code)
        if kind == "PortError":
            raise PortError(message)
        if kind == "UntrustedMeasurement":
            raise UntrustedMeasurement(message)
        raise JigError(message if kind == "JigError" else "%s: %s" % (kind, message))

    def _call(self, name, *args):
        if self._conn is None:
            raise JigError("the EtherCAT line is not open")
        t0 = time.monotonic()
        with self._lock:
            try:
                self._conn.send((name, args))
            except (BrokenPipeError, OSError):
                raise JigError("the EtherCAT master's process ended (exit %s)" % self._proc.exitcode) from None
            try:
                return self._reply(CALL_TIMEOUT_S, "answer %s" % name)
            finally:
                # the run's split (motion, bus, engine): waiting for the line (SDOs, a command's cycle)
                self.bus_seconds += time.monotonic() - t0

    # --- what the steps use (phases_cia402, phases_ecat) ---------------------------------------------
    @property
    def emcys(self):
        return [Emcy(*e) for e in self._call("emcy_list")] if self._conn is not None else []

    def line(self):
        """Every slave of the line (``ecat_master.EcatMaster.line``)."""
        return self._call("line")

    def new_trace(self, ctx, step):
        return EcatTrace(ctx, step)

    def read_statusword(self):
        return int(self._shared[0])

    def position(self):
        return int(self._shared[1])

    def state(self):
        return power402.state_of(self.read_statusword())

    def read(self, index, sub=0):
        return self._call("read", index, sub)

    def write(self, index, sub, value):
        return self._call("write", index, sub, value)

    def identify(self):
        return self._call("identify")

    def sync(self, on):
        return self._call("sync", on)

    def controlword(self, value):
        return self._call("controlword", value)

    def enable(self, on):
        return self._call("enable", on)

    def fault_reset(self):
        return self._call("fault_reset")

    def fault(self):
        return self._call("fault")

    def move(self, target, speed, accel=None, decel=None, relative=False):
        return self._call("move", target, speed, accel, decel, relative)

    def halt(self):
        return self._call("halt")

    def quick_stop(self):
        return self._call("quick_stop")

    def wait_target_reached(self, timeout):
        return self._call("wait_target_reached", timeout)

    def home(self, method, speed_switch=None, speed_zero=None, accel=None):
        return self._call("home", method, speed_switch, speed_zero, accel)

    def inputs(self):
        return self._call("inputs")

    def bus_health(self):
        return self._call("bus_health")

    def make_safe(self, emergency=False):
        try:
            return self._call("make_safe", emergency)
        except JigError as exc:
            return [str(exc)]

    def close(self):
        """Disable the drive, the line to INIT, the master's process ended."""
        if self._conn is not None:
            try:
                self._call("close")
            except JigError:
                pass
        self._ended()

    def _ended(self):
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._proc is not None:
            self._proc.join(5.0)
            if self._proc.is_alive():
                self._proc.kill()
            self._proc = None


def _serve(*args):
    from motorjig.station.ecat_master import serve

    serve(*args)
