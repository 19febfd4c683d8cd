"""What each jigctl subcommand does: talk to the bus through Master, print the result.

``motorjig.cli`` parses the command line and calls ``cmd_<name>(args)``; every
function here returns an exit status or raises (``UsageError`` for bad input, the
``motorjig.errors`` classes for bus trouble), and ``cli.main`` turns exceptions
into one sentence on stderr. Output is text, or JSON with ``--json``.
"""

import json
import sys
import time

from jig import frame as F
from jig.diag import SLAVE_TYPE as JIG_TYPE

from motorjig import names as N
from motorjig.decode import Decoder, describe_dict
from motorjig.errors import CommError, JigError, StatusError
from motorjig.master import AxisStatus, Master, MotionTimeoutError, jsonable

EXIT_OK = 0
EXIT_FAIL = 1
EXIT_USAGE = 2
EXIT_PORT = 3
EXIT_COMM = 4
EXIT_STATUS = 5
EXIT_INTERRUPT = 130


class UsageError(Exception):
    """Bad input from the user (exit status 2)."""


# --- input helpers ---------------------------------------------------------------
def parse_hex(tokens):
    """Bytes from hex tokens like '01 40', '0140', '0x01,0x40'."""
    text = " ".join(tokens).replace(",", " ").replace(":", " ")
    parts = []
    for tok in text.split():
        if tok.lower().startswith("0x"):
            tok = tok[2:]
            if len(tok) == 1:
                tok = "0" + tok
        parts.append(tok)
    joined = "".join(parts)
    try:
        data = bytes.fromhex(joined)
    except ValueError:
        raise UsageError("%r is not hex bytes (give bytes like: 01 40, or 0140)" % " ".join(tokens)) from None
    if not data:
        raise UsageError("no bytes given")
    return data


def bits_arg(text, table):
    """A bit mask from a number or comma-separated bit names."""
    if text is None:
        return 0
    try:
        return int(text.replace("_", ""), 0)
    except ValueError:
        pass
    try:
        return N.bit_value([t.strip() for t in text.split(",") if t.strip()], table)
    except KeyError as exc:
        raise UsageError("unknown bit name %s (names: %s)" % (exc, ", ".join(r[1] for r in table))) from None

# --- output helpers --------------------------------------------------------------
def emit(args, obj, text):
    if args.json:
        print(json.dumps(jsonable(obj)), flush=True)
    else:
        print(text, flush=True)


def flags_text(st):
    st = AxisStatus(st)
    names = st.flags
    return "0x%08X  %s" % (int(st), ", ".join(("!" + n if n in N.AXIS_ERROR_FLAGS else n) for n in names) or "-")


def open_master(args):
    if not args.port:
        raise UsageError("no port given: use --port PORT (or set JIGCTL_PORT); `jigctl ports` lists them")
    trace = _tracer() if args.verbose else None
    return Master(args.port, baud=args.baud, timeout=args.timeout / 1000.0, retries=args.retries,
                  ver8=forced_variant(args), trace=trace, echo=args.echo)


def forced_variant(args):
    """Master's ver8 argument: True/False when --ver8/--ver6 force it, None to detect."""
    if getattr(args, "ver8", False):
        return True
    if getattr(args, "ver6", False):
        return False
    return None


def _tracer():
    dec = Decoder()

    def trace(direction, item):
        if direction == "tx":
            sys.stderr.write("TX %s\n" % bytes(item).hex(" "))
        else:
            sys.stderr.write("RX %s\n" % dec.describe(item, "reply"))  # what the master receives is a reply
        sys.stderr.flush()

    return trace

# --- subcommands -------------------------------------------------------------------
def cmd_ports(args):
    from serial.tools import list_ports

    rows = [{"device": p.device, "description": p.description, "hwid": p.hwid}
            for p in sorted(list_ports.comports(), key=lambda p: p.device)]
    if args.json:
        emit(args, rows, "")
        return EXIT_OK
    if not rows:
        print("no serial ports found (the virtual bench: `make sim`, then --port socket://HOST:PORT "
              "or its /dev/pts path)")
    for r in rows:
        print("%-20s %s  [%s]" % (r["device"], r["description"], r["hwid"]))
    return EXIT_OK


