"""The station's report outputs (JUnit XML, HTML report) on records of real OpenHTF runs.

Each record comes from running an OpenHTF Test of small fake phases (no hardware)
in the main thread with the console silenced, written by OutputToJSON and read
back with json.load, exactly as the station saves it. The HTML report is also
opened in Debian's headless Chromium (see desk_browser.py).

    .venv/bin/python host_tests/test_station_reports.py [PNG]

renders the README's screenshot (default docs/station-report.png) from a realistic run.
"""

import contextlib
import json
import math
import os
import signal
import sys
import threading
import time

if __name__ == "__main__":  # run as a script: the import paths conftest.py gives pytest
    for _sub in ("tools", "host_tests"):
        sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), _sub))

import pytest  # noqa: E402

_sigint = signal.getsignal(signal.SIGINT)
htf = pytest.importorskip("openhtf", reason="openhtf is not installed (make setup)")
signal.signal(signal.SIGINT, _sigint)  # importing openhtf installs its own Ctrl-C handler
xmlschema = pytest.importorskip("xmlschema", reason="xmlschema is not installed (make setup)")

from openhtf import plugs  # noqa: E402
from openhtf.output.callbacks import json_factory  # noqa: E402
from openhtf.util import configuration, console_output, threads, units, validators  # noqa: E402

from motorjig.station import junit, report  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PULSE = units.UnitDescriptor("pulse", "pulse", "pulse")
PPS = units.UnitDescriptor("pps", "pps", "pps")
PLAN = "MJ-motion-basic"
META = {"test_version": "1.3", "plan_hash": "3f6c9a0e5d1b2c4a8e7f6d5c4b3a29181716151413121110f0e0d0c0b0a09080",
        "plan_file": "plans/motion-basic.toml", "operator": "j.doe",
        "drive": {"slave": 2, "protocol": 6, "slave_type": 20, "name": "Ezi-STEP Plus-R ST v6.0"}}


# --- running OpenHTF ----------------------------------------------------------------------------

@contextlib.contextmanager
def _quiet_openhtf(station):
    """No console output, no pytest arguments parsed as OpenHTF flags, our station id."""
    conf = configuration.CONF
    saved = sys.argv, console_output.CLI_QUIET, threading.excepthook, conf.station_id

    def excepthook(args):  # an aborted phase's thread ends in OpenHTF's ThreadTerminationError: expected
        if not issubclass(args.exc_type, threads.ThreadTerminationError):
            saved[2](args)

    sys.argv, console_output.CLI_QUIET, threading.excepthook = sys.argv[:1], True, excepthook
    conf.load(station_id=station)
    try:
        yield
    finally:
        sys.argv, console_output.CLI_QUIET, threading.excepthook = saved[:3]
        conf.load(station_id=saved[3])


def run_plan(tmp_path, *phases, plan=PLAN, dut="MJ-2403-0117", station="jig-bench-01", plug=None, **meta):
    """(the record dict read back from OutputToJSON's file, the TestRecord object) of a real run."""
    path = str(tmp_path / ("%s.json" % len(os.listdir(str(tmp_path)))))
    records = []
    with _quiet_openhtf(station):
        test = htf.Test(*phases, test_name=plan, **dict(META, **meta))
        test.configure(default_dut_id=dut)
        test.add_output_callbacks(json_factory.OutputToJSON(path, inline_attachments=True, indent=2), records.append)
        RUNNING[:] = [test]
        test.execute()
    with open(path, encoding="utf-8") as f:
        return json.load(f), records[0]


RUNNING = []  # the Test being executed, for the phase that aborts it


class LessThan(validators.ValidatorBase):
    """A validator of the station's own kind: x < limit."""

    def __init__(self, limit):
        self.limit = limit

    def __call__(self, value):
        return value is not None and value < self.limit

    def __str__(self):
        return "x < %s" % self.limit


