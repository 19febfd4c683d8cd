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
"""

from jig import counters as K
from jig import frame
from jig.bridge import B_PC_FRAMES, B_T_PC, SEEN_IDS
from jig.compat import ticks_diff
from jig.compat import const
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


class SafetyStop:
    def __init__(self, bridge, params, counters):
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
        ms = self.params.ram[P_SAFETY_TIMEOUT_MS]
        if ms == 0 or self.bridge.bs[B_PC_FRAMES] == 0 or self.fired_at == self.bridge.bs[B_PC_FRAMES]:
            return -1
        d = ms * 1000 - ticks_diff(now, self.bridge.bs[B_T_PC])
        return d if d > 0 else 0

    def poll(self, now):
        b = self.bridge
        if not self.todo:
            # The same armed test as wait_us, inline: this runs on every main-loop pass.
            ms = self.params.ram[P_SAFETY_TIMEOUT_MS]
            if ms == 0 or b.bs[B_PC_FRAMES] == 0 or self.fired_at == b.bs[B_PC_FRAMES]:
                return
            if ticks_diff(now, b.bs[B_T_PC]) <= ms * 1000:
                return
            self.fired_at = b.bs[B_PC_FRAMES]
            self.c.v[K.C_SAFETY_STOPS] += 1
            self.todo = b.seen()
            self.next_id = 0
            if not self.todo:
                return
        if self.waiting or b.busy():
            return
        while self.next_id < SEEN_IDS and not (self.todo & (1 << self.next_id)):
            self.next_id += 1
        if self.next_id >= SEEN_IDS:
            self.todo = 0
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


class CanSafety:
    """The CAN port's master-silence stop (see the module's docstring); driven by
    ``jig.canport.CanPort``'s slow pass. ``port`` gives is_open, listen, lines (good
    host lines since open), t_host (tick of the last), seen (node bitmap), cv (its
    counters) and queue_frame()."""

    def __init__(self, port, params, counters):
        self.port = port
        self.params = params
        self.c = counters
        self.fired_at = -1  # port.lines when it last fired
        self.next_node = 0  # the next node id to stop (action 2), _NMT (action 1), 0: nothing to send
        self.nmt = bytearray(NMT_STOP_ALL)
        self.sdo = bytearray(QUICK_STOP_SDO)

    def reset(self):
        """The port opened or closed: nothing pending, armed again."""
        self.fired_at = -1
        self.next_node = 0

    def _armed(self):
        port = self.port
        pr = self.params.ram
        return (pr[P_CAN_SAFETY] != CAN_SAFETY_OFF and pr[P_SAFETY_TIMEOUT_MS] != 0 and port.is_open
                and not port.listen and port.lines != 0 and self.fired_at != port.lines)

    def wait_us(self, now):
        """µs until the silence limit (0: frames still to queue; -1: not armed)."""
        if self.next_node:
            return 0
        if not self._armed():
            return -1
        d = self.params.ram[P_SAFETY_TIMEOUT_MS] * 1000 - ticks_diff(now, self.port.t_host)
        return d if d > 0 else 0

    def poll(self, now):
        port = self.port
        if not self.next_node:
            if not self._armed():
                return
            if ticks_diff(now, port.t_host) <= self.params.ram[P_SAFETY_TIMEOUT_MS] * 1000:
                return
            self.fired_at = port.lines
            self.c.v[K.C_SAFETY_STOPS] += 1
            port.cv[_CC_SAFETY] += 1
            self.next_node = _NMT if self.params.ram[P_CAN_SAFETY] == CAN_SAFETY_NMT_STOP else 1
        if self.next_node == _NMT:
            if port.queue_frame(NMT_ID, 0, 0, self.nmt, 2):
                self.next_node = 0
            return
        seen = port.seen
        n = self.next_node
        while n < 128:
            if seen[n >> 3] & (1 << (n & 7)):
                if not port.queue_frame(SDO_RX_BASE + n, 0, 0, self.sdo, 8):
                    self.next_node = n  # the FIFO is full: the rest on the next pass
                    return
            n += 1
        self.next_node = 0
