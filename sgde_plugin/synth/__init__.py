"""The built-in synthetic surround world: procedural street scenes, rendering, rig presets."""