def cmd_scan(args):
    lo, hi = args.first, args.last
    if not 0 <= lo <= hi <= F.MAX_SLAVE_ID:
        raise UsageError("scan range must be within 0..%d" % F.MAX_SLAVE_ID)
    if args.via_jig:
        return _scan_via_jig(args)
    tty = sys.stderr.isatty()
    with open_master(args) as m:
        def progress(i, found):
            sys.stderr.write("\rscanning id %2d of %d..%d, found %d " % (i, lo, hi, len(found)))
            sys.stderr.flush()

        found = m.scan(range(lo, hi + 1), timeout=args.timeout / 1000.0, progress=progress if tty else None)
        if tty:  # the progress line becomes a summary; pipes and logs get only the result
            sys.stderr.write("\rscanned ids %d..%d: %d found%s\n" % (lo, hi, len(found), " " * 10))
        variants = m.variants
    forced = forced_variant(args)
    rows = []
    for i, info in sorted(found.items()):
        row = {"slave": i, "jig": info is not None and info.type == JIG_TYPE,
               "variant": variants.get(i, 8 if forced else 6), "detected": forced is None}
        if info is not None:
            row.update(jsonable(info))
        rows.append(row)
    lines = []
    for r in rows:
        what = "%s (type %d) %s" % (r["type_name"], r["type"], r["version"]) if "type" in r else "(answers, no info)"
        lines.append("id %2d  Ver%d  %s%s" % (r["slave"], r["variant"], what, "  <- the jig" if r["jig"] else ""))
    if not rows:
        if args.json:
            emit(args, rows, "")
        raise CommError("no slave answered on ids %d..%d within %d ms each" % (lo, hi, args.timeout))
    emit(args, rows, "\n".join(lines))
    return EXIT_OK


def _scan_via_jig(args):
    with open_master(args) as m:
        sys.stderr.write("the jig (slave %d) is scanning its driver bus...\n" % args.jig_id)
        res = m.jig_bus_scan(args.jig_id)
    rows = [{"slave": i, "type": t, "type_name": N.slave_type_name(t)} for i, t in sorted(res.types.items())]
    lines = ["id %2d  %s (type %d)" % (r["slave"], r["type_name"], r["type"]) for r in rows]
    emit(args, rows, "\n".join(lines) if lines else "no drivers answered the jig")
    return EXIT_OK


def _optional(fn, *a):
    """Call fn; None when the slave does not support it (error status)."""
    try:
        return fn(*a)
    except StatusError:
        return None


def cmd_info(args):
    s = args.slave
    with open_master(args) as m:
        info = m.get_slave_info(s)
        motor = _optional(m.get_motor_info, s)
        alarm = _optional(m.get_alarm_type, s)
        st = None if info.type == JIG_TYPE else _optional(m.get_all_status, s)
    out = {"slave": s, "type": info.type, "type_name": info.type_name, "version": info.version,
           "motor": motor, "alarm": alarm, "status": st}
    lines = ["slave %d: %s (type %d)" % (s, info.type_name, info.type), "version   %s" % info.version]
    if motor is not None:
        lines.append("motor     %s (type %d)" % (motor.text, motor.type))
    if alarm is not None:
        lines.append("alarm     %s" % ("none" if alarm.code == 0 else "%d %s" % (alarm.code, alarm.name)))
    if st is not None:
        lines.append("position  %d (actual %d)" % (st.command_pos, st.actual_pos))
        lines.append("flags     %s" % flags_text(st.axis))
    emit(args, out, "\n".join(lines))
    return EXIT_OK


