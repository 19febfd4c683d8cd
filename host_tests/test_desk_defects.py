"""Defects found on MotorJig Desk, each with the browser test that showed it (headless Chromium).

One bench (drivers 2 and 3), one Desk and one browser for the module; the tests run
in file order, test_3 kills the bench (a lost connection in the middle of a motion
test); the tests after it start a bench and a Desk of their own (a mixed Ver6/Ver8
bus, a read-only Desk). Every wait is bounded and polls the page; no fixed sleeps.
"""

import csv
import os
import re
import socket
import threading

import pytest

import desk_browser as B

WHY_NOT = B.browser_missing()
if WHY_NOT and os.environ.get("CI") != "true":
    pytestmark = pytest.mark.skip(reason="browser tests need Chromium here: " + WHY_NOT)


@pytest.fixture(scope="module")
def desk(tmp_path_factory):
    if WHY_NOT:
        pytest.fail("browser tests cannot run: " + WHY_NOT)
    bench = page_proc = browser = None
    try:
        bench, url = B.start_bench()
        page_proc, page = B.start_desk("--port", url, "--timeout", "300")
        browser = B.Browser(downloads=str(tmp_path_factory.mktemp("downloads")))
        browser.open(page)
        yield type("Desk", (), {"bench": bench, "bench_url": url, "proc": page_proc, "url": page, "b": browser})
    finally:
        if browser is not None:
            browser.close()
        B.stop(page_proc)
        B.stop(bench)


def log_text(b):
    return b.js("""return document.querySelector('[data-testid="log"]').innerText;""")


def flat_log(b):
    """The log with every run of spaces as one (the decoder pads its columns)."""
    return re.sub(r"[ ]+", " ", log_text(b))


def lamp(b, flag):
    return b.el("lamps", '[data-flag="%s"]' % flag).get_attribute("class").split()


def value(b, testid):
    box = b.el(testid)
    if box.tag_name not in ("input", "textarea"):
        box = b.el(testid, "input")
    return box.get_attribute("value")


def press(b, testid, key):
    box = b.el(testid)
    if box.tag_name not in ("input", "textarea"):
        box = b.el(testid, "input")
    box.send_keys(key)


def esc(b):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    ActionChains(b.driver).send_keys(Keys.ESCAPE).perform()


def servo_on(b):
    b.click("btn-servo-on")
    b.wait_for(lambda: "on" in lamp(b, "servo_on"), 5, "servo on")


def clear_log(b):
    b.tab("tab-raw")
    b.click("btn-log-clear")
    b.wait_for(lambda: log_text(b).strip() == "", 5, "an empty log")


def test_page_is_connected_and_the_bus_scanned(desk):
    b = desk.b
    b.wait_for(lambda: "connected: " in b.text("conn-state"), 10, "connected")
    b.tab("tab-connect")
    b.click("btn-scan")
    b.wait_for(lambda: b.text("scan-progress") == "3 slave(s): ids 1, 2, 3", 20, "scan result")


def test_7_move_fields_start_at_the_seed_programs_values(desk):
    b = desk.b
    b.tab("tab-axis")
    assert [value(b, t) for t in ("move-target", "move-speed", "move-acc", "move-dec")] == \
        ["300000", "50000", "1000", "10"]


def test_1_frame_type_is_read_as_hex(desk):
    b = desk.b
    clear_log(b)
    b.type("raw-id", "2")
    b.type("raw-data", "")
    b.type("raw-type", "40")  # 0x40 GetAxisStatus, not 40 = 0x28
    b.click("btn-raw-send")
    b.wait_for(lambda: "RX reply id 2 GetAxisStatus(0x40)" in flat_log(b), 5, "GetAxisStatus sent as 40")
    assert "(0x28)" not in log_text(b)
    b.type("raw-type", "2A")  # ServoEnable, on
    b.type("raw-data", "01")
    b.click("btn-raw-send")
    b.wait_for(lambda: "TX request id 2 ServoEnable(0x2A) on=True" in flat_log(b), 5, "2A accepted")
    b.type("raw-type", "0x40")
    b.type("raw-data", "")
    b.click("btn-raw-send")
    b.wait_for(lambda: log_text(b).count("GetAxisStatus(0x40)") == 4, 5, "0x40 accepted too")
    b.type("raw-type", "140")
    b.click("btn-raw-send")
    b.wait_for(lambda: "frame type: '140' is not a hex byte" in log_text(b), 5, "three digits refused")


