"""One captured piece of a bus: the record every source produces and every sink takes.

A ``Record`` is what one frame, one dropped fragment or one run of noise looked
like on one bus: the bytes exactly as they were on the wire (header, stuffing and
tail included), the time its last byte arrived, which way it went when that is
known, and the parser's verdict. Sources: ``motorjig.capture.framer`` (a
listen-only adapter framed on the host) and ``motorjig.capture.jigstream`` (the
jig's own recording of both buses), so the pcapng writer, the text view and the
dissector take both alike. The jig's records also know when a frame started
(``t_first_us``), and two of them carry a count instead of bytes: ``noise`` (bytes
the jig's parser counted outside any frame, not recorded) and ``lost`` (records
the jig dropped because its capture ring was full). The jig's CAN records
(``can_id`` set) are frames on the CAN bus: ``data`` their data bytes, ``can_flags``
(``CAN_EXT``, ``CAN_RTR``) and ``can_dlc`` beside them; a CAN controller passes only
good frames, so their verdict is ``good``.

Verdicts are the parser's counters (``jig.parser.COUNTER_NAMES``) seen from one
frame, plus ``unfinished`` for a frame the capture ended in the middle of and
``lost`` for the jig's report of dropped records.
"""

from collections import namedtuple

from jig.parser import COUNTER_NAMES

# Direction relative to the recording device (the jig, or the sniffer's adapter):
# pcapng's EPB flag values. On the PC bus the jig is a slave, so inbound frames are
# requests; on the driver bus it is the master, so outbound frames are requests.
DIR_UNKNOWN = 0
DIR_INBOUND = 1
DIR_OUTBOUND = 2
DIRECTION_NAMES = ("?", "in", "out")

# Verdict codes (stable: the jig's records carry them as one byte, jig.capture V_*).
GOOD = 0
BAD_CRC = 1
BAD_STUFFING = 2
SHORT = 3
OVERLONG = 4
TIMEOUT = 5
RESYNC = 6
NOISE = 7
UNFINISHED = 8
# 9 is left out: the dissector's plusr.problem uses it for "no tail"
LOST = 10

#: code -> (name, text for people)
VERDICTS = {
    GOOD: ("good", "good frame"),
    BAD_CRC: ("bad_crc", "dropped: bad CRC"),
    BAD_STUFFING: ("bad_stuffing", "dropped: stuffing error (0xAA followed by a byte other than AA/CC/EE)"),
    SHORT: ("short", "dropped: too short (less than id, type and CRC)"),
    OVERLONG: ("overlong", "dropped: longer than the protocol allows"),
    TIMEOUT: ("timeout", "dropped: the line went silent inside the frame (inter-byte timeout)"),
    RESYNC: ("resync", "dropped: a new header (AA CC) inside the frame"),
    NOISE: ("noise", "bytes outside any frame"),
    UNFINISHED: ("unfinished", "the capture ended inside this frame"),
    LOST: ("lost", "records the jig dropped: its capture ring was full"),
}
VERDICT_CODES = {name: code for code, (name, _) in VERDICTS.items()}

#: the parser counter each verdict is counted in (jig.parser.COUNTER_NAMES)
VERDICT_COUNTER = {
    GOOD: "good", BAD_CRC: "crc_errors", BAD_STUFFING: "stuff_errors", SHORT: "short",
    OVERLONG: "overlong", TIMEOUT: "timeouts", RESYNC: "resyncs", NOISE: "noise",
}
assert set(VERDICT_COUNTER.values()) == set(COUNTER_NAMES)
COUNTER_VERDICT = {counter: code for code, counter in VERDICT_COUNTER.items()}

#: the start of every packet comment the writer puts in; the dissector reads the word after it
COMMENT_PREFIX = "parser: "
#: the start of the comment with a frame's start: "start: 694 us before the end (...)"
START_PREFIX = "start: "
#: the start of the comment of a count record (noise, lost): "jig: 3 records lost (...)"
JIG_PREFIX = "jig: "


def verdict_name(code):
    return VERDICTS[code][0] if code in VERDICTS else "verdict_%d" % code


def comment(code):
    """The packet comment of a record: 'parser: bad_crc (dropped: bad CRC)'."""
    name, text = VERDICTS.get(code, (verdict_name(code), "unknown verdict"))
    return "%s%s (%s)" % (COMMENT_PREFIX, name, text)


def start_comment(rec):
    """The packet comment with a frame's start (None when it is not known)."""
    if rec.t_first_us is None or rec.count is not None:
        return None
    return "%s%d us before the end (the start bit of the first byte, by the jig's clock)" % (
        START_PREFIX, rec.t_us - rec.t_first_us)


def count_text(rec):
    """What a count record says: '3 records lost (...)', '5 bytes outside any frame (...)'."""
    if rec.count is None:
        return None
    n = rec.count
    if rec.verdict == LOST:
        return "%d record%s lost (the jig's capture ring was full)" % (n, "" if n == 1 else "s")
    return "%d byte%s outside any frame (counted by the jig's parser, not recorded)" % (n, "" if n == 1 else "s")


def count_comment(rec):
    text = count_text(rec)
    return None if text is None else JIG_PREFIX + text


# A CAN frame's flags (the SocketCAN/slcan meaning; the jig's CAN records carry them)
CAN_EXT = 1  # 29-bit identifier
CAN_RTR = 2  # remote request: no data bytes, the DLC asks for that many


class Record(namedtuple("Record", "bus t_us direction data verdict t_first_us count can_id can_flags can_dlc",
                        defaults=(None, None, None, 0, 0))):
    """bus: index into the capture's interface list; t_us: host or jig time of the last
    byte, µs since the Unix epoch; direction: DIR_*; data: wire bytes (a CAN frame: its
    data bytes); verdict: code; t_first_us: the start bit of the first byte, when known
    (the jig's records); count: for the jig's noise and lost records (no data), bytes /
    records counted; can_id, can_flags, can_dlc: a CAN frame's identifier (None: not a
    CAN frame), flags (CAN_EXT, CAN_RTR) and DLC."""

    __slots__ = ()

    @property
    def good(self):
        return self.verdict == GOOD

    @property
    def is_can(self):
        return self.can_id is not None


class Bus(namedtuple("Bus", "name description baud")):
    """One interface of a capture: short name ("pc", "drivers"), text, baud rate."""

    __slots__ = ()


def pc_bus(baud, where=""):
    return Bus("pc", "PC bus, %d baud%s" % (baud, (", " + where) if where else ""), baud)


def driver_bus(baud, where=""):
    return Bus("drivers", "driver bus, %d baud%s" % (baud, (", " + where) if where else ""), baud)


def can_bus(bitrate, where=""):
    return Bus("can", "CAN bus, %d bit/s%s" % (bitrate, (", " + where) if where else ""), bitrate)


#: the buses a listen-only adapter can be on (--sniff --bus)
BUS_NAMES = ("pc", "drivers")
#: the buses of the jig's recording, in Record.bus order (the CAN bus only when the jig has a CAN port)
JIG_BUS_NAMES = ("pc", "drivers", "can")
CAN_BUS = 2


def make_bus(name, baud, where=""):
    return pc_bus(baud, where) if name == "pc" else driver_bus(baud, where)
