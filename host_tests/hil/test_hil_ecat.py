"""Hardware-in-the-loop: a real EtherCAT CiA 402 drive on this PC's network interface (as root).

Skipped unless ``--ecat-ifname`` is given (see conftest.py). What the bench's simulated line is
tested for in test_ecat_pysoem.py and test_station_ecat.py, checked on the real thing: the scan
names the drive from its SII, it is a CiA 402 drive, its PDOs carry what CSP needs, the station's
master takes it to OP and back; with ``--ecat-allow-move`` a 1 000-count CSP move whose position
follows, ending disabled.
"""

import os
import time

import pytest


def _opt(config, name, default=None):
    try:
        return config.getoption(name)
    except ValueError:  # the hil conftest's options are not loaded
        return default


@pytest.fixture
def line(request):
    ifname = _opt(request.config, "--ecat-ifname")
    if not ifname:
        pytest.skip("no --ecat-ifname: no real EtherCAT drive to test")
    if os.geteuid() != 0:
        pytest.skip("EtherCAT needs root (raw sockets)")
    pytest.importorskip("pysoem")
    return ifname, _opt(request.config, "--ecat-position", 0)


def test_the_scan_names_a_cia402_drive_whose_pdos_carry_csp(line):
    import pysoem

    ifname, position = line
    m = pysoem.Master()
    m.open(ifname)
    try:
        assert m.config_init() > position
        s = m.slaves[position]
        assert s.name and s.man
        assert int.from_bytes(s.sdo_read(0x1000, 0)[:4], "little") & 0xFFFF == 402
        rx = [int.from_bytes(s.sdo_read(0x1C12, i)[:2], "little") for i in range(1, s.sdo_read(0x1C12, 0)[0] + 1)]
        assert rx, "no RxPDO assigned"
    finally:
        m.close()


def test_the_stations_master_takes_it_to_op_and_back(line):
    from motorjig.station.drive_ecat import EcatDrive

    ifname, position = line
    d = EcatDrive(ifname, position, None, 0.001)
    d.open()
    try:
        time.sleep(1.0)
        h = d.bus_health()
        assert h["frames_lost"] == 0 and h["wkc_errors"] == 0, h
    finally:
        d.close()


def test_a_short_csp_move_follows(line, request):
    if not _opt(request.config, "--ecat-allow-move"):
        pytest.skip("no --ecat-allow-move")
    from motorjig.station.drive_ecat import EcatDrive

    ifname, position = line
    d = EcatDrive(ifname, position, None, 0.001)
    d.open()
    try:
        d.enable(True)
        start = d.position()
        d.move(start + 1000, 2000, 20000, 20000)
        time.sleep(1.5)
        assert abs(d.position() - (start + 1000)) <= d.read(0x6067)
        d.enable(False)
    finally:
        d.make_safe()
        d.close()
