"""Prior cache: zarr store, builds, the read API and the training-side dataset."""
