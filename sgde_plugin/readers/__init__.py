"""Dataset readers (nuScenes, DDAD, Synthetic Urban) into the common Rig."""
