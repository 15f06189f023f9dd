"""ONNX export of the prior-augmented depth nets and parity checks against onnxruntime."""
