"""Wire layouts of the jig's own diagnostic frames and of its GetSlaveInfo reply.

Frame types 0xF0-0xFA are not used by the Plus-R protocol. Request and reply
layouts (reply data always starts with the status byte)::

    0xF0 ReadCounters      req: -        reply: St, u8 n, n x u32 in WIRE_NAMES order
    0xF1 ResetCounters     req: -        reply: St
    0xF2 StartBusScan      req: -        reply: St  (scan of ids 0..15 runs in the background)
    0xF3 GetBusScanResult  req: -        reply: St, u8 state, u16 found bitmap (bit k = id k
                                                answered), 16 x u8 slave type per id (0 = none)
    0xF4 ReadCrashLog      req: -        reply: St, ASCII text (at most CRASH_TEXT_MAX bytes,
                                                printable only), NUL; empty text when there is
                                                no crash log or the HAL has no crash_summary()
    0xF5 StartTrace        req: u8 slave, u32 period µs, u8 framing (0 detect, 1 Ver6, 2 Ver8)
                                         reply: St, u16 ring size (samples), u32 jig tick now
                                                (a restart: the set is that one drive)
                           req: the same + u8 1 (join: the drive joins the set, the others go on)
                                         reply: St, u16 ring size, u32 jig tick now, u8 started
                                                (1: the sampler was off), u16 oldest index held,
                                                u16 next index, u32 set (bit k: drive k)
    0xF6 StopTrace         req: -        reply: St, the trace status (below); samples stay readable
                           req: u8 slave (leave: the others go on; the last one stops it)
                                         reply: St, that drive's status (below)
    0xF7 ReadTrace         req: u16 from index, u8 max n (0: 12)
                                         reply: St, u8 state, u16 next index, u8 n, n x sample
                                                (u32 tick, i32 command, i32 actual, i32 velocity,
                                                u32 axis flags)
                           req: the same + u8 1 (tagged; max n 0: 11)
                                         reply: St, u8 state, u16 next index, u8 n, n x (u8 slave,
                                                sample)
    0xF8 GetTraceStatus    req: -        reply: St, u8 state (0 off, 1 running), u8 slave, u32 period µs,
                                                u32 taken, u32 skipped, u32 lost (ring full),
                                                u32 failed, u16 oldest index held, u16 next index
                           req: u8 slave reply: St, u8 state, u8 slave, u32 set, u32 period µs, that
                                                drive's u32 taken, skipped, lost, failed since its
                                                join, u16 oldest index held, u16 next index
    0xF9 ReadTransactionTimes req: -     reply: St, u8 n, n x (u8 id, u8 type (Ver6) / sync (Ver8),
                                                u32 tick the request's last stop bit left on the driver
                                                bus, u32 tick the reply's last byte came in or
                                                0xFFFFFFFF: none), the last 16 forwarded requests,
                                                oldest first
    0xFA ReadCanCounters   req: -        reply: St, u8 n, n x u32 in CAN_WIRE_NAMES order (the CAN
                                                port's figures; n = 0 on a jig without one);
                                                ResetCounters resets them too
    0xFB TakeSafetyNotice req: -         reply: St, u8 pending (1: the safety stop fired since a PC
                                                last took the notice), u8 buses stopped (bit 0 the
                                                driver bus, bit 1 CAN), u32 ms since it fired, u16
                                                Plus-R ids stopped, 16 x u8 CAN nodes stopped (bit n
                                                of byte n >> 3); taking it clears it

The PC library decodes with ``decode_counters`` / ``decode_can_counters`` / ``decode_scan`` / ``decode_crash_log`` below, so the
layout exists once. ``SLAVE_TYPE`` is what the jig reports in GetSlaveInfo: 200
(0xC8), a code no FASTECH product uses (their list: 1, 3, 10, 11, 20, 30, 31, 35,
40, 50, 60, 100, 102, 105, 108, 110, 120, 130, 150, 155, 160, 180, 254, 255).
"""

from jig import counters, frame, parser
from jig.compat import const

READ_COUNTERS = const(0xF0)
RESET_COUNTERS = const(0xF1)
START_BUS_SCAN = const(0xF2)
GET_BUS_SCAN_RESULT = const(0xF3)
READ_CRASH_LOG = const(0xF4)
START_TRACE = const(0xF5)
STOP_TRACE = const(0xF6)
READ_TRACE = const(0xF7)
GET_TRACE_STATUS = const(0xF8)
READ_TRANSACTION_TIMES = const(0xF9)
READ_CAN_COUNTERS = const(0xFA)
TAKE_SAFETY_NOTICE = const(0xFB)
SAFETY_NOTICE_LEN = const(24)  # jig.safety.NOTICE_LEN
XT_ENTRY = const(10)  # u8 id, u8 b1, u32 request sent, u32 reply in

