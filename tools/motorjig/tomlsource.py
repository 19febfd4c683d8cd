"""Reading TOML files with the line of every key, for error messages that point at it.

``tomllib`` (``tomli`` before Python 3.11) parses; it keeps no positions, so
``KeyLines`` scans the text once for table headers and ``key =`` lines and maps a
key path such as ``("steps", 3, "speed")`` to its line. Keys inside inline tables
or multi-line values are not located: the message then names the key without a line.
"""

import re

try:
    import tomllib
except ImportError:  # Python < 3.11
    try:
        import tomli as tomllib
    except ImportError:
        tomllib = None


class SourceError(ValueError):
    """A problem in a file, with where it is: ``path:line: key: message``."""

    def __init__(self, path, line, key, message):
        self.path, self.line, self.key, self.message = path, line, key, message
        where = str(path) + (":%d" % line if line else "")
        super().__init__("%s: %s%s" % (where, key + ": " if key else "", message))


_HEADER = re.compile(r"^\s*(\[\[?)\s*([A-Za-z0-9_.\-\" ]+?)\s*\]\]?\s*(#.*)?$")
_KEY = re.compile(r"^\s*([A-Za-z0-9_\-]+|\"[^\"]*\")\s*=")


class KeyLines:
    """Line numbers of tables and keys in one TOML text."""

    def __init__(self, text):
        self.lines = {}
        counts = {}
        section = ()
        for no, line in enumerate(text.splitlines(), 1):
            m = _HEADER.match(line)
            if m:
                name = tuple(p.strip().strip('"') for p in m.group(2).split("."))
                if m.group(1) == "[[":
                    idx = counts.get(name, -1) + 1
                    counts[name] = idx
                    # a sub-array resets when its parent array gets a new element
                    for other in [k for k in counts if len(k) > len(name) and k[: len(name)] == name]:
                        del counts[other]
                    section = self._path(name[:-1], counts) + (name[-1], idx)
                else:
                    section = self._path(name, counts)
                self.lines.setdefault(section, no)
                continue
            m = _KEY.match(line)
            if m:
                self.lines.setdefault(section + (m.group(1).strip('"'),), no)

    @staticmethod
    def _path(name, counts):
        """A dotted table name with the current element index of every array on the way."""
        out = ()
        for i, part in enumerate(name):
            out += (part,)
            if name[: i + 1] in counts:
                out += (counts[name[: i + 1]],)
        return out

    def line(self, path):
        """The line of ``path`` (a tuple of names and indexes), else of its nearest table."""
        path = tuple(path)
        while path:
            if path in self.lines:
                return self.lines[path]
            path = path[:-1]
        return None


def dotted(path):
    """("steps", 3, "speed") -> "steps[3].speed"."""
    out = ""
    for p in path:
        out += "[%d]" % p if isinstance(p, int) else ("." if out else "") + str(p)
    return out


def read_toml(path):
    """(dict, KeyLines, raw bytes) of a TOML file; SourceError for a missing file or bad syntax."""
    if tomllib is None:
        raise SourceError(path, None, "", "reading TOML needs Python 3.11 or the package tomli")
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise SourceError(path, None, "", "cannot read: %s" % (exc.strerror or exc)) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise SourceError(path, None, "", "not UTF-8 text") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        msg = str(exc)
        m = re.search(r"\(at line (\d+), column \d+\)", msg)
        line = int(m.group(1)) if m else None
        raise SourceError(path, line, "", "not valid TOML: %s" % re.sub(r"\s*\(at line.*\)", "", msg)) from None
    return data, KeyLines(text), raw