def trapezoid(distance, vmax, accel, start=0, stall_at=None, dt=0.004):
    """A trace attachment of a trapezoidal move; the actual position lags the command and
    stops at stall_at (a fraction of the move) when given."""
    ta = min(vmax / accel, math.sqrt(abs(distance) / accel))
    vpk = accel * ta
    tc = max(0.0, (abs(distance) - accel * ta * ta) / vpk)
    total = 2 * ta + tc
    sign = 1 if distance >= 0 else -1

    def cmd(t):
        t = min(max(t, 0.0), total)
        if t < ta:
            s = 0.5 * accel * t * t
        elif t < ta + tc:
            s = 0.5 * accel * ta * ta + vpk * (t - ta)
        else:
            td = total - t
            s = abs(distance) - 0.5 * accel * td * td
        return start + sign * s

    rows, actual, lag = [], float(start), 0.012
    n = int((total + 0.15) / dt) + 1
    for i in range(n):
        t = i * dt
        new = cmd(t - lag) + 0.4 * math.sin(t * 70) * (t < total)  # a little servo ripple
        if stall_at is not None and abs(new - start) > stall_at * abs(distance):
            new = actual
        vel = (new - actual) / dt if i else 0.0
        actual = new
        rows.append([round(t, 4), round(cmd(t)), round(actual), round(vel)])
    return {"columns": ["t", "command", "actual", "velocity"],
            "units": {"t": "s", "command": "pulse", "actual": "pulse", "velocity": "pps"},
            "rows": rows, "target": start + distance}


def move_phase(name, distance, vmax=8000, accel=60000, start=0, stall_at=None):
    trace = trapezoid(distance, vmax, accel, start, stall_at)

    @htf.PhaseOptions(name=name)
    @htf.measures(htf.Measurement("final_position_error").in_range(-10, 10).with_units(PULSE),
                  htf.Measurement("peak_velocity").in_range(0.9 * vmax, 1.1 * vmax).with_units(PPS),
                  htf.Measurement("settle_time").with_validator(LessThan(0.2)).with_units(units.SECOND),
                  htf.Measurement("alarm").equals(0))
    def move(test):
        rows = trace["rows"]
        test.measurements.final_position_error = rows[-1][2] - trace["target"]
        test.measurements.peak_velocity = max(abs(r[3]) for r in rows)
        test.measurements.settle_time = 0.012 if stall_at is None else 0.35
        test.measurements.alarm = 0
        test.attach("trace", json.dumps(trace), mimetype="application/json")

    return move


@htf.measures(htf.Measurement("protocol").equals(6), htf.Measurement("slave_type").equals(20))
def identify_drive(test):
    test.measurements.protocol = 6
    test.measurements.slave_type = 20


@htf.measures(htf.Measurement("down_crc_errors").in_range(maximum=0),
              htf.Measurement("timeouts").in_range(maximum=0),
              htf.Measurement("turnaround_max").in_range(maximum=2000).with_units(units.MICROSECOND))
def bus_health(test):
    counters = {"up_frames_ok": 1834, "up_crc_errors": 0, "down_frames_ok": 1834, "down_crc_errors": 0,
                "timeouts": 0, "turnaround_min_us": 212, "turnaround_avg_us": 288, "turnaround_max_us": 941}
    test.measurements.down_crc_errors = counters["down_crc_errors"]
    test.measurements.timeouts = counters["timeouts"]
    test.measurements.turnaround_max = counters["turnaround_max_us"]
    test.attach("bus_counters", json.dumps(counters), mimetype="application/json")


def skip_brake_check(test):
    return htf.PhaseResult.SKIP


def lost_drive(test):
    raise ConnectionError("slave 2 did not answer <GetAxisStatus> after 3 retries")


def aborts_run(test):
    threading.Thread(target=RUNNING[0].abort_from_sig_int).start()  # what Ctrl-C does, from the main thread
    for _ in range(200):  # the abort stops the phase thread between two short sleeps
        time.sleep(0.01)


class DeadPort(plugs.BasePlug):
    def __init__(self):
        raise ConnectionError("serial port /dev/ttyUSB0 vanished")


@plugs.plug(port=DeadPort)
def needs_port(test, port):
    pass


MOVES = [("move_abs_10000", 10000, 0, None), ("move_abs_0", -10000, 10000, None),
         ("move_inc_2000", 2000, 0, None), ("move_inc_4000_stall", 4000, 2000, 0.75)]


