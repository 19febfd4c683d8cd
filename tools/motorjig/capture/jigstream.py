"""The jig's own recording of its buses: its record stream read into ``Record``s.

The firmware (``jig.capture``) streams one record per frame it received or sent on
either Plus-R bus or on the CAN bus, and per dropped fragment, over its capture port (the board's second
USB CDC port; a TCP port on the virtual bench). ``JigStream.feed(chunk)`` takes
that stream in pieces of any size and returns the records completed so far, as
``motorjig.capture.record.Record``: bus 0 the PC bus, 1 the driver bus, 2 the
CAN bus (only when the hello says the jig has a CAN port); the
direction relative to the jig; the frame's bytes as they were on the wire
(rebuilt from the body the jig's parser held, see ``wire_bytes``); the verdict;
the end and the start of the frame in µs since the Unix epoch.

A record, little-endian (docs/capture.md, "The jig's record stream")::

    0  u8   0xA5
    1  u8   type: 0..3 a frame on a channel (bit 1 the bus, bit 0 sent by the jig),
            4 / 6 a frame received on the PC / driver bus and passed on to the
            other (cut through), 0x10 hello, 0x11 lost, 0x12 clock,
            0x20 | channel noise, 0x30 / 0x31 a CAN frame received from / sent
            onto the CAN bus
    2  u8   verdict (record.py's codes; 0 for CAN)
    3  u8   n, data bytes that follow the header
    4  u32  t_first, 8 u32 t_end: the jig's µs ticks (wrapping at 2**30)
    (types 4, 6) 12 u32 t_first, 16 u32 t_end on the other bus
    12/20 n data (CAN: u32 identifier, u8 flags, u8 DLC, the data bytes)

Versions: 1 (no CAN) and 2 (CAN records; the hello gains the CAN bitrate) are read;
another is refused in one sentence.

A passed-on frame is one record in the stream and two ``Record``s here, one per
bus (received, then sent), with the same bytes and verdict.

Times: the hello record's tick is anchored to the host's clock when the chunk
holding it arrived; every later tick is unwrapped against the last one, and the
host's arrival time of its chunk picks the wrap count: the latest of tick + k *
2**30 that is not after the arrival by more than ``ARRIVAL_SLACK_US`` (k >= 0:
never backwards). A clock record comes after a second without records, but not
while the jig's ring is full (a stalled reader), so a gap may pass half the
period; a record is placed right while it reaches the host less than a period
(17.9 minutes) after its tick. A record's first tick is its end less
(t_end - t_first) mod 2**30. Relative times are the jig's clock (µs); the absolute
time is off by the latency of the hello's delivery (about a USB frame) and the two
clocks' drift.

A stream must start with a hello (``strict_start``; ``jigctl capture --jig`` skips
what an earlier recording left in the port's buffers instead). A stream that
does not, or that loses step (a record that cannot be one), raises
``StreamError`` once, with the records completed before it in ``.records``; the
reader then skips to the next hello and goes on from there.
"""

import struct

from jig.frame import MAX_BODY, stuff_into
from jig.params import BAUD_RATES

from motorjig.capture import record as R
from motorjig.capture.framer import char_time_us
from motorjig.capture.sniff import HostClock
from motorjig.errors import PortError

MARK = 0xA5
VERSION = 2  # the newest record format this reader knows (the hello's first data byte)
VERSIONS = (1, 2)  # the ones it reads: 1 is 2 without CAN
HEADER_LEN = 12
PASSED_HEADER_LEN = 20  # types 4 and 6: + t_first, t_end on the other bus
T_PC_PASSED, T_DRV_PASSED = 4, 6
T_HELLO, T_LOST, T_CLOCK, T_NOISE = 0x10, 0x11, 0x12, 0x20
T_CAN_IN, T_CAN_OUT = 0x30, 0x31  # received from / sent onto the CAN bus
CAN_HEAD = 6  # a CAN record's data before the frame's bytes: u32 id, u8 flags, u8 DLC
CAN_MAX_BITRATE = 1000000
HELLO_MIN = 20  # hello data before the name (format 1; format 2: HELLO_LEN[2])
HELLO_LEN = {1: 20, 2: 24}
TICKS_PERIOD = 1 << 30
_HALF = TICKS_PERIOD >> 1
#: how far after the chunk's arrival a record's unwrapped time may be (the hello's
#: latency and the clocks' drift) before it is taken for one a period earlier
ARRIVAL_SLACK_US = 5000000
#: the verdicts a frame record may carry (the jig's parser never says noise/unfinished/lost)
FRAME_VERDICTS = (R.GOOD, R.BAD_CRC, R.BAD_STUFFING, R.SHORT, R.OVERLONG, R.TIMEOUT, R.RESYNC)
PROTOCOLS = ("Ver6", "Ver8")
FORWARD_MODES = ("cut-through", "store-and-forward")

