"""Loggers chosen on the command line (``logger=``): TorchRL's, for real: W&B offline, an MLflow SQLite store, CSV."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.mark.parametrize("logger", [pytest.param("wandb", marks=pytest.mark.slow),
                                    pytest.param("mlflow", marks=pytest.mark.slow), "csv"])
def test_a_logger_chosen_on_the_command_line_gets_the_metrics_and_the_config(logger, tmp_path):
    """logger=wandb|mlflow|csv: TorchRL's logger of that name, for real (W&B offline, an MLflow file store),
    gets the evaluations' returns and, once, the run's config as hyperparameters."""
    env = {**os.environ, "WANDB_MODE": "offline", "WANDB_SILENT": "true"}
    run = tmp_path / "run"
    # a process of its own, as a user runs it: the W&B client's service writes its log by the process's end
    done = subprocess.run([sys.executable, "-m", "rlpipe.scripts.cli", "train", "sac-pendulum", f"logger={logger}",
                           "num_iterations=300", "eval_interval=300", "num_eval_episodes=1", "target_return=null",
                           "--no-progress", "--out", str(run)], env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    if logger == "mlflow":
        import mlflow

        client = mlflow.MlflowClient(tracking_uri=f"sqlite:///{run.resolve() / 'mlflow.db'}")
        (logged,) = client.search_runs([client.get_experiment_by_name(run.name).experiment_id])
        assert "average_return" in logged.data.metrics and logged.data.params["actor_learning_rate"] == "0.002"
    elif logger == "wandb":
        (records,) = (run / "wandb").glob("offline-run-*/run-*.wandb")  # the client's log, what `wandb sync` uploads
        data = records.read_bytes()
        assert b"average_return" in data and b"actor_learning_rate" in data
    else:
        logged = {p.name for p in (run / "csv").rglob("*.csv")}
        assert "average_return.csv" in logged, logged
