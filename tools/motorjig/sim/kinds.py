"""The bench's table of simulated drive kinds: what it puts on its CAN bus, and the faults it
knows there by name.

The bench (``sim.bench``) and its command line (``python -m motorjig.sim``) ask this table for
the CAN bus's default node and its fault list instead of naming a drive model; another kind of
simulated CAN drive is one more model module and a change of this entry.
"""

import importlib

# what --can-nodes puts on the bus by default: "module:class" with (clock, bus, node_id)
CAN_NODE = "motorjig.sim.cia402:Cia402Node"


def _can_model():
    return importlib.import_module(CAN_NODE.partition(":")[0])


def can_node(clock, bus, node_id):
    """The default CAN node: a simulated drive of the table's model (imported when first needed)."""
    return getattr(_can_model(), CAN_NODE.partition(":")[2])(clock, bus, node_id)


def can_faults():
    """{name: (value, default, what)} of the CAN node model's faults ({} without the model)."""
    try:
        return _can_model().FAULTS
    except ImportError:
        return {}


def parse_can_fault(name, value):
    """The model's own check of a CAN fault (ValueError when it has no such fault or a bad value);
    None when the model cannot be loaded (its set_fault judges then)."""
    try:
        parse = _can_model().parse_fault
    except ImportError:
        return None
    return parse(name, value)


# the buses the bench can add beside its own, each a module with add_arguments(ap) and start(args)
# (a child process with ``banner`` and ``title``, or None when its options ask for none)
EXTRA_BUSES = ("motorjig.sim.ecat_cli",)


def extra_buses():
    """The modules of ``EXTRA_BUSES`` (one whose dependencies are missing is left out)."""
    out = []
    for name in EXTRA_BUSES:
        try:
            out.append(importlib.import_module(name))
        except ImportError:
            continue
    return out
