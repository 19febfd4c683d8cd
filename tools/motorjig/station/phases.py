"""The station's steps as OpenHTF phases: one small function per step kind, with declared measurements.

``build_phase(step, plan, ctx)`` turns one expanded plan step into an OpenHTF phase:
the measurements are declared from the plan's limits (limits live in the plan, never
here), the phase gets the ``MotorJigPlug`` as ``bus``, and ``run_<kind>`` does the
bus work and sets the values. ``ctx`` is the run's ``RunContext`` (progress lines,
the operator's confirmation, the wiring).

The axis is sampled during a moving step by ``station.sampling``: by the jig itself
(GetAllStatus at a fixed period, every sample and the step's own commands dated by
the jig's clock) when its firmware has the sampler, else by the station (GetAllStatus
as fast as the bus allows, dated on this PC's clock at the middle of each round trip).
A step whose samples cannot judge the drive (a gap, a rate below the plan's floor, a
command the jig did not date) ends ERROR with the reason, never FAIL
(``sampling.UntrustedMeasurement``).
"""

import json
import re
import time

import openhtf as htf
from openhtf.util import threads, units

from jig import frame as F
from motorjig.errors import JigError
from motorjig.station.plug import MotorJigPlug
from motorjig.station.sampling import UntrustedMeasurement, new_trace

PULSE = units.UnitDescriptor("pulse", "pulse", "pulse")
S = units.SECOND
MS = units.MILLISECOND
US = units.MICROSECOND

DIR_PLUS = 1
DIR_MINUS = 0


class RunAborted(Exception):
    """The run was aborted (the Desk's Abort) before this step began."""


def trapezoid_time(distance, speed, acc_ms, dec_ms):
    """Seconds a move of ``distance`` pulses takes with the trapezoid profile: the axis
    reaches ``speed`` in acc_ms and stops from it in dec_ms (a triangle when the distance
    is too short to reach the speed).

    Written here on purpose, not taken from the simulated drive (``sim.driver.profile_time``):
    the limit must say what a drive should do, so a fault in the simulator's model shows as
    a failed move instead of testing the model against itself."""
    d, v = abs(distance), float(speed)
    ta, td = acc_ms / 1000.0, dec_ms / 1000.0
    if d >= v * (ta + td) / 2:
        return d / v + (ta + td) / 2
    # triangle: peak speed vp with vp * (ta' + td') / 2 = d, ta'/td' scaled by vp / v
    vp = (2 * d * v / (ta + td)) ** 0.5
    return (ta + td) * vp / v


# --- declaring measurements -----------------------------------------------------------
def _m(name, unit=None, doc=""):
    m = htf.Measurement(name).doc(doc)
    return m.with_units(unit) if unit is not None else m


def _range(name, lo, hi, unit=None, doc=""):
    return _m(name, unit, doc).in_range(minimum=lo, maximum=hi)


def _at_most(name, hi, unit=None, doc=""):
    return _m(name, unit, doc).in_range(maximum=hi)


def _equals(name, value, unit=None, doc=""):
    return _m(name, unit, doc).equals(value)


def _skip(test, name):
    """Leave a declared measurement out: outcome SKIPPED, no value, the phase not failed by it."""
    test.measurements.set_measurement_outcome_to_skipped(name)
    # OpenHTF keeps a cached copy of the measurement for the record, made when the phase
    # started, and does not update its outcome here: the record would say UNSET
    cached = getattr(test.measurements._measurements.get(name), "_cached", None)
    if cached:
        cached["outcome"] = "SKIPPED"


def _attachment(trace, target=None):
    att = {"columns": ["t", "command", "actual", "velocity"],
           "units": {"t": "s", "command": "pulse", "actual": "pulse", "velocity": "pps"},
           "rows": trace.rows, "target": target, "sampled_by": trace.source, "marks": trace.marks}
    if getattr(trace, "why", None):  # this PC sampled a step of a run the jig samples
        att["sampling_note"] = trace.why
    return json.dumps(att)


