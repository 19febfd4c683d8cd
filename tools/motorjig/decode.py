"""Human-readable decoding of frames seen on the line (monitor, raw, -v trace).

Where the direction is known (the master sent it, or received it) the caller says
so (``kind``). Where it is not (a sniffed line: ``jigctl monitor``) ``Decoder`` pairs
frames: a request is remembered per (slave, frame type) for ``PAIR_SECONDS``, and
the next frame with the same pair (and, in Ver8, the same sync number) that has
the shape of a reply is its reply. A frame seen without its request before it is
classed by its shape (a reply starts with a known status byte and has the reply
length of its frame type; a request has the request length); one that fits both,
e.g. ``02 2A 00`` (ServoEnable off, and also every ServoEnable reply), counts as
a request until its reply shows up.
"""

from jig import diag as D
from jig import frame as F

from motorjig import names as N
from motorjig.errors import status_meaning
from motorjig.master import REPLY_LEN, REPLY_LEN_VER8, REQUEST_LEN, VAR, AxisStatus


def _i32(d, o):
    return F.get_i32(d, o) if len(d) >= o + 4 else None


def _hex_word(d, off, w):
    v = 0
    for i in range(w):
        v |= d[off + i] << (8 * i)
    return "0x%0*X" % (2 * w, v), v


def _reply_fields(ftype, d, ver8=False):
    """Decoded fields of a good reply's data (after the status byte), or {}. Input
    words are 32 bits in Ver6, 32 or 64 in Ver8 (told apart by the length)."""
    n = len(d)
    if ftype in (F.GET_SLAVE_INFO, F.GET_MOTOR_INFO) and n >= 1:
        text = bytes(d[1:]).split(b"\x00")[0].decode("ascii", "replace")
        if ftype == F.GET_SLAVE_INFO:
            return {"slave_type": d[0], "type_name": N.slave_type_name(d[0]), "version": text}
        return {"motor_type": d[0], "motor": text}
    if ftype == F.GET_AXIS_STATUS and n == 4:
        return {"flags": AxisStatus(F.get_u32(d, 0)).flags}
    if ftype in (F.GET_PARAMETER, F.GET_ROM_PARAMETER, F.GET_COMMAND_POS, F.GET_ACTUAL_POS,
                 F.GET_POS_ERROR, F.GET_ACTUAL_VEL) and n == 4:
        return {"value": F.get_i32(d, 0)}
    if (ftype == F.GET_IO_OUTPUT and n == 4) or (ftype == F.GET_IO_INPUT and n in ((4, 8) if ver8 else (4,))):
        table = N.INPUT_BITS if ftype == F.GET_IO_INPUT else N.OUTPUT_BITS
        text, v = _hex_word(d, 0, n)
        return {"value": text, "bits": N.bit_names(v, table)}
    if ftype == F.GET_ALARM_TYPE and n == 1:
        return {"alarm": N.ALARM_NAMES.get(d[0], d[0])}
    if ftype == F.GET_ALL_STATUS and n in ((32, 36) if ver8 else (32,)):
        w = n - 28
        return {"inputs": _hex_word(d, 0, w)[0], "outputs": "0x%08X" % F.get_u32(d, w),
                "flags": AxisStatus(F.get_u32(d, w + 4)).flags, "command_pos": F.get_i32(d, w + 8),
                "actual_pos": F.get_i32(d, w + 12), "pos_error": F.get_i32(d, w + 16),
                "actual_vel": F.get_i32(d, w + 20), "pt_number": F.get_u32(d, w + 24)}
    if ftype == F.GET_MOTION_STATUS and n == 20:
        out = {"command_pos": F.get_i32(d, 0), "actual_pos": F.get_i32(d, 4),
               "pos_error": F.get_i32(d, 8), "actual_vel": F.get_i32(d, 12)}
        if ver8:  # Ver8: the axis flags in place of the PT number
            out["flags"] = AxisStatus(F.get_u32(d, 16)).flags
        return out
    if ftype == F.GET_IO_AXIS_STATUS and n in ((12, 16) if ver8 else (12,)):
        w = n - 8
        return {"inputs": _hex_word(d, 0, w)[0], "outputs": "0x%08X" % F.get_u32(d, w),
                "flags": AxisStatus(F.get_u32(d, w + 4)).flags}
    if ftype == D.READ_CRASH_LOG:
        try:
            return {"crash_log": D.decode_crash_log(b"\x00" + bytes(d))}
        except ValueError:
            return {}
    return {}


