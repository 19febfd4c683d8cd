"""jigctl results: the station's results database (``motorjig.station.store``) on the command line.

    jigctl results list   [--dut SN] [--plan NAME] [--slot S] [--verdict V] [--since DATE] [--until DATE] [--limit N]
    jigctl results show   RUN_ID
    jigctl results yield  --plan NAME [--slot S] [--by slot]
    jigctl results stats  --plan NAME [--slot S] [--by slot]
    jigctl results export --csv FILE [--dut ...] [--plan ...] [--slot ...] [--verdict ...] [--since ...] [--until ...]
    jigctl results import RECORD.json ...

A multi-up station's runs each carry their slot (the fixture position): ``--slot S`` keeps
that slot's runs, ``--by slot`` adds one row per slot to the whole (yield: runs, pass, fail,
error, yield; stats: n, min, mean, max, sigma, Cpk of each measurement in each slot).

Every subcommand takes ``--db PATH|URL`` (default ``$JIGCTL_DB``, else the SQLite file in
the user's data folder) and ``--json`` (one JSON document instead of the text). Exit
status 0, or 2 with one sentence on stderr (bad input, no such run, a database that
cannot be opened or is of another schema version).

One rule for what is not there: a name the database does not know (``--plan``, ``--dut``,
``--slot``, a run id) and a database that does not exist are errors (exit 2) in every subcommand;
only ``import`` (and ``jigctl test``) create the database. Filters that are each known but
match no run together (``--verdict``, ``--since``, ``--until``) are an empty answer (exit 0).
"""

import argparse
import json
import math
import os
import sys
import time

EXIT_OK, EXIT_ERROR = 0, 2
VERDICTS = ("PASS", "FAIL", "ERROR", "ABORTED", "TIMEOUT")
DB_HELP = ("results database: a SQLite file or postgresql://USER@HOST/DB (default: $JIGCTL_DB, else "
           "~/.local/share/motorjig/results.sqlite)")
SLOT_HELP = "only the runs of this slot (a multi-up fixture's position: 1, 2, A3 ...)"


class Refused(Exception):
    """A request that cannot be answered (no such run or plan, an unreadable record file)."""


def default_db():
    """The database ``--db`` means when it is not given: $JIGCTL_DB, else None (the default file)."""
    return os.environ.get("JIGCTL_DB") or None


def _verdict(text):
    v = text.upper()
    if v not in VERDICTS:
        raise argparse.ArgumentTypeError("verdict must be one of %s, not %r" % (", ".join(VERDICTS), text))
    return v


def _run_id(text):
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError("a run id is a number, not %r" % text) from None
    if v < 1:
        raise argparse.ArgumentTypeError("run ids start at 1")
    return v


def _slot(text):
    v = text.strip()
    if not v or any(ch.isspace() for ch in v):
        raise argparse.ArgumentTypeError("a slot is a fixture position's name such as 1, 2 or A3, not %r" % text)
    return v


