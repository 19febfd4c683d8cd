"""jig.board under CPython with fake machine/micropython/stm modules.

Checks the USART driver-enable register arithmetic and the register write order,
the receive-idle interrupt path (bytes reach the ring buffer, nothing in the
handler builds objects), the software-DE fallback, the jig I/O bit mapping, the
safe-boot decision and the crash log.
"""

import dis
import importlib
import sys
import types

import pytest

# Import the portable firmware modules with the real CPython environment first:
# jig.compat must not see the fake `micropython` module (it would try viper).
import jig.compat  # noqa: F401
import jig.params  # noqa: F401
import jig.ringbuf  # noqa: F401

USART2 = 0x40004400
USART3 = 0x40004800
CR1, CR3, ISR = 0x00, 0x08, 0x1C


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


class FakeUART:
    IRQ_RXIDLE = 0x10
    instances = {}

    def __init__(self, uart_id, **kw):
        self.id = uart_id
        self.kw = kw
        self.pending = bytearray()
        self.sent = []
        self.handler = None
        FakeUART.instances[uart_id] = self

    def irq(self, handler, trigger, hard=False):
        self.handler = handler
        self.trigger = trigger
        self.hard = hard

    def any(self):
        return len(self.pending)

    def readinto(self, buf, n):
        n = min(n, len(buf), len(self.pending))
        if n == 0:
            return None
        buf[:n] = self.pending[:n]
        del self.pending[:n]
        return n

    def write(self, buf, off, n):
        self.sent.append(bytes(buf[off : off + n]))
        return n

    def receive(self, data):
        """Bytes arrive, then the line goes idle: the IRQ fires."""
        self.pending += data
        self.handler(self)


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


class Mem32:
    """stm.mem32 stand-in: a register file that logs every write."""

    def __init__(self):
        self.regs = {}
        self.log = []

    def __getitem__(self, addr):
        return self.regs.get(addr, 0)

    def __setitem__(self, addr, value):
        value &= 0xFFFFFFFF
        self.regs[addr] = value
        self.log.append((addr, value))


@pytest.fixture
def fakes(monkeypatch, tmp_path):
    FakePin.levels = {}
    FakePin.instances = {}
    FakeUART.instances = {}
    FakeWDT.created = 0
    FakeTimer.made = []
    irq_calls = []
    machine = types.ModuleType("machine")
    machine.Pin = FakePin
    machine.UART = FakeUART
    machine.WDT = FakeWDT
    machine.WDT_RESET = 3
    machine.reset_cause = lambda: 1
    machine.resets = []
    machine.reset = lambda: machine.resets.append(1)
    machine.Timer = FakeTimer
    machine.disable_irq = lambda: irq_calls.append("off") or 7
    machine.enable_irq = lambda state: irq_calls.append(("on", state))
    micropython = types.ModuleType("micropython")
    micropython.alloc_emergency_exception_buf = lambda n: None
    micropython.const = lambda v: v
    stm = types.ModuleType("stm")
    stm.mem32 = Mem32()
    stm.USART2 = USART2
    stm.USART3 = USART3
    stm.USART_CR1 = CR1
    stm.USART_CR3 = CR3
    stm.USART_ISR = ISR
    stm.mem32.regs[USART2 + ISR] = 1 << 6  # TC set: the line is idle
    stm.mem32.regs[USART3 + ISR] = 1 << 6
    for name, mod in (("machine", machine), ("micropython", micropython), ("stm", stm)):
        monkeypatch.setitem(sys.modules, name, mod)
    monkeypatch.delitem(sys.modules, "jig.board", raising=False)
    board = importlib.import_module("jig.board")
    yield types.SimpleNamespace(board=board, machine=machine, stm=stm, irq_calls=irq_calls, tmp=tmp_path)
    sys.modules.pop("jig.board", None)


def make_board(fakes, name="MotorJig STM32H7_JIG with STM32H743VI"):
    b = fakes.board.Board(name)
    b.open(115200, 115200)
    return b


# --- DE register arithmetic ----------------------------------------------------------
def test_cr1_de_times_land_in_deat_and_dedt(fakes):
    bd = fakes.board
    cr1 = bd.cr1_with_de_times(0, 5, 3)
    assert (cr1 >> 21) & 0x1F == 5
    assert (cr1 >> 16) & 0x1F == 3
    assert cr1 & ~((0x1F << 21) | (0x1F << 16)) == 0


