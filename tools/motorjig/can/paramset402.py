"""Parameter-set files of CiA 402 drives: object-dictionary entries by index or name, in TOML.

The one format of ``jigctl can sdo dump`` / ``jigctl can sdo load`` and of a CiA 402 test
plan's ``parameters`` step (the golden set a drive is verified against), in the shape of the
Plus-R drives' ``motorjig.paramset``::

    # parameter set of node 5 (MotorJig CiA 402 drive (sim)), 2026-12-02 08:30 (jigctl can sdo dump)
    [drive]
    device_type = 0x00020192    # 0x1000, optional: the drive it was taken from
    vendor_id = 0x4D4A4947      # 0x1018:1, optional
    product_code = 0x00000402   # 0x1018:2, optional

    [objects]
    "0x6081" = 10000            # Profile velocity, UNSIGNED32
    "0x6099:01" = 5000          # Homing speeds.Speed during search for switch, UNSIGNED32

A key is ``INDEX[:SUB]`` in numbers or the EDS's names (``"Profile velocity"``,
``"0x6099:Speed during search for switch"``), resolved with ``motorjig.can.objects.find``; a
sub-index of two digits is hex, as jigctl's labels write it (``"0x1A00:0A"`` is sub 10);
every entry must be one value (not a whole record), of its data type (integers for the
integer types, true/false, numbers, text; bytes as a hex string) and within the EDS's
LowLimit/HighLimit. A set to write (``writable=True``) may hold only objects the EDS lets
one write. Any problem is a ``SourceError`` naming the file, the line and the key.
"""

import math
import re
import time

from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from motorjig.can import objects as O
from motorjig.commands import UsageError
from motorjig.tomlsource import SourceError, read_toml

DRIVE_KEYS = {"device_type": (0x1000, 0), "vendor_id": (0x1018, 1), "product_code": (0x1018, 2)}
READABLE = ("ro", "const", "rw", "rwr", "rww")
WRITABLE = ("rw", "rwr", "rww", "wo")
# writable objects that are commands, not settings: not part of a default dump
COMMANDS = {(0x6040, 0), (0x6060, 0), (0x607A, 0), (0x60FF, 0), (0x60FE, 1)}


_TWO_HEX = re.compile(r"^\s*([^:]+?)\s*:\s*([0-9A-Fa-f]{2})\s*$")


def object_key(key):
    """The INDEX[:SUB] text ``objects.find`` reads for a set's key: a two-digit sub-index is hex."""
    m = _TWO_HEX.match(key)
    return "%s:0x%s" % (m.group(1), m.group(2)) if m else key


class Entry:
    """One object of a set: ``index``, ``sub``, its ``var`` (ODVariable), ``value``, ``key`` as written."""

    def __init__(self, index, sub, var, value, key):
        self.index, self.sub, self.var, self.value, self.key = index, sub, var, value, key

    @property
    def label(self):
        """'0x6081:00 Profile velocity'."""
        return O.Target(self.index, self.sub, self.var).label

    @property
    def name(self):
        """A measurement-friendly name: 'x6081_00'."""
        return "x%04X_%02X" % (self.index, self.sub)


class ParamSet402:
    """``entries``: the Entry list in (index, sub) order; ``drive``: {device_type/vendor_id/product_code: int}."""

    def __init__(self, entries, drive=None, path=None, raw=b""):
        self.entries = sorted(entries, key=lambda e: (e.index, e.sub))
        self.drive = dict(drive or {})
        self.path = path
        self.raw = raw

    @property
    def values(self):
        """{(index, sub): value}."""
        return {(e.index, e.sub): e.value for e in self.entries}


