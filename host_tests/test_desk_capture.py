"""The Desk's recording of both buses through the jig (issue 19): the raw-frames tab's
Start / Stop / Download pcapng, in Debian's headless Chromium against the virtual bench.

``DeskCapture`` first on its own against a real-time bench (start, traffic, stop,
the pcapng read by the capture tests' own reader and by tshark with the dissector,
its failures as one sentence); then the page: a Desk on a bench's PC port with
``--capture-port`` (as for a real jig) records, stops and downloads a pcapng that
tshark reads with records of both buses; a Desk started with ``--bench`` knows the
bench's capture port; a Desk without one greys the controls out and says why.
"""

import os
import threading
import time

import pytest
import serial

import desk_browser as B
from test_capture_support import TSHARK, needs_tshark, parse_pcapng, run_tshark

from jig import frame as F
from motorjig.capture import record as R
from motorjig.errors import JigError
from motorjig.desk import server
from motorjig.desk.capture import NO_PORT, DeskCapture
from motorjig.desk.session import UserError
from motorjig.sim import Bench

WHY_NOT = B.browser_missing()
browser_test = pytest.mark.skipif(bool(WHY_NOT) and os.environ.get("CI") != "true",
                                  reason="browser tests need Chromium here: %s" % WHY_NOT)

LINKTYPES = {147: "pc", 148: "drivers"}


def ask(ser, slave, ftype):
    ser.reset_input_buffer()
    ser.write(F.encode(slave, ftype))
    out = b""
    end = time.monotonic() + 1.0
    while not out.endswith(b"\xaa\xee") and time.monotonic() < end:
        out += ser.read(64)
    return out


def buses_of(data):
    """{interface name: [packet bytes]} of a pcapng file, by the capture tests' own reader."""
    f = parse_pcapng(data)
    names = [LINKTYPES[i["linktype"]] for i in f["interfaces"]]
    assert [i["options"][2].decode() for i in f["interfaces"]] == names == ["pc", "drivers"]
    out = {n: [] for n in names}
    for p in f["packets"]:
        out[names[p["interface"]]].append(p["data"])
    return out


def tshark_rows(path):
    """(interface, id, type, kind) of every packet, as tshark with the dissector reads the file."""
    res = run_tshark(["-r", path, "-2", "-T", "fields", "-E", "separator=\t", "-e", "frame.interface_name",
                      "-e", "plusr.id", "-e", "plusr.type", "-e", "plusr.kind"])
    assert res.returncode == 0, res.stderr
    assert "Lua" not in res.stderr.replace('Running as user "root"', ""), res.stderr
    return [tuple(line.split("\t")) for line in res.stdout.splitlines()]


# --- DeskCapture on its own ------------------------------------------------------------------
@pytest.fixture(scope="module")
def bench():
    with Bench(driver_ids=(2, 3), pty=False) as b:
        yield b


def test_without_a_capture_port_every_action_says_why():
    cap = DeskCapture(None)
    assert cap.unavailable == NO_PORT and cap.summary() == NO_PORT
    for action in (cap.start, cap.stop, cap.pcapng):
        with pytest.raises(UserError) as exc:
            action()
        assert "--capture-port" in str(exc.value) and "\n" not in str(exc.value)


def test_a_port_that_is_not_there_is_one_sentence():
    cap = DeskCapture("/dev/ttyMOTORJIG-NO-CAPTURE")
    with pytest.raises(UserError) as exc:
        cap.start()
    assert str(exc.value).startswith("cannot open /dev/ttyMOTORJIG-NO-CAPTURE")
    assert cap.state == "idle" and not cap.recording
    with pytest.raises(UserError) as exc:
        cap.pcapng()
    assert str(exc.value).startswith("nothing recorded yet")


