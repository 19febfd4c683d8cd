"""The Desk's CiA 402 axis: one CANopen drive on the CAN link, driven as the Axis tab drives a Plus-R one.

One ``CanAxis`` per ``canlink.CanLink`` (so per Desk server, shared by every browser
tab). Everything goes by SDO through the link's python-canopen network, one transfer at
a time under the link's lock, so the SDO card and the axis never mix their answers:

* the power state machine is ``motorjig.can.power402``'s table: ``enable`` follows
  ``path`` to OPERATION ENABLED, each controlword checked against the state the
  statusword 0x6041 shows; ``fault_reset`` the path out of FAULT; ``disable`` a quick
  stop, then SWITCH ON DISABLED (a moving motor is stopped before its voltage goes);
* ``move``: profile position (0x6060 = 1; 0x6081/0x6083/0x6084, target 0x607A, the
  new-set-point handshake on statusword bit 12), absolute or relative;
* ``jog``: profile velocity (0x6060 = 3, 0x60FF) while the button is held: the page
  says "still held" (``jog_alive``) with every refresh and the watcher ends a jog
  that has not been confirmed for ``JOG_LEASE_S`` (a closed browser tab, a lost
  websocket), so a motor never goes on by itself;
* ``halt`` (controlword bit 8: a decelerating stop, the drive stays enabled) and
  ``quick_stop`` (controlword QUICK STOP); ``stop(emergency)`` is the Desk's STOP AXIS /
  EMERGENCY STOP and Esc for the CAN axis;
* ``make_safe`` (before the port closes, and when the Desk stops): quick stop, a wait
  for standstill, then disable voltage, on every node the Desk enabled and the watched one.

A watcher thread reads the watched node's statusword, mode 0x6061, position actual
0x6064, velocity actual 0x606C, following error 0x60F4 (and 0x603F in FAULT) every
``POLL_S``; the link names the node's last EMCY. The methods block (an SDO transfer, a
state to wait for): the page runs them in a worker thread; failures are ``UserError``
with one sentence.
"""

import threading
import time

from motorjig.can import cia301, power402
from motorjig.desk.session import UserError

POLL_S = 0.25  # the status watcher's period (a few Hz, five SDO uploads each)
STATE_TIMEOUT_S = 2.0  # a power state transition or a set-point acknowledge must come within this
STOP_WAIT_S = 3.0  # how long make_safe / disable wait for a quick stop to reach standstill
JOG_LEASE_S = 1.0  # a jog not confirmed by the page for this long is stopped

MODE_PP, MODE_PV, MODE_HOMING = 1, 3, 6
MODE_NAMES = {0: "none", MODE_PP: "profile position", 2: "velocity", MODE_PV: "profile velocity",
              4: "profile torque", MODE_HOMING: "homing", 7: "interpolated position",
              8: "cyclic sync position", 9: "cyclic sync velocity", 10: "cyclic sync torque"}

CW_ENABLED = 0x0F  # ENABLE OPERATION
CW_NEW_SETPOINT = 1 << 4
CW_IMMEDIATE = 1 << 5
CW_RELATIVE = 1 << 6
CW_HALT = 1 << 8
SW_FAULT = 1 << 3
SW_TARGET_REACHED = 1 << 10
SW_ACK = 1 << 12
SW_FOLLOWING_ERROR = 1 << 13

STATUS_OBJECTS = ((0x6041, "statusword"), (0x6061, "mode"), (0x6064, "position"), (0x606C, "velocity"),
                  (0x60F4, "following_error"))


def _int(text, what, low=-(1 << 31), high=(1 << 31) - 1):
    try:
        value = int(str(text).strip().replace("_", ""), 0)
    except ValueError:
        raise UserError("%s must be a whole number, not %r" % (what, str(text))) from None
    if not low <= value <= high:
        raise UserError("%s must be %d..%d, not %d" % (what, low, high, value))
    return value


def _optional(text, what):
    return None if str(text or "").strip() == "" else _int(text, what, 1, (1 << 32) - 1)


