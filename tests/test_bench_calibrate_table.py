"""`sgde bench calibrate --peer colmap [--scale F]`: the render scale reaches the rigs, bad use is refused, the
peer is left out where its model does not hold."""

from __future__ import annotations

import pytest

from sgde_plugin.benchmarks import calibrate as bench_calibrate
from sgde_plugin.cli import main


def test_scale_reaches_the_rendered_rigs(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[float] = []
    real = bench_calibrate.synth_sequence

    def render(*args, **kwargs):
        seen.append(kwargs["scale"])
        return real(*args, **kwargs)

    monkeypatch.setattr(bench_calibrate, "synth_sequence", render)
    row = bench_calibrate._accuracy_row("nuscenes", 0, "sync", None, glc=False, frames=1, scale=0.125)
    assert seen == [0.125] and row["scale"] == 0.125
    # the start's error is measured against the truth of the same render
    assert 0.3 < row["input"]["rotation_median_deg"] < 3.0


def test_peer_is_skipped_on_sequential_capture() -> None:
    row = bench_calibrate._accuracy_row("nuscenes", 0, "sequential", "colmap", glc=False, frames=1, scale=0.125)
    assert "sequential capture" in row["colmap"]["skipped"]
    assert "rotation_median_deg" not in row["colmap"]


def test_peer_is_skipped_on_cameras_colmap_cannot_model() -> None:
    pytest.importorskip("pycolmap")
    row = bench_calibrate._accuracy_row("urban-fisheye", 0, "sync", "colmap", glc=False, frames=1, scale=0.125)
    assert "no COLMAP equivalent" in row["colmap"]["skipped"]


def test_cli_passes_the_scale(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    calls: list[tuple] = []
    monkeypatch.setattr(bench_calibrate, "accuracy",
                        lambda peer, scale=None: calls.append((peer, scale)) or {"rows": [], "scale": scale})
    monkeypatch.setattr("sgde_plugin.commands.bench.machine_description", lambda: {})
    assert main(["bench", "calibrate", "--peer", "colmap", "--scale", "1"]) == 0
    assert calls == [("colmap", 1.0)]
    assert '"scale": 1.0' in capsys.readouterr().out


@pytest.mark.parametrize("args, expected", [
    (["bench", "calibrate", "--scale", "1"], "--peer colmap"),
    (["bench", "prior", "--peer", "colmap", "--scale", "1"], "--peer colmap"),
    (["bench", "calibrate", "--peer", "colmap", "--scale", "0"], "from 0.05 to 2"),
    (["bench", "calibrate", "--peer", "colmap", "--scale", "nan"], "from 0.05 to 2"),
])
def test_bad_scale_is_one_line_exit_2(args: list[str], expected: str, capsys: pytest.CaptureFixture) -> None:
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--scale" in err and expected in err, err
