"""Virtual bench: simulated RS-485 links, simulated Ezi-STEP Plus-R drives, and the
real jig firmware on a simulated HAL. ``python -m motorjig.sim`` runs it interactively.
"""

from .bench import Bench, SimBench
from .clock import PacedClock, VirtualClock
from .cpumodel import CpuModel
from .driver import SimDriver
from .hal import PowerLoss, SimCapturePort, SimFS, SimHAL
from .link import Bus

__all__ = ["Bench", "SimBench", "CpuModel", "SimDriver", "SimFS", "SimHAL", "SimCapturePort", "PowerLoss", "Bus",
           "VirtualClock", "PacedClock"]
