"""Open the jig's SLCAN port for python-can and python-canopen, after checking it is one.

``probe(url)`` sends ``V`` (SLCAN: version) and wants a ``Vhhss`` line back within
``PROBE_S``: a Plus-R RS-485 port, the REPL, the capture port or a missing device is
refused in one sentence (``PortError``) before any CANopen frame goes out. Then
``open_bus`` is python-can's own ``slcan`` interface on the same channel (a device path,
or any pyserial URL such as the bench's ``socket://127.0.0.1:N``) and ``open_network``
a python-canopen ``Network`` on that bus.
"""

import contextlib
import re
import time

import can
import canopen
import serial

from motorjig.errors import PortError
from motorjig.master import _open_error

SLCAN_BITRATES = (10000, 20000, 50000, 100000, 125000, 250000, 500000, 750000, 1000000)  # S0..S8
DEFAULT_BITRATE = 500000
PROBE_S = 1.0  # the jig answers V within a slow pass; USB, the OS and a busy bench add a little
SLEEP_AFTER_OPEN_S = 0.05  # python-can waits this long after opening (its default is 2 s for Arduinos)
NOTIFIER_CYCLE_S = 0.1  # how long closing the network may wait for its reader thread

_VERSION = re.compile(rb"V([0-9A-Fa-f]{4})$")


def _open_serial(url):
    try:
        port = serial.serial_for_url(url, baudrate=115200, timeout=0.02, do_not_open=True)
        port.open()
    except (serial.SerialException, OSError, ValueError) as exc:
        raise _open_error(url, exc) from None
    return port


def _reason(exc):
    text = str(exc).strip() or type(exc).__name__
    return text.rstrip(".")


def probe(url, wait=PROBE_S):
    """The SLCAN version string ('hhss') of the port at url; PortError if it is not one."""
    port = _open_serial(url)
    got = bytearray()
    try:
        try:
            port.reset_input_buffer()
        except (serial.SerialException, OSError, AttributeError):
            pass
        try:
            port.write(b"V\r")
            port.flush()
            end = time.monotonic() + wait
            while time.monotonic() < end:
                got += port.read(max(1, port.in_waiting))
                # Frames may come before the answer (a session left open): look at every line.
                for line in re.split(rb"[\r\x07]", bytes(got)):
                    m = _VERSION.search(line)
                    if m:
                        return m.group(1).decode()
        except (serial.SerialException, OSError) as exc:
            raise PortError("%s is not an SLCAN port: %s" % (url, _reason(exc))) from None
    finally:
        port.close()
    if got:
        seen = bytes(got[:24])
        raise PortError("%s is not an SLCAN port: it answered %r to V (the jig's SLCAN port is its third "
                        "USB serial port, e.g. /dev/ttyACM2)" % (url, seen))
    raise PortError("%s is not an SLCAN port: no answer to V in %g s (the jig's SLCAN port is its third "
                    "USB serial port, e.g. /dev/ttyACM2)" % (url, wait))


def open_bus(url, bitrate=DEFAULT_BITRATE, listen_only=False, check=True):
    """python-can's slcan bus on url at bitrate (one of SLCAN_BITRATES), checked first."""
    if bitrate not in SLCAN_BITRATES:
        raise ValueError("bitrate %d is not one SLCAN can set (%s)" % (bitrate, ", ".join(map(str, SLCAN_BITRATES))))
    if check:
        probe(url)
    try:
        return can.Bus(interface="slcan", channel=url, bitrate=bitrate, listen_only=listen_only,
                       sleep_after_open=SLEEP_AFTER_OPEN_S)
    except (can.CanError, serial.SerialException, OSError, ValueError) as exc:
        raise PortError("cannot open %s as an SLCAN port: %s" % (url, _reason(exc))) from None


@contextlib.contextmanager
def bus_session(url, bitrate=DEFAULT_BITRATE, listen_only=False):
    """open_bus for a with-block; the bus is shut down (SLCAN C, port closed) at its end."""
    bus = open_bus(url, bitrate, listen_only)
    try:
        yield bus
    finally:
        _shutdown(bus)


@contextlib.contextmanager
def network_session(url, bitrate=DEFAULT_BITRATE):
    """A python-canopen Network on the SLCAN bus at url, for a with-block."""
    bus = open_bus(url, bitrate)
    network = canopen.Network(bus)
    network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
    try:
        network.connect()
    except Exception:
        _shutdown(bus)
        raise
    try:
        yield network
    finally:
        try:
            network.disconnect()
        except (can.CanError, serial.SerialException, OSError):
            pass


def _shutdown(bus):
    try:
        bus.shutdown()
    except (can.CanError, serial.SerialException, OSError):
        pass
