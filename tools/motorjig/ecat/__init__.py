"""EtherCAT for MotorJig: the frame and its datagrams today; the simulated slaves of the bench and
the station's EtherCAT drive kind build on it (issue 33)."""
