"""Build, flash, deploy and query the MotorJig STM32H7_JIG board.

    python tools/flash.py build  [--micropython-dir DIR]     make firmware MICROPY_DIR=DIR
    python tools/flash.py flash  [--tool auto|dfu|stlink|pyocd] [--image FILE]
    python tools/flash.py deploy [--port PORT]                 firmware/ as .mpy onto a stock board
    python tools/flash.py info   --port PORT [--baud B] [--slave N]
    python tools/flash.py auto                                 flash an attached jig, else the bench + GUI

``--dry-run`` (before the command) prints the exact commands instead of running
them. Every failure is one sentence with the fix and a non-zero exit status.
The ``info`` command talks Plus-R through the firmware's own ``jig.frame`` and
``jig.parser`` modules.
"""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIRMWARE = os.path.join(ROOT, "firmware")
DEFAULT_BUILD = os.path.join(ROOT, "build", "STM32H7_JIG")
for _p in (FIRMWARE, os.path.join(ROOT, "tools")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

STM_DFU_ID = "0483:df11"  # the STM32 ROM bootloader in USB DFU mode
MICROPYTHON_USB_VID = 0xF055  # MicroPython's USB vendor id (REPL on USB)
USB_PRODUCT_TAG = "MotorJig"  # in the USB product string of the STM32H7_JIG image
FLASH_BASE = 0x08000000
FLASH_APP_MAX = 0x180000  # 1.5 MB: the last 512 KB of flash hold the filesystem
PYOCD_TARGET = "stm32h743xx"
MARCH = "armv7emdp"
DETECT_TIMEOUT = 15
FLASH_TIMEOUT = 600

INSTALL = {
    "dfu": "dfu-util (sudo apt-get install dfu-util)",
    "stlink": "st-flash (sudo apt-get install stlink-tools)",
    "pyocd": "pyocd (pip install pyocd; then pyocd pack install %s)" % PYOCD_TARGET,
}
ENTER_DFU = (
    "put the jig in DFU mode: hold BOOT0 while pressing RESET (or run 'mpremote bootloader' "
    "on a running board), or connect an ST-LINK to the SWD header J5"
)


class FlashError(Exception):
    """A failure with a one-sentence explanation for the user."""


class Runner:
    """Runs (or, in dry-run mode, prints) external commands."""

    def __init__(self, dry_run=False, out=None):
        self.dry_run = dry_run
        self.out = out or sys.stdout
        self.commands = []

    def say(self, text):
        self.out.write(text + "\n")
        self.out.flush()

    def show(self, cmd):
        return " ".join(_quote(c) for c in cmd)

    def run(self, cmd, what, timeout=FLASH_TIMEOUT, cwd=None):
        """Run cmd streaming its output (progress bars included); FlashError on failure."""
        self.commands.append(list(cmd))
        if self.dry_run:
            self.say(self.show(cmd))
            return 0
        self.say("$ " + self.show(cmd))
        try:
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=cwd)
        except FileNotFoundError:
            raise FlashError("%s is not installed: %s." % (cmd[0], _install_hint(cmd[0])))
        except OSError as e:
            raise FlashError("could not start %s (%s)." % (cmd[0], e.strerror or e))
        try:
            while True:
                chunk = proc.stdout.read1(256) if hasattr(proc.stdout, "read1") else proc.stdout.read(1)
                if not chunk:
                    break
                self.out.write(chunk.decode("utf-8", "replace"))
                self.out.flush()
            rc = proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise FlashError("%s did not finish within %d s; unplug and replug the board and try again." % (what, timeout))
        if rc != 0:
            raise FlashError("%s failed (%s exited with status %d); see its output above." % (what, cmd[0], rc))
        return rc

    def capture(self, cmd, timeout=DETECT_TIMEOUT):
        """Output of a detection command ('' if it cannot run)."""
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        except (OSError, subprocess.TimeoutExpired):
            return ""
        return (r.stdout or "") + (r.stderr or "")


