"""The CiA 402 drive's own samples as a station trace: TPDOs dated by the jig's clock.

``Cia402Trace`` is a ``sampling`` trace fed by the drive (``drive_cia402``) instead of a poll:
the rows, the marks and the checks that make a step ERROR instead of FAIL are the generic ones.
"""

import time

from motorjig.station.sampling import UntrustedMeasurement, _Sample, _Trace


class _Axis:
    """A CiA 402 sample's statusword as the flags the steps read (``motioning`` as the Plus-R axis's)."""

    __slots__ = ("statusword", "velocity")

    def __init__(self, statusword, velocity):
        self.statusword, self.velocity = statusword, velocity

    @property
    def motioning(self):
        return self.velocity != 0

    @property
    def target_reached(self):
        return bool(self.statusword & 0x400)

    @property
    def fault(self):
        return bool(self.statusword & 0x08)

    @property
    def internal_limit(self):
        return bool(self.statusword & 0x800)


class Cia402Trace(_Trace):
    """A CiA 402 drive's own samples (``drive_cia402``): TPDOs answering the station's SYNC,
    each dated by the jig's clock as it received it; a command is dated by the drive's SDO
    reply to it (``sent``), on the same clock. ``more(drive, _)`` takes what has come."""

    source = "drive"

    def __init__(self, ctx=None, step=None):
        super().__init__(ctx, step)

    def gap_cause(self):
        return "TPDOs that did not come: a busy bus, the jig or this PC"

    def begin(self, d, s=None):
        while not d.samples.empty():  # samples of an earlier step
            d.samples.get()
        d.sync(True)
        deadline = time.monotonic() + 2.0
        while not self.rows:
            self.more(d, s)
            if time.monotonic() > deadline:
                raise UntrustedMeasurement("no TPDO came from %s after SYNC: the step cannot be sampled" % d.label)

    def more(self, d, s=None):
        import queue

        out = []
        try:
            item = d.samples.get(timeout=d.period * self.wait_periods)
        except queue.Empty:
            return out
        while True:
            t, smp = self._sample(item)
            self._add(t, smp)
            out.append((t, smp))
            try:
                item = d.samples.get_nowait()
            except queue.Empty:
                return out

    wait_periods = 2  # how many sampling periods ``more`` waits for the next sample

    def _sample(self, item):
        """(t, _Sample) of one queued sample: (t, statusword, actual, velocity, following error)."""
        t, sw, pos, vel, ferr = item
        return t, _Sample(pos + ferr, pos, vel, _Axis(sw, vel))

    def mark(self, name, ftype=None):
        pass

    def sent(self, name, t):
        """The command ``name``'s instant on the jig's clock (the drive's SDO reply to it)."""
        if t is None:
            raise UntrustedMeasurement("the jig did not date %s: the step's times cannot be dated" % name)
        self.marks[name] = t

    def end(self, d):
        from motorjig.errors import JigError

        try:
            d.sync(False)
        except JigError:
            pass  # the drive's timers keep sending: harmless, and the step's own error says more
