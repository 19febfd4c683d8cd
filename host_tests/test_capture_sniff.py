"""jigctl capture --sniff: a capture's bytes played into a pty and through a loopback
TCP server (as a listen-only adapter would hear them), framed, shown and written.

The bench cannot stand in here: a socket to it sees only what it sends that client
(docs/capture.md), so the tests play the captures of host_tests/captures instead,
with their gaps, and compare what the sniffer made of them with what the capture
file states.
"""

import json
import os
import subprocess
import time
import tty

import pytest

from test_capture_support import (JIGCTL, Server, body_of, capture, capture_records, dissect, jigctl, needs_tshark,
                                  parse_pcapng, play, run_tshark)

from motorjig.capture import record as R

HERE = os.path.dirname(os.path.abspath(__file__))


def _no_traceback(res):
    err = res.stderr.decode() if isinstance(res.stderr, bytes) else res.stderr
    assert "Traceback" not in err, err


def _expected(cap):
    recs, rest = capture_records(cap)
    return [(r.data, r.verdict) for r in recs + rest if r.verdict != R.NOISE]


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="no pty on this OS")
def test_sniff_through_a_pty(tmp_path):
    cap = capture("25_")
    master, slave = os.openpty()
    tty.setraw(slave)  # the line discipline must not touch the bytes before the sniffer opens it
    pts = os.ttyname(slave)
    out = str(tmp_path / "pty.pcapng")
    # --count ends it when the last record is in (the 10 of capture 25); a long inter-byte
    # timeout keeps a loaded machine's stall from cutting a frame (timing is not tested here)
    proc = subprocess.Popen([JIGCTL, "capture", "--sniff", pts, "-w", out, "--json", "--count", "10",
                             "--duration", "30", "--interbyte-timeout", "1000"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 20
        while not _has_open(proc.pid, pts):
            assert time.monotonic() < deadline and proc.poll() is None, "the sniffer did not open the pty"
            time.sleep(0.02)
        time.sleep(0.1)
        play(lambda b: os.write(master, b), cap)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
        os.close(slave)
    assert proc.returncode == 0, stderr
    lines = [json.loads(line) for line in stdout.decode().splitlines()]
    summary = lines.pop()["summary"]
    shown = [(bytes.fromhex(d["wire"]), R.VERDICT_CODES[d["verdict"]]) for d in lines if d["verdict"] != "noise"]
    assert shown == _expected(cap)
    assert summary["verdicts"] == {"good": 9, "bad_crc": 1} and summary["files"] == [out]
    f = parse_pcapng(open(out, "rb").read())
    assert [p["data"] for p in f["packets"]] == [w for w, _v in shown]
    assert f["interfaces"][0]["options"][3].decode() == "PC bus, 115200 baud, %s" % pts
    times = [p["t_us"] for p in f["packets"]]
    gaps = [b - a for a, b in zip(times, times[1:])]
    assert gaps[0] > 80000 and gaps[-1] < 20000  # the 100 ms silence of id 0, then a 2.5 ms reply
    replies = [d for d in lines if d.get("frame", {}).get("kind") == "reply"]
    assert [d["frame"]["slave"] for d in replies] == [1, 2, 2]


def _has_open(pid, path):
    try:
        for fd in os.listdir("/proc/%d/fd" % pid):
            try:
                if os.readlink("/proc/%d/fd/%s" % (pid, fd)) == path:
                    return True
            except OSError:
                pass
    except OSError:
        return False
    return False


def test_sniff_over_tcp_shows_one_line_per_record(tmp_path):
    cap = capture("14_")
    srv = Server(lambda send: play(send, cap))
    try:
        res = jigctl("capture", "--sniff", srv.url, "--count", "6", "--duration", "30", "--interbyte-timeout", "1000")
    finally:
        srv.close()
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.decode().splitlines()
    assert len(lines) == 6, lines
    assert "bad_crc   dropped: bad CRC" in lines[0] and lines[0].endswith("| AA CC 01 40 01 D1 AA EE")
    assert "request   id 1  GetAllStatus(0x43)" in lines[1]
    assert "reply     id 1  MoveIncPos(0x35)" in lines[5] and "status 0x85" in lines[5]
    for line in lines:
        assert " pc " in line and " ? " in line  # bus, direction unknown
    err = res.stderr.decode()
    assert "capturing %s (pc) at 115200 baud" % srv.url in err
    assert "6 records" in err and "bad_crc 3" in err and "good 3" in err


@needs_tshark
def test_write_to_a_pipe_for_wireshark(tmp_path):
    """-w - : pcapng on standard output, flushed per packet, the text view on stderr."""
    cap = capture("06_")
    srv = Server(lambda send: play(send, cap))
    try:
        res = jigctl("capture", "--sniff", srv.url, "-w", "-", "--count", "3", "--duration", "30", "--bus", "drivers",
                     "--interbyte-timeout", "1000")
    finally:
        srv.close()
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    f = parse_pcapng(res.stdout)
    assert f["interfaces"][0]["linktype"] == 148 and f["interfaces"][0]["options"][2] == b"drivers"
    assert [body_of(p["data"])[:-2] for p in f["packets"]] == [b for b, _c in cap.frames]
    assert "GetActualPos(0x53)" in res.stderr.decode()
    tshark = run_tshark(["-r", "-", "-T", "fields", "-e", "plusr.type", "-e", "plusr.act_pos"], lua=True,
                        stdin_bytes=res.stdout)
    assert tshark.returncode == 0, tshark.stderr
    assert tshark.stdout.splitlines() == ["0x40\t", "0x51\t", "0x53\t43690"]


def test_rotation_from_the_command_line(tmp_path):
    frame = bytes.fromhex("AA CC 01 01 C1 E0 AA EE")
    srv = Server(lambda send: send(frame * 300))
    base = str(tmp_path / "bus.pcapng")
    try:
        res = jigctl("capture", "--sniff", srv.url, "-w", base, "--max-size", "2k", "--files", "3", "-q",
                     "--count", "300", "--duration", "10")
    finally:
        srv.close()
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    names = sorted(os.listdir(str(tmp_path)))
    assert len(names) == 3 and all(n.startswith("bus_") and n.endswith(".pcapng") for n in names), names
    for n in names:
        data = open(str(tmp_path / n), "rb").read()
        assert len(data) <= 2000 and parse_pcapng(data)["packets"]
    assert res.stdout == b"" and "300 records" in res.stderr.decode()


@pytest.mark.parametrize("args, code, text", [
    (["--sniff", "/dev/no-such-adapter"], 3, "cannot open /dev/no-such-adapter"),
    ([], 2, "give --sniff PORT"),
    (["--sniff", "loop://", "--max-size", "10M"], 2, "--max-size needs -w FILE"),
    (["--sniff", "loop://", "-w", "x.pcapng", "--files", "3"], 2, "--files needs --max-size"),
    (["--sniff", "loop://", "-w", "x.pcapng", "--max-size", "ten"], 2, "is not a size"),
    (["--sniff", "loop://", "-w", "/no/such/dir/x.pcapng"], 2, "cannot write /no/such/dir/x.pcapng"),
    (["--sniff", "loop://", "--baud", "1234"], 2, "baud rate 1234"),
    (["--sniff", "loop://", "--interbyte-timeout", "0"], 2, "--interbyte-timeout"),
])
def test_errors_are_one_sentence(args, code, text, tmp_path):
    res = jigctl("capture", *args)
    _no_traceback(res)
    err = res.stderr.decode()
    assert res.returncode == code, err
    assert text in err and err.startswith("jigctl: ") and len(err.strip().splitlines()) == 1, err


def test_every_option_has_help():
    res = jigctl("capture", "--help")
    assert res.returncode == 0
    text = res.stdout.decode()
    for opt in ("--sniff", "--bus", "--interbyte-timeout", "--duration", "--count", "--write", "--max-size",
                "--files", "--quiet", "--install-dissector", "--install-extcap"):
        assert opt in text
    import argparse

    from motorjig.cli import build_parser

    sub = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)][0]
    for action in sub.choices["capture"]._actions:
        assert action.help, action.option_strings