def test_2_a_received_frame_is_logged_as_a_reply(desk):
    b = desk.b
    clear_log(b)
    b.tab("tab-axis")
    b.click("btn-servo-off")  # its reply 02 2A 00 has the shape of a ServoEnable(off) request too
    b.tab("tab-raw")
    b.wait_for(lambda: "RX reply id 2 ServoEnable(0x2A) status OK" in flat_log(b), 5, "the reply")
    assert "RX request" not in flat_log(b)
    b.tab("tab-axis")
    b.click("btn-servo-on")
    b.wait_for(lambda: "on" in lamp(b, "servo_on"), 5, "servo on again")


def test_4_a_motion_test_of_distance_0_is_refused(desk):
    b = desk.b
    b.tab("tab-test")
    b.type("mt-cycles", "2")
    b.type("mt-distance", "0")
    b.type("mt-speed", "40000")
    b.click("btn-mt-start")
    b.wait_for(lambda: "distance must not be 0" in b.driver.page_source, 5, "the refusal")
    assert b.text("mt-summary") == ""


def test_5_after_an_emergency_stop_the_page_says_what_brings_the_axis_back(desk):
    b = desk.b
    b.tab("tab-axis")
    b.click("btn-estop")
    b.wait_for(lambda: "err" in lamp(b, "emergency_stop"), 5, "emergency_stop lamp")
    hint = b.wait_for(lambda: b.find("estop-hint") is not None and b.el("estop-hint").is_displayed()
                      and b.text("estop-hint"), 5, "the recovery hint")
    assert "Servo OFF, then Servo ON" in hint and "ALARM RESET and STOP AXIS do not clear it" in hint
    b.type("move-target", "1000")
    b.type("move-speed", "20000")
    b.click("btn-move-inc")  # refused by the drive: the message says what to do
    b.wait_for(lambda: "motion command refused" in b.driver.page_source
               and b.driver.page_source.count("Servo OFF, then Servo ON") >= 2, 5, "the refusal with the hint")
    b.click("btn-alarm-reset")
    b.click("btn-stop")
    b.wait_for(lambda: "err" in lamp(b, "emergency_stop"), 2, "still latched")
    b.click("btn-estop-recover")
    b.wait_for(lambda: "err" not in lamp(b, "emergency_stop") and "on" in lamp(b, "servo_on"), 5, "cleared")
    b.wait_for(lambda: not b.el("estop-hint").is_displayed(), 5, "the hint gone")


def test_6_esc_in_a_dialog_or_a_dropdown_closes_only_it(desk):
    b = desk.b
    clear_log(b)
    b.tab("tab-params")
    b.click("btn-param-save")
    b.wait_for(lambda: b.find("btn-param-save-yes") is not None and b.el("btn-param-save-yes").is_displayed(),
               5, "the Save-to-ROM dialog")
    esc(b)
    b.wait_for(lambda: b.find("btn-param-save-yes") is None or not b.el("btn-param-save-yes").is_displayed(),
               5, "the dialog closed")
    b.tab("tab-raw")
    assert "EMERGENCY STOP" not in log_text(b)  # the dialog's Esc closed only the dialog
    b.tab("tab-axis")
    b.el("plot-window").click()  # a dropdown
    b.wait_for(lambda: b.js("return document.querySelectorAll('.q-menu').length") > 0, 5, "the dropdown open")
    esc(b)
    b.wait_for(lambda: b.js("return document.querySelectorAll('.q-menu').length") == 0, 5, "the dropdown closed")
    assert "err" not in lamp(b, "emergency_stop")
    b.tab("tab-raw")
    assert "EMERGENCY STOP" not in log_text(b)
    esc(b)  # with nothing open Esc is still EMERGENCY STOP
    b.wait_for(lambda: "EMERGENCY STOP sent to all axes and slave 2" in log_text(b), 5, "the E-stop")
    b.tab("tab-axis")
    b.wait_for(lambda: "err" in lamp(b, "emergency_stop"), 5, "emergency_stop lamp")
    b.click("btn-estop-recover")
    b.wait_for(lambda: "err" not in lamp(b, "emergency_stop"), 5, "recovered")


