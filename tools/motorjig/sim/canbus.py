"""The simulated CAN bus of the virtual bench: frame time, arbitration, ACK, errors.

A ``CanBus`` carries classic CAN 2.0 frames between its ``CanNode``s at one bitrate.

* **Frame time**: the bits of the frame with worst-case bit stuffing (one stuff bit
  per 4 bits of the stuffed part after the first: SOF to CRC), plus CRC delimiter,
  ACK slot and delimiter, 7 bits EOF and 3 bits of intermission. A standard data
  frame of n bytes is 8n + 47 + (33 + 8n) // 4 bits (8 bytes: 135 bits, 270 µs at
  500 kbit/s), an extended one 8n + 67 + (53 + 8n) // 4 (8 bytes: 160 bits). A remote
  frame carries no data field whatever its DLC.
* **Arbitration**: when the bus goes idle (the end of the intermission; at once on an
  idle bus) every frame then pending at any node competes, and the one with the
  lowest arbitration field wins: the 11-bit base id first, then a standard frame
  beats an extended one with that base (its IDE bit is dominant), then the 18 low
  bits of an extended id, then a data frame beats a remote one (RTR dominant). The
  others wait for the next idle bus; equal keys go in the order they were queued.
  An error-passive node that has just transmitted waits 8 more bit times (suspend
  transmission), so the others get the bus first.
* **Delivery** at the end of EOF to every other node that is online and receives
  at this bitrate (listen-only nodes included): ``on_frame(t_us, can_id, ext, rtr,
  data)`` -- for a remote frame ``data`` is DLC zero bytes (a remote frame's DLC is
  ``len(data)`` of its ``transmit``, as in ``machine.CAN.send``). The sender gets
  ``on_tx_done(t_us, ok)`` with ``node.done`` set to the frame's ``TxFrame``.
* **ACK**: a frame is acknowledged by any other online node in normal mode at the
  bus's bitrate that is not bus-off. With none there it is an **ACK error**: nobody
  receives it, the sender's TEC goes up by 8 (not while it is already error
  passive: ISO 11898-1's exception for a lone passive transmitter, which therefore
  stays error passive and retries for ever instead of going bus-off) and the frame
  is sent again. The bus time of an error frame is the frame up to its ACK slot,
  a 6-bit error flag, an 8-bit error delimiter and the intermission.
* **Error frames on demand**: ``inject_errors(n)`` corrupts the next n frames put
  on the wire (a CRC error): the transmitter's TEC += 8, every other online
  receiver's REC += 1 (+ 8 is for the first receiver to flag, not modelled), the
  frame is sent again. A node at another bitrate (``node.bitrate``) neither
  receives nor acknowledges, and each frame it tries to send is a bit error there
  (TEC += 8): it goes bus-off after 32 tries, as a real one does.
* **Fault confinement** (simplified ISO 11898-1): a good transmission lowers TEC by
  1, a good reception REC by 1 (from above 127 back to 119..127: here 127); states
  error active (both < 96), warning (either >= 96), error passive (either >= 128),
  bus-off (TEC >= 256: it stops, its frames stay queued but are not sent until
  ``restart``, which after 128 x 11 recessive bits resets TEC and REC).
  ``node.on_state(t_us, state)`` is called on every change of state.
* **Load**: ``bus.load(t0, t1)`` is the fraction of [t0, t1) the bus was busy
  (frames and error frames, intermission included); ``bus.busy_us`` the total.

A listen-only node (``listen_only=True``) receives but never acknowledges nor
transmits (``transmit`` raises). Times are float µs on the bench's clock.
"""

import bisect

# Node error states (the numbers of machine.CAN's STATE_*).
STATE_ACTIVE = 1
STATE_WARNING = 2
STATE_PASSIVE = 3
STATE_BUS_OFF = 4

WARNING_LIMIT = 96
PASSIVE_LIMIT = 128
BUS_OFF_LIMIT = 256
ERROR_FRAME_BITS = 6 + 8  # error flag + error delimiter (after the bits before the error)
INTERMISSION_BITS = 3
SUSPEND_BITS = 8  # an error-passive transmitter's extra wait after its own frame
RECOVERY_BITS = 128 * 11  # bus-off recovery: 128 sequences of 11 recessive bits
MAX_KEEP = 100000  # busy intervals kept for load(); older ones are folded into a total


