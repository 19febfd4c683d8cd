"""The Desk's Test tab without web code: the plans, one run at a time on the station's engine, the records.

``Station`` lists the plans of the plans folder and the uploaded ones, and starts a
run with ``motorjig.station.run_plan`` (the very engine of ``jigctl test``) in a
worker thread once the ``BusSession`` has lent it the port. ``Run`` is what the page
shows of it: every step (pending, running, pass, fail, error, aborted) with its
measurements against their limits, the live samples of the moving steps, the
operator's prompt (the engine's worker waits until it is answered) and the verdict
with the record's files. Abort (also STOP, EMERGENCY STOP and Esc while a run has the
port) is the engine's abort: the running step ends, the axis gets an emergency stop
and the servo goes off.

Every run is stored in the results database (``motorjig.station.store``, the one
``jigctl test --db`` writes: by default a SQLite file per computer), and the station's
recent runs and today's yield are read from it. Without a database (``--db none``,
or it cannot be opened) they come from the records in the output folder instead
(each run leaves ``<plan>_<dut>_<time>.json`` there).

Multi-up (``--slots``): the chosen plan runs in every slot of the station's slots
(``motorjig.station.slots``: a slots file, or the drives' addresses) at once, or in one
of them, through ``slots.SlotRun``; ``SlotsRun`` keeps a ``Run`` per slot for the page,
routes each operator prompt to its slot's, and its abort (Abort, STOP) stops them all.
"""

import datetime
import glob
import inspect
import itertools
import json
import os
import re
import socket
import threading
import time

from motorjig.desk.axes import give_back, lend_ports
from motorjig.desk.session import UserError
from motorjig.tomlsource import SourceError, read_toml

MAX_UPLOAD = 512 * 1024  # bytes: a plan or parameter set is a few kB
MAX_SAMPLES = 30000  # per step: a 3-minute move at 150 samples a second
SERIAL_RE = re.compile(r"^[\x21-\x7e]{1,64}$")  # what a barcode holds: printable, no spaces
FILE_KINDS = {"html": "text/html; charset=utf-8", "json": "application/json", "xml": "application/xml"}


def default_plans_dir():
    """The repository's plans/ (an editable install), else plans/ in the current folder."""
    here = os.path.dirname(os.path.abspath(__file__))
    repo = os.path.normpath(os.path.join(here, "..", "..", "..", "plans"))
    return repo if os.path.isdir(repo) else os.path.abspath("plans")


def _signature(paths):
    """What tells a changed file: (mtime in ns, size) of each path, None for one that is gone."""
    out = []
    for p in paths:
        try:
            st = os.stat(p)
        except OSError:
            out.append(None)
        else:
            out.append((st.st_mtime_ns, st.st_size))
    return tuple(out)


def _inside(path, folder):
    """True when ``path`` (links resolved) lies in ``folder`` or below it."""
    path, folder = os.path.realpath(path), os.path.realpath(folder)
    try:
        return os.path.commonpath([path, folder]) == folder
    except ValueError:  # another drive (Windows)
        return False


def _serial(text, who=""):
    """A serial number as typed or scanned ("" for none), else UserError."""
    serial = str(text or "").strip()
    if serial and not SERIAL_RE.match(serial):
        raise UserError("%sserial number %r: 1..64 printable ASCII characters without spaces" % (who, serial))
    return serial


def _record_slot(path):
    """The slot a run record file names (its metadata's), "" for none or no file."""
    if not path:
        return ""
    try:
        with open(path, encoding="utf-8") as f:
            return str(json.load(f).get("metadata", {}).get("slot") or "")
    except (OSError, ValueError, AttributeError):
        return ""


def fmt_value(v):
    """A measured value as the steps list shows it."""
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, float):
        return "%.0f" % v if abs(v) >= 1e5 else "%.4g" % v
    text = str(v)
    return text if len(text) <= 60 else text[:57] + "..."


class PlanEntry:
    """One plan file: the loaded plan, or why it does not load."""

    def __init__(self, path, source, plan=None, error=""):
        self.path, self.source, self.plan, self.error = path, source, plan, error
        self.file = os.path.basename(path)

    @property
    def label(self):
        where = " (uploaded)" if self.source == "uploaded" else ""
        if self.plan is None:
            return "%s%s: does not load" % (self.file, where)
        return "%s %s%s" % (self.plan.name, self.plan.version, where)

    def describe(self):
        if self.plan is None:
            return self.error
        p = self.plan
        return "%s  ·  %d steps  ·  drive %s  ·  %s" % (p.description or p.name, len(p.steps), p.drive.describe(),
                                                     self.file)


