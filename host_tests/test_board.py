"""jig.board and jig.uartport under CPython with fake machine/micropython/stm modules.

Checks the receive path (bytes visible while a frame is still arriving, the
port's any/readinto/write being the UART's own methods, no interrupt handler),
the overflow count and the traffic LED from housekeeping, the USART
driver-enable register arithmetic and write order, the software-DE fallback, the
jig I/O bit mapping, jig.app bridging on the board, and main.py's safe boot,
crash and Ctrl-C paths. The pure boot modules are in test_boot.py.
"""

import importlib
import os
import sys
import types

import pytest

# Import the portable firmware modules with the real CPython environment first:
# jig.compat must not see the fake `micropython` module (it would try viper).
import jig.compat  # noqa: F401
import jig.crashlog
import jig.params  # noqa: F401
import jig.safeboot

USART2 = 0x40004400
USART3 = 0x40004800
CR1, CR3, ISR, ICR = 0x00, 0x08, 0x1C, 0x20
ISR_IDLE, ISR_TC = 1 << 4, 1 << 6
BASES = {2: USART2, 3: USART3}


class FakePin:
    OUT = "out"
    IN = "in"
    ALT = "alt"
    PULL_UP = "pull_up"
    levels = {}  # pin name -> level read by value()
    instances = {}

    def __init__(self, name, mode=None, pull=None, value=None, alt=None):
        self.name = name
        self.mode = mode
        self.pull = pull
        self.alt = alt
        self.level = value if value is not None else 0
        self.writes = []
        FakePin.instances[name] = self

    def init(self, mode=None, pull=None, value=None, alt=None):
        self.mode = mode
        self.alt = alt
        if value is not None:
            self.value(value)

    def value(self, v=None):
        if v is None:
            return FakePin.levels.get(self.name, self.level)
        self.level = v
        self.writes.append(v)
        return None


class Mem32:
    """stm.mem32 stand-in: a register file that logs every write; writing a 1 to a
    USART's ICR clears that bit in its ISR, as on the chip."""

    def __init__(self):
        self.regs = {}
        self.log = []

    def __getitem__(self, addr):
        return self.regs.get(addr, 0)

    def __setitem__(self, addr, value):
        value &= 0xFFFFFFFF
        self.regs[addr] = value
        self.log.append((addr, value))
        for base in BASES.values():
            if addr == base + ICR:
                self.regs[base + ISR] = self.regs.get(base + ISR, 0) & ~value


class FakeTxRegs:
    """The USART's ISR..TDR words as ``UartPort.queue``/``drain`` see them (word 0 =
    ISR, word 3 = TDR): the FIFO always has room, each byte written to TDR is sent."""

    def __init__(self, uart):
        self.uart = uart

    def __getitem__(self, word):
        return (1 << 7) | ISR_TC if word == 0 else 0

    def __setitem__(self, word, value):
        assert word == 3, "only TDR is written"
        self.uart.sent.append(bytes((value,)))


def board_app(fakes, tmp_path):
    """jig.app.App on Board, the ports' transmit-FIFO registers on FakeTxRegs (CPython
    has no USART): (board, app)."""
    from jig.app import App

    b = fakes.board.Board("MotorJig STM32H7_JIG with STM32H743VI")
    b.param_path = str(tmp_path / "jigparams.bin")
    app = App(b)
    for port in (b.up, b.down):
        port.regs = FakeTxRegs(port.uart)
    assert app.up.queued and app.down.queued
    return b, app


class NoClockHal:
    """Just what Rs485 binds from a HAL."""

    ticks_us = staticmethod(lambda: 0)
    sleep_us = staticmethod(lambda us: None)


