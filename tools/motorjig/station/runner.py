"""Running a plan: the OpenHTF test built from it, the pre-flight, progress, the outputs, the verdict.

``run_plan(plan, port, ...)`` is the one engine of ``jigctl test`` (and of the Desk's
Test tab): it builds an ``openhtf.Test`` whose phases are the plan's steps
(``phases.build_phase``), starts it with a pre-flight phase that refuses a drive of
the wrong variant or type before anything moves and sets the DUT id (the operator's
serial number, else the drive's own info), and writes, for every run that started:

* ``<base>.json``: OpenHTF's JSON test record (attachments inline: the move traces),
* ``<base>.xml``: JUnit XML (``station.junit``),
* ``<base>.html``: the self-contained report (``station.report``).

``<base>`` is ``<plan>_<dut>_<YYYYmmdd-HHMMSS-mmm>``. The outcome maps to the exit code
0 PASS, 1 FAIL, 2 anything else (ERROR, ABORTED, TIMEOUT; a bad plan or no connection
never gets this far and is also 2).
"""

import json
import os
import re
import sys
import threading
import time

import openhtf as htf
from openhtf.output.callbacks import json_factory
from openhtf.util import configuration, console_output, threads

from jig.params import P_DOWN_BAUD
from motorjig import names as N
from motorjig.errors import JigError
from motorjig.station import junit, kinds, report
from motorjig.station.phases import build_phase
from motorjig.station.plug import MotorJigPlug, make_safe

CONF = configuration.CONF
EXIT_PASS, EXIT_FAIL, EXIT_ERROR = 0, 1, 2
SERVO_TYPES = (1, 3, 30, 31, 35, 50)  # slave types of Ezi-SERVO drives (protocol notes 7.5)


class PreflightError(Exception):
    """The drive is not the one the plan is for (variant, type) or does not answer."""


def exit_code(outcome):
    return {"PASS": EXIT_PASS, "FAIL": EXIT_FAIL}.get(outcome, EXIT_ERROR)


class RunContext:
    """What the phases need from the run: the plan, progress, the operator."""

    def __init__(self, plan, out=None, confirm=None, on_event=None):
        self.plan = plan
        self.out = _never_fails(out)
        self._confirm = confirm
        self.on_event = on_event
        self.drive_is_servo = getattr(plan.drive, "slave_type", None) in SERVO_TYPES
        self.record = None
        self.files = {}
        self._t_step = 0.0
        self._n = 0
        self.timings = []
        self.test = None
        self.aborted = False
        self.run_id = self.store_error = None
        self.write_errors = []  # run files that could not be written (the record may still be stored)
        self._abort_sent = False
        self.end_cause = None  # why the run was cut short ("terminated by SIGTERM"), for the records
        self.slot = None  # the slot's name when the run is one of several at once (station.slots)

    def say(self, text):
        """A line of progress that is not a step's."""
        if self.out:
            self.out(text)

    def started(self, step):
        self._t_step = time.monotonic()
        self._n += 1
        if self.on_event:
            self.on_event({"event": "step", "step": step.name, "state": "running"})

    def finished(self, step, verdict, details, bus_s=0.0, results=()):
        """A step ended: its progress line and event; ``timings`` keeps (name, seconds in the
        step, seconds of them waiting for replies) for the benchmark."""
        dt = time.monotonic() - self._t_step
        self.timings.append((step.name, dt, bus_s))
        if self.out:
            self.out("[%2d/%d] %-32s %-5s %6.2f s" % (self._n, len(self.plan.steps), step.name, verdict, dt))
            for line in details:
                self.out("        %s" % line)
        if self.on_event:
            self.on_event({"event": "step", "step": step.name, "state": verdict.lower(), "details": details,
                           "seconds": dt, "measurements": [
                               {"name": n, "value": v, "unit": u, "limits": lim, "outcome": o}
                               for n, v, u, lim, o in results]})

    def sample(self, step, row):
        """A status sample of a moving step: (t, command, actual, velocity), for live plots."""
        if self.on_event:
            self.on_event({"event": "sample", "step": step.name, "row": row})

    def abort(self, cause=None):
        """Abort the run from another thread (the Desk's Abort, a signal): the running step is
        stopped, the axis gets an emergency stop and the servo goes off. ``cause`` names why, in
        the records (the first cause given stays)."""
        if cause and not self.end_cause:
            self.end_cause = cause
        self.aborted = True
        test = self.test
        # Once only: a second abort makes OpenHTF skip the teardown, which stops the axis.
        if test is not None and test.uid is not None and not self._abort_sent:
            self._abort_sent = True
            _abort_engine(test, self.end_cause or "aborted")

    def confirm(self, message):
        if self._confirm is None:
            raise PreflightError("the plan asks the operator to confirm %r: run on a terminal or with --yes"
                                 % message)
        return self._confirm(message)


