"""The step kinds on a CiA 402 drive: measurements and what each step does through ``Cia402Drive``.

``phases.build_phase`` takes ``measures_<kind>`` / ``run_<kind>`` from here when the plan's
``[drive] protocol`` is "cia402"; the phase around them (progress, verdicts, aborts) is
the same as for a Plus-R drive. Every step also measures ``emcy``: an EMCY with a non-zero
error code received during the step fails it, with the code and its CiA 301 meaning. The
CiA 402 mapping of every kind is in docs/station.md (*Step kinds on CiA 402*).

Moving steps are sampled by the drive's TPDOs on the station's SYNC, dated by the jig
(``sampling_cia402.Cia402Trace``); their trace goes into the record as a Plus-R move's does
(command = the demand, actual + following error actual).
"""

import json
import re
import time

from openhtf.util import units

from motorjig.can import cia301, power402
from motorjig.errors import JigError
from motorjig.station.drive import SdoRefused
from motorjig.station.drive_cia402 import SW_ACK, SW_ERROR, SW_INTERNAL_LIMIT, SW_TARGET_REACHED
from motorjig.station.sampling import UntrustedMeasurement

COUNTS = units.UnitDescriptor("count", "count", "count")
S = units.SECOND
MS = units.MILLISECOND
I32_MAX = 0x7FFFFFFF
SAVE = 0x65766173  # "save" (0x1010 store parameters), little-endian ASCII


def _h():
    from motorjig.station import phases  # the measurement helpers (phases imports this module)

    return phases


# --- identify ------------------------------------------------------------------------------
def measures_identify(step, plan):
    h, a = _h(), step.args
    want, mask = a.get("device_type", 0x00020192), a.get("device_type_mask", 0xFFFF)
    out = [h._equals("device_type", "0x%08X" % (want & mask), doc="0x1000 device type, the bits of 0x%08X" % mask),
           h._m("device_name", doc="0x1008 manufacturer device name"),
           h._m("hardware_version", doc="0x1009"), h._m("software_version", doc="0x100A")]
    if a.get("name_pattern") is not None:
        out.append(h._equals("name_ok", True, doc="0x1008 matches %r" % a["name_pattern"]))
    for key, doc in (("vendor_id", "0x1018:1 vendor id"), ("product_code", "0x1018:2 product code"),
                     ("revision", "0x1018:3 revision number")):
        out.append(h._equals(key, a[key], doc=doc) if a.get(key) is not None else h._m(key, doc=doc))
    out.append(h._m("serial", doc="0x1018:4 serial number (hex)"))
    if a.get("serial_pattern") is not None:
        out.append(h._equals("serial_ok", True, doc="the serial (8 hex digits) matches %r" % a["serial_pattern"]))
    return out


def run_identify(test, bus, step, ctx):
    a, ident = step.args, bus.drive.identify()
    m = test.measurements
    m["device_type"] = "0x%08X" % (ident["device_type"] & a.get("device_type_mask", 0xFFFF))
    for key in ("device_name", "hardware_version", "software_version", "vendor_id", "product_code", "revision"):
        m[key] = ident[key]
    serial = "%08X" % ident["serial"]
    m["serial"] = serial
    if a.get("name_pattern") is not None:
        m["name_ok"] = re.search(a["name_pattern"], ident["device_name"] or "") is not None
    if a.get("serial_pattern") is not None:
        m["serial_ok"] = re.search(a["serial_pattern"], serial) is not None


# --- parameters ------------------------------------------------------------------------------
def _entries(step):
    ps = step.paramset
    return list(ps.entries) if ps is not None else []


def measures_parameters(step, plan):
    h = _h()
    return [h._equals(e.name, e.value, doc=e.label) for e in _entries(step)]


