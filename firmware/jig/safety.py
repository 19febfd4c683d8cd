"""Master-silence safety stop (opt-in): stop the drivers when the PC goes quiet.

Like EtherCAT's process-data watchdog or a CANopen heartbeat consumer: once the PC
has sent at least one frame, if it then stays silent longer than
``safety_timeout_ms`` (0 = off), the jig sends MoveStop or EmergencyStop
(``safety_action`` 0 / 1) once to every driver id that has answered through the
bridge, and counts the event. ``safety_action`` 2 sends EmergencyStop and then
ServoEnable(off) to each: the station's choice for a run, so that a PC that died
mid-move leaves a drive with its servo off. It re-arms when the PC speaks again.

Mixed Ver6/Ver8 bus: the stop goes out in the jig's protocol first. A driver that
executed it answers OK in that layout; any other answer (a driver of the other
variant reads the frame as an unknown type and answers a frame-type error) makes
the jig send the stop once more in the other variant's framing to that id. Each
driver thus executes exactly one stop; on a bus of one variant nothing changes.
The servo-off of action 2 goes out in the framing the stop was executed in.

``CanSafety`` is the same watch on the CAN port (parameter 18 ``can_safety``, in the
same ``safety_timeout_ms`` window): while the SLCAN channel is open (normal mode;
listen-only never transmits), silence from the host longer than the window -- no
good SLCAN line; the ``O`` that opened it counts -- makes the jig send, once until
the host speaks again, either the NMT command "stop" to all nodes (action 1: id
0x000, data 02 00) or a CiA 402 quick stop to every node it has heard on the bus
(action 2: boot-up/heartbeat 0x701..0x77F or SDO reply 0x581..0x5FF; an expedited
SDO download of controlword 0x6040 = 0x0002 to 0x600 + node: 2B 40 60 00 02 00 00
00). The frames go through the port's TX FIFO; what does not fit goes on the next
slow pass. Counted in ``safety_stops`` and in the CAN port's ``can_safety_stops``.
After the quick stops (action 2), ``RESET_COMM_DELAY_US`` later, each of those nodes gets
the NMT command "reset communication" (id 0x000, data 82 node): its communication
objects go back to their power-on values (the run's PDO event timers, its heartbeat
period) and it waits in PRE-OPERATIONAL, so the bus falls quiet and the next user
finds the drive as it was switched on, less the axis's motion. Then, once the TX FIFO
has sent them (``END_SESSION_MAX_US`` at most), the jig ends the dead host's SLCAN session
(closes the channel and drops the lines it had not delivered): the next host opens a
channel of its own and receives nothing from before it.

``SafetyLease`` makes the two watches one lease, the run's safety net: the first of
them to fire makes the other fire too (the run's master is gone, whichever link showed
it first), each stops once, and when both are done the lease lets go: parameters 9,
10 and 18 go back to their saved (ROM) values in RAM. A run arms them in RAM only, so
after the stop nothing is armed that nobody asked for; a window saved to flash is a
setting, and stays. The lease keeps a notice of the stop (when, which ids and nodes)
until a PC takes it (diag 0xFB TakeSafetyNotice).
"""

from jig import counters as K
from jig import frame
from jig.bridge import B_PC_FRAMES, B_T_PC, SEEN_IDS
from jig.compat import const, ticks_add, ticks_diff
from jig.params import P_CAN_SAFETY, P_REPLY_TIMEOUT_MS, P_SAFETY_ACTION, P_SAFETY_TIMEOUT_MS

ACTION_EMERGENCY_STOP = const(1)
ACTION_EMERGENCY_STOP_SERVO_OFF = const(2)

# can_safety values
CAN_SAFETY_OFF = const(0)
CAN_SAFETY_NMT_STOP = const(1)
CAN_SAFETY_QUICK_STOP = const(2)
NMT_ID = const(0x000)
SDO_RX_BASE = const(0x600)  # the node's SDO server receives on 0x600 + node id
NMT_STOP_ALL = b"\x02\x00"  # command 0x02 (stop), node 0 (all)
QUICK_STOP_SDO = b"\x2B\x40\x60\x00\x02\x00\x00\x00"  # download 2 bytes to 0x6040 sub 0: 0x0002
_CC_SAFETY = const(16)  # jig.counters.CC_SAFETY
_NMT = const(255)  # CanSafety.next_node: the NMT stop is still to queue
NMT_RESET_COMM = const(0x82)
RESET_COMM_DELAY_US = const(100000)  # quick stop -> reset communication: the drive has acted on the SDO
END_SESSION_MAX_US = const(200000)  # the stop's frames left (or not, on a bus that takes none): end the session