def test_7_move_fields_remember_the_last_values_moved_with(desk):
    b = desk.b
    b.tab("tab-axis")
    servo_on(b)
    b.type("move-target", "2500")
    b.type("move-speed", "40000")
    b.type("move-acc", "")
    b.type("move-dec", "")
    b.click("btn-move-abs")
    b.wait_for(lambda: b.text("cmd-pos") == "2500", 10, "moved to 2500")
    b.open(desk.url)  # a fresh tab shows what the session remembers
    b.tab("tab-axis")
    assert [value(b, t) for t in ("move-target", "move-speed", "move-acc", "move-dec")] == ["2500", "40000", "", ""]


def test_7_enter_in_the_move_and_raw_fields_moves_and_sends(desk):
    from selenium.webdriver.common.keys import Keys

    b = desk.b
    b.tab("tab-axis")
    servo_on(b)
    b.type("move-target", "4000")
    press(b, "move-target", Keys.ENTER)  # the last move used: ABS
    b.wait_for(lambda: b.text("cmd-pos") == "4000", 10, "Enter moved to 4000")
    b.wait_for(lambda: "on" not in lamp(b, "motioning"), 10, "standstill")
    b.click("btn-move-inc")
    b.wait_for(lambda: b.text("cmd-pos") == "8000", 10, "INC +4000")
    b.wait_for(lambda: "on" not in lamp(b, "motioning"), 10, "standstill")
    press(b, "move-speed", Keys.ENTER)  # now the last one is INC
    b.wait_for(lambda: b.text("cmd-pos") == "12000", 10, "Enter repeated the INC")
    clear_log(b)
    b.type("raw-type", "40")
    b.type("raw-data", "")
    press(b, "raw-type", Keys.ENTER)
    b.wait_for(lambda: "GetAxisStatus(0x40)" in log_text(b), 5, "Enter sent the frame")
    b.type("raw-data", "")
    press(b, "raw-data", Keys.ENTER)
    b.wait_for(lambda: log_text(b).count("GetAxisStatus(0x40)") == 4, 5, "and again from the data field")


def test_7_csv_export_has_iso_time_seconds_from_start_and_the_slave(desk):
    b = desk.b
    b.tab("tab-axis")
    b.wait_for(lambda: int(b.text("plot-points").split()[0]) > 5, 5, "plot points")
    b.click("btn-csv")
    path = b.wait_for(lambda: [os.path.join(b.downloads, n) for n in os.listdir(b.downloads)
                               if n.endswith(".csv")], 10, "the CSV file")[0]
    assert "slave2" in os.path.basename(path)
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["time", "t_s", "slave", "command_pos", "actual_pos", "actual_vel_pps"]
    assert rows[1][1] == "0.000" and rows[1][2] == "2"
    assert rows[1][0][:4].isdigit() and rows[1][0][10] == "T"  # 2026-12-01T18:31:32.123+01:00
    assert float(rows[-1][1]) > 0


def test_7_the_header_shows_the_axis_as_a_control_and_the_protocol(desk):
    b = desk.b
    b.tab("tab-axis")
    b.wait_for(lambda: "2 Ezi-STEP" in b.text("axis-select"), 5, "axis 2 in the header")
    assert b.text("protocol") == "auto: Ver6"  # each slave's variant detected; the axis talks Ver6
    b.el("axis-select").click()
    b.wait_for(lambda: b.js("return document.querySelectorAll('.q-menu .q-item').length") >= 2, 5, "the choices")
    b.js("""Array.from(document.querySelectorAll('.q-menu .q-item'))
            .find(e => e.innerText.startsWith('3 ')).click();""")
    b.wait_for(lambda: "3 Ezi-STEP" in b.text("axis-select"), 5, "axis 3 chosen in the header")
    b.open(desk.url)  # the choice is the session's, not only this tab's
    b.wait_for(lambda: "3 Ezi-STEP" in b.text("axis-select"), 5, "axis 3 after a reload")
    b.el("axis-select").click()
    b.wait_for(lambda: b.js("return document.querySelectorAll('.q-menu .q-item').length") >= 2, 5, "the choices")
    b.js("""Array.from(document.querySelectorAll('.q-menu .q-item'))
            .find(e => e.innerText.startsWith('2 ')).click();""")
    b.wait_for(lambda: "2 Ezi-STEP" in b.text("axis-select"), 5, "axis 2 again")


