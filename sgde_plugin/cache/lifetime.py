"""Worker processes that die with their parent (Linux: prctl PR_SET_PDEATHSIG), so killing `sgde prior`
(even by kill -9, as a scheduler does) never leaves a fork server, workers or their memory behind.

Importing this module arms the signal in the importing process: it is only ever named in the fork
server's preload list (whose parent is the main process), and `die_with_parent()` is called by each
worker (whose parent is the fork server). Elsewhere both are no-ops.
"""

from __future__ import annotations

import ctypes
import signal
import sys

PR_SET_PDEATHSIG = 1


def die_with_parent(sig: int = signal.SIGKILL) -> bool:
    """Ask the kernel to send `sig` to this process when its parent exits; True when armed."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):  # pragma: no cover - no libc prctl
        return False


def _arm_on_import() -> None:
    # only in a fork server (its argv is `-c 'from multiprocessing.forkserver import main; ...'`)
    if any("multiprocessing.forkserver" in a for a in sys.argv):
        die_with_parent()


_arm_on_import()

__all__ = ["die_with_parent"]
