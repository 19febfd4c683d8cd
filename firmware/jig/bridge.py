"""Routing between the PC bus and the driver bus: forward, await, relay.

The machine is ``TRANSITIONS`` below (docs/bridge.md renders it): states IDLE,
AWAIT_PC (a forwarded PC request waits for its reply) and AWAIT_INT (a request of
the jig's own -- bus scan, safety stop -- is out); events are routing decisions on
frames from either side and the timeout.

* Frames for the jig's own id are answered by ``handlers`` on the PC port.
* Every other id is forwarded byte for byte, and one matching reply is relayed
  unchanged. Id 99 is forwarded and nothing is awaited.
* Matching needs no layout and no per-driver setting, so one bus may carry Ver6
  and Ver8 drives whatever the jig's own protocol: a reply matches when its first
  two body bytes equal the request's and it has a status byte (body of 5 bytes or
  more). Those two bytes are id + frame type for a Ver6 frame and id + sync number
  for a Ver8 one (a Ver8 drive echoes the sync; a Ver6-format probe sent to a Ver8
  drive comes back as ``id 51 crcL 80``, again the request's first two bytes).
* Anything else from the driver bus is dropped and counted: late replies (after
  the timeout), replies to an aborted wait, wrong id/type or sync, unsolicited
  frames.
* A new PC frame while a PC reply is awaited aborts the wait (counted). While
  the jig's own request is out, local frames are answered and the wait goes on;
  a PC frame for the driver bus aborts it (PC traffic has priority).
* The jig itself (bus scan, safety stop, the trace sampler) sends through
  ``request``; their replies go to that client, never to the PC. A request sent
  with ``hold`` (jig.trace) is not aborted by the PC: a PC frame for the driver bus
  that comes meanwhile is held (never passed on from its header, which would collide
  with the drive's answer) and sent whole once the request is done (``_release``).
  A client waiting for the bridge to be free sets ``bs[B_WAKE]``: the end of a relay,
  a broadcast or a stub then asks for the slow pass (``due[0]``).

Two forwarding modes (parameter ``forward_mode``, docs/bridge.md):

* **cut-through** (default): a frame goes on from its header (EV_START), both
  ways -- a PC frame to the driver bus, a driver frame to the PC while a reply is
  awaited -- and every further byte follows as it arrives (``up_bytes``: the raw
  bytes the parser consumed). The routing decision is taken at EV_HEAD, when the
  routing bytes are in: the slave id of a PC frame (one for the jig is ended on
  the driver bus with a tail: a frame too short to be one), the two matching
  bytes of a driver frame (one that does not match is ended with a tail on the PC
  bus). DE stays up until the frame's tail has gone. A frame that turns out bad
  has been passed on, as a wire would: it is counted (``cut_corrupt``,
  ``relay_corrupt``), and a PC that goes silent mid-frame gets the transmission
  ended cleanly (``cut_truncated``).
* **store-and-forward**: only whole, CRC-checked frames are sent on, re-stuffed
  from the parsed body (stuffing is canonical, so the bytes are the received ones).
"""

from array import array

from jig import frame, mem
from jig.counters import (C_ABORTS, C_BROADCASTS, C_CUT_CORRUPT, C_CUT_TRUNCATED, C_DOWN_IN, C_DOWN_OUT,
                          C_FORWARDS, C_INT_ABORTS, C_INT_REPLIES, C_INT_REQUESTS, C_INT_TIMEOUTS, C_LOCAL,
                          C_LOCAL_ERRORS, C_RELAY_CORRUPT, C_REPLIES, C_STALE, C_TIMEOUTS, C_UNAWAITED, C_UP_IN,
                          C_UP_OUT)
from jig.parser import (A_END, A_RESYNC, A_STORE, A_STUFF_ERROR, EV_DROP, EV_FRAME, EV_HEAD, EV_START, HEADER, HUNT,
                        MIN_BODY, S_BYTE_US, S_DROP_N, S_EVENT, S_N, S_STATE, S_T_LAST, S_WHY, TABLES)
from jig.compat import const, ticks_diff
from jig.params import P_INTERBYTE_US, P_REPLY_TIMEOUT_MS, P_SLAVE_ID

IDLE = const(0)
AWAIT_PC = const(1)  # a PC request was forwarded; its reply goes to the PC
AWAIT_INT = const(2)  # the jig's own request (scan, safety stop) is out
STATE_NAMES = ("IDLE", "AWAIT_PC", "AWAIT_INT")

E_PC_LOCAL = const(0)
E_PC_FORWARD = const(1)
E_PC_BROADCAST = const(2)
E_INTERNAL = const(3)
E_REPLY = const(4)
E_DOWN_OTHER = const(5)
E_TIMEOUT = const(6)
E_CUT_SHORT = const(7)
EVENT_NAMES = ("pc_local", "pc_forward", "pc_broadcast", "internal", "reply", "down_other", "timeout", "cut_short")

# Action flags (several may be combined in one transition)
F_ABORT = const(1)
F_LOCAL = const(2)
F_FORWARD = const(4)
F_BROADCAST = const(8)
F_SEND = const(16)
F_RELAY = const(32)
F_DELIVER = const(64)
F_STALE = const(128)
F_TIMEOUT = const(256)
F_REFUSED = const(512)
F_UNAWAITED = const(1024)
FLAG_NAMES = ("abort", "local", "forward", "broadcast", "send", "relay", "deliver", "stale", "timeout", "refused",
              "unawaited")

# Sync numbers of the jig's own Ver8 requests cycle through 0xC0..0xEF, where the
# protocol notes list no frame type (not even vendor-internal ones): a Ver6 drive on
# a mixed bus reads the sync byte as its frame type and must find an unknown one,
# never e.g. ServoEnable 0x2A or a firmware-flashing code.
INT_SYNC_FIRST = const(0xC0)
INT_SYNC_LAST = const(0xEF)

# Driver ids 0..SEEN_IDS-1 are tracked in the ``B_SEEN`` bitmap.
SEEN_IDS = const(30)