def _quote(s):
    s = str(s)
    if s and all(c.isalnum() or c in "-_./:=,@+%" for c in s):
        return s
    return "'" + s.replace("'", "'\\''") + "'"


def _install_hint(tool):
    for key, hint in INSTALL.items():
        if hint.startswith(os.path.basename(tool)):
            return "install " + hint
    if os.path.basename(tool) == "make":
        return "install make (sudo apt-get install make)"
    return "install it"


# --- images ----------------------------------------------------------------------------
def check_image(path):
    """Raise FlashError unless path looks like an STM32H7_JIG image; returns its kind."""
    if not os.path.isfile(path):
        raise FlashError(
            "no firmware image at %s: build it first with 'make firmware MICROPY_DIR=/path/to/micropython'." % path
        )
    with open(path, "rb") as f:
        data = f.read()
    ext = os.path.splitext(path)[1].lower()
    if ext == ".dfu":
        if not data.startswith(b"DfuSe") or len(data) < 16 + 16 or data[-8:-5] != b"UFD":
            raise FlashError("%s is not a DfuSe .dfu file: rebuild with 'make firmware' or pass the .bin." % path)
        return "dfu"
    if ext == ".hex":
        if not data.startswith(b":"):
            raise FlashError("%s is not an Intel HEX file: rebuild with 'make firmware'." % path)
        return "hex"
    if ext == ".bin":
        if len(data) < 8:
            raise FlashError("%s is too short to be a firmware image: rebuild with 'make firmware'." % path)
        sp = int.from_bytes(data[0:4], "little")
        reset = int.from_bytes(data[4:8], "little")
        if not (0x20000000 <= sp <= 0x24080000) or not (FLASH_BASE <= reset < FLASH_BASE + FLASH_APP_MAX) or not reset & 1:
            raise FlashError(
                "%s does not start with an STM32H7 vector table (stack 0x%08x, reset 0x%08x): "
                "pass the firmware.bin that 'make firmware' built." % (path, sp, reset)
            )
        if len(data) > FLASH_APP_MAX:
            raise FlashError(
                "%s is %d bytes, more than the %d bytes before the filesystem: trim the frozen modules."
                % (path, len(data), FLASH_APP_MAX)
            )
        return "bin"
    raise FlashError("%s has an unknown extension: pass firmware.dfu, firmware.bin or firmware.hex." % path)


# --- flashing --------------------------------------------------------------------------
def have(tool):
    return shutil.which(tool) is not None


def dfu_device_present(runner):
    return STM_DFU_ID in runner.capture(["dfu-util", "-l"]) if have("dfu-util") else False


def stlink_present(runner):
    if not have("st-info"):
        return have("st-flash")  # cannot probe: let st-flash report it
    out = runner.capture(["st-info", "--probe"])
    return "Found 0 stlink" not in out and "stlink" in out.lower()


def pyocd_present(runner):
    out = runner.capture(["pyocd", "list"])
    return bool(out) and "No available debug probes" not in out


def flash_command(tool, build, image=None):
    """(command, image path) for a tool: dfu | stlink | pyocd."""
    if tool == "dfu":
        path = image or os.path.join(build, "firmware.bin")
        if path.endswith(".dfu"):
            return ["dfu-util", "-a", "0", "-d", STM_DFU_ID, "-D", path], path
        return ["dfu-util", "-a", "0", "-d", STM_DFU_ID, "-s", "0x%08x:leave" % FLASH_BASE, "-D", path], path
    if tool == "stlink":
        path = image or os.path.join(build, "firmware.bin")
        return ["st-flash", "--reset", "write", path, "0x%08x" % FLASH_BASE], path
    if tool == "pyocd":
        path = image or os.path.join(build, "firmware.hex")
        return ["pyocd", "flash", "-t", PYOCD_TARGET, path], path
    raise FlashError("unknown tool %r: use dfu, stlink or pyocd." % tool)