def _alarm_code(m, s):
    return m.get_alarm_type(s).code


# --- the steps --------------------------------------------------------------------------
def measures_identify(step, plan):
    a = step.args
    expected = a["slave_type"] if a["slave_type"] is not None else plan.drive.slave_type
    out = [_equals("slave_type", expected, doc="GetSlaveInfo slave type"),
           _m("slave_name", doc="GetSlaveInfo text"),
           _equals("name_ok", True, doc="the text matches %r" % a["name_pattern"])]
    if a["motor_pattern"] is not None:
        out += [_m("motor_name", doc="GetMotorInfo text"),
                _equals("motor_ok", True, doc="the motor text matches %r" % a["motor_pattern"])]
    return out


def run_identify(test, bus, step, ctx):
    d, a = bus.drive, step.args
    info = d.identify()
    test.measurements["slave_type"] = info["slave_type"]
    test.measurements["slave_name"] = info["slave_name"]
    test.measurements["name_ok"] = re.search(a["name_pattern"], info["slave_name"]) is not None
    if a["motor_pattern"] is not None:
        motor = d.motor()
        test.measurements["motor_name"] = motor
        test.measurements["motor_ok"] = re.search(a["motor_pattern"], motor) is not None


def _param_names(step):
    ps = step.paramset
    mem = step.args["memory"]
    kinds = ("ram", "rom") if mem == "both" else (mem,)
    return [(k, p, v) for k in kinds for p, v in ps.items()]


def measures_parameters(step, plan):
    return [_equals("%s_%s" % (k, p.name), v, doc="parameter %d (%s) in %s" % (p.number, p.meaning, k.upper()))
            for k, p, v in _param_names(step)]


def run_parameters(test, bus, step, ctx):
    m, s = bus.master, bus.slave
    rows = _param_names(step)
    if step.args["mode"] == "apply":
        for p, v in step.paramset.items():
            m.set_parameter(s, p.number, v)
        m.save_all_parameters(s)
    for k, p, _ in rows:
        read = m.get_rom_parameter if k == "rom" else m.get_parameter
        test.measurements["%s_%s" % (k, p.name)] = read(s, p.number)


def measures_servo(step, plan):
    return [_equals("servo_on", step.args["on"], doc="the axis status's servo-on flag"),
            _equals("alarm", 0, doc="GetAlarmType (0: none)")]


def run_servo(test, bus, step, ctx):
    d = bus.drive
    test.measurements["servo_on"] = d.enable(step.args["on"])["servo_on"]
    test.measurements["alarm"] = d.fault()


def measures_alarm_reset(step, plan):
    return [_equals("alarm", 0, doc="GetAlarmType after the reset (0: none)")]


def run_alarm_reset(test, bus, step, ctx):
    d = bus.drive
    d.is_servo = ctx.drive_is_servo
    d.fault_reset()
    test.measurements["alarm"] = d.fault()


def _move_plan(m, s, a):
    """(start, target, acc_ms, dec_ms) of a move step, read from the drive where the plan is silent."""
    start = m.get_command_pos(s)
    target = a["position"] if a["mode"] == "abs" else start + a["distance"]
    acc = a["accel_ms"] if a["accel_ms"] is not None else m.get_parameter(s, 3)
    dec = a["decel_ms"] if a["decel_ms"] is not None else m.get_parameter(s, 4)
    return start, target, acc, dec


