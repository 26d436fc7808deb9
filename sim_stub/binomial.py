"""Binomial statistics of success rates, for `safemove eval` and `safemove compare`.

The Wilson score interval stays inside [0, 1] and keeps its coverage near 0 % and 100 %, where
the normal approximation does not. McNemar's exact test is a two-sided binomial test at one half
on the discordant pairs of two paired samples.
"""

from __future__ import annotations

from scipy.stats import binomtest

CONFIDENCE = 0.95


def wilson_interval(successes: int, n: int) -> tuple[float, float]:
    """The 95 % Wilson score interval of a success rate."""
    ci = binomtest(successes, n).proportion_ci(confidence_level=CONFIDENCE, method="wilson")
    return float(ci.low), float(ci.high)


def mcnemar_exact_p(only_first: int, only_second: int) -> float:
    """Two-sided exact McNemar p-value from the discordant pairs' counts (1 without any)."""
    discordant = only_first + only_second
    return 1.0 if discordant == 0 else float(binomtest(only_first, discordant).pvalue)