class Run:
    """One plan run as the page sees it; the engine's events arrive from its worker threads."""

    def __init__(self, number, plan, serial, operator, slot=None, prompt_ids=None):
        self.number = number
        self.plan = plan
        self.slot = slot  # the slot's name when it is one of several at once (a SlotsRun's)
        self.serial = serial
        self.operator = operator
        self.lock = threading.Lock()
        self.steps = [{"name": "preflight", "kind": "the drive is the plan's", "state": "running",
                       "seconds": None, "measurements": [], "details": []}]
        self.steps += [{"name": s.name, "kind": s.kind, "state": "pending", "seconds": None, "measurements": [],
                        "details": []} for s in plan.steps]
        self._row = {r["name"]: i for i, r in enumerate(self.steps) if i}
        self.samples = {}  # step name -> [[t, command, actual, velocity], ...]
        self.plot_step = None  # the step whose samples came last
        self.prompt = None  # {"id", "message"} while the engine waits for the operator
        self._prompt_ids = prompt_ids or itertools.count(1)  # a SlotsRun's runs share theirs
        self._answer = None
        self._answered = threading.Event()
        self.verdict = None  # PASS, FAIL, ERROR, ABORTED once it ended
        self.details = []  # the record's outcome details
        self.files = {}
        self.dut_id = serial
        self.started = time.time()
        self.ended = None
        self.version = 0  # bumped by every change, so a page redraws only what changed
        self.ctx = None
        self.ports = {}  # the ports its drive kind needs beside the PC port, borrowed from the Desk's axes
        self.lent = []  # the axes.DeskAxis they were borrowed from (given back after the run)
        self.abort_requested = False
        self.cause = None  # why it was aborted, for the records
        self._abort_delivered = False  # the engine's executor existed when ctx.abort() was called

    @property
    def running(self):
        return self.verdict is None

    # --- from the engine ----------------------------------------------------------------
    def on_start(self, ctx):
        self.ctx = ctx
        if self.abort_requested:
            self._abort_engine()

    def on_event(self, ev):
        with self.lock:
            i = self._row.get(ev.get("step"))
            if ev["event"] == "sample":
                rows = self.samples.setdefault(ev["step"], [])
                if len(rows) < MAX_SAMPLES:
                    rows.append(ev["row"])
                self.plot_step = ev["step"]
            elif ev["event"] == "step" and i is not None:
                row = self.steps[i]
                row["state"] = ev["state"]
                if self.steps[0]["state"] == "running":
                    self.steps[0]["state"] = "pass"
                if ev["state"] != "running":
                    row["seconds"] = ev.get("seconds")
                    row["details"] = list(ev.get("details") or ())
                    row["measurements"] = [dict(m) for m in ev.get("measurements") or ()]
            self.version += 1
        if ev["event"] == "step" and ev["state"] == "running" and self.abort_requested \
                and not self._abort_delivered and self.ctx is not None:
            # Abort came before the engine could take it; not from this thread (the phase's own).
            threading.Thread(target=self._abort_engine, daemon=True).start()

    def confirm(self, message):
        """The engine's operator prompt: blocks its worker until the page answers (or Abort)."""
        with self.lock:
            self.prompt = {"id": next(self._prompt_ids), "message": message}
            self._answer = None
            self._answered.clear()
            self.version += 1
        try:
            # Short waits: OpenHTF's abort reaches this thread only between two of them.
            while not self._answered.wait(0.1):
                pass
            return bool(self._answer) and not self.abort_requested
        finally:
            with self.lock:
                self.prompt = None
                self.version += 1

    def answer(self, prompt_id, ok):
        with self.lock:
            if self.prompt is None or self.prompt["id"] != prompt_id:
                return False
            self._answer = bool(ok)
            self._answered.set()
            return True

    def abort(self, cause="aborted from the Desk (Abort)"):
        """Abort: the engine stops the running step, then emergency stop and servo off. ``cause``
        goes into the records."""
        if not self.running:
            return
        self.cause = self.cause or cause
        self.abort_requested = True
        self._answered.set()
        if self.ctx is not None:
            self._abort_engine()

    def _abort_engine(self):
        """ctx.abort() once it can reach the engine: OpenHTF aborts only a test whose executor
        exists (its ``uid``), and a second abort forces even the teardown phases to be skipped."""
        if self._abort_delivered:
            return
        test = self.ctx.test
        self._abort_delivered = test is not None and test.uid is not None
        self.ctx.abort(self.cause)

    def finish(self, record, files, error=""):
        with self.lock:
            record = record or {}
            self.verdict = record.get("outcome") or "ERROR"
            if self.abort_requested and self.verdict not in ("PASS", "FAIL"):
                self.verdict = "ABORTED"
            self.details = [d.get("description") for d in record.get("outcome_details", []) if d.get("description")]
            if error:
                self.details.append(error)
            self.dut_id = record.get("dut_id") or self.serial
            self.files = dict(files or {})
            end_state = {"ABORTED": "aborted"}.get(self.verdict, "error")
            for row in self.steps:
                if row["state"] == "running":
                    row["state"] = end_state
                    if not row["details"] and self.details:
                        row["details"] = list(self.details)
                elif row["state"] == "pending":
                    row["state"] = "not run"
            self.ended = time.time()
            self.version += 1

    # --- for the page ---------------------------------------------------------------------
    def snapshot(self):
        with self.lock:
            return {"steps": [dict(r) for r in self.steps], "prompt": self.prompt, "verdict": self.verdict,
                    "details": list(self.details), "files": dict(self.files), "dut_id": self.dut_id,
                    "version": self.version, "plot_step": self.plot_step}

    def samples_of(self, step):
        with self.lock:
            return list(self.samples.get(step, ()))

    def first_failure(self):
        """(step name, [failure texts]) of the first step that did not pass, or None."""
        with self.lock:
            for row in self.steps:
                if row["state"] in ("fail", "error", "aborted"):
                    return row["name"], list(row["details"])
        return None

    def seconds(self):
        return (self.ended or time.time()) - self.started


