"""The SII EEPROM image of an EtherCAT slave (ETG.1000.6 / ETG.2010): made from an ESI device, read back.

A master reads a slave's identity, mailbox layout and description from this EEPROM through the
ESC's registers 0x0500-0x050F. Words 0x00-0x3F are fixed fields (``WORDS``); the categories
start at word 0x40, each a type word, a size word (in words) and its data, and 0xFFFF ends them.
``image(device, serial, alias)`` builds the bytes for a simulated slave; ``categories`` and
``fields`` read an image back (the tests, ``jigctl ecat dump``). Layouts are facts of the
specification; the checksum is CRC-8 (x^8 + x^2 + x + 1, start 0xFF) over words 0-6.
"""

import struct

from motorjig.ecat import esi

# fixed fields: word address -> name (32-bit values take two words)
WORDS = {0x04: "alias", 0x07: "checksum", 0x08: "vendor_id", 0x0A: "product_code", 0x0C: "revision",
         0x0E: "serial", 0x14: "boot_rx_offset", 0x15: "boot_rx_size", 0x16: "boot_tx_offset", 0x17: "boot_tx_size",
         0x18: "rx_offset", 0x19: "rx_size", 0x1A: "tx_offset", 0x1B: "tx_size", 0x1C: "mailbox_protocols",
         0x3E: "size_kbit_minus_1", 0x3F: "version"}
LONG_WORDS = (0x08, 0x0A, 0x0C, 0x0E)

CAT_STRINGS, CAT_GENERAL, CAT_FMMU, CAT_SYNCM, CAT_TXPDO, CAT_RXPDO, CAT_DC, CAT_END = 10, 30, 40, 41, 50, 51, 60, 0xFFFF
CATEGORY_NAMES = {CAT_STRINGS: "strings", CAT_GENERAL: "general", CAT_FMMU: "FMMU", CAT_SYNCM: "SyncM",
                  CAT_TXPDO: "TxPDO", CAT_RXPDO: "RxPDO", CAT_DC: "DC"}
FMMU_USE = {"Outputs": 1, "Inputs": 2, "MBoxState": 3}
SM_TYPE = {"MBoxOut": 1, "MBoxIn": 2, "Outputs": 3, "Inputs": 4}
# ESI data type names -> CoE data type codes (CiA 301 / ETG.1000.6)
DATA_TYPES = {"BOOL": 1, "SINT": 2, "INT": 3, "DINT": 4, "USINT": 5, "UINT": 6, "UDINT": 7, "REAL": 8,
              "LINT": 0x15, "ULINT": 0x1B, "BYTE": 5, "WORD": 6, "DWORD": 7}
PORTS_MII_MII = 0x0011  # physical ports 0 and 1 MII ("YY")


def crc8(data):
    """The SII checksum: CRC-8, polynomial x^8 + x^2 + x + 1, start value 0xFF, no reflection."""
    crc = 0xFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc << 1 ^ 0x07) & 0xFF if crc & 0x80 else crc << 1 & 0xFF
    return crc


class _Strings:
    """The string category's table: index 0 means 'no string'."""

    def __init__(self):
        self.items = []

    def add(self, text):
        if not text:
            return 0
        raw = text.encode("ascii", "replace")[:255]
        if raw in self.items:
            return self.items.index(raw) + 1
        if len(self.items) == 255:
            return 0
        self.items.append(raw)
        return len(self.items)

    def data(self):
        return bytes([len(self.items)]) + b"".join(bytes([len(s)]) + s for s in self.items)


