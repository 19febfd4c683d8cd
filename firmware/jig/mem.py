"""Copy bytes between preallocated buffers without allocating on MicroPython.

On MicroPython a slice (``src[a:b]``) creates a new object on the heap, so the
firmware copies with the viper loop where the port has one and with a plain byte
loop otherwise. CPython has no such concern and uses slice assignment.
"""

from jig.compat import IS_MICROPYTHON, NATIVE


def _copy_loop(dst, dst_off, src, src_off, n):
    for i in range(n):
        dst[dst_off + i] = src[src_off + i]


def _copy_slice(dst, dst_off, src, src_off, n):
    dst[dst_off : dst_off + n] = src[src_off : src_off + n]


if NATIVE is not None:
    copy = NATIVE.copy
elif IS_MICROPYTHON:
    copy = _copy_loop
else:
    copy = _copy_slice
