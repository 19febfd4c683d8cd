"""A simulated FASTECH Ezi-STEP Plus-R drive on a simulated RS-485 bus.

Answers every frame type of the protocol notes with the documented response
layout (unknown types: status 0x80, wrong request length: 0x82), after a
configurable turnaround delay. Motion follows a trapezoidal profile (start speed,
max speed, accel/decel times from parameters 2-4) evaluated in 1 ms steps of the
bus's clock, so positions and the axis status flags (moving, accelerating,
constant speed, decelerating, direction, in-position, servo on, limits, alarm,
e-stop, pause) evolve over time. Alarms, limit positions and communication
faults (silence, garbage, late or wrong-id replies, bad CRC, a forced status such
as 0xAA "your request arrived corrupted") can be injected.
RAM and ROM parameters 0-28 (SaveAllParameters copies RAM to ROM).

Each drive speaks Ver6 or Ver8 (``ver8``), independently of the others on the bus.
A Ver8 drive reads every frame the Ver8 way: it CRC-checks the whole body and takes
id / sync / type from its first three bytes, echoes the sync in its reply, and
answers an unknown type with 0x80. So the vendor library's Ver6-format probe
``id 51 crcL crcH`` gets ``id, 51, crcL, 80`` (a 4-byte body has no data at all:
always 0x80), which is how a host tells a Ver8 drive. Of Ver8's documented
frame-code changes (protocol notes §8) the drive models the ones whose layout the
notes give: inputs are 64 bits wide in SetIOInput 0x21 (u64 set + u64 clear),
GetIOInput 0x22, GetIOAxisStatus 0x41 and GetAllStatus 0x43, and GetMotionStatus
0x42 ends with the axis flags instead of the PT number. The reassigned or new
codes whose layout the notes do not give (0x24, 0x25, 0x27, 0x28, 0x44, 0x4F)
are answered with 0x80 by a Ver8 drive (``VER8_UNMODELLED``).
"""

import random
import struct

from jig import frame as F
from jig.parser import FrameParser

# Parameters 0-28: (min, max) and defaults (25-28 are STEP-specific guesses)
# (min, max) per parameter
PARAM_RANGE = (
    (0, 15), (1, 2500000), (1, 2500000), (1, 9999), (1, 9999), (1, 500), (1, 2500000),
    (1, 2500000), (1, 9999), (0, 1), (0, 1), (0, 1), (-134217727, 134217727),
    (-134217727, 134217727), (0, 1), (0, 1), (0, 1), (1, 2500000), (1, 2500000), (1, 9999),
    (0, 4), (0, 1), (-134217727, 134217727), (-134217727, 134217727), (0, 1), (0, 100),
    (0, 1), (0, 1), (0, 10),
)
PARAM_DEFAULT = (9, 500000, 1, 100, 100, 100, 5000, 1, 100, 0, 0, 0, 134217727, -134217727,
                 1, 1, 0, 5000, 1000, 50, 0, 0, 0, 0, 0, 50, 0, 0, 0)

# Axis status flag bits (§7.3)
FF_ERROR_ALL = 1 << 0
FF_HW_PLUS = 1 << 1
FF_HW_MINUS = 1 << 2
FF_SW_PLUS = 1 << 3
FF_SW_MINUS = 1 << 4
FF_STEP_ALARM = 1 << 7
FF_ESTOP = 1 << 16
FF_SLOW_STOP = 1 << 17
FF_ORIGIN_RETURNING = 1 << 18
FF_INPOSITION = 1 << 19
FF_SERVO_ON = 1 << 20
FF_ALARM_RESET = 1 << 21
FF_ORIGIN_OK = 1 << 25
FF_DIRECTION = 1 << 26
FF_MOTIONING = 1 << 27
FF_PAUSED = 1 << 28
FF_ACCEL = 1 << 29
FF_DECEL = 1 << 30
FF_CONST = 1 << 31

OUT_ALARM = 1 << 2
OUT_RUNSTOP = 1 << 3