class FakeUART:
    """machine.UART on stm32 as far as the port uses it: an rxbuf ring that the
    (C) RX interrupt fills, read and written through the stream methods."""

    mem = None  # the fake stm.mem32, for the USART's idle flag
    instances = {}

    def __init__(self, uart_id, **kw):
        self.id = uart_id
        self.kw = kw
        self.pending = bytearray()
        self.sent = []
        self.irq_calls = 0
        self.over_asks = 0  # reads asked for more than was waiting (would wait on stm32)
        FakeUART.instances[uart_id] = self

    def irq(self, *args, **kw):
        self.irq_calls += 1

    def any(self):
        return min(len(self.pending), self.kw["rxbuf"])

    def readinto(self, buf, n=None):
        if n is None:
            n = len(buf)
        if n > len(self.pending):
            self.over_asks += 1
        n = min(n, len(buf), len(self.pending))
        if n == 0:
            return None
        buf[:n] = self.pending[:n]
        del self.pending[:n]
        return n

    def write(self, buf, a, b=None):
        off, n = (0, a) if b is None else (a, b)
        self.sent.append(bytes(buf[off : off + n]))
        return n

    def arrive(self, data):
        """Bytes arrive while the line is still busy: in the ring, no idle yet."""
        self.pending += data

    def receive(self, data):
        """A burst arrives and the line goes idle: USART_ISR.IDLE is set."""
        self.pending += data
        base = BASES.get(self.id)
        if base is not None and FakeUART.mem is not None:
            FakeUART.mem.regs[base + ISR] = FakeUART.mem.regs.get(base + ISR, 0) | ISR_IDLE


class FakeWDT:
    created = 0

    def __init__(self, timeout):
        FakeWDT.created += 1
        FakeWDT.last = self
        self.timeout = timeout
        self.feeds = 0

    def feed(self):
        self.feeds += 1


class FakeTimer:
    PERIODIC = 1
    made = []

    def __init__(self, tid=-1, mode=None, period=None, callback=None, hard=False):
        self.period, self.callback, self.hard = period, callback, hard
        FakeTimer.made.append(self)


@pytest.fixture
def fakes(monkeypatch, tmp_path):
    FakePin.levels = {}
    FakePin.instances = {}
    FakeUART.instances = {}
    FakeWDT.created = 0
    FakeTimer.made = []
    machine = types.ModuleType("machine")
    machine.Pin = FakePin
    machine.UART = FakeUART
    machine.WDT = FakeWDT
    machine.WDT_RESET = 3
    machine.reset_cause = lambda: 1
    machine.resets = []
    machine.reset = lambda: machine.resets.append(1)
    machine.Timer = FakeTimer
    micropython = types.ModuleType("micropython")
    micropython.alloc_emergency_exception_buf = lambda n: None
    micropython.const = lambda v: v
    micropython.viper = lambda fn: fn  # the compiler's decorator; here the source runs as Python
    stm = types.ModuleType("stm")
    stm.mem32 = Mem32()
    FakeUART.mem = stm.mem32
    stm.USART2 = USART2
    stm.USART3 = USART3
    stm.USART_CR1 = CR1
    stm.USART_CR3 = CR3
    stm.USART_ISR = ISR
    stm.USART_ICR = ICR
    stm.mem32.regs[USART2 + ISR] = ISR_TC  # TC set: the line is idle
    stm.mem32.regs[USART3 + ISR] = ISR_TC
    for name, mod in (("machine", machine), ("micropython", micropython), ("stm", stm)):
        monkeypatch.setitem(sys.modules, name, mod)
    monkeypatch.delitem(sys.modules, "jig.board", raising=False)
    monkeypatch.delitem(sys.modules, "jig.uartport", raising=False)
    uartport = importlib.import_module("jig.uartport")
    board = importlib.import_module("jig.board")
    yield types.SimpleNamespace(board=board, uartport=uartport, machine=machine, stm=stm, tmp=tmp_path)
    sys.modules.pop("jig.board", None)
    sys.modules.pop("jig.uartport", None)


def make_board(fakes, name="MotorJig STM32H7_JIG with STM32H743VI"):
    b = fakes.board.Board(name)
    b.open(115200, 115200)
    return b


# --- receive path ------------------------------------------------------------------------
def test_uart_opened_with_the_rxbuf_ring_and_no_python_irq(fakes):
    make_board(fakes)
    for uid in (2, 3):
        u = FakeUART.instances[uid]
        assert u.kw["rxbuf"] == fakes.uartport.RXBUF >= 1024
        assert u.kw["baudrate"] == 115200
        assert u.kw["timeout"] == 0  # a read with nothing waiting returns at once
        assert u.irq_calls == 0  # the C RX interrupt fills the ring; no Python handler


