"""An ESI file (EtherCAT Slave Information, ETG.2000 XML) read into what MotorJig needs of a device.

The bench builds a simulated slave's SII EEPROM from it (``sii.image``), and a plan names its
drive's ESI so a record can say which device the station expected. Only the parts a master
reads from a slave are taken: identity, name and group, sync managers, FMMUs, the PDOs with
their entries, the mailbox protocols with the CoE details, the DC modes and the EEPROM's size
and config data. ``read(path)`` gives the file's devices; ``ValueError`` (one sentence, with the
file) for a file that is not such a description.
"""

import xml.etree.ElementTree as ET
from collections import namedtuple

Sm = namedtuple("Sm", "kind start size control enable")  # kind: MBoxOut, MBoxIn, Outputs, Inputs
PdoEntry = namedtuple("PdoEntry", "index sub bits name data_type")
Pdo = namedtuple("Pdo", "index name sm fixed entries")
DcMode = namedtuple("DcMode", "name assign_activate cycle_sync0 shift_sync0")
Device = namedtuple("Device", "vendor_id vendor_name product_code revision type_name name group_type group_name "
                              "sms fmmus rx_pdos tx_pdos mailbox coe dc_modes eeprom_bytes config_data")

# mailbox protocol bits of SII word 0x1C (ETG.1000.6)
MBX_AOE, MBX_EOE, MBX_COE, MBX_FOE, MBX_SOE = 0x01, 0x02, 0x04, 0x08, 0x10
# CoE details (SII general category): SDO, SDO info, PDO assign, PDO config, upload at startup, complete access
COE_SDO, COE_SDO_INFO, COE_PDO_ASSIGN, COE_PDO_CONFIG, COE_UPLOAD, COE_COMPLETE_ACCESS = 1, 2, 4, 8, 16, 32


def hex_number(text, what):
    """An ESI number: ``#x1A00`` (hex) or decimal; ValueError naming ``what``."""
    t = (text or "").strip()
    try:
        return int(t[2:], 16) if t[:2].lower() == "#x" else int(t, 10)
    except ValueError:
        raise ValueError("%s: %r is not a number (#x hex or decimal)" % (what, text)) from None


def _flag(el, attr):
    return (el.get(attr) or "0").strip().lower() in ("1", "true")


def _pdo(el, what):
    entries = []
    for e in el.findall("Entry"):
        index = hex_number(e.findtext("Index"), "%s entry index" % what)
        entries.append(PdoEntry(index, hex_number(e.findtext("SubIndex") or "0", "%s entry sub-index" % what),
                                hex_number(e.findtext("BitLen"), "%s entry bit length" % what),
                                e.findtext("Name") or "", e.findtext("DataType") or ""))
    sm = el.get("Sm")
    return Pdo(hex_number(el.findtext("Index"), "%s index" % what), el.findtext("Name") or "",
               None if sm is None else int(sm), _flag(el, "Fixed"), tuple(entries))


def _device(dev, vendor_id, vendor_name, groups, path):
    t = dev.find("Type")
    if t is None:
        raise ValueError("%s: a Device has no Type (product code, revision)" % path)
    sms = tuple(Sm(sm.text.strip(), hex_number(sm.get("StartAddress"), "Sm StartAddress"),
                   hex_number(sm.get("DefaultSize") or "0", "Sm DefaultSize"),
                   hex_number(sm.get("ControlByte"), "Sm ControlByte"), _flag(sm, "Enable"))
                for sm in dev.findall("Sm"))
    mailbox = 0
    coe = 0
    mb = dev.find("Mailbox")
    if mb is not None:
        for tag, bit in (("AoE", MBX_AOE), ("EoE", MBX_EOE), ("CoE", MBX_COE), ("FoE", MBX_FOE), ("SoE", MBX_SOE)):
            if mb.find(tag) is not None:
                mailbox |= bit
        c = mb.find("CoE")
        if c is not None:
            coe = COE_SDO
            for attr, bit in (("SdoInfo", COE_SDO_INFO), ("PdoAssign", COE_PDO_ASSIGN), ("PdoConfig", COE_PDO_CONFIG),
                              ("PdoUpload", COE_UPLOAD), ("CompleteAccess", COE_COMPLETE_ACCESS)):
                if _flag(c, attr):
                    coe |= bit
    dc = tuple(DcMode(m.findtext("Name") or "", hex_number(m.findtext("AssignActivate") or "0", "AssignActivate"),
                      hex_number(m.findtext("CycleTimeSync0") or "0", "CycleTimeSync0"),
                      hex_number(m.findtext("ShiftTimeSync0") or "0", "ShiftTimeSync0"))
               for m in dev.findall("Dc/OpMode"))
    ee = dev.find("Eeprom")
    size = hex_number(ee.findtext("ByteSize") or "2048", "Eeprom ByteSize") if ee is not None else 2048
    config = bytes.fromhex((ee.findtext("ConfigData") or "") if ee is not None else "")
    group_type = dev.findtext("GroupType") or ""
    return Device(vendor_id, vendor_name, hex_number(t.get("ProductCode"), "ProductCode"),
                  hex_number(t.get("RevisionNo") or "0", "RevisionNo"), (t.text or "").strip(),
                  (dev.findtext("Name") or "").strip(), group_type, groups.get(group_type, group_type),
                  sms, tuple((f.text or "").strip() for f in dev.findall("Fmmu")),
                  tuple(_pdo(p, "RxPdo") for p in dev.findall("RxPdo")),
                  tuple(_pdo(p, "TxPdo") for p in dev.findall("TxPdo")), mailbox, coe, dc, size, config)


def read(path):
    """The devices an ESI file describes, in its order; ValueError saying what is wrong."""
    try:
        root = ET.parse(path).getroot()
    except OSError as exc:
        raise ValueError("%s: cannot read the ESI file: %s" % (path, exc.strerror or exc)) from None
    except ET.ParseError as exc:
        raise ValueError("%s: not well-formed XML: %s" % (path, exc)) from None
    if root.tag != "EtherCATInfo":
        raise ValueError("%s: not an ESI file (its root is <%s>, not <EtherCATInfo>)" % (path, root.tag))
    vendor_id = hex_number(root.findtext("Vendor/Id"), "%s: Vendor Id" % path)
    vendor_name = (root.findtext("Vendor/Name") or "").strip()
    groups = {(g.findtext("Type") or ""): (g.findtext("Name") or "") for g in root.findall("Descriptions/Groups/Group")}
    devices = [_device(d, vendor_id, vendor_name, groups, path) for d in root.findall("Descriptions/Devices/Device")]
    if not devices:
        raise ValueError("%s: describes no device" % path)
    return devices


def sm_of(device, kind):
    """(number, ``Sm``) of the device's sync manager of ``kind`` (MBoxOut, MBoxIn, Outputs, Inputs), or None."""
    for n, sm in enumerate(device.sms):
        if sm.kind == kind:
            return n, sm
    return None
