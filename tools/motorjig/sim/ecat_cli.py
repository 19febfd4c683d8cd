"""The bench's EtherCAT bus as part of ``python -m motorjig.sim``: its options and its child process.

An entry of the table of simulated buses (``sim.kinds.EXTRA_BUSES``): ``--ecat-slaves N`` starts
``python -m motorjig.sim.ecat_bench`` beside the jig's bench (it answers frames in real time, in a
process of its own), ``--ecat-fault`` and ``--ecat-capture`` go to it, and its banner goes into
the bench's. The child gets SIGTERM when the bench dies, however it dies, and then removes its
network namespace.
"""

import os
import signal
import subprocess
import sys

TITLE = "the EtherCAT bench"


def add_arguments(ap):
    ap.add_argument("--ecat-slaves", type=int, default=0, metavar="N",
                    help="add an EtherCAT bus with N simulated CiA 402 servos (needs root: a network namespace)")
    ap.add_argument("--ecat-fault", action="append", default=[], metavar="[POS:]NAME[=VALUE]",
                    help="make an EtherCAT servo fail (python -m motorjig.sim.ecat_bench --help lists the faults)")
    ap.add_argument("--ecat-capture", metavar="FILE", help="record the EtherCAT bus's frames in a pcapng file")


def _die_with_parent():
    """In the child: SIGTERM when the bench dies, however it dies (SIGKILL too)."""
    import ctypes

    ctypes.CDLL(None).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def start(args):
    """The EtherCAT bench as a child process (``banner``: its line for the bench's banner, ``title``),
    or None when the options ask for none. ValueError with the reason it cannot start."""
    from .ecat_bus import Wire

    if not (args.ecat_slaves or args.ecat_fault or args.ecat_capture):
        return None
    if not 1 <= args.ecat_slaves <= 64:
        raise ValueError("--ecat-slaves must be 1..64%s" % (" (--ecat-fault and --ecat-capture need it)"
                                                            if not args.ecat_slaves else ""))
    why = Wire.check_permissions()
    if why:
        raise ValueError("--ecat-slaves: %s" % why)
    cmd = [sys.executable, "-m", "motorjig.sim.ecat_bench", "--slaves", str(args.ecat_slaves)]
    for spec in args.ecat_fault:
        cmd += ["--fault", spec]
    if args.ecat_capture:
        cmd += ["--capture", args.ecat_capture]
    tools = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([tools, os.path.join(os.path.dirname(tools), "firmware")] + [
        p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
                            env=env, preexec_fn=_die_with_parent)
    line = proc.stdout.readline()
    if not line.startswith("EtherCAT bench:"):
        proc.wait()
        said = proc.stderr.read().strip().replace("ecat_bench: --fault", "--ecat-fault").replace(
            "ecat_bench: --capture", "--ecat-capture").replace("ecat_bench: ", "--ecat-slaves: ")
        raise ValueError(said or "the EtherCAT bench did not start")
    proc.banner = "EtherCAT: " + line.split(":", 1)[1].strip().replace("; Ctrl-C stops", "")
    proc.title = TITLE
    return proc
