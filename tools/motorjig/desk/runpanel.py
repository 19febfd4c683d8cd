"""The Desk's Test tab (NiceGUI): pick a plan, scan the serial number, watch the run, read the verdict.

Layout only; the plans, the run and the records live in ``testrun.Station``, shared
by every browser tab. The serial-number field takes a barcode scanner's typing: its
Enter starts the run. While it runs every step shows its state and, once it ended,
its measurements against their limits; the moving steps are plotted from the
engine's samples as they come; an operator prompt is a dialog in every tab (its
answer lets the run go on; Abort ends it). At the end the verdict fills the top of
the tab in green or red, big enough to read from two metres, the tab that started
the run opens the HTML report in a new tab, and below come the steps, the plot, the
station's recent runs and today's yield.

Multi-up (the Desk started with ``--slots``): a row of slot panels takes the serial
field's place, one per slot (its drive, its serial field, its current step, a progress
bar, its verdict and report); START ALL runs the plan in every slot, a panel's Start in
that one; Abort (and STOP) stops them all; a prompt names its slot. A click on a panel
shows that slot's steps and moves below. The runs list gets a slot column and filter.
"""

import datetime
import time

from nicegui import ui

from motorjig.desk.testrun import MAX_UPLOAD, SlotsRun, fmt_value

CSS = """
.serial-box input {font-size:1.6rem; font-family:monospace; letter-spacing:.04em}
.verdict {min-height:58vh; border-radius:14px; color:#fff; display:flex; flex-direction:column;
          align-items:center; justify-content:center; text-align:center; padding:2vh 2vw; cursor:pointer}
.verdict.pass {background:#2e7d32}
.verdict.fail, .verdict.error, .verdict.aborted {background:#c62828}
.verdict .word {font-size:clamp(6rem, 26vh, 22rem); font-weight:900; line-height:1; letter-spacing:.06em}
.verdict .sub {font-size:clamp(1.4rem, 4.5vh, 3.2rem); font-weight:600; margin-top:1.5vh}
.verdict .why {font-size:clamp(1.1rem, 3vh, 2.2rem); font-family:monospace; margin-top:1vh; white-space:pre-line}
.verdict a {color:#fff; font-size:1.5rem; text-decoration:underline}
.verdict .hint {opacity:.8; font-size:1.1rem; margin-top:1.5vh}
.st {display:inline-block; min-width:5.4rem; text-align:center; border-radius:4px; padding:0 6px;
     font-size:12px; font-weight:700; background:#eceff1; color:#78909c; text-transform:uppercase}
.st.running {background:#1565c0; color:#fff; animation:st-pulse 1s ease-in-out infinite}
.st.pass {background:#2e7d32; color:#fff}
.st.fail {background:#c62828; color:#fff}
.st.error {background:#e65100; color:#fff}
.st.aborted {background:#6d4c41; color:#fff}
.st.not-run {background:#fafafa; color:#b0bec5}
@keyframes st-pulse {50% {opacity:.55}}
.step-row {border-bottom:1px solid #eceff1; padding:2px 0; width:100%}
.step-name {font-family:monospace; font-weight:600}
.mline {font-family:monospace; font-size:12px; color:#546e7a; margin-left:6.4rem; white-space:pre}
.mline.bad {color:#c62828; font-weight:700}
.vchip {display:inline-block; min-width:4.6rem; text-align:center; border-radius:4px; padding:0 6px;
        font-weight:700; color:#fff; background:#c62828}
.vchip.PASS {background:#2e7d32}
.slot-card {flex:1 1 0; min-width:14rem; cursor:pointer; border:3px solid transparent}
.slot-card.focused {border-color:#1565c0}
.slot-card .slot-serial input {font-size:1.2rem; font-family:monospace}
.slot-verdict {border-radius:8px; text-align:center; font-size:2.6rem; font-weight:900; letter-spacing:.05em;
               color:#fff; background:#eceff1; min-height:3.4rem}
.slot-verdict.running {background:#1565c0; font-size:1.4rem; line-height:3.4rem}
.slot-verdict.pass {background:#2e7d32}
.slot-verdict.fail, .slot-verdict.error, .slot-verdict.aborted {background:#c62828}
"""

STATE_TEXT = {"not run": "not run"}
MAX_LINES = 8  # measurements listed per step; more are summed up


