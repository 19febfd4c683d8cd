"""The dissector and the extcap into the user's own Wireshark folders (nothing system-wide).

Where they go is asked of Wireshark itself when ``tshark`` is on the PATH
(``tshark -G folders``, which follows ``$HOME``/``$XDG_CONFIG_HOME``):

* the dissector: "Personal Lua Plugins", ``~/.local/lib/wireshark/plugins/``;
* the extcap: "Personal Extcap path" (Wireshark 4.2 and later),
  ``~/.local/lib/wireshark/extcap/``; Wireshark 3.x-4.0 list no such path and read
  ``extcap/`` in their personal configuration folder (``~/.config/wireshark/extcap/``),
  so for those it goes there as well.

Without tshark the defaults above are used. The extcap is a small launcher per
interface (``motorjig-sniff``: a listen-only adapter; ``motorjig-jig``: the jig's
own recording of both buses) that runs ``motorjig.capture.extcap`` for that
interface with the Python that installed it.
"""

import os
import shutil
import stat
import subprocess
import sys

EXTCAP_NAME = "motorjig-sniff"
EXTCAP_JIG_NAME = "motorjig-jig"
EXTCAP_NAMES = (EXTCAP_NAME, EXTCAP_JIG_NAME)
PLUGIN_NAME = "plusr.lua"

_LAUNCHER = '''#!{python}
"""Wireshark extcap {name}: {what} (written by jigctl capture --install-extcap)."""
import sys

sys.path[:0] = [p for p in {paths!r} if p not in sys.path]
from motorjig.capture.extcap import main

sys.exit(main(interface={name!r}))
'''
_WHAT = {EXTCAP_NAME: "a Plus-R bus through a listen-only adapter",
         EXTCAP_JIG_NAME: "the jig's own recording of the PC bus and the driver bus"}


def dissector_source():
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), PLUGIN_NAME)


def wireshark_folders(tshark=None):
    """{label: path} from ``tshark -G folders``, or {} without tshark."""
    exe = tshark or shutil.which("tshark")
    if not exe:
        return {}
    try:
        out = subprocess.run([exe, "-G", "folders"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return {}
    folders = {}
    for line in out.splitlines():
        label, sep, path = line.partition(":")
        if sep and path.strip():
            folders.setdefault(label.strip(), path.strip())
    return folders


def _home(*parts):
    return os.path.join(os.path.expanduser("~"), *parts)


def plugin_dir(folders):
    return folders.get("Personal Lua Plugins") or _home(".local", "lib", "wireshark", "plugins")


def extcap_dirs(folders):
    """Where the extcap goes: the personal extcap path, plus the 3.x-4.0 one when
    this Wireshark has no personal extcap path (a list of (folder, why))."""
    personal = folders.get("Personal Extcap path")
    if personal:
        return [(personal, "Wireshark's personal extcap folder")]
    out = [(_home(".local", "lib", "wireshark", "extcap"), "the personal extcap folder of Wireshark 4.2 and later")]
    config = folders.get("Personal configuration")
    if config:
        out.append((os.path.join(config, "extcap"), "read by this Wireshark (3.x-4.0: the configuration folder)"))
    return out


def _mkdir(path):
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        raise OSError("cannot create %s: %s" % (path, exc.strerror)) from None


def install_dissector(folders=None):
    """Copy plusr.lua into the personal Lua plugin folder; returns the path written."""
    folders = wireshark_folders() if folders is None else folders
    target_dir = plugin_dir(folders)
    _mkdir(target_dir)
    target = os.path.join(target_dir, PLUGIN_NAME)
    shutil.copyfile(dissector_source(), target)
    return target


def _import_paths():
    """The folders that hold the jig and motorjig packages (editable install or source tree)."""
    import jig
    import motorjig

    return [os.path.dirname(os.path.dirname(os.path.abspath(m.__file__))) for m in (jig, motorjig)]


def launcher_text(python=None, name=EXTCAP_NAME):
    """The launcher of one interface: it lists and captures only that one, so the two
    launchers never offer the same interface twice."""
    return _LAUNCHER.format(python=python or sys.executable, paths=_import_paths(), name=name, what=_WHAT[name])


def install_extcap(folders=None):
    """Write a launcher per interface into each extcap folder; returns [(path, why)]."""
    folders = wireshark_folders() if folders is None else folders
    written = []
    for folder, why in extcap_dirs(folders):
        _mkdir(folder)
        for name in EXTCAP_NAMES:
            path = os.path.join(folder, name)
            with open(path, "w", encoding="utf-8") as f:
                f.write(launcher_text(name=name))
            os.chmod(path, os.stat(path).st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
            written.append((path, why))
    return written
