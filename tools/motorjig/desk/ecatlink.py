"""The Desk's EtherCAT line: one per Desk server, shared by every browser tab (the EtherCAT tab's work).

``EcatLink`` opens an EtherCAT line from this PC's network interface with the station's own master
(``station.drive_ecat.EcatDrive``: SOEM in a process of its own, the cycle at 1 ms) for one slave
of the line, takes it to OP, and offers what the tab shows: the slaves and their AL states, SDO
reads and writes, and the slave's CiA 402 axis (enable, disable, fault reset, CSP moves, halt,
quick stop). ``desk_axis`` is its ``axes.DeskAxis``: the header's STOP and EMERGENCY STOP reach the
axis, and a plan with ``protocol = "ethercat"`` borrows the interface for its run (the axis made
safe and the line closed first; opened again after the run).

Every failure is one sentence (``session.UserError``). It needs root, as every EtherCAT master does.
"""

import os
import threading

from motorjig.can import power402
from motorjig.desk.axes import LinkAxis
from motorjig.desk.session import UserError
from motorjig.errors import JigError

CYCLE_S = 0.001


def _object(text):
    index, _, sub = str(text).strip().partition(":")
    try:
        return int(index, 0), int(sub, 0) if sub else 0
    except ValueError:
        raise UserError("%r is not INDEX[:SUB] (e.g. 0x6041 or 0x1018:1)" % text) from None


class EcatLinkAxis(LinkAxis):
    """The EtherCAT tab's line as one of the Desk's axes."""

    title = "the EtherCAT tab's line"
    run_port = "ecat_ifname"
    missing = ("the EtherCAT interface is not known: start the Desk with --ecat-ifname (or open the line in the "
               "EtherCAT tab)")

    refusal = UserError

    def stop(self, emergency):
        return self.link.stop(emergency)

    def port(self):
        return self.link.ifname

    def reopen_with(self):
        return self.link.position if self.link.is_open else None

    def reopen(self, position):
        self.link.open(self.link.ifname, position)


