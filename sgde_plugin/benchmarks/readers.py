"""`sgde bench readers`: load time and peak memory of the nuScenes reader on trainval-sized tables.

A nuScenes-shaped table set is generated in a temporary folder (v1.0-trainval proportions: 850 scenes
of 40 keyframes; per keyframe interval 6 cameras x 6 frames at 12 Hz, 10 lidar and ~32 radar rows;
~2.65M `sample_data` rows and as many `ego_pose` rows, written with indent=0 like the real files).
Each measurement runs in a fresh subprocess that reports its wall time and peak RSS
(`resource.getrusage(...).ru_maxrss`), with the RSS after imports (torch, numpy) as the baseline.
Targets (issue 4): < 60 s and < 6 GB for the full tables. Wall time depends on what else runs on
the machine, so the CPU time (user + system) of the load is reported too, with the load average.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FULL_ROWS = 2_600_000
FAST_ROWS = 120_000
SAMPLES_PER_SCENE = 40
CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")
RADARS = ("RADAR_FRONT", "RADAR_FRONT_LEFT", "RADAR_FRONT_RIGHT", "RADAR_BACK_LEFT", "RADAR_BACK_RIGHT")
# rows per keyframe interval: cameras 12 Hz (6 per 0.5 s), lidar 20 Hz (10), radar ~13 Hz (6 or 7)
ROWS_PER_SAMPLE = 6 * 6 + 10 + 5 * 6.5
TIME_TARGET_S = 60.0
MEMORY_TARGET_GB = 6.0
LIMIT_TIME_S = 900


def _tok(kind: int, i: int) -> str:
    return f"{kind:x}{i:031x}"


_T_BASE = 1_532_402_927_000_000


def _channel_rows(channel: str, k: int) -> int:
    if channel in CAMERAS:
        return 6
    if channel == "LIDAR_TOP":
        return 10
    return 6 + (k + RADARS.index(channel)) % 2


def _scene_rows(s: int, channels: tuple[str, ...], sensors: list[dict]) -> tuple[dict, list[dict], dict, list[dict]]:
    """(log, calibrated_sensor rows, scene row, sample rows) of generated scene `s`."""
    log = {"token": _tok(9, s), "logfile": f"n015-2018-07-24-11-22-45+0800-{s}", "vehicle": "n015",
           "date_captured": "2018-07-24", "location": "singapore-onenorth"}
    calibs = []
    for ci, c in enumerate(channels):
        row = {"token": _tok(14, s * len(channels) + ci), "sensor_token": sensors[ci]["token"],
               "translation": [1.70079, 0.01594, 1.51095],
               "rotation": [0.4998015, -0.5030316, 0.4997798, -0.4973708], "camera_intrinsic": []}
        if c in CAMERAS:
            row["camera_intrinsic"] = [[1266.417, 0.0, 816.267], [0.0, 1266.417, 491.507], [0.0, 0.0, 1.0]]
        calibs.append(row)
    t0 = _T_BASE + s * 100_000_000
    stoks = [_tok(12, s * SAMPLES_PER_SCENE + k) for k in range(SAMPLES_PER_SCENE)]
    scene = {"token": _tok(13, s), "log_token": _tok(9, s), "nbr_samples": SAMPLES_PER_SCENE,
             "first_sample_token": stoks[0], "last_sample_token": stoks[-1],
             "name": f"scene-{s + 1:04d}", "description": "generated"}
    samples = [{"token": st, "timestamp": t0 + 500_000 * k, "prev": stoks[k - 1] if k else "",
                "next": stoks[k + 1] if k + 1 < len(stoks) else "", "scene_token": _tok(13, s)}
               for k, st in enumerate(stoks)]
    return log, calibs, scene, samples


def _channel_json(c: str, t0: int, stoks: list[str], cal_token: str, start: int,
                  first: bool) -> tuple[str, str, int]:
    """(sample_data text, ego_pose text, row count) of one channel of one scene, rows numbered from `start`."""
    ext, (w, h) = ("jpg", (1600, 900)) if c in CAMERAS else ("pcd.bin", (0, 0))
    plan = [(t0 + 500_000 * k + 12_000 + j * (500_000 // n), j == 0, stoks[k] if j == 0 else
             stoks[min(k + 1, len(stoks) - 1)])
            for k in range(SAMPLES_PER_SCENE) for n in [_channel_rows(c, k)] for j in range(n)]
    parts, eparts = [], []
    for i, (t, key, st) in enumerate(plan):
        idx = start + i
        folder_name = "samples" if key else "sweeps"
        prev = _tok(10, idx - 1) if i else ""
        nxt = _tok(10, idx + 1) if i + 1 < len(plan) else ""
        parts.append(
            f'{"" if first and i == 0 else ","}{{\n"token": "{_tok(10, idx)}",\n"sample_token": "{st}",\n'
            f'"ego_pose_token": "{_tok(11, idx)}",\n"calibrated_sensor_token": "{cal_token}",\n'
            f'"timestamp": {t},\n"fileformat": "{ext}",\n"is_key_frame": {"true" if key else "false"},\n'
            f'"height": {h},\n"width": {w},\n'
            f'"filename": "{folder_name}/{c}/n015-2018-07-24-11-22-45+0800__{c}__{t}.{ext}",\n'
            f'"prev": "{prev}",\n"next": "{nxt}"\n}}\n')
        x = 411.3 + 0.000004 * (t - t0)
        eparts.append(
            f'{"" if first and i == 0 else ","}{{\n"token": "{_tok(11, idx)}",\n"timestamp": {t},\n'
            f'"rotation": [\n0.5720320396729045,\n-0.0016977771610471074,\n0.011798001930183783,\n'
            f'-0.8201446642457809\n],\n"translation": [\n{x!r},\n1180.8932498976914,\n0.0\n]\n}}\n')
    return "".join(parts), "".join(eparts), len(plan)


def write_tables(root: Path, rows: int, version: str = "v1.0-trainval") -> dict:
    """Write a nuScenes-shaped table set with about `rows` sample_data rows; returns its counts."""
    folder = root / version
    folder.mkdir(parents=True, exist_ok=True)
    scenes = max(1, round(rows / (SAMPLES_PER_SCENE * ROWS_PER_SAMPLE)))
    channels = (*CAMERAS, "LIDAR_TOP", *RADARS)
    sensors = [{"token": _tok(15, i), "channel": c, "modality": "camera" if c.startswith("CAM") else
                c.split("_")[0].lower()} for i, c in enumerate(channels)]
    calibs, scene_rows, samples, logs = [], [], [], []
    n_sd = 0
    with open(folder / "sample_data.json", "w", encoding="utf-8") as sd_file, \
            open(folder / "ego_pose.json", "w", encoding="utf-8") as ego_file:
        sd_file.write("[\n")
        ego_file.write("[\n")
        for s in range(scenes):
            log, cal_rows, scene, scene_samples = _scene_rows(s, channels, sensors)
            logs.append(log)
            calibs.extend(cal_rows)
            scene_rows.append(scene)
            samples.extend(scene_samples)
            stoks = [row["token"] for row in scene_samples]
            for ci, c in enumerate(channels):
                sd_text, ego_text, n = _channel_json(c, _T_BASE + s * 100_000_000, stoks, cal_rows[ci]["token"],
                                                     n_sd, n_sd == 0)
                n_sd += n
                sd_file.write(sd_text)
                ego_file.write(ego_text)
        sd_file.write("]\n")
        ego_file.write("]\n")
    for name, table in (("scene", scene_rows), ("sample", samples), ("sensor", sensors),
                        ("calibrated_sensor", calibs), ("log", logs)):
        (folder / f"{name}.json").write_text(json.dumps(table, indent=0), encoding="utf-8")
    return {"scenes": scenes, "samples": len(samples), "sample_data_rows": n_sd,
            "sample_data_mb": round((folder / "sample_data.json").stat().st_size / 1e6, 1),
            "ego_pose_mb": round((folder / "ego_pose.json").stat().st_size / 1e6, 1)}


_CHILD = """
import json, resource, sys, time
from sgde_plugin.readers import load_rig, load_rigs
import sgde_plugin.cameras, numpy, torch
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t, c = time.perf_counter(), time.process_time()
what, location = sys.argv[1], sys.argv[2]
rigs = load_rigs(location) if what == "all" else [load_rig(location)]
elapsed, cpu = time.perf_counter() - t, time.process_time() - c
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"seconds": elapsed, "cpu_seconds": cpu, "peak_rss_gb": peak / 2**20,
                  "rss_after_imports_gb": base / 2**20, "rigs": len(rigs), "frames": sum(len(r.frames) for r in rigs)}))
