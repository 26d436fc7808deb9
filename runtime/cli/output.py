"""What every command prints: figures one per line, then one JSON line (the last line of
output is always one JSON object, for scripts)."""

from __future__ import annotations

import json
from typing import Any


def print_json(obj: Any) -> None:
    print(json.dumps(obj, separators=(",", ":")), flush=True)


def print_figures(result: dict[str, Any], json_only: bool) -> int:
    """Figures one per line (unless `json_only`), then the whole result as the last line."""
    if not json_only:
        for key, value in result.items():
            print(f"{key}: {value}")
    print_json(result)
    return 0


def finish(report_dict: dict[str, Any], exit_code: int) -> int:
    print_json(report_dict)
    return exit_code
