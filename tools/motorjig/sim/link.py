"""Simulated RS-485 buses: wire time per byte, half-duplex, DE, collisions.

A ``Bus`` carries bytes between its ``Node``s at the configured baud, 10 bit
times per byte (8N1). A transmission is one ``Segment``: byte i occupies
``[t0 + i*bt, t0 + (i+1)*bt)``. When a segment has left the wire its bytes are
delivered, all at once, to every other node (and to the sender too if its
receiver hears its own transmission: ``echo``). A node added with
``stream=True`` (a UART receiver, like the jig's ports) instead gets the bytes
while the segment is still arriving: each chunk of ``Bus.chunk`` bytes (default
1) when the stop bit of its last byte ends. The rules below are applied per
chunk, so both kinds of receiver see the same bytes:

* a byte is only on the line if the sender's DE was high for its whole span --
  bytes sent while DE is low are lost (DE transitions are recorded with their
  time stamps in ``Node.de_log``);
* bytes of two segments that overlap in time corrupt each other (collision);
* nodes with ``auto_de`` (USB adapters with automatic direction control, the
  simulated drivers) drive DE exactly around their own segments;
* fault injection: ``Node.corrupt(n)`` flips one bit in each of the node's next
  ``n`` transmissions (a frame byte that is not part of a stuffing pair, so the
  receiver sees a CRC error rather than a framing error); the choice is made when
  the segment is queued, and looks at the byte the node sent before it, so a frame
  written in several pieces (cut-through) is corrupted the same way, once.

Per-chunk events are only scheduled for a segment that a streaming node hears;
everything else costs one event per segment, as before.
"""

from collections import deque

BITS_PER_BYTE = 10


def _garbage(b):
    return (b ^ 0x5A ^ 0xFF) & 0xFF


def _flippable(data, i, prev):
    """Can data[i] get a bit flipped without changing the frame's framing?"""
    b = data[i]
    before = data[i - 1] if i > 0 else prev
    return b != 0xAA and b != 0xAB and before != 0xAA


def flip_for_crc(data):
    """Copy of a wire frame with one bit flipped before its tail, keeping the framing.

    The byte chosen (scanning back from the last CRC byte) is neither 0xAA, 0xAB nor
    the second byte of a stuffed ``AA AA`` pair, so the frame still parses and
    fails only its CRC check. Data without such a byte is returned unchanged.
    """
    out = bytearray(data)
    for i in range(len(out) - 3, 1, -1):
        if out[i] not in (0xAA, 0xAB) and out[i - 1] != 0xAA:
            out[i] ^= 0x01
            break
    return bytes(out)


def flip_in_piece(data, prev=-1):
    """Like ``flip_for_crc`` for a piece of a frame: flip the last byte that is
    neither 0xAA, 0xAB nor preceded by 0xAA (``prev``: the byte sent before the
    piece, -1 if none). Returns (data, index of the flipped byte or -1)."""
    for i in range(len(data) - 1, -1, -1):
        if _flippable(data, i, prev):
            out = bytearray(data)
            out[i] ^= 0x01
            return bytes(out), i
    return data, -1


def _tail_end(data, start, esc):
    """Index after the first frame tail (AA EE, not a stuffed AA AA) in data[start:],
    or -1; esc: the byte before start was an unpaired 0xAA. Returns (index, esc)."""
    for i in range(start, len(data)):
        b = data[i]
        if esc:
            esc = False
            if b == 0xEE:
                return i + 1, False
        else:
            esc = b == 0xAA
    return -1, esc


