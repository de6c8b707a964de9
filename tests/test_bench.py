"""The benchmarks' own arithmetic and tables (``rlpipe bench collect``, ``rlpipe bench ray``); no timing."""

import pytest

from rlpipe.scripts.bench.collect import collect_table, frames_per_batch, target_cell
from rlpipe.scripts.bench.ray import saturation


def test_blocks_are_the_presets_rounded_up_to_whole_vector_steps():
    assert frames_per_batch(50, 1) == 50
    assert frames_per_batch(50, 8) == 56
    assert frames_per_batch(50, 32) == 64
    assert frames_per_batch(160, 16) == 160


def test_the_target_cell_marks_half_the_raw_speed_and_above():
    assert target_cell(0.5) == "**0.50 met**"
    assert target_cell(0.49) == "0.49"


def test_the_collect_table_names_where_the_target_is_met():
    def row(env, n, torchrl, ours):
        return {"env": env, "preset": "p", "raw": 1000.0, "plain": 800.0, "envs_per_worker": n, "frames_per_batch": 50 * n,
                "torchrl": torchrl, "ours": ours, "torchrl_process": [200.0], "ours_process": [400.0] if ours else []}

    table = collect_table([row("A", 1, [100.0, 120.0], [300.0, 500.0]), row("A", 8, [400.0], []),
                           row("B", 1, [50.0], [390.0, 400.0])], 3000, [])
    assert ("| A | p | 1000 | 800 | 1 | 50 | 100 / 120 | 0.14 | 300 / 500 | **0.50 met** | 200 | 0.25 | 400 | "
            "**0.50 met** |") in table
    assert "| A | p | 1000 | 800 | 8 | 400 | 400 | 0.50 | - | - | 200 | 0.25 | - | - |" in table
    assert table.endswith("Target met (rlpipe in-process) for: A at envs_per_worker=1.")
    assert collect_table([row("A", 1, [1.0], [1.0])], 10, []).endswith("for: none.")


def test_actors_saturate_the_learner_where_their_steps_pay_for_its_updates():
    # 60 updates/s, 1 update per env step, 25 env steps/s per actor: 2.4 actors
    s = saturation(60.0, 25.0, 1.0, actors=(1, 2, 4))
    assert s["saturating_actors"] == pytest.approx(2.4)
    assert s["actors_needed"] == 3
    assert [(r["env_steps_per_s"], r["learner_bound"]) for r in s["rows"]] == [(25.0, False), (50.0, False), (60.0, True)]
    # half an update per env step: the learner can use twice the env steps
    assert saturation(60.0, 25.0, 0.5)["saturating_actors"] == pytest.approx(4.8)
    with pytest.raises(ValueError):
        saturation(60.0, 0.0, 1.0)


@pytest.mark.parametrize("options, message", [
    ({"frames": 0}, "--frames=0: expected a positive number of frames"),
    ({"workers": [1, 0]}, "--workers 1 0: expected positive integers"),
    ({"envs": ["CartPole-v1", "Pendulum-v1"]}, "bench ray measures one env; expected one env id"),
    ({"lengths": [5, 3]}, "--lengths 5 3: expected two iteration counts, 0 < N1 < N2"),
    ({"envs": ["CartPol-v1"]}, "--envs: unknown env id 'CartPol-v1'; did you mean 'CartPole-v1'"),
])
def test_bad_options_are_refused_before_anything_runs(options, message):
    from argparse import Namespace

    from rlpipe.pipelines.errors import InputError
    from rlpipe.scripts.bench.collect import check_args

    args = Namespace(**{"target": "ray", "frames": None, "workers": None, "envs_per_worker": None, "envs": None,
                        "lengths": None, "steps": None, **options})
    with pytest.raises(InputError, match=message.replace("(", r"\(")):
        check_args(args)


def test_the_tfagents_peer_finds_its_tutorial_scripts_in_a_checkout():
    from rlpipe.scripts.bench.peers import tfagents

    assert tfagents.SCRIPT.is_file() and tfagents.DQN_SCRIPT.is_file()
    assert "tf_agents" in tfagents.DQN_SCRIPT.read_text()
