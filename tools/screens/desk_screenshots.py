"""Take the screenshots of MotorJig Desk in docs/ (headless Chromium against the virtual bench).

    .venv/bin/python tools/screens/desk_screenshots.py [OUTDIR]        default: docs/
    .venv/bin/python tools/screens/desk_screenshots.py --can [OUTDIR]  only the CAN tab's (desk-can.png)

Starts the bench and the Desk as child processes, plays a short session (scan,
servo on, a move, a motion test, the parameter table, a raw frame with a broken
CRC, and on the Test tab ezi-step-eol failing on a drive with a wrong parameter,
then passing, then smoke passing; on a bench with CANopen nodes 5 and 6 the CAN tab:
open, scan, an SDO read, heartbeats and NMT start) and saves one PNG per main view. Uses the
browser helpers of the tests; the runs' records go to a temporary folder.
"""

import os
import shutil
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.join(ROOT, "host_tests"))

import desk_browser as B  # noqa: E402


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0
    only_can = "--can" in argv
    argv = [a for a in argv if a != "--can"]
    out = argv[0] if argv else os.path.join(ROOT, "docs")
    os.makedirs(out, exist_ok=True)
    why = B.browser_missing()
    if why:
        sys.stderr.write("desk_screenshots: %s.\n" % why)
        return 2
    can_tab(out)
    if only_can:
        print("screenshot written to %s" % os.path.join(out, "desk-can.png"))
        return 0
    wiring = os.path.join(ROOT, "plans", "ezi-step-eol.toml")
    bench, url = B.start_bench("2,3", "--wiring", wiring)
    faulty = desk = b = None
    results = tempfile.mkdtemp(prefix="motorjig-shots-")
    try:
        faulty, faulty_url = B.start_bench("2", "--wiring", wiring, "--fault", "param=3:250")
        desk, page = B.start_desk("--port", url, "--timeout", "300", "--out", results,
                                  "--db", os.path.join(results, "results.sqlite"), "--operator", "anna",
                                  "--station", "eol-station-1")
        b = B.Browser()
        b.driver.set_window_size(1440, 1300)
        b.open(page)
        b.click("btn-scan")
        b.wait_for(lambda: "ids 1, 2, 3" in b.text("scan-progress"), 20, "scan")
        time.sleep(1.5)  # let the notifications fade
        b.screenshot(os.path.join(out, "desk-connect.png"))

        b.tab("tab-axis")
        b.click("btn-servo-on")
        b.type("move-target", "20000")
        b.type("move-speed", "8000")
        b.click("btn-move-inc")
        time.sleep(1.6)  # mid-move: the lamps show the motion
        b.screenshot(os.path.join(out, "desk-axis.png"))
        b.wait_for(lambda: b.text("act-pos") == "20000", 20, "move done")

        b.tab("tab-test")
        b.type("mt-cycles", "2")
        b.type("mt-distance", "5000")
        b.type("mt-speed", "40000")
        b.click("btn-mt-start")
        b.wait_for(lambda: b.text("mt-summary").startswith(("PASS", "FAIL")), 60, "motion test")
        time.sleep(1.0)
        b.screenshot(os.path.join(out, "desk-motion-test.png"))

        b.tab("tab-params")
        b.click("btn-param-read")
        b.wait_for(lambda: "axis_acc_time" in b.text("param-table"), 20, "parameters")
        b.screenshot(os.path.join(out, "desk-parameters.png"))

        b.tab("tab-raw")
        b.click("btn-log-clear")
        b.click("btn-raw-send")
        time.sleep(0.5)
        b.el("raw-corrupt").click()
        b.click("btn-raw-send")
        time.sleep(1.5)
        b.screenshot(os.path.join(out, "desk-raw-log.png"))

        test_tab(b, out, url, faulty_url)
        print("screenshots written to %s" % out)
        return 0
    finally:
        if b is not None:
            b.close()
        B.stop(desk)
        B.stop(bench)
        B.stop(faulty)
        shutil.rmtree(results, ignore_errors=True)


def run_plan(b, label, serial, prompt=False, expect=None):
    """Run a plan from the Test tab and wait for its verdict; the report's tab is closed again.
    With ``expect`` the run is repeated (up to three times) until that is the verdict: on a
    busy machine the real-time bench can fall behind and a move take too long."""
    for _ in range(3):
        if _run_once(b, label, serial, prompt) == expect or expect is None:
            return
    raise RuntimeError("%s never ended %s (a busy machine?)" % (label, expect))


