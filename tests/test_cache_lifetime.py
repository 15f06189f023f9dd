"""Process lifetime of a build (issue #22, failure 4): killing only the main process (kill -9, as a
scheduler does) takes the fork server and the workers with it; SIGTERM stops a build cleanly (exit
143, workers gone); either way a resume completes the cache.

Runtime ~15 s on 2 cores (three short builds in subprocesses with 2 workers each).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from test_cache_kill import SCRIPT, _done_count

from sgde_plugin.cache.inspection import verify_cache
from sgde_plugin.cache.store import PriorCache, encode_prior
from sgde_plugin.cache.synthetic import SyntheticPriorCompute

FRAMES = 40
MAIN = '''
if __name__ == "__main__":
    from sgde_plugin.cli import Stopped, stop_on_sigterm

    try:
        with stop_on_sigterm():
            run(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]))
    except Stopped as exc:
        sys.exit(128 + exc.signum)
'''


def _descendants(pid: int) -> set[int]:
    """Every live process below `pid` (children, their children, ...)."""
    parents: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            parents[int(entry)] = int(stat.rsplit(")", 1)[1].split()[1])
    found, frontier = set(), {pid}
    while frontier:
        frontier = {p for p, pp in parents.items() if pp in frontier} - found
        found |= frontier
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _start(script: Path, out: Path) -> tuple[subprocess.Popen, set[int]]:
    """A 2-worker build, once it has written a new frame: (process, its fork server and workers)."""
    proc = subprocess.Popen([sys.executable, str(script), str(out), str(FRAMES), "2", "0.1"],
                            stderr=subprocess.PIPE, text=True)
    deadline, before = time.time() + 120, _done_count(out)
    while _done_count(out) <= before and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    assert proc.poll() is None, proc.stderr.read()
    kids = _descendants(proc.pid)
    assert len(kids) >= 3  # fork server + 2 workers (+ the resource tracker)
    return proc, kids


def _wait_gone(pids: set[int], timeout: float = 30.0) -> set[int]:
    deadline = time.time() + timeout
    while time.time() < deadline and any(_alive(p) for p in pids):
        time.sleep(0.05)
    return {p for p in pids if _alive(p)}


def test_workers_die_with_the_main_process_and_sigterm_stops_cleanly(tmp_path):
    script = tmp_path / "build_script.py"
    script.write_text(SCRIPT.split('if __name__ == "__main__":')[0] + MAIN)
    out = tmp_path / "c"

    proc, kids = _start(script, out)
    os.kill(proc.pid, signal.SIGKILL)  # only the main process
    proc.wait(30)
    assert _wait_gone(kids) == set()  # fork server, workers, resource tracker: all gone

    proc, kids = _start(script, out)
    os.kill(proc.pid, signal.SIGTERM)
    assert proc.wait(60) == 128 + signal.SIGTERM
    assert "Traceback" not in proc.stderr.read()
    assert _wait_gone(kids) == set()
    assert 0 < len(PriorCache(out).frames()) < FRAMES

    subprocess.run([sys.executable, str(script), str(out), str(FRAMES), "2", "0"], check=True, timeout=120)
    assert verify_cache(out)["ok"]
    cache = PriorCache(out)
    assert len(cache.frames()) == FRAMES
    compute = SyntheticPriorCompute(_Sizes())
    for fid in cache.frames()[::7]:
        for cam, (depth, conf) in compute(fid).items():
            h, w = depth.shape
            expected = encode_prior(depth, conf, h, w)[0].astype(np.float32)
            np.testing.assert_array_equal(cache.get(fid, cam)[0], expected)


class _Sizes:
    """The camera sizes of the script's rig, as SyntheticPriorCompute reads them."""

    def __init__(self) -> None:
        from types import SimpleNamespace

        self.cameras = [SimpleNamespace(name=n, width=w, height=h) for n, w, h in [("A", 64, 40), ("B", 64, 40),
                                                                                   ("C", 48, 32)]]
