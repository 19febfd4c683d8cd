"""EtherCAT frames (ETG.1000.4): an Ethernet frame of ethertype 0x88A4 carrying datagrams.

A frame is the 14-byte Ethernet header, a 2-byte EtherCAT header (little-endian: bits 0-10 the
length of the datagrams that follow, bits 12-15 the type, 1 for datagrams) and the datagrams.
A datagram is a 10-byte header -- command, index, address (position or station address and
register offset, or a 32-bit logical address), length with the "more datagrams follow" and
"circulating" bits, IRQ -- then its data and the 2-byte working counter. Every slave a frame
passes reads or writes the data of the datagrams addressed to it and adds to their counters.

``parse`` turns a received frame into ``Datagram``\\ s (ValueError, one sentence, for anything
that is not a whole EtherCAT frame); ``build`` makes one. Facts from the specification; the
names of the commands are the ones masters and Wireshark use.
"""

import struct

ETHERTYPE = 0x88A4
TYPE_DATAGRAMS = 1
ETH_HEADER = 14
ECAT_HEADER = 2
DATAGRAM_HEADER = 10
WKC_SIZE = 2
MIN_FRAME = 60  # an Ethernet frame without its FCS is padded to 60 bytes
MAX_DATA = 0x7FF  # the 11-bit length field
BROADCAST_MAC = b"\xff" * 6

# command code -> name (ETG.1000.4, table "EtherCAT command types")
COMMANDS = {0: "NOP", 1: "APRD", 2: "APWR", 3: "APRW", 4: "FPRD", 5: "FPWR", 6: "FPRW", 7: "BRD", 8: "BWR",
            9: "BRW", 10: "LRD", 11: "LWR", 12: "LRW", 13: "ARMW", 14: "FRMW"}
CODES = {name: code for code, name in COMMANDS.items()}
LOGICAL = (CODES["LRD"], CODES["LWR"], CODES["LRW"])


class Datagram:
    """One datagram: ``cmd`` (code), ``idx``, ``adp``/``ado`` (position or station address and
    register offset; for LRD/LWR/LRW ``logical`` is the 32-bit address instead), ``data``
    (bytearray: the slaves read and write it in place), ``wkc``, ``irq``, ``circulating``."""

    __slots__ = ("cmd", "idx", "adp", "ado", "data", "wkc", "irq", "circulating")

    def __init__(self, cmd, adp=0, ado=0, data=b"", idx=0, wkc=0, irq=0, circulating=False, logical=None):
        if isinstance(cmd, str):
            cmd = CODES[cmd]
        if cmd not in COMMANDS:
            raise ValueError("EtherCAT command %d is not one the specification defines (0..14)" % cmd)
        if len(data) > MAX_DATA:
            raise ValueError("a datagram carries at most %d bytes, not %d" % (MAX_DATA, len(data)))
        self.cmd, self.idx, self.wkc, self.irq, self.circulating = cmd, idx, wkc, irq, circulating
        if logical is not None:
            adp, ado = logical & 0xFFFF, logical >> 16
        self.adp, self.ado = adp & 0xFFFF, ado & 0xFFFF
        self.data = bytearray(data)

    @property
    def name(self):
        return COMMANDS[self.cmd]

    @property
    def logical(self):
        """The 32-bit logical address of an LRD/LWR/LRW (the address field read as one number)."""
        return self.adp | self.ado << 16

    def __repr__(self):
        where = ("logical 0x%08X" % self.logical if self.cmd in LOGICAL
                 else "adp 0x%04X ado 0x%04X" % (self.adp, self.ado))
        return "Datagram(%s idx %d %s, %d bytes, wkc %d)" % (self.name, self.idx, where, len(self.data), self.wkc)


def build(datagrams, src=b"\x02\x00\x00\x00\x00\x01", dst=BROADCAST_MAC):
    """An Ethernet frame carrying ``datagrams`` (padded to the 60-byte minimum)."""
    if not datagrams:
        raise ValueError("an EtherCAT frame carries at least one datagram")
    body = bytearray()
    for i, d in enumerate(datagrams):
        more = 0x8000 if i + 1 < len(datagrams) else 0
        length = len(d.data) | more | (0x4000 if d.circulating else 0)
        body += struct.pack("<BBHHHH", d.cmd, d.idx, d.adp, d.ado, length, d.irq) + d.data + struct.pack("<H", d.wkc)
    if len(body) > MAX_DATA:
        raise ValueError("the datagrams take %d bytes; an EtherCAT frame holds at most %d" % (len(body), MAX_DATA))
    frame = bytes(dst) + bytes(src) + struct.pack(">H", ETHERTYPE) + struct.pack("<H", len(body) | TYPE_DATAGRAMS << 12)
    frame += body
    return frame + bytes(max(0, MIN_FRAME - len(frame)))


def parse(frame):
    """The datagrams of a received EtherCAT frame; ValueError saying what is wrong otherwise."""
    frame = bytes(frame)
    if len(frame) < ETH_HEADER + ECAT_HEADER:
        raise ValueError("%d bytes are too short for an EtherCAT frame" % len(frame))
    (ethertype,) = struct.unpack_from(">H", frame, 12)
    if ethertype != ETHERTYPE:
        raise ValueError("ethertype 0x%04X is not EtherCAT's 0x%04X" % (ethertype, ETHERTYPE))
    (header,) = struct.unpack_from("<H", frame, ETH_HEADER)
    length, kind = header & MAX_DATA, header >> 12
    if kind != TYPE_DATAGRAMS:
        raise ValueError("EtherCAT frame type %d carries no datagrams (type 1 does)" % kind)
    end = ETH_HEADER + ECAT_HEADER + length
    if end > len(frame):
        raise ValueError("the EtherCAT header announces %d bytes of datagrams, the frame has %d"
                         % (length, len(frame) - ETH_HEADER - ECAT_HEADER))
    out, pos = [], ETH_HEADER + ECAT_HEADER
    while True:
        if pos + DATAGRAM_HEADER + WKC_SIZE > end:
            raise ValueError("datagram %d is cut off after %d bytes" % (len(out) + 1, end - pos))
        cmd, idx, adp, ado, flags, irq = struct.unpack_from("<BBHHHH", frame, pos)
        n = flags & MAX_DATA
        data_end = pos + DATAGRAM_HEADER + n
        if data_end + WKC_SIZE > end:
            raise ValueError("datagram %d announces %d bytes of data, %d are left" % (
                len(out) + 1, n, end - pos - DATAGRAM_HEADER - WKC_SIZE))
        if cmd not in COMMANDS:
            raise ValueError("datagram %d has command %d, not one the specification defines" % (len(out) + 1, cmd))
        (wkc,) = struct.unpack_from("<H", frame, data_end)
        out.append(Datagram(cmd, adp, ado, frame[pos + DATAGRAM_HEADER:data_end], idx, wkc, irq,
                            bool(flags & 0x4000)))
        pos = data_end + WKC_SIZE
        if not flags & 0x8000:
            return out
