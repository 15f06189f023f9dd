"""Surround-view self-calibration with the geometric loop constraint."""
