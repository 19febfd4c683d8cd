"""The same parser on a real MicroPython VM (the WebAssembly build, run by Node).

* every capture replays on MicroPython exactly as on CPython, frame by frame;
* parsing allocates nothing per frame in the steady state (gc.mem_alloc with the
  collector disabled), on the bulk and table paths, for any chunk size;
* the VM is what we think it is: MicroPython, no viper (so crc/mem use the portable
  code there), bytearray.find available.

Skipped, with the reason printed, when node or host_tests/wasm/node_modules is
missing -- except when CI=true, where that is a failure.
"""

import glob
import os

import pytest

import capture_format as cf
import wasm_vm

HERE = os.path.dirname(os.path.abspath(__file__))
CAPTURES = sorted(glob.glob(os.path.join(HERE, "captures", "*.cap")))
NAMES = [os.path.basename(p) for p in CAPTURES]

VM_CODE = """
import sys, os
import capture_format, vm_probe
from jig import compat, crc, mem
print("@@env", sys.implementation.name, compat.IS_MICROPYTHON, compat.NATIVE is None,
      crc.crc16 is crc.crc16_table, mem.copy is mem._copy_loop, hasattr(bytearray, "find"))
paths = ["/captures/" + n for n in %r]
print("@@report")
vm_probe.print_reports(paths, False)
v8 = [p for p in paths if capture_format.load(p).ver8]
v6 = [p for p in paths if p not in v8]
print("@@alloc")
vm_probe.print_alloc(v6, v8, 5)
print("@@leak")
from jig.parser import FrameParser
class Leaky(FrameParser):
    def copy_frame(self, dst, dst_off=0):
        self.keep = bytearray(8)
        return FrameParser.copy_frame(self, dst, dst_off)
bursts, span = vm_probe.load_bursts(v6)
print(*vm_probe.alloc_per_frame(bursts, span, rounds=3, parser_class=Leaky))
"""


@pytest.fixture(scope="module")
def vm_output():
    return wasm_vm.sections(VM_CODE % (NAMES,))


def test_vm_is_micropython_without_viper(vm_output):
    assert vm_output["env"] == ["micropython", "True", "True", "True", "True", "True"]


def test_captures_replay_identically_on_micropython(vm_output):
    expected = [line for path in CAPTURES for line in cf.report(cf.load(path), every_split=False)]
    wasm_vm.assert_same_report(vm_output["report_lines"], expected, len(CAPTURES))


def test_no_allocation_per_frame_on_micropython(vm_output):
    lines = vm_output["alloc_lines"]
    assert len(lines) == 16  # ver6/ver8 x bulk/table x 4 chunk sizes
    for line in lines:
        _, label, grew, frames = line.split()
        assert int(frames) > 0, label
        assert int(grew) == 0, "%s: %s bytes allocated over %s frames" % (label, grew, frames)


def test_the_allocation_probe_sees_an_allocation(vm_output):
    grew, frames = map(int, vm_output["leak_lines"][0].split())
    assert frames > 0 and grew >= frames * 8
