"""The built-in synthetic surround world: procedural street scenes, rendering, rig presets, sequences."""

from .presets import PRESETS, preset_cameras, preset_ring
from .render import render
from .sequence import SynthSequence, synth_sequence, write_synth
from .world import World, build_world

__all__ = [
    "PRESETS",
    "SynthSequence",
    "World",
    "build_world",
    "preset_cameras",
    "preset_ring",
    "render",
    "synth_sequence",
    "write_synth",
]
