"""Plus-R bus master for PCs: the vendor library's function set over any pyserial port.

    from motorjig.master import Master
    with Master("/dev/ttyUSB0", baud=115200) as m:      # or "socket://127.0.0.1:5000", "COM7"
        m.servo_enable(2, True)
        m.move_inc(2, 10000, 5000)
        print(m.get_all_status(2))

Every request is encoded with ``jig.frame`` and every reply is read with
``jig.parser.FrameParser`` -- the firmware's own modules; there is no second
encoder, CRC or parser on the host side.

Ver6 or Ver8 is decided per slave, as FASTECH's own host library does it, at
first contact (or ``scan``): a Ver6-format GetCommandPos probe ``id 51 crc``; a
normal Ver6 reply (``id 51 00 pos32``) means Ver6; a Ver8-layout frame-type error
(``id, 0x51, crcL, 0x80``: a Ver8 drive reads the probe's first three bytes as
id / sync / type) means Ver8, confirmed by a Ver8 GetCommandPos with sync 0xF1;
from then on each Ver8 request to that slave carries the next sync number
(0xF2, ...). ``ver8=True`` / ``ver8=False`` skip the detection and use one
framing for every slave. One bus may carry both variants.

A reply is the first good frame with the same slave id and frame type (and, in
Ver8 framing, the same sync number) as the request; anything else on the line
(a stale reply, the echo of our own request with ``echo=True``) is skipped. No reply within the
timeout raises ``NoReplyError`` (``ReplyCRCError`` when only frames with a bad
CRC came). A non-zero status byte raises the ``StatusError`` subclass for that
code; a reply whose length does not fit the frame type raises ``BadReplyError``.

Timeouts follow the vendor library: 100 ms by default, five times that for
ROM and servo-on frames, 15x for ClearPosition, 20x for PosTableWriteROM.
Failed requests are re-sent (``retries`` times) only for frames that are
harmless to repeat: reads, stops, parameter and I/O writes, alarm resets --
never motion starts.
"""

import socket
import time
from collections import namedtuple

import serial

from jig import diag as D
from jig import frame as F
from jig.compat import ticks_diff
from jig.parser import FrameParser

from motorjig import names as N
from motorjig.errors import (BadReplyError, JigError, NoReplyError, PortError, ReplyCRCError,
                             StatusError, status_error)

DEFAULT_TIMEOUT = 0.1  # seconds, the vendor library's COMM_WAITTIME
DEFAULT_BAUD = 115200
#: baud rates Plus-R drives are commonly set to (the manual page is unconfirmed)
BAUD_RATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)

#: frame types whose reply may take longer (multiplier of the per-call timeout)
TIMEOUT_FACTOR = {
    F.SAVE_ALL_PARAMETERS: 5,
    F.GET_ROM_PARAMETER: 5,
    F.IO_ASSIGN_MAP_READ_ROM: 5,
    F.SERVO_ENABLE: 5,
    F.POS_TABLE_READ_ROM: 5,
    F.CLEAR_POSITION: 15,
    F.POS_TABLE_WRITE_ROM: 20,
}

#: frame types that are harmless to send twice, so a failed attempt is retried
IDEMPOTENT = frozenset((
    F.GET_SLAVE_INFO, F.GET_MOTOR_INFO, F.GET_FIRMWARE_INFO, F.GET_ROM_PARAMETER, F.SET_PARAMETER,
    F.GET_PARAMETER, F.SET_IO_OUTPUT, F.SET_IO_INPUT, F.GET_IO_INPUT, F.GET_IO_OUTPUT,
    F.SET_IO_ASSIGN_MAP, F.GET_IO_ASSIGN_MAP, F.IO_ASSIGN_MAP_READ_ROM, F.TRIGGER_OUTPUT_STATUS,
    F.SERVO_ENABLE, F.SERVO_ALARM_RESET, F.STEP_ALARM_RESET, F.GET_ALARM_TYPE, F.MOVE_STOP,
    F.EMERGENCY_STOP, F.GET_AXIS_STATUS, F.GET_IO_AXIS_STATUS, F.GET_MOTION_STATUS,
    F.GET_ALL_STATUS, F.SET_COMMAND_POS, F.GET_COMMAND_POS, F.SET_ACTUAL_POS, F.GET_ACTUAL_POS,
    F.GET_POS_ERROR, F.GET_ACTUAL_VEL, F.CLEAR_POSITION, F.MOVE_PAUSE, F.POS_TABLE_READ_ITEM,
    F.POS_TABLE_WRITE_ITEM, F.POS_TABLE_READ_ROM, F.POS_TABLE_READ_ONE_ITEM,
    F.POS_TABLE_WRITE_ONE_ITEM, F.GET_PUSH_STATUS,
    D.READ_COUNTERS, D.RESET_COUNTERS, D.START_BUS_SCAN, D.GET_BUS_SCAN_RESULT, D.READ_CRASH_LOG,
    # the jig's sampler: a repeated StartTrace restarts it, a repeated ReadTrace (same
    # from-index) returns the same samples
    D.START_TRACE, D.STOP_TRACE, D.READ_TRACE, D.GET_TRACE_STATUS, D.READ_TRANSACTION_TIMES,
    D.READ_CAN_COUNTERS,
))

