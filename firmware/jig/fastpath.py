"""The main loop's cut-through hot path as machine code (viper): ``pump``.

``App.run`` hands its passes to ``pump`` where the port has a native emitter (the
board), the jig forwards cut-through and both RS-485 ports are plain (software
DE, /RE tied to DE, a write that returns after the last stop bit: ``Rs485.plain``).
The pieces of a frame passed on are queued for the port's transmitter (the
USART's FIFO on the board) and drained before DE drops, so the CPU goes on with
the next bytes while they go out.
One pass does what ``App.run``'s own pass does -- bytes waiting on the driver bus,
then on the PC bus, through the parser into the bridge -- but the frame events of
a forwarded transaction are acted on here, in machine code, on the bridge's state
array ``Bridge.bs``:

* a PC frame starts out on the driver bus at its first byte (the AA that can start
  a header goes on at once, the CC when it is in), routes at its id (to a driver,
  a broadcast, or the tail stub when it is for the jig), and its end starts the
  reply wait;
* a driver frame starts out to the PC the same way while a reply is awaited,
  matches (or is cut short) at its first two body bytes, and its end is the reply.

Every other event -- a local frame, a drop, a reply to the jig's own request, a
relay the PC talks over, anything in state AWAIT_INT -- goes to the bridge's own
``pc_event``/``down_event`` (Python), which share the state array, so the two
never disagree about where the bridge is. The portable twin of this module is
``Bridge.up_bytes``/``down_bytes`` with those methods: the WebAssembly VM and
store-and-forward run them, and the host tests run both and compare
(``host_tests/test_fastpath.py``). ``pump`` returns when its passes are used up,
the slow pass is due (``due[0]``) or, while the CAN port is open (``due[2]`` = 1),
the port's own pass (``due[1]``) with something to do, which ``App.run`` then
runs (with nothing to do -- its ring, FIFO and answers empty (``due[3]`` = 0), no
byte from the host -- the pump only moves ``due[1]`` a period on, as ``App.run``
would). The port's pass comes in the bridge's idle time: from an idle pass with no
transaction in flight, or once it has waited ``canport.CAN_DEFER_US`` past its due
tick (``App.run``'s rule too, ``App.bridge_idle``).

What a byte costs is mostly calls (a viper call with its pointer casts costs more
than the parser's work on a byte), so the per-byte work has none of its own: the
parser's machine runs inline (``jig.native.scan``'s source, on the parser's own
state array and table: one machine, the host tests run both on the same traffic),
and the raw bytes of a frame passed on go straight into the transmit FIFO's
register (``UartPort.queue``'s loop, inline) where the port has one
(``UartPort.regs``); elsewhere through ``Rs485.raw_part``. What is left per byte
are the UART's own calls (``any`` on both ports, ``readinto``) and a tick.

Under CPython the same source runs as plain Python through ``jig.compat``'s shims
(for those tests). The constants mirror ``jig.bridge``, ``jig.parser``, ``jig.native``,
``jig.uartport``, ``jig.counters`` and ``jig.params`` (viper folds only its own module's constants);
a host test checks they agree.
"""

from array import array

try:
    import micropython
except ImportError:  # CPython: run the source as plain Python
    from jig.compat import micropython_shim as micropython
from jig.compat import NATIVE, const, ptr8, ptr16, ptr32  # noqa: F401 (casts under viper)

