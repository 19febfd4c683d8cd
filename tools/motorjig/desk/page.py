"""The MotorJig Desk page (NiceGUI): layout only; state and bus work live in ``session``.

Every browser tab gets its own copy of the page, all showing the one shared
``BusSession`` (and the one ``testrun.Station`` of the Test tab, ``runpanel``).
Clicks run the session's methods in a worker thread (``run.io_bound``) so a slow
bus never freezes the page; a per-tab timer copies the session's state into the
widgets ten times a second, touching only what changed. Elements that tests and
people look for carry a ``data-testid``.

The raw-frames tab also records both buses through the jig (``capture.DeskCapture``,
one per server like the session): Start, Stop and Download pcapng, greyed out with
the reason beside them when the Desk has no capture port.

The CAN tab (``cantab``) opens the jig's SLCAN port itself, apart from the Plus-R
connection: its ``canlink.CanLink`` is one per server too.

STOP AXIS, EMERGENCY STOP and Esc also halt / quick-stop the CAN tab's CiA 402 axis
(``canaxis.CanAxis.stop``), before the Plus-R axes.
Esc is EMERGENCY STOP wherever the focus is, except while a dialog or a dropdown
is open: then Esc is theirs (it closes them) and stops nothing.
"""

import time

from nicegui import run, ui
from serial.tools import list_ports

from motorjig import names as N
from motorjig.master import BAUD_RATES

from motorjig.desk import forms
from motorjig.desk.widgets import Changed, tid
from motorjig.desk.session import ESTOP_RECOVERY, MOVES, UserError, protocol_name, stamp

CSS = """
.lamp {display:inline-block; padding:1px 7px; margin:2px; border-radius:9px; font-size:11px;
       background:#e6e6e6; color:#666; font-family:monospace}
.lamp.on {background:#2e7d32; color:#fff}
.lamp.err {background:#c62828; color:#fff}
.big-num {font-family:monospace; font-size:1.6rem; text-align:right; min-width:9rem}
.estop {font-weight:800; letter-spacing:.05em}
.chip {display:inline-block; padding:1px 8px; border-radius:4px; font-size:12px; font-weight:700;
       background:#546e7a; color:#fff; letter-spacing:.04em}
.chip.ro {background:#ffb300; color:#000}
.header-axis {min-width:13rem}
.header-axis .q-field__native, .header-axis .q-field__label, .header-axis .q-select__dropdown-icon {color:#fff}
.enter-hint .q-btn__content::after {content:"⏎"; opacity:.75; margin-left:.4em}
"""

# Esc on keydown, before Quasar sees it (it closes its dialogs and menus on keyup): an
# open dialog or dropdown (one not already fading out) takes the key for itself.
ESC_SCRIPT = """
<script>
window.addEventListener('keydown', (e) => {
  if (e.key !== 'Escape' || e.repeat) return;
  const open = Array.from(document.querySelectorAll('.q-dialog__inner, .q-menu'))
    .some(el => !/-leave-(active|to)/.test(el.className));
  if (!open) emitEvent('motorjig_estop');
}, true);
</script>
"""

PLOT_WINDOWS = {10: "10 s", 30: "30 s", 60: "60 s", 120: "120 s"}

#: the Ver6/Ver8 choice on Connect & bus -> Master's ver8 (None: each slave's variant detected)
PROTOCOLS = {"auto": "auto (detect each slave)", "6": "Ver6 only", "8": "Ver8 only"}
PROTOCOL_VER8 = {"auto": None, "6": False, "8": True}


def protocol_key(ver8):
    return "auto" if ver8 is None else "8" if ver8 else "6"


def build(session, station=None, capture=None, can_link=None, extra=()):
    """Register the page (and the run files' route) for one BusSession, its Station, its
    DeskCapture (None: a Desk without a capture port) and its CAN tab's ``canlink.CanLink``
    (None: one without a port chosen yet); ``extra``: (module, link, why) of each drive kind's tab
    (``kindtabs``)."""
    from nicegui import app
    from fastapi import HTTPException
    from fastapi.responses import FileResponse

    from motorjig.desk.cantab import make_link
    from motorjig.desk.testrun import FILE_KINDS

    can_why = None
    if can_link is None:
        can_link, can_why = make_link(read_only=session.read_only)

    @ui.page("/")
    async def index():
        DeskPage(session, station, capture, can_link, can_why, extra).build()

    @app.get("/runs/{name}")
    def run_file(name: str):
        """A file of the output folder: a run's record, JUnit XML or report."""
        path = station.file_path(name) if station is not None else None
        if path is None:
            raise HTTPException(status_code=404, detail="no such run file")
        return FileResponse(path, media_type=FILE_KINDS[name.rsplit(".", 1)[-1]])

    @app.get("/report/{run_id}")
    def stored_report(run_id: int):
        """The HTML report of a run in the results database, wherever it was written."""
        path = station.report_path(run_id) if station is not None else None
        if path is None:
            raise HTTPException(status_code=404, detail="no report of run %d" % run_id)
        return FileResponse(path, media_type=FILE_KINDS["html"])


