"""The table of drive kinds: the one place the station's engine learns which kinds there are.

A drive kind is a plug-in: its own modules (the drive it speaks to, its step kinds and what
they do, its plan keys and checks, its pre-flight) and one entry in this table. The engine
(plans, steps, records, the safety net) asks the table for a plan's kind (``[drive]
protocol``) and then speaks only to the ``DriveKind`` it gets. ``register`` adds a kind from
outside the project (a test's loopback drive, a user's own drive); the built-in kinds are
imported when first asked for, so python-canopen stays unloaded for a Plus-R run.

How to add a kind: docs/architecture.md, *Adding a drive kind*.
"""

import importlib

# name (a plan's [drive] protocol) -> the module whose KIND is that kind's DriveKind
_BUILTIN = {
    "plusr": "motorjig.station.kind_plusr",
    "cia402": "motorjig.station.kind_cia402",
    "ethercat": "motorjig.station.kind_ecat",
}
BUILTIN = tuple(_BUILTIN)  # the kinds the project ships (the docs' reference shows these)
_REGISTERED = {}
DEFAULT = "plusr"


class DriveKind:
    """What the engine needs of a drive kind; each kind's module makes one (its ``KIND``).

    Class attributes: ``name`` (the plan's ``[drive] protocol``), ``title`` (in sentences),
    ``drive_keys`` (the ``schema.key``\\ s of its ``[drive]`` table beside protocol and jig_id),
    ``step_kinds`` (the ``schema.Kind`` of every step its drives take), ``emergency_words``
    (what its emergency stop does, for messages). Every method has a default that suits a kind
    with nothing to say there."""

    name = ""
    title = ""
    drive_keys = ()
    step_kinds = ()
    emergency_words = "stop and switch off"
    disable_at_end = False  # a passing run ends with the drive switched off (tearDown)
    # a sentence naming the drive's own watch of a dead master when it has one: the jig's safety stop
    # is then not armed for the run (it would act on buses this run does not use)
    own_safety_net = None

    def reference(self, kinds_text):
        """Its part of the plan format's reference (docs/station.md) as markdown lines;
        ``kinds_text(step_kinds, suffix)`` renders step kinds as the reference does."""
        return ["", "### Step kinds of %s drives (`protocol = \"%s\"`)" % (self.title, self.name)] + \
            kinds_text(self.step_kinds)

    # --- the plan: read and checked, nothing on the bus -----------------------------------------
    def plan_drive(self, ck, values, plan_dir):
        """The plan's drive from its checked ``[drive]`` values: (an object with ``protocol``,
        ``jig_id``, ``as_dict()`` and ``describe()``, bytes the plan's hash covers too)."""
        raise NotImplementedError

    def old_spelling(self, ck, protocol, table):
        """A ``[drive] protocol`` value this kind took before kinds had names (Plus-R's 6, 8):
        the table rewritten (``table`` is a copy), or None when it is not this kind's."""
        return None

    def check_step(self, ck, step_path, kind, keys, args, plan_dir, drive, wiring, paramsets):
        """A step's checks that need the kind (its objects, its parameter sets); raise ck.error."""

    def wiring_default(self, drive):
        """parse_wiring's keywords that name the plan's drive as the fixture's default."""
        return {}

    def check_wired_drive(self, ck, wiring, drive):
        """The fixture must be wired to the plan's drive."""

    limit_inputs = "0 or 1"  # the drive inputs a limit-sensor relay may drive, in words

    # --- the records ---------------------------------------------------------------------------
    def record_code(self, drive):
        """The number the results database keeps in drive_protocol for a record's ``drive`` metadata."""
        try:
            return int(drive.get("protocol"))
        except (TypeError, ValueError):
            return None

    def stored_text(self, d):
        """A stored run's drive in words (``d``: the results database's drive: slave, protocol,
        slave_type, name), for ``jigctl results show``."""
        return "%s, slave %s, %s (%s)" % (self.title, d["slave"], d["slave_type"], d["name"] or "-")

    def identity_text(self, drive):
        """The drive's identity in words for the database's drive_name, or None (its name says it)."""
        return None

    # --- slots (several drives at once, station.slots) -------------------------------------------
    address_key = ""  # the [drive] key a slot sets to name its drive (jigctl test --slots 2,3)
    # a sentence when two slots of this kind cannot run at once on one port (None: they can)
    one_slot_per_port = None

    sampled_step_kinds = ()  # the step kinds that sample the axis (the moving ones)

    def slot_sample_rate(self, master, jig_id, n):
        """Samples per second each of ``n`` slots of this kind gets while all of them move (the
        jig's sampler shared), or None when its drives' traces do not share the jig's."""
        return None

    # --- the run -------------------------------------------------------------------------------
    ports = ()  # (key, option, what: "the jig's SLCAN port") of each port a run needs beside the jig's PC port
    checks_on_port = False  # check_on_port reads the drive (jigctl test --check --port)

    def check_on_port(self, ports, plan):
        """Read only: the drive against the plan, as the pre-flight will; a problem's sentence or None."""
        return None

    def before_run(self, ports):
        """A sentence when a port the run needs is not what it must be (before OpenHTF starts), else None."""
        return None

    def describe_run(self, plan, ports):
        """The drive and its ports in a few words, for the run's first line."""
        return "%s, %s" % (plan.drive.describe(), ports.get("port"))

    def conf(self, plan, ports):
        """OpenHTF CONF keys for the plug (``ports``: port, baud, timeout_ms, can_port, ...)."""
        return {}

    def open_drive(self, plug):
        """The plug's ``station.drive.Drive`` for this run (``plug.master``: the jig's PC port)."""
        raise NotImplementedError

    def safety_net_kw(self, plug):
        """Keywords for the plug's SafetyNet (a kind on another port names its drive there)."""
        return {}

    def step_functions(self, step, plan):
        """(measurements, run) of one expanded step: OpenHTF measurements and run(test, bus, step, ctx)."""
        raise NotImplementedError

    def preflight(self, test, bus, plan, serial, ctx):
        """Before the first step: the drive is the plan's; the record's ``drive`` metadata and the
        DUT id set (who samples the axis too, if the kind says). PreflightError refuses. The runner
        then resets the jig's counters, arms its safety net and starts counting bus time."""

    def after_abort(self, plan, ports):
        """After an aborted run, the emergency stop once more on a connection of its own."""


def register(kind):
    """Add (or replace) a drive kind; returns it. Its ``name`` is what plans write as protocol."""
    if not kind.name:
        raise ValueError("a drive kind needs a name")
    _REGISTERED[kind.name] = kind
    return kind


def unregister(name):
    _REGISTERED.pop(name, None)


def names():
    """Every kind's name: the built-in ones first, then the registered."""
    return tuple(_BUILTIN) + tuple(n for n in _REGISTERED if n not in _BUILTIN)


def get(name):
    """The DriveKind of that name; KeyError for one nobody registered."""
    if name in _REGISTERED:
        return _REGISTERED[name]
    if name in _BUILTIN:
        return register(importlib.import_module(_BUILTIN[name]).KIND)
    raise KeyError(name)


def of_record_code(code):
    """The kind whose records carry ``code`` in the database's drive_protocol (its ``CODE``); the
    default kind's otherwise (its codes are its variants)."""
    for name in names():
        kind = get(name)
        if getattr(kind, "CODE", None) == code:
            return kind
    return get(DEFAULT)


def kind_of(plan):
    """The plan's DriveKind (Plus-R when its [drive] names no protocol)."""
    return get(getattr(plan.drive, "protocol", None) or DEFAULT)