def _run_once(b, label, serial, prompt):
    first = b.driver.current_window_handle
    b.tab("tab-plan")
    b.choose("plan-select", label)
    b.type("serial", serial)
    b.click("btn-test-start")
    if prompt:
        b.wait_for(lambda: b.find("btn-prompt-yes") is not None and b.el("btn-prompt-yes").is_displayed(), 15,
                   "the prompt")
        b.click("btn-prompt-yes")
    b.wait_for(lambda: b.el("verdict").is_displayed() and b.text("verdict-word"), 60, "the verdict")
    b.wait_for(lambda: len(b.driver.window_handles) > 1, 10, "the report's tab")
    for h in b.driver.window_handles:
        if h != first:
            b.driver.switch_to.window(h)
            b.driver.close()
    b.driver.switch_to.window(first)
    b.wait_for(lambda: b.text("conn-state").startswith("connected: "), 10, "the port back")
    return b.text("verdict-word")


def connect(b, url):
    b.tab("tab-connect")
    b.type("port", url)
    b.click("btn-connect")
    b.wait_for(lambda: b.text("conn-state") == "connected: %s @ 115200" % url, 10, "connected to %s" % url)


def test_tab(b, out, url, faulty_url):
    """desk-test-fail.png: a FAIL as the operator sees it; desk-test.png: a PASS with the page below it."""
    b.driver.set_window_size(1440, 1000)
    connect(b, faulty_url)
    run_plan(b, "ezi-step-eol 1.0", "SN-24-1041", prompt=True, expect="FAIL")
    time.sleep(1.0)
    b.screenshot(os.path.join(out, "desk-test-fail.png"))
    connect(b, url)
    run_plan(b, "ezi-step-eol 1.0", "SN-24-1042", prompt=True, expect="PASS")
    run_plan(b, "smoke 1.0", "SN-24-1043", expect="PASS")
    time.sleep(1.0)
    # The whole tab in one picture: the verdict as tall as in a 1000-pixel window, then the rest.
    b.js("document.querySelectorAll('.verdict').forEach(v => v.style.minHeight = '560px');"
         "document.documentElement.style.overflow = 'hidden';")
    height = b.js("return document.documentElement.scrollHeight")
    b.driver.set_window_size(1440, height + 140)  # + the browser's own frame in headless mode
    time.sleep(0.8)
    b.screenshot(os.path.join(out, "desk-test.png"))


def can_tab(out):
    """desk-can.png: the CAN tab on a bench with CANopen nodes 5 and 6 after a scan, an SDO read of the
    device name, node 5 beating and started, the frame log naming it all."""
    desk = b = None
    try:
        desk, page = B.start_desk("--bench", "--drivers", "2", "--can-nodes", "5,6", "--timeout", "300")
        b = B.Browser()
        b.driver.set_window_size(1440, 1500)
        b.open(page)
        b.tab("tab-can")
        b.click("btn-can-open")
        b.wait_for(lambda: b.text("can-state").startswith("open: "), 10, "the SLCAN port open")
        b.click("btn-can-scan")
        b.wait_for(lambda: b.text("can-message").startswith("scan: "), 30, "the scan")
        for node, obj, value in (("5", "0x1017", "500"), ("6", "0x1017", "500")):
            b.type("can-sdo-node", node)
            b.type("can-sdo-object", obj)
            b.type("can-sdo-value", value)
            b.click("btn-can-sdo-write")
            b.wait_for(lambda n=node: b.text("can-sdo-result").startswith("node %s 0x1017:00" % n), 10,
                       "the heartbeat time written")
        b.type("can-nmt-node", "5")
        b.click("btn-can-nmt")
        b.wait_for(lambda: b.text("can-message") == "NMT start sent to node 5", 5, "NMT start")
        b.type("can-sdo-node", "5")
        b.type("can-sdo-object", "0x1008")
        b.click("btn-can-sdo-read")
        b.wait_for(lambda: "0x1008:00" in b.text("can-sdo-result"), 10, "the device name")
        b.click("btn-can-counters")
        b.wait_for(lambda: "can_rx_frames" in b.text("can-counters"), 10, "the jig's CAN counters")
        time.sleep(2.5)  # a few heartbeats in the log; the notifications fade
        b.screenshot(os.path.join(out, "desk-can.png"))
    finally:
        if b is not None:
            b.close()
        B.stop(desk)


if __name__ == "__main__":
    sys.exit(main())
