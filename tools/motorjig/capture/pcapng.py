"""pcapng files of Plus-R and CAN records, and of EtherCAT frames (standard library only).

Layout (pcapng, little-endian, every block 32-bit aligned)::

    SHB   section header, shb_userappl = the writer; shb_hardware = the recording
          device when it is known (the jig: its name, record format, protocol)
    IDB   one per bus: link type LINKTYPE_USER0 (147) for the PC bus, USER1 (148)
          for the driver bus (the dissector registers on both and tells the
          buses apart by it), snaplen 0, if_name ("pc", "drivers"),
          if_description ("PC bus, 115200 baud, ..."),
          if_speed = baud, if_tsresol = 6 (µs); the jig's CAN bus (only when the
          jig has a CAN port) a third: LINKTYPE_CAN_SOCKETCAN (227), if_name
          "can", if_speed = the bitrate, read by Wireshark's own CAN dissector
    EPB   one per record: interface = the record's bus, timestamp in µs, the
          wire bytes, opt_comment = the verdict ("parser: bad_crc (...)"),
          for the jig's records a second opt_comment with the frame's start
          ("start: 694 us before the end (...)") or, for its noise and lost
          records (no bytes), the count ("jig: 3 records lost (...)"),
          epb_flags = direction (1 inbound, 2 outbound; absent when unknown)
          plus the link-layer error bit of the verdict (CRC error, too long,
          too short, wrong inter-frame gap = timeout, symbol error = stuffing);
          a CAN frame: the 16 bytes of a SocketCAN frame (``socketcan``), the
          direction, no comment

``Writer`` writes one stream (a file, or standard output for ``wireshark -k -i -``,
flushed after every packet); ``RotatingWriter`` starts a new file when one
reaches ``max_size`` bytes and keeps the newest ``files`` of them. Its files are
named as dumpcap names a ring buffer, ``bus_00001_20261201233000.pcapng`` (number,
local time the file was opened), so Wireshark's File > File Set lists them; the
numbers go on after the highest one already in the folder for that name, so a
second run never overwrites, and never deletes, an earlier run's files.
"""

import os
import re
import struct
import time

from motorjig.capture import record as R

#: link type per bus: LINKTYPE_USER0 / USER1, where the dissector registers itself
#: (wiretap's USER0 / USER1): the bus is known from it in every pass, where the
#: interface's name is not (a Lua field is empty while no tree is built)
LINKTYPE_CAN_SOCKETCAN = 227
LINKTYPES = {"pc": 147, "drivers": 148, "can": LINKTYPE_CAN_SOCKETCAN}
LINKTYPE = LINKTYPES["pc"]
# The SocketCAN header's identifier word (big-endian): these bits above the identifier
SOCKETCAN_EFF = 1 << 31
SOCKETCAN_RTR = 1 << 30

SHB, IDB, EPB = 0x0A0D0D0A, 0x00000001, 0x00000006
BYTE_ORDER_MAGIC = 0x1A2B3C4D
OPT_END, OPT_COMMENT = 0, 1
SHB_HARDWARE, SHB_USERAPPL = 2, 4
IF_NAME, IF_DESCRIPTION, IF_SPEED, IF_TSRESOL = 2, 3, 8, 9
EPB_FLAGS = 2

# epb_flags bits 24..31: link-layer-dependent errors
FLAG_CRC_ERROR = 1 << 24
FLAG_TOO_LONG = 1 << 25
FLAG_TOO_SHORT = 1 << 26
FLAG_INTERFRAME_GAP = 1 << 27
FLAG_SYMBOL_ERROR = 1 << 31
VERDICT_FLAGS = {
    R.BAD_CRC: FLAG_CRC_ERROR, R.OVERLONG: FLAG_TOO_LONG, R.SHORT: FLAG_TOO_SHORT,
    R.TIMEOUT: FLAG_INTERFRAME_GAP, R.BAD_STUFFING: FLAG_SYMBOL_ERROR,
}


def _pad(data):
    return data + b"\0" * (-len(data) % 4)


