"""Shared set-up for the tests that talk to the real-time virtual bench.

``test_master_bench.py`` and ``test_cli_bench.py`` import the fixtures from here
(``from bench_fixtures import bench, port``): one bench per test module, and a
``port`` per test -- once its pseudo-terminal, once its TCP URL -- with every
injected fault cleared and both drives stopped, alarm-free, powered, at position
0 and with short ramps.

The bench runs in real time on a shared, often busy machine, so requests that do
not test timeouts use ``TIMEOUT`` (generous); the bench's own clock already keeps
the simulated jig and drives in step through host stalls (``sim.clock.PacedClock``).
"""

import contextlib
import os
import subprocess
import sys
import time

import pytest

from motorjig.master import Master
from motorjig.sim import Bench

DRIVE = 2
OTHER = 3
TIMEOUT = 0.5  # seconds: the reply timeout for everything that is not a timeout test
TIMEOUT_MS = int(TIMEOUT * 1000)


@pytest.fixture(scope="module")
def bench():
    with Bench(driver_ids=(DRIVE, OTHER), baud=115200) as b:
        yield b


def prepare(bench, url):
    """Clear the faults and bring both drives to a known state, through url."""
    bench.sim.clear_faults()
    with Master(url, timeout=TIMEOUT) as m:
        for s in (DRIVE, OTHER):
            m.emergency_stop(s)
            m.alarm_reset(s)
            m.servo_enable(s, True)
            m.clear_position(s)
            m.set_parameter(s, 3, 5)  # short accel/decel: fast tests
            m.set_parameter(s, 4, 5)


@pytest.fixture(params=["pty", "tcp"])
def port(request, bench):
    url = bench.pty_path if request.param == "pty" else bench.tcp_url
    prepare(bench, url)
    return url


def eventually(fn, want, timeout=5.0):
    """fn() once it equals want, or its last value after timeout seconds.

    For counts the bench thread updates: a request the PC has already given up on
    may still be on its way through the pty/TCP threads of a busy machine.
    """
    end = time.monotonic() + timeout
    while True:
        value = fn()
        if value == want or time.monotonic() >= end:
            return value
        time.sleep(0.005)


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SUBPROCESS_ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([os.path.join(ROOT, "firmware"), os.path.join(ROOT, "tools")]))


@contextlib.contextmanager
def bench_process(duration_s=120):
    """`python -m motorjig.sim` in its own process, as a user starts it; yields
    {"pty": path, "tcp": url} as it printed them. Its own process also keeps it clear
    of the garbage-collection pauses of the test process."""
    proc = subprocess.Popen([sys.executable, "-m", "motorjig.sim", "--no-demo", "--duration", str(duration_s)],
                            stdout=subprocess.PIPE, text=True, env=SUBPROCESS_ENV)
    urls = {}
    try:
        for line in proc.stdout:
            key, _, value = line.strip().partition(": ")
            if key in ("pty", "tcp"):
                urls[key] = value
            if len(urls) == 2:
                break
        assert len(urls) == 2, "the bench did not print its pty path and TCP URL"
        yield urls
    finally:
        proc.terminate()
        proc.wait(timeout=10)
