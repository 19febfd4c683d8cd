"""Test-plan files: read, check against ``schema``, and expand into the steps a run executes.

``load_plan(path)`` returns a ``Plan`` or raises ``PlanError`` naming the file, the
line (where TOML allows it) and the key: an unknown step kind, a missing or
misspelled key, a value of the wrong type or out of range, a parameter the drive
does not have, a wiring reference that is not wired. Nothing here touches the bus;
what only the drive can tell (its variant, its slave type) is checked by the run's
pre-flight before anything moves (``motorjig.station.runner``).

A plan is for one drive kind (``[drive] protocol``, an entry of the table of kinds,
``station.kinds``): the kind reads its ``[drive]`` keys into its own drive object, gives the
step kinds its drives take, and checks what only it can (a CiA 402 drive's objects against its
EDS, a Plus-R parameter set's slave type). A step kind or key the kind lacks is refused.

Repeats and sweeps are expanded here: ``repeat = 3`` gives three steps, a sweep key
given as a list gives one step per value, each with a unique name
(``move_speed_20000``; an unnamed step of a kind that came before: ``move_2``), so every
record, JUnit test case and plot is one step run. Two steps given the same ``name`` are
refused, naming both.
"""

import difflib
import hashlib
import itertools
import os
import re

from motorjig.commands import UsageError
from motorjig.station import kinds as K
from motorjig.station import schema as S
from motorjig.tomlsource import SourceError, dotted, read_toml

PlanError = SourceError


class Step:
    """One step run: ``kind``, unique ``name``, ``args`` (every key of the kind, defaults filled)."""

    def __init__(self, kind, name, args, index):
        self.kind, self.name, self.args, self.index = kind, name, args, index
        self.paramset = None  # parameters steps: the ParamSet (Plus-R) or ParamSet402 (CiA 402) of args["file"]

    def __repr__(self):
        return "Step(%s %r)" % (self.kind, self.name)


class Plan:
    def __init__(self, path, settings, drive, wiring, steps, digest, paramsets):
        self.path = path
        self.name = settings["name"]
        self.version = settings["version"]
        self.description = settings["description"]
        self.stop_on_fail = settings["stop_on_fail"]
        self.on_end = settings["on_end"]
        self.reset_jig_counters = settings["reset_jig_counters"]
        self.sampling = settings["sampling"]
        self.sample_rate_min = settings["sample_rate_min"]
        self.drive = drive
        self.wiring = wiring
        self.steps = steps
        self.hash = digest
        self.paramsets = paramsets  # path -> paramset.ParamSet / paramset402.ParamSet402