def realistic_phases(fail=True):
    moves = MOVES if fail else MOVES[:3]
    return [identify_drive] + [move_phase(n, d, start=s, stall_at=st) for n, d, s, st in moves] + [bus_health]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The records of the runs the tests look at, each run once."""
    tmp = tmp_path_factory.mktemp("records")
    mixed = [identify_drive, move_phase("move_abs_10000", 10000), move_phase("move_stall", 4000, stall_at=0.8),
             skip_brake_check, lost_drive, bus_health]
    return {
        "pass": run_plan(tmp, *realistic_phases(fail=False)),
        "fail": run_plan(tmp, *realistic_phases()),
        "mixed": run_plan(tmp, *mixed),
        "aborted": run_plan(tmp, identify_drive, aborts_run, bus_health),
        "no_port": run_plan(tmp, identify_drive, needs_port),
        "inject": run_plan(tmp, identify_drive, plan="<script>alert('plan')</script>", dut="<b>x</b>&amp;",
                           operator='"><img src=x onerror=alert(1)>'),
    }


def test_the_runs_have_the_outcomes_the_reports_are_tested_on(runs):
    assert {k: r["outcome"] for k, (r, _) in runs.items()} == {
        "pass": "PASS", "fail": "FAIL", "mixed": "ERROR", "aborted": "ABORTED", "no_port": "ERROR", "inject": "PASS"}
    mixed = runs["mixed"][0]
    assert [p["outcome"] for p in mixed["phases"]] == ["PASS", "PASS", "FAIL", "SKIP", "ERROR"]
    assert runs["no_port"][0]["phases"] == []  # OpenHTF opens every plug before the first phase


# --- JUnit XML ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def schema():
    return xmlschema.XMLSchema(junit.SCHEMA)


def _suite(xml_text):
    import xml.etree.ElementTree as ET

    root = ET.fromstring(xml_text.encode("utf-8"))
    assert root.tag == "testsuites" and len(root) == 1
    return root, root[0]


@pytest.mark.parametrize("run", ["pass", "fail", "mixed", "aborted", "no_port", "inject"])
def test_junit_is_schema_valid_for_every_kind_of_run(runs, schema, run):
    text = junit.junit_xml(runs[run][0])
    assert text.startswith('<?xml version="1.0" encoding="UTF-8"?>')
    schema.validate(text)


VALID_JUNIT = """<testsuites tests="4" failures="1" errors="1" skipped="1" time="1.5">
 <testsuite name="p" tests="4" failures="1" errors="1" skipped="1" time="1.5" timestamp="2026-01-02T03:04:05"
            hostname="h"><properties><property name="k" value="v"/></properties>
  <testcase name="a" classname="p" time="0.5"/>
  <testcase name="b" classname="p" time="0"><failure message="m" type="measurement">text</failure>
   <system-out>out</system-out></testcase>
  <testcase name="c"><error message="m" type="E">tb</error></testcase>
  <testcase name="d"><skipped/></testcase>
  <system-out/><system-err/>
 </testsuite>
