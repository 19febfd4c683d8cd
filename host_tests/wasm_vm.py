"""Run code on the MicroPython WebAssembly VM (host_tests/wasm/run_vm.mjs under Node) from a test.

``sections(code, files, what)`` runs ``code`` on the VM, with ``files`` ({name: path}) put in
/data, and splits what it prints into sections: a line ``@@name a b`` starts section ``name``
(its words in ``out[name]``), the lines after it are ``out[name + "_lines"]``. Without node or
host_tests/wasm/node_modules the test is skipped with the reason shown as a warning (so a -q
run still says so), except when CI=true, where that is a failure. ``assert_same_report`` compares
a capture replay report the VM printed with CPython's.
"""

import os
import shutil
import subprocess
import warnings

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
RUNNER = os.path.join(HERE, "wasm", "run_vm.mjs")
PACKAGE = os.path.join(HERE, "wasm", "node_modules", "@micropython", "micropython-webassembly-pyscript")


def missing():
    """Why the VM cannot run here, or None."""
    if shutil.which("node") is None:
        return "node is not installed (Debian: apt-get install nodejs npm)"
    if not os.path.isdir(PACKAGE):
        return "host_tests/wasm/node_modules is missing (run tools/setup.sh, which needs npm)"
    return None


def sections(code, files=None, what="MicroPython VM replay"):
    why = missing()
    if why:
        if os.environ.get("CI") == "true":
            pytest.fail("%s is required in CI: %s" % (what, why))
        warnings.warn("%s skipped: %s" % (what, why))
        pytest.skip(why)
    args = []
    for name, path in (files or {}).items():
        args += ["--file", "%s=%s" % (name, path)]
    result = subprocess.run(["node", RUNNER] + args + [code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, "the VM run failed:\n" + result.stderr[-3000:]
    out = {}
    current = None
    for line in result.stdout.splitlines():
        if line.startswith("@@"):
            head = line.split()
            current = head[0][2:]
            out[current] = head[1:]
            out[current + "_lines"] = []
        elif current:
            out[current + "_lines"].append(line)
    return out


def assert_same_report(got, expected, captures):
    """The VM's replay report is CPython's, line for line (the first line that differs is the
    one shown), and each of the captures met its check with every strategy agreeing."""
    assert len(got) == len(expected)
    for want_line, got_line in zip(expected, got):
        assert got_line == want_line
    assert [line.strip() for line in got].count("check ok") == captures
    assert [line.strip() for line in got].count("strategies all same") == captures
