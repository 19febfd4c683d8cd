"""Background bus scan: GetSlaveInfo to ids 0..15 on the driver bus, one per idle slot.

Any reply counts as a driver at that id, also from a driver of the other protocol
variant (mixed Ver6/Ver8 bus); only a good GetSlaveInfo in the jig's own layout
gives its slave type, else the type reads 0 (unknown).

StartBusScan (0xF2) only arms it; ``poll`` sends the next probe whenever the bridge
is idle, so no local reply ever waits for the scan and PC traffic always wins (a
PC request aborts the probe in flight, which is then retried). The result is read
with GetBusScanResult (0xF3, layout in ``jig.diag``).
"""

from jig import diag, frame
from jig.params import P_SCAN_TIMEOUT_MS


class Scanner:
    def __init__(self, bridge, params):
        self.bridge = bridge
        self.params = params
        self.state = diag.SCAN_IDLE
        self.next_id = 0
        self.found = 0
        self.types = bytearray(diag.SCAN_IDS)
        self.empty = bytearray(1)
        self.waiting = False

    def start(self):
        if self.state == diag.SCAN_RUNNING:
            return
        self.state = diag.SCAN_RUNNING
        self.next_id = 0
        self.found = 0
        for i in range(diag.SCAN_IDS):
            self.types[i] = 0
        self.bridge.due[0] = self.bridge.hal.ticks_us()  # the first probe at the next pass

    def pending(self):
        """True if the scan wants the bus (the app should poll soon)."""
        return self.state == diag.SCAN_RUNNING and not self.waiting

    def poll(self, now):
        if self.state != diag.SCAN_RUNNING or self.waiting or self.bridge.busy():
            return
        if self.next_id >= diag.SCAN_IDS:
            self.state = diag.SCAN_DONE
            return
        if self.bridge.request(self, self.next_id, frame.GET_SLAVE_INFO, self.empty, 0,
                               self.params.ram[P_SCAN_TIMEOUT_MS]):
            self.waiting = True

    def on_reply(self, p):
        i = self.next_id
        self.found |= 1 << i
        # A driver of the other protocol variant answers too (a frame-type error, or
        # an OK read in the wrong layout): found, its type stays 0 (unknown) unless
        # the reply reads as a good GetSlaveInfo in the jig's layout.
        if p.data_end - p.data_start >= 2 and p.body[p.data_start] == 0 and p.ftype == frame.GET_SLAVE_INFO:
            self.types[i] = p.body[p.data_start + 1]
        self.waiting = False
        self.next_id = i + 1

    def on_timeout(self):
        self.waiting = False
        self.next_id += 1

    def on_abort(self):
        self.waiting = False  # retry the same id

    def result_into(self, out):
        """GetBusScanResult reply data (status first) into out; returns its length."""
        out[0] = frame.STATUS_OK
        out[1] = self.state
        frame.put_u16(out, 2, self.found)
        for i in range(diag.SCAN_IDS):
            out[4 + i] = self.types[i]
        return diag.SCAN_REPLY_LEN