class Node:
    def __init__(self, bus, name, on_rx=None, echo=False, auto_de=False, record=True, stream=False):
        self.bus = bus
        self.name = name
        self.on_rx = on_rx
        self.echo = echo
        self.stream = stream  # True: get each chunk as its last stop bit ends
        self.auto_de = auto_de
        self.record = record
        self.de = False
        self.t_rise = None
        self.t_fall = None
        self.de_log = []  # (time µs, 0/1)
        self.tx_until = 0.0  # end of our last scheduled segment
        self.hw_pre_us = 0.0  # hardware-DE mode of a UART: DE lead/lag around segments
        self.hw_post_us = 0.0
        self.hw_de = False
        self.corrupt_next = 0  # fault: transmissions left whose bytes get one bit flipped
        self.last_byte = -1  # the last byte we queued (corruption looks across pieces)
        self.corrupt_hold = False  # a frame of ours was corrupted and its tail is not sent yet
        self.corrupt_esc = False  # while holding: the last byte was an unpaired 0xAA
        self.on_start = None  # fn(segment): another node's transmission starts (a UART's start bit)
        self.deaf_with_de = False  # /RE tied to DE: the receiver is off while our DE is up

    def corrupt(self, n=1):
        """Flip a bit (see ``flip_for_crc``) in each of our next n transmissions."""
        self.corrupt_next = n

    def set_de(self, on, t=None):
        on = bool(on)
        if on == self.de:
            return
        if t is None:
            t = self.bus.clock.now
        self.de = on
        if on:
            self.t_rise = t
        else:
            self.t_fall = t
        if self.record:
            self.de_log.append((t, 1 if on else 0))

    def deaf(self, t0, t1):
        """With /RE tied to DE (``deaf_with_de``): was our receiver off at some time in
        [t0, t1) (DE up then)? Judged from the last DE edges, which is exact for the
        chunk just ending."""
        if not self.deaf_with_de:
            return False
        if self.de:
            return self.t_rise is not None and self.t_rise < t1
        return self.t_fall is not None and self.t_fall > t0

    def driven_range(self, seg):
        """Indices [i0, i1) of seg's bytes sent while our DE was high."""
        if self.auto_de or self.hw_de:
            return 0, len(seg.data)
        if self.t_rise is None:
            return 0, 0
        bt = seg.bt
        t0 = seg.t0
        n = len(seg.data)
        # first byte whose start is at or after the rise
        d = (self.t_rise - t0) / bt
        i0 = 0 if d <= 0 else int(d) + (0 if d == int(d) else 1)
        if self.de:
            i1 = n
        else:
            if self.t_fall < self.t_rise:
                return 0, 0
            i1 = int((self.t_fall - t0) / bt + 1e-9)
            if i1 > n:
                i1 = n
        if i0 >= i1:
            return 0, 0
        return i0, i1

    def transmit(self, data):
        return self.bus.transmit(self, data)


class Segment:
    __slots__ = ("node", "t0", "bt", "data", "end", "got", "lost")

    def __init__(self, node, t0, bt, data):
        self.node = node
        self.t0 = t0
        self.bt = bt
        self.data = data
        self.end = t0 + bt * len(data)
        self.got = None  # bytes delivered so far (streamed segments)
        self.lost = 0