def test_cr1_de_times_keep_other_bits_and_replace_old_times(fakes):
    bd = fakes.board
    other = (1 << 29) | (1 << 3) | (1 << 2) | 1  # FIFOEN, TE, RE, UE
    old = other | (31 << 21) | (31 << 16)
    cr1 = bd.cr1_with_de_times(old, 2, 1)
    assert cr1 == other | (2 << 21) | (1 << 16)


def test_cr1_de_times_are_clamped_to_five_bits(fakes):
    bd = fakes.board
    cr1 = bd.cr1_with_de_times(0, 100, -4)
    assert (cr1 >> 21) & 0x1F == 31
    assert (cr1 >> 16) & 0x1F == 0
    assert cr1 >> 26 == 0  # nothing spilled into bits above DEAT


def test_cr3_de_mode_and_polarity(fakes):
    bd = fakes.board
    assert bd.cr3_with_de(0, True) == 1 << 14
    assert bd.cr3_with_de(1 << 15, True) == 1 << 14  # DEP cleared: DE active high
    assert bd.cr3_with_de((1 << 14) | 1, False) == 1
    assert bd.USART_CR3_DEM == 1 << 14 and bd.USART_CR3_DEP == 1 << 15


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
    assert pin.mode == FakePin.ALT and pin.alt == 7
    # In hardware mode the software DE calls leave the pin alone.
    before = list(pin.writes)
    b.up.de(1)
    assert pin.writes == before
    # Off again: pin back to a low output, DEM cleared.
    assert b.up.hw_de(False, 0, 0) is True
    assert pin.mode == FakePin.OUT and pin.level == 0
    assert mem[USART2 + CR3] & (1 << 14) == 0
    b.up.de(1)
    assert pin.level == 1


def test_software_de_when_stm_is_missing(fakes, monkeypatch):
    monkeypatch.setattr(fakes.board, "stm", None)
    b = make_board(fakes)
    assert b.up.base is None
    assert b.up.hw_de(True, 4, 2) is False
    b.up.de(1)
    assert FakePin.instances["UP_DE"].level == 1
    b.up.de(0)
    assert FakePin.instances["UP_DE"].level == 0


# --- receive path ------------------------------------------------------------------------
def test_uart_opened_with_large_rxbuf_and_hard_idle_irq(fakes):
    make_board(fakes)
    for uid in (2, 3):
        u = FakeUART.instances[uid]
        assert u.kw["rxbuf"] >= 1024
        assert u.kw["baudrate"] == 115200
        assert u.trigger == FakeUART.IRQ_RXIDLE and u.hard is True


def test_idle_irq_moves_bursts_into_the_ring(fakes):
    b = make_board(fakes)
    u = FakeUART.instances[2]
    data = bytes(range(256)) * 3 + b"\xaa\xcc\x01\x01\xc1\xe0\xaa\xee"  # > SCRATCH bytes
    u.receive(data)
    assert u.any() == 0
    assert b.up.any() == len(data)
    out = bytearray(1024)
    n = b.up.readinto(out, 1024)
    assert bytes(out[:n]) == data
    assert b.up.t_last == b.up.ring.t_last
    assert FakePin.instances["LED_TRAFFIC"].level == 1


def test_ring_overflow_is_counted_not_silent(fakes):
    b = make_board(fakes)
    u = FakeUART.instances[3]
    cap = b.down.ring.capacity()
    u.receive(b"\x55" * (cap + 100))
    assert b.down.any() == cap
    assert b.down.overflows == 100


def test_long_burst_without_idle_is_pumped_with_irqs_off(fakes):
    b = make_board(fakes)
    u = FakeUART.instances[2]
    u.pending += b"\x11" * fakes.board.PUMP_AT  # no idle interrupt yet
    assert b.up.any() == fakes.board.PUMP_AT
    assert fakes.irq_calls == ["off", ("on", 7)]
    assert b.up.pumps == 1


