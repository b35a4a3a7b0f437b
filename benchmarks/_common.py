"""What the benchmark scripts share: where the data is, peak memory, the machine.

Import it as ``from benchmarks._common import ...`` (a script run as ``python
benchmarks/X.py`` first puts the repository root on ``sys.path``).
"""

from __future__ import annotations

import os
import platform
import resource
from pathlib import Path

__all__ = ["DEFAULT_DATA", "peak_rss_mb", "machine"]

#: the shared data folder beside the checkout (``../shared/data``)
DEFAULT_DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB.

    ``VmHWM`` of /proc/self/status belongs to the current address space: unlike getrusage's
    ``ru_maxrss``, it does not carry the parent's peak over into a child started by fork +
    exec.  getrusage where /proc is absent.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def machine() -> dict:
    """The platform, architecture, processor and CPU count, for a benchmark's JSON."""
    return {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
    }
