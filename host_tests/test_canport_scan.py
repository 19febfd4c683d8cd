"""python-canopen's scanner through the jig on the real-time bench: no node unseen.

``network.scanner.search()`` sends its 127 SDO requests at once, faster than the bus
takes them. The jig must hold the host off (as a USB adapter does) rather than answer
BEL, which python-can ignores: a refused request is a node never found. Nodes with
high ids are the ones a refusing jig lost (their requests come last).
"""

import time

import canopen

from jig import counters as K
from motorjig.sim import Bench

NODES = (3, 64, 120, 127)
BITRATE = 500000


def test_the_scanner_finds_every_node_and_the_jig_refuses_none():
    with Bench(driver_ids=(2,), can_nodes=NODES, can_bitrate=BITRATE, pty=False) as bench:
        net = canopen.Network()
        net.connect(channel=bench.slcan_url, interface="slcan", bitrate=BITRATE, sleep_after_open=0.05)
        try:
            net.scanner.reset()
            net.scanner.search()
            end = time.monotonic() + 10.0
            while sorted(net.scanner.nodes) != list(NODES) and time.monotonic() < end:
                time.sleep(0.02)
            assert sorted(net.scanner.nodes) == list(NODES)
        finally:
            net.disconnect()
        cv = bench.sim.app.can.cv
        assert cv[K.CC_TX_REFUSED] == 0 and cv[K.CC_TX] >= 127