</testsuites>"""


def test_the_schema_accepts_the_documented_format(schema):
    schema.validate(VALID_JUNIT)


@pytest.mark.parametrize("broken", [
    ("testcase without name", '<testsuites><testsuite name="p" tests="1"><testcase classname="p"/></testsuite></testsuites>'),
    ("testsuite without tests", '<testsuites><testsuite name="p"/></testsuites>'),
    ("testsuite without name", '<testsuites><testsuite tests="0"/></testsuites>'),
    ("failure directly in the suite", '<testsuites><testsuite name="p" tests="0"><failure message="m"/></testsuite></testsuites>'),
    ("testcase directly in testsuites", '<testsuites><testcase name="c"/></testsuites>'),
    ("non-numeric count", '<testsuites><testsuite name="p" tests="three"/></testsuites>'),
    ("time with a unit", '<testsuites><testsuite name="p" tests="1"><testcase name="c" time="1.5s"/></testsuite></testsuites>'),
    ("negative count", '<testsuites><testsuite name="p" tests="-1"/></testsuites>'),
    ("bad timestamp", '<testsuites><testsuite name="p" tests="0" timestamp="yesterday"/></testsuites>'),
    ("two outcomes", '<testsuites><testsuite name="p" tests="1"><testcase name="c"><skipped/><failure/></testcase>'
                     '</testsuite></testsuites>'),
], ids=lambda b: b[0])
def test_the_schema_rejects_broken_reports(schema, broken):
    assert not schema.is_valid(broken[1])


def test_junit_counts_and_suite_attributes(runs):
    record = runs["mixed"][0]
    root, suite = _suite(junit.junit_xml(record))
    assert suite.get("name") == PLAN and suite.get("hostname") == "jig-bench-01"
    assert (suite.get("tests"), suite.get("failures"), suite.get("errors"), suite.get("skipped")) == ("5", "1", "1", "1")
    assert [root.get(k) for k in ("tests", "failures", "errors", "skipped")] == ["5", "1", "1", "1"]
    assert suite.get("timestamp").startswith(report.utc_time(record["start_time_millis"], sep="T")[:16])
    props = {p.get("name"): p.get("value") for p in suite.find("properties")}
    assert props["dut_id"] == "MJ-2403-0117" and props["plan_version"] == "1.3" and props["operator"] == "j.doe"
    assert props["plan_hash"] == META["plan_hash"] and props["station"] == "jig-bench-01" and props["outcome"] == "ERROR"
    cases = suite.findall("testcase")
    assert [c.get("name") for c in cases] == [p["name"] for p in record["phases"]]
    assert {c.get("classname") for c in cases} == {PLAN}
    assert all(float(c.get("time")) >= 0 for c in cases)
    assert cases[0].find("failure") is None and cases[0].find("error") is None
    assert cases[3].find("skipped") is not None


def test_junit_failure_names_the_measurement_value_unit_and_limit(runs):
    _, suite = _suite(junit.junit_xml(runs["mixed"][0]))
    failure = suite.find("testcase[@name='move_stall']/failure")
    assert failure.get("type") == "measurement"
    message = failure.get("message")
    err = [p for p in runs["mixed"][0]["phases"] if p["name"] == "move_stall"][0]["measurements"]["final_position_error"]
    assert "final_position_error = %d pulse, outside -10 <= x <= 10" % err["measured_value"] in message
    assert "settle_time = 0.35 s, outside x < 0.2" in message  # the custom validator's string form
    assert failure.text.splitlines() == message.split("; ")  # every failing measurement in the body too


def test_junit_error_carries_the_exception_type_and_message(runs):
    _, suite = _suite(junit.junit_xml(runs["mixed"][0]))
    error = suite.find("testcase[@name='lost_drive']/error")
    assert error.get("type") == "ConnectionError"
    assert error.get("message") == "ConnectionError: slave 2 did not answer <GetAxisStatus> after 3 retries"
    assert "Traceback" in error.text and "lost_drive" in error.text


@pytest.mark.parametrize("run,case,etype,message", [
    # a plug could not open the port: no phase ran, the run itself is the erroring testcase
    ("no_port", junit.RUN_CASE, "ConnectionError", "ConnectionError: serial port /dev/ttyUSB0 vanished"),
    # Ctrl-C: the phase it stopped records no exception, the run's outcome details say why
    ("aborted", "aborts_run", "ABORTED", "ABORTED: Test aborted by operator."),
])
def test_a_run_that_ended_in_error_outside_a_phase_exception_is_an_error_in_ci(runs, schema, run, case, etype, message):
    text = junit.junit_xml(runs[run][0])
    schema.validate(text)
    _, suite = _suite(text)
    assert suite.get("errors") == "1" and suite.get("tests") == str(len(suite.findall("testcase")))
    errors = suite.findall("testcase/error")
    assert len(errors) == 1
    assert suite.find("testcase[@name='%s']/error" % case) is errors[0]
    assert (errors[0].get("type"), errors[0].get("message")) == (etype, message)


def refused_drive(test):
    from motorjig.station.runner import PreflightError

    raise PreflightError("the plan is for slave type 1, but slave 2 is type 20: nothing was moved")


def no_terminal(test):
    from motorjig.station.runner import PreflightError

    raise PreflightError("the plan asks the operator to confirm 'motor on': run on a terminal or with --yes")


def aborted_before(test):
    from motorjig.station.phases import RunAborted

    raise RunAborted("aborted before step move")


def drive_went_quiet(test):
    from motorjig.errors import NoReplyError

    raise NoReplyError("slave 2 did not answer GetAllStatus (3 tries)")


def a_bug(test):
    return {}["oops"]


@pytest.mark.parametrize("phase, etype, sentence", [
    (refused_drive, "motorjig.station.runner.PreflightError", "the plan is for slave type 1, but slave 2 is type 20"),
    (no_terminal, "motorjig.station.runner.PreflightError", "run on a terminal or with --yes"),
    (aborted_before, "motorjig.station.phases.RunAborted", "aborted before step move"),
    (drive_went_quiet, "motorjig.errors.NoReplyError", "slave 2 did not answer GetAllStatus"),
])
def test_an_expected_refusal_is_a_sentence_without_a_traceback(tmp_path, schema, phase, etype, sentence):
    record, _ = run_plan(tmp_path, identify_drive, phase)
    text = junit.junit_xml(record)
    schema.validate(text)
    _, suite = _suite(text)
    error = suite.find("testcase[@name='%s']/error" % phase.__name__)
    assert error.get("type") == etype
    assert sentence in error.get("message") and error.text == error.get("message")
    assert "Traceback" not in text and "File \"" not in text
    page = report.html_report(record)
    assert "Traceback" not in page and sentence.replace("'", "&#x27;") in page


def test_an_unexpected_exception_keeps_its_traceback(tmp_path, schema):
    record, _ = run_plan(tmp_path, identify_drive, a_bug)
    _, suite = _suite(junit.junit_xml(record))
    error = suite.find("testcase[@name='a_bug']/error")
    assert error.get("type") == "KeyError" and error.get("message") == "KeyError: 'oops'"
    assert error.text.startswith("Traceback") and "a_bug" in error.text
    assert "Traceback" in report.html_report(record)


def test_the_expected_exception_names_are_real_classes():
    import importlib

    for name in report.EXPECTED_EXCEPTIONS:
        module, _, cls = name.rpartition(".")
        assert isinstance(getattr(importlib.import_module(module or "builtins"), cls), type), name
    from motorjig import errors

    assert report.expected_exception("%s.%s" % (errors.NoReplyError.__module__, errors.NoReplyError.__name__))


def test_junit_escapes_names_and_messages(runs):
    text = junit.junit_xml(runs["inject"][0])
    assert "<script>" not in text and "&lt;script&gt;" in text
    _, suite = _suite(text)
    assert suite.get("name") == "<script>alert('plan')</script>"


def control_bytes(test):
    raise ValueError("reply \x00\x1b[31m garbled\x1b[0m")


def test_junit_survives_control_characters_in_messages(tmp_path, schema):
    import xml.etree.ElementTree as ET

    record, _ = run_plan(tmp_path, control_bytes)
    text = junit.junit_xml(record)
    schema.validate(text)
    error = ET.fromstring(text.encode("utf-8")).find(".//error")
    assert error.get("message") == "ValueError: reply \ufffd\ufffd[31m garbled\ufffd[0m"


def test_a_testrecord_object_gives_the_same_reports_as_its_saved_json(runs):
    for key in ("fail", "mixed"):
        saved, obj = runs[key]
        converted = report.record_dict(obj)
        # OpenHTF goes on logging into the record after the output callbacks ran.
        logs = converted.pop("log_records")
        assert logs[:len(saved["log_records"])] == saved["log_records"]
        assert converted == {k: v for k, v in saved.items() if k != "log_records"}
        assert junit.junit_xml(obj) == junit.junit_xml(saved)
        assert report.html_report(obj) == report.html_report(saved)


@htf.measures(htf.Measurement("speed_curve").with_dimensions("speed").with_units(PPS),
              htf.Measurement("never_set").in_range(0, 1))
def odd_phase(test):
    for speed in range(0, 4000, 100):
        test.measurements.speed_curve[speed] = speed * 0.5
    trace = {"columns": ["t", "command", "actual"], "rows": [[i * 0.01, i, None if i == 3 else float("nan") if i == 5
                                                             else i] for i in range(60)], "target": None}
    test.attach("trace", json.dumps(trace), mimetype="application/json")
    test.attach("bus_counters", b"\xff not json", mimetype="application/octet-stream")
    return htf.PhaseResult.FAIL_AND_CONTINUE


def returns_fail(test):
    return htf.PhaseResult.FAIL_AND_CONTINUE


def test_reports_survive_odd_records(tmp_path, schema):
    record, _ = run_plan(tmp_path, odd_phase, returns_fail, plan="bare", test_version=None, plan_hash=None,
                         drive=None, operator=None)
    assert record["outcome"] == "FAIL"
    text = junit.junit_xml(record)
    schema.validate(text)
    _, suite = _suite(text)
    assert suite.find("testcase[@name='odd_phase']/failure").get("message") == "never_set was not measured"
    assert suite.find("testcase[@name='returns_fail']/failure").get("type") == "phase"
    page = report.html_report(record)
    assert page.count("<svg") == 1 and "Velocity" not in page  # a trace without a velocity column
    assert 'data-measurement="speed_curve"' in page and "..." in page


# --- HTML report without a browser ---------------------------------------------------------------

def test_html_escapes_every_record_string(runs):
    page = report.html_report(runs["inject"][0])
    assert "<script" not in page and "<b>x</b>" not in page and "<img" not in page
    assert "&lt;script&gt;alert(&#x27;plan&#x27;)&lt;/script&gt;" in page
    assert "&lt;b&gt;x&lt;/b&gt;&amp;amp;" in page


def test_html_is_self_contained(runs):
    page = report.html_report(runs["fail"][0])
    assert "http:" not in page and "https:" not in page and "<script" not in page and "@import" not in page
    assert page.count("<svg") == 2 * len(MOVES)


def test_html_lists_every_phase_and_measurement(runs):
    record = runs["fail"][0]
    page = report.html_report(record)
    for p in record["phases"]:
        assert 'data-phase="%s"' % p["name"] in page
        for m in p["measurements"]:
            assert 'data-measurement="%s"' % m in page
    assert "turnaround_max_us" in page and "941" in page  # the bus counters


# --- HTML report in Chromium --------------------------------------------------------------------

def _browser_missing():
    """Why the browser tests cannot run here, or None (desk_browser's check, without the GUI's packages)."""
    import desk_browser

    for path in (desk_browser.CHROMIUM, desk_browser.CHROMEDRIVER):
        if not os.access(path, os.X_OK):
            return "%s is missing (Debian: apt-get install chromium chromium-driver)" % path
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (make setup)"
    return None


@pytest.fixture(scope="module")
def browser():
    why = _browser_missing()
    if why:
        pytest.skip(why)
    import desk_browser

    b = desk_browser.Browser()
    yield b
    b.close()


def screenshot(browser, html_path, png_path, width=1280):
    """Save a full-page PNG of the report file html_path."""
    browser.driver.set_window_size(width, 900)
    browser.driver.get("file://" + os.path.abspath(html_path))
    # The window's size includes the browser's frame: add it so the viewport holds the whole page.
    height, frame = browser.js("return [document.documentElement.scrollHeight, outerHeight - innerHeight]")
    browser.driver.set_window_size(width, height + frame)
    browser.screenshot(png_path, clean=False)


def _open(browser, tmp_path, record, name):
    path = tmp_path / name
    path.write_text(report.html_report(record), encoding="utf-8")
    browser.driver.get("file://%s" % path)
    return browser


def test_report_in_chromium_fail_run(runs, browser, tmp_path):
    from selenium.webdriver.common.by import By

    b = _open(browser, tmp_path, runs["fail"][0], "fail.html")
    banner = b.el("verdict")
    assert b.text("verdict-text") == "FAIL"
    assert banner.value_of_css_property("background-color") in ("rgba(197, 34, 31, 1)", "rgb(197, 34, 31)")
    assert "final_position_error" in b.text("verdict-reason")

    traces = b.driver.find_elements(By.CSS_SELECTOR, '[data-testid="trace"]')
    assert [t.get_attribute("data-phase") for t in traces] == [m[0] for m in MOVES]
    for trace in traces:
        svgs = trace.find_elements(By.TAG_NAME, "svg")
        assert len(svgs) == 2  # position, velocity
        for svg in svgs:
            lines = svg.find_elements(By.CSS_SELECTOR, "polyline.series")
            assert lines
            for line in lines:
                assert len(line.get_attribute("points").split()) > 50
                box = b.js("const r = arguments[0].getBoundingClientRect(); return [r.width, r.height];", line)
                assert box[0] > 100 and box[1] > 20
        assert trace.find_elements(By.CSS_SELECTOR, "line.target")  # the dashed target

    failing = b.driver.find_elements(By.CSS_SELECTOR, "tr.meas.fail")
    names = {(r.find_element(By.XPATH, "ancestor::tbody").tag_name, r.get_attribute("data-measurement")) for r in failing}
    assert ("tbody", "final_position_error") in names
    cell = failing[0].find_element(By.TAG_NAME, "td")
    assert cell.value_of_css_property("background-color") not in ("rgba(0, 0, 0, 0)", "rgb(255, 255, 255)")
    ok = b.driver.find_elements(By.CSS_SELECTOR, 'tr.meas[data-outcome="PASS"]')
    assert ok and ok[0].find_element(By.TAG_NAME, "td").value_of_css_property("background-color") != \
        cell.value_of_css_property("background-color")

    assert b.el("bus-counters").text.count("turnaround") == 3
    # Nothing was fetched, and nothing on the page points outside the file.
    assert b.js("return performance.getEntriesByType('resource').length") == 0
    assert not b.js("return [...document.querySelectorAll('[src],[href]')]"
                    ".map(e => e.getAttribute('src') || e.getAttribute('href'))"
                    ".filter(u => /^(https?:)?\\/\\//i.test(u))")


@pytest.mark.parametrize("run,text,colour", [
    ("pass", "PASS", (19, 115, 51)),
    ("aborted", "ABORTED", (249, 171, 0)),
    ("mixed", "ERROR", (249, 171, 0)),
])
def test_report_in_chromium_banner_colours(runs, browser, tmp_path, run, text, colour):
    b = _open(browser, tmp_path, runs[run][0], run + ".html")
    assert b.text("verdict-text") == text
    assert b.el("verdict").value_of_css_property("background-color").replace("rgba", "rgb") in (
        "rgb(%d, %d, %d)" % colour, "rgb(%d, %d, %d, 1)" % colour)
    if run != "pass":
        assert "Traceback" in b.text("errors") or "aborted" in b.text("errors").lower()


def test_injected_plan_name_stays_text_in_chromium(runs, browser, tmp_path):
    from selenium.webdriver.common.by import By

    b = _open(browser, tmp_path, runs["inject"][0], "inject.html")
    assert not b.driver.find_elements(By.TAG_NAME, "script") and not b.driver.find_elements(By.TAG_NAME, "img")
    assert "<script>alert('plan')</script>" in b.el("verdict").text
    assert b.text("info-dut") == "<b>x</b>&amp;"


def test_screenshot_of_a_report(runs, browser, tmp_path):
    html_path = tmp_path / "report.html"
    html_path.write_text(report.html_report(runs["fail"][0]), encoding="utf-8")
    png = tmp_path / "report.png"
    screenshot(browser, str(html_path), str(png))
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert width >= 1000 and height > 1500


def main(argv):
    """Render docs/station-report.png (or argv[0]) from a realistic run."""
    import pathlib
    import tempfile

    out = argv[0] if argv else os.path.join(ROOT, "docs", "station-report.png")
    why = _browser_missing()
    if why:
        sys.stderr.write("station report screenshot: %s\n" % why)
        return 2
    import desk_browser

    with tempfile.TemporaryDirectory() as tmp:
        record, _ = run_plan(pathlib.Path(tmp), *realistic_phases())
        html_path = os.path.join(tmp, "report.html")
        with open(html_path, "w", encoding="utf-8") as f:
            f.write(report.html_report(record))
        b = desk_browser.Browser()
        try:
            screenshot(b, html_path, out)
        finally:
            b.close()
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
