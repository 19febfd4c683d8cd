"""One line per record for the terminal, like candump: time, bus, direction, what, bytes.

    12:00:00.102000  pc  ?  reply     id 1  GetCommandPos(0x51)    status OK  value=-1000  | AA CC 01 51 00 ...
    12:00:00.106500  pc  ?  bad_crc   dropped: bad CRC                                     | AA CC 02 51 00 ...

Good frames are read as Ver6 or Ver8 by ``variant.VariantReader`` and described by
``motorjig.decode`` (the text ``jigctl monitor`` prints); with the direction known
(the jig's own recording), request or reply follows from it. The jig's noise and
lost records have no bytes, only a count:

    12:00:01.200000  pc      ?    lost      3 records lost (the jig's capture ring was full)

The jig's CAN frames as candump prints them (identifier in hex, 3 digits standard, 8
extended; [DLC]; the data bytes, or "remote request"), then the CANopen object the
identifier is in the predefined connection set (CiA 301), as a hint:

    12:00:01.300000  can     in   705   [1]  05                        heartbeat node 5: operational
"""

import time

from jig.frame import BROADCAST_ID

from motorjig.capture import record as R
from motorjig.capture.variant import VariantReader
from motorjig.decode import Decoder, describe_dict


def stamp(t_us):
    s, us = divmod(t_us, 1000000)
    return time.strftime("%H:%M:%S", time.localtime(s)) + ".%06d" % us


#: CiA 301's predefined connection set: function code (identifier >> 7) -> name, for ids 1..127
_COB_FUNCTIONS = {1: "EMCY", 3: "TPDO1", 4: "RPDO1", 5: "TPDO2", 6: "RPDO2", 7: "TPDO3", 8: "RPDO3", 9: "TPDO4",
                  10: "RPDO4", 11: "SDO response", 12: "SDO request", 14: "heartbeat"}
_NMT_COMMANDS = {1: "start", 2: "stop", 0x80: "enter pre-operational", 0x81: "reset node", 0x82: "reset communication"}
_NMT_STATES = {0: "boot-up", 4: "stopped", 5: "operational", 0x7F: "pre-operational"}


def canopen_name(can_id, flags, data):
    """What a standard identifier is in CANopen's predefined connection set ('' for an
    extended one or none): 'NMT start node 5', 'SDO request node 5', 'heartbeat node 5:
    operational', 'TPDO1 node 5', 'SYNC', 'EMCY node 5', 'LSS request'."""
    if flags & R.CAN_EXT:
        return ""
    if can_id == 0:
        if len(data) >= 2:
            cmd = _NMT_COMMANDS.get(data[0], "command 0x%02X" % data[0])
            return "NMT %s %s" % (cmd, "all nodes" if data[1] == 0 else "node %d" % data[1])
        return "NMT"
    if can_id == 0x80:
        return "SYNC"
    if can_id == 0x100:
        return "TIME"
    if can_id in (0x7E4, 0x7E5):
        return "LSS response" if can_id == 0x7E4 else "LSS request"
    node = can_id & 0x7F
    name = _COB_FUNCTIONS.get(can_id >> 7)
    if name is None or node == 0:
        return ""
    text = "%s node %d" % (name, node)
    if name == "heartbeat" and len(data) == 1 and not flags & R.CAN_RTR:
        text += ": " + _NMT_STATES.get(data[0] & 0x7F, "state 0x%02X" % data[0])
    return text


def can_text(rec):
    """A CAN frame as candump prints it: '705   [1]  05', '18FF50E5   [2]  remote request'."""
    ident = ("%08X" if rec.can_flags & R.CAN_EXT else "%03X") % rec.can_id
    what = "remote request" if rec.can_flags & R.CAN_RTR else bytes(rec.data).hex(" ").upper()
    return "%s   [%d]  %s" % (ident, rec.can_dlc, what)


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
        if rec.is_can:
            del out["verdict"], out["wire"]
            out.update(id=rec.can_id, ext=bool(rec.can_flags & R.CAN_EXT), rtr=bool(rec.can_flags & R.CAN_RTR),
                       dlc=rec.can_dlc, data=bytes(rec.data).hex(" "))
            name = canopen_name(rec.can_id, rec.can_flags, rec.data)
            if name:
                out["canopen"] = name
            return out
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
        if rec.is_can:
            return ("%s %-38s %s" % (head, can_text(rec), d.get("canopen", ""))).rstrip()
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
