"""What this process uses: its peak resident memory (the metrics of a run, a map build's workers)."""

from __future__ import annotations

from pathlib import Path


def peak_rss_mb() -> float:
    """This process's peak resident memory, MB: VmHWM from /proc, which restarts at exec (Linux's
    ``ru_maxrss`` carries a parent's peak into a child started by fork + exec: a tracking run
    launched by a large process reported its parent's peak)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    try:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB
    except (ImportError, OSError):
        import psutil

        return psutil.Process().memory_info().rss / 2**20
