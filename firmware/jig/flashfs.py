"""The flash filesystem: littlefs on the board's internal flash, mounted at /flash.

``mount_flash(bdev)`` mounts it and, on a blank or unreadable flash, formats it
first (FAT is compiled out of the image). The block device comes from the board
(``jig.board.flash_device``): this module touches no hardware module itself.
The parameter file and the crash log live here.
"""

import os
import sys

FLASH_MOUNT = "/flash"


def is_mounted(path=None):
    """True if path (default: the flash mount point) exists."""
    try:
        os.stat(path or FLASH_MOUNT)
        return True
    except OSError:
        return False


def mount_flash(bdev):
    """Mount littlefs from bdev at /flash, formatting a blank/corrupt one.

    Returns "mounted", "formatted" or "none" (no usable flash filesystem:
    bdev is None, or it cannot be formatted).
    """
    if is_mounted():
        return "mounted"
    if bdev is None:
        return "none"
    result = "mounted"
    try:
        os.mount(os.VfsLfs2(bdev), FLASH_MOUNT)
    except OSError:
        try:
            os.VfsLfs2.mkfs(bdev)
            os.mount(os.VfsLfs2(bdev), FLASH_MOUNT)
        except OSError:
            return "none"  # no filesystem: parameters fall back to defaults
        result = "formatted"
    os.chdir(FLASH_MOUNT)
    for path in (FLASH_MOUNT, FLASH_MOUNT + "/lib"):
        if path not in sys.path:
            sys.path.append(path)
    return result
