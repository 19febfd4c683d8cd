"""Take the screenshots of MotorJig Desk in docs/ (headless Chromium against the virtual bench).

    .venv/bin/python tools/desk_screenshots.py [OUTDIR]      default: docs/

Starts the bench and the Desk as child processes, plays a short session (scan,
servo on, a move, a motion test, the parameter table, a raw frame with a broken
CRC) and saves one PNG per main view. Uses the browser helpers of the tests.
"""

import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "host_tests"))

import desk_browser as B  # noqa: E402


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0
    out = argv[0] if argv else os.path.join(ROOT, "docs")
    os.makedirs(out, exist_ok=True)
    why = B.browser_missing()
    if why:
        sys.stderr.write("desk_screenshots: %s.\n" % why)
        return 2
    bench, url = B.start_bench()
    desk = b = None
    try:
        desk, page = B.start_desk("--port", url, "--timeout", "300")
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
        print("screenshots written to %s" % out)
        return 0
    finally:
        if b is not None:
            b.close()
        B.stop(desk)
        B.stop(bench)


if __name__ == "__main__":
    sys.exit(main())