def _option(code, value):
    return struct.pack("<HH", code, len(value)) + _pad(value)


def _options(opts):
    if not opts:
        return b""
    return b"".join(_option(c, v) for c, v in opts) + _option(OPT_END, b"")


def _block(kind, body):
    body = _pad(body)
    length = 12 + len(body)
    return struct.pack("<II", kind, length) + body + struct.pack("<I", length)


def section_header(application, hardware=None):
    opts = [(SHB_USERAPPL, application.encode("utf-8"))]
    if hardware:
        opts.insert(0, (SHB_HARDWARE, hardware.encode("utf-8")))
    return _block(SHB, struct.pack("<IHHq", BYTE_ORDER_MAGIC, 1, 0, -1) + _options(opts))


def interface_description(bus, linktype=None):
    if linktype is None:
        linktype = LINKTYPES.get(bus.name, LINKTYPE)
    opts = [(IF_NAME, bus.name.encode("utf-8")), (IF_DESCRIPTION, bus.description.encode("utf-8"))]
    if bus.baud:
        opts.append((IF_SPEED, struct.pack("<Q", bus.baud)))
    opts.append((IF_TSRESOL, b"\x06"))
    return _block(IDB, struct.pack("<HHI", linktype, 0, 0) + _options(opts))


LINKTYPE_ETHERNET = 1


def ethernet_interface(name, description, speed=100000000):
    """The IDB of an Ethernet interface (an EtherCAT bus: Wireshark's ecatf/ecat/ecat_mailbox decode it)."""
    opts = [(IF_NAME, name.encode("utf-8")), (IF_DESCRIPTION, description.encode("utf-8")),
            (IF_SPEED, struct.pack("<Q", speed)), (IF_TSRESOL, b"\x06")]
    return _block(IDB, struct.pack("<HHI", LINKTYPE_ETHERNET, 0, 0) + _options(opts))


def ethernet_packet(interface, t_us, frame, direction=0, comment=None):
    """The EPB of one Ethernet frame on ``interface`` (its IDB's number) at ``t_us``; ``direction``
    1 inbound, 2 outbound as seen from the master's interface."""
    frame = bytes(frame)
    opts = [(OPT_COMMENT, comment.encode("utf-8"))] if comment else []
    if direction:
        opts.append((EPB_FLAGS, struct.pack("<I", direction)))
    head = struct.pack("<IIIII", interface, (t_us >> 32) & 0xFFFFFFFF, t_us & 0xFFFFFFFF, len(frame), len(frame))
    return _block(EPB, head + _pad(frame) + _options(opts))


def socketcan(rec):
    """A CAN Record as LINKTYPE_CAN_SOCKETCAN's 16 bytes: the identifier word (big-endian:
    bit 31 extended, bit 30 RTR), the data length, flags (0: classic CAN), two reserved
    bytes, the data padded to 8."""
    word = rec.can_id | (SOCKETCAN_EFF if rec.can_flags & R.CAN_EXT else 0) | (
        SOCKETCAN_RTR if rec.can_flags & R.CAN_RTR else 0)
    data = bytes(rec.data[:8])
    return struct.pack(">IBBBB", word, rec.can_dlc, 0, 0, 0) + data + b"\0" * (8 - len(data))


def packet(rec):
    """The EPB of one Record."""
    if rec.is_can:
        body = socketcan(rec)
        head = struct.pack("<IIIII", rec.bus, (rec.t_us >> 32) & 0xFFFFFFFF, rec.t_us & 0xFFFFFFFF, len(body), len(body))
        opts = [(EPB_FLAGS, struct.pack("<I", rec.direction))] if rec.direction else []
        return _block(EPB, head + body + _options(opts))
    flags = rec.direction | VERDICT_FLAGS.get(rec.verdict, 0)
    opts = [(OPT_COMMENT, R.comment(rec.verdict).encode("utf-8"))]
    more = R.count_comment(rec) if rec.count is not None else R.start_comment(rec)
    if more:
        opts.append((OPT_COMMENT, more.encode("utf-8")))
    if flags:
        opts.append((EPB_FLAGS, struct.pack("<I", flags)))
    n = len(rec.data)
    head = struct.pack("<IIIII", rec.bus, (rec.t_us >> 32) & 0xFFFFFFFF, rec.t_us & 0xFFFFFFFF, n, n)
    return _block(EPB, head + _pad(rec.data) + _options(opts))


