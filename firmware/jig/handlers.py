"""Frames addressed to the jig itself (slave 1 by default), answered locally.

Each handler gets the parsed request and writes the reply data -- status byte
first -- into a preallocated buffer, returning its length. Requests whose data
length is not the documented one get 0x82, unknown frame types 0x80, values out
of range or unknown parameter numbers 0x81.

In Ver8 a 4-byte body (a Ver6 frame without data, e.g. the vendor library's
GetCommandPos probe ``id 51 crcL crcH``) parses with a data length of -1 and is
answered as a Ver8 drive answers it: frame-type error 0x80, whatever its third
byte reads as, so the reply is ``id, sync=0x51, type=crcL, 0x80`` -- which is how
the vendor library recognises a Ver8 slave.

"No axis here": vendor masters probe every id with GetCommandPos (0x51) and poll
GetAxisStatus (0x40) / GetAllStatus (0x43), checking reply lengths exactly. The jig
answers them with status 0 and the documented length, all fields zero: position
0, no flags (not moving, no alarm, no limit), no inputs/outputs.

The jig's I/O (SetIOOutput / GetIOOutput / GetIOInput) uses bits 0..15 only (LEDs,
relays, buttons of the board); the upper 16 bits of the masks are ignored and read
as 0, which keeps every value a small int (no heap use on MicroPython).

No shadowing: SetParameter ``jig_slave_id`` (0) to an id at which a driver
answers on the driver bus gets 0x81, since the jig would answer in its place and
hide it. Ids the jig has relayed a reply from (``Bridge.seen()``) or found in its
bus scan are refused at once; any other new id is probed first with GetSlaveInfo
through ``Bridge.request`` (``scan_timeout_ms``), and the PC's reply is deferred
until that probe ends: an answer -> 0x81, a timeout -> the id is taken (the reply
still comes from the old id). A PC frame for the driver bus meanwhile aborts the
probe and the change (no reply: the PC has moved on). If the jig's own request is
out when the change comes (scan probe, safety stop), the id cannot be checked and
is refused too.

ReadCrashLog (0xF4) is the one handler that allocates: the HAL builds the summary
as a string. It runs only when a person asks for the crash log, never in the
bridging steady state.
"""

from jig import diag, frame, mem
from jig import params as P
from jig.compat import const
from jig.frame import get_u16, put_u16, put_u32
from jig.parser import S_HEAD, S_N

LEN_ANY = -1
DEFERRED = -1  # handle(): no reply now; the handler sends it later (Bridge.local_reply)
# While the sampler runs (or its request is out), a reply with more data bytes than this goes
# out in pieces with the sampler's slots between them (jig.trace.Trace.reply), not whole:
# ReadCounters, ReadCanCounters, ReadTransactionTimes, ReadCrashLog (their handlers end in
# ``_long``). One up to it (<= 50 wire bytes, 4.3 ms at 115 200 baud) stays under the
# inter-byte timeout (5 ms) even when a sample's reply ends at its start.
PACED_MIN = const(40)
_T_WAITING = const(10)  # jig.trace.T_WAITING (T_ON is 0; a host test checks they agree)


class SlaveIdCheck:
    """The probe of a new jig_slave_id: a Bridge.request client that answers the
    waiting SetParameter when the probe ends. Preallocated: nothing per frame."""

    def __init__(self, app):
        self.app = app
        self.busy = False
        self.new_id = 0
        self.slave = 0  # the request's id, sync and type, to answer it
        self.sync = -1
        self.ftype = 0
        self.out = bytearray(1)
        self.empty = bytearray(1)

    def start(self, p, new_id):
        """Probe new_id; False if the bridge cannot send now."""
        app = self.app
        if not app.bridge.request(self, new_id, frame.GET_SLAVE_INFO, self.empty, 0,
                                  app.params.ram[P.P_SCAN_TIMEOUT_MS]):
            return False
        self.busy = True
        self.new_id = new_id
        self.slave = p.slave
        self.sync = p.sync
        self.ftype = p.ftype
        return True

    def _answer(self, status):
        self.busy = False
        self.out[0] = status
        b = self.app.bridge
        b.local_reply(self.slave, self.ftype, self.sync, self.out, 1, b.hal.ticks_us())

    def on_reply(self, p):
        self._answer(frame.STATUS_DATA_ERROR)  # a driver answers there: refuse

    def on_timeout(self):
        self.app.params.set(P.P_SLAVE_ID, self.new_id)
        self._answer(frame.STATUS_OK)

    def on_abort(self):
        self.busy = False  # the PC moved on: no change, no reply