def test_any_readinto_write_are_the_uarts_own_methods(fakes):
    """No Python wrapper between the app and the C methods: the port's attributes
    are the UART's bound methods, made once."""
    b = make_board(fakes)
    for port in (b.up, b.down):
        for name in ("any", "readinto", "write"):
            m = getattr(port, name)
            assert m.__self__ is port.uart and m.__func__ is getattr(FakeUART, name)
        assert port.de.__self__ is port.de_pin
        assert port.tx_blocks is True and port.baud == 115200
        assert port.echo_free is True  # /RE tied to DE on the jig
        assert not hasattr(port, "t_last")  # the app takes the tick of its own read


def test_bytes_are_readable_while_the_frame_is_still_arriving(fakes):
    """Cut-through needs the first bytes before the last has arrived."""
    b = make_board(fakes)
    u = FakeUART.instances[2]
    frame_ = b"\xaa\xcc\x02\x40\xaa\xaa\x01\xc6\xaa\xee"
    u.arrive(frame_[:3])  # header + slave id so far; the line is still busy
    buf = bytearray(16)
    n = b.up.any()
    assert n == 3 and b.up.readinto(buf, n) == 3 and buf[:3] == frame_[:3]
    assert b.up.any() == 0
    u.arrive(frame_[3:])
    n = b.up.any()
    assert b.up.readinto(buf, n) == len(frame_) - 3 and bytes(buf[:n]) == frame_[3:]
    assert u.over_asks == 0


def test_write_passes_offset_and_length_without_slicing(fakes):
    b = make_board(fakes)
    buf = bytearray(b"\x00\x00\xaa\xcc\x01\x01\xc1\xe0\xaa\xee" + b"\x00" * 20)
    b.down.write(buf, 2, 8)
    b.down.write(buf, 4)
    assert FakeUART.instances[3].sent == [b"\xaa\xcc\x01\x01\xc1\xe0\xaa\xee", b"\x00\x00\xaa\xcc"]


def test_a_full_ring_counts_one_overflow_per_time_it_is_found_full(fakes):
    b = make_board(fakes)
    u = FakeUART.instances[3]
    rxbuf = fakes.uartport.RXBUF
    u.arrive(b"\x55" * (rxbuf - 1))
    b.housekeep(1000)
    assert b.down.overflows == 0 and FakePin.instances["LED_ERR"].level == 0
    u.arrive(b"\x55" * 50)  # the ring is full: the driver drops what follows
    b.housekeep(1010)
    b.housekeep(1020)  # still full: the same event
    assert b.down.overflows == 1 and b.up.overflows == 0
    assert FakePin.instances["LED_ERR"].level == 1
    buf = bytearray(256)
    b.down.readinto(buf, 256)
    b.housekeep(1030)
    u.arrive(b"\x55" * 256)  # full again
    b.housekeep(1040)
    assert b.down.overflows == 2
    b.housekeep(1040 + fakes.board.ERROR_LED_MS + 1)
    assert FakePin.instances["LED_ERR"].level == 0


def test_traffic_led_sees_a_burst_the_app_already_drained(fakes):
    """The USART's idle flag marks every burst that ended since the last look;
    housekeeping clears it, so the LED goes off once the line stays quiet."""
    b = make_board(fakes)
    led = FakePin.instances["LED_TRAFFIC"]
    mem = fakes.stm.mem32
    pc = FakeUART.instances[2]
    pc.receive(b"\xaa\xcc\x01\x01\xc1\xe0\xaa\xee")
    b.up.readinto(bytearray(8), b.up.any())  # the main loop drained it at once
    b.housekeep(2000)
    assert led.level == 1
    assert mem[USART2 + ISR] & ISR_IDLE == 0  # cleared through ICR
    assert mem[USART2 + ISR] & ISR_TC  # nothing else touched
    b.housekeep(2000 + fakes.board.TRAFFIC_LED_MS - 1)
    assert led.level == 1
    b.housekeep(2000 + fakes.board.TRAFFIC_LED_MS + 1)
    assert led.level == 0
    FakeUART.instances[3].receive(b"\x01")  # the driver bus lights it too
    b.housekeep(3000)
    assert led.level == 1