def status_lines(s, st):
    return [
        "slave %d" % s,
        "  command pos  %12d pulse" % st.command_pos,
        "  actual pos   %12d pulse" % st.actual_pos,
        "  pos error    %12d pulse" % st.pos_error,
        "  velocity     %12d pps" % st.actual_vel,
        "  flags        %s" % flags_text(st.axis),
        "  inputs       0x%08X  %s" % (st.inputs, ", ".join(N.bit_names(st.inputs, N.INPUT_BITS)) or "-"),
        "  outputs      0x%08X  %s" % (st.outputs, ", ".join(N.bit_names(st.outputs, N.OUTPUT_BITS)) or "-"),
    ]


def cmd_status(args):
    s = args.slave
    tty = sys.stdout.isatty() and not args.json
    count = args.count if args.count is not None else (None if args.watch else 1)
    from motorjig import safetynotice

    with open_master(args) as m:
        try:
            _status_loop(args, m, s, count, tty, lambda: safetynotice.take(m, args.jig_id))
        except KeyboardInterrupt:  # the normal end of --watch
            if not args.json:
                print()
    return EXIT_OK


def _status_loop(args, m, s, count, tty, take_notice):
    shown = 0
    drawn = 0
    while count is None or shown < count:
        st = m.get_all_status(s)
        if not shown:  # after the drive answered: a jig's notice never hides the drive's own reply
            notice = take_notice()
            if notice:
                note(notice)
        if args.json:
            emit(args, dict(jsonable(st), slave=s, t=time.time()), "")
        else:
            lines = status_lines(s, st)
            if tty and drawn:
                sys.stdout.write("\x1b[%dF\x1b[J" % drawn)  # back to the top of the last block
            elif drawn:
                print()
            print("\n".join(lines), flush=True)
            drawn = len(lines)
        shown += 1
        if count is not None and shown >= count:
            break
        time.sleep(args.interval)


class _stop_on_interrupt:
    """Ctrl-C while a move is being waited for also stops the axis (then ends jigctl)."""

    def __init__(self, m, slave):
        self.m = m
        self.slave = slave

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is KeyboardInterrupt:
            try:
                self.m.move_stop(self.slave)
                sys.stderr.write("\nstop sent to slave %d" % self.slave)
            except JigError:
                sys.stderr.write("\ncould not send a stop to slave %d" % self.slave)
        return False


def _wait(args, m, s):
    if not getattr(args, "wait", False):
        return None
    st = m.wait_motion_done(s, timeout=args.wait_timeout)
    return {"axis": st, "command_pos": m.get_command_pos(s)}


def cmd_move(args):
    s = args.slave
    kind = args.kind
    with open_master(args) as m:
        if kind == "abs":
            m.move_abs(s, args.position, args.speed)
            text = "slave %d: moving to %d at %d pps" % (s, args.position, args.speed)
        elif kind == "inc":
            m.move_inc(s, args.distance, args.speed)
            text = "slave %d: moving by %d at %d pps" % (s, args.distance, args.speed)
        elif kind == "jog":
            m.move_velocity(s, args.speed, args.direction)
            text = "slave %d: jogging %s at %d pps" % (s, "+" if args.direction else "-", args.speed)
            if args.duration is not None:
                with _stop_on_interrupt(m, s):
                    time.sleep(args.duration)
                m.move_stop(s)
                text += ", stopped after %.1f s" % args.duration
        elif kind == "home":
            m.move_origin(s)
            text = "slave %d: origin search started" % s
        else:
            m.move_to_limit(s, args.speed, args.direction)
            text = "slave %d: moving to the %s limit at %d pps" % (s, "+" if args.direction else "-", args.speed)
        with _stop_on_interrupt(m, s):
            done = _wait(args, m, s)
    out = {"slave": s, "move": kind, "ok": True}
    if done is not None:
        out.update(done)
        text += "; done at %d (flags %s)" % (done["command_pos"], flags_text(done["axis"]))
    emit(args, out, text)
    return EXIT_OK