VAR = -1  # variable-length reply (info strings)
#: data bytes after the status byte of a good reply (Ver6), for the length check
REPLY_LEN = {
    F.GET_SLAVE_INFO: VAR, F.GET_MOTOR_INFO: VAR, F.GET_FIRMWARE_INFO: 1,
    F.SAVE_ALL_PARAMETERS: 0, F.GET_ROM_PARAMETER: 4, F.SET_PARAMETER: 0, F.GET_PARAMETER: 4,
    F.SET_IO_OUTPUT: 0, F.SET_IO_INPUT: 0, F.GET_IO_INPUT: 4, F.GET_IO_OUTPUT: 4,
    F.SET_IO_ASSIGN_MAP: 0, F.GET_IO_ASSIGN_MAP: 5, F.IO_ASSIGN_MAP_READ_ROM: 1,
    F.TRIGGER_OUTPUT_STATUS: 1, F.SERVO_ENABLE: 0, F.SERVO_ALARM_RESET: 0, F.STEP_ALARM_RESET: 0,
    F.GET_ALARM_TYPE: 1, F.MOVE_STOP: 0, F.EMERGENCY_STOP: 0, F.MOVE_ORIGIN: 0, F.MOVE_ABS_POS: 0,
    F.MOVE_INC_POS: 0, F.MOVE_TO_LIMIT: 0, F.MOVE_VELOCITY: 0, F.POSITION_ABS_OVERRIDE: 0,
    F.POSITION_INC_OVERRIDE: 0, F.VELOCITY_OVERRIDE: 0, F.GET_AXIS_STATUS: 4,
    F.GET_IO_AXIS_STATUS: 12, F.GET_MOTION_STATUS: 20, F.GET_ALL_STATUS: 32, F.SET_COMMAND_POS: 0,
    F.GET_COMMAND_POS: 4, F.SET_ACTUAL_POS: 0, F.GET_ACTUAL_POS: 4, F.GET_POS_ERROR: 4,
    F.GET_ACTUAL_VEL: 4, F.CLEAR_POSITION: 0, F.MOVE_PAUSE: 0, F.POS_TABLE_READ_ITEM: 64,
    F.POS_TABLE_WRITE_ITEM: 1, F.POS_TABLE_READ_ROM: 1, F.POS_TABLE_WRITE_ROM: 1,
    F.POS_TABLE_RUN_ITEM: 0, F.POS_TABLE_READ_ONE_ITEM: 4, F.GET_PUSH_STATUS: 1,
    F.MOVE_ABS_POS_EX: 0, F.MOVE_INC_POS_EX: 0, F.MOVE_VELOCITY_EX: 0,
    # the jig's diagnostic frames (jig.diag)
    D.READ_COUNTERS: VAR, D.RESET_COUNTERS: 0, D.START_BUS_SCAN: 0,
    D.GET_BUS_SCAN_RESULT: D.SCAN_REPLY_LEN - 1, D.READ_CRASH_LOG: VAR,
    # (the sampler's frames: the single-drive reply, or a drive of the set's)
    D.START_TRACE: (6, D.TRACE_JOIN_REPLY_LEN - 1),
    D.STOP_TRACE: (D.TRACE_STATUS_REPLY_LEN - 1, D.TRACE_DRIVE_STATUS_REPLY_LEN - 1), D.READ_TRACE: VAR,
    D.GET_TRACE_STATUS: (D.TRACE_STATUS_REPLY_LEN - 1, D.TRACE_DRIVE_STATUS_REPLY_LEN - 1),
    D.READ_TRANSACTION_TIMES: VAR,
    D.READ_CAN_COUNTERS: VAR, D.TAKE_SAFETY_NOTICE: D.SAFETY_NOTICE_LEN,
}
#: data bytes of a request (Ver6); the monitor tells requests from replies with it
REQUEST_LEN = {
    F.GET_SLAVE_INFO: 0, F.GET_MOTOR_INFO: 0, F.GET_FIRMWARE_INFO: 0, F.SAVE_ALL_PARAMETERS: 0,
    F.GET_ROM_PARAMETER: 1, F.SET_PARAMETER: 5, F.GET_PARAMETER: 1, F.SET_IO_OUTPUT: 8,
    F.SET_IO_INPUT: 8, F.GET_IO_INPUT: 0, F.GET_IO_OUTPUT: 0, F.SET_IO_ASSIGN_MAP: 6,
    F.GET_IO_ASSIGN_MAP: 1, F.IO_ASSIGN_MAP_READ_ROM: 0, F.TRIGGER_OUTPUT_RUN_A: 18,
    F.TRIGGER_OUTPUT_STATUS: 0, F.SERVO_ENABLE: 1, F.SERVO_ALARM_RESET: 0, F.STEP_ALARM_RESET: 1,
    F.GET_ALARM_TYPE: 0, F.MOVE_STOP: 0, F.EMERGENCY_STOP: 0, F.MOVE_ORIGIN: 0, F.MOVE_ABS_POS: 8,
    F.MOVE_INC_POS: 8, F.MOVE_TO_LIMIT: 5, F.MOVE_VELOCITY: 5, F.POSITION_ABS_OVERRIDE: 4,
    F.POSITION_INC_OVERRIDE: 4, F.VELOCITY_OVERRIDE: 4, F.ALL_MOVE_STOP: 0, F.ALL_EMERGENCY_STOP: 0,
    F.ALL_MOVE_ORIGIN: 0, F.ALL_MOVE_ABS_POS: 8, F.ALL_MOVE_INC_POS: 8, F.GET_AXIS_STATUS: 0,
    F.GET_IO_AXIS_STATUS: 0, F.GET_MOTION_STATUS: 0, F.GET_ALL_STATUS: 0, F.SET_COMMAND_POS: 4,
    F.GET_COMMAND_POS: 0, F.SET_ACTUAL_POS: 4, F.GET_ACTUAL_POS: 0, F.GET_POS_ERROR: 0,
    F.GET_ACTUAL_VEL: 0, F.CLEAR_POSITION: 0, F.MOVE_PAUSE: 1, F.POS_TABLE_READ_ITEM: 2,
    F.POS_TABLE_WRITE_ITEM: 66, F.POS_TABLE_READ_ROM: 0, F.POS_TABLE_WRITE_ROM: 0,
    F.POS_TABLE_RUN_ITEM: 2, F.POS_TABLE_READ_ONE_ITEM: 4, F.POS_TABLE_WRITE_ONE_ITEM: 8,
    F.MOVE_PUSH: (26, 28), F.GET_PUSH_STATUS: 0, F.MOVE_ABS_POS_EX: 40, F.MOVE_INC_POS_EX: 40,
    F.MOVE_VELOCITY_EX: 37,
    D.READ_COUNTERS: 0, D.RESET_COUNTERS: 0, D.START_BUS_SCAN: 0, D.GET_BUS_SCAN_RESULT: 0,
    D.READ_CRASH_LOG: 0, D.START_TRACE: (6, 7), D.STOP_TRACE: (0, 1),
    D.READ_TRACE: (3, 4), D.GET_TRACE_STATUS: (0, 1),
    D.READ_TRANSACTION_TIMES: 0, D.READ_CAN_COUNTERS: 0, D.TAKE_SAFETY_NOTICE: 0,
}

#: Ver8 libraries widen the inputs to 64 bits; drives that keep 32 are accepted too
REPLY_LEN_VER8 = dict(REPLY_LEN)
REPLY_LEN_VER8.update({F.GET_IO_INPUT: (4, 8), F.GET_IO_AXIS_STATUS: (12, 16), F.GET_ALL_STATUS: (32, 36)})

SYNC_SEED = 0xF0  # the vendor V8 class starts its per-slave counters here
#: sync numbers of a Ver8 broadcast on a mixed bus: a Ver6 drive reads that byte as its
#: frame type, and the protocol notes list none (not even vendor-internal) in this range
MIXED_BROADCAST_SYNCS = range(0xC0, 0xF0)
POS_TABLE_ITEM_SIZE = 64
_READ_SLICE = 0.005  # seconds one port read may block; bounds the timeout overshoot

Frame = namedtuple("Frame", "slave sync ftype data body t")
Frame.__doc__ = """One checked frame off the line: data excludes id/sync/type/CRC; body is the
unstuffed frame id..CRC; t is time.time() when it completed."""

SlaveInfo = namedtuple("SlaveInfo", "type type_name version")
MotorInfo = namedtuple("MotorInfo", "type text")
Alarm = namedtuple("Alarm", "code name")
IOAssign = namedtuple("IOAssign", "mask level")
MotionStatus = namedtuple("MotionStatus", "command_pos actual_pos pos_error actual_vel pt_number axis",
                          defaults=(None,))
