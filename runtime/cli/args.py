"""argparse pieces every `safemove` command line shares: the config options, the actor for
--planner safemove, and number types that refuse NaN, inf and nonsense with a one-line
message."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path

from runtime.errors import UserError
from runtime.policy.shipped import DEFAULT_VARIANT, VARIANTS, shipped_model


def add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, default=None,
                   help="config file (default: the shipped runtime/config/default_config.yaml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config key, e.g. --set base.port=/dev/ttyUSB0 (repeatable)")


def add_policy_args(p: argparse.ArgumentParser) -> None:
    """--model or --variant (one of them): the actor for --planner safemove."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--model", type=Path, metavar="FILE.onnx",
                   help="the actor for --planner safemove, written by `safemove export`")
    g.add_argument("--variant", choices=VARIANTS,
                   help="the actor for --planner safemove that ships with this installation"
                        f" (default, without --model: {DEFAULT_VARIANT})")


def policy_model(args: argparse.Namespace, command: str,
                 instead: str = "give --model FILE.onnx") -> Path | None:
    """The actor file args.planner needs: --model, the shipped --variant or the shipped default
    for safemove, None for any other planner (which refuses both). Resolved before anything
    starts, so a missing file is one line; `instead` ends that line (shipped_model)."""
    if args.planner != "safemove":
        for flag, value in (("--model", args.model), ("--variant", args.variant)):
            if value is not None:
                raise UserError(f"{command}: {flag} is for --planner safemove, not {args.planner}")
        return None
    if args.model is not None:
        return args.model
    return shipped_model(args.variant or DEFAULT_VARIANT, instead)


def finite_float(text: str) -> float:
    """argparse type: a finite number (NaN or inf would reach the wheels as a command)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """argparse type: a finite number ≥ 0 (a standard deviation, a duration)."""
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be at least 0, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (a weight that must pull)."""
    value = finite_float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be above 0, got {text!r}")
    return value


def int_at_least(minimum: int) -> Callable[[str], int]:
    """argparse type: an integer ≥ minimum."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value

    return parse
