"""MLP actors rebuilt from bare weights: the architecture read off the weight shapes, checked.

An MLP actor is a chain of Linear layers (state_dict keys `<layer>.weight` (out, in) and
optionally `<layer>.bias` (out,), in registration order) whose sizes chain (each layer's input
is the previous layer's output) and whose last layer outputs 2 (v, ω); hidden activations are
one kind (ReLU by default), the output is tanh. Anything else in the dict is refused, naming the
key, because guessing the wiring of an unknown network would export the wrong function.
"""

from __future__ import annotations

from collections.abc import Mapping
from itertools import pairwise

import torch
from torch import nn

from runtime.errors import UserError

ACTIVATIONS = {"relu": nn.ReLU, "leaky_relu": nn.LeakyReLU, "tanh": nn.Tanh}


class NotAnMLP(UserError):
    """The weights do not describe an MLP actor."""


class MLPActor(nn.Module):
    """Linear → act → … → Linear → tanh, then optionally SB3's unscaling onto [low, high]."""

    def __init__(self, sizes: list[int], activation: str = "relu", bias: bool = True,
                 action_low: tuple[float, float] | None = None,
                 action_high: tuple[float, float] | None = None) -> None:
        super().__init__()
        self.sizes = list(sizes)
        self.activation = activation
        self.layers = nn.ModuleList(nn.Linear(a, b, bias=bias) for a, b in pairwise(sizes))
        self.act = ACTIVATIONS[activation]()
        self.unscale = action_low is not None and action_high is not None
        low = torch.tensor(action_low if self.unscale else (-1.0, -1.0), dtype=torch.float32)
        high = torch.tensor(action_high if self.unscale else (1.0, 1.0), dtype=torch.float32)
        self.register_buffer("action_low", low, persistent=False)
        self.register_buffer("action_high", high, persistent=False)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        x = obs
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x = layer(x)
            x = self.act(x) if i < last else torch.tanh(x)
        if self.unscale:  # stable-baselines3's unscale_action, as predict() applies it
            x = self.action_low + 0.5 * (x + 1.0) * (self.action_high - self.action_low)
        return x


def mlp_layers(state: Mapping[str, object], source: str) -> list[tuple[str, torch.Tensor,
                                                                      torch.Tensor | None]]:
    """(layer name, weight, bias) in order; refuses, naming the key, anything not an MLP actor."""
    groups: dict[str, dict[str, torch.Tensor]] = {}
    for key, value in state.items():
        if not isinstance(value, torch.Tensor):
            raise NotAnMLP(f"{source}: key '{key}' holds a {type(value).__name__}, not a tensor:"
                           " not a state_dict of an MLP actor")
        module, _, param = key.rpartition(".")
        if param not in ("weight", "bias") or not module:
            raise NotAnMLP(f"{source}: key '{key}' (shape {list(value.shape)}) is not a Linear"
                           " layer's weight or bias: not an MLP actor")
        if not value.is_floating_point():
            raise NotAnMLP(f"{source}: key '{key}' is {value.dtype}, not floating point")
        groups.setdefault(module, {})[param] = value
    if not groups:
        raise NotAnMLP(f"{source}: the state_dict is empty")
    layers: list[tuple[str, torch.Tensor, torch.Tensor | None]] = []
    prev_out: int | None = None
    for name, params in groups.items():
        w, b = params.get("weight"), params.get("bias")
        if w is None or w.dim() != 2:
            shape = None if w is None else list(w.shape)
            raise NotAnMLP(f"{source}: layer '{name}' has weight {shape}, not a Linear layer's"
                           " (out, in): not an MLP actor")
        if b is not None and tuple(b.shape) != (w.shape[0],):
            raise NotAnMLP(f"{source}: layer '{name}': bias {list(b.shape)} does not match"
                           f" weight {list(w.shape)}")
        if prev_out is not None and w.shape[1] != prev_out:
            raise NotAnMLP(f"{source}: layer '{name}' takes {w.shape[1]} inputs but the layer"
                           f" before outputs {prev_out}: not a chain of Linear layers")
        prev_out = int(w.shape[0])
        layers.append((name, w, b))
    if prev_out != 2:
        raise NotAnMLP(f"{source}: the last layer '{layers[-1][0]}' outputs {prev_out}; an actor"
                       " outputs 2 (v, ω)")
    if len({b is None for _, _, b in layers}) > 1:
        raise NotAnMLP(f"{source}: some layers have a bias and some do not")
    return layers


def mlp_from_state(state: Mapping[str, object], source: str, activation: str = "relu",
                   action_low: tuple[float, float] | None = None,
                   action_high: tuple[float, float] | None = None) -> MLPActor:
    """The MLP actor that `state` describes, with its weights."""
    layers = mlp_layers(state, source)
    sizes = [int(layers[0][1].shape[1])] + [int(w.shape[0]) for _, w, _ in layers]
    actor = MLPActor(sizes, activation, bias=layers[0][2] is not None, action_low=action_low,
                     action_high=action_high)
    with torch.no_grad():
        for linear, (_, w, b) in zip(actor.layers, layers):
            linear.weight.copy_(w.float())
            if b is not None:
                linear.bias.copy_(b.float())
    return actor.eval()