def test_traffic_led_without_stm_uses_waiting_bytes(fakes, monkeypatch):
    monkeypatch.setattr(fakes.uartport, "stm", None)
    b = make_board(fakes)
    led = FakePin.instances["LED_TRAFFIC"]
    FakeUART.instances[2].arrive(b"\x01\x02")
    b.housekeep(1000)
    assert led.level == 1
    b.up.readinto(bytearray(2), 2)
    b.housekeep(1000 + fakes.board.TRAFFIC_LED_MS + 1)
    assert led.level == 0


def test_housekeeping_runs_from_wdt_feed_at_most_every_few_ms(fakes, monkeypatch):
    b = make_board(fakes)
    ran = []
    monkeypatch.setattr(b, "housekeep", lambda now: ran.append(now))
    clock = [10000]
    monkeypatch.setattr(fakes.board, "ticks_ms", lambda: clock[0])
    b.t_house = clock[0]
    b.wdt_feed()
    clock[0] += fakes.board.HOUSEKEEP_MS - 1
    b.wdt_feed()
    assert ran == [] and b.wdt.feeds == 2
    clock[0] += 1
    b.wdt_feed()
    assert ran == [clock[0]]


def test_crash_streak_cleared_after_a_clean_minute(fakes, monkeypatch, tmp_path):
    path = str(tmp_path / "crash.txt")
    monkeypatch.setattr(jig.crashlog, "CRASH_PATH", path)
    jig.crashlog.record_crash(RuntimeError("x"))
    b = make_board(fakes)
    b.housekeep(b.t_start + jig.safeboot.CLEAN_RUN_MS - 1)
    assert jig.crashlog.parse_crash_counts(jig.crashlog.read_crash_log()) == (1, 1, 0)
    b.housekeep(b.t_start + jig.safeboot.CLEAN_RUN_MS + 1)
    assert jig.crashlog.parse_crash_counts(jig.crashlog.read_crash_log()) == (1, 0, 0)


# --- DE register arithmetic ----------------------------------------------------------
def test_cr1_de_times_land_in_deat_and_dedt(fakes):
    up = fakes.uartport
    cr1 = up.cr1_with_de_times(0, 5, 3)
    assert (cr1 >> 21) & 0x1F == 5
    assert (cr1 >> 16) & 0x1F == 3
    assert cr1 & ~((0x1F << 21) | (0x1F << 16)) == 0


def test_cr1_de_times_keep_other_bits_and_replace_old_times(fakes):
    up = fakes.uartport
    other = (1 << 29) | (1 << 3) | (1 << 2) | 1  # FIFOEN, TE, RE, UE
    old = other | (31 << 21) | (31 << 16)
    cr1 = up.cr1_with_de_times(old, 2, 1)
    assert cr1 == other | (2 << 21) | (1 << 16)


def test_cr1_de_times_are_clamped_to_five_bits(fakes):
    up = fakes.uartport
    cr1 = up.cr1_with_de_times(0, 100, -4)
    assert (cr1 >> 21) & 0x1F == 31
    assert (cr1 >> 16) & 0x1F == 0
    assert cr1 >> 26 == 0  # nothing spilled into bits above DEAT


def test_cr3_de_mode_and_polarity(fakes):
    up = fakes.uartport
    assert up.cr3_with_de(0, True) == 1 << 14
    assert up.cr3_with_de(1 << 15, True) == 1 << 14  # DEP cleared: DE active high
    assert up.cr3_with_de((1 << 14) | 1, False) == 1
    assert up.USART_CR3_DEM == 1 << 14 and up.USART_CR3_DEP == 1 << 15