TOOL_BINARY = {"dfu": "dfu-util", "stlink": "st-flash", "pyocd": "pyocd"}


def choose_tool(runner, wanted="auto"):
    """The flashing tool to use: the one asked for, else the first with a board attached."""
    if wanted != "auto":
        if not have(TOOL_BINARY[wanted]) and not runner.dry_run:
            raise FlashError("%s is not installed: install %s." % (TOOL_BINARY[wanted], INSTALL[wanted]))
        return wanted
    installed = [t for t in ("dfu", "stlink", "pyocd") if have(TOOL_BINARY[t])]
    if not installed:
        if runner.dry_run:
            runner.say("# note: no flashing tool installed; showing the dfu-util command")
            return "dfu"
        raise FlashError(
            "no flashing tool is installed: install %s, %s or %s." % (INSTALL["dfu"], INSTALL["stlink"], INSTALL["pyocd"])
        )
    probes = {"dfu": dfu_device_present, "stlink": stlink_present, "pyocd": pyocd_present}
    for t in installed:
        if probes[t](runner):
            return t
    if runner.dry_run:
        runner.say("# note: no board found in DFU mode or on a debug probe; showing the %s command" % TOOL_BINARY[installed[0]])
        return installed[0]
    others = [INSTALL[t] for t in ("dfu", "stlink", "pyocd") if t not in installed]
    hint = (" (for other ways in: install %s)" % " or ".join(others)) if others else ""
    raise FlashError("no board found with %s: %s%s." % (", ".join(TOOL_BINARY[t] for t in installed), ENTER_DFU, hint))


def cmd_flash(args, runner):
    if args.image and not runner.dry_run:
        check_image(args.image)
    elif not runner.dry_run and not os.path.isfile(os.path.join(args.build, "firmware.bin")):
        check_image(os.path.join(args.build, "firmware.bin"))
    tool = choose_tool(runner, args.tool)
    cmd, path = flash_command(tool, args.build, args.image)
    if not runner.dry_run:
        check_image(path)
        runner.say("flashing %s (%d bytes) with %s" % (path, os.path.getsize(path), TOOL_BINARY[tool]))
    runner.run(cmd, "flashing")
    if not runner.dry_run:
        after = "the jig restarts by itself" if tool != "dfu" or not path.endswith(".dfu") else "press RESET to start it"
        runner.say("flash: done; %s (set BOOT0 low if you used the BOOT0 jumper)." % after)
    return 0


# --- build -----------------------------------------------------------------------------
def cmd_build(args, runner):
    mp = args.micropython_dir or os.environ.get("MICROPY_DIR", "")
    cmd = ["make", "-C", ROOT, "firmware", "MICROPY_DIR=%s" % mp, "BUILD=%s" % args.build]
    runner.run(cmd, "the firmware build", timeout=3600)
    return 0


# --- deploy onto a stock MicroPython board --------------------------------------------------
def mpremote_cmd():
    exe = shutil.which("mpremote")
    if exe:
        return [exe]
    try:
        import mpremote  # noqa: F401
    except ImportError:
        raise FlashError("mpremote is not installed: run 'tools/setup.sh' (or pip install mpremote).")
    return [sys.executable, "-m", "mpremote"]


def firmware_sources():
    out = []
    for folder, _dirs, files in os.walk(os.path.join(FIRMWARE, "jig")):
        for name in sorted(files):
            if name.endswith(".py"):
                out.append(os.path.join(folder, name))
    return sorted(out)


