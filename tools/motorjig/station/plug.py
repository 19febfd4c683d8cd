"""The OpenHTF plug of the MotorJig bus: one ``motorjig.master.Master`` for a test's phases.

Public API: a user's own OpenHTF script can use it beside its own plugs::

    import openhtf as htf
    from openhtf.util import configuration
    from motorjig.station import MotorJigPlug

    configuration.CONF.load(motorjig_port="socket://127.0.0.1:5000", motorjig_slave=2)

    @htf.plug(bus=MotorJigPlug)
    def my_phase(test, bus):
        bus.master.servo_enable(bus.slave, True)

Configuration (OpenHTF ``CONF`` keys): ``motorjig_port`` (serial port or pyserial
URL), ``motorjig_baud``, ``motorjig_slave`` (the drive under test), ``motorjig_jig_id``,
``motorjig_timeout_ms``, ``motorjig_on_end`` ("stop-servo-off" or "none"),
``motorjig_safety_window_ms`` (the jig's safety net, below; 0: not armed). Each
slave's protocol variant -- the jig's and the drive's, each its own -- is detected at
first contact, as the vendor library does.

Safety lives in ``tearDown``, which OpenHTF runs at the end of every test, passed,
failed, errored or aborted: unless ``on_end`` is "none", a test that did not pass
(``note_failure`` / ``note_abort``, which the MotorJig phases call) ends with
MoveStop -- EmergencyStop after an abort -- and servo off. A lost connection makes
that impossible; tearDown then says so in the log and gives up quietly.

What no handler can catch (SIGKILL, a crashed PC, a pulled USB cable, a hung adapter)
is caught by the jig: ``arm_safety_net`` switches on the jig's master-silence safety
stop (parameters 9 ``safety_timeout_ms`` and 10 ``safety_action``, docs/diagnostics.md)
for the length of the run, and a heartbeat thread keeps the PC's side of it alive
during prompts and long waits (a cheap GetParameter to the jig whenever the bus has
been quiet for a quarter of the window). If the PC falls silent for the window, the
jig stops every drive it has seen (EmergencyStop, and servo off with
``on_end = "stop-servo-off"``). tearDown puts the jig's parameters back as they were.
"""

import logging
import threading
import time

from openhtf import plugs
from openhtf.util import configuration

from jig.params import P_CAN_SAFETY, P_SAFETY_ACTION, P_SAFETY_TIMEOUT_MS
from jig.safety import ACTION_EMERGENCY_STOP, ACTION_EMERGENCY_STOP_SERVO_OFF, CAN_SAFETY_QUICK_STOP
from motorjig.errors import JigError
from motorjig.master import Master
from motorjig.station import kinds

CONF = configuration.CONF
_LOG = logging.getLogger(__name__)

for _name, _doc, _default in (
        ("motorjig_port", "serial port or pyserial URL of the MotorJig bus", None),
        ("motorjig_baud", "baud rate of the bus", 115200),
        ("motorjig_slave", "slave id of the drive under test", 2),
        ("motorjig_jig_id", "slave id of the jig", 1),
        ("motorjig_timeout_ms", "reply timeout, ms", 100),
        ("motorjig_on_end", "stop-servo-off or none: what a test that did not pass does to the axis",
         "stop-servo-off"),
        ("motorjig_safety_window_ms", "the jig's master-silence safety stop during a run, ms (0: not armed)",
         1000),
        ("motorjig_protocol", "the drive's kind, an entry of the table of kinds (station.kinds)", kinds.DEFAULT),
        ("motorjig_can_port", "the jig's SLCAN port (device or pyserial URL) of a CiA 402 drive", None),
        ("motorjig_node_id", "the CiA 402 drive's node id", 5),
        ("motorjig_bitrate", "the CAN bitrate, bit/s", 500000),
        ("motorjig_eds", "the CiA 402 drive's EDS (default: the one the project ships)", None),
        ("motorjig_lss", "the plan gives the CiA 402 drive its node id (an lss step): do not ask for it at start",
         False),
        ("motorjig_slot", "a slot's run: the slot's name (station.slots; None: not a slot)", None),
        ("motorjig_master", "a slot's run: the jig's connection the slots share (a TimedMaster; None: the run's own)",
         None),
        ("motorjig_links", "a slot's run: the connections the slots share on a kind's own port (station.slots.Links)",
         None),
        ("motorjig_port_share", "a slot's run: how many slots of its kind run at once (they share its port)", 1),
        ("motorjig_safety_shared", "a slot's run: the slots' one SharedSafetyNet (None: the run's own SafetyNet)",
         None)):
    if _name not in CONF._declarations:  # a re-import (tests) must not declare twice
        CONF.declare(_name, _doc, default_value=_default)


