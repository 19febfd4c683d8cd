"""The Desk on a CiA 402 drive in headless Chromium: the CAN tab's axis and the Test tab's cia402 plans.

One bench process (``python -m motorjig.sim --drivers 2 --can-nodes 5``) whose node 5
faults with EMCY 0x2310 4 s into any move or jog (``--fault can:5:overcurrent=4000``: moves
shorter than that, cia402-smoke's among them, are untouched; the Desk's own ``--bench``
takes no faults, so the bench is a process of its own here) and one Desk on it
(``--port`` its PC port, ``--can-port`` its jig's SLCAN port). In file order, as one
operator session: the axis panel enables node 5 and a move reads back its target,
a jog goes while held and stops when released, Esc quick-stops a long move, Disable
switches it off, the overcurrent fault is named and Enable refused until Fault reset,
closing the port with the node enabled disables it first, and cia402-smoke passes from
the Test tab on the port the CAN tab lends it. Last, on a Desk with its own bench
(``--bench --drivers 2 --can-nodes 5``), cia402-smoke passes from the Test tab with the
CAN tab never opened. Every wait is bounded and polls the page.
"""

import os
import re
import time

import pytest
from selenium.webdriver.common.action_chains import ActionChains
from selenium.webdriver.common.keys import Keys

import desk_browser as B

WHY_NOT = B.browser_missing()
if WHY_NOT and os.environ.get("CI") != "true":
    pytestmark = pytest.mark.skip(reason="browser tests need Chromium here: " + WHY_NOT)

OVERCURRENT_MS = 4000  # longer than the jog below holds its button, shorter than the fault test's move


@pytest.fixture(scope="module")
def desk(tmp_path_factory):
    if WHY_NOT:
        pytest.fail("browser tests cannot run: " + WHY_NOT)
    tmp = tmp_path_factory.mktemp("desk-station402")
    with B.started() as run:
        bench, pc = B.start_bench("2", "--can-nodes", "5", "--fault", "can:5:overcurrent=%d" % OVERCURRENT_MS)
        run.append(bench)
        slcan = re.search(r"socket://\S+", B._read_until(bench, "slcan: socket://", 20)).group(0)
        page_proc, page = B.start_desk("--port", pc, "--can-port", slcan, "--timeout", "300",
                                       "--out", str(tmp / "results"), "--db", "none", "--operator", "tester")
        run.append(page_proc)
        yield type("Desk", (), {"b": run.browser(page), "slcan": slcan, "pc": pc})


def field(b, testid):
    box = b.el(testid)  # Quasar puts the testid on the native <input> itself
    return box if box.tag_name in ("input", "textarea") else b.el(testid, "input")


def axis(b, key):
    return b.text("can-axis-" + key)


def state(b):
    return axis(b, "state").split(" (")[0]


def wait_state(b, name, timeout=10):
    return b.wait_for(lambda: state(b) == name, timeout, "node 5 in %s (shows %r)" % (name, axis(b, "state")))


def position(b):
    try:
        return int(axis(b, "position"))
    except ValueError:
        return None


def move_abs(b, target, speed, accel):
    """An absolute move from the axis panel (accel both ways), waited for until it is read back."""
    for key, value in (("target", target), ("speed", speed), ("acc", accel), ("dec", accel)):
        b.type("can-axis-" + key, str(value))
    b.click("btn-can-move-abs")
    b.wait_for(lambda: position(b) == target and "target reached" in axis(b, "state"), 10,
               "position %d read back" % target)


def message(b):
    return b.text("can-message")


def test_the_axis_panel_watches_node_5_once_the_port_is_open(desk):
    b = desk.b
    b.tab("tab-can")
    b.click("btn-can-open")
    b.wait_for(lambda: b.text("can-state").startswith("open: %s" % desk.slcan), 10, "the port open")
    b.type("can-axis-node", "5")
    field(b, "can-axis-node").send_keys(Keys.ENTER)
    wait_state(b, "SWITCH ON DISABLED")
    assert axis(b, "mode").startswith("1 profile position")
    assert axis(b, "emcy") == "none since the port opened"


def test_enable_then_a_move_reads_back_its_target(desk):
    b = desk.b
    b.click("btn-can-enable")
    wait_state(b, "OPERATION ENABLED")
    move_abs(b, 8000, 20000, 200000)
    assert axis(b, "velocity") == "0" and axis(b, "following-error") == "0"
    b.type("can-axis-target", "-3000")
    b.click("btn-can-move-rel")
    b.wait_for(lambda: position(b) == 5000, 10, "position 5000 after a relative move of -3000")


def test_a_jog_goes_while_held_and_stops_when_released(desk):
    b = desk.b
    b.type("can-axis-speed", "5000")
    start = position(b)
    button = b.el("btn-can-jog-plus")
    ActionChains(b.driver).click_and_hold(button).perform()
    try:
        b.wait_for(lambda: axis(b, "velocity") == "5000", 5, "jogging at +5000 counts/s")
        assert axis(b, "mode").startswith("3 profile velocity")
        time.sleep(1.5)  # longer than the jog's lease: the held button keeps it going
        assert axis(b, "velocity") == "5000"
    finally:
        ActionChains(b.driver).release(button).perform()
    b.wait_for(lambda: axis(b, "velocity") == "0", 5, "the jog stopped on release")
    stopped = position(b)
    assert stopped > start + 5000
    time.sleep(0.6)
    assert position(b) == stopped and state(b) == "OPERATION ENABLED"