def test_start_traffic_stop_and_the_file_has_both_buses(bench, tmp_path):
    cap = DeskCapture(bench.capture_url)
    assert "nothing recorded yet" in cap.summary()
    msg = cap.start()
    assert msg.startswith("recording both buses from %s (MotorJig bridge" % bench.capture_url)
    assert cap.recording and bench.sim.app.capture.on
    with pytest.raises(UserError) as exc:
        cap.start()
    assert str(exc.value) == "already recording: press STOP RECORDING first"
    with serial.serial_for_url(bench.tcp_url, timeout=0.05) as pc:
        replies = [ask(pc, 2, F.GET_COMMAND_POS), ask(pc, 3, F.GET_AXIS_STATUS), ask(pc, 1, F.GET_SLAVE_INFO)]
        assert ask(pc, 9, F.GET_COMMAND_POS) == b""  # an absent id: a request without a reply
    assert all(r.endswith(b"\xaa\xee") for r in replies)
    end = time.monotonic() + 3.0
    while cap.per_bus != [7, 6] and time.monotonic() < end:
        time.sleep(0.05)
    # PC bus: 4 requests, 3 replies; driver bus: 3 forwarded (2, 3, 9), 2 replies, and the stub of
    # the request to the jig itself (cut through: its header went out before its id was known)
    assert cap.per_bus == [7, 6]
    assert cap.summary().startswith("recording: 13 records in ")
    stopped = cap.stop()
    assert stopped.startswith("recording stopped: 13 records in ") and not cap.recording
    time.sleep(0.1)
    assert not bench.sim.app.capture.on  # X reached the jig ...
    end = time.monotonic() + 2.0
    while bench.sim.capture.is_open and time.monotonic() < end:
        time.sleep(0.05)
    assert not bench.sim.capture.is_open  # ... and the port is free for the next reader
    data = cap.pcapng()
    by_bus = buses_of(data)
    assert by_bus["pc"] == [F.encode(2, F.GET_COMMAND_POS), replies[0], F.encode(3, F.GET_AXIS_STATUS), replies[1],
                            F.encode(1, F.GET_SLAVE_INFO), replies[2], F.encode(9, F.GET_COMMAND_POS)]
    assert by_bus["drivers"] == [F.encode(2, F.GET_COMMAND_POS), replies[0], F.encode(3, F.GET_AXIS_STATUS),
                                 replies[1], b"\xaa\xcc\x01\xaa\xee", F.encode(9, F.GET_COMMAND_POS)]
    assert cap.pcapng() == data  # the download again: the same file
    with pytest.raises(UserError) as exc:
        cap.stop()
    assert str(exc.value) == "not recording: press Start first"
    if TSHARK:
        path = str(tmp_path / "desk.pcapng")
        with open(path, "wb") as f:
            f.write(data)
        rows = tshark_rows(path)
        assert [r[0] for r in rows].count("pc") == 7 and [r[0] for r in rows].count("drivers") == 6
        assert rows[:4] == [("pc", "2", "0x51", "0"), ("drivers", "2", "0x51", "0"), ("drivers", "2", "0x51", "1"),
                            ("pc", "2", "0x51", "1")]
        assert rows[-2:] == [("pc", "9", "0x51", "0"), ("drivers", "9", "0x51", "0")]
    # A second recording starts afresh
    cap.start()
    with serial.serial_for_url(bench.tcp_url, timeout=0.05) as pc:
        ask(pc, 2, F.GET_COMMAND_POS)
    end = time.monotonic() + 3.0
    while cap.total < 4 and time.monotonic() < end:
        time.sleep(0.05)
    cap.stop()
    assert cap.per_bus == [2, 2] and len(buses_of(cap.pcapng())["pc"]) == 2


