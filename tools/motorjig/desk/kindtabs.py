"""The table of the Desk's drive-kind tabs: the tabs a drive kind adds beside the page's own.

Each entry is a module with ``TAB_ID``, ``LABEL``, ``add_arguments(parser)`` (the Desk's options for
it), ``make_link(args, read_only)`` -> (its link, or None and the sentence why) and ``Tab(page, link,
why)`` with ``build()``; its link has ``desk_axis`` (``axes.DeskAxis``: the header's STOP reaches it,
the Test tab borrows its port) and ``close()``. The page, the server and the Test tab go through this
table; adding a kind's tab is one module and one line here. (The CAN tab predates the table.)
"""

import importlib

TABS = ("motorjig.desk.ecattab",)


def modules():
    """The tab modules whose dependencies are there (the others are left out)."""
    out = []
    for name in TABS:
        try:
            out.append(importlib.import_module(name))
        except ImportError:
            continue
    return out