_RX_CHUNK = const(256)  # app.RX_CHUNK
# jig.canport: its own pass's period, its ring's (CanPort.rs) and FIFO's (CanPort.ts) indices
_CAN_POLL_US = const(100)
_CAN_DEFER_US = const(1000)  # ... and how long it waits for the bridge's idle time at most
_RS_HEAD = const(0)
_RS_TAIL = const(1)
_TS_HEAD = const(0)
_TS_TAIL = const(1)
_TS_DONE = const(2)
_TS_REC = const(3)
_TS_BUSY = const(4)
_MASK = const(0x3FFFFFFF)
_HALF = const(0x20000000)
_STUFF = const(0xAA)
_CC = const(0xCC)
_BROADCAST_ID = const(99)
# jig.parser (its machine runs inline here: jig.native.scan's source, the same table)
_EV_FRAME = const(1)
_EV_HEAD = const(2)
_EV_DROP = const(3)
_EV_START = const(4)
_S_STATE = const(0)
_S_N = const(1)
_S_EVENT = const(2)
_S_T_LAST = const(3)
_S_TIMEOUT = const(4)
_S_BYTE_US = const(5)
_S_LIMIT = const(6)
_S_MIN_LEN = const(7)
_S_HEAD_AT = const(8)
_S_STOP_DROP = const(9)
_S_GOOD = const(12)
_S_NOISE = const(13)
_S_STUFF_ERRORS = const(14)
_S_CRC_ERRORS = const(15)
_S_SHORT = const(16)
_S_OVERLONG = const(17)
_S_TIMEOUTS = const(18)
_S_RESYNCS = const(19)
_S_WHY = const(20)
_S_START_EV = const(21)
_S_DROP_N = const(22)
_HUNT = const(0)
_HEADER = const(1)
_A_NOISE = const(1)
_A_NOISE2 = const(2)
_A_START = const(3)
_A_STORE = const(4)
_A_LITERAL = const(5)
_A_RESYNC = const(6)
_A_END = const(7)
_A_STUFF_ERROR = const(8)
_CRC_AT = const(512)  # jig.native: the CRC table's first u16 in parser.TABLES
# jig.uartport: the USART's transmit FIFO
_ISR_TXFNF = const(1 << 7)
_ISR_BUSY = const(1 << 16)  # jig.bridge.ISR_BUSY: a byte is being received
_ARM_BYTES = const(2)  # jig.bridge.ARM_BYTES
_TDR = const(3)  # USART_TDR_WORDS_AFTER_ISR
_TX_FIFO_SPINS = const(1 << 20)
# jig.bridge
_IDLE = const(0)
_AWAIT_PC = const(1)
_AWAIT_INT = const(2)
_E_PC_LOCAL = const(0)
_E_PC_FORWARD = const(1)
_E_PC_BROADCAST = const(2)
_E_REPLY = const(4)
_N_EVENTS = const(8)
_F_ABORT = const(1)
_B_STATE = const(0)
_B_FWD = const(1)
_B_ROUTED = const(2)
_B_REL = const(3)
_B_CHECKED = const(4)
_B_P_B0 = const(5)
_B_P_B1 = const(6)
_B_DEADLINE = const(7)
_B_T_PC = const(8)
_B_PC_FRAMES = const(9)
_B_SEEN = const(10)
_B_WAKE = const(11)
_B_XHEAD = const(12)
_B_XCUR = const(13)
_B_T_SLOW = const(14)
_SLOW_AHEAD_US = const(3000)
_XT_N = const(16)
_SEEN_IDS = const(30)
# jig.counters
_C_UP_IN = const(0)
_C_UP_OUT = const(1)
_C_DOWN_IN = const(2)
_C_DOWN_OUT = const(3)
_C_FORWARDS = const(6)
_C_BROADCASTS = const(7)
_C_REPLIES = const(8)
_C_ABORTS = const(10)
_C_LOCAL = const(4)
_C_LOCAL_ERRORS = const(5)
_C_TA_COUNT = const(22)
_C_TA_MIN = const(23)
_C_TA_MAX = const(25)
_TA_SUM = const(32)
_TA_BASE = const(33)
# jig.frame
_STATUS_FRAME_TYPE_ERROR = const(0x80)
_STATUS_DATA_ERROR = const(0x81)
_STATUS_FRAME_ERROR = const(0x82)
# jig.params
_P_SLAVE_ID = const(0)
_P_REPLY_TIMEOUT_MS = const(3)
_P_INTERBYTE_US = const(4)
_P_DE_PRE_US = const(6)
_P_DE_POST_US = const(7)
# jig.capture
_CS_ON = const(0)
_CS_START = const(8)
_CH_PC_IN = const(0)
_CH_PC_OUT = const(1)
_CH_DRV_IN = const(2)
_CH_DRV_OUT = const(3)
_CS_T_IN = const(14)
_CS_HEAD = const(1)
_CS_TAIL = const(2)
_CS_NEXT = const(15)
_T_PC_PASSED = const(4)
_T_DRV_PASSED = const(6)
_STUB = const(3 << 8)  # V_SHORT << 8: the verdict of a stub ended with a tail


_NO_REGS = array("i", [0, 0, 0, 0])  # (a register block for a port without one: never written)
_NO_ISR = array("i", [0])  # (an ISR for a port without one: never BUSY; never written)


def _fifo(rs):
    """(1, the port's ISR..TDR register block) where the pump may fill the port's
    transmit FIFO itself (a queueing port with registers: ``UartPort.regs`` on the
    board), else (0, a dummy): the pieces then go through ``Rs485.raw_part``."""
    regs = getattr(rs.port, "regs", None)
    if not rs.queued or regs is None:
        return 0, _NO_REGS
    return 1, regs


def _line_isr(rs):
    """The port's USART ISR where the pump may watch its line for a start bit
    (``Bridge.watch_lines``): a plain port's ``isr`` (an address on the board, a
    word-indexed object in the simulation), else a block of zeros (never BUSY)."""
    isr = getattr(rs.port, "isr", None)
    if not rs.plain or isr is None or (isinstance(isr, int) and not NATIVE):
        return _NO_ISR
    return isr