def _state_class(state):
    return "st " + state.replace(" ", "-")


def _mline(m):
    """(text, failed) of one measurement: value against its limits."""
    unit = " " + m["unit"] if m.get("unit") else ""
    mark = {"PASS": "✔", "FAIL": "✘"}.get(m.get("outcome"), "·")
    text = "%s %s = %s%s" % (mark, m["name"], "unset" if m.get("value") is None else fmt_value(m["value"]), unit)
    if m.get("limits"):
        text += "   (%s)" % m["limits"]
    return text, m.get("outcome") not in ("PASS", "SKIPPED", None)  # SKIPPED: left out, nothing to judge


class TestPanel:
    """The Test tab of one browser tab."""

    def __init__(self, page, station):
        self.page = page
        self.station = station
        self.changed = page.changed
        self.rows = []  # per step: {"box", "state", "secs", "lines"}
        self.shown_run = None
        self.shown_version = None
        self.shown_prompt = None
        self.started_run = None  # the run this tab started: it opens that run's report
        self.report_opened = None
        self.records_key = None
        self.records_t = 0.0
        self.plot_key = None
        self.multi = bool(station.slots_spec)  # --slots: the slot panels instead of one serial field
        self.panels = {}  # slot name -> its widgets
        self.slots_key = None
        self.slots_t = 0.0
        self.focus_slot = None  # the slot whose steps and moves are shown
        self.run_cols = None

    # --- layout -----------------------------------------------------------------------------
    def build(self):
        ui.add_css(CSS)
        st = self.station
        with ui.card().classes("w-full q-pa-sm"):
            with ui.row().classes("items-end w-full no-wrap"):
                self.plan_select = tid(ui.select({}, label="test plan", on_change=self._plan_changed),
                                       "plan-select").classes("w-72")
                tid(ui.button(icon="upload_file", on_click=self._open_upload), "btn-plan-upload") \
                    .props("flat round").tooltip("upload a plan (and the parameter sets it names)")
                ui.button(icon="refresh", on_click=self._refresh_plans).props("flat round").tooltip(
                    "read the plans folder again")
                if self.multi:
                    self.serial = None
                    ui.space()
                else:
                    self.serial = tid(ui.input("serial number: scan or type, Enter starts"), "serial") \
                        .props("outlined autofocus").classes("serial-box flex-grow")
                    self.serial.on("keydown.enter", self._start)
                self.operator = tid(ui.input("operator", value=st.operator), "operator").classes("w-36")
                if self.multi:
                    self.btn_start = tid(ui.button("START ALL", icon="play_arrow", on_click=self._start_slots),
                                         "btn-slots-start").props("color=green-8 size=lg")
                else:
                    self.btn_start = tid(ui.button("START", icon="play_arrow", on_click=self._start),
                                         "btn-test-start").props("color=green-8 size=lg")
                self.btn_abort = tid(ui.button("ABORT", icon="stop", on_click=self._abort), "btn-test-abort") \
                    .props("color=red size=lg")
            self.plan_info = tid(ui.label(st.unavailable), "plan-info").classes("text-caption text-grey-8")
        self.slots_box = tid(ui.row().classes("w-full q-mt-sm gap-2 no-wrap items-stretch"), "slots")
        self.slots_box.set_visibility(self.multi)
        with tid(ui.element("div"), "verdict").classes("verdict w-full q-mt-sm") as self.verdict_box:
            self.verdict_word = tid(ui.label(""), "verdict-word").classes("word")
            self.verdict_sub = tid(ui.label(""), "verdict-sub").classes("sub")
            self.verdict_why = tid(ui.label(""), "verdict-why").classes("why")
            self.report_link = tid(ui.link("open the report", "#", new_tab=True), "report-link")
            ui.label("scan the next serial number to test the next drive; click here to see the steps") \
                .classes("hint")
        self.verdict_box.on("click", lambda: self.verdict_box.set_visibility(False))
        self.verdict_box.set_visibility(False)
        with ui.row().classes("w-full no-wrap items-start q-mt-sm"):
            with ui.card().classes("w-5/12"):
                self.run_title = tid(ui.label("no test run yet"), "run-title").classes("text-subtitle1")
                self.steps_box = tid(ui.column().classes("w-full gap-0"), "steps")
            with ui.card().classes("w-7/12"):
                self.plot_title = tid(ui.label("moves are plotted here as they run"), "test-plot-title") \
                    .classes("text-subtitle1")
                self.chart = tid(ui.echart({
                    "animation": False, "legend": {"top": 0}, "tooltip": {"trigger": "axis"},
                    "grid": {"left": 70, "right": 70, "top": 36, "bottom": 28},
                    "xAxis": {"type": "value", "min": 0, "axisLabel": {"formatter": "{value} s"}},
                    "yAxis": [{"type": "value", "position": "left", "scale": True},
                              {"type": "value", "position": "right", "scale": True, "splitLine": {"show": False}}],
                    "series": [
                        {"name": "command (pulses)", "type": "line", "showSymbol": False, "data": []},
                        {"name": "actual (pulses)", "type": "line", "showSymbol": False, "data": [],
                         "lineStyle": {"type": "dashed"}},
                        {"name": "velocity (pps, right)", "type": "line", "showSymbol": False, "data": [],
                         "yAxisIndex": 1},
                    ]}), "test-plot").classes("w-full h-72")
        with ui.card().classes("w-full q-mt-sm"):
            with ui.row().classes("items-center w-full"):
                ui.label("Recent runs of this station").classes("text-subtitle1")
                self.yield_label = tid(ui.label(""), "yield").classes("text-body1 q-ml-md")
                ui.space()
                self.slot_filter = tid(ui.select({"": "all slots"}, value="", label="slot",
                                                 on_change=lambda _e: self._records_again()), "slot-filter") \
                    .classes("w-32")
                self.slot_filter.set_visibility(False)
            self.runs_table = tid(ui.table(columns=_run_columns(False), rows=[], row_key="key",
                                           pagination={"rowsPerPage": 0}),
                                  "runs-table").classes("w-full").props("dense flat hide-pagination")
            self.runs_table.add_slot("body-cell-verdict", '<q-td :props="props"><span :class="\'vchip \' + '
                                     'props.value">{{ props.value }}</span></q-td>')
            self.runs_table.add_slot("body-cell-report", '<q-td :props="props"><a v-if="props.value" '
                                     ':href="props.value" target="_blank">report</a></q-td>')
            self.runs_note = tid(ui.label(""), "runs-note").classes("text-caption text-grey-7")
        with ui.dialog().props("persistent") as self.prompt_dialog, ui.card().classes("q-pa-lg"):
            ui.label("The test asks the operator:").classes("text-caption")
            self.prompt_text = tid(ui.label(""), "prompt-text").classes("text-h5")
            with ui.row().classes("q-mt-md"):
                tid(ui.button("Done", icon="check", on_click=lambda: self._answer(True)), "btn-prompt-yes") \
                    .props("color=green-8 size=lg")
                tid(ui.button("Not done", on_click=lambda: self._answer(False)), "btn-prompt-no") \
                    .props("outline size=lg")
                tid(ui.button("Abort", icon="stop", on_click=self._abort), "btn-prompt-abort") \
                    .props("color=red size=lg")
        with ui.dialog() as self.upload_dialog, ui.card():
            ui.label("Upload test plans").classes("text-subtitle1")
            ui.label("a plan and the parameter-set files it names; they are kept in %s" % st.upload_dir) \
                .classes("text-caption")
            tid(ui.upload(multiple=True, auto_upload=True, max_file_size=MAX_UPLOAD, on_upload=self._uploaded,
                          label="plan files (.toml)").props('accept=".toml"'), "plan-upload").classes("w-96")
            ui.button("Close", on_click=self.upload_dialog.close).props("flat")
        self._refresh_plans()

    # --- actions ------------------------------------------------------------------------------
    def _refresh_plans(self):
        entries = self.station.plans()
        options = {e.path: e.label for e in entries}
        value = self.plan_select.value
        if value not in options:
            value = self.station.selected if self.station.selected in options else next(iter(options), None)
        self.plan_select.set_options(options, value=value)
        self._show_plan(value)

    def _show_plan(self, key):
        if self.station.unavailable:
            self.plan_info.text = self.station.unavailable
            return
        entry = self.station.find_plan(key) if key else None
        self.plan_info.text = entry.describe() if entry else "no plans in %s: upload one" % self.station.plans_dir
        self.plan_info.classes(replace="text-caption " + ("text-red-9" if entry and entry.plan is None
                                                          else "text-grey-8"))

    def _plan_changed(self, e):
        if e.value:
            self.station.selected = e.value
        self._show_plan(e.value)
        self.records_key = None
        self.slots_key = None

    def _records_again(self):
        self.records_key = None

    def _open_upload(self):
        self.upload_dialog.open()

    async def _uploaded(self, e):
        data = await e.file.read()
        msg = await self.page.act(self.station.add_upload, e.file.name, data)
        if msg is not None:
            self._refresh_plans()
            for key, label in self.plan_select.options.items():
                if key.endswith("/" + e.file.name) and "(uploaded)" in label:
                    self.plan_select.value = key

    async def _start(self):
        if self.station.running:
            ui.notify("a test is running: wait for its verdict, or press Abort", type="warning")
            return
        serial = self.serial.value
        msg = await self.page.act(self.station.start, self.plan_select.value, serial, self.operator.value)
        if msg is not None:
            self.started_run = self.station.run.number
            self.serial.value = ""

    async def _start_slots(self, only=None):
        """START ALL (``only`` None) or one panel's Start: the plan in those slots, each with the
        serial in its field."""
        if self.station.running:
            ui.notify("a test is running: wait for its verdicts, or press Abort", type="warning")
            return
        names = [only] if only is not None else list(self.panels)
        serials = {n: self.panels[n]["serial"].value for n in names if n in self.panels}
        msg = await self.page.act(self.station.start_slots, self.plan_select.value, serials, self.operator.value,
                                  only)
        if msg is not None:
            self.started_run = self.station.run.number
            for n in serials:
                self.panels[n]["serial"].value = ""
            if only is not None:
                self._focus(only)

    async def _slot_enter(self, name):
        """Enter in a slot's serial field (a scanner's end): the next slot's field, or from the
        last one START ALL."""
        names = list(self.panels)
        i = names.index(name) if name in names else len(names) - 1
        if i + 1 < len(names):
            self.panels[names[i + 1]]["serial"].run_method("focus")
        else:
            await self._start_slots()

    def _focus(self, name):
        if name != self.focus_slot:
            self.focus_slot = name
            self.shown_run = None  # the steps list and the plot show that slot's run
            for n, p in self.panels.items():
                if n == name:
                    p["card"].classes(add="focused")
                else:
                    p["card"].classes(remove="focused")

    async def _abort(self):
        await self.page.act(self.station.abort)

    async def _answer(self, ok):
        prompt = self.shown_prompt
        if prompt is not None:
            await self.page.act(self.station.answer, prompt["id"], ok, quiet=True)

    # --- the 10 Hz refresh ------------------------------------------------------------------------
    def refresh(self):
        st = self.station
        run = st.run
        running = run is not None and run.running
        if self.changed("test-buttons", running):
            self.btn_start.set_enabled(not running)
            self.btn_abort.set_enabled(running)
            for p in self.panels.values():
                p["start"].set_enabled(not running)
        if self.multi:
            self._refresh_slots(run)
        elif run is not None:
            self._refresh_run(run)
        self._refresh_records()

    def _shown_run(self):
        """The Run whose steps and moves are shown: the run, or the focused slot's last one."""
        if self.multi:
            return self.station.slot_runs.get(self.focus_slot)
        run = self.station.run
        return None if isinstance(run, SlotsRun) else run

    # --- the slot panels ------------------------------------------------------------------------
    def _refresh_slots(self, run):
        st = self.station
        now = time.monotonic()
        key = self.plan_select.value
        if key != self.slots_key or now - self.slots_t > 2.0:
            self.slots_key, self.slots_t = key, now
            slots, why = st.slots(key)
            if self.changed("slots", (tuple((s.name, s.describe(), s.serial) for s in slots), why)):
                self._build_slots(slots, why)
        for name, panel in self.panels.items():
            self._show_slot(panel, st.slot_runs.get(name))
        if isinstance(run, SlotsRun):
            self._show_prompt(run.prompt())
            if not run.running and self.started_run == run.number and self.report_opened != run.number:
                self.report_opened = run.number  # the next drives: the first slot's field
                first = next(iter(self.panels.values()), None)
                if first is not None:
                    first["serial"].run_method("focus")
        shown = self._shown_run()
        if shown is not None:
            self._refresh_run(shown)

    def _build_slots(self, slots, why):
        self.slots_box.clear()
        self.panels = {}
        with self.slots_box:
            if why:
                tid(ui.label(why), "slots-error").classes("text-red-9 text-body1")
            for s in slots:
                with ui.card().classes("slot-card q-pa-sm gap-1") as card:
                    with ui.row().classes("items-center no-wrap w-full gap-2"):
                        ui.label("slot %s" % s.name).classes("text-h6")
                        ui.label(s.describe().split("(", 1)[-1].rstrip(")")).classes("text-caption text-grey-8")
                        ui.space()
                        start = tid(ui.button("Start", icon="play_arrow",
                                              on_click=lambda n=s.name: self._start_slots(n)),
                                    "btn-slot-start-%s" % s.name).props("color=green-8 dense")
                    hint = {"ask": "serial: scan or type (needed)", None: "serial: scan or type (none: the drive's id)"}
                    serial = tid(ui.input(hint.get(s.serial, "serial (default %s)" % s.serial)),
                                 "slot-serial-%s" % s.name).props("outlined dense").classes("slot-serial w-full")
                    serial.on("keydown.enter", lambda n=s.name: self._slot_enter(n))
                    step = tid(ui.label("waiting for a start"), "slot-step-%s" % s.name) \
                        .classes("text-body2 ellipsis w-full")
                    bar = tid(ui.linear_progress(value=0, show_value=False, size="10px"), "slot-progress-%s" % s.name)
                    verdict = tid(ui.label(""), "slot-verdict-%s" % s.name).classes("slot-verdict w-full")
                    report = tid(ui.link("report", "#", new_tab=True), "slot-report-%s" % s.name)
                    report.set_visibility(False)
                tid(card, "slot-%s" % s.name)
                card.on("click", lambda n=s.name: self._focus(n))
                self.panels[s.name] = {"card": card, "serial": serial, "step": step, "bar": bar, "verdict": verdict,
                                       "report": report, "start": start, "shown": None}
        running = self.station.running
        for p in self.panels.values():
            p["start"].set_enabled(not running)
        if self.focus_slot not in self.panels:
            self.focus_slot = None
            self._focus(next(iter(self.panels), None))
        else:
            self.panels[self.focus_slot]["card"].classes(add="focused")

    def _show_slot(self, panel, run):
        """A slot panel: its run's serial, current step, progress and verdict."""
        if run is None:
            return
        snap = run.snapshot()
        key = (run.number, snap["version"])
        if panel["shown"] == key:
            return
        panel["shown"] = key
        steps = snap["steps"]
        done = sum(1 for r in steps if r["state"] not in ("pending", "running"))
        current = next((i for i, r in enumerate(steps) if r["state"] == "running"), None)
        verdict = snap["verdict"]
        who = snap["dut_id"] or "DUT id from the drive"
        if verdict is None:
            where = "step %d/%d %s" % (current, len(steps) - 1, steps[current]["name"]) if current else "preflight"
            panel["step"].text = "%s  ·  %s" % (who, where)
        else:
            failure = run.first_failure()
            panel["step"].text = "%s  ·  %s" % (who, "at %s" % failure[0] if failure and verdict != "PASS"
                                                else "%.1f s" % run.seconds())
        panel["bar"].set_value(1.0 if verdict else done / float(len(steps)))
        state = (verdict or "running").lower()
        panel["verdict"].text = verdict or "running"
        panel["verdict"].classes(replace="slot-verdict w-full " + state)
        panel["card"].props('data-state="%s"' % state)
        html = snap["files"].get("html")
        if html:
            panel["report"].props('href="/runs/%s"' % html.replace("\\", "/").rsplit("/", 1)[-1])
        panel["report"].set_visibility(bool(html))

    def _refresh_run(self, run):
        snap = run.snapshot()
        if self.shown_run != run.number:
            self._new_run(run, snap)
        if snap["version"] != self.shown_version:
            self.shown_version = snap["version"]
            for row, step in zip(self.rows, snap["steps"]):
                self._show_step(row, step)
            if run.slot is None:  # (a slot's prompt: the SlotsRun's, whichever slot asks)
                self._show_prompt(snap["prompt"])
            elapsed = run.seconds()
            self.run_title.text = "%s%s %s  ·  %s  ·  %s%s" % (
                "slot %s: " % run.slot if run.slot is not None else "", run.plan.name, run.plan.version,
                snap["dut_id"] or "DUT id from the drive", snap["verdict"] or "running",
                "  ·  %.1f s" % elapsed if snap["verdict"] else "")
            if snap["verdict"] and run.slot is None and self.changed("verdict-shown", run.number):
                self._show_verdict(run, snap)
        if snap["verdict"] and run.slot is None and self.started_run == run.number \
                and self.report_opened != run.number:
            self.report_opened = run.number
            html = snap["files"].get("html")
            if html:
                ui.navigate.to("/runs/" + html.replace("\\", "/").rsplit("/", 1)[-1], new_tab=True)
            self.serial.run_method("focus")

    def _new_run(self, run, snap):
        self.shown_run = run.number
        self.shown_version = None
        self.verdict_box.set_visibility(False)
        self.steps_box.clear()
        self.rows = []
        with self.steps_box:
            for i, step in enumerate(snap["steps"]):
                with ui.column().classes("step-row gap-0") as box:
                    with ui.row().classes("items-center no-wrap gap-2"):
                        state = ui.label(step["state"]).classes(_state_class(step["state"]))
                        ui.label("%d" % i if i else "·").classes("text-grey-6").style("min-width:1.4rem")
                        ui.label(step["name"]).classes("step-name")
                        if step["kind"] != step["name"]:
                            ui.label(step["kind"]).classes("text-caption text-grey-7")
                        ui.space()
                        secs = ui.label("").classes("text-caption text-grey-8")
                    lines = ui.column().classes("gap-0")
                tid(box, "step-%s" % step["name"])
                self.rows.append({"box": box, "state": state, "secs": secs, "lines": lines, "shown": None})
        self.plot_key = None
        opts = self.chart.options
        for series in opts["series"]:
            series["data"] = []
        self.chart.update()
        self.plot_title.text = "moves are plotted here as they run"

    def _show_step(self, row, step):
        key = (step["state"], step["seconds"], len(step["measurements"]), tuple(step["details"]))
        if row["shown"] == key:
            return
        row["shown"] = key
        row["state"].text = STATE_TEXT.get(step["state"], step["state"])
        row["state"].classes(replace=_state_class(step["state"]))
        row["box"].props('data-state="%s"' % step["state"])
        row["secs"].text = "%.2f s" % step["seconds"] if step["seconds"] is not None else ""
        row["lines"].clear()
        with row["lines"]:
            judged = [m for m in step["measurements"] if m.get("limits") or m.get("outcome") == "FAIL"]
            bad = [m for m in judged if m.get("outcome") not in ("PASS", "SKIPPED", None)]
            # A long list (a parameter set) is summed up: its failures in full, the rest counted.
            shown = judged if len(judged) <= MAX_LINES else bad[:MAX_LINES]
            for m in shown:
                text, failed = _mline(m)
                ui.label(text).classes("mline bad" if failed else "mline")
            if len(shown) < len(judged):
                ui.label("✔ %d more measurements within their limits" % (len(judged) - len(bad))
                         if len(bad) <= MAX_LINES else "✘ and %d more out of their limits" % (len(bad) - MAX_LINES)) \
                    .classes("mline")
            if not judged:
                for line in step["details"]:
                    ui.label("✘ " + line).classes("mline bad")

    def _show_prompt(self, prompt):
        if prompt == self.shown_prompt:
            return
        self.shown_prompt = prompt
        if prompt is None:
            self.prompt_dialog.close()
        else:
            self.prompt_text.text = prompt["message"]
            self.prompt_dialog.open()

    def _show_verdict(self, run, snap):
        verdict = snap["verdict"]
        self.verdict_box.classes(replace="verdict w-full q-mt-sm " + verdict.lower())
        self.verdict_word.text = verdict
        self.verdict_sub.text = "%s  ·  %s %s  ·  %.1f s" % (snap["dut_id"] or "?", run.plan.name,
                                                             run.plan.version, run.seconds())
        why = ""
        failure = run.first_failure()
        if failure is not None:
            name, lines = failure
            why = "at %s:\n%s" % (name, "\n".join(lines[:3])) if lines else "at %s" % name
        elif snap["details"]:
            why = "\n".join(snap["details"][:3])
        self.verdict_why.text = why
        html = snap["files"].get("html")
        if html:
            self.report_link.props('href="/runs/%s"' % html.replace("\\", "/").rsplit("/", 1)[-1])
        self.report_link.set_visibility(bool(html))
        self.verdict_box.set_visibility(True)
        self.records_key = None

    def refresh_plot(self):
        run = self._shown_run()
        if run is None:
            return
        step = run.plot_step
        if step is None:
            return
        rows = run.samples_of(step)
        key = (run.number, step, len(rows))
        if key == self.plot_key:
            return
        self.plot_key = key
        stride = max(1, len(rows) // 800)
        rows = rows[::stride] + ([rows[-1]] if rows and (len(rows) - 1) % stride else [])
        opts = self.chart.options
        for i in range(3):
            opts["series"][i]["data"] = [[r[0], r[i + 1]] for r in rows]
        opts["xAxis"]["max"] = None
        self.chart.update()
        self.plot_title.text = "%s: %d samples" % (step, len(run.samples_of(step)))

    def _refresh_records(self):
        st = self.station
        now = time.monotonic()
        key = (st.records_version, self.plan_select.value, self.slot_filter.value)
        if key == self.records_key and now - self.records_t < 5.0:
            return
        self.records_key, self.records_t = key, now
        names = st.run_slots(self.plan_select.value)
        if self.changed("slot-filter", tuple(names)):
            value = self.slot_filter.value if self.slot_filter.value in names else ""
            self.slot_filter.set_options(dict([("", "all slots")] + [(n, "slot %s" % n) for n in names]), value=value)
            self.slot_filter.set_visibility(bool(names))
        if self.changed("run-cols", bool(names)):
            self.runs_table.columns = _run_columns(bool(names))
        today = datetime.date.today()
        rows = []
        for r in st.recent_runs(slot=self.slot_filter.value or None):
            when = datetime.datetime.fromtimestamp(r["start"])
            rows.append({"key": "%s-%s-%s" % (r["start"], r["dut"], r.get("slot", "")),
                         "when": when.strftime("%H:%M:%S" if when.date() == today else "%Y-%m-%d %H:%M"),
                         "slot": r.get("slot", ""),
                         "plan": r["plan"], "dut": r["dut"], "verdict": r["verdict"], "failed": r["failed"],
                         "operator": r["operator"], "seconds": "%.1f" % max(0.0, r["end"] - r["start"]),
                         "report": r["report"]})
        if self.changed("runs", repr(rows)):
            self.runs_table.rows = rows
            self.runs_table.update()
        note = st.records_error or "from %s" % st.records_source()
        if self.changed("runs-note", note):
            self.runs_note.text = note
            self.runs_note.classes(replace="text-caption " + ("text-red-9" if st.records_error else "text-grey-7"))
        entry = st.find_plan(self.plan_select.value) if self.plan_select.value else None
        name = entry.plan.name if entry is not None and entry.plan is not None else None
        text = _yield_text(st.yield_today(name), name) if name else ""
        everything = st.yield_today()
        text += ("  ·  " if text else "") + "all plans today: %d runs: %d PASS, %d FAIL, %d ERROR/ABORTED" % (
            everything["runs"], everything["PASS"], everything["FAIL"], everything["ERROR"] + everything["ABORTED"])
        if self.changed("yield", text):
            self.yield_label.text = text


def _run_columns(slots):
    """The runs table's columns; ``slots``: with the slot's, after the start time."""
    names = [("when", "started")] + ([("slot", "slot")] if slots else []) + [
        ("plan", "plan"), ("dut", "serial / DUT"), ("verdict", "verdict"), ("failed", "first failing step"),
        ("operator", "operator"), ("seconds", "s"), ("report", "")]
    return [{"name": k, "label": label, "field": k, "align": "left"} for k, label in names]


def _yield_text(y, name):
    if y["yield_pct"] is None:
        return "%s today: no runs yet" % name
    return "%s today: first-pass yield %.0f %% (%d of %d drives passed their first run)" % (
        name, y["yield_pct"], y["first_pass"], y["duts"])


def tid(element, name):
    return element.props('data-testid="%s"' % name)
