"""How much memory this machine can still give: checked before any large allocation.

A grid solve or a verification of a billion states that cannot fit is refused up front, with an
estimate and what to change, instead of dying half-way with an out-of-memory error.
"""

from __future__ import annotations

import os


def available_memory() -> int | None:
    """Bytes this machine can still give (MemAvailable on Linux, physical memory elsewhere), or None."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None