def slot_order(name):
    """Sort key of slot names: "2" before "10", "A3" before "A10"."""
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in re.findall(r"\d+|\D+", str(name)))


class SlotsRun:
    """Several slots' runs at once (``slots.SlotRun``) as the page sees them: a ``Run`` per slot
    in ``runs`` (by slot name); the prompts go to their slot's run, Abort to every slot."""

    def __init__(self, number, slots, runs):
        self.number = number
        self.slots = list(slots)
        self.plan = self.slots[0].plan
        self.runs = runs
        self.ports, self.lent = {}, []  # as a Run's
        self.engine = None  # the SlotRun, once its worker made it
        self.abort_requested = False
        self.cause = None
        self._lock = threading.Lock()
        self._who = [(s.describe() + ": ", s.name) for s in self.slots]

    @property
    def running(self):
        return any(r.running for r in self.runs.values())

    @property
    def verdict(self):
        if self.running:
            return None
        from motorjig.station.slots import overall

        return overall([r.verdict for r in self.runs.values()])

    def attach(self, engine):
        """The worker's SlotRun: an Abort that came before it existed reaches it now."""
        with self._lock:
            self.engine = engine
            aborted, cause = self.abort_requested, self.cause
        if aborted:
            engine.abort(cause)

    def abort(self, cause="aborted from the Desk (Abort)"):
        """Every slot: its running step ends, emergency stop and servo off (``SlotRun.abort``)."""
        with self._lock:
            self.abort_requested = True
            self.cause = self.cause or cause
            engine = self.engine
        for run in self.runs.values():
            run.abort(cause)
        if engine is not None:
            engine.abort(cause)

    def on_event(self, ev):
        run = self.runs.get(ev.get("slot"))
        if run is None:
            return
        if run.ctx is None and self.engine is not None:  # (its Abort then reaches its engine as a Run's does)
            run.ctx = self.engine.ctxs.get(run.slot)
        run.on_event(ev)

    def confirm(self, message):
        """A slot's operator prompt (SlotRun's message starts with "slot N (slave S): ")."""
        for prefix, name in self._who:
            if message.startswith(prefix):
                return self.runs[name].confirm(message)
        return next(iter(self.runs.values())).confirm(message)

    def answer(self, prompt_id, ok):
        return any(run.answer(prompt_id, ok) for run in self.runs.values())

    def prompt(self):
        """The prompt waiting for the operator, or None (SlotRun asks one at a time)."""
        for run in self.runs.values():
            prompt = run.prompt
            if prompt is not None:
                return prompt
        return None

    def finish(self, ctxs, errors, error=""):
        for name, run in self.runs.items():
            ctx = ctxs.get(name)
            why = errors.get(name) or (error if ctx is None else "")
            run.finish(ctx.record if ctx is not None else None, ctx.files if ctx is not None else {}, why)


