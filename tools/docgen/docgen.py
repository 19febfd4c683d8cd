"""What the tools/docgen/gen_*_doc.py generators share: their command line and the table's diagram.

Each generator renders one Markdown file from the code's own tables; ``main`` gives them
the same ``--check``/``--output`` interface (write the file, or exit 1 if the committed file
is not what the tables give), and ``table_edges`` draws a byte-driven transition table
(``TRANSITIONS[state][byte class] = (action, next state)``) of a firmware module as Markdown
tables and Mermaid edges.
"""

import argparse
import importlib
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def main(argv, name, description, default_output, render):
    """The generator ``name``'s command line: write ``render()`` to the output, or ``--check`` it."""
    rel = os.path.relpath(default_output, ROOT)
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--check", action="store_true", help="exit 1 if the file differs from the generated text")
    ap.add_argument("--output", default=default_output, help="file to write or check (default: %s)" % rel)
    args = ap.parse_args(argv)
    text = render()
    if args.check:
        try:
            with open(args.output, encoding="utf-8") as f:
                current = f.read()
        except OSError as e:
            print("%s: cannot read %s: %s" % (name, args.output, e.strerror))
            return 1
        if current != text:
            print("%s: %s is out of date; run: python tools/%s.py" % (name, args.output, name))
            return 1
        print("%s: %s is up to date" % (name, args.output))
        return 0
    try:
        os.makedirs(os.path.dirname(os.path.abspath(args.output)), exist_ok=True)
        with open(args.output, "w", encoding="utf-8") as f:
            f.write(text)
    except OSError as e:
        print("%s: cannot write %s: %s" % (name, args.output, e.strerror))
        return 1
    print("%s: wrote %s" % (name, args.output))
    return 0


def firmware_table(module, action_help, name):
    """Import ``jig.<module>`` (a byte-driven table) and check ``action_help`` still matches its actions."""
    firmware = os.path.join(ROOT, "firmware")
    if firmware not in sys.path:
        sys.path.insert(0, firmware)
    mod = importlib.import_module("jig." + module)
    if len(action_help) != len(mod.ACTION_NAMES):
        raise SystemExit("%s: %s.ACTION_NAMES changed; update ACTION_HELP" % (name, module))
    return mod


def table_rows(transitions, states, actions, counted=()):
    """Markdown rows of the transition table: per byte class its action and the next state."""
    lines = []
    for s, row in enumerate(transitions):
        cells = []
        for action, nxt in row:
            if action in counted:
                target = "stay, last → " + states[nxt]
            else:
                target = "stay" if nxt == s else "→ " + states[nxt]
            cells.append("%s, %s" % (actions[action], target))
        lines.append("| **%s** | %s |" % (states[s], " | ".join(cells)))
    return lines


def action_rows(actions, action_help):
    """The Markdown table of the actions and what each does."""
    return ["| action | meaning |", "| --- | --- |"] + [
        "| %s | %s |" % (name, help_text) for name, help_text in zip(actions, action_help)]


def table_edges(transitions, states, classes, actions, counted=()):
    """Mermaid lines, one edge per (state, next state); its label lists the byte classes by action.

    An action in ``counted`` stays in its state until a count runs out, so it also gets the
    self-loop the table does not show. No ':' or ';' inside a label: Mermaid reads those as syntax.
    """
    lines = []
    for s, row in enumerate(transitions):
        edges = {}
        for c, (action, nxt) in enumerate(row):
            edges.setdefault(nxt, {}).setdefault(action, []).append(classes[c])
            if action in counted and nxt != s:
                edges.setdefault(s, {}).setdefault(action, []).append(classes[c])
        for nxt in sorted(edges):
            parts = ["%s (%s)" % (", ".join(cls), actions[a]) for a, cls in sorted(edges[nxt].items())]
            lines.append("    %s --> %s: %s" % (states[s], states[nxt], " / ".join(parts)))
    return lines
