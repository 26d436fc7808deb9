"""The observation contract (ObsSpec) and the ONNX actor."""
