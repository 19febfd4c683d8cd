"""The name and length tables of the Lua dissector, generated from the project's Python tables.

``plusr.lua`` carries them between the ``BEGIN GENERATED`` and ``END GENERATED``
lines; this module writes that block from ``jig.frame``, ``jig.diag``,
``jig.params``, ``motorjig.names``, ``motorjig.errors``, ``motorjig.master``, ``motorjig.decode`` and
``motorjig.capture`` (record verdicts, link type, Ver8 request lengths), so the
dissector, ``jigctl capture`` and ``jigctl monitor`` name every code the same
way. ``host_tests/test_capture_dissector.py`` fails when the block is stale.

    python -m motorjig.capture.luagen --check     # exit 1 if plusr.lua is stale
    python -m motorjig.capture.luagen --write     # regenerate the block in place
"""

import argparse
import os
import sys

BEGIN = "-- BEGIN GENERATED"
END = "-- END GENERATED"
LUA_PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), "plusr.lua")


def lua_str(text):
    out = ['"']
    for ch in str(text):
        o = ord(ch)
        if ch in '"\\':
            out.append("\\" + ch)
        elif 0x20 <= o < 0x7F:
            out.append(ch)
        else:
            for b in ch.encode("utf-8"):
                out.append("\\%d" % b)
    out.append('"')
    return "".join(out)