class _Checker:
    def __init__(self, path, lines):
        self.path, self.lines = path, lines

    def error(self, keypath, message):
        return PlanError(self.path, self.lines.line(keypath), dotted(keypath), message)

    def table(self, data, keypath, keys, what):
        """The checked values of one table, defaults filled in; unknown keys refused."""
        if not isinstance(data, dict):
            raise self.error(keypath, "expected a table")
        known = {k.name: k for k in keys}
        for name in data:
            if name not in known:
                hint = difflib.get_close_matches(name, list(known), 1)
                raise self.error(keypath + (name,), "unknown key in %s%s (known: %s)" % (
                    what, "; did you mean '%s'?" % hint[0] if hint else "", ", ".join(known)))
        out = {}
        for k in keys:
            if k.name not in data:
                if k.default is S.REQUIRED:
                    raise self.error(keypath, "%s needs the key '%s' (%s)" % (what, k.name, k.doc))
                out[k.name] = k.default
                continue
            value = data[k.name]
            if k.sweep and isinstance(value, list):
                if not value:
                    raise self.error(keypath + (k.name,), "an empty list sweeps nothing")
                out[k.name] = [self.value(v, k, keypath + (k.name,)) for v in value]
            else:
                out[k.name] = self.value(value, k, keypath + (k.name,))
        return out

    def value(self, v, k, keypath):
        def bad(expected):
            return self.error(keypath, "expected %s, got %r" % (expected, v))

        isnum = isinstance(v, (int, float)) and not isinstance(v, bool)
        if k.type == "str" and not isinstance(v, str):
            raise bad("a string")
        if k.type == "int" and (not isinstance(v, int) or isinstance(v, bool)):
            raise bad("an integer")
        if k.type == "num" and not isnum:
            raise bad("a number")
        if k.type == "bool" and not isinstance(v, bool):
            raise bad("true or false")
        if k.type == "ref" and (isinstance(v, bool) or not isinstance(v, (int, str))):
            raise bad("a relay number or a wiring name")
        if k.type == "list" and (not isinstance(v, list)
                                 or not all(isinstance(x, (int, str)) and not isinstance(x, bool) for x in v)):
            raise bad("a list of numbers or wiring names")
        if k.type == "protocols":
            vs = v if isinstance(v, list) else [v]
            if not vs or any(x not in k.choices or isinstance(x, bool) for x in vs):
                raise bad("6, 8 or [6, 8]")
            return tuple(sorted(set(vs)))
        if k.type == "range":
            if (not isinstance(v, list) or len(v) != 2
                    or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
                raise bad("[min, max], two numbers")
            if v[0] > v[1]:
                raise self.error(keypath, "min %s is above max %s" % (v[0], v[1]))
            return (v[0], v[1])
        if k.choices and v not in k.choices:
            raise self.error(keypath, "expected one of %s, got %r" % (", ".join(repr(c) for c in k.choices), v))
        if isnum and (k.lo is not None and v < k.lo or k.hi is not None and v > k.hi):
            raise self.error(keypath, "must be %s, not %r" % (bounds_text(k.lo, k.hi), v))
        if k.type == "regex":
            if not isinstance(v, str):
                raise bad("a regular expression (a string)")
            try:
                re.compile(v)
            except re.error as exc:
                raise self.error(keypath, "%r is not a valid regular expression: %s" % (v, exc)) from None
        return v


def bounds_text(lo, hi):
    """The allowed range in words: 'between 1 and 2500000', '≥ 0', '≤ 10'."""
    if lo is not None and hi is not None:
        return "between %s and %s" % (lo, hi)
    return "≥ %s" % lo if lo is not None else "≤ %s" % hi


def _wiring(ck, data, drive, own=None):
    from motorjig.wiring import WiringError, parse_wiring

    if own is not None:  # a slot's own fixture: (its [wiring] table, the file it came from)
        table, source = own
        try:
            return parse_wiring(table, source=source, **K.get(drive.protocol).wiring_default(drive))
        except WiringError as exc:
            raise PlanError(source, None, exc.key or "", exc.reason) from None
    if "wiring" not in data:
        return None
    try:
        return parse_wiring(data["wiring"], source=ck.path, **K.get(drive.protocol).wiring_default(drive))
    except WiringError as exc:
        # exc.key is a dotted path such as "wiring.relay[1].drive_input": find its line
        parts = tuple(name or int(idx) for name, idx in re.findall(r"([A-Za-z_]+)|\[(\d+)\]", exc.key or ""))
        raise PlanError(ck.path, ck.lines.line(parts) if parts else None, exc.key or "", exc.reason) from None


def _wired(ck, wiring, keypath, ref, which):
    """The (number, other_bit, name) wiring entry that ``ref`` names; which = 'relay' or 'sense'."""
    entry = wiring.find(which, ref) if wiring is not None else None
    if entry is not None:
        return entry
    entries = () if wiring is None else (wiring.relays if which == "relay" else wiring.senses)
    known = ", ".join("%d%s" % (e[0], " (%s)" % e[2] if e[2] else "") for e in entries) or "none"
    raise ck.error(keypath, "%s %r is not in the plan's [wiring] (wired: %s)" % (which, ref, known))


# CiA 402's homing methods (0x6098): the standard's 1-14, 17-30, 33-35 and 37; -128..-1 are the
# manufacturer's own
HOMING_METHODS = tuple(range(1, 15)) + tuple(range(17, 31)) + (33, 34, 35, 37)


def _least_move_time(args, distance, speed):
    """The shortest time a move of ``distance`` at ``speed`` can take: distance / speed, plus its
    ramps where the step gives them (accel_ms/decel_ms, or accel/decel in counts/s²)."""
    from motorjig.station.phases import trapezoid_time

    acc_ms, dec_ms = args.get("accel_ms"), args.get("decel_ms")
    if args.get("accel") and args.get("decel"):
        accel = args["accel"] if not isinstance(args["accel"], list) else min(args["accel"])
        decel = args["decel"] if not isinstance(args["decel"], list) else min(args["decel"])
        acc_ms, dec_ms = 1000.0 * speed / accel, 1000.0 * speed / decel
    if acc_ms is not None and dec_ms is not None:
        return trapezoid_time(distance, speed, acc_ms, dec_ms)
    return abs(distance) / speed


def _check_step(ck, step_path, kind, keys, args, plan_dir, drive, wiring, paramsets):
    if kind == "parameters" and not os.path.exists(os.path.join(plan_dir, args["file"])):
        raise ck.error(step_path + ("file",), "parameter-set file %s not found" % os.path.join(plan_dir, args["file"]))
    K.get(drive.protocol).check_step(ck, step_path, kind, keys, args, plan_dir, drive, wiring, paramsets)
    for k in ("duration_s", "stop_time_s"):
        if args.get(k) is not None and args[k][1] <= 0:
            raise ck.error(step_path + (k,), "its upper limit is %g s: a motion takes time, so the step could never "
                                             "pass" % args[k][1])
    if kind == "move":
        need, other = ("position", "distance") if args["mode"] == "abs" else ("distance", "position")
        if args[need] is None:
            raise ck.error(step_path, "a move with mode = \"%s\" needs the key '%s'" % (args["mode"], need))
        if args[other] is not None:
            raise ck.error(step_path + (other,), "not used by mode = \"%s\" (give '%s')" % (args["mode"], need))
        distances = args["distance"] if isinstance(args["distance"], list) else [args["distance"]]
        if args["mode"] == "inc" and 0 in distances:
            raise ck.error(step_path + ("distance",), "a move of distance 0 tests nothing")
        if args["mode"] == "inc":
            speeds = args["speed"] if isinstance(args["speed"], list) else [args["speed"]]
            slowest = max(abs(d) / v for d in distances for v in speeds)
            if slowest > args["timeout_s"]:
                raise ck.error(step_path + ("timeout_s",), "the move takes at least %.3g s (distance / speed), longer "
                                                           "than timeout_s = %g" % (slowest, args["timeout_s"]))
            if args.get("duration_s") is not None:
                least = max(_least_move_time(args, d, v) for d in distances for v in speeds)
                if least > args["duration_s"][1]:
                    raise ck.error(step_path + ("duration_s",), "the move takes at least %.3g s (its trapezoid "
                                   "profile), above duration_s's upper limit %g s: it could never pass"
                                   % (least, args["duration_s"][1]))
        _duration_within_timeout(ck, step_path, args)
    elif kind == "home":
        _duration_within_timeout(ck, step_path, args)
        method = args.get("method")
        if method is not None and method not in HOMING_METHODS and not -128 <= method <= -1:
            raise ck.error(step_path + ("method",), "%d is no homing method: CiA 402 defines 1-14, 17-30, 33-35 and "
                                                    "37, and -128..-1 are the manufacturer's" % method)
    elif kind == "lss":
        if 127 < args["factory_node_id"] < 255:
            raise ck.error(step_path + ("factory_node_id",), "a node id is 1..127, or 255 for none, not %d"
                           % args["factory_node_id"])
        if step_path[1] != 0:
            raise ck.error(step_path + ("kind",), "an lss step must be the plan's first: it gives the drive the node "
                                                  "id every other step talks to")
    elif kind == "limit-sensor":
        relay = _wired(ck, wiring, step_path + ("relay",), args["relay"], "relay")
        if relay[1] not in (0, 1):
            raise ck.error(step_path + ("relay",), "relay %d drives drive input %d, not a limit input "
                                                   "(%s)" % (relay[0], relay[1], K.get(drive.protocol).limit_inputs))
    elif kind == "io":
        if wiring is None or not (wiring.relays or wiring.senses):
            raise ck.error(step_path, "an io step needs a [wiring] with relays or senses")
        for key, which in (("relays", "relay"), ("senses", "sense")):
            for i, ref in enumerate(args[key] or ()):
                _wired(ck, wiring, step_path + (key, i), ref, which)


def check_objects(ck, step_path, keys, args, drive):
    """A CiA 402 step's values that are written to objects (``Key.obj``): the EDS has each object,
    writable, and every value (each of a sweep) fits its data type and limits."""
    from motorjig.can import objects as O

    for k in keys:
        if k.obj is None or args.get(k.name) is None:
            continue
        index, sub = k.obj if isinstance(k.obj, tuple) else (k.obj, 0)
        label = "0x%04X:%02X" % (index, sub) if isinstance(k.obj, tuple) else "0x%04X" % index
        try:
            var = O.find(drive.od, "0x%04X:%d" % (index, sub), os.path.basename(drive.eds)).var
        except UsageError as exc:
            raise ck.error(step_path + (k.name,), "the drive cannot take %s: %s" % (
                k.name, str(exc).split(" (--force")[0])) from None
        if var is None or var.access_type not in ("rw", "rwr", "rww", "wo"):
            raise ck.error(step_path + (k.name,), "%s is not writable in %s" % (label, os.path.basename(drive.eds)))
        low, high = O.type_range(var)
        values = args[k.name] if isinstance(args[k.name], list) else [args[k.name]]
        for i, v in enumerate(values):
            if low is not None and not low <= v <= high:
                where = step_path + ((k.name, i) if isinstance(args[k.name], list) else (k.name,))
                raise ck.error(where, "%d is outside %s %s's limits in %s: %d..%d" % (
                    v, label, var.name, os.path.basename(drive.eds), low, high))


def _duration_within_timeout(ck, step_path, args):
    """A duration limit above the step's timeout could never be reached: the plan contradicts itself."""
    if args.get("duration_s") is not None and args["duration_s"][1] > args["timeout_s"]:
        raise ck.error(step_path + ("duration_s",), "its upper limit %g s is above timeout_s = %g: the step gives up "
                                                    "before that" % (args["duration_s"][1], args["timeout_s"]))


def _expand(ck, kind, name, explicit, args, index, out, owners, protocol=K.DEFAULT):
    """The step runs of one plan step, appended to ``out``. ``owners``: every step-run name so far
    -> (plan step index, explicit). A name given in the plan (``explicit``) must be free; a default
    name (the kind) that is taken is numbered (servo, servo_2)."""
    sweeps = [k for k, v in args.items() if isinstance(v, list) and S.kind_keys(kind, protocol)[k].sweep]
    combos = itertools.product(*[args[k] for k in sweeps]) if sweeps else [()]
    for combo in combos:
        a = dict(args)
        label = name
        for k, v in zip(sweeps, combo):
            a[k] = v
            label += "_%s_%s" % (k, v)
        for r in range(args["repeat"]):
            n = label + ("_%d" % (r + 1) if args["repeat"] > 1 else "")
            if n in owners and explicit and owners[n][0] != index:
                raise _same_name(ck, n, owners[n][0], index)
            base, i = n, 2
            while n in owners:
                n = "%s_%d" % (base, i)
                i += 1
            owners[n] = (index, explicit)
            out.append(Step(kind, n, a, index))


def _same_name(ck, name, first, second):
    """The error for two plan steps that would both be called ``name``."""
    line = ck.lines.line(("steps", first, "name")) or ck.lines.line(("steps", first))
    return ck.error(("steps", second, "name"), "two steps are named %r: steps[%d]%s and steps[%d]; give each "
                                               "step its own name" % (name, first, " (line %d)" % line if line else "",
                                                                      second))


def _drive(ck, d, plan_dir):
    """The plan's drive from its [drive] table (its kind's PlanDrive), and bytes the plan's hash covers
    too (a CiA 402 drive's EDS)."""
    if not isinstance(d, dict):
        raise ck.error(("drive",), "expected a table")
    protocol = d.get("protocol", K.DEFAULT)
    table = dict(d)
    if not isinstance(protocol, str) or protocol not in K.names():
        for name in K.names():  # a spelling from before kinds had names (Plus-R's 6 | 8 | [6, 8])
            old = K.get(name).old_spelling(ck, protocol, dict(table))
            if old is not None:
                protocol, table = name, old
                break
        else:
            raise ck.error(("drive", "protocol"), "expected %s, 6, 8 or [6, 8], got %r" % (
                " or ".join('"%s"' % p for p in K.names()), protocol))
    kind = K.get(protocol)
    own = kind.drive_keys
    mine = {k.name for k in own}
    for name in table:
        if name in mine:
            continue  # another kind may have a key of the same name (eds): this kind's own is meant
        for other in K.names():
            if other != protocol and name in {k.name for k in K.get(other).drive_keys}:
                raise ck.error(("drive", name), "'%s' is a key of protocol = \"%s\" drives; this plan's drive is "
                                                "protocol = \"%s\" (its keys: %s)" % (
                    name, other, protocol, ", ".join(k.name for k in S.DRIVE_KEYS + own)))
    table.pop("protocol", None)
    v = ck.table(table, ("drive",), tuple(k for k in S.DRIVE_KEYS if k.name != "protocol") + own, "[drive]")
    v["protocol"] = protocol
    return kind.plan_drive(ck, v, plan_dir)


def _check_wired_drive(ck, wiring, drive):
    """The fixture must be wired to the plan's drive (its kind says how it names it)."""
    K.get(drive.protocol).check_wired_drive(ck, wiring, drive)


def load_plan(path, address=None, wiring=None):
    """Read, check and expand one plan file. A slot's run (``station.slots``) gives its own address
    as ``address`` ({[drive] key: value} replacing the plan's) and its own fixture as ``wiring`` ((a
    [wiring] table, its file) in place of the plan's); the plan's hash stays the file's."""
    data, lines, raw = read_toml(path)
    if address:
        data["drive"] = dict(data.get("drive", {}), **address)
    ck = _Checker(path, lines)
    known = ("plan", "drive", "wiring", "steps")
    for name in data:
        if name not in known:
            hint = difflib.get_close_matches(name, known, 1)
            raise ck.error((name,), "unknown table%s (a plan has %s)" % (
                "; did you mean '%s'?" % hint[0] if hint else "", ", ".join("[%s]" % k for k in known)))
    if "plan" not in data:
        raise ck.error((), "no [plan] table (it needs at least name and version)")
    settings = ck.table(data["plan"], ("plan",), S.PLAN_KEYS, "[plan]")
    plan_dir = os.path.dirname(os.path.abspath(path))
    drive, eds_raw = _drive(ck, data.get("drive", {}), plan_dir)
    wiring = _wiring(ck, data, drive, wiring)
    if wiring is not None:
        _check_wired_drive(ck, wiring, drive)
    steps_data = data.get("steps")
    if not isinstance(steps_data, list) or not steps_data:
        raise ck.error(("steps",), "no steps (add [[steps]] tables)")
    steps, owners, named, paramsets = [], {}, {}, {}
    kinds = S.kinds(drive.protocol)
    title = K.get(drive.protocol).title
    for i, sd in enumerate(steps_data):
        sp = ("steps", i)
        if not isinstance(sd, dict):
            raise ck.error(sp, "expected a table")
        kind = sd.get("kind")
        if kind is None:
            raise ck.error(sp, "a step needs 'kind' (one of %s)" % ", ".join(kinds))
        if kind not in kinds:
            others = [p for p in K.names() if p != drive.protocol and kind in S.kinds(p)]
            if others:
                raise ck.error(sp + ("kind",), "a %s drive has no step kind %r (only protocol = \"%s\" drives "
                                               "do; this plan's kinds: %s)" % (
                    title, kind, others[0], ", ".join(kinds)))
            hint = difflib.get_close_matches(str(kind), list(kinds), 1)
            raise ck.error(sp + ("kind",), "unknown step kind %r%s (known: %s)" % (
                kind, "; did you mean '%s'?" % hint[0] if hint else "", ", ".join(kinds)))
        keys = S.COMMON_STEP_KEYS + kinds[kind].keys
        args = ck.table(sd, sp, keys, "a %s step" % kind)
        _check_step(ck, sp, kind, keys, args, plan_dir, drive, wiring, paramsets)
        first = len(steps)
        name = (args["name"] or kind).replace(" ", "_")
        if args["name"] is not None:
            if name in named:
                raise _same_name(ck, name, named[name], i)
            named[name] = i
        _expand(ck, kind, name, args["name"] is not None, args, i, steps, owners, drive.protocol)
        if kind == "parameters":
            for st in steps[first:]:
                st.paramset = paramsets[os.path.join(plan_dir, args["file"])]
    digest = hashlib.sha256(raw)
    digest.update(eds_raw)
    for ps_path in sorted(paramsets):
        digest.update(paramsets[ps_path].raw)
    return Plan(path, settings, drive, wiring, steps, digest.hexdigest(), paramsets)