def default_objects(od):
    """The (index, sub, var) a dump takes when no list is given: every value the EDS lets one
    read and write at 0x1017 (heartbeat) and from 0x2000 on, except the commands (controlword,
    mode, targets, outputs) -- a drive's settings, not its present orders."""
    out = []
    for index in sorted(od.indices):
        if index != 0x1017 and index < 0x2000:
            continue
        for var in _variables(od[index]):
            if var.access_type in ("rw", "rwr", "rww") and (index, var.subindex) not in COMMANDS:
                out.append((index, var.subindex, var))
    return out


def _variables(obj):
    if isinstance(obj, ODVariable):
        return [obj]
    return [v for v in O.members(obj)]


def select(od, text, eds_name="the EDS"):
    """The (index, sub, var) that a comma-separated list of INDEX[:SUB] names (UsageError on a bad
    one); a whole record/array gives its readable and writable members."""
    out = []
    for part in [p.strip() for p in text.split(",")]:
        if not part:
            raise UsageError("an empty entry in the object list %r" % text)
        t = O.find(od, part, eds_name)
        if t.container is not None and t.var is not None and t.sub not in t.container.subindices:
            raise UsageError("0x%04X %s has no sub-index %d in %s" % (t.index, t.container.name, t.sub, eds_name))
        if t.var is None:
            members = [v for v in O.members(t.container) if v.access_type in ("rw", "rwr", "rww")]
            if not members:
                raise UsageError("0x%04X %s has no sub-index one can both read and write" % (t.index, t.container.name))
            out += [(t.index, v.subindex, v) for v in members]
        else:
            if t.var.access_type not in READABLE:
                raise UsageError("%s is write-only (access %s in %s): it cannot be dumped" % (
                    t.label, t.var.access_type, eds_name))
            out.append((t.index, t.sub, t.var))
    seen, unique = set(), []
    for item in out:
        if item[:2] not in seen:
            seen.add(item[:2])
            unique.append(item)
    return unique


def check_value(var, value):
    """``value`` as var's data type wants it (bytes from a hex string), or ValueError saying why not."""
    name, bits, kind = O.type_info(var)
    if kind == "bool":
        if not isinstance(value, bool):
            raise ValueError("expected true or false (%s), got %r" % (name, value))
        return value
    if kind in ("int", "uint"):
        if not isinstance(value, int) or isinstance(value, bool):
            raise ValueError("expected an integer (%s), got %r" % (name, value))
        low, high = O.type_range(var)
        if not low <= value <= high:
            raise ValueError("%d is out of range for %s: %d..%d" % (value, name, low, high))
        return value
    if kind == "float":
        if not isinstance(value, (int, float)) or isinstance(value, bool) or math.isnan(value):
            raise ValueError("expected a number (%s), got %r" % (name, value))
        low, high = O.type_range(var)
        if (low is not None and value < low) or (high is not None and value > high):
            raise ValueError("%g is out of range: %g..%g" % (value, low, high))
        return float(value)
    if kind == "str":
        if not isinstance(value, str):
            raise ValueError("expected text (%s), got %r" % (name, value))
        return value
    if not isinstance(value, str):
        raise ValueError("expected hex bytes as a string such as \"01 02 0A\" (%s), got %r" % (name, value))
    try:
        return bytes.fromhex(value)
    except ValueError:
        raise ValueError("%r is not hex bytes" % value) from None


