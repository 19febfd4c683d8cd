"""The motorjig-sniff extcap: its answers to Wireshark's questions, a capture into a fifo,
and tshark capturing through it (``tshark -i motorjig-sniff``) from a loopback server.

tshark runs with HOME set to a temporary folder into which ``jigctl capture
--install-dissector --install-extcap`` installed both, so nothing of the user's
own Wireshark set-up is touched (and this works as root too: Debian's init.lua
runs user plugins for root, and extcaps in the personal folders are found).
"""

import os
import subprocess
import time

import pytest

from test_capture_support import (Server, body_of, capture, installed, needs_tshark,  # noqa: F401
                                  parse_pcapng, play, read_fifo, run_tshark)

from motorjig.capture import extcap


def test_interfaces_dlts_and_config(capsys):
    assert extcap.main(["--extcap-interfaces", "--extcap-version=4.0"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("extcap {version=")
    assert out[1].startswith("interface {value=motorjig-sniff}{display=")
    assert extcap.main(["--extcap-interface", "motorjig-sniff", "--extcap-dlts"]) == 0
    dlts = capsys.readouterr().out.splitlines()
    assert [d.split("}")[0] for d in dlts] == ["dlt {number=147", "dlt {number=148"]
    assert extcap.main(["--extcap-interface", "motorjig-sniff", "--extcap-config"]) == 0
    config = capsys.readouterr().out
    for call in ("--port", "--baud", "--bus", "--interbyte-timeout"):
        assert "{call=%s}" % call in config
    assert "{value=115200}{display=115200}{default=true}" in config


@pytest.mark.parametrize("args, text", [
    (["--extcap-interface", "other", "--extcap-dlts"], "unknown interface 'other'"),
    (["--extcap-interface", "motorjig-sniff", "--capture", "--port", "loop://"], "no --fifo"),
    (["--extcap-interface", "motorjig-sniff", "--capture", "--fifo", "FIFO"], "no port given"),
    (["--capture", "--fifo", "FIFO", "--port", "/dev/no-such-adapter"], "cannot open /dev/no-such-adapter"),
    ([], "nothing to do"),
])
def test_failures_say_why(args, text, capsys, tmp_path):
    args = [str(tmp_path / "fifo") if a == "FIFO" else a for a in args]
    assert extcap.main(args) == 1
    err = capsys.readouterr().err
    assert err.startswith("motorjig-sniff: ") and text in err and len(err.strip().splitlines()) == 1


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no fifos on this OS")
def test_capture_into_a_fifo(installed, tmp_path):
    """What Wireshark does: start the launcher with --capture --fifo and read pcapng from it."""
    cap = capture("06_")
    srv = Server(lambda send: play(send, cap))
    fifo = str(tmp_path / "fifo")
    os.mkfifo(fifo)
    launcher = str(installed / ".local/lib/wireshark/extcap/motorjig-sniff")
    proc = subprocess.Popen([launcher, "--capture", "--extcap-interface", "motorjig-sniff", "--fifo", fifo,
                             "--port", srv.url, "--baud", "115200", "--bus", "pc"], stderr=subprocess.PIPE)
    try:
        data = read_fifo(fifo, proc, 3)
    finally:
        if proc.poll() is None:
            proc.kill()
        srv.close()
    assert proc.returncode == 0, proc.stderr.read()
    f = parse_pcapng(data)
    assert [body_of(p["data"])[:-2] for p in f["packets"]] == [b for b, _c in cap.frames]


@needs_tshark
def test_tshark_captures_through_the_extcap(installed):
    listed = run_tshark(["-D"], home=str(installed), lua=False)
    assert "motorjig-sniff" in listed.stdout, listed.stderr
    cap = capture("25_")
    srv = Server(lambda send: play(send, cap))
    try:
        res = run_tshark(["-i", "motorjig-sniff", "-o", "extcap.motorjig_sniff.port:" + srv.url,
                          "-o", "extcap.motorjig_sniff.baud:115200", "-o", "extcap.motorjig_sniff.interbytetimeout:1000",
                          "-a", "duration:4",
                          "-T", "fields", "-e", "plusr.id", "-e", "plusr.type", "-e", "plusr.status",
                          "-e", "plusr.crc.status", "-e", "plusr.request_in"],
                         home=str(installed), lua=False, timeout=60)
    finally:
        srv.close()
    assert res.returncode == 0, res.stderr
    assert "Lua" not in res.stderr.replace('Running as user "root"', ""), res.stderr
    rows = [line.split("\t") for line in res.stdout.splitlines()]
    assert [(r[0], r[1]) for r in rows] == [
        ("0", "0x51"), ("1", "0x51"), ("1", "0x51"), ("2", "0x51"), ("2", "0x51"), ("2", "0x51"), ("2", "0x51"),
        ("3", "0x51"), ("2", "0x01"), ("2", "0x01")]
    assert [r[3] for r in rows] == ["1", "1", "1", "1", "0", "1", "1", "1", "1", "1"]  # the flipped CRC bit
    assert [r[2] for r in rows if r[2]] == ["0x00", "0x00", "0x00"]
    assert [r[4] for r in rows if r[4]] == ["2", "6", "9"]


@needs_tshark
def test_tshark_on_a_refused_adapter_port_fails_at_once(installed):
    """As for the jig's interface: the extcap opens the fifo first and closes it on a
    failure, so tshark ends with the extcap's sentence instead of waiting for ever."""
    t = time.monotonic()
    res = run_tshark(["-i", "motorjig-sniff", "-o", "extcap.motorjig_sniff.port:socket://127.0.0.1:1",
                      "-o", "extcap.motorjig_sniff.baud:115200", "-a", "duration:3"],
                     home=str(installed), lua=False, timeout=40)
    took = time.monotonic() - t
    assert res.returncode != 0 and took < 15, (took, res.stderr)
    assert "cannot open socket://127.0.0.1:1" in res.stderr, res.stderr


@needs_tshark
def test_tshark_on_a_quiet_adapter_ends_with_its_duration(installed):
    """A bus nobody talks on: the header reaches tshark at once and -a duration ends it."""
    srv = Server(lambda send: None)
    try:
        t = time.monotonic()
        res = run_tshark(["-i", "motorjig-sniff", "-o", "extcap.motorjig_sniff.port:" + srv.url,
                          "-o", "extcap.motorjig_sniff.baud:115200", "-a", "duration:3"],
                         home=str(installed), lua=False, timeout=30)
        took = time.monotonic() - t
    finally:
        srv.close()
    assert res.returncode == 0 and took < 20, (took, res.stderr)
    assert res.stdout.strip() == "" and "0 packets captured" in res.stderr, res.stderr
