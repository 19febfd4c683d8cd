"""Take the README's pictures of Wireshark showing the buses the jig recorded.

    .venv/bin/python tools/screens/capture_screenshot.py [OUT.png]         default: docs/wireshark-both-buses.png
    .venv/bin/python tools/screens/capture_screenshot.py --can [OUT.png]   default: docs/wireshark-can.png

Without --can: a short session on the virtual bench with the jig recording both
RS-485 buses (parameter 13): GetSlaveInfo to ids 0..4 as a bus scan does, servo
on, a move, GetAllStatus polls, a parameter read, a request with a broken CRC;
a driver-bus reply selected with its Plus-R tree expanded.

With --can: the bench has a CAN bus with two simulated CiA 402 drives (nodes 5
and 6, heartbeat every 100 ms) and the host talks CANopen through the jig's
SLCAN port while the jig records all three buses: NMT reset (the boot-ups), SDO
uploads from node 5 (0x1000, 0x1018 sub 1, the segmented 0x1008 device name),
heartbeats, NMT start, SYNC and the TPDOs it asks for, node 5 enabled and moved
by RPDOs until an injected overcurrent (can:overcurrent) faults it: its EMCY,
selected with its CANopen tree expanded; a Plus-R transaction in between. The
CAN interface is decoded as CANopen (-d can.subdissector,canopen).

Either way the jig's record stream becomes pcapng with jigctl's own code
(motorjig.capture) and opens in Wireshark with the Plus-R dissector on a virtual
X display (Xvfb); the screen is then saved.

Needs Debian's wireshark-qt, xvfb, xdotool and imagemagick (not part of the
setup: only these pictures need them).
"""

import os
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path[:0] = [os.path.join(ROOT, "firmware"), os.path.join(ROOT, "tools")]

from jig import frame  # noqa: E402
from jig import params as P  # noqa: E402
from motorjig.capture import pcapng  # noqa: E402
from motorjig.capture.jigstream import JigStream  # noqa: E402
from motorjig.sim import SimBench  # noqa: E402
from motorjig.sim.cia402 import Cia402Node  # noqa: E402

LUA = os.path.join(ROOT, "tools", "motorjig", "capture", "plusr.lua")
NEEDED = (("wireshark", "wireshark-qt"), ("tshark", "wireshark-qt"), ("Xvfb", "xvfb"), ("xdotool", "xdotool"),
          ("import", "imagemagick"))
BUS = "%Cus:frame.interface_name:0:R"
DIR = "%Cus:frame.packet_flags_direction:0:R"


def columns(cols):
    """The gui.column.format preference for [(title, format, width)]."""
    return "gui.column.format:" + ",".join('"%s","%s"' % (title, fmt) for title, fmt, _w in cols)


def widths(cols):
    """The recent file's column.width line for [(title, format, width)]: a custom column
    is named there by its fields alone (no occurrence, no resolved flag)."""
    names = [fmt.rsplit(":", 2)[0] if fmt.startswith("%Cus:") else fmt for _t, fmt, _w in cols]
    return "column.width: " + ", ".join('"%s", %d' % (name, w) for name, (_t, _f, w) in zip(names, cols))


class Picture:
    """One picture: its session, how Wireshark shows it, which packet is selected."""

    name = "jig-both-buses"  # the pcapng's name, Wireshark's window title
    out = "wireshark-both-buses.png"
    what = "both buses"
    cols = [("No.", "%m", 45), ("Time", "%t", 85), ("Bus", BUS, 70), ("Dir", DIR, 78), ("Info", "%i", 620),
            ("Turnaround", "%Cus:plusr.turnaround:0:R", 120), ("Response", "%Cus:plusr.time:0:R", 120)]
    args = []  # more Wireshark/tshark options
    select = "plusr.kind == 1 && frame.interface_name == \"drivers\" && plusr.type == 0x43"  # a GetAllStatus reply
    details_y = 524  # the third line of the packet details pane: the Plus-R tree
    keys = ["shift+Right"]  # typed there: its subtrees expanded
    recent = []  # more lines of Wireshark's recent file (the profile's)
    recent_common = []  # and of recent_common (the main window's geometry)
    size = (1500, 900)  # the screen's and the window's

    def session(self):
        """The bench session with the jig recording; returns the bench."""
        b = SimBench(driver_ids=(2, 3), jig_params={P.P_CAPTURE: 1}, turnaround_us=300.0)
        for slave in range(5):
            b.transact(frame.encode(slave, frame.GET_SLAVE_INFO), timeout_us=60000)
        b.transact(frame.encode(2, frame.SERVO_ENABLE, b"\x01"))
        b.transact(frame.encode(2, frame.MOVE_INC_POS, (2000).to_bytes(4, "little", signed=True)
                                + (10000).to_bytes(4, "little")))
        for _ in range(3):
            b.transact(frame.encode(2, frame.GET_ALL_STATUS))
            b.run_for(20000)
        b.transact(frame.encode(2, frame.GET_PARAMETER, b"\x01"))
        bad = frame.encode(3, frame.GET_COMMAND_POS)
        b.pc.send(bad[:-3] + bytes([bad[-3] ^ 1]) + bad[-2:])
        b.run_for(60000)
        b.transact(frame.encode(3, frame.GET_ALL_STATUS))
        return b