def test_esc_quick_stops_a_long_move(desk):
    b = desk.b
    b.type("can-axis-target", "0")
    b.type("can-axis-speed", "20000")
    b.click("btn-can-move-abs")
    b.wait_for(lambda: position(b) == 0, 10, "back at 0")
    b.type("can-axis-target", "100000")  # 5 s: Esc comes well before the bench's overcurrent (4 s)
    b.click("btn-can-move-abs")
    b.wait_for(lambda: abs(int(axis(b, "velocity") or 0)) > 0, 5, "moving")
    b.driver.find_element("tag name", "body").send_keys(Keys.ESCAPE)
    wait_state(b, "SWITCH ON DISABLED", 5)  # quick stop, then (0x605A 0-4) switch on disabled
    b.wait_for(lambda: axis(b, "velocity") == "0", 5, "standstill")
    stopped = position(b)
    assert 0 < stopped < 40000
    time.sleep(0.6)
    assert position(b) == stopped
    assert "CAN node 5: quick stop" in b.driver.page_source
    # the tab's line no longer says the move it sent (issue 31: "node 5: move to ..." stayed)
    b.wait_for(lambda: message(b).startswith("the axis was stopped"), 5, "the tab's line after the stop")


def test_disable_switches_an_enabled_node_off(desk):
    b = desk.b
    b.click("btn-can-enable")
    wait_state(b, "OPERATION ENABLED")
    b.click("btn-can-disable")
    wait_state(b, "SWITCH ON DISABLED")


def test_a_fault_is_named_and_enable_waits_for_fault_reset(desk):
    b = desk.b
    b.click("btn-can-enable")
    wait_state(b, "OPERATION ENABLED")
    b.type("can-axis-target", "160000")  # 8 s: the bench's overcurrent comes at 4 s
    b.type("can-axis-speed", "20000")
    b.click("btn-can-move-rel")
    wait_state(b, "FAULT", 12)
    b.wait_for(lambda: axis(b, "emcy").startswith("0x2310 continuous over current"), 5, "the EMCY named")
    assert axis(b, "fault").startswith("0x2310")
    b.click("btn-can-enable")
    b.wait_for(lambda: "press Fault reset first" in message(b), 5, "Enable refused in FAULT")
    assert "0x2310" in message(b)
    assert state(b) == "FAULT"
    b.click("btn-can-fault-reset")
    wait_state(b, "SWITCH ON DISABLED")
    assert axis(b, "fault") == ""
    b.click("btn-can-enable")
    wait_state(b, "OPERATION ENABLED")


def test_closing_the_port_disables_the_enabled_node_first(desk):
    b = desk.b
    assert state(b) == "OPERATION ENABLED"
    b.click("btn-can-close")
    b.wait_for(lambda: b.text("can-state") == "closed", 10, "the port closed")
    assert axis(b, "state") == "the SLCAN port is not open"
    b.click("btn-can-open")
    b.wait_for(lambda: b.text("can-state").startswith("open: "), 10, "the port open again")
    wait_state(b, "SWITCH ON DISABLED")


def test_cia402_smoke_passes_from_the_test_tab_on_the_lent_can_port(desk):
    b = desk.b
    # smoke's moves go out by 10000 and back to 0: from 0 they are short (the bench's overcurrent is for longer ones)
    b.click("btn-can-enable")
    wait_state(b, "OPERATION ENABLED")
    move_abs(b, 0, 200000, 2000000)
    b.tab("tab-plan")
    b.choose("plan-select", "cia402-smoke 1.0")
    assert "CAN node 5" in b.text("plan-info")
    result = run_plan_from_test_tab(b, "cia402-smoke 1.0", "SN-402")
    assert result == "PASS", b.text("steps")
    b.tab("tab-can")  # the port comes back to the CAN tab, open as it was
    b.wait_for(lambda: b.text("can-state").startswith("open: %s" % desk.slcan), 10, "the CAN tab's port back")
    wait_state(b, "SWITCH ON DISABLED")


def run_plan_from_test_tab(b, label, serial):
    """Start label for serial from the Test tab (Enter in the serial field), up to three times
    while the verdict is not PASS; returns the last verdict word."""
    first = b.driver.current_window_handle
    b.tab("tab-plan")
    b.choose("plan-select", label)
    for attempt in range(1, 4):
        b.type("serial", "%s-%d" % (serial, attempt))
        field(b, "serial").send_keys(Keys.ENTER)
        result = b.wait_for(lambda: b.text("verdict-word") if b.visible("verdict") else "", 60, "the verdict")
        for handle in b.driver.window_handles:  # a passing run opens its report in a tab of its own
            if handle != first:
                b.driver.switch_to.window(handle)
                b.driver.close()
        b.driver.switch_to.window(first)
        if result == "PASS":
            break
    return result


def test_on_the_desks_own_bench_cia402_smoke_passes_with_the_can_tab_never_opened(tmp_path):
    """`jigctl gui --bench --can-nodes 5`: the Test tab takes the bench's SLCAN port itself."""
    with B.started() as run:
        proc, page = B.start_desk("--bench", "--drivers", "2", "--can-nodes", "5", "--timeout", "300",
                                  "--out", str(tmp_path / "results"), "--db", "none")
        run.append(proc)
        b = run.browser(page)
        result = run_plan_from_test_tab(b, "cia402-smoke 1.0", "SN-402-BENCH")
        assert result == "PASS", b.text("steps")
        b.tab("tab-can")
        assert b.text("can-state") == "closed"  # as it was: the run did not leave it open
