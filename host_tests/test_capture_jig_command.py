"""jigctl capture --jig and the motorjig-jig extcap against a loopback capture port.

The port is a TCP server (test_capture_jig_support.JigServer) that answers S with a
stream the real firmware recorded on the bench (a few transactions, bad CRCs on
both buses, noise, the tick wrap) and notes the X at the end; before the stream it
sends the tail of an earlier recording, as a USB pipe may still hold one. What the
command shows and writes is compared with what ``JigStream`` reads from the same
stream; the failures are each one sentence and an exit status.
"""

import json
import os
import signal
import subprocess
import time

import pytest

from test_capture_jig_support import BenchCapture, JigServer, frame, hello, read_all, scenario
from test_capture_support import (JIGCTL, installed, jigctl, needs_tshark, parse_pcapng, read_fifo,  # noqa: F401
                                  run_tshark)

from jig import capture as C

from motorjig.capture import extcap
from motorjig.capture import record as R

LEFTOVER = frame(C.CH_PC_IN, b"\x02\x40\x01\x20", 10, 500)[7:]  # the end of an earlier recording


@pytest.fixture(scope="module")
def stream():
    return bytes(scenario(BenchCapture()).stream)


@pytest.fixture(scope="module")
def expected(stream):
    recs, _js = read_all(stream)
    return recs


def _shape(recs):
    """What must survive the trip: bus, direction, bytes, verdict, count, the frame's
    length in time, and the times relative to the first record."""
    t0 = recs[0].t_us
    return [(r.bus, r.direction, r.data, r.verdict, r.count,
             None if r.t_first_us is None else r.t_us - r.t_first_us, r.t_us - t0) for r in recs]


def _no_traceback(res):
    err = res.stderr.decode() if isinstance(res.stderr, bytes) else res.stderr
    assert "Traceback" not in err, err


def _stopped(srv):
    """The command started with X, S (afresh, even if the jig was recording) and sent X
    before it ended (wait a little: the server reads it in its loop)."""
    assert srv.stopped.wait(5), "no X: %r" % bytes(srv.commands)
    assert bytes(srv.commands) == b"XSX", bytes(srv.commands)
    return True


def test_both_buses_into_one_pcapng(stream, expected, tmp_path):
    srv = JigServer(stream, before=LEFTOVER)
    out = str(tmp_path / "jig.pcapng")
    try:
        res = jigctl("capture", "--jig", srv.url, "-w", out, "--json", "--count", str(len(expected)),
                     "--duration", "30")
        assert _stopped(srv)
    finally:
        srv.close()
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    lines = [json.loads(line) for line in res.stdout.decode().splitlines()]
    summary = lines.pop()["summary"]
    assert len(lines) == len(expected)
    assert [(d["bus"], d["dir"], bytes.fromhex(d["wire"]), d["verdict"]) for d in lines] == [
        (("pc", "drivers")[r.bus], R.DIRECTION_NAMES[r.direction], r.data, R.verdict_name(r.verdict)) for r in expected]
    kinds = [d["frame"]["kind"] for d in lines if "frame" in d]
    assert "request" in kinds and "reply" in kinds  # known from the direction
    assert summary["records"] == len(expected) and summary["files"] == [out]
    assert summary["verdicts"]["bad_crc"] == 4 and summary["verdicts"]["noise"] == 1
    assert summary["noise"] == {"pc": 3, "drivers": 0} and summary["lost"] == 0
    assert summary["jig"]["name"] == "MotorJig bridge 0.1"
    f = parse_pcapng(open(out, "rb").read())
    assert [i["options"][3].decode() for i in f["interfaces"]] == [
        "PC bus, 115200 baud, jig %s" % srv.url, "driver bus, 115200 baud, jig %s" % srv.url]
    assert [i["linktype"] for i in f["interfaces"]] == [147, 148]
    assert [(p["interface"], p["data"]) for p in f["packets"]] == [(r.bus, r.data) for r in expected]
    got = read_all(stream)[0]
    assert _shape(got) == _shape(expected)
    times = [p["t_us"] for p in f["packets"]]
    assert [t - times[0] for t in times] == [r.t_us - expected[0].t_us for r in expected]
    assert abs(times[0] / 1e6 - time.time()) < 60  # anchored to the host's clock at the hello