class TimedMaster(Master):
    """A Master that keeps every request's round-trip time (seconds) for bus-health, and that
    two threads may share (the phases and the safety net's heartbeat): one request at a time."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self._roundtrips = threading.local()
        self.lock = threading.RLock()
        self.last_request = time.monotonic()  # when the PC last spoke, for the heartbeat

    def request(self, *a, **kw):
        with self.lock:
            t0 = self.last_request = time.monotonic()
            try:
                fr = super().request(*a, **kw)
            finally:
                self.last_request = time.monotonic()
            self.roundtrips.append(time.monotonic() - t0)
            return fr

    @property
    def roundtrips(self):
        """This thread's round trips: the runs of several slots share one master, each keeps its own."""
        rts = getattr(self._roundtrips, "list", None)
        if rts is None:
            rts = self._roundtrips.list = []
        return rts

    def detect_variant(self, *a, **kw):
        with self.lock:
            self.last_request = time.monotonic()
            return super().detect_variant(*a, **kw)

    def broadcast(self, *a, **kw):
        with self.lock:
            self.last_request = time.monotonic()
            return super().broadcast(*a, **kw)


class SafetyNet:
    """The jig's master-silence safety stop, armed for one run, with a heartbeat thread.

    ``arm()`` remembers the jig's parameters 9 and 10, sets the window and the action and
    starts the heartbeat; ``disarm()`` stops it and restores them. Either raises JigError
    when the jig does not answer (the caller decides what that means for the run). Each CiA 402
    drive of the run (``can_drive``, ``add_can_drive``) arms the jig's CAN safety stop too
    (parameter 18) and has its port's silence window kept open by the heartbeat."""

    def __init__(self, master, jig_id, window_ms, servo_off, can_drive=None):
        self.m = master
        self.can_drives = [can_drive] if can_drive is not None else []
        self.jig_id = jig_id
        self.window_ms = int(window_ms)
        self.action = ACTION_EMERGENCY_STOP_SERVO_OFF if servo_off else ACTION_EMERGENCY_STOP
        self.saved = None
        self._stop = threading.Event()
        self._thread = None

    def arm(self):
        m, j = self.m, self.jig_id
        saved = (m.get_parameter(j, P_SAFETY_TIMEOUT_MS), m.get_parameter(j, P_SAFETY_ACTION))
        try:
            m.set_parameter(j, P_SAFETY_ACTION, self.action)
        except JigError:
            # A jig from before "servo off" (action 2): EmergencyStop alone still stops the axis.
            self.action = ACTION_EMERGENCY_STOP
            m.set_parameter(j, P_SAFETY_ACTION, self.action)
        self.saved = saved  # from here on disarm() has something to put back
        if self.can_drives:
            self._arm_can()
        self.stops_before = self.stops()
        m.set_parameter(j, P_SAFETY_TIMEOUT_MS, self.window_ms)
        self._stop.clear()
        self._thread = threading.Thread(target=self._beat, name="motorjig-heartbeat", daemon=True)
        self._thread.start()

    def _arm_can(self):
        if self.saved is not None and len(self.saved) == 2:
            m, j = self.m, self.jig_id
            self.saved += (m.get_parameter(j, P_CAN_SAFETY),)
            m.set_parameter(j, P_CAN_SAFETY, CAN_SAFETY_QUICK_STOP)

    def add_can_drive(self, drive):
        """A CiA 402 drive joins an armed net (a slot's run that starts after another's)."""
        self.can_drives.append(drive)
        self._arm_can()

    def remove_can_drive(self, drive):
        if drive in self.can_drives:
            self.can_drives.remove(drive)

    def _beat(self):
        period = self.window_ms / 4000.0
        while not self._stop.wait(period / 2):
            for d in list(self.can_drives):
                if time.monotonic() - d.last_sent >= period:
                    try:
                        d.keep_alive()  # the CAN port's own silence window
                    except Exception:  # a lost connection: the jig's stop will act, which is the point
                        pass
            if time.monotonic() - self.m.last_request < period:
                continue  # the phases keep the jig's window open themselves
            try:
                self.m.get_parameter(self.jig_id, P_SAFETY_TIMEOUT_MS)
            except Exception:  # a lost connection: the jig's stop will act, which is the point
                pass

    def stops(self):
        """The jig's safety_stops counter (it counts every time the silence stop fired)."""
        return self.m.read_counters(self.jig_id).get("safety_stops", 0)

    def fired(self):
        """True when the jig's safety stop has fired since the net was armed: this PC was silent
        for the window, and the jig stopped the axis in the middle of whatever was measured."""
        try:
            return self.stops() != self.stops_before
        except JigError:
            return False

    def stop_heartbeat(self):
        self._stop.set()
        t, self._thread = self._thread, None
        if t is not None and t is not threading.current_thread():
            t.join(2.0)

    def disarm(self):
        self.stop_heartbeat()
        if self.saved is None:
            return
        timeout_ms, action = self.saved[:2]
        self.m.set_parameter(self.jig_id, P_SAFETY_TIMEOUT_MS, timeout_ms)
        self.m.set_parameter(self.jig_id, P_SAFETY_ACTION, action)
        if len(self.saved) > 2:
            self.m.set_parameter(self.jig_id, P_CAN_SAFETY, self.saved[2])
        self.saved = None