def _category(kind, data):
    data = bytes(data) + (b"\x00" if len(data) % 2 else b"")
    return struct.pack("<HH", kind, len(data) // 2) + data


def _pdos(pdos, strings):
    out = b""
    for p in pdos:
        out += struct.pack("<HBBBBH", p.index, len(p.entries), 0xFF if p.sm is None else p.sm, 0,
                           strings.add(p.name), 0x0010 if p.fixed else 0)
        for e in p.entries:
            out += struct.pack("<HBBBBH", e.index, e.sub, strings.add(e.name), DATA_TYPES.get(e.data_type.upper(), 0),
                               e.bits, 0)
    return out


def image(device, serial=0, alias=0):
    """The SII EEPROM bytes of ``device`` (an ``esi.Device``) with this serial number and alias."""
    size = max(128, device.eeprom_bytes)
    words = bytearray(0x80)
    config = device.config_data[:8].ljust(8, b"\x00")
    words[0:8] = config
    struct.pack_into("<H", words, 0x04 * 2, alias)
    words[0x07 * 2] = crc8(words[0:14])
    struct.pack_into("<IIII", words, 0x08 * 2, device.vendor_id, device.product_code, device.revision, serial)
    rx = esi.sm_of(device, "MBoxOut")
    tx = esi.sm_of(device, "MBoxIn")
    if rx and tx:
        mbx = (rx[1].start, rx[1].size, tx[1].start, tx[1].size)
        struct.pack_into("<HHHH", words, 0x14 * 2, *mbx)  # the bootstrap mailbox: the same
        struct.pack_into("<HHHHH", words, 0x18 * 2, *(mbx + (device.mailbox,)))
    struct.pack_into("<HH", words, 0x3E * 2, size * 8 // 1024 - 1, 1)
    strings = _Strings()
    name = strings.add(device.name)  # string 1: what masters (SOEM) show as the slave's name
    order = strings.add(device.type_name)
    group = strings.add(device.group_name or device.group_type)
    image_idx = 0
    general = struct.pack("<BBBBBBBBBBBBhBBHH12x", group, image_idx, order, name, 0, device.coe, 0, 0, 0,
                          1 if device.coe else 0, 0, 0, 0, group, 0, PORTS_MII_MII, 0)
    fmmu = bytes(FMMU_USE.get(f, 0) for f in device.fmmus)
    syncm = b"".join(struct.pack("<HHBBBB", sm.start, sm.size, sm.control, 0, 1 if sm.enable else 0,
                                 SM_TYPE.get(sm.kind, 0)) for sm in device.sms)
    tx_pdos = _pdos(device.tx_pdos, strings)
    rx_pdos = _pdos(device.rx_pdos, strings)
    cats = _category(CAT_STRINGS, strings.data()) + _category(CAT_GENERAL, general)
    if fmmu:
        cats += _category(CAT_FMMU, fmmu)
    if syncm:
        cats += _category(CAT_SYNCM, syncm)
    if tx_pdos:
        cats += _category(CAT_TXPDO, tx_pdos)
    if rx_pdos:
        cats += _category(CAT_RXPDO, rx_pdos)
    out = bytes(words) + cats + struct.pack("<H", CAT_END)
    if len(out) > size:
        raise ValueError("the SII of %s takes %d bytes, its EEPROM holds %d" % (device.name, len(out), size))
    return out + b"\xff" * (size - len(out))


def fields(data):
    """The fixed fields of an SII image: {name: value}."""
    out = {}
    for word, name in WORDS.items():
        fmt = "<I" if word in LONG_WORDS else "<H"
        out[name] = struct.unpack_from(fmt, data, word * 2)[0]
    out["checksum_ok"] = crc8(data[0:14]) == data[14]
    return out


def categories(data):
    """The categories of an SII image in order: [(type, data bytes)]; ValueError for a broken chain."""
    out, pos = [], 0x80
    while pos + 2 <= len(data):
        (kind,) = struct.unpack_from("<H", data, pos)
        if kind == CAT_END:
            return out
        if pos + 4 > len(data):
            break
        (words,) = struct.unpack_from("<H", data, pos + 2)
        end = pos + 4 + 2 * words
        if end > len(data):
            raise ValueError("SII category %d at byte %d runs past the EEPROM's end" % (kind, pos))
        out.append((kind, bytes(data[pos + 4:end])))
        pos = end
    raise ValueError("the SII's categories have no end marker (0xFFFF)")


def strings(data):
    """The string category's strings (index 1 first)."""
    for kind, raw in categories(data):
        if kind == CAT_STRINGS:
            out, pos = [], 1
            for _ in range(raw[0] if raw else 0):
                n = raw[pos]
                out.append(raw[pos + 1:pos + 1 + n].decode("ascii", "replace"))
                pos += 1 + n
            return out
    return []


def device_name(data):
    """The name a master shows for the slave (the general category's name string)."""
    names = strings(data)
    for kind, raw in categories(data):
        if kind == CAT_GENERAL and len(raw) > 3 and 0 < raw[3] <= len(names):
            return names[raw[3] - 1]
    return ""
