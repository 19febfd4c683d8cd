"""Small helpers every tab of MotorJig Desk uses: stable test ids and change tracking."""


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