def run_parameters(test, bus, step, ctx):
    d = bus.drive
    entries = _entries(step)
    if step.args.get("mode") == "apply":
        for e in entries:
            d.write(e.index, e.sub, e.value)
        d.write(0x1010, 1, SAVE)
    for e in entries:
        try:
            test.measurements[e.name] = d.read(e.index, e.sub)
        except SdoRefused as exc:  # the drive refuses an object the golden set has: that object
            # fails (not a broken run), unmeasured, with the abort as the reason the console and the
            # HTML show
            _h().not_measured(test, e.name, "refused by the drive: SDO abort %s" % cia301.abort_text(exc.code))
            test.logger.warning("%s: %s", e.name, exc)


# --- servo, alarm-reset ----------------------------------------------------------------------
def measures_servo(step, plan):
    h = _h()
    want = power402.OPERATION_ENABLED if step.args.get("on", True) else power402.SWITCH_ON_DISABLED
    return [h._equals("state", want, doc="the power state reached (statusword 0x6041)"),
            h._m("transition_time_max", S, "the slowest transition: the drive's reply to the controlword to the "
                                   "statusword showing the state, on the jig's clock"),
            h._equals("fault", 0, doc="0x603F error code in FAULT (0: no fault)")]


def run_servo(test, bus, step, ctx):
    d = bus.drive
    got = d.enable(step.args.get("on", True))
    test.measurements["state"] = got["state"]
    times = [t for _, _, t in got["transitions"] if t is not None]
    test.measurements["transition_time_max"] = max(times) if times else 0.0
    test.attach("transitions", json.dumps([{"controlword": cw, "state": st, "seconds": t}
                                           for cw, st, t in got["transitions"]]), "application/json")
    test.measurements["fault"] = d.fault()


def measures_alarm_reset(step, plan):
    h = _h()
    return [h._equals("fault", 0, doc="0x603F error code after the fault reset (0: no fault)"),
            h._m("state", doc="the power state after the reset")]


def run_alarm_reset(test, bus, step, ctx):
    d = bus.drive
    try:
        d.fault_reset()
    except JigError:
        pass  # the drive stays in FAULT: the measurement says so
    test.measurements["fault"] = d.fault()
    test.measurements["state"] = d.state()


# --- move --------------------------------------------------------------------------------------
def _ramp_ms(speed, acc):
    return 1000.0 * speed / acc


def measures_move(step, plan):
    h, a = _h(), step.args
    if a.get("duration_s") is not None:
        duration = [h._range("duration", a["duration_s"][0], a["duration_s"][1], S,
                             "from the drive's reply to the new set-point to standstill, on the jig's clock")]
    else:
        tol = a.get("duration_tolerance", 0.15)
        duration = [h._m("duration", S, "from the drive's reply to the new set-point to standstill"),
                    h._range("duration_ratio", round(1 - tol, 4), round(1 + tol, 4), None,
                             "duration / the time the trapezoid profile takes")]
    return duration + [
        h._m("expected_duration", S, "time the trapezoid profile takes (0x6081, 0x6083, 0x6084)"),
        h._at_most("position_error", a.get("position_error_max", 0), COUNTS, "|target - 0x6064| after the move"),
        h._at_most("following_error", a.get("following_error_max", 0), COUNTS, "peak |0x60F4| sampled"),
        h._equals("target_reached", True, doc="stopped at the target, statusword bit 10 (target reached), no fault"),
        h._equals("fault", 0, doc="0x603F error code after the move (0: no fault)"),
        h._m("samples", doc="TPDO samples during the move"),
        h._m("sample_rate", units.HERTZ, "TPDO samples per second")]


def _profile(d, a, speed):
    acc = a.get("accel") or d.read(0x6083)
    dec = a.get("decel") or d.read(0x6084)
    return acc, dec


