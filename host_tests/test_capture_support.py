"""Shared helpers of the capture tests (no tests here): captures into records and pcapng,
an independent pcapng reader, and tshark with the Plus-R dissector.

The reader is written from the pcapng specification, not from the writer, so the
tests check the files the writer makes rather than the writer against itself.
"""

import glob
import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import threading
import time

import pytest

import capture_format as cf
from motorjig.capture import pcapng
from motorjig.capture import record as R
from motorjig.capture.framer import Framer
from motorjig.capture.install import dissector_source

HERE = os.path.dirname(os.path.abspath(__file__))
CAPTURES = sorted(glob.glob(os.path.join(HERE, "captures", "*.cap")))
LUA = dissector_source()
TSHARK = shutil.which("tshark")
#: 2026-01-01 00:00:00 UTC in µs: the captures' time 0
EPOCH_US = 1767225600 * 1000000

needs_tshark = pytest.mark.skipif(TSHARK is None, reason="tshark is not installed (Debian: apt-get install tshark)")


# --- captures -> records -> pcapng ---------------------------------------------------
def capture_records(cap, step=0):
    """The records of a capture file, fed burst by burst at its times (``step`` > 0: in
    pieces of that many bytes), its trailing gap checked, then flushed."""
    timeout = cap.timeout_us if cap.timeout_us >= 0 else 5000
    fr = Framer(ver8=cap.ver8, interbyte_timeout_us=timeout)
    recs = []
    for t, data in cap.bursts:
        data = bytes(data)
        pieces = [data] if step <= 0 else [data[i:i + step] for i in range(0, len(data), step)]
        for piece in pieces:
            recs += fr.feed(piece, EPOCH_US + t)
    if cap.end_gap >= 0:
        recs += fr.check_timeout(EPOCH_US + cap.end_gap)
    return recs, fr.flush()


def write_pcapng(path, records, buses=None):
    buses = buses or [R.pc_bus(115200)]
    with open(path, "wb") as f:
        w = pcapng.Writer(f, buses)
        for rec in records:
            w.write(rec)
    return path


def body_of(wire):
    """Unstuffed body of a good frame's wire bytes."""
    out = bytearray()
    i = 2
    while i < len(wire) - 2:
        out.append(wire[i])
        i += 2 if wire[i] == 0xAA else 1
    return bytes(out)


# --- an independent pcapng reader ------------------------------------------------------
class Block:
    def __init__(self, kind, body, offset):
        self.kind, self.body, self.offset = kind, body, offset


def read_blocks(data):
    """Every block of a little-endian pcapng file, its lengths checked."""
    blocks = []
    off = 0
    while off < len(data):
        assert len(data) - off >= 12, "truncated block at %d" % off
        kind, length = struct.unpack_from("<II", data, off)
        assert length % 4 == 0 and length >= 12, "block at %d has length %d" % (off, length)
        assert off + length <= len(data), "block at %d runs past the end" % off
        (trailer,) = struct.unpack_from("<I", data, off + length - 4)
        assert trailer == length, "block at %d: lengths %d and %d differ" % (off, length, trailer)
        blocks.append(Block(kind, data[off + 8:off + length - 4], off))
        off += length
    return blocks


def read_options(body, start):
    opts = []
    off = start
    while off + 4 <= len(body):
        code, n = struct.unpack_from("<HH", body, off)
        if code == 0:
            break
        opts.append((code, body[off + 4:off + 4 + n]))
        off += 4 + n + (-n % 4)
    return opts


def parse_pcapng(data):
    """{'shb': options, 'interfaces': [dict], 'packets': [dict]} of a file."""
    blocks = read_blocks(data)
    assert blocks and blocks[0].kind == 0x0A0D0D0A, "no section header first"
    magic, major, minor = struct.unpack_from("<IHH", blocks[0].body, 0)
    assert (magic, major, minor) == (0x1A2B3C4D, 1, 0)
    out = {"shb": dict(read_options(blocks[0].body, 16)), "interfaces": [], "packets": []}
    for b in blocks[1:]:
        if b.kind == 1:
            linktype, _reserved, snaplen = struct.unpack_from("<HHI", b.body, 0)
            opts = dict(read_options(b.body, 8))
            out["interfaces"].append({"linktype": linktype, "snaplen": snaplen, "options": opts})
        elif b.kind == 6:
            ifid, hi, lo, caplen, origlen = struct.unpack_from("<IIIII", b.body, 0)
            data_end = 20 + caplen
            opts = read_options(b.body, data_end + (-caplen % 4))
            flags = [struct.unpack("<I", v)[0] for c, v in opts if c == 2]
            out["packets"].append({
                "interface": ifid, "t_us": (hi << 32) | lo, "caplen": caplen, "origlen": origlen,
                "data": b.body[20:data_end], "comments": [v.decode("utf-8") for c, v in opts if c == 1],
                "flags": flags[0] if flags else None})
        elif b.kind == 0x0A0D0D0A:
            raise AssertionError("a second section in one file")
        else:
            raise AssertionError("unexpected block type 0x%X" % b.kind)
    return out


