"""Prior settings: every PriorConfig field reachable from a YAML file and the command line, presets, the
round trip through a file, the fingerprint following every setting, and one-line refusals.

Runtime ~6 s on 2 cores (one 1-frame synthetic rig at 400x225 for the command-line build).
"""

from __future__ import annotations

import pytest

from sgde_plugin.cache.fingerprints import config_document, digest, fingerprint
from sgde_plugin.cache.store import PriorCache
from sgde_plugin.cli import build_parser
from sgde_plugin.cli import main as cli_main
from sgde_plugin.commands.prior import SETTING_OPTIONS, load_rig_with_override, settings_from_args
from sgde_plugin.errors import InputError
from sgde_plugin.stereo.config import RUNTIME_FIELDS, SETTINGS, PriorConfig
from sgde_plugin.stereo.presets import PRESETS, load_prior_config, read_config_file, save_prior_config

# a value other than the default for every field (all valid together)
CHANGED = {
    "matcher": "torch", "matcher_arch": "pkg.mod:make", "matcher_options": {"width": 3, "names": ["a", "b"]},
    "matcher_iters": 7, "matcher_input_scale": 1 / 255, "matcher_flow_output": True, "matcher_pad": 8,
    "device": "cuda", "matcher_batch": 4, "scale": 0.25, "min_depth": 2.0, "max_depth": 150.0, "block_size": 5,
    "p1": 4, "p2": 64, "uniqueness": 5, "speckle_window": 50, "speckle_range": 3, "lr_max_diff": 1.5,
    "border_px": 3, "refine_iterations": 2, "min_zncc": 0.4, "max_abs_diff": 10.0, "min_texture": 0.25,
    "min_region_px": 100, "color": False, "margin_px": 4, "max_azimuth_deg": 70.0, "max_elevation_deg": 40.0,
    "fisheye": "virtual", "confidence_disparity_px": 4.0, "edge_jump_px": 2.0, "normalize": "local", "antialias": True,
    "min_confidence": 0.3, "edge_depth_ratio": 0.2, "edge_window_px": 9,
    "normalize_sigma": 6.0, "ground_depth_ratio": 2.0, "sweep_planes": 64, "sweep_step_px": 1.5, "sweep_window": 5,
    "sweep_paths": 2, "sweep_p1": 0.1, "sweep_p2": 0.5, "sweep_uniqueness": 0.1,
}


@pytest.fixture
def model(tmp_path):
    path = tmp_path / "model.pt"
    path.write_bytes(b"weights")
    return path


def test_every_field_round_trips_through_a_file_and_has_an_option(model, tmp_path):
    names = list(SETTINGS)
    assert sorted(CHANGED) == sorted(n for n in names if n != "matcher_path")
    config = PriorConfig.from_settings(**CHANGED, matcher_path=str(model))
    default = PriorConfig.from_settings(matcher="torch", matcher_path=str(model))
    assert all(config.get(n) != default.get(n) for n in CHANGED if n != "matcher")
    assert load_prior_config(save_prior_config(config, tmp_path / "c.yaml")) == config
    assert PriorConfig.from_settings(**config.settings()) == config
    for preset in PRESETS:  # presets and matcher-dependent defaults survive the round trip too
        for matcher in ("sgbm", "raft-stereo"):
            path = {"matcher_path": str(model)} if matcher != "sgbm" else {}
            c = load_prior_config(preset=preset, overrides={"matcher": matcher, **path})
            assert load_prior_config(save_prior_config(c, tmp_path / "p.yaml")) == c
    # every field has a command-line option (matcher_options through --matcher-option KEY=VALUE)
    options = {name for name, _, _ in SETTING_OPTIONS} | {"matcher_options"}
    assert options == set(names)
    args = build_parser().parse_args(
        ["prior", "D", "--out", "C", "--matcher", "torch", "--matcher-path", str(model), "--block-size", "5",
         "--no-color", "--matcher-flow-output", "--min-zncc", "0.4", "--matcher-option", "width=3",
         "--matcher-option", "names=[a, b]"])
    got = load_prior_config(overrides=settings_from_args(args))
    got_values = (got.sgbm.block_size, got.images.color, got.matcher.flow_output, got.filters.min_zncc)
    assert got_values == (5, False, True, 0.4)
    assert got.matcher.options == {"width": 3, "names": ["a", "b"]}