class FakeJig:
    """A capture port as DeskCapture's opener returns it: records, then the end given.

    Each call is logged in ``log`` (shared by every port it opens) as (what, port number),
    so a test sees the order in which two recordings touched the port."""

    def __init__(self, log, n, records=(), ends=None, close_s=0.0):
        self.log, self.n, self.recs, self.ends, self.close_s = log, n, records, ends, close_s
        self.go = threading.Event()  # run() returns or raises once set
        self.stream = self

    def start(self):
        self.log.append(("start", self.n))
        return {"version": 1}

    def run(self, sinks):
        for rec in self.recs:
            for sink in sinks:
                sink(rec)
        self.go.wait(5.0)
        if self.ends is not None:
            raise self.ends

    def stop(self):
        self.log.append(("stop", self.n))
        self.go.set()

    def close(self):
        time.sleep(self.close_s)
        self.log.append(("close", self.n))

    def description(self):
        return "fake jig %d" % self.n

    def buses(self):
        return [R.pc_bus(115200), R.driver_bus(115200)]


def frame_record(bus=0):
    return R.Record(bus, 10 ** 15, R.DIR_INBOUND, F.encode(2, F.GET_COMMAND_POS), R.GOOD)


def fake_capture(ports):
    """A DeskCapture whose n-th start opens ports[n]."""
    it = iter(ports)
    return DeskCapture("fake://jig", opener=lambda url: next(it))


def test_a_recording_that_ends_by_itself_has_closed_its_port_before_the_next_starts():
    # The jig's port failed: the read thread closes it (X) by itself. A Start arriving
    # while that close is under way must wait, or the old X would stop the new recording.
    log = []
    first = FakeJig(log, 1, [frame_record()], ends=JigError("the jig stopped recording"), close_s=1.0)
    second = FakeJig(log, 2)
    cap = fake_capture([first, second])
    cap.start()
    first.go.set()
    end = time.monotonic() + 3.0
    while cap.state != "stopped" and time.monotonic() < end:
        time.sleep(0.005)
    assert cap.state == "stopped" and cap.error == "recording ended: the jig stopped recording"
    assert ("close", 1) not in log  # still closing
    cap.start()
    assert log == [("start", 1), ("close", 1), ("start", 2)]
    assert cap.recording and cap.error == "" and cap.total == 0
    assert cap.stop().startswith("recording stopped: 0 records")
    assert log[-2:] == [("stop", 2), ("close", 2)]


def test_a_start_while_a_stop_is_still_closing_the_port_waits_for_it():
    # Another tab (or a recording without records: no question asked) presses Start while
    # Stop is still sending X and closing: the old X must not reach the new recording.
    log = []
    first, second = FakeJig(log, 1, close_s=1.0), FakeJig(log, 2)
    cap = fake_capture([first, second])
    cap.start()
    stopping = threading.Thread(target=cap.stop)
    stopping.start()
    end = time.monotonic() + 3.0
    while cap.state != "stopped" and time.monotonic() < end:
        time.sleep(0.005)
    assert cap.state == "stopped" and ("close", 1) not in log  # the page's Start is live again
    cap.start()
    stopping.join(5)
    assert log == [("start", 1), ("stop", 1), ("close", 1), ("start", 2)]
    cap.stop()


def test_a_download_that_outlasts_a_new_start_does_not_mark_the_new_recording_downloaded():
    log = []
    ports = [FakeJig(log, 1, [frame_record()]), FakeJig(log, 2, [frame_record()])]
    cap = fake_capture(ports)
    cap.start()
    end = time.monotonic() + 2.0
    while cap.total < 1 and time.monotonic() < end:
        time.sleep(0.005)
    cap.stop()
    records = cap.records

    def records_while_another_tab_starts():
        out = records()
        cap.start()  # the file is still being built when the new recording begins
        return out

    cap.records = records_while_another_tab_starts
    assert len(parse_pcapng(cap.pcapng())["packets"]) == 1
    cap.records = records
    end = time.monotonic() + 2.0
    while cap.total < 1 and time.monotonic() < end:
        time.sleep(0.005)
    cap.stop()
    assert cap.unsaved  # the new recording was never downloaded: Start will ask