class SharedSafetyNet:
    """One SafetyNet for the runs of several slots on one jig (multi-up): the first run to join arms
    the jig, the last to leave disarms it, so a slot that ends early never leaves the others'
    axes unguarded. ``join``/``leave`` are what a run's plug calls in place of arm/disarm."""

    def __init__(self, master, jig_id, window_ms, servo_off):
        self.net = SafetyNet(master, jig_id, window_ms, servo_off)
        self.window_ms = self.net.window_ms
        self._users = 0
        self._lock = threading.Lock()

    def join(self, can_drive=None):
        with self._lock:
            if self._users == 0:
                if can_drive is not None:
                    self.net.can_drives.append(can_drive)
                self.net.arm()
            elif can_drive is not None:
                self.net.add_can_drive(can_drive)
            self._users += 1
            return self.net

    def leave(self, can_drive=None):
        with self._lock:
            if can_drive is not None:
                self.net.remove_can_drive(can_drive)
            self._users -= 1
            if self._users == 0:
                self.net.disarm()


class MotorJigPlug(plugs.BasePlug):
    """The bus, the drive under test (``slave``; ``drive``: the station.drive interface to it) and
    the jig (``jig_id``). ``kind``: the drive's kind (``motorjig_protocol``), which opens the drive
    (on the jig's PC port, or another of the jig's ports), the jig itself always on ``motorjig_port``."""

    auto_placeholder = True  # each run may substitute its own subclass (for_run)

    # A run's own settings (``for_run``): what it sets here wins over CONF, so the runs of several
    # slots in one process each have their own drive, and share the jig's connection and safety net.
    settings = {}

    def __init__(self):
        shared = self.conf("motorjig_master")  # a slot's run: the jig's connection is the slots' (not closed here)
        if shared is None and not self.conf("motorjig_port"):
            raise JigError("no port: set motorjig_port (jigctl test --port ...)")
        self._own_master = shared is None
        self.master = shared or TimedMaster(self.conf("motorjig_port"), baud=self.conf("motorjig_baud"),
                                            timeout=self.conf("motorjig_timeout_ms") / 1000.0)
        self.protocol = self.conf("motorjig_protocol")
        self.kind = kinds.get(self.protocol)
        try:
            self.drive = self.kind.open_drive(self)
        except BaseException:
            self._close_master()
            raise
        self.slave = self.conf("motorjig_slave")
        self.jig_id = self.conf("motorjig_jig_id")
        self.on_end = self.conf("motorjig_on_end")
        self.failed = False
        self.aborted = False
        self.safety = None  # the SafetyNet while armed (arm_safety_net)
        self.trace_period_us = None  # the jig samples the moving steps at this period (None: this PC does)

    @classmethod
    def for_run(cls, settings, name="run"):
        """A subclass of this plug with ``settings`` ({CONF key: value}) of its own (OpenHTF keys
        plugs by class: each run's phases get theirs with ``with_plugs(bus=...)``)."""
        return type("MotorJigPlug_%s" % name, (cls,), {"settings": dict(settings)})

    def conf(self, name):
        """A setting of this run: its own (``for_run``), else OpenHTF's CONF."""
        if name in self.settings:
            return self.settings[name]
        return getattr(CONF, name)

    def _close_master(self):
        if self._own_master:
            self.master.close()

    def note_failure(self):
        self.failed = True

    def note_abort(self):
        self.aborted = True

    def arm_safety_net(self, window_ms=None):
        """Arm the jig's master-silence safety stop for this run (see the module's doc); returns the
        SafetyNet, or None when ``window_ms`` (default: CONF) is 0. Raises JigError if the jig
        does not take it."""
        shared = self.conf("motorjig_safety_shared") if window_ms is None else None
        if shared is not None:  # the slots' one net: joined here, left in tearDown
            self._can_drive = self.kind.safety_net_kw(self).get("can_drive")
            self.safety = shared.join(self._can_drive)
            self._shared_safety = shared
            return self.safety
        window_ms = self.conf("motorjig_safety_window_ms") if window_ms is None else window_ms
        if not window_ms:
            return None
        net = SafetyNet(self.master, self.jig_id, window_ms, servo_off=self.on_end != "none",
                        **self.kind.safety_net_kw(self))
        self.safety = net
        net.arm()
        return net

    def _disarm(self):
        shared = getattr(self, "_shared_safety", None)
        if shared is not None:
            self._shared_safety = None
            shared.leave(self._can_drive)
        elif self.safety is not None:
            self.safety.disarm()

    def tearDown(self):
        try:
            if self.on_end != "none" and (self.failed or self.aborted):
                self.make_safe(emergency=self.aborted)
            elif self.on_end != "none" and self.kind.disable_at_end:
                self._disable()  # (a CiA 402 run always ends with the operation disabled)
        finally:
            try:
                self.drive.close()
            except Exception as exc:
                _LOG.error("closing the drive's connection failed: %s", exc)
            try:
                try:
                    self._disarm()
                except Exception as exc:  # the jig's window stays: it stops the axis when we are gone
                    _LOG.error("disarming the jig's safety stop failed: %s", exc)
            finally:
                self._close_master()

    def _disable(self):
        try:
            self.drive.enable(False)
        except Exception as exc:  # the gentle way failed: quick stop and disable voltage
            _LOG.error("disabling the drive failed: %s", exc)
            self.make_safe(emergency=True)

    def make_safe(self, emergency=False):
        """Stop the axis and switch it off (Plus-R: MoveStop/EmergencyStop and servo off; CiA 402:
        quick stop and disable voltage); the problems met, as texts."""
        return self.drive.make_safe(emergency)


def make_safe(m, s, emergency=False):
    """Stop the axis and switch the servo off, trying each action whatever the one before did:
    MoveStop and a wait for standstill (EmergencyStop when that fails, or at once if
    ``emergency``), then servo off. Returns the problems met, as texts (also logged)."""
    problems = []

    def attempt(what, fn, *args):
        try:
            fn(*args)
            return True
        except Exception as exc:  # a garbled reply, a timeout, a closed port: try the next action anyway
            problems.append("%s: %s" % (what, exc))
            _LOG.error("making the axis safe, %s failed: %s", what, exc)
            return False

    stopped = False
    if not emergency:
        stopped = attempt("MoveStop", m.move_stop, s) and attempt("waiting for standstill", m.wait_motion_done, s, 5.0)
    if not stopped:
        attempt("EmergencyStop", m.emergency_stop, s)
    attempt("servo off", m.servo_enable, s, False)
    if not problems:
        _LOG.info("axis stopped (%s) and servo off", "MoveStop" if stopped else "EmergencyStop")
    return problems