def context(app):
    """What ``pump`` works with, bound once (a tuple: pump unpacks it at each call)."""
    b = app.bridge
    up = app.hal.up
    down = app.hal.down
    from jig.bridge import FLAT_FLAGS, FLAT_NEXT, TIMEOUT_MULTIPLIER
    from jig.parser import TABLES
    from jig import crc
    from jig.compat import native_source

    enc = native_source()  # jig.native: put_body and stuff (as Python on CPython)
    up_fifo, up_regs = _fifo(app.up)
    down_fifo, down_regs = _fifo(app.down)
    up_isr = _line_isr(app.up)
    down_isr = _line_isr(app.down)
    # the CAN port's queues and its host port's any (looked at only while it is open: due[2])
    can_rs = can_ts = _NO_REGS
    can_any = up.any
    if app.can is not None:
        can_rs = app.can.rs
        can_ts = app.can.ts
        if app._can_any is not None:
            can_any = app._can_any

    return (up.any, up.readinto, up.de, up.write, app.up.raw_part, app.up.drain, app.up.early,
            down.any, down.readinto, down.de, app.down.raw_part, app.down.drain, app.down.early,
            app.hal.ticks_us, app.hal.sleep_us,
            app.up_parser, app.up_parser.st, app.up_rx, app.up_parser.body,
            app.down_parser, app.down_parser.st, app.down_rx, app.down_parser.body,
            TABLES, b.pc_event, b.down_event, b.bs, app.counters.v, app.due, app.params.ram, b.hdr, b.tail,
            TIMEOUT_MULTIPLIER, FLAT_NEXT, FLAT_FLAGS,
            app.handlers.handle, app.handlers, app.handlers.after_reply, b.reply, b.body, b.txbuf, b.head, enc.put_body, enc.stuff,
            crc.TABLE, app.capture.cs, app.capture.ring, app.capture.put, b.xt, up_fifo, up_regs, down_fifo, down_regs,
            can_rs, can_ts, can_any, up_isr, down_isr)