class Station:
    """The Test tab's state, shared by every browser tab of one Desk."""

    def __init__(self, session, plans_dir=None, out_dir="results", operator="", station=None, upload_dir=None,
                 store=None, slots=None):
        self.session = session
        self.slots_spec = slots  # --slots: a slots file or the drives' addresses ("2,3"); None: one drive
        self.slot_runs = {}  # slot name -> its last Run (a Start of one slot leaves the others' shown)
        self._slots_cache = {}  # plan path -> (what they were loaded from, its signature, (slots, error))
        self.store = store  # a motorjig.station.store.Store, or None: the records of out_dir
        self.plans_dir = os.path.abspath(plans_dir or default_plans_dir())
        self.out_dir = os.path.abspath(out_dir)
        self.upload_dir = os.path.abspath(upload_dir or os.path.join(self.out_dir, "uploaded-plans"))
        self.operator = operator
        self.station = station
        self.run = None  # the running or the last run
        self._worker = None  # the thread of the running or the last run
        self.selected = None  # the plan last chosen (new tabs start with it)
        self._number = 0
        self._lock = threading.Lock()
        self._plan_cache = {}  # path -> (what it was loaded from, its signature, PlanEntry or None)
        self._record_cache = {}  # path -> (mtime, size, summary)
        self._stored = {}  # run id -> (first failing step, report path, slot): stored runs do not change
        self._own_files = set()  # the files this Desk's runs wrote (real paths)
        self.records_error = ""
        self.records_version = 0
        self.axes = []  # the tabs' axes.DeskAxis a run borrows its drive kind's ports from (server.py sets it)
        try:
            from motorjig.station import load_plan, run_plan  # noqa: F401
            self.unavailable = ""
        except ImportError as exc:
            self.unavailable = ("the Test tab needs the station's OpenHTF (%s): pip install 'motorjig[station]'"
                                % exc)

    # --- plans ----------------------------------------------------------------------------------
    def plans(self):
        """Every plan of the plans folder, then the uploaded ones (parameter sets are left out)."""
        out = []
        for folder, source in ((self.plans_dir, "plans"), (self.upload_dir, "uploaded")):
            for path in sorted(glob.glob(os.path.join(folder, "*.toml"))):
                entry = self._entry(path, source)
                if entry is not None:
                    out.append(entry)
        return out

    def _entry(self, path, source):
        """The plan file at ``path``, loaded again when it or a parameter set it uses changed."""
        if not os.path.isfile(path):
            return None
        cached = self._plan_cache.get(path)
        if cached is not None and _signature(cached[0]) == cached[1]:
            return cached[2]
        entry = self._load(path, source)
        if entry is not None and entry.plan is not None:
            deps = (path,) + tuple(sorted(getattr(entry.plan, "paramsets", None) or ()))
        else:  # a plan that does not load may name a parameter set not there yet: its folder too
            deps = (path, os.path.dirname(path))
        self._plan_cache[path] = (deps, _signature(deps), entry)
        return entry

    def _load(self, path, source):
        """A PlanEntry, or None for a parameter set or wiring file (no [plan], no [[steps]])."""
        error = self.unavailable
        if not error:
            from motorjig.station import load_plan

            try:
                return PlanEntry(path, source, plan=load_plan(path))
            except (ValueError, OSError) as exc:  # PlanError (a SourceError) names file, line and key
                error = str(exc)
        try:  # it does not load: a plan with a mistake, or no plan at all?
            table = read_toml(path)[0]
        except SourceError as exc:
            return PlanEntry(path, source, error=str(exc))
        if "plan" not in table and "steps" not in table:
            return None
        return PlanEntry(path, source, error=error)

    def find_plan(self, key):
        for entry in self.plans():
            if entry.path == key:
                return entry
        return None

    def add_upload(self, filename, data):
        """Keep an uploaded file beside the other uploads; returns a sentence about it."""
        if self.session.read_only:
            raise UserError("uploading a plan refused: this Desk is read-only (--read-only)")
        name = os.path.basename(str(filename or "")).strip()
        if not re.match(r"^[A-Za-z0-9][A-Za-z0-9._-]*\.toml$", name):
            raise UserError("%r: a plan is a .toml file named with letters, digits, . _ -" % filename)
        if len(data) > MAX_UPLOAD:
            raise UserError("%s is %d bytes: a plan is at most %d" % (name, len(data), MAX_UPLOAD))
        os.makedirs(self.upload_dir, exist_ok=True)
        path = os.path.join(self.upload_dir, name)
        with open(path, "wb") as f:
            f.write(data)
        self._plan_cache.pop(path, None)
        entry = self._entry(path, "uploaded")
        if entry is None:
            return "%s kept beside the uploaded plans (not a plan: a parameter set or wiring file)" % name
        if entry.plan is None:
            return "%s uploaded, but it does not load: %s" % (name, entry.error)
        return "%s uploaded: plan %s %s, %d steps" % (name, entry.plan.name, entry.plan.version,
                                                      len(entry.plan.steps))

    # --- running ------------------------------------------------------------------------------------
    @property
    def running(self):
        run = self.run
        return run is not None and run.running

    def start(self, key, serial="", operator=""):
        """Start the plan at path ``key`` for DUT ``serial``; returns a sentence (the run goes on)."""
        entry = self._startable(key)
        serial = _serial(serial)
        with self._lock:
            if self.running:
                raise UserError("a test is running: wait for its verdict, or press Abort")
            ports, lent = self._lend_ports(entry.plan)
            self._number += 1
            run = Run(self._number, entry.plan, serial, str(operator or self.operator or "").strip())
            try:
                url, baud = self.session.lend_port("the test run (%s)" % entry.plan.name, run.abort)
            except Exception:
                give_back(lent)
                raise
            run.ports, run.lent = ports, lent
            self.run = run
        self.session.log("info", "test %s %s started for %s" % (entry.plan.name, entry.plan.version,
                                                                 serial or "the drive's own id"))
        # Joined by shutdown(): the Desk stops only after the run's tearDown made the drive safe.
        self._worker = threading.Thread(target=self._work, args=(run, url, baud), name="desk-test-run", daemon=True)
        self._worker.start()
        return "test %s started%s" % (entry.plan.name, " for %s" % serial if serial else "")

    def _startable(self, key):
        """The PlanEntry of ``key`` when a run of it may start, else UserError."""
        if self.session.read_only:
            raise UserError("starting a test refused: this Desk is read-only (--read-only)")
        if self.unavailable:
            raise UserError(self.unavailable)
        entry = self.find_plan(key) if key else None
        if entry is None:
            raise UserError("choose a plan first")
        if entry.plan is None:
            raise UserError(entry.error)
        return entry

    # --- multi-up -----------------------------------------------------------------------------------
    def slots(self, key):
        """(the slots the plan at ``key`` runs in, why not: a sentence); ([], "") without --slots.
        Read again when the plan, the slots file or a fixture's wiring file changed."""
        if not self.slots_spec:
            return [], ""
        entry = self.find_plan(key) if key else None
        if entry is None or entry.plan is None:
            return [], "choose a plan that loads: it runs in every slot"
        cached = self._slots_cache.get(key)
        if cached is not None and cached[0][0] is entry and _signature(cached[0][1:]) == cached[1]:
            return cached[2]
        from motorjig.station.slots import SlotError, load_slots

        try:
            got = load_slots(self.slots_spec, key), ""
        except SlotError as exc:
            got = [], str(exc)
        files = [self.slots_spec] if os.path.isfile(self.slots_spec) else []
        files += sorted({s.plan.wiring.source for s in got[0] if s.plan.wiring is not None and s.plan.wiring.source})
        self._slots_cache[key] = ((entry,) + tuple(files), _signature(files), got)
        return got

    def start_slots(self, key, serials=None, operator="", only=None):
        """Start the plan at ``key`` in every slot, or in slot ``only``; ``serials``: {slot name:
        the serial typed or scanned} (none: the slots file's, else the drive's own id). One
        SlotRun at a time: it has the jig's port. Returns a sentence (the runs go on)."""
        entry = self._startable(key)
        slots, why = self.slots(key)
        if why:
            raise UserError(why)
        if not slots:
            raise UserError("no slots: start the Desk with --slots FILE (or the drives' addresses, 2,3)")
        if only is not None:
            slots = [s for s in slots if s.name == str(only)]
            if not slots:
                raise UserError("no slot %r" % only)
        serials = dict(serials or {})
        chosen = {}
        for s in slots:
            serial = _serial(serials.get(s.name), s.describe() + ": ")
            if not serial and s.serial == "ask":
                raise UserError("%s: scan or type its serial number (the slots file asks for it)" % s.describe())
            chosen[s.name] = serial or (s.serial if s.serial != "ask" else "")
        operator = str(operator or self.operator or "").strip()
        from motorjig.station import kinds
        from motorjig.station.slots import Slot

        slots = [Slot(s.name, s.plan, chosen[s.name] or None) for s in slots]  # (SlotRun reads the serials here)

        needed = {}
        for s in slots:
            for port in kinds.kind_of(s.plan).ports:
                needed.setdefault(port[0], port)
        who = "the test run (%s, %s)" % (entry.plan.name, "slot %s" % slots[0].name if len(slots) == 1
                                          else "%d slots" % len(slots))
        with self._lock:
            if self.running:
                raise UserError("a test is running: wait for its verdict, or press Abort")
            try:
                ports, lent = lend_ports(self.axes, list(needed.values()), who)
            except LookupError as exc:
                raise UserError("%s: %s" % (entry.plan.name, exc)) from None
            ids = itertools.count(1)
            runs = {}
            for s in slots:
                self._number += 1
                runs[s.name] = Run(self._number, s.plan, chosen[s.name], operator, slot=s.name, prompt_ids=ids)
            self._number += 1
            multi = SlotsRun(self._number, slots, runs)
            try:
                url, baud = self.session.lend_port(who, multi.abort)
            except Exception:
                give_back(lent)
                raise
            multi.ports, multi.lent = ports, lent
            self.run = multi
            self.slot_runs.update(runs)
        self.session.log("info", "test %s %s started in %s" % (
            entry.plan.name, entry.plan.version, ", ".join("%s (%s)" % (s.describe(), chosen[s.name] or
                                                                         "the drive's own id") for s in slots)))
        self._worker = threading.Thread(target=self._work_slots, args=(multi, url, baud), name="desk-test-slots",
                                        daemon=True)
        self._worker.start()
        return "test %s started in %s" % (entry.plan.name, "slot %s" % slots[0].name if len(slots) == 1
                                           else "%d slots" % len(slots))

    def _work_slots(self, multi, url, baud):
        from motorjig.station.slots import SlotError, SlotRun

        ctxs, errors, error = {}, {}, ""
        try:
            engine = SlotRun(multi.slots, url, baud=baud, operator=next(iter(multi.runs.values())).operator or None,
                             station=self.station, out_dir=self.out_dir, out=None, confirm=multi.confirm,
                             timeout_ms=max(1, round(self.session.timeout * 1000)), on_event=multi.on_event,
                             db=self.store, **multi.ports)
            multi.attach(engine)
            ctxs = engine.run()
            errors = dict(engine.errors)
        except SlotError as exc:  # refused before anything moved (the slots' sample rate): its sentence
            error = str(exc)
        except Exception as exc:  # the engine itself failed: every slot is an error, with the reason
            error = "the runs could not go on: %s: %s" % (type(exc).__name__, exc)
        finally:
            try:
                self.session.take_port_back()
            except Exception as exc:  # never leave the runs without their verdicts
                self.session.log("error", "the port could not be taken back: %s" % exc)
            for problem in give_back(multi.lent):
                self.session.log("error", problem)
            stored = [ctx.store_error for ctx in ctxs.values() if getattr(ctx, "store_error", None)]
            if stored:
                self.records_error = ("a run was not stored in the results database: %s (its files are written)"
                                      % stored[0])
            for ctx in ctxs.values():
                for path in (ctx.files or {}).values():
                    self._own_files.add(os.path.realpath(path))
            multi.finish(ctxs, errors, error)
            for name, run in multi.runs.items():
                self.session.log("info", "test %s, slot %s: %s (%s)%s" % (
                    run.plan.name, name, run.verdict, run.dut_id, "; " + "; ".join(run.details) if run.details
                    else ""))
            self.records_version += 1

    def _lend_ports(self, plan):
        """The ports the plan's drive kind needs beside the jig's PC port (``DriveKind.ports``), each
        borrowed from the tab's axis that holds it (made safe and its port closed first; reopened
        after the run): ({key: port} for run_plan, the axes lent)."""
        from motorjig.station import kinds

        try:
            return lend_ports(self.axes, kinds.kind_of(plan).ports, "the test run (%s)" % plan.name)
        except LookupError as exc:
            raise UserError("%s: %s" % (plan.name, exc)) from None

    def _work(self, run, url, baud):
        from motorjig.station import run_plan

        record, files, error = None, {}, ""
        try:
            ctx = run_plan(run.plan, url, baud=baud, serial=run.serial or None, operator=run.operator or None,
                           station=self.station, out_dir=self.out_dir, out=None, confirm=run.confirm,
                           timeout_ms=max(1, round(self.session.timeout * 1000)), on_event=run.on_event,
                           on_start=run.on_start, db=self.store, **run.ports)
            record, files = ctx.record, ctx.files
            if getattr(ctx, "store_error", None):
                error = "the run was not stored in the results database: %s (its files are written)" % (
                    ctx.store_error)
        except Exception as exc:  # the engine itself failed: the run is an error, with the reason
            error = "the run could not go on: %s: %s" % (type(exc).__name__, exc)
        finally:
            # The port first: once a tab sees the verdict, the next DUT's run can start at once.
            try:
                self.session.take_port_back()
            except Exception as exc:  # never leave the run without its verdict
                self.session.log("error", "the port could not be taken back: %s" % exc)
            for problem in give_back(run.lent):
                self.session.log("error", problem)
            if error and record is not None:
                self.records_error = error
            for path in (files or {}).values():
                self._own_files.add(os.path.realpath(path))
            run.finish(record, files, error if error and record is None else "")
            self.session.log("info", "test %s: %s (%s)%s" % (run.plan.name, run.verdict, run.dut_id,
                                                             "; " + "; ".join(run.details) if run.details else ""))
            self.records_version += 1

    def shutdown(self, timeout=10.0):
        """The Desk stops: abort a running test and wait (up to ``timeout`` s) until its worker
        ended, so the plug's tearDown (stop, emergency stop, servo off) and the engine's last
        emergency stop have reached the drive. True when no run is left going."""
        run, worker = self.run, self._worker
        if run is not None and run.running:
            self.session.log("info", "test %s: the Desk stops: aborting it" % run.plan.name)
            run.abort("aborted: the Desk was stopped")
        if worker is not None and worker is not threading.current_thread():
            worker.join(timeout)
            return not worker.is_alive()
        return True

    def abort(self):
        run = self.run
        if run is None or not run.running:
            raise UserError("no test is running")
        run.abort()  # (a SlotsRun's: every slot)
        self.session.log("info", "test %s: Abort pressed" % run.plan.name)
        from motorjig.station import kinds

        return "test aborted: %s" % kinds.kind_of(run.plan).emergency_words

    def answer(self, prompt_id, ok):
        run = self.run
        if self.session.read_only:
            raise UserError("answering refused: this Desk is read-only (--read-only)")
        if run is None or not run.answer(prompt_id, ok):
            return None
        return "confirmed" if ok else "answered: not done"

    # --- files and records ---------------------------------------------------------------------------
    def file_path(self, name):
        """The path of a run file in the output folder (by its bare name), or None."""
        if name != os.path.basename(name) or name.startswith("."):
            return None
        ext = name.rsplit(".", 1)[-1]
        path = os.path.join(self.out_dir, name)
        return path if ext in FILE_KINDS and os.path.isfile(path) and _inside(path, self.out_dir) else None

    def report_path(self, run_id):
        """The HTML report of a stored run, or None: only an .html file in the output folder (or
        one this Desk's runs wrote), whatever other path the database may name."""
        if self.store is None:
            return None
        try:
            return self._stored_run(int(run_id))[1] or None
        except Exception:
            return None

    def _stored_run(self, run_id):
        got = self._stored.get(run_id)
        if got is None:
            r = self.store.run(run_id) or {}
            failed = next((p["name"] for p in r.get("phases", []) if p.get("outcome") in ("FAIL", "ERROR")), "")
            html = (r.get("files") or {}).get("html") or ""
            slot = r["slot"] if "slot" in r else _record_slot((r.get("files") or {}).get("json"))
            got = self._stored[run_id] = (failed, html if self._servable_report(html) else "", slot or "")
        return got

    def _servable_report(self, path):
        if not path or not str(path).lower().endswith(".html") or not os.path.isfile(path):
            return False
        real = os.path.realpath(path)
        return real.lower().endswith(".html") and (_inside(real, self.out_dir) or real in self._own_files)

    def station_name(self):
        return self.station or socket.gethostname()

    def _summary(self, path):
        """A run record of the output folder as a row of the runs table (None: not a record)."""
        try:
            st = os.stat(path)
        except OSError:
            return None
        cached = self._record_cache.get(path)
        if cached is not None and cached[:2] == (st.st_mtime, st.st_size):
            return cached[2]
        try:
            with open(path, encoding="utf-8") as f:
                r = json.load(f)
            failed = next((p["name"] for p in r.get("phases", []) if p.get("outcome") in ("FAIL", "ERROR")), "")
            html = os.path.basename(path)[:-5] + ".html"
            summary = {"start": r["start_time_millis"] / 1000.0, "end": (r.get("end_time_millis") or 0) / 1000.0,
                       "plan": r.get("metadata", {}).get("test_name", ""), "dut": r.get("dut_id") or "",
                       "verdict": r.get("outcome", ""), "operator": r.get("metadata", {}).get("operator", ""),
                       "station": r.get("station_id", ""), "failed": failed,
                       "slot": str(r.get("metadata", {}).get("slot") or ""),
                       "report": "/runs/" + html if os.path.isfile(os.path.join(self.out_dir, html)) else ""}
        except (OSError, ValueError, KeyError, TypeError):
            summary = None
        self._record_cache[path] = (st.st_mtime, st.st_size, summary)
        return summary

    def _folder_rows(self):
        rows = [self._summary(p) for p in glob.glob(os.path.join(self.out_dir, "*.json"))]
        return sorted((r for r in rows if r), key=lambda r: r["start"], reverse=True)

    @staticmethod
    def _row(r):
        return {"start": r["start_ms"] / 1000.0, "end": (r["end_ms"] or r["start_ms"]) / 1000.0, "plan": r["plan"],
                "dut": r["dut"], "verdict": r["verdict"], "operator": r["operator"], "station": r["station"],
                "id": r["id"], "failed": "", "report": "", "slot": r.get("slot") or ""}

    def _store_knows_slots(self):
        """The database keeps each run's slot (its runs(slot=...)); an older one does not: the
        slot is then read from the run's record file."""
        try:
            return "slot" in inspect.signature(self.store.runs).parameters
        except (TypeError, ValueError):
            return False

    def recent_runs(self, limit=12, slot=None):
        """This station's last runs, newest first: the database's, else the output folder's;
        ``slot``: of that slot only."""
        slot = str(slot) if slot not in (None, "") else None
        if self.store is None:
            return [r for r in self._folder_rows() if slot is None or r["slot"] == slot][:limit]
        try:
            me = self.station_name()
            if slot is None:
                found = self.store.runs(station=me, limit=limit)
            elif self._store_knows_slots():
                found = self.store.runs(station=me, limit=limit, slot=slot)
            else:  # filtered here, over the last runs
                found = self.store.runs(station=me, limit=max(limit, 200))
            rows = []
            for r in found:
                row = self._row(r)
                failed, html, row_slot = self._stored_run(row["id"])
                row["failed"], row["report"] = failed, "/report/%d" % row["id"] if html else ""
                row["slot"] = row["slot"] or row_slot
                if slot is None or row["slot"] == slot:
                    rows.append(row)
            self.records_error = ""
            return rows[:limit]
        except Exception as exc:  # the database went away: say so, keep the page alive
            self.records_error = "the results database cannot be read: %s" % exc
            return []

    def run_slots(self, key=None):
        """The slots the runs list can be filtered by: the configured ones (for the plan at
        ``key``) and those of this station's recent runs, in slot order."""
        names = {s.name for s in self.slots(key)[0]}
        names.update(r["slot"] for r in self.recent_runs(limit=50) if r["slot"])
        return sorted(names, key=slot_order)

    def yield_today(self, plan_name=None):
        """Today's runs (local date) of this station: counts per verdict, the DUTs and the
        first-pass yield (the DUTs whose first run today passed, of the DUTs tested today)."""
        today = datetime.date.today()
        if self.store is None:
            rows = [r for r in self._folder_rows() if datetime.date.fromtimestamp(r["start"]) == today]
        else:
            try:
                me = self.station_name()
                rows = [self._row(r) for r in self.store.runs(plan=plan_name, since=today, limit=0, station=me)]
            except Exception as exc:
                self.records_error = "the results database cannot be read: %s" % exc
                rows = []
        if plan_name:
            rows = [r for r in rows if r["plan"] == plan_name]
        counts = {"PASS": 0, "FAIL": 0, "ERROR": 0, "ABORTED": 0}
        first = {}
        for r in sorted(rows, key=lambda r: r["start"]):
            counts[r["verdict"] if r["verdict"] in counts else "ERROR"] += 1
            first.setdefault(r["dut"], r["verdict"])
        duts = len(first)
        passed = sum(1 for v in first.values() if v == "PASS")
        return dict(counts, runs=len(rows), duts=duts, first_pass=passed,
                    yield_pct=round(100.0 * passed / duts, 1) if duts else None)

    def records_source(self):
        if self.store is not None:
            return "results database %s (station %s)" % (self.store.name, self.station_name())
        return "the records in %s" % self.out_dir
