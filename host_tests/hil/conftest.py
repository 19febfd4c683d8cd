"""Options and the serial link of the hardware-in-the-loop suite.

    .venv/bin/python -m pytest host_tests/hil --port /dev/ttyUSB0 [--baud 115200]
        [--slave 1] [--driver-id 2] [--usb /dev/ttyACM0] [--allow-move]
    sudo .venv/bin/python -m pytest host_tests/hil --ecat-ifname eth1 [--ecat-position 0] [--ecat-allow-move]

Without ``--port`` every test here is skipped (the normal ``make test`` run); without
``--ecat-ifname`` the EtherCAT ones are (``test_hil_ecat.py``: a real EtherCAT drive on a NIC).
``--driver-id`` names a real Plus-R driver behind the jig for the forwarding
tests; ``--allow-move`` additionally lets one test turn its shaft by 100 pulses;
``--usb`` is the jig's USB REPL port, used to restart it with mpremote.
"""

import pytest

import flash  # tools/flash.py (host_tests/conftest.py puts tools/ on sys.path)


def pytest_addoption(parser):
    group = parser.getgroup("hil", "hardware-in-the-loop (host_tests/hil)")
    group.addoption("--port", default=None, help="serial port/URL of the PC-side RS-485 adapter wired to the jig")
    group.addoption("--baud", type=int, default=115200, help="baud rate of the PC bus (default 115200)")
    group.addoption("--slave", type=int, default=1, help="the jig's slave id (default 1)")
    group.addoption("--driver-id", type=int, default=None, help="id of a real driver on the jig's driver bus")
    group.addoption("--usb", default=None, help="the jig's USB REPL port, for restarts with mpremote")
    group.addoption("--allow-move", action="store_true", default=False, help="allow a 100-pulse move of --driver-id")
    group.addoption("--ecat-ifname", default=None, help="a network interface cabled to a real EtherCAT CiA 402 drive")
    group.addoption("--ecat-position", type=int, default=0, help="that drive's position on its line (default 0)")
    group.addoption("--ecat-allow-move", action="store_true", default=False,
                    help="allow a 1 000-count CSP move of that drive")


def _opt(config, name, default=None):
    try:
        return config.getoption(name)
    except ValueError:  # conftest loaded after option parsing: options absent
        return default


class Link:
    """Request/reply over the PC bus with the firmware's own encoder and parser."""

    def __init__(self, ser):
        self.ser = ser

    def send_raw(self, data):
        self.ser.write(data)
        self.ser.flush()

    def request(self, slave, ftype, data=b"", timeout=0.3):
        """Reply data (status first) of the first matching frame, or None."""
        return flash.transact(self.ser, slave, ftype, data, timeout)


@pytest.fixture(scope="session")
def hil(request):
    port = _opt(request.config, "--port")
    if not port:
        pytest.skip("hardware-in-the-loop: give --port (e.g. pytest host_tests/hil --port /dev/ttyUSB0)")
    import serial

    try:
        ser = serial.serial_for_url(port, baudrate=_opt(request.config, "--baud", 115200), timeout=0.02)
    except serial.SerialException as e:
        pytest.exit("cannot open %s: %s" % (port, e), returncode=2)
    link = Link(ser)
    link.slave = _opt(request.config, "--slave", 1)
    link.driver = _opt(request.config, "--driver-id")
    link.usb = _opt(request.config, "--usb")
    link.allow_move = _opt(request.config, "--allow-move", False)
    yield link
    ser.close()
