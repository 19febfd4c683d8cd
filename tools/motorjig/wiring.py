"""How a test jig's relays and inputs are wired to one drive's I/O, read from TOML.

A ``[wiring]`` table, which a test plan file contains too (so a plan or a
wiring-only file will do)::

    [wiring]
    slave = 2                 # optional: the Plus-R drive wired to the jig
    # node = 5                # or: the CANopen (CiA 402) drive of node id 5 (not with slave)
    [[wiring.relay]]          # jig relay k = the jig's output bit k (SetIOOutput on slave 1)
    relay = 0
    drive_input = 0           # the drive input bit it drives (§7.2)
    name = "limit+"           # optional label
    [[wiring.sense]]          # a drive output bit reaching the jig's input k (GetIOInput on slave 1)
    jig_input = 0
    drive_output = 15         # §7.1
    name = "user out 0"

Wired to a CiA 402 drive (``node``), ``drive_input`` is a bit of its digital inputs
0x60FD (0 negative limit, 1 positive limit, 2 home switch, 16-31 vendor inputs) and
``drive_output`` a bit of its digital outputs 0x60FE:1 (16-31 vendor outputs).

``WIRING_SCHEMA`` describes every key (type, range, meaning); the parser checks
against it and nothing else, so a docs generator can render the same table. Unknown
keys are errors, so a misspelling never passes silently. Each problem raises
``WiringError`` naming the file and the key: ``plan.toml: wiring.relay[1].drive_input:
expected an integer 0..31, got 'x'`` (array indexes count from 0).

Only the standard library: ``tomllib`` (Python 3.11+), else the ``tomli`` package.
"""

from collections import namedtuple

try:
    import tomllib
except ImportError:  # Python < 3.11
    try:
        import tomli as tomllib
    except ImportError:
        tomllib = None


class WiringError(ValueError):
    """A problem in a wiring: ``source: key: reason``."""

    def __init__(self, source, key, reason):
        self.source, self.key, self.reason = source, key, reason
        super().__init__("%s: %s: %s" % (source, key, reason) if key else "%s: %s" % (source, reason))


# kind: "integer" (lo..hi), "string", or "tables" (an array of tables, [[wiring.KEY]],
# whose keys are the WIRING_SCHEMA entry "wiring.KEY")
Field = namedtuple("Field", "key kind lo hi required meaning")

WIRING_SCHEMA = {
    "wiring": (
        Field("slave", "integer", 0, 15, False,
              "the Plus-R drive wired to the jig (default: the plan's [drive] slave, else the bench's first driver)"),
        Field("node", "integer", 1, 127, False,
              "instead of slave: the CANopen drive of this node id wired to the jig (default for a plan whose "
              "[drive] has a node_id: that node)"),
        Field("relay", "tables", None, None, False, "a jig relay wired to a drive input"),
        Field("sense", "tables", None, None, False, "a drive output wired to a jig input"),
    ),
    "wiring.relay": (
        Field("relay", "integer", 0, 15, True, "jig relay k = the jig's output bit k (SetIOOutput on slave 1)"),
        Field("drive_input", "integer", 0, 31, True,
              "the drive input bit it drives (Plus-R §7.2: 0 Limit+, 1 Limit-, 2 Origin, 13 Stop, 26-31 User IN 0-5; "
              "CiA 402 0x60FD: 0 negative limit, 1 positive limit, 2 home switch, 16-31 vendor inputs)"),
        Field("name", "string", None, None, False, "a label (test plans may name the relay by it)"),
    ),
    "wiring.sense": (
        Field("jig_input", "integer", 0, 15, True, "jig input k = the jig's input bit k (GetIOInput on slave 1)"),
        Field("drive_output", "integer", 0, 31, True,
              "the drive output bit that reaches it (Plus-R §7.1: 2 Alarm, 3 Run/Stop, 15-23 User OUT 0-8; "
              "CiA 402 0x60FE:1: 0 brake, 16-31 vendor outputs)"),
        Field("name", "string", None, None, False, "a label (test plans may name the input by it)"),
    ),
}