def measures_move(step, plan):
    a = step.args
    if a["duration_s"] is not None:
        duration = [_range("duration", a["duration_s"][0], a["duration_s"][1], S,
                           "time from the move command to standstill")]
    else:
        tol = a["duration_tolerance"]
        duration = [_m("duration", S, "time from the move command to standstill"),
                    _range("duration_ratio", round(1 - tol, 4), round(1 + tol, 4), None,
                           "duration / the time the trapezoid profile takes")]
    return duration + [
        _m("expected_duration", S, "time the trapezoid profile takes (speed, accel/decel times)"),
        _at_most("position_error", a["position_error_max"], PULSE, "|target - actual| after the move"),
        _at_most("following_error", a["following_error_max"], PULSE,
                 "peak |command - actual| sampled during the move"),
        _equals("in_position", True, doc="stopped, no error flag, the command position at the target"),
        _equals("alarm", 0, doc="GetAlarmType after the move (0: none)"),
        _m("samples", doc="status samples taken during the move"),
        _m("sample_rate", units.HERTZ, "status samples per second")]


def _send_move(m, s, a, target, acc, dec, custom):
    """The step's move command: the Ex frame when the step sets its own accel/decel times (custom)."""
    if a["mode"] == "abs":
        if custom:
            m.move_abs_ex(s, target, a["speed"], accel_ms=acc, decel_ms=dec)
        else:
            m.move_abs(s, target, a["speed"])
    elif custom:
        m.move_inc_ex(s, a["distance"], a["speed"], accel_ms=acc, decel_ms=dec)
    else:
        m.move_inc(s, a["distance"], a["speed"])


# the frame type each kind of move goes out as (the jig dates the command by it)
_MOVE_FTYPES = {("abs", False): F.MOVE_ABS_POS, ("abs", True): F.MOVE_ABS_POS_EX,
                ("inc", False): F.MOVE_INC_POS, ("inc", True): F.MOVE_INC_POS_EX}


def run_move(test, bus, step, ctx):
    m, s, a = bus.master, bus.slave, step.args
    start, target, acc, dec = _move_plan(m, s, a)
    expected = trapezoid_time(target - start, a["speed"], acc, dec)
    trace = new_trace(bus, ctx, step)
    trace.begin(m, s)
    try:
        custom = a["accel_ms"] is not None or a["decel_ms"] is not None
        trace.mark("move", _MOVE_FTYPES[(a["mode"], custom)])
        _send_move(m, s, a, target, acc, dec, custom)
        trace.sent(m, s, "move")
        done = trace.until_stopped(m, s, a["timeout_s"])
        if not done:
            m.move_stop(s)
            m.wait_motion_done(s, timeout=5.0)
    finally:
        trace.end(m)
    last = trace.last
    t_move, t_end = trace.time_of("move"), trace.t_stop
    duration = t_end - t_move
    n, rate, _ = trace.stats(t_move, t_end)
    test.measurements["duration"] = round(duration, 4)
    if a["duration_s"] is None:
        if expected > 0:
            test.measurements["duration_ratio"] = round(duration / expected, 4)
        else:  # an abs move to where the axis already is: no profile to compare with, nothing to judge
            _skip(test, "duration_ratio")
    test.measurements["expected_duration"] = round(expected, 4)
    test.measurements["position_error"] = abs(target - last.actual_pos)
    test.measurements["following_error"] = trace.peak_error
    test.measurements["in_position"] = bool(done and last.command_pos == target and not last.axis.error_all)
    test.measurements["alarm"] = _alarm_code(m, s)
    test.measurements["samples"] = n
    test.measurements["sample_rate"] = round(rate, 1)
    test.attach("trace", _attachment(trace, target), "application/json")
    if done:  # a drive that never stopped is judged (duration, in_position) whatever the samples
        trace.check(t_move, t_end, ctx.plan.sample_rate_min)


def measures_home(step, plan):
    lo, hi = step.args["duration_s"]
    return [_range("duration", lo, hi, S, "time from MoveOrigin to standstill"),
            _equals("origin_ok", True, doc="the axis status's origin-return-OK flag"),
            _equals("alarm", 0, doc="GetAlarmType after the search (0: none)")]


