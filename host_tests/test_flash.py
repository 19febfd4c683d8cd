"""tools/flash.py: command construction, tool detection and error paths.

Flashing tools are fake shell scripts on a PATH that holds nothing else; each one
records its arguments and prints what the real tool would.
"""

import io
import os
import shutil
import stat
import subprocess
import sys

import pytest

import flash
from jig import diag, frame
from jig.parser import FrameParser

GOOD_SP = 0x2407BFF8
GOOD_RESET = 0x08000871


def write_bin(path, sp=GOOD_SP, reset=GOOD_RESET, size=4096):
    data = sp.to_bytes(4, "little") + reset.to_bytes(4, "little") + bytes(size - 8)
    path.write_bytes(data)
    return str(path)


@pytest.fixture
def env(tmp_path, monkeypatch):
    """Empty PATH with a folder for fake tools, and a build folder with an image."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    build = tmp_path / "build"
    build.mkdir()
    write_bin(build / "firmware.bin")
    (build / "firmware.hex").write_text(":020000040800F2\n:00000001FF\n")
    monkeypatch.setenv("PATH", str(bindir))

    def tool(name, stdout="", rc=0):
        log = tmp_path / (name + ".args")
        script = bindir / name
        script.write_text(
            "#!/bin/sh\nprintf '%%s\\n' \"$@\" >> '%s'\nprintf '%%s' '%s'\nexit %d\n"
            % (log, stdout.replace("'", ""), rc)
        )
        script.chmod(script.stat().st_mode | stat.S_IXUSR)
        return log

    class Env:
        pass

    e = Env()
    e.tool = tool
    e.build = str(build)
    e.tmp = tmp_path
    return e


def run(argv):
    out = io.StringIO()
    err = io.StringIO()
    old = sys.stderr
    sys.stderr = err
    try:
        rc = flash.main(argv, out)
    finally:
        sys.stderr = old
    return rc, out.getvalue(), err.getvalue()


def args_of(log):
    return log.read_text().splitlines() if log.exists() else None


def assert_one_sentence(err):
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].endswith(".")


def test_help_lists_commands():
    r = subprocess.run([sys.executable, flash.__file__, "--help"], capture_output=True, text=True)
    assert r.returncode == 0
    for cmd in ("build", "flash", "deploy", "info", "auto", "--dry-run"):
        assert cmd in r.stdout


def test_no_tool_installed_says_how_to_install_each(env):
    rc, out, err = run(["--build", env.build, "flash"])
    assert rc == 1
    assert_one_sentence(err)
    for hint in ("apt-get install dfu-util", "apt-get install stlink-tools", "pip install pyocd"):
        assert hint in err


def test_dfu_util_without_device_explains_dfu_mode(env):
    log = env.tool("dfu-util", stdout="dfu-util 0.11\nNo DFU capable USB device available\n")
    rc, out, err = run(["--build", env.build, "flash"])
    assert rc == 1
    assert_one_sentence(err)
    assert "BOOT0" in err and "stlink-tools" in err
    assert args_of(log) == ["-l"]  # only probed, nothing written


def test_dfu_flash_command_and_progress(env):
    log = env.tool(
        "dfu-util",
        stdout='Found DFU: [0483:df11] ver=0200, devnum=5, cfg=1, intf=0, alt=0, name="@Internal Flash"\n'
        "Download [=========================] 100%\n",
    )
    rc, out, err = run(["--build", env.build, "flash"])
    assert rc == 0, err
    calls = args_of(log)
    assert calls[0] == "-l"
    assert calls[1:] == ["-a", "0", "-d", "0483:df11", "-s", "0x08000000:leave", "-D",
                         os.path.join(env.build, "firmware.bin")]
    assert "100%" in out  # the tool's progress reaches the user


def test_dfu_failure_is_one_sentence(env):
    script = env.tmp / "bin" / "dfu-util"
    script.write_text('#!/bin/sh\nif [ "$1" = -l ]; then echo "Found DFU: [0483:df11]"; exit 0; fi\necho "dfu-util: Error during download"; exit 74\n')
    script.chmod(0o755)
    rc, out, err = run(["--build", env.build, "flash"])
    assert rc == 1
    assert_one_sentence(err)
    assert "status 74" in err


def test_st_flash_used_when_only_stlink_sees_the_board(env):
    env.tool("dfu-util", stdout="No DFU capable USB device available\n")
    env.tool("st-info", stdout="Found 1 stlink programmers\n  chipid: 0x0450\n")
    log = env.tool("st-flash", stdout="Flash written and verified! jolly good!\n")
    rc, out, err = run(["--build", env.build, "flash"])
    assert rc == 0, err
    assert args_of(log) == ["--reset", "write", os.path.join(env.build, "firmware.bin"), "0x08000000"]


def test_pyocd_flashes_the_hex(env):
    log = env.tool("pyocd", stdout="  #   Probe/Board   Unique ID\n  0   STLINK-V3     0032\n")
    rc, out, err = run(["--build", env.build, "flash", "--tool", "pyocd"])
    assert rc == 0, err
    assert args_of(log) == ["flash", "-t", "stm32h743xx", os.path.join(env.build, "firmware.hex")]


def test_dry_run_prints_exact_command_and_runs_nothing(env):
    log = env.tool("st-flash")
    rc, out, err = run(["--dry-run", "--build", env.build, "flash", "--tool", "stlink"])
    assert rc == 0
    assert out.strip().splitlines()[-1] == "st-flash --reset write %s 0x08000000" % os.path.join(env.build, "firmware.bin")
    assert args_of(log) is None


def test_missing_image_says_how_to_build(env, tmp_path):
    env.tool("dfu-util", stdout="Found DFU: [0483:df11]\n")
    rc, out, err = run(["--build", str(tmp_path / "empty"), "flash"])
    assert rc == 1
    assert_one_sentence(err)
    assert "make firmware MICROPY_DIR=" in err


@pytest.mark.parametrize(
    "name,content,needle",
    [
        ("x.bin", (0x12345678).to_bytes(4, "little") + GOOD_RESET.to_bytes(4, "little"), "vector table"),
        ("x.bin", GOOD_SP.to_bytes(4, "little") + (0x08000870).to_bytes(4, "little"), "vector table"),  # even
        ("x.bin", b"\x00" * 4, "too short"),
        ("x.dfu", b"not a dfu file at all, really not", "DfuSe"),
        ("x.hex", b"garbage", "Intel HEX"),
        ("x.elf", b"\x7fELF", "unknown extension"),
    ],
)
def test_wrong_files_are_refused(env, tmp_path, name, content, needle):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(flash.FlashError) as e:
        flash.check_image(str(path))
    assert needle in str(e.value)
    rc, out, err = run(["--build", env.build, "flash", "--image", str(path)])
    assert rc == 1 and needle in err
    assert_one_sentence(err)


def test_good_images_pass(env, tmp_path):
    assert flash.check_image(os.path.join(env.build, "firmware.bin")) == "bin"
    dfu = b"DfuSe\x01" + bytes(20) + b"Target" + bytes(40) + b"\x00\x00\x11\xdf\x83\x04\x1a\x01UFD\x10" + bytes(4)
    (tmp_path / "f.dfu").write_bytes(dfu)
    assert flash.check_image(str(tmp_path / "f.dfu")) == "dfu"
    big = tmp_path / "big.bin"
    write_bin(big, size=flash.FLASH_APP_MAX + 4)
    with pytest.raises(flash.FlashError, match="filesystem"):
        flash.check_image(str(big))


def test_build_runs_the_make_target(env, monkeypatch):
    log = env.tool("make", stdout="firmware: done\n")
    rc, out, err = run(["--build", env.build, "build", "--micropython-dir", "/opt/mp"])
    assert rc == 0, err
    assert args_of(log) == ["-C", flash.ROOT, "firmware", "MICROPY_DIR=/opt/mp", "BUILD=" + env.build]


def test_build_without_make(env):
    rc, out, err = run(["--build", env.build, "build"])
    assert rc == 1
    assert_one_sentence(err)
    assert "apt-get install make" in err


# --- deploy --------------------------------------------------------------------------------
def test_deploy_compiles_every_module_and_copies_with_mpremote(env, tmp_path):
    log = env.tool("mpremote", stdout="cp ok\n")
    stage = tmp_path / "stage"
    rc, out, err = run(["deploy", "--port", "/dev/ttyACM7", "--stage", str(stage)])
    assert rc == 0, err
    sources = flash.firmware_sources()
    assert sources
    for src in sources:
        rel = os.path.relpath(src, flash.FIRMWARE)[:-3] + ".mpy"
        mpy = stage / "lib" / rel
        assert mpy.read_bytes()[:2] == b"M\x06"
    calls = args_of(log)
    assert calls[:6] == ["connect", "/dev/ttyACM7", "fs", "cp", "-r", str(stage / "lib")]
    assert calls[-1] == "reset" and ":/flash/main.py" in calls


def test_deploy_dry_run_lists_mpy_cross_and_mpremote(env):
    env.tool("mpremote")
    rc, out, err = run(["--dry-run", "deploy"])
    assert rc == 0
    lines = out.strip().splitlines()
    assert sum("mpy_cross -march=armv7emdp" in line for line in lines) == len(flash.firmware_sources())
    assert "connect auto fs cp -r" in lines[-1]


def test_deploy_failure_names_the_port_problem(env):
    env.tool("mpremote", stdout="mpremote: no device found\n", rc=1)
    rc, out, err = run(["deploy", "--stage", str(env.tmp / "s")])
    assert rc == 1
    assert_one_sentence(err)
    assert "--port" in err


# --- info ------------------------------------------------------------------------------------
class FakeJig:
    """A serial port with a jig behind it: answers GetSlaveInfo and ReadCounters."""

    def __init__(self, slave=1, silent=False):
        self.slave = slave
        self.silent = silent
        self.rx = bytearray()
        self.parser = FrameParser()

    def reset_input_buffer(self):
        pass

    def write(self, data):
        i = 0
        while i < len(data):
            i = self.parser.feed(data, i, len(data))
            if self.parser.ready and not self.silent and self.parser.slave == self.slave:
                ft = self.parser.ftype
                if ft == frame.GET_SLAVE_INFO:
                    reply = bytes([0, diag.SLAVE_TYPE]) + diag.NAME + b"\x00"
                elif ft == diag.READ_COUNTERS:
                    reply = bytes([0, 2]) + (7).to_bytes(4, "little") + (0xAA).to_bytes(4, "little")
                else:
                    reply = bytes([0x80])
                self.rx += b"\x00\xaa" + frame.encode(self.slave, ft, reply)  # noise first

    def read(self, n):
        out = bytes(self.rx[:n])
        del self.rx[:n]
        return out

    def close(self):
        pass


def info_args(**kw):
    import argparse

    return argparse.Namespace(port="loop://", baud=115200, slave=kw.get("slave", 1))


def test_info_reads_slave_info_and_counters():
    out = io.StringIO()
    r = flash.Runner(out=out)
    assert flash.cmd_info(info_args(), r, ser=FakeJig()) == 0
    text = out.getvalue()
    assert "type 200" in text and diag.NAME.decode() in text
    assert "%s" % diag.WIRE_NAMES[0] in text and " 7" in text and "170" in text


def test_info_no_reply_is_one_sentence():
    with pytest.raises(flash.FlashError, match="no reply from slave 1"):
        flash.cmd_info(info_args(), flash.Runner(out=io.StringIO()), ser=FakeJig(silent=True))


@pytest.mark.parametrize(
    "message,needle",
    [
        ("[Errno 16] could not open port /dev/ttyUSB0: [Errno 16] Device or resource busy", "in use"),
        ("[Errno 13] could not open port /dev/ttyUSB0: [Errno 13] Permission denied", "dialout"),
        ("[Errno 2] could not open port /dev/ttyUSB9: [Errno 2] No such file or directory", "list_ports"),
    ],
)
def test_serial_open_errors(monkeypatch, message, needle):
    import serial

    def boom(*a, **k):
        raise serial.SerialException(message)

    monkeypatch.setattr(serial, "serial_for_url", boom)
    rc, out, err = run(["info", "--port", "/dev/ttyUSB0"])
    assert rc == 1 and needle in err
    assert_one_sentence(err)


# --- auto --------------------------------------------------------------------------------------
def test_auto_starts_the_bench_without_a_jig(env, monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(os, "execv", lambda path, argv: calls.append(argv))
    monkeypatch.setattr(flash, "micropython_boards", lambda: [])
    rc, out, err = run(["--build", str(tmp_path / "nothing-built"), "auto", "--drivers", "2,3"])
    assert rc == 0, err
    assert calls == [[sys.executable, "-m", "motorjig.desk", "--bench", "--drivers", "2,3"]]


def test_auto_flashes_a_jig_waiting_in_dfu_mode(env, monkeypatch):
    log = env.tool("dfu-util", stdout="Found DFU: [0483:df11] ver=0200\n")
    monkeypatch.setattr(os, "execv", lambda *a: pytest.fail("bench started"))
    rc, out, err = run(["--build", env.build, "auto"])
    assert rc == 0, err
    assert "0x08000000:leave" in args_of(log)


def test_unexpected_errors_are_one_line(env, monkeypatch):
    def broken(*a, **k):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(flash, "choose_tool", broken)
    rc, out, err = run(["--build", env.build, "flash"])
    assert rc == 1
    assert "disk on fire" in err and "Traceback" not in err


def test_only_motorjig_boards_are_switched_to_dfu(monkeypatch):
    from serial.tools import list_ports

    class P:
        def __init__(self, device, vid, product):
            self.device, self.vid, self.product, self.description = device, vid, product, ""

    ports = [P("/dev/ttyACM0", 0xF055, "Pyboard Virtual Comm Port in FS Mode"),
             P("/dev/ttyACM1", 0xF055, "MotorJig STM32H7_JIG RS-485 bridge"),
             P("/dev/ttyUSB0", 0x0403, "MotorJig lookalike FTDI")]
    monkeypatch.setattr(list_ports, "comports", lambda: ports)
    assert flash.micropython_boards() == ["/dev/ttyACM1"]


def test_of_a_jigs_two_usb_ports_auto_picks_the_repl_not_the_capture_port(monkeypatch):
    from serial.tools import list_ports

    class P:
        def __init__(self, device, location, serial="3254335D3037"):
            self.device, self.location, self.serial_number = device, location, serial
            self.vid, self.product, self.description = 0xF055, "MotorJig STM32H7_JIG RS-485 bridge", ""

    # pyserial lists ports in no particular order: the capture port (interface 2) first
    ports = [P("/dev/ttyACM5", "1-1.2:1.2"), P("/dev/ttyACM4", "1-1.2:1.0"),
             P("/dev/ttyACM7", "1-1.3:1.2", "OTHERJIG"), P("/dev/ttyACM6", "1-1.3:1.0", "OTHERJIG")]
    monkeypatch.setattr(list_ports, "comports", lambda: ports)
    assert flash.micropython_boards() == ["/dev/ttyACM4", "/dev/ttyACM6"]


def test_auto_switches_a_running_jig_to_dfu_then_flashes(env, monkeypatch):
    state = env.tmp / "in-dfu"
    script = env.tmp / "bin" / "dfu-util"
    script.write_text(
        "#!/bin/sh\nprintf '%%s\\n' \"$@\" >> '%s'\n"
        "if [ \"$1\" = -l ]; then [ -f '%s' ] && echo 'Found DFU: [0483:df11]'; exit 0; fi\necho 100%%\n"
        % (env.tmp / "dfu.args", state)
    )
    script.chmod(0o755)
    mp = env.tmp / "bin" / "mpremote"
    mp.write_text("#!/bin/sh\nprintf '%%s\\n' \"$@\" >> '%s'\n: > '%s'\n" % (env.tmp / "mp.args", state))
    mp.chmod(0o755)
    monkeypatch.setattr(flash, "micropython_boards", lambda: ["/dev/ttyACM1"])
    monkeypatch.setattr(os, "execv", lambda *a: pytest.fail("bench started"))
    rc, out, err = run(["--build", env.build, "auto"])
    assert rc == 0, err
    assert (env.tmp / "mp.args").read_text().split() == ["connect", "/dev/ttyACM1", "bootloader"]
    assert "0x08000000:leave" in (env.tmp / "dfu.args").read_text()


# --- tools/firmware/build_firmware.sh and tools/firmware/test_qemu.sh -------------------------------------------
SCRIPTS = os.path.join(flash.ROOT, "tools", "firmware")


def sh(script, *args, env=None):
    return subprocess.run([os.path.join(SCRIPTS, script)] + list(args), capture_output=True, text=True,
                          env=env, timeout=60)


def test_build_script_explains_the_checkout_when_micropython_dir_is_missing(tmp_path):
    r = sh("build_firmware.sh", "", str(tmp_path / "b"), os.path.join(flash.ROOT, "boards", "STM32H7_JIG"))
    assert r.returncode != 0
    assert "git clone --branch v1.28.0" in r.stderr and "lib/stm32lib lib/tinyusb" in r.stderr
    r = sh("build_firmware.sh", str(tmp_path / "nowhere"), str(tmp_path / "b"), os.path.join(flash.ROOT, "boards", "STM32H7_JIG"))
    assert r.returncode != 0 and "does not exist" in r.stderr


def fake_micropython(tmp_path):
    """A MicroPython-shaped tree and fake cross tools first on PATH; make records its args."""
    mp = tmp_path / "mp"
    (mp / "ports" / "stm32").mkdir(parents=True)
    (mp / "ports" / "stm32" / "Makefile").write_text("")
    (mp / "py").mkdir()
    (mp / "py" / "mpconfig.h").write_text(
        "#define MICROPY_VERSION_MAJOR (1)\n#define MICROPY_VERSION_MINOR (28)\n#define MICROPY_VERSION_MICRO (0)\n")
    hal = mp / "lib" / "stm32lib" / "STM32H7xx_HAL_Driver" / "Inc"
    hal.mkdir(parents=True)
    (hal / "stm32h7xx_hal.h").write_text("")
    (mp / "lib" / "tinyusb").mkdir(parents=True)
    (mp / "lib" / "tinyusb" / "README.rst").write_text("")
    (mp / "mpy-cross" / "build").mkdir(parents=True)
    cross = mp / "mpy-cross" / "build" / "mpy-cross"
    cross.write_text("#!/bin/sh\n")
    cross.chmod(0o755)
    bindir = tmp_path / "fakebin"
    bindir.mkdir()
    libc = tmp_path / "libc.a"
    libc.write_text("")
    tools = {
        "arm-none-eabi-gcc": "echo %s" % libc,
        "make": "printf '%s\\n' \"$@\" > '" + str(tmp_path / "make.args") + "'\n"
                "for a in \"$@\"; do case $a in BUILD=*) b=${a#BUILD=};; esac; done\n"
                "for f in firmware.elf firmware.dfu firmware.hex; do echo x > $b/$f; done\necho LINK $b/firmware.elf",
        "arm-none-eabi-objcopy": "echo bin > \"$4\"",
        "arm-none-eabi-size": "echo '   text    data     bss     dec     hex filename'; echo ' 361724      64  286948  648736   9e620 firmware.elf'",
        "git": "exit 1",
    }
    for name, body in tools.items():
        p = bindir / name
        p.write_text("#!/bin/sh\n" + body + "\n")
        p.chmod(0o755)
    env = dict(os.environ, PATH=str(bindir) + os.pathsep + os.environ.get("PATH", ""))
    return mp, env


def test_build_script_make_command_and_flag_change(tmp_path):
    mp, env = fake_micropython(tmp_path)
    build = tmp_path / "build"
    board = os.path.join(flash.ROOT, "boards", "STM32H7_JIG")
    r = sh("build_firmware.sh", str(mp), str(build), board, env=env)
    assert r.returncode == 0, r.stderr
    args = (tmp_path / "make.args").read_text().splitlines()
    assert args[:2] == ["-C", str(mp / "ports" / "stm32")]
    for want in ("BOARD_DIR=" + board, "BUILD=" + str(build), "MPY_CROSS_FLAGS=-march=armv7emdp",
                 "FROZEN_MANIFEST=" + os.path.join(board, "manifest.py")):
        assert want in args
    assert "v1.28.0" in r.stdout and "361724" in r.stdout and "firmware.dfu" in r.stdout
    assert "micropython=v1.28.0" in (build / "build-info.txt").read_text()
    # Same flags: frozen code kept; other flags: stale frozen .mpy removed.
    (build / "frozen_mpy").mkdir()
    assert sh("build_firmware.sh", str(mp), str(build), board, env=env).returncode == 0
    assert (build / "frozen_mpy").exists()
    env2 = dict(env, MPY_CROSS_FLAGS="-march=armv7m")
    assert sh("build_firmware.sh", str(mp), str(build), board, env=env2).returncode == 0
    assert not (build / "frozen_mpy").exists()


def test_build_script_starts_clean_when_the_board_configuration_changes(tmp_path):
    mp, env = fake_micropython(tmp_path)
    build = tmp_path / "build"
    board = tmp_path / "board"
    shutil.copytree(os.path.join(flash.ROOT, "boards", "STM32H7_JIG"), board)
    assert sh("build_firmware.sh", str(mp), str(build), str(board), env=env).returncode == 0
    (build / "genhdr").mkdir()
    (build / "genhdr" / "qstrdefs.generated.h").write_text("stale")
    r = sh("build_firmware.sh", str(mp), str(build), str(board), env=env)
    assert r.returncode == 0 and (build / "genhdr").exists()  # same board: the build folder is kept
    with open(board / "mpconfigboard.h", "a") as f:
        f.write("#define MICROPY_HW_USB_CDC_NUM_CHANGED (1)\n")
    r = sh("build_firmware.sh", str(mp), str(build), str(board), env=env)
    assert r.returncode == 0, r.stderr
    assert "building from clean" in r.stdout and not (build / "genhdr").exists()
    # a build folder from before the stamp existed is started clean as well
    (build / ".board-config").unlink()
    (build / "genhdr").mkdir()
    r = sh("build_firmware.sh", str(mp), str(build), str(board), env=env)
    assert "building from clean" in r.stdout and not (build / "genhdr").exists()


def test_build_script_names_missing_submodules_and_tools(tmp_path):
    mp, env = fake_micropython(tmp_path)
    board = os.path.join(flash.ROOT, "boards", "STM32H7_JIG")
    for f in (mp / "lib" / "tinyusb").iterdir():
        f.unlink()
    r = sh("build_firmware.sh", str(mp), str(tmp_path / "b"), board, env=env)
    assert r.returncode != 0 and "submodule update --init --depth 1 lib/stm32lib lib/tinyusb" in r.stderr
    (tmp_path / "libc.a").unlink()
    (mp / "lib" / "tinyusb" / "README.rst").write_text("")
    r = sh("build_firmware.sh", str(mp), str(tmp_path / "b"), board, env=env)
    assert r.returncode != 0 and "apt-get install libnewlib-arm-none-eabi" in r.stderr


def test_qemu_script_skips_without_micropython_dir(tmp_path):
    r = sh("test_qemu.sh", "", str(tmp_path))
    assert r.returncode == 0 and "skipped" in r.stdout