def frame_bits(ext, rtr, dlc):
    """Bits of a classic CAN frame on the wire with worst-case stuffing, intermission
    included. ``dlc``: data bytes (ignored for a remote frame)."""
    n = 0 if rtr else min(dlc, 8)
    stuffed = (54 if ext else 34) + 8 * n  # SOF .. CRC
    return stuffed + (stuffed - 1) // 4 + 10 + INTERMISSION_BITS  # + CRC del, ACK, ACK del, EOF


def arbitration_key(can_id, ext, rtr):
    """Sort key of a frame's arbitration field: lower wins."""
    if ext:
        base, low = can_id >> 18, can_id & 0x3FFFF
    else:
        base, low = can_id, 0
    return (base << 21) | ((1 if ext else 0) << 20) | (low << 1) | (1 if rtr else 0)


class TxFrame:
    """One frame a node has queued: what ``transmit`` returns."""

    __slots__ = ("node", "can_id", "ext", "rtr", "data", "key", "seq", "bits", "tries", "tag")

    def __init__(self, node, can_id, ext, rtr, data, seq):
        self.node = node
        self.can_id = can_id
        self.ext = bool(ext)
        self.rtr = bool(rtr)
        self.data = bytes(len(data)) if rtr else bytes(data)
        self.key = (arbitration_key(can_id, ext, rtr), seq)
        self.seq = seq
        self.bits = frame_bits(self.ext, self.rtr, len(self.data))
        self.tries = 0  # times it was on the wire (errors included)
        self.tag = None  # free for the owner (SimCan: its TX buffer index)


class CanNode:
    """A CAN controller on the bus. ``online`` False: it takes no part (not started)."""

    def __init__(self, bus, name, on_frame=None, on_tx_done=None, listen_only=False):
        self.bus = bus
        self.name = name
        self.on_frame = on_frame
        self.on_tx_done = on_tx_done
        self.on_state = None  # fn(t_us, state) on every change of error state
        self.listen_only = bool(listen_only)
        self.online = True
        self.bitrate = None  # None: the bus's; another value: it cannot talk to the others
        self.tec = 0
        self.rec = 0
        self.state = STATE_ACTIVE
        self.warning_entries = 0
        self.passive_entries = 0
        self.bus_off_entries = 0
        self.pending = []  # TxFrame, in the order queued
        self.done = None  # the frame on_tx_done is about
        self.suspend_until = 0.0
        self.recovering = False
        self.sent = 0  # frames sent and acknowledged
        self.received = 0

    # --- the node's side -----------------------------------------------------------
    def transmit(self, can_id, ext, rtr, data):
        """Queue one frame; returns its ``TxFrame``. Sent when it wins arbitration."""
        if self.listen_only:
            raise ValueError("%s: a listen-only node does not transmit" % self.name)
        if len(data) > 8:
            raise ValueError("%s: a classic CAN frame carries at most 8 bytes" % self.name)
        if not 0 <= can_id < (1 << 29 if ext else 1 << 11):
            raise ValueError("%s: CAN id 0x%X out of range" % (self.name, can_id))
        bus = self.bus
        bus._seq += 1
        f = TxFrame(self, can_id, ext, rtr, data, bus._seq)
        self.pending.append(f)
        bus._kick()
        return f

    def cancel(self, frame=None):
        """Withdraw one queued frame (None: all); no on_tx_done. True if one was queued
        (a frame on the wire now is not withdrawn: it completes)."""
        if frame is None:
            had = bool(self.pending)
            self.pending = [f for f in self.pending if f is self.bus._on_wire]
            return had
        if frame in self.pending and frame is not self.bus._on_wire:
            self.pending.remove(frame)
            return True
        return False

    def restart(self):
        """Leave bus-off: after 128 x 11 recessive bits, TEC = REC = 0, error active."""
        if self.state != STATE_BUS_OFF or self.recovering:
            return
        self.recovering = True
        bus = self.bus
        bus.clock.after(RECOVERY_BITS * bus.bit_us, self._recovered)

    def reset(self):
        """Counters and state as at power-on (a controller re-initialised)."""
        self.tec = self.rec = 0
        self.recovering = False
        self.state = STATE_ACTIVE
        self.warning_entries = self.passive_entries = self.bus_off_entries = 0

    def _recovered(self):
        if not self.recovering:
            return
        self.recovering = False
        self.tec = self.rec = 0
        self._update_state()
        self.bus._kick()

    # --- the bus's side ------------------------------------------------------------
    def talks(self):
        """Can take part in the protocol now (receive, acknowledge, send)?"""
        return self.online and self.state != STATE_BUS_OFF and (
            self.bitrate is None or self.bitrate == self.bus.bitrate)

    def _update_state(self):
        if self.state == STATE_BUS_OFF and (self.recovering or self.tec >= BUS_OFF_LIMIT):
            return
        if self.tec >= BUS_OFF_LIMIT:
            new = STATE_BUS_OFF
        elif self.tec >= PASSIVE_LIMIT or self.rec >= PASSIVE_LIMIT:
            new = STATE_PASSIVE
        elif self.tec >= WARNING_LIMIT or self.rec >= WARNING_LIMIT:
            new = STATE_WARNING
        else:
            new = STATE_ACTIVE
        if new == self.state:
            return
        old, self.state = self.state, new
        if new == STATE_BUS_OFF:
            self.bus_off_entries += 1
        elif new == STATE_PASSIVE:
            self.passive_entries += 1
        elif new == STATE_WARNING and old == STATE_ACTIVE:
            self.warning_entries += 1
        if self.on_state is not None:
            self.on_state(self.bus.clock.now, new)

    def _tx_error(self, ack_error=False):
        if ack_error and self.state == STATE_PASSIVE:
            return  # ISO 11898-1: a passive transmitter's ACK error does not count
        self.tec += 8
        self._update_state()

    def _rx_error(self):
        self.rec += 1
        self._update_state()

    def _tx_ok(self):
        self.sent += 1
        if self.tec:
            self.tec -= 1
            self._update_state()

    def _rx_ok(self):
        self.received += 1
        if self.rec > 127:
            self.rec = 127
            self._update_state()
        elif self.rec:
            self.rec -= 1
            self._update_state()


