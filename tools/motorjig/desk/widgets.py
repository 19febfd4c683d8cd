"""Small helpers every tab of MotorJig Desk uses: stable test ids, change tracking, running an action."""


def tid(element, name):
    """Give an element a stable data-testid (for tests and for people reading the DOM)."""
    return element.props('data-testid="%s"' % name)


class Changed:
    """Remembers what was last pushed to each widget, so unchanged values are not resent."""

    def __init__(self):
        self.last = {}

    def __call__(self, key, value):
        if self.last.get(key, object()) == value:
            return False
        self.last[key] = value
        return True


async def run_action(fn, args, say, user_error):
    """Run ``fn(*args)`` off the event loop (``nicegui.run.io_bound``); its failure (``user_error``: a
    sentence; anything else: a bug, named in one sentence) goes to ``say(text, error=True)``. Returns
    its result, or None when it failed."""
    from nicegui import run

    try:
        return await run.io_bound(fn, *args)
    except user_error as exc:
        say(str(exc), error=True)
    except Exception as exc:  # a bug: one sentence on the page, never a traceback
        say("internal error (%s: %s)" % (type(exc).__name__, exc), error=True)
    return None
