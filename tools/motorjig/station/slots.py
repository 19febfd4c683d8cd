"""Multi-up: several drives under test at once, each a slot with its own run, verdict and records.

A slot is one position of the fixture: a drive (named by its kind's ``address_key``, the
``[drive]`` key a slot sets), the plan it runs, its serial number and, when the plan uses the jig's relays and inputs, its own wiring of them.
``load_slots`` reads the slots from a slots file or from a list of addresses
(``jigctl test PLAN --slots 2,3,4,5``); ``check_slots`` refuses what would fight before
anything moves (one drive in two slots, a jig relay or input in two slots' wiring, two slots
of a kind that cannot share its port, two jigs); ``SlotRun`` runs every slot's plan at once,
each in its own thread as its own OpenHTF run (``runner.run_plan`` with a ``Shared``): the
runs share the jig's connection (one request at a time), its safety net (armed by the first
run, disarmed by the last) and the results database, and nothing else.

How runs end: a slot that fails or errors ends alone, its axis stopped, and the others go on;
Ctrl-C, SIGTERM, SIGHUP and the Desk's STOP abort every slot (each stops its own axis);
SIGKILL is the jig's: its safety stop stops every drive it has seen.

Exit status over the slots (``exit_code``): 0 when every slot passed, 2 when any slot ended
neither PASS nor FAIL (ERROR, ABORTED, TIMEOUT: a slot nobody could judge), else 1.

A slots file (TOML; paths in it are relative to it)::

    [[slot]]
    name = "1"                   # default: its place in the file, from 1
    slave = 2                    # the drive: its kind's address key (as the plan's [drive] names it)
    serial = "SN-0001"           # optional; "ask": typed or scanned at the start; none: read from the drive
    wiring = "fixture-1.toml"    # optional: this slot's [wiring] (jig relays and inputs), in place of the plan's
    plan = "other.toml"          # optional: this slot's own plan (default: jigctl test's PLAN)
"""

import os
import threading

from motorjig.station import kinds, runner
from motorjig.station import plan as P
from motorjig.tomlsource import SourceError, read_toml

SLOT_KEYS = ("name", "plan", "serial", "wiring")  # beside its kind's address key
# The jig's sampler must offer each slot this much more than the plan's floor: the PC's frames delay
# some of its requests, which then skip a period (two slots at 115 200 baud: 105/s at most, 99-100 measured)
RATE_MARGIN = 1.1


class SlotError(Exception):
    """The slots cannot run as given (one sentence, nothing has moved)."""


class Slot:
    """One position of the fixture: ``name``, its ``plan`` (loaded with the slot's address and
    wiring), ``serial`` (None: read from the drive; "ask": asked at the start)."""

    def __init__(self, name, plan, serial=None):
        self.name, self.plan, self.serial = str(name), plan, serial

    @property
    def kind(self):
        return kinds.kind_of(self.plan)

    def describe(self):
        """'slot 2 (slave 3)': who a line or a prompt is about."""
        key = self.kind.address_key
        return "slot %s (%s %s)" % (self.name, key.replace("_", " "), getattr(self.plan.drive, key, "?"))


def _plan(path, address, wiring, who):
    try:
        return P.load_plan(path, address=address, wiring=wiring)
    except (P.PlanError, SourceError) as exc:
        raise SlotError("%s: %s" % (who, exc)) from None


def _address(text):
    try:
        value = int(text, 0)
    except ValueError:
        raise SlotError("--slots takes the drives' addresses, e.g. 2,3,4,5, or a slots file (.toml): %r is "
                        "neither" % text) from None
    return value


def load_slots(spec, plan_path=None):
    """The slots of ``spec``: a slots file (TOML), or addresses of the plan's kind ("2,3,4,5")
    with the plan's own wiring for none of them (a plan with [wiring] needs a slots file)."""
    if spec.endswith(".toml") or os.path.isfile(spec):
        return _load_file(spec, plan_path)
    if not plan_path:
        raise SlotError("--slots with addresses needs the plan to run in them")
    first = _plan(plan_path, None, None, plan_path)
    key = kinds.kind_of(first).address_key
    if not key:
        raise SlotError("%s: a %s drive cannot be put in slots" % (plan_path, kinds.kind_of(first).title))
    if first.wiring is not None:
        raise SlotError("%s uses the jig's relays and inputs ([wiring]): each slot needs its own wiring of them; "
                        "give the slots in a slots file (docs/station.md, Multi-up)" % plan_path)
    parts = [p.strip() for p in spec.split(",") if p.strip()]
    if not parts:
        raise SlotError("--slots is empty: give the drives' addresses, e.g. 2,3,4,5, or a slots file")
    slots = [Slot(i + 1, _plan(plan_path, {key: _address(p)}, None, "slot %d" % (i + 1)))
             for i, p in enumerate(parts)]
    check_slots(slots)
    return slots