def deploy_commands(stage, port):
    """mpy-cross commands per module, then the mpremote command that copies and resets."""
    cmds = []
    for src in firmware_sources():
        rel = os.path.relpath(src, FIRMWARE)
        dst = os.path.join(stage, "lib", rel[:-3] + ".mpy")
        cmds.append(([sys.executable, "-m", "mpy_cross", "-march=" + MARCH, "-s", rel, "-o", dst, src], os.path.dirname(dst)))
    mpr = mpremote_cmd() + ["connect", port or "auto"]
    copy = mpr + [
        "fs", "cp", "-r", os.path.join(stage, "lib"), ":/flash/",
        "+", "fs", "cp", os.path.join(FIRMWARE, "main.py"), ":/flash/main.py",
        "+", "reset",
    ]
    return cmds, copy


def cmd_deploy(args, runner):
    stage = args.stage
    if not stage:
        if runner.dry_run:
            stage = os.path.join(tempfile.gettempdir(), "motorjig-deploy")
        else:
            stage = tempfile.mkdtemp(prefix="motorjig-deploy-")
    compiles, copy = deploy_commands(stage, args.port)
    for cmd, folder in compiles:
        if not runner.dry_run:
            os.makedirs(folder, exist_ok=True)
        if runner.dry_run:
            runner.say(runner.show(cmd))
            continue
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise FlashError(
                "mpy-cross could not compile %s: %s" % (os.path.relpath(cmd[-1], ROOT), (r.stderr or r.stdout).strip().splitlines()[-1:])
            )
    if not runner.dry_run:
        runner.say("deploy: compiled %d modules for %s into %s" % (len(compiles), MARCH, stage))
    try:
        runner.run(copy, "copying to the board")
    except FlashError as e:
        raise FlashError(
            "%s Check that a MicroPython board is connected over USB (--port /dev/ttyACM0) and that no "
            "other program (a terminal, Thonny) holds its port." % e
        )
    if not runner.dry_run:
        runner.say("deploy: done; the board restarted into the bridge (on the jig image itself the frozen copy wins).")
    return 0


# --- info: GetSlaveInfo and the counters over RS-485 ----------------------------------------
def open_serial(port, baud):
    try:
        import serial
    except ImportError:
        raise FlashError("pyserial is not installed: run 'tools/setup.sh' (or pip install pyserial).")
    try:
        return serial.serial_for_url(port, baudrate=baud, timeout=0.02)
    except serial.SerialException as e:
        text = str(e)
        low = text.lower()
        if "busy" in low or "in use" in low or "errno 16" in low:
            raise FlashError("serial port %s is in use by another program: close it (terminal, jigctl, GUI) and retry." % port)
        if "permission" in low or "errno 13" in low:
            raise FlashError(
                "no permission to open %s: add yourself to the dialout group (sudo usermod -aG dialout $USER) and log in again." % port
            )
        if "no such file" in low or "errno 2" in low or "could not open" in low:
            raise FlashError(
                "serial port %s does not exist: list ports with 'python -m serial.tools.list_ports'." % port
            )
        raise FlashError("cannot open serial port %s (%s)." % (port, text))


def transact(ser, slave, ftype, data=b"", timeout=0.3, clock=None):
    """Send one request, return the reply's data field (status first) or None on timeout."""
    import time

    from jig import frame
    from jig.parser import FrameParser

    clock = clock or time.monotonic
    p = FrameParser()
    ser.reset_input_buffer()
    ser.write(frame.encode(slave, ftype, data))
    deadline = clock() + timeout
    while clock() < deadline:
        chunk = ser.read(256)
        i = 0
        while i < len(chunk):
            i = p.feed(chunk, i, len(chunk))
            if p.ready and p.slave == slave and p.ftype == ftype:
                return bytes(p.body[p.data_start : p.data_end])
    return None


def slave_info_text(data):
    """'type N, "name"' from a GetSlaveInfo reply data field."""
    if len(data) < 2 or data[0] != 0:
        raise FlashError("the jig answered GetSlaveInfo with status 0x%02x: check the slave id (--slave)." % (data[0] if data else 0xFF))
    name = bytes(data[2:]).split(b"\x00")[0].decode("ascii", "replace")
    return "type %d, %r" % (data[1], name)


