"""An EtherCAT slave's firmware, whatever device it is: the AL state machine, the mailbox, the process data.

Sits on an ``ecat_esc.Esc`` as a slave's firmware sits on its ESC's PDI. The device behind it
(``ecat_servo.EcatServo``) gives what only it knows: the process data's sizes, its CoE
answers, what outputs do, what inputs say, and its reaction when the master goes away.

The EtherCAT state machine (ETG.1000.6): INIT, PRE-OP, SAFE-OP, OP (BOOT refused). A request
is checked as a real slave checks it and refused with its AL status code (``AL_CODES``): the
mailbox sync managers must match the SII for PRE-OP, the process-data ones the PDO sizes for
SAFE-OP. While an error is shown (AL status bit 4) only a lower state or an acknowledged
request (AL control bit 4) is taken. In OP the process-data watchdog runs: when the master's
outputs stop for its time (0x0420), the slave drops to SAFE-OP with error 0x001B and the
device reacts (a drive stops).

The mailbox: a message written to SM0 goes to the device's protocol (CoE; others are answered
with a mailbox error), replies and emergencies are queued for SM1 and put there one by one as
the master reads them.
"""

import struct

from .ecat_esc import SM_DIR_WRITE, SM_MODE_MAILBOX

INIT, PREOP, BOOT, SAFEOP, OP = 1, 2, 3, 4, 8
STATE_NAMES = {INIT: "INIT", PREOP: "PRE-OP", BOOT: "BOOT", SAFEOP: "SAFE-OP", OP: "OP"}
AL_ACK = 0x10

# AL status codes (ETG.1000.6, table "AL Status Codes")
AL_NO_ERROR = 0x0000
AL_INVALID_STATE_CHANGE = 0x0011
AL_UNKNOWN_STATE = 0x0012
AL_BOOT_NOT_SUPPORTED = 0x0013
AL_INVALID_MAILBOX = 0x0016
AL_INVALID_SM = 0x0017
AL_NO_VALID_INPUTS = 0x0018
AL_NO_VALID_OUTPUTS = 0x0019
AL_SYNC_ERROR = 0x001A
AL_SM_WATCHDOG = 0x001B
AL_INVALID_OUTPUT_CONFIG = 0x001D
AL_INVALID_INPUT_CONFIG = 0x001E
AL_INVALID_DC_SYNC = 0x0030
AL_CODES = {
    AL_NO_ERROR: "no error", AL_INVALID_STATE_CHANGE: "invalid requested state change",
    AL_UNKNOWN_STATE: "unknown requested state", AL_BOOT_NOT_SUPPORTED: "bootstrap not supported",
    AL_INVALID_MAILBOX: "invalid mailbox configuration (PRE-OP)", AL_INVALID_SM: "invalid sync manager configuration",
    AL_NO_VALID_INPUTS: "no valid inputs available", AL_NO_VALID_OUTPUTS: "no valid outputs",
    AL_SYNC_ERROR: "synchronization error", AL_SM_WATCHDOG: "sync manager watchdog",
    AL_INVALID_OUTPUT_CONFIG: "invalid output configuration", AL_INVALID_INPUT_CONFIG: "invalid input configuration",
    AL_INVALID_DC_SYNC: "invalid DC SYNC configuration",
}

# the transitions a master may ask for: (from, to)
ALLOWED = {(INIT, INIT), (INIT, PREOP), (PREOP, PREOP), (PREOP, INIT), (PREOP, SAFEOP), (SAFEOP, SAFEOP),
           (SAFEOP, INIT), (SAFEOP, PREOP), (SAFEOP, OP), (OP, OP), (OP, INIT), (OP, PREOP), (OP, SAFEOP)}

# mailbox types (ETG.1000.6): the header's low nibble
MBX_ERROR, MBX_AOE, MBX_EOE, MBX_COE, MBX_FOE, MBX_SOE, MBX_VOE = 0, 1, 2, 3, 4, 5, 15
MBX_HEADER = 6
MBX_ERR_UNSUPPORTED_PROTOCOL = 0x0002
MBX_ERR_SIZE_TOO_SHORT = 0x0004