MotionStatus.__doc__ = """GetMotionStatus: Ver6 ends with the running PT number (axis None); Ver8 with
the axis flags instead (pt_number None)."""
IOAxisStatus = namedtuple("IOAxisStatus", "inputs outputs axis")
BusScan = namedtuple("BusScan", "state types")
TraceSample = namedtuple("TraceSample", "t_us command_pos actual_pos actual_vel axis")
TraceSample.__doc__ = """One sample of the jig's own trace (``Master.trace_read``): t_us is the jig's
clock in µs since StartTrace (unfolded from its 30-bit ticks), the time the jig began sending
that GetAllStatus request; axis is the AxisStatus word."""
TransactionTime = namedtuple("TransactionTime", "slave b1 request_end reply_end round_trip_us")
AllStatus = namedtuple("AllStatus", "inputs outputs axis command_pos actual_pos pos_error actual_vel "
                                    "pt_number")


class AxisStatus(int):
    """The u32 axis-status word, with every flag readable by name.

    ``st.motioning``, ``st.servo_on``, ``st.flags`` (names of the set flags),
    ``st.errors`` (the set flags that mean trouble).
    """

    def __getattr__(self, name):
        bit = N.AXIS_FLAG_BITS.get(name)
        if bit is None:
            raise AttributeError(name)
        return bool(int(self) >> bit & 1)

    @property
    def flags(self):
        return N.bit_names(int(self), N.AXIS_FLAGS)

    @property
    def errors(self):
        return [n for n in self.flags if n in N.AXIS_ERROR_FLAGS]

    def __repr__(self):
        return "AxisStatus(0x%08X: %s)" % (int(self), ", ".join(self.flags) or "-")


def jsonable(value):
    """Results as plain JSON types (namedtuples -> dicts, AxisStatus -> value + flags)."""
    if isinstance(value, AxisStatus):
        return {"value": int(value), "flags": value.flags}
    if hasattr(value, "_asdict"):
        return {k: jsonable(v) for k, v in value._asdict().items()}
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (bytes, bytearray)):
        return value.hex(" ")
    return value


def _i32(value):
    if not -0x80000000 <= value <= 0x7FFFFFFF:
        raise ValueError("%d does not fit a signed 32-bit field" % value)
    return value


def _u32(value):
    if not 0 <= value <= 0xFFFFFFFF:
        raise ValueError("%d does not fit an unsigned 32-bit field" % value)
    return value


def pack(*fields):
    """Little-endian data from (kind, value) pairs; kind is 'u8', 'u16', 'i32', 'u32' or 'u64'."""
    out = bytearray()
    for kind, value in fields:
        value = int(value)
        if kind == "u8":
            if not 0 <= value <= 0xFF:
                raise ValueError("%d does not fit a byte" % value)
            out.append(value)
        elif kind == "u16":
            if not 0 <= value <= 0xFFFF:
                raise ValueError("%d does not fit an unsigned 16-bit field" % value)
            b = bytearray(2)
            F.put_u16(b, 0, value)
            out += b
        elif kind == "u64":
            if not 0 <= value <= 0xFFFFFFFFFFFFFFFF:
                raise ValueError("%d does not fit an unsigned 64-bit field" % value)
            out += bytes((value >> (8 * i)) & 0xFF for i in range(8))
        else:
            b = bytearray(4)
            F.put_u32(b, 0, _i32(value) if kind == "i32" else _u32(value))
            out += b
    return bytes(out)


def _check_slave(slave):
    if not (0 <= slave <= F.MAX_SLAVE_ID):
        raise ValueError("slave id must be 0..%d, not %d" % (F.MAX_SLAVE_ID, slave))


def _open_error(url, exc):
    """One sentence for a pyserial open failure."""
    text = str(exc)
    low = text.lower()
    if "lock" in low or "busy" in low or "resource temporarily unavailable" in low:
        return PortError("port %s is busy (another program has it open)" % url)
    if "connection refused" in low:
        return PortError("cannot connect to %s: connection refused (is the bench running?)" % url)
    if "no such file" in low or "filenotfound" in low or "cannot find" in low:
        return PortError("port %s does not exist (see `jigctl ports`)" % url)
    if "permission denied" in low or "access is denied" in low:
        return PortError("no permission to open %s (on Linux: add yourself to the dialout group)" % url)
    if "invalid url" in low or "expected" in low or "not known" in low:
        return PortError("%s is not a valid port or URL (%s)" % (url, text.rstrip(".")))
    return PortError("cannot open %s: %s" % (url, text.rstrip(".")))