def run_home(test, bus, step, ctx):
    m, s = bus.master, bus.slave
    trace = new_trace(bus, ctx, step)
    trace.begin(m, s)
    try:
        trace.mark("home", F.MOVE_ORIGIN)
        m.move_origin(s)
        trace.sent(m, s, "home")
        done = trace.until_stopped(m, s, step.args["timeout_s"])
        if not done:
            m.move_stop(s)
            m.wait_motion_done(s, timeout=5.0)
    finally:
        trace.end(m)
    t_home, t_end = trace.time_of("home"), trace.t_stop
    test.measurements["duration"] = round(t_end - t_home, 4)
    test.measurements["origin_ok"] = bool(done and m.get_axis_status(s).origin_ok)
    test.measurements["alarm"] = _alarm_code(m, s)
    test.attach("trace", _attachment(trace), "application/json")
    if done:
        trace.check(t_home, t_end, ctx.plan.sample_rate_min, "the origin search")


def _io_entries(step, wiring):
    """The wired relays and senses this io step checks (the loader made sure each is wired)."""
    def pick(which, entries, refs):
        return list(entries) if refs is None else [wiring.find(which, r) for r in refs]

    return pick("relay", wiring.relays, step.args["relays"]), pick("sense", wiring.senses, step.args["senses"])


def measures_io(step, plan):
    relays, senses = _io_entries(step, plan.wiring)
    out = []
    for relay, bit, name in relays:
        what = "drive inputs (wired bits) with relay %d%s " % (relay, " (%s)" % name if name else "")
        out += [_equals("relay_%d_on" % relay, 1 << bit, doc=what + "on"),
                _equals("relay_%d_off" % relay, 0, doc=what + "off")]
    for jig_in, bit, name in senses:
        what = "jig inputs (wired bits) with drive output %d%s " % (bit, " (%s)" % name if name else "")
        out += [_equals("sense_%d_on" % jig_in, 1 << jig_in, doc=what + "on"),
                _equals("sense_%d_off" % jig_in, 0, doc=what + "off")]
    return out


def _switch_and_read(m, out_slave, bit, in_slave, mask, settle):
    """Output ``bit`` of ``out_slave`` on, then off; the masked inputs of ``in_slave`` after each."""
    read = []
    for on in (True, False):
        if on:
            m.set_io_output(out_slave, set_mask=1 << bit)
        else:
            m.set_io_output(out_slave, clear_mask=1 << bit)
        time.sleep(settle)
        read.append(m.get_io_input(in_slave) & mask)
    return read


def run_io(test, bus, step, ctx):
    m, s, jig = bus.master, bus.slave, bus.jig_id
    wiring = ctx.plan.wiring
    relays, senses = _io_entries(step, wiring)
    settle = step.args["settle_ms"] / 1000.0
    drive_mask = wiring.drive_input_mask  # only the wired bits count
    jig_mask = wiring.jig_input_mask
    relay_mask = sum(1 << e[0] for e in wiring.relays)
    output_mask = sum(1 << e[1] for e in wiring.senses)
    try:
        m.set_io_output(jig, clear_mask=relay_mask)
        for relay, _, _ in relays:
            on, off = _switch_and_read(m, jig, relay, s, drive_mask, settle)
            test.measurements["relay_%d_on" % relay] = on
            test.measurements["relay_%d_off" % relay] = off
        m.set_io_output(s, clear_mask=output_mask)
        for jig_in, bit, _ in senses:
            on, off = _switch_and_read(m, s, bit, jig, jig_mask, settle)
            test.measurements["sense_%d_on" % jig_in] = on
            test.measurements["sense_%d_off" % jig_in] = off
    finally:  # a relay left on (a limit input!) would stop the next step or the next drive
        m.set_io_output(jig, clear_mask=relay_mask)
        m.set_io_output(s, clear_mask=output_mask)


