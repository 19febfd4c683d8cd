"""Plus-R frame layout: constants, frame-type and status codes, encoding, field access.

Wire layout (Ver6)::

    AA CC | stuffed(slave, type, data..., crc_lo, crc_hi) | AA EE

Ver8 inserts a sync-number byte after the slave id. Every 0xAA between header and
tail, CRC bytes included, is sent twice. The CRC covers the unstuffed bytes before
it. Multi-byte fields in the data are little-endian.

The codes are the ones in the vendor's Ver6 communication manual and library (see
docs/plusr-protocol.md of the shared design notes). Encoding writes into a caller's
buffer so the firmware never allocates per frame; ``encode`` is the allocating
convenience for host code.
"""

from jig import crc as _crc
from jig import mem
from jig.compat import NATIVE, const

# Delimiters
STUFF = const(0xAA)  # the only delimiter byte; doubled inside a frame
HEADER2 = const(0xCC)  # AA CC starts a frame
TAIL2 = const(0xEE)  # AA EE ends a frame

BROADCAST_ID = const(99)
MAX_SLAVE_ID = const(15)
# Data field limit: 248 payload bytes plus the status byte of a reply.
MAX_DATA = const(249)
# Unstuffed body: id, sync (Ver8 only), type, data, 2 CRC bytes.
MAX_BODY = const(254)
# Worst case on the wire: header + every body byte doubled + tail.
MAX_WIRE = const(2 + 2 * MAX_BODY + 2)

# --- Frame types (§5 of the protocol notes) -------------------------------------
GET_SLAVE_INFO = const(0x01)
GET_MOTOR_INFO = const(0x05)
GET_FIRMWARE_INFO = const(0x07)
SAVE_ALL_PARAMETERS = const(0x10)
GET_ROM_PARAMETER = const(0x11)
SET_PARAMETER = const(0x12)
GET_PARAMETER = const(0x13)
SET_IO_OUTPUT = const(0x20)
SET_IO_INPUT = const(0x21)
GET_IO_INPUT = const(0x22)
GET_IO_OUTPUT = const(0x23)
SET_IO_ASSIGN_MAP = const(0x24)
GET_IO_ASSIGN_MAP = const(0x25)
IO_ASSIGN_MAP_READ_ROM = const(0x26)
TRIGGER_OUTPUT_RUN_A = const(0x27)
TRIGGER_OUTPUT_STATUS = const(0x28)
SERVO_ENABLE = const(0x2A)
SERVO_ALARM_RESET = const(0x2B)
STEP_ALARM_RESET = const(0x2C)
GET_ALARM_TYPE = const(0x2E)
MOVE_STOP = const(0x31)
EMERGENCY_STOP = const(0x32)
MOVE_ORIGIN = const(0x33)
MOVE_ABS_POS = const(0x34)
MOVE_INC_POS = const(0x35)
MOVE_TO_LIMIT = const(0x36)
MOVE_VELOCITY = const(0x37)
POSITION_ABS_OVERRIDE = const(0x38)
POSITION_INC_OVERRIDE = const(0x39)
VELOCITY_OVERRIDE = const(0x3A)
ALL_MOVE_STOP = const(0x3B)
ALL_EMERGENCY_STOP = const(0x3C)
ALL_MOVE_ORIGIN = const(0x3D)
ALL_MOVE_ABS_POS = const(0x3E)
ALL_MOVE_INC_POS = const(0x3F)
GET_AXIS_STATUS = const(0x40)
GET_IO_AXIS_STATUS = const(0x41)
GET_MOTION_STATUS = const(0x42)
GET_ALL_STATUS = const(0x43)
SET_COMMAND_POS = const(0x50)
GET_COMMAND_POS = const(0x51)
SET_ACTUAL_POS = const(0x52)
GET_ACTUAL_POS = const(0x53)
GET_POS_ERROR = const(0x54)
GET_ACTUAL_VEL = const(0x55)
CLEAR_POSITION = const(0x56)
MOVE_PAUSE = const(0x58)
POS_TABLE_READ_ITEM = const(0x60)
POS_TABLE_WRITE_ITEM = const(0x61)
POS_TABLE_READ_ROM = const(0x62)
POS_TABLE_WRITE_ROM = const(0x63)
POS_TABLE_RUN_ITEM = const(0x64)
POS_TABLE_IS_DATA = const(0x65)
POS_TABLE_RUN_ONE_ITEM = const(0x68)
POS_TABLE_CHECK_STOP_MODE = const(0x69)
POS_TABLE_READ_ONE_ITEM = const(0x6A)
POS_TABLE_WRITE_ONE_ITEM = const(0x6B)
POS_TABLE_IS_DATA_EX = const(0x6C)
MOVE_PUSH = const(0x78)
GET_PUSH_STATUS = const(0x79)
MOVE_ABS_POS_EX = const(0x80)
MOVE_INC_POS_EX = const(0x81)
MOVE_VELOCITY_EX = const(0x82)

