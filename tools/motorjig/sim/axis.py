"""The axis model both simulated drives share: one motor, two protocol faces.

The Plus-R drive (``driver.SimDriver``, RS-485) and the CANopen drive of ``sim.kinds``
(CiA 402) move their shaft with the same ``Motion``: a
trapezoidal profile integrated in ``STEP_MS`` steps of the bench's clock, whose
duration ``profile_time`` gives in closed form. Positions are in pulses (counts),
speeds in pulses (counts) per second. The Plus-R face gives its ramps as times
(parameters 3/4: ms from 0 to the move's speed); CiA 402 gives accelerations in
counts/s², which ``ramp_ms`` turns into the same ramp time.

``at_origin`` is the origin flag of a rotary axis both drives home on.
"""

import math

STEP_MS = 1.0  # motion integration step


def profile_time(distance, speed, acc_ms, dec_ms, start_speed=1):
    """Seconds the simulated drive's model takes to move ``distance`` pulses at ``speed`` pps.

    The model (``Motion``): the axis starts at the start speed vs = min(start_speed, speed),
    accelerates at speed / acc time, runs at speed, decelerates at speed / dec time back
    to vs exactly at the target, and stops. With v = speed, ta, td in seconds and D =
    |distance|, that takes

        D / v + (ta + td) * (v - vs)**2 / (2 * v**2)            if D >= (ta + td) * (v**2 - vs**2) / (2 * v)

    (with vs = 1 pps: D / v + (ta + td) / 2 to within 0.05 %), and for a shorter move a
    triangle that peaks at vp = sqrt(vs**2 + 2 * D * v / (ta + td)):

        (vp - vs) * (ta + td) / v

    Speeds below 1 pps and times below 1 ms count as 1, as in the drive. The simulated
    move ends at the first 1 ms step at or after this time (up to 2 ms later).
    """
    d = abs(distance)
    if d == 0:
        return 0.0
    v = float(max(1, speed))
    vs = float(max(1, min(start_speed, speed)))
    t_ramps = (max(1, acc_ms) + max(1, dec_ms)) / 1000.0
    if d >= t_ramps * (v * v - vs * vs) / (2 * v):
        return d / v + t_ramps * (v - vs) ** 2 / (2 * v * v)
    vp = math.sqrt(vs * vs + 2 * d * v / t_ramps)
    return (vp - vs) * t_ramps / v


class Motion:
    """Trapezoidal single-axis motion integrated in fixed steps (``profile_time``).

    Each step moves by the mean of the speeds at its start and end. A position move
    never ends a step faster than the braking curve to the start speed allows; on the
    curve it decelerates at the rate that lands it at the start speed exactly on the
    target (the set one, to rounding), then stops there. So a move lasts
    ``profile_time`` rounded up to the next step (+ at most one step).
    """

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
        """Decelerate from the present speed to standstill in dec_ms."""
        if self.moving:
            self.stopping = True
            speed = max(abs(self.vel), 1.0)
            self.dec = speed / (max(1, dec_ms) / 1000.0)

    def halt(self):
        self.moving = False
        self.stopping = False
        self.vel = 0.0
        self.phase = 0

    def _arrive(self):
        self.pos = float(self.target)
        self.halt()

    def _toward_vmax(self, s, dt):
        """The speed after dt on the way to vmax (accelerating, or slowing after a lower override)."""
        if s < self.vmax:
            self.phase = 1
            return min(s + self.acc * dt, self.vmax)
        if s > self.vmax:
            self.phase = 3
            return max(s - self.dec * dt, self.vmax)
        self.phase = 2
        return s

    def step(self, dt):
        if not self.moving:
            return
        s = abs(self.vel)
        d = self.direction
        if self.stopping:
            s1 = s - self.dec * dt
            self.phase = 3
            if s1 <= 0:
                self.pos = float(round(self.pos + d * s * s / (2 * self.dec)))
                self.halt()
                return
        elif self.target is None:
            s1 = self._toward_vmax(s, dt)
        else:
            left = (self.target - self.pos) * d
            if left <= 0:
                self._arrive()
                return
            vs = self.vstart
            # (the tolerance keeps an axis that reached the braking curve on it)
            if s * s - vs * vs >= 2 * self.dec * left * (1 - 1e-9):
                s1 = s - (s * s - vs * vs) / (2 * left) * dt
                self.phase = 3
                if s1 <= vs:
                    self._arrive()
                    return
            else:
                s1 = self._toward_vmax(s, dt)
                # End the step no faster than the braking curve allows (a steep ramp up
                # would overshoot it by a whole step's speed gain, then brake too hard).
                b = self.dec * dt
                on_curve = (math.sqrt(b * b + 4 * (vs * vs + 2 * self.dec * left - b * s)) - b) / 2
                if on_curve < s1:
                    if on_curve <= vs:  # it reaches the target within this step
                        self._arrive()
                        return
                    s1 = on_curve
                    self.phase = 3
            if (s + s1) / 2 * dt >= left:
                self._arrive()
                return
        self.pos += d * (s + s1) / 2 * dt
        self.vel = d * s1


def ramp_ms(speed, accel):
    """The ramp time (ms, float) the model takes from 0 to ``speed`` (counts/s) at
    ``accel`` (counts/s²): how a CiA 402 acceleration becomes a ``Motion`` ramp."""
    return 1000.0 * max(1.0, float(speed)) / max(1.0, float(accel))


def at_origin(mech, origin_pos, origin_width, rev_pulses):
    """True while a shaft at ``mech`` is on the origin flag (``origin_pos`` +-
    ``origin_width``/2, in pulses; on a rotary axis of ``rev_pulses`` per turn, or a
    linear one when ``rev_pulses`` is None/0)."""
    off = mech - origin_pos
    if rev_pulses:
        half = rev_pulses / 2.0
        off = (off + half) % rev_pulses - half
    return abs(off) <= origin_width / 2.0