# SafetyLease.busy / the notice's "buses" byte
LEASE_PC = const(1)  # the PC port's watch (Plus-R drives on the driver bus)
LEASE_CAN = const(2)  # the CAN port's watch
# The notice (TakeSafetyNotice's reply after its status byte): u8 pending, u8 buses
# that stopped (LEASE_*), u32 ms since it fired, u16 Plus-R ids stopped, 16 x u8 the
# CAN nodes stopped (bit n of byte n >> 3: node n).
NOTICE_LEN = const(24)
_N_IDS = const(6)
_N_NODES = const(8)


class SafetyLease:
    """The run's safety net: the PC port's and the CAN port's silence watches as one
    lease (see the module's docstring). ``pc`` and ``can`` are the watches (set by them)."""

    def __init__(self, params):
        self.params = params
        self.pc = None
        self.can = None
        self.busy = 0  # LEASE_* bits of the watches whose stop is under way
        self.notice = bytearray(NOTICE_LEN)
        self.age_s = 0  # whole seconds since it fired, up to t_mark
        self.t_mark = 0

    def fired(self, now, which):
        """A watch fires: the first makes a new notice and fires the other one too."""
        first = not self.busy
        self.busy |= which
        n = self.notice
        if first:
            for i in range(NOTICE_LEN):
                n[i] = 0
            n[0] = 1
            self.age_s = 0
            self.t_mark = now
        n[1] |= which
        if first:
            other = self.can if which == LEASE_PC else self.pc
            if other is not None:
                other.force(now)

    def stopped_ids(self, mask):
        n = self.notice
        n[_N_IDS] |= mask & 0xFF
        n[_N_IDS + 1] |= (mask >> 8) & 0xFF

    def stopped_nodes(self, seen):
        n = self.notice
        for i in range(16):
            n[_N_NODES + i] |= seen[i]

    def done(self, which):
        """A watch's stop is over; the last one lets the lease go."""
        if not self.busy & which:
            return
        self.busy &= ~which
        if not self.busy:
            pr = self.params
            for num in (P_SAFETY_TIMEOUT_MS, P_SAFETY_ACTION, P_CAN_SAFETY):
                pr.ram[num] = pr.rom[num]

    def poll(self, now):
        """The slow pass: the notice's age, in whole seconds (ticks_us wraps in 17 min)."""
        if self.notice[0]:
            d = ticks_diff(now, self.t_mark)
            if d >= 1000000:
                s = d // 1000000
                self.age_s += s
                self.t_mark = ticks_add(self.t_mark, s * 1000000)

    def take_notice(self, now, out, o):
        """The notice into out[o:o + NOTICE_LEN], then forgotten (a PC has told its user)."""
        self.poll(now)
        n = self.notice
        for i in range(NOTICE_LEN):
            out[o + i] = n[i]
        if n[0]:
            ms = self.age_s * 1000 + ticks_diff(now, self.t_mark) // 1000
            for i in range(4):
                out[o + 2 + i] = (ms >> (8 * i)) & 0xFF
            n[0] = 0
        return NOTICE_LEN


