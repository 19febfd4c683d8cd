"""The Desk's CAN tab (NiceGUI): the jig's CAN port, its CANopen nodes, a live frame log, SDO and NMT.

Layout only: the work is ``canlink.CanLink``, one per Desk server and shared by
every browser tab as the bus session is. The tab opens the jig's SLCAN port (its
third USB port, or the bench's) itself, apart from the Plus-R connection of the
other tabs; the jig's own CAN counters (ReadCanCounters, 0xFA) come through that
Plus-R connection, as the diagnostics tab reads the jig's counters.

Clicks run the link's methods in a worker thread (``run.io_bound``): an SDO
transfer waits for its node, the page never does. A timer copies the link's
state, its node list and the frames logged since the last tick into the widgets
five times a second; the log shows the newest frames at the bottom, at most
``LOG_LINES`` of them, and at most ``PUSH_MAX`` new ones a tick (a busier bus is
summed up in one line: Save log has all the link keeps). Every failure is one
sentence in the tab (``can-message``) and a notification, never a traceback.

The CiA 402 axis card drives one node through ``link.axis`` (``canaxis.CanAxis``):
Enable, Disable, Fault reset, Halt, Quick stop, profile position moves and a jog held
down (renewed every refresh while the button is held); the header's STOP AXIS,
EMERGENCY STOP and Esc reach it through ``page.DeskPage._stop``.
"""

import time

from nicegui import run, ui

from motorjig.desk.widgets import Changed, run_action, tid
from motorjig.desk.session import UserError

LOG_LINES = 500  # lines the browser keeps in the frame log
PUSH_MAX = 400  # new lines shown a tick (0.2 s: 2000 frames/s, a scan whole); more are summed up in one line
REFRESH_S = 0.2

#: machine.CAN's controller states (the jig's can_state counter)
CAN_STATES = {0: "stopped", 1: "error active", 2: "error warning", 3: "error passive", 4: "bus-off"}


def jig_can_counters(session):
    """The jig's CAN counters ({name: value}) through the Desk's Plus-R connection (ReadCanCounters, 0xFA)."""
    from motorjig.master import Master

    if not hasattr(Master, "can_counters"):
        raise UserError("this jigctl cannot read the jig's CAN counters (ReadCanCounters, 0xFA)")
    jig = session.jig_id()
    try:
        res = session._bus(lambda m: m.can_counters(jig))
    except UserError as exc:
        raise UserError("the jig's CAN counters come through its PC port: %s" % exc) from None
    return dict(res.items() if hasattr(res, "items") else res)


