"""The Plus-R drive kind: FASTECH Ezi-STEP / Ezi-SERVO Plus-R drives on the jig's driver bus.

Its entry in the table of kinds (``station.kinds``): the ``[drive]`` keys (slave, variant,
slave type), the step kinds of ``schema_plusr.STEP_KINDS`` run by ``station.phases``, the drive
``drive_plusr.PlusRDrive`` behind the jig's PC port, and its pre-flight (the drive answers in
the plan's variant, of the plan's type, no step above its axis_max_speed).
"""

import re

from motorjig.station import schema_plusr as S
from motorjig.station.kinds import DriveKind


class PlanDrive:
    """A Plus-R drive as a plan names it; ``variants``: the protocol variants it may speak, e.g.
    (6,) or (6, 8)."""

    protocol = "plusr"

    def __init__(self, slave, variants, slave_type, jig_id):
        self.slave, self.variants, self.slave_type, self.jig_id = slave, variants, slave_type, jig_id

    def as_dict(self):
        return {"protocol": self.protocol, "slave": self.slave, "variant": list(self.variants),
                "slave_type": self.slave_type, "jig_id": self.jig_id}

    def describe(self):
        """The drive in a few words: 'slave 2, Ver6/Ver8, type 20'."""
        return "slave %d, %s, type %d" % (self.slave, "/".join("Ver%d" % v for v in self.variants), self.slave_type)


class PlusRKind(DriveKind):
    name = "plusr"
    title = "Plus-R"
    drive_keys = S.DRIVE_KEYS
    step_kinds = S.STEP_KINDS
    emergency_words = "EmergencyStop, servo off"
    limit_inputs = "0 limit +, 1 limit -"
    address_key = "slave"

    # --- the plan ---------------------------------------------------------------------------------
    def plan_drive(self, ck, v, plan_dir):
        drive = PlanDrive(v["slave"], v["variant"], v["slave_type"], v["jig_id"])
        if drive.slave in (drive.jig_id, 99):
            raise ck.error(("drive", "slave"), "slave %d is the jig or the broadcast id, not a drive" % drive.slave)
        return drive, b""

    def old_spelling(self, ck, protocol, table):
        """Plans from before named kinds: protocol = 6 | 8 | [6, 8] is a Plus-R drive of those variants."""
        from motorjig.station.plan import PlanError

        try:
            variants = ck.value(protocol, self.drive_keys[1], ("drive", "protocol"))
        except PlanError:
            return None
        if "variant" in table:
            raise ck.error(("drive", "variant"), "the variants are given twice: as protocol = %r and here" % (
                protocol,))
        table["protocol"], table["variant"] = self.name, list(variants)
        return table

    def check_step(self, ck, step_path, kind, keys, args, plan_dir, drive, wiring, paramsets):
        if kind == "parameters":
            import os

            from motorjig import paramset

            path = os.path.join(plan_dir, args["file"])
            ps = paramsets[path] = paramset.load(path)
            if ps.slave_type is not None and ps.slave_type != drive.slave_type:
                raise ck.error(step_path + ("file",), "%s is a parameter set of slave type %d, the plan's drive is "
                                                      "type %d" % (args["file"], ps.slave_type, drive.slave_type))

    def wiring_default(self, drive):
        return {"default_slave": drive.slave}

    def check_wired_drive(self, ck, wiring, drive):
        node = getattr(wiring, "node", None)
        if node is not None:
            raise ck.error(("wiring", "node"), "the fixture is wired to CAN node %d, the plan tests the Plus-R "
                                               "drive at slave %d" % (node, drive.slave))
        if wiring.slave != drive.slave:
            raise ck.error(("wiring", "slave"), "the fixture is wired to slave %s, the plan tests slave %d"
                           % (wiring.slave, drive.slave))

    def stored_text(self, d):
        return "slave %s, Ver%s, type %s (%s)" % (d["slave"], d["protocol"], d["slave_type"], d["name"] or "-")

    # --- the run ----------------------------------------------------------------------------------
    checks_on_port = True

    def check_on_port(self, ports, plan):
        """Read only: the drive's variant and slave type against the plan's (the run's preflight check)."""
        from motorjig.master import Master
        from motorjig.station.runner import PreflightError, check_drive

        with Master(ports["port"], baud=ports["baud"], timeout=ports["timeout_ms"] / 1000.0) as m:
            try:
                check_drive(m, plan.drive, plan.steps)
            except PreflightError as exc:
                return str(exc).replace(": nothing was moved", "")
        return None

    sampled_step_kinds = ("move", "home", "limit-sensor", "stop-response")

    def slot_sample_rate(self, master, jig_id, n):
        """The jig's sampler polls the moving slots' drives in turn: one transaction a period each."""
        from jig.params import P_DOWN_BAUD
        from motorjig.station.sampling import trace_period_us

        return 1e6 / (trace_period_us(master.get_parameter(jig_id, P_DOWN_BAUD)) * n)

    def describe_run(self, plan, ports):
        return "drive slave %d, %s" % (plan.drive.slave, ports["port"])

    def conf(self, plan, ports):
        return {"motorjig_slave": plan.drive.slave, "motorjig_lss": False}

    def open_drive(self, plug):
        from motorjig.station.drive_plusr import PlusRDrive

        return PlusRDrive(plug.master, plug.conf("motorjig_slave"), plug.conf("motorjig_jig_id"))

    def step_functions(self, step, plan):
        from motorjig.station import phases

        kind = step.kind.replace("-", "_")
        return getattr(phases, "measures_" + kind)(step, plan), getattr(phases, "run_" + kind)

    def preflight(self, test, bus, plan, serial, ctx):
        from motorjig.station import runner

        variant, info = runner.check_drive(bus.master, plan.drive, plan.steps)
        s = bus.slave
        test.test_record.metadata["drive"] = {"slave": s, "protocol": variant, "slave_type": info.type,
                                              "name": info.version}
        if not serial:
            test.dut_id = "slave%d-%s" % (s, re.sub(r"[^A-Za-z0-9.]+", "-", info.version).strip("-"))
        runner.choose_sampling(test, bus, plan)

    def after_abort(self, plan, ports):
        from motorjig.station import runner

        if ports.get("master") is not None:  # a slot's run: through the slots' connection, which stays open
            from motorjig.station.plug import make_safe

            make_safe(ports["master"], plan.drive.slave, emergency=True)
            return
        runner.emergency_stop(ports["port"], ports["baud"], plan.drive.slave, ports["timeout_ms"])


KIND = PlusRKind()