def _run_for(trace, m, s, a, direction):
    """A velocity move at the step's speed, sampled for its after_ms (limit-sensor, stop-response)."""
    trace.mark("move", F.MOVE_VELOCITY)
    m.move_velocity(s, a["speed"], direction)
    trace.sent(m, s, "move")
    trace.sample_until(m, s, a["after_ms"] / 1000.0)


def measures_limit_sensor(step, plan):
    lo, hi = step.args["stop_time_s"]
    return [_equals("stopped", True, doc="the axis stopped after the limit input"),
            _equals("limit_flag", True, doc="the axis status flags the hardware limit"),
            _range("stop_time", lo, hi, S, "time from the relay switching to standstill")]


def run_limit_sensor(test, bus, step, ctx):
    m, s, jig, a = bus.master, bus.slave, bus.jig_id, step.args
    relay, drive_input, _ = ctx.plan.wiring.find("relay", a["relay"])  # the loader checked it is wired
    direction = DIR_PLUS if drive_input == 0 else DIR_MINUS
    trace = new_trace(bus, ctx, step)
    trace.begin(m, s)
    stopped = False
    try:
        _run_for(trace, m, s, a, direction)
        trace.mark("relay", F.SET_IO_OUTPUT)
        m.set_io_output(jig, set_mask=1 << relay)
        trace.sent_local("relay")
        stopped = trace.until_stopped(m, s, a["timeout_s"])
        limit = "hw_limit_plus" if direction == DIR_PLUS else "hw_limit_minus"
        test.measurements["stopped"] = stopped
        test.measurements["limit_flag"] = bool(getattr(trace.last.axis, limit))
    finally:
        m.set_io_output(jig, clear_mask=1 << relay)
        if trace.last is None or trace.last.axis.motioning:
            m.move_stop(s)
        trace.end(m)
    if trace.source == "jig":  # the relay's instant, to within half a sample period: when the drive saw it
        trace.date_by_flag("relay", limit, trace.time_of("move"))
    t_relay, t_end = trace.time_of("relay"), trace.t_stop
    test.measurements["stop_time"] = round(t_end - t_relay, 4)
    test.attach("trace", _attachment(trace), "application/json")
    if stopped:
        trace.check(t_relay, t_end, ctx.plan.sample_rate_min, "the stop at the limit")


def measures_stop_response(step, plan):
    lo, hi = step.args["stop_time_s"]
    return [_equals("stopped", True, doc="the axis came to standstill"),
            _range("stop_time", lo, hi, S, "time from the stop command to standstill"),
            _at_most("overshoot", step.args["overshoot_max"], PULSE, "travel after the stop command")]


def run_stop_response(test, bus, step, ctx):
    m, s, a = bus.master, bus.slave, step.args
    trace = new_trace(bus, ctx, step)
    trace.begin(m, s)
    stopped = False
    stop_ftype = F.EMERGENCY_STOP if a["stop"] == "emergency-stop" else F.MOVE_STOP
    try:
        _run_for(trace, m, s, a, DIR_PLUS)
        trace.mark("stop", stop_ftype)
        if a["stop"] == "emergency-stop":
            m.emergency_stop(s)
        else:
            m.move_stop(s)
        trace.sent(m, s, "stop")
        stopped = trace.until_stopped(m, s, 10.0)
    finally:  # a velocity move runs until stopped: never leave it running
        if trace.last is None or trace.last.axis.motioning:
            m.emergency_stop(s)
        trace.end(m)
    t_stop, t_end = trace.time_of("stop"), trace.t_stop
    test.measurements["stopped"] = stopped
    test.measurements["stop_time"] = round(t_end - t_stop, 4)
    # the command position when the stop went out (between the samples around it) to where it ended
    test.measurements["overshoot"] = int(round(abs(trace.rows[-1][1] - trace.position_at(t_stop))))
    test.attach("trace", _attachment(trace), "application/json")
    if a["stop"] == "emergency-stop" and a["recover"]:
        m.servo_enable(s, False)
        m.servo_enable(s, True)
    if stopped:
        trace.check(t_stop - 0.02, t_end, ctx.plan.sample_rate_min, "the stop")


