"""One line per record for the terminal, like candump: time, bus, direction, what, bytes.

    12:00:00.102000  pc  ?  reply     id 1  GetCommandPos(0x51)    status OK  value=-1000  | AA CC 01 51 00 ...
    12:00:00.106500  pc  ?  bad_crc   dropped: bad CRC                                     | AA CC 02 51 00 ...

Good frames are read as Ver6 or Ver8 by ``variant.VariantReader`` and described by
``motorjig.decode`` (the text ``jigctl monitor`` prints); with the direction known
(the jig's own recording), request or reply follows from it. The jig's noise and
lost records have no bytes, only a count:

    12:00:01.200000  pc      ?    lost      3 records lost (the jig's capture ring was full)
"""

import time

from jig.frame import BROADCAST_ID

from motorjig.capture import record as R
from motorjig.capture.variant import VariantReader
from motorjig.decode import Decoder, describe_dict


def stamp(t_us):
    s, us = divmod(t_us, 1000000)
    return time.strftime("%H:%M:%S", time.localtime(s)) + ".%06d" % us


def kind_by_direction(bus_name, direction):
    """Request or reply from the direction (relative to the jig), or None if unknown:
    on the driver bus the jig is the master, on the PC bus a slave."""
    if direction == R.DIR_UNKNOWN:
        return None
    requests_in = bus_name != "drivers"
    return "request" if (direction == R.DIR_INBOUND) == requests_in else "reply"


class TextView:
    """Turns records into dicts (``--json``) and lines; one decoder per bus."""

    def __init__(self, buses, forced_variant=None):
        self.buses = tuple(buses)
        self.reader = VariantReader(forced_variant)
        self.decoders = [Decoder() for _ in self.buses]

    def as_dict(self, rec):
        bus = self.buses[rec.bus]
        out = {"t": rec.t_us / 1e6, "bus": bus.name, "dir": R.DIRECTION_NAMES[rec.direction],
               "verdict": R.verdict_name(rec.verdict), "wire": rec.data.hex(" ")}
        if rec.t_first_us is not None:
            out["t_first"] = rec.t_first_us / 1e6
        if rec.count is not None:
            out["count"] = rec.count
        if rec.verdict != R.GOOD:
            return out
        body = _body(rec.data)
        fr = self.reader.frame(rec.bus, body, rec.t_us / 1e6)
        kind = kind_by_direction(bus.name, rec.direction)
        if fr.slave == BROADCAST_ID:
            kind = "broadcast"
        d = self.decoders[rec.bus].as_dict(fr, kind)
        d.pop("t", None)
        out["variant"] = 8 if fr.sync >= 0 else 6
        out["frame"] = d
        return out

    def line(self, rec, d=None):
        d = d or self.as_dict(rec)
        head = "%s  %-7s %-3s " % (stamp(rec.t_us), d["bus"], d["dir"])
        if "frame" in d:
            what = describe_dict(d["frame"])
        elif rec.count is not None:
            return "%s %-9s %s" % (head, d["verdict"], R.count_text(rec))
        else:
            what = "%-9s %s" % (d["verdict"], R.VERDICTS.get(rec.verdict, ("", ""))[1])
        return "%s %s  | %s" % (head, what.rstrip(), d["wire"].upper())


def _body(wire):
    """The unstuffed body of a good frame's wire bytes (AA CC ... AA EE)."""
    out = bytearray()
    i = 2
    end = len(wire) - 2
    while i < end:
        b = wire[i]
        out.append(b)
        i += 2 if b == 0xAA else 1
    return bytes(out)
