"""CiA 301 facts as names for people: SDO abort codes, EMCY error codes, NMT commands and
states, device profiles, and what a CAN frame is by its COB-ID (``describe_frame``).

Only tables and the small functions that look things up in them; the frames themselves
come from python-can, the protocol work from python-canopen.
"""

import struct

# SDO abort codes (CiA 301, table "SDO abort codes").
ABORT_CODES = {
    0x05030000: "toggle bit not alternated",
    0x05040000: "SDO protocol timed out",
    0x05040001: "client/server command specifier not valid or unknown",
    0x05040002: "invalid block size",
    0x05040003: "invalid sequence number",
    0x05040004: "CRC error",
    0x05040005: "out of memory",
    0x06010000: "unsupported access to an object",
    0x06010001: "attempt to read a write only object",
    0x06010002: "attempt to write a read only object",
    0x06020000: "object does not exist in the object dictionary",
    0x06040041: "object cannot be mapped to the PDO",
    0x06040042: "the number and length of the objects to be mapped would exceed the PDO length",
    0x06040043: "general parameter incompatibility",
    0x06040047: "general internal incompatibility in the device",
    0x06060000: "access failed due to a hardware error",
    0x06070010: "data type does not match, length of service parameter does not match",
    0x06070012: "data type does not match, length of service parameter too high",
    0x06070013: "data type does not match, length of service parameter too low",
    0x06090011: "sub-index does not exist",
    0x06090030: "invalid value for parameter",
    0x06090031: "value of parameter written too high",
    0x06090032: "value of parameter written too low",
    0x06090036: "maximum value is less than minimum value",
    0x060A0023: "resource not available: SDO connection",
    0x08000000: "general error",
    0x08000020: "data cannot be transferred or stored to the application",
    0x08000021: "data cannot be transferred or stored to the application because of local control",
    0x08000022: "data cannot be transferred or stored to the application because of the present device state",
    0x08000023: "object dictionary dynamic generation failed or no object dictionary is present",
    0x08000024: "no data available",
}

# EMCY error codes (CiA 301 table "Emergency error codes", with the CiA 402 codes a drive sends).
# Looked up exactly, then by the code's class (high byte, then high nibble).
EMCY_CODES = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2000: "current",
    0x2100: "current, device input side",
    0x2200: "current inside the device",
    0x2300: "current, device output side",
    0x2310: "continuous over current",
    0x2320: "short circuit or earth leakage",
    0x3000: "voltage",
    0x3100: "mains voltage",
    0x3200: "voltage inside the device",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x3300: "output voltage",
    0x4000: "temperature",
    0x4100: "ambient temperature",
    0x4200: "device temperature",
    0x4210: "excess temperature device",
    0x5000: "device hardware",
    0x6000: "device software",
    0x6100: "internal software",
    0x6200: "user software",
    0x6300: "data set",
    0x7000: "additional modules",
    0x7300: "sensor",
    0x8000: "monitoring",
    0x8100: "communication",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard error or heartbeat error",
    0x8140: "recovered from bus off",
    0x8150: "CAN-ID collision",
    0x8200: "protocol error",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8240: "unexpected SYNC data length",
    0x8250: "RPDO timeout",
    0x8600: "positioning controller",
    0x8611: "following error",
    0x8612: "reference limit",
    0x9000: "external error",
    0xF000: "additional functions",
    0xFF00: "device specific",
}

# NMT: command names (as jigctl takes them) -> command specifier, and heartbeat states.
NMT_COMMANDS = {"start": 0x01, "stop": 0x02, "preop": 0x80, "reset": 0x81, "reset-comm": 0x82}
NMT_COMMAND_NAMES = {0x01: "start", 0x02: "stop", 0x80: "enter pre-operational", 0x81: "reset node",
                     0x82: "reset communication"}
NMT_STATES = {0x00: "boot-up", 0x04: "stopped", 0x05: "operational", 0x7F: "pre-operational"}

