"""The bench's EtherCAT segment: a line of simulated slaves a frame passes in order, and its wire.

``Segment.process(frame)`` takes one EtherCAT frame from the master through every slave, as it
runs through a real line and back: each slave serves each datagram (``ecat_esc.Esc.serve``),
the position field and the working counters change in place, the first slave marks the source
address as an ESC does, and the frame returns. A slave with its link down ends the line before
it (the one before closes its port); one that loses frames returns nothing.

``Wire`` is the segment's Ethernet side: a network namespace of the bench's own with a veth pair,
the master's end outside it (the interface a master such as SOEM opens like a NIC), the slaves'
end inside, read and written with a raw socket of ethertype 0x88A4. It needs root (network
namespaces and raw sockets); ``Wire.check_permissions`` says so in one sentence. ``serve`` runs
the segment on the wire until stopped, on the bench's clock.
"""

import ctypes
import os
import select
import socket
import struct
import subprocess
import sys
import time

from motorjig.ecat.frame import ETHERTYPE

from .clock import VirtualClock

CLONE_NEWNET = 0x40000000
ETH_HEADER = 14


class Segment:
    """Slaves in line order (objects with ``esc`` and optionally ``lost_every``)."""

    def __init__(self, slaves):
        self.slaves = list(slaves)
        self.frames = 0
        self.lost = 0
        self.errors = 0  # frames that were not EtherCAT datagram frames
        self.turnaround = [0] * 64  # frames by the time the slaves took to serve them, 50 µs bins (the last: more)
        self.turnaround_max_us = 0.0

    def turnaround_text(self):
        """The slaves' time per frame, from receiving it to sending it back: median, p99, max."""
        n = sum(self.turnaround)
        if not n:
            return "no frames yet"

        def pct(q):
            seen = 0
            for i, c in enumerate(self.turnaround):
                seen += c
                if seen >= q * n:
                    return (i + 1) * 50
            return self.turnaround_max_us

        return "%d frames, turnaround median < %d us, p99 < %d us, max %.0f us" % (n, pct(0.5), pct(0.99),
                                                                               self.turnaround_max_us)

    def _line(self):
        """The slaves the frames reach now, their ports set as the line is."""
        line = []
        for s in self.slaves:
            if not s.esc.link_up:
                break
            line.append(s)
        for i, s in enumerate(line):
            s.esc.downstream = i + 1 < len(line)
            s.esc.hops_back = len(line) - 1 - i
            s.esc.position = i
        return line

    def process(self, frame):
        """The frame as it comes back to the master (a bytearray), or None when it is lost."""
        frame = bytearray(frame)
        self.frames += 1
        if len(frame) < ETH_HEADER + 2 or struct.unpack_from(">H", frame, 12)[0] != ETHERTYPE:
            self.errors += 1
            return None
        header = struct.unpack_from("<H", frame, ETH_HEADER)[0]
        if header >> 12 != 1:
            self.errors += 1
            return None
        end = min(len(frame), ETH_HEADER + 2 + (header & 0x7FF))
        datagrams = []
        pos = ETH_HEADER + 2
        while pos + 12 <= end:
            cmd, _idx, adp, ado, flags = struct.unpack_from("<BBHHH", frame, pos)
            n = flags & 0x7FF
            if pos + 10 + n + 2 > end:
                self.errors += 1
                return None
            datagrams.append([pos, cmd, adp, ado, n, struct.unpack_from("<H", frame, pos + 10 + n)[0]])
            pos += 10 + n + 2
            if not flags & 0x8000:
                break
        view = memoryview(frame)
        for s in self._line():
            lost_every = getattr(s, "lost_every", None)
            s.esc.frames += 1
            if lost_every and s.esc.al_state == 8 and s.esc.frames % lost_every == 0:
                self.lost += 1
                return None
            t_ns = s.esc.clock_ns()
            for d in datagrams:
                p, cmd, adp, ado, n, wkc = d
                d[2], d[5] = s.esc.serve(cmd, adp, ado, view[p + 10:p + 10 + n], wkc, t_ns)
        for p, _cmd, adp, _ado, n, wkc in datagrams:
            struct.pack_into("<H", frame, p + 2, adp)
            struct.pack_into("<H", frame, p + 10 + n, wkc)
        if self.slaves:
            frame[6] |= 0x02  # the first ESC marks the source address as processed
        return frame


def _run(cmd):
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise OSError("%s failed: %s" % (" ".join(cmd), (r.stderr or r.stdout).strip()))


