"""motorjig.capture.jigport.JigCapture on the bench's capture port (SimCapturePort,
the firmware's jig.capture behind it), read through a serial-like adapter that runs
the bench's clock: a stale stream left in the port's transmit buffer by an earlier
reader, a recording the jig ends itself, a port that closes at once (a second
reader) and one that says nothing."""

import socket
import struct
import threading

import pytest

from test_capture_jig_support import EPOCH_US

from jig import frame as F

from motorjig.capture.jigport import STOPPED_MSG, JigCapture
from motorjig.capture.jigstream import StreamError, _sdiff
from motorjig.errors import PortError
from motorjig.sim.bench import SimBench


class BenchClock:
    def __init__(self, bench):
        self.bench = bench

    def now_us(self):
        return EPOCH_US + int(self.bench.clock.now)

    def monotonic(self):
        return self.bench.clock.now / 1e6


class BenchPort:
    """The host's side of SimBench's capture port as pyserial would give it: ``read``
    runs the bench ``step_us`` while nothing has come (a read timeout)."""

    def __init__(self, bench, step_us=1000.0):
        self.bench = bench
        self.port = bench.capture
        self.step_us = step_us
        self.buf = bytearray()
        self.port.host_open()

    def _pull(self):
        self.buf += self.port.host_read()

    def read(self, n=1):
        self._pull()
        if not self.buf:
            self.bench.run_for(self.step_us)
            self._pull()
        data = bytes(self.buf[:n])
        del self.buf[:n]
        return data

    @property
    def in_waiting(self):
        self._pull()
        return len(self.buf)

    def write(self, data):
        self.port.host_send(data)

    def flush(self):
        pass

    def reset_input_buffer(self):
        self._pull()
        self.buf.clear()

    def close(self):
        self.port.host_close()


def _capture(bench):
    clk = BenchClock(bench)
    return JigCapture("bench", clock=clk, port=BenchPort(bench), monotonic=clk.monotonic)


def _slave_info_records(recs):
    wire = F.encode(1, F.GET_SLAVE_INFO)
    return [r for r in recs if r.data == wire]


def test_the_port_keeps_its_transmit_buffer_when_asked():
    b = SimBench()
    port = b.capture
    port.keep_on_close = True
    port.host_open()
    port.sink = lambda chunk: 0  # the reader takes nothing
    port.write(b"abc")
    b.run_for(5000)
    port.host_close()
    assert bytes(port.tx) == b"abc"
    port.sink = None
    port.host_open()
    b.run_for(5000)
    assert port.host_read() == b"abc"
    port.keep_on_close = False
    port.write(b"def")
    port.host_close()
    assert port.tx == bytearray()


def test_a_second_reader_gets_no_stale_records():
    """The first reader stalls (the port's transmit buffer fills with its hello and
    records) and goes away without X; the board's CDC keeps that buffer. The next
    reader's recording starts with a hello of its own, and none of the old records."""
    b = SimBench()
    port = b.capture
    port.keep_on_close = True
    assert b.capture_start()
    port.sink = lambda chunk: 0  # stalled
    for _ in range(5):
        b.request(1, F.GET_SLAVE_INFO)
    b.run_for(20000)
    assert len(port.tx) > 100
    port.host_close()
    port.sink = None
    tick0 = b.hal.ticks_us()
    cap = _capture(b)
    try:
        hello = cap.start()
        assert _sdiff(hello["tick"], tick0) > 0  # the new hello, not the old one
        got = []
        b.request(2, F.GET_COMMAND_POS)
        cap.run([got.append], duration=0.05)
        assert _slave_info_records(got) == [] and cap.stream.hellos == 1
        assert F.encode(2, F.GET_COMMAND_POS) in [r.data for r in got]
    finally:
        cap.close()


def test_the_jig_ending_the_recording_itself_is_told():
    b = SimBench()
    # (the PC has talked: the jig streams in the PC bus's quiet windows, and one that
    # never talked has no window until the tick wrap, 3 s into the bench)
    b.request(2, F.GET_COMMAND_POS)
    cap = _capture(b)
    try:
        cap.start()
        got = []
        cap.run([got.append], duration=3.5)  # no traffic: the jig's clock records keep it going
        assert got == [] and cap.stream.clocks >= 3
        assert b.request(b.jig_id, F.SET_PARAMETER, struct.pack("<Bi", 13, 0))[0] is not None
        assert not b.app.capture.on
        t_off = b.clock.now / 1e6
        with pytest.raises(StreamError) as exc:
            cap.run([got.append], duration=20)
        assert str(exc.value) == STOPPED_MSG
        assert STOPPED_MSG == "the jig stopped recording (parameter 13 capture = 0, or a reset)"
        assert b.clock.now / 1e6 - t_off < 3.5  # told within SILENCE_S (and a read)
    finally:
        cap.close()


class ClosingServer:
    """A TCP server that closes every connection at once (the bench's capture port
    with a reader attached already); ``reset``: with an RST."""

    def __init__(self, reset=False):
        self.reset = reset
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(4)
        self.url = "socket://127.0.0.1:%d" % self.sock.getsockname()[1]
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            if self.reset:
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            conn.close()

    def close(self):
        self.sock.close()
        self._thread.join(5)


def start_fails(url, wait):
    """The sentence of the PortError a start on url raises (the port closed after it)."""
    cap = None
    try:
        with pytest.raises(PortError) as exc:
            cap = JigCapture(url)  # (a reset may already come while the port opens)
            cap.start(wait=wait)
    finally:
        if cap is not None:
            cap.close()
    return str(exc.value)


@pytest.mark.parametrize("reset", [False, True], ids=["eof", "reset"])
def test_a_port_that_closes_at_once_has_another_reader(reset):
    srv = ClosingServer(reset)
    try:
        assert start_fails(srv.url, 1.0) == ("%s closed the connection at once: another reader is attached "
                                             "(one reader at a time)" % srv.url)
    finally:
        srv.close()


def test_a_port_that_says_nothing_may_have_another_reader():
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    url = "socket://127.0.0.1:%d" % srv.getsockname()[1]
    try:
        assert start_fails(url, 0.3) == ("%s is not a MotorJig capture port: no hello record in 0.3 s "
                                         "(nothing came), or another program is reading it" % url)
    finally:
        srv.close()


def test_a_second_reader_on_the_real_time_bench_is_told():
    """One capture reader at a time: a second TCP client is closed at once; the pty
    while a TCP reader is attached says nothing."""
    from motorjig.sim.bench import Bench

    with Bench() as bench:
        first = JigCapture(bench.capture_url)
        try:
            first.start()
            assert start_fails(bench.capture_url, 1.0) == (
                "%s closed the connection at once: another reader is attached (one reader at a time)"
                % bench.capture_url)
            if bench.capture_pty_path:
                assert start_fails(bench.capture_pty_path, 0.5).endswith(
                    "(nothing came), or another program is reading it")
        finally:
            first.close()