# --- tshark ---------------------------------------------------------------------------------
def run_tshark(args, home=None, timeout=60, lua=True, stdin_bytes=None):
    """tshark with the dissector (-X lua_script:, or the plugin installed under ``home``)."""
    env = dict(os.environ)
    if home is not None:
        env["HOME"] = home
        env.pop("XDG_CONFIG_HOME", None)
    cmd = [TSHARK] + (["-X", "lua_script:" + LUA] if lua else []) + list(args)
    res = subprocess.run(cmd, capture_output=True, timeout=timeout, env=env, input=stdin_bytes)
    res.stdout = res.stdout.decode("utf-8", "replace")
    res.stderr = res.stderr.decode("utf-8", "replace")
    return res


def _flatten(node, out):
    """{field: [values]} of a tshark -T json --no-duplicate-keys layer tree (repeated
    fields come as lists; subtrees as objects)."""
    for k, v in node.items():
        for item in (v if isinstance(v, list) else [v]):
            if isinstance(item, dict):
                if k.startswith("plusr."):
                    out.setdefault(k, []).append("")  # a field with a subtree: its expert info
                _flatten(item, out)
            else:
                out.setdefault(k, []).append(item)
                if k == "_ws.expert.message":
                    out.setdefault("expert_messages", []).append(item)


def dissect(path, *options, two_pass=True, home=None):
    """[{field: [values]}] per packet, dissected by tshark -T json with the dissector."""
    args = ["-r", path, "-T", "json", "--no-duplicate-keys"] + (["-2"] if two_pass else [])
    for o in options:
        args += ["-o", o]
    res = run_tshark(args, home=home, lua=home is None)
    assert res.returncode == 0, res.stderr
    assert "Lua" not in res.stderr.replace('Running as user "root"', ""), res.stderr
    assert "Lua Error" not in res.stdout, [line for line in res.stdout.splitlines() if "Lua Error" in line][:3]
    packets = []
    for p in json.loads(res.stdout):
        flat = {}
        _flatten(p["_source"]["layers"], flat)
        packets.append(flat)
    return packets


def fields(path, names, display_filter=None, *options):
    """Rows of tshark -T fields (one list of strings per packet shown)."""
    args = ["-r", path, "-2", "-T", "fields", "-E", "separator=\t", "-E", "occurrence=f"]
    for n in names:
        args += ["-e", n]
    if display_filter:
        args += ["-Y", display_filter]
    for o in options:
        args += ["-o", o]
    res = run_tshark(args)
    assert res.returncode == 0, res.stderr
    return [line.split("\t") for line in res.stdout.splitlines()]


def one(packet, name, default=None):
    v = packet.get(name)
    return v[0] if v else default


def num(packet, name):
    v = one(packet, name)
    return None if v is None else int(v, 0)


def load(path):
    return cf.load(path)


# --- playing captures to the sniffer ---------------------------------------------------
JIGCTL = os.path.join(os.path.dirname(sys.executable), "jigctl")


def capture(name):
    return load([c for c in CAPTURES if os.path.basename(c).startswith(name)][0])


def play(write, cap, speed=1.0):
    """Write a capture's bursts at its times (µs), from now."""
    t0 = time.monotonic()
    for t, data in cap.bursts:
        wait = t0 + t / 1e6 / speed - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        write(bytes(data))


class Server:
    """A loopback TCP server that plays bytes to the first client, then holds the line open."""

    def __init__(self, send):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.url = "socket://127.0.0.1:%d" % self.sock.getsockname()[1]
        self.done = threading.Event()
        self._closed = threading.Event()
        self._send = send
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        try:
            conn, _ = self.sock.accept()
        except OSError:  # closed before anyone connected
            return
        with conn:
            time.sleep(0.2)  # the sniffer is reading by now: it opened the port to connect
            try:
                self._send(conn.sendall)
            except OSError:
                return
            self.done.set()
            self._closed.wait(30)

    def close(self):
        self._closed.set()
        self.sock.close()


def jigctl(*args, env=None, timeout=60, stdin=None):
    return subprocess.run([JIGCTL] + list(args), capture_output=True, timeout=timeout, env=env, stdin=stdin)


@pytest.fixture
def installed(tmp_path):
    """The dissector and both extcaps installed into a temporary HOME (what a user's
    `jigctl capture --install-dissector --install-extcap` does); returns that HOME."""
    env = dict(os.environ, HOME=str(tmp_path))
    env.pop("XDG_CONFIG_HOME", None)
    res = jigctl("capture", "--install-dissector", "--install-extcap", env=env)
    assert res.returncode == 0, res.stderr
    out = res.stdout.decode()
    assert "capture interface: motorjig-sniff" in out and "capture interface: motorjig-jig" in out, out
    return tmp_path


def read_fifo(fifo, proc, packets):
    """What Wireshark does with an extcap's fifo: read pcapng from it until it holds
    ``packets`` packets, close it, and wait for the extcap (``proc``) to end by itself."""
    data = b""
    with open(fifo, "rb") as f:
        while True:
            try:
                if len(parse_pcapng(data)["packets"]) >= packets:
                    break
            except Exception:  # a block still coming
                pass
            chunk = os.read(f.fileno(), 65536)
            assert chunk, "the extcap closed the fifo early: %s" % proc.stderr.read()
            data += chunk
    proc.wait(10)  # the fifo is closed: the extcap ends by itself
    return data