def test_a_failure_after_stop_is_not_reported_as_the_recording_s_end():
    log = []
    port = FakeJig(log, 1, [frame_record()], ends=JigError("port gone"))
    cap = fake_capture([port])
    cap.start()
    cap.stop()  # the thread then fails: the user stopped it, nothing ended by itself
    assert cap.error == "" and cap.summary().startswith("1 records in ")
    assert log == [("start", 1), ("stop", 1), ("close", 1)]


def test_unsaved_until_the_finished_recording_is_downloaded():
    log = []
    ports = [FakeJig(log, 1, [frame_record(0), frame_record(1)]), FakeJig(log, 2), FakeJig(log, 3, [frame_record()])]
    cap = fake_capture(ports)
    assert not cap.unsaved
    cap.start()
    end = time.monotonic() + 2.0
    while cap.total < 2 and time.monotonic() < end:
        time.sleep(0.005)
    cap.pcapng()  # a download while recording: what comes next is not in it
    assert not cap.unsaved
    cap.stop()
    assert cap.unsaved
    assert len(parse_pcapng(cap.pcapng())["packets"]) == 2
    assert not cap.unsaved
    cap.start()
    cap.stop()
    assert not cap.unsaved  # nothing recorded: nothing to lose
    cap.start()
    cap.stop()
    assert cap.unsaved and cap.total == 1


def test_the_desk_options():
    p = server.build_parser()
    assert p.parse_args(["--capture-port", "/dev/ttyACM1"]).capture_port == "/dev/ttyACM1"
    assert p.parse_args([]).capture_port is None
    assert "--capture-port" in " ".join(p.format_help().split())


# --- the page --------------------------------------------------------------------------------
def _need_browser():
    if WHY_NOT:  # in CI the setup installs the browser, so its absence is a failure
        pytest.fail("browser tests cannot run: " + WHY_NOT)


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    _need_browser()
    b = B.Browser(downloads=str(tmp_path_factory.mktemp("downloads")))
    try:
        yield b
    finally:
        b.close()


def disabled(b, testid):
    return b.el(testid).get_attribute("disabled") is not None