def add_results_arguments(sp):
    """The ``results`` subcommands, on the parser jigctl made for ``results``."""
    sp.add_argument("--db", default=default_db(), metavar="PATH|URL", help=DB_HELP)
    sub = sp.add_subparsers(dest="results_command", metavar="SUBCOMMAND")
    sub.required = True

    def add(name, help_text):
        p = sub.add_parser(name, help=help_text, description=help_text)
        # SUPPRESS: given before the subcommand (jigctl --json results ...), the value stands
        p.add_argument("--db", default=argparse.SUPPRESS, metavar="PATH|URL", help=DB_HELP)
        p.add_argument("--json", action="store_true", default=argparse.SUPPRESS,
                       help="machine-readable JSON output")
        return p

    def filters(p):
        p.add_argument("--dut", help="only this DUT (serial number)")
        p.add_argument("--plan", help="only this plan (its name)")
        p.add_argument("--slot", type=_slot, help=SLOT_HELP)
        p.add_argument("--verdict", type=_verdict, help="only runs with this verdict: " + ", ".join(VERDICTS))
        p.add_argument("--since", metavar="DATE", help="runs started on or after: YYYY-MM-DD, 'YYYY-MM-DD HH:MM' "
                                                       "(local time), today, yesterday, 7d, 12h")
        p.add_argument("--until", metavar="DATE", help="runs started before the end of (a date) or at (a time)")

    p = add("list", "the last runs, newest first")
    filters(p)
    p.add_argument("--limit", type=int, default=50, help="at most this many (default 50, 0: all)")
    p = add("show", "one run: its drive, files, steps and every measurement with its limits")
    p.add_argument("run_id", type=_run_id, metavar="RUN_ID", help="the run's id (jigctl results list)")

    def by_slot(p, what):
        p.add_argument("--plan", required=True, help="the plan's name")
        p.add_argument("--slot", type=_slot, help=SLOT_HELP)
        p.add_argument("--by", choices=["slot"], help="also " + what + " of each slot")

    by_slot(add("yield", "first-pass yield (a DUT's first run passed) and final yield (its last run passed)"),
            "runs, pass, fail, error and yield")
    by_slot(add("stats", "per step and measurement: n, min, mean, max, sigma and Cpk against the limits"),
            "the figures")
    p = add("export", "every measurement of the matching runs as CSV, one row each")
    p.add_argument("--csv", required=True, metavar="FILE", help="the CSV file to write ('-': standard output)")
    filters(p)
    p = add("import", "store records written earlier (jigctl test's .json files); a run stored already is kept once")
    p.add_argument("records", nargs="+", metavar="RECORD", help="OpenHTF JSON records")


# --- output ----------------------------------------------------------------------------------------

def _local(ms):
    return "-" if ms is None else time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(ms / 1000.0))


def _num(x, digits=6):
    """A number for people: integers whole (134217727, not 1.34218e+08), others with ``digits``
    significant digits but never fewer than the integer part has (0.02739, 1.83, 1250.5,
    134217727.3); an exponent only below 0.0001."""
    if x is None:
        return "-"
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return str(x)
    if isinstance(x, int):
        return str(x)
    if not math.isfinite(x):
        return str(x)
    if x == int(x) and abs(x) < 1e15:
        return str(int(x))
    mag = math.floor(math.log10(abs(x)))
    if mag < -4:
        return "%.*g" % (digits, x)
    # digits significant digits; a large number that is not whole keeps one decimal (a mean of counts)
    text = "%.*f" % (max(digits - 1 - mag, 1 if mag >= digits - 1 else 0), x)
    return text.rstrip("0").rstrip(".") if "." in text else text


def _count(n, word):
    return "%d %s%s" % (n, word, "" if n == 1 else "s")


def _table(headers, rows):
    rows = [[str(c) for c in r] for r in rows]
    widths = [max([len(h)] + [len(r[i]) for r in rows]) for i, h in enumerate(headers)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(headers, widths)).rstrip()]
    lines += ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    return "\n".join(lines)


def _emit(args, obj, text):
    if args.json:
        print(json.dumps(obj, indent=2))
    elif text:
        print(text)


def _no_plan(st, plan):
    plans = st.plans()
    known = ", ".join(sorted(plans)) or "none yet"
    return "no runs of plan %r in %s (plans there: %s)" % (plan, st.name, known)


def _known_names(args, st):
    """The one rule of every subcommand: a --plan or --dut the database has no run of is refused
    (a typo must not read as "no runs"); filters that match nothing together are an empty answer."""
    plan = getattr(args, "plan", None)
    if plan is not None and plan not in st.plans():
        raise Refused(_no_plan(st, plan))
    dut = getattr(args, "dut", None)
    if dut is not None and not st.runs(dut=dut, limit=1):
        raise Refused("no runs of DUT %r in %s" % (dut, st.name))
    slot = getattr(args, "slot", None)
    if slot is not None and not st.runs(slot=slot, limit=1):
        raise Refused("no runs in slot %r in %s (slots there: %s)"
                      % (slot, st.name, ", ".join(st.slots()) or "none, no run was a slot"))


# --- the subcommands ---------------------------------------------------------------------------------

def _filter_args(args):
    return {"dut": args.dut, "plan": args.plan, "verdict": args.verdict, "since": args.since, "until": args.until,
            "slot": args.slot}


def _slot_text(slot):
    return "-" if slot is None else slot


