"""Loggers chosen on the command line (``logger=``): TorchRL's, for real: W&B offline, an MLflow SQLite store, CSV."""

from __future__ import annotations

import pytest

from rlpipe.scripts.cli import main

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


@pytest.mark.parametrize("logger", ["wandb", "mlflow", "csv"])
def test_a_logger_chosen_on_the_command_line_gets_the_metrics_and_the_config(logger, tmp_path, monkeypatch, capsys):
    """logger=wandb|mlflow|csv: TorchRL's logger of that name, for real (W&B offline, an MLflow file store),
    gets the evaluations' returns and, once, the run's config as hyperparameters."""
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    run = tmp_path / "run"
    code = main(["train", "sac-pendulum", f"logger={logger}", "num_iterations=300", "eval_interval=300",
                 "num_eval_episodes=1", "target_return=null", "--no-progress", "--out", str(run)])
    assert code == 0, capsys.readouterr().err
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