def cmd_stop(args, emergency=False):
    with open_master(args) as m:
        if args.all:
            (m.all_emergency_stop if emergency else m.all_move_stop)()
            who = "all slaves (broadcast)"
        else:
            (m.emergency_stop if emergency else m.move_stop)(args.slave)
            who = "slave %d" % args.slave
    what = "emergency stop" if emergency else "stop"
    emit(args, {"slave": "all" if args.all else args.slave, "command": what, "ok": True}, "%s: %s sent" % (who, what))
    return EXIT_OK


def cmd_estop(args):
    return cmd_stop(args, emergency=True)


def cmd_servo(args):
    on = args.state == "on"
    with open_master(args) as m:
        m.servo_enable(args.slave, on)
    emit(args, {"slave": args.slave, "servo": on, "ok": True}, "slave %d: servo %s" % (args.slave, args.state))
    return EXIT_OK


def cmd_alarm_reset(args):
    s = args.slave
    with open_master(args) as m:
        if args.kind == "auto":
            servo = m.get_slave_info(s).type in N.SERVO_TYPES
        else:
            servo = args.kind == "servo"
        m.alarm_reset(s, servo=servo)
        alarm = _optional(m.get_alarm_type, s)
    text = "slave %d: alarm reset sent (%s)" % (s, "ServoAlarmReset" if servo else "StepAlarmReset on/off")
    if alarm is not None:
        text += "; alarm now: %s" % alarm.name
    emit(args, {"slave": s, "ok": True, "alarm": alarm}, text)
    return EXIT_OK


def _param_table(args):
    if args.slave == args.jig_id or getattr(args, "jig", False):
        return "jig", N.jig_params()
    return "ezi-step", N.STEP_PARAMS


def _param(args, table, key):
    p = N.find_param(table, key)
    if p is None:
        raise UsageError("no parameter %r in the %s table (see `jigctl param list`)" % (key, _param_table(args)[0]))
    return p


def cmd_param(args):
    s = args.slave
    which, table = _param_table(args)
    act = args.action
    if act == "list":
        values = {}
        if not args.offline:
            with open_master(args) as m:
                for p in table:
                    values[p.number] = _optional(m.get_parameter, s, p.number)
        rows = []
        for p in table:
            row = p.as_dict()
            if not args.offline:
                row["value"] = values.get(p.number)
            rows.append(row)
        lines = ["%s parameters%s" % (which, "" if args.offline else " of slave %d" % s)]
        for r in rows:
            val = "" if args.offline else ("%12s" % ("-" if r["value"] is None else r["value"]))
            full = (r["min"], r["max"]) == (-0x80000000, 0x7FFFFFFF)
            rng = "(unconfirmed)" if full else "%s..%s" % (r["min"], r["max"])
            line = "%3d %-24s%s  %-6s %-24s default %-10s %s" % (
                r["number"], r["name"], val, r["unit"] if len(r["unit"]) <= 6 else "", rng,
                "-" if r["default"] is None else r["default"], r["unit"] if len(r["unit"]) > 6 else "")
            lines.append(line.rstrip())
        emit(args, {"slave": s, "table": which, "params": rows}, "\n".join(lines))
        return EXIT_OK
    if act in ("dump", "load"):
        if which == "jig":
            raise UsageError("param %s works on a drive's parameters, not the jig's" % act)
        return _param_file(args, s, act)
    if act == "save":
        with open_master(args) as m:
            m.save_all_parameters(s)
        emit(args, {"slave": s, "saved": True}, "slave %d: parameters saved to ROM" % s)
        return EXIT_OK
    p = _param(args, table, args.param)
    if act == "get":
        with open_master(args) as m:
            v = (m.get_rom_parameter if args.rom else m.get_parameter)(s, p.number)
        emit(args, {"slave": s, "param": p.number, "name": p.name, "value": v, "unit": p.unit, "rom": args.rom},
             "%d %s = %d%s%s" % (p.number, p.name, v, " " + p.unit if p.unit else "", " (ROM)" if args.rom else ""))
        return EXIT_OK
    # set
    try:
        p.check(args.value)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if which == "jig" and p.number == 0:
        return _set_jig_id(args, s, args.value)
    with open_master(args) as m:
        m.set_parameter(s, p.number, args.value)
        v = m.get_parameter(s, p.number)
    restart = which == "jig" and p.effect == "restart"
    note = "takes effect after `param save` and a restart of the jig" if restart else "`param save` keeps it"
    emit(args, {"slave": s, "param": p.number, "name": p.name, "value": v, "needs_restart": restart},
         "%d %s = %d%s (RAM; %s)" % (p.number, p.name, v, " " + p.unit if p.unit else "", note))
    return EXIT_OK


