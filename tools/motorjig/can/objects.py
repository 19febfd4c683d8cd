"""Objects of an EDS for the command line: find one by number or name, parse a value typed
on the command line by the object's data type and range, and show a value read back.

The EDS is read by python-canopen (``canopen.import_od``); this module only adds what a
command line needs on top: one-sentence ``UsageError``s for an unknown object or a value
that does not fit, and text for people.
"""

import math
import os
import struct

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.objectdictionary import datatypes as T

from motorjig.commands import UsageError

# data type -> (name, bits, kind): kind 'int' (signed), 'uint', 'bool', 'float', 'str', 'bytes'
TYPES = {
    T.BOOLEAN: ("BOOLEAN", 1, "bool"),
    T.INTEGER8: ("INTEGER8", 8, "int"), T.INTEGER16: ("INTEGER16", 16, "int"),
    T.INTEGER24: ("INTEGER24", 24, "int"), T.INTEGER32: ("INTEGER32", 32, "int"),
    T.INTEGER40: ("INTEGER40", 40, "int"), T.INTEGER48: ("INTEGER48", 48, "int"),
    T.INTEGER56: ("INTEGER56", 56, "int"), T.INTEGER64: ("INTEGER64", 64, "int"),
    T.UNSIGNED8: ("UNSIGNED8", 8, "uint"), T.UNSIGNED16: ("UNSIGNED16", 16, "uint"),
    T.UNSIGNED24: ("UNSIGNED24", 24, "uint"), T.UNSIGNED32: ("UNSIGNED32", 32, "uint"),
    T.UNSIGNED40: ("UNSIGNED40", 40, "uint"), T.UNSIGNED48: ("UNSIGNED48", 48, "uint"),
    T.UNSIGNED56: ("UNSIGNED56", 56, "uint"), T.UNSIGNED64: ("UNSIGNED64", 64, "uint"),
    T.REAL32: ("REAL32", 32, "float"), T.REAL64: ("REAL64", 64, "float"),
    T.VISIBLE_STRING: ("VISIBLE_STRING", 0, "str"), T.UNICODE_STRING: ("UNICODE_STRING", 0, "str"),
    T.OCTET_STRING: ("OCTET_STRING", 0, "bytes"), T.DOMAIN: ("DOMAIN", 0, "bytes"),
}

# 0x1010 store parameters / 0x1011 restore defaults take these words (as ASCII, little-endian).
SIGNATURES = {0x1010: "save", 0x1011: "load"}

KIND_HINT = {
    "bool": "0/1, true/false or on/off", "int": "a whole number", "uint": "a whole number (decimal or 0x hex)",
    "float": "a number", "str": "text", "bytes": "hex bytes such as 01 02 0A",
}


def load_eds(path):
    """The object dictionary of an EDS file (UsageError if it cannot be read)."""
    if not os.path.isfile(path):
        raise UsageError("the EDS %s does not exist" % path)
    try:
        return canopen.import_od(path)
    except Exception as exc:  # the library's parser raises many kinds
        raise UsageError("cannot read the EDS %s: %s" % (path, exc)) from None


def type_info(var):
    """(name, bits, kind) of an ODVariable's data type."""
    return TYPES.get(var.data_type, ("type 0x%04X" % (var.data_type or 0), 0, "bytes"))


def type_range(var):
    """(low, high) a value of var may take: the EDS's LowLimit/HighLimit within the type's own."""
    _, bits, kind = type_info(var)
    if kind == "uint":
        low, high = 0, (1 << bits) - 1
    elif kind == "int":
        low, high = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    elif kind == "bool":
        low, high = 0, 1
    else:
        low = high = None
    if var.min is not None:
        low = var.min if low is None else max(low, var.min)
    if var.max is not None:
        high = var.max if high is None else min(high, var.max)
    return low, high


def _number(text):
    text = text.strip().replace("_", "")
    try:
        return int(text, 0)
    except ValueError:
        return None


class Target:
    """One object on the command line: index, sub-index, and its ODVariable (None when the
    EDS does not have it and --force sends it anyway) or the record/array it belongs to."""

    def __init__(self, index, sub, var=None, container=None):
        self.index = index
        self.sub = sub
        self.var = var
        self.container = container

    @property
    def label(self):
        """'0x6041:00 Statusword' / '0x1018:01 Identity object.Vendor-ID'."""
        text = "0x%04X:%02X" % (self.index, self.sub)
        name = object_name(self.var, self.container)
        return text + (" " + name if name else "")


def object_name(var, container=None):
    if var is None:
        return container.name if container is not None else ""
    parent = var.parent if isinstance(var.parent, (ODRecord, ODArray)) else None
    return "%s.%s" % (parent.name, var.name) if parent is not None else var.name


def _by_name(mapping, text):
    """The entry of a canopen name mapping whose name equals text, ignoring case, spaces and
    '_'/'-' differences."""
    def norm(s):
        return "".join(ch for ch in s.lower() if ch.isalnum())

    want = norm(text)
    for name, obj in mapping.items():
        if norm(name) == want:
            return obj
    return None


