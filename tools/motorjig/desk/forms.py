"""What the operator typed into the page, checked before anything is sent.

Every function returns the value or raises ``InputError`` with one sentence that
names the field; the page shows that sentence next to nothing having moved.
"""

import string

from jig import frame as F

MAX_SPEED = 2500000  # pps, the drives' speed parameter limit (the same as jigctl's)
MAX_ACCEL_MS = 9999  # ms, the range of the drives' acc/dec time parameters 3 and 4
I32 = (-0x80000000, 0x7FFFFFFF)


class InputError(ValueError):
    """A field holds something that cannot be sent."""


def number(text, what, lo=None, hi=None, blank=None):
    """An integer from a field (decimal, 0x.. hex, _ separators); blank gives ``blank``."""
    if text is None or str(text).strip() == "":
        if blank is not None:
            return blank
        raise InputError("%s is empty" % what)
    if isinstance(text, float):
        if not text.is_integer():
            raise InputError("%s must be a whole number, not %s" % (what, text))
        value = int(text)
    elif isinstance(text, int):
        value = text
    else:
        try:
            value = int(str(text).strip().replace("_", ""), 0)
        except ValueError:
            raise InputError("%s: %r is not a whole number" % (what, text)) from None
    if lo is not None and value < lo or hi is not None and value > hi:
        raise InputError("%s must be %d..%d, not %d" % (what, lo, hi, value))
    return value


def position(text, what="position"):
    return number(text, what, *I32)


def speed(text, what="speed"):
    return number(text, what, 1, MAX_SPEED)


def accel(text, what):
    """An acc/dec time in ms, or None when the field is left blank (the drive's parameter applies)."""
    value = number(text, what, 1, MAX_ACCEL_MS, blank=0)
    return value or None


def distance(text, what="distance"):
    """A move distance that is not 0 (a move of 0 pulses proves nothing)."""
    value = position(text, what)
    if value == 0:
        raise InputError("%s must not be 0: a move of 0 pulses tests nothing" % what)
    return value


def hex_byte(text, what):
    """One byte written in hex, with or without 0x: '40', '2A', '0x40'."""
    t = str(text if text is not None else "").strip()
    digits = t[2:] if t.lower().startswith("0x") else t
    if not t:
        raise InputError("%s is empty" % what)
    if not 1 <= len(digits) <= 2 or any(c not in string.hexdigits for c in digits):
        raise InputError("%s: %r is not a hex byte (00..FF, e.g. 40 or 0x40)" % (what, text))
    return int(digits, 16)


def slave_id(text, what="slave id"):
    return number(text, what, 0, F.MAX_SLAVE_ID)


def hex_bytes(text, what):
    """Bytes from hex like '01 40', '0140' or '0x01,0x40'; empty text gives b''."""
    tokens = str(text or "").replace(",", " ").replace(":", " ").split()
    parts = []
    for tok in tokens:
        if tok.lower().startswith("0x"):
            tok = tok[2:].rjust(2, "0")
        parts.append(tok)
    try:
        return bytes.fromhex("".join(parts))
    except ValueError:
        raise InputError("%s: %r is not hex bytes (write them like 01 40 or 0140)" % (what, text)) from None


def corrupt_crc(wire):
    """The same frame with its CRC broken (for testing a receiver's CRC check).

    The CRC's high byte sits just before the tail ``AA EE``; when it is 0xAA it is
    stuffed as ``AA AA``, and the pair becomes one 0xAB so the frame stays well formed.
    """
    wire = bytes(wire)
    if len(wire) < 6 or wire[-2:] != bytes((F.STUFF, F.TAIL2)):
        raise InputError("not a complete frame")
    if wire[-3] == F.STUFF and wire[-4] == F.STUFF:
        return wire[:-4] + b"\xab" + wire[-2:]
    flipped = wire[-3] ^ 0x01
    if flipped == F.STUFF:
        flipped = wire[-3] ^ 0x02
    return wire[:-3] + bytes((flipped,)) + wire[-2:]