def test_irq_handler_builds_no_objects(fakes):
    """The handler bytecode has no container/slice/format/closure/keyword-call ops,
    and calls only the bound methods stored once in __init__."""
    bd = fakes.board
    code = bd.Port._on_rx_idle.__code__
    banned = ("BUILD_", "SLICE", "FORMAT", "MAKE_FUNCTION", "CALL_FUNCTION_KW", "CALL_KW", "KW_NAMES", "LIST_", "DICT_")
    ops = [ins.opname for ins in dis.get_instructions(code)]
    assert not [op for op in ops if any(op.startswith(b) or b in op for b in banned)]
    assert not [c for c in code.co_consts if isinstance(c, (float, str, tuple)) and c != code.co_consts[0]]
    b = make_board(fakes)
    port = b.up
    stored = (port._uart_any, port._uart_readinto, port._ring_write, port._scratch)
    for _ in range(3):
        FakeUART.instances[2].receive(b"\x01\x02\x03")
    assert (port._uart_any, port._uart_readinto, port._ring_write, port._scratch) == stored
    # Every method the handler calls is reached through self._x, never self.a.b(...).
    attrs = [ins.argval for ins in dis.get_instructions(code) if ins.opname in ("LOAD_ATTR", "LOAD_METHOD")]
    assert {"_uart_any", "_uart_readinto", "_ring_write", "_scratch", "_led"} <= set(attrs)
    assert "ring" not in attrs and "uart" not in attrs


def test_write_passes_length_without_slicing(fakes):
    b = make_board(fakes)
    buf = bytearray(b"\xaa\xcc\x01\x01\xc1\xe0\xaa\xee" + b"\x00" * 20)
    b.down.write(buf, 0, 8)
    assert FakeUART.instances[3].sent == [b"\xaa\xcc\x01\x01\xc1\xe0\xaa\xee"]
    assert b.down.tx_blocks is True


# --- jig I/O, watchdog ------------------------------------------------------------------
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


# --- safe boot ---------------------------------------------------------------------------
def test_safe_boot_decision(fakes):
    bd = fakes.board
    assert bd.decide_boot(False, 0) == bd.MODE_BRIDGE
    assert bd.decide_boot(True, 0) == bd.MODE_SAFE_BUTTON
    assert bd.decide_boot(False, bd.SAFE_AFTER_CRASHES - 1) == bd.MODE_BRIDGE
    assert "3 times" in bd.decide_boot(False, 3)


def test_safe_button_debounced(fakes, monkeypatch):
    bd = fakes.board
    monkeypatch.setattr(bd, "sleep_ms", lambda ms: None)
    FakePin.levels = {"BTN_SAFE": 0}
    assert bd.safe_button_held("STM32H7_JIG") is True
    FakePin.levels = {"BTN_SAFE": 1}
    assert bd.safe_button_held("STM32H7_JIG") is False
    FakePin.levels = {"PC13": 1}  # NUCLEO user button is active high
    assert bd.safe_button_held("NUCLEO_H743ZI") is True


# --- crash log -----------------------------------------------------------------------------
def test_crash_log_counts_streak_and_clears(fakes):
    bd = fakes.board
    path = str(fakes.tmp / "crash.txt")
    try:
        raise ValueError("boom")
    except ValueError as e:
        assert bd.record_crash(e, (("forwards", 12), ("replies", 11)), 1234, path=path) == (1, 1, 0)
    text = bd.read_crash_log(path)
    assert "ValueError: boom" in text and "forwards=12" in text and "1234 ms" in text
    assert bd.record_crash(wdt=True, path=path) == (2, 2, 1)
    assert bd.parse_crash_counts(bd.read_crash_log(path)) == (2, 2, 1)
    assert "watchdog reset" in bd.crash_summary(path)
    assert bd.clear_crash_streak(path) is True
    assert bd.parse_crash_counts(bd.read_crash_log(path)) == (2, 0, 1)
    assert bd.clear_crash_streak(path) is False


def test_crash_log_missing_or_garbage(fakes):
    bd = fakes.board
    path = str(fakes.tmp / "none.txt")
    assert bd.parse_crash_counts(bd.read_crash_log(path)) == (0, 0, 0)
    assert bd.crash_summary(path) == "no crash recorded"
    assert bd.parse_crash_counts("junk\ncrashes=x consecutive=2\n") == (0, 2, 0)