class Wiring:
    """``slave`` (the Plus-R drive; None: not given), ``node`` (the CiA 402 drive's
    CANopen node id; None: not given; never both), ``relays`` ((relay, drive_input,
    name), ...), ``senses`` ((jig_input, drive_output, name), ...); name is "" when not
    given."""

    def __init__(self, slave=None, relays=(), senses=(), source="<wiring>", node=None):
        if slave is not None and node is not None:
            raise ValueError("a wiring connects one drive: slave %r or node %r, not both" % (slave, node))
        self.slave = slave
        self.node = node
        self.relays = tuple(relays)
        self.senses = tuple(senses)
        self.source = source

    @property
    def drive(self):
        """Who is wired, for people: "slave 2", "CAN node 5" or "" (not given)."""
        if self.node is not None:
            return "CAN node %d" % self.node
        return "" if self.slave is None else "slave %d" % self.slave

    @property
    def drive_input_mask(self):
        """The drive input bits some relay drives."""
        mask = 0
        for _, bit, _ in self.relays:
            mask |= 1 << bit
        return mask

    @property
    def jig_input_mask(self):
        """The jig input bits some drive output reaches."""
        mask = 0
        for k, _, _ in self.senses:
            mask |= 1 << k
        return mask

    def drive_inputs(self, jig_outputs):
        """The drive input bits the relays set in ``jig_outputs`` (a mask of the jig's outputs) drive."""
        mask = 0
        for relay, bit, _ in self.relays:
            if jig_outputs >> relay & 1:
                mask |= 1 << bit
        return mask

    def jig_inputs(self, drive_outputs):
        """The jig input bits the drive's outputs ``drive_outputs`` (a mask) set."""
        mask = 0
        for k, bit, _ in self.senses:
            if drive_outputs >> bit & 1:
                mask |= 1 << k
        return mask

    def find(self, which, ref):
        """The (number, bit, name) entry of a relay (``which`` = "relay") or a jig input ("sense")
        that ``ref`` names, by its number or its name; None when nothing is wired so."""
        for entry in self.relays if which == "relay" else self.senses:
            if ref == entry[0] if isinstance(ref, int) else (ref and ref == entry[2]):
                return entry
        return None

    def describe(self):
        """One line per wire, for people."""
        lines = []
        inp, out = ("0x60FD bit", "0x60FE:1 bit") if self.node is not None else ("drive input", "drive output")
        for relay, bit, name in self.relays:
            lines.append("jig relay %d -> %s %d%s" % (relay, inp, bit, " (%s)" % name if name else ""))
        for k, bit, name in self.senses:
            lines.append("%s %d -> jig input %d%s" % (out, bit, k, " (%s)" % name if name else ""))
        return lines

    def __repr__(self):
        if self.node is not None:
            return "Wiring(node=%r, relays=%r, senses=%r)" % (self.node, self.relays, self.senses)
        return "Wiring(slave=%r, relays=%r, senses=%r)" % (self.slave, self.relays, self.senses)


def _kind_text(f):
    if f.kind == "integer":
        return "an integer %d..%d" % (f.lo, f.hi)
    if f.kind == "string":
        return "a string"
    return "an array of tables ([[wiring.%s]])" % f.key


def _check(source, path, table, section):
    """The values of ``table`` per WIRING_SCHEMA[section]: {key: value}, absent optional keys None."""
    fields = WIRING_SCHEMA[section]
    if not isinstance(table, dict):
        raise WiringError(source, path, "expected a table, got %r" % (table,))
    known = [f.key for f in fields]
    for key in table:
        if key not in known:
            raise WiringError(source, "%s.%s" % (path, key), "unknown key (known: %s)" % ", ".join(known))
    out = {}
    for f in fields:
        where = "%s.%s" % (path, f.key)
        if f.key not in table:
            if f.required:
                raise WiringError(source, where, "missing: %s is required" % _kind_text(f))
            out[f.key] = None
            continue
        v = table[f.key]
        if f.kind == "integer":
            ok = isinstance(v, int) and not isinstance(v, bool) and f.lo <= v <= f.hi
        elif f.kind == "string":
            ok = isinstance(v, str)
        else:
            ok = isinstance(v, list) and all(isinstance(x, dict) for x in v)
        if not ok:
            got = "a table" if isinstance(v, dict) else repr(v)
            raise WiringError(source, where, "expected %s, got %s" % (_kind_text(f), got))
        out[f.key] = v
    return out


