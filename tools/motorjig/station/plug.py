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
``motorjig_timeout_ms``, ``motorjig_on_end`` ("stop-servo-off" or "none"). Each
slave's protocol variant is detected at first contact, as the vendor library does.

Safety lives in ``tearDown``, which OpenHTF runs at the end of every test, passed,
failed, errored or aborted: unless ``on_end`` is "none", a test that did not pass
(``note_failure`` / ``note_abort``, which the MotorJig phases call) ends with
MoveStop -- EmergencyStop after an abort -- and servo off. A lost connection makes
that impossible; tearDown then says so in the log and gives up quietly.
"""

import logging
import time

from openhtf import plugs
from openhtf.util import configuration

from motorjig.errors import JigError
from motorjig.master import Master

CONF = configuration.CONF
_LOG = logging.getLogger(__name__)

for _name, _doc, _default in (
        ("motorjig_port", "serial port or pyserial URL of the MotorJig bus", None),
        ("motorjig_baud", "baud rate of the bus", 115200),
        ("motorjig_slave", "slave id of the drive under test", 2),
        ("motorjig_jig_id", "slave id of the jig", 1),
        ("motorjig_timeout_ms", "reply timeout, ms", 100),
        ("motorjig_on_end", "stop-servo-off or none: what a test that did not pass does to the axis",
         "stop-servo-off")):
    if _name not in CONF._declarations:  # a re-import (tests) must not declare twice
        CONF.declare(_name, _doc, default_value=_default)


class TimedMaster(Master):
    """A Master that keeps every request's round-trip time (seconds) for bus-health."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.roundtrips = []

    def request(self, *a, **kw):
        t0 = time.monotonic()
        fr = super().request(*a, **kw)
        self.roundtrips.append(time.monotonic() - t0)
        return fr


class MotorJigPlug(plugs.BasePlug):
    """The bus, the drive under test (``slave``) and the jig (``jig_id``)."""

    def __init__(self):
        if not CONF.motorjig_port:
            raise JigError("no port: set motorjig_port (jigctl test --port ...)")
        self.master = TimedMaster(CONF.motorjig_port, baud=CONF.motorjig_baud,
                                  timeout=CONF.motorjig_timeout_ms / 1000.0)
        self.slave = CONF.motorjig_slave
        self.jig_id = CONF.motorjig_jig_id
        self.on_end = CONF.motorjig_on_end
        self.failed = False
        self.aborted = False

    def note_failure(self):
        self.failed = True

    def note_abort(self):
        self.aborted = True

    def tearDown(self):
        try:
            if self.on_end != "none" and (self.failed or self.aborted):
                self.make_safe(emergency=self.aborted)
        finally:
            self.master.close()

    def make_safe(self, emergency=False):
        make_safe(self.master, self.slave, emergency)


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