BUS_SUMS = {
    "crc_errors": ("up_crc_errors", "down_crc_errors"),
    "stuffing_errors": ("up_stuff_errors", "down_stuff_errors"),
    "timeouts": ("timeouts",),
    "overflows": ("up_rx_overflows", "down_rx_overflows"),
}


def measures_bus_health(step, plan):
    a = step.args
    out = [_at_most(name, a[name + "_max"], doc="sum of the jig's " + " + ".join(parts))
           for name, parts in BUS_SUMS.items()]
    out += [_at_most("turnaround_max", a["turnaround_max_us"], US, "the jig's longest handling time"),
            _at_most("roundtrip_max", a["roundtrip_max_ms"], MS, "longest request/reply round trip seen here")
            if a["roundtrip_max_ms"] is not None else
            _m("roundtrip_max", MS, "longest request/reply round trip seen here (reported, not judged: this PC's)"),
            _m("roundtrip_avg", MS, "mean round trip"), _m("roundtrip_min", MS, "shortest round trip")]
    doc = "the drive's longest GetAllStatus response on the jig's clock (request's end to reply's end)"
    out.append(_at_most("drive_response_max", a["drive_response_max_us"], US, doc)
               if a["drive_response_max_us"] is not None else _m("drive_response_max", US, doc))
    return out


def run_bus_health(test, bus, step, ctx):
    m = bus.master
    counters = m.read_counters(bus.jig_id)
    for name, parts in BUS_SUMS.items():
        test.measurements[name] = sum(counters.get(p, 0) for p in parts)
    test.measurements["turnaround_max"] = counters.get("turnaround_max_us", 0)
    rt = m.roundtrips or [0.0]
    test.measurements["roundtrip_max"] = round(max(rt) * 1000, 3)
    test.measurements["roundtrip_avg"] = round(sum(rt) / len(rt) * 1000, 3)
    test.measurements["roundtrip_min"] = round(min(rt) * 1000, 3)
    test.attach("bus_counters", json.dumps(counters), "application/json")
    responses = _drive_responses(m, bus.slave, bus.jig_id)
    if responses:
        test.measurements["drive_response_max"] = max(responses)
    else:  # a jig that does not date the requests it forwards: nothing to judge the drive's response by
        _skip(test, "drive_response_max")


def _drive_responses(m, s, jig, n=8):
    """The drive's response times (µs) to n GetAllStatus requests, as the jig timed them; [] when the
    jig's firmware keeps no transaction times."""
    for _ in range(n):
        m.get_all_status(s)
    try:
        times = m.transaction_times(jig)
    except JigError:
        return []
    return [t.round_trip_us for t in times if t.slave == s and t.round_trip_us is not None]


def measures_prompt(step, plan):
    return [_equals("confirmed", True, doc=step.args["message"])]


def run_prompt(test, bus, step, ctx):
    test.measurements["confirmed"] = bool(ctx.confirm(step.args["message"]))


# --- the phase around a step ----------------------------------------------------------------
def _results(test, measures):
    """Every measurement of the phase: (name, value, unit, limits, outcome), in declaration order."""
    out = []
    for declared in measures:
        meas = test.get_measurement(declared.name)
        unit = declared.units.suffix if declared.units is not None and declared.units.suffix else ""
        limits = ", ".join(str(v) for v in declared.validators)
        out.append((declared.name, meas.value, unit, limits, meas.outcome.name))
    return out


def not_measured(test, name, why):
    """A step could not measure ``name`` (the drive refused it): the measurement stays unset, and
    ``why`` goes with it to the console, the HTML report and the record (attachment "why_unset")."""
    test.state.setdefault("why_unset", {})[name] = why