class CanBus:
    def __init__(self, clock, bitrate, name="can"):
        if bitrate <= 0:
            raise ValueError("bitrate must be positive")
        self.clock = clock
        self.name = name
        self.bitrate = bitrate
        self.bit_us = 1e6 / bitrate
        self.nodes = []
        self._seq = 0
        self._on_wire = None  # the TxFrame being sent
        self._idle_at = clock.now  # when the bus is (or was) next free
        self._arb_due = False
        self._errors_to_inject = 0
        self.frames = 0  # good frames
        self.error_frames = 0  # injected (or wrong-bitrate) error frames
        self.ack_errors = 0
        self.monitor = None  # fn(t_end, frame, outcome) for tests: "ok", "ack", "error"
        # busy intervals, for load(): starts, ends, busy time before each
        self._starts = []
        self._ends = []
        self._cum = []
        self._busy_before = 0.0  # busy time of intervals dropped from the lists
        self.busy_us = 0.0

    def add_node(self, name, on_frame=None, on_tx_done=None, listen_only=False):
        node = CanNode(self, name, on_frame, on_tx_done, listen_only)
        self.nodes.append(node)
        return node

    def remove_node(self, node):
        node.online = False
        node.pending = [f for f in node.pending if f is self._on_wire]
        if node in self.nodes:
            self.nodes.remove(node)

    def inject_errors(self, n=1):
        """The next n frames on the wire end in an error frame (a CRC error)."""
        self._errors_to_inject += n

    def frame_us(self, ext, rtr, dlc):
        """Time of one frame on the wire at this bitrate (worst-case stuffing, with
        intermission)."""
        return frame_bits(ext, rtr, dlc) * self.bit_us

    # --- load ------------------------------------------------------------------------
    def _busy_until(self, t):
        """Busy time from the start of the bench up to t."""
        i = bisect.bisect_right(self._starts, t) - 1
        if i < 0:
            return self._busy_before
        s, e = self._starts[i], self._ends[i]
        return self._cum[i] + (min(t, e) - s)

    def load(self, t0, t1):
        """The fraction of [t0, t1) the bus was busy (0..1)."""
        if t1 <= t0:
            return 0.0
        return (self._busy_until(t1) - self._busy_until(t0)) / (t1 - t0)

    def _busy(self, t0, t1):
        self._starts.append(t0)
        self._ends.append(t1)
        self._cum.append(self.busy_us)
        self.busy_us += t1 - t0
        if len(self._starts) > 2 * MAX_KEEP:
            k = len(self._starts) - MAX_KEEP
            self._busy_before = self._cum[k]
            del self._starts[:k], self._ends[:k], self._cum[:k]

    # --- arbitration and the wire -------------------------------------------------------
    def _kick(self):
        """Something may be sendable: arbitrate once the bus is idle."""
        if self._on_wire is not None or self._arb_due:
            return
        self._arb_due = True
        # Frames queued at this same instant join: the event runs after them.
        self.clock.at(max(self.clock.now, self._idle_at), self._arbitrate)

    def _arbitrate(self):
        self._arb_due = False
        if self._on_wire is not None:
            return
        now = self.clock.now
        best = None
        wait = None
        for nd in self.nodes:
            if not nd.pending or not nd.online or nd.state == STATE_BUS_OFF or nd.listen_only:
                continue
            if nd.suspend_until > now:
                wait = nd.suspend_until if wait is None else min(wait, nd.suspend_until)
                continue
            for f in nd.pending:
                if best is None or f.key < best.key:
                    best = f
        if best is None:
            if wait is not None:
                self._arb_due = True
                self.clock.at(wait, self._arbitrate)
            return
        self._start(best, now)

    def _start(self, f, t0):
        self._on_wire = f
        f.tries += 1
        node = f.node
        bit = self.bit_us
        if node.bitrate is not None and node.bitrate != self.bitrate:
            # Its bits make no sense to the others: an error in the arbitration field.
            self._errors(f, t0, t0 + (1 + 11 + ERROR_FRAME_BITS + INTERMISSION_BITS) * bit, "error")
            return
        if self._errors_to_inject > 0:
            self._errors_to_inject -= 1
            ack_at = f.bits - INTERMISSION_BITS - 7  # a CRC error is flagged after the ACK delimiter
            self._errors(f, t0, t0 + (ack_at + ERROR_FRAME_BITS + INTERMISSION_BITS) * bit, "error")
            return
        # The ACK is decided at the ACK slot: whoever is there then answers it.
        self.clock.at(t0 + (f.bits - INTERMISSION_BITS - 8) * bit, self._ack_slot, f, t0)

    def _ack_slot(self, f, t0):
        node = f.node
        bit = self.bit_us
        for nd in self.nodes:
            if nd is not node and not nd.listen_only and nd.talks():
                break
        else:
            self._errors(f, t0, self.clock.now + (ERROR_FRAME_BITS + INTERMISSION_BITS) * bit, "ack")
            return
        self._idle_at = t0 + f.bits * bit
        self._busy(t0, self._idle_at)
        self.clock.at(self._idle_at - INTERMISSION_BITS * bit, self._end_of_frame, f)

    def _errors(self, f, t0, t1, kind):
        self._idle_at = t1
        self._busy(t0, t1)
        self.clock.at(t1, self._end_of_error, f, kind)

    def _end_of_error(self, f, kind):
        self._on_wire = None
        node = f.node
        if kind == "ack":
            self.ack_errors += 1
            node._tx_error(ack_error=True)
        else:
            self.error_frames += 1
            node._tx_error()
            if node.bitrate is None or node.bitrate == self.bitrate:
                for nd in self.nodes:
                    if nd is not node and nd.talks():
                        nd._rx_error()
        if node.state == STATE_PASSIVE:
            node.suspend_until = self.clock.now + SUSPEND_BITS * self.bit_us
        if self.monitor is not None:
            self.monitor(self.clock.now, f, kind)
        self._kick()

    def _end_of_frame(self, f):
        t = self.clock.now
        node = f.node
        if f in node.pending:
            node.pending.remove(f)
        self.frames += 1
        for nd in list(self.nodes):
            if nd is node or not nd.talks():
                continue
            nd._rx_ok()
            if nd.on_frame is not None:
                nd.on_frame(t, f.can_id, f.ext, f.rtr, f.data)
        node._tx_ok()
        if node.state == STATE_PASSIVE:
            node.suspend_until = self._idle_at + SUSPEND_BITS * self.bit_us
        if self.monitor is not None:
            self.monitor(t, f, "ok")
        # The bus is free after the intermission; the next arbitration waits for it.
        self._on_wire = None
        self._kick()
        if node.on_tx_done is not None:
            node.done = f
            node.on_tx_done(t, True)
