"""The across-env statistics of the ablation study (rliable's estimators, written with NumPy/SciPy)
on inputs whose answers are known by hand."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from rlpipe.pipelines.analysis import aggregate as agg
from rlpipe.pipelines.analysis.study import ingredient_sentences, study_statistics

pytestmark = pytest.mark.unit


def test_iqm_of_a_known_array():
    # 8 scores sorted 0 1 2 3 4 5 6 100: the middle half 2 3 4 5 -> 3.5 (the outlier 100 is cut).
    assert agg.iqm(np.array([[0.0, 1.0], [2.0, 3.0], [4.0, 5.0], [6.0, 100.0]])) == pytest.approx(3.5)
    assert agg.iqm(np.array([[1.0, np.nan], [3.0, 5.0], [np.nan, 7.0]])) == pytest.approx(4.0)  # NaN dropped


def test_normalised_scores_put_random_at_0_and_the_full_agent_at_1():
    assert agg.normalise_scores(np.array([-1200.0, -150.0, -675.0]), -1200.0, -150.0) == pytest.approx([0, 1, 0.5])
    assert np.isnan(agg.normalise_scores(3.0, 1.0, 1.0))


def test_stratified_bootstrap_ci_contains_the_point_estimate_and_keeps_every_env():
    rng = np.random.default_rng(3)
    scores = np.stack([rng.normal(0.2, 0.1, 5), rng.normal(0.9, 0.1, 5)], axis=1)  # (5 seeds, 2 envs)
    point, low, high = agg.stratified_bootstrap_ci(scores, agg.iqm, reps=500)
    assert low < point < high
    # Every resample draws each env's runs from that env alone: the per-env means stay apart.
    _, low_env, high_env = agg.stratified_bootstrap_ci(scores, lambda s: np.nanmean(s, axis=0), reps=500)
    assert high_env[0] < low_env[1]
    # The same inputs give the same interval (fixed seed).
    assert agg.stratified_bootstrap_ci(scores, agg.iqm, reps=500)[1] == low


def test_probability_of_improvement_of_a_dominating_variant_is_one():
    better = np.array([[5.0, 50.0], [6.0, 60.0], [7.0, 70.0]])
    worse = better - 100.0  # every run of it below every run of better, on both envs
    assert agg.probability_of_improvement(better, worse) == (1.0, 1.0, 1.0)
    assert agg.probability_of_improvement(worse, better) == (0.0, 0.0, 0.0)
    p, low, high = agg.probability_of_improvement(better, better)  # all ties count half
    assert p == pytest.approx(0.5) and low <= 0.5 <= high


def test_performance_profile_counts_runs_above_tau_per_env():
    scores = np.array([[0.0, 1.0], [0.5, 1.0], [1.0, 1.0], [1.5, 1.0]])
    profile, low, high = agg.performance_profile(scores, np.array([-1.0, 0.25, 0.75, 2.0]), reps=200)
    # env 0: 4, 3, 2, 0 of 4 runs above; env 1: 4, 4, 4, 0 -> averaged
    assert profile == pytest.approx([1.0, 0.875, 0.75, 0.0])
    assert np.all(low <= profile + 1e-12) and np.all(profile <= high + 1e-12)


def test_sentences_say_where_intervals_overlap():
    rows = []
    for env, (rand, full) in {"A-v0": (0.0, 100.0), "B-v0": (-10.0, 10.0)}.items():
        for seed in range(5):
            rows += [{"env": env, "variant": "full", "seed": seed, "final_return": full + seed},
                     # far below on A, the same as the full agent on B
                     {"env": env, "variant": "no_clipped_double_q", "seed": seed,
                      "final_return": (rand + seed) if env == "A-v0" else full + seed}]
    records = pd.DataFrame(rows).assign(auc=0.0)
    st = study_statistics(records, {"A-v0": 0.0, "B-v0": -10.0})
    assert st.envs == ["A-v0", "B-v0"]
    assert st.improvement.loc[0, "p"] == pytest.approx(0.75)  # 1 on A, 0.5 on B
    sentence = ingredient_sentences(st)["no_clipped_double_q"]
    assert "lower than the full agent, intervals apart, on A-v0" in sentence
    assert "overlaps the full agent's on B-v0" in sentence
    assert "P(full > no_clipped_double_q) = 0.75" in sentence
