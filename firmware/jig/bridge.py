"""Routing between the PC bus and the driver bus: forward, await, relay.

The machine is ``TRANSITIONS`` below (docs/bridge.md renders it): states IDLE,
AWAIT_PC (a forwarded PC request waits for its reply) and AWAIT_INT (a request of
the jig's own -- bus scan, safety stop -- is out); events are the classified
frames from either side and the timeout.

* Frames for the jig's own id are answered by ``handlers`` on the PC port.
* Every other id is forwarded byte-for-byte (re-stuffing the parsed body gives the
  received wire bytes: stuffing is canonical) and one matching reply is relayed
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
* The jig itself (bus scan, safety stop) sends through ``request``; their replies
  go to that client, never to the PC.

Forwarding and relaying are blocking sends (``rs485.send`` returns when the line
is released), so the transient FORWARDING/RELAYING states never see an event.
"""

from jig import counters as K
from jig import frame
from jig.compat import const, ticks_add, ticks_diff
from jig.params import P_REPLY_TIMEOUT_MS, P_SLAVE_ID

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
EVENT_NAMES = ("pc_local", "pc_forward", "pc_broadcast", "internal", "reply", "down_other", "timeout")

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
FLAG_NAMES = ("abort", "local", "forward", "broadcast", "send", "relay", "deliver", "stale", "timeout", "refused")

# Sync numbers of the jig's own Ver8 requests cycle through 0xC0..0xEF, where the
# protocol notes list no frame type (not even vendor-internal ones): a Ver6 drive on
# a mixed bus reads the sync byte as its frame type and must find an unknown one,
# never e.g. ServoEnable 0x2A or a firmware-flashing code.
INT_SYNC_FIRST = const(0xC0)
INT_SYNC_LAST = const(0xEF)

# Driver ids 0..SEEN_IDS-1 are tracked in the ``seen`` bitmap (a small int on MicroPython).
SEEN_IDS = const(30)

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


