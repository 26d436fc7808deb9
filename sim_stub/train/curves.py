"""Learning curves from training runs' `monitor.csv`: success rate and episode return against
environment steps, one line per run (a variant), with matplotlib's file-only backend.

Each episode is placed at the environment steps collected when it ended (the running sum of
episode lengths: with N envs the order is the order episodes ended, which is how VecMonitor
writes them). Both curves are means over the last `window` episodes, so a curve starts once
`window` episodes have ended.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Curve:
    steps: np.ndarray  # env steps at each episode's end
    success: np.ndarray  # rolling success rate
    episode_return: np.ndarray  # rolling mean return


def read_curve(monitor_csv: Path, window: int) -> Curve:
    """The rolling curves of one run (empty arrays while fewer than `window` episodes)."""
    with monitor_csv.open(encoding="utf-8", newline="") as f:
        next(f)  # the JSON header line
        rows = list(csv.DictReader(f))
    lengths = np.array([int(r["l"]) for r in rows])
    returns = np.array([float(r["r"]) for r in rows])
    success = np.array([r["outcome"] == "success" for r in rows], dtype=float)
    if len(rows) < window:
        empty = np.zeros(0)
        return Curve(empty, empty, empty)
    kernel = np.ones(window) / window
    return Curve(np.cumsum(lengths)[window - 1:], np.convolve(success, kernel, "valid"),
                 np.convolve(returns, kernel, "valid"))


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