def test_hw_de_register_sequence_and_pin_function(fakes):
    b = make_board(fakes)
    mem = fakes.stm.mem32
    mem.regs[USART2 + CR1] = 0x2000000D  # FIFOEN | TE | RE | UE as MicroPython left it
    mem.log.clear()
    assert b.up.hw_de(True, 4, 2) is True
    writes = [(a - USART2, v) for a, v in mem.log]
    # UE off first, then CR3, then CR1 with the times and UE back on.
    assert writes[0] == (CR1, 0x2000000C)
    assert writes[1] == (CR3, 1 << 14)
    assert writes[2] == (CR1, 0x2000000D | (4 << 21) | (2 << 16))
    pin = FakePin.instances["UP_DE"]
    assert pin.mode == FakePin.ALT and pin.alt == 7 and b.up.hw is True
    # In hardware mode a software DE call reaches only the output register: the
    # pin stays in its alternate function, driven by the USART.
    b.up.de(1)
    assert pin.mode == FakePin.ALT
    # Off again: pin back to a low output, DEM cleared, software DE works.
    assert b.up.hw_de(False, 0, 0) is True
    assert pin.mode == FakePin.OUT and pin.level == 0
    assert mem[USART2 + CR3] & (1 << 14) == 0
    b.up.de(1)
    assert pin.level == 1


def test_software_de_when_stm_is_missing(fakes, monkeypatch):
    monkeypatch.setattr(fakes.uartport, "stm", None)
    b = make_board(fakes)
    assert b.up.base is None
    assert b.up.hw_de(True, 4, 2) is False
    b.up.de(1)
    assert FakePin.instances["UP_DE"].level == 1
    b.up.de(0)
    assert FakePin.instances["UP_DE"].level == 0


# --- jig I/O, watchdog, profiles --------------------------------------------------------
def test_outputs_drive_relays_and_read_back(fakes):
    b = make_board(fakes)
    b.set_outputs(0b1010 | (1 << 20))
    assert [FakePin.instances["RLY%d" % k].level for k in (1, 2, 3, 4)] == [0, 1, 0, 1]
    assert b.get_outputs() == 0b1010


def test_inputs_are_active_low_bits(fakes):
    b = make_board(fakes)
    FakePin.levels = {"IN1": 1, "IN2": 0, "IN3": 1, "IN4": 0, "BTN_SAFE": 1}
    assert b.get_inputs() == 0b01010
    FakePin.levels["BTN_SAFE"] = 0
    assert b.get_inputs() == 0b11010


def test_watchdog_starts_on_first_feed_only(fakes):
    b = make_board(fakes)
    assert FakeWDT.created == 0
    b.wdt_feed()
    b.wdt_feed()
    assert FakeWDT.created == 1 and b.wdt.feeds == 2
    assert b.wdt.timeout == fakes.board.WDT_MS


def test_profiles(fakes):
    bd = fakes.board
    assert bd.profile_for("NUCLEO_H743ZI2 with STM32H743")[0] == "NUCLEO_H743ZI"
    assert bd.profile_for("MotorJig STM32H7_JIG with STM32H743VI")[0] == "STM32H7_JIG"
    assert bd.profile_for("something else")[0] == "STM32H7_JIG"
    jig = dict(bd.PROFILES)["STM32H7_JIG"]
    assert jig["up"][0] != jig["down"][0]
    nucleo = make_board(fakes, "NUCLEO_H743ZI2 with STM32H743")
    assert nucleo.up.echo_free is False and FakeUART.instances[6].kw["rxbuf"] == fakes.uartport.RXBUF


def test_safe_button_pin_per_profile(fakes, monkeypatch):
    monkeypatch.setattr(jig.safeboot, "sleep_ms", lambda ms: None)
    pin, active = fakes.board.safe_button("STM32H7_JIG")
    assert pin.name == "BTN_SAFE" and active == 0 and pin.pull == FakePin.PULL_UP
    FakePin.levels = {"BTN_SAFE": 0}
    assert jig.safeboot.button_held(pin, active) is True
    pin, active = fakes.board.safe_button("NUCLEO_H743ZI")
    FakePin.levels = {"PC13": 1}  # NUCLEO user button is active high
    assert jig.safeboot.button_held(pin, active) is True


def test_no_flash_device_off_the_board(fakes):
    assert fakes.board.flash_device() is None  # no pyb module here
    assert fakes.board.early_boot() == "none"


