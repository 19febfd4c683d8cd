"""The Desk's CiA 402 axis (``motorjig.desk.canaxis``) and the Test tab's CAN port lending, without a browser.

One real-time bench in this process (``Bench(driver_ids=(2,), can_nodes=(5,))``, its
jig's SLCAN port served on TCP) and the Desk's own ``CanLink`` on it: input refused in
one sentence before anything is sent, STOP AXIS never switching on a drive that is not
enabled (a halt's controlword carries ENABLE OPERATION), closing the port mid-move
leaving the drive standing with its voltage off, the EMCY of a fault named, and a
CiA 402 plan refused without an SLCAN port / the port lent to a run refusing Open.
"""

import os
import time

import pytest

from motorjig.can import power402
from motorjig.desk.canlink import CanLink
from motorjig.desk.session import UserError
from motorjig.sim.bench import Bench

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def bench():
    b = Bench(driver_ids=(2,), can_nodes=(5,), pty=False).start()
    try:
        yield b
    finally:
        b.stop()


@pytest.fixture
def link(bench):
    link = CanLink(bench.slcan_url, 500000)
    link.open()
    try:
        yield link
    finally:
        if link.state != "closed":
            link.close()
        link.axis.close()


def state(link):
    return link.axis._state(5)[0]


def wait(predicate, timeout=5.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def test_commands_need_a_node_and_numbers(link):
    with pytest.raises(UserError, match="choose the CiA 402 node"):
        link.axis.enable()
    with pytest.raises(UserError, match=r"the node id must be 1\.\.127, not 200"):
        link.axis.enable("200")
    frames = link.tx
    with pytest.raises(UserError, match="the speed \\(counts/s\\) must be a whole number, not 'fast'"):
        link.axis.move("abs", "1000", "fast", node_id="5")
    with pytest.raises(UserError, match="a move is 'abs' or 'rel'"):
        link.axis.move("sideways", "1000", "100", node_id="5")
    assert link.tx == frames  # nothing sent


def test_stop_axis_never_switches_on_a_drive_that_is_not_enabled(link):
    ax = link.axis
    ax.watch(5)
    assert ax.disable() == "node 5: SWITCH ON DISABLED"
    link.sdo_write(5, "0x6040", "6")  # SHUTDOWN: READY TO SWITCH ON, where 0x0F would switch it on
    assert state(link) == power402.READY
    assert ax.stop(emergency=False) == ""  # a halt is ENABLE OPERATION | bit 8: not sent
    time.sleep(0.1)
    assert state(link) == power402.READY
    assert ax.halt() == "node 5 is not in OPERATION ENABLED: nothing to halt"
    assert state(link) == power402.READY
    assert ax.stop(emergency=True) == "CAN node 5: quick stop"  # QUICK STOP from READY: switch on disabled
    assert wait(lambda: state(link) == power402.SWITCH_ON_DISABLED)


def test_closing_the_port_mid_move_leaves_the_drive_standing_disabled(bench, link):
    ax = link.axis
    ax.watch(5)
    assert ax.enable() == "node 5: OPERATION ENABLED"
    assert 5 in ax.enabled
    ax.move("rel", "200000", "20000", node_id="5")
    assert wait(lambda: ax._read(0x606C) != 0)
    assert link.close().startswith("SLCAN port %s closed" % bench.slcan_url)
    assert ax.enabled == set()
    link.open()
    assert state(link) == power402.SWITCH_ON_DISABLED
    p = ax._read(0x6064)
    time.sleep(0.3)
    assert ax._read(0x6064) == p and ax._read(0x606C) == 0


def test_a_fault_is_named_and_enable_refused_until_fault_reset(bench, link):
    ax = link.axis
    ax.watch(5)
    ax.enable()
    bench.sim.set_fault("can:overcurrent", 20, 5)
    try:
        ax.move("rel", "20000", "20000", node_id="5")
        assert wait(lambda: state(link) == power402.FAULT)
        st = ax.poll()
        assert st["fault_code"] == 0x2310 and st["emcy"].startswith("0x2310 continuous over current")
        with pytest.raises(UserError, match=r"node 5 is in FAULT \(last EMCY 0x2310 continuous over current\): "
                                            "press Fault reset first"):
            ax.enable()
    finally:
        bench.sim.clear_faults()
    assert ax.fault_reset() == "node 5: SWITCH ON DISABLED"
    assert ax.fault_reset() == "node 5 is not in FAULT (SWITCH ON DISABLED): nothing to reset"


def test_a_cia402_plan_borrows_the_can_tabs_port_and_refuses_without_one(bench, link):
    from motorjig.desk.axes import give_back
    from motorjig.desk.session import BusSession
    from motorjig.desk.testrun import Station
    from motorjig.station import load_plan

    plan = load_plan(os.path.join(ROOT, "plans", "cia402-smoke.toml"))
    station = Station(BusSession(), plans_dir=os.path.join(ROOT, "plans"), out_dir=os.path.join(ROOT, "results"))
    with pytest.raises(UserError, match="cia402-smoke: its drive is on the jig's SLCAN port: start the Desk "
                                        "with --can-port"):
        station._lend_ports(plan)
    station.axes = [link.desk_axis]
    link.axis.watch(5)
    link.axis.enable()
    ports, lent = station._lend_ports(plan)
    assert ports == {"can_port": bench.slcan_url} and lent == [link.desk_axis]
    assert link.state == "closed" and link.summary() == "lent to the test run (cia402-smoke)"
    assert link.desk_axis.status() == "lent to the test run (cia402-smoke)"
    with pytest.raises(UserError, match=r"the SLCAN port is lent to the test run \(cia402-smoke\)"):
        link.open()
    with pytest.raises(UserError, match=r"the SLCAN port is lent to the test run \(cia402-smoke\)"):
        link.axis.enable()
    assert link.axis.describe() == {"state": "the SLCAN port is lent to the test run (cia402-smoke)"}
    assert give_back(lent) == []
    assert link.is_open and link.lent == ""
    assert state(link) == power402.SWITCH_ON_DISABLED  # made safe before it was lent


def test_a_port_that_cannot_come_back_is_said_and_the_other_axes_still_get_theirs(link):
    from motorjig.desk.axes import DeskAxis, give_back, lend_ports

    class Other(DeskAxis):
        title, run_port, back = "the other port", "other_port", 0

        def lend(self, who):
            return "other:" + who

        def take_back(self):
            self.back += 1
            return ""

    class Broken(Other):
        title, run_port = "a broken port", "broken_port"

        def take_back(self):
            raise OSError("unplugged")

    other, broken = Other(), Broken()
    kw, lent = lend_ports([broken, other], [("broken_port", "--b", "b port"), ("other_port", "--o", "o port")], "run")
    assert kw == {"broken_port": "other:run", "other_port": "other:run"}
    assert give_back(lent) == ["a broken port could not be taken back: unplugged"] and other.back == 1
    with pytest.raises(LookupError, match="its drive is on the jig's c port: start the Desk with --c"):
        lend_ports([other], [("other_port", "--o", "o"), ("c_port", "--c", "the jig's c port")], "run")
    assert other.back == 2  # the port it had already lent came back


def test_stopping_the_desk_mid_jog_leaves_the_node_standing_disabled(bench, link):
    from motorjig.desk.server import stop_desk
    from motorjig.desk.session import BusSession

    ax = link.axis
    ax.watch(5)
    ax.enable()
    ax.jog(1, "20000")
    assert wait(lambda: ax._read(0x606C) == 20000)
    stop_desk(BusSession(), can=link)  # what Ctrl-C, SIGTERM and SIGHUP end in
    assert link.state == "closed"
    link.open()
    assert state(link) == power402.SWITCH_ON_DISABLED
    p = ax._read(0x6064)
    time.sleep(0.3)
    assert ax._read(0x6064) == p and ax._read(0x606C) == 0