def _load_file(path, plan_path):
    try:
        data, _lines, _raw = read_toml(path)
    except SourceError as exc:
        raise SlotError(str(exc)) from None
    here = os.path.dirname(os.path.abspath(path))
    unknown = [k for k in data if k != "slot"]
    if unknown:
        raise SlotError("%s: unknown key %r (a slots file has [[slot]] tables)" % (path, unknown[0]))
    tables = data.get("slot")
    if not isinstance(tables, list) or not tables:
        raise SlotError("%s: no slots (add [[slot]] tables)" % path)
    slots = []
    for i, t in enumerate(tables):
        where = "%s: slot[%d]" % (path, i)
        if not isinstance(t, dict):
            raise SlotError("%s: expected a table" % where)
        plan_path_i = os.path.join(here, t["plan"]) if isinstance(t.get("plan"), str) else plan_path
        if not plan_path_i:
            raise SlotError("%s: no plan (give plan = \"...\" or the plan on the command line)" % where)
        name = str(t.get("name", i + 1))
        serial = t.get("serial")
        if serial is not None and (not isinstance(serial, str) or not serial.strip()):
            raise SlotError("%s: serial must be a non-empty string (\"ask\": asked at the start)" % where)
        wiring = None
        if "wiring" in t:
            wiring = _wiring_table(os.path.join(here, str(t["wiring"])), where)
        address = {k: v for k, v in t.items() if k not in SLOT_KEYS}
        if not address:
            raise SlotError("%s: no drive: give its address (slave, node_id or position, as its plan's kind "
                            "names it)" % where)
        slots.append(Slot(name, _plan(plan_path_i, address, wiring, "slot %s" % name), serial))
    check_slots(slots)
    return slots


def _wiring_table(path, where):
    try:
        data, _lines, _raw = read_toml(path)
    except SourceError as exc:
        raise SlotError("%s: %s" % (where, exc)) from None
    if "wiring" not in data:
        raise SlotError("%s: %s has no [wiring] table" % (where, path))
    return data["wiring"], path


def check_slots(slots):
    """Refuse (SlotError) slots that would fight: two names alike, one drive twice, two slots of a
    kind that cannot share its port, two jigs, a jig relay or input wired in two slots."""
    names, drives, per_kind, relays, senses = {}, {}, {}, {}, {}
    jigs = {s.plan.drive.jig_id for s in slots}
    if len(jigs) > 1:
        raise SlotError("the slots' plans name %d jigs (jig_id %s): the slots of a run share one jig"
                        % (len(jigs), ", ".join(str(j) for j in sorted(jigs))))
    for s in slots:
        if s.name in names:
            raise SlotError("two slots are named %r" % s.name)
        names[s.name] = s
        kind = s.kind
        drive = (kind.name, getattr(s.plan.drive, kind.address_key, None))
        if drive in drives:
            raise SlotError("%s and %s are one drive: each slot tests its own" % (drives[drive].describe(),
                                                                                 s.describe()))
        drives[drive] = s
        per_kind.setdefault(kind.name, []).append(s)
        wiring = s.plan.wiring
        if wiring is None:
            continue
        for used, entries, what in ((relays, wiring.relays, "jig relay"), (senses, wiring.senses, "jig input")):
            for number, _bit, _name in entries:
                if number in used:
                    raise SlotError("%s and %s both use %s %d: a relay or input serves one slot at a time; give "
                                    "each slot its own wiring (docs/station.md, Multi-up)"
                                    % (used[number].describe(), s.describe(), what, number))
                used[number] = s
    for name, group in per_kind.items():
        sentence = kinds.get(name).one_slot_per_port
        if sentence and len(group) > 1:
            raise SlotError("%s and %s: %s" % (group[0].describe(), group[1].describe(), sentence))


