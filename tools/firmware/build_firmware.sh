#!/usr/bin/env bash
# Builds the STM32H7_JIG MicroPython image (firmware.dfu/.hex/.bin) against a
# MicroPython checkout the user names, with firmware/ frozen in for armv7emdp.
#
#   tools/firmware/build_firmware.sh MICROPY_DIR BUILD_DIR BOARD_DIR
#
# Called by `make firmware MICROPY_DIR=...`. Nothing is written into the
# MicroPython tree except its own mpy-cross build (mpy-cross/build), and nothing
# into this project outside BUILD_DIR.
set -euo pipefail

MICROPY_DIR=${1:-}
BUILD=${2:-}
BOARD_DIR=${3:-}
JOBS=${JOBS:-2}
MPY_CROSS_FLAGS=${MPY_CROSS_FLAGS:--march=armv7emdp}

say() { printf 'firmware: %s\n' "$*"; }
die() { printf 'firmware: %s\n' "$*" >&2; exit 1; }
# shellcheck source=tools/firmware/micropython_build.sh
. "$(dirname "$0")/micropython_build.sh"

explain_checkout() {
    cat >&2 <<'EOF'
firmware: MICROPY_DIR must name a MicroPython checkout. Make one (outside this project) with:

    git clone --branch v1.28.0 --depth 1 https://github.com/micropython/micropython.git
    cd micropython
    git submodule update --init --depth 1 lib/stm32lib lib/tinyusb

  (only those two submodules are needed: this board has no networking), then run
    make firmware MICROPY_DIR=/absolute/path/to/micropython
  If the stm32lib commit the release pins cannot be fetched, check out the newest
  "work-...H7-..." branch of https://github.com/micropython/stm32lib in lib/stm32lib.
EOF
    exit 1
}

[ -n "$BUILD" ] && [ -n "$BOARD_DIR" ] || die "usage: tools/firmware/build_firmware.sh MICROPY_DIR BUILD_DIR BOARD_DIR (run it through 'make firmware')."
[ -n "$MICROPY_DIR" ] || explain_checkout
[ -d "$MICROPY_DIR" ] || { printf 'firmware: MICROPY_DIR=%s does not exist.\n' "$MICROPY_DIR" >&2; explain_checkout; }
MICROPY_DIR=$(cd "$MICROPY_DIR" && pwd)
[ -f "$MICROPY_DIR/ports/stm32/Makefile" ] || { printf 'firmware: %s is not a MicroPython checkout (no ports/stm32/Makefile).\n' "$MICROPY_DIR" >&2; explain_checkout; }
[ -f "$BOARD_DIR/mpconfigboard.h" ] || die "board folder $BOARD_DIR has no mpconfigboard.h; run this from the MotorJig project."
BOARD_DIR=$(cd "$BOARD_DIR" && pwd)
mkdir -p "$BUILD"
BUILD=$(cd "$BUILD" && pwd)

