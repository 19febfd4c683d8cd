"""The CiA 402 drive kind: a CANopen CiA 402 drive on the jig's CAN port (its SLCAN port).

Its entry in the table of kinds (``station.kinds``): the ``[drive]`` keys (node id, bitrate,
EDS), the step kinds of ``schema_cia402.STEP_KINDS`` run by ``station.phases_cia402`` (each with
the EMCY rule around it: an EMCY during a step fails it), the drive
``drive_cia402.Cia402Drive`` through python-canopen, every object a step writes and every
parameter-set entry checked against the EDS when the plan loads, and its pre-flight (device
profile 402, the identity 0x1018 in the record).
"""

import os

from motorjig.station import schema_cia402 as S
from motorjig.station.kinds import DriveKind


_ODS = {}  # EDS path -> its ObjectDictionary (a run's phases share one plug; a test runs many runs)


def object_dictionary(path):
    """The canopen ObjectDictionary of an EDS (default: the one the project ships), read once."""
    import canopen

    from motorjig.can import EDS_PATH

    path = path or EDS_PATH
    if path not in _ODS:
        _ODS[path] = canopen.import_od(path)
    return _ODS[path]


def check_402_step(ck, step_path, kind, keys, args, plan_dir, drive, paramsets):
    """A CiA 402 step's checks against the drive's object dictionary (on CAN or on EtherCAT): the objects
    it writes or compares, and its parameter set."""
    from motorjig.station.plan import check_objects

    check_objects(ck, step_path, keys, args, drive)
    if kind == "parameters":
        from motorjig.can import paramset402

        path = os.path.join(plan_dir, args["file"])
        paramsets[path] = paramset402.load(path, drive.od, os.path.basename(drive.eds),
                                           writable=args["mode"] == "apply")


class PlanDrive:
    """A CiA 402 drive as a plan names it: ``node_id`` on the CAN bus at ``bitrate``; ``eds``: its
    EDS (absolute path), ``od``: the canopen ObjectDictionary read from it."""

    protocol = "cia402"

    def __init__(self, node_id, bitrate, eds, od, jig_id):
        self.node_id, self.bitrate, self.eds, self.od, self.jig_id = node_id, bitrate, eds, od, jig_id

    def as_dict(self):
        return {"protocol": self.protocol, "node_id": self.node_id, "bitrate": self.bitrate,
                "eds": os.path.basename(self.eds), "jig_id": self.jig_id}

    def describe(self):
        """The drive in a few words: 'CAN node 5, 500000 bit/s, motorjig-cia402.eds'."""
        return "CAN node %d, %d bit/s, %s" % (self.node_id, self.bitrate, os.path.basename(self.eds))


