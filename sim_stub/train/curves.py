"""Learning curves from training runs' `monitor.csv`: success rate and episode return against
environment steps, one line per run (a variant), with matplotlib's file-only backend.

Each episode is placed at the environment steps collected when it ended (the running sum of
episode lengths: with N envs the order is the order episodes ended, which is how VecMonitor
writes them). Both curves are means over the last `window` episodes, so a curve starts once
`window` episodes have ended.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from runtime.errors import UserError
from sim_stub.train.ship import read_json

MONITOR_COLUMNS = ("r", "l", "outcome")


@dataclass(frozen=True)
class Curve:
    steps: np.ndarray  # env steps at each episode's end
    success: np.ndarray  # rolling success rate
    episode_return: np.ndarray  # rolling mean return


def read_monitor(monitor_csv: Path) -> list[dict[str, str]]:
    """The Monitor file's rows (r, l, t, outcome), in the order the episodes ended, after its
    JSON header line; a file that is not one, or a row that does not parse, is refused naming
    the file and line. A last line without its newline is one the monitor of a run still
    training is writing: it is left for the next read."""
    try:
        text = monitor_csv.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UserError(f"{monitor_csv}: file not found (not a `safemove train` run"
                        " directory?)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{monitor_csv}: cannot read the training monitor: {exc}") from None
    lines = text[:text.rfind("\n") + 1].splitlines()
    if not lines or not lines[0].startswith("#"):
        raise UserError(f"{monitor_csv}: line 1: not a training monitor (no '#{{...}}' header)")
    try:
        reader = csv.DictReader(lines[1:])
        missing = [c for c in MONITOR_COLUMNS if c not in (reader.fieldnames or ())]
        rows = list(reader)
    except csv.Error as exc:
        raise UserError(f"{monitor_csv}: cannot read the training monitor: {exc}") from None
    if missing:
        raise UserError(f"{monitor_csv}: line 2: no column {', '.join(missing)} (a training"
                        " monitor has r, l, t, outcome)")
    for line, row in enumerate(rows, start=3):
        try:
            ok = (math.isfinite(float(row["r"])) and int(row["l"]) > 0
                  and bool(row["outcome"]))
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise UserError(f"{monitor_csv}: line {line}: not an episode (a finite return r,"
                            f" a length l ≥ 1 and an outcome): {row}")
    return rows


def read_curve(monitor_csv: Path, window: int) -> Curve:
    """The rolling curves of one run (empty arrays while fewer than `window` episodes)."""
    rows = read_monitor(monitor_csv)
    lengths = np.array([int(r["l"]) for r in rows])
    returns = np.array([float(r["r"]) for r in rows])
    success = np.array([r["outcome"] == "success" for r in rows], dtype=float)
    if len(rows) < window:
        empty = np.zeros(0)
        return Curve(empty, empty, empty)
    kernel = np.ones(window) / window
    return Curve(np.cumsum(lengths)[window - 1:], np.convolve(success, kernel, "valid"),
                 np.convolve(returns, kernel, "valid"))


def run_figures(runs: dict[str, Path], window: int) -> dict[str, dict[str, Any]]:
    """Per run directory (label → folder): its episodes and env steps so far, success (%) and
    mean return over its last `window` episodes (None while fewer), whether it has finished
    (its summary.json is written last) and where TD3 took over from the demonstrations."""
    figures = {}
    for label, folder in runs.items():
        if not folder.is_dir():
            raise UserError(f"{folder}: not a directory (a `safemove train` run directory)")
        rows = read_monitor(folder / "monitor.csv")
        summary_path = folder / "summary.json"
        summary: dict[str, Any] = {}
        if summary_path.exists():
            summary = read_json(summary_path)
            if not isinstance(summary, dict):
                raise UserError(f"{summary_path}: not a `safemove train` summary")
        demo = summary.get("demo_steps")  # none in a plain TD3 run's
        last = rows[-window:] if len(rows) >= window else []
        figures[label] = {
            "episodes": len(rows),
            "env_steps": sum(int(r["l"]) for r in rows),
            "success_pct_last": (round(100.0 * sum(r["outcome"] == "success" for r in last)
                                       / window, 1) if last else None),
            "return_last": (round(sum(float(r["r"]) for r in last) / window, 2)
                            if last else None),
            "finished": bool(summary),
            "td3_from": demo if isinstance(demo, int) and demo > 0 else None,
        }
    return figures


def plot_curves(runs: dict[str, Path], out_png: Path, window: int = 50,
                td3_from: int | None = None) -> None:
    """One figure, success rate above return, a line per run (label → its monitor.csv);
    `td3_from`: the env steps at which TD3 took over from the demonstrations (a dashed line)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_s, ax_r) = plt.subplots(2, 1, sharex=True, figsize=(7, 6))
    for label, path in runs.items():
        c = read_curve(path, window)
        ax_s.plot(c.steps, 100.0 * c.success, label=label)
        ax_r.plot(c.steps, c.episode_return, label=label)
    ax_s.set_ylabel(f"success, % (last {window} episodes)")
    ax_s.set_ylim(-2, 102)
    ax_r.set_ylabel(f"return (mean of last {window})")
    ax_r.set_xlabel("environment steps (control cycles)")
    for ax in (ax_s, ax_r):
        ax.grid(alpha=0.3)
        if td3_from:
            ax.axvline(td3_from, color="grey", linestyle="--", linewidth=1)
    if td3_from:
        ax_s.text(td3_from, 2, " TD3 from here; DWA demonstrations before", fontsize=8)
    ax_s.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(out_png, dpi=100)
    plt.close(fig)