class Wire:
    """The segment's veth pair in a namespace of its own (see the module's docstring)."""

    def __init__(self, tag=None):
        tag = str(tag or os.getpid())
        self.netns = "motorjig-ecat-%s" % tag
        self.master_ifname = ("mjm%s" % tag)[:15]
        self.slave_ifname = ("mjs%s" % tag)[:15]
        self.sock = None

    @staticmethod
    def check_permissions():
        """None, or the one sentence saying why this user cannot make the bench's EtherCAT wire."""
        if os.geteuid() != 0:
            return ("the EtherCAT bench makes a network namespace and a veth pair and opens raw sockets: "
                    "run it as root (sudo), as a real EtherCAT master needs too")
        if not os.path.exists("/sbin/ip") and not os.path.exists("/usr/sbin/ip") and not os.path.exists("/bin/ip"):
            return "the EtherCAT bench needs the ip command: apt-get install iproute2"
        return None

    def create(self):
        """Make the namespace and the veth pair, both ends up; open the slaves' raw socket inside."""
        self.remove()
        _run(["ip", "netns", "add", self.netns])
        try:
            _run(["ip", "link", "add", self.master_ifname, "type", "veth", "peer", "name", self.slave_ifname])
            _run(["ip", "link", "set", self.slave_ifname, "netns", self.netns])
            _run(["ip", "link", "set", self.master_ifname, "up"])
            _run(["ip", "netns", "exec", self.netns, "ip", "link", "set", self.slave_ifname, "up"])
            for ifname, where in ((self.master_ifname, []), (self.slave_ifname, ["ip", "netns", "exec", self.netns])):
                # no IPv6 chatter on a fieldbus wire
                subprocess.run(where + ["sysctl", "-qw", "net.ipv6.conf.%s.disable_ipv6=1" % ifname],
                               capture_output=True)
            self.sock = self._open_inside()
        except Exception:
            self.remove()
            raise
        return self

    def _open_inside(self):
        libc = ctypes.CDLL(None, use_errno=True)
        own = os.open("/proc/self/ns/net", os.O_RDONLY)
        target = os.open("/var/run/netns/%s" % self.netns, os.O_RDONLY)
        try:
            if libc.setns(target, CLONE_NEWNET) != 0:
                raise OSError(ctypes.get_errno(), "cannot enter the network namespace %s" % self.netns)
            try:
                sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETHERTYPE))
                sock.bind((self.slave_ifname, ETHERTYPE))
                sock.setblocking(False)
            finally:
                libc.setns(own, CLONE_NEWNET)
        finally:
            os.close(own)
            os.close(target)
        return sock

    def remove(self):
        """Close the socket and delete the namespace (its veth end goes with it, the peer too)."""
        if self.sock is not None:
            self.sock.close()
            self.sock = None
        subprocess.run(["ip", "netns", "del", self.netns], capture_output=True)
        subprocess.run(["ip", "link", "del", self.master_ifname], capture_output=True)

    def serve(self, segment, clock, stop=lambda: False, on_frame=None, control=None):
        """Answer the master's frames until ``stop()``: each frame through the segment at once, the
        bench's events (drive motion, watchdogs) in between, at the wall clock's pace.
        ``control``: (a readable file, fn(line)) for the bench's own commands."""
        sock = self.sock
        watch = [sock] + ([control[0]] if control else [])
        while not stop():
            wall = clock.wall()
            VirtualClock.run_until(clock, wall)
            nxt = clock.next_time()
            timeout = 0.01 if nxt is None else min(0.01, max(0.0, (nxt - clock.wall()) / 1e6))
            ready, _w, _x = select.select(watch, [], [], timeout)
            if control and control[0] in ready:
                line = control[0].readline()
                if not line:
                    watch.remove(control[0])  # the controlling side went away: serve on
                else:
                    control[1](line)
            if sock not in ready:
                continue
            while True:
                try:
                    frame, address = sock.recvfrom(2048)
                except BlockingIOError:
                    break
                if address[2] == socket.PACKET_OUTGOING:
                    continue  # our own reply, seen on the way out
                VirtualClock.run_until(clock, clock.wall())
                t0 = time.perf_counter()
                try:
                    out = segment.process(frame)
                except Exception as exc:  # a slave model's bug: that frame is lost, the bus goes on
                    segment.errors += 1
                    out = None
                    if segment.errors == 1:
                        print("ecat bench: a frame could not be served (%s: %s); the bus goes on"
                              % (type(exc).__name__, exc), file=sys.stderr, flush=True)
                if out is not None:
                    sock.send(out)
                us = (time.perf_counter() - t0) * 1e6
                segment.turnaround[min(63, int(us // 50))] += 1
                if us > segment.turnaround_max_us:
                    segment.turnaround_max_us = us
                if on_frame is not None:
                    on_frame(frame, out)
