"""Parameter-set files: a drive's parameters by name, in TOML.

The one format of ``jigctl param dump`` / ``jigctl param load`` and of a test plan's
``parameters`` step (the golden set a drive is verified against)::

    # parameter set of slave 2 (Ezi-STEP Plus-R ST), RAM, 2026-12-01 18:30
    [drive]
    slave_type = 20

    [parameters]
    axis_max_speed = 500000     # 1: max speed, pps
    axis_acc_time = 100         # 3: acceleration time, ms

Keys are the parameter names of ``motorjig.names.STEP_PARAMS`` (or their numbers,
``3 = 100``); every value is range-checked against that table. A name or number the
drive's table does not have is an error that names the file, line and key.
"""

import time

from motorjig import names as N
from motorjig.tomlsource import SourceError, read_toml

TABLE = N.STEP_PARAMS


class ParamSet:
    """``values``: {number: value} in number order; ``slave_type``: the drive it was taken from."""

    def __init__(self, values, slave_type=None, path=None, raw=b""):
        self.values = dict(sorted(values.items()))
        self.slave_type = slave_type
        self.path = path
        self.raw = raw

    def items(self):
        """(Param, value) in number order."""
        return [(N.find_param(TABLE, n), v) for n, v in self.values.items()]


def load(path):
    """Read and check a parameter-set file; SourceError (file:line: key: why) on any problem."""
    data, lines, raw = read_toml(path)
    unknown = sorted(set(data) - {"drive", "parameters"})
    if unknown:
        raise SourceError(path, lines.line((unknown[0],)), unknown[0],
                          "unknown table (a parameter set has [drive] and [parameters])")
    drive = data.get("drive", {})
    slave_type = drive.get("slave_type")
    for k in drive:
        if k != "slave_type":
            raise SourceError(path, lines.line(("drive", k)), "drive." + k, "unknown key (only slave_type)")
    if slave_type is not None and (not isinstance(slave_type, int) or isinstance(slave_type, bool)):
        raise SourceError(path, lines.line(("drive", "slave_type")), "drive.slave_type", "expected an integer")
    params = data.get("parameters")
    if not isinstance(params, dict) or not params:
        raise SourceError(path, lines.line(("parameters",)), "parameters", "no [parameters] table with values")
    values = {}
    for name, value in params.items():
        where = lines.line(("parameters", name))
        p = N.find_param(TABLE, name)
        if p is None:
            raise SourceError(path, where, "parameters." + name,
                              "the drive has no such parameter (Ezi-STEP Plus-R: 0..%d, see "
                              "`jigctl param list --offline`)" % TABLE[-1].number)
        if not isinstance(value, int) or isinstance(value, bool):
            raise SourceError(path, where, "parameters." + name, "expected an integer, got %r" % (value,))
        try:
            p.check(value)
        except ValueError as exc:
            raise SourceError(path, where, "parameters." + name, str(exc)) from None
        if p.number in values:
            raise SourceError(path, where, "parameters." + name, "parameter %d given twice" % p.number)
        values[p.number] = value
    return ParamSet(values, slave_type, path, raw)


def dumps(values, slave=None, slave_type=None, memory="RAM", when=None):
    """The file text of ``values`` ({number: value}), one commented line per parameter."""
    when = when or time.strftime("%Y-%m-%d %H:%M")
    what = "slave %s" % slave if slave is not None else "a drive"
    if slave_type is not None:
        what += " (%s)" % N.slave_type_name(slave_type)
    out = ["# parameter set of %s, %s, %s (jigctl param dump)" % (what, memory, when), ""]
    if slave_type is not None:
        out += ["[drive]", "slave_type = %d" % slave_type, ""]
    out.append("[parameters]")
    for number, value in sorted(values.items()):
        p = N.find_param(TABLE, number)
        left = "%s = %d" % (p.name, value)
        out.append("%-40s # %d: %s%s" % (left, number, p.meaning, ", " + p.unit if p.unit else ""))
    return "\n".join(out) + "\n"
