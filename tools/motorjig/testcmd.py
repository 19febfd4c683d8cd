"""jigctl test: run a test plan with MotorJig Station, or check one (``--check``).

    jigctl test PLAN --port URL [--can-port URL] [--serial SN] [--operator NAME] [--out DIR] [--yes] [--json]
    jigctl test PLAN --port URL --slots 2,3,4,5 | --slots SLOTS.toml [...]
    jigctl test --check PLAN [--port URL] [--slots ...]

``--slots`` tests several drives at once (multi-up, ``station.slots``): each slot runs the plan
as its own run with its own records and verdict; a summary follows, and the exit status is 0
when every slot passed, 2 when any could not be judged (ERROR, aborted), else 1.

A plan whose drive kind reaches its drive on another of the jig's ports (a CiA 402 drive: the
jig's SLCAN port, ``--can-port``; on the bench its ``slcan_url``) needs that port too, beside
``--port``, the jig's PC port (its relays, inputs, counters and safety net): the kind says which
(``station.kinds``).

One progress line per step as it runs, then the verdict and the files written.
Exit status: 0 pass, 1 fail, 2 error (a bad plan, no connection, a drive of the wrong
variant, an aborted run). ``--check`` reads and checks the plan without touching the
bus; with ``--port`` it also asks the drive (read only: its variant and slave type)
whether the plan is for it.
"""

import json
import os
import sys

from motorjig.errors import JigError, PortError

EXIT_PASS, EXIT_FAIL, EXIT_ERROR = 0, 1, 2


def add_test_arguments(sp):
    sp.add_argument("plan", help="the plan file (TOML), e.g. plans/smoke.toml")
    from motorjig.station import kinds

    for kind in (kinds.get(n) for n in kinds.names()):
        for key, option, what in kind.ports:  # each kind's ports beside the jig's PC port, from the table
            if option not in sp._option_string_actions:
                sp.add_argument(option, dest=key, metavar="NAME",
                                help="%s, for a plan with protocol = \"%s\"" % (what, kind.name))
    sp.add_argument("--check", action="store_true",
                    help="only check the plan (with --port: also that the drive is the plan's variant and type)")
    sp.add_argument("--serial", help="the DUT's serial number (default: from the drive's own info)")
    sp.add_argument("--slots", metavar="ADDRS|FILE",
                    help="test several drives at once, each its own run and records: their addresses (2,3,4,5: "
                         "Plus-R slaves, CAN nodes) or a slots file (docs/station.md, Multi-up); exit status "
                         "0 all passed, 1 some failed, 2 some could not be judged")
    sp.add_argument("--operator", help="who runs the test (default: $USER, else the login name, else "
                                       "'unknown')")
    sp.add_argument("--station", help="station name in the records (default: this computer's name)")
    sp.add_argument("--out", default="results", help="folder for the record, JUnit XML and HTML report "
                                                     "(default ./results)")
    sp.add_argument("--yes", "-y", action="store_true", help="confirm every operator prompt (unattended runs)")
    sp.add_argument("--safety-window", type=int, default=1000, metavar="MS",
                    help="arm the jig's safety stop for the run: if this PC falls silent for MS ms (killed, "
                         "crashed, cable pulled) the jig stops the drive itself (default 1000; 0: not armed)")
    from motorjig.resultscmd import DB_HELP, default_db

    sp.add_argument("--db", default=default_db(), metavar="PATH|URL|none",
                    help=DB_HELP + "; every run is stored there, 'none': nowhere")


def _say(args, text):
    if not args.json:
        print(text, flush=True)


def _err(text, args=None):
    from motorjig.commands import fail

    if args is not None and getattr(args, "json", False):
        print(json.dumps({"verdict": "ERROR", "ok": False, "error": text}))
    return fail(EXIT_ERROR, text)


