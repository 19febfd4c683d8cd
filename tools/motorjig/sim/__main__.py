"""python -m motorjig.sim: the virtual bench, interactive.

Starts the simulated jig and drivers in real time, prints the pseudo-terminal path
and the pyserial TCP URL of the PC side, runs a short demo session (scan -> info ->
servo on -> move -> status) through that TCP port, then keeps serving until
Ctrl-C (or --duration seconds).
"""

import argparse
import struct
import sys
import time

from jig import frame as F
from jig.parser import FrameParser

from .bench import Bench


def _ids(text):
    try:
        ids = tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError("expected comma-separated ids, e.g. 2,3")
    for i in ids:
        if not 0 <= i <= 15:
            raise argparse.ArgumentTypeError("driver ids must be 0..15, got %d" % i)
    return ids


def parse_args(argv):
    ap = argparse.ArgumentParser(prog="python -m motorjig.sim", description=__doc__.split("\n\n")[1])
    ap.add_argument("--drivers", type=_ids, default=(2, 3), help="simulated driver ids (default 2,3)")
    ap.add_argument("--baud", type=int, default=115200, help="baud rate of both buses (default 115200)")
    ap.add_argument("--tcp-port", type=int, default=0, help="TCP port for socket:// (default: a free one)")
    ap.add_argument("--no-demo", action="store_true", help="skip the scripted demo session")
    ap.add_argument("--no-pty", action="store_true", help="do not create a pseudo-terminal")
    ap.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (default: run until Ctrl-C)")
    return ap.parse_args(argv)


class DemoClient:
    """A minimal bus master over pyserial (what any PC program would do)."""

    def __init__(self, url):
        import serial

        self.ser = serial.serial_for_url(url, timeout=0.05)

    def request(self, slave, ftype, data=b"", timeout=0.3):
        self.ser.reset_input_buffer()
        self.ser.write(F.encode(slave, ftype, data))
        p = FrameParser()
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            chunk = self.ser.read(256)
            i = 0
            while i < len(chunk):
                i = p.feed(chunk, i)
                if p.ready and p.slave == slave and p.ftype == ftype:
                    return bytes(p.body[p.data_start : p.data_end])
        return None

    def close(self):
        self.ser.close()


def demo(url, ids, out=print):
    c = DemoClient(url)
    try:
        out("demo: scanning ids 0..15 with GetSlaveInfo (0x01) ...")
        found = []
        for i in range(16):
            r = c.request(i, F.GET_SLAVE_INFO, timeout=0.05)
            if r and r[0] == 0:
                name = r[2:].split(b"\x00")[0].decode("ascii", "replace")
                found.append(i)
                out("  id %2d: slave type %3d  %s" % (i, r[1], name))
        drivers = [i for i in found if i in ids]
        if not drivers:
            out("demo: no driver answered")
            return False
        d = drivers[0]
        r = c.request(d, F.SERVO_ENABLE, b"\x01")
        out("demo: servo on id %d -> status 0x%02X" % (d, r[0] if r else -1))
        r = c.request(d, F.MOVE_INC_POS, struct.pack("<iI", 10000, 20000))
        out("demo: move id %d by 10000 pulses at 20000 pps -> status 0x%02X" % (d, r[0] if r else -1))
        for _ in range(8):
            time.sleep(0.15)
            r = c.request(d, F.GET_ALL_STATUS)
            if r:
                _in, _out, flags, cmd, act, err, vel, _pt = struct.unpack("<IIIiiiiI", r[1:])
                out("  status: pos %6d  speed %6d pps  flags 0x%08X%s" % (cmd, vel, flags, "  moving" if flags & (1 << 27) else ""))
                if not flags & (1 << 27) and cmd == 10000:
                    break
        return True
    finally:
        c.close()


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    if args.baud not in (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600):
        print("error: --baud must be one of 9600 19200 38400 57600 115200 230400 460800 921600", file=sys.stderr)
        return 2
    if not 0 <= args.tcp_port <= 65535:
        print("error: --tcp-port must be 0..65535", file=sys.stderr)
        return 2
    bench = Bench(driver_ids=args.drivers, baud=args.baud, tcp_port=args.tcp_port, pty=not args.no_pty)
    try:
        bench.start()
    except OSError as exc:
        bench.stop()
        print("error: cannot start the bench: %s" % exc, file=sys.stderr)
        return 1
    try:
        print("MotorJig virtual bench: jig = slave 1, drivers %s, %d baud" % (",".join(map(str, args.drivers)), args.baud))
        if bench.pty_path:
            print("  pty: %s" % bench.pty_path)
        print("  tcp: %s" % bench.tcp_url)
        sys.stdout.flush()
        if not args.no_demo:
            demo(bench.tcp_url, args.drivers)
        print("serving; Ctrl-C to stop" + (" (stopping after %g s)" % args.duration if args.duration else ""))
        sys.stdout.flush()
        t_end = time.monotonic() + args.duration if args.duration else None
        while t_end is None or time.monotonic() < t_end:
            if bench.error is not None:
                print("error: simulation stopped: %s" % bench.error, file=sys.stderr)
                return 1
            time.sleep(0.1)
    except KeyboardInterrupt:
        print("stopped")
    finally:
        bench.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
