"""Surround-view self-calibration with the geometric loop constraint (GLC), design step 2.

`calibrate(rig, images, method="glc")` refines the extrinsics of a rig over windows of frames and
returns the refined rig and its `calibration` report block. Methods: none, pairwise, wo-glc, glc.
Modules: overlap (predicted overlaps), features / views (SIFT, LoFTR, fisheye virtual views),
outliers (USAC), correspondences (all T x T frame pairs), ba (loop-constrained adjustment), methods,
acceptance (beta, iterations, alpha), pipeline (windows and history), simulate (test scenes).
"""

from .acceptance import ALPHA_M, BETA_DDAD, BETA_NUSCENES, BETA_SYNTH, AcceptanceRules, default_beta
from .ba import AdjustConfig, Observations, adjust, robust_adjust
from .correspondences import MatchConfig, PairMatches, Timings, find_correspondences
from .methods import METHODS, run_method
from .pipeline import CALIB_VERSION, calibrate, calibration_at, check_extrinsics, reference_camera

__all__ = [
    "ALPHA_M",
    "BETA_DDAD",
    "BETA_NUSCENES",
    "BETA_SYNTH",
    "CALIB_VERSION",
    "METHODS",
    "AcceptanceRules",
    "AdjustConfig",
    "MatchConfig",
    "Observations",
    "PairMatches",
    "Timings",
    "adjust",
    "calibrate",
    "calibration_at",
    "check_extrinsics",
    "default_beta",
    "find_correspondences",
    "reference_camera",
    "robust_adjust",
    "run_method",
]
