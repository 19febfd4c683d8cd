# Sourced by tools/firmware/build_firmware.sh and tools/firmware/test_qemu.sh: the steps both take
# before building a MicroPython port. The functions use the caller's say/die and
# JOBS.

# Appends the apt package of each missing ARM cross tool to the caller's `missing`
# array (newlib is checked through the compiler: it has no command of its own).
check_arm_toolchain() {
    if ! command -v arm-none-eabi-gcc >/dev/null; then
        missing+=(gcc-arm-none-eabi)
        return
    fi
    local libc
    libc=$(arm-none-eabi-gcc -mcpu=cortex-m7 -mthumb -print-file-name=libc.a 2>/dev/null || true)
    [ -f "$libc" ] || missing+=(libnewlib-arm-none-eabi)
}

# build_mpy_cross MICROPY_DIR LOG: builds the tree's own mpy-cross unless it is
# built already (frozen .mpy files must match the runtime of that tree).
build_mpy_cross() {
    [ -x "$1/mpy-cross/build/mpy-cross" ] && return 0
    say "building mpy-cross"
    make -C "$1/mpy-cross" -j"$JOBS" >"$2" 2>&1 \
        || die "building mpy-cross failed; see $2 (a host C compiler is needed: sudo apt-get install build-essential)."
}

# empty_micropython_lib DIR: the manifest machinery insists on a micropython-lib
# folder with a README.md even though nothing here require()s from it.
empty_micropython_lib() {
    mkdir -p "$1"
    [ -f "$1/README.md" ] || printf 'Empty on purpose: nothing is frozen from micropython-lib.\n' >"$1/README.md"
}
