"""The jig's parameter table: ranges, RAM and ROM copies, atomic save to flash.

``TABLE`` is the data the handlers, the docs and the PC tools all read:
``(number, name, unit, min, max, default, when)`` where ``when`` is "immediate"
(applied as soon as SetParameter succeeds) or "restart" (used from the next boot;
SaveAllParameters first).

File format (little-endian)::

    "MJP1" | u8 count | count x i32 value | u16 CRC-16 over everything before it

Saving writes a temporary file and renames it over the old one (atomic on
littlefs), so power loss at any moment leaves either the old or the new file. A
filesystem that cannot rename over an existing file gets remove-then-rename, and
loading falls back to a complete temporary file if the main one is missing. A
missing or corrupt file gives the defaults and is reported (``load`` returns
False; the app counts it). A file with fewer values than ``COUNT`` (written before
parameters were added) loads: the values it has, the defaults for the rest.
"""

from jig import crc as _crc
from jig.compat import const
from jig.frame import get_i32, put_i32, put_u16
from jig.slcan import SLCAN_BITRATES

P_SLAVE_ID = const(0)
P_UP_BAUD = const(1)
P_DOWN_BAUD = const(2)
P_REPLY_TIMEOUT_MS = const(3)
P_INTERBYTE_US = const(4)
P_DE_MODE = const(5)
P_DE_PRE_US = const(6)
P_DE_POST_US = const(7)
P_PROTOCOL = const(8)
P_SAFETY_TIMEOUT_MS = const(9)
P_SAFETY_ACTION = const(10)
P_SCAN_TIMEOUT_MS = const(11)
P_FORWARD_MODE = const(12)
P_CAPTURE = const(13)
P_CAN_BITRATE = const(14)
P_CAN_LISTEN_ONLY = const(15)
P_CAN_TERMINATION = const(16)
P_CAN_BUS_OFF_RESTART_MS = const(17)
P_CAN_SAFETY = const(18)

# forward_mode values
CUT_THROUGH = const(0)  # bytes go on as they arrive (a wire, less the routing)
STORE_AND_FORWARD = const(1)  # only whole, CRC-checked frames go on

IMMEDIATE = "immediate"
RESTART = "restart"

# (number, name, unit, min, max, default, when)
TABLE = (
    (0, "jig_slave_id", "", 0, 15, 1, IMMEDIATE),
    (1, "up_baud", "bps", 9600, 921600, 115200, RESTART),
    (2, "down_baud", "bps", 9600, 921600, 115200, RESTART),
    (3, "reply_timeout_ms", "ms", 1, 1000, 50, IMMEDIATE),
    (4, "interbyte_timeout_us", "us", 100, 100000, 5000, IMMEDIATE),
    (5, "de_mode", "0=software 1=hardware", 0, 1, 0, RESTART),
    (6, "de_pre_us", "us", 0, 1000, 10, IMMEDIATE),
    (7, "de_post_us", "us", 0, 1000, 0, IMMEDIATE),
    (8, "protocol", "0=Ver6 1=Ver8", 0, 1, 0, RESTART),
    (9, "safety_timeout_ms", "ms, 0=off", 0, 60000, 0, IMMEDIATE),
    (10, "safety_action", "0=MoveStop 1=EmergencyStop 2=EmergencyStop+servo off", 0, 2, 0, IMMEDIATE),
    (11, "scan_timeout_ms", "ms", 1, 100, 20, IMMEDIATE),
    (12, "forward_mode", "0=cut-through 1=store-and-forward", 0, 1, 0, RESTART),
    (13, "capture", "0=off 1=record both buses", 0, 1, 0, IMMEDIATE),
    (14, "can_bitrate", "bps", 10000, 1000000, 500000, RESTART),
    (15, "can_listen_only", "0=normal 1=listen only", 0, 1, 0, IMMEDIATE),
    (16, "can_termination", "0=no 1=fit the J4 120 ohm jumper", 0, 1, 1, IMMEDIATE),
    (17, "can_bus_off_restart_ms", "ms, 0=stay off until closed", 0, 60000, 100, IMMEDIATE),
    (18, "can_safety", "0=off 1=NMT stop all 2=CiA 402 quick stop to nodes seen", 0, 2, 0, IMMEDIATE),
)
COUNT = const(19)

