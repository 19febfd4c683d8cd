#!/usr/bin/env bash
# Runs the firmware modules on an emulated Cortex-M7 and prints instruction figures.
#
#   tools/firmware/test_qemu.sh MICROPY_DIR OUT_DIR        (make test-qemu MICROPY_DIR=...)
#
# Builds MicroPython's qemu port for BOARD=MPS2_AN500 (Cortex-M7, double-precision
# FPU) with the stm32 port's VM settings (computed goto, -Os for the VM loop, as
# ports/stm32 builds it; the qemu port's own defaults differ by 3-8 %) and the `jig` package, the capture replay and tools/firmware/qemu/qemu_suite.py
# frozen in (armv7emdp), runs it in qemu-system-arm with -icount shift=0 (1
# instruction = 1 ns of virtual time, so ticks_us x 1000 = instructions) and
# executes qemu_suite.main() through the REPL's paste mode. Two user C modules of
# our own go into this build only (tools/firmware/qemu/cmodules): the board's Python stack
# and the benchmark's HAL port in C (memport). Exits 0 with a message
# when MICROPY_DIR is not set.
set -euo pipefail

MICROPY_DIR=${1:-}
OUT=${2:-}
JOBS=${JOBS:-2}
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
PY=${PYTHON:-$ROOT/.venv/bin/python}
[ -x "$PY" ] || PY=python3

say() { printf 'test-qemu: %s\n' "$*"; }
die() { printf 'test-qemu: %s\n' "$*" >&2; exit 1; }
# shellcheck source=tools/firmware/micropython_build.sh
. "$ROOT/tools/firmware/micropython_build.sh"

if [ -z "$MICROPY_DIR" ]; then
    say "skipped: MICROPY_DIR is not set (make test-qemu MICROPY_DIR=/path/to/micropython)."
    exit 0
fi
[ -f "$MICROPY_DIR/ports/qemu/Makefile" ] \
    || die "$MICROPY_DIR is not a MicroPython checkout (no ports/qemu/Makefile): see 'make firmware' for how to clone one."
MICROPY_DIR=$(cd "$MICROPY_DIR" && pwd)
[ -n "$OUT" ] || OUT="$ROOT/build/qemu"
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)

missing=()
command -v qemu-system-arm >/dev/null || missing+=(qemu-system-arm)
check_arm_toolchain
if [ ${#missing[@]} -gt 0 ]; then
    die "missing tools: install them with 'sudo apt-get install ${missing[*]}' and run again."
fi

build_mpy_cross "$MICROPY_DIR" "$OUT/mpy-cross.log"

# Frozen content: the firmware package, the capture replay module with every
# capture and CPython's report for it, the suite and the modules it imports.
gen="$OUT/gen"
mkdir -p "$gen"
"$PY" "$ROOT/tools/firmware/qemu/gen_captures.py" "$gen"
capture_line=""
if [ -f "$ROOT/host_tests/capture_format.py" ]; then
    capture_line="module(\"capture_format.py\", base_path=\"$ROOT/host_tests\")"
fi
cat >"$gen/manifest.py" <<EOF
package("jig", base_path="$ROOT/firmware")
$capture_line
module("bridge_probe.py", base_path="$ROOT/host_tests")
module("trace_probe.py", base_path="$ROOT/host_tests")
module("qemu_suite.py", base_path="$ROOT/tools/firmware/qemu")
module("board_check.py", base_path="$ROOT/tools/firmware/qemu")
module("memrx.py", base_path="$ROOT/tools/firmware/qemu")
module("can_suite.py", base_path="$ROOT/tools/firmware/qemu")
module("qemu_captures.py", base_path="$gen")
EOF
empty_micropython_lib "$OUT/no-micropython-lib"
# Recompile all frozen code every time: it is small, and stale .mpy files would
# otherwise survive a change of flags or of the generated captures.
rm -rf "$OUT/build/frozen_mpy"
# make does not notice changed compiler flags: start over when they differ.
# The stm32 port's VM settings: computed goto, -Os for the VM loop, and (as the
# STM32H7_JIG board sets it) call frames on a Python stack instead of the heap.
vm_cflags="-DMICROPY_OPT_COMPUTED_GOTO=1 -include $ROOT/tools/firmware/qemu/cmodules/pystack/pystack.h"
# The heap: the port's default (140 KB) is less than the suite's rigs take with the
# capture ring (16 KB an App, as on the board, whose heap is several times this).
HEAP=393216
vm_flags="$vm_cflags CSUPEROPT=-Os HEAP=$HEAP"
if [ "$(cat "$OUT/build/.vm-flags" 2>/dev/null)" != "$vm_flags" ]; then
    rm -rf "$OUT/build"
    mkdir -p "$OUT/build"
    printf '%s\n' "$vm_flags" >"$OUT/build/.vm-flags"
fi

say "building the qemu port (BOARD=MPS2_AN500) with firmware/ frozen in, into $OUT/build"
if ! make -C "$MICROPY_DIR/ports/qemu" -j"$JOBS" BOARD=MPS2_AN500 BUILD="$OUT/build" \
        FROZEN_MANIFEST="$gen/manifest.py" MPY_LIB_DIR="$OUT/no-micropython-lib" \
        MPY_CROSS_FLAGS=-march=armv7emdp USER_C_MODULES="$ROOT/tools/firmware/qemu/cmodules" \
        CFLAGS_EXTRA="$vm_cflags" CSUPEROPT=-Os MICROPY_HEAP_SIZE=$HEAP >"$OUT/build.log" 2>&1; then
    tail -n 20 "$OUT/build.log" >&2
    die "the qemu port did not build (full log: $OUT/build.log)."
fi
elf="$OUT/build/firmware.elf"
[ -f "$elf" ] || die "no $elf after the build; see $OUT/build.log."

# Paste mode (Ctrl-E ... Ctrl-D) runs the suite; machine.reset() ends QEMU.
script=$'\x05import sys, machine\ntry:\n    import qemu_suite\n    rc = qemu_suite.main()\nexcept Exception as e:\n    sys.print_exception(e)\n    rc = 99\nprint("QEMU-EXIT", rc)\nmachine.reset()\n\x04'
say "running qemu-system-arm -machine mps2-an500 -icount shift=0 (takes a minute or two)"
set +e
printf '%s' "$script" | timeout "${QEMU_TIMEOUT:-300}" qemu-system-arm -machine mps2-an500 -nographic \
    -monitor null -semihosting -icount shift=0 -serial stdio -kernel "$elf" >"$OUT/run.log" 2>&1
qemu_rc=$?
set -e
tr -d '\r' <"$OUT/run.log" | grep -E '^(qemu_suite|RESULT|FAIL|QEMU-EXIT|Traceback|  File|[A-Za-z]*Error)' | sed 's/^/    /'
if [ $qemu_rc -eq 124 ]; then
    die "QEMU did not finish within ${QEMU_TIMEOUT:-300} s; see $OUT/run.log."
fi
grep -q '^QEMU-EXIT 0' <(tr -d '\r' <"$OUT/run.log") || die "the suite failed on the emulated Cortex-M7; see $OUT/run.log."
version=$(git -C "$MICROPY_DIR" describe --tags 2>/dev/null || echo unknown)
say "passed (MicroPython $version, qemu $(qemu-system-arm --version | head -n1 | sed 's/.*version //'))."