# --- the app on this HAL ----------------------------------------------------------------
def test_app_bridges_on_the_board_hal(fakes, tmp_path):
    """jig.app.App runs on Board: a local answer, a forward and a relayed reply."""
    from jig import frame
    from jig.app import App
    from jig.parser import FrameParser

    b = fakes.board.Board("MotorJig STM32H7_JIG with STM32H743VI")
    b.param_path = str(tmp_path / "jigparams.bin")
    app = App(b)
    pc, drv = FakeUART.instances[2], FakeUART.instances[3]
    de_up = FakePin.instances["UP_DE"]

    pc.receive(frame.encode(1, frame.GET_SLAVE_INFO))
    app.poll()
    assert len(pc.sent) == 1
    p = FrameParser()
    p.feed(pc.sent[0])
    assert p.ready and p.slave == 1 and p.ftype == frame.GET_SLAVE_INFO and p.body[p.data_start] == 0
    assert de_up.writes[-2:] == [1, 0]  # software DE around the reply

    request = frame.encode(2, frame.GET_AXIS_STATUS)
    reply = frame.encode(2, frame.GET_AXIS_STATUS, b"\x00\x00\x00\x00\x08")
    pc.receive(request)
    app.poll()
    assert b"".join(drv.sent) == request  # cut through: header+id first, the rest as it came
    n_pc = len(pc.sent)
    drv.receive(reply)
    app.poll()
    assert b"".join(pc.sent[n_pc:]) == reply
    assert b.wdt is not None and b.wdt.feeds >= 1


# --- main.py ---------------------------------------------------------------------------------
def load_main(fakes, monkeypatch, tmp_path):
    import importlib.util
    import os

    monkeypatch.setattr(fakes.board, "CRASH_PATH", str(tmp_path / "crash.txt"))
    monkeypatch.setattr(fakes.board, "PARAM_PATH", str(tmp_path / "jigparams.bin"))
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "firmware", "main.py")
    spec = importlib.util.spec_from_file_location("jig_main_under_test", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # runs main() itself: machine is the fake here
    return mod


def test_main_safe_boot_when_button_held(fakes, monkeypatch, tmp_path):
    FakePin.levels = {"BTN_SAFE": 0}
    mod = load_main(fakes, monkeypatch, tmp_path)  # the import-time run: safe boot
    assert mod.main() == fakes.board.MODE_SAFE_BUTTON
    assert FakeUART.instances == {}  # no port opened: both transceivers stay receiving
    assert FakePin.instances["LED_ERR"].level == 1
    assert FakeWDT.created == 0


def test_main_safe_boot_after_a_crash_streak(fakes, monkeypatch, tmp_path):
    FakePin.levels = {"BTN_SAFE": 0}
    mod = load_main(fakes, monkeypatch, tmp_path)
    FakePin.levels = {"BTN_SAFE": 1}
    for _ in range(fakes.board.SAFE_AFTER_CRASHES):
        fakes.board.record_crash(RuntimeError("x"))
    assert "crashed 3 times" in mod.main()


def test_main_logs_a_crash_and_resets(fakes, monkeypatch, tmp_path):
    from jig.app import App

    FakePin.levels = {"BTN_SAFE": 0}
    mod = load_main(fakes, monkeypatch, tmp_path)
    FakePin.levels = {"BTN_SAFE": 1}

    def run(self):
        self.poll()
        raise RuntimeError("bridge fell over")

    monkeypatch.setattr(App, "run", run)
    assert mod.main() == "crashed"
    assert fakes.machine.resets == [1]
    log = fakes.board.read_crash_log()
    assert "RuntimeError: bridge fell over" in log and "up_frames_in=0" in log
    assert fakes.board.parse_crash_counts(log) == (1, 1, 0)


def test_main_ctrl_c_keeps_the_watchdog_fed(fakes, monkeypatch, tmp_path):
    from jig.app import App

    FakePin.levels = {"BTN_SAFE": 0}
    mod = load_main(fakes, monkeypatch, tmp_path)
    FakePin.levels = {"BTN_SAFE": 1}

    def run(self):
        self.poll()
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
