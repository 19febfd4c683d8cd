"""Compile every firmware module with mpy-cross for the Cortex-M7 (armv7emdp).

Fails (exit 1) on the first module that does not compile, naming it. The .mpy
files go to a temporary folder; nothing is written into the source tree.
"""

import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
FIRMWARE = os.path.join(ROOT, "firmware")
MARCH = "armv7emdp"


def firmware_modules():
    for folder, _dirs, files in os.walk(FIRMWARE):
        for name in sorted(files):
            if name.endswith(".py"):
                yield os.path.join(folder, name)


def main():
    modules = list(firmware_modules())
    failed = 0
    with tempfile.TemporaryDirectory() as out:
        for path in modules:
            rel = os.path.relpath(path, FIRMWARE)
            target = os.path.join(out, rel[:-3] + ".mpy")
            os.makedirs(os.path.dirname(target), exist_ok=True)
            cmd = [sys.executable, "-m", "mpy_cross", "-march=" + MARCH, "-s", rel, "-o", target, path]
            result = subprocess.run(cmd, capture_output=True, text=True)
            if result.returncode != 0:
                failed += 1
                print("mpy-cross failed for %s:\n%s" % (rel, (result.stderr or result.stdout).strip()))
    if failed:
        print("check-mpy: %d of %d firmware modules do not compile for %s" % (failed, len(modules), MARCH))
        return 1
    print("check-mpy: %d firmware modules compile for %s" % (len(modules), MARCH))
    return 0


if __name__ == "__main__":
    sys.exit(main())
