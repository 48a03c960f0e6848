"""Peak memory of a benchmark's child process (imported by the child scripts of bench/*.py)."""

from __future__ import annotations

import resource

# Prepended to a child script run with ``python -c``: makes this module importable there.
CHILD_PRELUDE = f"import sys; sys.path.insert(0, {str(__import__('pathlib').Path(__file__).resolve().parent)!r})\n"


def hwm_kb() -> int:
    """This process's own peak RSS in KiB (``VmHWM``).

    ``ru_maxrss`` is not usable in a child: Linux carries the parent's high-water mark over
    fork + exec, so a child of a big parent reports the parent's. It is the fallback where
    /proc is absent.
    """
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