def _never_fails(out):
    """``out`` for progress lines that cannot end a run: the operator's terminal may be gone (EIO
    after a hang-up, a closed pipe) while the axis still has to be stopped and the records written."""
    if out is None:
        return None

    def write(text):
        try:
            out(text)
        except (OSError, ValueError):
            pass

    return write


def console_confirm(message, stdin=sys.stdin, out=sys.stderr):
    """Ask on the terminal; Enter or y confirms. The wait polls the terminal in short slices, so an
    abort (Ctrl-C, SIGTERM: OpenHTF stops the step's thread between two Python instructions)
    ends it at once instead of after the operator's next Enter."""
    import select

    out.write("\n>>> %s\n    press Enter when done (n + Enter: not done): " % message)
    out.flush()
    while True:
        try:
            ready = select.select([stdin], [], [], 0.2)[0]
        except (ValueError, OSError, TypeError):  # not a selectable file (a test's StringIO): just read
            ready = True
        if ready:
            break
    answer = stdin.readline()
    if not answer:
        raise PreflightError("no answer to %r (input closed)" % message)
    return answer.strip().lower() in ("", "y", "yes")


def check_drive(m, drive, steps=()):
    """The drive behind Master ``m`` against the plan's ``[drive]``, read only: (variant, SlaveInfo),
    or PreflightError saying what is wrong. Afterwards ``m`` frames the drive's requests in its
    variant (the jig's in the jig's own: a Ver6 jig may serve a Ver8 drive and the reverse)."""
    s = drive.slave
    variant = m.detect_variant(s)
    if variant is None:
        raise PreflightError("slave %d does not answer (check the cable, --port, --baud and [drive] slave)" % s)
    if variant not in drive.variants:
        raise PreflightError("the plan is for a %s drive, but slave %d answers as Ver%d: nothing was moved"
                             % (" or ".join("Ver%d" % v for v in drive.variants), s, variant))
    # detect_variant noted the drive's variant: from here on its frames go in it, no probing; the
    # jig (slave 1) and any other slave are framed in their own variant, detected at first contact
    info = m.get_slave_info(s)
    if info.type != drive.slave_type:
        raise PreflightError("the plan is for slave type %d (%s), but slave %d is type %d (%s): nothing was moved"
                             % (drive.slave_type, N.slave_type_name(drive.slave_type), s, info.type,
                                info.type_name))
    if steps:
        check_speeds(steps, m.get_parameter(s, P_AXIS_MAX_SPEED), s)
    return variant, info


P_AXIS_MAX_SPEED = 1  # the drive's parameter 1, axis_max_speed (pps): it caps every move's speed


def check_speeds(steps, max_speed, slave):
    """A step that asks for more than the drive's axis_max_speed would run slower than the plan
    says and fail a good drive (duration_ratio): refused before anything moves."""
    for step in steps:
        speed = step.args.get("speed")
        if speed is not None and speed > max_speed:
            raise PreflightError("step %s moves at %d pps, above slave %d's axis_max_speed (parameter 1) of %d "
                                 "pps: lower the step's speed or raise the parameter; nothing was moved"
                                 % (step.name, speed, slave, max_speed))


