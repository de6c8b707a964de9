"""Tests of rlpipe.pipelines.analysis on real run directories written in tmp_path."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pandas as pd
import pytest

from rlpipe.pipelines import analysis as A

VARIANTS = [
    "full",
    "no_deterministic_policy",
    "no_experience_replay",
    "no_target_networks",
    "no_target_policy_smoothing",
    "no_delayed_policy_updates",
    "no_clipped_double_q",
]
HEADER = [
    "step", "frames", "average_return", "average_episode_length", "loss_actor", "loss_qvalue",
    "steps_per_s", "updates_per_s", "wall_time",
]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def write_run(root: Path, name: str, env: str, seed: int, evals, variant: str | None = None,
              log_every: int = 0) -> Path:
    """A run directory with metrics.csv (eval rows + log-only rows), summary.json, config.json.

    ``evals`` is a list of (step, average_return); with ``log_every`` a log-only row (empty
    return columns) follows each evaluation.
    """
    run = root / name
    run.mkdir(parents=True)
    with open(run / "metrics.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(HEADER)
        for i, (step, ret) in enumerate(evals):
            w.writerow([step, step * 10, ret, 200, 0.5, 1.5, 900.0, 100.0, i * 2.0])
            if log_every:
                w.writerow([step + log_every, (step + log_every) * 10, "", "", 0.4, 1.2, 910.0,
                            101.0, i * 2.0 + 1.0])
    summary = {"algo": "td3", "env": env, "seed": seed,
               "final_average_return": evals[-1][1] if evals else None,
               "frames": evals[-1][0] * 10 if evals else 0, "wall_time_s": 12.0}
    if variant is not None:
        summary["variant"] = variant
    (run / "summary.json").write_text(json.dumps(summary))
    (run / "config.json").write_text(json.dumps({"env": env, "seed": seed}))
    return run


def check_png(path: Path, min_bytes: int = 5000) -> None:
    assert path.is_file(), path
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, path
    assert len(data) > min_bytes, (path, len(data))


@pytest.fixture
def ablation_runs(tmp_path):
    """2 envs (one with a slash) x 7 variants x 3 seeds; seeds evaluate at offset steps; the
    'no_clipped_double_q' variant on Pendulum has one seed only."""
    rng = np.random.default_rng(1)
    dirs = []
    for env in ["Pendulum-v1", "rlpipe/MinitaurBullet-v0"]:
        for vi, variant in enumerate(VARIANTS):
            seeds = [0] if (env == "Pendulum-v1" and variant == "no_clipped_double_q") else [0, 1, 2]
            for seed in seeds:
                steps = np.arange(0, 5001, 500) + seed  # slightly different steps per seed
                rets = -1500 + (1400 - 150 * vi) * (1 - np.exp(-steps / 1500))
                rets = rets + rng.normal(0, 40, steps.size)
                name = f"td3_{A.safe_filename(env)}_{variant}_s{seed}"
                dirs.append(write_run(tmp_path / "runs", name, env, seed,
                                      list(zip(steps.tolist(), rets.tolist())),
                                      variant=variant, log_every=100))
    return dirs


# ------------------------------------------------------------------ reading


def test_read_metrics_eval_rows_and_errors(tmp_path):
    run = write_run(tmp_path, "r", "Pendulum-v1", 0, [(0, -1200.0), (10, -800.0)], log_every=5)
    all_rows = A.read_metrics(run, eval_only=False)
    assert len(all_rows) == 4 and all_rows["average_return"].isna().sum() == 2
    ev = A.read_metrics(run)
    assert ev["step"].tolist() == [0, 10] and ev["average_return"].tolist() == [-1200.0, -800.0]
    assert A.read_metrics(run / "metrics.csv")["step"].tolist() == [0, 10]

    with pytest.raises(ValueError, match="metrics.csv"):
        A.read_metrics(tmp_path / "nowhere")
    no_eval = tmp_path / "no_eval"
    no_eval.mkdir()
    with open(no_eval / "metrics.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(HEADER)
        w.writerow([5, 50, "", "", 0.4, 1.2, 910.0, 101.0, 1.0])
    with pytest.raises(ValueError, match="no evaluation rows") as err:
        A.read_metrics(no_eval)
    assert str(no_eval) in str(err.value)


# ------------------------------------------------------------------ statistics


def test_area_under_curve_known_curves():
    assert A.area_under_curve([0, 10], [0, 10]) == pytest.approx(5.0)  # line: mean = 5
    assert A.area_under_curve([0, 5, 10], [3, 3, 3]) == pytest.approx(3.0)  # constant
    # step 0..2..10: area = 2*(0+4)/2 + 8*(4+4)/2 = 36 -> 3.6
    assert A.area_under_curve([0, 2, 10], [0, 4, 4]) == pytest.approx(3.6)
    assert A.area_under_curve([10, 0], [10, 0]) == pytest.approx(5.0)  # unsorted input
    assert A.area_under_curve([7], [-42.0]) == -42.0  # single point
    assert A.area_under_curve([100, 200], [1.0, float("nan")]) == 1.0  # NaN dropped
    assert math.isnan(A.area_under_curve([], []))
    x = np.linspace(0, 1000, 101)  # y = x^2 over [0, 1000] -> mean 1000^2 / 3
    assert A.area_under_curve(x, x**2) == pytest.approx(1000**2 / 3, rel=1e-3)


def _records():
    rows = []
    for seed, (a, b) in enumerate([(10.0, 3.0), (12.0, 1.0), (8.0, 2.5), (11.0, 2.0), (9.5, 4.0)]):
        rows.append(dict(env="E", variant="full", seed=seed, final_return=a, auc=a / 2))
        rows.append(dict(env="E", variant="no_target_networks", seed=seed, final_return=b, auc=b))
    rows.append(dict(env="E", variant="no_clipped_double_q", seed=0, final_return=5.0, auc=1.0))
    return pd.DataFrame(rows)


def test_summarise_runs_ci_contains_mean_and_is_reproducible():
    s1 = A.summarise_runs(_records())
    s2 = A.summarise_runs(_records())
    pd.testing.assert_frame_equal(s1, s2)
    assert {"env", "variant", "n", "mean", "ci_low", "ci_high", "iqm", "auc_mean"} <= set(s1)
    assert s1["variant"].tolist() == ["full", "no_clipped_double_q", "no_target_networks"]
    full = s1.set_index("variant").loc["full"]
    assert full["n"] == 5 and full["mean"] == pytest.approx(10.1)
    assert full["ci_low"] < full["mean"] < full["ci_high"]
    assert 8.0 <= full["ci_low"] and full["ci_high"] <= 12.0
    assert full["iqm"] == pytest.approx(np.mean([9.5, 10.0, 11.0]))  # trims 8 and 12
    assert full["auc_mean"] == pytest.approx(10.1 / 2)


def test_summarise_runs_single_seed():
    one = A.summarise_runs(_records()).set_index("variant").loc["no_clipped_double_q"]
    assert one["n"] == 1 and one["mean"] == 5.0 and one["iqm"] == 5.0
    assert one["ci_low"] == one["ci_high"] == 5.0
    assert A.bootstrap_ci([3.0]) == (3.0, 3.0)
    assert all(math.isnan(v) for v in A.bootstrap_ci([]))


def test_aggregate_curves_aligns_offset_steps():
    curves = {
        ("E", "full", 0): ([0, 10, 20], [0.0, 10.0, 20.0]),
        ("E", "full", 1): ([1, 11, 21], [1.0, 11.0, 21.0]),  # same line y = x, offset steps
        ("E", "solo", 0): pd.DataFrame({"step": [0, 5], "average_return": [1.0, 2.0]}),
    }
    agg = A.aggregate_curves(curves)
    full = agg[agg["variant"] == "full"]
    assert full["step"].tolist() == [1, 10, 11, 20]  # union of steps inside the common range
    np.testing.assert_allclose(full["mean"], full["step"])  # interpolation keeps y = x
    assert (full["n"] == 2).all()
    solo = agg[agg["variant"] == "solo"]
    assert solo["ci_low"].tolist() == solo["mean"].tolist() == [1.0, 2.0]


# ------------------------------------------------------------------ ablation report


def test_collect_runs_and_ablation_report(ablation_runs, tmp_path):
    records, curves = A.collect_runs(ablation_runs)
    assert len(records) == 2 * 7 * 3 - 2
    assert set(records["variant"]) == set(VARIANTS)
    row = records[(records["env"] == "Pendulum-v1") & (records["variant"] == "full")
                  & (records["seed"] == 1)].iloc[0]
    metrics = A.read_metrics(row["run_dir"])
    assert row["final_return"] == metrics["average_return"].iloc[-1]
    assert set(curves.columns) >= set(A.CURVE_COLUMNS)
    assert curves["average_return"].notna().all()  # log-only rows are not in the curves

    out = tmp_path / "report" / "nested"
    paths = A.write_ablation_report(records, curves, out)
    names = sorted(p.name for p in paths)
    assert names == sorted(["ablation.csv", "ablation.md", "curves_Pendulum-v1.png",
                            "curves_rlpipe_MinitaurBullet-v0.png", "ecdf_final_returns.png", "report.html"])
    assert all(p.parent == out and p.is_file() for p in paths)
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temp files left

    table = pd.read_csv(out / "ablation.csv")
    assert list(table.columns) == ["env", "variant", "seed", "final_return", "auc"]
    assert len(table) == len(records)

    md = (out / "ablation.md").read_text()
    for variant in VARIANTS:
        assert variant in md
    assert "**full** ★" in md
    assert "## Pendulum-v1" in md and "## rlpipe/MinitaurBullet-v0" in md
    assert "bootstrap" in md and "interquartile mean" in md.lower()
    # within each env the table rows are sorted by mean, best first
    summary = A.summarise_runs(records)
    for env, s in summary.groupby("env"):
        assert s["mean"].is_monotonic_decreasing
        pos = [md.index(f"| `{v}`" if v != "full" else "| **full**", md.index(f"## {env}"))
               for v in s["variant"]]
        assert pos == sorted(pos)

    for p in paths:
        if p.suffix == ".png":
            check_png(p, 10_000)
    # the same study as one page: a table per env, every variant, the full agent marked, figures inline
    page = (out / "report.html").read_text()
    for variant in VARIANTS:
        assert f">{variant}" in page
    assert page.count("★") >= 2 and page.count('<table class="variants"') == 2
    assert page.count('src="data:image/svg+xml;base64,') == 2 + 1 + 1  # curves per env, ECDFs, every run
    assert "http://" not in page and "https://" not in page  # opens offline
    img = mpimg.imread(out / "curves_rlpipe_MinitaurBullet-v0.png")
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 300
    assert img[..., :3].std() > 0.05  # not a blank image


def test_ablation_report_single_run_per_variant(tmp_path):
    records = pd.DataFrame([dict(env="a/b", variant=v, seed=0, final_return=float(i), auc=0.5)
                            for i, v in enumerate(["full", "no_target_networks"])])
    curves = pd.DataFrame([dict(env="a/b", variant=v, seed=0, step=0, average_return=-1.0)
                           for v in ["full", "no_target_networks"]])
    paths = A.write_ablation_report(records, curves, tmp_path / "one")
    assert (tmp_path / "one" / "curves_a_b.png") in paths
    for p in paths:
        assert p.is_file()
    assert "**full** ★" in (tmp_path / "one" / "ablation.md").read_text()


# ------------------------------------------------------------------ single-run plots


def test_plot_return_curves_two_runs(tmp_path):
    r1 = write_run(tmp_path, "td3_seed0", "rlpipe/MinitaurBullet-v0", 0,
                   [(0, -5.0), (100, 1.0), (200, 4.0)], log_every=50)
    r2 = write_run(tmp_path, "td3_seed1", "rlpipe/MinitaurBullet-v0", 1,
                   [(0, -4.0), (100, 2.0), (200, 3.5)])
    out = A.plot_return_curves([r1, r2], tmp_path / "plots" / "cmp.png")
    assert out == tmp_path / "plots" / "cmp.png"
    check_png(out)
    assert mpimg.imread(out).shape[-1] in (3, 4)
    out2 = A.plot_return_curves([r1, r2], tmp_path / "cmp2.png", labels=["a", "b"], x="frames")
    check_png(out2)
    with pytest.raises(ValueError):
        A.plot_return_curves([r1], tmp_path / "x.png", labels=["a", "b"])
    with pytest.raises(ValueError, match="metrics.csv"):
        A.plot_return_curves([tmp_path / "missing"], tmp_path / "x.png")


def test_plot_gives_each_env_its_own_axis_and_says_so(tmp_path, capsys):
    """`rlpipe plot` once drew CartPole's and Minitaur's returns on one axis without a word."""
    from rlpipe.pipelines.analysis.plots import return_curves_figure
    from rlpipe.scripts.cli import main

    cart = [write_run(tmp_path, f"dqn_seed{i}", "CartPole-v0", i, [(0, 10.0), (100, 150.0 + i)]) for i in (0, 1)]
    minitaur = write_run(tmp_path, "sac_seed0", "rlpipe/MinitaurBullet-v0", 0, [(0, 0.1), (100, 0.4)])
    fig = return_curves_figure([cart[0], minitaur, cart[1]])
    axes = {ax.get_title(): sorted(line.get_label() for line in ax.get_lines()) for ax in fig.axes}
    assert axes == {"CartPole-v0": ["dqn_seed0", "dqn_seed1"], "rlpipe/MinitaurBullet-v0": ["sac_seed0"]}
    assert [ax.get_title() for ax in return_curves_figure(cart).axes] == ["CartPole-v0"]
    assert main(["plot", str(cart[0]), str(minitaur), "--out", str(tmp_path / "both.png")]) == 0
    out = capsys.readouterr().out
    assert "one axis per env: CartPole-v0, rlpipe/MinitaurBullet-v0" in out
    check_png(tmp_path / "both.png")


def test_plot_ecdf(tmp_path):
    returns = np.random.default_rng(0).normal(-200, 50, size=50)
    out = A.plot_ecdf(returns, tmp_path / "eval" / "ecdf.png", title="TD3 on Pendulum-v1")
    check_png(out)
    assert mpimg.imread(out).ndim == 3
    check_png(A.plot_ecdf([3.0], tmp_path / "one.png"), 2000)  # a single episode
    with pytest.raises(ValueError):
        A.plot_ecdf([], tmp_path / "none.png")


def test_plot_training_returns_robust_and_repeatable(tmp_path):
    out = tmp_path / "run" / "returns.png"
    rows = [{"step": 0, "average_return": -900.0}, {"step": 5, "average_return": ""}]
    assert A.plot_training_returns(rows, out, "TD3 on Pendulum-v1") == out  # one point
    check_png(out, 2000)
    assert A.plot_training_returns([], out, "empty").is_file()  # no evaluation yet
    run = write_run(tmp_path, "r", "Pendulum-v1", 0, [(0, -900.0), (10, -500.0)], log_every=5)
    for _ in range(3):  # overwritten in place, never leaves temp files
        A.plot_training_returns(A.read_metrics(run, eval_only=False), out, "TD3")
        A.plot_training_returns(run, out, "TD3")
    check_png(out, 2000)
    assert [p.name for p in out.parent.iterdir()] == ["returns.png"]


def test_safe_filename():
    assert A.safe_filename("rlpipe/MinitaurBullet-v0") == "rlpipe_MinitaurBullet-v0"
    assert A.safe_filename("../x y") == "x_y"
    assert "/" not in A.safe_filename("a/b/c")


def test_read_run_info_of_a_run_in_progress_reads_its_config(tmp_path):
    # a run writes config.json as {"algo", "config"}; summary.json comes only at its end
    (tmp_path / "config.json").write_text(json.dumps({"algo": "dqn", "config": {"env": "CartPole-v1", "seed": 4}}))
    assert A.read_run_info(tmp_path) == {"algo": "dqn", "env": "CartPole-v1", "seed": 4}
    (tmp_path / "summary.json").write_text(json.dumps({"env": "CartPole-v1", "final_average_return": 9.5}))
    assert A.read_run_info(tmp_path)["final_average_return"] == 9.5
