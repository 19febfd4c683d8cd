"""The SLCAN reader's and encoder's machine code on the emulated Cortex-M7: parity and cost.

``make test-qemu`` builds MicroPython's qemu port (MPS2_AN500, Cortex-M7) with the
firmware frozen in and measures the whole CAN port. This tool measures
``jig.slcan`` alone, in seconds, on any such build: it runs the ELF in
``qemu-system-arm -icount shift=0`` (1 instruction = 1 ns of virtual time, so
``ticks_us`` x 1000 = instructions), pastes the work tree's ``jig/slcanfast.py``
and ``jig/slcan.py`` through the REPL (compiled there by the port's own compiler
and native emitter, so edits need no rebuild) and prints:

* parity: every capture of host_tests/captures/slcan replayed (whole and byte by
  byte) through the viper engine (machine code) and the table engine (bytecode)
  gives CPython's report; pseudo-random streams cut at random give both engines
  the same offsets, events, fields, counts and partial line after every call;
* instructions per ``feed`` of one whole line (``t``/``T`` with 8 data bytes, ...)
  and per ``encode_frame``, for both engines, and the heap allocated (0).

With ``--can-suite`` it runs make test-qemu's CAN port figures (tools/firmware/qemu/can_suite.py)
instead, with the work tree's ``jig.slcan`` -- or that of ``--rev REV``, for a
before/after on one build -- in place of the frozen one.

    .venv/bin/python tools/firmware/slcan_qemu.py [--elf build/qemu/build/firmware.elf]
    .venv/bin/python tools/firmware/slcan_qemu.py --can-suite [--rev f2cbeda~1]

Exits 1 if a parity check fails or an allocation is seen, 2 if it cannot run.
"""

import argparse
import glob
import os
import shutil
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DEFAULT_ELF = os.path.join(ROOT, "build", "qemu", "build", "firmware.elf")
CAPTURES = os.path.join(ROOT, "host_tests", "captures", "slcan")

# The paste's first block: the work tree's modules replace the frozen ones.
SETUP = """
import sys, io, jig
class _NS:
    pass
def _mod(src, name, extra=None):
    g = {'__name__': name}
    if extra:
        g.update(extra)
    exec(src, g)
    ns = _NS()
    for k in g:
        setattr(ns, k, g[k])
    sys.modules[name] = ns
    return ns
"""