class DeskPage:
    """One browser tab's widgets and the callbacks that feed them."""

    def __init__(self, session, station=None, capture=None, can_link=None, can_why=None, extra=()):
        self.s = session
        self.extra = list(extra)  # (module, link, why) of the drive kinds' own tabs (kindtabs)
        self.can_link = can_link  # the CAN tab's link (one per server), or None: can_why says why
        self.can_why = can_why
        self.station = station
        if capture is None:
            from motorjig.desk.capture import DeskCapture

            capture = DeskCapture()
        self.capture = capture
        self.test_panel = None
        self.last_move = session.last_move  # what Enter in a move field repeats (the session's, every tab)
        self.changed = Changed()
        self.log_seq = 0
        self.lamps = {}
        self.plot_paused = False
        self.plot_window = 30
        self.jogging = False

    # --- running actions -----------------------------------------------------------------
    async def act(self, fn, *args, quiet=False):
        """Run a session method off the event loop; show its sentence or its error."""
        try:
            msg = await run.io_bound(fn, *args)
        except (UserError, forms.InputError) as exc:
            if str(exc) != self.s.lost_message():  # losing the line is logged once, by the session
                self.s.log("error", str(exc))
            ui.notify(str(exc), type="negative", position="bottom-right", multi_line=True, timeout=8000)
            return None
        except Exception as exc:  # a bug: one sentence on the page, never a traceback
            self.s.log("error", "internal error (%s: %s)" % (type(exc).__name__, exc))
            ui.notify("internal error (%s: %s)" % (type(exc).__name__, exc), type="negative")
            return None
        if isinstance(msg, str) and not quiet:
            ui.notify(msg, position="bottom-right")
        return msg

    # --- layout ----------------------------------------------------------------------------
    def build(self):
        ui.add_css(CSS)
        s = self.s
        # Both fire again when a tab's websocket reconnects, so the count stays right.
        ui.context.client.on_connect(self._seen)
        ui.context.client.on_disconnect(self._gone)
        with ui.header().classes("items-center bg-blue-grey-9 q-py-xs"):
            ui.label("MotorJig Desk").classes("text-h6")
            self.conn_label = tid(ui.label(""), "conn-state").classes("q-ml-md")
            self.axis_select = tid(ui.select({}, label="axis", on_change=self._pick_axis), "axis-select") \
                .props("dense borderless options-dense").classes("q-ml-md header-axis")
            self.protocol_chip = tid(ui.label(""), "protocol").classes("chip")
            with self.protocol_chip:
                self.protocol_tip = ui.tooltip("")
            if s.read_only:
                tid(ui.label("READ-ONLY"), "read-only").classes("chip ro").tooltip(
                    "started with --read-only: the page shows the status and the runs and sends nothing")
            ui.space()
            tid(ui.button("STOP AXIS", on_click=lambda: self._stop(False)), "btn-stop").props("color=orange") \
                .tooltip("decelerating stop of the selected axis (also ends a motion test or a scan; the CAN "
                         "tab's CiA 402 axis: halt)")
            tid(ui.button("EMERGENCY STOP (Esc)", on_click=lambda: self._stop(True)),
                "btn-estop").props("color=red size=lg").classes("estop")
        ui.add_body_html(ESC_SCRIPT)
        ui.on("motorjig_estop", self._esc)
        with tid(ui.card(), "lost-banner").classes("w-full bg-red-1") as self.lost_banner:
            with ui.row().classes("items-center"):
                ui.icon("link_off", color="red", size="md")
                self.lost_text = tid(ui.label(""), "lost-text").classes("text-red-9")
                tid(ui.button("Reconnect", on_click=self._reconnect), "btn-reconnect")
        self.lost_banner.set_visibility(False)
        with tid(ui.card(), "safety-notice").classes("w-full bg-amber-1") as self.notice_banner:
            with ui.row().classes("items-center"):
                ui.icon("warning", color="orange", size="md")
                self.notice_text = tid(ui.label(""), "safety-notice-text")
                tid(ui.button("OK", on_click=self._notice_seen), "btn-safety-notice-ok").props("flat dense")
        self.notice_banner.set_visibility(False)
        with ui.tabs().classes("w-full") as tabs:
            made = [(testid, tid(ui.tab(label), testid), build) for testid, label, build in self._tab_list()]
        self.tabs = tabs
        opened = dict((testid, tab) for testid, tab, _build in made)
        first = opened["tab-connect"] if not s.connected or s.axis is None else opened["tab-axis"]
        # Not animated: a sliding panel is half-way across the screen when the operator clicks in it.
        with ui.tab_panels(tabs, value=first, animated=False).classes("w-full"):
            for _testid, tab, build in made:
                with ui.tab_panel(tab):
                    build()
        ui.timer(0.1, self._refresh)
        ui.timer(0.25, self._refresh_plot)

    def _tab_list(self):
        """The page's tabs in order: (test id, label, the method that builds its panel). The Test tab is
        there when the Desk has a station."""
        tabs = [("tab-connect", "Connect & bus", self._connect_panel)]
        if self.station is not None:
            tabs.append(("tab-plan", "Test", self._plan_tab))
        return tabs + [("tab-axis", "Axis", self._axis_panel), ("tab-test", "Motion test", self._test_panel),
                       ("tab-params", "Parameters", self._param_panel), ("tab-io", "I/O", self._io_panel),
                       ("tab-diag", "Jig diagnostics", self._diag_panel),
                       ("tab-raw", "Raw frames & log", self._raw_panel), ("tab-can", "CAN", self._can_tab)] + [
            (m.TAB_ID, m.LABEL, (lambda m=m, link=link, why=why: m.Tab(self, link, why).build()))
            for m, link, why in self.extra]

    def _plan_tab(self):
        from motorjig.desk.runpanel import TestPanel

        self.test_panel = TestPanel(self, self.station)
        self.test_panel.build()

    def _can_tab(self):
        from motorjig.desk.cantab import CanTab

        CanTab(self, self.can_link, self.can_why).build()

    def _seen(self):
        self.s.viewers += 1

    def _gone(self):
        self.s.viewers = max(0, self.s.viewers - 1)

    async def _esc(self, _e=None):
        await self._stop(True)

    def _axes(self):
        """Every axis STOP reaches, in order (``axes.DeskAxis``): the tabs' own (the CAN tab's: halt /
        quick stop of the nodes it enabled or watches), then the bus session's (the selected axis; a
        running motion test, scan or test run)."""
        tabs = [self.can_link.desk_axis] if self.can_link is not None else []
        tabs += [link.desk_axis for _m, link, _why in self.extra if link is not None]
        return tabs + [self.s.desk_axis]

    async def _stop(self, emergency):
        """STOP AXIS / EMERGENCY STOP / Esc: every axis of ``_axes`` in turn. An axis that is not
        there (the bus not connected) is left out when another one stopped something, so the
        operator reads what was stopped, not a refusal."""
        stopped = False
        for axis in self._axes():
            if stopped and not axis.present():
                continue
            stopped = bool(await self.act(axis.stop, emergency)) or stopped

    def _notice_seen(self):
        self.s.safety_notice = ""  # said: every tab lets it go

    async def _reconnect(self):
        await self.act(self.s.reconnect)

    # --- connect & bus ------------------------------------------------------------------------
    def _connect_panel(self):
        s = self.s
        with ui.row().classes("items-end"):
            self.port = tid(ui.input("Port or pyserial URL", value=s.url,
                                     placeholder="/dev/ttyUSB0, COM7, socket://127.0.0.1:5000"),
                            "port").classes("w-80")
            self.port_pick = tid(ui.select([], label="serial ports", on_change=self._pick_port), "port-list") \
                .classes("w-56")
            ui.button(icon="refresh", on_click=self._refresh_ports).props("flat").tooltip("refresh the port list")
            self.baud = tid(ui.select(list(BAUD_RATES), value=s.baud, label="baud"), "baud").classes("w-32")
            self.protocol = tid(ui.select(PROTOCOLS, value=protocol_key(s.ver8), label="Ver6/Ver8"),
                                "protocol-pick").classes("w-52").tooltip(
                "auto: each slave's variant is detected, as jigctl scan does (a bus may carry both); "
                "Ver6 only / Ver8 only: one framing for every slave")
            tid(ui.button("Connect", on_click=self._connect), "btn-connect")
            tid(ui.button("Disconnect", on_click=lambda: self.act(s.disconnect)), "btn-disconnect").props("outline")
        self._refresh_ports()
        ui.separator()
        with ui.row().classes("items-center"):
            tid(ui.button("Scan", icon="search", on_click=self._scan), "btn-scan")
            tid(ui.button("Scan via jig", on_click=self._scan_via_jig), "btn-scan-jig").props("outline")
            self.scan_label = tid(ui.label(""), "scan-progress")
            self.scan_bar = ui.linear_progress(value=0, show_value=False).classes("w-48")
            self.scan_bar.set_visibility(False)
        cols = [{"name": "id", "label": "id", "field": "id", "align": "left"},
                {"name": "type", "label": "slave type", "field": "type", "align": "left"},
                {"name": "type_name", "label": "name", "field": "type_name", "align": "left"},
                {"name": "version", "label": "version", "field": "version", "align": "left"},
                {"name": "protocol", "label": "protocol", "field": "protocol", "align": "left"},
                {"name": "role", "label": "role", "field": "role", "align": "left"}]
        self.slave_table = tid(ui.table(columns=cols, rows=[], row_key="id"), "slave-table").classes("w-full").props("dense")
        with ui.row().classes("items-center"):
            ui.label("Axis to work with:")
            self.axis_pick = tid(ui.toggle({}, on_change=self._pick_axis), "axis-pick")

    def _refresh_ports(self):
        ports = sorted(p.device for p in list_ports.comports())
        self.port_pick.set_options(ports)
        if not ports:
            self.port_pick.props('hint="no serial ports found"')

    def _pick_port(self, e):
        if e.value:
            self.port.value = e.value

    async def _connect(self):
        await self.act(self.s.connect, self.port.value, self.baud.value,
                       PROTOCOL_VER8.get(self.protocol.value or "auto"))

    async def _scan(self):
        rows = await self.act(self.s.scan, quiet=True)
        if rows is not None:
            ui.notify("scan: %d slave(s) found" % len(rows), position="bottom-right")

    async def _scan_via_jig(self):
        rows = await self.act(self.s.scan_via_jig, quiet=True)
        if rows is not None:
            ui.notify("scan via jig: %d slave(s)" % len(rows), position="bottom-right")

    async def _pick_axis(self, e):
        if e.value is not None and e.value != self.s.axis:
            await self.act(self.s.select_axis, e.value, quiet=True)
            self.changed.last.pop("axis_pick", None)  # a refused choice shows the session's axis again

    # --- axis panel, motion and plot -------------------------------------------------------------
    def _axis_panel(self):
        s = self.s
        with ui.row().classes("w-full no-wrap items-start"):
            with ui.card().classes("w-1/2"):
                with ui.grid(columns=4).classes("items-center"):
                    for label, key in (("command position", "cmd-pos"), ("actual position", "act-pos"),
                                       ("position error", "pos-err"), ("velocity (pps)", "vel")):
                        with ui.column().classes("gap-0"):
                            ui.label(label).classes("text-caption")
                            setattr(self, key.replace("-", "_"), tid(ui.label("-"), key).classes("big-num"))
                ui.label("axis status").classes("text-caption q-mt-sm")
                with tid(ui.element("div"), "lamps"):
                    for bit, name, meaning in N.AXIS_FLAGS:
                        lamp = ui.label(name).classes("lamp").props('data-flag="%s"' % name).tooltip(
                            "bit %d: %s" % (bit, meaning))
                        self.lamps[name] = lamp
                with tid(ui.row(), "estop-hint").classes("items-center bg-red-1 q-pa-xs rounded-borders") \
                        as self.estop_hint:
                    ui.icon("report", color="red")
                    ui.label(ESTOP_RECOVERY).classes("text-red-10 text-body2").style("max-width:30rem")
                    tid(ui.button("Servo OFF → ON", on_click=lambda: self.act(s.recover_estop)),
                        "btn-estop-recover").props("color=red outline dense")
                self.estop_hint.set_visibility(False)
                with ui.row().classes("text-caption"):
                    ui.label("inputs:")
                    self.inputs_label = tid(ui.label("-"), "inputs")
                with ui.row().classes("text-caption"):
                    ui.label("outputs:")
                    self.outputs_label = tid(ui.label("-"), "outputs")
                self.poll_label = tid(ui.label(""), "poll-state").classes("text-caption text-grey-7")
                with ui.row():
                    tid(ui.button("Servo ON", on_click=lambda: self.act(s.servo, True)), "btn-servo-on")
                    tid(ui.button("Servo OFF", on_click=lambda: self.act(s.servo, False)), "btn-servo-off") \
                        .props("outline")
                    tid(ui.button("Alarm reset", on_click=lambda: self.act(s.alarm_reset)), "btn-alarm-reset") \
                        .props("outline")
                    tid(ui.button("Clear position", on_click=lambda: self.act(s.clear_position)), "btn-clear-pos") \
                        .props("outline")
            with ui.card().classes("w-1/2"):
                ui.label("Motion").classes("text-subtitle1")
                last = s.move_fields
                with ui.row():
                    self.target = tid(ui.input("position / distance (pulses)", value=last["target"]), "move-target")
                    self.speed = tid(ui.input("speed (pps)", value=last["speed"]), "move-speed").classes("w-28")
                    self.acc = tid(ui.input("accel (ms)", value=last["acc"], placeholder="drive's"),
                                   "move-acc").classes("w-24")
                    self.dec = tid(ui.input("decel (ms)", value=last["dec"], placeholder="drive's"),
                                   "move-dec").classes("w-24")
                for box in (self.target, self.speed, self.acc, self.dec):
                    box.on("keydown.enter", lambda: self._move(*self.last_move))
                self.changed("move_seq", s.move_seq)  # the fields above are this move's already
                self.move_buttons = {}
                with ui.row():
                    for key, text in MOVES.items():
                        testid = "btn-" + text.lower().replace(" ", "-")  # btn-move-abs, -inc, -dec
                        self.move_buttons[key] = tid(ui.button(text, on_click=lambda k=key: self._move(*k)), testid)
                self._mark_enter()
                with ui.row().classes("items-center"):
                    ui.label("hold to jog:")
                    for sign, text in ((-1, "Jog −"), (1, "Jog +")):
                        b = tid(ui.button(text), "btn-jog-%s" % ("minus" if sign < 0 else "plus")).props("outline")
                        b.on("mousedown", lambda _, d=sign: self._jog_press(d))
                        b.on("touchstart", lambda _, d=sign: self._jog_press(d))
                        for ev in ("mouseup", "mouseleave", "touchend"):
                            b.on(ev, lambda _: self._jog_release())
                    tid(ui.button("Home", on_click=lambda: self.act(s.home)), "btn-home").props("outline")
                    tid(ui.button("Limit −", on_click=lambda: self.act(s.to_limit, -1, self.speed.value)),
                        "btn-limit-minus").props("outline")
                    tid(ui.button("Limit +", on_click=lambda: self.act(s.to_limit, 1, self.speed.value)),
                        "btn-limit-plus").props("outline")
                ui.label("Leave accel/decel blank to use the drive's parameters 3 and 4; filled in, the move is "
                         "sent as MoveAbsPosEx / MoveIncPosEx with its own times. Enter in a field repeats the "
                         "move marked ⏎ (the last one used).").classes("text-caption text-grey-7")
        with ui.card().classes("w-full"):
            with ui.row().classes("items-center"):
                ui.label("Live plot").classes("text-subtitle1")
                tid(ui.switch("pause", on_change=lambda e: setattr(self, "plot_paused", e.value)), "plot-pause")
                tid(ui.select(PLOT_WINDOWS, value=self.plot_window, label="window",
                              on_change=lambda e: setattr(self, "plot_window", e.value)), "plot-window").classes("w-24")
                tid(ui.button("Export CSV", icon="download", on_click=self._export_csv), "btn-csv").props("outline")
                self.plot_points = tid(ui.label("0 points"), "plot-points").classes("text-caption")
            self.chart = tid(ui.echart({
                "animation": False,
                "legend": {"top": 0},
                "tooltip": {"trigger": "axis"},
                "grid": {"left": 70, "right": 70, "top": 36, "bottom": 28},
                "xAxis": {"type": "value", "min": -self.plot_window, "max": 0,
                          "axisLabel": {"formatter": "{value} s"}},
                "yAxis": [{"type": "value", "position": "left", "scale": True},
                          {"type": "value", "position": "right", "scale": True, "splitLine": {"show": False}}],
                "series": [
                    {"name": "command position (pulses)", "type": "line", "showSymbol": False, "data": []},
                    {"name": "actual position (pulses)", "type": "line", "showSymbol": False, "data": [],
                     "lineStyle": {"type": "dashed"}},
                    {"name": "velocity (pps, right axis)", "type": "line", "showSymbol": False, "data": [],
                     "yAxisIndex": 1},
                ],
            }), "plot").classes("w-full h-72")

    def _mark_enter(self):
        for key, button in self.move_buttons.items():
            button.classes(add="enter-hint") if key == self.last_move else button.classes(remove="enter-hint")

    async def _move(self, kind, sign):
        # Move DEC moves down by the field's magnitude; the field keeps it as typed
        said = await self.act(self.s.move, kind, self.target.value, self.speed.value, self.acc.value, self.dec.value,
                              sign)
        if said is not None and (kind, sign) != self.last_move:  # a refused move leaves ⏎ where it was
            self.last_move = (kind, sign)
            self._mark_enter()
        return said

    def _take_move_fields(self):
        """Another tab (or this one) sent a move: show its values and its Enter button here, so
        Enter in this tab repeats that move and not what this tab showed before."""
        s = self.s
        if not self.changed("move_seq", s.move_seq):
            return
        fields, last = dict(s.move_fields), s.last_move
        for box, key in ((self.target, "target"), (self.speed, "speed"), (self.acc, "acc"), (self.dec, "dec")):
            if box.value != fields[key]:
                box.value = fields[key]
        if last != self.last_move:
            self.last_move = last
            self._mark_enter()

    async def _jog_press(self, direction):
        self.jogging = True
        if await self.act(self.s.jog, direction, self.speed.value, quiet=True) is None:
            self.jogging = False

    async def _jog_release(self):
        if self.jogging:  # mouseleave fires without a press too
            self.jogging = False
            await self.act(self.s.jog_release, quiet=True)

    def _export_csv(self):
        slave = "slave%s-" % self.s.axis if self.s.axis is not None else ""
        ui.download.content(self.s.history_csv(), time.strftime("motorjig-plot-" + slave + "%Y%m%d-%H%M%S.csv"),
                            "text/csv")

    # --- motion test ---------------------------------------------------------------------------------
    def _test_panel(self):
        s = self.s
        with ui.row().classes("items-end"):
            self.mt_cycles = tid(ui.input("cycles", value="3"), "mt-cycles").classes("w-24")
            self.mt_dist = tid(ui.input("distance (pulses)", value="10000"), "mt-distance")
            self.mt_speed = tid(ui.input("speed (pps)", value="20000"), "mt-speed")
            tid(ui.button("Start motion test", on_click=self._motion_test), "btn-mt-start")
            tid(ui.button("STOP TEST", on_click=lambda: self.act(s.stop_axis)), "btn-mt-stop") \
                .props("outline color=orange").tooltip("ends the motion test: the axis stops (decelerating)")
        ui.label("Each cycle moves +distance then -distance; a move passes when the command position changed "
                 "by exactly the distance and no error flag is set (the checks of jigctl motion-test).") \
            .classes("text-caption text-grey-7")
        self.mt_summary = tid(ui.label(""), "mt-summary").classes("text-h6")
        cols = [{"name": k, "label": k, "field": k, "align": "left"}
                for k in ("cycle", "distance", "start", "end", "seconds", "result", "problem")]
        self.mt_table = tid(ui.table(columns=cols, rows=[], row_key="n"), "mt-table").classes("w-full")

    async def _motion_test(self):
        await self.act(self.s.run_motion_test, self.mt_cycles.value, self.mt_dist.value, self.mt_speed.value)

    # --- parameters ------------------------------------------------------------------------------------
    def _param_panel(self):
        with ui.row().classes("items-end"):
            self.par_slave = tid(ui.input("slave id", placeholder="selected axis"), "param-slave").classes("w-28")
            tid(ui.button("Read table", icon="download", on_click=self._read_params), "btn-param-read")
            self.par_title = tid(ui.label(""), "param-title")
        with ui.row().classes("items-end"):
            self.par_key = tid(ui.input("parameter (number or name)"), "param-key").classes("w-56")
            self.par_value = tid(ui.input("new value"), "param-value").classes("w-32")
            tid(ui.button("Write to RAM", on_click=self._write_param), "btn-param-write")
            tid(ui.button("Save all to ROM…", on_click=self._confirm_save), "btn-param-save").props("outline color=red")
        cols = [{"name": k, "label": k.upper() if k in ("ram", "rom") else k, "field": k, "align": "left"}
                for k in ("number", "name", "unit", "range", "ram", "rom", "effect", "meaning")]
        self.par_table = tid(ui.table(columns=cols, rows=[], row_key="number",
                                      pagination={"rowsPerPage": 0}), "param-table").classes("w-full").props("dense")
        self.par_table.on("rowClick", lambda e: self._param_clicked(e.args))
        with ui.dialog() as self.save_dialog, ui.card():
            self.save_text = ui.label("")
            with ui.row():
                tid(ui.button("Save to ROM", on_click=self._save_params), "btn-param-save-yes").props("color=red")
                ui.button("Cancel", on_click=self.save_dialog.close).props("flat")

    def _param_slave(self):
        text = (self.par_slave.value or "").strip()
        if text:
            return forms.slave_id(text)
        if self.s.axis is None:
            raise forms.InputError("no axis selected: scan the bus, or type a slave id")
        return self.s.axis

    def _param_clicked(self, args):
        try:
            row = args[1]
            self.par_key.value = str(row["number"])
            self.par_value.value = str(row["ram"])
        except (IndexError, KeyError, TypeError):
            pass

    async def _read_params(self):
        try:
            slave = self._param_slave()
        except forms.InputError as exc:
            ui.notify(str(exc), type="negative")
            return
        self.par_title.text = "reading slave %d ..." % slave
        res = await self.act(self.s.read_params, slave, quiet=True)
        if res is None:
            self.par_title.text = ""
            return
        which, rows = res
        self.par_title.text = "%s parameters of slave %d" % (which, slave)
        self.par_table.rows = rows
        self.par_table.update()

    async def _write_param(self):
        try:
            slave = self._param_slave()
        except forms.InputError as exc:
            ui.notify(str(exc), type="negative")
            return
        value = await self.act(self.s.write_param, slave, self.par_key.value, self.par_value.value, quiet=True)
        if value is None:
            return
        ui.notify("slave %d parameter %s = %d (RAM)" % (slave, self.par_key.value, value), position="bottom-right")
        for row in self.par_table.rows:
            if str(row["number"]) == str(self.par_key.value).strip() or row["name"] == str(self.par_key.value).strip():
                row["ram"] = value
        self.par_table.update()

    def _confirm_save(self):
        try:
            slave = self._param_slave()
        except forms.InputError as exc:
            ui.notify(str(exc), type="negative")
            return
        self.save_text.text = ("Save every RAM parameter of slave %d to ROM? The drive keeps them after "
                               "power-off." % slave)
        self.save_dialog.open()

    async def _save_params(self):
        self.save_dialog.close()
        await self.act(self.s.save_params, self._param_slave())
        await self._read_params()

    # --- I/O -----------------------------------------------------------------------------------------------
    def _io_panel(self):
        with ui.row().classes("items-end"):
            self.io_slave = tid(ui.input("slave id", placeholder="selected axis"), "io-slave").classes("w-28")
            tid(ui.button("Read I/O", on_click=self._read_io), "btn-io-read")
            self.io_auto = tid(ui.switch("refresh every second"), "io-auto")
        self.io_title = ui.label("")
        ui.label("inputs").classes("text-caption")
        self.io_inputs = tid(ui.element("div"), "io-inputs")
        ui.label("outputs (click to switch)").classes("text-caption")
        self.io_outputs = tid(ui.row(), "io-outputs")
        ui.timer(1.0, lambda: self._read_io() if self.io_auto.value else None)

    async def _read_io(self):
        try:
            text = (self.io_slave.value or "").strip()
            slave = forms.slave_id(text) if text else self.s.axis
        except forms.InputError as exc:
            ui.notify(str(exc), type="negative")
            return
        if slave is None:
            ui.notify("no axis selected: scan the bus, or type a slave id", type="negative")
            return
        res = await self.act(self.s.io_bits, slave, quiet=True)
        if res is None:
            return
        inputs, outputs = res
        self.io_title.text = "slave %d (%s)" % (slave, self.s.param_table(slave)[0])
        key = ("io", slave, tuple(inputs), tuple(outputs))
        if not self.changed("io", key):
            return
        self.io_inputs.clear()
        with self.io_inputs:
            for bit, name, on in inputs:
                ui.label(name).classes("lamp on" if on else "lamp").tooltip("bit %d" % bit)
        self.io_outputs.clear()
        with self.io_outputs:
            for bit, name, on in outputs:
                tid(ui.switch(name, value=on,
                              on_change=lambda e, b=bit, sl=slave: self._set_output(sl, b, e.value)),
                    "out-%s" % name)

    async def _set_output(self, slave, bit, on):
        await self.act(self.s.set_output, slave, bit, on, quiet=True)
        self.changed.last.pop("io", None)

    # --- jig diagnostics -------------------------------------------------------------------------------------
    def _diag_panel(self):
        with ui.row().classes("items-center"):
            tid(ui.button("Read counters", on_click=self._read_counters), "btn-counters")
            self.diag_auto = tid(ui.switch("refresh every second"), "diag-auto")
            tid(ui.button("Reset counters", on_click=self._reset_counters), "btn-counters-reset").props("outline")
            tid(ui.button("Crash log", on_click=self._crash_log), "btn-crash").props("outline")
            tid(ui.button("Bus-scan result", on_click=self._scan_result), "btn-scan-result").props("outline")
        self.diag_text = tid(ui.label(""), "diag-text").classes("font-mono")
        cols = [{"name": "name", "label": "counter", "field": "name", "align": "left"},
                {"name": "value", "label": "value", "field": "value", "align": "right"}]
        self.counter_table = tid(ui.table(columns=cols, rows=[], row_key="name", pagination={"rowsPerPage": 0}),
                                 "counter-table").classes("w-96")
        ui.timer(1.0, lambda: self._read_counters() if self.diag_auto.value else None)

    async def _read_counters(self):
        res = await self.act(self.s.counters, quiet=True)
        if res is not None:
            self.counter_table.rows = [{"name": k, "value": v} for k, v in res.items()]
            self.counter_table.update()

    async def _reset_counters(self):
        await self.act(self.s.reset_counters)
        await self._read_counters()

    async def _crash_log(self):
        res = await self.act(self.s.crash_log, quiet=True)
        if res is not None:
            self.diag_text.text = "crash log: " + res

    async def _scan_result(self):
        res = await self.act(self.s.bus_scan_result, quiet=True)
        if res is not None:
            self.diag_text.text = "jig bus scan: " + res

    # --- raw frames and log -------------------------------------------------------------------------------
    def _raw_panel(self):
        s = self.s
        with ui.row().classes("items-end"):
            self.raw_id = tid(ui.input("slave id", value="2"), "raw-id").classes("w-20")
            self.raw_type = tid(ui.input("frame type (hex)", value="0x40"), "raw-type").classes("w-32")
            self.raw_data = tid(ui.input("data (hex)", placeholder="e.g. 10 27 00 00"), "raw-data")
            self.raw_corrupt = tid(ui.checkbox("break the CRC"), "raw-corrupt")
            tid(ui.button("Send", icon="send", on_click=self._send_raw), "btn-raw-send")
        with ui.row().classes("items-end"):
            self.raw_wire = tid(ui.input("or wire bytes as typed (AA CC ... AA EE, nothing added)"),
                                "raw-wire").classes("w-2/3")
        for box in (self.raw_id, self.raw_type, self.raw_data, self.raw_wire):
            box.on("keydown.enter", self._send_raw)  # Enter sends, as the Send button
        with ui.row().classes("items-center"):
            tid(ui.switch("log polling frames", value=s.log_polls,
                          on_change=lambda e: setattr(s, "log_polls", e.value)), "log-polls")
            tid(ui.button("Clear", on_click=self._clear_log), "btn-log-clear").props("outline")
            tid(ui.button("Save log", icon="download", on_click=self._save_log), "btn-log-save").props("outline")
        self.log_view = tid(ui.log(max_lines=1000), "log").classes("w-full h-96 text-xs")
        self._capture_row()

    def _capture_row(self):
        cap = self.capture
        ui.label("Recording both buses through the jig").classes("text-subtitle2 q-mt-md")
        with ui.row().classes("items-center"):
            self.cap_start = tid(ui.button("Start recording", icon="fiber_manual_record",
                                           on_click=self._capture_start), "btn-capture-start").props("outline")
            self.cap_stop = tid(ui.button("STOP RECORDING", icon="stop", on_click=self._capture_stop),
                                "btn-capture-stop").props("outline")
            self.cap_download = tid(ui.button("Download pcapng", icon="download", on_click=self._capture_download),
                                    "btn-capture-download").props("outline")
            self.cap_state = tid(ui.label(cap.summary()), "capture-state").classes("text-caption")
        ui.label("Every frame the jig receives or sends on the PC bus and on the driver bus, with its own "
                 "microsecond clock and its parser's verdict; open the file in Wireshark with the Plus-R "
                 "dissector (jigctl capture --install-dissector).").classes("text-caption text-grey-7")
        with ui.dialog() as self.cap_dialog, ui.card():
            self.cap_dialog_text = tid(ui.label(""), "capture-replace-text")
            with ui.row():
                tid(ui.button("Download pcapng", icon="download", on_click=self._capture_download_first),
                    "btn-capture-replace-download")
                tid(ui.button("Start new recording", on_click=self._capture_replace), "btn-capture-replace-yes") \
                    .props("color=red")
                tid(ui.button("Cancel", on_click=self.cap_dialog.close), "btn-capture-replace-cancel").props("flat")
        self._capture_buttons()

    def _capture_buttons(self):
        cap = self.capture
        key = (cap.unavailable, cap.state, cap.buses is not None)
        if not self.changed("capture_buttons", key):
            return
        off = bool(cap.unavailable)
        for button, enabled in ((self.cap_start, not off and cap.state not in ("recording", "starting")),
                                (self.cap_stop, not off and cap.state == "recording"),
                                (self.cap_download, not off and cap.buses is not None)):
            button.enable() if enabled else button.disable()
        if off:
            for button in (self.cap_start, self.cap_stop, self.cap_download):
                button.tooltip(cap.unavailable)

    async def _capture_start(self):
        cap = self.capture
        if cap.unsaved:  # never replace a recording nobody downloaded without asking
            self.cap_dialog_text.text = ("The last recording (%s) has not been downloaded. A new recording "
                                         "replaces it." % cap.summary())
            self.cap_dialog.open()
            return
        await self._capture_replace()

    async def _capture_replace(self):
        self.cap_dialog.close()
        await self.act(self.capture.start)
        self._capture_buttons()

    async def _capture_download_first(self):
        self.cap_dialog.close()
        await self._capture_download()

    async def _capture_stop(self):
        await self.act(self.capture.stop)
        self._capture_buttons()

    async def _capture_download(self):
        data = await self.act(self.capture.pcapng, quiet=True)
        if data is not None:
            ui.download.content(data, self.capture.file_name(), "application/x-pcapng")

    async def _send_raw(self):
        await self.act(self.s.send_raw, self.raw_id.value, self.raw_type.value, self.raw_data.value,
                       self.raw_corrupt.value, self.raw_wire.value, quiet=True)

    def _clear_log(self):
        self.s.clear_log()
        self.log_view.clear()

    def _save_log(self):
        ui.download.content(self.s.log_text(), time.strftime("motorjig-desk-%Y%m%d-%H%M%S.log"), "text/plain")

    # --- the 10 Hz refresh ------------------------------------------------------------------------------------
    def _refresh(self):
        s = self.s
        ch = self.changed
        state = s.state
        conn = {"connected": "connected: %s @ %d" % (s.url, s.baud), "lost": "CONNECTION LOST",
                "disconnected": "not connected", "lent": "test run: the plan has the port"}[state]
        if ch("conn", conn):
            self.conn_label.text = conn
        if ch("notice", s.safety_notice):
            self.notice_banner.set_visibility(bool(s.safety_notice))
            self.notice_text.text = s.safety_notice
        if ch("lost", (state, s.lost_reason)):
            self.lost_banner.set_visibility(state == "lost")
            self.lost_text.text = s.lost_message() if state == "lost" else ""
        options = {r["id"]: self._axis_label(r) for r in s.drivers()}  # never the jig
        if s.axis is not None and s.axis not in options:
            options[s.axis] = "%d" % s.axis
        if ch("axis_select", (tuple(options.items()), s.axis)):
            self.axis_select.set_options(options, value=s.axis)
        proto, tip = self._protocol_text()
        if ch("protocol", (proto, tip)):
            self.protocol_chip.text = proto
            self.protocol_tip.text = tip
        prog = s.scan_progress
        rows = [dict(r, role="jig (slave %d)" % r["id"] if r["jig"] else "jig's id (not an axis)"
                     if s.is_jig(r["id"]) else "driver",
                     protocol="Ver%d" % r["variant"] if r.get("variant") else "?") for r in s.slaves.values()]
        if prog is not None:
            scan_text = "scanning id %d of %d ..." % prog
        elif rows:
            scan_text = "%d slave(s): ids %s" % (len(rows), ", ".join(str(r["id"]) for r in rows))
        else:
            scan_text = ""
        if ch("scan", (prog, scan_text)):
            self.scan_bar.set_visibility(prog is not None)
            if prog is not None:
                self.scan_bar.value = (prog[0] + 1) / (prog[1] + 1)
            self.scan_label.text = scan_text
        if ch("slaves", repr(rows)):
            self.slave_table.rows = rows
            self.slave_table.update()
            self.axis_pick.set_options({r["id"]: self._axis_label(r) for r in s.drivers()},
                                       value=s.axis if s.axis in s.slaves else None)
        if ch("axis_pick", s.axis) and s.axis in s.slaves:
            self.axis_pick.value = s.axis
        self._take_move_fields()
        self._refresh_axis()
        self._refresh_test()
        if self.test_panel is not None:
            self.test_panel.refresh()
        cap_text = self.capture.summary()
        if ch("capture", cap_text):
            self.cap_state.text = cap_text
        self._capture_buttons()
        new = s.log_since(self.log_seq)
        for e in new:
            self.log_view.push("%s  %-5s %s" % (stamp(e.t), e.kind.upper(), e.text))
        if new:
            self.log_seq = new[-1].seq

    def _axis_label(self, row):
        v = self.s.variant_of(row["id"])
        return "%d %s%s" % (row["id"], row["type_name"], " (Ver%d)" % v if v else "")

    def _protocol_text(self):
        """The header's protocol chip and its tooltip: the forced framing, or auto with the axis's
        detected variant."""
        s = self.s
        if s.ver8 is not None:
            return protocol_name(s.ver8), ("the framing the Desk talks to every slave: %s (forced on Connect & "
                                           "bus; auto detects each slave's)" % protocol_name(s.ver8))
        found = ", ".join("%d Ver%d" % (r["id"], r["variant"]) for r in s.slaves.values() if r.get("variant"))
        v = s.variant_of(s.axis) if s.axis is not None else None
        text = "auto: Ver%d" % v if v else "auto"
        return text, ("each slave's Ver6/Ver8 variant is detected, as jigctl scan does%s" % (
            " (%s)" % found if found else "") + ("; the axis, slave %d, talks Ver%d" % (s.axis, v) if v else ""))

    def _refresh_axis(self):
        s, ch = self.s, self.changed
        v = s.status_view()
        if v is None:
            values = ("-", "-", "-", "-")
            flags, errors, ins, outs = set(), set(), "-", "-"
        else:
            values = tuple("%d" % v[k] for k in ("command_pos", "actual_pos", "pos_error", "actual_vel"))
            flags, errors = v["flags"], v["errors"]
            ins, outs = ", ".join(v["inputs"]) or "-", ", ".join(v["outputs"]) or "-"
        for label, key, value in zip((self.cmd_pos, self.act_pos, self.pos_err, self.vel),
                                     ("cmd", "act", "err", "vel"), values):
            if ch(key, value):
                label.text = value
        for name, lamp in self.lamps.items():
            cls = "lamp err" if name in errors else "lamp on" if name in flags else "lamp"
            if ch("lamp-" + name, cls):
                lamp.classes(replace=cls)
        latched = "emergency_stop" in flags
        if ch("estop_hint", latched):
            self.estop_hint.set_visibility(latched)
        if ch("ins", ins):
            self.inputs_label.text = ins
        if ch("outs", outs):
            self.outputs_label.text = outs
        if not s.connected:
            poll = ""
        elif s.status_error:
            poll = s.status_error
        else:
            poll = "status read %.0f times a second" % s.poll_rate() if s.status is not None else ""
        if ch("poll", poll):
            self.poll_label.text = poll

    def _refresh_test(self):
        mt = self.s.motion_test
        key = (mt["running"], len(mt["moves"]), mt["summary"])
        if not self.changed("mt", key):
            return
        self.mt_summary.text = mt["summary"]
        self.mt_table.rows = [{"n": i, "cycle": r["cycle"], "distance": r["distance"], "start": r.get("start", ""),
                               "end": r.get("end", ""), "seconds": r.get("seconds", ""),
                               "result": "PASS" if r["ok"] else "FAIL", "problem": r.get("problem", "")}
                              for i, r in enumerate(mt["moves"])]
        self.mt_table.update()

    def _refresh_plot(self):
        if self.test_panel is not None:
            self.test_panel.refresh_plot()
        if self.plot_paused:
            return
        rows = self.s.history_rows(self.plot_window)
        key = (len(rows), rows[-1].t if rows else 0, self.plot_window)
        if not self.changed("plot", key):
            return
        t_end = rows[-1].t if rows else 0
        step = max(1, len(rows) // 600)
        rows = rows[::step]
        opts = self.chart.options
        span = t_end - rows[0].t if rows else 0
        opts["xAxis"]["min"] = -min(self.plot_window, max(1, int(span + 0.999)))  # fit until the window fills
        for i, field in enumerate(("command_pos", "actual_pos", "actual_vel")):
            opts["series"][i]["data"] = [[round(r.t - t_end, 3), getattr(r, field)] for r in rows]
        self.chart.update()
        self.plot_points.text = "%d points" % len(rows)
