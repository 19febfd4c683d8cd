"""The bench's EtherCAT bus seen by an unmodified master: pysoem (SOEM) on the veth interface the bench makes.

The bench runs as a separate process (``python -m motorjig.sim.ecat_bench --control``), as it does
for a user; these tests drive it as SOEM's users do: scan, SDO, PDO remap in PRE-OP, map, DC, OP,
a CSP move at a 1 ms cycle, a profile position move, a fault and its reset, the watchdog stopping
the axis when the master goes silent, a slave that refuses OP. They need root (a network namespace,
raw sockets) and skip, saying so, without it; the namespace is gone after them.
"""

import os
import struct
import subprocess
import sys
import time

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join(os.path.join(ROOT, d) for d in ("firmware", "tools")))

pysoem = pytest.importorskip("pysoem")
if os.geteuid() != 0:
    pytest.skip("the EtherCAT bench needs root (a network namespace and raw sockets)", allow_module_level=True)

CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE, CW_FAULT_RESET = 0x06, 0x07, 0x0F, 0x80
MODE_PP, MODE_CSV, MODE_CSP = 1, 9, 8
OUT = struct.Struct("<HiiBx")  # the ESI's default RxPDO 0x1600: controlword, target position, velocity, mode
IN = struct.Struct("<HiiiBxI")  # TxPDO 0x1A00: statusword, position, velocity, following error, mode, inputs


