"""Particle weights, the effective sample size and selective, low-variance resampling.

Weights are kept as log sums since the last resampling and normalised as
``exp((log w - max) / (ogain x gainParticles))``: the likelihood of a scan is so peaked that raw weights
would make one particle take everything at the first resampling; the gain smooths that. GMapping scales
the gain by the filter's own particle count, which makes the weights flatter the more particles there are:
Neff then stays high, resampling stops selecting, and wrong lineages survive (orebro at 150 particles:
5.1, 0.19 and 3.0 m over three seeds, against 0.048, 0.041 and 0.045 m with the gain of 50). carto scales
it by a fixed count, so that more particles sample the same posterior more densely (docs/gmapping.md).

Resampling happens only when the effective sample size Neff = 1 / sum(w^2) falls below a threshold
(GMapping's selective resampling). With ``adaptive`` the threshold follows the seeds' rule
``resampleThreshold x particles / (1 + 2 H)``, H the map's entropy: when the map is uncertain
(cluttered, much half-seen) the weights carry less information, and resampling on them would throw
away hypotheses that are still as good as the others.
"""
from __future__ import annotations

import numpy as np


def normalized(log_weights: np.ndarray, ogain: float, gain_particles: int = 0) -> np.ndarray:
    """Normalised weights from log weights, smoothed by ``ogain`` x ``gain_particles`` (0: the number of
    particles, as GMapping does)."""
    lw = np.asarray(log_weights, dtype=np.float64)
    w = np.exp((lw - lw.max()) / (ogain * (gain_particles or lw.shape[0])))
    return w / w.sum()


def neff(weights: np.ndarray) -> float:
    """Effective sample size of normalised weights: the number of particles when they are equal, 1 when one
    particle has all the weight."""
    w = np.asarray(weights, dtype=np.float64)
    return float(1.0 / np.sum(w * w))


def threshold(particles: int, resample_threshold: float, entropy: float | None = None) -> float:
    """Neff below which to resample: ``resample_threshold x particles``, divided by ``1 + 2 entropy`` when the
    map's entropy (bits per known cell, 0..1) is given."""
    base = resample_threshold * particles
    return base if entropy is None else base / (1.0 + 2.0 * entropy)


def low_variance(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Indices of the particles kept (with repetition): one uniform draw, then evenly spaced pointers into
    the cumulative weights, so a particle of weight w is copied floor(N w) or ceil(N w) times."""
    w = np.asarray(weights, dtype=np.float64)
    n = w.shape[0]
    cumulative = np.cumsum(w)
    cumulative[-1] = 1.0  # no pointer may fall past the end through rounding
    pointers = (rng.uniform(0.0, 1.0) + np.arange(n)) / n
    return np.searchsorted(cumulative, pointers, side="right").astype(np.int64)