class EcatLink:
    """See the module's docstring. ``ifname``: the interface (from --ecat-ifname or the tab)."""

    def __init__(self, ifname="", read_only=False):
        self.ifname = ifname
        self.position = 0
        self.read_only = read_only
        self.state = "closed"
        self.reason = ""
        self.lent = ""
        self.drive = None
        self.line = []  # the slaves as the last open or refresh saw them
        self._lock = threading.RLock()
        self.desk_axis = EcatLinkAxis(self)

    @property
    def is_open(self):
        return self.state == "open"

    def summary(self):
        if self.state == "open":
            return "open: %s, slave %d in OP, %g ms cycle" % (self.ifname, self.position, CYCLE_S * 1000)
        if self.lent:
            return "lent to %s" % self.lent
        if self.state == "lost":
            return "line lost: %s" % self.reason
        return "closed"

    def _need(self):
        if self.lent:
            raise UserError("the EtherCAT line is lent to %s: it comes back with its verdict" % self.lent)
        if self.drive is None or self.state != "open":
            raise UserError("open the EtherCAT line first")
        if self.read_only:
            raise UserError("refused: this Desk is read-only (--read-only)")
        return self.drive

    def _call(self, fn, *args):
        try:
            return fn(*args)
        except JigError as exc:
            raise UserError(str(exc)) from None

    # --- the line ----------------------------------------------------------------------------------
    def open(self, ifname=None, position=None):
        """Open the line and take it to OP (a few seconds: SOEM scans, maps and starts the cycle)."""
        from motorjig.station.drive_ecat import EcatDrive

        with self._lock:
            if self.lent:
                raise UserError("the EtherCAT line is lent to %s: it comes back with its verdict" % self.lent)
            if self.read_only:
                raise UserError("refused: this Desk is read-only (--read-only)")
            ifname = (ifname if ifname is not None else self.ifname).strip()
            position = self.position if position is None else int(position)
            if not ifname:
                raise UserError("give the network interface on the EtherCAT line (the bench prints its own: mjmN)")
            if not os.path.exists(os.path.join("/sys/class/net", ifname)):
                raise UserError("no network interface named %s (`ip link` lists them)" % ifname)
            if os.geteuid() != 0:
                raise UserError("an EtherCAT master opens raw sockets: start the Desk as root (sudo)")
            if self.state == "open":
                self.close()
            d = EcatDrive(ifname, position, None, CYCLE_S)
            try:
                d.open()
            except (JigError, OSError) as exc:
                d.close()
                raise UserError(str(exc)) from None
            self.drive, self.ifname, self.position, self.state, self.reason = d, ifname, position, "open", ""
            self.line = self._call(d.line)
            return "%s open: slave %d (%s) in OP" % (ifname, position, d.identity.get("name") or "?")

    def close(self):
        """Quick stop and disable the axis, take the line to INIT, stop the cycle."""
        with self._lock:
            d, self.drive = self.drive, None
            self.state = "closed"
            if d is not None:
                d.make_safe(True)
                d.close()
            return "EtherCAT line closed"

    def slaves(self):
        """[{position, name, vendor, product, revision, state, al_status}] of the line."""
        d = self.drive
        if d is not None and self.state == "open":
            try:
                self.line = d.line()
            except JigError as exc:
                self.state, self.reason = "lost", str(exc)
        return self.line

    # --- objects --------------------------------------------------------------------------------------
    def sdo_read(self, obj):
        index, sub = _object(obj)
        d = self.drive if self.state == "open" else self._need()
        value = self._call(d.read, index, sub)
        return "0x%04X:%02X = %s" % (index, sub, "0x%X (%d)" % (value, value) if isinstance(value, int) else repr(value))

    def sdo_write(self, obj, value):
        index, sub = _object(obj)
        d = self._need()
        try:
            v = int(str(value).strip(), 0)
        except ValueError:
            raise UserError("%r is not a number (decimal, or 0x hex)" % value) from None
        self._call(d.write, index, sub, v)
        return "0x%04X:%02X = %d written" % (index, sub, v)

    # --- the axis ---------------------------------------------------------------------------------------
    def status(self):
        """{state, statusword, position} of the axis, or None when the line is not open."""
        d = self.drive
        if d is None or self.state != "open":
            return None
        sw = d.read_statusword()
        return {"state": power402.state_of(sw) or "?", "statusword": sw, "position": d.position()}

    def enable(self):
        got = self._call(self._need().enable, True)
        return "slave %d: %s" % (self.position, got["state"])

    def disable(self):
        got = self._call(self._need().enable, False)
        return "slave %d: %s" % (self.position, got["state"])

    def fault_reset(self):
        d = self._need()
        self._call(d.fault_reset)
        return "slave %d: %s" % (self.position, d.state())

    def move(self, target, speed):
        d = self._need()
        try:
            target, speed = int(str(target), 0), int(str(speed), 0)
        except ValueError:
            raise UserError("target and speed are whole numbers of counts and counts/s") from None
        if speed <= 0:
            raise UserError("the speed must be above 0 counts/s")
        if d.state() != power402.OPERATION_ENABLED:
            raise UserError("slave %d is in %s: press Enable first" % (self.position, d.state()))
        self._call(d.move, target, speed)
        return "slave %d: CSP move to %d at %d counts/s" % (self.position, target, speed)

    def stop(self, emergency=False):
        """Halt (the station's ramp along 0x6084) or, for an emergency, quick stop; None when the line is
        not open (nothing to stop)."""
        d = self.drive
        if d is None or self.state != "open" or self.read_only:
            return None
        if emergency:
            self._call(d.quick_stop)
            return "slave %d: quick stop" % self.position
        self._call(d.halt)
        return "slave %d: halt" % self.position


def make_link(ifname="", read_only=False):
    """(EcatLink, None), or (None, the sentence) when pysoem is missing."""
    try:
        import pysoem  # noqa: F401
    except ImportError:
        return None, "the EtherCAT tab needs pysoem: pip install the [ecat] extra (make setup)"
    return EcatLink(ifname, read_only=read_only), None