def cmd_info(args, runner, ser=None):
    from jig import diag, frame

    if runner.dry_run:
        runner.say("# open %s at %d baud, send GetSlaveInfo (0x01) and ReadCounters (0x%02X) to slave %d"
                   % (args.port, args.baud, diag.READ_COUNTERS, args.slave))
        return 0
    own = ser is None
    if own:
        ser = open_serial(args.port, args.baud)
    try:
        data = transact(ser, args.slave, frame.GET_SLAVE_INFO)
        if data is None:
            raise FlashError(
                "no reply from slave %d at %d baud on %s: check A/B wiring, the baud rate (--baud), the id (--slave) "
                "and that the jig is not in safe boot." % (args.slave, args.baud, args.port)
            )
        runner.say("slave %d: %s" % (args.slave, slave_info_text(data)))
        data = transact(ser, args.slave, diag.READ_COUNTERS)
        if data is None:
            runner.say("counters: no reply to ReadCounters (a driver, not the jig, may own this id).")
            return 0
        try:
            counters = diag.decode_counters(data)
        except ValueError as e:
            raise FlashError("the ReadCounters reply does not decode (%s): update tools and firmware together." % e)
        runner.say("counters:")
        for name, value in counters.items():
            runner.say("  %-22s %d" % (name, value))
        return 0
    finally:
        if own:
            ser.close()


# --- auto: the README's main job ----------------------------------------------------------
def _usb_interface(location):
    """The USB interface number in a port's location ("1-1.2:1.0" -> 0), or -1."""
    if not location or ":" not in location:
        return -1
    try:
        return int(location.rsplit(".", 1)[-1])
    except ValueError:
        return -1


def micropython_boards():
    """The REPL ports of running jigs: MicroPython's USB vendor id and our product string
    (so an unrelated MicroPython board is never switched to DFU mode). A jig has two CDC
    ports with the same ids, the REPL and the capture stream: per board (serial number)
    the one on the lowest USB interface, the REPL's, is kept."""
    try:
        from serial.tools import list_ports
    except ImportError:
        return []
    found = {}
    for p in list_ports.comports():
        text = "%s %s" % (getattr(p, "product", "") or "", getattr(p, "description", "") or "")
        if getattr(p, "vid", None) == MICROPYTHON_USB_VID and USB_PRODUCT_TAG in text:
            key = getattr(p, "serial_number", None) or p.device
            rank = (_usb_interface(getattr(p, "location", None)), p.device)
            if key not in found or rank < found[key][0]:
                found[key] = (rank, p.device)
    return sorted(device for _rank, device in found.values())


def bench_command():
    """The virtual bench with MotorJig Desk connected to it (prints the page's URL)."""
    return [sys.executable, "-m", "motorjig.desk", "--bench"]


def cmd_auto(args, runner):
    image = os.path.join(args.build, "firmware.bin")
    built = os.path.isfile(image)
    if built:
        if dfu_device_present(runner):
            runner.say("auto: a board is waiting in DFU mode and %s exists: flashing it." % image)
            args.tool, args.image = "dfu", None
            return cmd_flash(args, runner)
        boards = micropython_boards()
        if boards and have("dfu-util"):
            runner.say("auto: MicroPython board on %s and a built image: switching it to DFU mode and flashing." % boards[0])
            runner.run(mpremote_cmd() + ["connect", boards[0], "bootloader"], "switching the board to DFU mode", timeout=30)
            if not runner.dry_run:
                import time

                for _ in range(20):
                    if dfu_device_present(runner):
                        break
                    time.sleep(0.5)
            args.tool, args.image = "dfu", None
            return cmd_flash(args, runner)
    elif dfu_device_present(runner):
        runner.say("auto: a board is in DFU mode but no image is built (make firmware MICROPY_DIR=...); starting the virtual bench.")
    cmd = bench_command() + list(args.bench_args)
    if runner.dry_run:
        runner.say(runner.show(cmd))
        return 0
    try:
        import importlib.util

        if importlib.util.find_spec("motorjig.sim") is None or importlib.util.find_spec("nicegui") is None:
            raise ImportError
    except ImportError:
        raise FlashError("the virtual bench and its GUI (motorjig.sim, nicegui) are not installed: run 'make setup'.")
    runner.say("auto: no jig to flash; starting the virtual bench and MotorJig Desk on it: " + runner.show(cmd))
    sys.stdout.flush()
    os.execv(cmd[0], cmd)
    return 0  # not reached


