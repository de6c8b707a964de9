"""The rlpipe runs the benchmarks time: a preset trained once per seed, and when it first reached a return."""

from __future__ import annotations

import json
import sys
from pathlib import Path


def train_seeds(preset: str, overrides: list[str], seeds: int, out: Path) -> list[dict]:
    from rlpipe.pipelines import pipeline_class, resolve_preset
    from rlpipe.pipelines.config import apply_overrides

    results = []
    for seed in range(seeds):
        algo, cfg = resolve_preset(preset)
        cfg = apply_overrides(cfg, [*overrides, f"seed={seed}"])
        result = pipeline_class(algo)(cfg).train(out / f"{preset}-seed{seed}", progress=False)
        results.append(result)
        print(f"  seed {seed}: {json.dumps(result.summary)}", file=sys.stderr)
    return results


def first_reaching(evaluations: list[dict], threshold: float, key: str = "step") -> int | None:
    for e in evaluations:
        if e["average_return"] >= threshold:
            return e[key]
    return None