def slcan_line(cob, data=b""):
    """The SLCAN line of a standard data frame."""
    return b"t%03X%d%s\r" % (cob, len(data), bytes(data).hex().upper().encode())


class CanPicture(Picture):
    """The CAN bus beside the RS-485 buses, decoded as CANopen, an EMCY selected."""

    name = "jig-can-bus"
    out = "wireshark-can.png"
    what = "the CAN bus and the RS-485 buses"
    cols = [("No.", "%m", 45), ("Time", "%t", 85), ("Bus", BUS, 70), ("Dir", DIR, 78),
            ("COB-ID", "%Cus:can.id:0:R", 105), ("Node", "%Cus:canopen.node_id:0:R", 50), ("Info", "%i", 480),
            ("Object", "%Cus:canopen.sdo.main_idx:0:R", 210), ("Sub", "%Cus:canopen.sdo.sub_idx:0:R", 45),
            ("Data", "%Cus:canopen.sdo.data.bytes or canopen.pdo.data.bytes:0:R", 300)]
    args = ["-d", "can.subdissector,canopen"]
    select = "canopen.em.err_code"  # the EMCY
    size = (1500, 1000)
    recent = ["gui.geometry_main_upper_pane: 684", "gui.geometry_main_lower_pane: 860"]
    recent_common = ["gui.geometry_main_x: 0", "gui.geometry_main_y: 0", "gui.geometry_main_width: %d" % size[0],
                     "gui.geometry_main_height: %d" % size[1]]
    details_y = 815  # the packet details pane's third line: the CANopen tree
    keys = ["Right", "Down", "Down", "Right"]  # expanded, and its "Type: EMCY" subtree

    def session(self):
        b = SimBench(driver_ids=(2,), can_nodes=(5, 6), can_bitrate=500000, jig_params={P.P_CAPTURE: 1},
                     turnaround_us=300.0,
                     can_node_factory=lambda clock, bus, i: Cia402Node(clock, bus, i, heartbeat_ms=100))
        b.run_for(20000)  # the drives power up (their boot-ups unheard: the jig's CAN port is closed)
        b.slcan_send(b"S6\rO\r")  # 500 kbit/s, open
        b.slcan_read(2)
        b.slcan_send(slcan_line(0x000, b"\x81\x00"))  # NMT reset node, all: the boot-ups
        b.slcan_read(3)
        self.sdo_upload(b, 5, 0x1000, 0)
        self.sdo_upload(b, 5, 0x1018, 1)
        self.sdo_upload(b, 5, 0x1008, 0)
        b.run_for(90000)  # the pre-operational heartbeats
        b.slcan_send(slcan_line(0x000, b"\x01\x00"))  # NMT start, all
        b.run_for(3000)
        b.transact(frame.encode(2, frame.GET_ALL_STATUS))
        b.slcan_send(slcan_line(0x080))  # SYNC: TPDO2 and TPDO3 of each node
        b.run_for(3000)
        b.set_fault("can:overcurrent", 4.0, 5)  # 4 ms into its next move
        for cw in (0x06, 0x07, 0x0F):  # RPDO1: controlword, profile position mode
            b.slcan_send(slcan_line(0x205, cw.to_bytes(2, "little") + b"\x01"))
            b.run_for(2000)
        b.slcan_send(slcan_line(0x305, (20000).to_bytes(4, "little") + (50000).to_bytes(4, "little")))  # RPDO2
        b.run_for(2000)
        b.slcan_send(slcan_line(0x205, b"\x1f\x00\x01"))  # new set-point: the move
        b.run_for(20000)
        b.slcan_send(slcan_line(0x080))
        b.run_for(90000)  # the operational heartbeats
        return b

    @staticmethod
    def sdo_upload(b, node, index, sub):
        """An SDO upload as a client does it: initiate, then segments until the last."""
        req = bytes([0x40, index & 0xFF, index >> 8, sub])
        toggle = 0
        while True:
            b.slcan_send(slcan_line(0x600 + node, req.ljust(8, b"\0")))
            got = b.slcan_read(2)
            at = got.find(b"t%03X8" % (0x580 + node))
            if at < 0:
                raise RuntimeError("node %d did not answer the SDO upload of 0x%04X" % (node, index))
            scs = int(got[at + 5:at + 7], 16)
            if scs >> 5 == 4 or (scs >> 5 == 2 and scs & 2) or (scs >> 5 == 0 and scs & 1):
                return  # an abort, an expedited upload, the last segment
            req = bytes([0x60 | toggle])
            toggle ^= 0x10


