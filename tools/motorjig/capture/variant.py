"""Ver6 or Ver8: reading one good frame off a bus whose slaves' variants are not known.

A Ver8 frame has a sync byte after the slave id; nothing else in the frame says
which layout it is. A listener (the sniffer, the dissector) reads the body both
ways and keeps the one that fits the protocol: a request whose data length is
the one its frame type takes, or a reply whose first data byte is a status code
and whose length fits (a non-zero status stands alone, as in the Ver8 drive's
frame-type error to the vendor's Ver6 probe). A 4-byte body can only be Ver6
(``id type crc crc``: a Ver8 frame needs at least id, sync, type, CRC). When
both readings fit or neither does, the slave's variant seen last on that bus
decides (told by a frame of 5 bytes or more: the vendor's 4-byte Ver6 probe
goes to Ver8 drives too), and Ver6 when there is none. The Lua dissector applies this same rule
to the same tables (``luagen`` exports them; a test compares both on every
capture).
"""

from jig import frame as F

from motorjig.master import REPLY_LEN, REPLY_LEN_VER8, REQUEST_LEN, VAR, Frame
from motorjig.names import STATUS_NAMES

#: Ver8 request lengths: SetIOInput takes two u64 masks there (Master.set_io_input)
REQUEST_LEN_VER8 = dict(REQUEST_LEN)
REQUEST_LEN_VER8[F.SET_IO_INPUT] = 16


def fits_request(ftype, data, ver8):
    want = (REQUEST_LEN_VER8 if ver8 else REQUEST_LEN).get(ftype)
    if want is None:
        return False
    return len(data) in want if isinstance(want, tuple) else len(data) == want


def fits_reply(ftype, data, ver8):
    if not data or data[0] not in STATUS_NAMES:
        return False
    if data[0] != F.STATUS_OK:
        return len(data) == 1
    want = (REPLY_LEN_VER8 if ver8 else REPLY_LEN).get(ftype)
    if want is None:
        return False
    n = len(data) - 1
    return want == VAR or (n in want if isinstance(want, tuple) else n == want)


def fits(body, ver8):
    """Whether the unstuffed body (id..CRC) reads as a sensible frame in that layout."""
    head = 3 if ver8 else 2
    if len(body) < head + 2:
        return False
    ftype = body[head - 1]
    data = body[head:len(body) - 2]
    return fits_request(ftype, data, ver8) or fits_reply(ftype, data, ver8)


def frame(body, ver8, t=0.0):
    """A motorjig.master.Frame of the body read in that layout (Ver6 below 5 bytes)."""
    head = 3 if ver8 and len(body) >= 5 else 2
    return Frame(body[0], body[1] if head == 3 else -1, body[head - 1], body[head:len(body) - 2], bytes(body), t)


class VariantReader:
    """Reads good frames as Ver6 or Ver8; ``forced`` 6 or 8 skips the rule."""

    def __init__(self, forced=None):
        self.forced = forced
        self.seen = {}  # (bus, slave id) -> 6/8 from the last frame that told

    def variant(self, bus, body):
        if self.forced is not None:
            return self.forced
        as6, as8 = fits(body, False), len(body) >= 5 and fits(body, True)
        if as6 != as8:
            v = 6 if as6 else 8
            if len(body) >= 5:  # the vendor's 4-byte Ver6 probe goes to Ver8 drives too
                self.seen[(bus, body[0])] = v
            return v
        return self.seen.get((bus, body[0]), 6)

    def frame(self, bus, body, t=0.0):
        return frame(body, self.variant(bus, body) == 8, t)
