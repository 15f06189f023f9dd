"""Worker processes that die with their parent (Linux: prctl PR_SET_PDEATHSIG), so killing `sgde prior`
(even by kill -9, as a scheduler does) never leaves a fork server, workers or their memory behind.

Importing this module inside a fork server (it is in the fork server's preload list) arms the signal
there, so the fork server dies with the main process; each worker (whose parent is the fork server)
calls `die_with_parent()` itself. Imported anywhere else, the module does nothing.
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


def _in_fork_server() -> bool:
    """True while `multiprocessing.forkserver.main` is on the stack (it imports its preload list)."""
    frame = sys._getframe(1)
    while frame is not None:
        code = frame.f_code
        if code.co_name == "main" and code.co_filename.replace("\\", "/").endswith("multiprocessing/forkserver.py"):
            return True
        frame = frame.f_back
    return False


def _arm_on_import() -> None:
    if _in_fork_server():
        die_with_parent()


_arm_on_import()

__all__ = ["die_with_parent"]
