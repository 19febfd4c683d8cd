"""Starting MotorJig Desk: `jigctl gui` options, the non-loopback warning, and the
`make` path (`python -m motorjig.desk --bench`: the bench and the page connected to it)."""

import socket

import pytest

import desk_browser as B
from motorjig import cli
from motorjig.desk import server


def test_only_loopback_addresses_are_quiet():
    for host in ("127.0.0.1", "127.0.0.2", "localhost", "::1"):
        assert server.security_warning(host) is None
    for host in ("0.0.0.0", "192.168.1.20", "::", "bench-pc.local"):
        w = server.security_warning(host)
        assert w.startswith("WARNING") and "anyone who can reach this address can move the motors" in w
    assert server.page_url("0.0.0.0", 8470) == "http://127.0.0.1:8470/"
    assert server.page_url("::1", 81) == "http://[::1]:81/"


def test_gui_help_lists_its_options(capsys):
    assert cli.main(["gui", "--help"]) == 0
    out = capsys.readouterr().out
    for opt in ("--http-port", "--host", "--open", "--bench", "--port"):
        assert opt in out


@pytest.mark.parametrize("argv,needle", [
    (["gui", "--http-port", "0"], "the HTTP port must be 1..65535"),
    (["gui", "--bench", "--drivers", "1"], "driver ids must be 2..15"),
])
def test_bad_options_are_one_sentence(capsys, argv, needle):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err


def test_other_hosts_warn_and_a_busy_port_is_a_sentence(capsys):
    pytest.importorskip("nicegui")
    busy = socket.socket()
    busy.bind(("0.0.0.0", 0))
    busy.listen(1)
    try:
        rc = cli.main(["gui", "--host", "0.0.0.0", "--http-port", str(busy.getsockname()[1])])
    finally:
        busy.close()
    err = capsys.readouterr().err
    assert rc == 3
    assert "WARNING: MotorJig Desk listens on 0.0.0.0 without a password" in err
    assert "cannot listen on 0.0.0.0 port" in err and "choose another with --http-port" in err
    assert "Traceback" not in err


def test_bench_mode_serves_a_page_connected_to_the_bench():
    """What `make` runs without a board: bench + Desk in one process, the URL printed."""
    pytest.importorskip("nicegui")
    proc, url = B.start_desk("--bench")
    try:
        early = "".join(proc.early)
        assert "virtual bench: jig = slave 1, drivers 2,3; other programs can use socket://127.0.0.1:" in early
        assert "; found 1 (jig), 2 (Ezi-STEP Plus-R ST), 3 (Ezi-STEP Plus-R ST); working with slave 2" in early
        assert url.startswith("http://127.0.0.1:")
        html = B.wait_http(url, 10)
        assert "<title>MotorJig Desk</title>" in html
    finally:
        B.stop(proc)
    assert proc.returncode is not None


@pytest.mark.parametrize("argv,needle", [
    (["--baud", "12345"], "baud rate must be one of 9600"),
    (["--bench", "--tcp-port", "70000"], "the bench's TCP port must be 1..65535"),
])
def test_module_options_are_checked(capsys, argv, needle):
    with pytest.raises(SystemExit) as exc:
        server.main(argv)
    assert exc.value.code == 2 and needle in capsys.readouterr().err