DEVICE = r"""
import gc
from time import ticks_us, ticks_diff
S = sys.modules['jig.slcan']
print("@@engine", S.SlcanReader.ENGINE, S.encode_frame is S.encode_py)
CLASSES = (S.reader_class("viper"), S.reader_class("table"))
fails = 0

def snap(r):
    return (r.ev, r.err, r.cmd, r.can_id, r.ext, r.rtr, r.dlc, r.arg, r.lines, bytes(r.st), bytes(r.counts),
            bytes(r.data))

# 1. the captures through both engines: CPython's report
for cls in CLASSES:
    got = []
    for name in NAMES:
        got.extend(SR.report(SR.load(name + ".slcan"), False, cls))
    ok = got == WANT
    fails += not ok
    print("@@captures", cls.ENGINE, "ok" if ok else "differ", len(NAMES))

# 2. pseudo-random streams, cut at random, timed across the line timeout
seed = 0x2545F491
def rnd(k):
    global seed
    seed ^= (seed << 13) & 0xFFFFFFFF
    seed ^= seed >> 17
    seed ^= (seed << 5) & 0xFFFFFFFF
    return seed % k
ALPHA = b"\r\r\r\n0189AFCcf7tTrRsSZOLVNx \x07\xff"
GOOD = (b"t18181122334455667788\r", b"T1ABCDEF081122334455667788\r", b"r7FF8\r", b"t0000\r", b"S6\r", b"O\r",
        b"s0A1b\r", b"Z1\r", b"t1234aabbccdd\r", b"T1FFFFFFF0\r")
calls = 0
bad = 0
buf = bytearray(200)
for case in range(STREAMS):
    n = 0
    while n < 150:
        if rnd(3):
            g = GOOD[rnd(len(GOOD))]
            for c in g:
                buf[n] = c
                n += 1
        else:
            buf[n] = ALPHA[rnd(len(ALPHA))] if rnd(4) else rnd(256)
            n += 1
        if rnd(5) == 0 and n > 0:
            buf[rnd(n)] = ALPHA[rnd(len(ALPHA))]
    a = CLASSES[0](1000)
    b = CLASSES[1](1000)
    now = 0x3FFFF000
    i = 0
    while i < n and not bad:
        end = i + 1 + rnd(40)
        if end > n:
            end = n
        now = (now + rnd(1300)) & 0x3FFFFFFF
        if rnd(8) == 0 and a.gap(now) != b.gap(now):
            bad = 1
        while i < end:
            j = a.feed(buf, i, end, now)
            calls += 1
            if b.feed(buf, i, end, now) != j or snap(a) != snap(b):
                bad = 1
                print("differ", case, i, end, bytes(buf[:n]))
                break
            i = j
fails += bad
print("@@streams", STREAMS, calls, "ok" if not bad else "differ")

# 3. cost: instructions per call, a whole line in one buffer
N = 100
def loop():
    for k in range(N):
        pass
t0 = ticks_us(); loop(); EMPTY = ticks_diff(ticks_us(), t0)
LINES = (b"t18181122334455667788\r", b"T1ABCDEF081122334455667788\r", b"t0000\r", b"r7FF8\r", b"S6\r", b"t12G4567\r")
def feed_cost(cls, line):
    r = cls()
    n = len(line)
    r.feed(line, 0, n, 1000)
    t0 = ticks_us()
    for k in range(N):
        r.feed(line, 0, n, 1000)
    return (ticks_diff(ticks_us(), t0) - EMPTY) * 1000 // N
for line in LINES:
    print("@@feed", line[:-1].decode(), len(line), feed_cost(CLASSES[0], line), feed_cost(CLASSES[1], line))
DATA = b"\x11\x22\x33\x44\x55\x66\x77\x88"
out = bytearray(40)
def enc_cost(enc, args):
    a0, a1, a2, a3, a4, a5 = args
    o = out
    t0 = ticks_us()
    for k in range(N):
        enc(o, 0, a0, a1, a2, a3, a4, a5)
    return (ticks_diff(ticks_us(), t0) - EMPTY) * 1000 // N
for args in ((0x181, 0, 0, DATA, 8, -1), (0x1ABCDEF0, 1, 0, DATA, 8, -1), (0x181, 0, 0, DATA, 8, 12345),
             (0x7FF, 0, 1, DATA, 0, -1)):
    end = S.encode_py(out, 0, args[0], args[1], args[2], args[3], args[4], args[5])
    print("@@encode", bytes(out[:end - 1]).decode(), end, enc_cost(S.slcanfast_encode, args), enc_cost(S.encode_py, args))

# 4. nothing allocated: lines read and written back, a dropped line, a refused one
for cls in CLASSES:
    r = cls(1000)
    for rounds in (1, 20):
        gc.collect()
        gc.disable()
        a0 = gc.mem_alloc()
        for k in range(rounds):
            for line in LINES:
                r.feed(line, 0, len(line), 5)
                if r.ev == 1 and r.cmd in b"tTrR":
                    S.encode_frame(out, 0, r.can_id, r.ext, r.rtr, r.data, r.dlc, 77)
            r.feed(LINES[0], 0, 9, 5)
            r.gap(3000)
        grew = gc.mem_alloc() - a0
        gc.enable()
    fails += grew != 0
    print("@@alloc", cls.ENGINE, grew)
print("@@fails", fails)
"""


def fail(msg, code=2):
    print("slcan_qemu: " + msg, file=sys.stderr)
    sys.exit(code)


def expected_reports(names):
    """CPython's replay report of every capture (the table engine)."""
    sys.path.insert(0, os.path.join(ROOT, "firmware"))
    sys.path.insert(0, os.path.join(ROOT, "host_tests"))
    import slcan_replay as sr

    want = []
    for name in names:
        want.extend(sr.report(sr.load(os.path.join(CAPTURES, name + ".slcan"))))
    return want


CAN_SUITE = """
import machine
try:
    import qemu_suite, can_suite
    print("@@engine", getattr(sys.modules['jig.slcan'].SlcanReader, 'ENGINE', 'table (before the engines)'))
    can_suite.run(qemu_suite.result, qemu_suite.fail, qemu_suite.check_board())
    print("@@fails 0")
except Exception as e:
    sys.print_exception(e)
machine.reset()
"""


def source_at(rev, path):
    """The text of path (relative to the repository) at git revision rev, or None."""
    run = subprocess.run(["git", "-C", ROOT, "show", "%s:%s" % (rev, path)], capture_output=True)
    return run.stdout.decode("utf-8") if run.returncode == 0 else None


