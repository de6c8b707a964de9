"""`rlpipe tune` with its trials on a two-node Ray cluster (tests/conftest.py's ``ray_cluster``): one seed's run on
each node. Apart from test_tune.py so that it runs with the Ray files (conftest's RAY_FILES), one Ray at a time."""

from __future__ import annotations

import pytest

pytest.importorskip("optuna", reason="Optuna is not installed: `pip install -e '.[tune]'` (scripts/setup.sh does)")
pytest.importorskip("ray", reason="Ray is not installed: `pip install -e '.[ray]'` (scripts/setup.sh does)")

from test_tune import TINY, load, tune  # noqa: E402


@pytest.mark.slow
def test_trials_run_on_a_ray_cluster_one_seed_per_node(tmp_path, ray_cluster):
    out = tmp_path / "study"
    done = tune(["tune", "dqn", "env=CartPole-v1", "--target", "8", "--budget", "10m", "--trials", "1",
                 "--cap", "90", "--confirm-seeds", "0", f"ray.address={ray_cluster.address}", *TINY, "--out", str(out)],
                tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    (trial,) = load(out).trials
    assert trial.state.name == "COMPLETE" and len(trial.user_attrs["seconds"]) == 2
    nodes = trial.user_attrs["nodes"]
    assert None not in nodes and len(set(nodes)) == 2  # each seed's run on a node of its own
    assert (out / "dqn-cartpole-v1-tuned.yaml").exists()
