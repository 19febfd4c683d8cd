"""``jigctl can dump``: a live line per CAN frame, like candump, with its CANopen meaning.

``FrameText(od)`` makes the lines: time, interface, id, [dlc], data bytes, then what
``cia301.describe_frame`` says the frame is (NMT, SYNC, EMCY with its error code named,
heartbeat, SDO, PDO, LSS); with an object dictionary (``--eds``) SDO objects get their
names and values, and PDOs their mapped objects (the EDS's default mapping: a node
remapped at run time shows what the EDS says). ``run_dump`` reads python-can messages
until a count, a duration or Ctrl-C, printing lines and handing every message to a
python-can logger chosen by the file's extension (``--log``).
"""

import os
import sys
import time

import can

from motorjig.can import cia301
from motorjig.can.objects import decode as od_decode_value
from motorjig.can.objects import object_name, show
from motorjig.commands import UsageError

# python-can writers that need nothing beyond python-can itself.
LOG_EXTENSIONS = (".asc", ".blf", ".csv", ".db", ".log", ".trc", ".txt")
INTERFACE = "slcan"


def _var(od, index, sub):
    if od is None or index not in od:
        return None
    obj = od[index]
    if hasattr(obj, "subindices"):
        try:
            return obj[sub]
        except (KeyError, IndexError):
            return None
    return obj if sub == 0 else None


def pdo_layout(od, service):
    """[(ODVariable, bits)] the EDS maps into service ('TPDO1'..'RPDO4'), or None."""
    number = int(service[-1])
    base = 0x1A00 if service.startswith("T") else 0x1600
    mapping = od.get(base + number - 1) if base + number - 1 in od else None
    if mapping is None or 0 not in mapping:
        return None
    count = mapping[0].default or 0
    layout = []
    for sub in range(1, count + 1):
        if sub not in mapping:
            return None
        entry = mapping[sub].default or 0
        var = _var(od, entry >> 16, (entry >> 8) & 0xFF)
        if var is None:
            return None
        layout.append((var, entry & 0xFF))
    return layout


class FrameText:
    """Text lines for frames; names from od (a canopen ObjectDictionary) when given."""

    def __init__(self, od=None):
        self.od = od
        self._layouts = {}

    def od_name(self, index, sub):
        var = _var(self.od, index, sub)
        return object_name(var) if var is not None else None

    def od_decode(self, index, sub, raw):
        var = _var(self.od, index, sub)
        if var is None:
            return None
        try:
            return show(var, od_decode_value(var, raw))
        except (ValueError, Exception):  # a value that does not fit the EDS's type: show the bytes
            return None

    def pdo_decode(self, service, node, data):
        if self.od is None:
            return None
        if service not in self._layouts:
            self._layouts[service] = pdo_layout(self.od, service)
        layout = self._layouts[service]
        if not layout:
            return None
        value = int.from_bytes(bytes(data), "little")
        parts = []
        at = 0
        for var, bits in layout:
            if at + bits > 8 * len(data) or bits % 8:
                return None
            raw = ((value >> at) & ((1 << bits) - 1)).to_bytes(bits // 8, "little")
            try:
                parts.append("%s=%s" % (var.name, show(var, od_decode_value(var, raw))))
            except Exception:
                return None
            at += bits
        return ", ".join(parts)

    def meaning(self, msg):
        if self.od is None:
            return cia301.describe_frame(msg.arbitration_id, msg.data, msg.is_extended_id, msg.is_remote_frame)
        return cia301.describe_frame(msg.arbitration_id, msg.data, msg.is_extended_id, msg.is_remote_frame,
                                     self.od_name, self.od_decode, self.pdo_decode)

    def line(self, msg, t0):
        """'(   0.012345)  slcan  705   [1]  05                        heartbeat node 5: ...'"""
        ident = ("%08X" % msg.arbitration_id) if msg.is_extended_id else ("%3X" % msg.arbitration_id).rjust(8)
        if msg.is_remote_frame:
            data = "remote request"
        else:
            data = " ".join("%02X" % b for b in msg.data)
        head = "(%11.6f)  %s  %s   [%d]  %-23s" % (msg.timestamp - t0, INTERFACE, ident, msg.dlc, data)
        what = self.meaning(msg)
        return head + ("  " + what if what else "")

    def record(self, msg, t0):
        """The --json form of a frame (one JSON object a line)."""
        return {"t": round(msg.timestamp - t0, 6), "id": msg.arbitration_id, "ext": msg.is_extended_id,
                "rtr": msg.is_remote_frame, "dlc": msg.dlc, "data": bytes(msg.data).hex(),
                "meaning": self.meaning(msg)}


def check_log_path(path):
    """UsageError unless path is a file python-can can log to (by extension) in a folder that exists."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in LOG_EXTENSIONS:
        raise UsageError("--log %s: give a file ending in %s (python-can's formats)" % (path, ", ".join(LOG_EXTENSIONS)))
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise UsageError("cannot write %s: No such file or directory" % path)
    if os.path.isdir(path):
        raise UsageError("cannot write %s: Is a directory" % path)


def run_dump(bus, text, count=None, duration=None, log=None, as_json=False, out=None, stop=None):
    """Print (and log) frames from bus until count frames, duration seconds, stop() or Ctrl-C.
    Returns the number of frames."""
    import json

    out = out or sys.stdout
    writer = can.Logger(log) if log else None
    t0 = time.time()
    end = time.monotonic() + duration if duration is not None else None
    n = 0
    try:
        while count is None or n < count:
            if stop is not None and stop():
                break
            wait = 0.1
            if end is not None:
                wait = min(wait, end - time.monotonic())
                if wait <= 0:
                    break
            msg = bus.recv(wait)
            if msg is None:
                continue
            n += 1
            if writer is not None:
                writer.on_message_received(msg)
            if as_json:
                out.write(json.dumps(text.record(msg, t0)) + "\n")
            else:
                out.write(text.line(msg, t0) + "\n")
            out.flush()
    except KeyboardInterrupt:
        pass  # Ctrl-C ends the dump, not an error: the log is closed below as always
    finally:
        if writer is not None:
            writer.stop()
    return n