def default_operator():
    """Who runs the test when --operator is not given: $USER, $LOGNAME, the login name; 'unknown'
    (never blank: a record must say nobody was named)."""
    name = os.environ.get("USER") or os.environ.get("LOGNAME")
    if not name:
        try:
            import getpass

            name = getpass.getuser()
        except Exception:  # no user name anywhere (a container's uid without a passwd entry)
            name = ""
    return name.strip() or "unknown"


def _unanswerable_prompt(args, plan):
    """The first prompt step nobody could answer (no --yes, no terminal), as a sentence, or None."""
    if args.yes or sys.stdin.isatty():
        return None
    for step in plan.steps:
        if step.kind == "prompt":
            return ("step %s asks the operator to confirm, but there is no terminal to answer on: run with "
                    "--yes (unattended) or on a terminal" % step.name)
    return None


def cmd_test(args):
    try:
        from motorjig.station import kinds
        from motorjig.station import plan as P
    except ImportError as exc:
        return _err("the station needs the 'station' extra (%s): pip install 'motorjig[station]'" % exc, args)
    from motorjig.commands import note

    try:
        plan = P.load_plan(args.plan)
    except P.PlanError as exc:
        return _err(str(exc), args)
    if args.safety_window < 0 or args.safety_window > 60000:
        return _err("--safety-window must be 0 (not armed) or 1..60000 ms, not %d" % args.safety_window, args)
    problem = _unanswerable_prompt(args, plan)
    if problem and not args.check:
        return _err("%s: %s" % (args.plan, problem), args)
    if getattr(args, "slots", None) is not None:
        return _cmd_slots(args)
    kind = kinds.kind_of(plan)
    extra = {key: getattr(args, key, None) for key, _option, _what in kind.ports}
    ports = dict(extra, port=args.port, baud=args.baud, timeout_ms=args.timeout)
    if args.check:
        if args.port and kind.checks_on_port:
            try:
                refused = kind.check_on_port(ports, plan)
            except JigError as exc:
                return _err(str(exc), args)
            if refused:
                return _err("%s: %s" % (args.plan, refused), args)
        if args.json:
            print(json.dumps({"plan": plan.name, "version": plan.version, "hash": plan.hash, "ok": True,
                              "steps": [s.name for s in plan.steps]}))
        else:
            print("%s: plan %r version %s is valid: %d steps (%s)%s" % (
                args.plan, plan.name, plan.version, len(plan.steps), ", ".join(s.name for s in plan.steps),
                "; the drive is the plan's" if args.port and kind.checks_on_port else ""), flush=True)
        if problem and not args.json:  # a check moves nothing and asks nothing: a note for the run
            note("%s (when it runs)" % problem)
        return EXIT_PASS
    if not args.port:
        return _err("no port: give --port (or set JIGCTL_PORT)", args)
    for port, option, what in kind.ports:
        if not ports.get(port):
            return _err("%s is a plan for a %s drive: give %s with %s" % (
                args.plan, kind.title, what, option), args)
    from motorjig.master import Master

    from motorjig import safetynotice

    try:
        m = Master(args.port, baud=args.baud)  # a wrong port name is said plainly, before OpenHTF starts
    except PortError as exc:
        return _err(str(exc), args)
    try:
        notice = safetynotice.take(m, plan.drive.jig_id)  # what a run before this one left behind, said once
    finally:
        m.close()
    if notice:
        note(notice)
    from motorjig.station import runner

    store, problem = _open_store(args)
    if problem:
        return _err(problem, args)
    problem = runner.check_out_dir(args.out)  # after --db: a refused run leaves no empty folder behind
    if problem:
        if store is not None:
            store.close()
        return _err(problem, args)
    confirm = (lambda message: True) if args.yes else (runner.console_confirm if sys.stdin.isatty() else None)
    problem = kind.before_run(ports)  # a wrong second port is said plainly, before OpenHTF starts
    if problem:
        return _err(problem, args)
    what = kind.describe_run(plan, ports)
    _say(args, "plan %s %s (%s), %s" % (plan.name, plan.version, plan.hash[:12], what))
    try:
        ctx = runner.run_plan(plan, args.port, baud=args.baud, serial=args.serial,
                              operator=args.operator or default_operator(), station=args.station,
                              out_dir=args.out, out=None if args.json else print, confirm=confirm,
                              timeout_ms=args.timeout, db=store, safety_window_ms=args.safety_window, **extra)
    finally:
        if store is not None:
            store.close()
    try:
        return _report(args, plan, ctx, store)
    except OSError:  # the terminal went away after the run (SIGHUP): the records say it all
        return runner.exit_code(runner.summary(ctx)["verdict"])