# Request data lengths (-1: several allowed, checked in the handler)
REQ_LEN = {
    0x01: 0, 0x05: 0, 0x07: 0, 0x10: 0, 0x11: 1, 0x12: 5, 0x13: 1,
    0x20: 8, 0x21: 8, 0x22: 0, 0x23: 0, 0x24: 6, 0x25: 1, 0x26: 0, 0x27: 18, 0x28: 0,
    0x2A: 1, 0x2B: 0, 0x2C: 1, 0x2E: 0,
    0x31: 0, 0x32: 0, 0x33: 0, 0x34: 8, 0x35: 8, 0x36: 5, 0x37: 5, 0x38: 4, 0x39: 4, 0x3A: 4,
    0x3B: 0, 0x3C: 0, 0x3D: 0, 0x3E: 8, 0x3F: 8,
    0x40: 0, 0x41: 0, 0x42: 0, 0x43: 0,
    0x50: 4, 0x51: 0, 0x52: 4, 0x53: 0, 0x54: 0, 0x55: 0, 0x56: 0, 0x58: 1,
    0x60: 2, 0x61: 66, 0x62: 0, 0x63: 0, 0x64: 2, 0x65: 0, 0x68: 3, 0x69: 0,
    0x6A: 4, 0x6B: 8, 0x6C: 4,
    0x78: -1, 0x79: 0, 0x80: 40, 0x81: 40, 0x82: 37,
}
# Reply data lengths after the status byte, for status 0 (variable: -1)
REPLY_LEN = {
    0x01: -1, 0x05: -1, 0x07: 1, 0x11: 4, 0x13: 4, 0x22: 4, 0x23: 4, 0x25: 5, 0x26: 1, 0x28: 1,
    0x2E: 1, 0x40: 4, 0x41: 12, 0x42: 20, 0x43: 32, 0x51: 4, 0x53: 4, 0x54: 4, 0x55: 4,
    0x60: 64, 0x61: 1, 0x62: 1, 0x63: 1, 0x65: 32, 0x69: 1, 0x6A: 4, 0x6C: 8, 0x79: 1,
}

# Ver8 request lengths that differ from Ver6 (64-bit input masks)
REQ_LEN_VER8 = dict(REQ_LEN)
REQ_LEN_VER8[0x21] = 16
# Ver8 frame codes with a changed meaning or new, whose layout the protocol notes do
# not give: a Ver8 drive answers them with 0x80 instead of a guessed layout.
VER8_UNMODELLED = (0x24, 0x25, 0x27, 0x28, 0x44, 0x4F)
# Ver8 reply lengths after the status byte that differ from Ver6
REPLY_LEN_VER8 = dict(REPLY_LEN)
REPLY_LEN_VER8.update({0x22: 8, 0x41: 16, 0x43: 36})
for _t in VER8_UNMODELLED:
    REQ_LEN_VER8.pop(_t, None)
    REPLY_LEN_VER8.pop(_t, None)

STEP_MS = 1.0  # motion integration step