# Device profiles (0x1000 device type, low 16 bits).
PROFILES = {
    0: "no profile",
    401: "CiA 401 generic I/O modules",
    402: "CiA 402 drives and motion control",
    404: "CiA 404 measuring devices and closed-loop controllers",
    406: "CiA 406 encoders",
    408: "CiA 408 fluid power technology",
    410: "CiA 410 inclinometers",
    418: "CiA 418 battery modules",
    419: "CiA 419 battery chargers",
}

# LSS command specifiers (CiA 305) by the value in byte 0.
LSS_COMMANDS = {
    0x04: "switch state global", 0x11: "configure node id", 0x13: "configure bit timing",
    0x15: "activate bit timing", 0x17: "store configuration", 0x40: "switch selective vendor",
    0x41: "switch selective product", 0x42: "switch selective revision", 0x43: "switch selective serial",
    0x44: "switch selective response", 0x4C: "identify non-configured", 0x4F: "identify slave",
    0x50: "identify non-configured slave", 0x51: "fast scan", 0x5A: "inquire vendor",
    0x5B: "inquire product", 0x5C: "inquire revision", 0x5D: "inquire serial", 0x5E: "inquire node id",
}

LSS_MASTER_ID = 0x7E5
LSS_SLAVE_ID = 0x7E4


def abort_text(code):
    """'0x06020000 object does not exist in the object dictionary' (unknown codes say so)."""
    return "0x%08X %s" % (code, ABORT_CODES.get(code, "unknown abort code"))


def emcy_name(code):
    """The name of an EMCY error code, by the code itself or else its class."""
    for key in (code, code & 0xFF00, code & 0xF000):
        if key in EMCY_CODES:
            return EMCY_CODES[key]
    return "unknown error code"


def profile_name(device_type):
    """'CiA 402 drives and motion control' for a 0x1000 value whose low 16 bits are 402."""
    number = device_type & 0xFFFF
    return PROFILES.get(number, "profile %d" % number)


def nmt_state_name(byte):
    return NMT_STATES.get(byte & 0x7F, "state 0x%02X" % byte)


# --- what a frame is -------------------------------------------------------------
# Function codes of the predefined connection set (COB-ID bits 10..7) for node ids 1..127.
_FUNCTIONS = {
    0x080: "EMCY", 0x180: "TPDO1", 0x200: "RPDO1", 0x280: "TPDO2", 0x300: "RPDO2", 0x380: "TPDO3",
    0x400: "RPDO3", 0x480: "TPDO4", 0x500: "RPDO4", 0x580: "SDO tx", 0x600: "SDO rx", 0x700: "heartbeat",
}


def classify(can_id, ext=False):
    """(service, node_id) of a frame by its COB-ID: ('NMT', 0), ('SYNC', 0), ('TIME', 0),
    ('LSS master', 0), ('LSS slave', 0), ('EMCY', 5), ('TPDO1', 5), ..., or (None, 0)."""
    if ext:
        return None, 0
    if can_id == 0x000:
        return "NMT", 0
    if can_id == 0x080:
        return "SYNC", 0
    if can_id == 0x100:
        return "TIME", 0
    if can_id == LSS_MASTER_ID:
        return "LSS master", 0
    if can_id == LSS_SLAVE_ID:
        return "LSS slave", 0
    node = can_id & 0x7F
    function = can_id & 0x780
    if node and function in _FUNCTIONS:
        return _FUNCTIONS[function], node
    return None, 0


def _sdo_object(data):
    index, sub = struct.unpack_from("<HB", data, 1)
    return index, sub


def _object_text(index, sub, od_name):
    text = "0x%04X:%02X" % (index, sub)
    name = od_name(index, sub) if od_name else None
    return text + (" " + name if name else "")