def _failed_lines(results, why=None):
    """The failed ones as 'name = value unit (limits)' texts; an unset one with its reason if known."""
    why = why or {}
    return ["%s = %s%s (%s)" % (name, ("unset: " + why[name] if name in why else "unset") if value is None else value,
                                " " + unit if unit else "", limits or "a value")
            for name, value, unit, limits, outcome in results if outcome not in ("PASS", "SKIPPED")]


# OpenHTF ends a phase after 3 minutes unless the phase says otherwise. A prompt waits for the
# operator as long as it takes (Abort or Ctrl-C ends it); a step with its own timeout_s gets that,
# its wait before (after_ms) and a minute's margin, so its own timeout (which stops the axis) acts
# first. OpenHTF needs a number (None means its default, and the record is JSON: no infinity).
DEFAULT_PHASE_TIMEOUT_S = 180.0
WAIT_FOREVER_S = 10 * 365 * 86400.0


def phase_timeout(step):
    """Seconds OpenHTF lets this step's phase run before it kills it (a TIMEOUT verdict)."""
    if step.kind == "prompt":
        return WAIT_FOREVER_S
    a = step.args
    own = a.get("timeout_s", 0) + a.get("after_ms", 0) / 1000.0 + 60.0
    return max(DEFAULT_PHASE_TIMEOUT_S, own)


def _step_functions(step, plan):
    """(measurements, run) of a step: its drive kind's (the table of kinds, ``station.kinds``)."""
    from motorjig.station import kinds

    return kinds.kind_of(plan).step_functions(step, plan)


def build_phase(step, plan, ctx):
    """One OpenHTF phase for one expanded plan step."""
    measures, run = _step_functions(step, plan)

    def phase(test, bus):
        if getattr(ctx, "aborted", False):  # an Abort that came before OpenHTF could deliver it
            bus.note_abort()
            raise RunAborted("aborted before step %s" % step.name)
        ctx.started(step)
        test.state["why_unset"] = {}
        n0 = len(bus.master.roundtrips)
        drive_s0 = getattr(bus.drive, "bus_seconds", 0.0)

        def bus_s():  # seconds of the step spent waiting for replies: the jig's PC port and the drive's SDO
            return sum(bus.master.roundtrips[n0:]) + getattr(bus.drive, "bus_seconds", 0.0) - drive_s0

        try:
            run(test, bus, step, ctx)
        except (KeyboardInterrupt, threads.ThreadTerminationError):
            bus.note_abort()
            ctx.finished(step, "ABORTED", [], bus_s())
            raise
        except BaseException as exc:
            bus.note_failure()
            ctx.finished(step, "ERROR", ["%s: %s" % (type(exc).__name__, exc)], bus_s(),
                         _results(test, measures))
            raise
        results = _results(test, measures)
        why = test.state.pop("why_unset", None) or {}
        if why:
            test.attach("why_unset", json.dumps(why), "application/json")
        failed = _failed_lines(results, why)
        if failed and bus.safety is not None and bus.safety.fired():
            bus.note_failure()
            why = ("the jig's safety stop fired during the step: this PC was silent for more than %d ms and the "
                   "jig stopped the axis; the drive was not judged" % bus.safety.window_ms)
            ctx.finished(step, "ERROR", [why], bus_s(), results)
            raise UntrustedMeasurement(why)
        if failed:
            bus.note_failure()
            # the report's banner says why the run failed: the first failing step's measurements
            test.test_record.metadata.setdefault("verdict_reason", "%s: %s" % (step.name, "; ".join(failed)))
        ctx.finished(step, "FAIL" if failed else "PASS", failed, bus_s(), results)

    phase.__name__ = step.name
    phase.__doc__ = "%s step %r" % (step.kind, step.name)
    phase = htf.measures(*measures)(phase)
    phase = htf.plug(bus=MotorJigPlug)(phase)
    return htf.PhaseOptions(name=step.name, timeout_s=phase_timeout(step))(phase)