def test_matcher_dependent_defaults_and_layer_order(model, tmp_path):
    sgbm, learned = PriorConfig(), PriorConfig.from_settings(matcher="raft-stereo", matcher_path=str(model))
    f, m = sgbm.filters, sgbm.matcher
    sgbm_values = (f.refine_iterations, sgbm.images.color, f.min_texture, m.flow_output)
    assert sgbm_values == (1, False, 0.5, False)
    assert (learned.filters.refine_iterations, learned.images.color, learned.filters.min_texture) == (0, True, 0.0)
    assert learned.matcher.flow_output and learned.matcher.iters == 32
    # a saved SGBM file switched to a learned matcher takes the learned defaults (nulls, not SGBM's values)
    path = save_prior_config(sgbm, tmp_path / "s.yaml")
    switched = load_prior_config(path, overrides={"matcher": "onnx", "matcher_path": str(model)})
    assert (switched.filters.refine_iterations, switched.images.color) == (0, True)
    # defaults < preset < file < overrides; a file may name its preset
    path.write_text("preset: ddad\nuniqueness: 9\n")
    assert load_prior_config(path).geometry.max_depth == 200.0 and load_prior_config(path).sgbm.uniqueness == 9
    assert load_prior_config(path, preset="nuscenes").geometry.max_depth == 80.0
    assert load_prior_config(path, overrides={"max_depth": 120, "uniqueness": None}).geometry.max_depth == 120.0
    assert read_config_file(path) == {"preset": "ddad", "uniqueness": 9}


