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
        assert w.startswith("WARNING") and "anyone who has the URL with its token can move the motors" in w
        assert server.security_warning(host, read_only=True).startswith("NOTE") and "read-only" in \
            server.security_warning(host, read_only=True)
    assert server.page_url("0.0.0.0", 8470) == "http://127.0.0.1:8470/"
    assert server.page_url("::1", 81) == "http://[::1]:81/"
    assert server.page_url("0.0.0.0", 8470, "abc") == "http://127.0.0.1:8470/?token=abc"


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
    assert "WARNING: MotorJig Desk listens on 0.0.0.0: anyone who has the URL with its token" in err
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


# --- remote viewing: the token, and --read-only -----------------------------------------------------
@pytest.fixture(scope="module")
def remote(tmp_path_factory):
    """A read-only Desk bound to every address (the tests only connect to 127.0.0.1)."""
    pytest.importorskip("nicegui")
    tmp = tmp_path_factory.mktemp("remote")
    bench = proc = None
    try:
        bench, bench_url = B.start_bench("2")
        proc, url = B.start_desk("--host", "0.0.0.0", "--read-only", "--port", bench_url, "--out", str(tmp),
                                 "--db", "none")
        base, token = url.split("/?token=")
        cookie = "motorjig_desk_token_%s" % base.rsplit(":", 1)[1]
        yield type("Remote", (), {"proc": proc, "url": url, "base": base, "token": token, "bench_url": bench_url,
                                  "cookie": cookie})
    finally:
        B.stop(proc)
        B.stop(bench)


def _ws_url(base, query=""):
    return base.replace("http://", "ws://") + "/_nicegui_ws/socket.io/?EIO=4&transport=websocket" + query


def test_bound_to_another_address_the_desk_prints_a_token_url(remote):
    assert remote.base.startswith("http://127.0.0.1:") and len(remote.token) >= 30
    early = "".join(remote.proc.early)
    assert "NOTE: MotorJig Desk listens on 0.0.0.0, read-only" in early
    assert "found 1 (jig), 2 (Ezi-STEP Plus-R ST); working with slave 2" in early  # scanned at start


def test_without_the_token_no_page_file_or_websocket_is_answered(remote):
    import httpx
    from nicegui import __version__ as ng
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    for path in ("/", "/runs/x.html", "/report/1", "/_nicegui/%s/static/nicegui.js" % ng,
                 "/_nicegui_ws/socket.io/?EIO=4&transport=polling"):
        r = httpx.get(remote.base + path)
        assert r.status_code == 401, (path, r.status_code)
        assert "needs its token" in r.text and "MotorJig" in r.text
        assert httpx.get(remote.base + path, params={"token": "wrong"}).status_code == 403
        assert httpx.get(remote.base + path, cookies={remote.cookie: "wrong"}).status_code == 403
    for query, status in (("", 401), ("&token=wrong", 403)):
        with pytest.raises(InvalidStatus) as exc:
            connect(_ws_url(remote.base, query), open_timeout=5)
        assert exc.value.response.status_code == status


def test_with_the_token_the_page_the_cookie_and_the_websocket_work(remote):
    import httpx
    from websockets.sync.client import connect

    r = httpx.get(remote.url)
    assert r.status_code == 200 and "<title>MotorJig Desk</title>" in r.text
    cookie = r.cookies.get(remote.cookie)  # named after the port: two Desks on one host keep theirs
    assert cookie == remote.token and "httponly" in r.headers["set-cookie"].lower()
    assert httpx.get(remote.base + "/", cookies={remote.cookie: cookie}).status_code == 200
    for kw in ({"uri": _ws_url(remote.base, "&token=" + remote.token)},
               {"uri": _ws_url(remote.base), "additional_headers": {"Cookie": "%s=%s" % (remote.cookie, cookie)}}):
        with connect(open_timeout=5, **kw) as ws:
            assert ws.recv(timeout=5).startswith("0{")  # engine.io's open packet: the socket is there


def test_read_only_shows_the_status_and_refuses_a_move_and_a_test(remote):
    if B.browser_missing():
        pytest.skip(B.browser_missing())
    b = B.Browser()
    try:
        b.open(remote.url)
        assert b.text("read-only") == "READ-ONLY"
        b.tab("tab-axis")
        before = b.wait_for(lambda: b.text("cmd-pos").lstrip("-").isdigit() and b.text("cmd-pos"), 10,
                            "the live status")
        b.type("move-target", "5000")
        b.type("move-speed", "20000")
        b.click("btn-move-inc")
        b.wait_for(lambda: "Move refused: this Desk is read-only" in b.driver.page_source, 5, "the refusal")
        b.click("btn-servo-on")
        b.wait_for(lambda: "Servo on/off refused: this Desk is read-only" in b.driver.page_source, 5, "servo")
        b.tab("tab-plan")
        b.type("serial", "SN-RO")
        b.click("btn-test-start")
        b.wait_for(lambda: "starting a test refused: this Desk is read-only" in b.driver.page_source, 5, "test")
        b.tab("tab-axis")
        assert b.text("cmd-pos") == before and b.text("conn-state").startswith("connected: ")
    finally:
        b.close()
    from motorjig.master import Master

    with Master(remote.bench_url, timeout=0.5) as m:  # nothing reached the drive
        st = m.get_all_status(2)
    assert st.command_pos == int(before) and "servo_on" not in st.axis.flags


# --- on loopback: no token, but only under this computer's own names ---------------------------------
@pytest.fixture(scope="module")
def local(tmp_path_factory):
    pytest.importorskip("nicegui")
    proc, url = B.start_desk("--out", str(tmp_path_factory.mktemp("local")), "--db", "none")
    try:
        yield type("Local", (), {"url": url, "port": int(url.rsplit(":", 1)[1].strip("/"))})
    finally:
        B.stop(proc)


def _raw_ws_status(port, host_header):
    """The status line a websocket upgrade with ``host_header`` gets (a raw request: the client
    libraries set Host from the URL)."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(("GET /_nicegui_ws/socket.io/?EIO=4&transport=websocket HTTP/1.1\r\nHost: %s\r\n"
                   "Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n"
                   "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\r\n" % host_header).encode())
        return s.recv(4096).decode("latin-1").split("\r\n", 1)[0]


def test_on_loopback_a_request_under_another_name_is_refused(local):
    """DNS rebinding: a page of evil.example whose name now points at 127.0.0.1 gets nothing."""
    import httpx
    from websockets.sync.client import connect

    base, port = "http://127.0.0.1:%d" % local.port, local.port
    for host in ("evil.example:%d" % port, "evil.example", "127.0.0.1.evil.example:%d" % port,
                 "localhost:%d" % (port + 1), "192.168.1.20:%d" % port):
        for path in ("/", "/runs/x.html", "/report/1", "/_nicegui_ws/socket.io/?EIO=4&transport=polling"):
            r = httpx.get(base + path, headers={"Host": host})
            assert r.status_code == 403, (host, path, r.status_code)
            assert "another name" in r.text
        assert " 403 " in _raw_ws_status(port, host), host
    for host in ("127.0.0.1:%d" % port, "localhost:%d" % port, "[::1]:%d" % port, "LocalHost:%d" % port):
        r = httpx.get(base + "/", headers={"Host": host})
        assert r.status_code == 200 and "<title>MotorJig Desk</title>" in r.text, host
    assert " 101 " in _raw_ws_status(port, "localhost:%d" % port)
    with connect(_ws_url(base), open_timeout=5) as ws:
        assert ws.recv(timeout=5).startswith("0{")