class Bridge:
    def __init__(self, hal, up, down, handlers, params, counters, ver8=False):
        self.hal = hal
        self.up = up  # rs485.Rs485 on the PC bus
        self.down = down  # rs485.Rs485 on the driver bus
        self.handlers = handlers
        self.params = params
        self.c = counters
        self.ver8 = ver8
        self.state = IDLE
        self.txbuf = bytearray(frame.MAX_WIRE)
        self.body = bytearray(frame.MAX_BODY)
        self.reply = bytearray(frame.MAX_DATA)
        # First two body bytes of the pending request: id and (Ver6) type / (Ver8) sync.
        self.p_b0 = -1
        self.p_b1 = -1
        self.deadline = 0
        self.client = None  # None: the PC; else an object with on_reply/on_timeout/on_abort
        self.seen = 0  # bitmap of driver ids that answered
        self.t_pc = 0  # tick of the last frame from the PC
        self.pc_frames = 0  # PC frames since boot (the safety stop arms on the first)
        self.sync_next = INT_SYNC_FIRST  # Ver8 sync numbers of jig-originated requests

    def _event(self, ev):
        flags, self.state = TRANSITIONS[self.state][ev]
        return flags

    def _abort(self):
        if self.client is None:
            self.c.v[K.C_ABORTS] += 1
        else:
            self.c.v[K.C_INT_ABORTS] += 1
            client = self.client
            self.client = None
            client.on_abort()

    # --- frames from the PC ----------------------------------------------------
    def on_pc_frame(self, p, t_in):
        """A good frame from the PC, whose last byte arrived at tick t_in."""
        v = self.c.v
        v[K.C_UP_IN] += 1
        self.t_pc = t_in
        self.pc_frames += 1
        slave = p.slave
        if slave == self.params.ram[P_SLAVE_ID]:
            ev = E_PC_LOCAL
        elif slave == frame.BROADCAST_ID:
            ev = E_PC_BROADCAST
        else:
            ev = E_PC_FORWARD
        flags = self._event(ev)
        if flags & F_ABORT:
            self._abort()
        if flags & F_LOCAL:
            self._local(p, t_in)
        elif flags & (F_FORWARD | F_BROADCAST):
            self._send(self.down, p.body, p.body_len, t_in)
            v[K.C_DOWN_OUT] += 1
            if flags & F_FORWARD:
                v[K.C_FORWARDS] += 1
                # The frame type is body[1] (Ver6) or body[2] (Ver8): wait as long
                # as the slower of the two readings asks (no layout assumed).
                body = p.body
                m = TIMEOUT_MULTIPLIER[body[1]]
                if TIMEOUT_MULTIPLIER[body[2]] > m:
                    m = TIMEOUT_MULTIPLIER[body[2]]
                self._pend(None, slave, body[1], self.params.ram[P_REPLY_TIMEOUT_MS] * m)
            else:
                v[K.C_BROADCASTS] += 1

    def _send(self, rs, body, blen, t_in):
        """Stuff body[0:blen] onto rs (re-stuffing a parsed body gives its received
        wire bytes) and record the turnaround from t_in, when the frame this answers
        or forwards ended."""
        n = frame.stuff_into(self.txbuf, body, blen)
        rs.send(self.txbuf, n)
        self.c.turnaround(ticks_diff(rs.t_tx_start, t_in))

    def _pend(self, client, b0, b1, timeout_ms):
        self.client = client
        self.p_b0 = b0
        self.p_b1 = b1
        # The wait starts when our request has left the wire.
        self.deadline = ticks_add(self.hal.ticks_us(), timeout_ms * 1000)

    def _local(self, p, t_in):
        v = self.c.v
        v[K.C_LOCAL] += 1
        n = self.handlers.handle(p, self.reply)
        if n < 0:
            return  # deferred: the handler answers later through local_reply
        self.local_reply(p.slave, p.ftype, p.sync, self.reply, n, t_in)
        self.handlers.after_reply(p)

    def local_reply(self, slave, ftype, sync, data, n, t_in):
        """Send the jig's reply (data[0:n], status first) to the PC; t_in is when the
        request ended (for the turnaround figures)."""
        status = data[0]
        if status == frame.STATUS_FRAME_TYPE_ERROR or status == frame.STATUS_DATA_ERROR or status == frame.STATUS_FRAME_ERROR:
            self.c.v[K.C_LOCAL_ERRORS] += 1
        blen = frame.build_body(self.body, slave, ftype, data, 0, n, sync)
        self._send(self.up, self.body, blen, t_in)
        self.c.v[K.C_UP_OUT] += 1

    # --- jig-originated requests ---------------------------------------------
    def request(self, client, slave, ftype, data, n, timeout_ms, framing=-1):
        """Send a request of our own downstream; False if the bridge is busy.
        ``framing``: -1 the jig's protocol, 0 Ver6, 1 Ver8 (a mixed bus)."""
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
        v = self.c.v
        v[K.C_INT_REQUESTS] += 1
        v[K.C_DOWN_OUT] += 1
        self._pend(client, slave, self.body[1], timeout_ms)
        return True

    def busy(self):
        return self.state != IDLE

    # --- frames from the drivers ----------------------------------------------
    def on_down_frame(self, p, t_in):
        v = self.c.v
        v[K.C_DOWN_IN] += 1
        # Stale-reply protection keeps its strength: for a Ver6 drive the second
        # byte is the frame type, as before; for a Ver8 drive it is the sync
        # number, which changes with every request, so a late reply to an older
        # request never matches (the type check adds nothing once the sync differs).
        body = p.body
        match = (
            self.state != IDLE
            and p.body_len >= 5
            and body[0] == self.p_b0
            and body[1] == self.p_b1
        )
        flags = self._event(E_REPLY if match else E_DOWN_OTHER)
        if flags & (F_RELAY | F_DELIVER) and p.slave < SEEN_IDS:
            self.seen |= 1 << p.slave
        if flags & F_RELAY:
            self._send(self.up, p.body, p.body_len, t_in)
            v[K.C_REPLIES] += 1
            v[K.C_UP_OUT] += 1
        elif flags & F_DELIVER:
            client = self.client
            self.client = None
            v[K.C_INT_REPLIES] += 1
            client.on_reply(p)
        elif flags & F_STALE:
            v[K.C_STALE] += 1

    def poll(self, now):
        """Time out the pending wait."""
        if self.state != IDLE and ticks_diff(now, self.deadline) >= 0:
            self._event(E_TIMEOUT)
            client = self.client
            if client is None:
                self.c.v[K.C_TIMEOUTS] += 1
            else:
                self.client = None
                self.c.v[K.C_INT_TIMEOUTS] += 1
                client.on_timeout()

    def wait_us(self, now):
        """µs until the pending wait times out (-1: nothing pending)."""
        if self.state == IDLE:
            return -1
        d = ticks_diff(self.deadline, now)
        return d if d > 0 else 0
