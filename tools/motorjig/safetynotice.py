"""The jig's safety-stop notice, in one sentence for the next user.

When a run's master falls silent (a killed ``jigctl test``, a crashed PC, a pulled
cable) the jig stops the axes itself, lets its safety net go and keeps a notice of it
(``Master.take_safety_notice``). Whoever talks to the jig next -- ``jigctl status`` or
``stats``, the next ``jigctl test``, the Desk -- takes it and tells the user once.
"""

import time

from motorjig.errors import JigError


def describe(notice, now=None):
    """The notice (jig.diag.decode_safety_notice) as one sentence."""
    now = time.time() if now is None else now
    at = now - notice["ms_ago"] / 1000.0
    what = []
    if notice["nodes"]:
        what.append("CAN node%s %s" % ("s" if len(notice["nodes"]) > 1 else "", _join(notice["nodes"])))
    if notice["ids"]:
        what.append("drive%s %s" % ("s" if len(notice["ids"]) > 1 else "", _join(notice["ids"])))
    stopped = " and ".join(what) if what else "no drive (none had answered yet)"
    return ("the jig stopped %s after the run's master went silent at %s (%s ago); its safety net is "
            "let go and its parameters are as before the run" % (stopped, time.strftime("%H:%M:%S", time.localtime(at)),
                                                                 _ago(notice["ms_ago"])))


def take(master, jig_id=1):
    """The jig's notice as a sentence, or None (nothing happened, or a jig that keeps none)."""
    try:
        notice = master.take_safety_notice(jig_id)
    except JigError:  # a jig from before the notice, or none at that id: nothing to tell
        return None
    return describe(notice) if notice else None


def _join(numbers):
    numbers = [str(n) for n in numbers]
    return numbers[0] if len(numbers) == 1 else ", ".join(numbers[:-1]) + " and " + numbers[-1]


def _ago(ms):
    s = ms // 1000
    if s < 120:
        return "%d s" % s
    if s < 7200:
        return "%d min" % (s // 60)
    return "%.1f h" % (s / 3600.0)