def run_move(test, bus, step, ctx):
    d, a = bus.drive, step.args
    start = d.position()
    target = a["position"] if a.get("mode", "inc") == "abs" else start + a["distance"]
    acc, dec = _profile(d, a, a["speed"])
    expected = _h().trapezoid_time(target - start, a["speed"], _ramp_ms(a["speed"], acc), _ramp_ms(a["speed"], dec))
    trace = d.new_trace(ctx, step)
    trace.begin(d)
    try:
        trace.sent("move", d.move(target, a["speed"], a.get("accel"), a.get("decel")))
        done = trace.until_stopped(d, None, a.get("timeout_s", 30.0))
        if not done:
            d.halt()
    finally:
        trace.end(d)
    t_move, t_end = trace.time_of("move"), trace.t_stop
    n, rate, _ = trace.stats(t_move, t_end)
    m = test.measurements
    m["duration"] = round(t_end - t_move, 4)
    if a.get("duration_s") is None:
        m["duration_ratio"] = round((t_end - t_move) / expected, 4) if expected else 0.0
    m["expected_duration"] = round(expected, 4)
    actual = d.position()
    m["position_error"] = abs(target - actual)
    m["following_error"] = trace.peak_error
    fault = d.fault()
    reached = d.wait_target_reached(0.5) if done and not fault else False
    m["target_reached"] = bool(done and reached and actual == target and not fault)
    m["fault"] = fault
    m["samples"] = n
    m["sample_rate"] = round(rate, 1)
    test.attach("trace", _h()._attachment(trace, target), "application/json")
    if done:
        trace.check(t_move, t_end, ctx.plan.sample_rate_min)


# --- home --------------------------------------------------------------------------------------
def measures_home(step, plan):
    h, a = _h(), step.args
    lo, hi = a.get("duration_s") or (0.0, 30.0)
    return [h._range("duration", lo, hi, S, "from the homing start to homing attained, on the jig's clock"),
            h._equals("homing_attained", True, doc="statusword bits 12 (homing attained) and 10, no homing error (13)"),
            h._equals("fault", 0, doc="0x603F error code after the homing (0: no fault)")]


def run_home(test, bus, step, ctx):
    d, a = bus.drive, step.args
    trace = d.new_trace(ctx, step)
    trace.begin(d)
    homed, t_end = False, None
    try:
        trace.sent("home", d.home(a.get("method", 19), a.get("speed_switch"), a.get("speed_zero"), a.get("accel")))
        deadline = time.monotonic() + a.get("timeout_s", 60.0)
        while t_end is None and time.monotonic() < deadline:
            for t, smp in trace.more(d):
                sw = smp.axis.statusword
                if t >= trace.time_of("home") and (sw & SW_ERROR or sw & (SW_ACK | SW_TARGET_REACHED)
                                                   == SW_ACK | SW_TARGET_REACHED or sw & 0x08):
                    homed, t_end = not sw & (SW_ERROR | 0x08), t
                    break
        if t_end is None:
            d.halt()
    finally:
        trace.end(d)
        d.controlword(0x0F)  # bit 4 back down (and no halt): the next homing or move has its edge
    t_end = t_end if t_end is not None else trace.rows[-1][0]
    test.measurements["duration"] = round(t_end - trace.time_of("home"), 4)
    test.measurements["homing_attained"] = homed
    test.measurements["fault"] = d.fault()
    test.attach("trace", _h()._attachment(trace), "application/json")


# --- stop-response ---------------------------------------------------------------------------------
def measures_stop_response(step, plan):
    h, a = _h(), step.args
    lo, hi = a.get("stop_time_s", (0.0, 0.5))
    return [h._equals("stopped", True, doc="the axis came to standstill"),
            h._range("stop_time", lo, hi, S, "from the drive's reply to the stop to standstill, on the jig's clock"),
            h._at_most("overshoot", a.get("overshoot_max", 100000), COUNTS, "travel after the stop"),
            h._m("state", doc="the power state after the stop")]


