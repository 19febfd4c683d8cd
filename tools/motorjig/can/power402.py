"""The CiA 402 power state machine as the master sees a drive: a table the station runs.

``STATES`` says how the statusword 0x6041 shows each state (``state_of`` decodes it),
``TRANSITIONS`` lists the standard's numbered transitions with the controlword 0x6040
command that makes each one (none for the automatic ones the drive makes itself), and
``path`` finds the shortest run of commands from one state to another. The state names
are python-canopen's (``canopen.profiles.p402.State402``) and the simulated drive's
(``motorjig.sim.cia402``), so a state from any of the three compares equal.
docs/cia402-states.md is generated from these tables by tools/docgen/gen_cia402_doc.py.
"""

from collections import namedtuple

NOT_READY = "NOT READY TO SWITCH ON"
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
FAULT_REACTION = "FAULT REACTION ACTIVE"
FAULT = "FAULT"

# (state, statusword mask, value): bits 0-3 ready to switch on, switched on, operation
# enabled, fault; bit 5 quick stop (0 = active); bit 6 switch on disabled. The states
# whose mask leaves bit 5 out show it as the drive pleases.
STATES = (
    (NOT_READY, 0x4F, 0x00),
    (SWITCH_ON_DISABLED, 0x4F, 0x40),
    (READY, 0x6F, 0x21),
    (SWITCHED_ON, 0x6F, 0x23),
    (OPERATION_ENABLED, 0x6F, 0x27),
    (QUICK_STOP_ACTIVE, 0x6F, 0x07),
    (FAULT_REACTION, 0x4F, 0x0F),
    (FAULT, 0x4F, 0x08),
)
STATE_NAMES = tuple(s[0] for s in STATES)

# controlword commands (bits 0-3 and 7) -> the controlword the station writes
SHUTDOWN = "SHUTDOWN"
SWITCH_ON = "SWITCH ON"
ENABLE_OPERATION = "ENABLE OPERATION"
DISABLE_VOLTAGE = "DISABLE VOLTAGE"
QUICK_STOP = "QUICK STOP"
DISABLE_OPERATION = "DISABLE OPERATION"
FAULT_RESET = "FAULT RESET"
COMMANDS = {
    SHUTDOWN: 0x06,
    SWITCH_ON: 0x07,
    ENABLE_OPERATION: 0x0F,
    DISABLE_VOLTAGE: 0x00,
    QUICK_STOP: 0x02,
    DISABLE_OPERATION: 0x07,  # the same bits as switch on: the state tells them apart
    FAULT_RESET: 0x80,  # acts on the rising edge of bit 7
}
# Written in FAULT before a fault reset so that bit 7 rises even if the last controlword
# had it set (a fault reset the drive faulted again after); FAULT ignores it. python-canopen's
# BaseNode402.reset_from_fault does the same.
FAULT_RESET_ARM = COMMANDS[DISABLE_VOLTAGE]

# One row per (transition, command): number as CiA 402 numbers it, from, to, command
# (None: automatic, the drive makes it), controlword (None when automatic), and when it
# applies beyond the command. 0x605A is the quick stop option code.
Transition = namedtuple("Transition", "number source target command controlword condition")


def _t(number, source, target, command=None, condition=""):
    return Transition(number, source, target, command, None if command is None else COMMANDS[command], condition)