def _param_file(args, s, act):
    """param dump FILE: the drive's RAM (--rom: ROM) values as a parameter-set file;
    param load FILE: every value of the file to RAM (checked first), --save to ROM too."""
    from motorjig import paramset
    from motorjig.tomlsource import SourceError

    if act == "load":
        try:
            ps = paramset.load(args.file)
        except SourceError as exc:
            raise UsageError(str(exc)) from None
        with open_master(args) as m:
            info = m.get_slave_info(s)
            if ps.slave_type is not None and info.type != ps.slave_type:
                raise UsageError("%s is for slave type %d, slave %d is type %d (%s)" % (
                    args.file, ps.slave_type, s, info.type, info.type_name))
            for number, value in ps.values.items():
                m.set_parameter(s, number, value)
            if args.save:
                m.save_all_parameters(s)
        emit(args, {"slave": s, "file": args.file, "written": len(ps.values), "saved": args.save},
             "slave %d: %d parameters from %s written to RAM%s" % (
                 s, len(ps.values), args.file, " and saved to ROM" if args.save else " (`param save` keeps them)"))
        return EXIT_OK
    with open_master(args) as m:
        info = m.get_slave_info(s)
        read = m.get_rom_parameter if args.rom else m.get_parameter
        values = {p.number: read(s, p.number) for p in paramset.TABLE}
    text = paramset.dumps(values, s, info.type, "ROM" if args.rom else "RAM")
    if args.file in (None, "-"):
        sys.stdout.write(text)
    else:
        with open(args.file, "w", encoding="utf-8") as f:
            f.write(text)
        emit(args, {"slave": s, "file": args.file, "read": len(values), "rom": args.rom},
             "slave %d: %d parameters (%s) written to %s" % (s, len(values), "ROM" if args.rom else "RAM", args.file))
    return EXIT_OK


def _set_jig_id(args, s, new):
    """jig_slave_id: the jig answers at the new id right after its reply, so read it
    back there; a refusal (0x81) means a driver answers at that id on the driver bus."""
    with open_master(args) as m:
        try:
            m.set_parameter(s, 0, new)
        except StatusError as exc:
            if exc.status != F.STATUS_DATA_ERROR:
                raise
            exc.args = ("the jig (slave %d) refused jig_slave_id = %d (status 0x81): a driver answers at id %d "
                        "on its driver bus and the jig would hide it, or the jig could not check the id just "
                        "now; pick a free id (`jigctl scan`)" % (s, new, new),)
            raise
        v = m.get_parameter(new, 0)
    moved = new != s
    text = "0 jig_slave_id = %d (RAM; `param save` keeps it)" % v
    if moved:
        text += "\nthe jig now answers as slave %d, no longer %d: use --slave %d --jig-id %d" % (new, s, new, new)
    emit(args, {"slave": new, "previous_slave": s, "param": 0, "name": "jig_slave_id", "value": v, "moved": moved,
                "needs_restart": False},
         text)
    return EXIT_OK


