"""The jig's own event counters, in the order 0xF0 ReadCounters sends them.

``NAMES`` is the wire order; the ``C_*`` indices point into ``Counters.v``. The PC
library decodes ReadCounters with ``jig.diag.WIRE_NAMES`` (these names followed by
the two parsers' counters), so there is exactly one copy of the layout.

Conservation laws the tests check (``pending`` is 1 while a reply is awaited):

* forwards = replies + relay_corrupt + timeouts + aborts + unawaited + pending
  (PC requests sent downstream)
* int_requests = int_replies + int_timeouts + int_aborts + pending  (scan/safety)
* up_frames_in + cut_corrupt + cut_truncated = local_requests + forwards + broadcasts
  (cut through, the routing decision comes before the frame is known to be good)
"""

from array import array

from jig.compat import const
from jig.slcan import ERR_NAMES as _SLCAN_ERR_NAMES

NAMES = (
    "up_frames_in",  # good frames received from the PC
    "up_frames_out",  # frames sent to the PC (local replies + relayed replies)
    "down_frames_in",  # good frames received from the driver bus
    "down_frames_out",  # frames sent on the driver bus (forwards, broadcasts, scan, safety)
    "local_requests",  # frames for the jig's own id
    "local_errors",  # local replies with status 0x80/0x81/0x82
    "forwards",  # PC requests forwarded that await a reply
    "broadcasts",  # PC frames to id 99 forwarded (no reply awaited)
    "replies",  # matching replies relayed to the PC
    "timeouts",  # forwarded requests that got no matching reply in time
    "aborts",  # waits abandoned because the PC sent a new request
    "stale_drops",  # driver-bus frames dropped: late, unmatched or unsolicited
    "echo_drops",  # bytes heard on our own port while transmitting, discarded
    "up_rx_overflows",  # bytes lost: upstream RX buffer full
    "down_rx_overflows",  # bytes lost: downstream RX buffer full
    "int_requests",  # jig-originated requests (bus scan, safety stop)
    "int_replies",
    "int_timeouts",
    "int_aborts",
    "safety_stops",  # times the master-silence stop fired
    "param_errors",  # parameter file missing/corrupt at boot (defaults used)
    "param_saves",  # SaveAllParameters that wrote the file
    "turnaround_count",  # frames whose handling time was measured (local replies and
    # frames sent on whole, store-and-forward; cut through, make bench measures the latency)
    "turnaround_min_us",  # jig handling time: last byte in -> DE up for the answer
    "turnaround_avg_us",
    "turnaround_max_us",
    "cut_corrupt",  # cut-through: PC frames passed on that turned out bad (CRC, stuffing, length)
    "cut_truncated",  # cut-through: PC went silent mid-frame; the transmission was ended
    "relay_corrupt",  # cut-through: replies relayed to the PC that turned out bad
    "unawaited",  # forwards that ended before their frame type was known: no reply awaited
    "capture_records",  # records of both buses written into the capture ring (parameter 13)
    "capture_lost",  # records the capture ring had no room for
)

C_UP_IN = const(0)
C_UP_OUT = const(1)
C_DOWN_IN = const(2)
C_DOWN_OUT = const(3)
C_LOCAL = const(4)
C_LOCAL_ERRORS = const(5)
C_FORWARDS = const(6)
C_BROADCASTS = const(7)
C_REPLIES = const(8)
C_TIMEOUTS = const(9)
C_ABORTS = const(10)
C_STALE = const(11)
C_ECHO = const(12)
C_UP_OVERFLOWS = const(13)
C_DOWN_OVERFLOWS = const(14)
C_INT_REQUESTS = const(15)
C_INT_REPLIES = const(16)
C_INT_TIMEOUTS = const(17)
C_INT_ABORTS = const(18)
C_SAFETY_STOPS = const(19)
C_PARAM_ERRORS = const(20)
C_PARAM_SAVES = const(21)
C_TA_COUNT = const(22)
C_TA_MIN = const(23)
C_TA_AVG = const(24)
C_TA_MAX = const(25)
C_CUT_CORRUPT = const(26)
C_CUT_TRUNCATED = const(27)
C_RELAY_CORRUPT = const(28)
C_UNAWAITED = const(29)
C_CAPTURE_RECORDS = const(30)
C_CAPTURE_LOST = const(31)
COUNT = const(32)
# Kept in the same array after the wire counters, never sent: the turnaround average
# is _TA_SUM / (C_TA_COUNT - _TA_BASE) (the sum restarts before it leaves a small int).
_TA_SUM = const(32)
_TA_BASE = const(33)
_SLOTS = const(34)