def test_live_view_lines(stream, expected):
    srv = JigServer(stream)
    try:
        res = jigctl("capture", "--jig", srv.url, "--count", "6", "--duration", "30")
        assert _stopped(srv)
    finally:
        srv.close()
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.decode().splitlines()
    assert len(lines) == 6
    assert " pc      in   request   id 2  GetCommandPos(0x51)" in lines[0]
    assert " drivers out  request   id 2  GetCommandPos(0x51)" in lines[1]
    assert " drivers in   reply     id 2  GetCommandPos(0x51)" in lines[2]
    assert " pc      out  reply     id 2  GetCommandPos(0x51)" in lines[3]
    assert " drivers out  short" in lines[4] and lines[4].endswith("| AA CC 01 AA EE")
    err = res.stderr.decode()
    assert ("capturing the jig's recording from %s: PC bus 115200 baud, driver bus 115200 baud (Ver6, jig id 1)"
            % srv.url) in err
    assert "6 records" in err and "the jig lost 0 records" in err


@needs_tshark
def test_write_to_a_pipe_for_wireshark(stream, expected):
    srv = JigServer(stream)
    try:
        res = jigctl("capture", "--jig", srv.url, "-w", "-", "--count", str(len(expected)), "--duration", "30")
        assert _stopped(srv)
    finally:
        srv.close()
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    assert "GetCommandPos(0x51)" in res.stderr.decode()  # the live view on stderr
    ts = run_tshark(["-r", "-", "-T", "fields", "-e", "frame.interface_name", "-e", "plusr.request_in",
                     "-e", "plusr.turnaround", "-Y", "plusr.turnaround"], stdin_bytes=res.stdout)
    assert ts.returncode == 0, ts.stderr
    rows = [line.split("\t") for line in ts.stdout.splitlines()]
    assert {r[0] for r in rows} == {"pc", "drivers"} and len(rows) == 9
    assert all(r[1] and float(r[2]) >= 0 for r in rows)


def test_rotation_keeps_both_interfaces_in_every_file(stream, expected, tmp_path):
    srv = JigServer(stream)
    base = str(tmp_path / "jig.pcapng")
    try:
        res = jigctl("capture", "--jig", srv.url, "-w", base, "--max-size", "2k", "--files", "2", "-q",
                     "--count", str(len(expected)), "--duration", "30")
        assert _stopped(srv)
    finally:
        srv.close()
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    names = sorted(os.listdir(str(tmp_path)))
    assert len(names) == 2 and all(n.startswith("jig_") for n in names), names
    for n in names:
        f = parse_pcapng(open(str(tmp_path / n), "rb").read())
        assert len(f["interfaces"]) == 2 and f["packets"]
    assert res.stdout == b"" and "%d records" % len(expected) in res.stderr.decode()


def test_duration_ends_it_and_sends_x(stream):
    srv = JigServer(stream, chunk=40, gap=0.2)  # slower than the duration
    try:
        t = time.monotonic()
        res = jigctl("capture", "--jig", srv.url, "--duration", "1.5", "-q")
        took = time.monotonic() - t
        assert _stopped(srv)
    finally:
        srv.close()
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    assert took < 10 and not srv.sent_all.is_set()