def describe_sdo(data, request, od_name=None, od_decode=None):
    """An SDO frame's meaning: 'upload 0x6041:00 Statusword', '0x6041:00 = 0x0237', 'abort ...'."""
    if len(data) < 1:
        return "empty"
    ccs = data[0] >> 5
    if len(data) >= 4:
        index, sub = _sdo_object(data)
        obj = _object_text(index, sub, od_name)
    else:
        index = sub = None
        obj = "?"
    if ccs == 4 and len(data) >= 8:
        return "abort %s: %s" % (obj, abort_text(struct.unpack_from("<I", data, 4)[0]))
    expedited_size = 4 - ((data[0] >> 2) & 3) if data[0] & 0x03 == 0x03 else None
    if request:
        if ccs == 2:
            return "upload %s" % obj
        if ccs == 1:
            if expedited_size is not None and len(data) >= 4 + expedited_size:
                return "download %s = %s" % (obj, _value_text(data[4:4 + expedited_size], index, sub, od_decode))
            return "download %s (segmented)" % obj
        if ccs == 0:
            return "download segment"
        if ccs == 3:
            return "upload segment request"
        return "command 0x%02X" % data[0]
    if ccs == 2:
        if expedited_size is not None and len(data) >= 4 + expedited_size:
            return "%s = %s" % (obj, _value_text(data[4:4 + expedited_size], index, sub, od_decode))
        return "%s (segmented upload)" % obj
    if ccs == 3:
        return "download %s done" % obj
    if ccs == 0:
        return "upload segment"
    if ccs == 1:
        return "download segment done"
    return "command 0x%02X" % data[0]


def _value_text(raw, index, sub, od_decode):
    if od_decode:
        text = od_decode(index, sub, bytes(raw))
        if text is not None:
            return text
    value = int.from_bytes(raw, "little")
    return "0x%0*X" % (2 * len(raw), value)


def describe_frame(can_id, data, ext=False, rtr=False, od_name=None, od_decode=None, pdo_decode=None):
    """One line saying what a frame is in CANopen terms ('' when it is nothing known).

    od_name(index, sub) -> name or None and od_decode(index, sub, raw) -> text or None name
    SDO objects and values from an EDS; pdo_decode(service, node, data) -> text or None
    names a PDO's mapped objects.
    """
    service, node = classify(can_id, ext)
    if service is None:
        return ""
    if rtr:
        return "%s node %d (remote request)" % (service, node) if node else "%s (remote request)" % service
    data = bytes(data)
    if service == "NMT":
        if len(data) != 2:
            return "NMT (%d bytes?)" % len(data)
        what = NMT_COMMAND_NAMES.get(data[0], "command 0x%02X" % data[0])
        return "NMT %s %s" % (what, "all nodes" if data[1] == 0 else "node %d" % data[1])
    if service in ("SYNC", "TIME"):
        return service + (" counter %d" % data[0] if service == "SYNC" and data else "")
    if service.startswith("LSS"):
        if not data:
            return service
        return "%s %s" % (service, LSS_COMMANDS.get(data[0], "command 0x%02X" % data[0]))
    if service == "EMCY":
        if len(data) < 3:
            return "EMCY node %d (%d bytes?)" % (node, len(data))
        code, register = struct.unpack_from("<HB", data)
        return "EMCY node %d: 0x%04X %s, error register 0x%02X" % (node, code, emcy_name(code), register)
    if service == "heartbeat":
        if len(data) != 1:
            return "heartbeat node %d (%d bytes?)" % (node, len(data))
        return "heartbeat node %d: %s" % (node, nmt_state_name(data[0]))
    if service.startswith("SDO"):
        request = service == "SDO rx"
        return "SDO %s node %d: %s" % ("request" if request else "response", node,
                                       describe_sdo(data, request, od_name, od_decode))
    text = pdo_decode(service, node, data) if pdo_decode else None
    return "%s node %d%s" % (service, node, ": " + text if text else "")
