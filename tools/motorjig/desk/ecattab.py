"""The Desk's EtherCAT tab (NiceGUI): a line from this PC's network interface, its slaves, SDO, the axis.

Layout only: the work is ``ecatlink.EcatLink``, one per Desk server and shared by every browser tab.
Clicks run the link's methods in a worker thread (``run.io_bound``: opening the line takes a few
seconds, an SDO waits for the mailbox); a timer copies the link's state, the slaves and the axis's
status into the widgets. Every failure is one sentence in the tab (``ecat-message``), never a
traceback. The header's STOP AXIS and EMERGENCY STOP reach the axis through ``link.desk_axis``.
"""

from nicegui import ui

from motorjig.desk.session import UserError
from motorjig.desk.widgets import Changed, run_action, tid

TAB_ID = "tab-ecat"
LABEL = "EtherCAT"
REFRESH_S = 0.25


def add_arguments(ap):
    """The Desk's option for this tab: the interface a plan's run borrows (and the tab opens)."""
    ap.add_argument("--ecat-ifname", metavar="IF", default="",
                    help="this PC's network interface on an EtherCAT line (the EtherCAT tab; a protocol = "
                         "\"ethercat\" plan's runs borrow it); needs root")


def make_link(args, read_only):
    from motorjig.desk.ecatlink import make_link as make

    return make(getattr(args, "ecat_ifname", "") or "", read_only)


class Tab:
    """The EtherCAT tab of one browser tab (``link``: the server's EcatLink, or None: ``why`` says why)."""

    def __init__(self, page, link, why=None):
        self.page, self.link, self.why = page, link, why
        self.changed = Changed()

    async def act(self, fn, *args):
        res = await run_action(fn, args, self._say, UserError)
        if isinstance(res, str):
            self._say(res)
        return res

    def _say(self, text, error=False):
        self.message.text = text
        self.message.classes(replace="text-red-9" if error else "text-grey-9")
        ui.notify(text, type="negative" if error else "info")

    def build(self):
        if self.link is None:
            tid(ui.label(self.why or "no EtherCAT"), "ecat-unavailable").classes("text-red-9")
            return
        link = self.link
        with ui.row().classes("items-end"):
            self.ifname = tid(ui.input("network interface", value=link.ifname, placeholder="eth1, mjm1234"),
                              "ecat-ifname").classes("w-56")
            self.position = tid(ui.number("slave position", value=link.position, min=0, step=1, format="%d"),
                                "ecat-position").classes("w-32")
            tid(ui.button("Open", icon="power", on_click=self._open), "btn-ecat-open")
            tid(ui.button("Close", on_click=lambda: self.act(link.close)), "btn-ecat-close").props("outline")
            self.state = tid(ui.label(link.summary()), "ecat-state").classes("q-ml-md")
        self.message = tid(ui.label(""), "ecat-message").classes("text-grey-9")
        cols = [{"name": k, "label": label, "field": k, "align": "left"} for k, label in (
            ("position", "position"), ("name", "name (SII)"), ("vendor", "vendor"), ("product", "product"),
            ("revision", "revision"), ("state", "AL state"), ("al_status", "AL status code"))]
        with ui.card().classes("w-full"):
            ui.label("Slaves").classes("text-subtitle1")
            self.slaves = tid(ui.table(columns=cols, rows=[], row_key="position", pagination={"rowsPerPage": 0}),
                              "ecat-slaves").classes("w-full").props("dense hide-pagination")
        with ui.card().classes("w-full"):
            with ui.row().classes("items-end"):
                ui.label("SDO").classes("text-subtitle1")
                self.obj = tid(ui.input("INDEX[:SUB]", value="0x6041"), "ecat-sdo-object").classes("w-36")
                self.value = tid(ui.input("value"), "ecat-sdo-value").classes("w-36")
                tid(ui.button("Read", on_click=lambda: self.act(link.sdo_read, self.obj.value)), "btn-ecat-sdo-read")
                tid(ui.button("Write", on_click=lambda: self.act(link.sdo_write, self.obj.value, self.value.value)),
                    "btn-ecat-sdo-write").props("outline")
        with ui.card().classes("w-full"):
            with ui.row().classes("items-center"):
                ui.label("CiA 402 axis (CSP at 1 ms)").classes("text-subtitle1")
                self.axis_state = tid(ui.label("-"), "ecat-axis-state").classes("q-ml-md")
            with ui.row().classes("items-end"):
                tid(ui.button("Enable", on_click=lambda: self.act(link.enable)), "btn-ecat-enable")
                tid(ui.button("Disable", on_click=lambda: self.act(link.disable)), "btn-ecat-disable").props("outline")
                tid(ui.button("Fault reset", on_click=lambda: self.act(link.fault_reset)), "btn-ecat-reset") \
                    .props("outline")
                self.target = tid(ui.input("target, counts", value="10000"), "ecat-target").classes("w-36")
                self.speed = tid(ui.input("speed, counts/s", value="20000"), "ecat-speed").classes("w-36")
                tid(ui.button("Move", icon="play_arrow", on_click=lambda: self.act(
                    link.move, self.target.value, self.speed.value)), "btn-ecat-move")
                tid(ui.button("Halt", on_click=lambda: self.act(link.stop, False)), "btn-ecat-halt").props("color=orange")
                tid(ui.button("Quick stop", on_click=lambda: self.act(link.stop, True)), "btn-ecat-quick-stop") \
                    .props("color=red")
        ui.timer(REFRESH_S, self.refresh)

    async def _open(self):
        await self.act(self.link.open, self.ifname.value or "", int(self.position.value or 0))

    def refresh(self):
        link, ch = self.link, self.changed
        summary = link.summary()
        if ch("state", summary):
            self.state.text = summary
        rows = link.line if link.state == "open" else []
        if ch("slaves", repr(rows)):
            self.slaves.rows = rows
            self.slaves.update()
        st = link.status()
        text = "-" if st is None else "%s, statusword 0x%04X, position %d" % (st["state"], st["statusword"],
                                                                             st["position"])
        if ch("axis", text):
            self.axis_state.text = text