def _signalled(srv, ready, out, sig):
    """jigctl capture --jig srv -w out, sent sig a second after ``ready`` is set: it must
    end by itself with exit 0, X sent, no traceback. Returns (the pcapng parsed, stderr)."""
    proc = subprocess.Popen([JIGCTL, "capture", "--jig", srv.url, "-w", out, "-q"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        assert ready.wait(20)
        time.sleep(1.0)  # the command has read what was sent by then
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=20)
        assert _stopped(srv)
    finally:
        if proc.poll() is None:
            proc.kill()
        srv.close()
    assert proc.returncode == 0 and b"Traceback" not in stderr, stderr
    return parse_pcapng(open(out, "rb").read()), stderr


def test_ctrl_c_ends_it_and_sends_x(stream, tmp_path):
    srv = JigServer(stream, chunk=40, gap=0.2)
    out = str(tmp_path / "c.pcapng")
    f, stderr = _signalled(srv, srv.started, out, signal.SIGINT)
    assert len(f["interfaces"]) == 2 and f["packets"]
    assert b"records" in stderr  # the summary


def test_a_reader_that_goes_away_ends_it(stream):
    srv = JigServer(stream, chunk=40, gap=0.1)
    proc = subprocess.Popen([JIGCTL, "capture", "--jig", srv.url, "-w", "-", "-q"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        head = proc.stdout.read(200)
        proc.stdout.close()  # as `| head -c 200` does
        proc.wait(20)
        assert _stopped(srv)
        stderr = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
        srv.close()
    assert head[:4] == b"\x0a\x0d\x0d\x0a"  # a pcapng section header
    assert proc.returncode == 0 and b"Traceback" not in stderr, stderr


def test_a_stream_out_of_step_is_one_sentence_and_keeps_what_came(stream, expected, tmp_path):
    broken = stream[:600] + b"\x13\x37" * 20 + stream[600:]
    srv = JigServer(broken)
    out = str(tmp_path / "b.pcapng")
    try:
        res = jigctl("capture", "--jig", srv.url, "-w", out, "-q", "--duration", "30")
        assert _stopped(srv)
    finally:
        srv.close()
    _no_traceback(res)
    err = res.stderr.decode().strip().splitlines()
    assert res.returncode == 3, err
    assert err[-1].startswith("jigctl: the stream from %s is out of step: " % srv.url), err
    f = parse_pcapng(open(out, "rb").read())
    before = read_all(stream[:600])[0]
    assert [p["data"] for p in f["packets"]] == [r.data for r in before] and before


def _one_sentence(res, code, text):
    _no_traceback(res)
    err = res.stderr.decode()
    assert res.returncode == code, err
    assert text in err and err.startswith("jigctl: ") and len(err.strip().splitlines()) == 1, err


def test_a_port_that_sends_no_hello():
    srv = JigServer(b"", answer=False)
    try:
        t = time.monotonic()
        res = jigctl("capture", "--jig", srv.url)
        took = time.monotonic() - t
    finally:
        srv.close()
    _one_sentence(res, 3, "%s is not a MotorJig capture port: no hello record in 2 s (nothing came)" % srv.url)
    assert took < 15


def test_a_port_that_sends_something_else():
    srv = JigServer(b"MotorJig bridge 0.1 says hello\r\n" * 4)
    try:
        res = jigctl("capture", "--jig", srv.url)
        assert _stopped(srv)
    finally:
        srv.close()
    _one_sentence(res, 3, "is not a MotorJig capture port: no hello record in 2 s (128 bytes of something else came)")


@pytest.mark.parametrize("args, code, text", [
    (["--jig", "/dev/no-such-capture-port"], 3, "cannot open /dev/no-such-capture-port"),
    (["--jig", "loop://", "--sniff", "loop://"], 2, "give --sniff PORT or --jig PORT, not both"),
    (["--jig", "loop://", "--bus", "drivers,usb"], 2, "--bus takes pc, drivers or can (comma-separated) with --jig"),
    (["--sniff", "loop://", "--bus", "can"], 2, "--bus must be pc or drivers with --sniff, not 'can'"),
    (["--jig", "loop://", "--interbyte-timeout", "5"], 2, "--interbyte-timeout is for --sniff"),
    (["--jig", "loop://", "-w", "/no/such/dir/x.pcapng"], 2, "cannot write /no/such/dir/x.pcapng"),
    (["--jig", "loop://", "-w", "/no/such/dir/x.pcapng", "--max-size", "1M"], 2, "cannot write /no/such/dir"),
    (["--jig", "loop://", "--count", "0"], 2, "--count must be at least 1"),
    ([], 2, "or --jig PORT (the jig's capture port)"),
])
def test_errors_are_one_sentence(args, code, text):
    _one_sentence(jigctl("capture", *args), code, text)


def test_help_names_the_jig_option():
    res = jigctl("capture", "--help")
    assert res.returncode == 0
    text = " ".join(res.stdout.decode().split())
    assert "--jig PORT" in text and "the jig's own recording of both buses" in text
    assert "motorjig-jig" in text  # --install-extcap says it installs both interfaces
    # the shared connection options are told apart: which apply to a capture, which do not
    assert "--baud is the adapter's baud rate with --sniff" in text and "a capture only listens" in text
    import argparse

    from motorjig.cli import build_parser

    sub = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)][0]
    for action in sub.choices["capture"]._actions:
        assert action.help, action.option_strings


# --- the motorjig-jig extcap ------------------------------------------------------------------
def test_extcap_lists_and_configures_the_jig_interface(capsys):
    assert extcap.main(["--extcap-interfaces"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[2] == ("interface {value=motorjig-jig}{display=MotorJig jig: PC bus, driver bus and CAN bus (the jig's "
                      "own recording)}")
    assert extcap.main(["--extcap-interfaces"], interface="motorjig-jig") == 0
    only = capsys.readouterr().out.splitlines()
    assert len(only) == 2 and only[1].startswith("interface {value=motorjig-jig}")
    assert extcap.main(["--extcap-interface", "motorjig-jig", "--extcap-dlts"], interface="motorjig-jig") == 0
    dlts = capsys.readouterr().out.splitlines()
    assert [d.split("}")[0] for d in dlts] == ["dlt {number=147", "dlt {number=148", "dlt {number=227"]
    assert extcap.main(["--extcap-interface", "motorjig-jig", "--extcap-config"]) == 0
    config = capsys.readouterr().out.splitlines()
    assert len(config) == 1 and "{call=--port}" in config[0] and "{required=true}" in config[0]
    assert "capture port" in config[0]


@pytest.mark.parametrize("argv, text", [
    (["--extcap-interface", "motorjig-jig", "--capture", "--port", "loop://"], "no --fifo"),
    (["--extcap-interface", "motorjig-jig", "--capture", "--fifo", "FIFO"], "no port given"),
    (["--extcap-interface", "motorjig-jig", "--capture", "--fifo", "FIFO", "--port", "/dev/no-such-port"],
     "cannot open /dev/no-such-port"),
    (["--extcap-interface", "motorjig-sniff", "--extcap-config"], "unknown interface 'motorjig-sniff'"),
])
def test_extcap_failures_say_why(argv, text, capsys, tmp_path):
    argv = [str(tmp_path / "fifo") if a == "FIFO" else a for a in argv]
    assert extcap.main(argv, interface="motorjig-jig") == 1
    err = capsys.readouterr().err
    assert err.startswith("motorjig-jig: ") and text in err and len(err.strip().splitlines()) == 1, err


def test_extcap_refuses_a_port_without_hello(tmp_path, capsys):
    srv = JigServer(b"", answer=False)
    try:
        code = extcap.main(["--extcap-interface", "motorjig-jig", "--capture", "--fifo", str(tmp_path / "f"),
                            "--port", srv.url])
    finally:
        srv.close()
    err = capsys.readouterr().err
    assert code == 1 and "is not a MotorJig capture port" in err and len(err.strip().splitlines()) == 1
    # opened first (dumpcap waits in open() for the writer) and closed with nothing in it
    assert os.path.getsize(str(tmp_path / "f")) == 0


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no fifos on this OS")
def test_extcap_captures_into_a_fifo(installed, tmp_path, stream, expected):
    launcher = str(installed / ".local/lib/wireshark/extcap/motorjig-jig")
    ran = subprocess.run([launcher, "--extcap-interfaces"], capture_output=True, text=True, timeout=30)
    assert ran.returncode == 0 and "{value=motorjig-jig}" in ran.stdout and "motorjig-sniff" not in ran.stdout
    srv = JigServer(stream)
    fifo = str(tmp_path / "fifo")
    os.mkfifo(fifo)
    proc = subprocess.Popen([launcher, "--capture", "--extcap-interface", "motorjig-jig", "--fifo", fifo,
                             "--port", srv.url], stderr=subprocess.PIPE)
    try:
        data = read_fifo(fifo, proc, len(expected))
        assert _stopped(srv)
    finally:
        if proc.poll() is None:
            proc.kill()
        srv.close()
    assert proc.returncode == 0, proc.stderr.read()
    f = parse_pcapng(data)
    assert [i["options"][2] for i in f["interfaces"]] == [b"pc", b"drivers"]
    assert [(p["interface"], p["data"]) for p in f["packets"]] == [(r.bus, r.data) for r in expected]


@needs_tshark
def test_tshark_captures_through_the_jig_extcap(installed, stream, expected):
    listed = run_tshark(["-D"], home=str(installed), lua=False)
    assert "motorjig-jig" in listed.stdout and "motorjig-sniff" in listed.stdout, listed.stderr
    srv = JigServer(stream)
    try:
        res = run_tshark(["-i", "motorjig-jig", "-o", "extcap.motorjig_jig.port:" + srv.url, "-a", "duration:4",
                          "-T", "fields", "-e", "frame.interface_name", "-e", "plusr.kind", "-e", "plusr.turnaround"],
                         home=str(installed), lua=False, timeout=60)
        assert _stopped(srv)
    finally:
        srv.close()
    assert res.returncode == 0, res.stderr
    assert "Lua" not in res.stderr.replace('Running as user "root"', ""), res.stderr
    rows = [line.split("\t") for line in res.stdout.splitlines()]
    assert len(rows) == len(expected)
    assert [r[0] for r in rows] == [("pc", "drivers")[r.bus] for r in expected]
    assert sum(1 for r in rows if r[2]) == 9  # every good reply on both buses has its turnaround


@needs_tshark
def test_tshark_on_a_quiet_jig_ends_with_its_duration(installed):
    """Only the hello, then silence: the extcap's header reaches tshark at once, so
    -a duration:3 ends it (before the fix dumpcap waited for the header for ever)."""
    srv = JigServer(hello())
    try:
        t = time.monotonic()
        res = run_tshark(["-i", "motorjig-jig", "-o", "extcap.motorjig_jig.port:" + srv.url, "-a", "duration:3"],
                         home=str(installed), lua=False, timeout=30)
        took = time.monotonic() - t
        assert _stopped(srv)
    finally:
        srv.close()
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "" and took < 20, (res.stdout, res.stderr)
    assert "0 packets captured" in res.stderr, res.stderr


@needs_tshark
def test_tshark_on_a_refused_port_fails_at_once(installed):
    """The extcap opens the fifo first and closes it on a failure: tshark ends with the
    extcap's sentence instead of waiting for a writer that never comes."""
    t = time.monotonic()
    res = run_tshark(["-i", "motorjig-jig", "-o", "extcap.motorjig_jig.port:socket://127.0.0.1:1",
                      "-a", "duration:3"], home=str(installed), lua=False, timeout=40)
    took = time.monotonic() - t
    assert res.returncode != 0 and took < 15, (took, res.stderr)
    assert "cannot open socket://127.0.0.1:1" in res.stderr, res.stderr


def test_extcap_with_a_bad_fifo_path_is_one_sentence(capsys):
    code = extcap.main(["--extcap-interface", "motorjig-jig", "--capture", "--fifo", "/nonexist/f",
                        "--port", "loop://"])
    err = capsys.readouterr().err
    assert code == 1 and err.startswith("motorjig-jig: cannot open /nonexist/f: ") and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_sigterm_and_sighup_end_it_as_ctrl_c_does(stream, expected, tmp_path, sig):
    """`timeout 5 jigctl capture ...`, a closed terminal: X to the jig, the whole file
    (its buffered end too), the summary, exit 0 as for Ctrl-C."""
    srv = JigServer(stream)
    out = str(tmp_path / "t.pcapng")
    f, stderr = _signalled(srv, srv.sent_all, out, sig)
    assert [(p["interface"], p["data"]) for p in f["packets"]] == [(r.bus, r.data) for r in expected]
    assert b"%d records" % len(expected) in stderr, stderr  # the summary


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full")
def test_a_full_output_is_an_output_error_not_a_port_error(stream, expected):
    srv = JigServer(stream)
    try:
        res = jigctl("capture", "--jig", srv.url, "-w", "/dev/full", "-q", "--count", str(len(expected)),
                     "--duration", "30")
        assert _stopped(srv)
    finally:
        srv.close()
    _no_traceback(res)
    err = res.stderr.decode().strip().splitlines()
    assert res.returncode == 3, err
    assert err[-1] == "jigctl: writing /dev/full failed: No space left on device.", err
    assert "port error" not in res.stderr.decode()
    assert len(err) == 2 and " records (" in err[0], err  # the summary (up to the failed write), then the error


def test_a_stream_error_still_prints_the_summary(stream, tmp_path):
    broken = stream[:600] + b"\x13\x37" * 20 + stream[600:]
    srv = JigServer(broken)
    try:
        res = jigctl("capture", "--jig", srv.url, "-q", "--duration", "30")
        assert _stopped(srv)
    finally:
        srv.close()
    err = res.stderr.decode().strip().splitlines()
    assert res.returncode == 3 and len(err) == 2, err
    assert " records (" in err[0] and err[1].startswith("jigctl: the stream from "), err


@pytest.mark.parametrize("args, text", [
    (["--max-size", "inf", "-w", "x.pcapng"], "'inf' is not a size"),
    (["--max-size", "1e400", "-w", "x.pcapng"], "'1e400' is not a size"),
    (["--max-size", "nan", "-w", "x.pcapng"], "'nan' is not a size"),
    (["--duration", "nan"], "--duration must be a finite number of seconds"),
    (["--duration", "inf"], "--duration must be a finite number of seconds"),
    (["--interbyte-timeout", "nan"], "--interbyte-timeout must be a finite number of ms"),
])
def test_non_finite_numbers_are_refused(args, text, tmp_path):
    args = [str(tmp_path / a) if a == "x.pcapng" else a for a in args]
    base = ["--sniff", "loop://"] if "--interbyte-timeout" in args else ["--jig", "loop://"]
    _one_sentence(jigctl("capture", *(base + args)), 2, text)


def test_ctrl_c_before_the_hello_says_so():
    srv = JigServer(b"", answer=False)  # never answers: the command waits for the hello
    proc = subprocess.Popen([JIGCTL, "capture", "--jig", srv.url], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 20
        while b"S" not in bytes(srv.commands) and time.monotonic() < deadline:
            time.sleep(0.02)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
        srv.close()
    assert proc.returncode == 0 and b"Traceback" not in stderr, stderr
    assert stderr.decode().strip() == "jigctl: stopped before the jig answered.", stderr
