"""The benchmark pages, made from the committed result JSON under ``benchmarks/results/``.

    python benchmarks/pages.py      # from the repository's root (with rlpipe's venv: matplotlib draws the plots)

writes ``docs/benchmarks/index.md`` (one table per question, each with its plot), the plots beside it
(``docs/benchmarks/*.png``), and the summary table at the top of ``BENCHMARKS.md`` (between its
``summary`` markers). ``tests/test_bench_pages.py`` checks that the committed pages are what this makes
from the committed JSON, so a figure on the site is always one a command wrote down.

Which JSON answers which question is chosen below (``TIME_TO_TARGET``, ``UPDATES``, ``COLLECTION``,
``GPU``, ``ANYTIME``): for each task and peer, the newest command that timed that pair; the older ones stay in
BENCHMARKS.md's log. A figure is never typed here: the script reads it from the file.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
PAGES = ROOT / "docs" / "benchmarks"
BENCHMARKS = ROOT / "BENCHMARKS.md"
SUMMARY_START = "<!-- summary: made by `python benchmarks/pages.py` from benchmarks/results/; do not edit -->"
SUMMARY_END = "<!-- summary end -->"

PEER_NAMES = {"sbx": "SBX + RL-Zoo", "sb3": "SB3 + RL-Zoo", "cleanrl": "CleanRL", "tfagents": "TF-Agents' tutorial",
              "torchrl": "TorchRL's recipe"}


@dataclass(frozen=True)
class Pair:
    """One row of the time-to-target table: ``side`` (rlpipe's) against ``peer`` in one command's JSON."""

    label: str
    """the task as a reader names it"""
    heading: str
    """BENCHMARKS.md's heading with this task's detail"""
    json: str
    """the file under benchmarks/results/time-to-return/"""
    task: str
    """the bench's task name in that file"""
    peer: str | None
    """the peer's side, or None where no peer was timed"""
    side: str = "rlpipe"


TIME_TO_TARGET = [
    Pair("Pendulum-v1 SAC to -200", "Pendulum-v1 SAC to -200", "2026-11-29-c98d626-pendulum-sac-heldout.json",
         "pendulum-sac", "sbx"),
    Pair("Pendulum-v1 SAC to -200", "Pendulum-v1 SAC to -200", "2026-11-27-d8e1637.json", "pendulum-sac", "sb3"),
    Pair("Pendulum-v1 SAC to -200", "Pendulum-v1 SAC to -200", "2026-11-27-d8e1637.json", "pendulum-sac", "cleanrl"),
    Pair("Pendulum-v1 SAC to -200", "TorchRL's own recipes against rlpipe", "2026-12-02-91840b3-torchrl-short.json", "pendulum-sac", "torchrl"),
    Pair("Pendulum-v1 TD3 to -200", "Pendulum-v1 TD3 to -200", "2026-11-29-08b24dc-heldout-sbx.json",
         "pendulum-td3", "sbx"),
    Pair("Pendulum-v1 TD3 to -200", "Pendulum-v1 TD3 to -200", "2026-11-27-d8e1637.json", "pendulum-td3", "sb3"),
    Pair("Pendulum-v1 TD3 to -200", "Pendulum-v1 TD3 to -200", "2026-11-27-d8e1637.json", "pendulum-td3", "cleanrl"),
    Pair("Pendulum-v1 TD3 to -200", "TorchRL's own recipes against rlpipe", "2026-12-02-91840b3-torchrl-short.json", "pendulum-td3", "torchrl"),
    Pair("InvertedPendulum-v5 TD3 to 950", "InvertedPendulum-v5 TD3 to 950", "2026-11-29-08b24dc-heldout-sbx.json",
         "invpendulum-td3", "sbx"),
    Pair("InvertedPendulum-v5 TD3 to 950", "TorchRL's own recipes against rlpipe", "2026-12-02-91840b3-torchrl-short.json", "invpendulum-td3", "torchrl"),
    Pair("InvertedPendulum-v5 SAC to 950", "InvertedPendulum-v5 SAC to 950", "2026-11-29-08b24dc-heldout-sbx.json",
         "invpendulum-sac", "sbx"),
    Pair("InvertedPendulum-v5 SAC to 950", "TorchRL's own recipes against rlpipe", "2026-12-02-91840b3-torchrl-short.json", "invpendulum-sac", "torchrl"),
    Pair("CartPole-v1 DQN to 475", "CartPole-v1 DQN to 475", "2026-11-29-08b24dc-heldout-sbx.json",
         "cartpole-v1-dqn", "sbx"),
    Pair("CartPole-v1 DQN to 475", "CartPole-v1 DQN to 475", "2026-11-27-d8e1637.json", "cartpole-v1-dqn", "sb3"),
    Pair("CartPole-v1 DQN to 475", "CartPole-v1 DQN to 475", "2026-11-27-d8e1637.json", "cartpole-v1-dqn", "cleanrl"),
    Pair("CartPole-v1 DQN to 475", "TorchRL's own recipes against rlpipe", "2026-12-02-91840b3-torchrl-short.json", "cartpole-v1-dqn", "torchrl"),
    Pair("CartPole-v0 DQN to 195", "CartPole-v0 DQN to 195, against CleanRL",
         "2026-11-29-c98d626-cartpole-v0-heldout.json", "cartpole-v0-dqn", "cleanrl"),
    Pair("CartPole-v0 DQN to 195", "CartPole-v0 DQN to 195, against CleanRL", "2026-11-27-16d7bc4-cartpole-v0.json",
         "cartpole-v0-dqn", "sbx"),
    Pair("CartPole-v0 DQN to 195", "CartPole-v0 DQN to 195, against CleanRL", "2026-11-27-16d7bc4-cartpole-v0.json",
         "cartpole-v0-dqn", "sb3"),
    Pair("CartPole-v0 DQN to 195", "CartPole-v0 DQN to 195, against CleanRL", "2026-11-27-16d7bc4-cartpole-v0.json",
         "cartpole-v0-dqn", "tfagents"),
    Pair("CartPole-v0 DQN to 195", "TorchRL's own recipes against rlpipe", "2026-12-02-91840b3-torchrl-short.json", "cartpole-v0-dqn", "torchrl"),
    Pair("HalfCheetah-v5 SAC to 3,000", "HalfCheetah-v5 SAC to 3,000", "2026-11-29-8fe68e7-halfcheetah-heldout.json",
         "halfcheetah-sac", "sbx"),
    Pair("HalfCheetah-v5 SAC to 3,000", "TorchRL's own recipes against rlpipe", "2026-12-03-fb86c42-torchrl-long.json",
         "halfcheetah-sac", "torchrl"),
    Pair("Minitaur SAC to 1.0", "Minitaur SAC to 1.0, against SBX", "2026-11-29-a13faf7-minitaur-1.json",
         "minitaur-sac-1", "sbx"),
    Pair("Minitaur SAC to 1.0", "Minitaur SAC to 1.0, against TF-Agents' own tutorial",
         "2026-11-29-5e02349-minitaur-1-tfagents.json", "minitaur-sac-1", "tfagents"),
    Pair("Acrobot-v1 DQN to -100, sized default", "The sized default and the development suite",
         "2026-12-02-6184a1a-acrobot-sized-sbx.json", "acrobot-dqn", "sbx"),
    Pair("Acrobot-v1 DQN to -100, sized default", "TorchRL's own recipes against rlpipe", "2026-12-02-91840b3-torchrl-short.json", "acrobot-dqn", "torchrl"),
    Pair("InvertedDoublePendulum-v5 SAC to 9,000, sized default", "The sized default and the development suite",
         "2026-12-02-efd41b6-idp-sized-sbx.json", "invdoublependulum-sac", "sbx"),
    Pair("InvertedDoublePendulum-v5 SAC to 9,000, sized default", "TorchRL's own recipes against rlpipe",
         "2026-12-02-efd41b6-torchrl-dev.json", "invdoublependulum-sac", "torchrl"),
    Pair("Reacher-v5 SAC to -5, sized default", "The sized default and the development suite",
         "2026-12-02-efd41b6-reacher-sized-sbx.json", "reacher-sac", "sbx"),
    Pair("Reacher-v5 SAC to -5, sized default", "TorchRL's own recipes against rlpipe",
         "2026-12-02-efd41b6-torchrl-dev.json", "reacher-sac", "torchrl"),
    Pair("Swimmer-v5 SAC to 40, sized default", "The sized default and the development suite",
         "2026-12-02-fdc1ddd-swimmer-sized-sbx.json", "swimmer-sac", "sbx"),
    Pair("Swimmer-v5 SAC to 40, sized default", "TorchRL's own recipes against rlpipe",
         "2026-12-03-fb86c42-torchrl-long.json", "swimmer-sac", "torchrl"),
    Pair("LunarLanderContinuous-v3 SAC to 200, sized default", "The sized default and the development suite",
         "2026-12-03-23b0abf-lunarlander-sbx.json", "lunarlandercontinuous-sac", "sbx"),
    Pair("LunarLanderContinuous-v3 SAC to 200, sized default", "TorchRL's own recipes against rlpipe",
         "2026-12-03-fb86c42-torchrl-long.json", "lunarlandercontinuous-sac", "torchrl"),
    Pair("Acrobot-v1 DQN to -100, tuned 30 min", "The sized default and the development suite",
         "2026-12-02-d36e01a-acrobot-tuned-sbx.json", "acrobot-dqn", "sbx"),
    Pair("InvertedDoublePendulum-v5 SAC to 9,000, tuned 30 min", "The sized default and the development suite",
         "2026-12-02-246967f-idp-tuned-sbx.json", "invdoublependulum-sac", "sbx"),
    Pair("Reacher-v5 SAC to -5, tuned 30 min", "The sized default and the development suite",
         "2026-12-02-e78301c-reacher-tuned-sbx.json", "reacher-sac", "sbx"),
    Pair("Swimmer-v5 SAC to 40, tuned 30 min", "The sized default and the development suite",
         "2026-12-03-144292a-swimmer-tuned-sbx.json", "swimmer-sac", "sbx"),
    Pair("LunarLanderContinuous-v3 SAC to 200, tuned 30 min", "The sized default and the development suite",
         "2026-12-03-23b0abf-lunarlander-sbx.json", "lunarlandercontinuous-sac", "sbx", side="preset"),
    Pair("Minitaur to 5", "Minitaur to 5, SAC against CrossQ",
         "2026-11-29-c8dfaff-minitaur-5-sac-crossq.json", "minitaur-sac-5", None, side="crossq"),
]

COMMANDS = {
    "2026-11-29-c98d626-pendulum-sac-heldout.json":
        "rlpipe bench time-to-return --tasks pendulum-sac --seeds 10 --seed 100 --peers sbx",
    "2026-11-29-08b24dc-heldout-sbx.json":
        "rlpipe bench time-to-return --tasks pendulum-sac pendulum-td3 invpendulum-td3 invpendulum-sac "
        "cartpole-v1-dqn --seeds 5 --seed 100 --peers sbx --no-crossq",
    "2026-11-27-d8e1637.json":
        "rlpipe bench time-to-return --tasks pendulum-sac pendulum-td3 cartpole-v1-dqn --seeds 5 --peers cleanrl sb3 sbx",
    "2026-11-29-c98d626-cartpole-v0-heldout.json":
        "rlpipe bench time-to-return --tasks cartpole-v0-dqn --seeds 5 --seed 100 --peers cleanrl",
    "2026-11-27-16d7bc4-cartpole-v0.json":
        "rlpipe bench time-to-return --tasks cartpole-v0-dqn --seeds 5 --peers cleanrl sb3 sbx tfagents",
    "2026-11-29-8fe68e7-halfcheetah-heldout.json":
        "rlpipe bench time-to-return --tasks halfcheetah-sac --seeds 5 --seed 100 --peers sbx --no-crossq --cap-scale 0.5",
    "2026-11-29-a13faf7-minitaur-1.json":
        "rlpipe bench time-to-return --tasks minitaur-sac-1 --seeds 5 --peers sbx --no-crossq --cap-scale 0.3",
    "2026-11-29-5e02349-minitaur-1-tfagents.json":
        "rlpipe bench time-to-return --tasks minitaur-sac-1 --seeds 5 --peers tfagents --side-seeds tfagents=1 "
        "--no-crossq --cap-scale 0.3 --cap tfagents=110000",
    "2026-12-02-6184a1a-acrobot-sized-sbx.json":
        "rlpipe bench time-to-return --tasks acrobot-dqn --seeds 5 --seed 100 --peers sbx",
    "2026-12-02-efd41b6-idp-sized-sbx.json":
        "rlpipe bench time-to-return --tasks invdoublependulum-sac --seeds 5 --seed 100 --peers sbx",
    "2026-12-02-efd41b6-reacher-sized-sbx.json":
        "rlpipe bench time-to-return --tasks reacher-sac --seeds 5 --seed 100 --peers sbx",
    "2026-12-02-fdc1ddd-swimmer-sized-sbx.json":
        "rlpipe bench time-to-return --tasks swimmer-sac --seeds 5 --seed 100 --peers sbx --cap-scale 0.4",
    "2026-12-02-efd41b6-hopper-sized-sbx.json":
        "rlpipe bench time-to-return --envs Hopper-v5 --target-return 500 --seeds 3 --seed 100 --peers sbx",
    "2026-12-02-91840b3-torchrl-short.json":
        "rlpipe bench time-to-return --tasks pendulum-sac pendulum-td3 cartpole-v0-dqn cartpole-v1-dqn acrobot-dqn "
        "invpendulum-sac invpendulum-td3 --seeds 1 --seed 100 --peers torchrl --torchrl-sota DIR --no-crossq",
    "2026-12-02-efd41b6-torchrl-dev.json":
        "rlpipe bench time-to-return --tasks invdoublependulum-sac reacher-sac --seeds 1 --seed 100 --peers torchrl "
        "--torchrl-sota DIR --cap torchrl=50000",
    "2026-12-02-d36e01a-acrobot-tuned-sbx.json":
        "rlpipe bench time-to-return --tasks acrobot-dqn --preset benchmarks/results/tune/2026-12-02-335b2a4-acrobot-dqn/"
        "dqn-acrobot-v1-tuned.yaml --seeds 5 --seed 100 --peers sbx",
    "2026-12-02-246967f-idp-tuned-sbx.json":
        "rlpipe bench time-to-return --tasks invdoublependulum-sac --preset benchmarks/results/tune/"
        "2026-12-02-ff4b74f-idp-sac/sac-inverteddoublependulum-v5-tuned.yaml --seeds 5 --seed 100 --peers sbx",
    "2026-12-02-e78301c-reacher-tuned-sbx.json":
        "rlpipe bench time-to-return --tasks reacher-sac --preset benchmarks/results/tune/"
        "2026-12-02-246967f-reacher-sac/sac-reacher-v5-tuned.yaml --seeds 5 --seed 100 --peers sbx",
    "2026-12-03-144292a-swimmer-tuned-sbx.json":
        "rlpipe bench time-to-return --tasks swimmer-sac --preset benchmarks/results/tune/"
        "2026-12-03-3679480-swimmer-sac/sac-swimmer-v5-tuned.yaml --seeds 5 --seed 100 --peers sbx --cap-scale 0.4",
    "2026-12-03-23b0abf-lunarlander-sbx.json":
        "rlpipe bench time-to-return --tasks lunarlandercontinuous-sac --also-preset benchmarks/results/tune/"
        "2026-12-03-25dd45a-lunarlander-sac/sac-lunarlandercontinuous-v3-tuned.yaml --seeds 5 --seed 100 --peers sbx "
        "--cap sbx=75000",
    "2026-12-03-fb86c42-torchrl-long.json":
        "rlpipe bench time-to-return --tasks halfcheetah-sac swimmer-sac lunarlandercontinuous-sac --seeds 1 --seed 100 "
        "--peers torchrl --torchrl-sota DIR --cap torchrl=50000 --no-crossq",
    "2026-11-29-c8dfaff-minitaur-5-sac-crossq.json":
        "rlpipe bench time-to-return --tasks minitaur-sac-5 --seeds 5 --peers none --cap-scale 0.1",
}

UPDATES = ("2026-11-29-b61039f-floor.json", "2026-11-29-b61039f-floor-compile.json",
           "rlpipe bench floor", "2026-11-29, at b61039f")
COLLECTION = (("2026-11-29-26bfe9b-collect-50.json", "rlpipe bench collect --envs CartPole-v1 Pendulum-v1 --frames 3000"),
              ("2026-11-29-26bfe9b-collect-200.json", "rlpipe bench collect --envs CartPole-v1 Pendulum-v1 --frames 3000 "
                                                      "collector.frames_per_batch=200"),
              ("2026-11-29-26bfe9b-collect-minitaur.json", "rlpipe bench collect --envs MinitaurBulletEnv-v0 --frames 1000"))
COLLECTION_WHEN = "2026-11-29, at 26bfe9b"
GPU = ("2026-11-28-h200-training-process.json",
       "rlpipe bench gpu --parts training --modes process cpu-copy step blocks --steps 4000", "2026-11-28, at 486ae97")
GPU_MODES = ("1 step, 1 update; policy on the GPU", "blocks of 32; policy on the GPU", "blocks of 32; policy on a CPU copy",
             "blocks of 32 from a collector process, overlapping the updates; policy on its CPU copy")


def slug(heading: str) -> str:
    """The anchor mkdocs gives a heading (Python-Markdown's ``toc`` slugify)."""
    text = re.sub(r"[^\w\s-]", "", heading).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


def _load(*parts: str) -> dict:
    return json.loads((RESULTS.joinpath(*parts)).read_text())


def _when(name: str) -> str:
    """``2026-11-29, at c98d626`` from a file named ``2026-11-29-c98d626-...json``."""
    date, commit = name[:10], name[11:].split("-")[0].split(".")[0]
    return f"{date}, at {commit}"


def _seeds(data: dict, side: dict) -> str:
    first = data.get("first_seed") or 0
    return f"{first}-{first + side['runs'] - 1}" if side["runs"] > 1 else str(first)


def _preset(data: dict, task: str, side: str) -> str:
    """What the rlpipe side trained: a preset's name, a preset file's name, or the sized default's ``ALGO env=ID``."""
    found = re.search(r"rlpipe train ([^`]+)`", data["tasks"][task]["settings"][side])
    if not found:
        return "?"
    first, _, rest = found.group(1).partition(" ")
    return f"{Path(first).name} {rest}".strip() if first.endswith((".yaml", ".yml")) else found.group(1)


def _peer_name(data: dict, task: str, peer: str) -> str:
    settings = data["tasks"][task]["settings"][peer]
    return "SBX, SB3's defaults (no RL-Zoo entry)" if peer == "sbx" and "default (no" in settings else PEER_NAMES[peer]


def _time(side: dict) -> str:
    reached = f"{side['reached']}/{side['runs']}"
    return f"{side['median_s']:.1f} s ({reached})" if side["median_s"] is not None else f"not reached ({reached})"


def _peer_runs(data: dict, task: str, peer: str) -> list[dict]:
    return [run for run in data["runs"] if run["task"] == task and run["side"] == peer]


def _ratio(data: dict, pair: Pair) -> tuple[float | None, str]:
    """rlpipe's median against the peer's, both from one command. Where the peer's median is not reached, the ratio
    is a bound: each of its runs would have reached the target no sooner than a floor (its seconds where it reached
    it; where it did not, the seconds from launch to the cap: ``wall_s`` less ``tail_s``, the exit after training),
    and the median of the runs' times is no less than the median of their floors."""
    ours, theirs = data["summary"][pair.task][pair.side], data["summary"][pair.task][pair.peer]
    if theirs["median_s"] is not None:
        ratio = theirs["median_s"] / ours["median_s"]
        return ratio, f"**{ratio:.1f}x**"
    floors = [run["seconds"] if run["reached"] else run["wall_s"] - (run.get("tail_s") or 0.0)
              for run in _peer_runs(data, pair.task, pair.peer)]
    bound = statistics.median(floors) / ours["median_s"]
    return bound, f"more than {bound:.1f}x"


def time_to_target(link: str | None) -> tuple[list[str], list[dict]]:
    """The summary table (task links to ``link``'s headings, or the headings named in quotes), its commands, and
    the figures to plot."""
    files = list(dict.fromkeys(pair.json for pair in TIME_TO_TARGET))
    lines = ["| task | rlpipe (preset) | peer | rlpipe median | peer median | rlpipe sooner | seeds, date |",
             "|---|---|---|---|---|---|---|"]
    plotted, last = [], None
    for pair in TIME_TO_TARGET:
        data = _load("time-to-return", pair.json)
        ours = data["summary"][pair.task][pair.side]
        task = f"[{pair.label}]({link}#{slug(pair.heading)})" if link else pair.label
        preset = f"`{_preset(data, pair.task, pair.side)}`"
        if last is not None and pair.label == last.label:
            preset = "" if pair.side == last.side else preset
            task = "" if pair.heading == last.heading or not link else task
        last = pair
        note = f"[{files.index(pair.json) + 1}]"
        if pair.peer is None:
            lines.append(f"| {task} | {preset} | none timed | **{_time(ours)}** | — | — | {_seeds(data, ours)}, "
                         f"{pair.json[:10]} {note} |")
            continue
        theirs = data["summary"][pair.task][pair.peer]
        ratio, shown = _ratio(data, pair)
        lines.append(f"| {task} | {preset} | {_peer_name(data, pair.task, pair.peer)} | **{_time(ours)}** | "
                     f"{_time(theirs)} | {shown} | {_seeds(data, ours)}, {pair.json[:10]} {note} |")
        plotted.append({"label": f"{pair.label}: {PEER_NAMES[pair.peer]}", "rlpipe": ours["median_s"],
                        "peer": theirs["median_s"], "bound": ratio if theirs["median_s"] is None else None})
    lines += ["", "The commands (each JSON under `benchmarks/results/time-to-return/`, with a PNG of every seed beside it):", ""]
    lines += [f"{n}. `{COMMANDS[name]}` ({_when(name)}; `{name}`)" for n, name in enumerate(files, 1)]
    return lines, plotted


def updates() -> tuple[list[str], list[dict]]:
    eager, compiled = _load("bench", UPDATES[0]), _load("bench", UPDATES[1])
    compiled_ms = {case["case"]: case["update_ms"] for case in compiled["cases"]}
    lines = [f"`{UPDATES[2]}` ({UPDATES[3]}; `benchmarks/results/bench/{UPDATES[0]}`, and `{UPDATES[1]}` with "
             f"`compile=true`): one update on a fixed batch, one CPU thread, against its arithmetic floor (the update's "
             f"matmul FLOPs at this CPU's measured rate on [256, 256] matmuls, {eager['matmul_gflops_per_s']:.1f} "
             "GFLOP/s).", "",
             "| update | ms | updates/s | floor ms | of the floor | compiled ms |", "|---|---|---|---|---|---|"]
    for case in eager["cases"]:
        lines.append(f"| {case['case']} | {case['update_ms']:.2f} | {1000 / case['update_ms']:,.0f} | "
                     f"{case['floor_ms']:.2f} | {case['fraction']:.0%} | {compiled_ms[case['case']]:.2f} |")
    return lines, eager["cases"]


def collection() -> tuple[list[str], list[dict]]:
    lines = [f"`rlpipe bench collect` ({COLLECTION_WHEN}; JSON under `benchmarks/results/bench/`): env steps per second of one "
             "env, random actions (raw env), CleanRL's loop with the preset's policy network (plain loop), and the "
             "collectors in the learner's process and in one collector process; the mean of two runs each.", "",
             "| env (preset) | block | raw env | plain loop | TorchRL `Collector` | rlpipe `GymCollector` | "
             "TorchRL, 1 process | rlpipe, 1 process | rlpipe / plain loop (1 process) |",
             "|---|---|---|---|---|---|---|---|---|"]
    rows = []
    for name, _ in COLLECTION:
        for row in _load("bench", name)["rows"]:
            mean = {key: statistics.fmean(row[key]) for key in ("torchrl", "ours", "torchrl_process", "ours_process")}
            lines.append(f"| {row['env']} (`{row['preset']}`) | {row['frames_per_batch']} | {row['raw']:,.0f} | "
                         f"{row['plain']:,.0f} | {mean['torchrl']:,.0f} | {mean['ours']:,.0f} | "
                         f"{mean['torchrl_process']:,.0f} | {mean['ours_process']:,.0f} | "
                         f"{mean['ours_process'] / row['plain']:.2f} |")
            rows.append({"label": f"{row['env']}, block {row['frames_per_batch']}", "plain": row["plain"], **mean})
    lines += ["", "The commands:", ""] + [f"- `{command}` (`{name}`)" for name, command in COLLECTION]
    return lines, rows


def gpu() -> tuple[list[str], dict]:
    data = _load("gpu", GPU[0])
    rate = {(run["case"], run["mode"]): run["updates_per_s_in_run"] for run in data["training"]}
    cases = list(dict.fromkeys(run["case"] for run in data["training"]))
    lines = [f"`{GPU[1]}` ({GPU[2]}; one {data['device']}, torch {data['torch']}; `benchmarks/results/gpu/{GPU[0]}`): "
             "the whole training loop on HalfCheetah-v5 with CleanRL's settings (256x256, batch 256, one update per env "
             "step, the update compiled and replayed as CUDA graphs, the env on the CPU), env steps (= updates) per "
             "second inside the run.", "",
             "| algorithm | " + " | ".join(GPU_MODES) + " |", "|---|" + "---|" * len(GPU_MODES)]
    for case in cases:
        lines.append(f"| {case}, HalfCheetah-v5 | " + " | ".join(f"{rate[case, mode]:,.0f}" for mode in GPU_MODES) + " |")
    return lines, {case: [rate[case, mode] for mode in GPU_MODES] for case in cases}


ANYTIME = {
    "2026-12-06-41bb2df-hopper-sbx.json": (
        "The best agent in ten minutes: Hopper-v5, return against wall-clock (`rlpipe bench anytime`)", "anytime.png"),
    "2026-12-07-aa73372-halfcheetah-sbx.json": (
        "The best agent in ten minutes: HalfCheetah-v5 (`rlpipe bench anytime`)", "anytime-halfcheetah.png"),
    "2026-12-08-dd3816a-ant-sbx.json": (
        "The best agent in ten minutes: Ant-v5 (`rlpipe bench anytime`)", "anytime-ant.png"),
}
"""``rlpipe bench anytime``'s files under benchmarks/results/anytime/ (the return each side had at each wall-clock
mark): each file's heading in BENCHMARKS.md and its figure on the site's page"""


def anytime(link: str) -> list[str]:
    """Per env of each ANYTIME file: every curve's mean greedy return and its 95% interval at five of its marks,
    then the file's figure."""
    lines = []
    for name, (heading, png) in ANYTIME.items():
        data = _load("anytime", name)
        marks = data["marks_s"]
        shown = sorted({round(i * (len(marks) - 1) / 4) for i in range(5)})
        seeds = data["seeds"]
        for env in data["envs"]:
            lines += [f"{env}, {len(seeds)} seeds ({seeds[0]}-{seeds[-1]}), {_when(name)} "
                      f"([the command and every seed]({link}#{slug(heading)})):", "",
                      "| curve (mean [95% CI]) | " + " | ".join(f"{marks[i]:.0f} s" for i in shown) + " |",
                      "|---|" + "---|" * len(shown)]
            for curve, c in data["curves"][env].items():
                cells = [("—" if c["mean"][i] is None else f"{c['mean'][i]:.0f}")
                         + (f" [{c['low'][i]:.0f}, {c['high'][i]:.0f}]" if c["low"][i] is not None else "")
                         for i in shown]
                label = {"rlpipe": "rlpipe, exported (the kept best)", "rlpipe (last)": "rlpipe, the last policy"}
                lines.append(f"| {label.get(curve, PEER_NAMES.get(curve, curve))} | " + " | ".join(cells) + " |")
            lines.append("")
        lines += [f"![{', '.join(data['envs'])}: greedy return against wall-clock time, mean and 95% band over seeds]"
                  f"({png})", ""]
    return lines


def summary_block() -> str:
    """The summary BENCHMARKS.md opens with."""
    table, _ = time_to_target(None)
    return "\n".join([SUMMARY_START, *table, SUMMARY_END])


def index_page() -> str:
    ttt, _ = time_to_target("log.md")
    upd, _ = updates()
    col, _ = collection()
    gpu_lines, _ = gpu()
    return "\n".join([
        "# Benchmarks", "",
        "<!-- made by `python benchmarks/pages.py` from benchmarks/results/; do not edit -->", "",
        "What a user of rlpipe gets on a small CPU machine (2 cores, no GPU, unless a table says otherwise). Each "
        "table is made from the JSON its command wrote; where a peer appears it ran in the same command, on the "
        "same machine, interleaved with rlpipe, so a ratio is read within its row only. The [log](log.md) has "
        "each command's machine, load and tries.", "",
        "## Time to a trained agent", "",
        "Seconds from launching the command (imports included) to the moment the mean return of the last 5 training "
        "episodes reached the target, confirmed by a 10-episode greedy evaluation whose time is left out; the median "
        "over seeds, with how many seeds reached the target within the step cap. A median that is not reached is "
        "counted as never, so the ratio is then a bound.", "",
        *ttt, "",
        "![Time to the target: rlpipe against each peer](time-to-target.png)", "",
        "## Learning per second", "",
        "### Updates per second", "",
        *upd, "",
        "![Each update against its arithmetic floor](updates.png)", "",
        "### Env steps per second", "",
        *col, "",
        "![Env steps per second, one env](collection.png)", "",
        "## The best agent in the time you have", "",
        "`rlpipe train env=ID time_budget=10m` as a user types it against the peer, each evaluated greedily at fixed "
        "times of its own clock (from its launch, imports counted, the benchmark's evaluations left out) on the same "
        "10 episodes; rlpipe's exported policy is what `policy/` would hold had the run ended there.", "",
        *anytime("log.md"),
        "## The training loop on a GPU", "",
        *gpu_lines, "",
        "![The training loop on a GPU](gpu.png)", "",
        "Not on this page (their figures are in the [log](log.md), not kept as JSON): the sized default on the "
        "development suite, the learner's threads on a busy machine, DQN with CleanRL's settings in one process, "
        "and the update alone on a GPU.", ""])


def draw(out: Path) -> list[Path]:
    """The plots, as PNG files in ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _, ttt = time_to_target(None)
    _, cases = updates()
    _, rows = collection()
    _, loops = gpu()
    written = []

    def save(fig, name):
        fig.tight_layout()
        path = out / name
        fig.savefig(path, dpi=110, metadata={"Software": None})
        plt.close(fig)
        written.append(path)

    fig, ax = plt.subplots(figsize=(8, 0.38 * len(ttt) + 1.2))
    ys = range(len(ttt))
    ax.barh([y + 0.2 for y in ys], [r["rlpipe"] for r in ttt], 0.4, label="rlpipe", color="#3f51b5")
    peer = [r["peer"] if r["peer"] is not None else r["rlpipe"] * r["bound"] for r in ttt]
    bars = ax.barh([y - 0.2 for y in ys], peer, 0.4, label="peer", color="#bbbbbb")
    for bar, r in zip(bars, ttt, strict=True):
        if r["peer"] is None:
            bar.set_hatch("//")
            ax.text(bar.get_width(), bar.get_y() + 0.2, " not reached by the median", va="center", fontsize=7)
    ax.set_yticks(list(ys), [r["label"] for r in ttt], fontsize=7)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlim(right=max(peer) * 6)
    ax.set_xlabel("median seconds to the target (log scale)")
    ax.legend(loc="lower right", fontsize=8)
    save(fig, "time-to-target.png")

    fig, ax = plt.subplots(figsize=(9, 0.45 * len(cases) + 1.2))
    ys = range(len(cases))
    ax.barh([y + 0.2 for y in ys], [c["update_ms"] for c in cases], 0.4, label="measured", color="#3f51b5")
    ax.barh([y - 0.2 for y in ys], [c["floor_ms"] for c in cases], 0.4, label="arithmetic floor", color="#bbbbbb")
    ax.set_yticks(list(ys), [re.sub(r" \([^()]*\)$", "", c["case"]) for c in cases], fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("ms per update, one CPU thread")
    ax.legend(loc="upper right", fontsize=8)
    save(fig, "updates.png")

    keys = (("plain", "plain loop"), ("torchrl", "TorchRL, in-process"), ("ours", "rlpipe, in-process"),
            ("torchrl_process", "TorchRL, 1 process"), ("ours_process", "rlpipe, 1 process"))
    fig, ax = plt.subplots(figsize=(8, 4))
    width = 0.8 / len(keys)
    for k, (key, name) in enumerate(keys):
        ax.bar([x + k * width for x in range(len(rows))], [r[key] for r in rows], width, label=name)
    ax.set_xticks([x + 0.4 - width / 2 for x in range(len(rows))], [r["label"] for r in rows], fontsize=7, rotation=15)
    ax.set_yscale("log")
    ax.set_ylabel("env steps per second (log scale)")
    ax.legend(fontsize=7)
    save(fig, "collection.png")

    fig, ax = plt.subplots(figsize=(8, 3.5))
    width = 0.8 / len(loops)
    for k, (case, rates) in enumerate(loops.items()):
        ax.bar([x + k * width for x in range(len(GPU_MODES))], rates, width, label=f"{case}, HalfCheetah-v5")
    ax.set_xticks([x + 0.4 - width / 2 for x in range(len(GPU_MODES))],
                  ["1 step, 1 update", "blocks of 32", "blocks, CPU-copy policy", "blocks from a process"], fontsize=8)
    ax.set_ylabel("env steps (= updates) per second")
    ax.legend(fontsize=8)
    save(fig, "gpu.png")

    from rlpipe.scripts.bench import anytime as anytime_bench

    for name, (_, png) in ANYTIME.items():
        written.append(anytime_bench.plot(_load("anytime", name), out / png))
    return written


def with_summary(benchmarks: str) -> str:
    """BENCHMARKS.md's text with its summary block replaced by the one the JSON makes."""
    start, end = benchmarks.index(SUMMARY_START), benchmarks.index(SUMMARY_END) + len(SUMMARY_END)
    return benchmarks[:start] + summary_block() + benchmarks[end:]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python benchmarks/pages.py", description=__doc__.split("\n")[0])
    parser.add_argument("--no-plots", action="store_true", help="write the Markdown only")
    args = parser.parse_args(argv)
    PAGES.mkdir(parents=True, exist_ok=True)
    (PAGES / "index.md").write_text(index_page())
    BENCHMARKS.write_text(with_summary(BENCHMARKS.read_text()))
    if not args.no_plots:
        draw(PAGES)


if __name__ == "__main__":
    main()