class Motion:
    """Trapezoidal single-axis motion integrated in fixed steps."""

    def __init__(self):
        self.pos = 0.0
        self.vel = 0.0  # signed pps
        self.target = None  # None: velocity mode
        self.vmax = 0.0  # unsigned target speed
        self.direction = 1
        self.moving = False
        self.stopping = False
        self.phase = 0  # 1 accel, 2 const, 3 decel
        self.acc = 1.0
        self.dec = 1.0
        self.vstart = 1.0

    def start(self, target, vmax, direction, acc_ms, dec_ms, vstart):
        self.target = target
        self.vmax = float(max(1, vmax))
        self.direction = direction
        self.acc = self.vmax / (max(1, acc_ms) / 1000.0)
        self.dec = self.vmax / (max(1, dec_ms) / 1000.0)
        self.vstart = float(max(1, min(vstart, vmax)))
        self.moving = True
        self.stopping = False
        self.phase = 0
        if abs(self.vel) < self.vstart:
            self.vel = self.vstart * direction

    def stop(self, dec_ms):
        if self.moving:
            self.stopping = True
            speed = max(abs(self.vel), 1.0)
            self.dec = speed / (max(1, dec_ms) / 1000.0)

    def halt(self):
        self.moving = False
        self.stopping = False
        self.vel = 0.0
        self.phase = 0

    def step(self, dt):
        if not self.moving:
            return
        speed = abs(self.vel)
        d = self.direction
        if self.stopping:
            speed -= self.dec * dt
            self.phase = 3
            if speed <= 0:
                self.pos += d * 0.5 * abs(self.vel) * dt
                self.halt()
                self.pos = float(round(self.pos))
                return
        elif self.target is not None:
            remaining = (self.target - self.pos) * d
            if remaining <= 0:
                self.pos = float(self.target)
                self.halt()
                return
            brake = speed * speed / (2 * self.dec)
            if self.phase == 3 or remaining <= brake + speed * dt:
                speed = max(speed - self.dec * dt, self.vstart, 0.02 * self.vmax)
                self.phase = 3
            elif speed < self.vmax:
                speed = min(speed + self.acc * dt, self.vmax)
                self.phase = 1
            else:
                speed = self.vmax
                self.phase = 2
            if remaining <= speed * dt:
                self.pos = float(self.target)
                self.halt()
                return
        else:
            if speed < self.vmax:
                speed = min(speed + self.acc * dt, self.vmax)
                self.phase = 1
            elif speed > self.vmax:
                speed = max(speed - self.dec * dt, self.vmax)
                self.phase = 3
            else:
                self.phase = 2
        self.vel = speed * d
        self.pos += self.vel * dt