class CanTab:
    """The CAN tab of one browser tab. ``link``: the server's CanLink, or None: then ``why`` says why
    the tab has nothing to offer (python-can or canopen missing)."""

    def __init__(self, page, link, why=None):
        self.page = page
        self.s = page.s
        self.link = link
        self.why = why
        self.changed = Changed()
        self.seq = 0
        self.paused = False

    # --- actions --------------------------------------------------------------------------------------
    async def act(self, fn, *args, quiet=False):
        """Run a link method off the event loop; its sentence (unless quiet), or its failure's, in the tab."""
        res = await run_action(fn, args, self._say, UserError)
        if isinstance(res, str) and not quiet:
            self._say(res)
        return res

    def _say(self, text, error=False):
        self.message.text = text
        self.message.classes(replace="text-red-9" if error else "text-grey-9")
        ui.notify(text, type="negative" if error else None, position="bottom-right", multi_line=error,
                  timeout=8000 if error else 3000)

    # --- layout ---------------------------------------------------------------------------------------------
    def build(self):
        if self.link is None:
            tid(ui.label(self.why or "no CAN port"), "can-unavailable").classes("text-red-9")
            return
        link = self.link
        from motorjig.desk.canlink import BITRATES, NMT_CHOICES

        with ui.row().classes("items-end"):
            self.port = tid(ui.input("SLCAN port or pyserial URL", value=link.url,
                                     placeholder="/dev/ttyACM2, COM9, socket://127.0.0.1:5002"),
                            "can-port").classes("w-80")
            self.bitrate = tid(ui.select({b: "%g kbit/s" % (b / 1000) for b in BITRATES}, value=link.bitrate,
                                         label="bitrate"), "can-bitrate").classes("w-32")
            tid(ui.button("Open", icon="power", on_click=self._open), "btn-can-open")
            tid(ui.button("Close", on_click=lambda: self.act(link.close)), "btn-can-close").props("outline")
            self.state = tid(ui.label(link.summary()), "can-state").classes("q-ml-md")
        self.message = tid(ui.label(""), "can-message").classes("text-grey-9")
        if link.read_only:
            ui.label("read-only Desk: the port is opened listen-only (SLCAN's L) and only listened to (no scan, SDO, NMT "
                     "or axis commands)") \
                .classes("text-caption text-grey-7")
        self._nodes_card(NMT_CHOICES)
        with ui.row().classes("w-full no-wrap items-start"):
            with ui.column().classes("w-3/5"):
                self._sdo_card()
            with ui.card().classes("w-2/5"):
                self._counters_card()
        self._axis_card()
        self._log_card()
        ui.timer(REFRESH_S, self.refresh)

    def _nodes_card(self, nmt_commands):
        with ui.card().classes("w-full"):
            with ui.row().classes("items-center"):
                ui.label("Nodes").classes("text-subtitle1")
                tid(ui.button("Scan", icon="search", on_click=self._scan), "btn-can-scan")
                ui.separator().props("vertical")
                self.nmt_command = tid(ui.select(nmt_commands, value="start", label="NMT"),
                                       "can-nmt-command").classes("w-48")
                self.nmt_node = tid(ui.input("node (0 = all)", value="0"), "can-nmt-node").classes("w-28")
                tid(ui.button("Send NMT", on_click=self._nmt), "btn-can-nmt").props("outline")
            cols = [{"name": k, "label": label, "field": k, "align": "left"} for k, label in (
                ("id", "node"), ("nmt", "NMT state"), ("name", "name (0x1008)"), ("profile", "profile"),
                ("device_type", "device type (0x1000)"), ("vendor", "vendor (0x1018:1)"),
                ("product", "product (:2)"), ("revision", "revision (:3)"), ("serial", "serial (:4)"))]
            self.nodes = tid(ui.table(columns=cols, rows=[], row_key="id", pagination={"rowsPerPage": 0}),
                             "can-nodes").classes("w-full").props("dense hide-pagination")
            ui.label("Scan: python-canopen's scanner (an SDO upload of 0x1000 to ids 1..127), then each node's "
                     "name and identity by SDO; the NMT state is the node's last heartbeat.") \
                .classes("text-caption text-grey-7")

    def _axis_card(self):
        """The CiA 402 axis (``canaxis.CanAxis``): its state, the power state machine, moves, jog, stops."""
        ax = self.link.axis
        with tid(ui.card(), "can-axis").classes("w-full"):
            with ui.row().classes("items-end"):
                ui.label("CiA 402 axis").classes("text-subtitle1")
                self.axis_node = tid(ui.input("node", value="" if ax.node_id is None else str(ax.node_id)),
                                     "can-axis-node").classes("w-20")
                self.axis_node.on("blur", self._axis_watch)
                self.axis_node.on("keydown.enter", self._axis_watch)
                tid(ui.button("Enable", icon="power_settings_new", on_click=lambda: self._axis(ax.enable)),
                    "btn-can-enable").props("color=green")
                tid(ui.button("Disable", on_click=lambda: self._axis(ax.disable)), "btn-can-disable") \
                    .props("outline")
                tid(ui.button("Fault reset", on_click=lambda: self._axis(ax.fault_reset)), "btn-can-fault-reset") \
                    .props("outline")
                ui.separator().props("vertical")
                tid(ui.button("Halt", on_click=lambda: self._axis(ax.halt)), "btn-can-halt").props("color=orange") \
                    .tooltip("controlword bit 8: a decelerating stop, the drive stays enabled (STOP AXIS does it too)")
                tid(ui.button("Quick stop", on_click=lambda: self._axis(ax.quick_stop)), "btn-can-quick-stop") \
                    .props("color=red").tooltip("controlword QUICK STOP, as the drive's 0x605A says "
                                                "(EMERGENCY STOP and Esc do it too)")
            # the buttons above the status: a status line that grows or wraps never moves a held jog
            # button from under the pointer (that would be a mouseleave: a release)
            with ui.row().classes("items-end"):
                self.axis_target = tid(ui.input("target / distance (counts)", value="10000"),
                                       "can-axis-target").classes("w-44")
                self.axis_speed = tid(ui.input("speed (counts/s)", value="20000"), "can-axis-speed").classes("w-32")
                self.axis_acc = tid(ui.input("accel (counts/s²)", placeholder="drive's"), "can-axis-acc") \
                    .classes("w-32")
                self.axis_dec = tid(ui.input("decel (counts/s²)", placeholder="drive's"), "can-axis-dec") \
                    .classes("w-32")
                tid(ui.button("Move ABS", on_click=lambda: self._axis_move("abs")), "btn-can-move-abs")
                tid(ui.button("Move REL", on_click=lambda: self._axis_move("rel")), "btn-can-move-rel") \
                    .props("outline")
                for sign, text in ((-1, "Jog −"), (1, "Jog +")):
                    b = tid(ui.button(text), "btn-can-jog-%s" % ("minus" if sign < 0 else "plus")).props("outline")
                    b.on("mousedown", lambda _, d=sign: self._jog_press(d))
                    b.on("touchstart", lambda _, d=sign: self._jog_press(d))
                    for ev in ("mouseup", "mouseleave", "touchend"):
                        b.on(ev, lambda _: self._jog_release())
            grid = (("state", "state (0x6041)"), ("mode", "mode (0x6061)"), ("position", "position (0x6064)"),
                    ("velocity", "velocity (0x606C)"), ("following_error", "following error (0x60F4)"),
                    ("fault", "fault (0x603F)"), ("emcy", "last EMCY"))
            self.axis_fields = {}
            with ui.grid(columns="auto 1fr").classes("gap-x-4 gap-y-0"):
                for key, label in grid:
                    ui.label(label).classes("text-grey-7")
                    self.axis_fields[key] = tid(ui.label(""), "can-axis-" + key.replace("_", "-")).classes("font-mono")
            self.axis_error = tid(ui.label(""), "can-axis-error").classes("text-red-9")
            ui.label("Moves in profile position (0x6060 = 1, the new-set-point handshake); jog in profile velocity "
                     "(0x6060 = 3) while the button is held, at the speed field's value. Enable follows the "
                     "CiA 402 power state machine to OPERATION ENABLED; Disable quick-stops, then SWITCH ON "
                     "DISABLED. Closing the port or the Desk disables a node enabled here first.") \
                .classes("text-caption text-grey-7")
        self.axis_jogging = False
        self.stops_seen = None

    async def _axis(self, fn, *args, quiet=False):
        return await self.act(fn, *args, self.axis_node.value, quiet=quiet)

    async def _axis_watch(self, _e=None):
        if str(self.axis_node.value or "").strip():
            await self.act(self.link.axis.watch, self.axis_node.value)

    async def _axis_move(self, kind):
        await self._axis(self.link.axis.move, kind, self.axis_target.value, self.axis_speed.value,
                         self.axis_acc.value, self.axis_dec.value)

    async def _jog_press(self, direction):
        self.axis_jogging = True
        # quiet: a notification popping up under the pointer would be a mouseleave (a release)
        if await self._axis(self.link.axis.jog, direction, self.axis_speed.value, quiet=True) is None:
            self.axis_jogging = False

    async def _jog_release(self):
        if self.axis_jogging:  # mouseleave fires without a press too
            self.axis_jogging = False
            await self.act(self.link.axis.jog_release, quiet=True)

    def _refresh_axis(self):
        ax = self.link.axis
        if self.axis_jogging:
            ax.jog_alive()
        if self.stops_seen != ax.stop_seq:  # a STOP from the header (or another tab): the last move is over
            if self.stops_seen is not None:
                self.message.text = "the axis was stopped (%s)" % time.strftime("%H:%M:%S")
                self.message.classes(replace="text-grey-9")
            self.stops_seen = ax.stop_seq
        fields = ax.describe()
        if self.changed("axis", repr(fields)):
            for key, label in self.axis_fields.items():
                label.text = fields.get(key, "")
            self.axis_error.text = fields.get("error", "")

    def _sdo_card(self):
        with ui.card().classes("w-full"):
            with ui.row().classes("items-end"):
                ui.label("SDO").classes("text-subtitle1")
                rows = self.link.node_rows()  # (a reload: the node scanned before is still the one to ask)
                self.sdo_node = tid(ui.input("node", value=str(rows[0]["id"]) if rows else ""),
                                    "can-sdo-node").classes("w-20")
                self.sdo_object = tid(ui.input("object: index:sub or EDS name", value="0x1008",
                                               placeholder="0x6041, 0x1018:2, Producer heartbeat time"),
                                      "can-sdo-object").classes("w-60")
                self.sdo_value = tid(ui.input("value to write"), "can-sdo-value").classes("w-32")
                tid(ui.button("Read", on_click=self._sdo_read), "btn-can-sdo-read")
                tid(ui.button("Write", on_click=self._sdo_write), "btn-can-sdo-write").props("outline")
            self.sdo_node.on("keydown.enter", self._sdo_read)
            self.sdo_object.on("keydown.enter", self._sdo_read)
            self.sdo_value.on("keydown.enter", self._sdo_write)
            self.sdo_result = tid(ui.label(""), "can-sdo-result").classes("font-mono")
            ui.label("Values are typed as the EDS says (numbers in decimal or 0x hex, text as typed, bytes in "
                     "hex); a node's refusal is shown with its abort code by name.").classes("text-caption text-grey-7")

    def _counters_card(self):
        with ui.row().classes("items-center"):
            ui.label("The jig's CAN port").classes("text-subtitle1")
            tid(ui.button("Read", on_click=self._read_counters), "btn-can-counters").props("outline dense")
            self.counters_auto = tid(ui.switch("every second"), "can-counters-auto")
        cols = [{"name": "name", "label": "counter", "field": "name", "align": "left"},
                {"name": "value", "label": "value", "field": "value", "align": "right"}]
        self.counters = tid(ui.table(columns=cols, rows=[], row_key="name", pagination={"rowsPerPage": 0}),
                            "can-counters").classes("w-full").props("dense hide-pagination") \
            .style("max-height: 24rem")  # about 30 counters: the table scrolls
        self.counters_note = tid(ui.label("through the jig's PC port (Connect & bus), as the diagnostics tab "
                                          "reads them"), "can-counters-note").classes("text-caption text-grey-7")
        ui.timer(1.0, lambda: self._read_counters(auto=True) if self.counters_auto.value else None)

    def _log_card(self):
        with ui.row().classes("items-center q-mt-sm"):
            ui.label("Frames").classes("text-subtitle1")
            tid(ui.switch("pause", on_change=lambda e: setattr(self, "paused", e.value)), "can-log-pause")
            tid(ui.button("Clear", on_click=self._clear_log), "btn-can-log-clear").props("outline dense")
            tid(ui.button("Save log", icon="download", on_click=self._save_log), "btn-can-log-save") \
                .props("outline dense")
            self.log_count = tid(ui.label(""), "can-log-count").classes("text-caption")
        self.log_view = tid(ui.log(max_lines=LOG_LINES), "can-log").classes("w-full h-96 text-xs")

    # --- callbacks ----------------------------------------------------------------------------------------------
    async def _open(self):
        await self.act(self.link.open, self.port.value, self.bitrate.value)

    async def _scan(self):
        rows = await self.act(self.link.scan)
        if rows is not None:
            found = ", ".join("%d %s" % (r["id"], r["name"] or "?") for r in rows)
            self._say("scan: %d node(s)%s" % (len(rows), ": " + found if found else " answered"))
            if rows and not str(self.sdo_node.value or "").strip():
                self.sdo_node.value = str(rows[0]["id"])
            cia402 = [r["id"] for r in rows if "402" in r.get("profile", "")]
            if cia402 and not str(self.axis_node.value or "").strip():
                self.axis_node.value = str(cia402[0])
                await self._axis_watch()

    async def _nmt(self):
        await self.act(self.link.nmt, self.nmt_command.value, self.nmt_node.value)

    async def _sdo_read(self):
        res = await self.act(self.link.sdo_read, self.sdo_node.value, self.sdo_object.value)
        if res is not None:
            self._sdo_show("node %s %s = %s" % (str(self.sdo_node.value).strip(), res[0], res[1]))
        else:  # the refusal in the result's place: never an earlier answer under a field that names another
            self.sdo_result.text = self.message.text

    async def _sdo_write(self):
        res = await self.act(self.link.sdo_write, self.sdo_node.value, self.sdo_object.value, self.sdo_value.value)
        if res is not None:
            self._sdo_show("node %s %s := %s written" % (str(self.sdo_node.value).strip(), res[0], res[1]))
        else:
            self.sdo_result.text = self.message.text

    def _sdo_show(self, text):
        self.sdo_result.text = text
        self.message.text = text
        self.message.classes(replace="text-grey-9")

    async def _read_counters(self, auto=False):
        try:
            res = await run.io_bound(jig_can_counters, self.s)
        except UserError as exc:
            if auto:  # every second: said once in the note, not in a notification each time
                self.counters_note.text = str(exc)
            else:
                self._say(str(exc), error=True)
            return
        if not res:
            self.counters_note.text = "the jig has no CAN port (its ReadCanCounters reply is empty)"
            return
        self.counters.rows = [{"name": k, "value": "%d (%s)" % (v, CAN_STATES.get(v, "?")) if k == "can_state" else v}
                              for k, v in res.items()]
        self.counters.update()
        self.counters_note.text = "read %s through the jig's PC port" % time.strftime("%H:%M:%S")

    def _clear_log(self):
        self.link.clear_log()
        self.log_view.clear()

    def _save_log(self):
        ui.download.content(self.link.log_text(), time.strftime("motorjig-can-%Y%m%d-%H%M%S.log"), "text/plain")

    # --- the refresh --------------------------------------------------------------------------------------------
    def refresh(self):
        from motorjig.desk.canlink import format_entry

        link, ch = self.link, self.changed
        summary = link.summary() + (" (scanning ...)" if link.scanning else "")
        if ch("state", summary):
            self.state.text = summary
            self.state.classes(replace="text-red-9" if link.state == "lost" else "")
        self._refresh_axis()
        rows = link.node_rows()
        if ch("nodes", repr(rows)):
            self.nodes.rows = rows
            self.nodes.update()
        if self.paused:
            return
        new = link.frames_since(self.seq)
        if not new:
            return
        self.seq = new[-1].seq
        if len(new) > PUSH_MAX:
            self.log_view.push("... %d frames not shown here (a busy bus: Save log keeps the newest %d)"
                               % (len(new) - PUSH_MAX, link.keep))
            new = new[-PUSH_MAX:]
        for e in new:
            self.log_view.push(format_entry(e))
        if ch("count", link.last_seq):
            self.log_count.text = "%d frames logged" % link.last_seq


def make_link(url="", bitrate=500000, read_only=False):
    """(CanLink, None), or (None, the sentence) when python-can or canopen is missing."""
    try:
        from motorjig.desk.canlink import CanLink
    except ImportError as exc:
        return None, ("the CAN tab needs python-can and canopen (%s is missing): pip install the [can] extra "
                      "(make setup)" % exc.name)
    return CanLink(url, bitrate, read_only=read_only), None


__all__ = ["CanTab", "jig_can_counters", "make_link"]
