"""The test-plan format, as data: every table, step kind and key with its type and meaning.

This is the one source of the plan format. ``motorjig.station.plan`` checks plan
files against it, and ``render_reference()`` writes the format's reference in
docs/station.md from it (a test keeps the two equal), so the documentation cannot
drift from what the loader accepts.

A key is ``Key(name, type, default, doc, ...)``; ``default`` is ``REQUIRED`` for a
key that must be given. Types:

* ``str``, ``int``, ``num`` (int or float), ``bool``
* ``regex``: a string that is a valid Python regular expression (checked when the plan loads)
* ``range``: ``[min, max]``, two numbers, min <= max (a limit)
* ``ref``: a relay or jig-input reference, its number or its ``name`` in the wiring
* ``choice``: one of ``choices``
* ``protocols``: 6, 8, or a list of them (the variants a drive may speak)
* ``protocol``: the drive's kind, a name in the table of kinds (or, as plans before CiA 402
  drives wrote it, the Plus-R variants ``6``, ``8``, ``[6, 8]``)

A plan is for one kind of drive (``[drive] protocol``, an entry of the table of kinds,
``station.kinds``): ``DRIVE_KEYS`` are every drive's, the kind's ``drive_keys`` its own, and
its ``step_kinds`` the step kinds it takes, with their keys (each kind's in its own module,
``schema_<kind>.py``); ``PROMPT``, the operator's step, is every kind's. A key with ``obj``
set is written to that object of the drive (its kind checks it when the plan loads).

A key with ``sweep=True`` may also be given as a list of values: the step then runs
once per value (``speed = [1000, 20000, 50000]``). Every step may repeat
(``repeat = 3``).
"""

from collections import namedtuple

REQUIRED = object()

Key = namedtuple("Key", "name type default doc choices lo hi sweep obj")
Key.__new__.__defaults__ = ((), None, None, False, None)


def key(name, type_, default, doc, choices=(), lo=None, hi=None, sweep=False, obj=None):
    return Key(name, type_, default, doc, tuple(choices), lo, hi, sweep, obj)


Kind = namedtuple("Kind", "name doc keys measurements")

I32 = (-0x80000000, 0x7FFFFFFF)
SPEED = (1, 2500000)

# --- the plan's tables ---------------------------------------------------------------
PLAN_KEYS = (
    key("name", "str", REQUIRED, "the plan's name (the test name in every record)"),
    key("version", "str", REQUIRED, "the plan's version, e.g. \"1.2\""),
    key("description", "str", "", "what the plan is for"),
    key("stop_on_fail", "bool", True, "end the run at the first failed step"),
    key("on_end", "choice", "stop-servo-off",
        "what a run that fails, errors or is interrupted does to the axis at the end: MoveStop "
        "(EmergencyStop when interrupted) and servo off, or nothing",
        choices=("stop-servo-off", "none")),
    key("reset_jig_counters", "bool", True,
        "reset the jig's bus counters when the run starts, so bus-health covers this run only"),
    key("sampling", "choice", "auto",
        "who samples the axis during moving steps: the jig itself at a fixed period on its own clock "
        "(`jig`: a busy PC cannot spoil a measurement), this PC through the jig (`pc`), or the jig when "
        "its firmware can (`auto`)", choices=("auto", "jig", "pc")),
    key("sample_rate_min", "num", 100.0,
        "samples per second below which a moving step's trace cannot judge the drive: the step ends "
        "ERROR (not FAIL), as it does for a gap of 4 sample periods (at least 20 ms)", lo=0, hi=100000),
)

U32 = (0, 0xFFFFFFFF)

DRIVE_KEYS = (
    key("protocol", "protocol", None, "the drive's kind, an entry of the table of kinds (docs/architecture.md): "
        "Ezi-STEP Plus-R on RS-485 or a CANopen CiA 402 drive on the jig's CAN port; the other keys of `[drive]` are "
        "that kind's (below). `6`, `8` or `[6, 8]` is a Plus-R drive with those variants (plans written before "
        "CiA 402 drives)"),
    key("jig_id", "int", 1, "the jig's own slave id on its PC port (its counters, relays and inputs)", lo=0, hi=15),
)

COMMON_STEP_KEYS = (
    key("kind", "choice", REQUIRED, "the step kind (below)"),
    key("name", "str", None, "the step's name in the records (default: its kind, numbered when a kind comes "
        "again); two steps given the same name are refused"),
    key("repeat", "int", 1, "run the step this many times", lo=1, hi=1000),
)

# The operator's step: every kind's.
PROMPT = Kind("prompt", "An operator instruction, confirmed on the console or in the Desk (`--yes` confirms "
         "unattended).", (
        key("message", "str", REQUIRED, "what the operator must do"),
    ), ("confirmed",))


