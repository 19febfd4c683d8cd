"""MotorJig Station: test plans that put a drive through its paces, on OpenHTF.

Public API, for ``jigctl test``, the Desk, and a user's own OpenHTF scripts:

* ``load_plan(path)``: read and check a plan file (``PlanError`` names file, line, key)
* ``run_plan(plan, port, ...)``: run it; the record, JUnit XML and HTML report are written
* ``MotorJigPlug``: the OpenHTF plug of the bus (configured with ``motorjig_*`` CONF keys)
* ``build_phase(step, plan, ctx)``: one plan step as an OpenHTF phase
* ``trapezoid_time``: the time a trapezoid move takes, as the move step expects it

Needs the ``station`` extra (openhtf): ``pip install 'motorjig[station]'``.
"""

from motorjig.station.plan import PlanError, load_plan
from motorjig.station.plug import MotorJigPlug
from motorjig.station.phases import build_phase, trapezoid_time
from motorjig.station.runner import RunContext, exit_code, run_plan, summary

__all__ = ["PlanError", "load_plan", "MotorJigPlug", "build_phase", "trapezoid_time", "RunContext",
           "exit_code", "run_plan", "summary"]