class Bus:
    def __init__(self, clock, baud, name="bus", chunk=1):
        if chunk < 1:
            raise ValueError("chunk must be at least 1 byte")
        self.clock = clock
        self.name = name
        self.chunk = chunk  # bytes per delivery to streaming nodes
        self.nodes = []
        self.in_flight = []  # segments still on the wire
        self.recent = deque()  # delivered segments that may still overlap one in flight
        self.set_baud(baud)
        self.collisions = 0  # bytes corrupted by overlapping transmissions
        self.lost = 0  # bytes sent with DE low
        self.corrupted = 0  # transmissions changed by Node.corrupt
        self.unheard = 0  # bytes a receiver missed because its own DE was up (/RE tied to DE)
        self.busy_us = 0.0  # wire time of every byte sent (the bus load over a span: its growth / the span)
        self.monitor = None  # optional fn(segment, delivered bytes) for tests

    def set_baud(self, baud):
        self.baud = baud
        self.bt = BITS_PER_BYTE * 1e6 / baud

    def add_node(self, name, on_rx=None, echo=False, auto_de=False, record=True, stream=False):
        node = Node(self, name, on_rx, echo, auto_de, record, stream)
        self.nodes.append(node)
        return node

    def _streamed(self, sender):
        """Does a streaming receiver hear sender's transmissions?"""
        for nd in self.nodes:
            if nd.stream and nd.on_rx is not None and (nd is not sender or nd.echo):
                return True
        return False

    def transmit(self, node, data, t0=None):
        """Queue data from node (after its previous segment); returns the end time."""
        clock = self.clock
        now = clock.now
        if t0 is None or t0 < now:
            t0 = now
        if node.hw_de:
            # The UART raises DE itself, waits the lead time, sends, waits the lag.
            if t0 < node.tx_until:
                t0 = node.tx_until
            node.set_de(1, t0)
            t0 += node.hw_pre_us
        elif t0 < node.tx_until:
            t0 = node.tx_until
        data = bytes(data)
        if (node.corrupt_next > 0 or node.corrupt_hold) and data:
            data = self._corrupt(node, data)
        if data:
            node.last_byte = data[-1]
        seg = Segment(node, t0, self.bt, data)
        self.busy_us += len(data) * self.bt
        node.tx_until = seg.end
        self.in_flight.append(seg)
        if node.auto_de:
            node.set_de(1, t0)
        for nd in self.nodes:
            if nd.on_start is not None and nd is not node and data:
                clock.at(t0, nd.on_start, seg)
        n = len(data)
        if n > 1 and self._streamed(node):
            seg.got = bytearray()
            b = self.chunk if self.chunk < n else n
            clock.at(t0 + b * seg.bt, self._deliver_chunk, seg, 0, b)
        else:
            clock.at(seg.end, self._deliver, seg)
        return seg.end

    def receiving(self, node, delay=0.0):
        """Is a byte of another node's arriving at node now (a UART's ISR.BUSY: from
        its start bit, seen ``delay`` µs after the segment began, to the segment's
        end)? Only what is on the line counts: a sender's DE must be up."""
        now = self.clock.now
        for seg in self.in_flight:
            other = seg.node
            if (other is not node and seg.t0 + delay <= now < seg.end
                    and (other.de or other.auto_de or other.hw_de)):
                return True
        return False

    def _overlapping(self, seg):
        for other in self.in_flight:
            if other.node is not seg.node and other.t0 < seg.end and other.end > seg.t0:
                yield other
        for other in self.recent:
            if other.node is not seg.node and other.t0 < seg.end and other.end > seg.t0:
                yield other

    def _retire(self, seg):
        self.in_flight.remove(seg)
        recent = self.recent
        recent.append(seg)  # deliveries come in order of end time
        lo = self.clock.now
        for s in self.in_flight:
            if s.t0 < lo:
                lo = s.t0
        while recent and recent[0].end <= lo:
            recent.popleft()

    def _corrupt(self, node, data):
        """Node.corrupt: one flipped bit per frame, also when the frame is sent in
        pieces (after a flip, none until that frame's tail has been sent)."""
        start = 0
        esc = node.corrupt_esc
        while True:
            if node.corrupt_hold:
                end, esc = _tail_end(data, start, esc)
                if end < 0:
                    break
                node.corrupt_hold = False
                start = end
            if node.corrupt_next <= 0 or start >= len(data):
                break
            prev = data[start - 1] if start else node.last_byte
            piece, i = flip_in_piece(data[start:], prev)
            if i < 0:
                break
            data = data[:start] + piece
            node.corrupt_next -= 1
            self.corrupted += 1
            node.corrupt_hold = True
            start += i + 1
            esc = False  # the flipped byte is not 0xAA
        node.corrupt_esc = esc
        return data

    def _on_line(self, seg, a, b):
        """seg's bytes [a, b) as they are on the line now: bytes sent with DE low
        left out, bytes that overlap another talker's segment garbled."""
        i0, i1 = seg.node.driven_range(seg)
        if i0 < a:
            i0 = a
        if i1 > b:
            i1 = b
        seg.lost += (b - a) - (i1 - i0 if i1 > i0 else 0)
        if i0 >= i1:
            return b""
        data = seg.data
        out = None
        bt = seg.bt
        if len(self.in_flight) > 1 or self.recent:
            for other in self._overlapping(seg):
                # our bytes overlapping [other.t0, other.end)
                x = max(i0, int((other.t0 - seg.t0) / bt))
                y = min(i1, int((other.end - seg.t0) / bt + 0.999999))
                for i in range(x, y):
                    if out is None:
                        out = bytearray(data)
                    out[i] = _garbage(out[i])
                    self.collisions += 1
        if out is not None:
            data = bytes(out)
        if i0 or i1 != len(data):
            data = data[i0:i1]
        return data

    def _finish(self, seg):
        node = seg.node
        if node.auto_de:
            node.set_de(0, seg.end)
        elif node.hw_de:
            node.set_de(0, seg.end + node.hw_post_us)
        self.lost += seg.lost
        self._retire(seg)

    def _deliver(self, seg):
        data = self._on_line(seg, 0, len(seg.data))
        self._finish(seg)
        self._hand_out(seg, data)

    def _deliver_chunk(self, seg, a, b):
        """Bytes [a, b) of a streamed segment, at the end of byte b-1's stop bit."""
        data = self._on_line(seg, a, b)
        n = len(seg.data)
        if data:
            seg.got += data
            t = self.clock.now
            for nd in self.nodes:
                if nd.stream and nd.on_rx is not None and (nd is not seg.node or nd.echo):
                    if nd is not seg.node and nd.deaf(seg.t0 + a * seg.bt, t):
                        self.unheard += len(data)
                        continue
                    nd.on_rx(data, t)
        if b < n:
            c = b + self.chunk
            if c > n:
                c = n
            self.clock.at(seg.t0 + c * seg.bt, self._deliver_chunk, seg, b, c)
            return
        self._finish(seg)
        self._hand_out(seg, bytes(seg.got), streamed=True)

    def _hand_out(self, seg, data, streamed=False):
        if self.monitor is not None:
            self.monitor(seg, data)
        if not data:
            return
        t = seg.end
        for nd in self.nodes:
            if nd.on_rx is None or (streamed and nd.stream):
                continue
            if nd is seg.node and not nd.echo:
                continue
            if nd is not seg.node and nd.deaf(seg.t0, t):
                self.unheard += len(data)
                continue
            nd.on_rx(data, t)

    def inject(self, data, t=None):
        """Noise/foreign bytes on the line from an anonymous talker at time t."""
        if not hasattr(self, "_noise"):
            self._noise = self.add_node("noise", auto_de=True, record=False)
        if t is None:
            self.transmit(self._noise, data)
        else:
            self.clock.at(t, self.transmit, self._noise, data)
