"""The Desk stopped by a signal while its Test tab runs a plan: the axis stops, the records are written.

A Desk (its own process, as `jigctl gui` runs) starts a long move from an uploaded plan in
headless Chromium; then the Desk gets SIGTERM (systemd, a CI's abort) or SIGHUP (its
terminal closed). The run ends ABORTED with the cause in its record and in the results
database, the drive stands still with its servo off (read through a connection of the
test's own once the Desk is gone), and the Desk exits by itself.
"""

import glob
import json
import os
import signal
import time

import pytest

import desk_browser as B
from motorjig.master import Master

WHY_NOT = B.browser_missing()
if WHY_NOT and os.environ.get("CI") != "true":
    pytestmark = pytest.mark.skip(reason="browser tests need Chromium here: " + WHY_NOT)



@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_a_signal_to_the_desk_mid_run_stops_the_axis_and_writes_the_records(tmp_path, sig):
    if WHY_NOT:
        pytest.fail("browser tests cannot run: " + WHY_NOT)
    bench = desk = browser = None
    try:
        bench, url = B.start_bench("2")
        desk, page = B.start_desk("--port", url, "--timeout", "300", "--out", str(tmp_path / "results"),
                                  "--db", str(tmp_path / "results.sqlite"), "--operator", "tester")
        browser = b = B.Browser()
        b.open(page)
        plan = tmp_path / "long-move.toml"
        plan.write_text(B.LONG_MOVE_PLAN)
        B.upload_plan(b, plan, "long-move.toml uploaded")
        b.wait_for(lambda: "long-move 1.0 (uploaded)" in b.text("plan-select"), 5, "the uploaded plan chosen")
        b.type("serial", "SN-SIG-1")
        b.click("btn-test-start")
        try:
            b.wait_for(lambda: (lambda e: e is not None and e.get_attribute("data-state") == "running")(
                b.find("step-long")), 20, "the move running")
        except AssertionError:
            b.screenshot("/tmp/desk-signals.png")
            raise
        time.sleep(0.5)
        desk.send_signal(sig)
        assert desk.wait(30) is not None  # the Desk ends by itself
        with Master(url, timeout=0.5) as m:
            st = m.get_all_status(2)
            time.sleep(0.2)
            again = m.get_all_status(2)
        flags = set(st.axis.flags)
        assert "motioning" not in flags and "servo_on" not in flags, flags
        assert st.actual_vel == 0 and again.actual_pos == st.actual_pos and 0 < st.actual_pos < 400000
        records = glob.glob(str(tmp_path / "results" / "long-move_*.json"))
        assert len(records) == 1
        with open(records[0]) as f:
            rec = json.load(f)
        assert rec["outcome"] == "ABORTED"
        assert rec["outcome_details"][0]["description"] == "aborted: the Desk was stopped"
        from motorjig.station.store import open_store

        with open_store(str(tmp_path / "results.sqlite")) as st:
            assert [r["verdict"] for r in st.runs()] == ["ABORTED"]
    finally:
        if browser is not None:
            browser.close()
        B.stop(desk)
        B.stop(bench)