def can_suite_script(rev):
    """tools/firmware/qemu/can_suite.py's CAN port figures with jig.slcan (and jig.slcanfast) of
    the work tree, or of git revision rev, in place of the frozen ones."""
    blocks = [SETUP]
    for name in ("slcanfast", "slcan"):
        path = "firmware/jig/%s.py" % name
        if rev:
            text = source_at(rev, path)
        else:
            with open(os.path.join(ROOT, path), encoding="utf-8") as f:
                text = f.read()
        if text is None and name == "slcan":
            fail("%s has no %s." % (rev, path))
        if text is not None:
            blocks.append("jig.%s = _mod(%r, 'jig.%s')" % (name, text, name))
    blocks.append(CAN_SUITE)
    return "".join("\x05" + b + "\n\x04" for b in blocks)


def paste_script(streams):
    def read(*parts):
        with open(os.path.join(ROOT, *parts), encoding="utf-8") as f:
            return f.read()

    names = [os.path.basename(p)[:-len(".slcan")] for p in sorted(glob.glob(os.path.join(CAPTURES, "*.slcan")))]
    files = {}
    for name in names:
        for ext in (".slcan", ".expect"):
            files[name + ext] = read("host_tests", "captures", "slcan", name + ext)
    blocks = [
        SETUP,
        "_fast = _mod(%r, 'jig.slcanfast')\njig.slcanfast = _fast" % read("firmware", "jig", "slcanfast.py"),
        "_s = _mod(%r, 'jig.slcan')\njig.slcan = _s\n_s.slcanfast_encode = _fast.encode_frame"
        % read("firmware", "jig", "slcan.py"),
        "FILES = %r\ndef _open(path):\n    return io.StringIO(FILES[path])\n"
        "SR = _mod(%r, 'slcan_replay', {'open': _open})" % (files, read("host_tests", "slcan_replay.py")),
        "NAMES = %r\nWANT = %r\nSTREAMS = %d" % (names, expected_reports(names), streams),
        "import machine\ntry:\n    exec(%r)\nexcept Exception as e:\n    sys.print_exception(e)\n"
        "    print('@@fails 99')\nmachine.reset()\n" % DEVICE,
    ]
    return "".join("\x05" + b + "\n\x04" for b in blocks)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--elf", default=DEFAULT_ELF, help="a qemu build of make test-qemu (default: %(default)s)")
    ap.add_argument("--streams", type=int, default=200, help="pseudo-random streams for the parity check")
    ap.add_argument("--timeout", type=int, default=300, help="seconds before QEMU is stopped")
    ap.add_argument("--raw", action="store_true", help="print QEMU's whole output")
    ap.add_argument("--can-suite", action="store_true",
                    help="instead: the CAN port's figures of tools/firmware/qemu/can_suite.py (a make test-qemu ELF "
                         "with memcan) with the work tree's jig.slcan in place of the frozen one")
    ap.add_argument("--rev", help="with --can-suite: jig.slcan (and jig.slcanfast) of this git revision")
    args = ap.parse_args(argv)
    if args.rev and not args.can_suite:
        fail("--rev goes with --can-suite.")
    if not os.path.isfile(args.elf):
        fail("no %s: build one with make test-qemu MICROPY_DIR=... or name one with --elf." % args.elf)
    if shutil.which("qemu-system-arm") is None:
        fail("qemu-system-arm is missing: install it (Debian: apt-get install qemu-system-arm).")
    script = can_suite_script(args.rev) if args.can_suite else paste_script(args.streams)
    try:
        run = subprocess.run(["qemu-system-arm", "-machine", "mps2-an500", "-nographic", "-monitor", "null",
                              "-semihosting", "-icount", "shift=0", "-serial", "stdio", "-kernel", args.elf],
                             input=script.encode("utf-8"), capture_output=True,
                             timeout=args.timeout)
    except subprocess.TimeoutExpired:
        fail("QEMU did not finish within %d s." % args.timeout)
    text = run.stdout.decode("utf-8", "replace").replace("\r", "")
    lines = [ln for ln in text.split("\n")
             if ln.startswith(("@@", "differ", "Traceback", "  File", "RESULT can ", "FAIL"))
             or ln.split(":")[0].endswith("Error")]
    if args.raw:
        print(text)
    fails = None
    for ln in lines:
        head = ln.split()
        if head[0] == "@@feed":
            print("feed %-28s %2s bytes: viper %6s, table %6s instructions" % tuple(head[1:]))
        elif head[0] == "@@encode":
            print("encode_frame %-30s (%2s bytes): viper %5s, table %6s instructions" % tuple(head[1:]))
        elif head[0] == "@@fails":
            fails = int(head[1])
        else:
            print(ln.lstrip("@"))
    if fails is None:
        fail("the run on the emulator did not finish (--raw shows QEMU's output).")
    return 1 if fails else 0


if __name__ == "__main__":
    sys.exit(main())