def cmd_io(args):
    s = args.slave
    act = args.action or "show"
    with open_master(args) as m:
        if act in ("out", "in"):
            table = N.OUTPUT_BITS if act == "out" else N.INPUT_BITS
            set_mask = bits_arg(args.set, table)
            clear_mask = bits_arg(args.clear, table)
            (m.set_io_output if act == "out" else m.set_io_input)(s, set_mask, clear_mask)
        elif act == "map":
            if args.pin is None:
                raise UsageError("io map needs a pin index")
            if args.mask is not None:
                if args.level not in (0, 1):
                    raise UsageError("io map needs a level of 0 (low active) or 1 (high active)")
                m.set_io_assign_map(s, args.pin, args.mask, args.level)
            a = m.get_io_assign_map(s, args.pin)
            emit(args, {"slave": s, "pin": args.pin, "mask": a.mask, "level": a.level},
                 "slave %d pin %d: mask 0x%08X, %s active" % (s, args.pin, a.mask, "high" if a.level else "low"))
            return EXIT_OK
        elif act == "read-rom":
            r = m.io_assign_map_read_rom(s)
            emit(args, {"slave": s, "result": r}, "slave %d: I/O map reloaded from ROM (result %d)" % (s, r))
            return EXIT_OK
        inputs = m.get_io_input(s)
        outputs = m.get_io_output(s)
    jig = s == args.jig_id
    in_names = N.bit_names(inputs, () if jig else N.INPUT_BITS)
    out_names = N.bit_names(outputs, () if jig else N.OUTPUT_BITS)
    emit(args, {"slave": s, "inputs": inputs, "outputs": outputs, "input_bits": in_names, "output_bits": out_names},
         "slave %d\n  inputs   0x%08X  %s\n  outputs  0x%08X  %s" % (
             s, inputs, ", ".join(in_names) or "-", outputs, ", ".join(out_names) or "-"))
    return EXIT_OK


def cmd_raw(args):
    data = parse_hex(args.hex)
    with open_master(args) as m:
        m.discard_input()
        if args.no_crc:
            wire = data
            want = None
        else:
            if len(data) < 2:
                raise UsageError("give at least the slave id and the frame type (e.g. 02 40)")
            v8 = data[0] != F.BROADCAST_ID and 0 <= data[0] <= F.MAX_SLAVE_ID and m.variant(data[0]) == 8
            sync = m.next_sync(data[0]) if (args.ver8 or v8) else -1
            try:
                wire = F.encode(data[0], data[1], data[2:], sync)
            except ValueError:
                raise UsageError("too much data for one frame (at most %d bytes)" % F.MAX_DATA) from None
            want = (data[0], data[1])
        m.write(wire)
        frames = []
        dec = Decoder()
        end = time.monotonic() + args.timeout / 1000.0
        reply = None
        echo_seen = False
        while reply is None:
            left = end - time.monotonic()
            if left <= 0:
                break
            fr = m.read_frame(left)
            if fr is None:
                break
            if args.echo and not frames and not echo_seen and fr.body == _body_of(wire):
                echo_seen = True
                continue
            d = dec.as_dict(fr, "reply" if fr.data and (want is None or (fr.slave, fr.ftype) == want) else None)
            frames.append(d)
            if want is None or (fr.slave, fr.ftype) == want:
                reply = d
    out = {"sent": wire.hex(" "), "frames": frames, "reply": reply}
    lines = ["sent     %s" % wire.hex(" ")] + ["received %s" % describe_dict(d) for d in frames]
    if reply is None:
        if args.json:
            emit(args, out, "")
        else:
            print("\n".join(lines))
        if want:
            raise CommError("no reply from slave %d within %d ms" % (want[0], args.timeout))
        raise CommError("no frame came back within %d ms" % args.timeout)
    emit(args, out, "\n".join(lines))
    status = reply.get("status")
    if status:  # shown above; the exit status tells scripts
        return fail(EXIT_STATUS, "slave %d replied with status 0x%02X: %s" % (
            reply["slave"], status, reply["meaning"]))
    return EXIT_OK


def _body_of(wire):
    from jig.parser import FrameParser

    p = FrameParser()
    p.feed(wire)
    return bytes(p.body[:p.body_len]) if p.ready else None


LINE_ERRORS = ("crc_errors", "stuff_errors", "short", "overlong", "timeouts", "resyncs")