# Baud parameters must also be one of these.
BAUD_RATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
# can_bitrate must be one of SLCAN's S0..S8 rates.
CAN_BITRATES = SLCAN_BITRATES

MAGIC = b"MJP1"
FILE_SIZE = const(4 + 1 + 4 * COUNT + 2)


def valid(num, value):
    """True if value is allowed for parameter num."""
    if num < 0 or num >= COUNT:
        return False
    row = TABLE[num]
    if value < row[3] or value > row[4]:
        return False
    if (num == P_UP_BAUD or num == P_DOWN_BAUD) and value not in BAUD_RATES:
        return False
    if num == P_CAN_BITRATE and value not in CAN_BITRATES:
        return False
    return True


class FileFS:
    """The HAL ``fs`` on a real filesystem (MicroPython or CPython): open/os.rename."""

    def read_into(self, path, buf):
        try:
            with open(path, "rb") as f:
                return f.readinto(buf)
        except OSError:
            return -1

    def write(self, path, buf, n):
        with open(path, "wb") as f:
            f.write(memoryview(buf)[0:n])

    def rename(self, src, dst):
        import os

        os.rename(src, dst)

    def remove(self, path):
        import os

        try:
            os.remove(path)
        except OSError:
            pass


class Params:
    def __init__(self, fs=None, path=None):
        self.fs = fs
        self.path = path
        self.ram = [row[5] for row in TABLE]
        self.rom = [row[5] for row in TABLE]
        self.buf = bytearray(FILE_SIZE + 8)  # + room to notice an oversized file

    def get(self, num):
        return self.ram[num]

    def get_rom(self, num):
        return self.rom[num]

    def set(self, num, value):
        """Set the RAM value; False (nothing changed) if num or value is not allowed."""
        if not valid(num, value):
            return False
        self.ram[num] = value
        return True

    def _decode(self, n):
        buf = self.buf
        if n < 7 or buf[0:4] != MAGIC:
            return False
        count = buf[4]
        if n != 4 + 1 + 4 * count + 2 or _crc.crc16(buf, 0, n) != 0:
            return False
        for i in range(COUNT):
            v = TABLE[i][5]
            if i < count:
                x = get_i32(buf, 5 + 4 * i)
                if valid(i, x):
                    v = x
            self.rom[i] = v
            self.ram[i] = v
        return True

    def load(self):
        """Read ROM (and RAM) from the file; defaults and False if missing/corrupt."""
        for i in range(COUNT):
            self.rom[i] = self.ram[i] = TABLE[i][5]
        if self.fs is None:
            return False
        n = self.fs.read_into(self.path, self.buf)
        if self._decode(n):
            return True
        # A save interrupted between remove and rename leaves only the temp file.
        if n < 0:
            n = self.fs.read_into(self.path + ".tmp", self.buf)
            if self._decode(n):
                return True
        return False  # _decode changed nothing: the defaults set above stay

    def encode(self, values):
        """File image of values into self.buf; returns its length."""
        buf = self.buf
        buf[0:4] = MAGIC
        buf[4] = COUNT
        for i in range(COUNT):
            put_i32(buf, 5 + 4 * i, values[i])
        n = 5 + 4 * COUNT
        put_u16(buf, n, _crc.crc16(buf, 0, n))
        return n + 2

    def save(self):
        """Write the RAM values as the new ROM set, atomically. False on a write error."""
        if self.fs is None:
            return False
        n = self.encode(self.ram)
        tmp = self.path + ".tmp"
        try:
            self.fs.write(tmp, self.buf, n)
            try:
                self.fs.rename(tmp, self.path)
            except OSError:
                self.fs.remove(self.path)
                self.fs.rename(tmp, self.path)
        except OSError:
            return False
        for i in range(COUNT):
            self.rom[i] = self.ram[i]
        return True