def test_7_a_silent_port_message_names_the_ver6_ver8_setting(desk):
    b = desk.b
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    held = []
    t = threading.Thread(target=lambda: held.append(server.accept()), daemon=True)
    t.start()
    try:
        b.tab("tab-connect")
        b.type("port", "socket://127.0.0.1:%d" % server.getsockname()[1])
        b.click("btn-connect")
        b.wait_for(lambda: "silent port" in b.driver.page_source, 10, "the silent-port message")
        src = b.driver.page_source
        assert "the Ver6/Ver8 setting (now auto, each slave's variant detected" in src
    finally:
        server.close()
        for conn, _ in held:
            conn.close()
    b.connect(desk.bench_url, "back on the bench")


def enter_hint(b):
    """The move button marked ⏎ (what Enter in a move field repeats)."""
    return [t for t in ("btn-move-abs", "btn-move-inc", "btn-move-dec")
            if "enter-hint" in b.el(t).get_attribute("class").split()]


def settled(b):
    """The command position once the axis stands still."""
    b.wait_for(lambda: "on" not in lamp(b, "motioning"), 10, "standstill")
    return int(b.text("cmd-pos"))


def test_8_after_a_reload_move_dec_keeps_its_distance_sign_and_enter(desk):
    """Issue: after MOVE DEC 5000 a reload showed -5000 with ⏎ on MOVE ABS; MOVE DEC then moved +5000."""
    from selenium.webdriver.common.keys import Keys

    b = desk.b
    b.tab("tab-axis")
    servo_on(b)
    start = settled(b)
    b.type("move-target", "5000")
    b.type("move-speed", "40000")
    b.type("move-acc", "")
    b.type("move-dec", "")
    b.click("btn-move-dec")
    b.wait_for(lambda: b.text("cmd-pos") == str(start - 5000), 10, "MOVE DEC 5000")
    settled(b)
    b.open(desk.url)
    b.tab("tab-axis")
    assert value(b, "move-target") == "5000"  # the distance as typed; the button says which way
    assert enter_hint(b) == ["btn-move-dec"]
    b.click("btn-move-dec")
    b.wait_for(lambda: b.text("cmd-pos") == str(start - 10000), 10, "MOVE DEC again: the same way")
    settled(b)
    press(b, "move-target", Keys.ENTER)
    b.wait_for(lambda: b.text("cmd-pos") == str(start - 15000), 10, "Enter: MOVE DEC once more")
    settled(b)
    assert value(b, "move-target") == "5000" and enter_hint(b) == ["btn-move-dec"]


def test_8_a_second_tab_takes_the_values_of_a_move_sent_from_another(desk):
    """Issue: a second tab kept its stale move fields, and Enter there repeated its old values."""
    from selenium.webdriver.common.keys import Keys

    b = desk.b
    first = b.driver.current_window_handle
    b.driver.switch_to.new_window("tab")
    second = b.driver.current_window_handle
    try:
        b.open(desk.url)
        b.tab("tab-axis")
        b.driver.switch_to.window(first)
        b.tab("tab-axis")
        servo_on(b)
        start = settled(b)
        b.type("move-target", "1500")
        b.type("move-speed", "30000")
        b.type("move-acc", "200")
        b.type("move-dec", "")
        b.click("btn-move-inc")
        b.wait_for(lambda: b.text("cmd-pos") == str(start + 1500), 10, "MOVE INC 1500 in the first tab")
        settled(b)
        b.driver.switch_to.window(second)
        b.wait_for(lambda: b.live() and b.text("cmd-pos") == str(start + 1500) and
                   [value(b, t) for t in ("move-target", "move-speed", "move-acc", "move-dec")] ==
                   ["1500", "30000", "200", ""], 10, "the second tab, live, showing the move sent")
        assert enter_hint(b) == ["btn-move-inc"]
        press(b, "move-speed", Keys.ENTER)  # repeats the move sent, not this tab's old one
        b.wait_for(lambda: b.text("cmd-pos") == str(start + 3000), 10, "Enter in the second tab: INC 1500")
        settled(b)
    finally:
        b.driver.switch_to.window(second)
        b.driver.close()
        b.driver.switch_to.window(first)