# The hello's data: version, protocol, forward_mode, slave id, up_baud, down_baud,
# interbyte_timeout_us, ring size, (format 2) CAN bitrate (0: no CAN port); then the name.
_HELLO = struct.Struct("<BBBBIIII")


class StreamError(PortError):
    """The stream is not (or no longer) the jig's record stream (a port problem for
    jigctl: exit status 3); ``records`` holds what was read before the fault in the
    same chunk, ``offset`` where in the stream it was."""

    def __init__(self, message, records=(), offset=0):
        super().__init__(message)
        self.records = list(records)
        self.offset = offset


def wire_bytes(body, verdict):
    """The bytes a frame record stood for on the wire, rebuilt from the body the jig's
    parser held: header and tail for a whole frame (good, bad CRC, short); no tail for
    one cut off (overlong: the byte that overflowed is not kept; timeout; resync: the
    new header starts the next record); the 0xAA of a stuffing error, without the
    byte after it (not kept either)."""
    wire = bytearray(4 + 2 * len(body))
    end = stuff_into(wire, body, len(body))  # header, stuffed body, tail
    if verdict in (R.GOOD, R.BAD_CRC, R.SHORT):
        return bytes(wire[:end])
    if verdict == R.BAD_STUFFING:
        return bytes(wire[:end - 1])
    return bytes(wire[:end - 2])


def _sdiff(a, b):
    """a - b in ticks, as the nearest of the wrapping values (within half a period)."""
    return ((a - b + _HALF) % TICKS_PERIOD) - _HALF


def parse_hello(data):
    """The hello record's data as a dict (ValueError if it cannot be one; a version this
    reader does not know is read as the newest)."""
    size = HELLO_LEN.get(data[0] if data else 0, HELLO_LEN[VERSION])
    if len(data) < size:
        raise ValueError("a hello record of %d bytes (at least %d)" % (len(data), size))
    version, protocol, forward, slave, up, down, interbyte, ring = _HELLO.unpack_from(data, 0)
    can = struct.unpack_from("<I", data, HELLO_MIN)[0] if size > HELLO_MIN else 0
    return {"version": version, "protocol": protocol, "variant": PROTOCOLS[protocol] if protocol < 2 else "?",
            "forward_mode": forward, "slave_id": slave, "up_baud": up, "down_baud": down,
            "interbyte_timeout_us": interbyte, "ring_size": ring, "can_bitrate": can,
            "name": bytes(data[size:]).decode("ascii", "replace")}


def refusal(name, version):
    """The one sentence about a stream in a record format this reader does not read."""
    return "%s speaks record format %d; this jigctl reads formats %s (update motorjig)" % (
        name, version, " and ".join(str(v) for v in VERSIONS))


def _find_hello(buf, i):
    """Where in buf (from i) a hello record may start: its first bytes A5 10 00, or the
    end of buf less the one or two bytes that may begin them."""
    j = buf.find(b"\xa5\x10\x00", i)
    if j >= 0:
        return j
    n = len(buf)
    if n - i >= 2 and buf[n - 2] == MARK and buf[n - 1] == T_HELLO:
        return n - 2
    if n - i >= 1 and buf[n - 1] == MARK:
        return n - 1
    return n


def _plausible_hello(head, data, any_version=False):
    """True if a record that says it is a hello looks like one (used to find step again)."""
    if head[1] != T_HELLO or head[2] != 0 or head[4] != head[5] or len(data) < HELLO_MIN:
        return False
    if data[0] not in VERSIONS and not any_version:
        return False
    if len(data) < HELLO_LEN.get(data[0], HELLO_LEN[VERSION]):
        return False
    h = parse_hello(data)
    return (h["protocol"] < 2 and h["forward_mode"] < 2 and h["up_baud"] in BAUD_RATES and h["down_baud"] in BAUD_RATES
            and h["can_bitrate"] <= CAN_MAX_BITRATE)