class SafetyStop:
    def __init__(self, bridge, params, counters, lease=None):
        self.lease = lease if lease is not None else SafetyLease(params)
        self.lease.pc = self
        self.bridge = bridge
        self.params = params
        self.c = counters
        self.fired_at = -1  # bridge.bs[B_PC_FRAMES] value when it last fired
        self.todo = 0  # bitmap of ids still to stop
        self.next_id = 0
        self.waiting = False
        self.other = False  # the current id gets the stop in the other variant's framing
        self.ftype = frame.MOVE_STOP
        self.servo_off = False  # the current id's stop is done: its ServoEnable(off) is next
        self.empty = bytearray(1)  # no data for a stop; one 0 byte (off) for ServoEnable

    def wait_us(self, now):
        """µs until the silence limit is reached or the next stop can go out (-1:
        not armed, or only a reply or the bridge's timeout moves things on)."""
        if self.todo:
            return -1 if self.waiting or self.bridge.busy() else 0
        if not self._armed():
            return -1
        d = self.params.ram[P_SAFETY_TIMEOUT_MS] * 1000 - ticks_diff(now, self.bridge.bs[B_T_PC])
        return d if d > 0 else 0

    def _armed(self):
        b = self.bridge
        return (self.params.ram[P_SAFETY_TIMEOUT_MS] != 0 and b.bs[B_PC_FRAMES] != 0
                and self.fired_at != b.bs[B_PC_FRAMES])

    def _fire(self, now):
        b = self.bridge
        self.fired_at = b.bs[B_PC_FRAMES]
        self.c.v[K.C_SAFETY_STOPS] += 1
        self.todo = b.seen()
        self.next_id = 0
        self.lease.fired(now, LEASE_PC)
        self.lease.stopped_ids(self.todo)
        if not self.todo:
            self.lease.done(LEASE_PC)

    def force(self, now):
        """The lease fires (the CAN port's watch saw the silence first): stop now, if armed."""
        if not self.todo and self._armed():
            self._fire(now)

    def poll(self, now):
        b = self.bridge
        if not self.todo:
            # The same armed test as wait_us, inline: this runs on every main-loop pass.
            ms = self.params.ram[P_SAFETY_TIMEOUT_MS]
            if ms == 0 or b.bs[B_PC_FRAMES] == 0 or self.fired_at == b.bs[B_PC_FRAMES]:
                return
            if ticks_diff(now, b.bs[B_T_PC]) <= ms * 1000:
                return
            self._fire(now)
            if not self.todo:
                return
        if self.waiting or b.busy():
            return
        while self.next_id < SEEN_IDS and not (self.todo & (1 << self.next_id)):
            self.next_id += 1
        if self.next_id >= SEEN_IDS:
            self.todo = 0
            self.lease.done(LEASE_PC)
            return
        n = 0
        if self.servo_off:
            ftype = frame.SERVO_ENABLE
            n = 1
        elif self.params.ram[P_SAFETY_ACTION]:
            ftype = frame.EMERGENCY_STOP
        else:
            ftype = frame.MOVE_STOP
        self.ftype = ftype
        framing = -1
        if self.other:
            framing = 0 if b.ver8 else 1
        if b.request(self, self.next_id, ftype, self.empty, n, self.params.ram[P_REPLY_TIMEOUT_MS], framing):
            self.waiting = True

    def _done(self):
        self.waiting = False
        self.other = False
        self.servo_off = False
        self.todo &= ~(1 << self.next_id)
        if not self.todo:
            self.lease.done(LEASE_PC)

    def _stopped(self):
        # The stop was executed (in the framing ``other`` says): servo off next, if asked.
        if self.params.ram[P_SAFETY_ACTION] == ACTION_EMERGENCY_STOP_SERVO_OFF:
            self.waiting = False
            self.servo_off = True
        else:
            self._done()

    def on_reply(self, p):
        if self.servo_off:
            self._done()
        # Executed: status 0 and nothing else, in the layout the stop was sent in.
        elif (not self.other and p.ftype == self.ftype and p.data_end - p.data_start == 1
                and p.body[p.data_start] == 0):
            self._stopped()
        elif self.other:
            self._stopped()
        else:
            self.waiting = False
            self.other = True  # not executed there: the other variant's framing next

    def on_timeout(self):
        self._done()

    def on_abort(self):
        # The PC is back: it is in charge again.
        self.waiting = False
        self.other = False
        self.servo_off = False
        self.todo = 0
        self.lease.done(LEASE_PC)