def _stamp(t):
    return time.strftime("%H:%M:%S", time.localtime(t)) + ".%03d" % int(t % 1 * 1000)


def cmd_monitor(args):
    log_path = args.log
    if log_path is None:
        log_path = time.strftime("jigctl-monitor-%Y%m%d-%H%M%S.log")
    log = None
    if log_path != "-":
        try:
            log = open(log_path, "a", encoding="utf-8")
        except OSError as exc:
            raise UsageError("cannot write the log file %s: %s" % (log_path, exc.strerror)) from None

    def show(line, record):
        if args.json:
            print(json.dumps(record), flush=True)
        else:
            print(line, flush=True)

    dec = Decoder()
    count = 0
    try:
        with open_master(args) as m:
            if not args.json:
                sys.stderr.write("monitoring %s at %d baud%s; Ctrl-C ends%s\n" % (
                    args.port, args.baud, "" if args.duration is None else " for %g s" % args.duration,
                    "" if log is None else "; log: %s" % log_path))
            p = m.parser
            seen = {name: 0 for name in LINE_ERRORS}
            end = None if args.duration is None else time.monotonic() + args.duration
            try:
                while end is None or time.monotonic() < end:
                    left = 0.2 if end is None else min(0.2, end - time.monotonic())
                    fr = m.read_frame(max(0.0, left))
                    for name in LINE_ERRORS:  # broken frames are shown too, as counts
                        n = getattr(p, name) - seen[name]
                        if n:
                            seen[name] += n
                            t = time.time()
                            line = "%s  line error: %d x %s" % (_stamp(t), n, name)
                            show(line, {"t": t, "kind": "line_error", "error": name, "count": n})
                            if log is not None:
                                log.write(line + "\n")
                    if fr is None:
                        continue
                    d = dec.as_dict(fr)
                    count += 1
                    line = "%s  %s" % (_stamp(fr.t), describe_dict(d))
                    show(line, d)
                    if log is not None:
                        log.write("%s  raw [%s]\n" % (line, fr.body.hex(" ")))
                        log.flush()
            except KeyboardInterrupt:
                pass
            errors = {name: getattr(p, name) for name in LINE_ERRORS + ("noise",)}
    finally:
        if log is not None:
            log.close()
    summary = {"frames": count, "errors": errors, "log": None if log is None else log_path}
    if args.json:
        print(json.dumps({"summary": summary}), flush=True)
    else:
        sys.stderr.write("%d frames; line errors: %s\n" % (
            count, ", ".join("%s %d" % kv for kv in errors.items() if kv[1]) or "none"))
    return EXIT_OK


def cmd_motion_test(args):
    s = args.slave
    moves = []
    with open_master(args) as m:
        if args.servo_on:
            m.servo_enable(s, True)
        with _stop_on_interrupt(m, s):
            _motion_cycles(args, m, s, moves)
    passed = sum(1 for r in moves if r["ok"])
    summary = {"slave": s, "moves": moves, "passed": passed, "failed": len(moves) - passed}
    emit(args, summary, "%d of %d moves passed" % (passed, len(moves)))
    return EXIT_OK if passed == len(moves) and moves else EXIT_FAIL


def _motion_cycles(args, m, s, moves):
    for cycle in range(args.cycles):
        for sign in (1, -1):
            d = sign * args.distance
            rec = {"cycle": cycle + 1, "distance": d}
            t0 = time.monotonic()
            try:
                p0 = m.get_command_pos(s)
                m.move_inc(s, d, args.speed)
                st = m.wait_motion_done(s, timeout=args.move_timeout)
                p1 = m.get_command_pos(s)
                rec.update(start=p0, end=p1, flags=st.flags)
                problems = []
                if p1 - p0 != d:
                    problems.append("moved %d instead of %d" % (p1 - p0, d))
                if st.errors:
                    problems.append("error flags: %s" % ", ".join(st.errors))
                rec["ok"] = not problems
                if problems:
                    rec["problem"] = "; ".join(problems)
            except (JigError, MotionTimeoutError) as exc:
                rec.update(ok=False, problem=str(exc))
            rec["seconds"] = round(time.monotonic() - t0, 3)
            moves.append(rec)
            if not args.json:
                print("cycle %d  move %+d  %s  %.2f s%s" % (
                    rec["cycle"], d, "PASS" if rec["ok"] else "FAIL", rec["seconds"],
                    "" if rec["ok"] else "  (%s)" % rec["problem"]), flush=True)
            if not rec["ok"] and args.stop_on_fail:
                break
        if moves and not moves[-1]["ok"] and args.stop_on_fail:
            break