class JigStream:
    """Incremental reader of the jig's record stream (see the module docstring).

    ``where``: the port, for the interfaces' descriptions and the errors. ``clock``:
    has ``now_us()`` (default ``sniff.HostClock``), read when ``feed`` gets no
    ``host_us``. ``strict_start``: the first bytes must be a hello record
    (else StreamError); False skips whatever comes before the first hello.
    """

    def __init__(self, where="", clock=None, strict_start=True):
        self.where = where
        self.clock = clock or HostClock()
        self.strict_start = strict_start
        self.hello = None  # the last hello, as a dict (parse_hello) plus its "tick"
        self.hellos = 0  # hello records read (more than one: the jig restarted recording)
        self.lost = 0  # records the jig reported lost (ring full), in total
        self.noise = [0, 0]  # bytes outside any frame the jig counted, per bus
        self.can_frames = 0  # CAN records read
        self.records = 0  # records returned
        self.bytes = 0  # stream bytes fed
        self.skipped = 0  # stream bytes skipped while looking for a hello
        self.clocks = 0  # clock records read
        self._buf = bytearray()
        self._pos = 0  # stream offset of _buf[0]
        self._hunting = True  # looking for a hello (at the start, and after losing step)
        self._started = False  # a first hello has been seen
        self._ref_tick = None  # the latest tick seen ...
        self._ref_us = None  # ... and its time in µs since the epoch
        self._char = (0.0, 0.0)  # character time per bus, µs
        self._host_us = None  # when the chunk being read arrived

    @property
    def in_step(self):
        return not self._hunting

    @property
    def has_can(self):
        """True if the hello says the jig has a CAN port (a CAN bitrate)."""
        return bool(self.hello and self.hello["can_bitrate"])

    def buses(self, where=None):
        """The PC bus and the driver bus, with the bauds the hello gave (Record.bus 0, 1),
        and the CAN bus (2) when the jig has a CAN port."""
        where = self.where if where is None else where
        h = self.hello or {}
        tag = ("jig " + where) if where else "jig"
        out = [R.pc_bus(h.get("up_baud", 0), tag), R.driver_bus(h.get("down_baud", 0), tag)]
        if self.has_can:
            out.append(R.can_bus(h["can_bitrate"], tag))
        return out

    def description(self):
        """One line about the jig from its hello: name, variant, forwarding, bauds."""
        h = self.hello
        if h is None:
            return "no hello yet"
        return "%s (record format %d, slave id %d, %s, %s), PC bus %d baud, driver bus %d baud%s" % (
            h["name"] or "MotorJig", h["version"], h["slave_id"], h["variant"],
            FORWARD_MODES[h["forward_mode"]] if h["forward_mode"] < 2 else "forward_mode %d" % h["forward_mode"],
            h["up_baud"], h["down_baud"], ", CAN bus %d bit/s" % h["can_bitrate"] if h["can_bitrate"] else "")

    # --- time -------------------------------------------------------------------------
    def _abs(self, tick):
        """µs since the epoch of a jig tick: unwrapped against the latest tick seen, then
        as many periods on as the chunk's arrival says (see the module docstring)."""
        t = self._ref_us + _sdiff(tick, self._ref_tick)
        if self._host_us is not None:
            k = (self._host_us + ARRIVAL_SLACK_US - t) // TICKS_PERIOD
            if k > 0:
                t += k * TICKS_PERIOD
        return t

    def _span(self, end, t_first, t_end):
        """The first tick's time, from the end's (a record's first tick is never after its end)."""
        return end - ((t_end - t_first) % TICKS_PERIOD)

    def _advance(self, tick):
        t = self._abs(tick)
        if t > self._ref_us:
            self._ref_tick = tick
            self._ref_us = t

    # --- reading ----------------------------------------------------------------------
    def feed(self, chunk, host_us=None):
        """The records completed by this chunk of the stream (host_us: when it arrived,
        µs since the epoch; default: the clock now). StreamError if the stream is not in
        step (once per loss of step, with the records read before it; then the reader
        looks for the next hello)."""
        if host_us is None:
            host_us = self.clock.now_us()
        self._host_us = host_us
        self.bytes += len(chunk)
        buf = self._buf
        buf += chunk
        out = []
        error = None
        i = 0
        while True:
            if self._hunting:
                if not self._started and self.strict_start and len(buf) - i >= 2:
                    self.strict_start = False  # said once
                    if buf[i] != MARK or buf[i + 1] != T_HELLO:
                        error = error or (
                            "%s does not start with the jig's hello record (first bytes %s): is it the jig's "
                            "capture port?" % (self._name(), bytes(buf[i:i + 4]).hex(" ").upper()), self._pos + i)
                j = _find_hello(buf, i)
                self.skipped += j - i
                i = j
                if i + HEADER_LEN > len(buf):
                    break
                head = struct.unpack_from("<BBBBII", buf, i)
                n = head[3]
                if n < HELLO_MIN or head[4] != head[5]:
                    i += 1
                    self.skipped += 1
                    continue
                if i + HEADER_LEN + n > len(buf):
                    break  # the rest of a possible hello has not come yet
                data = bytes(buf[i + HEADER_LEN:i + HEADER_LEN + n])
                if data[0] not in VERSIONS and _plausible_hello(head, data, any_version=True):
                    error = error or (refusal(self._name(), data[0]), self._pos + i)
                if not _plausible_hello(head, data):
                    i += 1
                    self.skipped += 1
                    continue
                self._hunting = False
                hlen = HEADER_LEN
            else:
                if i + HEADER_LEN > len(buf):
                    break
                head = struct.unpack_from("<BBBBII", buf, i)
                why = self._bad_header(head)
                if why is not None:
                    self._hunting = True
                    error = error or (why, self._pos + i)
                    continue
                n = head[3]
                hlen = PASSED_HEADER_LEN if head[1] in (T_PC_PASSED, T_DRV_PASSED) else HEADER_LEN
                if i + hlen + n > len(buf):
                    break  # the rest of the record has not come yet
                if hlen != HEADER_LEN:
                    head += struct.unpack_from("<II", buf, i + HEADER_LEN)
                    if max(head[6:]) >= TICKS_PERIOD:
                        self._hunting = True
                        error = error or ("%s is out of step: a record's tick past the jig's 2**30 period"
                                          % self._name(), self._pos + i)
                        continue
                data = bytes(buf[i + hlen:i + hlen + n])
                if head[1] == T_HELLO and data[0] not in VERSIONS:
                    # (checked as the first one is; hunting skips it and goes on to the next hello)
                    self._hunting = True
                    error = error or (refusal(self._name(), data[0]), self._pos + i)
                    continue
                why = self._bad_data(head, data)
                if why is not None:
                    self._hunting = True
                    error = error or (why, self._pos + i)
                    continue
            out += self._records(head, data, host_us)
            i += hlen + n
        del buf[:i]
        self._pos += i
        self.records += len(out)
        if error is not None:
            raise StreamError(error[0], out, error[1])
        return out

    def _name(self):
        return "the stream from %s" % self.where if self.where else "the stream"

    def _bad_header(self, head):
        """Why a record header cannot be one (None if it can)."""
        mark, typ, verdict, n, t0, t1 = head
        where = self._name()
        if mark != MARK:
            return "%s is out of step: 0x%02X where a record's mark 0xA5 should be" % (where, mark)
        if t0 >= TICKS_PERIOD or t1 >= TICKS_PERIOD:
            return "%s is out of step: a record's tick 0x%08X is past the jig's 2**30 period" % (where, max(t0, t1))
        if typ < 4 or typ in (T_PC_PASSED, T_DRV_PASSED):
            if verdict not in FRAME_VERDICTS:
                return "%s is out of step: a frame record with verdict %d" % (where, verdict)
            if n > MAX_BODY:
                return "%s is out of step: a frame record of %d bytes (at most %d)" % (where, n, MAX_BODY)
            return None
        if typ == T_HELLO:
            if n < HELLO_MIN:
                return "%s is out of step: a hello record of %d bytes" % (where, n)
            return None
        if typ == T_LOST or T_NOISE <= typ < T_NOISE + 4:
            return None if n == 4 else "%s is out of step: a record of type 0x%02X with %d bytes (4)" % (where, typ, n)
        if typ == T_CLOCK:
            return None if n == 0 else "%s is out of step: a clock record with %d bytes" % (where, n)
        if typ in (T_CAN_IN, T_CAN_OUT) and self.hello is not None and self.hello["version"] >= 2:
            if verdict != 0:
                return "%s is out of step: a CAN record with verdict %d" % (where, verdict)
            if not CAN_HEAD <= n <= CAN_HEAD + 8:
                return "%s is out of step: a CAN record of %d bytes (%d to %d)" % (where, n, CAN_HEAD, CAN_HEAD + 8)
            return None
        return "%s is out of step: unknown record type 0x%02X" % (where, typ)

    def _bad_data(self, head, data):
        """Why a record's data cannot be its type's (None if it can): a CAN frame's."""
        if head[1] not in (T_CAN_IN, T_CAN_OUT):
            return None
        can_id, flags, dlc = struct.unpack_from("<IBB", data, 0)
        where = self._name()
        if not self.has_can:
            return "%s is out of step: a CAN record from a jig whose hello says it has no CAN port" % where
        if flags > (R.CAN_EXT | R.CAN_RTR) or dlc > 8:
            return "%s is out of step: a CAN record with flags 0x%02X and DLC %d" % (where, flags, dlc)
        if can_id > (0x1FFFFFFF if flags & R.CAN_EXT else 0x7FF):
            return "%s is out of step: a CAN record with identifier 0x%X" % (where, can_id)
        if len(data) != CAN_HEAD + (0 if flags & R.CAN_RTR else dlc):
            return "%s is out of step: a CAN record of %d bytes for DLC %d" % (where, len(data), dlc)
        return None

    def _frame(self, channel, verdict, wire, t0, t1):
        """The Record of a frame on a channel (bit 1 the bus, bit 0 sent by the jig)."""
        bus = channel >> 1
        end = self._abs(t1)
        first = self._span(end, t0, t1)
        if channel & 1:
            # sent: handed to the transmitter at t_first (a first tick not marked: t_end)
            start = first if (t0 != t1 or not wire) else end - int(round(len(wire) * self._char[bus]))
            return R.Record(bus, end, R.DIR_OUTBOUND, wire, verdict, start)
        # received: t_first is the read that brought the header (or, not marked, t_end)
        c = self._char[bus]
        start = int(round(min(first - c, end - len(wire) * c)))
        return R.Record(bus, end, R.DIR_INBOUND, wire, verdict, start)

    def _records(self, head, data, host_us):
        typ, verdict, t0, t1 = head[1], head[2], head[4], head[5]
        if typ == T_HELLO:
            self._on_hello(data, t1, host_us)
            return []
        if self._ref_tick is None:  # (cannot happen: the reader is in step only after a hello)
            return []
        if typ < 4:
            rec = self._frame(typ, verdict, wire_bytes(data, verdict), t0, t1)
            self._advance(t1)
            return [rec]
        if typ in (T_PC_PASSED, T_DRV_PASSED):
            wire = wire_bytes(data, verdict)
            into = typ & 3  # the channel it came in on
            recs = [self._frame(into, verdict, wire, t0, t1), self._frame(into ^ 3, verdict, wire, head[6], head[7])]
            self._advance(t1)
            self._advance(head[7])
            return recs
        end = self._abs(t1)
        first = self._span(end, t0, t1)
        self._advance(t1)
        if typ in (T_CAN_IN, T_CAN_OUT):
            can_id, flags, dlc = struct.unpack_from("<IBB", data, 0)
            self.can_frames += 1
            return [R.Record(R.CAN_BUS, end, R.DIR_OUTBOUND if typ & 1 else R.DIR_INBOUND, data[CAN_HEAD:], R.GOOD,
                             None, None, can_id, flags, dlc)]
        if typ == T_CLOCK:
            self.clocks += 1
            return []
        count = struct.unpack("<I", data)[0]
        if typ == T_LOST:
            self.lost += count
            return [R.Record(0, end, R.DIR_UNKNOWN, b"", R.LOST, first, count)]
        bus = (typ & 3) >> 1
        self.noise[bus] += count
        return [R.Record(bus, end, R.DIR_INBOUND, b"", R.NOISE, None, count)]

    def _on_hello(self, data, tick, host_us):
        h = parse_hello(data)
        h["tick"] = tick
        # Go on with the same timeline where the jig's clock agrees with the host's within
        # a second (the recording restarted); else (the jig restarted, or step was lost for
        # longer than half the tick period) anchor anew.
        if self._ref_tick is None or abs(self._abs(tick) - host_us) > 1000000:
            self._ref_tick, self._ref_us = tick, host_us
        else:
            self._advance(tick)
        self.hello = h
        self.hellos += 1
        self._started = True
        self._char = tuple(char_time_us(b) if b else 0.0 for b in (h["up_baud"], h["down_baud"]))
