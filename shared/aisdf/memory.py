"""Keeping a long-running service's resident memory near what it holds (glibc's malloc).

glibc gives every thread that allocates concurrently an arena of its own (up to 8 per core)
and keeps freed memory in them: a query service whose answer and bake threads each pass large
temporary arrays grows by hundreds of MB it no longer uses. ``cap_arenas`` bounds the arenas
(as ``MALLOC_ARENA_MAX`` does), ``trim`` hands freed memory back to the system. Both do
nothing where the C library is not glibc."""

from __future__ import annotations

import ctypes
import ctypes.util

M_ARENA_MAX = -8  # mallopt parameter (malloc.h)
_LIBC = None


def _libc():
    global _LIBC
    if _LIBC is None:
        try:
            lib = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            _LIBC = lib if hasattr(lib, "mallopt") and hasattr(lib, "malloc_trim") else False
        except OSError:
            _LIBC = False
    return _LIBC


def cap_arenas(n: int = 2) -> bool:
    """At most ``n`` malloc arenas from now on; True where it took effect."""
    lib = _libc()
    return bool(lib) and lib.mallopt(M_ARENA_MAX, int(n)) == 1


def trim() -> bool:
    """Return freed heap memory to the system; True where some was."""
    lib = _libc()
    return bool(lib) and lib.malloc_trim(0) == 1