def load(path, od, eds_name="the EDS", writable=False):
    """Read and check a parameter-set file against ``od``; SourceError (file:line: key: why) on any
    problem. ``writable``: every object must be one the EDS lets one write (an apply, a load)."""
    data, lines, raw = read_toml(path)
    unknown = sorted(set(data) - {"drive", "objects"})
    if unknown:
        raise SourceError(path, lines.line((unknown[0],)), unknown[0],
                          "unknown table (a CiA 402 parameter set has [drive] and [objects])")
    drive = data.get("drive", {})
    if not isinstance(drive, dict):
        raise SourceError(path, lines.line(("drive",)), "drive", "expected a table")
    for k, v in drive.items():
        where = lines.line(("drive", k))
        if k not in DRIVE_KEYS:
            raise SourceError(path, where, "drive." + k, "unknown key (known: %s)" % ", ".join(DRIVE_KEYS))
        if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= 0xFFFFFFFF:
            raise SourceError(path, where, "drive." + k, "expected an integer 0..0xFFFFFFFF, got %r" % (v,))
    objs = data.get("objects")
    if not isinstance(objs, dict) or not objs:
        raise SourceError(path, lines.line(("objects",)), "objects", "no [objects] table with values")
    entries, seen = [], {}
    for key, value in objs.items():
        where = lines.line(("objects", key))
        dotted = "objects." + key

        def bad(message):
            return SourceError(path, where, dotted, message)

        try:
            t = O.find(od, object_key(key), eds_name)
        except UsageError as exc:
            raise bad(str(exc).split(" (--force")[0]) from None
        if t.container is not None and t.sub not in t.container.subindices:
            raise bad("0x%04X %s has no sub-index %d in %s" % (t.index, t.container.name, t.sub, eds_name))
        if t.var is None:
            raise bad("0x%04X %s has sub-indexes: give one, e.g. \"0x%04X:%02X\"" % (
                t.index, t.container.name, t.index, max(1, min(t.container.subindices or [1]))))
        access = t.var.access_type
        if writable and access not in WRITABLE:
            raise bad("%s is read-only (access %s in %s): it cannot be written" % (t.label, access, eds_name))
        if not writable and access not in READABLE:
            raise bad("%s is write-only (access %s in %s): it cannot be read back" % (t.label, access, eds_name))
        try:
            checked = check_value(t.var, value)
        except ValueError as exc:
            raise bad("%s: %s" % (t.label, exc)) from None
        if (t.index, t.sub) in seen:
            raise bad("%s is given twice (also as %r)" % (t.label, seen[(t.index, t.sub)]))
        seen[(t.index, t.sub)] = key
        entries.append(Entry(t.index, t.sub, t.var, checked, key))
    return ParamSet402(entries, drive, path, raw)


def _toml_value(var, value):
    _, bits, kind = O.type_info(var)
    if kind == "bool":
        return "true" if value else "false"
    if kind in ("int", "uint"):
        return "%d" % value
    if kind == "float":
        return repr(float(value)) if math.isfinite(value) else ("inf" if value > 0 else "-inf")
    if kind == "str":
        return '"%s"' % value.replace("\\", "\\\\").replace('"', '\\"')
    return '"%s"' % bytes(value).hex(" ").upper()


def dumps(values, node=None, drive=None, name=None, when=None):
    """The file text of ``values`` ([(index, sub, var, value)]), one commented line per object;
    ``drive``: {device_type/vendor_id/product_code: int} read from the node; ``name``: its 0x1008."""
    when = when or time.strftime("%Y-%m-%d %H:%M")
    what = "node %s" % node if node is not None else "a drive"
    if name:
        what += " (%s)" % name
    out = ["# parameter set of %s, %s (jigctl can sdo dump)" % (what, when), ""]
    drive = {k: v for k, v in (drive or {}).items() if v is not None}
    if drive:
        out.append("[drive]")
        for k in DRIVE_KEYS:
            if k in drive:
                index, sub = DRIVE_KEYS[k]
                out.append("%-28s # 0x%04X%s" % ("%s = 0x%08X" % (k, drive[k]), index, ":%d" % sub if sub else ""))
        out.append("")
    out.append("[objects]")
    for index, sub, var, value in sorted(values, key=lambda x: (x[0], x[1])):
        parent = isinstance(var.parent, (ODRecord, ODArray))
        key = '"0x%04X:%02X"' % (index, sub) if parent else '"0x%04X"' % index
        left = "%s = %s" % (key, _toml_value(var, value))
        out.append("%-28s # %s, %s" % (left, O.object_name(var), O.type_info(var)[0]))
    return "\n".join(out) + "\n"