@browser_test
@needs_tshark
def test_record_stop_and_download_from_the_page(browser):
    b = browser
    bench = page_proc = None
    try:
        bench, url = B.start_bench()
        capture_url = B._read_until(bench, "capture: socket://", 10).split("capture:", 1)[1].strip()
        page_proc, page = B.start_desk("--port", url, "--capture-port", capture_url, "--timeout", "300")
        b.open(page)
        b.tab("tab-raw")
        b.wait_for(lambda: "nothing recorded yet" in b.text("capture-state"), 10, "the recording's state")
        assert capture_url in b.text("capture-state")
        assert disabled(b, "btn-capture-stop") and disabled(b, "btn-capture-download")
        assert not disabled(b, "btn-capture-start")
        b.click("btn-capture-start")
        b.wait_for(lambda: b.text("capture-state").startswith("recording: "), 10, "recording")
        b.wait_for(lambda: disabled(b, "btn-capture-start") and not disabled(b, "btn-capture-stop"), 5,
                   "Start greyed out, Stop live")
        b.type("raw-id", "2")
        b.type("raw-type", "0x51")
        b.click("btn-raw-send")
        b.wait_for(lambda: "frames on the PC bus, 2 on the driver bus" in b.text("capture-state"), 10,
                   "one transaction on both buses")
        b.type("raw-id", "3")
        b.type("raw-type", "0x40")
        b.click("btn-raw-send")
        b.wait_for(lambda: ": 4 frames on the PC bus, 4 on the driver bus" in b.text("capture-state"), 10,
                   "two transactions")
        b.click("btn-capture-stop")
        b.wait_for(lambda: b.text("capture-state").startswith("8 records in "), 10, "stopped")
        assert not disabled(b, "btn-capture-start") and not disabled(b, "btn-capture-download")
        # Start again before downloading: the page asks before it replaces the recording
        b.click("btn-capture-start")
        b.wait_for(lambda: b.visible("capture-replace-text"), 5, "the replace question")
        assert b.text("capture-replace-text").startswith("The last recording (8 records in ")
        b.click("btn-capture-replace-cancel")
        b.wait_for(lambda: not b.visible("capture-replace-text"), 5, "the question closed")
        assert b.text("capture-state").startswith("8 records in ")  # nothing started, nothing lost
        b.click("btn-capture-start")
        b.wait_for(lambda: b.visible("btn-capture-replace-download"), 5, "the replace question")
        b.click("btn-capture-replace-download")  # its Download saves the file, as the row's button
        path = b.wait_for(lambda: [os.path.join(b.downloads, n) for n in os.listdir(b.downloads)
                                   if n.endswith(".pcapng")], 10, "the pcapng file")[0]
        assert os.path.basename(path).startswith("motorjig-capture-")
        with open(path, "rb") as f:
            data = f.read()
        by_bus = buses_of(data)
        assert by_bus["pc"][0::2] == by_bus["drivers"][0::2] == [F.encode(2, 0x51), F.encode(3, 0x40)]
        assert by_bus["pc"][1::2] == by_bus["drivers"][1::2]  # replies relayed unchanged
        rows = tshark_rows(path)
        assert [(r[0], r[1], r[2], r[3]) for r in rows] == [
            ("pc", "2", "0x51", "0"), ("drivers", "2", "0x51", "0"), ("drivers", "2", "0x51", "1"),
            ("pc", "2", "0x51", "1"), ("pc", "3", "0x40", "0"), ("drivers", "3", "0x40", "0"),
            ("drivers", "3", "0x40", "1"), ("pc", "3", "0x40", "1")]
        # Downloaded: Start begins a new recording at once
        b.click("btn-capture-start")
        b.wait_for(lambda: b.text("capture-state").startswith("recording: "), 10, "a new recording")
        assert not b.visible("capture-replace-text")
        b.click("btn-raw-send")
        b.wait_for(lambda: ": 2 frames on the PC bus, 2 on the driver bus" in b.text("capture-state"), 10,
                   "one transaction")
        b.click("btn-capture-stop")
        b.wait_for(lambda: b.text("capture-state").startswith("4 records in "), 10, "stopped")
        b.click("btn-capture-start")  # not downloaded: asked, and this time replaced
        b.wait_for(lambda: b.visible("btn-capture-replace-yes"), 5, "the replace question")
        b.click("btn-capture-replace-yes")
        b.wait_for(lambda: b.text("capture-state").startswith("recording: 0 records in "), 10, "replaced")
        b.click("btn-capture-stop")
    finally:
        B.stop(page_proc)
        B.stop(bench)


@browser_test
def test_bench_mode_knows_the_capture_port_and_a_desk_without_one_says_why(browser):
    b = browser
    proc = other = None
    try:
        proc, page = B.start_desk("--bench")
        early = "".join(proc.early)
        assert "  the jig's capture port: socket://127.0.0.1:" in early
        capture_url = early.split("the jig's capture port: ", 1)[1].split()[0]
        b.open(page)
        b.tab("tab-raw")
        b.wait_for(lambda: "nothing recorded yet" in b.text("capture-state"), 10, "the recording's state")
        assert capture_url in b.text("capture-state") and not disabled(b, "btn-capture-start")
        bench_url = early.split("other programs can use ", 1)[1].split()[0]
        other, page2 = B.start_desk("--port", bench_url)  # no --capture-port
        b.open(page2)
        b.tab("tab-raw")
        b.wait_for(lambda: b.text("capture-state") == NO_PORT, 10, "why there is no recording")
        for testid in ("btn-capture-start", "btn-capture-stop", "btn-capture-download"):
            assert disabled(b, testid)
    finally:
        B.stop(other)
        B.stop(proc)
