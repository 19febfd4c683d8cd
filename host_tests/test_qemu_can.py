"""tools/firmware/qemu/can_suite.py: the CAN port's figures for the emulated Cortex-M7 also run
(quickly) here, on Python stand-ins for its C models, so the frozen code cannot rot
between `make test-qemu` runs: the port opens on the host's O, frames go both ways in
the probes and the bridge completes its transactions beside a busy CAN port."""

import importlib
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_suite(monkeypatch):
    monkeypatch.syspath_prepend(os.path.join(ROOT, "tools", "firmware", "qemu"))
    monkeypatch.syspath_prepend(os.path.join(ROOT, "host_tests"))
    for name in ("qemu_suite", "can_suite"):
        sys.modules.pop(name, None)
    return importlib.import_module("can_suite")


def test_quick_can_suite(monkeypatch):
    cs = load_suite(monkeypatch)
    lines = []
    fails = []
    cs.run(lines.append, fails.append, None, quick=True)
    assert fails == []
    text = "\n".join(lines)
    assert "can frame received -> SLCAN line out" in text
    assert "can SLCAN line in -> frame queued" in text
    for name in ("no CAN port in the HAL", "CAN port closed", "CAN port open, idle",
                 "CAN port busy, its slow pass held off", "CAN port busy, everything in"):
        assert "can bridge cut-through, %s:" % name in text


def test_port_probe_counts_frames_both_ways(monkeypatch):
    """The probes' own checks can fail: a port that drops the host's line is reported."""
    cs = load_suite(monkeypatch)
    from jig import canport

    monkeypatch.setattr(canport.CanPort, "queue_frame", lambda self, *a: True)  # a frame never sent
    fails = []
    cs.port_figures(lambda s: None, fails.append, None, 3)
    assert fails and "frames sent" in fails[0]


def test_busy_bridge_receives_can_frames(monkeypatch):
    cs = load_suite(monkeypatch)
    from jig import params

    rig = cs.can_rig(params.CUT_THROUGH)
    assert cs.open_port(rig, lambda s: None)
    rig.hal.slcan.load(cs.TX_LINE, len(cs.TX_LINE))
    cs.Busy(rig, False).forward(4)
    assert not rig.stuck
    can = rig.app.can
    assert can.cv[0] >= 3  # frames received from the bus, served by the slow pass
    assert rig.hal.can.sent >= 3  # the host's lines sent on