def test_fingerprint_follows_every_setting_but_the_runtime_ones(model):
    base = PriorConfig.from_settings(matcher="torch", matcher_path=str(model))
    base_fp = digest(config_document(base))
    for name, value in CHANGED.items():
        if name == "matcher":
            continue
        changed = base.replace(**{name: value})
        same = digest(config_document(changed)) == base_fp
        assert same == (name in RUNTIME_FIELDS), name
    for preset, settings in PRESETS.items():  # a preset is exactly its settings, fingerprint included
        explicit = PriorConfig.from_settings(**settings)
        assert digest(config_document(load_prior_config(preset=preset))) == digest(config_document(explicit))
    assert digest(config_document(load_prior_config(preset="ddad"))) != digest(config_document(PriorConfig()))
    model.write_bytes(b"other weights")
    assert digest(config_document(base)) != base_fp


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("uniqness: 9\n", "uniqness: unknown setting"),
        ("uniqueness: many\n", "uniqueness: expected an integer, got 'many'"),
        ("scale: 3.0\n", "scale: must be in (0, 2]"),
        ("color: 1\n", "color: expected true or false, got 1"),
        ("min_zncc: .nan\n", "min_zncc: must be a finite number"),
        ("fisheye: sideways\n", "fisheye: expected one of direct, virtual"),
        ("preset: mars\n", "preset: unknown preset 'mars'"),
        ("[1, 2]\n", "expected a mapping"),
        ("scale: [\n", "not valid YAML"),
        ("sgbm: {p1: 100, p2: 1}\n", "p2: must be greater than p1"),
        ("max_azimuth_deg: 0\n", "max_azimuth_deg: must be in (0, 90) degrees, got 0"),
        ("margin_px: 100000\n", "margin_px: must be in [0, 1024] pixels, got 100000"),
    ],
)
def test_sgde_prior_refuses_a_bad_config_file_in_one_line(tmp_path, capsys, text, needle):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    code = cli_main(["prior", str(tmp_path / "no-rig-needed"), "--out", str(tmp_path / "c"), "--config", str(path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert str(path) in err[0] and needle in err[0], err[0]
    assert not (tmp_path / "c").exists()


def test_bad_command_line_values_and_presets_are_one_line(tmp_path, capsys):
    for argv, needle in (
        (["--preset", "mars"], "preset: unknown preset 'mars'"),
        (["--device", "tpu"], "device: expected one of cpu, cuda"),
        (["--matcher-option", "novalue"], "--matcher-option: expected KEY=VALUE"),
        (["--matcher", "raft-stereo"], "matcher_path: matcher 'raft-stereo' needs a model file"),
        (["--matcher-path", str(tmp_path)], "matcher_path: matcher 'sgbm' takes no model file (the learned ones do: "),
        (["--matcher", "planesweep", "--matcher-path", "m.pt"], "matcher_path: matcher 'planesweep' takes no model"),
    ):
        code = cli_main(["prior", str(tmp_path), "--out", str(tmp_path / "c"), *argv])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and needle in err[0], (argv, err)
    with pytest.raises(InputError, match="block_size: must be odd"):
        PriorConfig.from_settings(block_size=4)


# settings the build could not use (a ZeroDivisionError, OpenCV assertions, tens of GB allocated) or silently
# misused (every frame empty, inflated confidences): one line naming the setting, exit 2, before the cache exists
OUT_OF_RANGE = [
    (["--max-azimuth-deg", "0"], "max_azimuth_deg: must be in (0, 90) degrees"),
    (["--max-azimuth-deg", "500"], "max_azimuth_deg: must be in (0, 90) degrees"),
    (["--max-azimuth-deg", "-10"], "max_azimuth_deg: must be in (0, 90) degrees"),
    (["--max-elevation-deg", "95"], "max_elevation_deg: must be in (0, 90) degrees"),
    (["--max-azimuth-deg", "1", "--max-elevation-deg", "89"],
     "max_elevation_deg: tan(max_elevation_deg) / tan(max_azimuth_deg) must be at most 16, got 3.28e+03"),
    (["--normalize", "local", "--normalize-sigma", "0"], "normalize_sigma: must be in (0, 1024] pixels"),
    (["--margin-px", "100000"], "margin_px: must be in [0, 1024] pixels"),
    (["--border-px", "100000"], "border_px: must be in [0, 1024] pixels"),
    (["--confidence-disparity-px", "-2"], "confidence_disparity_px: must be positive"),
    (["--p1", "-5"], "p1: must not be negative"),
    (["--p1", "100", "--p2", "1"], "p2: must be greater than p1 (OpenCV SGBM needs P2 > P1), got p1 = 100, p2 = 1"),
    (["--uniqueness", "-5"], "uniqueness: must be in [0, 100]"),
    (["--speckle-window", "-1"], "speckle_window: must not be negative"),
    (["--lr-max-diff", "-1"], "lr_max_diff: must be positive"),
    (["--lr-max-diff", "0"], "lr_max_diff: must be positive"),
    (["--min-zncc", "1"], "min_zncc: must be in [-1, 1)"),
    (["--min-zncc", "-2"], "min_zncc: must be in [-1, 1)"),
    (["--edge-jump-px", "-1"], "edge_jump_px: must not be negative"),
    (["--matcher-input-scale", "0"], "matcher_input_scale: must be positive"),
    (["--max-abs-diff", "0"], "max_abs_diff: must be positive"),
    # the cache stores float16 depths: beyond 65504 m (or under 6.2e-5 m) a depth would be served clipped
    (["--max-depth", "1e9"], "max_depth: must be at most 65504 m"),
    (["--min-depth", "1e-6"], "min_depth: must be at least 6.2e-05 m (the cache stores float16 depths)"),
]


@pytest.fixture(scope="module")
def small_rig(tmp_path_factory):
    synth = pytest.importorskip("sgde_plugin.synth.sequence")
    return synth.write_synth("nuscenes", 1, tmp_path_factory.mktemp("rig") / "nus", scale=0.25)


@pytest.mark.parametrize(("argv", "needle"), OUT_OF_RANGE)
def test_out_of_range_settings_are_one_line_and_leave_no_cache(small_rig, tmp_path, capsys, argv, needle):
    out = tmp_path / "cache"
    code = cli_main(["prior", str(small_rig), "--out", str(out), "--workers", "1", *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and needle in err[0], (argv, err)
    assert not out.exists()


def test_a_corrected_rerun_after_a_bad_setting_builds_into_the_same_out(small_rig, tmp_path, capsys):
    out = str(tmp_path / "cache")
    assert cli_main(["prior", str(small_rig), "--out", out, "--workers", "1", "--max-azimuth-deg", "0"]) == 2
    assert cli_main(["prior", str(small_rig), "--out", out, "--workers", "1"]) == 0
    assert "1 frames built" in capsys.readouterr().out


def test_range_limits_keep_the_defaults_and_the_usable_edge_values():
    edges = {"p1": 0, "p2": 1, "uniqueness": 0, "speckle_window": 0, "speckle_range": 0, "max_azimuth_deg": 89.9,
             "max_elevation_deg": 0.5, "margin_px": 1024, "border_px": 0, "normalize_sigma": 0.1,
             "lr_max_diff": 0.01, "confidence_disparity_px": 0.01, "min_zncc": -1.0, "max_abs_diff": 0.5,
             "min_depth": 6.2e-5, "max_depth": 65504.0, "edge_jump_px": 0.0, "matcher_input_scale": 1e-3}
    config = PriorConfig.from_settings(edges)
    assert all(config.get(name) == value for name, value in edges.items())
    for preset in PRESETS:
        load_prior_config(preset=preset)


def test_sgde_prior_applies_preset_file_and_flags_to_the_cache_fingerprint(tmp_path, capsys):
    synth = pytest.importorskip("sgde_plugin.synth.sequence")
    root = synth.write_synth("nuscenes", 1, tmp_path / "nus", scale=0.25)
    true_rig = str(root / "rig_true.json")
    path = tmp_path / "prior.yaml"
    path.write_text("preset: ddad\nuniqueness: 12\nmin_region_px: 150\n")
    out = str(tmp_path / "cache")
    argv = ["prior", str(root), "--out", out, "--rig", true_rig, "--workers", "1", "--config", str(path)]
    assert cli_main([*argv, "--min-region-px", "120"]) == 0
    capsys.readouterr()
    rig = load_rig_with_override(str(root), true_rig)
    expected = PriorConfig.from_settings(**{**PRESETS["ddad"], "uniqueness": 12, "min_region_px": 120})
    assert PriorCache(out).fingerprint == fingerprint(rig, expected)
    # the same settings from another file are the same cache; a changed file is refused, naming the change
    save_prior_config(expected, tmp_path / "same.yaml")
    assert cli_main(["prior", str(root), "--out", out, "--rig", true_rig, "--config", str(tmp_path / "same.yaml")]) == 0
    assert "0 frames built, 1 already there" in capsys.readouterr().out
    assert cli_main([*argv, "--preset", "nuscenes", "--min-region-px", "120"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "max_depth 200.0 -> 80.0" in err[0]


# config-document digests: the nesting by concern was checked against the flat fields of commit 68affc8; they
# were re-pinned when issue #16 added edge_depth_ratio and edge_window_px, and again when it added
# ground_depth_ratio (a new setting changes every document), when it added the plane sweep's `sweep_*`, and when
# `fisheye: tiled` became the default (session 9; pinhole priors unchanged, their documents name the new default).
# The grouping must not change any cache's fingerprint
PINNED = {"defaults": "b934871acf5854f31bf9", "synthetic": "b934871acf5854f31bf9", "nuscenes": "74169fe7d6719fd72010",
          "ddad": "19d17477b007a6b78b82", "fisheye": "29764736c35af56e6383", "changed": "4cba36597dd1ad4ac249"}


def test_fingerprints_are_those_of_the_flat_config():
    got = {"defaults": digest(config_document(PriorConfig()))}
    got |= {name: digest(config_document(load_prior_config(preset=name))) for name in PRESETS}
    changed = {k: v for k, v in CHANGED.items() if k not in ("matcher", "matcher_path")}  # SGBM: no model file
    got["changed"] = digest(config_document(PriorConfig.from_settings(changed)))
    assert got == PINNED


def test_nested_and_flat_config_files_and_every_group_in_the_fingerprint(model, tmp_path):
    path = tmp_path / "nested.yaml"
    path.write_text("preset: ddad\nsgbm: {uniqueness: 9, p2: 40}\nmatcher: {name: torch, path: " + str(model) + "}\n"
                    "geometry:\n  scale: 0.25\nmin_zncc: 0.3\n")
    config = load_prior_config(path)
    got = (config.sgbm.uniqueness, config.sgbm.p2, config.geometry.scale, config.filters.min_zncc)
    assert got == (9, 40, 0.25, 0.3)
    assert config.matcher.name == "torch" and config.geometry.max_depth == 200.0
    flat = PriorConfig.from_settings({**PRESETS["ddad"], "uniqueness": 9, "p2": 40, "matcher": "torch",
                                      "matcher_path": str(model), "scale": 0.25, "min_zncc": 0.3})
    assert config == flat and load_prior_config(save_prior_config(config, tmp_path / "s.yaml")) == config
    for text, needle in (("sgbm: {blocksize: 5}\n", "sgbm.blocksize: unknown setting"),
                         ("sgbm: {uniqueness: 9}\nuniqueness: 8\n", "uniqueness: given twice"),
                         ("filters: 3\n", "filters: expected a mapping")):
        path.write_text(text)
        with pytest.raises(InputError, match=needle):
            load_prior_config(path)
    # the fingerprint document holds every group whatever the matcher (none is dropped for SGBM or a learned one)
    for c in (PriorConfig(), config):
        assert set(c.to_dict()) >= set(SETTINGS) - set(RUNTIME_FIELDS)
