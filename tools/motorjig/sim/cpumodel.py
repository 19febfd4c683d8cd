"""The jig's CPU time on the bench's virtual timeline: one named structure.

``SimHAL`` charges it (a pass that read bytes, each byte, the slow pass, a write of
capture records, an idle pass) and every benchmark prints it with ``describe``, so a
field added here is charged and printed everywhere at once, never half-known.
"""

from collections import namedtuple

_FIELDS = ("pass_us", "byte_us", "slow_pass_us", "capture_write_us", "idle_pass_us")
_LABELS = ("a pass", "a byte", "a slow pass", "a capture write", "an idle pass")


class CpuModel(namedtuple("CpuModel", _FIELDS)):
    """µs per main-loop pass that read input, per byte read, per slow pass, per write of
    capture records and per idle pass. All zero (``CpuModel()``): an infinitely fast CPU."""

    __slots__ = ()

    def __new__(cls, pass_us=0.0, byte_us=0.0, slow_pass_us=0.0, capture_write_us=0.0, idle_pass_us=0.0):
        self = super().__new__(cls, float(pass_us), float(byte_us), float(slow_pass_us), float(capture_write_us),
                               float(idle_pass_us))
        if min(self) < 0:
            raise ValueError("cpu_model: times must not be negative")
        return self

    @classmethod
    def of(cls, value):
        """A ``CpuModel`` from one, from None (infinitely fast) or from a tuple of 2 to 5
        figures in the fields' order."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        value = tuple(value)
        if not 2 <= len(value) <= len(_FIELDS):
            raise ValueError("cpu_model: (us per pass, us per byte[, us per slow pass[, us per capture write"
                             "[, us per idle pass]]])")
        return cls(*value)

    @classmethod
    def from_instructions(cls, hz, per_pass, per_byte, slow_pass=0, capture_write=0, idle_pass=0):
        """From instruction counts, at ``hz`` instructions a second."""
        return cls(*(n / hz * 1e6 for n in (per_pass, per_byte, slow_pass, capture_write, idle_pass)))

    @property
    def off(self):
        return not any(self)

    def describe(self, hz=None):
        """One line naming every figure: in instructions at ``hz`` if given, else in µs."""
        if self.off:
            return "off (an infinitely fast CPU)"
        if hz:
            parts = ["%s %d" % (label, round(v * hz / 1e6)) for label, v in zip(_LABELS, self)]
            return "instructions: %s (at %g MHz, one a cycle)" % (", ".join(parts), hz / 1e6)
        return "µs: " + ", ".join("%s %.2f" % (label, v) for label, v in zip(_LABELS, self))