def application_name():
    try:
        from importlib.metadata import version

        v = version("motorjig")
    except Exception:  # running from the source tree
        v = "unknown"
    return "MotorJig jigctl capture %s" % v


class Writer:
    """pcapng onto one binary stream; ``flush_each`` for pipes (live viewing)."""

    def __init__(self, stream, buses, flush_each=False, application=None, hardware=None):
        self.stream = stream
        self.buses = tuple(buses)
        self.flush_each = flush_each
        self.size = 0
        self.packets = 0
        head = section_header(application or application_name(), hardware)
        head += b"".join(interface_description(b) for b in self.buses)
        self._put(head)
        if flush_each:  # a reader of a pipe needs the header before the first packet
            self.stream.flush()

    def _put(self, data):
        self.stream.write(data)
        self.size += len(data)

    def write(self, rec):
        if not 0 <= rec.bus < len(self.buses):
            raise ValueError("record for bus %d, but the capture has %d" % (rec.bus, len(self.buses)))
        self.write_block(packet(rec))

    def write_block(self, block):
        self._put(block)
        self.packets += 1
        if self.flush_each:
            self.stream.flush()

    def flush(self):
        self.stream.flush()

    def close(self):
        self.stream.close()


def ring_name(path, index, when=None):
    """bus.pcapng, 3 -> bus_00003_20261201233000.pcapng (when: time.time(), default now)"""
    stem, ext = os.path.splitext(path)
    stamp = time.strftime("%Y%m%d%H%M%S", time.localtime(time.time() if when is None else when))
    return "%s_%05d_%s%s" % (stem, index, stamp, ext or ".pcapng")


def highest_ring_index(path):
    """The highest number among the ring files of path already on disk (0: none)."""
    stem, ext = os.path.splitext(path)
    folder = os.path.dirname(stem) or "."
    pattern = re.compile(re.escape(os.path.basename(stem)) + r"_([0-9]{5,})(?:_[0-9]{14})?" + re.escape(ext or ".pcapng")
                         + "$")
    try:
        names = os.listdir(folder)
    except OSError:
        return 0
    return max([int(m.group(1)) for m in map(pattern.match, names) if m] or [0])


class RotatingWriter:
    """Files of at most max_size bytes (a packet never splits; each file is a whole
    pcapng with its own header), the newest ``files`` kept (None: all)."""

    def __init__(self, path, buses, max_size, files=None, application=None, hardware=None):
        self.path = path
        self.buses = tuple(buses)
        self.max_size = max_size
        self.files = files
        self.application = application
        self.hardware = hardware
        self.index = highest_ring_index(path)  # the first file is the next number
        self.written = []  # paths, oldest first
        self.packets = 0
        self._w = None
        self._open_next()

    def _open_next(self):
        if self._w is not None:
            self._w.close()
        self.index += 1
        name = ring_name(self.path, self.index)
        self._w = Writer(open(name, "wb"), self.buses, application=self.application, hardware=self.hardware)
        self.written.append(name)
        while self.files is not None and len(self.written) > self.files:
            old = self.written.pop(0)
            try:
                os.remove(old)
            except OSError:
                pass

    @property
    def current(self):
        return self.written[-1]

    def write(self, rec):
        if not 0 <= rec.bus < len(self.buses):
            raise ValueError("record for bus %d, but the capture has %d" % (rec.bus, len(self.buses)))
        block = packet(rec)
        if self._w.packets and self._w.size + len(block) > self.max_size:
            self._open_next()
        self._w.write_block(block)
        self.packets += 1

    def flush(self):
        self._w.flush()

    def close(self):
        self._w.close()