def exit_code(verdicts):
    """0 every slot passed, 2 any slot ended neither PASS nor FAIL, else 1."""
    codes = [runner.exit_code(v) for v in verdicts]
    if not codes or runner.EXIT_ERROR in codes:
        return runner.EXIT_ERROR
    return runner.EXIT_FAIL if runner.EXIT_FAIL in codes else runner.EXIT_PASS


def overall(verdicts):
    """The slots' verdicts in one word, by the exit status's rule."""
    return {runner.EXIT_PASS: "PASS", runner.EXIT_FAIL: "FAIL"}.get(exit_code(verdicts), "ERROR")


class Links:
    """Connections the slots' runs share on a kind's own port (one CAN network for every CiA 402
    slot on the jig's SLCAN port): the first run to ``take`` a key opens it, the last to
    ``give_back`` closes it."""

    def __init__(self):
        self._open = {}
        self._lock = threading.Lock()

    def take(self, key, opener):
        with self._lock:
            entry = self._open.get(key)
            if entry is None:
                entry = self._open[key] = [opener(), 0]
            entry[1] += 1
            return entry[0]

    def give_back(self, key, closer):
        with self._lock:
            entry = self._open.get(key)
            if entry is None:
                return
            entry[1] -= 1
            if entry[1] > 0:
                return
            del self._open[key]
        closer(entry[0])


class Shared:
    """What the runs of the slots share (``run_plan(..., slot=...)``): the slot's ``name``, the
    jig's connection ``master``, its safety net ``safety`` (None: not armed), the kinds' port
    connections ``links``, ``db_lock``, and ``share``: how many slots of its kind run at once (a
    kind whose drives sample on their own port divides the port among them)."""

    def __init__(self, name, master, safety, db_lock, links, share=1):
        self.name, self.master, self.safety, self.db_lock, self.links = name, master, safety, db_lock, links
        self.share = share