def _preflight(plan, serial, ctx):
    @htf.PhaseOptions(name="preflight")
    @htf.plug(bus=MotorJigPlug)
    def preflight(test, bus):
        """Is the drive there, of the plan's variant and type? Sets the DUT id."""
        if serial:
            test.dut_id = serial  # first: a refused drive's record still names it
        if ctx.aborted:
            raise PreflightError("aborted before the first step")
        if ctx.slot is not None:
            _name_the_slot(test, bus)
        bus.kind.preflight(test, bus, plan, serial, ctx)
        # every kind's: the jig's counters from here (a slot's: from the slots' start, reset once for
        # all of them), its safety net for the run, bus time from here
        if plan.reset_jig_counters and ctx.slot is None:
            bus.master.reset_counters(bus.jig_id)
        arm_safety_net(test, bus, ctx)
        bus.master.roundtrips.clear()

    return preflight


def _name_the_slot(test, bus):
    """A slot's record says its slot, and its plug's own settings where OpenHTF's copy of CONF
    (``metadata["config"]``, shared by the slots' runs) would show another run's."""
    md = test.test_record.metadata
    md["slot"] = bus.conf("motorjig_slot")
    config = md.get("config")
    if isinstance(config, dict):
        config.update({k: v for k, v in bus.settings.items() if isinstance(v, (str, int, float, bool, type(None)))})


def choose_sampling(test, bus, plan):
    """Who samples the axis in the moving steps (plan.sampling): the jig, when its firmware has the
    sampler, at the period its driver bus allows (``sampling.trace_period_us``); else this PC."""
    from motorjig.station import sampling

    bus.trace_period_us = None
    if plan.sampling != "pc":
        if sampling.jig_can_trace(bus.master, bus.jig_id):
            bus.trace_period_us = sampling.trace_period_us(bus.master.get_parameter(bus.jig_id, P_DOWN_BAUD))
        elif plan.sampling == "jig":
            raise PreflightError("the plan has the jig sample the axis (sampling = \"jig\"), but the jig's firmware "
                                 "has no sampler: update the jig or set sampling = \"pc\"; nothing was moved")
    test.test_record.metadata["sampling"] = (
        {"by": "jig", "period_us": bus.trace_period_us} if bus.trace_period_us else
        {"by": "pc", "why": "the plan says so" if plan.sampling == "pc" else "the jig's firmware has no sampler"})


def arm_safety_net(test, bus, ctx):
    """The jig's master-silence safety stop for the length of the run (plug.SafetyNet): what no
    signal handler can catch (SIGKILL, a crashed PC, a pulled cable) the jig catches. A drive kind with
    a watch of its own (``DriveKind.own_safety_net``) relies on it: the jig is not armed."""
    own = kinds.kind_of(ctx.plan).own_safety_net
    if own:
        test.test_record.metadata["safety_net"] = {"armed": False, "by": own}
        return
    try:
        net = bus.arm_safety_net()
    except JigError as exc:
        note = "the jig's safety stop could not be armed (%s): a killed PC would leave the axis as it is" % exc
        test.test_record.metadata["safety_net"] = {"armed": False, "problem": str(exc)}
        ctx.say(note)
        return
    if net is not None:
        test.test_record.metadata["safety_net"] = {"armed": True, "window_ms": net.window_ms,
                                                   "action": net.action}


def build_test(plan, ctx, operator=None, plug=None):
    """The plan's OpenHTF test; ``plug``: the run's own subclass of MotorJigPlug (``for_run``)."""
    phases = [build_phase(step, plan, ctx) for step in plan.steps]
    if plug is not None:
        phases = [ph.with_plugs(bus=plug) for ph in phases]
    # OpenHTF reads its own flags from sys.argv here (-v, --config-file, ...): jigctl's are not for it
    argv, sys.argv = sys.argv, sys.argv[:1]
    try:
        test = htf.Test(*phases, test_name=plan.name, test_version=plan.version, plan_hash=plan.hash,
                        plan_file=os.path.abspath(plan.path), operator=operator or "unknown")
        test.configure(stop_on_first_failure=plan.stop_on_fail, default_dut_id="unknown")
    finally:
        sys.argv = argv
    return test


