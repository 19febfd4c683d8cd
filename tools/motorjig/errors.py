"""Exceptions of the bus-master library, one class per way a request can fail.

Everything the library raises on purpose derives from ``JigError``, so a caller
(and ``jigctl``) can catch one class and print ``str(exc)``: every message is one
sentence a person understands.

* ``PortError``       the serial port / socket cannot be opened or used.
* ``CommError``       the request went out but no usable reply came back:
  ``NoReplyError`` (timeout, vendor code 6), ``ReplyCRCError`` (a reply arrived
  but failed its CRC, vendor code 7), ``BadReplyError`` (wrong reply length,
  vendor code 8).
* ``StatusError``     the slave answered with a non-zero communication status
  (0x80-0x8B, 0xAA); one subclass per status code, e.g. ``MotionRefusedError``
  for 0x85. ``exc.status`` holds the code.
"""

from jig import frame as F


class JigError(Exception):
    """Base class of every error the bus-master library raises."""


class PortError(JigError):
    """The port could not be opened (unknown, busy, refused) or failed while in use."""


class CommError(JigError):
    """A request got no usable reply."""

    def __init__(self, message, slave=None, ftype=None):
        super().__init__(message)
        self.slave = slave
        self.ftype = ftype


class NoReplyError(CommError):
    """No matching reply arrived within the timeout."""


class ReplyCRCError(CommError):
    """Only replies with a bad CRC arrived within the timeout."""


class BadReplyError(CommError):
    """A reply arrived but its data length does not fit the frame type."""


class StatusError(JigError):
    """The slave replied with a non-zero communication status."""

    status = None
    meaning = "the slave reported an error"

    def __init__(self, status, slave=None, ftype=None, frame_name=None):
        self.status = status
        self.slave = slave
        self.ftype = ftype
        what = frame_name or ("frame type 0x%02X" % ftype if ftype is not None else "the request")
        who = "slave %d" % slave if slave is not None else "the slave"
        super().__init__("%s refused %s: %s (status 0x%02X)" % (who, what, self.meaning, status))


class FrameTypeError(StatusError):
    meaning = "it does not know this frame type"


class DataError(StatusError):
    meaning = "a value is out of range, or a ROM read/write failed"


class FrameFormatError(StatusError):
    meaning = "the frame does not fit the specification (wrong data length?)"


class MotionRefusedError(StatusError):
    meaning = "motion command refused (axis moving or stopping, servo off, or an alarm is active)"


class ResetRefusedError(StatusError):
    meaning = "reset refused (the drive is on, or the reset input holds it)"


class ServoOnRefusedError(StatusError):
    meaning = "servo-on refused"


class ServoOffFailedError(StatusError):
    meaning = "servo-off failed"


class RomAccessError(StatusError):
    meaning = "ROM access error"


class RequestCRCError(StatusError):
    meaning = "the request arrived with a bad CRC (line noise?)"


class UnknownStatusError(StatusError):
    meaning = "unknown status code"


class _ServoOnAlarm(ServoOnRefusedError):
    meaning = "servo-on refused because an alarm is active"


class _ServoOnEstop(ServoOnRefusedError):
    meaning = "servo-on refused because the emergency stop is active"


class _ServoOnPin(ServoOnRefusedError):
    meaning = "servo-on refused because Servo-ON is assigned to an input pin"


STATUS_ERRORS = {
    F.STATUS_FRAME_TYPE_ERROR: FrameTypeError,
    F.STATUS_DATA_ERROR: DataError,
    F.STATUS_FRAME_ERROR: FrameFormatError,
    F.STATUS_MOTION_REFUSED: MotionRefusedError,
    F.STATUS_RESET_REFUSED: ResetRefusedError,
    F.STATUS_SERVO_ON_ALARM: _ServoOnAlarm,
    F.STATUS_SERVO_ON_ESTOP: _ServoOnEstop,
    F.STATUS_SERVO_ON_PIN: _ServoOnPin,
    F.STATUS_SERVO_OFF_FAILED: ServoOffFailedError,
    F.STATUS_ROM_ACCESS_ERROR: RomAccessError,
    F.STATUS_CRC_ERROR: RequestCRCError,
}


def status_error(status, slave=None, ftype=None, frame_name=None):
    """The exception instance for a non-zero status byte."""
    cls = STATUS_ERRORS.get(status, UnknownStatusError)
    return cls(status, slave, ftype, frame_name)


def status_meaning(status):
    """Human text for a status byte (0 included)."""
    if status == F.STATUS_OK:
        return "OK"
    return STATUS_ERRORS.get(status, UnknownStatusError).meaning
