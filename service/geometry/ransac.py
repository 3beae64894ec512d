"""One generic RANSAC loop (MSAC scoring, adaptive stopping), vectorised across hypotheses.

The loop knows nothing about cameras: a problem supplies `propose` (minimal
samples -> a batch of hypotheses) and `score` (hypotheses -> truncated costs of
every datum). Hypotheses are a tuple of arrays sharing a leading hypothesis
axis, so a batch of 128 minimal problems is solved and scored in a few numpy
passes instead of 128 Python calls.

MSAC (Torr & Zisserman 2000): each datum costs min(c, 1) where c is its
squared residual in units of the inlier threshold, so inliers (c < 1) count by
how well they fit and outliers by a constant; the hypothesis with the lowest
total wins. The loop stops once a better sample is unlikely at the requested
confidence: with inlier ratio w and samples of m, a draw is all-inlier with
probability w^m, and n draws miss every such sample with probability
(1 - w^m)^n, hence n = log(1 - confidence) / log(1 - w^m). Random draws come
from the caller's numpy Generator, so a seed makes the result deterministic.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .errors import CalibrationError
from .vec import FloatArray

Hypotheses = tuple[np.ndarray, ...]
"""A batch of models: arrays that share a leading hypothesis axis (possibly of length 0)."""


@dataclass(frozen=True)
class RansacOptions:
    confidence: float = 0.999
    max_iterations: int = 5000
    batch: int = 128  # minimal samples drawn, solved and scored together


@dataclass(frozen=True)
class RansacOutcome:
    """The best hypothesis (each array without its leading axis), its costs on every datum, the draws made."""

    model: tuple[np.ndarray, ...]
    costs: FloatArray
    iterations: int

    @property
    def inliers(self) -> np.ndarray:
        return self.costs < 1.0


def draw_samples(rng: np.random.Generator, n: int, m: int, count: int) -> np.ndarray:
    """count rows of m distinct indices below n."""
    samples = rng.integers(0, n, size=(count, m))
    for _ in range(100):
        s = np.sort(samples, axis=1)
        dup = np.any(s[:, 1:] == s[:, :-1], axis=1)
        if not dup.any():
            break
        samples[dup] = rng.integers(0, n, size=(int(dup.sum()), m))
    return samples


def required_iterations(inlier_ratio: float, m: int, confidence: float) -> int:
    good = inlier_ratio**m
    if good >= 1.0:
        return 1
    if good <= 0.0:
        return 10**9
    return int(np.ceil(np.log(1.0 - confidence) / np.log(1.0 - good)))


def ransac(
    n: int,
    sample_size: int,
    propose: Callable[[np.ndarray], Hypotheses],
    score: Callable[[Hypotheses], FloatArray],
    options: RansacOptions,
    rng: np.random.Generator,
) -> RansacOutcome:
    """The hypothesis of lowest total MSAC cost over random minimal samples of the n data.

    propose maps (K, sample_size) index rows to at most K valid hypotheses;
    score maps M hypotheses to (M, n) costs truncated to [0, 1] (< 1: inlier).
    Raises CalibrationError when no valid hypothesis with enough inliers is found.
    """
    if n < sample_size:
        raise CalibrationError(f"need at least {sample_size} usable people, got {n}")
    best_total = np.inf
    best: RansacOutcome | None = None
    required, done = options.max_iterations, 0
    while done < min(required, options.max_iterations):
        count = min(options.batch, options.max_iterations - done)
        hypotheses = propose(draw_samples(rng, n, sample_size, count))
        done += count
        if len(hypotheses[0]) == 0:
            continue
        costs = score(hypotheses)
        total = costs.sum(1)
        i = int(np.argmin(total))
        if total[i] < best_total:
            best_total = float(total[i])
            best = RansacOutcome(tuple(h[i] for h in hypotheses), costs[i], done)
            required = required_iterations(float(best.inliers.mean()), sample_size, options.confidence)
    if best is None or best.inliers.sum() < sample_size:
        raise CalibrationError("no consistent group of upright people found (RANSAC found no valid hypothesis)")
    return RansacOutcome(best.model, best.costs, done)
