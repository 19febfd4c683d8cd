"""The SLCAN reader's machine code (jig.slcanfast) on the emulated Cortex-M7.

tools/firmware/slcan_qemu.py on the ELF of ``make test-qemu`` (build/qemu/build/firmware.elf,
or the one named by SLCAN_QEMU_ELF): the work tree's jig.slcan and jig.slcanfast
compiled there by the port's own native emitter, the captures replayed through the
viper engine and the table engine give CPython's report, pseudo-random streams give
both engines the same state after every call, and nothing is allocated. The
instruction figures it prints are not asserted (they belong in benchmarks).

Skipped, with the reason, when there is no such ELF or no qemu-system-arm.
"""

import os
import shutil
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ELF = os.environ.get("SLCAN_QEMU_ELF") or os.path.join(ROOT, "build", "qemu", "build", "firmware.elf")


@pytest.fixture(scope="module")
def report():
    if shutil.which("qemu-system-arm") is None:
        pytest.skip("qemu-system-arm is not installed")
    if not os.path.isfile(ELF):
        pytest.skip("no %s (make test-qemu MICROPY_DIR=... builds it)" % ELF)
    run = subprocess.run([sys.executable, os.path.join(ROOT, "tools", "firmware", "slcan_qemu.py"), "--elf", ELF,
                          "--streams", "100"], capture_output=True, text=True, timeout=300)
    return run.returncode, run.stdout.splitlines(), run.stderr


def test_the_machine_code_is_the_default_engine(report):
    _rc, lines, err = report
    assert "engine viper False" in lines, (lines, err)


def test_the_machine_code_agrees_with_the_table_engine(report):
    rc, lines, err = report
    assert rc == 0, (lines, err)
    assert [ln.split()[2] for ln in lines if ln.startswith("captures")] == ["ok", "ok"]
    streams = [ln.split() for ln in lines if ln.startswith("streams")]
    assert streams and streams[0][3] == "ok" and int(streams[0][2]) > 1000


def test_nothing_is_allocated_on_the_m7(report):
    _rc, lines, _err = report
    assert sorted(ln for ln in lines if ln.startswith("alloc")) == ["alloc table 0", "alloc viper 0"]