# --- the app on this HAL ----------------------------------------------------------------
def test_app_bridges_on_the_board_hal(fakes, tmp_path):
    """jig.app.App runs on Board: a local answer, a forward and a relayed reply."""
    from jig import frame
    from jig.parser import FrameParser

    b, app = board_app(fakes, tmp_path)
    pc, drv = FakeUART.instances[2], FakeUART.instances[3]
    de_up = FakePin.instances["UP_DE"]

    pc.receive(frame.encode(1, frame.GET_SLAVE_INFO))
    app.poll()
    p = FrameParser()
    p.feed(b"".join(pc.sent))  # one write (the pump) or queued byte by byte (Rs485.send)
    assert p.ready and p.slave == 1 and p.ftype == frame.GET_SLAVE_INFO and p.body[p.data_start] == 0
    assert de_up.writes[-2:] == [1, 0]  # software DE around the reply
    # cut through, its header went on before the id was known: ended as a stub
    assert b"".join(drv.sent) == bytes((0xAA, 0xCC, 1, 0xAA, 0xEE))
    drv.sent.clear()

    request = frame.encode(2, frame.GET_AXIS_STATUS)
    reply = frame.encode(2, frame.GET_AXIS_STATUS, b"\x00\x00\x00\x00\x08")
    pc.receive(request)
    app.poll()
    assert b"".join(drv.sent) == request  # cut through: the header first, the rest as it came
    n_pc = len(pc.sent)
    drv.receive(reply)
    app.poll()
    assert b"".join(pc.sent[n_pc:]) == reply
    assert b.wdt is not None and b.wdt.feeds >= 1


def test_app_reads_only_the_bytes_waiting(fakes, tmp_path):
    from jig import frame

    _b, app = board_app(fakes, tmp_path)
    pc, drv = FakeUART.instances[2], FakeUART.instances[3]
    pc.receive(frame.encode(2, frame.GET_AXIS_STATUS))
    app.poll()
    drv.receive(frame.encode(2, frame.GET_AXIS_STATUS, b"\x00\x00\x00\x00\x08"))
    app.poll()
    assert len(drv.sent) >= 1 and len(pc.sent) >= 1
    assert pc.over_asks == 0 and drv.over_asks == 0