def _report(args, plan, ctx, store):
    from motorjig.station import runner

    result = runner.summary(ctx)
    if store is not None:
        result["db"] = {"db": store.name, "run_id": ctx.run_id, "error": ctx.store_error}
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print("%s  %s  dut %s" % (result["verdict"], plan.name, result["dut_id"]))
        for d in result["details"]:
            if d:
                print("  " + d)
        for ext in ("html", "xml", "json"):
            if ext in ctx.files:
                print("  %-4s %s" % (ext, ctx.files[ext]))
        if store is not None and ctx.run_id is not None:
            print("  db   run %d in %s" % (ctx.run_id, store.name))
    for problem in ctx.write_errors:
        from motorjig.commands import fail

        fail(0, "a run file was not written: %s" % problem)
    if store is not None and ctx.store_error:
        from motorjig.commands import fail

        # the verdict stands (its exit status too): the drive was tested, only the database missed it
        fail(0, "the run was not stored: %s; its files are written (jigctl results import %s stores it "
                "later)" % (ctx.store_error, ctx.files.get("json", "RECORD.json")))
    return runner.exit_code(result["verdict"])


def _open_store(args):
    """(the results database or None, an error sentence or None)."""
    if args.db is not None and args.db.strip().lower() == "none":
        return None, None
    try:
        from motorjig.station.store import StoreError, open_store
    except ImportError as exc:
        return None, ("the results database needs the 'station' extra (%s): pip install 'motorjig[station]' "
                      "(or --db none)" % exc)
    try:
        return open_store(args.db), None  # before anything moves: a wrong --db is said now
    except StoreError as exc:
        return None, "%s (--db none runs without the results database)" % exc


def _ask_serials(slots, stdin=sys.stdin, out=sys.stderr):
    """Each slot whose serial is "ask": typed or scanned now, before anything moves."""
    for s in slots:
        if s.serial != "ask":
            continue
        if not stdin.isatty():
            raise ValueError("%s asks for its serial number, but there is no terminal to type it on: give it in "
                             "the slots file" % s.describe())
        out.write("%s: scan or type the serial number: " % s.describe())
        out.flush()
        text = stdin.readline().strip()
        if not text:
            raise ValueError("%s: no serial number given" % s.describe())
        s.serial = text


