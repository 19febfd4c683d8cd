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
