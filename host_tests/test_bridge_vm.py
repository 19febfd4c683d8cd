"""The bridge on a real MicroPython VM (WebAssembly build): no heap use per transaction."""

import os
import shutil
import subprocess

import pytest

import bridge_probe

HERE = os.path.dirname(os.path.abspath(__file__))
RUN_VM = os.path.join(HERE, "wasm", "run_vm.mjs")
PKG = os.path.join(HERE, "wasm", "node_modules", "@micropython", "micropython-webassembly-pyscript")


def run_vm(code):
    if shutil.which("node") is None or not os.path.isdir(PKG):
        pytest.skip("node or the MicroPython WebAssembly package is missing (tools/setup.sh)")
    r = subprocess.run(["node", RUN_VM, "--file", "bridge_probe.py=" + os.path.join(HERE, "bridge_probe.py"),
                        "import sys\nsys.path.append('/data')\nimport bridge_probe as b\n" + code],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_zero_heap_bytes_per_transaction_on_micropython():
    out = run_vm(
        "print(b.forward_alloc(300))\n"
        "print(b.local_alloc(300))\n"
        "print(b.local_alloc(300, True))\n"
        "print(b.scan_all_absent())\n"
        "print(b.forward_alloc(300, capture=True))\n"
        "print(b.local_alloc(300, capture=True))\n"
        "import sys\nprint(sys.implementation.name)\n"
    )
    lines = out.split()
    assert lines[-1] == "micropython"
    assert out.splitlines()[:3] == ["(0, True)", "(0, True)", "(0, True)"]
    assert out.splitlines()[3] == "(16, 2, 0)"  # background scan: 16 probes, done, no heap
    # capture on: four records a forwarded transaction, streamed by the slow pass, no heap
    assert out.splitlines()[4:6] == ["(0, True)", "(0, True)"]


def test_probe_sanity_under_cpython():
    r = bridge_probe.Rig()
    for _ in range(10):
        r.forward_once()
    assert r.hal.up.writes == 10 and r.hal.down.writes == 10
    assert bytes(r.hal.down.out[: r.hal.down.out_n]) == bytes(r.req)
    assert bytes(r.hal.up.out[: r.hal.up.out_n]) == bytes(r.reply)
    c = r.app.counters.as_dict()
    assert c["forwards"] == 10 and c["replies"] == 10
    assert bridge_probe.scan_all_absent()[:2] == (16, 2)