def test_8_every_stop_button_names_what_it_stops(desk):
    """Issue: three buttons read STOP (the axis, the recording, the motion test)."""
    b = desk.b
    b.tab("tab-axis")
    assert b.text("btn-stop") == "STOP AXIS"
    b.tab("tab-test")
    assert b.text("btn-mt-stop") == "STOP TEST"
    b.tab("tab-raw")
    assert b.text("btn-capture-stop").split("\n")[-1] == "STOP RECORDING"  # after its icon's name
    buttons = b.js("""return Array.from(document.querySelectorAll('button'))
                      .map(e => e.innerText.trim().split('\\n').pop()).filter(t => /^stop$/i.test(t));""")
    assert buttons == []


def test_3_a_motion_test_ends_at_the_first_lost_connection(desk):
    b = desk.b
    b.tab("tab-axis")
    b.click("btn-servo-on")
    b.wait_for(lambda: "on" in lamp(b, "servo_on"), 5, "servo on")
    b.tab("tab-test")
    b.type("mt-cycles", "5")
    b.type("mt-distance", "20000")
    b.type("mt-speed", "20000")  # about a second per move
    b.click("btn-mt-start")
    b.wait_for(lambda: b.text("mt-summary") == "running", 5, "the motion test running")
    B.stop(desk.bench)
    summary = b.wait_for(lambda: b.text("mt-summary").startswith(("PASS", "FAIL")) and b.text("mt-summary"),
                         15, "the end of the motion test")
    rows = b.js("""return document.querySelectorAll('[data-testid="mt-table"] tbody tr').length""")
    assert summary == "FAIL: 0 of 1 moves passed (connection lost)", summary
    assert rows == 1
    assert b.text("conn-state") == "CONNECTION LOST"


# --- defects that need a bench or a Desk of their own ------------------------------------------------------
def header_choices(b):
    b.el("axis-select").click()
    b.wait_for(lambda: b.js("return document.querySelectorAll('.q-menu .q-item').length") > 0, 5, "the choices")
    items = b.js("return Array.from(document.querySelectorAll('.q-menu .q-item')).map(e => e.innerText.trim());")
    esc_closes = b.js("return document.querySelectorAll('.q-menu').length")
    if esc_closes:
        esc(b)  # a dropdown takes Esc for itself
        b.wait_for(lambda: b.js("return document.querySelectorAll('.q-menu').length") == 0, 5, "closed")
    return items


def slave_rows(b):
    return b.js("""return Array.from(document.querySelectorAll('[data-testid="slave-table"] tbody tr'))
                   .map(tr => Array.from(tr.children).map(td => td.innerText.trim()));""")


def test_9_a_mixed_bus_is_scanned_per_slave_variant_and_the_jig_is_never_an_axis(desk):
    """Issue: on a Ver8 jig with drive 2 Ver6 and drive 3 Ver8 the Desk listed the jig and drive 3
    as "answered with an error", picked slave 1 as the axis and failed every call."""
    b = desk.b
    bench = page_proc = None
    try:
        bench, url = B.start_bench("2,3:v8", "--jig-protocol", "8")
        page_proc, page = B.start_desk("--port", url, "--timeout", "300")
        b.open(page)
        b.wait_for(lambda: b.text("conn-state") == "connected: %s @ 115200" % url, 10, "connected")
        b.tab("tab-connect")
        b.click("btn-scan")
        b.wait_for(lambda: b.text("scan-progress") == "3 slave(s): ids 1, 2, 3", 20, "scan result")
        rows = {r[0]: r for r in slave_rows(b)}
        assert rows["1"][2] == "MotorJig bridge" and rows["1"][4] == "Ver8" and rows["1"][5].startswith("jig")
        assert rows["2"][2] == "Ezi-STEP Plus-R ST" and rows["2"][4] == "Ver6" and rows["2"][5] == "driver"
        assert rows["3"][2] == "Ezi-STEP Plus-R ST" and rows["3"][4] == "Ver8" and rows["3"][5] == "driver"
        assert "answered with an error" not in b.driver.page_source
        b.wait_for(lambda: b.text("axis-select").endswith("2 Ezi-STEP Plus-R ST (Ver6)"), 5, "axis 2")
        assert b.text("protocol") == "auto: Ver6"
        choices = header_choices(b)
        assert choices == ["2 Ezi-STEP Plus-R ST (Ver6)", "3 Ezi-STEP Plus-R ST (Ver8)"], choices
        assert "1" not in b.text("axis-pick")  # the jig is not offered on Connect & bus either
        for axis, ver in ((3, 8), (2, 6)):
            b.choose("axis-select", "%d Ezi-STEP Plus-R ST (Ver%d)" % (axis, ver))
            b.wait_for(lambda: b.text("protocol") == "auto: Ver%d" % ver, 5, "the axis's variant in the header")
            b.tab("tab-axis")
            servo_on(b)
            start = settled(b)
            b.type("move-target", "1000")
            b.type("move-speed", "40000")
            b.click("btn-move-inc")
            b.wait_for(lambda: b.text("cmd-pos") == str(start + 1000), 10, "slave %d moved" % axis)
            b.tab("tab-connect")
    finally:
        B.stop(page_proc)
        B.stop(bench)