class Cia402Kind(DriveKind):
    name = "cia402"
    title = "CiA 402"
    drive_keys = S.DRIVE_KEYS
    step_kinds = S.STEP_KINDS
    emergency_words = "quick stop, disable voltage"
    limit_inputs = "0x60FD bit 0 negative, 1 positive limit"
    disable_at_end = True  # a CiA 402 run always ends with the operation disabled

    def reference(self, kinds_text):
        from motorjig.station.schema import PROMPT

        return ["", "### Step kinds of CiA 402 drives (`protocol = \"cia402\"`)", "",
                "Positions in counts, speeds in counts/s, accelerations in counts/s², as the drive's objects are. "
                "An EMCY with an error code during any step fails that step: every step but `bus-health` (which "
                "counts the run's) also has the measurement `emcy`, `\"none\"` or the codes received, named."] + \
            kinds_text([k for k in self.step_kinds if k is not PROMPT], " (cia402)") + \
            ["", "`prompt` as for Plus-R drives."] + S.paramset_reference()

    # --- the plan ---------------------------------------------------------------------------------
    def plan_drive(self, ck, v, plan_dir):
        from motorjig.can import EDS_PATH
        from motorjig.can import objects as O
        from motorjig.commands import UsageError

        eds = os.path.normpath(os.path.join(plan_dir, v["eds"])) if v["eds"] is not None else EDS_PATH
        try:
            od = O.load_eds(eds)
            with open(eds, "rb") as f:
                eds_raw = f.read()
        except (UsageError, OSError) as exc:
            raise ck.error(("drive", "eds"), str(exc).rstrip(".")) from None
        return PlanDrive(v["node_id"], v["bitrate"], eds, od, v["jig_id"]), eds_raw

    def check_step(self, ck, step_path, kind, keys, args, plan_dir, drive, wiring, paramsets):
        check_402_step(ck, step_path, kind, keys, args, plan_dir, drive, paramsets)

    def wiring_default(self, drive):
        return {"default_node": drive.node_id}

    def check_wired_drive(self, ck, wiring, drive):
        node = getattr(wiring, "node", None)
        if node != drive.node_id:
            where, what = (("wiring", "slave"), "Plus-R slave %s" % wiring.slave) if node is None else (
                ("wiring", "node"), "CAN node %s" % node)
            raise ck.error(where, "the fixture is wired to %s, the plan tests CAN node %d" % (what, drive.node_id))

    # --- the records --------------------------------------------------------------------------------
    CODE = 402  # drive_protocol in the results database (its drive_slave: the node id)

    def record_code(self, drive):
        return self.CODE

    def stored_text(self, d):
        return "CiA 402, CAN node %s, device type 0x%08X (%s)" % (d["slave"], d["slave_type"] or 0, d["name"] or "-")

    def identity_text(self, drive):
        """'vendor 0x4D4A4947 product 0x00000402 rev 0x00010000 serial 0x53490005'."""
        if drive.get("vendor_id") is None:
            return None
        values = []
        for k in ("vendor_id", "product_code", "revision", "serial"):
            try:
                values.append(int(drive.get(k)))
            except (TypeError, ValueError):
                values.append(0)
        return "vendor 0x%08X product 0x%08X rev 0x%08X serial 0x%08X" % tuple(values)

    # --- the run ----------------------------------------------------------------------------------
    ports = (("can_port", "--can-port", "the jig's SLCAN port"),)
    address_key = "node_id"

    def before_run(self, ports):
        import logging

        from motorjig.can.port import probe
        from motorjig.errors import PortError

        # python-canopen logs each SDO transfer it gives up as an error; the step's error says it
        logging.getLogger("canopen.sdo.client").setLevel(logging.CRITICAL)
        try:
            probe(ports["can_port"])
        except PortError as exc:
            return str(exc)
        return None

    def describe_run(self, plan, ports):
        return "drive node %d at %d bit/s on %s, jig on %s" % (plan.drive.node_id, plan.drive.bitrate,
                                                                ports["can_port"], ports["port"])

    def conf(self, plan, ports):
        return {"motorjig_node_id": plan.drive.node_id, "motorjig_bitrate": plan.drive.bitrate,
                "motorjig_eds": getattr(plan.drive, "eds", None), "motorjig_can_port": ports.get("can_port"),
                "motorjig_lss": bool(plan.steps) and plan.steps[0].kind == "lss"}

    def open_drive(self, plug):
        from motorjig.errors import JigError
        from motorjig.station.drive_cia402 import Cia402Drive, sync_period
        conf = plug.conf
        if not conf("motorjig_can_port"):
            raise JigError("no CAN port: set motorjig_can_port (jigctl test --can-port ...)")
        d = Cia402Drive(conf("motorjig_can_port"), conf("motorjig_node_id"), conf("motorjig_bitrate"),
                        object_dictionary(conf("motorjig_eds")), plug.master, conf("motorjig_jig_id"),
                        links=conf("motorjig_links"),
                        period=sync_period(conf("motorjig_bitrate"), conf("motorjig_port_share") or 1))
        try:
            d.open(require_node=not conf("motorjig_lss"))  # an lss step first: the node has no id yet
        except BaseException:
            d.close()
            raise
        return d

    def safety_net_kw(self, plug):
        return {"can_drive": plug.drive}  # the jig's CAN safety stop too (parameter 18)

    def step_functions(self, step, plan):
        from motorjig.station import phases
        from motorjig.station import phases_cia402 as P

        kind = step.kind.replace("-", "_")
        if kind == "prompt":  # the operator's step is every kind's
            return phases.measures_prompt(step, plan), phases.run_prompt
        inner = getattr(P, "run_" + kind)
        if step.kind in P.OWN_EMCY_KINDS:
            return getattr(P, "measures_" + kind)(step, plan), inner
        return P.with_emcy_rule(getattr(P, "measures_" + kind)(step, plan), inner)

    def preflight(self, test, bus, plan, serial, ctx):
        """The plug has opened the drive (node answers, trace TPDOs mapped); its device profile must
        be 402. The records name it, its EDS and its identity."""
        from motorjig.station import runner

        d = bus.drive
        if not d.ready:  # the plan's lss step gives the drive its id first: identified there
            test.test_record.metadata["drive"] = dict(protocol=self.name, node_id=d.node_id, bitrate=d.bitrate,
                                                      eds=getattr(plan.drive, "eds", None))
            return
        device_type = d.read(0x1000)
        if device_type & 0xFFFF != 402:
            raise runner.PreflightError("node %d has device profile %d (0x1000 = 0x%08X), not CiA 402: nothing was "
                                        "moved" % (d.node_id, device_type & 0xFFFF, device_type))
        ident = {"vendor_id": d.read(0x1018, 1), "product_code": d.read(0x1018, 2), "revision": d.read(0x1018, 3),
                 "serial": d.read(0x1018, 4)}
        test.test_record.metadata["drive"] = dict(
            protocol=self.name, node_id=d.node_id, bitrate=d.bitrate, eds=getattr(plan.drive, "eds", None),
            device_type=device_type, **ident)
        if not serial:
            test.dut_id = "node%d-%08X-%08X" % (d.node_id, ident["product_code"], ident["serial"])
        test.test_record.metadata["sampling"] = {"by": "drive", "period_us": int(round(d.period * 1e6)),
                                                 "dated_by": "jig"}

    def after_abort(self, plan, ports):
        """Quick stop and disable voltage once more, on a CAN connection of its own (not for a slot's
        run: the plug's tearDown did it through the slots' network, and a connection of its own would
        take the jig's one SLCAN session from the other slots)."""
        from motorjig.station.drive_cia402 import make_safe_on
        if ports.get("can_port") and ports.get("master") is None:
            make_safe_on(ports["can_port"], plan.drive.node_id, plan.drive.bitrate,
                         getattr(plan.drive, "od", None) or object_dictionary(getattr(plan.drive, "eds", None)))


KIND = Cia402Kind()