def run_stop_response(test, bus, step, ctx):
    d, a = bus.drive, step.args
    speed = a.get("speed", 20000)
    far = max(-I32_MAX, min(I32_MAX, d.position() + speed * 60))  # never reached: the stop ends it
    trace = d.new_trace(ctx, step)
    trace.begin(d)
    stopped = False
    quick = a.get("stop", "quick-stop") == "quick-stop"
    try:
        trace.sent("move", d.move(far, speed))
        trace.sample_until(d, None, a.get("after_ms", 200) / 1000.0)
        trace.sent("stop", d.quick_stop() if quick else d.halt())
        stopped = trace.until_stopped(d, None, 10.0)
    finally:
        if not stopped:
            d.quick_stop()
        trace.end(d)
    t_stop, t_end = trace.time_of("stop"), trace.t_stop
    m = test.measurements
    m["stopped"] = stopped
    m["stop_time"] = round(t_end - t_stop, 4)
    m["overshoot"] = int(round(abs(trace.rows[-1][2] - trace.position_at(t_stop, column=2))))
    m["state"] = d.state()
    test.attach("trace", _h()._attachment(trace), "application/json")
    if a.get("recover", True):
        if quick:
            d.enable(True)  # 0x605A 0-4: the drive is in SWITCH ON DISABLED now
        else:
            d.controlword(power402.COMMANDS[power402.DISABLE_OPERATION])  # drop the halted move ...
            d.enable(True)  # ... and enable again: the demand is the actual position
    if stopped:
        trace.check(t_stop - 0.02, t_end, ctx.plan.sample_rate_min, "the stop")


# --- bus-health ---------------------------------------------------------------------------------------
LOST = ("can_rx_lost", "can_rx_overruns", "can_tx_failed")


def measures_bus_health(step, plan):
    h, a = _h(), step.args
    jitter_max = a.get("heartbeat_jitter_max_ms")
    doc = "largest |heartbeat interval - 0x1017| over the run (the silence since the last one counts), on the jig's clock"
    return [h._at_most("error_frames", a.get("error_frames_max", 0),
                       doc="the jig's CAN port over the run: error-warning and error-passive entries"),
            h._m("tec_max", doc="the jig's transmit error counter (now: the jig keeps no maximum)"),
            h._m("rec_max", doc="the jig's receive error counter (now: the jig keeps no maximum)"),
            h._equals("bus_off", 0, doc="bus-off entries of the jig's CAN port over the run"),
            h._equals("lost_frames", 0, doc="frames lost by the jig: " + " + ".join(LOST)),
            h._at_most("heartbeat_jitter", jitter_max, MS, doc) if jitter_max is not None
            else h._m("heartbeat_jitter", MS, doc),
            h._at_most("emcy", a.get("emcy_max", 0), doc="EMCYs with an error code over the run")]


def run_bus_health(test, bus, step, ctx):
    from motorjig.station.drive_cia402 import HEARTBEAT_MS

    d, m = bus.drive, test.measurements
    counters = d.bus_health()
    m["error_frames"] = counters.get("can_warning_entries", 0) + counters.get("can_passive_entries", 0)
    m["tec_max"], m["rec_max"] = counters.get("can_tec", 0), counters.get("can_rec", 0)
    m["bus_off"] = counters.get("can_bus_off_entries", 0)
    m["lost_frames"] = sum(counters.get(k, 0) for k in LOST)
    d.read(0x1000)  # a fresh reply: the jig's time now, for a heartbeat that did not come
    beats, now = list(d.heartbeats), d.sdo_stamp
    gaps = [b - a for a, b in zip(beats, beats[1:])]
    if now is not None and (beats or d.t_opened is not None):
        gaps.append(max(HEARTBEAT_MS / 1000.0, now - (beats[-1] if beats else d.t_opened)))
    jitter = round(max(abs(g * 1000 - HEARTBEAT_MS) for g in gaps), 1) if gaps else 0.0
    limit = step.args.get("heartbeat_jitter_max_ms")
    if limit is not None and jitter > limit:
        # Judge the drive only on what the jig dated and saw: a PC's arrival time, or a heartbeat
        # the jig lost on the way to this PC, is not the drive's irregularity.
        unstamped = d.unstamped()
        lost = counters.get("can_rx_lost", 0) + counters.get("can_rx_overruns", 0)
        if unstamped:
            raise UntrustedMeasurement(
                "heartbeat_jitter %.0f ms cannot be judged: %d frames came without the jig's timestamp (their "
                "times are this PC's, not the bus's)" % (jitter, unstamped))
        if lost:
            raise UntrustedMeasurement(
                "heartbeat_jitter %.0f ms cannot be judged: the jig lost %d received frames on the way to this "
                "PC (can_rx_lost + can_rx_overruns), a heartbeat may be among them" % (jitter, lost))
    m["heartbeat_jitter"] = jitter
    m["emcy"] = len([e for e in d.emcys if e.code])
    test.attach("bus_counters", json.dumps(counters), "application/json")
    test.attach("heartbeats", json.dumps(beats), "application/json")
    test.attach("emcys", json.dumps([{"t": e.t, "code": e.code, "register": e.register, "text": e.text}
                                     for e in d.emcys]), "application/json")