# The CAN port's figures (jig.canport), in the order 0xFA ReadCanCounters sends them
# (ReadCounters' reply has no room left for them). Events count since the last
# ResetCounters; tec .. bitrate are the present values.
CAN_NAMES = (
    "can_rx_frames",  # frames received from the CAN bus
    "can_tx_frames",  # frames sent onto the bus (the host's and the safety stop's)
    "can_rx_lost",  # received frames the RX ring could not hold (the host too slow)
    "can_rx_overruns",  # the controller's RX FIFO overran (RECV_ERR_OVERRUN)
    "can_tx_failed",  # frames handed to the controller that did not go (bus-off, restart)
    "can_tx_refused",  # SLCAN frame lines answered BEL: the TX FIFO was full
    "can_warning_entries",  # error warning entered (TEC or REC >= 96)
    "can_passive_entries",  # error passive entered (TEC or REC >= 128)
    "can_bus_off_entries",  # bus-off entered (TEC >= 256)
    "can_bus_off_restarts",  # restarts after can_bus_off_restart_ms
    "can_tec",  # the controller's transmit error counter now
    "can_rec",  # ... receive error counter now
    "can_state",  # 0 stopped (closed), 1 error active, 2 warning, 3 passive, 4 bus-off
    "can_open",  # 1: the SLCAN channel is open
    "can_listen_only",  # 1: opened listen-only
    "can_bitrate",  # bps of the session (SLCAN Sn, else parameter 14)
    "can_safety_stops",  # CAN safety stops sent (parameter 18)
    "slcan_lines",  # good SLCAN lines from the host
) + tuple(["slcan_" + n for n in _SLCAN_ERR_NAMES])  # lines refused, by kind
CC_RX = const(0)
CC_TX = const(1)
CC_RX_LOST = const(2)
CC_RX_OVERRUNS = const(3)
CC_TX_FAILED = const(4)
CC_TX_REFUSED = const(5)
CC_WARNINGS = const(6)  # then passive and bus-off entries
CC_PASSIVES = const(7)
CC_BUS_OFFS = const(8)
CC_RESTARTS = const(9)
CC_TEC = const(10)
CC_REC = const(11)
CC_STATE = const(12)
CC_OPEN = const(13)
CC_LISTEN = const(14)
CC_BITRATE = const(15)
CC_SAFETY = const(16)
CC_LINES = const(17)
CAN_COUNT = const(18)  # kept by jig.canport; the SLCAN reader's error counts follow on the wire


class Counters:
    """Integer counters in a preallocated 32-bit array (jig.fastpath's machine code
    counts in it too; a counter wraps after 2**31 events)."""

    def __init__(self):
        self.v = array("i", bytes(4 * _SLOTS))

    def reset(self):
        v = self.v
        for i in range(_SLOTS):
            v[i] = 0

    def turnaround(self, us):
        """Record one jig handling time in µs (the average is worked out in
        ``update_average``, when the counters are read)."""
        v = self.v
        if us < 0:
            us = 0
        n = v[C_TA_COUNT]
        v[C_TA_COUNT] = n + 1
        if n == 0 or us < v[C_TA_MIN]:
            v[C_TA_MIN] = us
        if us > v[C_TA_MAX]:
            v[C_TA_MAX] = us
        s = v[_TA_SUM] + us
        if s > 0x3FFFFFFF:  # keep the sum a small int: restart the average window
            s = us
            v[_TA_BASE] = n
        v[_TA_SUM] = s

    def update_average(self):
        v = self.v
        n = v[C_TA_COUNT] - v[_TA_BASE]
        if n:
            v[C_TA_AVG] = v[_TA_SUM] // n

    def get(self, name):
        self.update_average()
        return self.v[NAMES.index(name)]

    def as_dict(self):
        self.update_average()
        return dict(zip(NAMES, self.v))
