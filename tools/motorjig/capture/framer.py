"""Bytes off a bus, with their arrival times, cut into records by the firmware's parser.

``Framer.feed(chunk, t_us)`` runs ``jig.parser.FrameParser`` (the firmware's own
state machine, with its drop and start events switched on) over each chunk and
cuts the stream where the parser's events fall: every good frame, every dropped
fragment (its verdict is the parser counter that moved) and every run of noise
becomes one ``Record`` holding exactly the bytes it had on the wire. Nothing is
lost or counted twice: the records of a stream, joined, are the stream.

Times: a chunk's last byte is taken to have arrived at ``t_us`` and the bytes
before it one character time apart (``byte_us``), so frames that came in one USB
packet still get distinct, ordered times. The parser judges inter-byte gaps on
the same times; a USB adapter that holds bytes back (FTDI's latency timer) makes
gaps look longer than they were, which is why the sniffer's default inter-byte
timeout is longer than the jig's.
"""

from jig import crc as _crc
from jig.compat import TICKS_PERIOD
from jig.frame import MAX_BODY
from jig.parser import COUNTER_NAMES, EV_DROP, EV_FRAME, EV_NONE, EV_START, HEADER, HUNT, FrameParser

from motorjig.capture import record as R

# The drop counters, and the verdict each stands for.
_DROPS = tuple((COUNTER_NAMES.index(c), R.COUNTER_VERDICT[c])
               for c in ("crc_errors", "short", "stuff_errors", "overlong", "timeouts", "resyncs"))
_NOISE = COUNTER_NAMES.index("noise")


def char_time_us(baud):
    """One 8N1 character (10 bits) at baud, in µs."""
    return 10e6 / baud


class Framer:
    """Cuts one bus's byte stream into Records (see the module docstring).

    ``ver8``: None for a bus that may carry both variants (the longest Ver8 body is
    accepted; fields are read later, per frame), True/False for the limits of one
    layout. ``byte_us``: character time for the timestamps and the parser's gap
    measurement (0: bytes of a chunk all arrive at its time, as the capture files say).
    """

    def __init__(self, bus=0, byte_us=0.0, interbyte_timeout_us=5000, ver8=None, direction=R.DIR_UNKNOWN):
        self.bus = bus
        self.direction = direction
        self.byte_us = float(byte_us)
        self.parser = FrameParser(ver8=bool(ver8), interbyte_timeout_us=int(interbyte_timeout_us),
                                  byte_us=int(byte_us), stop_drop=True, start_ev=True)
        if ver8 is None:
            self.parser.max_body = MAX_BODY
        # CPython's CRC builds its two-bytes-a-step table on first use (~12 ms): do it
        # now, not on the first frame, where the delay would look like line silence.
        _crc.crc16(bytearray(2), 0, 2)
        self._raw = bytearray()  # bytes of the record being collected
        self._raw_t = 0  # time of its last byte

    def _record(self, data, t_us, verdict):
        return R.Record(self.bus, int(round(t_us)), self.direction, bytes(data), verdict)

    def feed(self, data, t_us):
        """Records completed by this chunk, whose last byte arrived at t_us (µs)."""
        p = self.parser
        n = len(data)
        # A silence before this chunk ends what came before it first (a frame, or a lone
        # 0xAA that would otherwise join this chunk's bytes in one record); judged as
        # the parser judges it, from the earliest time the chunk's first byte can have come.
        first = t_us - (n - 1) * int(self.byte_us) if n > 1 else t_us
        out = self.check_timeout(first) if p.state != HUNT else []
        now = int(t_us) % TICKS_PERIOD
        i = 0
        while True:
            before = p.counters()
            j = p.feed(data, i, n, now)
            ev = p.event
            if j > i:
                self._raw += data[i:j]
                self._raw_t = t_us - (n - j) * self.byte_us
            t_end = t_us - (n - j) * self.byte_us
            if ev == EV_START:
                # The header's AA CC are the last two bytes; what came before is noise.
                if len(self._raw) > 2:
                    out.append(self._record(self._raw[:-2], t_end - 2 * self.byte_us, R.NOISE))
                del self._raw[:-2]
            elif ev == EV_FRAME:
                out.append(self._record(self._raw, t_end, R.GOOD))
                self._raw = bytearray()
            elif ev == EV_DROP:
                verdict = self._dropped(before, p.counters())
                if verdict == R.RESYNC:  # the new header (AA CC) starts the next frame
                    out.append(self._record(self._raw[:-2], t_end - 2 * self.byte_us, R.RESYNC))
                    del self._raw[:-2]
                else:
                    t = self._raw_t if verdict == R.TIMEOUT else t_end
                    out.append(self._record(self._raw, t, verdict))
                    self._raw = bytearray()
            elif ev == EV_NONE:
                break
            i = j
        self._noise_out(out, t_us)
        return out

    def check_timeout(self, t_us):
        """Records ended by silence: call when no bytes came for a while."""
        p = self.parser
        before = p.counters()
        p.check_timeout(int(t_us) % TICKS_PERIOD)
        after = p.counters()
        out = []
        if p.event == EV_DROP:
            out.append(self._record(self._raw, self._raw_t, self._dropped(before, after)))
            self._raw = bytearray()
        elif after[_NOISE] != before[_NOISE] and self._raw:  # a lone 0xAA timed out
            out.append(self._record(self._raw, self._raw_t, R.NOISE))
            self._raw = bytearray()
        return out

    def flush(self):
        """The end of the capture: what is left, as one record (a frame cut off, or noise)."""
        out = []
        if self._raw:
            verdict = R.UNFINISHED if self.parser.in_frame() else R.NOISE
            out.append(self._record(self._raw, self._raw_t, verdict))
            self._raw = bytearray()
        self.parser.reset()
        return out

    def _noise_out(self, out, t_us):
        """Outside a frame the collected bytes are noise, but for a 0xAA that may start one."""
        p = self.parser
        if p.in_frame() or not self._raw:
            return
        keep = 1 if p.state == HEADER else 0
        if len(self._raw) > keep:
            end = len(self._raw) - keep
            out.append(self._record(self._raw[:end], t_us - keep * self.byte_us, R.NOISE))
            del self._raw[:end]

    @staticmethod
    def _dropped(before, after):
        for index, verdict in _DROPS:
            if after[index] != before[index]:
                return verdict
        raise AssertionError("the parser dropped a frame without counting it")