def _request_fields(ftype, d):
    n = len(d)
    if ftype in (F.MOVE_ABS_POS, F.MOVE_INC_POS, F.ALL_MOVE_ABS_POS, F.ALL_MOVE_INC_POS) and n == 8:
        return {"position": F.get_i32(d, 0), "speed": F.get_u32(d, 4)}
    if ftype in (F.MOVE_VELOCITY, F.MOVE_TO_LIMIT) and n == 5:
        return {"speed": F.get_u32(d, 0), "direction": "+" if d[4] else "-"}
    if ftype == F.SET_PARAMETER and n == 5:
        return {"param": d[0], "value": F.get_i32(d, 1)}
    if ftype in (F.GET_PARAMETER, F.GET_ROM_PARAMETER) and n == 1:
        return {"param": d[0]}
    if ftype in (F.SERVO_ENABLE, F.STEP_ALARM_RESET, F.MOVE_PAUSE) and n == 1:
        return {"on": bool(d[0])}
    if ftype in (F.SET_COMMAND_POS, F.SET_ACTUAL_POS, F.POSITION_ABS_OVERRIDE,
                 F.POSITION_INC_OVERRIDE) and n == 4:
        return {"position": F.get_i32(d, 0)}
    if ftype == F.VELOCITY_OVERRIDE and n == 4:
        return {"speed": F.get_u32(d, 0)}
    return {}


def looks_like_reply(ftype, data, ver8=False):
    if not data or data[0] not in N.STATUS_NAMES:
        return False
    if data[0] != F.STATUS_OK:
        return len(data) == 1
    want = (REPLY_LEN_VER8 if ver8 else REPLY_LEN).get(ftype)
    return want == VAR or want == len(data) - 1 or (isinstance(want, tuple) and len(data) - 1 in want)


def looks_like_request(ftype, data):
    want = REQUEST_LEN.get(ftype)
    if isinstance(want, tuple):
        return len(data) in want
    return want is None or want == len(data)


#: how long a sniffed request waits for its reply (drives answer within milliseconds;
#: the longest reply timeout jigctl uses is 5 s, for SaveAllParameters)
PAIR_SECONDS = 5.0


class Decoder:
    """Turns Frames into dicts and one-line descriptions, pairing replies with requests."""

    def __init__(self):
        self.pending = {}  # (slave, frame type) -> (time, sync) of a request not answered yet

    def _asked(self, fr):
        """True when fr can answer a request seen before (same pair, in time, same sync)."""
        key = (fr.slave, fr.ftype)
        asked = self.pending.get(key)
        if asked is None:
            return False
        t, sync = asked
        if fr.t and t and fr.t - t > PAIR_SECONDS:
            del self.pending[key]
            return False
        return sync < 0 or fr.sync < 0 or sync == fr.sync

    def note(self, fr, kind):
        """Remember a frame whose direction is known: a request waits for its reply."""
        key = (fr.slave, fr.ftype)
        if kind == "request":
            self.pending[key] = (fr.t, fr.sync)
        elif kind == "reply":
            self.pending.pop(key, None)

    def classify(self, fr):
        """'request', 'reply' or 'broadcast', for a frame whose direction is not known.

        A frame with the shape of a reply that answers a request seen before is a
        reply. Otherwise its shape decides; a frame that fits both counts as a request.
        """
        if fr.slave == F.BROADCAST_ID:
            return "broadcast"
        ver8 = fr.sync >= 0
        reply_shape = looks_like_reply(fr.ftype, fr.data, ver8)
        if reply_shape and (self._asked(fr) or not looks_like_request(fr.ftype, fr.data)):
            self.note(fr, "reply")
            return "reply"
        self.note(fr, "request")
        return "request"

    def as_dict(self, fr, kind=None):
        if kind is None:
            kind = self.classify(fr)
        else:
            self.note(fr, kind)
        out = {"t": fr.t, "kind": kind, "slave": fr.slave, "type": fr.ftype,
               "name": N.frame_name(fr.ftype), "data": bytes(fr.data).hex(" ")}
        if fr.sync >= 0:
            out["sync"] = fr.sync
        if kind == "reply" and fr.data:
            out["status"] = fr.data[0]
            out["status_name"] = N.status_name(fr.data[0])
            if fr.data[0] == F.STATUS_OK:
                out.update(_reply_fields(fr.ftype, fr.data[1:], fr.sync >= 0))
            else:
                out["meaning"] = status_meaning(fr.data[0])
        elif kind != "reply":
            out.update(_request_fields(fr.ftype, fr.data))
        return out

    def describe(self, fr, kind=None):
        return describe_dict(self.as_dict(fr, kind))


def describe_dict(d):
    head = "%-9s id %-2d %-22s" % (d["kind"], d["slave"], "%s(0x%02X)" % (d["name"], d["type"]))
    if "sync" in d:
        head += " sync %d" % d["sync"]
    extra = []
    if "status" in d:
        extra.append("status %s" % ("OK" if d["status"] == 0 else "0x%02X %s" % (d["status"], d["meaning"])))
    fields = [(k, v) for k, v in d.items() if k not in _BASE]
    for k, v in fields:
        if isinstance(v, list):
            v = ",".join(v) or "-"
        extra.append("%s=%s" % (k, v))
    nbytes = len(d["data"].split())
    if not fields and nbytes > (1 if "status" in d else 0):
        extra.append("data [%s]" % d["data"])
    return head + "  " + "  ".join(extra)


_BASE = ("t", "kind", "slave", "type", "name", "data", "sync", "status", "status_name", "meaning")