@micropython.viper
def pump(ctx, passes: int) -> int:
    """Run passes passes of the main loop (< 0: until the slow pass is due); return
    the passes left (0, or what was left when the slow pass fell due)."""
    (up_any, up_read, up_de, up_write, up_queue, up_drain, up_early, down_any, down_read, down_de,
     down_queue, down_drain, down_early, ticks, sleep,
     up_parser, up_st, up_rx, up_body, down_parser, down_st, down_rx, down_body,
     tables, pc_event, down_event, bs_arr, v_arr, due_arr, ram, hdr_buf, tail, tmult_buf, next_buf,
     flags_buf, handle, handlers, after_reply, reply_buf, reply_body, txbuf, head_obj, put_body, stuff,
     crc_table, cs_arr, cap_ring, cap_put, xt_arr, up_fifo, up_regs, down_fifo, down_regs,
     can_rs, can_ts, can_any, up_isr, down_isr) = ctx
    head = int(head_obj)
    reply = ptr8(reply_buf)
    ust = ptr32(up_st)
    ub = ptr8(up_body)
    urx = ptr8(up_rx)
    dst = ptr32(down_st)
    db = ptr8(down_body)
    drx = ptr8(down_rx)
    step = ptr8(tables)  # the parser's transition table ...
    crct = ptr16(tables)  # ... and its CRC table
    bs = ptr32(bs_arr)
    v = ptr32(v_arr)
    due = ptr32(due_arr)
    hdr = ptr8(hdr_buf)
    tmult = ptr8(tmult_buf)
    nxt = ptr8(next_buf)
    flg = ptr16(flags_buf)
    uearly = ptr32(up_early)  # Rs485.early: tick DE went up and the AA went ahead of a frame, -1: not
    dearly = ptr32(down_early)
    cs = ptr32(cs_arr)  # jig.capture's state: recording on, where each frame began
    xt = ptr32(xt_arr)  # Bridge.xt: the last forwarded requests' times
    uq = int(up_fifo)  # 1: the pump fills the port's transmit FIFO itself (ureg: its ISR..TDR)
    ureg = ptr32(up_regs)
    dq = int(down_fifo)
    dreg = ptr32(down_regs)
    crs = ptr32(can_rs)
    cts = ptr32(can_ts)
    # the lines' USART ISRs (Bridge.watch_lines; without them a block of zeros: never BUSY)
    uisr = ptr32(up_isr)
    disr = ptr32(down_isr)
    while passes != 0:
        if passes > 0:
            passes -= 1
        # side 0: the driver bus first (a reply already in goes before a new PC request);
        # side 1: the PC bus. Each side: read what is waiting, run it through the parser's
        # machine (inline below), pass the raw bytes of a frame being cut through on to the
        # other bus, act on the frame events.
        side = 0
        avail = int(down_any())
        if avail == 0:
            avail = int(up_any())
            if avail == 0:  # an idle pass
                t = int(ticks())
                # Bridge.watch_lines: an armed bus whose byte never came is let go ...
                if (dearly[1] & uearly[1]) >= 0:  # (either is >= 0: one test while neither is)
                    if dearly[1] >= 0 and ((t - dearly[1]) & _MASK) > _ARM_BYTES * ust[_S_BYTE_US]:
                        dearly[1] = -1  # Rs485.disarm
                        down_de(0)
                    if uearly[1] >= 0 and ((t - uearly[1]) & _MASK) > _ARM_BYTES * dst[_S_BYTE_US]:
                        uearly[1] = -1
                        up_de(0)
                # ... and a frame's first byte starting takes the other bus now (DE up), so
                # the pre-delay runs while the byte arrives
                if ((uisr[0] | disr[0]) & _ISR_BUSY) != 0 and bs[_B_FWD] == 0 and bs[_B_REL] == 0:
                    state = bs[_B_STATE]
                    if state == _IDLE:
                        if ((uisr[0] & _ISR_BUSY) != 0 and ust[_S_STATE] == _HUNT and dearly[0] < 0
                                and dearly[1] < 0 and ((t - ust[_S_T_LAST]) & _MASK) > ust[_S_BYTE_US]):
                            down_de(1)  # Rs485.arm
                            dearly[1] = t
                    elif state == _AWAIT_PC:
                        # (the PC bus is blind while armed: only while the PC is quiet)
                        if ((disr[0] & _ISR_BUSY) != 0 and (uisr[0] & _ISR_BUSY) == 0
                                and dst[_S_STATE] == _HUNT and ((t - dst[_S_T_LAST]) & _MASK) > dst[_S_BYTE_US]
                                and ust[_S_STATE] == _HUNT and ((t - ust[_S_T_LAST]) & _MASK) > ust[_S_BYTE_US]
                                and uearly[0] < 0 and uearly[1] < 0):
                            up_de(1)
                            uearly[1] = t
                if ((t - due[0]) & _MASK) < _HALF:
                    return passes
                if due[2] != 0 and ((t - due[1]) & _MASK) < _HALF:
                    # the CAN port's own pass (open: due[2] = 1): App.run's when something waits
                    # (its ring, its FIFO, answers: due[3], the host's bytes) ...
                    if (due[3] != 0 or crs[_RS_TAIL] != crs[_RS_HEAD] or cts[_TS_REC] != cts[_TS_DONE]
                            or (cts[_TS_BUSY] == 0 and cts[_TS_TAIL] != cts[_TS_HEAD]) or int(can_any()) != 0):
                        # ... in the bridge's idle time: not while a transaction is in flight (a
                        # reply awaited, a frame coming in or passed on, a start bit on either
                        # line) unless it has waited CAN_DEFER_US (due[1] stays put meanwhile)
                        if ((bs[_B_STATE] | bs[_B_FWD] | bs[_B_REL]) == 0 and ust[_S_STATE] == _HUNT
                                and dst[_S_STATE] == _HUNT and ((uisr[0] | disr[0]) & _ISR_BUSY) == 0) or (
                                ((t - due[1]) & _MASK) >= _CAN_DEFER_US):
                            due[4] = 1  # (App._run_pump: serve now)
                            return passes
                    else:
                        # ... else only the next one a period on, on its grid (as App.run)
                        t1 = (due[1] + _CAN_POLL_US) & _MASK
                        d = (t1 - t) & _MASK
                        if d == 0 or d >= _HALF:
                            t1 = (t + _CAN_POLL_US) & _MASK
                        due[1] = t1
                continue
            side = 1
        while avail != 0:
            n = avail if avail < _RX_CHUNK else _RX_CHUNK
            if side == 0:
                n = int(down_read(down_rx, n))
                sp = dst
                bp = db
                rx = drx
                oq = uq  # (a reply relayed goes to the PC bus)
                oreg = ureg
            else:
                n = int(up_read(up_rx, n))
                sp = ust
                bp = ub
                rx = urx
                oq = dq  # (a request cut through goes to the driver bus)
                oreg = dreg
            now = int(ticks())
            i = 0
            while i < n:
                # --- jig.native.scan(st, rx, i, n, body, TABLES, now), inline: the same
                # machine on the same state (S_*), up to the next event or the end of rx
                ev = 0
                ps = sp[_S_STATE]
                nb = sp[_S_N]
                j = i
                if ps != _HUNT:
                    t = now
                    count = n - i
                    if sp[_S_BYTE_US] != 0 and count > 1:
                        t = (now - (count - 1) * sp[_S_BYTE_US]) & _MASK
                    if ((t - sp[_S_T_LAST] + _HALF) & _MASK) - _HALF > sp[_S_TIMEOUT]:
                        if ps == _HEADER:
                            sp[_S_NOISE] += 1
                        else:
                            sp[_S_TIMEOUTS] += 1
                            if sp[_S_STOP_DROP] != 0:
                                ev = _EV_DROP
                                sp[_S_WHY] = 0
                                sp[_S_DROP_N] = nb
                        ps = _HUNT
                        sp[_S_STATE] = _HUNT
                if ev != 0:
                    sp[_S_EVENT] = ev
                else:
                    sp[_S_T_LAST] = now
                    limit = sp[_S_LIMIT]
                    head_at = sp[_S_HEAD_AT]
                    stop_drop = sp[_S_STOP_DROP]
                    start_ev = sp[_S_START_EV]
                    while j < n:
                        c = rx[j]
                        j += 1
                        code = step[(ps << 8) | c]
                        ps = code & 3
                        a = code >> 2
                        if a == _A_STORE or a == _A_LITERAL:
                            if nb >= limit:
                                sp[_S_OVERLONG] += 1
                                nb = 0
                                ps = _HUNT
                                if stop_drop != 0:
                                    ev = _EV_DROP
                                    sp[_S_WHY] = _A_STORE
                                    sp[_S_DROP_N] = limit
                                    break
                            else:
                                bp[nb] = c
                                nb += 1
                                if nb == head_at:
                                    ev = _EV_HEAD
                                    break
                        elif a == _A_START:
                            nb = 0
                            if start_ev != 0:
                                ev = _EV_START
                                break
                        elif a == _A_END:
                            if nb < sp[_S_MIN_LEN]:
                                sp[_S_SHORT] += 1
                            else:
                                crc = 0xFFFF
                                k = 0
                                while k < nb:
                                    crc = (crc >> 8) ^ crct[_CRC_AT + ((crc ^ bp[k]) & 0xFF)]
                                    k += 1
                                if crc != 0:
                                    sp[_S_CRC_ERRORS] += 1
                                else:
                                    sp[_S_GOOD] += 1
                                    ev = _EV_FRAME
                                    break
                            if stop_drop != 0:
                                ev = _EV_DROP
                                sp[_S_WHY] = _A_END
                                sp[_S_DROP_N] = nb
                                break
                        elif a == _A_NOISE:
                            sp[_S_NOISE] += 1
                        elif a == _A_NOISE2:
                            sp[_S_NOISE] += 2
                        elif a == _A_RESYNC:
                            sp[_S_RESYNCS] += 1
                            if stop_drop != 0:
                                ev = _EV_DROP
                                sp[_S_WHY] = _A_RESYNC
                                sp[_S_DROP_N] = nb
                                nb = 0
                                break
                            nb = 0
                        elif a == _A_STUFF_ERROR:
                            sp[_S_STUFF_ERRORS] += 1
                            if stop_drop != 0:
                                ev = _EV_DROP
                                sp[_S_WHY] = _A_STUFF_ERROR
                                sp[_S_DROP_N] = nb
                                break
                    sp[_S_STATE] = ps
                    sp[_S_N] = nb
                    sp[_S_EVENT] = ev
                # --- the raw bytes just parsed, of a frame being passed on to the other bus
                if j > i:
                    if side == 0:
                        fw = bs[_B_REL]
                    else:
                        fw = bs[_B_FWD]
                    if fw != 0:
                        if oq != 0:
                            # UartPort.queue, inline: into the transmit FIFO, waiting while it is full
                            k = i
                            while k < j:
                                spins = 0
                                while (oreg[0] & _ISR_TXFNF) == 0 and spins <= _TX_FIFO_SPINS:
                                    spins += 1
                                if spins > _TX_FIFO_SPINS:
                                    break  # the transmitter stopped
                                oreg[_TDR] = rx[k]
                                k += 1
                        elif side == 0:
                            up_queue(down_rx, i, j - i)
                        else:
                            down_queue(up_rx, i, j - i)
                i = j
                if ev == 0:
                    continue
                state = bs[_B_STATE]
                if side == 0:
                    if ev == _EV_START:
                        # Bridge._down_start: to the PC at once while its reply is awaited
                        cs[_CS_START + _CH_DRV_IN] = now
                        if state == _AWAIT_PC and bs[_B_FWD] == 0:
                            # Rs485.begin (taken early: the AA has gone and was stamped, the CC follows)
                            if uearly[0] >= 0:
                                uearly[0] = -1
                                if uq != 0 and (ureg[0] & _ISR_TXFNF) != 0:
                                    ureg[_TDR] = _CC  # (into the FIFO behind the AA: room for it)
                                else:
                                    up_queue(hdr_buf, 1, 1)
                            else:
                                cs[_CS_START + _CH_PC_OUT] = now
                                if uearly[1] >= 0:  # Rs485._take: armed (watch_lines), DE up since then (+ 1: whole µs)
                                    wait = int(ram[_P_DE_PRE_US])
                                    if wait > 0:
                                        wait = wait + 1 - ((((int(ticks()) - uearly[1]) & _MASK) + _HALF) & _MASK) + _HALF
                                    uearly[1] = -1
                                else:
                                    up_de(1)
                                    wait = int(ram[_P_DE_PRE_US])
                                if wait > 0:
                                    sleep(wait)
                                up_queue(hdr_buf, 0, 2)
                            bs[_B_REL] = 1
                            bs[_B_CHECKED] = 0
                            t = (now + int(ram[_P_INTERBYTE_US]) + 1) & _MASK
                            if ((t - due[0]) & _MASK) >= _HALF:
                                due[0] = t
                    elif ev == _EV_HEAD:
                        # Bridge._down_head: relay a match, cut short a frame that is not one
                        relaying = bs[_B_REL]
                        if relaying == 0 and (state != _AWAIT_PC or bs[_B_FWD] != 0):
                            continue
                        b0 = db[0]
                        b1 = db[1]
                        if b0 != bs[_B_P_B0] or b1 != bs[_B_P_B1]:
                            if relaying != 0:
                                up_queue(tail, 0, 2)
                                bs[_B_REL] = 0
                                up_drain()
                                post = int(ram[_P_DE_POST_US])
                                if post != 0:
                                    sleep(post)
                                up_de(0)
                                if cs[_CS_ON] != 0:
                                    cap_put(cs_arr, cap_ring, _CH_PC_OUT | _STUB, down_body, 2, ticks())
                        elif relaying != 0:
                            bs[_B_CHECKED] = 1
                        else:
                            hdr[2] = b0
                            hdr[3] = b1
                            k = 4
                            if b1 == _STUFF:
                                hdr[4] = b1
                                k = 5
                            if uearly[0] >= 0:
                                uearly[0] = -1
                                up_queue(hdr_buf, 1, k - 1)
                            else:
                                cs[_CS_START + _CH_PC_OUT] = now
                                if uearly[1] >= 0:  # Rs485._take: armed (watch_lines), DE up since then (+ 1: whole µs)
                                    wait = int(ram[_P_DE_PRE_US])
                                    if wait > 0:
                                        wait = wait + 1 - ((((int(ticks()) - uearly[1]) & _MASK) + _HALF) & _MASK) + _HALF
                                    uearly[1] = -1
                                else:
                                    up_de(1)
                                    wait = int(ram[_P_DE_PRE_US])
                                if wait > 0:
                                    sleep(wait)
                                up_queue(hdr_buf, 0, k)
                            bs[_B_REL] = 1
                            bs[_B_CHECKED] = 1
                            t = (now + int(ram[_P_INTERBYTE_US]) + 1) & _MASK
                            if ((t - due[0]) & _MASK) >= _HALF:
                                due[0] = t
                    elif ev == _EV_FRAME and bs[_B_REL] != 0:
                        # Bridge.on_down_frame: the reply, relayed as it came
                        v[_C_DOWN_IN] += 1
                        bs[_B_REL] = 0
                        up_drain()
                        post = int(ram[_P_DE_POST_US])
                        if post != 0:
                            sleep(post)
                        up_de(0)
                        if cs[_CS_ON] != 0:
                            cs[_CS_T_IN] = now
                            cap_put(cs_arr, cap_ring, _T_DRV_PASSED, down_body, dst[_S_N], ticks())
                        bs[_B_STATE] = nxt[state * _N_EVENTS + _E_REPLY]
                        b0 = db[0]
                        if b0 < _SEEN_IDS:
                            bs[_B_SEEN] |= 1 << b0
                        v[_C_REPLIES] += 1
                        v[_C_UP_OUT] += 1
                        k = bs[_B_XCUR]  # Bridge._xt_reply
                        if k >= 0:
                            xt[4 * k + 3] = now
                            bs[_B_XCUR] = -1
                        if bs[_B_WAKE] != 0:
                            due[0] = now  # the driver bus is free (jig.trace waits for it)
                    else:
                        down_event(down_parser, ev, now)
                else:
                    if ev == _EV_START and bs[_B_REL] == 0 and state != _AWAIT_INT:
                        # Bridge._pc_start: on to the driver bus from the header
                        cs[_CS_START + _CH_PC_IN] = now
                        if uearly[1] >= 0:
                            uearly[1] = -1  # Rs485.disarm: the PC talks
                            up_de(0)
                        if dearly[0] >= 0:
                            dearly[0] = -1
                            if dq != 0 and (dreg[0] & _ISR_TXFNF) != 0:
                                dreg[_TDR] = _CC
                            else:
                                down_queue(hdr_buf, 1, 1)
                        else:
                            cs[_CS_START + _CH_DRV_OUT] = now
                            if dearly[1] >= 0:  # Rs485._take: armed (watch_lines), DE up since then (+ 1: whole µs)
                                wait = int(ram[_P_DE_PRE_US])
                                if wait > 0:
                                    wait = wait + 1 - ((((int(ticks()) - dearly[1]) & _MASK) + _HALF) & _MASK) + _HALF
                                dearly[1] = -1
                            else:
                                down_de(1)
                                wait = int(ram[_P_DE_PRE_US])
                            if wait > 0:
                                sleep(wait)
                            down_queue(hdr_buf, 0, 2)
                        bs[_B_FWD] = 1
                        bs[_B_ROUTED] = 0
                        t = (now + int(ram[_P_INTERBYTE_US]) + 1) & _MASK
                        if ((t - due[0]) & _MASK) >= _HALF:
                            due[0] = t
                    elif ev == _EV_HEAD and bs[_B_FWD] != 0 and bs[_B_REL] == 0 and state != _AWAIT_INT:
                        # Bridge._pc_head: route at the id
                        slave = ub[0]
                        if slave == int(ram[_P_SLAVE_ID]):
                            bs[_B_FWD] = 0
                            down_queue(tail, 0, 2)
                            down_drain()
                            post = int(ram[_P_DE_POST_US])
                            if post != 0:
                                sleep(post)
                            down_de(0)
                            if cs[_CS_ON] != 0:
                                cap_put(cs_arr, cap_ring, _CH_DRV_OUT | _STUB, up_body, 1, ticks())
                            if bs[_B_WAKE] != 0:
                                due[0] = now  # (jig.trace waits for a free driver bus)
                            continue
                        bs[_B_ROUTED] = 1
                        v[_C_DOWN_OUT] += 1
                        k = state * _N_EVENTS
                        if slave == _BROADCAST_ID:
                            k += _E_PC_BROADCAST
                            v[_C_BROADCASTS] += 1
                        else:
                            k += _E_PC_FORWARD
                            v[_C_FORWARDS] += 1
                            bs[_B_P_B1] = -1
                        bs[_B_STATE] = nxt[k]
                        if flg[k] & _F_ABORT:
                            v[_C_ABORTS] += 1  # (no client: the jig's own wait is AWAIT_INT)
                    elif ev == _EV_FRAME and bs[_B_FWD] != 0:
                        # Bridge.on_pc_frame: the tail has gone out with the raw bytes
                        v[_C_UP_IN] += 1
                        bs[_B_T_PC] = now
                        bs[_B_PC_FRAMES] += 1
                        bs[_B_FWD] = 0
                        down_drain()
                        post = int(ram[_P_DE_POST_US])
                        if post != 0:
                            sleep(post)
                        down_de(0)
                        if bs[_B_WAKE] != 0 and state != _AWAIT_PC:
                            due[0] = now  # a broadcast has gone (jig.trace waits for a free driver bus)
                        if cs[_CS_ON] != 0:
                            cs[_CS_T_IN] = now
                            cap_put(cs_arr, cap_ring, _T_PC_PASSED, up_body, ust[_S_N], ticks())
                        if state == _AWAIT_PC:
                            # Bridge._pend_pc: the reply wait starts now
                            m = tmult[ub[1]]
                            if ust[_S_N] > 2 and tmult[ub[2]] > m:
                                m = tmult[ub[2]]
                            bs[_B_P_B0] = ub[0]
                            bs[_B_P_B1] = ub[1]
                            t = int(ticks())
                            d = (t + int(ram[_P_REPLY_TIMEOUT_MS]) * m * 1000) & _MASK
                            bs[_B_DEADLINE] = d
                            if ((d - due[0]) & _MASK) >= _HALF:
                                due[0] = d
                            # Bridge._xt_request
                            k = bs[_B_XHEAD]
                            bs[_B_XHEAD] = k + 1 if k + 1 < _XT_N else 0
                            bs[_B_XCUR] = k
                            k *= 4
                            xt[k] = ub[0]
                            xt[k + 1] = ub[1]
                            xt[k + 2] = t
                            xt[k + 3] = -1
                            # as Bridge.on_pc_frame after _pend_pc: records wait, the drive is thinking:
                            # the slow pass now
                            if cs[_CS_HEAD] != cs[_CS_TAIL] and ((now - cs[_CS_NEXT]) & _MASK) < _HALF:
                                due[0] = now
                            elif ((now - bs[_B_T_SLOW] + _HALF) & _MASK) - _HALF >= _SLOW_AHEAD_US:
                                due[0] = now  # the drive thinks: the slow pass now, not inside its reply
                    elif ev == _EV_FRAME and bs[_B_FWD] == 0 and ub[0] == int(ram[_P_SLAVE_ID]):
                        # Bridge.on_pc_frame and _local: a frame for the jig, answered here
                        v[_C_UP_IN] += 1
                        bs[_B_T_PC] = now
                        bs[_B_PC_FRAMES] += 1
                        k = state * _N_EVENTS + _E_PC_LOCAL
                        bs[_B_STATE] = nxt[k]
                        if flg[k] & _F_ABORT:
                            v[_C_ABORTS] += 1  # (the PC's own wait: a local frame has no abort in AWAIT_INT)
                            if bs[_B_WAKE] != 0:
                                due[0] = now  # the driver bus is free (jig.trace waits for it)
                        v[_C_LOCAL] += 1
                        rec = cs[_CS_ON]
                        if rec != 0:
                            cap_put(cs_arr, cap_ring, _CH_PC_IN, up_body, ust[_S_N], now)
                        n_rep = int(handle(up_parser, reply_buf))  # Bridge._local (the handlers: Python)
                        if n_rep < 0:
                            continue  # answered later, through Bridge.local_reply
                        # Bridge.local_reply
                        status = reply[0]
                        if status == _STATUS_FRAME_TYPE_ERROR or status == _STATUS_DATA_ERROR or status == _STATUS_FRAME_ERROR:
                            v[_C_LOCAL_ERRORS] += 1
                        sync = -1
                        ftype = ub[1]
                        if head == 3:
                            sync = ub[1]
                            ftype = ub[2]
                        blen = int(put_body(reply_body, ub[0], sync, ftype, reply_buf, n_rep, crc_table))
                        m = int(stuff(txbuf, reply_body, blen))
                        # Rs485.send
                        t_tx = int(ticks())
                        if uearly[0] >= 0:
                            uearly[0] = -1  # (the reply's AA has gone)
                            up_write(txbuf, 1, m - 1)
                        else:
                            if uearly[1] >= 0:  # Rs485._take: armed (watch_lines), DE up since then (+ 1: whole µs)
                                wait = int(ram[_P_DE_PRE_US])
                                if wait > 0:
                                    wait = wait + 1 - ((((int(ticks()) - uearly[1]) & _MASK) + _HALF) & _MASK) + _HALF
                                uearly[1] = -1
                            else:
                                up_de(1)
                                wait = int(ram[_P_DE_PRE_US])
                            if wait > 0:
                                sleep(wait)
                            up_write(txbuf, 0, m)
                        post = int(ram[_P_DE_POST_US])
                        if post != 0:
                            sleep(post)
                        up_de(0)
                        if rec != 0:
                            cs[_CS_START + _CH_PC_OUT] = t_tx
                            cap_put(cs_arr, cap_ring, _CH_PC_OUT, reply_body, blen, ticks())
                        # Counters.turnaround(ticks_diff(t_tx, now))
                        us = ((t_tx - now + _HALF) & _MASK) - _HALF
                        if us < 0:
                            us = 0
                        k = v[_C_TA_COUNT]
                        v[_C_TA_COUNT] = k + 1
                        if k == 0 or us < v[_C_TA_MIN]:
                            v[_C_TA_MIN] = us
                        if us > v[_C_TA_MAX]:
                            v[_C_TA_MAX] = us
                        tsum = v[_TA_SUM] + us
                        if tsum > 0x3FFFFFFF:
                            tsum = us
                            v[_TA_BASE] = k
                        v[_TA_SUM] = tsum
                        v[_C_UP_OUT] += 1
                        if int(handlers.pending_change) >= 0:
                            after_reply(up_parser)  # a parameter change that waited for the reply
                    else:
                        pc_event(up_parser, ev, now)
            if side == 0:
                # Bridge._early: an AA that may start a reply's header goes on to the PC at once
                if dst[_S_STATE] == _HEADER:
                    if uearly[0] < 0 and bs[_B_STATE] == _AWAIT_PC and bs[_B_FWD] == 0 and bs[_B_REL] == 0:
                        # Rs485.raise_early
                        if uearly[1] >= 0:  # Rs485._take: armed (watch_lines), DE up since then (+ 1: whole µs)
                            uearly[0] = uearly[1]
                            wait = int(ram[_P_DE_PRE_US])
                            if wait > 0:
                                wait = wait + 1 - ((((int(ticks()) - uearly[1]) & _MASK) + _HALF) & _MASK) + _HALF
                            uearly[1] = -1
                        else:
                            uearly[0] = now
                            up_de(1)
                            wait = int(ram[_P_DE_PRE_US])
                        if wait > 0:
                            sleep(wait)
                        cs[_CS_START + _CH_PC_OUT] = int(ticks())  # (the copy's start: its AA handed over)
                        if uq != 0 and (ureg[0] & _ISR_TXFNF) != 0:
                            ureg[_TDR] = _STUFF  # (the transmitter was idle: the FIFO has room)
                        else:
                            up_queue(hdr_buf, 0, 1)
                        t = (now + int(ram[_P_INTERBYTE_US]) + 1) & _MASK
                        if ((t - due[0]) & _MASK) >= _HALF:
                            due[0] = t
                elif uearly[0] >= 0:
                    uearly[0] = -1  # Rs485.drop_early: no header followed
                    cs[_CS_START + _CH_PC_OUT] = -1
                    up_drain()
                    post = int(ram[_P_DE_POST_US])
                    if post != 0:
                        sleep(post)
                    up_de(0)
                elif uearly[1] >= 0 and dst[_S_STATE] == _HUNT:
                    uearly[1] = -1  # Rs485.disarm: the byte whose start armed it was no AA
                    up_de(0)
            else:
                # Bridge._early: an AA that may start a PC header goes on to the driver bus at once
                if ust[_S_STATE] == _HEADER:
                    if dearly[0] < 0 and bs[_B_STATE] == _IDLE and bs[_B_FWD] == 0 and bs[_B_REL] == 0:
                        # Rs485.raise_early
                        if dearly[1] >= 0:  # Rs485._take: armed (watch_lines), DE up since then (+ 1: whole µs)
                            dearly[0] = dearly[1]
                            wait = int(ram[_P_DE_PRE_US])
                            if wait > 0:
                                wait = wait + 1 - ((((int(ticks()) - dearly[1]) & _MASK) + _HALF) & _MASK) + _HALF
                            dearly[1] = -1
                        else:
                            dearly[0] = now
                            down_de(1)
                            wait = int(ram[_P_DE_PRE_US])
                        if wait > 0:
                            sleep(wait)
                        cs[_CS_START + _CH_DRV_OUT] = int(ticks())  # (the copy's start: its AA handed over)
                        if dq != 0 and (dreg[0] & _ISR_TXFNF) != 0:
                            dreg[_TDR] = _STUFF
                        else:
                            down_queue(hdr_buf, 0, 1)
                        t = (now + int(ram[_P_INTERBYTE_US]) + 1) & _MASK
                        if ((t - due[0]) & _MASK) >= _HALF:
                            due[0] = t
                elif dearly[0] >= 0:
                    dearly[0] = -1  # Rs485.drop_early: no header followed
                    cs[_CS_START + _CH_DRV_OUT] = -1
                    down_drain()
                    post = int(ram[_P_DE_POST_US])
                    if post != 0:
                        sleep(post)
                    down_de(0)
                elif dearly[1] >= 0 and ust[_S_STATE] == _HUNT:
                    dearly[1] = -1  # Rs485.disarm: the byte whose start armed it was no AA
                    down_de(0)
            avail = 0
            if side == 0:
                side = 1
                avail = int(up_any())
        if ((now - due[0]) & _MASK) < _HALF:  # (a pass that read input: by its last read's tick)
            return passes
        # the CAN port's own pass after a pass that read input only once it has waited
        # CAN_DEFER_US: the bridge's idle passes come first (the next one serves it)
        if due[2] != 0 and ((now - due[1]) & _MASK) < _HALF and ((now - due[1]) & _MASK) >= _CAN_DEFER_US:
            if (due[3] != 0 or crs[_RS_TAIL] != crs[_RS_HEAD] or cts[_TS_REC] != cts[_TS_DONE]
                    or (cts[_TS_BUSY] == 0 and cts[_TS_TAIL] != cts[_TS_HEAD]) or int(can_any()) != 0):
                due[4] = 1
                return passes
            t1 = (due[1] + _CAN_POLL_US) & _MASK
            d = (t1 - now) & _MASK
            if d == 0 or d >= _HALF:
                t1 = (now + _CAN_POLL_US) & _MASK
            due[1] = t1
    return 0