TRANSITIONS = (
    _t(1, NOT_READY, SWITCH_ON_DISABLED, None, "the drive has initialised (after power-on, transition 0)"),
    _t(2, SWITCH_ON_DISABLED, READY, SHUTDOWN),
    _t(3, READY, SWITCHED_ON, SWITCH_ON),
    _t(4, SWITCHED_ON, OPERATION_ENABLED, ENABLE_OPERATION),
    _t(5, OPERATION_ENABLED, SWITCHED_ON, DISABLE_OPERATION),
    _t(6, SWITCHED_ON, READY, SHUTDOWN),
    _t(7, READY, SWITCH_ON_DISABLED, DISABLE_VOLTAGE),
    _t(7, READY, SWITCH_ON_DISABLED, QUICK_STOP),
    _t(8, OPERATION_ENABLED, READY, SHUTDOWN),
    _t(9, OPERATION_ENABLED, SWITCH_ON_DISABLED, DISABLE_VOLTAGE),
    _t(10, SWITCHED_ON, SWITCH_ON_DISABLED, DISABLE_VOLTAGE),
    _t(10, SWITCHED_ON, SWITCH_ON_DISABLED, QUICK_STOP),
    _t(11, OPERATION_ENABLED, QUICK_STOP_ACTIVE, QUICK_STOP,
       "the drive stops as 0x605A says; with 0x605A 0 it goes straight on by 12"),
    _t(12, QUICK_STOP_ACTIVE, SWITCH_ON_DISABLED, None, "the quick stop has ended and 0x605A is 0-4"),
    _t(12, QUICK_STOP_ACTIVE, SWITCH_ON_DISABLED, DISABLE_VOLTAGE),
    _t(13, NOT_READY, FAULT_REACTION, None, "the drive detects a fault"),
    _t(13, SWITCH_ON_DISABLED, FAULT_REACTION, None, "the drive detects a fault"),
    _t(13, READY, FAULT_REACTION, None, "the drive detects a fault"),
    _t(13, SWITCHED_ON, FAULT_REACTION, None, "the drive detects a fault"),
    _t(13, OPERATION_ENABLED, FAULT_REACTION, None, "the drive detects a fault"),
    _t(13, QUICK_STOP_ACTIVE, FAULT_REACTION, None, "the drive detects a fault"),
    _t(14, FAULT_REACTION, FAULT, None, "the fault reaction (0x605E) has ended"),
    _t(15, FAULT, SWITCH_ON_DISABLED, FAULT_RESET, "bit 7 rises (the cause of the fault is gone)"),
    _t(16, QUICK_STOP_ACTIVE, OPERATION_ENABLED, ENABLE_OPERATION, "0x605A is 5-8 (the drive holds QUICK STOP ACTIVE)"),
)
HOLDS_QUICK_STOP = range(5, 9)  # the 0x605A values with which transition 16 exists


def state_of(statusword):
    """The state a statusword shows (bits outside the state's mask ignored), or None
    for a pattern the standard gives no state."""
    for name, mask, value in STATES:
        if statusword & mask == value:
            return name
    return None


def route(from_state, to_state, quick_stop_option=None):
    """The rows of ``TRANSITIONS`` the master commands to go from one state to another,
    fewest first (ties: the table's order). Transition 16 is used only when
    ``quick_stop_option`` (0x605A) is 5-8. ValueError for an unknown state or a state the
    master cannot reach or leave by commands (NOT READY TO SWITCH ON, FAULT REACTION
    ACTIVE: the drive leaves them by itself)."""
    for name in (from_state, to_state):
        if name not in STATE_NAMES:
            raise ValueError("unknown CiA 402 state %r" % (name,))
    usable = [t for t in TRANSITIONS if t.command is not None
              and (t.number != 16 or quick_stop_option in HOLDS_QUICK_STOP)]
    came = {from_state: None}  # breadth-first: state -> the row that reached it first
    frontier = [from_state]
    while frontier and to_state not in came:
        nxt = []
        for state in frontier:
            for t in usable:
                if t.source == state and t.target not in came:
                    came[t.target] = t
                    nxt.append(t.target)
        frontier = nxt
    if to_state not in came:
        raise ValueError("no controlword path from %s to %s%s" % (from_state, to_state, _why(from_state, to_state)))
    rows = []
    state = to_state
    while came[state] is not None:
        rows.append(came[state])
        state = came[state].source
    return rows[::-1]


def _why(from_state, to_state):
    if from_state in (NOT_READY, FAULT_REACTION):
        auto = [t for t in TRANSITIONS if t.source == from_state and t.command is None and t.number != 13][0]
        return " (the drive leaves %s by itself: transition %d to %s)" % (from_state, auto.number, auto.target)
    if to_state in (NOT_READY, FAULT_REACTION, FAULT):
        return " (only the drive enters %s)" % to_state
    return ""


def path(from_state, to_state, quick_stop_option=None):
    """[(controlword, expected state), ...] from one state to another (see ``route``);
    [] when they are the same. Leaving FAULT starts with ``FAULT_RESET_ARM`` (expected:
    FAULT) so that the fault reset's bit 7 rises. QUICK STOP ACTIVE as a target lasts
    only while the drive stops unless 0x605A is 5-8 (then transition 12 follows)."""
    steps = []
    for t in route(from_state, to_state, quick_stop_option):
        if t.command == FAULT_RESET:
            steps.append((FAULT_RESET_ARM, FAULT))
        steps.append((t.controlword, t.target))
    return steps