TRACE_SAMPLE = const(20)  # bytes: u32 tick, i32 command, i32 actual, i32 velocity, u32 flags
TRACE_CHUNK = const(12)  # samples per ReadTrace reply at most
TRACE_CHUNK_TAGGED = const(11)  # samples per tagged ReadTrace reply at most
TRACE_STATUS_REPLY_LEN = const(27)  # incl. status
TRACE_DRIVE_STATUS_REPLY_LEN = const(31)  # incl. status
TRACE_JOIN_REPLY_LEN = const(16)  # incl. status
TRACE_JOIN = const(1)  # StartTrace's 7th byte
TRACE_TAGGED = const(1)  # ReadTrace's 4th byte
TRACE_STATE_NAMES = ("off", "running")

SLAVE_TYPE = const(200)
NAME = b"MotorJig bridge"
VERSION = b"0.1"

WIRE_NAMES = (
    counters.NAMES
    + tuple(["up_" + n for n in parser.COUNTER_NAMES])
    + tuple(["down_" + n for n in parser.COUNTER_NAMES])
)
N_WIRE = len(WIRE_NAMES)
# ReadCounters' reply is at its size limit (2 + 4 x 61 data bytes at most): the CAN
# port's counters have their own frame.
CAN_WIRE_NAMES = counters.CAN_NAMES
N_CAN_WIRE = len(CAN_WIRE_NAMES)

SCAN_IDS = const(16)  # ids 0..15
SCAN_IDLE = const(0)  # never started
SCAN_RUNNING = const(1)
SCAN_DONE = const(2)
SCAN_STATE_NAMES = ("idle", "running", "done")
SCAN_REPLY_LEN = const(1 + 1 + 2 + 16)  # incl. status

CRASH_TEXT_MAX = frame.MAX_DATA - 2  # reply data = status + text + NUL


def decode_counters(data):
    """Reply data of ReadCounters (status first) -> dict name -> value (host side)."""
    if len(data) < 2 or data[0] != 0:
        raise ValueError("bad ReadCounters reply")
    n = data[1]
    if len(data) != 2 + 4 * n:
        raise ValueError("bad ReadCounters reply length")
    out = {}
    for i in range(n):
        name = WIRE_NAMES[i] if i < N_WIRE else "counter_%d" % i
        out[name] = frame.get_u32(data, 2 + 4 * i)
    return out


def decode_can_counters(data):
    """Reply data of ReadCanCounters (status first) -> dict name -> value (host side);
    empty when the jig has no CAN port."""
    if len(data) < 2 or data[0] != 0:
        raise ValueError("bad ReadCanCounters reply")
    n = data[1]
    if len(data) != 2 + 4 * n:
        raise ValueError("bad ReadCanCounters reply length")
    out = {}
    for i in range(n):
        name = CAN_WIRE_NAMES[i] if i < N_CAN_WIRE else "can_counter_%d" % i
        out[name] = frame.get_u32(data, 2 + 4 * i)
    return out


def decode_safety_notice(data):
    """Reply data of TakeSafetyNotice (status first) -> None (no stop since the last one was
    taken) or a dict: ms_ago, pc_bus / can (what stopped), ids (Plus-R ids), nodes (CAN
    node ids)."""
    if len(data) != 1 + SAFETY_NOTICE_LEN or data[0] != 0:
        raise ValueError("bad TakeSafetyNotice reply")
    if not data[1]:
        return None
    ids = frame.get_u16(data, 7)
    return {"ms_ago": frame.get_u32(data, 3), "pc_bus": bool(data[2] & 1), "can": bool(data[2] & 2),
            "ids": [i for i in range(16) if ids >> i & 1],
            "nodes": [n for n in range(1, 128) if data[9 + (n >> 3)] >> (n & 7) & 1]}


def decode_scan(data):
    """Reply data of GetBusScanResult -> (state name, {id: slave type}) (host side)."""
    if len(data) != SCAN_REPLY_LEN or data[0] != 0:
        raise ValueError("bad GetBusScanResult reply")
    found = data[2] | (data[3] << 8)
    ids = {}
    for i in range(SCAN_IDS):
        if found & (1 << i):
            ids[i] = data[4 + i]
    return SCAN_STATE_NAMES[data[1]], ids


def decode_crash_log(data):
    """Reply data of ReadCrashLog (status first) -> the text, '' if none (host side)."""
    if len(data) < 2 or data[0] != 0 or data[-1] != 0 or len(data) > 2 + CRASH_TEXT_MAX:
        raise ValueError("bad ReadCrashLog reply")
    text = bytes(data[1:-1])
    if 0 in text or any(c < 0x20 or c > 0x7E for c in text):
        raise ValueError("ReadCrashLog text is not printable ASCII")
    return text.decode("ascii")


