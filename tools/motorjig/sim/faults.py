"""The faults a simulated drive can be given, whatever protocol it speaks: one table, one parser.

Every simulated drive on the bench (the Plus-R drive, the CiA 402 nodes) takes its faults by
name with ``set_fault(name, value)``, from the command line's ``--fault`` and from tests. The
faults of the shared axis (``AXIS``: lost steps, a slow motor, a dead input, no origin) mean
the same on every drive; each protocol face adds its own (an alarm code, an SDO abort, a CRC
error). A drive's list is a ``FaultTable`` of ``Fault`` entries; the table checks a value the
same way for all of them and says what is wrong in one sentence (``ValueError``).

A ``FaultTable`` reads like the dict the docs and ``--help`` print: name -> (the value it
takes, its default, what it does).
"""

from collections import namedtuple
from collections.abc import Mapping

# name; takes: the value's form in words ("" for a switch); default (None: a value is needed);
# does: what the drive then does; check(value) -> the checked value (ValueError with the reason)
Fault = namedtuple("Fault", "name takes default does check")


def number(value, cast, what):
    """``value`` (a number or its text, as the command line gives it) as ``cast``; ValueError
    saying ``what`` was expected."""
    if isinstance(value, bool):
        raise ValueError("expected %s, got %r" % (what, value))
    try:
        if cast is int and isinstance(value, str):
            text = value.strip()
            return int(text, 16) if text[:2].lower() == "0x" else int(text, 10)
        return cast(value)
    except (TypeError, ValueError):
        raise ValueError("expected %s, got %r" % (what, value)) from None


def in_range(value, cast, what, lo, hi):
    """``number`` that must lie in lo..hi (inclusive; None: open)."""
    v = number(value, cast, what)
    if (lo is not None and v < lo) or (hi is not None and v > hi) or v != v or v in (float("inf"), -float("inf")):
        raise ValueError("expected %s, got %s" % (what, value))
    return v


def switch(name, does):
    """A fault that is on or off and takes no value."""
    return Fault(name, "", None, does, None)


def speed_limit(name, does):
    """The motor loses steps above a speed (counts or pulses per second)."""
    return Fault(name, "PPS", 20000, does, lambda v: in_range(v, int, "a speed in pps > 0", 1, None))


# the faults of the axis every simulated drive shares (sim.axis); the names are the Plus-R
# drive's, a face may give one its own name and keep this one as an alias
SLUGGISH = Fault("sluggish", "FACTOR", 1.5, "every move takes FACTOR times its profile time (the motor runs slow)",
                 lambda v: in_range(v, float, "a factor >= 1", 1.0, None))
DEAD_INPUT_CHECK = (lambda v: in_range(v, int, "an input bit 0..31", 0, 31))


def dead_input(where):
    return Fault("dead-input", "BIT", None, "a broken wire: %s BIT (0..31) always reads 0 (repeatable)" % where,
                 DEAD_INPUT_CHECK)


class FaultTable(Mapping):
    """A drive's faults by name (``Fault`` entries), with aliases (another name for one)."""

    def __init__(self, faults, aliases=None):
        self._faults = {f.name: f for f in faults}
        self.aliases = dict(aliases or {})

    def __getitem__(self, name):
        f = self._faults[name]
        return f.takes, f.default, f.does

    def __iter__(self):
        return iter(self._faults)

    def __len__(self):
        return len(self._faults)

    def parse(self, name, value=None):
        """(the fault's own name, its checked value) of fault ``name`` with ``value`` (None: its
        default; a switch gives True or False). ValueError with a one-line reason otherwise."""
        name = self.aliases.get(name, name)
        f = self._faults.get(name)
        if f is None:
            raise ValueError("unknown fault %r (known: %s)" % (name, ", ".join(self._faults)))
        if f.check is None:
            if value in (None, True, False):
                return name, value is not False
            raise ValueError("%s: takes no value, got %r" % (name, value))
        if value is None:
            value = f.default
            if value is None:
                raise ValueError("%s: needs a value: %s=%s" % (name, name, f.takes))
        try:
            return name, f.check(value)
        except ValueError as exc:
            raise ValueError("%s: %s" % (name, exc)) from None