class EcatSlave:
    """The firmware of one slave on ``esc`` for ``device`` (see the module's docstring). ``clock``
    is the bench's (µs); ``mailbox`` the SII's (rx start, rx size, tx start, tx size)."""

    WATCH_US = 1000.0  # how often the firmware looks at its watchdog

    def __init__(self, clock, esc, device, mailbox):
        self.clock = clock
        self.esc = esc
        self.device = device
        self.mailbox = mailbox
        esc.app = self
        self.queue = []  # mailbox messages waiting for SM1
        self.counter = 0  # the mailbox counter of our messages (1..7)
        self.refuse_op = None  # an AL status code: OP is refused with it (a fault of the bench)
        self.transitions = []  # (t_us, from, to, code) for tests
        self.watchdog_trips = 0
        self._watch_gen = 0

    # --- the AL state machine ------------------------------------------------------------------
    @property
    def state(self):
        return self.esc.al_state

    def al_control(self, value):
        esc = self.esc
        want, ack = value & 0x0F, value & AL_ACK
        cur = esc.al_state
        error = bool(esc.u8(0x0130) & 0x10)
        if error and not ack and want >= cur:
            return  # an error shown: only a lower state, or an acknowledged request
        if want not in STATE_NAMES:
            self._refuse(cur, want, AL_UNKNOWN_STATE)
            return
        if want == BOOT:
            self._refuse(cur, want, AL_BOOT_NOT_SUPPORTED)
            return
        if (cur, want) not in ALLOWED:
            self._refuse(cur, want, AL_INVALID_STATE_CHANGE)
            return
        code = self._check(cur, want)
        if code:
            self._refuse(cur, want, code)
            return
        self._enter(cur, want, AL_NO_ERROR)

    def _check(self, cur, want):
        if want >= PREOP and cur == INIT and not self._mailbox_ok():
            return AL_INVALID_MAILBOX
        if want >= SAFEOP and cur <= PREOP:
            out_size, in_size = self.device.pdo_sizes()
            if not self._pd_sm_ok(2, out_size, True):
                return AL_INVALID_OUTPUT_CONFIG
            if not self._pd_sm_ok(3, in_size, False):
                return AL_INVALID_INPUT_CONFIG
            sync = self.esc.sync0()
            if sync is not None and not 125000 <= sync[1] <= 100000000:
                return AL_INVALID_DC_SYNC
        if want == OP and cur == SAFEOP and self.refuse_op:
            return self.refuse_op
        return 0

    def _mailbox_ok(self):
        rx, rx_size, tx, tx_size = self.mailbox
        for n, start, size, write in ((0, rx, rx_size, True), (1, tx, tx_size, False)):
            s, length, control, enabled = self.esc.sm(n)
            if not enabled or s != start or length != size or not control & SM_MODE_MAILBOX:
                return False
            if bool(control & SM_DIR_WRITE) != write:
                return False
        return True

    def _pd_sm_ok(self, n, size, write):
        _start, length, control, enabled = self.esc.sm(n)
        if size == 0:
            return not enabled or length == 0
        return enabled and length == size and not control & SM_MODE_MAILBOX and bool(control & SM_DIR_WRITE) == write

    def _refuse(self, cur, want, code):
        self.esc.set_al_status(cur, True, code)
        self.transitions.append((self.clock.now, cur, want, code))

    def _enter(self, cur, new, code):
        self.esc.set_al_status(new, bool(code), code)
        self.transitions.append((self.clock.now, cur, new, code))
        if new < PREOP:
            self.queue = []
            self.esc.mailbox_out_full = False
        if cur == OP and new != OP:
            self.device.outputs_lost("left OP for %s" % STATE_NAMES[new])
        if new == OP:
            self.esc.wd_last_ns = self.esc.clock_ns()
            self._watch_gen += 1
            self.clock.after(self.WATCH_US, self._watch, self._watch_gen)

    def _watch(self, gen):
        if gen != self._watch_gen or self.state != OP:
            return
        if self.esc.watchdog_expired():
            self.watchdog_trips += 1
            self._enter(OP, SAFEOP, AL_SM_WATCHDOG)  # outputs_lost: the device reacts
            return
        self.clock.after(self.WATCH_US, self._watch, gen)

    # --- process data ----------------------------------------------------------------------------
    def fill_inputs(self, sm, view):
        if self.state >= SAFEOP:
            data = self.device.pd_inputs()
            view[:len(data)] = data

    def outputs_written(self, sm, data):
        if self.state == OP:
            self.device.pd_outputs(data)

    # --- the mailbox -------------------------------------------------------------------------------
    def mailbox_written(self, raw):
        if self.state < PREOP or len(raw) < MBX_HEADER:
            return
        length, _address, _channel, kind = struct.unpack_from("<HHBB", raw, 0)
        body = bytes(raw[MBX_HEADER:MBX_HEADER + length])
        if length > len(raw) - MBX_HEADER:
            self._mailbox_error(MBX_ERR_SIZE_TOO_SHORT)
            return
        if kind & 0x0F == MBX_COE:
            for reply in self.device.coe(body):
                self.send(MBX_COE, reply)
        else:
            self._mailbox_error(MBX_ERR_UNSUPPORTED_PROTOCOL)

    def _mailbox_error(self, detail):
        self.send(MBX_ERROR, struct.pack("<HH", 0x0001, detail))

    def send(self, kind, body):
        """Queue a mailbox message of ``kind`` for the master (an SDO reply, an emergency)."""
        if self.state < PREOP:
            return
        self.counter = self.counter % 7 + 1
        self.queue.append(struct.pack("<HHBB", len(body), 0, 0, kind | self.counter << 4) + bytes(body))
        self._post()

    def mailbox_read(self):
        self._post()

    def _post(self):
        if self.queue and self.esc.post_mailbox(self.queue[0]):
            self.queue.pop(0)