class Master:
    """A Plus-R bus master on one serial port (or pyserial URL).

    ``timeout`` is the per-call reply timeout in seconds (multiplied for slow frame
    types), ``retries`` how often an idempotent request is re-sent after a failed
    attempt. ``ver8``: None (default) detects each slave's variant at first contact,
    True / False use Ver8 (sync-number byte) / Ver6 framing for every slave. ``trace`` is
    called as ``trace(direction, wire_or_frame)`` for every frame sent ("tx",
    bytes) and received ("rx", Frame) -- the CLI's -v uses it. ``echo=True`` is for
    adapters that hear their own transmissions: the copy of each request is skipped.

    One Master per port, used from one thread at a time.
    """

    def __init__(self, port, baud=DEFAULT_BAUD, timeout=DEFAULT_TIMEOUT, retries=2, ver8=None,
                 trace=None, echo=False, open=True):
        self.url = port
        self.baud = baud
        self.timeout = timeout
        self.retries = retries
        self.ver8 = ver8
        self.trace = trace
        self.echo = echo
        # Finds good frames in either layout; fields are read per slave (_frame).
        self.parser = FrameParser()
        self.parser.max_body = F.MAX_BODY
        self._serial = None
        self._sync = {}
        self._variants = {}  # slave id -> 6 or 8, as detected
        self._rx = b""
        self._rx_pos = 0
        self._trace = None  # the running trace_start's jig, next index and clock unfolding
        if open:
            self.open()

    # --- connection --------------------------------------------------------------
    def open(self):
        if self._serial is not None:
            return self
        if not isinstance(self.baud, int) or self.baud <= 0:
            raise ValueError("baud rate must be a positive integer, not %r" % (self.baud,))
        try:
            self._serial = serial.serial_for_url(self.url, baudrate=self.baud, timeout=_READ_SLICE,
                                                 write_timeout=2.0, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise _open_error(self.url, exc) from None
        return self

    connect = open

    def close(self):
        port, self._serial = self._serial, None
        if port is None:
            return
        sock = getattr(port, "_socket", None)
        if sock is not None and str(self.url).startswith("socket://"):
            # pyserial's socket close() sleeps 0.3 s "for quick reconnects"; a command
            # line tool that opens one connection per run does not need that wait.
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()
            port._socket = None
            port.is_open = False
        else:
            port.close()

    @property
    def is_open(self):
        return self._serial is not None

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    # --- low level ---------------------------------------------------------------
    def _port(self):
        if self._serial is None:
            raise PortError("port %s is not open" % self.url)
        return self._serial

    def last_sync(self, slave):
        """The sync number of the last Ver8 request sent to slave (None: none yet); the jig's
        ReadTransactionTimes names a Ver8 request by it."""
        return self._sync.get(slave)

    def next_sync(self, slave):
        """The sync number for the next Ver8 request to slave (one counter per slave)."""
        if slave == F.BROADCAST_ID:
            used = set(self._sync.values())
            s = (max(self._sync.values()) + 1) & 0xFF if self._sync else SYNC_SEED
            if 6 in self._variants.values():  # Ver6 drives hear it too: no type of theirs
                r = MIXED_BROADCAST_SYNCS
                if s not in r:
                    s = r[0]
                while s in used:
                    s = s + 1 if s + 1 in r else r[0]
            while s in used:
                s = (s + 1) & 0xFF
            for k in self._sync:
                self._sync[k] = s
            return s
        s = (self._sync.get(slave, SYNC_SEED) + 1) & 0xFF
        self._sync[slave] = s
        return s

    def write(self, wire):
        """Put bytes on the line as they are."""
        port = self._port()
        try:
            port.write(wire)
            port.flush()
        except (serial.SerialException, OSError) as exc:
            raise PortError("writing to %s failed: %s" % (self.url, exc)) from None
        if self.trace:
            self.trace("tx", bytes(wire))

    def _read_some(self):
        port = self._port()
        try:
            n = port.in_waiting
            if not n:
                data = port.read(1)  # blocks at most _READ_SLICE (the port's timeout)
                if not data:
                    return b""
                n = port.in_waiting
                return data + (port.read(n) if n else b"")
            return port.read(n)
        except (serial.SerialException, OSError) as exc:
            raise PortError("reading from %s failed: %s" % (self.url, exc)) from None

    def discard_input(self):
        """Drop unread bytes and any partial frame (done before every request)."""
        port = self._port()
        try:
            port.reset_input_buffer()
        except (serial.SerialException, OSError):
            pass
        self._rx = b""
        self._rx_pos = 0
        self.parser.reset()

    # --- variants ----------------------------------------------------------------
    @property
    def variants(self):
        """{slave id: 6 or 8} of the slaves whose variant is known (detected or forced)."""
        return dict(self._variants)

    def _known_ver8(self, slave):
        """True/False when slave's framing is known (forced or detected), else None."""
        if self.ver8 is not None:
            return bool(self.ver8)
        v = self._variants.get(slave)
        return None if v is None else v == 8

    def variant(self, slave):
        """6 or 8: the slave's protocol variant, detected now if not known yet (Ver6
        when the slave gives no recognisable answer: requests then fail as usual)."""
        known = self._known_ver8(slave)
        if known is None:
            self.detect_variant(slave)
            known = self._known_ver8(slave)
        return 8 if known else 6

    def detect_variant(self, slave, timeout=None, retries=None):
        """Run the vendor library's detection on slave: 6, 8, or None (no answer, or an
        answer that is neither a normal Ver6 reply nor a Ver8 frame-type error)."""
        _check_slave(slave)
        if timeout is None:
            timeout = self.timeout
        if retries is None:
            retries = min(self.retries, 1)  # the vendor library sends the probe twice
        probe = _unstuffed_body(slave, F.GET_COMMAND_POS, b"", -1)  # id 51 crcL crcH
        found = None
        for _ in range(1 + retries):
            self.discard_input()
            self.write(F.encode(slave, F.GET_COMMAND_POS))
            try:
                fr = self._await_reply(slave, F.GET_COMMAND_POS, -1, timeout, probe)
            except (NoReplyError, ReplyCRCError):
                continue
            b = fr.body
            if len(b) == 9 and b[2] == F.STATUS_OK:
                found = 6  # id 51 00 pos32: a normal Ver6 reply
            elif len(b) == 6 and b[2] == probe[2] and b[3] == F.STATUS_FRAME_TYPE_ERROR:
                found = 8  # id, sync=51, type=crcL, 80: a Ver8 drive's frame-type error
            break
        if found == 8:
            # The Ver8 probe: sync 0xF1 (the counter's first), echoed in the reply.
            sync = self.next_sync(slave)
            body = _unstuffed_body(slave, F.GET_COMMAND_POS, b"", sync)
            self.discard_input()
            self.write(F.encode(slave, F.GET_COMMAND_POS, b"", sync))
            try:
                self._await_reply(slave, F.GET_COMMAND_POS, sync, timeout, body)
            except (NoReplyError, ReplyCRCError):
                found = None
        if found is not None:
            self._variants[slave] = found
        return found

    def _frame(self, body, t, ver8=None):
        """A Frame from an unstuffed body, read in slave's known layout (Ver6 if unknown)."""
        if ver8 is None:
            ver8 = bool(self._known_ver8(body[0]))
        h = 3 if ver8 and len(body) >= 5 else 2
        return Frame(body[0], body[1] if h == 3 else -1, body[h - 1], body[h:len(body) - 2], body, t)

    def read_frame(self, timeout):
        """The next good frame off the line, or None after timeout seconds."""
        deadline = time.monotonic() + timeout
        p = self.parser
        while True:
            while self._rx_pos < len(self._rx):
                self._rx_pos = p.feed(self._rx, self._rx_pos, len(self._rx))
                if p.ready:
                    fr = self._frame(bytes(p.body[:p.body_len]), time.time())
                    if self.trace:
                        self.trace("rx", fr)
                    return fr
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._rx = self._read_some()
            self._rx_pos = 0

    def frames(self, duration):
        """Yield every good frame seen on the line for duration seconds (None: forever)."""
        end = None if duration is None else time.monotonic() + duration
        while True:
            left = 0.2 if end is None else end - time.monotonic()
            if left <= 0:
                return
            fr = self.read_frame(min(left, 0.2))
            if fr is not None:
                yield fr

    def _await_reply(self, slave, ftype, sync, timeout, sent_body):
        deadline = time.monotonic() + timeout
        crc_before = self.parser.crc_errors
        # Only the first identical frame can be the echo: some OK replies are byte for
        # byte equal to their request (StepAlarmReset 0, ServoEnable 0: "id type 00").
        echo_pending = self.echo
        while True:
            fr = self.read_frame(max(0.0, deadline - time.monotonic()))
            if fr is None:
                name = N.frame_name(ftype)
                if self.parser.crc_errors != crc_before:
                    raise ReplyCRCError("the reply from slave %d to %s failed its CRC (line noise?)"
                                        % (slave, name), slave, ftype)
                raise NoReplyError("no reply from slave %d to %s within %d ms" % (
                    slave, name, round(timeout * 1000)), slave, ftype)
            if echo_pending and fr.body == sent_body:
                echo_pending = False  # our own request, heard back by an echoing adapter
                continue
            # Same id, type (and sync) in the layout we sent, and a status byte; read
            # off the raw body, since the frame's fields follow the slave's known layout.
            b = fr.body
            h = 3 if sync >= 0 else 2
            if len(b) >= h + 3 and b[:h] == sent_body[:h]:
                return self._frame(b, fr.t, sync >= 0)

    def request(self, slave, ftype, data=b"", timeout=None, retries=None, check=True, ver8=None):
        """Send one request and return its reply Frame (``data[0]`` is the status).

        With ``check`` (default) a non-zero status raises its StatusError and the
        reply length is checked against the frame type. ``ver8`` None frames it in the
        slave's variant (detected first if not known); True/False force the framing.
        """
        if slave != F.BROADCAST_ID:
            _check_slave(slave)
        if timeout is None:
            timeout = self.timeout * TIMEOUT_FACTOR.get(ftype, 1)
        if retries is None:
            retries = self.retries
        attempts = 1 + retries if ftype in IDEMPOTENT else 1
        if ver8 is None:
            ver8 = self._broadcast_ver8() if slave == F.BROADCAST_ID else self.variant(slave) == 8
        last = None
        for attempt in range(attempts):
            sync = self.next_sync(slave) if ver8 else -1
            wire = F.encode(slave, ftype, data, sync)
            body = _unstuffed_body(slave, ftype, data, sync)
            self.discard_input()
            self.write(wire)
            try:
                fr = self._await_reply(slave, ftype, sync, timeout, body)
            except (NoReplyError, ReplyCRCError) as exc:
                last = exc
                continue
            if fr.data[0] == F.STATUS_CRC_ERROR and attempt + 1 < attempts:
                continue  # the slave saw our request corrupted: send it again
            if check:
                self._check(fr)
            return fr
        raise last

    def _check(self, fr):
        status = fr.data[0]
        if status != F.STATUS_OK:
            raise status_error(status, fr.slave, fr.ftype, N.frame_name(fr.ftype))
        table = REPLY_LEN_VER8 if fr.sync >= 0 else REPLY_LEN
        want = table.get(fr.ftype)
        got = len(fr.data) - 1
        allowed = want if isinstance(want, tuple) else (want,)
        if want is not None and want != VAR and got not in allowed:
            raise BadReplyError("slave %d replied to %s with %d data bytes, expected %s" % (
                fr.slave, N.frame_name(fr.ftype), got, " or ".join(map(str, allowed))), fr.slave, fr.ftype)
        if want == VAR and got < 1:
            raise BadReplyError("slave %d replied to %s without data" % (fr.slave, N.frame_name(fr.ftype)),
                                fr.slave, fr.ftype)

    def call(self, slave, ftype, data=b"", **kw):
        """request() and return only the reply data after the status byte."""
        return self.request(slave, ftype, data, **kw).data[1:]

    def _broadcast_ver8(self):
        return bool(self.ver8) or (self.ver8 is None and 8 in self._variants.values())

    def broadcast(self, ftype, data=b""):
        """Send a frame to every slave (id 99); no reply is awaited.

        With detection on and both variants known on the bus, it goes out twice: in
        Ver6 (a Ver8 drive reads that as a frame-type error and, as for any broadcast,
        does not answer) and in Ver8 with a sync number that no Ver6 drive takes for a
        frame type of its own."""
        self.discard_input()
        if not self._broadcast_ver8() or (self.ver8 is None and 6 in self._variants.values()):
            self.write(F.encode(F.BROADCAST_ID, ftype, data))
            time.sleep(0.001)
        if self._broadcast_ver8():
            self.write(F.encode(F.BROADCAST_ID, ftype, data, self.next_sync(F.BROADCAST_ID)))
            time.sleep(0.001)

    # --- info / parameters -------------------------------------------------------
    def is_slave_exist(self, slave, timeout=None):
        """True when slave answers GetSlaveInfo (any status) within the timeout; one try
        (after the variant probe, with the same timeout, when the variant is not known)."""
        ver8 = self._known_ver8(slave)
        if ver8 is None:
            ver8 = self.detect_variant(slave, timeout=timeout, retries=0) == 8
        try:
            self.request(slave, F.GET_SLAVE_INFO, timeout=timeout, retries=0, check=False, ver8=ver8)
            return True
        except (NoReplyError, ReplyCRCError):
            return False

    def get_slave_info(self, slave):
        d = self.call(slave, F.GET_SLAVE_INFO)
        return SlaveInfo(d[0], N.slave_type_name(d[0]), _cstr(d[1:]))

    def get_motor_info(self, slave):
        d = self.call(slave, F.GET_MOTOR_INFO)
        return MotorInfo(d[0], _cstr(d[1:]))

    def get_firmware_info(self, slave):
        return self.call(slave, F.GET_FIRMWARE_INFO)[0]

    def save_all_parameters(self, slave):
        self.call(slave, F.SAVE_ALL_PARAMETERS)

    def get_parameter(self, slave, number):
        return F.get_i32(self.call(slave, F.GET_PARAMETER, pack(("u8", number))), 0)

    def get_rom_parameter(self, slave, number):
        return F.get_i32(self.call(slave, F.GET_ROM_PARAMETER, pack(("u8", number))), 0)

    def set_parameter(self, slave, number, value):
        self.call(slave, F.SET_PARAMETER, pack(("u8", number), ("i32", value)))

    # --- I/O -----------------------------------------------------------------------
    def set_io_output(self, slave, set_mask=0, clear_mask=0):
        self.call(slave, F.SET_IO_OUTPUT, pack(("u32", set_mask), ("u32", clear_mask)))

    def set_io_input(self, slave, set_mask=0, clear_mask=0):
        """Virtual inputs; Ver8 drives take 64-bit masks."""
        kind = "u64" if self.variant(slave) == 8 else "u32"
        self.call(slave, F.SET_IO_INPUT, pack((kind, set_mask), (kind, clear_mask)))

    def get_io_input(self, slave):
        d = self.call(slave, F.GET_IO_INPUT)
        return _uint(d, 0, len(d))

    def get_io_output(self, slave):
        return F.get_u32(self.call(slave, F.GET_IO_OUTPUT), 0)

    def get_io_assign_map(self, slave, pin):
        d = self.call(slave, F.GET_IO_ASSIGN_MAP, pack(("u8", pin)))
        return IOAssign(F.get_u32(d, 0), d[4])

    def set_io_assign_map(self, slave, pin, mask, level):
        self.call(slave, F.SET_IO_ASSIGN_MAP, pack(("u8", pin), ("u32", mask), ("u8", level)))

    def io_assign_map_read_rom(self, slave):
        return self.call(slave, F.IO_ASSIGN_MAP_READ_ROM)[0]

    # --- drive control / alarms -----------------------------------------------------
    def servo_enable(self, slave, on=True):
        self.call(slave, F.SERVO_ENABLE, pack(("u8", 1 if on else 0)))

    def servo_alarm_reset(self, slave):
        self.call(slave, F.SERVO_ALARM_RESET)

    def step_alarm_reset(self, slave, assert_reset=True):
        self.call(slave, F.STEP_ALARM_RESET, pack(("u8", 1 if assert_reset else 0)))

    def alarm_reset(self, slave, servo=False):
        """Clear an alarm: ServoAlarmReset on a servo, StepAlarmReset assert + release on a STEP."""
        if servo:
            self.servo_alarm_reset(slave)
        else:
            self.step_alarm_reset(slave, True)
            self.step_alarm_reset(slave, False)

    def get_alarm_type(self, slave):
        code = self.call(slave, F.GET_ALARM_TYPE)[0]
        return Alarm(code, N.ALARM_NAMES.get(code, "unknown alarm %d" % code))

    # --- motion ----------------------------------------------------------------------
    def move_stop(self, slave):
        self.call(slave, F.MOVE_STOP)

    def emergency_stop(self, slave):
        self.call(slave, F.EMERGENCY_STOP)

    def move_pause(self, slave, pause=True):
        self.call(slave, F.MOVE_PAUSE, pack(("u8", 1 if pause else 0)))

    def move_origin(self, slave):
        self.call(slave, F.MOVE_ORIGIN)

    def move_abs(self, slave, position, speed):
        self.call(slave, F.MOVE_ABS_POS, pack(("i32", position), ("u32", speed)))

    def move_inc(self, slave, distance, speed):
        self.call(slave, F.MOVE_INC_POS, pack(("i32", distance), ("u32", speed)))

    def move_to_limit(self, slave, speed, direction):
        """Run towards the limit sensor; direction 1 = +, 0 = -."""
        self.call(slave, F.MOVE_TO_LIMIT, pack(("u32", speed), ("u8", 1 if direction else 0)))

    def move_velocity(self, slave, speed, direction):
        """Jog at speed pps until stopped; direction 1 = +, 0 = -."""
        self.call(slave, F.MOVE_VELOCITY, pack(("u32", speed), ("u8", 1 if direction else 0)))

    def position_abs_override(self, slave, position):
        self.call(slave, F.POSITION_ABS_OVERRIDE, pack(("i32", position)))

    def position_inc_override(self, slave, distance):
        self.call(slave, F.POSITION_INC_OVERRIDE, pack(("i32", distance)))

    def velocity_override(self, slave, speed):
        self.call(slave, F.VELOCITY_OVERRIDE, pack(("u32", speed)))

    def _ex_option(self, accel_ms, decel_ms, ignore_stop_input):
        flags = (1 if ignore_stop_input else 0) | (2 if accel_ms else 0) | (4 if decel_ms else 0)
        return pack(("u32", flags), ("u16", accel_ms or 0), ("u16", decel_ms or 0)) + bytes(24)

    def move_abs_ex(self, slave, position, speed, accel_ms=None, decel_ms=None, ignore_stop_input=False):
        self.call(slave, F.MOVE_ABS_POS_EX, pack(("i32", position), ("u32", speed))
                  + self._ex_option(accel_ms, decel_ms, ignore_stop_input))

    def move_inc_ex(self, slave, distance, speed, accel_ms=None, decel_ms=None, ignore_stop_input=False):
        self.call(slave, F.MOVE_INC_POS_EX, pack(("i32", distance), ("u32", speed))
                  + self._ex_option(accel_ms, decel_ms, ignore_stop_input))

    def move_velocity_ex(self, slave, speed, direction, accdec_ms=None, ignore_stop_input=False):
        """Jog with its own acc/dec time (VELOCITY_OPTION_EX)."""
        flags = (1 if ignore_stop_input else 0) | (2 if accdec_ms else 0)
        self.call(slave, F.MOVE_VELOCITY_EX, pack(("u32", speed), ("u8", 1 if direction else 0), ("u32", flags),
                                                  ("u16", accdec_ms or 0)) + bytes(26))

    # --- all axes (broadcast, no reply) ------------------------------------------------
    def all_move_stop(self):
        self.broadcast(F.ALL_MOVE_STOP)

    def all_emergency_stop(self):
        self.broadcast(F.ALL_EMERGENCY_STOP)

    def all_move_origin(self):
        self.broadcast(F.ALL_MOVE_ORIGIN)

    def all_move_abs(self, position, speed):
        self.broadcast(F.ALL_MOVE_ABS_POS, pack(("i32", position), ("u32", speed)))

    def all_move_inc(self, distance, speed):
        self.broadcast(F.ALL_MOVE_INC_POS, pack(("i32", distance), ("u32", speed)))

    # --- status / position ---------------------------------------------------------------
    def get_axis_status(self, slave):
        return AxisStatus(F.get_u32(self.call(slave, F.GET_AXIS_STATUS), 0))

    def get_io_axis_status(self, slave):
        d = self.call(slave, F.GET_IO_AXIS_STATUS)
        w = len(d) - 8  # 4 (Ver6) or 8 (Ver8) bytes of inputs
        return IOAxisStatus(_uint(d, 0, w), F.get_u32(d, w), AxisStatus(F.get_u32(d, w + 4)))

    def get_motion_status(self, slave):
        fr = self.request(slave, F.GET_MOTION_STATUS)
        d = fr.data[1:]
        last = F.get_u32(d, 16)
        if fr.sync >= 0:  # Ver8: axis flags in place of the PT number
            return MotionStatus(F.get_i32(d, 0), F.get_i32(d, 4), F.get_i32(d, 8), F.get_i32(d, 12), None,
                                AxisStatus(last))
        return MotionStatus(F.get_i32(d, 0), F.get_i32(d, 4), F.get_i32(d, 8), F.get_i32(d, 12), last)

    def get_all_status(self, slave):
        d = self.call(slave, F.GET_ALL_STATUS)
        w = len(d) - 28
        o = w + 8
        return AllStatus(_uint(d, 0, w), F.get_u32(d, w), AxisStatus(F.get_u32(d, w + 4)),
                         F.get_i32(d, o), F.get_i32(d, o + 4), F.get_i32(d, o + 8), F.get_i32(d, o + 12),
                         F.get_u32(d, o + 16))

    def set_command_pos(self, slave, position):
        self.call(slave, F.SET_COMMAND_POS, pack(("i32", position)))

    def get_command_pos(self, slave):
        return F.get_i32(self.call(slave, F.GET_COMMAND_POS), 0)

    def set_actual_pos(self, slave, position):
        self.call(slave, F.SET_ACTUAL_POS, pack(("i32", position)))

    def get_actual_pos(self, slave):
        return F.get_i32(self.call(slave, F.GET_ACTUAL_POS), 0)

    def get_pos_error(self, slave):
        return F.get_i32(self.call(slave, F.GET_POS_ERROR), 0)

    def get_actual_vel(self, slave):
        return F.get_i32(self.call(slave, F.GET_ACTUAL_VEL), 0)

    def clear_position(self, slave):
        self.call(slave, F.CLEAR_POSITION)

    # --- position table (items as raw 64-byte blocks, layout in the protocol notes §5.9) ----
    def pos_table_read_item(self, slave, item):
        return bytes(self.call(slave, F.POS_TABLE_READ_ITEM, pack(("u16", item))))

    def pos_table_write_item(self, slave, item, block):
        if len(block) != POS_TABLE_ITEM_SIZE:
            raise ValueError("a position-table item is %d bytes, not %d" % (POS_TABLE_ITEM_SIZE, len(block)))
        return self.call(slave, F.POS_TABLE_WRITE_ITEM, pack(("u16", item)) + bytes(block))[0] != 0

    def pos_table_read_rom(self, slave):
        return self.call(slave, F.POS_TABLE_READ_ROM)[0] == 0

    def pos_table_write_rom(self, slave):
        return self.call(slave, F.POS_TABLE_WRITE_ROM)[0] == 0

    def pos_table_run_item(self, slave, item):
        self.call(slave, F.POS_TABLE_RUN_ITEM, pack(("u16", item)))

    # --- helpers ---------------------------------------------------------------------------
    def wait_motion_done(self, slave, timeout=10.0, poll=0.02):
        """Poll the axis status until the axis stops moving; returns the last AxisStatus.

        Raises MotionTimeoutError when the axis still moves after timeout seconds.
        """
        end = time.monotonic() + timeout
        while True:
            st = self.get_axis_status(slave)
            if not st.motioning:
                return st
            if time.monotonic() > end:
                raise MotionTimeoutError("slave %d still moving after %.1f s" % (slave, timeout))
            time.sleep(poll)

    def scan(self, ids=range(F.MAX_SLAVE_ID + 1), timeout=None, progress=None):
        """Find the slaves on ids; returns {id: SlaveInfo or None}; ``variants`` has
        each found slave's variant afterwards.

        With detection on, each id gets the vendor's Ver6-format probe (one try) and
        a slave that answers it recognisably is then asked GetSlaveInfo in its own
        variant; with a forced variant, GetSlaveInfo in that framing (one try). A
        slave that replies with an error status is listed with None as its info.
        ``progress(id, found_so_far)`` is called before each probe.
        """
        found = {}
        for i in ids:
            if progress:
                progress(i, dict(found))
            if self.ver8 is None:
                self._variants.pop(i, None)  # a scan looks again
                if self.detect_variant(i, timeout=timeout, retries=0) is None:
                    continue
            try:
                fr = self.request(i, F.GET_SLAVE_INFO, timeout=timeout, retries=0, check=False)
            except (NoReplyError, ReplyCRCError):
                continue
            try:
                self._check(fr)
                d = fr.data[1:]
                found[i] = SlaveInfo(d[0], N.slave_type_name(d[0]), _cstr(d[1:]))
            except JigError:
                found[i] = None
        return found

    # --- the jig's own frames (slave 1 by default; layouts in jig.diag) ---------------------
    def _jig_reply(self, jig, ftype, decode, name, data=b""):
        """Request ftype from the jig and decode its reply data with jig.diag's decode."""
        fr = self.request(jig, ftype, data)
        try:
            return decode(fr.data)
        except ValueError as exc:
            raise BadReplyError("slave %d sent a bad %s reply (%s)" % (jig, name, exc), jig, ftype) from None

    def read_counters(self, jig=1):
        """The jig's counters as {name: value} (0xF0), decoded by jig.diag.decode_counters."""
        return self._jig_reply(jig, D.READ_COUNTERS, D.decode_counters, "ReadCounters")

    def can_counters(self, jig=1):
        """The jig's CAN port figures as {name: value} (0xFA ReadCanCounters), decoded by
        jig.diag.decode_can_counters; {} from a jig without a CAN port. ResetCounters
        resets them too."""
        return self._jig_reply(jig, D.READ_CAN_COUNTERS, D.decode_can_counters, "ReadCanCounters")

    def reset_counters(self, jig=1):
        self.call(jig, D.RESET_COUNTERS)

    def take_safety_notice(self, jig=1):
        """What the jig's safety stop did since a PC last asked (0xFB TakeSafetyNotice): None, or
        a dict (jig.diag.decode_safety_notice). Asking clears it: show it to the user. Not
        retried (a lost reply loses the notice, never shows it twice)."""
        return self._jig_reply(jig, D.TAKE_SAFETY_NOTICE, D.decode_safety_notice, "TakeSafetyNotice")

    def start_bus_scan(self, jig=1):
        """Make the jig probe ids 0..15 on its driver bus in the background (0xF2)."""
        self.call(jig, D.START_BUS_SCAN)

    def get_bus_scan_result(self, jig=1):
        """(state, {id: slave type}) of the jig's bus scan (0xF3); state is idle/running/done."""
        return BusScan(*self._jig_reply(jig, D.GET_BUS_SCAN_RESULT, D.decode_scan, "GetBusScanResult"))

    def read_crash_log(self, jig=1):
        """The jig's crash summary (0xF4) as text; '' from a jig whose HAL keeps no crash log."""
        return self._jig_reply(jig, D.READ_CRASH_LOG, D.decode_crash_log, "ReadCrashLog")

    # --- the jig's own sampler (0xF5..0xF8; layouts in jig.diag) ------------------------------
    def trace_start(self, slave, period_us, jig=1, ver8=None):
        """Make the jig poll slave with GetAllStatus every period_us µs on its own clock
        and keep the samples (read them with ``trace_read``). The slave is contacted first
        if this Master has not (the jig samples only drives it has seen answer), and
        polled in its variant (``ver8`` forces one). Returns the jig's ring size in samples."""
        fr = self._start_trace(slave, period_us, jig, ver8, b"")
        try:
            size, t0 = D.decode_trace_start(fr.data)
        except ValueError as exc:
            raise BadReplyError("slave %d sent a bad StartTrace reply (%s)" % (jig, exc), jig, D.START_TRACE) from None
        self._trace = {"jig": jig, "next": 0, "raw": t0, "t": 0}
        return size

    def _start_trace(self, slave, period_us, jig, ver8, extra):
        _check_slave(slave)
        v8 = self.variant(slave) == 8 if ver8 is None else bool(ver8)
        framing = 2 if v8 else 1
        data = pack(("u8", slave), ("u32", period_us), ("u8", framing)) + extra
        try:
            return self.request(jig, D.START_TRACE, data)
        except StatusError as exc:
            if exc.status != F.STATUS_DATA_ERROR or slave == jig:
                raise
            # The jig may not have seen this drive answer since it started (a variant known
            # from before its reset): one request through it, then once more.
            self.request(slave, F.GET_AXIS_STATUS, ver8=v8)
            return self.request(jig, D.START_TRACE, data)

    # A set of drives sampled at once (several slots moving; the station's tracehub reads
    # them). A jig whose sampler knows one drive only answers these with 0x82 (StatusError).
    def trace_join(self, slave, period_us, jig=1, ver8=None):
        """Add slave to the drives the jig samples in turn (StartTrace's join), the others
        sampling on; the sampler starts if it was off (``started``). Returns {ring, tick,
        started, first, next, set}: tick the jig's at the join, first/next the indexes
        held, set the drive ids now sampled."""
        fr = self._start_trace(slave, period_us, jig, ver8, bytes([D.TRACE_JOIN]))
        try:
            return D.decode_trace_join(fr.data)
        except ValueError as exc:
            raise BadReplyError("slave %d sent a bad StartTrace reply (%s)" % (jig, exc), jig, D.START_TRACE) from None

    def trace_leave(self, slave, jig=1):
        """Take slave out of the jig's set (the last one out stops the sampler); returns its
        figures since it joined (``trace_drive_status``)."""
        _check_slave(slave)
        return self._jig_reply(jig, D.STOP_TRACE, D.decode_trace_drive_status, "StopTrace", bytes([slave]))

    def trace_drive_status(self, slave, jig=1):
        """{state, slave, set, period_us, taken, skipped, lost, failed, first, next}: the
        sampler's state and set, and slave's figures since it joined."""
        _check_slave(slave)
        return self._jig_reply(jig, D.GET_TRACE_STATUS, D.decode_trace_drive_status, "GetTraceStatus",
                               bytes([slave]))

    def trace_read_tagged(self, frm, jig=1):
        """One chunk of the set's samples from ring index frm: (state, next index, [(slave,
        tick, command, actual, velocity, flags), ...]), raw 30-bit ticks. Naming frm releases
        the samples before it."""
        fr = self.request(jig, D.READ_TRACE, pack(("u16", frm), ("u8", 0), ("u8", D.TRACE_TAGGED)))
        try:
            return D.decode_trace_chunk_tagged(fr.data)
        except ValueError as exc:
            raise BadReplyError("slave %d sent a bad ReadTrace reply (%s)" % (jig, exc), jig, D.READ_TRACE) from None

    def trace_read(self, jig=None, max_chunks=None):
        """The samples the jig has taken since the last read, as TraceSample tuples (t_us
        since trace_start, wrap-unfolded). Reads chunks until one comes back short
        (``max_chunks`` limits the reads)."""
        tr = self._trace
        if tr is None:
            raise JigError("trace_read before trace_start")
        if jig is None:
            jig = tr["jig"]
        out = []
        reads = 0
        stale = 0
        while max_chunks is None or reads < max_chunks:
            fr = self.request(jig, D.READ_TRACE, pack(("u16", tr["next"]), ("u8", 0)))
            reads += 1
            try:
                _state, nxt, samples = D.decode_trace_chunk(fr.data)
            except ValueError as exc:
                raise BadReplyError("slave %d sent a bad ReadTrace reply (%s)" % (jig, exc), jig, D.READ_TRACE) from None
            if (nxt - len(samples)) & 0xFFFF != tr["next"]:
                # A late reply to an earlier read (one that timed out here and was sent
                # again): Ver6 frames carry no sequence number, the from-index tells.
                stale += 1  # (the next request drops what is queued: this converges)
                if stale > 50:
                    raise BadReplyError("slave %d keeps answering ReadTrace for another index" % jig, jig,
                                        D.READ_TRACE)
                continue
            for raw, cmd, act, vel, flags in samples:
                tr["t"] = self.trace_time_us(raw)
                tr["raw"] = raw
                out.append(TraceSample(tr["t"], cmd, act, vel, AxisStatus(flags)))
            tr["next"] = nxt
            if len(samples) < D.TRACE_CHUNK:
                break
        return out

    def trace_time_us(self, tick):
        """A jig tick (30-bit µs: a sample's, or ReadTransactionTimes') on the running trace's time
        base, µs since trace_start: unfolded from the newest sample read, < 2**29 µs away."""
        tr = self._trace
        if tr is None:
            raise JigError("trace_time_us before trace_start")
        return tr["t"] + ticks_diff(tick, tr["raw"])

    def trace_status(self, jig=1):
        """The jig's sampler: {state, slave, period_us, taken, skipped, lost, failed, first, next}."""
        return self._jig_reply(jig, D.GET_TRACE_STATUS, D.decode_trace_status, "GetTraceStatus")

    def trace_stop(self, jig=None):
        """Stop the jig's sampler; returns its final status (``trace_status``). The samples
        not read yet stay readable with ``trace_read``."""
        if jig is None:
            jig = self._trace["jig"] if self._trace else 1
        return self._jig_reply(jig, D.STOP_TRACE, D.decode_trace_status, "StopTrace")

    def transaction_times(self, jig=1):
        """The jig's clock on the last 16 requests it forwarded (0xF9), oldest first:
        TransactionTime(slave, b1, request_end, reply_end, round_trip_us) -- b1 the frame type
        (Ver6) or sync (Ver8); request_end the jig tick (µs, 30-bit) when the request's last
        stop bit left on the driver bus, reply_end when the reply's last byte came in (None:
        no reply), round_trip_us their difference (None without a reply). This request
        itself is for the jig, so it is not among them."""
        fr = self.request(jig, D.READ_TRANSACTION_TIMES)
        try:
            rows = D.decode_transaction_times(fr.data)
        except ValueError as exc:
            raise BadReplyError("slave %d sent a bad ReadTransactionTimes reply (%s)" % (jig, exc), jig,
                                D.READ_TRANSACTION_TIMES) from None
        return [TransactionTime(s, b1, t0, t1, None if t1 is None else (t1 - t0) & 0x3FFFFFFF)
                for s, b1, t0, t1 in rows]

    def jig_bus_scan(self, jig=1, timeout=5.0, poll=0.05):
        """Start the jig's bus scan and wait for its result."""
        self.start_bus_scan(jig)
        end = time.monotonic() + timeout
        while True:
            res = self.get_bus_scan_result(jig)
            if res.state == "done":
                return res
            if time.monotonic() > end:
                raise MotionTimeoutError("the jig's bus scan did not finish within %.1f s" % timeout)
            time.sleep(poll)


class MotionTimeoutError(JigError):
    """The axis kept moving past the wait timeout."""


def _cstr(b):
    b = bytes(b)
    end = b.find(b"\x00")
    if end >= 0:
        b = b[:end]
    return b.decode("ascii", "replace")


def _uint(buf, off, n):
    v = 0
    for i in range(n):
        v |= buf[off + i] << (8 * i)
    return v


def _unstuffed_body(slave, ftype, data, sync):
    body = bytearray(F.MAX_BODY)
    n = F.build_body(body, slave, ftype, data, 0, -1, sync)
    return bytes(body[:n])


__all__ = ["Master", "Frame", "SlaveInfo", "MotorInfo", "Alarm", "IOAssign", "MotionStatus",
           "IOAxisStatus", "AllStatus", "BusScan", "TraceSample", "TransactionTime", "AxisStatus", "MotionTimeoutError", "StatusError", "jsonable",
           "pack", "BAUD_RATES", "DEFAULT_TIMEOUT"]