def _install_env(home, path=None):
    env = dict(os.environ, HOME=str(home))
    env.pop("XDG_CONFIG_HOME", None)
    if path is not None:
        env["PATH"] = path
    return env


def test_install_without_tshark_uses_the_default_folders(tmp_path):
    res = jigctl("capture", "--install-dissector", "--install-extcap", env=_install_env(tmp_path, "/nonexistent"))
    _no_traceback(res)
    assert res.returncode == 0, res.stderr
    plugin = tmp_path / ".local/lib/wireshark/plugins/plusr.lua"
    launcher = tmp_path / ".local/lib/wireshark/extcap/motorjig-sniff"
    assert plugin.read_bytes() == open(os.path.join(HERE, "../tools/motorjig/capture/plusr.lua"), "rb").read()
    assert os.access(str(launcher), os.X_OK)
    out = res.stdout.decode()
    assert str(plugin) in out and str(launcher) in out and "tshark was not found" in out
    ran = subprocess.run([str(launcher), "--extcap-interfaces"], capture_output=True, text=True, timeout=30,
                         env={"PATH": "/nonexistent"})
    assert ran.returncode == 0 and "interface {value=motorjig-sniff}" in ran.stdout


@needs_tshark
def test_install_asks_wireshark_where(tmp_path):
    res = jigctl("capture", "--install-dissector", "--install-extcap", env=_install_env(tmp_path))
    assert res.returncode == 0, res.stderr
    out = res.stdout.decode()
    assert "dissector installed: %s" % (tmp_path / ".local/lib/wireshark/plugins/plusr.lua") in out
    folders = run_tshark(["-G", "folders"], home=str(tmp_path), lua=False).stdout
    if "Personal Extcap path" not in folders:  # Wireshark 3.x-4.0 read extcap/ in the configuration folder
        assert os.access(str(tmp_path / ".config/wireshark/extcap/motorjig-sniff"), os.X_OK)
    listed = run_tshark(["-D"], home=str(tmp_path), lua=False).stdout
    assert "motorjig-sniff" in listed
    pcap = str(tmp_path / "c.pcapng")
    from test_capture_support import write_pcapng

    recs, _rest = capture_records(capture("05_"))
    write_pcapng(pcap, recs)
    p = dissect(pcap, home=str(tmp_path))  # the installed plugin, no -X
    assert [x.get("plusr.type") for x in p] == [["0x31"], ["0x2a"], ["0x2e"], ["0x35"]]