CAN_STATE_NAMES = ("closed", "error active", "error warning", "error passive", "bus-off")


def _can_figures(m, jig):
    """(CAN counters, termination advice 0/1) of the jig's CAN port; ({}, None) from a jig
    without one (a HAL without CAN, or firmware from before it: frame type refused)."""
    try:
        can = m.can_counters(jig)
    except StatusError:
        return {}, None
    if not can:
        return {}, None
    try:
        term = m.get_parameter(jig, 16)  # can_termination
    except StatusError:
        term = None
    return can, term


def can_block(can, term):
    """The "CAN port" block of `jigctl stats` (lines)."""
    state = can.get("can_state", 0)
    name = CAN_STATE_NAMES[state] if 0 <= state < len(CAN_STATE_NAMES) else "state %d" % state
    if can.get("can_open"):
        lines = ["CAN port: %s, %s, %d bit/s, TEC %d, REC %d" % (
            "open, listen-only" if can.get("can_listen_only") else "open", name, can.get("can_bitrate", 0),
            can.get("can_tec", 0), can.get("can_rec", 0))]
    else:
        lines = ["CAN port: closed, %d bit/s" % can.get("can_bitrate", 0)]
    if term is not None:
        lines.append("  termination: %s" % ("fit J4-TERM (120 ohm): the jig is an end of the CAN bus" if term
                                            else "leave J4-TERM open: the jig is not an end of the CAN bus"))
    shown = ("can_state", "can_open", "can_listen_only", "can_bitrate", "can_tec", "can_rec")
    rest = [(k, v) for k, v in can.items() if k not in shown]
    width = max(len(k) for k, _ in rest) if rest else 0
    lines += ["  %-*s %d" % (width, k, v) for k, v in rest]
    return lines


def cmd_stats(args):
    from motorjig import safetynotice

    with open_master(args) as m:
        counters = m.read_counters(args.jig_id)
        can, term = _can_figures(m, args.jig_id)
        notice = safetynotice.take(m, args.jig_id)
        if args.reset:
            m.reset_counters(args.jig_id)
    width = max(len(k) for k in counters) if counters else 0
    lines = ["note: %s" % notice] if notice else []
    lines += ["jig (slave %d) counters%s" % (args.jig_id, ", now reset" if args.reset else "")]
    lines += ["  %-*s %d" % (width, k, v) for k, v in counters.items()]
    if can:
        lines += can_block(can, term)
    emit(args, {"jig": args.jig_id, "counters": counters, "can": can, "can_termination": term,
                "reset": args.reset, "safety_notice": notice}, "\n".join(lines))
    return EXIT_OK


def cmd_crashlog(args):
    with open_master(args) as m:
        text = m.read_crash_log(args.jig_id)
    shown = text or "no crash recorded"
    emit(args, {"jig": args.jig_id, "crash_log": text},
         "jig (slave %d) crash log: %s" % (args.jig_id, shown))
    return EXIT_OK


def note(message):
    """A note for the user on stderr, one sentence: 'jigctl: note: ...'."""
    sys.stderr.write("jigctl: note: %s.\n" % message.rstrip("."))
    sys.stderr.flush()


def fail(code, message):
    message = message.rstrip(".")
    sys.stderr.write("jigctl: %s%s\n" % (message, "" if message.endswith((".", "?", "!")) else "."))
    sys.stderr.flush()
    return code
