"""The run's TorchRL logger, as ``config.logger`` names it, writing into the run directory.

TorchRL's own loggers (``get_logger``): TensorBoard events in ``RUN/tb`` (the default), CSV files in ``RUN/csv``,
Weights & Biases (files in ``RUN/wandb``; ``WANDB_MODE=offline`` needs no network, ``wandb sync`` uploads later)
and MLflow (an SQLite store, ``RUN/mlflow.db``: ``mlflow ui --backend-store-uri sqlite:///RUN/mlflow.db``; MLflow 3
refuses its old file store unless told to). ``close_logger`` ends a W&B or MLflow run, so that its last figures and
summary are written. A fresh run logs its
config once as hyperparameters (flattened to ``a.b`` keys: every logger takes those); a resumed one goes on
with the scalars.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from torchrl.record.loggers import Logger, TensorboardLogger, get_logger

from rlpipe.pipelines.config import config_to_dict

__all__ = ["close_logger", "run_logger"]


def run_logger(cfg, run_path: Path, fresh: bool) -> Logger:
    """The logger ``cfg.logger`` names for the run in ``run_path``; a ``fresh`` run's config logged as hyperparameters."""
    name = cfg.logger
    if name == "tensorboard":
        logger = TensorboardLogger(exp_name="tb", log_dir=str(run_path))
    elif name == "csv":
        logger = get_logger("csv", str(run_path), "csv")
    elif name == "wandb":
        logger = get_logger("wandb", str(run_path), run_path.name,
                            wandb_kwargs={"project": "rlpipe", "dir": str(run_path), "group": f"{cfg.env}"})
    else:  # mlflow: TorchRL's get_logger would make a file store of the path
        from torchrl.record.loggers.mlflow import MLFlowLogger

        logger = MLFlowLogger(exp_name=run_path.name, tracking_uri=f"sqlite:///{run_path.resolve() / 'mlflow.db'}")
    if fresh and name != "tensorboard":  # TensorBoard's hparams need a metric to pair with: its events stay scalars
        logger.log_hparams(_flat(config_to_dict(cfg)))
    return logger


def close_logger(logger: Logger) -> None:
    """End the logger's run where it has one (W&B's ``finish``, MLflow's ``end_run``): its files complete."""
    kind = type(logger).__name__
    if kind == "WandbLogger":
        logger.experiment.finish()
    elif kind == "MLFlowLogger":
        import mlflow

        mlflow.end_run()


def _flat(config: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"collector.workers": 1, ...}`` with every value a number, a bool or a string (lists and None as JSON)."""
    flat: dict[str, Any] = {}
    for key, value in config.items():
        if isinstance(value, dict) and key != "env_kwargs":
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value if isinstance(value, (int, float, str, bool)) else json.dumps(value)
    return flat