def _list(args, st):
    _known_names(args, st)
    runs = st.runs(limit=args.limit, **_filter_args(args))
    slots = any(r["slot"] is not None for r in runs)  # the column only where there are slots
    text = _table(["id", "start", "plan", "version", "dut", "station"] + ["slot"] * slots + ["verdict", "time"],
                  [[r["id"], _local(r["start_ms"]), r["plan"], r["plan_version"], r["dut"], r["station"] or "-"]
                   + [_slot_text(r["slot"])] * slots
                   + [r["verdict"], "-" if r["seconds"] is None else "%.1f s" % r["seconds"]] for r in runs]) \
        if runs else "no runs in %s match" % st.name
    _emit(args, {"db": st.name, "runs": runs}, text)
    return EXIT_OK


def _show(args, st):
    r = st.run(args.run_id)
    if r is None:
        raise Refused("no run %d in %s" % (args.run_id, st.name))
    if args.json:
        _emit(args, r, None)
        return EXIT_OK
    d = r["drive"]
    lines = ["run %d  %s %s (%s)  %s" % (r["id"], r["plan"], r["plan_version"], (r["plan_hash"] or "-")[:12],
                                         r["verdict"]),
             "dut %s, station %s%s, operator %s, %s, %s" % (
                 r["dut"], r["station"] or "-", "" if r["slot"] is None else ", slot %s" % r["slot"], r["operator"],
                 _local(r["start_ms"]), "-" if r["seconds"] is None else "%.2f s" % r["seconds"])]
    if d["slave"] is not None:
        from motorjig.station import kinds

        lines.append("drive: " + kinds.of_record_code(d["protocol"]).stored_text(d))
    if r["details"]:
        lines.append("details: " + r["details"])
    for kind, path in r["files"].items():
        lines.append("  %-4s %s" % (kind, path))
    rows = []
    for ph in r["phases"]:
        if not ph["measurements"]:
            rows.append([ph["name"], "-", "", "", "", ph["outcome"]])
        for m in ph["measurements"]:
            value = m["text"] if m["text"] is not None else "(not measured)"
            rows.append([ph["name"], m["name"], value, m["unit"] or "", m["limits"] or "", m["outcome"]])
    lines += ["", _table(["step", "measurement", "value", "unit", "limits", "outcome"], rows)]
    print("\n".join(lines))
    return EXIT_OK


def _yield(args, st):
    _known_names(args, st)
    y = st.yield_(args.plan, slot=args.slot)
    if not y["runs"]:  # a known plan and a known slot, but no run of the one in the other
        if args.by == "slot":
            y["by_slot"] = []
        _emit(args, y, "no runs of plan %s in slot %s in %s" % (args.plan, args.slot, st.name))
        return EXIT_OK
    pct = lambda f: "%.1f %%" % (100.0 * f)  # noqa: E731
    lines = ["plan %s%s: %s, %s" % (y["plan"], "" if args.slot is None else ", slot %s" % args.slot,
                                    _count(y["duts"], "DUT"), _count(y["runs"], "run")),
             "  first-pass yield  %7s  (%d of %s passed the first run)"
             % (pct(y["first_pass_yield"]), y["first_pass"], _count(y["duts"], "DUT")),
             "  final yield       %7s  (%d of %s passed the last run)"
             % (pct(y["final_yield"]), y["final_pass"], _count(y["duts"], "DUT"))]
    if args.by == "slot":
        y["by_slot"] = rows = st.yield_by_slot(args.plan, slot=args.slot)
        total = {k: sum(r[k] for r in rows) for k in ("runs", "pass", "fail", "error")}
        lines += ["", "runs per slot (yield: the share of the slot's runs that passed; error: ERROR, TIMEOUT, "
                      "ABORTED)",
                  _table(["slot", "runs", "pass", "fail", "error", "yield"],
                         [[_slot_text(r["slot"]), r["runs"], r["pass"], r["fail"], r["error"], pct(r["yield"])]
                          for r in rows]
                         + [["all", total["runs"], total["pass"], total["fail"], total["error"],
                             pct(total["pass"] / total["runs"])]])]
    _emit(args, y, "\n".join(lines))
    return EXIT_OK


