"""Statistics across envs, as the field reports them (Agarwal et al. 2021, "Deep RL at the Edge of
the Statistical Precipice", the ``rliable`` library): scores normalised per env, the interquartile
mean (IQM) over every run of every env with a stratified-bootstrap 95% confidence interval,
performance profiles, and the probability of improvement of one variant over another.

Why not ``rliable`` itself: ``pip install rliable`` (1.2.0) pulls ``arch`` 7.2, which fails to
import under our pandas 3.1 (``deprecate_kwarg() missing 1 required positional argument``), and
rliable imports ``arch`` at module level; rliable 1.2 also caps ``arch<8``. The estimators are
short, so they are written here with NumPy/SciPy, following rliable's definitions:

* scores are an array ``(runs, envs)`` per variant (the runs of one env are its seeds);
* a stratified bootstrap resamples the runs of each env separately (with replacement), so every
  resample keeps every env, and the interval is the percentile one;
* IQM = :func:`scipy.stats.trim_mean` (25% cut from each end) of all ``runs x envs`` scores;
* the performance profile at ``tau`` is the fraction of runs scoring above ``tau``, averaged over envs;
* the probability of improvement P(X > Y) is, per env, the Mann-Whitney U statistic over
  ``n * m`` (a tie counts half), averaged over envs.

Every bootstrap has a fixed seed, so the same runs always give the same intervals.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
import pandas as pd

__all__ = [
    "AGG_RESAMPLES",
    "normalise_scores",
    "score_matrices",
    "iqm",
    "stratified_bootstrap_ci",
    "aggregate_iqm",
    "performance_profile",
    "probability_of_improvement",
    "compare_to_reference",
]

AGG_RESAMPLES = 2000  # rliable's figures use 2,000 (IQM) and 1,000 (profiles, P(improvement))
CONFIDENCE = 0.95
SEED = 0


def normalise_scores(final: np.ndarray | float, random: float, reference: float) -> np.ndarray:
    """``(final - random) / (reference - random)``: the random agent scores 0, ``reference`` 1.

    NaN where ``reference`` equals ``random`` (no scale to measure by).
    """
    span = reference - random
    if not np.isfinite(span) or span == 0:
        return np.full(np.shape(final), np.nan)
    return (np.asarray(final, dtype=float) - random) / span


def score_matrices(records: pd.DataFrame, random_scores: Mapping[str, float], reference: str = "full",
                   ) -> tuple[dict[str, np.ndarray], list[str]]:
    """Per variant, its normalised final returns as an array ``(runs, envs)``.

    ``records`` has ``env``, ``variant``, ``seed``, ``final_return``; an env's scale runs from
    ``random_scores[env]`` (0) to the mean final return of ``reference`` there (1). Envs lacking a
    random score or the reference are left out; a variant with fewer runs on an env than the
    most it has anywhere is padded with NaN (dropped by the estimators). Returns the matrices and
    the envs (column order).
    """
    envs = [e for e in sorted(records["env"].astype(str).unique())
            if e in random_scores and ((records["env"] == e) & (records["variant"] == reference)).any()]
    out: dict[str, np.ndarray] = {}
    for variant, group in records.groupby("variant", sort=True):
        columns = []
        for env in envs:
            ref = records.loc[(records["env"] == env) & (records["variant"] == reference), "final_return"].mean()
            finals = group.loc[group["env"] == env].sort_values("seed")["final_return"].to_numpy(dtype=float)
            columns.append(normalise_scores(finals, random_scores[env], ref))
        if not columns:
            continue
        rows = max(len(c) for c in columns)
        out[str(variant)] = np.stack([np.pad(c, (0, rows - len(c)), constant_values=np.nan) for c in columns], axis=1)
    return out, envs


def iqm(scores: np.ndarray) -> float:
    """Interquartile mean of every finite score (all runs of all envs pooled, as rliable's
    ``aggregate_iqm``); NaN when none is finite."""
    return float(_iqm_batch(np.asarray(scores, dtype=float)[None])[0])


def _iqm_batch(draws: np.ndarray) -> np.ndarray:
    """``iqm`` of each of ``draws`` ``(reps, runs, envs)``, whose NaNs lie in the same places in each (a stratified
    resample keeps each env's count of finite runs)."""
    from scipy import stats

    finite = np.isfinite(draws[0])
    if not finite.any():
        return np.full(len(draws), np.nan)
    return stats.trim_mean(draws[:, finite], 0.25, axis=1)


def _resamples(scores: np.ndarray, rng: np.random.Generator, reps: int) -> np.ndarray:
    """``reps`` stratified resamples at once, ``(reps, runs, envs)``: the runs of each env (column) drawn with
    replacement among that env's finite runs, NaN below them."""
    columns = [scores[:, j][np.isfinite(scores[:, j])] for j in range(scores.shape[1])]
    rows = max((c.size for c in columns), default=0)
    out = np.full((reps, rows, len(columns)), np.nan)
    for j, col in enumerate(columns):
        if col.size:
            out[:, :col.size, j] = col[rng.integers(0, col.size, (reps, col.size))]
    return out


def stratified_bootstrap_ci(scores: np.ndarray | tuple[np.ndarray, ...], statistic: Callable[..., float | np.ndarray],
                            reps: int = AGG_RESAMPLES, confidence: float = CONFIDENCE, seed: int = SEED, *,
                            batched: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``statistic`` of ``scores`` with its stratified-bootstrap percentile interval.

    ``scores``: one ``(runs, envs)`` array, or a tuple of them (each resampled on its own, as for
    P(X > Y)); ``statistic`` takes as many arrays and returns a number or an array; with ``batched``, it takes
    them with a leading axis of resamples, ``(reps, runs, envs)``, and returns one result per resample (the point
    estimate is then its result on a batch of one).
    Returns ``(point, low, high)`` as arrays (0-d for a number).
    """
    arrays = scores if isinstance(scores, tuple) else (scores,)
    arrays = tuple(np.asarray(a, dtype=float) for a in arrays)
    rng = np.random.default_rng(seed)
    resamples = [_resamples(a, rng, reps) for a in arrays]
    if batched:
        point = np.asarray(statistic(*(a[None] for a in arrays)), dtype=float)[0]
        draws = np.asarray(statistic(*resamples), dtype=float)
    else:
        point = np.asarray(statistic(*arrays), dtype=float)
        draws = np.stack([np.asarray(statistic(*(r[i] for r in resamples)), dtype=float) for i in range(reps)])
    tail = (1 - confidence) / 2 * 100
    low, high = np.nanpercentile(draws, [tail, 100 - tail], axis=0)
    return point, low, high


def aggregate_iqm(matrices: Mapping[str, np.ndarray], reps: int = AGG_RESAMPLES) -> pd.DataFrame:
    """Per variant: ``iqm`` of its normalised scores, ``ci_low``/``ci_high`` (stratified bootstrap,
    95%) and ``n`` (finite scores), best first."""
    rows = []
    for variant, scores in matrices.items():
        point, low, high = stratified_bootstrap_ci(scores, _iqm_batch, reps, batched=True)
        rows.append({"variant": variant, "n": int(np.isfinite(scores).sum()), "iqm": float(point),
                     "ci_low": float(low), "ci_high": float(high)})
    out = pd.DataFrame(rows, columns=["variant", "n", "iqm", "ci_low", "ci_high"])
    return out.sort_values(["iqm", "variant"], ascending=[False, True], na_position="last").reset_index(drop=True)


def _profile_batch(draws: np.ndarray, taus: np.ndarray) -> np.ndarray:
    """The fraction of each env's finite runs above each of ``taus``, averaged over envs: ``(reps, taus)``."""
    fractions = []
    for j in range(draws.shape[2]):
        finite = np.isfinite(draws[0, :, j])
        if finite.any():
            fractions.append((draws[:, finite, j][:, None, :] > taus[None, :, None]).mean(axis=2))
    return np.mean(fractions, axis=0) if fractions else np.full((len(draws), taus.size), np.nan)


def performance_profile(scores: np.ndarray, taus: np.ndarray, reps: int = 1000,
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fraction of runs with a normalised score above each ``tau`` (averaged over envs), with its
    stratified-bootstrap 95% band: ``(profile, low, high)``, each of ``taus``' shape."""
    taus = np.asarray(taus, dtype=float)
    return stratified_bootstrap_ci(scores, lambda s: _profile_batch(s, taus), reps, batched=True)


def _p_improvement_batch(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) of each resample pair ``(reps, runs, envs)``: per env the Mann-Whitney U over ``n m`` (a tie counts
    half), averaged over the envs both have finite runs on."""
    per_env = []
    for j in range(x.shape[2]):
        a, b = x[:, np.isfinite(x[0, :, j]), j], y[:, np.isfinite(y[0, :, j]), j]
        if a.shape[1] and b.shape[1]:
            wins = (a[:, :, None] > b[:, None, :]).sum((1, 2)) + 0.5 * (a[:, :, None] == b[:, None, :]).sum((1, 2))
            per_env.append(wins / (a.shape[1] * b.shape[1]))
    return np.mean(per_env, axis=0) if per_env else np.full(len(x), np.nan)


def probability_of_improvement(x: np.ndarray, y: np.ndarray, reps: int = 1000) -> tuple[float, float, float]:
    """P(X > Y): the probability that a run of X scores above a run of Y on an env, averaged over
    envs, with the 95% stratified-bootstrap interval (X and Y resampled independently):
    ``(p, low, high)``. Works on raw or normalised scores alike (it only compares within an env)."""
    point, low, high = stratified_bootstrap_ci((np.asarray(x, float), np.asarray(y, float)), _p_improvement_batch,
                                               reps, batched=True)
    return float(point), float(low), float(high)


def compare_to_reference(matrices: Mapping[str, np.ndarray], reference: str = "full", reps: int = 1000,
                         ) -> pd.DataFrame:
    """P(reference > variant) with its interval for every other variant: columns ``variant``,
    ``p``, ``ci_low``, ``ci_high``, the largest ``p`` first."""
    rows = []
    if reference in matrices:
        for variant, scores in matrices.items():
            if variant != reference:
                p, low, high = probability_of_improvement(matrices[reference], scores, reps)
                rows.append({"variant": variant, "p": p, "ci_low": low, "ci_high": high})
    out = pd.DataFrame(rows, columns=["variant", "p", "ci_low", "ci_high"])
    return out.sort_values(["p", "variant"], ascending=[False, True]).reset_index(drop=True)