# --- command line ------------------------------------------------------------------------
def build_parser():
    ap = argparse.ArgumentParser(
        prog="flash.py",
        description="Build, flash, deploy and query the MotorJig STM32H7_JIG board.",
    )
    ap.add_argument("--dry-run", action="store_true", help="print the exact commands instead of running them")
    ap.add_argument("--build", default=DEFAULT_BUILD, help="build folder with firmware.* (default: %(default)s)")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")
    b = sub.add_parser("build", help="build the image: make firmware MICROPY_DIR=...")
    b.add_argument("--micropython-dir", help="MicroPython checkout (default: $MICROPY_DIR)")
    f = sub.add_parser("flash", help="flash the built image (dfu-util, st-flash or pyocd)")
    f.add_argument("--tool", choices=("auto", "dfu", "stlink", "pyocd"), default="auto",
                   help="flashing tool (default: the first installed one that sees a board)")
    f.add_argument("--image", help="image file (default: firmware.bin, .hex for pyocd)")
    d = sub.add_parser("deploy", help="copy firmware/ as .mpy onto a stock MicroPython board with mpremote")
    d.add_argument("--port", help="serial port of the board (default: mpremote's auto)")
    d.add_argument("--stage", help=argparse.SUPPRESS)
    i = sub.add_parser("info", help="read GetSlaveInfo and the counters of a jig over RS-485")
    i.add_argument("--port", required=True, help="serial port or pyserial URL of the PC-side RS-485 adapter")
    i.add_argument("--baud", type=int, default=115200, help="baud rate (default: %(default)s)")
    i.add_argument("--slave", type=int, default=1, help="the jig's slave id (default: %(default)s)")
    a = sub.add_parser("auto", help="flash an attached jig if an image is built, else start the virtual bench "
                       "with MotorJig Desk on it (further options go to 'python -m motorjig.desk --bench')")
    a.set_defaults(bench_args=[])
    # Sub-commands see the global options too (flash.py flash --dry-run works).
    for p in (b, f, d, i, a):
        p.add_argument("--dry-run", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
        p.add_argument("--build", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    return ap


COMMANDS = {"build": cmd_build, "flash": cmd_flash, "deploy": cmd_deploy, "info": cmd_info, "auto": cmd_auto}


def main(argv=None, out=None):
    ap = build_parser()
    args, extra = ap.parse_known_args(argv)
    if extra:
        if args.command != "auto":
            ap.error("unrecognized arguments: %s" % " ".join(extra))
        args.bench_args = [a for a in extra if a != "--"]
    if not args.command:
        ap.print_help()
        return 2
    if not hasattr(args, "tool"):
        args.tool, args.image = "auto", None
    runner = Runner(args.dry_run, out)
    try:
        return COMMANDS[args.command](args, runner)
    except FlashError as e:
        sys.stderr.write("flash.py %s: %s\n" % (args.command, e))
        return 1
    except KeyboardInterrupt:
        sys.stderr.write("flash.py %s: interrupted.\n" % args.command)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like: stop quietly
        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 0
    except Exception as e:  # never a traceback for the user
        sys.stderr.write("flash.py %s: unexpected error (%s: %s); run with --dry-run to see the commands.\n"
                         % (args.command, type(e).__name__, e))
        return 1


if __name__ == "__main__":
    sys.exit(main())