# Everything about the bridge that changes per frame lives in one integer array,
# ``Bridge.bs`` (an array store costs less than an attribute store on MicroPython, and
# the machine-code pump in ``jig.fastpath`` shares it):
B_STATE = const(0)  # IDLE, AWAIT_PC or AWAIT_INT
B_FWD = const(1)  # 1: a PC frame is being passed on to the driver bus (cut-through)
B_ROUTED = const(2)  # ... and its id is in: it is for the drivers
B_REL = const(3)  # 1: a driver frame is being passed on to the PC (cut-through)
B_CHECKED = const(4)  # ... and it matched the request
B_P_B0 = const(5)  # first two body bytes of the pending request: id and
B_P_B1 = const(6)  # (Ver6) type / (Ver8) sync; -1: nothing matches yet
B_DEADLINE = const(7)  # tick at which the pending wait times out
B_T_PC = const(8)  # tick of the last good frame from the PC
B_PC_FRAMES = const(9)  # good PC frames since boot (the safety stop arms on the first)
B_SEEN = const(10)  # bitmap of driver ids that answered
B_WAKE = const(11)  # 1: a client (jig.trace) waits for the bridge to be free: ask for the slow pass then
B_XHEAD = const(12)  # the next entry of Bridge.xt to write
B_XCUR = const(13)  # the entry of the forwarded request awaiting its reply (-1: none)
B_T_SLOW = const(14)  # tick of the last slow pass (poll)
B_SIZE = const(15)

# Bridge.xt: the last XT_N forwarded PC requests, 4 ints each: id, second body byte
# (Ver6 type / Ver8 sync), tick when the request's last stop bit had left on the driver
# bus, tick when the reply's last byte came in (-1: none); ReadTransactionTimes (0xF9).
XT_N = const(16)

# TRANSITIONS[state][event] = (action flags, next state)
TRANSITIONS = (
    # IDLE
    (
        (F_LOCAL, IDLE),
        (F_FORWARD, AWAIT_PC),
        (F_BROADCAST, IDLE),
        (F_SEND, AWAIT_INT),
        (F_STALE, IDLE),
        (F_STALE, IDLE),
        (0, IDLE),
        (0, IDLE),
    ),
    # AWAIT_PC: the PC moved on if it sends anything new
    (
        (F_ABORT | F_LOCAL, IDLE),
        (F_ABORT | F_FORWARD, AWAIT_PC),
        (F_ABORT | F_BROADCAST, IDLE),
        (F_REFUSED, AWAIT_PC),
        (F_RELAY, IDLE),
        (F_STALE, AWAIT_PC),
        (F_TIMEOUT, IDLE),
        (F_UNAWAITED, IDLE),
    ),
    # AWAIT_INT: local frames do not need the driver bus; PC traffic has priority
    (
        (F_LOCAL, AWAIT_INT),
        (F_ABORT | F_FORWARD, AWAIT_PC),
        (F_ABORT | F_BROADCAST, IDLE),
        (F_REFUSED, AWAIT_INT),
        (F_DELIVER, IDLE),
        (F_STALE, AWAIT_INT),
        (F_TIMEOUT, IDLE),
        (0, AWAIT_INT),
    ),
)


def _multipliers():
    m = bytearray(256)
    for i in range(256):
        m[i] = 1
    # The vendor library's longer waits for slow frame types.
    for t in (frame.SAVE_ALL_PARAMETERS, frame.GET_ROM_PARAMETER, frame.IO_ASSIGN_MAP_READ_ROM,
              frame.SERVO_ENABLE, frame.POS_TABLE_READ_ROM):
        m[t] = 5
    m[frame.CLEAR_POSITION] = 15
    m[frame.POS_TABLE_WRITE_ROM] = 20
    return m


TIMEOUT_MULTIPLIER = _multipliers()

# TRANSITIONS flattened for the hot path (here and in jig.fastpath): index
# state * N_EVENTS + event.
N_EVENTS = len(EVENT_NAMES)
FLAT_NEXT = bytes([nxt for row in TRANSITIONS for _f, nxt in row])
FLAT_FLAGS = array("H", [f for row in TRANSITIONS for f, _n in row])

# What an EV_DROP on the PC side means for a frame being cut through
_WHY_TIMEOUT = const(0)
_TICKS_MASK = const(0x3FFFFFFF)
_TICKS_HALF = const(0x20000000)
# A tick d µs on is ((t - _TICKS_MASK) + d - 1) & _TICKS_MASK, not (t + d) & _TICKS_MASK:
# on a 32-bit MicroPython port t + d past 2**30 - 1 is no small int but a long one, a
# heap allocation per forwarded request in the d µs before every tick wrap (every
# 17.9 min); t - _TICKS_MASK lies in -(2**30 - 1)..0, so every step stays a small int.
# jig.frame's values, folded here (a module attribute is a dictionary look-up per use)
_STUFF = const(0xAA)
_BROADCAST_ID = const(99)
# jig.capture's indices, record types and verdicts, folded here (const() takes no
# imported name, and a module attribute is a dictionary look-up per use; a host test
# checks they agree)
_CH_DRV_IN = const(2)
_CH_DRV_OUT = const(3)
_CH_PC_IN = const(0)
_CH_PC_OUT = const(1)
_CS_HEAD = const(1)
_CS_NEXT = const(15)
_CS_ON = const(0)
_CS_START = const(8)
_CS_T_IN = const(14)
_CS_TAIL = const(2)
_QUIET_US = const(2000)
# A forwarded request's end, this long or more after the last slow pass: the slow pass
# runs now, while the drive thinks, instead of a little later inside a frame passed on
# (the line watch's, 5 ms after a frame began, or the 10 ms one), where it would stall
# the copy: at most one every SLOW_AHEAD_US, never one a transaction.
SLOW_AHEAD_US = const(3000)
_T_DRV_PASSED = const(6)
_T_PC_PASSED = const(4)
_V_BAD_CRC = const(1)
_V_BAD_STUFFING = const(2)
_V_OVERLONG = const(4)
_V_RESYNC = const(6)
_V_SHORT = const(3)
_V_TIMEOUT = const(5)
ISR_BUSY = const(1 << 16)  # USART_ISR.BUSY (RM0433): a byte is being received (start bit seen)
ARM_BYTES = const(2)  # an armed bus is let go if no byte came within this many byte times
_PIECE = const(16)  # bytes of a paced reply written at a time (the USART's transmit FIFO)
_SHORT_STUB = const(3 << 8)  # _V_SHORT << 8: a stub ended with a tail (const() takes no imported name)


