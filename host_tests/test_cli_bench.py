"""Every jigctl subcommand against the virtual bench, over its pty and its TCP port.

Commands run in-process through ``motorjig.cli.main`` (fast, output captured);
a few run the installed console script to prove there is never a traceback.
Set-up shared with test_master_bench.py is in bench_fixtures.py.
"""

import json
import os
import subprocess
import sys
import time

import pytest

from bench_fixtures import DRIVE, OTHER, TIMEOUT, TIMEOUT_MS, bench, port  # noqa: F401 (fixtures)
from jig import frame as F
from motorjig import cli
from motorjig.master import Master
from motorjig.sim import Bench

FAST = "200000"
JIGCTL = os.path.join(os.path.dirname(sys.executable), "jigctl")


class Run:
    def __init__(self, capsys, port):
        self.capsys = capsys
        self.port = port

    def __call__(self, *argv, code=0):
        self.capsys.readouterr()
        # generous timeout: the bench runs in real time on a shared, busy machine
        rc = cli.main(["--port", self.port, "--timeout", str(TIMEOUT_MS)] + [str(a) for a in argv])
        out, err = self.capsys.readouterr()
        assert rc == code, (argv, rc, out, err)
        self.out, self.err = out, err
        if code not in (0, 1):
            self.assert_one_sentence()
        return out

    def json(self, *argv, code=0):
        return json.loads(self(*argv, "--json", code=code))

    def assert_one_sentence(self):
        lines = [ln for ln in self.err.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("jigctl: ") and lines[0].endswith((".", "?")), self.err
        assert "Traceback" not in self.err


@pytest.fixture
def run(capsys, port):
    return Run(capsys, port)


def test_ports(run):
    rows = run.json("ports")
    assert isinstance(rows, list)


def test_scan(run):
    rows = run.json("scan", "--first", 0, "--last", 4)  # one try per id: the present ones must answer
    assert [r["slave"] for r in rows] == [1, DRIVE, OTHER]
    assert rows[0]["jig"] and rows[1]["type"] == 20
    assert run.err == ""  # no progress line when stderr is not a terminal
    run("scan", "--first", 5, "--last", 6, "--timeout", 100, code=4)
    assert "no slave answered on ids 5..6" in run.err
    text = run("scan", "--first", 1, "--last", 3)
    assert "<- the jig" in text and "Ezi-STEP Plus-R ST" in text
    rows = run.json("scan", "--via-jig")
    assert [(r["slave"], r["type"]) for r in rows] == [(DRIVE, 20), (OTHER, 20)]


def test_info(run):
    d = run.json("info")
    assert d["type"] == 20 and d["status"]["axis"]["flags"] and d["alarm"]["code"] == 0
    assert "sim" in run("info", "--slave", OTHER)
    d = run.json("--slave", 1, "info")
    assert d["type_name"] == "MotorJig bridge" and d["motor"] is None


def test_status_and_watch(run):
    d = run.json("status")
    assert "servo_on" in d["axis"]["flags"] and d["command_pos"] == 0
    text = run("status", "--watch", "--count", 3, "--interval", 0.01)
    assert text.count("command pos") == 3 and "servo_on" in text
    lines = run("status", "--watch", "--count", 2, "--interval", 0.01, "--json").splitlines()
    assert [json.loads(ln)["slave"] for ln in lines] == [DRIVE, DRIVE]
    run("-v", "status")
    assert "TX " + F.encode(DRIVE, F.GET_ALL_STATUS).hex(" ") in run.err and "RX reply     id 2  GetAllStatus(0x43)" in run.err
    run("-v", "servo", "off")  # its reply (status only) is as long as the request: still a reply
    assert "RX reply     id 2  ServoEnable(0x2A)" in run.err and "RX request" not in run.err, run.err
    run("servo", "on")


def test_move_kinds(bench, run):
    d = run.json("move", "inc", 1000, "--speed", FAST, "--wait")
    assert d["command_pos"] == 1000 and "servo_on" in d["axis"]["flags"]
    assert run.json("move", "abs", -300, "--speed", FAST, "--wait")["command_pos"] == -300
    assert "stopped after" in run("move", "jog", "+", "--speed", 20000, "--for", 0.05)
    d = run.json("move", "home", "--wait")
    assert "origin_ok" in d["axis"]["flags"]
    bench.sim.drivers[DRIVE].limit_plus = 250
    d = run.json("move", "limit", "+", "--speed", FAST, "--wait")
    assert d["command_pos"] == 250 and "hw_limit_plus" in d["axis"]["flags"]
    assert "moving by 10000 at 5000 pps" in run("move", "inc", 10000, "--speed", 5000)
    run("stop")


def test_stops_and_servo(run):
    run("move", "jog", "-", "--speed", 20000)
    assert "stop sent" in run("stop")
    assert run.json("estop")["command"] == "emergency stop"
    assert run.json("servo", "off")["servo"] is False
    assert "servo on" in run("servo", "on")
    run("move", "jog", "+", "--speed", 20000)
    assert "broadcast" in run("stop", "--all")
    assert "broadcast" in run("estop", "--all")


def test_alarm_reset(bench, run):
    bench.sim.drivers[DRIVE].inject_alarm(3)
    assert run.json("info")["alarm"]["name"] == "step-out"
    d = run.json("alarm-reset")
    assert d["alarm"]["code"] == 0
    bench.sim.drivers[DRIVE].inject_alarm(3)
    assert "ServoAlarmReset" in run("alarm-reset", "--kind", "servo")


def test_param(run):
    d = run.json("param", "list")
    assert d["table"] == "ezi-step" and len(d["params"]) == 29
    assert d["params"][3]["name"] == "axis_acc_time" and d["params"][3]["value"] == 5
    assert run.json("param", "set", "axis_max_speed", 300000)["value"] == 300000
    assert run.json("param", "get", 1)["value"] == 300000
    run("param", "save")
    assert run.json("param", "get", "axis_max_speed", "--rom")["value"] == 300000
    run("param", "set", 1, 500000)
    run("param", "save")
    assert "org_speed" in run("param", "list", "--offline")
    assert all("value" not in p for p in run.json("param", "list", "--offline")["params"])
    d = run.json("--slave", 1, "param", "list")
    assert d["table"] == "jig" and d["params"][0]["name"] == "jig_slave_id" and d["params"][0]["value"] == 1
    assert run.json("param", "get", "scan_timeout_ms", "--jig", "--slave", 1)["value"] == 20
    # the jig's restart parameters say so when set; the others do not
    assert "restart of the jig" in run("--slave", 1, "param", "set", "forward_mode", 1)
    assert run.json("--slave", 1, "param", "set", "forward_mode", 0)["needs_restart"] is True
    assert run.json("--slave", 1, "param", "set", "scan_timeout_ms", 20)["needs_restart"] is False
    assert "restart" not in run("param", "set", 1, 500000)


def test_io(run):
    d = run.json("io", "out", "--set", "user_out0,user_out2")
    assert d["output_bits"] == ["user_out0", "user_out2"]
    d = run.json("io", "out", "--clear", "user_out2")
    assert d["output_bits"] == ["user_out0"]
    run("io", "out", "--clear", 0xFFFFFF)
    d = run.json("io", "in", "--set", "jog_plus")
    assert "jog_plus" in d["input_bits"]
    run("io", "in", "--clear", "jog_plus")
    assert "inputs" in run("io")
    d = run.json("io", "map", 4, 0x2000, 1)
    assert (d["mask"], d["level"]) == (0x2000, 1)
    assert run.json("io", "map", 4)["mask"] == 0x2000
    assert run.json("io", "read-rom")["result"] == 0
    assert "outputs" in run("--slave", 1, "io")


def test_raw(run):
    d = run.json("raw", "02", "40")
    assert d["sent"] == "aa cc 02 40 01 20 aa ee"
    assert d["reply"]["status"] == 0 and "servo_on" in d["reply"]["flags"]
    text = run("raw", "0x02,0x51")
    assert "GetCommandPos" in text and "value=0" in text
    d = run.json("raw", "--no-crc", "AA CC 02 01 C1 10 AA EE")  # a correct frame, typed in full
    assert d["reply"]["version"].endswith("v6.0")
    run("raw", "--no-crc", "AA CC 02 40 00 00 AA EE", "--timeout", 150, code=4)  # bad CRC: nobody answers
    assert "no frame came back" in run.err
    run("servo", "off")
    d = run.json("raw", "02 35 10 27 00 00 88 13 00 00", code=5)  # MoveIncPos refused
    assert d["reply"]["status"] == 0x85 and "slave 2 replied with status 0x85" in run.err
    run("raw", "02", "zz", code=2)
    run("raw", "02", code=2)


def test_monitor_sees_the_replies_of_another_client(bench, port, tmp_path):
    log = tmp_path / "mon.log"
    mon = subprocess.Popen([JIGCTL, "--port", port, "monitor", "--duration", "3", "--log", str(log), "--json"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # Ask until the monitor has logged three replies: how long it takes to start
        # depends on the machine's load, so no fixed head start is assumed.
        with Master(bench.tcp_url, timeout=TIMEOUT) as m:
            while mon.poll() is None and (not log.exists() or log.read_text().count("GetAxisStatus") < 3):
                m.get_axis_status(DRIVE)
                time.sleep(0.02)
        out, err = mon.communicate(timeout=10)
    finally:
        if mon.poll() is None:
            mon.kill()
    assert mon.returncode == 0, err
    rows = [json.loads(ln) for ln in out.splitlines()]
    frames = [r for r in rows if "summary" not in r]
    assert len(frames) >= 3 and all(f["name"] == "GetAxisStatus" and f["kind"] == "reply" for f in frames)
    assert rows[-1]["summary"]["frames"] == len(frames) and rows[-1]["summary"]["errors"]["crc_errors"] == 0
    text = log.read_text()
    assert text.count("GetAxisStatus") >= 3 and "raw [02 40 00" in text


def test_motion_test(run):
    d = run.json("motion-test", "--cycles", 2, "--distance", 1000, "--speed", FAST)
    assert (d["passed"], d["failed"]) == (4, 0)
    assert [mv["distance"] for mv in d["moves"]] == [1000, -1000, 1000, -1000]
    run("servo", "off")
    d = run.json("motion-test", "--cycles", 1, "--distance", 100, "--speed", FAST, code=1)
    assert d["failed"] == 2 and "0x85" in d["moves"][0]["problem"]
    text = run("motion-test", "--cycles", 1, "--distance", 100, "--speed", FAST, "--servo-on")
    assert "2 of 2 moves passed" in text


def test_stats(run):
    d = run.json("stats", "--reset")
    assert d["counters"]["up_frames_in"] > 0 and d["reset"]
    d = run.json("stats")
    assert d["counters"]["up_frames_in"] <= 3  # only this request (and a few fixture leftovers)
    assert "turnaround_avg_us" in run("stats")


# --- error paths -----------------------------------------------------------------
def test_no_reply(run):
    run("--slave", 9, "--retries", 0, "info", code=4)
    assert "no reply from slave 9 to GetSlaveInfo within 500 ms" in run.err


def test_refused_move_0x85(run):
    run("servo", "off")
    run("move", "inc", 100, code=5)
    assert "0x85" in run.err and "refused" in run.err


def test_crc_error_status(bench, run):
    bench.sim.drivers[DRIVE].force(F.STATUS_CRC_ERROR)  # until cleared (the fixture clears it)
    run("move", "inc", 100, code=5)
    assert "bad CRC" in run.err and "0xAA" in run.err
    run("status", "--retries", 0, code=5)
    bench.sim.drivers[DRIVE].force(F.STATUS_CRC_ERROR, frames=1)
    assert run.json("status")["command_pos"] == 0  # re-sent once, then answered


def test_corrupted_reply(bench, run):
    # --ver6: no variant detection first, so the corruption hits the status reply
    bench.sim.corrupt_to_pc(1)
    run("status", "--retries", 0, "--ver6", code=4)
    assert "the reply from slave 2 to GetAllStatus failed its CRC" in run.err
    bench.sim.corrupt_to_pc(1)
    assert run.json("status", "--ver6")["command_pos"] == 0  # retried
    bench.sim.corrupt_to_pc(1)  # a corrupted detection probe: sent again, then detected
    assert run.json("status")["command_pos"] == 0


def test_crashlog(bench, run, monkeypatch):
    assert run.json("crashlog") == {"jig": 1, "crash_log": ""}
    assert "crash log: no crash recorded" in run("crashlog")
    monkeypatch.setattr(bench.sim.hal, "crash_summary", lambda: "crashes=1 consecutive=1 wdt_resets=0; last: boom",
                        raising=False)
    assert run.json("crashlog")["crash_log"] == "crashes=1 consecutive=1 wdt_resets=0; last: boom"
    assert "last: boom" in run("crashlog", "--jig-id", 1)
    assert run.json("raw", "01 F4")["reply"]["crash_log"].endswith("last: boom")  # decoded for raw/monitor
    run("crashlog", "--jig-id", 2, code=5)  # a drive refuses the jig's frame type (0x80)


def test_bad_input(run, bench):
    run("--baud", 12345, "info", code=2)
    assert "baud rate 12345" in run.err
    run("--slave", 16, "info", code=2)
    run("param", "set", "axis_acc_time", 0, code=2)
    assert "between 1 and 9999" in run.err
    run("--slave", 1, "param", "set", "up_baud", 1000, code=2)
    run("param", "get", "no_such_param", code=2)
    run("io", "out", "--set", "no_such_bit", code=2)
    run("--timeout", 0, "info", code=2)
    with Master(bench.pty_path):
        rc = cli.main(["--port", bench.pty_path, "info"])
        assert rc == 3
    rc = cli.main(["--port", "/dev/does-not-exist", "info"])
    assert rc == 3


def test_argparse_errors_and_help(capsys):
    assert cli.main(["move", "inc", "ten"]) == 2
    assert cli.main(["move", "inc", "10", "--speed", "0"]) == 2
    assert "speed must be" in capsys.readouterr().err
    for argv in (["--help"], ["move", "--help"], ["move", "jog", "--help"], ["param", "set", "--help"],
                 ["monitor", "--help"], ["raw", "--help"]):
        assert cli.main(argv) == 0
        assert "usage:" in capsys.readouterr().out
    assert cli.main(["info"]) == 2 or os.environ.get("JIGCTL_PORT")


def test_ver8_option(capsys):
    with Bench(driver_ids=(DRIVE,), baud=115200, ver8=True) as b:
        t = str(TIMEOUT_MS)
        assert cli.main(["--port", b.tcp_url, "--ver8", "--json", "--timeout", t, "info"]) == 0
        assert json.loads(capsys.readouterr().out)["type"] == 20
        assert cli.main(["--port", b.tcp_url, "--ver8", "-v", "--timeout", t, "raw", "02", "51"]) == 0
        out, err = capsys.readouterr()
        assert "sync" in out and "GetCommandPos" in out


def test_console_script_never_shows_a_traceback(bench):
    cases = [
        (["--port", "/dev/does-not-exist", "info"], 3, "does not exist"),
        (["--port", "socket://127.0.0.1:1", "scan"], 3, "connection refused"),
        (["--port", bench.tcp_url, "--slave", "9", "status"], 4, "no reply"),
        (["--port", bench.tcp_url, "raw", "xyz"], 2, "not hex"),
        (["--port", bench.tcp_url, "param", "set", "1", "0"], 2, "between 1 and 2500000"),
    ]
    for argv, code, text in cases:
        p = subprocess.run([JIGCTL] + argv, capture_output=True, text=True, timeout=30)
        assert p.returncode == code, (argv, p.stderr)
        assert text in p.stderr and "Traceback" not in p.stderr and len(p.stderr.splitlines()) == 1
    p = subprocess.run([JIGCTL, "--port", bench.tcp_url, "--timeout", str(TIMEOUT_MS), "--json", "info"],
                       capture_output=True, text=True, timeout=30)
    assert p.returncode == 0 and json.loads(p.stdout)["type"] == 20


def test_monitor_pairs_requests_with_replies_and_shows_line_errors(capsys, tmp_path, monkeypatch):
    # A sniffer's view: both directions on one line, written into a pseudo-terminal.
    import threading
    import tty

    from motorjig import commands

    # Write the stream once the monitor has opened the port (opening flushes the
    # input): no head start is guessed, however busy the machine.
    opened = threading.Event()

    def open_and_tell(args, _real=commands.open_master):
        m = _real(args)
        opened.set()
        return m

    monkeypatch.setattr(commands, "open_master", open_and_tell)

    master_fd, slave_fd = os.openpty()
    tty.setraw(slave_fd)
    bad = bytearray(F.encode(2, F.GET_AXIS_STATUS, b"\x00\x00\x00\x00\x08"))
    bad[-3] ^= 0xFF
    stream = (F.encode(2, F.STEP_ALARM_RESET, b"\x00")          # request: release
              + F.encode(2, F.STEP_ALARM_RESET, b"\x00")        # its reply: the same bytes
              + F.encode(2, F.MOVE_INC_POS, bytes.fromhex("10270000 88130000"))
              + F.encode(2, F.MOVE_INC_POS, b"\x85")
              + bytes(bad)
              + F.encode(3, F.GET_COMMAND_POS) + F.encode(3, F.GET_COMMAND_POS, b"\x00\x18\xfc\xff\xff"))

    def feed():
        if opened.wait(10):
            os.write(master_fd, stream)

    t = threading.Thread(target=feed)
    t.start()
    try:
        log = tmp_path / "sniff.log"
        rc = cli.main(["--port", os.ttyname(slave_fd), "monitor", "--duration", "1.2", "--log", str(log), "--json"])
        t.join()
    finally:
        os.close(master_fd)
        os.close(slave_fd)
    assert rc == 0
    rows = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
    kinds = [(r.get("kind"), r.get("name"), r.get("status")) for r in rows if "summary" not in r]
    assert kinds == [
        ("request", "StepAlarmReset", None), ("reply", "StepAlarmReset", 0),
        ("request", "MoveIncPos", None), ("reply", "MoveIncPos", 0x85),
        ("line_error", None, None),
        ("request", "GetCommandPos", None), ("reply", "GetCommandPos", 0),
    ]
    assert rows[2]["position"] == 10000 and rows[2]["speed"] == 5000
    assert rows[4]["error"] == "crc_errors" and rows[6]["value"] == -1000
    assert rows[-1]["summary"]["frames"] == 6 and rows[-1]["summary"]["errors"]["crc_errors"] == 1
    text = log.read_text()
    assert "line error: 1 x crc_errors" in text and "motion command refused" in text


def test_mixed_bus_scan_variants_and_jig_id_that_would_shadow_a_driver(capsys):
    """Ver8 jig, Ver6 driver 2, Ver8 driver 3: scan shows each variant; moving the jig
    onto a driver's id is refused with a clear message; a free id is taken, read back
    there, and said so."""
    with Bench(driver_ids=(DRIVE, OTHER), baud=115200, jig_ver8=True, ver8_drivers=(OTHER,)) as b:
        def run(*argv):
            capsys.readouterr()
            rc = cli.main(["--port", b.tcp_url, "--timeout", str(TIMEOUT_MS)] + [str(a) for a in argv])
            out, err = capsys.readouterr()
            return rc, out, err

        rc, out, _ = run("scan", "--first", 0, "--last", 5, "--json")
        assert rc == 0
        assert [(r["slave"], r["variant"]) for r in json.loads(out)] == [(1, 8), (DRIVE, 6), (OTHER, 8)]
        rc, out, _ = run("scan", "--first", 1, "--last", 3)
        assert "id  1  Ver8" in out and "id  2  Ver6" in out and "id  3  Ver8" in out
        assert run("info", "--slave", OTHER)[0] == 0  # a Ver8 drive, found by detection
        for target in (DRIVE, OTHER):
            rc, _, err = run("--slave", 1, "param", "set", "jig_slave_id", target)
            assert rc == 5 and "refused jig_slave_id = %d" % target in err and "driver answers" in err
        assert b.sim.jig_id == 1
        rc, out, err = run("--slave", 1, "param", "set", "jig_slave_id", 7)
        assert rc == 0, err
        assert "the jig now answers as slave 7" in out and "jig_slave_id = 7" in out
        assert b.sim.jig_id == 7
        rc, out, _ = run("scan", "--first", 0, "--last", 8, "--json")
        assert [(r["slave"], r["variant"], r["jig"]) for r in json.loads(out)] == [
            (DRIVE, 6, False), (OTHER, 8, False), (7, 8, True)]
