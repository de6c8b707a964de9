"""The run directory: everything a person wants after a run, in one folder.

    config.json      the resolved config (and which pipeline made it)
    metrics.csv      one row per evaluation/log point
    events.*         TensorBoard events (TorchRL's TensorboardLogger), under tb/
    checkpoints/     what --resume continues from
    policy/          the exported policy (loads with torch alone)
    returns.png      average return against iterations
    summary.json     final figures, wall time, frames, speeds
"""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path
from typing import Any

from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.files import atomic_path, write_json_atomic

__all__ = ["RunDir", "default_run_dir"]

BASE_COLUMNS = ["step", "frames", "updates", "average_return", "average_episode_length"]
SPEED_COLUMNS = ["train_episode_return", "steps_per_s", "updates_per_s", "wall_time"]
# collector workers alive, and the restarts of the collector and the background evaluator (blank for
# a run that has none of them); see supervision.Supervisor
WORKER_COLUMNS = ["workers_alive", "collector_restarts", "evaluator_restarts"]


def default_run_dir(algo: str, env_id: str) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return Path("runs") / f"{algo}-{env_id.replace('/', '_')}-{stamp}"


class RunDir:
    """A run's folder. ``create`` refuses a folder that already holds a run; ``open`` resumes one."""

    def __init__(self, path: Path | str):
        self.path = Path(path)

    # paths
    config_path = property(lambda self: self.path / "config.json")
    metrics_path = property(lambda self: self.path / "metrics.csv")
    summary_path = property(lambda self: self.path / "summary.json")
    checkpoints = property(lambda self: self.path / "checkpoints")
    policy_dir = property(lambda self: self.path / "policy")
    returns_png = property(lambda self: self.path / "returns.png")

    def holds_run(self) -> bool:
        return self.config_path.exists()

    @classmethod
    def create(cls, path: Path | str, algo: str, config: dict) -> RunDir:
        run = cls(path)
        if run.path.exists() and not run.path.is_dir():
            raise InputError(f"--out {run.path}: exists and is not a directory; expected a new or empty directory")
        if run.holds_run():
            raise InputError(
                f"--out {run.path}: already holds a run (config.json); pass --resume {run.path} to continue it, "
                "or choose another --out"
            )
        if run.path.exists() and any(run.path.iterdir()):
            raise InputError(f"--out {run.path}: directory is not empty; expected a new or empty directory")
        run.path.mkdir(parents=True, exist_ok=True)
        run.write_config(algo, config)
        return run

    def write_config(self, algo: str, config: dict) -> None:
        write_json_atomic(self.config_path, {"algo": algo, "config": config})

    @classmethod
    def open(cls, path: Path | str) -> RunDir:
        run = cls(path)
        if not run.holds_run():
            raise InputError(f"{run.path}: not a run directory (no config.json); expected the --out folder of a run")
        return run

    def read_config(self) -> tuple[str, dict]:
        try:
            data = json.loads(self.config_path.read_text())
            return data["algo"], data["config"]
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            raise InputError(f"{self.config_path}: not a valid rlpipe config.json ({exc})") from exc


class MetricsCSV:
    """metrics.csv: one row per evaluation/log point, columns fixed at the run's start.

    TorchRL's CSVLogger writes one file per scalar; a person comparing runs wants one table, so the
    table is written here (TensorBoard gets the same scalars through TorchRL's logger).
    """

    def __init__(self, path: Path, loss_names: list[str], resume_after_step: int | None = None):
        self.path = Path(path)
        self.columns = BASE_COLUMNS + [f"loss_{n}" for n in loss_names] + SPEED_COLUMNS + WORKER_COLUMNS
        if resume_after_step is not None and self.path.exists():
            # Rows past the checkpoint will be produced again by the resumed run.
            with self.path.open(newline="") as fh:
                rows = [r for r in csv.DictReader(fh) if int(r["step"]) <= resume_after_step]
            self._rewrite(rows)
        elif not self.path.exists():
            self._rewrite([])

    def _rewrite(self, rows: list[dict]) -> None:
        with atomic_path(self.path) as tmp, tmp.open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=self.columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)

    def append(self, row: dict[str, Any]) -> None:
        with self.path.open("a", newline="") as fh:
            csv.DictWriter(fh, fieldnames=self.columns, extrasaction="ignore").writerow(
                {k: _fmt(v) for k, v in row.items()}
            )

    def rows(self) -> list[dict[str, str]]:
        with self.path.open(newline="") as fh:
            return list(csv.DictReader(fh))


def _fmt(v: Any) -> Any:
    if isinstance(v, float):
        return f"{v:.6g}"
    return v