def drop_tick(st, now):
    """Tick of the last byte of the frame parser st just dropped: a frame cut by
    silence ended with the last byte before it, the others with the byte read now."""
    return st[S_T_LAST] if st[S_WHY] == _WHY_TIMEOUT else now


def drop_verdict(st):
    """The capture verdict of the frame parser st just dropped (EV_DROP)."""
    why = st[S_WHY]
    if why == _WHY_TIMEOUT:
        return _V_TIMEOUT
    if why == A_END:
        return _V_SHORT if st[S_DROP_N] < MIN_BODY else _V_BAD_CRC
    if why == A_STORE:
        return _V_OVERLONG
    if why == A_RESYNC:
        return _V_RESYNC
    if why == A_STUFF_ERROR:
        return _V_BAD_STUFFING
    return _V_BAD_CRC


def arm_overdue(rs, st, now):
    """rs was armed by a start bit on st's bus (``Rs485.arm``) more than ``ARM_BYTES``
    byte times ago and is still armed: the byte never came."""
    armed = rs.early[1]
    return armed >= 0 and (now - armed) & _TICKS_MASK > ARM_BYTES * st[S_BYTE_US]


def _quiet(st, now):
    """Parser st hunts for a header and its bus has been silent for a byte time: a
    byte starting now may be a frame's first."""
    return st[S_STATE] == HUNT and (now - st[S_T_LAST]) & _TICKS_MASK > st[S_BYTE_US]


def _isr_block(rs):
    """The USART ISR of rs's port as a word-indexed block, or None: only a plain port's,
    and only where it is an object (an address is for the machine-code pump)."""
    isr = getattr(rs.port, "isr", None)
    if not rs.plain or isr is None or isinstance(isr, int):
        return None
    return isr