case "$BUILD/" in
    "$MICROPY_DIR"/*) die "BUILD ($BUILD) is inside the MicroPython tree; give a folder outside it." ;;
esac

# --- tools --------------------------------------------------------------------------
missing=()
check_arm_toolchain
command -v make >/dev/null || missing+=(make)
command -v python3 >/dev/null || missing+=(python3)
command -v gcc >/dev/null || missing+=(gcc)
if [ ${#missing[@]} -gt 0 ]; then
    die "missing build tools: install them with 'sudo apt-get install ${missing[*]}' and run again."
fi

# --- submodules ---------------------------------------------------------------------
for sub in lib/stm32lib lib/tinyusb; do
    if [ -z "$(ls -A "$MICROPY_DIR/$sub" 2>/dev/null)" ]; then
        die "$MICROPY_DIR/$sub is empty: run 'git -C $MICROPY_DIR submodule update --init --depth 1 lib/stm32lib lib/tinyusb'."
    fi
done
[ -f "$MICROPY_DIR/lib/stm32lib/STM32H7xx_HAL_Driver/Inc/stm32h7xx_hal.h" ] \
    || die "$MICROPY_DIR/lib/stm32lib has no STM32H7 HAL: check out a stm32lib commit that includes H7 (see the release's pinned submodule)."

version=$(git -C "$MICROPY_DIR" describe --tags 2>/dev/null || true)
if [ -z "$version" ]; then
    version=$(sed -n 's/^#define MICROPY_VERSION_\(MAJOR\|MINOR\|MICRO\) (\([0-9]*\))/\2/p' "$MICROPY_DIR/py/mpconfig.h" | paste -sd. -)
    version="v$version"
fi
say "MicroPython $version at $MICROPY_DIR"

# --- mpy-cross from the same tree (frozen .mpy must match the runtime) ---------------
build_mpy_cross "$MICROPY_DIR" "$BUILD/mpy-cross.log"

# --- frozen code: recompile everything when the mpy-cross flags change ---------------
# The manifest step only recompiles a .py newer than its .mpy, so stale frozen code
# built with other flags would survive a flag change otherwise.
flags_stamp="$BUILD/.mpy-cross-flags"
if [ ! -f "$flags_stamp" ] || [ "$(cat "$flags_stamp")" != "$MPY_CROSS_FLAGS" ]; then
    rm -rf "$BUILD/frozen_mpy" "$BUILD/frozen_content.c"
    printf '%s' "$MPY_CROSS_FLAGS" >"$flags_stamp"
fi

# --- board configuration: start clean when it changes -----------------------------------
# The port's incremental build does not notice a changed mpconfigboard.h everywhere: after
# the board gained a third CDC port and machine.CAN, a build over the old folder failed on
# stale generated qstrs ("redeclaration of enumerator"). So a change of any board file
# (or of the MicroPython tree's version) empties the build folder first.
board_stamp="$BUILD/.board-config"
board_sum=$( (printf '%s\n' "$version"; cat "$BOARD_DIR"/*) | sha256sum | cut -d' ' -f1)
if { [ -f "$board_stamp" ] && [ "$(cat "$board_stamp")" != "$board_sum" ]; } \
   || { [ ! -f "$board_stamp" ] && [ -e "$BUILD/firmware.elf" ]; }; then
    say "the board configuration (or the MicroPython version) changed since the last build: building from clean"
    find "$BUILD" -mindepth 1 -maxdepth 1 ! -name 'mpy-cross.log' -exec rm -rf {} +
    printf '%s' "$MPY_CROSS_FLAGS" >"$flags_stamp"
fi
mkdir -p "$BUILD"
printf '%s' "$board_sum" >"$board_stamp"

mpy_lib="$BUILD/no-micropython-lib"
empty_micropython_lib "$mpy_lib"

say "building STM32H7_JIG into $BUILD (make -j$JOBS; a first build takes a few minutes)"
log="$BUILD/build.log"
set +e
make -C "$MICROPY_DIR/ports/stm32" -j"$JOBS" \
    BOARD_DIR="$BOARD_DIR" BUILD="$BUILD" \
    FROZEN_MANIFEST="$BOARD_DIR/manifest.py" MPY_LIB_DIR="$mpy_lib" \
    MPY_CROSS_FLAGS="$MPY_CROSS_FLAGS" 2>&1 | tee "$log" | awk '
        /^(LINK|GEN .*firmware)/ || /[Ee]rror/ { print; fflush(); next }
        /^CC / { n++; if (n % 100 == 0) { printf "firmware:   %d C files compiled\n", n; fflush() } }'
status=${PIPESTATUS[0]}
set -e
if [ "$status" -ne 0 ]; then
    tail -n 25 "$log" >&2
    die "the MicroPython build failed (full log: $log)."
fi

# A single flat image for SWD programmers (st-flash/pyocd write it at 0x08000000).
arm-none-eabi-objcopy -O binary "$BUILD/firmware.elf" "$BUILD/firmware.bin"

{
    echo "board=STM32H7_JIG"
    echo "micropython=$version"
    echo "stm32lib=$(git -C "$MICROPY_DIR/lib/stm32lib" rev-parse --short HEAD 2>/dev/null || echo unknown)"
    echo "tinyusb=$(git -C "$MICROPY_DIR/lib/tinyusb" rev-parse --short HEAD 2>/dev/null || echo unknown)"
    echo "mpy_cross_flags=$MPY_CROSS_FLAGS"
    echo "built=$(date -u +%Y-%m-%dT%H:%M:%SZ)"
} >"$BUILD/build-info.txt"

say "image sizes:"
arm-none-eabi-size "$BUILD/firmware.elf" | sed 's/^/    /'
for f in firmware.dfu firmware.hex firmware.bin; do
    printf '    %-14s %8d bytes\n' "$f" "$(stat -c %s "$BUILD/$f")"
done
say "done: $BUILD/firmware.dfu (flash it with 'make flash')"
