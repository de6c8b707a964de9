"""What a tutorial's reader sees of a run: the live log on the terminal and the report page, opened in a
real browser (headless Chromium through Playwright: Debian's ``chromium``, which scripts/setup.sh installs).

Set ``RLPIPE_SCREENSHOT=path.png`` to keep a screenshot of the run's page (the README's picture).
"""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from rlpipe.pipelines.training.triggers import eval_line, log_line

MODULE = [sys.executable, "-m", "rlpipe.scripts.cli"]
TINY = ["num_iterations=300", "initial_collect_steps=100", "eval_interval=100", "num_eval_episodes=2",
        "log_interval=100", "checkpoint_interval=100", "policy_save_interval=100"]
NUMBER = r"-?(?:\d+(?:\.\d*)?(?:e[-+]?\d+)?|nan|inf)"
EVAL_LINE = re.compile(rf"^step = (\d+): AverageReturn = ({NUMBER}), AverageEpisodeLength = ({NUMBER}), "
                       rf"env steps/s = {NUMBER}, updates/s = {NUMBER}$")
LOSS_LINE = re.compile(rf"^step = (\d+): loss = ({NUMBER})(, .*)?$")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="Debian's chromium is not installed (scripts/setup.sh installs it as root with "
                             "apt-get install chromium); the report page's browser test needs it")


