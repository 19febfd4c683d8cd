#!/usr/bin/env bash
# Sets up everything the host side needs, once: a virtual environment in .venv with
# the project installed (editable) plus its test, bench, board and gui extras, the
# WebAssembly MicroPython used to replay captures on a real MicroPython VM, and
# (under CI, or where apt can) Debian's chromium + chromedriver for the GUI's browser tests and
# Debian's postgresql for the results database's tests.
# Safe to run again: it only redoes a step whose inputs changed.
set -euo pipefail
cd "$(dirname "$0")/.."

say() { printf 'setup: %s\n' "$*"; }

as_root() { if [ "$(id -u)" = 0 ]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else return 1; fi; }

apt_install() {
    command -v apt-get >/dev/null || return 1
    say "installing Debian packages: $*"
    as_root apt-get update -qq && as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
}

PYTHON=${PYTHON:-python3}
if ! command -v "$PYTHON" >/dev/null; then
    apt_install python3 python3-venv || { say "python3 is missing: install it (Debian: apt-get install python3 python3-venv)"; exit 1; }
fi

if [ ! -x .venv/bin/python ]; then
    if ! "$PYTHON" -m venv .venv 2>/dev/null; then
        rm -rf .venv
        apt_install python3-venv || { say "python3 cannot make a virtual environment: apt-get install python3-venv"; exit 1; }
        "$PYTHON" -m venv .venv
    fi
fi

stamp=.venv/.motorjig-installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    say "installing the project and its test/bench/board/gui/station/can/ecat extras into .venv"
    .venv/bin/python -m pip install -q --upgrade pip
    .venv/bin/python -m pip install -q -e '.[test,bench,board,gui,station,can,ecat]'
    touch "$stamp"
fi

# The WebAssembly MicroPython VM (npm) runs the capture replay on real MicroPython.
wasm=host_tests/wasm
if [ ! -d "$wasm/node_modules/@micropython" ] || [ "$wasm/package.json" -nt "$wasm/node_modules" ]; then
    if ! command -v npm >/dev/null; then
        if [ "${CI:-}" = true ]; then
            apt_install nodejs npm || { say "node/npm are required in CI and could not be installed"; exit 1; }
        else
            say "node/npm not found: the MicroPython (WebAssembly) replay will be skipped (Debian: apt-get install nodejs npm)"
        fi
    fi
    if command -v npm >/dev/null; then
        say "installing the WebAssembly MicroPython VM (npm)"
        (cd "$wasm" && npm install --no-audit --no-fund --loglevel=error >/dev/null)
        touch "$wasm/node_modules"
    fi
fi

# Debian's headless Chromium and its chromedriver run the GUI's browser tests
# (host_tests/test_desk_browser.py); nothing is downloaded by selenium itself.
if [ ! -x /usr/bin/chromium ] || [ ! -x /usr/bin/chromedriver ]; then
    if [ "${CI:-}" = true ]; then
        apt_install chromium chromium-driver || { say "chromium/chromedriver are required in CI and could not be installed"; exit 1; }
    else
        say "chromium/chromedriver not found: the GUI's browser tests will be skipped (Debian: apt-get install chromium chromium-driver)"
    fi
fi

# Debian's PostgreSQL server binaries: the results database's tests and benchmark start a
# throw-away cluster of their own (initdb + pg_ctl, station/pgtemp.py); no service is used.
if ! compgen -G '/usr/lib/postgresql/*/bin/initdb' >/dev/null && ! command -v initdb >/dev/null; then
    if [ "${CI:-}" = true ]; then
        apt_install postgresql || { say "postgresql is required in CI and could not be installed"; exit 1; }
    else
        say "PostgreSQL not found: the results database's PostgreSQL tests will be skipped (Debian: apt-get install postgresql)"
    fi
fi

# Debian's tshark runs the Plus-R Lua dissector and the extcap in the capture tests
# (host_tests/test_capture_*.py); the Python side needs nothing of Wireshark.
if ! command -v tshark >/dev/null; then
    if [ "${CI:-}" = true ]; then
        apt_install tshark || { say "tshark is required in CI and could not be installed"; exit 1; }
    else
        say "tshark not found: the capture tests that run Wireshark's dissector will be skipped (Debian: apt-get install tshark)"
    fi
fi