def _base_name(record, plan):
    ms = record["start_time_millis"]
    # milliseconds too: two runs of one DUT within a second must not overwrite each other's files
    when = time.strftime("%Y%m%d-%H%M%S", time.localtime(ms / 1000.0)) + "-%03d" % (ms % 1000)
    safe = lambda t: re.sub(r"[^A-Za-z0-9._-]+", "-", str(t)).strip("-") or "x"  # noqa: E731
    slot = record.get("metadata", {}).get("slot")
    dut = safe(record.get("dut_id") or "unknown") + ("_slot" + safe(slot) if slot is not None else "")
    return "%s_%s_%s" % (safe(plan.name), dut, when)


def _writer(ctx, out_dir, db=None, db_lock=None):
    ctx.run_id = ctx.store_error = None
    ctx.write_errors = []

    def write(test_record):
        if ctx.end_cause:
            _name_the_cause(test_record, ctx.end_cause)
        as_json = json_factory.convert_test_record_to_json(test_record)
        text = "".join(json_factory.stream_json(as_json, indent=2))
        record = json.loads(text)
        ctx.record = record  # first: the verdict stands whatever happens to the files
        base = os.path.join(out_dir, _base_name(record, ctx.plan))
        outputs = (("json", lambda: text), ("xml", lambda: junit.junit_xml(record)),
                   ("html", lambda: report.html_report(record)))
        for ext, content in outputs:
            path = "%s.%s" % (base, ext)
            try:
                os.makedirs(out_dir, exist_ok=True)
                with open(path, "w", encoding="utf-8") as f:
                    f.write(content())
                ctx.files[ext] = path
            except Exception as exc:  # OpenHTF would only log it: the caller must see it
                ctx.write_errors.append("%s: %s" % (path, exc))
        if db is not None:
            if db_lock is None:
                _store(ctx, db, record)
            else:  # the slots' runs share one database connection
                with db_lock:
                    _store(ctx, db, record)

    return write


def _name_the_cause(test_record, cause):
    """The run's end cause first in its outcome details (what the summary, JUnit and the report
    show), in place of what the interrupted step happened to raise."""
    from openhtf.core.test_record import OutcomeDetails

    test_record.metadata["end_cause"] = cause
    code = next((name for name, c in SIGNAL_CAUSES if c == cause), "ABORTED")
    details = [d for d in test_record.outcome_details if d.description != cause]
    test_record.outcome_details[:] = [OutcomeDetails(code, cause)] + details


def check_out_dir(out_dir):
    """A sentence saying why run files cannot be written into out_dir, or None (checked before anything moves)."""
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as exc:
        return "cannot use %s for the run's files: %s" % (out_dir, exc.strerror or exc)
    if not os.access(out_dir, os.W_OK):
        return "cannot write the run's files into %s" % out_dir
    return None


def _store(ctx, db, record):
    """The run into the results database (a ``store.Store`` or what ``open_store`` takes): its id in
    ``ctx.run_id``; a failure in ``ctx.store_error`` for the caller to report (the files stay)."""
    try:
        from motorjig.station import store

        if isinstance(db, store.Store):
            ctx.run_id = db.add_run(record, ctx.files)
        else:
            with store.open_store(db) as st:
                ctx.run_id = st.add_run(record, ctx.files)
    except Exception as exc:  # OpenHTF would only log it: the caller must see it
        ctx.store_error = str(exc) or type(exc).__name__