class SlotRun:
    """Every slot's plan at once (see the module's doc). ``run()`` returns {slot name: RunContext};
    ``abort(cause)`` from any thread aborts them all (the Desk's STOP, a signal)."""

    def __init__(self, slots, port, baud=115200, operator=None, station=None, out_dir=".", out=print,
                 confirm=None, timeout_ms=100, on_event=None, db=None, safety_window_ms=1000, **ports):
        self.slots = list(slots)
        self.plan = self.slots[0].plan  # (the signal handler's words)
        self.port, self.baud, self.timeout_ms = port, baud, timeout_ms
        self.operator, self.station, self.out_dir = operator, station, out_dir
        self._out, self._confirm, self._on_event = out, confirm, on_event
        self.db, self.safety_window_ms, self.ports = db, safety_window_ms, ports
        self.ctxs = {}
        self.errors = {}  # slot name -> what ended its worker (the engine itself failed)
        self.aborted = False
        self.end_cause = None
        self._lock = threading.Lock()
        self._prompt = threading.Lock()  # one operator prompt at a time

    # --- what the signal handler and the Desk call ------------------------------------------------
    def say(self, text):
        if self._out:
            try:
                self._out(text)
            except (OSError, ValueError):
                pass

    def abort(self, cause=None):
        with self._lock:
            self.aborted = True
            self.end_cause = self.end_cause or cause
            ctxs = list(self.ctxs.values())
        for ctx in ctxs:
            ctx.abort(cause)

    # --- the run ---------------------------------------------------------------------------------
    def run(self):
        from openhtf.util import configuration

        from motorjig.station.plug import SharedSafetyNet, TimedMaster

        jig_id = self.slots[0].plan.drive.jig_id
        master = TimedMaster(self.port, baud=self.baud, timeout=self.timeout_ms / 1000.0)
        try:
            self.check_rates(master, jig_id)
            if any(s.plan.reset_jig_counters for s in self.slots):
                master.reset_counters(jig_id)  # once, for all: a slot's reset would blank another's bus-health
            safety = None
            if self.safety_window_ms:
                safety = SharedSafetyNet(master, jig_id, self.safety_window_ms,
                                         servo_off=any(s.plan.on_end != "none" for s in self.slots))
            if self.station:
                configuration.CONF.load(station_id=self.station)
            db_lock, links = threading.Lock(), Links()
            share = {}
            for s in self.slots:
                share[s.kind.name] = share.get(s.kind.name, 0) + 1
            workers = [threading.Thread(target=self._run_slot, args=(s, Shared(s.name, master, safety, db_lock, links,
                                                                               share[s.kind.name])),
                                        name="motorjig-slot-%s" % s.name, daemon=True) for s in self.slots]
            handlers = runner._catch_signals(self)
            hook, threading.excepthook = threading.excepthook, runner._quiet_abort(threading.excepthook)
            try:
                for w in workers:
                    w.start()
                for w in workers:
                    while w.is_alive():
                        w.join(0.2)  # (short waits: the main thread takes the signals meanwhile)
            finally:
                threading.excepthook = hook
                runner._restore_signals(handlers)
        finally:
            master.close()
        return self.ctxs

    def check_rates(self, master, jig_id):
        """SlotError before anything moves when the slots sharing the jig's sampler would each get
        no more samples per second than a plan's floor (``sample_rate_min``) and a margin
        (``RATE_MARGIN``: the PC's own frames delay some of the sampler's requests, which then skip
        a period): their moving steps could only end ERROR."""
        by_kind = {}
        for s in self.slots:
            if any(step.kind in s.kind.sampled_step_kinds for step in s.plan.steps):
                by_kind.setdefault(s.kind.name, []).append(s)
        for group in by_kind.values():
            if len(group) < 2:
                continue
            rate = group[0].kind.slot_sample_rate(master, jig_id, len(group))
            for s in group:
                if rate is not None and s.plan.sampling != "pc" and rate < s.plan.sample_rate_min * RATE_MARGIN:
                    raise SlotError(
                        "%d slots moving at once get at most %.0f samples/s each from the jig's sampler at its driver "
                        "bus's baud rate (fewer while the PC talks), too close to %s's floor of %g "
                        "(sample_rate_min): their moving steps could not be judged; use fewer slots, a faster driver "
                        "bus (921 600 baud) or a lower floor; nothing was moved"
                        % (len(group), rate, s.describe(), s.plan.sample_rate_min))

    def _run_slot(self, slot, shared):
        who = slot.describe()

        def out(text):
            self.say("\n".join("%s | %s" % (slot.name, line) for line in str(text).split("\n")))

        def confirm(message):
            if self._confirm is None:
                raise runner.PreflightError("the plan asks the operator to confirm %r: run on a terminal or with "
                                            "--yes" % message)
            with self._prompt:
                return self._confirm("%s: %s" % (who, message))

        def on_event(event):
            if self._on_event is not None:
                self._on_event(dict(event, slot=slot.name))

        def on_start(ctx):
            with self._lock:
                self.ctxs[slot.name] = ctx
                aborted, cause = self.aborted, self.end_cause
            if aborted:  # a STOP or a signal came before this slot's run existed
                ctx.abort(cause)

        try:
            runner.run_plan(slot.plan, self.port, baud=self.baud, serial=slot.serial, operator=self.operator,
                            station=self.station, out_dir=self.out_dir, out=out if self._out else None,
                            confirm=confirm, timeout_ms=self.timeout_ms, on_event=on_event, on_start=on_start,
                            db=self.db, safety_window_ms=self.safety_window_ms, slot=shared, **self.ports)
        except BaseException as exc:  # the engine failed in this slot: its axis is stopped, the others go on
            self.errors[slot.name] = "%s: %s" % (type(exc).__name__, exc)
            self.say("%s | the station failed in this slot: %s" % (slot.name, self.errors[slot.name]))


def summary(slot, ctx, error=None):
    """One slot's run in plain values: ``runner.summary`` with the slot's name and drive; a failed
    run's details start with why (its first failing step's measurements)."""
    if ctx is None:
        result = {"verdict": "ERROR", "dut_id": slot.serial, "plan": slot.plan.name, "details": [error or
                  "the slot's run did not start"], "files": {}, "steps": [], "write_errors": []}
    else:
        result = runner.summary(ctx)
        reason = (ctx.record or {}).get("metadata", {}).get("verdict_reason")
        if reason and result["verdict"] == "FAIL":
            result["details"] = [reason]
        if error:
            result["details"] = list(result["details"]) + [error]
    result["slot"] = slot.name
    result["drive"] = slot.describe()
    return result
