"""The step kinds on an EtherCAT CiA 402 drive: CiA 402's steps (``phases_cia402``) through ``EcatDrive``,
and the one that is EtherCAT's own, ``bus-health``: the cycle judged over the run.

The moving steps are CiA 402's: ``EcatDrive`` gives them the same methods (move in CSP with the
station's trapezoid, samples every cycle dated by the distributed clock). ``step_functions``
picks a step's measurements and run, with the EMCY rule of every CiA 402 step around them.
"""

import json

from motorjig.station import phases_cia402 as P

MS = P.MS


def measures_bus_health(step, plan):
    h, a = P._h(), step.args
    late = a.get("late_cycles_max")
    doc_late = "cycles the PC sent more than 1.5 periods after the one before (the PC's lateness)"
    return [h._at_most("frames_lost", a.get("frames_lost_max", 0), doc="frames that did not come back"),
            h._at_most("wkc_errors", a.get("wkc_errors_max", 0), doc="frames with a working counter short of "
                                                                   "the expected"),
            h._at_most("late_cycles", late, doc=doc_late) if late is not None else h._m("late_cycles", doc=doc_late),
            h._m("period_p99", MS, "99th percentile of the period between two cycles on the master's side"),
            h._m("period_max", MS, "the longest period between two cycles"),
            h._at_most("emcy", a.get("emcy_max", 0), doc="emergencies with an error code over the run")]


def run_bus_health(test, bus, step, ctx):
    d, m = bus.drive, test.measurements
    counters = d.bus_health()
    m["frames_lost"] = counters["frames_lost"]
    m["wkc_errors"] = counters["wkc_errors"]
    m["late_cycles"] = counters["late_cycles"]
    m["period_p99"] = counters["period_p99_ms"]
    m["period_max"] = counters["period_max_ms"]
    m["emcy"] = len([e for e in d.emcys if e.code])
    test.attach("bus_counters", json.dumps(counters), "application/json")
    test.attach("emcys", json.dumps([{"t": e.t, "code": e.code, "register": e.register, "text": e.text}
                                     for e in d.emcys]), "application/json")


OWN = {"bus-health": (measures_bus_health, run_bus_health)}


def step_functions(step, plan):
    """(measurements, run) of one expanded step on an EtherCAT drive."""
    from motorjig.station import phases

    if step.kind == "prompt":
        return phases.measures_prompt(step, plan), phases.run_prompt
    if step.kind in OWN:
        measures, run = OWN[step.kind]
        return measures(step, plan), run
    kind = step.kind.replace("-", "_")
    return P.with_emcy_rule(getattr(P, "measures_" + kind)(step, plan), getattr(P, "run_" + kind))