def run_plan(plan, port, baud=115200, serial=None, operator=None, station=None, out_dir=".", out=print,
             confirm=None, timeout_ms=100, on_event=None, on_start=None, db=None, safety_window_ms=1000,
             can_port=None, slot=None, **more_ports):
    """Run ``plan`` on the drive behind ``port`` (the jig's PC port); a kind whose drive is on another
    port gets it by its key in ``DriveKind.ports`` (``can_port``: the jig's SLCAN port, and the other
    kinds' keys in ``more_ports``); returns the RunContext (``record``, ``files``).
    ``db``: the results database to store the run in (None: none), see ``station.store``.
    ``slot``: this run is one slot's of several at once (a ``station.slots.Shared``: its name, the
    jig's connection, safety net and database lock the slots share); the caller handles signals."""
    ctx = RunContext(plan, out, confirm, on_event)
    ctx.slot = slot.name if slot is not None else None
    kind = kinds.kind_of(plan)
    ports = dict(more_ports, port=port, baud=baud, timeout_ms=timeout_ms, can_port=can_port)
    if slot is not None:
        ports["master"] = slot.master  # what after_abort stops the axis through
    load = {"motorjig_port": port, "motorjig_baud": baud, "motorjig_slave": getattr(plan.drive, "slave", 2),
            "motorjig_jig_id": plan.drive.jig_id, "motorjig_timeout_ms": timeout_ms,
            "motorjig_on_end": plan.on_end, "motorjig_safety_window_ms": safety_window_ms,
            "motorjig_protocol": kind.name, "motorjig_can_port": can_port, "motorjig_lss": False}
    own = kind.conf(plan, ports)
    for name in own:  # a kind's own settings are declared by the kind's entry, not in the plug
        if name not in CONF._declarations:
            CONF.declare(name, "a setting of %s drives (station.kinds: %s)" % (kind.title, kind.name))
    load.update(own)
    if slot is not None:
        load.update(motorjig_slot=slot.name, motorjig_master=slot.master, motorjig_safety_shared=slot.safety,
                    motorjig_links=slot.links, motorjig_port_share=slot.share)
    elif station:
        load["station_id"] = station
    if slot is None:
        CONF.load(**load)  # (the slots' runs leave CONF alone: each has its own plug settings)
    console_output.CLI_QUIET = True  # our own progress lines instead of OpenHTF's banner
    plug = MotorJigPlug.for_run(load, ctx.slot or "run")
    test = build_test(plan, ctx, operator, plug)
    test.add_output_callbacks(_writer(ctx, out_dir, db, slot.db_lock if slot is not None else None))
    ctx.test = test
    if on_start is not None:  # the caller may abort from here on (ctx.abort)
        on_start(ctx)
    hook = threading.excepthook
    if slot is None:  # (the slots' runs end at unrelated times: SlotRun sets the quiet hook once for all)
        threading.excepthook = _quiet_abort(hook)
    handlers = _catch_signals(ctx)
    try:
        test.execute(test_start=_preflight(plan, serial, ctx).with_plugs(bus=plug))
    except KeyboardInterrupt:
        pass  # OpenHTF has aborted the run, torn the plug down and written the record
    except BaseException as exc:  # the engine itself failed: the axis is made safe all the same
        ctx.abort("the station failed: %s: %s" % (type(exc).__name__, exc))  # finally: EmergencyStop
        raise
    finally:
        ctx.test = None
        if slot is None:
            threading.excepthook = hook
        if (ctx.aborted or (ctx.record or {}).get("outcome") == "ABORTED") and plan.on_end != "none":
            kind.after_abort(plan, ports)
        _restore_signals(handlers)
    return ctx


# What each signal means for a run: all of them abort it (EmergencyStop, servo off, the records
# written with the cause), as Ctrl-C does. SIGHUP is a closed terminal or SSH session.
SIGNAL_CAUSES = (("SIGINT", "interrupted by SIGINT (Ctrl-C)"), ("SIGTERM", "terminated by SIGTERM"),
                 ("SIGHUP", "terminated by SIGHUP (the terminal was closed)"))