class Bench:
    def __init__(self, slaves, tag):
        self.tag = tag
        self.netns = "motorjig-ecat-%s" % tag
        self.proc = subprocess.Popen([sys.executable, "-m", "motorjig.sim.ecat_bench", "--slaves", str(slaves),
                                      "--tag", tag, "--control"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, env=ENV, cwd=ROOT)
        line = self.proc.stdout.readline()
        assert "EtherCAT bench:" in line, line + self.proc.stderr.read()
        self.ifname = line.split("on interface ")[1].split()[0]

    def cmd(self, line):
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        reply = self.proc.stdout.readline().strip()
        assert reply.startswith("ok"), reply
        return reply

    def stop(self):
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        subprocess.run(["ip", "netns", "del", self.netns], capture_output=True)


@pytest.fixture(scope="module")
def bench():
    b = Bench(2, "p%d" % os.getpid())
    try:
        yield b
    finally:
        b.stop()
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert b.netns not in listed  # the bench leaves no namespace behind


@pytest.fixture
def master(bench):
    bench.cmd("power-cycle")  # every test finds the drives as they power up
    m = pysoem.Master()
    m.open(bench.ifname)
    try:
        assert m.config_init() == 2
        yield m
    finally:
        m.state = pysoem.INIT_STATE
        m.write_state()
        m.close()


def cycle(m, n=1, period=0.001):
    """``n`` process-data cycles at ``period``: the working counters that were not as expected."""
    bad = 0
    t = time.perf_counter()
    for _ in range(n):
        m.send_processdata()
        if m.receive_processdata(2000) != m.expected_wkc:
            bad += 1
        t += period
        while time.perf_counter() < t:
            pass
    return bad


def to_op(m):
    m.config_map()
    assert m.state_check(pysoem.SAFEOP_STATE, 50000) == pysoem.SAFEOP_STATE
    cycle(m, 3)
    m.state = pysoem.OP_STATE
    m.write_state()
    for _ in range(50):
        cycle(m, 1)
        if m.state_check(pysoem.OP_STATE, 2000) == pysoem.OP_STATE:
            return
    raise AssertionError("the slaves did not reach OP: %s" % [hex(s.al_status) for s in m.slaves])


def put(m, cw, target=0, velocity=0, mode=MODE_CSP):
    for s in m.slaves:
        s.output = OUT.pack(cw, target, velocity, mode)


def status(slave):
    return IN.unpack(bytes(slave.input))


def enable(m, mode, target=0):
    """Fault reset (a drive the last master left faults when its master goes), then enable."""
    for cw in (0, CW_FAULT_RESET, CW_SHUTDOWN, CW_SWITCH_ON, CW_ENABLE):
        put(m, cw, target, 0, mode)
        cycle(m, 5)
    for s in m.slaves:
        assert status(s)[0] & 0x6F == 0x27, hex(status(s)[0])  # OPERATION ENABLED


def test_a_scan_finds_both_slaves_with_the_identity_and_name_of_their_sii(master):
    master.read_state()
    for s in master.slaves:
        assert (s.man, s.id, s.rev) == (0x4D4A4947, 0x402, 0x00010000)
        assert s.name == "MotorJig ECAT servo"
        assert s.state == pysoem.PREOP_STATE
    serials = [struct.unpack("<I", s.sdo_read(0x1018, 4))[0] for s in master.slaves]
    assert len(set(serials)) == 2


def test_sdo_reads_writes_and_aborts(master):
    s = master.slaves[0]
    assert s.sdo_read(0x1008, 0).decode().startswith("MotorJig")  # a normal (not expedited) upload
    s.sdo_write(0x6081, 0, struct.pack("<I", 12345))
    assert struct.unpack("<I", s.sdo_read(0x6081, 0))[0] == 12345
    with pytest.raises(pysoem.SdoError) as exc:
        s.sdo_read(0x2345, 0)
    assert exc.value.abort_code == 0x06020000  # object does not exist
    with pytest.raises(pysoem.SdoError) as exc:
        s.sdo_write(0x6041, 0, struct.pack("<H", 0))
    assert exc.value.abort_code == 0x06010002  # read only


def test_a_pdo_remap_in_preop_changes_the_process_image_and_is_refused_in_safeop(master):
    s = master.slaves[1]
    s.sdo_write(0x1C13, 0, b"\x00")
    s.sdo_write(0x1A00, 0, b"\x00")
    for n, entry in enumerate((0x60410010, 0x60640020, 0x606C0020), 1):
        s.sdo_write(0x1A00, n, struct.pack("<I", entry))
    s.sdo_write(0x1A00, 0, b"\x03")
    s.sdo_write(0x1C13, 0, b"\x01")
    master.config_map()
    assert len(s.input) == 10 and len(master.slaves[0].input) == 20
    assert master.state_check(pysoem.SAFEOP_STATE, 50000) == pysoem.SAFEOP_STATE
    with pytest.raises(pysoem.SdoError) as exc:
        s.sdo_write(0x1A00, 0, b"\x00")
    assert exc.value.abort_code == 0x08000022  # not in this state


def test_dc_then_op_and_a_csp_move_at_1_ms_whose_position_follows_the_targets(master):
    assert master.config_dc()
    to_op(master)
    enable(master, MODE_CSP)
    bad = 0
    worst = 0
    for k in range(1, 1001):  # 20 000 counts in 1 s: a ramp of 20 counts a cycle
        put(master, CW_ENABLE, 20 * k, 0, MODE_CSP)
        bad += cycle(master, 1)
        for s in master.slaves:
            worst = max(worst, abs(status(s)[3]))
    cycle(master, 5)
    for s in master.slaves:
        sw, pos, _vel, ferr, mode, _inputs = status(s)
        assert pos == 20000 and mode == MODE_CSP and sw & 0x1000  # bit 12: the targets are followed
    assert worst == 0 and bad <= 10, (worst, bad)


def test_a_profile_position_move(master):
    for s in master.slaves:
        s.sdo_write(0x6081, 0, struct.pack("<I", 100000))  # profile velocity
        s.sdo_write(0x6083, 0, struct.pack("<I", 1000000))
        s.sdo_write(0x6084, 0, struct.pack("<I", 1000000))
    to_op(master)
    enable(master, MODE_PP)
    put(master, CW_ENABLE | 0x10, 25000, 0, MODE_PP)  # new set-point
    cycle(master, 5)
    put(master, CW_ENABLE, 25000, 0, MODE_PP)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 3:
        cycle(master, 10)
        if all(status(s)[0] & 0x0400 and status(s)[1] == 25000 for s in master.slaves):
            break
    assert [status(s)[1] for s in master.slaves] == [25000, 25000]


def test_a_fault_faults_the_drive_with_its_emergency_and_a_fault_reset_clears_it(master, bench):
    emcys = []
    master.slaves[0].add_emergency_callback(emcys.append)
    to_op(master)
    enable(master, MODE_CSV)
    bench.cmd("fault 0:overcurrent=20")
    put(master, CW_ENABLE, 0, 20000, MODE_CSV)
    cycle(master, 100)
    sw = status(master.slaves[0])[0]
    assert sw & 0x4F == 0x08, hex(sw)  # FAULT
    assert status(master.slaves[1])[0] & 0x6F == 0x27  # the other drive runs on
    master.slaves[0].mbx_receive()
    assert [e.error_code for e in emcys][:1] == [0x2310]
    bench.cmd("clear 0")
    put(master, CW_FAULT_RESET, 0, 0, MODE_CSV)
    cycle(master, 5)
    assert status(master.slaves[0])[0] & 0x4F == 0x40  # SWITCH ON DISABLED


def test_the_watchdog_stops_the_axis_when_the_master_goes_silent(master):
    emcys = {0: [], 1: []}
    for n, s in enumerate(master.slaves):
        s.add_emergency_callback(emcys[n].append)
    to_op(master)
    enable(master, MODE_CSV)
    put(master, CW_ENABLE, 0, 20000, MODE_CSV)
    cycle(master, 50)
    assert all(abs(status(s)[2]) > 0 for s in master.slaves)
    time.sleep(0.4)  # no process data: the watchdog (100 ms) runs out
    master.read_state()
    for s in master.slaves:
        assert s.state == pysoem.SAFEOP_STATE | 0x10 and s.al_status == 0x001B  # SM watchdog
        sw = struct.unpack("<H", s.sdo_read(0x6041, 0))[0]
        assert sw & 0x4F == 0x08, hex(sw)  # the drive faulted (0x6007 = 1)
        assert struct.unpack("<i", s.sdo_read(0x606C, 0))[0] == 0  # and stands
    # each said why, in the mailbox: EMCY 0x8130 (the master's life sign was lost)
    assert [[e.error_code for e in emcys[n]] for n in (0, 1)] == [[0x8130], [0x8130]]


def test_a_slave_that_refuses_op_says_why(master, bench):
    bench.cmd("fault 1:refuse-op=0x001A")
    master.config_map()
    master.state_check(pysoem.SAFEOP_STATE, 50000)
    cycle(master, 3)
    master.state = pysoem.OP_STATE
    master.write_state()
    master.state_check(pysoem.OP_STATE, 50000)
    master.read_state()
    assert master.slaves[0].state == pysoem.OP_STATE
    assert master.slaves[1].state == pysoem.SAFEOP_STATE | 0x10 and master.slaves[1].al_status == 0x001A


def test_the_benchs_capture_decodes_in_tshark_as_ethercat_with_coe_and_nothing_malformed(tmp_path):
    """`python -m motorjig.sim --ecat-slaves 1 --ecat-capture FILE`, as a user starts it; a scan and SDOs."""
    import shutil

    tshark = shutil.which("tshark")
    if tshark is None:
        pytest.skip("tshark is not installed (apt-get install tshark)")
    path = tmp_path / "ecat.pcapng"
    proc = subprocess.Popen([sys.executable, "-m", "motorjig.sim", "--ecat-slaves", "1", "--ecat-capture", str(path),
                             "--no-demo", "--no-pty"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ENV, cwd=ROOT)
    try:
        ifname = netns = None
        for _ in range(20):
            line = proc.stdout.readline()
            if "EtherCAT:" in line:
                ifname = line.split("on interface ")[1].split()[0]
                netns = line.split("(namespace ")[1].split()[0].rstrip(",)")
                break
        assert ifname, proc.stderr.read()
        m = pysoem.Master()
        m.open(ifname)
        assert m.config_init() == 1
        assert m.slaves[0].sdo_read(0x1008, 0).startswith(b"MotorJig")
        with pytest.raises(pysoem.SdoError):
            m.slaves[0].sdo_read(0x2345, 0)
        m.close()
    finally:
        proc.terminate()
        proc.wait(20)
    assert netns not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout.split()

    def fields(*args):
        r = subprocess.run([tshark, "-r", str(path)] + list(args), capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        return [line for line in r.stdout.splitlines() if line]

    assert len(fields()) > 100
    assert fields("-Y", "_ws.malformed") == []
    # the only expert note is about SOEM's own source address (01:01:01:01:01:01 is a group address)
    assert set(fields("-Y", "_ws.expert", "-T", "fields", "-e", "_ws.expert.message")) <= {
        "Source MAC must not be a group address: IEEE 802.3-2002, Section 3.2.3(b)"}
    coe = fields("-Y", "ecat_mailbox.coe", "-T", "fields", "-e", "ecat_mailbox.coe.sdoreq")
    assert len(coe) >= 4  # the requests and the slave's answers, an abort among them
    aborts = fields("-Y", "ecat_mailbox.coe.abortcode", "-T", "fields", "-e", "ecat_mailbox.coe.abortcode")
    assert aborts and all(int(a, 0) == 0x06020000 for a in aborts)  # 'object does not exist', as answered


def jigctl(*args):
    return subprocess.run([sys.executable, "-m", "motorjig.cli"] + list(args), capture_output=True, text=True,
                          env=ENV, cwd=ROOT, timeout=120)


def test_jigctl_ecat_scans_reads_writes_shows_the_pdos_and_dumps_the_sii(bench):
    bench.cmd("power-cycle")
    r = jigctl("ecat", "scan", "--ifname", bench.ifname)
    assert r.returncode == 0, r.stderr
    rows = [line for line in r.stdout.splitlines() if "MotorJig ECAT servo" in line]
    assert len(rows) == 2 and "0x4D4A4947 0x00000402 0x00010000" in rows[0]
    r = jigctl("ecat", "sdo", "write", "--ifname", bench.ifname, "1", "0x6081", "4321")
    assert r.returncode == 0 and "written" in r.stdout, r.stderr
    r = jigctl("ecat", "sdo", "read", "--ifname", bench.ifname, "1", "0x6081")
    assert r.returncode == 0 and "0x6081:00 Profile velocity = 0x10E1 (4321)" in r.stdout, r.stdout + r.stderr
    r = jigctl("ecat", "pdo", "--ifname", bench.ifname, "0")
    assert r.returncode == 0 and "0x1C12 RxPDO (outputs): 0x1600" in r.stdout
    assert "0x1600:2  0x607A:00  32 bits" in r.stdout, r.stdout
    r = jigctl("ecat", "dump", "--ifname", bench.ifname, "0")
    assert r.returncode == 0 and "vendor 0x4D4A4947 product 0x00000402" in r.stdout and "(checksum ok)" in r.stdout
    assert "name: MotorJig ECAT servo" in r.stdout and "category SyncM (41): 32 bytes" in r.stdout, r.stdout
    r = jigctl("ecat", "state", "--ifname", bench.ifname, "--set", "preop")
    assert r.returncode == 0 and r.stdout.count("PRE-OP, AL status 0x0000") == 2, r.stdout


@pytest.mark.parametrize("args, said", [
    (["scan", "--ifname", "nosuch0"], "no network interface named nosuch0"),
    (["sdo", "read", "--ifname", "IF", "7", "0x6041"], "slave position 7 is not on the line (2 slaves: 0..1)"),
    (["sdo", "read", "--ifname", "IF", "0", "0x2345"], "abort 0x06020000"),
    (["sdo", "read", "--ifname", "IF", "0", "nope"], "'nope' is not INDEX[:SUB]"),
    (["sdo", "write", "--ifname", "IF", "0", "0x6041", "1"], "abort 0x06010002"),
])
def test_jigctl_ecat_errors_are_one_sentence(bench, args, said):
    r = jigctl("ecat", *[bench.ifname if a == "IF" else a for a in args])
    assert r.returncode != 0 and said in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1