# --- main.py ---------------------------------------------------------------------------------
def load_main(fakes, monkeypatch, tmp_path):
    import importlib.util
    import os

    monkeypatch.setattr(jig.crashlog, "CRASH_PATH", str(tmp_path / "crash.txt"))
    monkeypatch.setattr(jig.safeboot, "sleep_ms", lambda ms: None)
    monkeypatch.setattr(fakes.board, "PARAM_PATH", str(tmp_path / "jigparams.bin"))
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "firmware", "main.py")
    spec = importlib.util.spec_from_file_location("jig_main_under_test", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # runs main() itself: machine is the fake here
    return mod


def test_main_safe_boot_when_button_held(fakes, monkeypatch, tmp_path):
    FakePin.levels = {"BTN_SAFE": 0}
    mod = load_main(fakes, monkeypatch, tmp_path)  # the import-time run: safe boot
    assert mod.main() == jig.safeboot.MODE_SAFE_BUTTON
    assert FakeUART.instances == {}  # no port opened: both transceivers stay receiving
    assert FakePin.instances["LED_ERR"].level == 1
    assert FakeWDT.created == 0


def test_main_safe_boot_after_a_crash_streak(fakes, monkeypatch, tmp_path):
    FakePin.levels = {"BTN_SAFE": 0}
    mod = load_main(fakes, monkeypatch, tmp_path)
    FakePin.levels = {"BTN_SAFE": 1}
    for _ in range(jig.safeboot.SAFE_AFTER_CRASHES):
        jig.crashlog.record_crash(RuntimeError("x"))
    assert "crashed 3 times" in mod.main()


def test_main_logs_a_crash_and_resets(fakes, monkeypatch, tmp_path):
    from jig.app import App

    FakePin.levels = {"BTN_SAFE": 0}
    mod = load_main(fakes, monkeypatch, tmp_path)
    FakePin.levels = {"BTN_SAFE": 1}

    real_run = App.run

    def run(self, passes=-1):
        real_run(self, 1)  # one real pass, then the failure
        raise RuntimeError("bridge fell over")

    monkeypatch.setattr(App, "run", run)
    assert mod.main() == "crashed"
    assert fakes.machine.resets == [1]
    log = jig.crashlog.read_crash_log()
    assert "RuntimeError: bridge fell over" in log and "up_frames_in=0" in log
    assert jig.crashlog.parse_crash_counts(log) == (1, 1, 0)


def test_main_ctrl_c_keeps_the_watchdog_fed(fakes, monkeypatch, tmp_path):
    from jig.app import App

    FakePin.levels = {"BTN_SAFE": 0}
    mod = load_main(fakes, monkeypatch, tmp_path)
    FakePin.levels = {"BTN_SAFE": 1}

    real_run = App.run

    def run(self, passes=-1):
        real_run(self, 1)  # one real pass, then the failure
        raise KeyboardInterrupt

    monkeypatch.setattr(App, "run", run)
    assert mod.main() == "stopped"
    assert fakes.machine.resets == []
    assert FakeWDT.created == 1  # started by the first main-loop pass
    assert len(FakeTimer.made) == 1 and FakeTimer.made[0].hard is True
    assert FakeTimer.made[0].period < fakes.board.WDT_MS
    feeds = FakeWDT.last.feeds
    FakeTimer.made[0].callback(None)
    assert FakeWDT.last.feeds == feeds + 1


# --- transmit FIFO (queue/drain: viper on ISR/TDR; here as Python on a register block) ------
def test_queue_puts_each_byte_into_tdr_and_drain_waits_for_tc(fakes):
    b = make_board(fakes)
    up = fakes.uartport
    regs = bytearray(16)  # word 0 = ISR, word 3 = TDR, as at USART + 0x1C
    regs[0] = up.USART_ISR_TXFNF | up.USART_ISR_TC
    b.down.regs = regs
    data = bytearray(b"\x00\xaa\xcc\x02\x43\xd1\x2b\xaa\xee")
    seen = bytearray()
    for i in range(1, len(data)):
        assert b.down.queue(data, i, 1) == 1
        seen.append(regs[12])
    assert seen == data[1:]
    assert b.down.queue(data, 1, 8) == 8 and regs[12] == 0xEE  # the last byte queued is in TDR
    assert b.down.drain() == 0


def test_queue_stops_when_the_fifo_stays_full(fakes):
    b = make_board(fakes)
    regs = bytearray(16)
    regs[0] = fakes.uartport.USART_ISR_TC  # TXFNF clear: the FIFO is full and never empties
    b.down.regs = regs
    assert b.down.queue(b"\xaa\xcc", 0, 2) == 0
    assert regs[12] == 0


def test_rs485_queues_on_the_board_port(fakes):
    from jig.rs485 import Rs485

    b = make_board(fakes)

    rs = Rs485(NoClockHal(), b.down)
    assert rs.plain and rs.queued
    assert rs.raw_part.__func__ is type(b.down).queue and rs.drain.__func__ is type(b.down).drain


def test_a_port_without_registers_has_only_the_blocking_write(fakes, monkeypatch):
    monkeypatch.setattr(fakes.uartport, "usart_base", lambda uid: None)
    b = make_board(fakes)
    assert b.down.queue is None and b.down.drain is None
    from jig.rs485 import Rs485

    rs = Rs485(NoClockHal(), b.down)
    assert rs.plain and not rs.queued and rs.raw_part == b.down.write


# --- the capture port (the second USB CDC port) ------------------------------------------
class FakeVCP:
    """pyb.USB_VCP as the stm32 port has it: flow control set by init(flow=...)."""

    CTS = 2
    made = []

    def __init__(self, index):
        self.index = index
        self.flow = -1
        FakeVCP.made.append(self)

    def init(self, flow=-1):
        self.flow = flow


def test_the_capture_port_is_the_second_usb_cdc_port_with_cts_flow(fakes, monkeypatch):
    pyb = types.ModuleType("pyb")
    pyb.USB_VCP = FakeVCP
    FakeVCP.made = []
    monkeypatch.setitem(sys.modules, "pyb", pyb)
    b = fakes.board.Board("STM32H7_JIG")
    assert b.capture is FakeVCP.made[0]
    # CTS flow: a write takes only what fits and nothing while no PC has the port open
    assert b.capture.index == 1 and b.capture.flow == FakeVCP.CTS
    # the third is the SLCAN port of the CAN port, set up the same way
    assert b.slcan is FakeVCP.made[1] and b.slcan.index == 2 and b.slcan.flow == FakeVCP.CTS


def test_no_capture_port_without_pyb(fakes):
    b = fakes.board.Board("STM32H7_JIG")
    assert b.capture is None and b.slcan is None


class FakeCAN:
    """machine.CAN as far as Board.can_open uses it."""

    MODE_NORMAL = 0
    MODE_SILENT = 3
    made = []

    def __init__(self, index, bitrate, mode=0):
        if bitrate > 1000000:
            raise ValueError("bitrate")
        self.index, self.bitrate, self.mode = index, bitrate, mode
        self.filters = "unset"
        self.deinits = 0
        FakeCAN.made.append(self)

    def set_filters(self, filters):
        self.filters = filters

    def deinit(self):
        self.deinits += 1


@pytest.mark.parametrize("name", ["STM32H7_JIG", "NUCLEO_H743ZI"])
def test_can_open_is_fdcan1_receiving_all_in_the_mode_asked(fakes, monkeypatch, name):
    monkeypatch.setattr(fakes.machine, "CAN", FakeCAN, raising=False)
    b = fakes.board.Board(name)
    can = b.can_open(500000, 0)
    assert (can.index, can.bitrate, can.mode, can.filters) == (1, 500000, FakeCAN.MODE_NORMAL, None)
    assert b.can_open(125000, 1).mode == FakeCAN.MODE_SILENT
    assert b.can_open(2000000, 0) is None  # a bitrate the controller refuses
    b.can_close(can)
    assert can.deinits == 1


def test_no_can_without_machine_can(fakes):
    assert fakes.board.Board("STM32H7_JIG").can_open(500000, 0) is None


def _boot_modes(monkeypatch, accepts):
    """The usb_mode calls of jigusb.py on a build whose CDC modes are ``accepts``."""
    pyb = types.ModuleType("pyb")
    modes = []

    def usb_mode(mode):
        modes.append(mode)
        if mode not in accepts:
            raise ValueError("mode not supported")

    pyb.usb_mode = usb_mode
    monkeypatch.setitem(sys.modules, "pyb", pyb)
    sys.modules.pop("jigusb", None)
    importlib.import_module("jigusb")
    sys.modules.pop("jigusb", None)
    return modes


def test_the_usb_boot_file_asks_for_three_cdc_ports(monkeypatch):
    assert _boot_modes(monkeypatch, ("VCP+VCP+VCP", "VCP+VCP")) == ["VCP+VCP+VCP"]
    board_h = open(os.path.join(os.path.dirname(__file__), "..", "boards", "STM32H7_JIG", "mpconfigboard.h")).read()
    assert "#define MICROPY_HW_USB_CDC_NUM      (3)" in board_h
    assert '#define MICROPY_BOARD_FROZEN_BOOT_FILE "jigusb.py"' in board_h
    # machine.CAN on FDCAN1, PD1 TX / PD0 RX, as upstream's NUCLEO_H743ZI
    assert '#define MICROPY_HW_CAN1_NAME        "FDCAN1"' in board_h
    assert "(pin_D1)" in board_h and "(pin_D0)" in board_h
    pins = open(os.path.join(os.path.dirname(__file__), "..", "boards", "STM32H7_JIG", "pins.csv")).read().split()
    assert "CAN_TX,PD1" in pins and "CAN_RX,PD0" in pins and ",PD0" not in pins and ",PD1" not in pins


def test_the_usb_boot_file_falls_back_to_two_ports_then_the_repl_only(monkeypatch):
    assert _boot_modes(monkeypatch, ("VCP+VCP",)) == ["VCP+VCP+VCP", "VCP+VCP"]
    assert _boot_modes(monkeypatch, ()) == ["VCP+VCP+VCP", "VCP+VCP"]  # nothing raised: the REPL only