# --- Communication status: first data byte of every reply (§4) ---------------
STATUS_OK = const(0x00)
STATUS_FRAME_TYPE_ERROR = const(0x80)
STATUS_DATA_ERROR = const(0x81)
STATUS_FRAME_ERROR = const(0x82)
STATUS_MOTION_REFUSED = const(0x85)
STATUS_RESET_REFUSED = const(0x86)
STATUS_SERVO_ON_ALARM = const(0x87)
STATUS_SERVO_ON_ESTOP = const(0x88)
STATUS_SERVO_ON_PIN = const(0x89)
STATUS_SERVO_OFF_FAILED = const(0x8A)
STATUS_ROM_ACCESS_ERROR = const(0x8B)
STATUS_CRC_ERROR = const(0xAA)


# --- Little-endian field access --------------------------------------------------
def get_u16(buf, off):
    return buf[off] | (buf[off + 1] << 8)


def get_u32(buf, off):
    return buf[off] | (buf[off + 1] << 8) | (buf[off + 2] << 16) | (buf[off + 3] << 24)


def get_i32(buf, off):
    # Sign-extend through the top byte: no constant wider than a MicroPython small
    # int is involved, so values within +-2**30 never allocate.
    hi = buf[off + 3]
    if hi & 0x80:
        hi -= 256
    return (hi << 24) | (buf[off + 2] << 16) | (buf[off + 1] << 8) | buf[off]


def put_u16(buf, off, value):
    buf[off] = value & 0xFF
    buf[off + 1] = (value >> 8) & 0xFF


def put_u32(buf, off, value):
    """Store a 32-bit value; negative values are stored in two's complement."""
    buf[off] = value & 0xFF
    buf[off + 1] = (value >> 8) & 0xFF
    buf[off + 2] = (value >> 16) & 0xFF
    buf[off + 3] = (value >> 24) & 0xFF


put_i32 = put_u32


# --- Encoding ----------------------------------------------------------------------
def build_body(body, slave, ftype, data=b"", data_start=0, data_end=-1, sync=-1):
    """Write the unstuffed body (id, [sync], type, data, CRC lo, CRC hi) into body.

    ``sync`` >= 0 selects the Ver8 layout. Returns the body length.
    """
    if data_end < 0:
        data_end = len(data)
    n = data_end - data_start
    if n < 0 or n > MAX_DATA:
        raise ValueError("data length out of range")
    if NATIVE is not None and data_start == 0:
        return NATIVE.put_body(body, slave, sync, ftype, data, n, _crc.TABLE)
    body[0] = slave
    pos = 1
    if sync >= 0:
        body[1] = sync
        pos = 2
    body[pos] = ftype
    pos += 1
    mem.copy(body, pos, data, data_start, n)
    pos += n
    c = _crc.crc16(body, 0, pos)
    body[pos] = c & 0xFF
    body[pos + 1] = c >> 8
    return pos + 2


def stuff_into(out, body, body_len, out_off=0):
    """Write header, stuffed body[0:body_len] and tail into out at out_off.

    The body must already end with its CRC. Returns the end offset in out. Runs of
    bytes between 0xAA are copied in one go; only the 0xAA bytes are handled singly
    (on the board the viper loop of jig.native does it all).
    """
    if NATIVE is not None and out_off == 0:
        return NATIVE.stuff(out, body, body_len)
    out[out_off] = STUFF
    out[out_off + 1] = HEADER2
    o = out_off + 2
    i = 0
    while i < body_len:
        j = body.find(b"\xaa", i, body_len)
        if j < 0:
            j = body_len
        n = j - i
        mem.copy(out, o, body, i, n)
        o += n
        if j == body_len:
            break
        out[o] = STUFF
        out[o + 1] = STUFF
        o += 2
        i = j + 1
    out[o] = STUFF
    out[o + 1] = TAIL2
    return o + 2


def encode_into(out, body, slave, ftype, data=b"", sync=-1):
    """Encode a frame into out, using body (MAX_BODY bytes) as scratch; returns length."""
    n = build_body(body, slave, ftype, data, 0, -1, sync)
    return stuff_into(out, body, n)


def encode(slave, ftype, data=b"", sync=-1):
    """Allocating convenience for host code: the wire bytes of one frame."""
    body = bytearray(MAX_BODY)
    out = bytearray(MAX_WIRE)
    n = encode_into(out, body, slave, ftype, bytes(data), sync)
    return bytes(out[:n])