def decode_trace_start(data):
    """Reply data of StartTrace -> (ring size in samples, jig tick at the start) (host side)."""
    if len(data) != 7 or data[0] != 0:
        raise ValueError("bad StartTrace reply")
    return frame.get_u16(data, 1), frame.get_u32(data, 3)


def decode_trace_status(data):
    """Reply data of StopTrace / GetTraceStatus -> dict (host side)."""
    if len(data) != TRACE_STATUS_REPLY_LEN or data[0] != 0 or data[1] >= len(TRACE_STATE_NAMES):
        raise ValueError("bad trace status reply")
    g = frame.get_u32
    return {"state": TRACE_STATE_NAMES[data[1]], "slave": data[2], "period_us": g(data, 3), "taken": g(data, 7),
            "skipped": g(data, 11), "lost": g(data, 15), "failed": g(data, 19), "first": frame.get_u16(data, 23),
            "next": frame.get_u16(data, 25)}


def decode_trace_join(data):
    """Reply data of a joining StartTrace -> dict: ring, tick, started, first (oldest index
    held), next, set (the drive ids in the set) (host side)."""
    if len(data) != TRACE_JOIN_REPLY_LEN or data[0] != 0:
        raise ValueError("bad StartTrace (join) reply")
    members = frame.get_u32(data, 12)
    return {"ring": frame.get_u16(data, 1), "tick": frame.get_u32(data, 3), "started": bool(data[7]),
            "first": frame.get_u16(data, 8), "next": frame.get_u16(data, 10),
            "set": [i for i in range(32) if members >> i & 1]}


def decode_trace_drive_status(data):
    """Reply data of a leaving StopTrace / GetTraceStatus for one drive -> dict; taken,
    skipped, lost, failed are that drive's since its join (host side)."""
    if len(data) != TRACE_DRIVE_STATUS_REPLY_LEN or data[0] != 0 or data[1] >= len(TRACE_STATE_NAMES):
        raise ValueError("bad trace drive status reply")
    g = frame.get_u32
    members = g(data, 3)
    return {"state": TRACE_STATE_NAMES[data[1]], "slave": data[2], "set": [i for i in range(32) if members >> i & 1],
            "period_us": g(data, 7), "taken": g(data, 11), "skipped": g(data, 15), "lost": g(data, 19),
            "failed": g(data, 23), "first": frame.get_u16(data, 27), "next": frame.get_u16(data, 29)}


def decode_trace_chunk(data):
    """Reply data of ReadTrace -> (state name, next index, [(tick, command, actual,
    velocity, flags), ...]) with raw 30-bit ticks (host side)."""
    if len(data) < 5 or data[0] != 0 or data[1] >= len(TRACE_STATE_NAMES):
        raise ValueError("bad ReadTrace reply")
    n = data[4]
    if n > TRACE_CHUNK or len(data) != 5 + TRACE_SAMPLE * n:
        raise ValueError("bad ReadTrace reply length")
    out = []
    for i in range(n):
        k = 5 + TRACE_SAMPLE * i
        out.append((frame.get_u32(data, k), frame.get_i32(data, k + 4), frame.get_i32(data, k + 8),
                    frame.get_i32(data, k + 12), frame.get_u32(data, k + 16)))
    return TRACE_STATE_NAMES[data[1]], frame.get_u16(data, 2), out


def decode_transaction_times(data):
    """Reply data of ReadTransactionTimes -> [(id, type or sync, t request sent, t reply in
    or None), ...] oldest first, raw 30-bit ticks (host side)."""
    if len(data) < 2 or data[0] != 0 or len(data) != 2 + XT_ENTRY * data[1]:
        raise ValueError("bad ReadTransactionTimes reply")
    out = []
    for i in range(data[1]):
        k = 2 + XT_ENTRY * i
        t_rep = frame.get_u32(data, k + 6)
        out.append((data[k], data[k + 1], frame.get_u32(data, k + 2), None if t_rep == 0xFFFFFFFF else t_rep))
    return out


def decode_trace_chunk_tagged(data):
    """Reply data of a tagged ReadTrace -> (state name, next index, [(slave, tick, command,
    actual, velocity, flags), ...]) with raw 30-bit ticks (host side)."""
    if len(data) < 5 or data[0] != 0 or data[1] >= len(TRACE_STATE_NAMES):
        raise ValueError("bad ReadTrace reply")
    n = data[4]
    if n > TRACE_CHUNK_TAGGED or len(data) != 5 + (TRACE_SAMPLE + 1) * n:
        raise ValueError("bad ReadTrace reply length")
    out = []
    for i in range(n):
        k = 5 + (TRACE_SAMPLE + 1) * i
        out.append((data[k], frame.get_u32(data, k + 1), frame.get_i32(data, k + 5), frame.get_i32(data, k + 9),
                    frame.get_i32(data, k + 13), frame.get_u32(data, k + 17)))
    return TRACE_STATE_NAMES[data[1]], frame.get_u16(data, 2), out