"""


def _measure(what: str, location: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", _CHILD, what, location], capture_output=True, text=True,
                          timeout=LIMIT_TIME_S)
    if proc.returncode != 0:
        return {"error": (proc.stderr.strip().splitlines() or ["failed"])[-1]}
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out = {k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()}
    out["meets_target"] = out["seconds"] < TIME_TARGET_S and out["peak_rss_gb"] < MEMORY_TARGET_GB
    out["meets_target_in_cpu_time"] = out["cpu_seconds"] < TIME_TARGET_S and out["peak_rss_gb"] < MEMORY_TARGET_GB
    return out


def run(fast: bool = False) -> dict:
    """Generate the tables, then time and measure four loads in fresh processes."""
    rows = FAST_ROWS if fast else FULL_ROWS
    with tempfile.TemporaryDirectory(prefix="sgde_bench_nuscenes_") as tmp:
        root = Path(tmp)
        t = time.perf_counter()
        counts = write_tables(root, rows)
        generate_s = time.perf_counter() - t
        base = f"{root}::v1.0-trainval"
        results = {
            "one_scene_keyframes": _measure("one", f"{base}::scene-0001"),
            "all_scenes_keyframes": _measure("all", base),
            "one_scene_sweeps": _measure("one", f"{base}::scene-0001::sweeps"),
            "all_scenes_sweeps": _measure("all", f"{base}::sweeps"),
        }
    return {
        "load_average_1min": round(os.getloadavg()[0], 2),
        "tables": counts,
        "generate_seconds": round(generate_s, 1),
        "targets": {"seconds": TIME_TARGET_S, "peak_rss_gb": MEMORY_TARGET_GB},
        **results,
        "meets_targets": all(r.get("meets_target", False) for r in results.values()),
    }


if __name__ == "__main__":
    print(json.dumps(run(fast="--fast" in sys.argv), indent=1))