def _value(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return lua_str(v)
    if isinstance(v, (tuple, list)):
        return "{" + ", ".join(_value(x) for x in v) + "}"
    raise TypeError("no Lua form for %r" % (v,))


def _map(name, table, key_hex=False):
    lines = ["G.%s = {" % name]
    for k in sorted(table):
        key = "0x%02X" % k if key_hex else str(k)
        lines.append("  [%s] = %s," % (key, _value(table[k])))
    lines.append("}")
    return lines


def _list(name, rows):
    return ["G.%s = {" % name] + ["  %s," % _value(r) for r in rows] + ["}"]


def _lengths(table):
    """{type: int or tuple} -> {type: list of allowed lengths} (-1: any)."""
    return {k: list(v) if isinstance(v, tuple) else [v] for k, v in table.items()}


def tables():
    """(name, lines) of every generated table, in order."""
    from jig import diag as D
    from jig import frame as F
    from jig import params as JP
    from jig.parser import MIN_BODY

    from motorjig import decode as DEC
    from motorjig import master as M
    from motorjig import names as N
    from motorjig.capture import pcapng, record as R, variant as V
    from motorjig.errors import status_meaning

    scalars = [
        ("LINKTYPE_PC", pcapng.LINKTYPES["pc"]), ("LINKTYPE_DRIVERS", pcapng.LINKTYPES["drivers"]), ("BROADCAST_ID", F.BROADCAST_ID), ("MAX_SLAVE_ID", F.MAX_SLAVE_ID),
        ("MIN_BODY", MIN_BODY), ("MAX_BODY", F.MAX_BODY), ("MAX_DATA", F.MAX_DATA), ("VAR", M.VAR),
        ("STATUS_OK", F.STATUS_OK), ("COMMENT_PREFIX", R.COMMENT_PREFIX),
        ("START_PREFIX", R.START_PREFIX), ("JIG_PREFIX", R.JIG_PREFIX),
        ("DIR_INBOUND", R.DIR_INBOUND), ("DIR_OUTBOUND", R.DIR_OUTBOUND),
        ("PAIR_MS", int(DEC.PAIR_SECONDS * 1000)),
    ]
    out = [("scalars", ["G.%s = %s" % (k, _value(v)) for k, v in scalars])]
    out.append(("FRAME_NAMES", _map("FRAME_NAMES", N.FRAME_NAMES, True)))
    out.append(("STATUS_NAMES", _map("STATUS_NAMES", N.STATUS_NAMES, True)))
    out.append(("STATUS_MEANINGS", _map("STATUS_MEANINGS", {c: status_meaning(c) for c in N.STATUS_NAMES}, True)))
    out.append(("AXIS_FLAGS", _list("AXIS_FLAGS", N.AXIS_FLAGS)))
    out.append(("AXIS_ERROR_FLAGS", _list("AXIS_ERROR_FLAGS", N.AXIS_ERROR_FLAGS)))
    out.append(("INPUT_BITS", _list("INPUT_BITS", N.INPUT_BITS)))
    out.append(("OUTPUT_BITS", _list("OUTPUT_BITS", N.OUTPUT_BITS)))
    out.append(("ALARM_NAMES", _map("ALARM_NAMES", N.ALARM_NAMES)))
    out.append(("SLAVE_TYPES", _map("SLAVE_TYPES", N.SLAVE_TYPES)))
    out.append(("STEP_PARAMS", _map("STEP_PARAMS", {p.number: (p.name, p.unit) for p in N.STEP_PARAMS})))
    out.append(("JIG_PARAMS", _map("JIG_PARAMS", {row[0]: (row[1], row[2]) for row in JP.TABLE})))
    out.append(("REQUEST_LEN", _map("REQUEST_LEN", _lengths(M.REQUEST_LEN), True)))
    out.append(("REQUEST_LEN_VER8", _map("REQUEST_LEN_VER8", _lengths(V.REQUEST_LEN_VER8), True)))
    out.append(("REPLY_LEN", _map("REPLY_LEN", _lengths(M.REPLY_LEN), True)))
    out.append(("REPLY_LEN_VER8", _map("REPLY_LEN_VER8", _lengths(M.REPLY_LEN_VER8), True)))
    jig = [("READ_COUNTERS", D.READ_COUNTERS), ("RESET_COUNTERS", D.RESET_COUNTERS),
           ("START_BUS_SCAN", D.START_BUS_SCAN), ("GET_BUS_SCAN_RESULT", D.GET_BUS_SCAN_RESULT),
           ("READ_CRASH_LOG", D.READ_CRASH_LOG), ("SLAVE_TYPE", D.SLAVE_TYPE), ("SCAN_IDS", D.SCAN_IDS),
           ("SCAN_REPLY_LEN", D.SCAN_REPLY_LEN)]
    out.append(("JIG", ["G.JIG = {"] + ["  %s = %s," % (k, _value(v)) for k, v in jig] + ["}"]))
    out.append(("COUNTER_NAMES", _list("COUNTER_NAMES", D.WIRE_NAMES)))
    out.append(("SCAN_STATES", _map("SCAN_STATES", dict(enumerate(D.SCAN_STATE_NAMES)))))
    out.append(("VERDICTS", _map("VERDICTS", {c: v[0] for c, v in R.VERDICTS.items()})))
    return out


def render():
    lines = [BEGIN + " by motorjig.capture.luagen from the project's Python tables: do not edit;",
             "-- regenerate with: python -m motorjig.capture.luagen --write",
             "local G = {}"]
    for _name, body in tables():
        lines.extend(body)
    lines.append(END)
    return "\n".join(lines) + "\n"


def split(text):
    """(before, generated block, after) of a dissector source."""
    b = text.find(BEGIN)
    e = text.find(END, b)
    if b < 0 or e < 0:
        raise ValueError("no generated block (%s ... %s) in the dissector" % (BEGIN, END))
    e = text.index("\n", e) + 1
    return text[:b], text[b:e], text[e:]


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m motorjig.capture.luagen",
                                 description="Generate or check the tables block of the Plus-R Lua dissector.")
    ap.add_argument("--check", action="store_true", help="exit 1 if the block in the file is not what the tables give")
    ap.add_argument("--write", action="store_true", help="rewrite the block in the file")
    ap.add_argument("file", nargs="?", default=LUA_PATH, help="the dissector (default: the package's plusr.lua)")
    args = ap.parse_args(argv)
    fresh = render()
    if not (args.check or args.write):
        sys.stdout.write(fresh)
        return 0
    with open(args.file, encoding="utf-8") as f:
        text = f.read()
    before, block, after = split(text)
    if args.write:
        if block != fresh:
            with open(args.file, "w", encoding="utf-8") as f:
                f.write(before + fresh + after)
        print("%s: tables %s" % (args.file, "regenerated" if block != fresh else "already current"))
        return 0
    if block != fresh:
        print("%s: the generated tables are stale; run python -m motorjig.capture.luagen --write" % args.file)
        return 1
    print("%s: tables current" % args.file)
    return 0

if __name__ == "__main__":
    sys.exit(main())