def parse_wiring(table, source="<wiring>", default_slave=None, default_node=None):
    """A ``Wiring`` from the already parsed ``[wiring]`` table (a dict). When the table
    names neither ``slave`` nor ``node``: ``default_node`` (a CiA 402 plan's [drive]
    node_id) if given, else ``default_slave`` (a Plus-R plan's [drive] slave).
    WiringError on any problem."""
    top = _check(source, "wiring", table, "wiring")
    slave, node = top["slave"], top["node"]
    if slave is not None and node is not None:
        raise WiringError(source, "wiring.node", "a wiring connects one drive: give slave (Plus-R) or node "
                                                 "(CiA 402), not both")
    if slave is None and node is None:
        if default_node is not None:
            node = default_node
        else:
            slave = default_slave
    relays, senses = [], []
    for key, section, out, own, other in (("relay", "wiring.relay", relays, "relay", "drive_input"),
                                          ("sense", "wiring.sense", senses, "jig_input", "drive_output")):
        names = {}
        used = {}
        for i, item in enumerate(top[key] or ()):
            where = "wiring.%s[%d]" % (key, i)
            v = _check(source, where, item, section)
            k = v[own]
            if k in used:
                raise WiringError(source, "%s.%s" % (where, own), "%s %d is already wired in wiring.%s[%d]"
                                  % (own.replace("_", " "), k, key, used[k]))
            used[k] = i
            name = v["name"] or ""
            if name:
                if name in names:
                    raise WiringError(source, where + ".name", "name %r is already used by wiring.%s[%d]"
                                      % (name, key, names[name]))
                names[name] = i
            out.append((k, v[other], name))
    return Wiring(slave, relays, senses, source, node)


def load_wiring(path):
    """The wiring of a TOML file: its ``[wiring]`` table, with a test plan's ``[drive]
    slave`` as the default slave, or for a plan whose ``[drive]`` names a ``node_id`` (a
    CANopen drive) that node as the default node. WiringError (naming the file) on any problem."""
    source = str(path)
    if tomllib is None:
        raise WiringError(source, "", "reading TOML needs Python 3.11+ (tomllib) or the tomli package "
                                      "(pip install tomli)")
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except OSError as exc:
        raise WiringError(source, "", "cannot read it: %s" % (exc.strerror or exc)) from None
    except tomllib.TOMLDecodeError as exc:
        raise WiringError(source, "", "not valid TOML: %s" % exc) from None
    if "wiring" not in data:
        raise WiringError(source, "", "no [wiring] table")
    slave = node = None
    drive = data.get("drive")
    if isinstance(drive, dict) and "node_id" in drive:
        node = drive["node_id"]
        if not isinstance(node, int) or isinstance(node, bool) or not 1 <= node <= 127:
            raise WiringError(source, "drive.node_id", "expected an integer 1..127, got %r" % (node,))
    elif isinstance(drive, dict) and "slave" in drive:
        slave = drive["slave"]
        if not isinstance(slave, int) or isinstance(slave, bool) or not 0 <= slave <= 15:
            raise WiringError(source, "drive.slave", "expected an integer 0..15, got %r" % (slave,))
    return parse_wiring(data["wiring"], source, slave, node)


def load_slot_fixtures(path):
    """The fixture of a multi-up slots file (``station.slots``), without its plans: for each
    ``[[slot]]`` (its ``slave`` or None, its ``node_id`` or None, its ``Wiring`` or None), each
    wiring defaulting to its slot's drive (what the bench is wired as). WiringError on any problem."""
    import os

    from motorjig.tomlsource import SourceError, read_toml

    source = str(path)
    try:
        data = read_toml(path)[0]
    except SourceError as exc:
        raise WiringError(source, "", exc.message) from None
    tables = data.get("slot")
    if not isinstance(tables, list) or not tables:
        raise WiringError(source, "", "no [[slot]] tables")
    here = os.path.dirname(os.path.abspath(path))
    out = []
    for i, slot in enumerate(tables):
        slave = slot.get("slave") if isinstance(slot.get("slave"), int) else None
        node = slot.get("node_id") if isinstance(slot.get("node_id"), int) else None
        wiring = None
        if "wiring" in slot:
            wpath = os.path.join(here, str(slot["wiring"]))
            try:
                table = read_toml(wpath)[0].get("wiring")
            except SourceError as exc:
                raise WiringError(source, "slot[%d].wiring" % i, str(exc)) from None
            if table is None:
                raise WiringError(source, "slot[%d].wiring" % i, "%s has no [wiring] table" % wpath)
            wiring = parse_wiring(table, wpath, default_slave=slave, default_node=node)
        out.append((slave, node, wiring))
    return out