def write_pcapng(b, path):
    """The jig's record stream so far as pcapng at path (jigctl's own writer); returns the record count."""
    js = JigStream("virtual bench")
    records = js.feed(bytes(b.app.capture.drain_to(bytearray())))
    with open(path, "wb") as f:
        w = pcapng.Writer(f, js.buses(), hardware=js.description())
        for r in records:
            w.write(r)
    return len(records)


def first_match(pic, path, home):
    """Frame number of the packet to select (tshark with the same dissectors); None if none matches."""
    out = subprocess.run(["tshark", "-r", path, "-X", "lua_script:" + LUA] + pic.args
                         + ["-2", "-Y", pic.select, "-T", "fields", "-e", "frame.number"],
                         capture_output=True, text=True, env=dict(os.environ, HOME=home), timeout=60)
    lines = out.stdout.split()
    return int(lines[0]) if lines else None


def start_xvfb(env, size):
    """An Xvfb on a free display (it writes the display's number to the pipe); returns (process, ':N')."""
    r, w = os.pipe()
    xvfb = subprocess.Popen(["Xvfb", "-displayfd", str(w), "-screen", "0", "%dx%dx24" % size, "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, pass_fds=(w,), env=env)
    os.close(w)
    with os.fdopen(r) as f:
        number = f.readline().strip()
    return xvfb, ":" + number if number else None


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0
    pic = Picture()
    if argv and argv[0] == "--can":
        pic = CanPicture()
        argv = argv[1:]
    if len(argv) > 1 or (argv and argv[0].startswith("-")):
        sys.stderr.write("capture_screenshot: usage: capture_screenshot.py [--can] [OUT.png] (see --help).\n")
        return 2
    out = os.path.abspath(argv[0] if argv else os.path.join(ROOT, "docs", pic.out))
    missing = sorted({pkg for prog, pkg in NEEDED if shutil.which(prog) is None})
    if missing:
        sys.stderr.write("capture_screenshot: needs %s (sudo apt-get install %s).\n"
                         % (", ".join(missing), " ".join(missing)))
        return 2
    tmp = tempfile.mkdtemp(prefix="motorjig-ws-")
    xvfb = ws = None
    try:
        cap = os.path.join(tmp, pic.name + ".pcapng")
        try:
            n = write_pcapng(pic.session(), cap)
        except RuntimeError as e:
            sys.stderr.write("capture_screenshot: the bench session failed: %s.\n" % e)
            return 1
        home = os.path.join(tmp, "home")
        conf = os.path.join(home, ".config", "wireshark")
        os.makedirs(conf)
        with open(os.path.join(conf, "recent"), "w") as f:  # the packet list's column widths, the panes
            f.write("\n".join([widths(pic.cols)] + pic.recent) + "\n")
        with open(os.path.join(conf, "recent_common"), "w") as f:
            f.write("".join(line + "\n" for line in pic.recent_common))
        env = dict(os.environ, HOME=home, XDG_RUNTIME_DIR=tmp)
        env.pop("XDG_CONFIG_HOME", None)
        xvfb, display = start_xvfb(env, pic.size)
        if display is None:
            sys.stderr.write("capture_screenshot: Xvfb did not start.\n")
            return 1
        env["DISPLAY"] = display
        select = first_match(pic, cap, home)
        if select is None:
            sys.stderr.write("capture_screenshot: no packet of the session matches %r.\n" % pic.select)
            return 1
        ws = subprocess.Popen(["wireshark", "-r", cap, "-X", "lua_script:" + LUA, "-o", columns(pic.cols),
                               "-o", "gui.packet_list_show_minimap:FALSE", "-g", str(select)] + pic.args,
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        win = ""
        for _ in range(60):
            time.sleep(0.5)
            win = subprocess.run(["xdotool", "search", "--name", pic.name], env=env,
                                 capture_output=True, text=True).stdout.split()
            if win:
                break
        if not win:
            sys.stderr.write("capture_screenshot: Wireshark did not open a window within 30 s.\n")
            return 1
        w = win[0]
        subprocess.run(["xdotool", "windowmove", w, "0", "0", "windowsize", w] + [str(x) for x in pic.size], env=env)
        time.sleep(2)
        # The packet details pane (no window manager here: click into it): the protocol's
        # tree of the selected packet, expanded as the picture's keys say.
        subprocess.run(["xdotool", "mousemove", "120", str(pic.details_y), "click", "1", "key"] + pic.keys, env=env)
        subprocess.run(["xdotool", "mousemove", str(pic.size[0] - 100), "38"], env=env)  # no hover highlight
        time.sleep(2)
        # a screen of text looks the same in 256 colours, at a quarter of the PNG's size
        subprocess.run(["import", "-window", "root", "-dither", "None", "-colors", "256", "PNG8:" + out], env=env,
                       check=True)
        print("capture_screenshot: %d records of %s, packet %d selected: %s" % (n, pic.what, select, out))
        return 0
    finally:
        for p in (ws, xvfb):
            if p is not None:
                p.terminate()
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.kill()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