def kinds(protocol=None):
    """The step kinds of a drive kind (the table of kinds, ``station.kinds``; None: the default
    kind's), name -> Kind."""
    from motorjig.station import kinds as K

    return {k.name: k for k in K.get(protocol or K.DEFAULT).step_kinds}


def kind_keys(kind, protocol=None):
    """Every key a step of this kind accepts on this protocol's drives, name -> Key."""
    return {k.name: k for k in COMMON_STEP_KEYS + kinds(protocol)[kind].keys}


# --- the reference in docs/station.md ---------------------------------------------------
def _default_text(k):
    if k.default is REQUIRED:
        return "**required**"
    if k.default is None:
        return "-"
    if isinstance(k.default, bool):
        return "`%s`" % str(k.default).lower()
    if isinstance(k.default, tuple):
        return "`[%s]`" % ", ".join(str(v) for v in k.default)
    if isinstance(k.default, str):
        return '`"%s"`' % k.default
    if isinstance(k.default, int) and k.hi == U32[1] and k.default > 0xFF:
        return "`0x%08X`" % k.default  # a 32-bit identity or mask reads best in hex
    return "`%s`" % k.default


def _type_text(k):
    t = k.type
    if k.type == "protocols":
        t = "`6` / `8` / `[6, 8]`"
    elif k.type == "protocol":
        t = " / ".join('`"%s"`' % c for c in k.choices)
    elif k.choices and t in ("choice", "int"):
        t = " / ".join('`"%s"`' % c if isinstance(c, str) else "`%s`" % c for c in k.choices)
    elif k.lo is not None or k.hi is not None:
        t = "%s %s..%s" % (t, "" if k.lo is None else k.lo, "" if k.hi is None else k.hi)
    if k.sweep:
        t += " (or a list: sweep)"
    return t


def _table(keys):
    rows = ["| key | type | default | meaning |", "| --- | --- | --- | --- |"]
    for k in keys:
        rows.append("| `%s` | %s | %s | %s |" % (k.name, _type_text(k), _default_text(k), k.doc))
    return rows


def _wiring_tables():
    """The [wiring] tables from motorjig.wiring.WIRING_SCHEMA, the one source its parser checks."""
    from motorjig.wiring import WIRING_SCHEMA

    out = []
    for table, fields in WIRING_SCHEMA.items():
        header = "[[%s]]" % table if table != "wiring" else "[wiring]"
        out += ["", "#### `%s`" % header, "", "| key | type | required | meaning |", "| --- | --- | --- | --- |"]
        for f in fields:
            kind = "array of tables `[[wiring.%s]]`" % f.key if f.kind == "tables" else f.kind
            if f.lo is not None:
                kind += " %s..%s" % (f.lo, f.hi)
            out.append("| `%s` | %s | %s | %s |" % (f.key, kind, "yes" if f.required else "no", f.meaning))
    return out


def render_reference():
    """The plan format's reference as markdown (docs/station.md between its markers): the generic
    tables, then each shipped drive kind's (the table of kinds: its [drive] keys, its step kinds)."""
    from motorjig.station import kinds as K

    shipped = [K.get(name) for name in K.BUILTIN]
    protocol = DRIVE_KEYS[0]._replace(choices=tuple(k.name for k in shipped), default=K.DEFAULT)
    out = ["### `[plan]`", ""] + _table(PLAN_KEYS)
    out += ["", "### `[drive]`", ""] + _table((protocol,) + DRIVE_KEYS[1:])
    for kind in shipped:
        out += ["", "#### `protocol = \"%s\"`" % kind.name, ""] + _table(kind.drive_keys)
    out += ["", "### `[wiring]`: the fixture (also read by `python -m motorjig.sim --wiring`)"] + _wiring_tables()
    out += ["", "### `[[steps]]`: keys of every step", ""] + _table(COMMON_STEP_KEYS)
    out += ["", "Step kinds by protocol (a kind the plan's protocol lacks is refused): " + "; ".join(
        "`%s`: %s" % (k.name, ", ".join(sk.name for sk in k.step_kinds)) for k in shipped) + "."]
    for kind in shipped:
        out += kind.reference(kinds_text)
    return "\n".join(out) + "\n"


def kinds_text(kind_list, suffix=""):
    out = []
    for k in kind_list:
        out += ["", "#### `kind = \"%s\"`%s" % (k.name, suffix), "", k.doc, ""]
        if k.keys:
            out += _table(k.keys)
        else:
            out.append("No keys of its own.")
        out += ["", "Measurements: " + ", ".join("`%s`" % m for m in k.measurements) + "."]
    return out