class Handlers:
    def __init__(self, app):
        self.app = app  # gives params, counters, hal, scanner, parsers, apply_params()
        info = bytearray(1 + 1 + len(diag.NAME) + 1 + len(diag.VERSION) + 1)
        info[0] = frame.STATUS_OK
        info[1] = diag.SLAVE_TYPE
        s = diag.NAME + b" " + diag.VERSION + b"\x00"
        info[2:] = s
        self.info = info
        self.counter_values = [0] * diag.N_WIRE
        self.can_values = [0] * diag.N_CAN_WIRE
        self.pending_change = -1
        self.id_check = SlaveIdCheck(app)
        # frame type -> (handler, required request data length or LEN_ANY), as a list
        # indexed by frame type (a subscript is cheaper than a dict's get on the board)
        by_type = {
            frame.GET_SLAVE_INFO: (self.slave_info, 0),
            frame.SAVE_ALL_PARAMETERS: (self.save_all, 0),
            frame.GET_ROM_PARAMETER: (self.get_rom_param, 1),
            frame.SET_PARAMETER: (self.set_param, 5),
            frame.GET_PARAMETER: (self.get_param, 1),
            frame.SET_IO_OUTPUT: (self.set_io_output, 8),
            frame.GET_IO_INPUT: (self.get_io_input, 0),
            frame.GET_IO_OUTPUT: (self.get_io_output, 0),
            frame.GET_AXIS_STATUS: (self.no_axis, 0),
            frame.GET_ALL_STATUS: (self.no_axis, 0),
            frame.GET_COMMAND_POS: (self.no_axis, 0),
            diag.READ_COUNTERS: (self.read_counters, 0),
            diag.RESET_COUNTERS: (self.reset_counters, 0),
            diag.START_BUS_SCAN: (self.start_scan, 0),
            diag.GET_BUS_SCAN_RESULT: (self.scan_result, 0),
            diag.READ_CRASH_LOG: (self.crash_log, 0),
            # (jig.trace checks their lengths: each has a longer form for a set of drives)
            diag.START_TRACE: (self.trace_start, LEN_ANY),
            diag.STOP_TRACE: (self.trace_stop, LEN_ANY),
            diag.READ_TRACE: (self.trace_read, LEN_ANY),
            diag.GET_TRACE_STATUS: (self.trace_status, LEN_ANY),
            diag.READ_TRANSACTION_TIMES: (self.transaction_times, 0),
            diag.READ_CAN_COUNTERS: (self.read_can_counters, 0),
            diag.TAKE_SAFETY_NOTICE: (self.take_safety_notice, 0),
        }
        self.table = [None] * 256
        for ftype, entry in by_type.items():
            self.table[ftype] = entry
        # Reply data lengths (status included) of the no-axis answers.
        self.no_axis_len = bytearray(256)
        self.no_axis_len[frame.GET_AXIS_STATUS] = 1 + 4
        self.no_axis_len[frame.GET_ALL_STATUS] = 1 + 32
        self.no_axis_len[frame.GET_COMMAND_POS] = 1 + 4

    def handle(self, p, out):
        """Reply data (status first) for request p into out; returns its length, or
        DEFERRED when the reply is sent later (a jig_slave_id check is under way)."""
        # (read from the parser's state array: its properties are calls)
        st = p.st
        body = p.body
        head = st[S_HEAD]
        n = st[S_N] - 2 - head  # data length
        entry = self.table[body[head - 1]]
        if entry is None or n < 0:  # n < 0: a Ver6 frame read as Ver8 (type = a CRC byte)
            out[0] = frame.STATUS_FRAME_TYPE_ERROR
            return 1
        fn, need = entry
        if need != LEN_ANY and n != need:
            out[0] = frame.STATUS_FRAME_ERROR
            return 1
        return fn(p, body, head, out)

    def _long(self, p, o, out, n):
        """The end of a handler whose reply can be long (more than PACED_MIN data bytes):
        while the sampler runs or its request is out, the reply goes in pieces with the
        driver bus read between them (returns DEFERRED: it has gone), else whole (n).
        (Here, not in ``handle``: the other local frames pay nothing for it.)"""
        if n > PACED_MIN:
            ts = self.app.trace.ts
            if ts[0] or ts[_T_WAITING]:  # (T_ON) the sampler runs, or its request is out
                return self.app.trace.reply(p, o, out, n)
        return n

    def after_reply(self, p):
        """Run changes that must wait until the reply has gone (new slave id etc.)."""
        if self.pending_change >= 0:
            self.pending_change = -1
            self.app.apply_params()

    def slave_info(self, p, d, o, out):
        n = len(self.info)
        mem.copy(out, 0, self.info, 0, n)
        return n

    def no_axis(self, p, d, o, out):
        n = self.no_axis_len[d[o - 1]]  # by frame type
        for i in range(n):
            out[i] = 0
        return n

    # --- parameters ------------------------------------------------------------
    def get_param(self, p, d, o, out):
        return self._param_reply(d[o], False, out)

    def get_rom_param(self, p, d, o, out):
        return self._param_reply(d[o], True, out)

    def _param_reply(self, num, rom, out):
        if num >= P.COUNT:
            out[0] = frame.STATUS_DATA_ERROR
            return 1
        params = self.app.params
        out[0] = frame.STATUS_OK
        put_u32(out, 1, params.get_rom(num) if rom else params.get(num))
        return 5

    def set_param(self, p, d, o, out):
        num = d[o]
        if num == P.P_SLAVE_ID:
            return self._set_slave_id(p, frame.get_i32(d, o + 1), out)
        if num >= P.COUNT or not self.app.params.set(num, frame.get_i32(d, o + 1)):
            out[0] = frame.STATUS_DATA_ERROR
            return 1
        if P.TABLE[num][6] == P.IMMEDIATE:
            self.pending_change = num
        out[0] = frame.STATUS_OK
        return 1

    def _set_slave_id(self, p, new_id, out):
        app = self.app
        out[0] = frame.STATUS_DATA_ERROR
        if not P.valid(P.P_SLAVE_ID, new_id):
            return 1
        if new_id != app.params.ram[P.P_SLAVE_ID]:
            bit = 1 << new_id
            if (app.bridge.seen() | app.scanner.found) & bit or self.id_check.busy:
                return 1  # a driver answers there (or a check is still running)
            if not self.id_check.start(p, new_id):
                return 1  # the jig's own request is out: cannot check now
            return DEFERRED
        out[0] = frame.STATUS_OK
        return 1

    def save_all(self, p, d, o, out):
        if self.app.save_params():
            out[0] = frame.STATUS_OK
        else:
            out[0] = frame.STATUS_ROM_ACCESS_ERROR
        return 1

    # --- jig I/O -----------------------------------------------------------------
    def set_io_output(self, p, d, o, out):
        hal = self.app.hal
        cur = hal.get_outputs() & 0xFFFF
        cur = (cur | get_u16(d, o)) & ~get_u16(d, o + 4) & 0xFFFF
        hal.set_outputs(cur)
        out[0] = frame.STATUS_OK
        return 1

    def get_io_output(self, p, d, o, out):
        out[0] = frame.STATUS_OK
        put_u16(out, 1, self.app.hal.get_outputs() & 0xFFFF)
        put_u16(out, 3, 0)
        return 5

    def get_io_input(self, p, d, o, out):
        out[0] = frame.STATUS_OK
        put_u16(out, 1, self.app.hal.get_inputs() & 0xFFFF)
        put_u16(out, 3, 0)
        return 5

    # --- diagnostics -------------------------------------------------------------
    def read_counters(self, p, d, o, out):
        vals = self.app.counter_values(self.counter_values)
        n = len(vals)
        out[0] = frame.STATUS_OK
        out[1] = n
        for i in range(n):
            put_u32(out, 2 + 4 * i, vals[i] & 0x3FFFFFFF)
        return self._long(p, o, out, 2 + 4 * n)

    def read_can_counters(self, p, d, o, out):
        can = self.app.can
        out[0] = frame.STATUS_OK
        if can is None:  # a HAL without CAN: no figures
            out[1] = 0
            return 2
        vals = can.counter_values(self.can_values)
        n = len(vals)
        out[1] = n
        for i in range(n):
            put_u32(out, 2 + 4 * i, vals[i] & 0x3FFFFFFF)
        return self._long(p, o, out, 2 + 4 * n)

    def take_safety_notice(self, p, d, o, out):
        out[0] = frame.STATUS_OK
        n = self.app.lease.take_notice(self.app.hal.ticks_us(), out, 1)
        return 1 + n

    def reset_counters(self, p, d, o, out):
        self.app.reset_counters()
        out[0] = frame.STATUS_OK
        return 1

    def start_scan(self, p, d, o, out):
        self.app.scanner.start()
        out[0] = frame.STATUS_OK
        return 1

    def scan_result(self, p, d, o, out):
        return self.app.scanner.result_into(out)

    # --- the jig's own sampler (jig.trace) -------------------------------------------
    def trace_start(self, p, d, o, out):
        return self.app.trace.start(p, d, o, out)

    def trace_stop(self, p, d, o, out):
        return self.app.trace.stop(p, d, o, out)

    def trace_read(self, p, d, o, out):
        return self.app.trace.read(p, d, o, out)  # sends its reply itself: DEFERRED

    def trace_status(self, p, d, o, out):
        return self.app.trace.status(p, d, o, out)

    def transaction_times(self, p, d, o, out):
        return self._long(p, o, out, self.app.bridge.transaction_times_into(out))

    def crash_log(self, p, d, o, out):
        # Allocates (the HAL's string, its encoding): fine for a frame a person sends
        # now and then; the bridging steady state never comes here.
        text = b""
        fn = getattr(self.app.hal, "crash_summary", None)
        if fn is not None:
            try:
                text = fn() or b""
                if isinstance(text, str):
                    text = text.encode()
            except Exception:  # an unreadable log reads as none
                text = b""
        n = len(text)
        if n > diag.CRASH_TEXT_MAX:
            n = diag.CRASH_TEXT_MAX
        out[0] = frame.STATUS_OK
        for i in range(n):
            c = text[i]
            out[1 + i] = c if 0x20 <= c <= 0x7E else 0x3F  # printable ASCII only, else '?'
        out[1 + n] = 0
        return self._long(p, o, out, n + 2)
