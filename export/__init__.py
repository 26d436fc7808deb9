"""Torch checkpoint → ONNX actor for the runtime (`safemove export`): checkpoints of four kinds
(`checkpoint`), MLP actors rebuilt from weights (`mlp`), export and verification with the
observation spec embedded (`onnx_export`), recorded observations for parity (`observations`),
the training and evaluation records of an actor to ship (`ship`).
Needs the `export` extra (torch, onnx); the robot image does not."""