class CanAxis:
    """The CiA 402 axis of a CanLink (see the module docstring)."""

    def __init__(self, link, poll_s=POLL_S):
        self.link = link
        self.poll_s = poll_s
        self.node_id = None  # the watched (and driven) node
        self.enabled = set()  # nodes the Desk took to OPERATION ENABLED (make_safe's list)
        self.status = {}  # the watcher's last reading (see poll)
        self.jogging = 0  # -1, 0, +1
        self._jog_until = 0.0
        self._busy = threading.Lock()  # one command (enable, a move ...) at a time; stops never wait for it
        self._stop_seq = 0  # bumped by every stop: a command waiting for a state gives up
        self._jog_gen = 0  # bumped by every release and stop: a jog start that comes after it does nothing
        self._thread = None
        self._quit = threading.Event()

    # --- SDO through the link -------------------------------------------------------------------------
    def _need_node(self):
        if self.node_id is None:
            raise UserError("choose the CiA 402 node to drive first (its id, 1..127)")
        return self.node_id

    def _read(self, index, sub=0, nid=None):
        link = self.link
        with link._lock:
            node = link._node(link._network(), self._need_node() if nid is None else nid)
            try:
                raw = node.sdo.upload(index, sub)
                var = node.object_dictionary.get_variable(index, sub)
                return var.decode_raw(raw) if var is not None else int.from_bytes(raw, "little")
            except Exception as exc:
                raise UserError(link._failure("the upload of 0x%04X:%02X" % (index, sub), exc, node.id)) from None

    def _write(self, index, value, sub=0, nid=None):
        link = self.link
        with link._lock:
            node = link._node(link._network(), self._need_node() if nid is None else nid)
            try:
                var = node.object_dictionary.get_variable(index, sub)
                node.sdo.download(index, sub, var.encode_raw(value))
            except Exception as exc:
                raise UserError(link._failure("the download of 0x%04X:%02X = %s" % (index, sub, value), exc,
                                              node.id)) from None

    def _state(self, nid=None):
        sw = self._read(0x6041, nid=nid)
        return power402.state_of(sw), sw

    def _wait(self, done, what, timeout=STATE_TIMEOUT_S, nid=None):
        """Read the statusword until done(state, sw); UserError after timeout or when a stop came."""
        seq = self._stop_seq
        deadline = time.monotonic() + timeout
        while True:
            state, sw = self._state(nid)
            if done(state, sw):
                return state, sw
            if self._stop_seq != seq:
                raise UserError("node %d: stopped before %s" % (nid or self.node_id, what))
            if time.monotonic() > deadline:
                raise UserError("node %d did not %s within %g s (it is in %s)" % (
                    nid or self.node_id, what, timeout, state or "an undefined state, statusword 0x%04X" % sw))
            time.sleep(0.01)

    def _command(self, fn, *args):
        if not self._busy.acquire(timeout=STATE_TIMEOUT_S + 1):
            raise UserError("the CAN axis is busy with another command: wait a moment")
        try:
            return fn(*args)
        finally:
            self._busy.release()

    # --- choosing the node ------------------------------------------------------------------------------
    def watch(self, node_id):
        """Drive and watch this node from now on (the watcher thread starts with the first)."""
        nid = parse_node_id(node_id)
        if nid != self.node_id:
            self.node_id = nid
            self.status = {}
        if self._thread is None:
            self._thread = threading.Thread(target=self._watch_loop, name="desk-can-axis", daemon=True)
            self._thread.start()
        return nid

    def _take(self, node_id):
        if node_id is not None and str(node_id).strip():
            self.watch(node_id)
        return self._need_node()

    # --- power state machine --------------------------------------------------------------------------------
    def enable(self, node_id=None):
        """Take the node along power402.path to OPERATION ENABLED; returns a sentence."""
        nid = self._take(node_id)
        return self._command(self._go, nid, power402.OPERATION_ENABLED)

    def _go(self, nid, target):
        state, _ = self._state()
        if state == power402.FAULT_REACTION:
            state, _ = self._wait(lambda s, sw: s != power402.FAULT_REACTION, "end its fault reaction")
        if state == power402.FAULT and target == power402.OPERATION_ENABLED:
            raise UserError("node %d is in FAULT%s: press Fault reset first" % (nid, self._emcy_words(nid)))
        option = self._read(0x605A) if state == power402.QUICK_STOP_ACTIVE else None
        try:
            steps = power402.path(state, target, option)
        except ValueError as exc:
            raise UserError("node %d: %s" % (nid, exc)) from None
        for cw, expected in steps:
            if target == power402.OPERATION_ENABLED:
                self.enabled.add(nid)  # from the first controlword on, make_safe takes care of it
            self._write(0x6040, cw)
            self._wait(lambda s, sw, e=expected: s == e, "reach %s (controlword 0x%04X)" % (expected, cw))
        if target != power402.OPERATION_ENABLED:
            self.enabled.discard(nid)
        return "node %d: %s" % (nid, target)

    def disable(self, node_id=None):
        """Quick stop (a moving motor stops first), then SWITCH ON DISABLED; returns a sentence."""
        nid = self._take(node_id)
        self.jogging = 0
        self._stop_seq += 1
        return self._command(self._disable, nid)

    def _disable(self, nid):
        state, _ = self._state()
        if state in (power402.FAULT, power402.FAULT_REACTION):
            self.enabled.discard(nid)
            return "node %d is in %s: its power is already off (Fault reset to leave it)" % (nid, state)
        if state == power402.OPERATION_ENABLED:
            self._write(0x6040, power402.COMMANDS[power402.QUICK_STOP])
            self._standstill(nid)
        return self._go(nid, power402.SWITCH_ON_DISABLED)

    def _standstill(self, nid):
        """Wait (up to STOP_WAIT_S) until a quick stop has ended: the state left QUICK STOP ACTIVE or
        the velocity is 0."""
        deadline = time.monotonic() + STOP_WAIT_S
        while time.monotonic() < deadline:
            state, _ = self._state(nid)
            if state != power402.QUICK_STOP_ACTIVE or self._read(0x606C, nid=nid) == 0:
                return
            time.sleep(0.01)

    def fault_reset(self, node_id=None):
        """The path out of FAULT (0x00 then the rising edge of bit 7) to SWITCH ON DISABLED."""
        nid = self._take(node_id)
        state, _ = self._state()
        if state not in (power402.FAULT, power402.FAULT_REACTION):
            return "node %d is not in FAULT (%s): nothing to reset" % (nid, state)
        return self._command(self._go, nid, power402.SWITCH_ON_DISABLED)

    # --- motion -----------------------------------------------------------------------------------------------
    def _need_enabled(self, nid):
        state, _ = self._state()
        if state != power402.OPERATION_ENABLED:
            raise UserError("node %d is in %s, not OPERATION ENABLED: press Enable first" % (nid, state))

    def _set_mode(self, mode):
        if self._read(0x6061) != mode:
            self._write(0x6060, mode)
            deadline = time.monotonic() + STATE_TIMEOUT_S
            while self._read(0x6061) != mode:
                if time.monotonic() > deadline:
                    raise UserError("node %d did not take mode of operation %d (%s)" % (
                        self.node_id, mode, MODE_NAMES.get(mode, "?")))
                time.sleep(0.01)

    def move(self, kind, target, speed, accel="", decel="", node_id=None):
        """A profile position move: kind 'abs' (target 0x607A) or 'rel' (a distance); speed in
        counts/s (0x6081), accel/decel in counts/s² (0x6083/0x6084; blank: the drive's own)."""
        nid = self._take(node_id)
        if kind not in ("abs", "rel"):
            raise UserError("a move is 'abs' or 'rel', not %r" % kind)
        target = _int(target, "the target" if kind == "abs" else "the distance")
        speed = _int(speed, "the speed (counts/s)", 1, (1 << 32) - 1)
        accel, decel = _optional(accel, "the acceleration (counts/s²)"), _optional(decel, "the deceleration (counts/s²)")
        return self._command(self._move, nid, kind, target, speed, accel, decel)

    def _move(self, nid, kind, target, speed, accel, decel):
        self._need_enabled(nid)
        self.jogging = 0
        self._set_mode(MODE_PP)
        self._write(0x6081, speed)
        if accel is not None:
            self._write(0x6083, accel)
        if decel is not None:
            self._write(0x6084, decel)
        self._write(0x607A, target)
        base = CW_ENABLED | CW_IMMEDIATE | (CW_RELATIVE if kind == "rel" else 0)
        self._write(0x6040, base)  # bit 4 low first: the next write is its rising edge (halt cleared too)
        self._write(0x6040, base | CW_NEW_SETPOINT)
        self._wait(lambda s, sw: bool(sw & SW_ACK) or s != power402.OPERATION_ENABLED,
                   "acknowledge the set-point (statusword bit 12)")
        self._write(0x6040, base)
        return "node %d: move %s %d at %d counts/s" % (nid, "to" if kind == "abs" else "by", target, speed)

    def jog(self, direction, speed, node_id=None):
        """Profile velocity at ±speed until jog_release (or the page stops confirming it)."""
        nid = self._take(node_id)
        speed = _int(speed, "the jog speed (counts/s)", 1, (1 << 31) - 1)
        sign = 1 if direction > 0 else -1
        self._jog_until = time.monotonic() + JOG_LEASE_S
        return self._command(self._jog, nid, sign, speed, self._jog_gen)

    def _jog(self, nid, sign, speed, gen):
        self._need_enabled(nid)
        self._set_mode(MODE_PV)
        if gen != self._jog_gen:  # released (or stopped) before the drive was told to go
            return "node %d: jog released" % nid
        self._write(0x60FF, sign * speed)
        self.jogging = sign
        self._jog_until = time.monotonic() + JOG_LEASE_S
        self._write(0x6040, CW_ENABLED)  # halt cleared: the velocity set applies
        return "node %d: jog %s at %d counts/s" % (nid, "+" if sign > 0 else "-", speed)

    def jog_alive(self):
        """The page still holds the jog button: the jog goes on for JOG_LEASE_S more."""
        if self.jogging:
            self._jog_until = time.monotonic() + JOG_LEASE_S

    def jog_release(self):
        """The jog button was let go: velocity 0 with the drive's deceleration (a halt as well)."""
        was, self.jogging = self.jogging, 0
        self._jog_gen += 1
        nid = self._need_node()
        self._halt(nid)
        return "node %d: jog released" % nid if was else "node %d: halt" % nid

    def _halt(self, nid):
        """Halt (bit 8) a node in OPERATION ENABLED; False, with nothing sent, in any other state: its
        controlword carries ENABLE OPERATION, which in READY TO SWITCH ON would switch the drive on."""
        self._stop_seq += 1
        self._jog_gen += 1
        if self._state(nid)[0] != power402.OPERATION_ENABLED:
            return False
        self._write(0x6040, CW_ENABLED | CW_HALT | CW_IMMEDIATE, nid=nid)
        if self._read(0x6061, nid=nid) == MODE_PV:
            self._write(0x60FF, 0, nid=nid)
        return True

    @property
    def stop_seq(self):
        """How many stops (STOP, EMERGENCY STOP, quick stop) this axis has had: the tab sees one."""
        return self._stop_seq

    def halt(self, node_id=None):
        """Controlword bit 8: the drive stops with its deceleration and stays enabled."""
        nid = self._take(node_id)
        self.jogging = 0
        if not self._halt(nid):
            return "node %d is not in OPERATION ENABLED: nothing to halt" % nid
        return "node %d: halt (controlword bit 8; the drive stays enabled)" % nid

    def quick_stop(self, node_id=None):
        """Controlword QUICK STOP: the drive stops as its 0x605A says (then SWITCH ON DISABLED for 0-4)."""
        nid = self._take(node_id)
        self.jogging = 0
        self._stop_seq += 1
        self._jog_gen += 1
        self._write(0x6040, power402.COMMANDS[power402.QUICK_STOP], nid=nid)
        return "node %d: quick stop" % nid

    def stop(self, emergency=False):
        """The Desk's STOP AXIS (halt) or EMERGENCY STOP / Esc (quick stop) for the CAN axis: every
        node the Desk enabled and the watched one; None when there is nothing to stop (no port open,
        no node chosen). Never waits for a command in progress: a move's handshake gives up."""
        link = self.link
        if not link.is_open or link.read_only:
            return None
        nodes = sorted(self.enabled | ({self.node_id} if self.node_id is not None else set()))
        if not nodes:
            return None
        self.jogging = 0
        self._stop_seq += 1
        self._jog_gen += 1
        said, problems = [], []
        for nid in nodes:
            try:
                if emergency:
                    self._write(0x6040, power402.COMMANDS[power402.QUICK_STOP], nid=nid)
                elif not self._halt(nid):
                    continue  # not enabled: nothing moves, and a halt's controlword must not switch it on
                said.append(str(nid))
            except UserError as exc:
                problems.append(str(exc))
        text = "CAN node%s %s: %s" % ("s" if len(said) > 1 else "", ", ".join(said),
                                      "quick stop" if emergency else "halt") if said else ""
        if problems:
            raise UserError("; ".join(([text] if text else []) + problems))
        return text

    def make_safe(self):
        """Before the port closes (or the Desk stops): every node the Desk enabled, and the watched one
        when it is enabled, is quick-stopped, waited for and disabled; returns the problems met."""
        problems = []
        link = self.link
        if not link.is_open or link.read_only:
            return problems
        self.jogging = 0
        self._stop_seq += 1
        nodes = set(self.enabled)
        if self.node_id is not None:
            nodes.add(self.node_id)
        for nid in sorted(nodes):
            try:
                state, _ = self._state(nid)
                if state not in (power402.OPERATION_ENABLED, power402.QUICK_STOP_ACTIVE, power402.SWITCHED_ON,
                                 power402.READY):
                    self.enabled.discard(nid)
                    continue
                if state == power402.OPERATION_ENABLED:
                    self._write(0x6040, power402.COMMANDS[power402.QUICK_STOP], nid=nid)
                    self._standstill(nid)
                self._write(0x6040, power402.COMMANDS[power402.DISABLE_VOLTAGE], nid=nid)
                self.enabled.discard(nid)
            except UserError as exc:
                problems.append(str(exc))
        return problems

    # --- the watcher ------------------------------------------------------------------------------------------
    def _emcy_words(self, nid):
        e = self.link.emcys.get(nid)
        return "" if e is None else " (last EMCY 0x%04X %s)" % (e[0], cia301.emcy_name(e[0]))

    def poll(self):
        """Read the watched node's status once (``status``: state, statusword, mode, position,
        velocity, following error, fault code, last EMCY; ``error``: why it could not be read)."""
        nid = self.node_id
        link = self.link
        st = {"node": nid, "t": time.time()}
        if nid is None or not link.is_open:
            return st
        if link.read_only:
            st["error"] = "read-only Desk: the node's status is not asked for (SDO is refused)"
        else:
            try:
                for index, key in STATUS_OBJECTS:
                    st[key] = self._read(index, nid=nid)
                sw = st["statusword"]
                st["state"] = power402.state_of(sw) or "undefined"
                if sw & SW_FAULT:
                    st["fault_code"] = self._read(0x603F, nid=nid)
            except UserError as exc:
                st["error"] = str(exc)
        e = link.emcys.get(nid)
        if e is not None:
            st["emcy"] = "0x%04X %s (register 0x%02X) at %s" % (e[0], cia301.emcy_name(e[0]), e[1],
                                                               time.strftime("%H:%M:%S", time.localtime(e[2])))
        if nid == self.node_id:
            self.status = st
        return st

    def _watch_loop(self):
        while not self._quit.wait(self.poll_s):
            try:
                if self.jogging and time.monotonic() > self._jog_until and self.node_id is not None:
                    self.jogging = 0  # the page stopped confirming the held button: stop the motor
                    try:
                        self._halt(self.node_id)
                    except UserError:
                        pass
                if self.node_id is not None and self.link.is_open:
                    self.poll()
            except Exception as exc:  # the watcher must outlive anything: the page shows why
                self.status = {"node": self.node_id, "t": time.time(), "error": "internal error (%s: %s)" % (
                    type(exc).__name__, exc)}

    def close(self):
        self._quit.set()

    def describe(self):
        """The watched node's status as {field: text} for the page."""
        st = self.status
        if self.node_id is None:
            return {"state": "no node chosen"}
        if not self.link.is_open:
            return {"state": "the SLCAN port is lent to %s" % self.link.lent if self.link.lent
                    else "the SLCAN port is not open"}
        if not st or st.get("node") != self.node_id:
            return {"state": "reading node %d ..." % self.node_id}
        out = {}
        if "statusword" in st:
            out["state"] = "%s (0x6041 = 0x%04X%s%s)" % (
                st["state"], st["statusword"], ", target reached" if st["statusword"] & SW_TARGET_REACHED else "",
                ", following error" if st["statusword"] & SW_FOLLOWING_ERROR else "")
            out["mode"] = "%d %s" % (st["mode"], MODE_NAMES.get(st["mode"], ""))
            out["position"] = str(st["position"])
            out["velocity"] = str(st["velocity"])
            out["following_error"] = str(st["following_error"])
        if "fault_code" in st:
            out["fault"] = "0x%04X %s" % (st["fault_code"], cia301.emcy_name(st["fault_code"]))
        out["emcy"] = st.get("emcy", "none since the port opened")
        if "error" in st:
            out["error"] = st["error"]
        if self.jogging:
            out["jog"] = "jogging %s" % ("+" if self.jogging > 0 else "-")
        return out


__all__ = ["CanAxis", "JOG_LEASE_S", "MODE_NAMES", "POLL_S"]


def parse_node_id(text):
    """A CANopen node id typed on the page: 1..127, else a UserError in one sentence."""
    try:
        nid = int(str(text).strip(), 0)
    except ValueError:
        raise UserError("the node id must be a number 1..127, not %r" % str(text)) from None
    if not 1 <= nid <= 127:
        raise UserError("the node id must be 1..127, not %d" % nid)
    return nid