# --- io, limit-sensor: through the wiring ---------------------------------------------------------
def measures_io(step, plan):
    return _h().measures_io(step, plan)  # the Plus-R step's measurements: the same wires


def run_io(test, bus, step, ctx):
    h, m, d, jig = _h(), bus.master, bus.drive, bus.jig_id
    wiring = ctx.plan.wiring
    relays, senses = h._io_entries(step, wiring)
    settle = step.args["settle_ms"] / 1000.0
    relay_mask = sum(1 << e[0] for e in wiring.relays)
    output_mask = sum(1 << e[1] for e in wiring.senses)
    outputs = d.read(0x60FE, 1) & ~output_mask & 0xFFFFFFFF
    try:
        m.set_io_output(jig, clear_mask=relay_mask)
        for relay, _, _ in relays:
            for on in (True, False):
                m.set_io_output(jig, **{"set_mask" if on else "clear_mask": 1 << relay})
                time.sleep(settle)
                test.measurements["relay_%d_%s" % (relay, "on" if on else "off")] = (
                    d.inputs() & wiring.drive_input_mask)
        if senses:
            d.write(0x60FE, 2, d.read(0x60FE, 2) | output_mask)  # the wired outputs enabled (0x60FE:2 mask)
        for jig_in, bit, _ in senses:
            for on in (True, False):
                d.write(0x60FE, 1, outputs | (1 << bit if on else 0))
                time.sleep(settle)
                test.measurements["sense_%d_%s" % (jig_in, "on" if on else "off")] = (
                    m.get_io_input(jig) & wiring.jig_input_mask)
    finally:  # a relay left on (a limit input!) would stop the next step or the next drive
        m.set_io_output(jig, clear_mask=relay_mask)
        d.write(0x60FE, 1, outputs)


LIMIT_BITS = {0: -1, 1: +1}  # 0x60FD bit 0: negative limit switch, bit 1: positive


def measures_limit_sensor(step, plan):
    h, a = _h(), step.args
    lo, hi = a.get("stop_time_s", (0.0, 0.5))
    return [h._equals("stopped", True, doc="the axis stopped after the limit input"),
            h._equals("limit_flag", True, doc="0x60FD shows the limit switch and the statusword internal limit "
                                              "active (bit 11)"),
            h._range("stop_time", lo, hi, S, "from the drive showing the limit (statusword bit 11, dated by the "
                                             "jig) to standstill")]


