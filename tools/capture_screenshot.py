"""Take the README's picture of Wireshark showing both buses, recorded by the jig.

    .venv/bin/python tools/capture_screenshot.py [OUT.png]   default: docs/wireshark-both-buses.png

Runs a short session on the virtual bench with the jig recording both buses
(parameter 13): GetSlaveInfo to ids 0..4 as a bus scan does, servo on, a move,
GetAllStatus polls, a parameter read, a request with a broken CRC; turns the
jig's record stream into pcapng with jigctl's own code (motorjig.capture), and
opens it in Wireshark with the Plus-R dissector on a virtual X display (Xvfb),
a driver-bus reply selected and its tree expanded, then saves the screen.

Needs Debian's wireshark-qt, xvfb, xdotool and imagemagick (not part of the
setup: only this picture needs them).
"""

import os
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [os.path.join(ROOT, "firmware"), os.path.join(ROOT, "tools")]

from jig import frame  # noqa: E402
from jig import params as P  # noqa: E402
from motorjig.capture import pcapng  # noqa: E402
from motorjig.capture.jigstream import JigStream  # noqa: E402
from motorjig.sim import SimBench  # noqa: E402

LUA = os.path.join(ROOT, "tools", "motorjig", "capture", "plusr.lua")
NEEDED = (("wireshark", "wireshark-qt"), ("Xvfb", "xvfb"), ("xdotool", "xdotool"), ("import", "imagemagick"))
COLUMNS = ('gui.column.format:"No.","%m","Time","%t","Bus","%Cus:frame.interface_name:0:R",'
           '"Dir","%Cus:frame.packet_flags_direction:0:R","Info","%i",'
           '"Turnaround","%Cus:plusr.turnaround:0:R","Response","%Cus:plusr.time:0:R"')
WIDTHS = ("%m", 45, "%t", 85, "%Cus:frame.interface_name:0:R", 60, "%Cus:frame.packet_flags_direction:0:R", 72,
          "%i", 640, "%Cus:plusr.turnaround:0:R", 120, "%Cus:plusr.time:0:R", 120)
SIZE = (1500, 900)
DETAILS_Y = 524  # the third line of the packet details pane: the Plus-R tree
SELECT = "plusr.kind == 1 && frame.interface_name == \"drivers\" && plusr.type == 0x43"  # a GetAllStatus reply


def session(path):
    """The bench session, recorded by the jig, as pcapng at path; returns the packets."""
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
    js = JigStream("virtual bench")
    records = js.feed(bytes(b.app.capture.drain_to(bytearray())))
    with open(path, "wb") as f:
        w = pcapng.Writer(f, js.buses(), hardware=js.description())
        for r in records:
            w.write(r)
    return len(records)


def first_match(path, home):
    """Frame number of the packet to select (tshark with the same dissector)."""
    out = subprocess.run(["tshark", "-r", path, "-X", "lua_script:" + LUA, "-2", "-Y", SELECT, "-T", "fields",
                          "-e", "frame.number"], capture_output=True, text=True, env=dict(os.environ, HOME=home),
                         timeout=60)
    lines = out.stdout.split()
    return int(lines[0]) if lines else 1


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0
    out = os.path.abspath(argv[0] if argv else os.path.join(ROOT, "docs", "wireshark-both-buses.png"))
    missing = [pkg for prog, pkg in NEEDED if shutil.which(prog) is None]
    if missing:
        sys.stderr.write("capture_screenshot: needs %s (sudo apt-get install %s).\n"
                         % (", ".join(missing), " ".join(missing)))
        return 2
    tmp = tempfile.mkdtemp(prefix="motorjig-ws-")
    xvfb = ws = None
    try:
        cap = os.path.join(tmp, "jig-both-buses.pcapng")
        n = session(cap)
        home = os.path.join(tmp, "home")
        conf = os.path.join(home, ".config", "wireshark")
        os.makedirs(conf)
        with open(os.path.join(conf, "recent"), "w") as f:  # the packet list's column widths
            f.write("column.width: %s\n" % ", ".join(str(x) for x in WIDTHS))
        env = dict(os.environ, HOME=home, DISPLAY=":91", XDG_RUNTIME_DIR=tmp)
        env.pop("XDG_CONFIG_HOME", None)
        xvfb = subprocess.Popen(["Xvfb", ":91", "-screen", "0", "%dx%dx24" % SIZE, "-nolisten", "tcp"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(2)
        select = first_match(cap, home)
        ws = subprocess.Popen(["wireshark", "-r", cap, "-X", "lua_script:" + LUA, "-o", COLUMNS,
                               "-o", "gui.packet_list_show_minimap:FALSE", "-g", str(select)],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        win = ""
        for _ in range(60):
            time.sleep(0.5)
            win = subprocess.run(["xdotool", "search", "--name", "jig-both-buses"], env=env,
                                 capture_output=True, text=True).stdout.split()
            if win:
                break
        if not win:
            sys.stderr.write("capture_screenshot: Wireshark did not open a window within 30 s.\n")
            return 1
        w = win[0]
        subprocess.run(["xdotool", "windowmove", w, "0", "0", "windowsize", w, str(SIZE[0]), str(SIZE[1])], env=env)
        time.sleep(2)
        # The packet details pane (no window manager here: click into it): the Plus-R
        # tree of the selected packet, its subtrees expanded (Shift+Right).
        subprocess.run(["xdotool", "mousemove", "120", str(DETAILS_Y), "click", "1", "key", "shift+Right"], env=env)
        time.sleep(2)
        subprocess.run(["import", "-window", "root", out], env=env, check=True)
        print("capture_screenshot: %d records of both buses, packet %d selected: %s" % (n, select, out))
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