def _cmd_slots(args):
    """jigctl test PLAN --slots ...: every slot's run at once, a summary, the exit status over them."""
    from motorjig.station import kinds, runner, slots as SL

    if args.serial:
        return _err("--serial names one drive: with --slots give each slot's serial in a slots file", args)
    try:
        slots = SL.load_slots(args.slots, args.plan)
    except (SL.SlotError, JigError) as exc:  # refused, or the jig stopped answering before the slots started
        return _err(str(exc), args)
    ports = {"port": args.port, "baud": args.baud, "timeout_ms": args.timeout}
    for name in {s.kind.name for s in slots}:
        for key, _option, _what in kinds.get(name).ports:
            ports[key] = getattr(args, key, None)
    if args.check:
        if args.port:
            for s in slots:
                if s.kind.checks_on_port:
                    try:
                        refused = s.kind.check_on_port(ports, s.plan)
                    except JigError as exc:
                        return _err(str(exc), args)
                    if refused:
                        return _err("%s: %s" % (s.describe(), refused), args)
        if args.json:
            print(json.dumps({"ok": True, "slots": [{"slot": s.name, "drive": s.describe(), "plan": s.plan.name}
                                                   for s in slots]}))
        else:
            print("%d slots are valid: %s" % (len(slots), "; ".join("%s, plan %s" % (s.describe(), s.plan.name)
                                                                     for s in slots)), flush=True)
        return EXIT_PASS
    if not args.port:
        return _err("no port: give --port (or set JIGCTL_PORT)", args)
    for s in slots:
        problem = _unanswerable_prompt(args, s.plan)
        if problem:
            return _err("%s: %s" % (s.describe(), problem), args)
        for key, option, what in s.kind.ports:
            if not ports.get(key):
                return _err("%s is for a %s drive: give %s with %s" % (s.describe(), s.kind.title, what, option), args)
    try:
        _ask_serials(slots)
    except ValueError as exc:
        return _err(str(exc), args)
    from motorjig import safetynotice
    from motorjig.commands import note
    from motorjig.master import Master

    try:
        m = Master(args.port, baud=args.baud)
    except PortError as exc:
        return _err(str(exc), args)
    try:
        notice = safetynotice.take(m, slots[0].plan.drive.jig_id)
    finally:
        m.close()
    if notice:
        note(notice)
    store, problem = _open_store(args)
    if problem:
        return _err(problem, args)
    problem = runner.check_out_dir(args.out)
    for s in slots if not problem else ():
        problem = s.kind.before_run(ports)
        if problem:
            break
    if problem:
        if store is not None:
            store.close()
        return _err(problem, args)
    confirm = (lambda message: True) if args.yes else (runner.console_confirm if sys.stdin.isatty() else None)
    for s in slots:
        _say(args, "%s: plan %s %s (%s), %s" % (s.describe(), s.plan.name, s.plan.version, s.plan.hash[:12],
                                                 s.kind.describe_run(s.plan, ports)))
    extra = {k: v for k, v in ports.items() if k not in ("port", "baud", "timeout_ms")}
    run = SL.SlotRun(slots, args.port, baud=args.baud, operator=args.operator or default_operator(),
                     station=args.station, out_dir=args.out, out=None if args.json else print, confirm=confirm,
                     timeout_ms=args.timeout, db=store, safety_window_ms=args.safety_window, **extra)
    try:
        ctxs = run.run()
    except (SL.SlotError, JigError) as exc:  # refused, or the jig stopped answering before the slots started
        return _err(str(exc), args)
    finally:
        if store is not None:
            store.close()
    results = [SL.summary(s, ctxs.get(s.name), run.errors.get(s.name)) for s in slots]
    for s, r in zip(slots, results):
        ctx = ctxs.get(s.name)
        if store is not None and ctx is not None:
            r["db"] = {"db": store.name, "run_id": ctx.run_id, "error": ctx.store_error}
    verdicts = [r["verdict"] for r in results]
    try:
        _report_slots(args, results, SL.overall(verdicts))
    except OSError:  # the terminal went away after the run (SIGHUP): the records say it all
        pass
    return SL.exit_code(verdicts)


def _report_slots(args, results, verdict):
    from motorjig.commands import fail

    if args.json:
        print(json.dumps({"verdict": verdict, "slots": results}, indent=2))
        return
    print("")
    for r in results:
        print("%-5s %s  %s  dut %s" % (r["verdict"], r["drive"], r["plan"], r["dut_id"]))
        for d in r["details"]:
            if d:
                print("      " + d)
        if r["files"].get("html"):
            print("      html %s" % r["files"]["html"])
        db = r.get("db")
        if db and db.get("run_id") is not None:
            print("      db   run %d in %s" % (db["run_id"], db["db"]))
    passed = sum(1 for r in results if r["verdict"] == "PASS")
    print("%s: %d of %d slots passed" % (verdict, passed, len(results)))
    for r in results:
        for problem in r.get("write_errors", ()):
            fail(0, "slot %s: a run file was not written: %s" % (r["slot"], problem))
        db = r.get("db")
        if db and db.get("error"):
            fail(0, "slot %s: the run was not stored: %s" % (r["slot"], db["error"]))