class CanSafety:
    """The CAN port's master-silence stop (see the module's docstring); driven by
    ``jig.canport.CanPort``'s slow pass. ``port`` gives is_open, listen, lines (good
    host lines since open), t_host (tick of the last), seen (node bitmap), cv (its
    counters) and queue_frame()."""

    def __init__(self, port, params, counters, lease=None):
        self.lease = lease if lease is not None else SafetyLease(params)
        self.lease.can = self
        self.port = port
        self.params = params
        self.c = counters
        self.fired_at = -1  # port.lines when it last fired
        self.next_node = 0  # the next node id to stop (action 2), _NMT (action 1), 0: nothing to send
        self.resetting = False  # next_node walks the stopped nodes for their reset communication
        self.ending = False  # the stop's frames are queued: the session ends when they have left
        self.end_by = 0
        self.reset_at = 0  # tick from which the resets may go
        self.stopped = bytearray(16)  # the nodes the quick stop went to
        self.nmt = bytearray(NMT_STOP_ALL)
        self.sdo = bytearray(QUICK_STOP_SDO)
        self.reset_comm = bytearray(2)

    def reset(self):
        """The port opened or closed: nothing pending, armed again."""
        self.fired_at = -1
        self.next_node = 0
        self.resetting = False
        self.ending = False
        self.lease.done(LEASE_CAN)

    def force(self, now):
        """The lease fires (the PC port's watch saw the silence first): stop now, if armed."""
        if not self.next_node and self._armed_any():
            self._fire(now)

    def _armed_any(self):
        # Armed whether or not the host has spoken on this port: the lease is the run's.
        port = self.port
        pr = self.params.ram
        return (pr[P_CAN_SAFETY] != CAN_SAFETY_OFF and pr[P_SAFETY_TIMEOUT_MS] != 0 and port.is_open
                and not port.listen and self.fired_at != port.lines)

    def _fire(self, now):
        port = self.port
        self.fired_at = port.lines
        self.c.v[K.C_SAFETY_STOPS] += 1
        port.cv[_CC_SAFETY] += 1
        self.resetting = False
        seen = port.seen
        for i in range(16):
            self.stopped[i] = seen[i]
        self.lease.fired(now, LEASE_CAN)
        self.lease.stopped_nodes(seen)
        self.next_node = _NMT if self.params.ram[P_CAN_SAFETY] == CAN_SAFETY_NMT_STOP else 1

    def _armed(self):
        # Its own silence watch: armed once the host has spoken on this port.
        return self.port.lines != 0 and self._armed_any()

    def wait_us(self, now):
        """µs until the silence limit (0: frames still to queue; -1: not armed)."""
        if self.ending:
            return 1000
        if self.next_node:
            if self.resetting:
                d = ticks_diff(self.reset_at, now)
                return d if d > 0 else 0
            return 0
        if not self._armed():
            return -1
        d = self.params.ram[P_SAFETY_TIMEOUT_MS] * 1000 - ticks_diff(now, self.port.t_host)
        return d if d > 0 else 0

    def _end(self, now):
        self.next_node = 0
        self.resetting = False
        self.ending = True
        self.end_by = ticks_add(now, END_SESSION_MAX_US)

    def poll(self, now):
        port = self.port
        if self.ending:
            if port.tx_idle() or ticks_diff(now, self.end_by) >= 0:
                port.end_session()  # (-> reset(): the lease's CAN part is done)
            return
        if not self.next_node:
            if not self._armed():
                return
            if ticks_diff(now, port.t_host) <= self.params.ram[P_SAFETY_TIMEOUT_MS] * 1000:
                return
            self._fire(now)
        if self.next_node == _NMT:
            if port.queue_frame(NMT_ID, 0, 0, self.nmt, 2):
                self._end(now)
            return
        if self.resetting and ticks_diff(now, self.reset_at) < 0:
            return
        stopped = self.stopped
        n = self.next_node
        while n < 128:
            if stopped[n >> 3] & (1 << (n & 7)):
                if self.resetting:
                    self.reset_comm[0] = NMT_RESET_COMM
                    self.reset_comm[1] = n
                    ok = port.queue_frame(NMT_ID, 0, 0, self.reset_comm, 2)
                else:
                    ok = port.queue_frame(SDO_RX_BASE + n, 0, 0, self.sdo, 8)
                if not ok:
                    self.next_node = n  # the FIFO is full: the rest on the next pass
                    return
            n += 1
        if self.resetting:
            self._end(now)
        else:
            self.resetting = True  # the quick stops are out: the resets after the drives acted on them
            self.reset_at = ticks_add(now, RESET_COMM_DELAY_US)
            self.next_node = 1
