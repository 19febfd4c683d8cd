"""MotorJig on CAN: the PC side of the jig's CAN port (SLCAN) with python-can and python-canopen,
and the EDS of the simulated CiA 402 drive (``EDS_PATH``).
"""

import os

EDS_PATH = os.path.join(os.path.dirname(__file__), "motorjig-cia402.eds")