@pytest.fixture(scope="module")
def read_only(desk):
    """A read-only Desk of its own on a bench with a fixed TCP port (so it can come back on it)."""
    port = B.free_port()
    ro = type("ReadOnly", (), {"port": port, "bench": None, "proc": None})
    try:
        ro.bench, ro.bench_url = B.start_bench("2,3", "--tcp-port", str(port))
        ro.proc, ro.url = B.start_desk("--port", ro.bench_url, "--timeout", "300", "--read-only")
        yield ro
    finally:
        B.stop(ro.proc)
        B.stop(ro.bench)


def test_9_read_only_lets_the_operator_choose_the_axis_to_watch(desk, read_only):
    """Issue: choosing the axis to watch was refused in read-only."""
    b = desk.b
    b.open(read_only.url)
    assert b.text("read-only") == "READ-ONLY"
    b.wait_for(lambda: b.text("axis-select").startswith("2 Ezi-STEP"), 10, "axis 2")
    b.el("axis-select").click()
    b.wait_for(lambda: b.js("return document.querySelectorAll('.q-menu .q-item').length") >= 2, 5, "the choices")
    b.js("""Array.from(document.querySelectorAll('.q-menu .q-item'))
            .find(e => e.innerText.startsWith('3 ')).click();""")
    b.wait_for(lambda: b.text("axis-select").startswith("3 Ezi-STEP"), 5, "axis 3 chosen")
    b.tab("tab-axis")
    b.wait_for(lambda: b.text("cmd-pos").lstrip("-").isdigit(), 5, "slave 3's status")
    assert "refused" not in b.driver.page_source
    b.open(read_only.url)  # the session's choice, not only this tab's
    b.wait_for(lambda: b.text("axis-select").startswith("3 Ezi-STEP"), 5, "axis 3 after a reload")


def test_a_refused_move_leaves_the_enter_mark_where_it_was(desk, read_only):
    """Issue 31: in read-only, a refused MOVE DEC still moved ⏎ onto that button."""
    b = desk.b
    b.open(read_only.url)
    b.tab("tab-axis")
    b.wait_for(lambda: b.text("cmd-pos").lstrip("-").isdigit(), 10, "the live status")
    before = enter_hint(b)
    b.click("btn-move-dec")
    b.wait_for(lambda: "read-only" in b.driver.page_source.replace(">READ-ONLY<", ""), 5, "the refusal")
    assert enter_hint(b) == before


def test_9_read_only_reconnects_on_request_and_by_itself(desk, read_only):
    """Issue: a read-only Desk refused Reconnect after a lost connection ("this Desk is read-only"),
    and nothing reconnected by itself."""
    b = desk.b
    b.open(read_only.url)
    b.tab("tab-axis")
    b.wait_for(lambda: b.text("cmd-pos").lstrip("-").isdigit(), 10, "the live status")
    B.stop(read_only.bench)
    b.wait_for(lambda: b.visible("lost-banner"), 10, "the lost banner")
    b.click("btn-reconnect")  # the bench is down: the sentence says so, not "read-only"
    b.wait_for(lambda: "connection refused" in b.driver.page_source or "read-only" in b.driver.page_source
               .replace(">READ-ONLY<", ""), 5, "the reconnect's answer")
    assert "this Desk is read-only" not in b.driver.page_source
    read_only.bench, url = B.start_bench("2,3", "--tcp-port", str(read_only.port))
    assert url == read_only.bench_url
    b.wait_for(lambda: b.text("conn-state") == "connected: %s @ 115200" % url and not b.visible("lost-banner"),
               15, "connected again by itself")
    b.wait_for(lambda: b.text("cmd-pos").lstrip("-").isdigit(), 5, "the status again")