class SimDriver:
    """One simulated drive. Set the fault attributes to misbehave."""

    def __init__(self, clock, bus, slave_id, turnaround_us=300.0, ver8=False, slave_type=20,
                 name=None, servo_on=False, seed=None):
        self.clock = clock
        self.bus = bus
        self.id = slave_id
        self.turnaround_us = turnaround_us
        self.ver8 = ver8
        self.slave_type = slave_type
        if name is None:
            name = b"Ezi-STEP Plus-R ST (sim) v8.0" if ver8 else b"Ezi-STEP Plus-R ST (sim) v6.0"
        self.name = name
        self.node = bus.add_node("driver-%d" % slave_id, self._rx, auto_de=True, record=False)
        # byte_us: bytes handed over in one piece arrived one character time apart
        # (a jig cutting a frame through sends it in several pieces).
        self.parser = FrameParser(ver8, byte_us=max(1, int(bus.bt)))
        self.ram = list(PARAM_DEFAULT)
        self.rom = list(PARAM_DEFAULT)
        self.motion = Motion()
        self.t_motion = clock.now
        self.servo_on = servo_on
        self.alarm = 0
        self.estop = False
        self.paused = False
        self.origin_ok = False
        self.outputs = 0
        self.inputs = 0  # 32 bits in Ver6, 64 in Ver8
        self.io_map = {}
        self.pos_table = {}
        self.limit_plus = None  # position of the + limit sensor (None: none)
        self.limit_minus = None
        self.limit_hit = 0
        self.actual_offset = 0
        self.alarm_reset_held = False
        # faults
        self.silent = False  # never answer
        self.garbage = False  # answer random bytes instead
        self.late_us = 0.0  # extra delay before answering
        self.wrong_id = None  # answer with this id instead
        self.bad_crc = False  # corrupt the reply's CRC
        # answer addressed requests with only this status byte, without executing them
        # (0xAA: "your request arrived corrupted"); None: off. See force().
        self.force_status = None
        self.force_frames = None  # requests left to answer so (None: until cleared)
        self.rng = random.Random(seed if seed is not None else slave_id)
        # statistics
        self.requests = 0
        self.replies = 0
        self.last_request = None  # unstuffed body of the last request for us
        self.received = []  # (time, ftype) of frames for us, if record_requests
        self.record_requests = False

    # --- motion ---------------------------------------------------------------
    def update(self):
        now = self.clock.now
        dt_us = now - self.t_motion
        m = self.motion
        if not m.moving or self.paused:
            self.t_motion = now
            return
        steps = int(dt_us // (STEP_MS * 1000))
        for _ in range(steps):
            m.step(STEP_MS / 1000.0)
            self._check_limits()
            if not m.moving:
                break
        self.t_motion += steps * STEP_MS * 1000 if m.moving else dt_us
        if not m.moving:
            self.t_motion = now

    def _check_limits(self):
        m = self.motion
        if self.limit_plus is not None and m.pos >= self.limit_plus and m.direction > 0:
            m.pos = float(self.limit_plus)
            m.halt()
            self.limit_hit = FF_HW_PLUS
        elif self.limit_minus is not None and m.pos <= self.limit_minus and m.direction < 0:
            m.pos = float(self.limit_minus)
            m.halt()
            self.limit_hit = FF_HW_MINUS

    def flags(self):
        self.update()
        m = self.motion
        f = self.limit_hit
        if self.alarm:
            f |= FF_ERROR_ALL | FF_STEP_ALARM
        if self.estop:
            f |= FF_ESTOP
        if m.moving:
            f |= FF_MOTIONING
            f |= (FF_ACCEL, FF_CONST, FF_DECEL)[m.phase - 1] if m.phase else 0
            if m.stopping:
                f |= FF_SLOW_STOP
        elif self.servo_on:
            f |= FF_INPOSITION
        if m.direction > 0:
            f |= FF_DIRECTION
        if self.servo_on:
            f |= FF_SERVO_ON
        if self.paused:
            f |= FF_PAUSED
        if self.origin_ok:
            f |= FF_ORIGIN_OK
        if self.alarm_reset_held:
            f |= FF_ALARM_RESET
        return f

    def out_bits(self):
        o = self.outputs
        if self.alarm:
            o |= OUT_ALARM
        if self.motion.moving:
            o |= OUT_RUNSTOP
        return o

    def inject_alarm(self, code=3):
        self.update()
        self.alarm = code
        self.motion.halt()
        self.servo_on = False

    # --- communication --------------------------------------------------------
    def clear_faults(self):
        """Every fault switch off, limit sensors removed (alarms and motion stay)."""
        self.force(None)
        self.silent = False
        self.garbage = False
        self.late_us = 0.0
        self.wrong_id = None
        self.bad_crc = False
        self.limit_plus = None
        self.limit_minus = None

    def force(self, status, frames=None):
        """Answer the next ``frames`` addressed requests (None: all, until ``force(None)``)
        with just ``status``, without executing them. Broadcasts are not affected."""
        self.force_status = None  # never half-set while the bench thread reads it
        self.force_frames = frames
        self.force_status = status

    def _forced(self):
        """The status to answer with instead of executing this request, or None."""
        status = self.force_status
        if status is None:
            return None
        left = self.force_frames
        if left is not None:
            if left <= 1:
                self.force_status = None
                self.force_frames = None
            else:
                self.force_frames = left - 1
        return status

    def _rx(self, data, t):
        p = self.parser
        i = 0
        n = len(data)
        while i < n:
            i = p.feed(data, i, n, int(t))
            if p.ready and (p.slave == self.id or p.slave == F.BROADCAST_ID):
                self._request(p)

    def _request(self, p):
        self.requests += 1
        body = bytes(p.body[: p.body_len])
        self.last_request = body
        if self.record_requests:
            self.received.append((self.clock.now, p.ftype))
        data = bytes(p.body[p.data_start : p.data_end])
        broadcast = p.slave == F.BROADCAST_ID
        forced = None if broadcast or self.silent else self._forced()
        if forced is not None:
            reply = bytes([forced])
        elif p.data_end < p.data_start:
            # Ver8 reading of a 4-byte body (a Ver6 frame without data): the "type"
            # is a CRC byte, there is no data at all -> frame-type error.
            reply = bytes([F.STATUS_FRAME_TYPE_ERROR])
        else:
            reply = self.handle(p.ftype, data, broadcast)
        if broadcast or self.silent:
            return
        self.clock.after(self.turnaround_us + self.late_us, self._send_reply, p.ftype, p.sync, reply)

    def _send_reply(self, ftype, sync, reply):
        if self.garbage:
            wire = bytes(self.rng.randrange(256) for _ in range(self.rng.randrange(3, 20)))
        else:
            sid = self.id if self.wrong_id is None else self.wrong_id
            wire = F.encode(sid, ftype, reply, sync if self.ver8 else -1)
            if self.bad_crc:
                wire = bytearray(wire)
                i = len(wire) - 3
                wire[i] = wire[i] ^ 0x01 if wire[i] not in (0xAA, 0xAB) else 0x11
                wire = bytes(wire)
        self.replies += 1
        self.bus.transmit(self.node, wire)

    def handle(self, ftype, data, broadcast=False):
        """Reply data (status first) for one request; also used directly by tests."""
        need = (REQ_LEN_VER8 if self.ver8 else REQ_LEN).get(ftype)
        if need is None:
            return bytes([F.STATUS_FRAME_TYPE_ERROR])
        if ftype == 0x78:
            if len(data) not in (26, 28):
                return bytes([F.STATUS_FRAME_ERROR])
        elif len(data) != need:
            return bytes([F.STATUS_FRAME_ERROR])
        self.update()
        fn = getattr(self, "_h%02X" % ftype, None)
        if fn is None:
            return b"\x00"
        out = fn(data)
        return bytes([out]) if isinstance(out, int) else bytes(out)

    # helpers
    @staticmethod
    def _ok(fmt="", *vals):
        return b"\x00" + struct.pack("<" + fmt, *vals)

    def _can_move(self):
        if self.motion.moving or not self.servo_on or self.alarm or self.estop:
            return False
        return True

    def _start(self, target, speed, direction):
        self.limit_hit = 0
        self.paused = False
        r = self.ram
        self.motion.start(target, speed, direction, r[3], r[4], r[2])
        self.t_motion = self.clock.now

    # info / parameters
    def _h01(self, d):
        return bytes([0, self.slave_type]) + self.name + b"\x00"

    def _h05(self, d):
        return b"\x00\x01EzM-56M (sim)\x00"

    def _h07(self, d):
        return b"\x00\x01"

    def _h10(self, d):
        self.rom = list(self.ram)
        return 0

    def _h11(self, d):
        if d[0] > 28:
            return F.STATUS_DATA_ERROR
        return self._ok("i", self.rom[d[0]])

    def _h12(self, d):
        num = d[0]
        (val,) = struct.unpack_from("<i", d, 1)
        if num > 28 or not PARAM_RANGE[num][0] <= val <= PARAM_RANGE[num][1]:
            return F.STATUS_DATA_ERROR
        self.ram[num] = val
        return 0

    def _h13(self, d):
        if d[0] > 28:
            return F.STATUS_DATA_ERROR
        return self._ok("i", self.ram[d[0]])

    # I/O
    def _h20(self, d):
        s, c = struct.unpack("<II", d)
        self.outputs = (self.outputs | s) & ~c & 0xFFFFFFFF
        return 0

    def _in_fmt(self):
        """struct code of the input word: 64 bits in Ver8, 32 in Ver6."""
        return "Q" if self.ver8 else "I"

    def _h21(self, d):
        w = self._in_fmt()
        s, c = struct.unpack("<" + w + w, d)
        self.inputs = (self.inputs | s) & ~c & (0xFFFFFFFFFFFFFFFF if self.ver8 else 0xFFFFFFFF)
        return 0

    def _h22(self, d):
        return self._ok(self._in_fmt(), self.inputs)

    def _h23(self, d):
        return self._ok("I", self.out_bits())

    def _h24(self, d):
        pin, mask, level = struct.unpack("<BIB", d)
        if pin >= 22:
            return F.STATUS_DATA_ERROR
        self.io_map[pin] = (mask, level)
        return 0

    def _h25(self, d):
        if d[0] >= 22:
            return F.STATUS_DATA_ERROR
        mask, level = self.io_map.get(d[0], (0, 0))
        return self._ok("IB", mask, level)

    def _h26(self, d):
        return self._ok("B", 0)

    def _h27(self, d):
        return 0

    def _h28(self, d):
        return self._ok("B", 0)

    # drive control
    def _h2A(self, d):
        if d[0]:
            if self.alarm:
                return F.STATUS_SERVO_ON_ALARM
            if self.estop:
                self.estop = False
            self.servo_on = True
        else:
            self.motion.halt()
            self.servo_on = False
        return 0

    def _h2B(self, d):
        self.alarm = 0
        return 0

    def _h2C(self, d):
        if d[0]:
            self.alarm_reset_held = True
        else:
            if self.alarm_reset_held:
                self.alarm = 0
            self.alarm_reset_held = False
        return 0

    def _h2E(self, d):
        return self._ok("B", self.alarm)

    # motion
    def _h31(self, d):
        self.motion.stop(self.ram[4])
        return 0

    def _h32(self, d):
        self.motion.halt()
        self.estop = True
        return 0

    def _h33(self, d):
        if not self._can_move():
            return F.STATUS_MOTION_REFUSED
        self.motion.halt()
        self.motion.pos = 0.0
        self.origin_ok = True
        return 0

    def _move_abs(self, target, speed):
        if not self._can_move():
            return F.STATUS_MOTION_REFUSED
        if target == round(self.motion.pos):
            return 0
        self._start(target, speed, 1 if target > self.motion.pos else -1)
        return 0

    def _h34(self, d):
        return self._move_abs(*struct.unpack("<iI", d))

    def _h35(self, d):
        dist, speed = struct.unpack("<iI", d)
        return self._move_abs(int(round(self.motion.pos)) + dist, speed)

    def _h36(self, d):
        speed, direction = struct.unpack("<IB", d)
        if not self._can_move():
            return F.STATUS_MOTION_REFUSED
        lim = self.limit_plus if direction else self.limit_minus
        if lim is None:
            self._start(None, speed, 1 if direction else -1)
        else:
            self._start(lim, speed, 1 if direction else -1)
        return 0

    def _h37(self, d):
        speed, direction = struct.unpack("<IB", d)
        if not self._can_move():
            return F.STATUS_MOTION_REFUSED
        self._start(None, speed, 1 if direction else -1)
        return 0

    def _h38(self, d):
        (target,) = struct.unpack("<i", d)
        if not self.motion.moving or self.motion.target is None:
            return F.STATUS_MOTION_REFUSED
        self.motion.target = target
        return 0

    def _h39(self, d):
        (dist,) = struct.unpack("<i", d)
        if not self.motion.moving or self.motion.target is None:
            return F.STATUS_MOTION_REFUSED
        self.motion.target += dist
        return 0

    def _h3A(self, d):
        (speed,) = struct.unpack("<I", d)
        if not self.motion.moving:
            return F.STATUS_MOTION_REFUSED
        self.motion.vmax = float(max(1, speed))
        return 0

    _h3B = _h31
    _h3C = _h32
    _h3D = _h33
    _h3E = _h34
    _h3F = _h35

    # status
    def _positions(self):
        self.update()
        cmd = int(round(self.motion.pos))
        act = cmd + self.actual_offset
        return cmd, act, cmd - act, int(round(self.motion.vel))

    def _h40(self, d):
        return self._ok("I", self.flags())

    def _h41(self, d):
        return self._ok(self._in_fmt() + "II", self.inputs, self.out_bits(), self.flags())

    def _h42(self, d):
        cmd, act, err, vel = self._positions()
        # Ver8: the axis flags take the place of the running PT number
        return self._ok("iiiiI", cmd, act, err, vel, self.flags() if self.ver8 else 0)

    def _h43(self, d):
        cmd, act, err, vel = self._positions()
        return self._ok(self._in_fmt() + "IIiiiiI", self.inputs, self.out_bits(), self.flags(), cmd, act, err,
                        vel, 0)

    def _h50(self, d):
        (self.motion.pos,) = struct.unpack("<i", d)
        self.motion.pos = float(self.motion.pos)
        return 0

    def _h51(self, d):
        return self._ok("i", self._positions()[0])

    def _h52(self, d):
        (act,) = struct.unpack("<i", d)
        self.actual_offset = act - self._positions()[0]
        return 0

    def _h53(self, d):
        return self._ok("i", self._positions()[1])

    def _h54(self, d):
        return self._ok("i", self._positions()[2])

    def _h55(self, d):
        return self._ok("i", self._positions()[3])

    def _h56(self, d):
        self.motion.pos = 0.0
        self.actual_offset = 0
        return 0

    def _h58(self, d):
        if d[0]:
            if not self.motion.moving:
                return F.STATUS_MOTION_REFUSED
            self.paused = True
        else:
            self.paused = False
            self.t_motion = self.clock.now
        return 0

    # position table
    def _h60(self, d):
        (item,) = struct.unpack("<H", d)
        if item > 255:
            return F.STATUS_DATA_ERROR
        return b"\x00" + self.pos_table.get(item, bytes(64))

    def _h61(self, d):
        (item,) = struct.unpack_from("<H", d)
        if item > 255:
            return self._ok("B", 0)
        self.pos_table[item] = bytes(d[2:66])
        return self._ok("B", 1)

    def _h62(self, d):
        return self._ok("B", 0)

    def _h63(self, d):
        return self._ok("B", 0)

    def _h64(self, d):
        (item,) = struct.unpack("<H", d)
        if item > 255:
            return F.STATUS_DATA_ERROR
        if not self._can_move():
            return F.STATUS_MOTION_REFUSED
        it = self.pos_table.get(item, bytes(64))
        pos, _low, high = struct.unpack_from("<iII", it)
        cmd = struct.unpack_from("<H", it, 16)[0]
        if cmd >= 4:  # INC variants
            pos += int(round(self.motion.pos))
        return self._move_abs(pos, high or 1000)

    def _h65(self, d):
        bitmap = bytearray(32)
        for k in self.pos_table:
            bitmap[k >> 3] |= 1 << (k & 7)
        return b"\x00" + bytes(bitmap)

    def _h68(self, d):
        return 0

    def _h69(self, d):
        return self._ok("B", 0)

    def _h6A(self, d):
        item, off = struct.unpack("<HH", d)
        if item > 255 or off > 60:
            return F.STATUS_DATA_ERROR
        it = self.pos_table.get(item, bytes(64))
        return self._ok("i", struct.unpack_from("<i", it, off)[0])

    def _h6B(self, d):
        item, off, val = struct.unpack("<HHi", d)
        if item > 255 or off > 60:
            return F.STATUS_DATA_ERROR
        it = bytearray(self.pos_table.get(item, bytes(64)))
        struct.pack_into("<i", it, off, val)
        self.pos_table[item] = bytes(it)
        return 0

    def _h6C(self, d):
        return b"\x00" + bytes(8)

    def _h78(self, d):
        start, speed, pos = struct.unpack_from("<IIi", d)
        return self._move_abs(pos, speed)

    def _h79(self, d):
        return self._ok("B", 0)

    def _h80(self, d):
        return self._move_abs(*struct.unpack_from("<iI", d))

    def _h81(self, d):
        dist, speed = struct.unpack_from("<iI", d)
        return self._move_abs(int(round(self.motion.pos)) + dist, speed)

    def _h82(self, d):
        return self._h37(d[0:5])