def run_limit_sensor(test, bus, step, ctx):
    m, d, jig, a = bus.master, bus.drive, bus.jig_id, step.args
    relay, drive_input, _ = ctx.plan.wiring.find("relay", a["relay"])  # the loader checked it is wired
    direction = LIMIT_BITS.get(drive_input, +1)
    far = max(-I32_MAX, min(I32_MAX, d.position() + direction * a["speed"] * 60))
    trace = d.new_trace(ctx, step)
    trace.begin(d)
    stopped = flag = False
    n0 = len(d.sw_log)
    try:
        trace.sent("move", d.move(far, a["speed"]))
        trace.sample_until(d, None, a.get("after_ms", 100) / 1000.0)
        m.set_io_output(jig, set_mask=1 << relay)
        stopped = trace.until_stopped(d, None, a.get("timeout_s", 10.0))
        flag = bool(d.inputs() & (1 << drive_input)) and bool(d.read_statusword() & SW_INTERNAL_LIMIT)
    finally:
        m.set_io_output(jig, clear_mask=1 << relay)
        if not stopped:
            d.quick_stop()
        trace.end(d)
        d.controlword(power402.COMMANDS[power402.DISABLE_OPERATION])  # drop the move the limit held ...
        d.enable(True)  # ... and enable again: the demand is the actual position
    # the relay's instant as the drive saw it: its internal-limit flag as TPDO1 (sent on every change of
    # the statusword) brought it; else halfway from the sample before the flag. A sample pairs the last
    # TPDO2 (statusword) with a TPDO3 (velocity), so at a long period (slots sharing the bus) the first
    # standstill sample may still carry the statusword from before the limit.
    t_move = trace.time_of("move")
    t_flag = next((t for t, sw in d.sw_log[n0:] if sw & SW_INTERNAL_LIMIT and t >= t_move), None)
    if t_flag is not None:
        trace.marks["relay"] = t_flag
    else:
        trace.date_by_flag("relay", "internal_limit", t_move)
    test.measurements["stopped"] = stopped
    test.measurements["limit_flag"] = flag
    test.measurements["stop_time"] = round(trace.t_stop - trace.time_of("relay"), 4)
    test.attach("trace", _h()._attachment(trace), "application/json")
    if stopped:
        trace.check(trace.time_of("relay"), trace.t_stop, ctx.plan.sample_rate_min, "the stop at the limit")


def measures_lss(step, plan):
    h = _h()
    return [h._equals("found", True, doc="a drive answered at the factory node id %d (255: LSS fast scan of the "
                                         "unconfigured)" % step.args.get("factory_node_id", 255)),
            h._m("vendor_id", doc="its LSS address: 0x1018:1"), h._m("product_code", doc="0x1018:2"),
            h._m("serial", doc="0x1018:4 (hex)"),
            h._equals("node_id", plan.drive.node_id, doc="the node id it answers at afterwards (SDO 0x1000)")]


def run_lss(test, bus, step, ctx):
    d, m = bus.drive, test.measurements
    ids = d.lss_configure(step.args.get("factory_node_id", 255))
    m["found"] = ids is not None
    if ids is None:
        return
    m["vendor_id"], m["product_code"], m["serial"] = ids[0], ids[1], "%08X" % ids[3]
    d.connect_node(wait_s=5.0)  # boots with its new id; then the trace TPDOs, heartbeat, operational
    m["node_id"] = d.node_id
    drive = test.test_record.metadata.setdefault("drive", {})
    drive.update(vendor_id=ids[0], product_code=ids[1], revision=ids[2], serial=ids[3], device_type=d.read(0x1000))
    if test.test_record.dut_id in (None, "", "unknown"):
        test.dut_id = "node%d-%08X-%08X" % (d.node_id, ids[1], ids[3])


# --- the EMCY rule of every step --------------------------------------------------------------------------------
# bus-health judges the run's EMCYs itself (its measurement ``emcy``)
OWN_EMCY_KINDS = ("bus-health",)


def measures_emcy():
    return _h()._equals("emcy", "none", doc="EMCYs with an error code the drive sent during the step")


def emcy_since(drive, n0):
    """'none', or the EMCYs with an error code received since drive.emcys[n0], named."""
    got = [e.text for e in drive.emcys[n0:] if e.code]
    return "; ".join(got) if got else "none"


def with_emcy_rule(measures, inner):
    """(measurements, run) of a step with the EMCY rule around it: the step measures ``emcy``, and an
    EMCY that came while it failed is its verdict, not what it broke."""

    def run(test, bus, step, ctx):
        n0 = len(bus.drive.emcys)
        try:
            inner(test, bus, step, ctx)
        except Exception:
            emcy = emcy_since(bus.drive, n0)
            if emcy == "none":
                raise
            test.measurements["emcy"] = emcy
            return
        test.measurements["emcy"] = emcy_since(bus.drive, n0)

    return measures + [measures_emcy()], run
