"""The Desk's axes: one interface for every way the Desk reaches drives, whatever their protocol.

The page's STOP AXIS and EMERGENCY STOP go over every axis; the Test tab borrows, for a run, the
ports its plan's drive kind needs (``DriveKind.ports``) from the axis that holds each one. An
axis is the bus session (the jig's PC port, ``session.BusSession.desk_axis``) or a tab's own link
(the CAN tab's SLCAN port, ``canlink.CanLink.desk_axis``); a new drive kind's tab adds one to
the list the Desk is built with and the page, STOP and the Test tab need no change.
"""


class DeskAxis:
    """What the page and the Test tab ask of an axis. ``title`` names it in sentences; ``run_port``
    is the run's port keyword it lends (a ``DriveKind.ports`` key), "" when it lends none."""

    title = ""
    run_port = ""

    def present(self):
        """Is it there to stop now (its port open)?"""
        return True

    def stop(self, emergency):
        """STOP AXIS (``emergency`` False) or EMERGENCY STOP: a sentence of what it stopped, None
        when it had nothing to stop. Never waits for a command in progress."""
        return None

    def status(self):
        """Its state in a few words (open, closed, lent to ...)."""
        return ""

    def lend(self, who):
        """Give the port to ``who`` (a test run) until ``take_back``: the run's port value. The
        axis is made safe and its port closed first; raise ``session.UserError`` with the reason
        when it cannot be lent."""
        raise NotImplementedError

    def take_back(self):
        """After the run: reopen the port as it was before ``lend``; a sentence of a problem, or ""."""
        return ""


class LinkAxis(DeskAxis):
    """A tab's own link (a port it opens and closes) as an axis: ``lend`` closes the link (its axis made
    safe first) and marks it lent; ``take_back`` opens it again as it was. A subclass says what it lends
    (``port``), the sentence when it has none (``missing``), the exception a refusal is (``refusal``: the
    Desk's ``session.UserError``) and how to open it again (``reopen_with``, ``reopen``); the link has ``is_open``, ``state``, ``read_only``, ``lent``, ``summary()``, ``close()``."""

    missing = ""
    refusal = Exception

    def __init__(self, link):
        self.link = link
        self._reopen = None

    def present(self):
        return self.link.is_open

    def status(self):
        return self.link.summary()

    def port(self):
        raise NotImplementedError

    def reopen_with(self):
        """What ``reopen`` needs to open the link again, or None when it was not open."""
        raise NotImplementedError

    def reopen(self, how):
        raise NotImplementedError

    def lend(self, who):
        link = self.link
        if not self.port():
            raise self.refusal(self.missing)
        if link.read_only:
            raise self.refusal("refused: this Desk is read-only (--read-only)")
        self._reopen = self.reopen_with()
        if link.state != "closed":
            link.close()  # the axis is quick-stopped and disabled first
        link.lent = who
        return self.port()

    def take_back(self):
        how, self._reopen = self._reopen, None
        self.link.lent = ""
        if how is None:
            return ""
        try:
            self.reopen(how)
        except Exception as exc:
            return "%s could not be opened again after the run: %s" % (self.title, exc)
        return ""


def lend_ports(axes, needed, who):
    """Borrow each port of ``needed`` ((key, option, what) of a drive kind) from the axis of
    ``axes`` that holds it: ({key: value} for the run, the axes lent, to give back). ``LookupError``
    with the reason when an axis for a port is missing; what ``lend`` raises otherwise (the ports
    already borrowed are given back first)."""
    by_port = {a.run_port: a for a in axes if a.run_port}
    kw, lent = {}, []
    try:
        for key, option, what in needed:
            axis = by_port.get(key)
            if axis is None:
                raise LookupError("its drive is on %s: start the Desk with %s" % (what, option))
            kw[key] = axis.lend(who)
            lent.append(axis)
    except BaseException:
        give_back(lent)
        raise
    return kw, lent


def give_back(lent):
    """``take_back`` on every lent axis, even when one fails: the sentences of their problems."""
    problems = []
    for axis in lent:
        try:
            said = axis.take_back()
        except Exception as exc:  # the others still get their ports back
            said = "%s could not be taken back: %s" % (axis.title, exc)
        if said:
            problems.append(said)
    return problems