def find(od, text, eds_name="the EDS", force=False):
    """The Target that 'INDEX[:SUB]' names (index and sub as numbers or names).

    Without a sub-index a plain variable is sub 0 and a record/array comes back whole
    (``var`` None, ``container`` set). force: an object the EDS lacks is still a Target
    (``var`` None) when given by number.
    """
    head, sep, tail = text.partition(":")
    if not head.strip():
        raise UsageError("%r is not an object: give INDEX[:SUB], e.g. 0x6041 or 0x1018:1 or a name" % text)
    index = _number(head)
    if index is None:
        obj = _by_name(od.names, head)
        if obj is None:
            raise UsageError("%r is not the name of an object in %s" % (head.strip(), eds_name))
        index = obj.index
    elif not 0 <= index <= 0xFFFF:
        raise UsageError("index %s is not 0..0xFFFF" % head.strip())
    else:
        obj = od.get(index) if index in od else None
    sub = None
    if sep:
        sub = _number(tail)
        if sub is None:
            if obj is None or isinstance(obj, ODVariable):
                raise UsageError("%r is not a sub-index (a number 0..255)" % tail.strip())
            var = _by_name(obj.names, tail)
            if var is None:
                raise UsageError("0x%04X %s has no sub-index named %r in %s" % (index, obj.name, tail.strip(), eds_name))
            return Target(index, var.subindex, var, obj)
        if not 0 <= sub <= 0xFF:
            raise UsageError("sub-index %s is not 0..255" % tail.strip())
    if obj is None:
        if force and sub is not None:
            return Target(index, sub)
        if force:
            return Target(index, 0)
        raise UsageError("0x%04X is not an object in %s (--force sends it anyway, untyped)" % (index, eds_name))
    if isinstance(obj, ODVariable):
        if sub not in (None, 0):
            if force:
                return Target(index, sub)
            raise UsageError("0x%04X %s is a single value: it has no sub-index %d" % (index, obj.name, sub))
        return Target(index, 0, obj)
    if sub is None:
        return Target(index, 0, None, obj)
    try:
        var = obj[sub]
    except (KeyError, IndexError):
        if force:
            return Target(index, sub, None, obj)
        raise UsageError("0x%04X %s has no sub-index %d in %s" % (index, obj.name, sub, eds_name)) from None
    return Target(index, sub, var, obj)


def members(container):
    """The ODVariables of a record/array in sub-index order (an array: those the EDS lists)."""
    return [container[s] for s in sorted(container.subindices)]


def parse_value(var, text, label, force=False):
    """The value text means for var, checked against its type and the EDS's range
    (force: not the EDS's LowLimit/HighLimit, only what the type can hold)."""
    name, bits, kind = type_info(var)
    what = "%s (%s: %s)" % (label, name, KIND_HINT[kind])
    if kind == "bool":
        t = text.strip().lower()
        if t in ("1", "true", "on", "yes"):
            return True
        if t in ("0", "false", "off", "no"):
            return False
        raise UsageError("%r is not a value for %s" % (text, what))
    if kind in ("int", "uint"):
        value = _number(text)
        if value is None and var.index in SIGNATURES and text.strip().lower() == SIGNATURES[var.index]:
            value = int.from_bytes(SIGNATURES[var.index].encode(), "little")
        if value is None:
            raise UsageError("%r is not a value for %s" % (text, what))
        low, high = _type_only_range(var) if force else type_range(var)
        if not low <= value <= high:
            raise UsageError("%d is out of range for %s: %d..%d" % (value, label, low, high))
        return value
    if kind == "float":
        try:
            value = float(text)
        except ValueError:
            raise UsageError("%r is not a value for %s" % (text, what)) from None
        if math.isnan(value):
            raise UsageError("NaN is not a value for %s" % label)
        low, high = (None, None) if force else type_range(var)
        if (low is not None and value < low) or (high is not None and value > high):
            raise UsageError("%g is out of range for %s: %g..%g" % (value, label, low, high))
        if bits == 32 and math.isfinite(value):
            try:
                struct.pack("<f", value)
            except OverflowError:
                raise UsageError("%g does not fit %s (REAL32)" % (value, label)) from None
        return value
    if kind == "str":
        if var.data_type == T.VISIBLE_STRING and not text.isascii():
            raise UsageError("%r is not a value for %s: only ASCII characters" % (text, what))
        return text
    return parse_hex(text, what)


def _type_only_range(var):
    _, bits, kind = type_info(var)
    if kind == "uint":
        return 0, (1 << bits) - 1
    if kind == "int":
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    return 0, 1


def parse_hex(text, what="hex bytes"):
    t = text.replace(",", " ").replace(":", " ").strip()
    if t.lower().startswith("0x") and " " not in t:
        t = t[2:]
    try:
        return bytes.fromhex(t.replace(" ", "") if " " not in t else t)
    except ValueError:
        raise UsageError("%r is not a value for %s" % (text, what)) from None


def encode(var, value):
    """The bytes an SDO download sends for a parsed value."""
    if var.data_type == T.BOOLEAN:
        return b"\x01" if value else b"\x00"
    return var.encode_raw(value)


def decode(var, raw):
    """The Python value of raw bytes read from var (ValueError if their size does not fit)."""
    _, bits, kind = type_info(var)
    if bits and kind != "bool" and len(raw) != bits // 8:
        raise ValueError("%d bytes came for a %d-bit value" % (len(raw), bits))
    if kind == "bool":
        if len(raw) != 1:
            raise ValueError("%d bytes came for a BOOLEAN" % len(raw))
        return bool(raw[0])
    return var.decode_raw(bytes(raw))


def show(var, value):
    """A value for people: unsigned numbers in decimal and hex, a value description or the
    set bits named where the EDS has them, strings as text, bytes in hex."""
    _, bits, kind = type_info(var)
    if kind == "bool":
        return "true" if value else "false"
    if kind == "uint":
        text = "%d (0x%0*X)" % (value, max(2, (bits + 3) // 4), value)
    elif kind == "int":
        text = "%d" % value
    elif kind == "float":
        text = "%g" % value
    elif kind == "str":
        return repr(value)
    else:
        return bytes(value).hex(" ").upper() or "(empty)"
    desc = var.value_descriptions.get(value) if kind in ("int", "uint") else None
    if desc:
        text += " " + desc
    return text


def jsonable(value):
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).hex()
    return value
