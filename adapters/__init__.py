"""Adapters of the SGDE depth prior to BEVDepth-style and VoxFormer-style pipelines."""
