"""The CiA 402 bus-health step judges the drive only on what the jig dated and saw.

Its heartbeat jitter comes from the jig's SLCAN timestamps. A frame that came without one
(dated by this PC, which a loaded PC delays) or heartbeats the jig lost on the way to this PC
cannot show the drive's irregularity: past its limit the step is then ERROR with the reason,
never FAIL (issue 31: a false FAIL "heartbeat_jitter = 66 ms" on a loaded PC).
"""

import types

import pytest

from motorjig.station.phases_cia402 import run_bus_health
from motorjig.station.sampling import UntrustedMeasurement


class FakeDrive:
    def __init__(self, beats, unstamped=0, lost=0):
        self.heartbeats = beats
        self.t_opened = beats[0] - 0.1
        self.sdo_stamp = beats[-1] + 0.05
        self.emcys = []
        self._unstamped = unstamped
        self._lost = lost

    def bus_health(self):
        return {"can_rx_lost": self._lost}

    def read(self, index):
        return 0

    def unstamped(self):
        return self._unstamped


def run(drive, limit=20):
    test = types.SimpleNamespace(measurements={}, attach=lambda *a: None)
    bus = types.SimpleNamespace(drive=drive)
    step = types.SimpleNamespace(args={"heartbeat_jitter_max_ms": limit})
    run_bus_health(test, bus, step, None)
    return test.measurements


REGULAR = [1.0 + 0.1 * i for i in range(20)]
LATE = REGULAR[:10] + [t + 0.066 for t in REGULAR[10:]]  # one interval of 166 ms


def test_regular_heartbeats_dated_by_the_jig_are_judged():
    assert run(FakeDrive(REGULAR))["heartbeat_jitter"] == pytest.approx(0.0, abs=0.1)
    assert run(FakeDrive(LATE))["heartbeat_jitter"] == pytest.approx(66.0, abs=0.1)  # the drive's: FAIL


def test_past_the_limit_with_frames_this_pc_dated_is_an_error_with_the_reason():
    with pytest.raises(UntrustedMeasurement, match="3 frames came without the jig's timestamp"):
        run(FakeDrive(LATE, unstamped=3))
    assert run(FakeDrive(REGULAR, unstamped=3))["heartbeat_jitter"] < 1  # within the limit: judged


def test_past_the_limit_with_frames_the_jig_lost_is_an_error_with_the_reason():
    with pytest.raises(UntrustedMeasurement, match="the jig lost 2 received frames"):
        run(FakeDrive(LATE, lost=2))
