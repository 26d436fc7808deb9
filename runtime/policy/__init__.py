"""The observation contract (ObsSpec), the ONNX actor and the actors shipped with the package."""
