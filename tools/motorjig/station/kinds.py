"""The table of drive kinds: each kind's name and the module that speaks to it.

Generic code (the runner, the Desk) asks this table about a plan's drive instead of
branching on its protocol; a new kind is one more row and its own module. The drive
module is imported only when its kind is used (python-canopen stays unloaded for a
Plus-R run).
"""

import importlib

# kind (a plan's [drive] protocol) -> "module:class" of its station.drive.Drive
KINDS = {
    "plusr": "motorjig.station.drive_plusr:PlusRDrive",
    "cia402": "motorjig.station.drive_cia402:Cia402Drive",
}
DEFAULT = "plusr"


def kind_of(plan):
    """The plan's drive kind (its ``[drive] protocol``; Plus-R when it names none)."""
    return getattr(plan.drive, "protocol", None) or DEFAULT


def drive_class(kind):
    """The ``Drive`` class of a kind; KeyError for a kind not in the table."""
    module, _, name = KINDS[kind].partition(":")
    return getattr(importlib.import_module(module), name)