def _stats(args, st):
    _known_names(args, st)
    rows = st.stats(args.plan, slot=args.slot)
    doc = {"plan": args.plan, "stats": rows}
    if args.slot is not None:
        doc["slot"] = args.slot
    head = ["step", "measurement", "n", "min", "mean", "max", "sigma", "LSL", "USL", "Cpk", "unit"]
    figures = lambda s: [s["n"], _num(s["min"]), _num(s["mean"]), _num(s["max"]), _num(s["sigma"], 4),  # noqa: E731
                         _num(s["low"]), _num(s["high"]), _num(s["cpk"], 3), s["unit"] or ""]
    if args.by == "slot":
        doc["by_slot"] = per_slot = st.stats_by_slot(args.plan, slot=args.slot) if rows else []
    if not rows:
        text = "plan %s has no numeric measurements%s" % (args.plan, "" if args.slot is None
                                                          else " in slot %s" % args.slot)
    elif args.by == "slot":
        # each measurement's whole ("all"), then its slots, so that a slot off the others stands out
        table = []
        for s in rows:
            key = (s["step"], s["measurement"], s["unit"], s["limits"])
            table.append([s["step"], s["measurement"], "all"] + figures(s))
            table += [[s["step"], s["measurement"], _slot_text(p["slot"])] + figures(p) for p in per_slot
                      if (p["step"], p["measurement"], p["unit"], p["limits"]) == key]
        text = _table(head[:2] + ["slot"] + head[2:], table)
    else:
        text = _table(head, [[s["step"], s["measurement"]] + figures(s) for s in rows])
    _emit(args, doc, text)
    return EXIT_OK


def _export(args, st):
    _known_names(args, st)
    if args.csv == "-":
        st.export_csv(sys.stdout, **_filter_args(args))
        return EXIT_OK
    try:
        n = st.export_csv(args.csv, **_filter_args(args))
    except OSError as exc:
        raise Refused("cannot write %s: %s" % (args.csv, exc.strerror or exc)) from None
    _emit(args, {"file": os.path.abspath(args.csv), "rows": n},
          "%s to %s" % (_count(n, "row"), args.csv) if n else "no runs in %s match: %s has the header only"
          % (st.name, args.csv))
    return EXIT_OK


def _import(args, st):
    items = []
    for path in args.records:
        try:
            with open(path, encoding="utf-8") as f:
                record = json.load(f)
        except OSError as exc:
            raise Refused("cannot read %s: %s" % (path, exc.strerror or exc)) from None
        except ValueError as exc:
            raise Refused("%s is not JSON (%s)" % (path, exc)) from None
        if not isinstance(record, dict) or "start_time_millis" not in record:
            raise Refused("%s is not an OpenHTF test record" % path)
        base = os.path.splitext(path)[0]
        files = {"json": path}
        files.update((ext, base + "." + ext) for ext in ("xml", "html") if os.path.exists(base + "." + ext))
        items.append((record, files))
    ids = st.add_runs(items)
    _emit(args, {"db": st.name, "run_ids": ids},
          "%s in %s: run ids %s" % (_count(len(ids), "record"), st.name, ", ".join(map(str, ids))))
    return EXIT_OK


HANDLERS = {"list": _list, "show": _show, "yield": _yield, "stats": _stats, "export": _export, "import": _import}


def cmd_results(args):
    from motorjig.commands import fail

    try:
        from motorjig.station import store as S
    except ImportError as exc:
        return fail(EXIT_ERROR, "the results database needs the 'station' extra (%s): "
                                "pip install 'motorjig[station]'" % exc)
    try:
        # only import writes: the others refuse a database that is not there instead of creating it
        with S.open_store(args.db, create=args.results_command == "import") as st:
            return HANDLERS[args.results_command](args, st)
    except (S.StoreError, Refused) as exc:
        return fail(EXIT_ERROR, str(exc))
    except BrokenPipeError:
        raise  # output piped into e.g. head, which has exited: jigctl's main handles it
    except OSError as exc:
        name = getattr(exc, "filename", None)
        return fail(EXIT_ERROR, "%s%s" % ("%s: " % name if name else "", exc.strerror or exc))