def rlpipe(*args, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([*MODULE, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=timeout)


def read_rows(run: Path) -> list[dict[str, str]]:
    with (run / "metrics.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))


# --- the live log --------------------------------------------------------------------------------


@pytest.mark.unit
def test_loss_line_gives_sacs_total_loss_first_as_the_tutorial_prints_it():
    row = {"loss_actor": -3.0, "loss_qvalue": 5.5, "loss_alpha": 0.25, "loss_alpha_value": 0.9,
           "loss_entropy": 1.5, "train_episode_return": -120.0, "steps_per_s": 500.0}
    line = log_line(200, row)
    assert line.startswith("step = 200: loss = 2.75, ")  # actor + critic + alpha, as TF-Agents' SacAgent sums it
    assert "actor_loss = -3" in line and "qvalue_loss = 5.5" in line and "alpha_loss = 0.25" in line
    assert "alpha_value = 0.9" in line and "entropy = 1.5" in line  # diagnostics, not in the total
    assert log_line(5000, {"loss_loss": 0.5}) == "step = 5000: loss = 0.5"  # DQN: the tutorial's line exactly


@pytest.mark.unit
def test_eval_line_names_the_tutorials_metrics_and_the_speeds():
    line = eval_line(10000, {"average_return": 12.5, "average_episode_length": 200.0}, 512.25, 480.0)
    assert line == ("step = 10000: AverageReturn = 12.500000, AverageEpisodeLength = 200.000000, "
                    "env steps/s = 512.2, updates/s = 480.0")
    assert EVAL_LINE.match(line)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two short CartPole runs from the command line: one with ``video=true``; one filmed afterwards by
    ``rlpipe video`` (its page copied before), side by side."""
    root = tmp_path_factory.mktemp("report")
    trained, filmed = root / "trained", root / "filmed"

    def with_video():
        return rlpipe("train", "dqn", *TINY, "video=true", "--out", trained, "--no-progress", cwd=root)

    def then_video():
        train = rlpipe("train", "dqn", *TINY, "seed=1", "--out", filmed, "--no-progress", cwd=root)
        before = (filmed / "report.html").read_text() if train.returncode == 0 else ""
        return train, before, rlpipe("video", filmed, "--episodes", "1", cwd=root)

    with ThreadPoolExecutor(max_workers=2) as pool:
        a, b = pool.submit(with_video), pool.submit(then_video)
        return {"root": root, "trained": trained, "filmed": filmed, "train": a.result(), "film": b.result()}


def test_no_progress_output_is_the_tutorials_log(runs):
    proc, run = runs["train"], runs["trained"]
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    rows = read_rows(run)
    # one line per evaluation, with the figures metrics.csv holds
    evals = [EVAL_LINE.match(line) for line in lines if EVAL_LINE.match(line)]
    eval_rows = [r for r in rows if r["average_return"]]
    assert [int(m[1]) for m in evals] == [int(r["step"]) for r in eval_rows] == [0, 100, 200, 300]
    for m, r in zip(evals, eval_rows):
        assert float(m[2]) == pytest.approx(float(r["average_return"]), rel=1e-5)
        assert float(m[3]) == pytest.approx(float(r["average_episode_length"]), rel=1e-5)
    # one line per log interval: the tutorial's `step = N: loss = X`
    losses = [LOSS_LINE.match(line) for line in lines if LOSS_LINE.match(line)]
    log_rows = [r for r in rows if r["loss_loss"]]
    assert [int(m[1]) for m in losses] == [int(r["step"]) for r in log_rows] == [100, 200, 300]
    for m, r in zip(losses, log_rows):
        assert float(m[2]) == pytest.approx(float(r["loss_loss"]), rel=1e-4)
    # the random agent's return first, once
    assert sum(line.startswith("random agent: AverageReturn = ") for line in lines) == 1
    # nothing of a progress bar, on either stream
    assert "\r" not in proc.stdout + proc.stderr and "it/s" not in proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr


def test_the_random_agents_return_is_kept_in_the_run(runs):
    run = runs["trained"]
    baseline = json.loads((run / "baseline.json").read_text())
    assert baseline["episodes"] == len(baseline["returns"]) == 2  # num_eval_episodes
    assert baseline["average_return"] == pytest.approx(sum(baseline["returns"]) / 2)
    assert 8 <= baseline["average_return"] <= 200  # CartPole-v0 pays 1 a step, 200 steps at most


@pytest.mark.parametrize("episodes, expected", [("0", None), ("3", 3)])
def test_baseline_episodes_sets_the_random_agents_episodes_or_turns_it_off(tmp_path, episodes, expected):
    from rlpipe.pipelines.config import apply_overrides
    from rlpipe.pipelines.dqn import DQN, preset

    cfg = apply_overrides(preset("dqn"), ["num_iterations=10", "initial_collect_steps=10", "eval_interval=0",
                                          "num_eval_episodes=1", f"baseline_episodes={episodes}"])
    DQN(cfg).train(tmp_path / "run", progress=False)
    path = tmp_path / "run" / "baseline.json"
    if expected is None:
        assert not path.exists()
    else:
        assert json.loads(path.read_text())["episodes"] == expected


def test_a_baseline_episodes_below_minus_one_is_one_clear_error():
    from rlpipe.pipelines import InputError
    from rlpipe.pipelines.config import apply_overrides, validate
    from rlpipe.pipelines.dqn import preset

    with pytest.raises(InputError, match=r"baseline_episodes=-2: expected -1 \(num_eval_episodes\), 0"):
        validate(apply_overrides(preset("dqn"), ["baseline_episodes=-2"]))


def test_rlpipe_video_puts_the_video_on_the_page(runs):
    train, before, film = runs["film"]
    run = runs["filmed"]
    assert train.returncode == 0, train.stderr[-3000:]
    assert film.returncode == 0, film.stderr[-3000:]
    assert 'id="no-video"' in before and "<video" not in before
    page = (run / "report.html").read_text()
    assert '<source src="trained-agent.mp4" type="video/mp4">' in page
    assert f"report: {run / 'report.html'}" in film.stdout


def test_train_with_video_true_films_the_trained_agent(runs):
    run = runs["trained"]
    assert (run / "trained-agent.mp4").stat().st_size > 1000
    assert "trained-agent.mp4" in runs["train"].stdout
    assert '<source src="trained-agent.mp4"' in (run / "report.html").read_text()


# --- the page, in a real browser ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def browser():
    if CHROMIUM is None:
        pytest.skip(needs_chromium.kwargs["reason"])
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        # Playwright's own Chromium download is unreachable here: drive the system's.
        browser = pw.chromium.launch(executable_path=CHROMIUM)
        yield browser
        browser.close()


def open_page(browser, path: Path):
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("console", lambda msg: errors.append(msg.text) if msg.type == "error" else None)
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.goto(path.resolve().as_uri())
    page.wait_for_load_state("load")
    return page, errors


def image_size(page, selector: str) -> tuple[int, int, float, float]:
    """(naturalWidth, naturalHeight, shown width, shown height) of an image: 0 where it did not render."""
    return tuple(page.eval_on_selector(selector, """img => { const r = img.getBoundingClientRect();
        return [img.complete ? img.naturalWidth : 0, img.complete ? img.naturalHeight : 0, r.width, r.height]; }"""))


@needs_chromium
def test_a_newcomers_run_page_in_chromium(runs, browser):
    """Train a short run with its video, open RUN/report.html from disk: the curve, the table, a playing video."""
    run = runs["trained"]
    assert runs["train"].returncode == 0, runs["train"].stderr[-3000:]
    page, errors = open_page(browser, run / "report.html")
    try:
        for figure in ("#returns-plot img", "#losses-plot img", "#speed-plot img"):
            natural_w, natural_h, shown_w, shown_h = image_size(page, figure)
            assert natural_w > 100 and natural_h > 100 and shown_w > 100 and shown_h > 100, figure
        # the evaluation table holds metrics.csv's evaluations, figure for figure
        table = page.eval_on_selector_all("#evaluations tbody tr", """rows => rows.map(r =>
            Object.fromEntries([...r.querySelectorAll('td')].map(td => [td.dataset.col, td.textContent.trim()])))""")
        expected = [r for r in read_rows(run) if r["average_return"]]
        assert len(table) == len(expected) == 4
        for shown, row in zip(table, expected):
            for col in ("step", "frames", "updates", "average_return", "average_episode_length", "wall_time"):
                assert shown[col] == row[col], (col, shown, row)
        # the random agent's return is on the page: baseline.json's figure and episodes
        baseline = json.loads((run / "baseline.json").read_text())
        facts = dict(page.eval_on_selector_all("#facts tr", """rows => rows.map(r =>
            [r.querySelector('th').textContent.trim(), r.querySelector('td').textContent.trim()])"""))
        shown = facts["random agent's AverageReturn"]
        assert shown.endswith(f"({baseline['episodes']} episodes)"), shown
        assert float(shown.split()[0]) == pytest.approx(baseline["average_return"], abs=0.05), (shown, baseline)
        # the video plays: data loaded, a duration, time moving
        state = page.evaluate("""async () => {
            const v = document.querySelector('#agent-video');
            await v.play();
            const t0 = performance.now();
            while (v.currentTime === 0 && performance.now() - t0 < 10000) await new Promise(r => setTimeout(r, 50));
            return {readyState: v.readyState, duration: v.duration, currentTime: v.currentTime,
                    width: v.videoWidth, error: v.error && v.error.code, src: v.currentSrc};
        }""")
        assert state["error"] is None, state
        assert state["readyState"] >= 2 and state["duration"] > 0 and state["currentTime"] > 0, state
        assert state["width"] == 600 and state["src"].endswith("trained-agent.mp4"), state
        assert errors == [], errors
        shot = os.environ.get("RLPIPE_SCREENSHOT")
        if shot:
            page.evaluate("document.querySelector('#agent-video').pause()")
            page.screenshot(path=shot, full_page=True)
    finally:
        page.close()


@pytest.mark.slow
@needs_chromium
def test_the_comparison_page_in_chromium(runs, browser):
    root = runs["root"]
    proc = rlpipe("report", runs["trained"], runs["filmed"], "--out", root / "pages" / "compare.html", cwd=root)
    assert proc.returncode == 0, proc.stderr[-3000:]
    page, errors = open_page(browser, root / "pages" / "compare.html")
    try:
        for figure in (".curves img", "#ecdf-plot img", "#runs-plot img"):
            natural_w, _, shown_w, shown_h = image_size(page, figure)
            assert natural_w > 100 and shown_w > 100 and shown_h > 100, figure
        # the two runs differ only in their seed: one variant, n = 2
        variants = page.eval_on_selector_all(".variants tbody tr", "rows => rows.map(r => r.innerText)")
        assert len(variants) == 1 and "\t2\t" in variants[0], variants
        runs_table = page.inner_text("#runs")
        for run in (runs["trained"], runs["filmed"]):
            final = [r for r in read_rows(run) if r["average_return"]][-1]["average_return"]
            assert f"{float(final):.1f}" in runs_table
        # each run's page is linked, relative to the comparison page, and opens
        links = page.eval_on_selector_all("#runs a", "as => as.map(a => a.href)")
        assert len(links) == 2
        page.goto(links[0])
        assert page.title().startswith("DQN on CartPole-v0")
        assert errors == [], errors
    finally:
        page.close()


@pytest.mark.unit
def test_comparison_pools_seeds_of_one_config_and_names_variants_by_what_differs(tmp_path):
    from rlpipe.pipelines.analysis.report_pages import run_labels

    def run(name, **config):
        folder = tmp_path / name
        folder.mkdir()
        base = {"env": "Pendulum-v1", "seed": 0, "clipped_double_q": True, "video": False, "log_interval": 100}
        (folder / "config.json").write_text(json.dumps({"algo": "td3", "config": {**base, **config}}))
        return str(folder)

    runs = [run("a", seed=0), run("b", seed=1, video=True, log_interval=50), run("c", clipped_double_q=False)]
    labels = run_labels(runs)
    assert labels[runs[0]] == labels[runs[1]] == "clipped_double_q=true"
    assert labels[runs[2]] == "clipped_double_q=false"
    assert run_labels(runs[:2]) == {runs[0]: "td3", runs[1]: "td3"}  # nothing differs but the seed


@pytest.mark.unit
def test_comparison_of_several_algorithms_pools_only_runs_whose_configs_agree(tmp_path):
    """`rlpipe report run-td3 run-td3-nocdq run-dqn` once pooled both TD3 runs into "td3 (n=2)"."""
    from rlpipe.pipelines.analysis.report_pages import run_labels

    def run(name, algo, **config):
        folder = tmp_path / name
        folder.mkdir()
        base = {"env": "Pendulum-v1", "seed": 0, "num_iterations": 1000}
        if algo == "td3":
            base["clipped_double_q"] = True
        (folder / "config.json").write_text(json.dumps({"algo": algo, "config": {**base, **config}}))
        return str(folder)

    td3_a, td3_b = run("td3-0", "td3"), run("td3-1", "td3", seed=1, checkpoint_keep=5)
    nocdq, dqn = run("td3-nocdq", "td3", clipped_double_q=False), run("dqn", "dqn", env="CartPole-v0")
    labels = run_labels([td3_a, td3_b, nocdq, dqn])
    assert labels[td3_a] == labels[td3_b] == "td3 clipped_double_q=true"  # seeds of one config: one variant
    assert labels[nocdq] == "td3 clipped_double_q=false"
    assert labels[dqn] == "dqn"
    assert len(set(run_labels([td3_a, nocdq, dqn]).values())) == 3


@pytest.mark.unit
def test_a_finished_run_trained_on_further_is_not_shown_as_finished(tmp_path):
    """Its old summary.json (of iteration 200) once made the page of a run stopped at 300 say "finished"."""
    from rlpipe.pipelines.analysis.report_pages import write_run_report

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"algo": "dqn", "config": {"env": "CartPole-v0", "seed": 0,
                                                                           "num_iterations": 400}}))
    (run / "summary.json").write_text(json.dumps({"algo": "dqn", "env": "CartPole-v0", "iterations": 200,
                                                  "frames": 300, "updates": 200, "wall_time_s": 9.1}))
    (run / "metrics.csv").write_text("step,frames,updates,average_return,average_episode_length,wall_time\n"
                                     "0,100,0,20,20,1\n200,300,200,50,50,9\n300,400,300,60,60,12\n")
    page = write_run_report(run).read_text()
    assert "stopped at iteration 300 of 400" in page and "rlpipe train dqn --resume" in page
    assert ">finished<" not in page and "9.1 s" not in page  # the first stretch's figures are not the run's


# --- bad input ---------------------------------------------------------------------------------------------


def test_report_of_a_folder_that_is_not_a_run_is_one_line(tmp_path):
    (tmp_path / "empty").mkdir()
    proc = rlpipe("report", tmp_path / "empty", cwd=tmp_path)
    assert proc.returncode == 2 and proc.stderr.startswith("rlpipe: error:") and len(proc.stderr.splitlines()) == 1
    assert "not a run directory" in proc.stderr
    assert list(tmp_path.iterdir()) == [tmp_path / "empty"]