class Bridge:
    def __init__(self, hal, up, down, handlers, params, counters, ver8=False, cut_through=True, due=None,
                 capture=None, down_parser=None):
        self.hal = hal
        self.up = up  # rs485.Rs485 on the PC bus
        self.down = down  # rs485.Rs485 on the driver bus
        self.handlers = handlers
        self.params = params
        self.ram = params.ram  # (bound once: the hot path reads ids and times from it)
        self.c = counters
        self.v = counters.v
        self.ver8 = ver8
        self.cut_through = cut_through
        # Cut through between plain ports, the other bus is taken (DE up) and the AA
        # sent on as soon as a byte that can start a header is in (``_early``).
        self.early_ok = cut_through and up.plain and down.plain
        # ... and earlier still, at the start bit of that byte (``watch_lines``), where
        # the receiving port shows its USART's ISR as a word-indexed block (``isr``:
        # the simulated ports; on the board the machine-code pump reads the register
        # itself, and this portable loop runs only store-and-forward there).
        self.up_isr = _isr_block(up) if self.early_ok else None
        self.down_isr = _isr_block(down) if self.early_ok else None
        self.head = 3 if ver8 else 2  # id, [sync], type
        # due[0]: tick by which the app's slow pass must run (the reply deadline).
        self.due = due if due is not None else array("i", [0])
        bs = array("i", bytes(4 * B_SIZE))
        bs[B_P_B0] = bs[B_P_B1] = -1
        bs[B_XCUR] = -1
        self.bs = bs
        self.xt = array("i", [-1] * (4 * XT_N))
        self.txbuf = bytearray(frame.MAX_WIRE)
        self.body = bytearray(frame.MAX_BODY)
        self.reply = bytearray(frame.MAX_DATA)
        self.client = None  # None: the PC; else an object with on_reply/on_timeout/on_abort
        # A client's request that *holds* PC frames (jig.trace): a PC frame for the driver
        # bus waits in ``held`` until that request's reply is in or its wait is over.
        self.holding = False
        self.held = bytearray(frame.MAX_BODY)
        self.held_n = 0
        self.held_t = 0
        self.sync_next = INT_SYNC_FIRST  # Ver8 sync numbers of jig-originated requests
        self.hdr = bytearray(2 + 2 * 3)  # AA CC + the (stuffed) head of a frame cut through
        self.hdr[0] = frame.STUFF
        self.hdr[1] = frame.HEADER2
        self.tail = bytes((frame.STUFF, frame.TAIL2))
        self._ticks = hal.ticks_us
        self._turnaround = counters.turnaround
        # Cut through, the raw bytes go straight to the port (queued or written: Rs485.part adds
        # nothing to it for an echo-free port whose write returns after the last stop bit).
        self.fwd_part = down.raw_part if down.tx_blocks and not down.track_echo else down.part
        self.rel_part = up.raw_part if up.tx_blocks and not up.track_echo else up.part
        # The recording of both buses (jig.capture): a record per frame received or
        # sent while cs[_CS_ON]; cs[_CS_START + channel] is where a frame's first byte was.
        if capture is None:
            from jig.capture import Capture

            capture = Capture(None, None, 64)
        self.cs = capture.cs
        self.cap_ring = capture.ring
        self.cap_put = capture.put
        self.down_p = down_parser  # what a relay the PC talks over had passed on (its record)

    def _record(self, kind, body, n, t_end=-1):
        """One capture record (kind: channel | verdict << 8) of body[0:n] whose last
        byte was at tick t_end (received: when its chunk was read), or now (sent: its
        last stop bit has just gone)."""
        self.cap_put(self.cs, self.cap_ring, kind, body, n, self._ticks() if t_end < 0 else t_end)

    def _record_passed(self, kind, body, n, t_in):
        """The record of a frame cut through (kind: _T_PC_PASSED or _T_DRV_PASSED | verdict
        << 8): it ended at tick t_in on its own bus, and now on the other."""
        self.cs[_CS_T_IN] = t_in
        self.cap_put(self.cs, self.cap_ring, kind, body, n, self._ticks())

    # --- what other parts of the jig read ------------------------------------------
    def seen(self):
        """Bitmap of the driver ids that answered since boot."""
        return self.bs[B_SEEN]

    def stream_window(self, now):
        """True when a stall of the main loop costs nothing (jig.capture streams then):
        a forwarded request awaits its reply and nothing is being passed on, or the PC
        has sent no frame for _QUIET_US."""
        bs = self.bs
        if bs[B_STATE] == AWAIT_PC and not bs[B_FWD] and not bs[B_REL]:
            return True
        d = ticks_diff(now, bs[B_T_PC])
        return d > _QUIET_US or d < 0  # (negative: the last PC frame is over half a tick period old)

    def busy(self):
        bs = self.bs
        return bs[B_STATE] != IDLE or bs[B_FWD] != 0

    def _event(self, ev):
        bs = self.bs
        k = bs[B_STATE] * N_EVENTS + ev
        bs[B_STATE] = FLAT_NEXT[k]
        return FLAT_FLAGS[k]

    def _abort(self):
        if self.client is None:
            self.v[C_ABORTS] += 1
        else:
            self.v[C_INT_ABORTS] += 1
            client = self.client
            self.client = None
            self.holding = False
            client.on_abort()

    # --- bytes from the PC -------------------------------------------------------
    def up_bytes(self, p, buf, n, now):
        """Parse buf[0:n] from the PC (arrived by tick now) and act on every event."""
        st = p.st
        scan = p.scan
        body = p.body
        bs = self.bs
        i = 0
        while i < n:
            j = scan(st, buf, i, n, body, TABLES, now)
            if bs[B_FWD] and j > i:
                self.fwd_part(buf, i, j - i)  # the raw bytes of the frame being cut through
            if st[S_EVENT]:
                self.pc_event(p, st[S_EVENT], now)
            i = j
        if self.early_ok:
            self._early(st, self.down, now, bs[B_STATE] == IDLE and not bs[B_FWD] and not bs[B_REL])

    def pc_event(self, p, ev, now):
        """Act on parser event ev of the PC side's parser p."""
        if ev == EV_START:
            self._pc_start(now)
        elif ev == EV_HEAD:
            self._pc_head(p.body, now)
        elif ev == EV_FRAME:
            self.on_pc_frame(p, now)
        elif ev == EV_DROP:
            self._pc_drop(p.st, p.body, now)

    def _pc_start(self, now):
        """Cut-through: a header from the PC. It goes on to the driver bus at once,
        before its id is known (routing follows at the id). While the jig's own
        request is out, the driver bus is its: wait for the id then."""
        bs = self.bs
        cs = self.cs
        cs[_CS_START + _CH_PC_IN] = now
        if self.up.early[1] >= 0:
            self.up.disarm()  # the PC talks: no answer's first byte goes to it now
        if bs[B_REL]:  # the PC talks over a reply in progress: stop relaying
            self._end_relay(True)
        if bs[B_STATE] == AWAIT_INT:
            return
        if self.down.early[0] < 0:  # (else its AA went at once, stamped then)
            cs[_CS_START + _CH_DRV_OUT] = now
        self.down.begin(self.hdr, 0, 2)
        bs[B_FWD] = 1
        bs[B_ROUTED] = 0
        self._watch_line(now)

    def _pc_head(self, body, now):
        """Cut-through: the id of a PC frame is known; route it now."""
        slave = body[0]
        bs = self.bs
        if bs[B_REL]:  # (a frame that started with a resync: no EV_START)
            self._end_relay(True)
        if slave == self.ram[P_SLAVE_ID]:
            if bs[B_FWD]:
                # Already on the driver bus as AA CC id: end it with a tail there. The
                # drives see a frame too short to be one and drop it; the jig's reply
                # is not held up behind a copy of the whole frame.
                bs[B_FWD] = 0
                self.fwd_part(self.tail, 0, 2)
                self.down.finish()
                if self.cs[_CS_ON]:
                    self._record(_CH_DRV_OUT | _SHORT_STUB, body, 1)
                if bs[B_WAKE]:
                    self.due[0] = now  # the driver bus is free again (jig.trace waits for it)
            return  # answered when complete
        if not bs[B_FWD]:
            if self.holding and bs[B_STATE] == AWAIT_INT:
                return  # held: it goes on whole when the jig's own request is done (on_pc_frame)
            # Not passed on from its header (the jig's own request was out, or the
            # frame began with a resync): it starts now with header and id, re-stuffed.
            hdr = self.hdr
            hdr[2] = slave
            k = 3
            if slave == _STUFF:
                hdr[3] = slave
                k = 4
            if self.down.early[0] < 0:
                self.cs[_CS_START + _CH_DRV_OUT] = now
            self.down.begin(hdr, 0, k)
            bs[B_FWD] = 1
            self._watch_line(now)
        bs[B_ROUTED] = 1
        v = self.v
        v[C_DOWN_OUT] += 1
        if slave == _BROADCAST_ID:
            flags = self._event(E_PC_BROADCAST)
            v[C_BROADCASTS] += 1
        else:
            flags = self._event(E_PC_FORWARD)
            v[C_FORWARDS] += 1
            bs[B_P_B1] = -1  # nothing matches until the request's second byte is known
        if flags & F_ABORT:
            self._abort()

    def _pc_drop(self, st, body, now):
        """A PC frame ended without being good (recorded); cut through, the copy being
        passed on ends with it."""
        bs = self.bs
        rec = self.cs[_CS_ON]
        if not bs[B_FWD]:
            if rec:
                self._record(_CH_PC_IN | drop_verdict(st) << 8, body, st[S_DROP_N], drop_tick(st, now))
            return
        bs[B_FWD] = 0
        self.down.finish()
        if bs[B_WAKE]:
            self.due[0] = now  # (jig.trace waits for a free driver bus)
        if rec:
            self._record_passed(_T_PC_PASSED | drop_verdict(st) << 8, body, st[S_DROP_N], drop_tick(st, now))
        if not bs[B_ROUTED]:
            return  # it broke off before its id: no driver was asked anything
        v = self.v
        why = st[S_WHY]
        if why == _WHY_TIMEOUT:
            v[C_CUT_TRUNCATED] += 1
        else:
            v[C_CUT_CORRUPT] += 1
        if bs[B_STATE] == AWAIT_PC and bs[B_P_B1] < 0:
            n = st[S_N]
            if n >= 2 and why != _WHY_TIMEOUT:
                # The drive got a whole frame with a bad CRC (or length): it may answer
                # it (status 0xAA), as it would on a direct line. Await that.
                self._pend_pc(body, n)
            else:
                self._event(E_CUT_SHORT)
                v[C_UNAWAITED] += 1

    def on_pc_frame(self, p, t_in):
        """A good frame from the PC, whose last byte arrived at tick t_in."""
        v = self.v
        v[C_UP_IN] += 1
        bs = self.bs
        bs[B_T_PC] = t_in
        bs[B_PC_FRAMES] += 1
        body = p.body
        rec = self.cs[_CS_ON]
        if bs[B_FWD]:
            # Cut through: the tail has gone out with the raw bytes.
            bs[B_FWD] = 0
            self.down.finish()
            if bs[B_WAKE] and bs[B_STATE] != AWAIT_PC:
                self.due[0] = t_in  # a broadcast has gone (jig.trace waits for a free driver bus)
            if rec:
                self._record_passed(_T_PC_PASSED, body, p.st[S_N], t_in)
            if bs[B_STATE] == AWAIT_PC:
                self._pend_pc(body, p.st[S_N])
                self._xt_request(body, self._ticks())
                cs = self.cs
                if cs[_CS_HEAD] != cs[_CS_TAIL] and (t_in - cs[_CS_NEXT]) & _TICKS_MASK < _TICKS_HALF:
                    self.due[0] = t_in  # records wait, the drive thinks: the slow pass streams now
                elif ticks_diff(t_in, bs[B_T_SLOW]) >= SLOW_AHEAD_US:
                    self.due[0] = t_in  # the drive thinks: the slow pass now, not inside its reply
            return
        if rec:
            self._record(_CH_PC_IN, body, p.st[S_N], t_in)
        slave = body[0]
        if slave == self.ram[P_SLAVE_ID]:
            ev = E_PC_LOCAL
        elif slave == _BROADCAST_ID:
            ev = E_PC_BROADCAST
        else:
            ev = E_PC_FORWARD
            if self.holding and bs[B_STATE] == AWAIT_INT:
                n = p.st[S_N]  # held until the jig's own request is done (_release)
                mem.copy(self.held, 0, body, 0, n)
                self.held_n = n
                self.held_t = t_in
                return
        if ev == E_PC_BROADCAST and self.holding and bs[B_STATE] == AWAIT_INT:
            n = p.st[S_N]
            mem.copy(self.held, 0, body, 0, n)
            self.held_n = n
            self.held_t = t_in
            return
        flags = self._event(ev)
        if flags & F_ABORT:
            self._abort()
            if bs[B_WAKE] and ev == E_PC_LOCAL:
                self.due[0] = t_in  # the PC's wait is over: the driver bus is free (jig.trace)
        if flags & F_LOCAL:
            self._local(p, t_in)
        elif flags & (F_FORWARD | F_BROADCAST):
            self._route_whole(flags, body, p.st[S_N], t_in)

    def _route_whole(self, flags, body, n, t_in):
        """Send a whole PC frame body[0:n] on (forward or broadcast) and await its reply."""
        v = self.v
        self._send(self.down, body, n, t_in)
        v[C_DOWN_OUT] += 1
        if flags & F_FORWARD:
            v[C_FORWARDS] += 1
            self._pend_pc(body, n)
            self._xt_request(body, self._ticks())
            cs = self.cs
            if cs[_CS_HEAD] != cs[_CS_TAIL] and (t_in - cs[_CS_NEXT]) & _TICKS_MASK < _TICKS_HALF:
                self.due[0] = t_in  # records wait, the drive thinks: the slow pass streams now
        else:
            v[C_BROADCASTS] += 1
            if self.bs[B_WAKE]:
                self.due[0] = t_in  # (jig.trace waits for a free driver bus)

    def _xt_request(self, body, t):
        """A forwarded PC request's last stop bit has left at tick t: a new entry of xt."""
        bs = self.bs
        k = bs[B_XHEAD]
        bs[B_XHEAD] = k + 1 if k + 1 < XT_N else 0
        bs[B_XCUR] = k
        xt = self.xt
        k *= 4
        xt[k] = body[0]
        xt[k + 1] = body[1]
        xt[k + 2] = t
        xt[k + 3] = -1

    def _xt_reply(self, t):
        """The awaited reply's last byte came in at tick t."""
        bs = self.bs
        k = bs[B_XCUR]
        if k >= 0:
            self.xt[4 * k + 3] = t
            bs[B_XCUR] = -1

    def transaction_times_into(self, out):
        """ReadTransactionTimes reply data (St, u8 n, n x (u8 id, u8 b1, u32 request sent,
        u32 reply in or 0xFFFFFFFF)), oldest first, into out; returns its length."""
        xt = self.xt
        k = self.bs[B_XHEAD]
        n = 0
        o = 2
        for _ in range(XT_N):
            j = 4 * k
            if xt[j] >= 0:
                out[o] = xt[j]
                out[o + 1] = xt[j + 1]
                frame.put_u32(out, o + 2, xt[j + 2])
                t = xt[j + 3]
                if t < 0:
                    out[o + 6] = out[o + 7] = out[o + 8] = out[o + 9] = 0xFF
                else:
                    frame.put_u32(out, o + 6, t)
                o += 10
                n += 1
            k = k + 1 if k + 1 < XT_N else 0
        out[0] = frame.STATUS_OK
        out[1] = n
        return o

    def _release(self):
        """The jig's own request that held PC frames is done: a PC frame held meanwhile
        goes on now, whole (as store-and-forward sends it)."""
        self.holding = False
        n = self.held_n
        if n:
            self.held_n = 0
            body = self.held
            flags = self._event(E_PC_BROADCAST if body[0] == _BROADCAST_ID else E_PC_FORWARD)
            if flags & F_ABORT:
                self._abort()
            # Its turnaround counts from the release: the wait behind the jig's own request is the
            # driver bus being busy (at most one sample's transaction), not the jig's handling.
            self._route_whole(flags, body, n, self._ticks())

    def _send(self, rs, body, blen, t_in):
        """Stuff body[0:blen] onto rs (re-stuffing a parsed body gives its received
        wire bytes) and record the turnaround from t_in, when the frame this answers
        or forwards ended."""
        n = frame.stuff_into(self.txbuf, body, blen)
        rs.send(self.txbuf, n)
        self._turnaround(ticks_diff(rs.t_tx_start, t_in))
        if self.cs[_CS_ON]:
            ch = _CH_DRV_OUT if rs is self.down else _CH_PC_OUT
            self.cs[_CS_START + ch] = rs.t_tx_start
            self._record(ch, body, blen)

    def _pend_pc(self, body, n):
        """Await the reply to the PC request body[0:n]. Its timeout: the frame type is
        body[1] (Ver6) or body[2] (Ver8); wait as long as the slower of the two
        readings asks (no layout assumed)."""
        m = TIMEOUT_MULTIPLIER[body[1]]
        if n > 2 and TIMEOUT_MULTIPLIER[body[2]] > m:
            m = TIMEOUT_MULTIPLIER[body[2]]
        self._pend(None, body[0], body[1], self.ram[P_REPLY_TIMEOUT_MS] * m)

    def _pend(self, client, b0, b1, timeout_ms):
        self.client = client
        bs = self.bs
        bs[B_P_B0] = b0
        bs[B_P_B1] = b1
        # The wait starts when our request has left the wire.
        d = ((self._ticks() - _TICKS_MASK) + timeout_ms * 1000 - 1) & _TICKS_MASK  # tick + timeout (above)
        bs[B_DEADLINE] = d
        due = self.due
        if (d - due[0]) & _TICKS_MASK >= _TICKS_HALF:  # d comes before due[0]
            due[0] = d

    def _early(self, st, rs, now, may):
        """After a chunk: it ended on an AA that can start a header (parser in HEADER)
        and a frame from this side would go on at its header (``may``: the PC's in
        IDLE, a driver's while a reply is awaited) -- take the other bus now and send
        that AA on at once (``Rs485.raise_early``): the frame then leaves the jig one
        byte time after it arrives, not two (the AA does not wait for its CC), and
        ``begin`` goes on from the CC. No header followed (the parser left HEADER
        without a start, or timed out there: ``gap``) -- let the bus go: it carried a
        lone AA, as a wire would have."""
        if st[S_STATE] == HEADER:
            if may and rs.early[0] < 0:
                rs.raise_early()
                # the copy's start for its record: its AA handed to the transmitter (after the pre-delay)
                self.cs[_CS_START + (_CH_DRV_OUT if rs is self.down else _CH_PC_OUT)] = self._ticks()
                self._watch_line(now)
        elif rs.early[0] >= 0:
            self._drop_early(rs)
        elif rs.early[1] >= 0 and st[S_STATE] == HUNT:
            rs.disarm()  # the byte whose start armed it was no AA

    def watch_lines(self, up_st, down_st, now):
        """An idle pass, cut through: a byte starting on a bus (its USART's BUSY flag)
        where a frame's AA would go on at once (``_early``: from the PC while the
        bridge is idle, from the drivers while a reply is awaited -- then only while
        the PC is quiet), after a silence of a byte
        time or more (a frame's first byte, not one of a stream of noise), with its
        parser hunting for a header: take the other bus now (``Rs485.arm``), so
        the DE pre-delay runs while the byte arrives instead of after it. ``_early``
        goes on when the byte is in, or lets the bus go if it is no AA; an idle pass
        lets it go if none came within ``ARM_BYTES`` byte times (the slow pass too:
        ``App._gap``)."""
        down = self.down
        if arm_overdue(down, up_st, now):
            down.disarm()
        up = self.up
        if arm_overdue(up, down_st, now):
            up.disarm()
        bs = self.bs
        if bs[B_FWD] or bs[B_REL]:
            return
        state = bs[B_STATE]
        up_isr = self.up_isr
        if up_isr is None:
            return
        if state == IDLE:
            if (up_isr[0] & ISR_BUSY and _quiet(up_st, now) and down.early[0] < 0 and down.early[1] < 0):
                down.arm(now)
        elif state == AWAIT_PC:
            # The PC bus is blind while armed (/RE tied to DE): only while the PC is quiet
            # (its line idle, not mid-frame, silent for a byte time); a frame it starts
            # anyway lets the bus go (_pc_start)
            down_isr = self.down_isr
            if (down_isr[0] & ISR_BUSY and not up_isr[0] & ISR_BUSY and _quiet(down_st, now)
                    and _quiet(up_st, now) and up.early[0] < 0 and up.early[1] < 0):
                up.arm(now)

    def _drop_early(self, rs):
        """No header followed the AA sent on early: let rs go (no copy to record)."""
        if rs.early[0] >= 0:
            rs.drop_early()
            self.cs[_CS_START + (_CH_DRV_OUT if rs is self.down else _CH_PC_OUT)] = -1

    def _watch_line(self, now):
        """A frame is being cut through: the slow pass must look at the line within the
        inter-byte timeout (and keeps doing so while the frame lasts) to end the
        transmission cleanly if the sender falls silent."""
        t = ((now - _TICKS_MASK) + self.ram[P_INTERBYTE_US]) & _TICKS_MASK  # now + timeout + 1 (above)
        due = self.due
        if (t - due[0]) & _TICKS_MASK >= _TICKS_HALF:  # t comes before due[0]
            due[0] = t

    def _local(self, p, t_in):
        self.v[C_LOCAL] += 1
        n = self.handlers.handle(p, self.reply)
        if n < 0:
            return  # deferred: the handler answers later through local_reply
        body = p.body
        head = self.head
        self.local_reply(body[0], body[head - 1], body[1] if head == 3 else -1, self.reply, n, t_in)
        self.handlers.after_reply(p)

    def local_reply(self, slave, ftype, sync, data, n, t_in):
        """Send the jig's reply (data[0:n], status first) to the PC; t_in is when the
        request ended (for the turnaround figures)."""
        v = self.v
        status = data[0]
        if status == frame.STATUS_FRAME_TYPE_ERROR or status == frame.STATUS_DATA_ERROR or status == frame.STATUS_FRAME_ERROR:
            v[C_LOCAL_ERRORS] += 1
        blen = frame.build_body(self.body, slave, ftype, data, 0, n, sync)
        self._send(self.up, self.body, blen, t_in)
        v[C_UP_OUT] += 1

    def local_reply_paced(self, slave, ftype, sync, data, n, t_in, body, wire, client):
        """``local_reply`` for a long reply, built in the caller's ``body`` and ``wire``
        buffers and written in pieces of 16 bytes (the USART's FIFO); between the
        pieces ``client.between()`` may send a request of its own on the driver bus
        (jig.trace: a sample slot due), while the piece before it leaves. A port
        without a transmit queue (``Rs485.queued``: hardware DE, echo, no ``queue``)
        sends it whole."""
        blen = frame.build_body(body, slave, ftype, data, 0, n, sync)
        m = frame.stuff_into(wire, body, blen)
        rs = self.up
        t_tx = self._ticks()
        if rs.queued:
            k = _PIECE if m > _PIECE else m
            rs.begin(wire, 0, k)
            client.between()
            while k < m:
                rs.drain()
                j = m - k
                if j > _PIECE:
                    j = _PIECE
                rs.part(wire, k, j)
                k += j
                client.between()
            rs.finish()
        else:
            # No transmit queue (or hardware DE, which drops between pieces): whole.
            rs.send(wire, m)
            client.between()
        self._turnaround(ticks_diff(t_tx, t_in))
        if self.cs[_CS_ON]:
            self.cs[_CS_START + _CH_PC_OUT] = t_tx
            self._record(_CH_PC_OUT, body, blen)
        self.v[C_UP_OUT] += 1

    # --- jig-originated requests ---------------------------------------------
    def request(self, client, slave, ftype, data, n, timeout_ms, framing=-1, hold=False):
        """Send a request of our own downstream; False if the bridge is busy.
        ``framing``: -1 the jig's protocol, 0 Ver6, 1 Ver8 (a mixed bus). ``hold``: a
        PC frame for the driver bus that comes meanwhile waits until this request is
        done (its reply in, or its wait over) instead of aborting it (jig.trace)."""
        if self.bs[B_FWD]:  # a broadcast is being cut through (the state is IDLE)
            return False
        flags = self._event(E_INTERNAL)
        if not flags & F_SEND:
            return False
        sync = -1
        if framing == 1 or (framing < 0 and self.ver8):
            sync = self.sync_next
            self.sync_next = sync + 1 if sync < INT_SYNC_LAST else INT_SYNC_FIRST
        blen = frame.build_body(self.body, slave, ftype, data, 0, n, sync)
        m = frame.stuff_into(self.txbuf, self.body, blen)
        self.down.send(self.txbuf, m)
        if self.cs[_CS_ON]:
            self.cs[_CS_START + _CH_DRV_OUT] = self.down.t_tx_start
            self._record(_CH_DRV_OUT, self.body, blen)
        v = self.v
        v[C_INT_REQUESTS] += 1
        v[C_DOWN_OUT] += 1
        self._pend(client, slave, self.body[1], timeout_ms)
        self.holding = hold
        return True

    # --- bytes from the drivers ------------------------------------------------
    def down_bytes(self, p, buf, n, now):
        """Parse buf[0:n] from the driver bus (arrived by tick now) and act on every event."""
        st = p.st
        scan = p.scan
        body = p.body
        bs = self.bs
        i = 0
        while i < n:
            j = scan(st, buf, i, n, body, TABLES, now)
            if bs[B_REL] and j > i:
                self.rel_part(buf, i, j - i)
            if st[S_EVENT]:
                self.down_event(p, st[S_EVENT], now)
            i = j
        if self.early_ok:
            self._early(st, self.up, now, bs[B_STATE] == AWAIT_PC and not bs[B_FWD] and not bs[B_REL])

    def down_event(self, p, ev, now):
        """Act on parser event ev of the driver side's parser p."""
        if ev == EV_START:
            self._down_start(now)
        elif ev == EV_HEAD:
            self._down_head(p.body, now)
        elif ev == EV_FRAME:
            self.on_down_frame(p, now)
        elif ev == EV_DROP:
            self._down_drop(p.st, p.body, now)

    def _down_drop(self, st, body, now):
        """A driver frame ended without being good (recorded); cut through, the copy
        being relayed ends with it."""
        bs = self.bs
        rec = self.cs[_CS_ON]
        if bs[B_REL]:
            checked = bs[B_CHECKED]
            self._end_relay(False)
            if rec:
                self._record_passed(_T_DRV_PASSED | drop_verdict(st) << 8, body, st[S_DROP_N], drop_tick(st, now))
            if checked:
                self.v[C_RELAY_CORRUPT] += 1
                self._event(E_REPLY)  # the answer came, broken: the PC's CRC check rejects it
                if bs[B_WAKE]:
                    self.due[0] = now  # (jig.trace waits for a free driver bus)
            # (else it broke off before its first two bytes: not the answer, still awaited)
        elif rec:
            self._record(_CH_DRV_IN | drop_verdict(st) << 8, body, st[S_DROP_N], drop_tick(st, now))

    def gap(self, p, from_pc, now):
        """Slow pass: let parser p judge the silence up to now. True if it dropped a
        partial frame (a frame being passed on is then ended cleanly)."""
        st = p.st
        p.scan(st, p.body, 0, 0, p.body, TABLES, now)
        if st[S_EVENT] == EV_DROP:
            if from_pc:
                self._pc_drop(st, p.body, now)
            else:
                self._down_drop(st, p.body, now)
        if st[S_STATE] == HUNT:
            self._drop_early(self.down if from_pc else self.up)  # a lone AA, then silence
            return True
        return False

    def _matches(self, body):
        # Stale-reply protection keeps its strength: for a Ver6 drive the second byte
        # is the frame type, as always; for a Ver8 drive it is the sync number, which
        # changes with every request, so a late reply to an older request never
        # matches (the type check adds nothing once the sync differs).
        bs = self.bs
        return body[0] == bs[B_P_B0] and body[1] == bs[B_P_B1]

    def _down_start(self, now):
        """Cut-through: a header on the driver bus while a PC request is awaited (and
        the PC is not talking). Nothing else talks there then but the drive asked, so
        it goes on to the PC at once; its first two bytes confirm it (``_down_head``)."""
        bs = self.bs
        cs = self.cs
        cs[_CS_START + _CH_DRV_IN] = now
        if bs[B_STATE] != AWAIT_PC or bs[B_FWD]:
            return
        if self.up.early[0] < 0:  # (else its AA went at once, stamped then)
            cs[_CS_START + _CH_PC_OUT] = now
        self.up.begin(self.hdr, 0, 2)
        bs[B_REL] = 1
        bs[B_CHECKED] = 0
        self._watch_line(now)

    def _down_head(self, body, now):
        """Cut-through: the first two body bytes of a driver frame are in. A frame being
        relayed that does not match (a late reply) is cut short with a tail: the PC
        sees a frame too short to be one, which its parser drops (counted as stale
        when the whole frame is in). A match not relayed yet goes on from here."""
        bs = self.bs
        relaying = bs[B_REL]
        if not relaying and (bs[B_STATE] != AWAIT_PC or bs[B_FWD]):
            return
        if not self._matches(body):
            if relaying:
                self.rel_part(self.tail, 0, 2)
                self._end_relay(False)
                if self.cs[_CS_ON]:
                    self._record(_CH_PC_OUT | _SHORT_STUB, body, 2)
            return
        if relaying:
            bs[B_CHECKED] = 1
            return
        b0 = body[0]
        b1 = body[1]
        # AA CC and the two bytes, re-stuffed (an id is never 0xAA; a sync may be)
        hdr = self.hdr
        hdr[2] = b0
        hdr[3] = b1
        k = 4
        if b1 == _STUFF:
            hdr[4] = b1
            k = 5
        if self.up.early[0] < 0:
            self.cs[_CS_START + _CH_PC_OUT] = now
        self.up.begin(hdr, 0, k)
        bs[B_REL] = 1
        bs[B_CHECKED] = 1
        self._watch_line(now)

    def _end_relay(self, count_abort):
        """Stop relaying a driver frame to the PC; ``count_abort``: the PC talks over it
        (the copy on the PC bus ends there, without a tail: recorded as such)."""
        bs = self.bs
        bs[B_REL] = 0
        self.up.finish()
        if count_abort and self.cs[_CS_ON] and self.down_p is not None:
            p = self.down_p
            self._record(_CH_PC_OUT | _V_TIMEOUT << 8, p.body, p.st[S_N])
        if count_abort and bs[B_CHECKED]:
            self.v[C_ABORTS] += 1
            self._event(E_CUT_SHORT)

    def on_down_frame(self, p, t_in):
        v = self.v
        v[C_DOWN_IN] += 1
        body = p.body
        bs = self.bs
        rec = self.cs[_CS_ON]
        if bs[B_REL]:
            # Relayed as it came: the tail has gone with the raw bytes.
            self._end_relay(False)
            if rec:
                self._record_passed(_T_DRV_PASSED, body, p.st[S_N], t_in)
            self._event(E_REPLY)
            if body[0] < SEEN_IDS:
                bs[B_SEEN] |= 1 << body[0]
            v[C_REPLIES] += 1
            v[C_UP_OUT] += 1
            self._xt_reply(t_in)
            if bs[B_WAKE]:
                self.due[0] = t_in  # (jig.trace waits for a free driver bus)
            return
        if rec:
            self._record(_CH_DRV_IN, body, p.st[S_N], t_in)
        match = bs[B_STATE] != IDLE and p.st[S_N] >= 5 and self._matches(body)
        if match and self.cut_through and self.client is None:
            match = False  # cut through, a reply to the PC is relayed from its head or not at all
        flags = self._event(E_REPLY if match else E_DOWN_OTHER)
        if flags & (F_RELAY | F_DELIVER) and body[0] < SEEN_IDS:
            bs[B_SEEN] |= 1 << body[0]
        if flags & F_RELAY:
            self._send(self.up, body, p.st[S_N], t_in)
            v[C_REPLIES] += 1
            v[C_UP_OUT] += 1
            self._xt_reply(t_in)
            if bs[B_WAKE]:
                self.due[0] = t_in  # (jig.trace waits for a free driver bus)
        elif flags & F_DELIVER:
            client = self.client
            self.client = None
            v[C_INT_REPLIES] += 1
            if self.holding:
                client.on_reply(p)  # (jig.trace: its next slot is already in due[0])
                self._release()
            else:
                self.due[0] = t_in  # let the client send its next request at once
                client.on_reply(p)
        elif flags & F_STALE:
            v[C_STALE] += 1

    def poll(self, now):
        """Time out the pending wait."""
        # (the wait starts when the request has gone, and no timeout cuts a frame
        # being passed on short: cut through, either is still in progress)
        bs = self.bs
        bs[B_T_SLOW] = now
        if (bs[B_STATE] != IDLE and not bs[B_REL] and not bs[B_FWD]
                and ticks_diff(now, bs[B_DEADLINE]) >= 0):
            self._event(E_TIMEOUT)
            client = self.client
            if client is None:
                self.v[C_TIMEOUTS] += 1
            else:
                self.client = None
                self.v[C_INT_TIMEOUTS] += 1
                client.on_timeout()
                if self.holding:
                    self._release()

    def wait_us(self, now):
        """µs until the pending wait times out (-1: nothing pending, or a frame is
        being passed on, which no timeout cuts short)."""
        bs = self.bs
        if bs[B_STATE] == IDLE or bs[B_REL] or bs[B_FWD]:
            return -1
        d = ticks_diff(bs[B_DEADLINE], now)
        return d if d > 0 else 0
