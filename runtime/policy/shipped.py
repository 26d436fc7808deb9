"""The trained actors that ship inside the package, one per observation-spec preset.

They are package data (`runtime/policy/models/<variant>.onnx`, listed in pyproject.toml), found
beside this module, so they resolve the same in a checkout and in a non-editable install such
as the robot's /opt/safemove/.venv. A file that is absent is a user error naming the path: an
installation may lack one, and the user can still give their own model.
"""

from __future__ import annotations

from pathlib import Path

from runtime.errors import UserError
from runtime.policy.obs_spec import PRESETS

# the paper's ablation variants: a shipped model's spec is the preset of its name
VARIANTS: tuple[str, ...] = tuple(PRESETS)
DEFAULT_VARIANT = "safemove"
MODELS_DIR = Path(__file__).resolve().parent / "models"


def _path(variant: str) -> Path:
    return MODELS_DIR / f"{variant}.onnx"


def shipped_model(variant: str, instead: str = "give --model FILE.onnx") -> Path:
    """The shipped actor file of `variant`; `instead` ends the message when it is absent, so
    each command can name its own way out."""
    if variant not in VARIANTS:
        raise UserError(f"unknown policy variant '{variant}' (variants: {', '.join(VARIANTS)})")
    path = _path(variant)
    if not path.is_file():
        raise UserError(f"no shipped '{variant}' policy in this installation ({path}); {instead}")
    return path


def shipped_variants() -> list[str]:
    """The variants whose file this installation has."""
    return [v for v in VARIANTS if _path(v).is_file()]


def variant_of(model: Path) -> str | None:
    """The shipped variant `model` is, or None for any other file: reports name what ran."""
    resolved = model.resolve()
    return next((v for v in VARIANTS if _path(v).resolve() == resolved), None)
