"""The SLCAN reader on a real MicroPython VM (the WebAssembly build, run by Node).

* the VM has no native emitter: jig.slcan runs its table engine there (the viper
  module does not compile);
* every captured SLCAN stream (host_tests/captures/slcan) replays on MicroPython
  exactly as on CPython, event by event, fed whole and byte by byte, and meets its
  sidecar;
* reading the streams and writing each frame back with encode_frame allocates
  nothing in the steady state (gc.mem_alloc with the collector off), for any chunk
  size, timeouts (gap) included; and the probe does see an allocation when there is one.

Skipped, with the reason printed, when node or host_tests/wasm/node_modules is
missing -- except when CI=true, where that is a failure.
"""

import glob
import os

import pytest

import slcan_replay as sr
import wasm_vm

HERE = os.path.dirname(os.path.abspath(__file__))
CAPTURES = sorted(glob.glob(os.path.join(HERE, "captures", "slcan", "*.slcan")))
NAMES = [os.path.basename(p) for p in CAPTURES]
CHUNKS = (0, 1, 7, 64)

VM_CODE = """
import sys
sys.path.insert(0, '/data')
import slcan_replay as sr
from jig import compat
from jig import slcan
print("@@env", sys.implementation.name, compat.IS_MICROPYTHON)
try:
    from jig import slcanfast
    why = "imported"
except Exception as e:
    why = type(e).__name__
print("@@engine", slcan.SlcanReader.ENGINE, slcan.encode_frame is slcan.encode_py, slcan.FAST is None, why)
caps = [sr.load('/data/' + n) for n in %r]
print("@@report")
for cap in caps:
    for line in sr.report(cap):
        print(line)
print("@@alloc")
for chunk in %r:
    grew, count = sr.alloc_per_line(caps, chunk)
    print("alloc", chunk, grew, count)
print("@@leak")
class Leaky(sr.SlcanReader):
    def feed(self, buf, i, n, now):
        self.keep = bytearray(8)
        return sr.SlcanReader.feed(self, buf, i, n, now)
print(*sr.alloc_per_line(caps[:1], 0, 3, Leaky))
"""


@pytest.fixture(scope="module")
def vm_output():
    files = {"slcan_replay.py": os.path.join(HERE, "slcan_replay.py")}
    for path in CAPTURES:
        base = path[: -len(".slcan")]
        for p in (path, base + ".expect"):
            files[os.path.basename(p)] = p
    return wasm_vm.sections(VM_CODE % (NAMES, CHUNKS), files, "MicroPython VM replay of the SLCAN captures")


def test_vm_is_micropython(vm_output):
    assert vm_output["env"] == ["micropython", "True"]


def test_the_vm_without_a_native_emitter_runs_the_table_engine(vm_output):
    """The WebAssembly build rejects viper at compile time: jig.slcan falls back to the
    portable reader and encoder (the board runs jig.slcanfast's machine code)."""
    engine, portable_encoder, no_fast, why = vm_output["engine"]
    assert (engine, portable_encoder, no_fast) == ("table", "True", "True")
    assert why != "imported"


def test_captures_replay_identically_on_micropython(vm_output):
    expected = [line for path in CAPTURES for line in sr.report(sr.load(path))]
    wasm_vm.assert_same_report(vm_output["report_lines"], expected, len(CAPTURES))


def test_no_allocation_per_line_on_micropython(vm_output):
    lines = vm_output["alloc_lines"]
    assert len(lines) == len(CHUNKS)
    for line in lines:
        _, chunk, grew, count = line.split()
        assert int(count) > 0, chunk
        assert int(grew) == 0, "chunk %s: %s bytes allocated over %s lines" % (chunk, grew, count)


def test_the_allocation_probe_sees_an_allocation(vm_output):
    grew, count = map(int, vm_output["leak_lines"][0].split())
    assert count > 0 and grew >= count * 8
