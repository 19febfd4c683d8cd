"""Markdown tables generated from the firmware's data (bridge states, parameters, counters).

docs/bridge.md, docs/parameters.md, docs/diagnostics.md and docs/station.md embed these
between ``<!-- BEGIN name -->`` / ``<!-- END name -->`` markers; a host test checks
they match, and ``python -m motorjig.sim.doctables --write`` refreshes them.
Every table listed for a document must have its markers there.
"""

import os
import re
import sys

from jig import bridge, diag, params

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def bridge_table():
    rows = ["| state \\ event | " + " | ".join(bridge.EVENT_NAMES) + " |",
            "| --- |" + " --- |" * len(bridge.EVENT_NAMES)]
    for s, name in enumerate(bridge.STATE_NAMES):
        cells = []
        for flags, nxt in bridge.TRANSITIONS[s]:
            acts = [n for i, n in enumerate(bridge.FLAG_NAMES) if flags & (1 << i)] or ["-"]
            cells.append("%s → %s" % (", ".join(acts), bridge.STATE_NAMES[nxt]))
        rows.append("| **%s** | %s |" % (name, " | ".join(cells)))
    return "\n".join(rows)


def param_table():
    rows = ["| # | name | unit | min | max | default | takes effect |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for num, name, unit, lo, hi, default, when in params.TABLE:
        rows.append("| %d | `%s` | %s | %d | %d | %d | %s |" % (num, name, unit or "-", lo, hi, default, when))
    return "\n".join(rows)


def counter_table():
    rows = ["| index | name |", "| --- | --- |"]
    for i, name in enumerate(diag.WIRE_NAMES):
        rows.append("| %d | `%s` |" % (i, name))
    return "\n".join(rows)


def timeout_table():
    rows = ["| frame type | multiplier |", "| --- | --- |"]
    for t in range(256):
        m = bridge.TIMEOUT_MULTIPLIER[t]
        if m != 1:
            rows.append("| 0x%02X | ×%d |" % (t, m))
    return "\n".join(rows)


def station_plan_format():
    from motorjig.station.schema import render_reference

    return render_reference().rstrip("\n")


TABLES = {
    "docs/station.md": {"plan-format": station_plan_format},
    "docs/bridge.md": {"bridge-states": bridge_table, "timeouts": timeout_table},
    "docs/parameters.md": {"params": param_table},
    "docs/diagnostics.md": {"counters": counter_table},
}


def expected(path, text):
    """text with every marked table regenerated (ValueError: required markers missing)."""
    for name, fn in TABLES[path].items():
        pat = re.compile(r"(<!-- BEGIN %s -->\n)(?:.*?\n)?(<!-- END %s -->)" % (name, name), re.S)
        if not pat.search(text):
            raise ValueError("%s has no %s markers" % (path, name))
        text = pat.sub(lambda m: m.group(1) + fn() + "\n" + m.group(2), text)
    return text


def main(argv):
    write = "--write" in argv
    stale = 0
    for rel in TABLES:
        path = os.path.join(ROOT, rel)
        try:
            with open(path) as f:
                text = f.read()
            new = expected(rel, text)
        except (OSError, ValueError) as exc:
            print("error: %s" % exc, file=sys.stderr)
            return 1
        if new != text:
            stale += 1
            if write:
                with open(path, "w") as f:
                    f.write(new)
                print("updated %s" % rel)
            else:
                print("%s is out of date (run with --write)" % rel)
    return 1 if stale and not write else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