def _catch_signals(ctx):
    """Install the run's signal handlers (main thread only: the Desk's worker has its own
    shutdown); returns the ones to put back."""
    import signal

    if threading.current_thread() is not threading.main_thread():
        return {}
    previous = {}
    terminals = [fd for fd in (1, 2) if _isatty(fd)]  # known now: a hung-up terminal no longer says

    def on_signal(signum, frame):
        name = signal.Signals(signum).name
        cause = dict(SIGNAL_CAUSES)[name]
        first = not ctx.aborted
        if signum == signal.SIGHUP:
            _detach_terminal(terminals)
        if first:
            ctx.say("\n%s: stopping the axis (%s) and writing the records"
                    % (cause, kinds.kind_of(ctx.plan).emergency_words))
        else:
            ctx.say("%s: already stopping the axis, please wait" % name)
        # From a thread of its own: OpenHTF's abort takes a lock this (main) thread may hold.
        threading.Thread(target=ctx.abort, args=(cause,), name="motorjig-abort", daemon=True).start()

    for name, _cause in SIGNAL_CAUSES:
        num = getattr(signal, name, None)
        if num is not None:
            previous[num] = signal.signal(num, on_signal)
    return previous


def _restore_signals(previous):
    import signal

    for num, handler in previous.items():
        signal.signal(num, handler)


def _isatty(fd):
    try:
        return os.isatty(fd)
    except OSError:
        return False


def _detach_terminal(fds):
    """After SIGHUP the terminal is gone: writing to it would fail (EIO). What is still to say goes
    nowhere; the records say it all."""
    for fd in fds:
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, fd)
            os.close(null)
        except OSError:
            pass


def _quiet_abort(hook):
    """A threading.excepthook that says nothing of the phase thread OpenHTF stops on an abort
    (the record says the run was aborted; a traceback on the operator's terminal would not help)."""
    def excepthook(args):
        if not issubclass(args.exc_type, threads.ThreadTerminationError):
            hook(args)

    return excepthook


def emergency_stop(port, baud, slave, timeout_ms):
    """After an abort: EmergencyStop and servo off once more, on a connection of its own (the
    plug's tearDown did it already unless the abort came between two steps)."""
    from motorjig.errors import JigError
    from motorjig.master import Master

    try:
        with Master(port, baud=baud, timeout=timeout_ms / 1000.0) as m:
            make_safe(m, slave, emergency=True)
    except (JigError, OSError):
        pass  # the port cannot be opened any more: the record says how the run ended


def _abort_engine(test, cause):
    """Abort OpenHTF's executor from any thread, with the real cause in the record's log (OpenHTF's
    own abort_from_sig_int logs "Aborting ... due to SIGINT" at error level whatever the cause: the
    Desk's Abort too)."""
    from openhtf.util import logs

    executor = getattr(test, "_executor", None)
    if executor is None:  # an OpenHTF without the attribute: its own call, its own words
        test.abort_from_sig_int()
        return
    logs.get_record_logger_for(test.uid).warning("aborting the run: %s", cause)
    with test._lock:
        executor.abort()


def summary(ctx):
    """The run in a few plain values (what --json prints)."""
    r = ctx.record or {}
    steps = []
    for ph in r.get("phases", []):
        ms = {name: {"value": m.get("measured_value"), "outcome": m.get("outcome"),
                     "limits": m.get("validators", [])} for name, m in ph.get("measurements", {}).items()}
        steps.append({"name": ph["name"], "outcome": ph.get("outcome"), "measurements": ms})
    details = [d.get("description") for d in r.get("outcome_details", [])]
    return {"verdict": r.get("outcome", "ERROR"), "dut_id": r.get("dut_id"), "plan": ctx.plan.name,
            "plan_version": ctx.plan.version, "plan_hash": ctx.plan.hash, "station": r.get("station_id"),
            "operator": r.get("metadata", {}).get("operator"), "details": details, "files": ctx.files,
            "write_errors": ctx.write_errors,
            "steps": steps}
