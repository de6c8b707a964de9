"""The fast tier: the loop's arithmetic on its own, no envs, no processes (``pytest -m unit``, seconds).

Triggers (which run when an iteration count moves), the run state (counters, owed work, what a
checkpoint keeps of it) and the samples-per-insert rate limiter.
"""

from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict

from rlpipe.pipelines.config import TrainConfig
from rlpipe.pipelines.training.rate_limiter import SampleToInsertRatio
from rlpipe.pipelines.training.state import RunState
from rlpipe.pipelines.training.triggers import (
    EVAL,
    EXPORT,
    LOG,
    SAVE,
    VIDEO,
    IntervalTrigger,
    Trigger,
    crossed,
    default_triggers,
)

pytestmark = pytest.mark.unit


# --- triggers ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("previous, now, interval, expected", [
    (0, 1, 1, True), (0, 99, 100, False), (0, 100, 100, True), (99, 100, 100, True), (100, 100, 100, False),
    (100, 199, 100, False), (150, 250, 100, True), (0, 1000, 100, True), (5, 7, 0, False),
])
def test_crossed_means_a_multiple_in_the_half_open_span(previous, now, interval, expected):
    assert crossed(previous, now, interval) is expected


def names_due(triggers, previous, now, last):
    return [t.name for t in triggers if t.due(previous, now, last)]


def test_default_triggers_run_in_the_tutorials_order():
    cfg = TrainConfig(num_iterations=1000, log_interval=100, eval_interval=250, policy_save_interval=500,
                      checkpoint_interval=500)
    triggers = default_triggers(cfg)
    assert [t.name for t in triggers] == [LOG, EVAL, EXPORT, SAVE]
    assert names_due(triggers, 450, 500, 1000) == [LOG, EVAL, EXPORT, SAVE]
    assert names_due(triggers, 0, 50, 1000) == []
    assert names_due(triggers, 150, 250, 1000) == [LOG, EVAL]


def test_the_last_iteration_is_evaluated_in_its_own_triggers_and_leaves_the_checkpoint_to_the_end():
    triggers = default_triggers(TrainConfig(num_iterations=1000, log_interval=100, eval_interval=200,
                                            policy_save_interval=500, checkpoint_interval=500))
    # the final firing saves after the last block: not twice; the evaluation is the iteration's, whatever
    # the interval, so that a user's triggers after it see its return
    assert names_due(triggers, 950, 1000, 1000) == [LOG, EVAL, EXPORT]
    assert EVAL in names_due(default_triggers(TrainConfig(num_iterations=1000, eval_interval=300)), 950, 1000, 1000)


def test_the_built_in_trigger_names_are_those_old_checkpoints_hold():
    # a checkpoint records what its iteration still owes by these names: a run saved by any rlpipe resumes
    assert (LOG, EVAL, EXPORT, SAVE, VIDEO) == ("log", "eval", "export", "save", "video")


def test_the_video_is_a_final_firing_only_and_only_when_asked_for():
    assert VIDEO not in [t.name for t in default_triggers(TrainConfig())]
    video, = [t for t in default_triggers(TrainConfig(video=True)) if t.name == VIDEO]
    assert not video.due(0, 10**6, 10**6)


def test_an_interval_of_zero_never_triggers():
    triggers = default_triggers(TrainConfig(num_iterations=1000, eval_interval=0))
    assert EVAL not in names_due(triggers, 0, 999, 1000)
    assert EVAL in names_due(triggers, 999, 1000, 1000)  # 0: only before and after training


def test_a_block_crossing_several_multiples_runs_a_trigger_once():
    trigger = IntervalTrigger(10, lambda loop: None, name="mine")
    assert trigger.due(0, 35, 100) and not trigger.due(30, 39, 100)


def test_interval_trigger_calls_its_function_with_the_loop_and_takes_its_name():
    seen = []

    def probe(loop):
        seen.append(loop)

    trigger = IntervalTrigger(5, probe)
    assert trigger.name == "probe" and trigger.interval == 5
    trigger("the loop")
    assert seen == ["the loop"]


def test_a_trigger_without_a_call_says_so():
    with pytest.raises(NotImplementedError):
        Trigger(1)(None)


# --- the run state -------------------------------------------------------------------------------------


def cfg(**kw) -> TrainConfig:
    return TrainConfig(**{"initial_collect_steps": 100, "collect_steps_per_iteration": 2, **kw})


def test_iteration_counts_frames_past_the_initial_collect_in_whole_iterations():
    c = cfg()
    state = RunState.fresh(c)
    assert state.insert(60, c) == (0, 0)
    assert state.insert(60, c) == (0, 10)  # 20 frames past 100, 2 per iteration
    assert state.insert(3, c) == (10, 11)
    assert state.position() == {"step": 11, "frames": 123, "updates": 0}


def test_updates_are_owed_from_the_first_update_frame_at_the_configured_ratio():
    c = cfg(learning_starts=50)
    state = RunState.fresh(c)
    state.insert(60, c)
    assert state.limiter.owed == 5  # 10 frames past 50, one update per 2 frames
    assert [state.updated() for _ in range(5)] == [1, 2, 3, 4, 5]
    assert state.limiter.owed == 0 and state.updates == 5


def test_state_round_trips_through_a_checkpoint_with_its_owed_work():
    c = cfg()
    state = RunState.fresh(c)
    state.insert(131, c)
    state.updated()
    state.owed = [EVAL, EXPORT]
    state.pending_evals.append(({"step": 10, "frames": 120, "updates": 1},
                                TensorDict({"module": {"weight": torch.ones(2)}}, [])))
    saved = torch.load(_saved(state.state_dict()), weights_only=True)  # what a checkpoint file holds
    back = RunState.fresh(c)
    back.load_state_dict(saved)
    assert back.position() == state.position() and back.owed == [EVAL, EXPORT]
    assert back.limiter.state_dict() == state.limiter.state_dict()
    (at, weights), = back.pending_evals
    assert at == {"step": 10, "frames": 120, "updates": 1}
    assert torch.equal(weights["module", "weight"], torch.ones(2))


def _saved(data):
    import io

    buffer = io.BytesIO()
    torch.save(data, buffer)
    buffer.seek(0)
    return buffer


def test_resume_forgets_owed_work_whose_rows_were_written_after_the_checkpoint():
    c = cfg()
    state = RunState.fresh(c)
    state.iteration = 200
    state.owed = [LOG, EVAL, EXPORT]
    state.pending_evals.extend([({"step": 100}, None), ({"step": 200}, None)])
    rows = [{"step": "100", "average_return": "-3", "steps_per_s": ""},
            {"step": "200", "average_return": "", "steps_per_s": "51.2"}]
    state.forget_done(rows)
    assert state.owed == [EVAL, EXPORT]  # logged at 200; not evaluated at 200
    assert [at["step"] for at, _ in state.pending_evals] == [200]


# --- the rate limiter (Reverb's SampleToInsertRatio) ----------------------------------------------


def pay(limiter: SampleToInsertRatio) -> int:
    """Make every owed update, as the loop does."""
    owed = limiter.owed
    limiter.made(owed)
    return owed


@pytest.mark.parametrize("updates_per_frame", [1.0, 0.5, 1 / 3, 4.0])
def test_ratio_holds_for_uneven_blocks(updates_per_frame):
    limiter = SampleToInsertRatio(updates_per_frame)
    blocks = [7, 1, 50, 3, 13, 64, 2, 2, 31, 100, 9]
    frames = updates = 0
    for block in blocks:
        owed = limiter.insert(block)
        assert owed == limiter.owed
        updates += pay(limiter)
        frames += block
        # never more than owed, and less by under one update
        assert 0 <= frames * updates_per_frame - updates < 1 + 1e-9, (frames, updates)
        assert limiter.owed == 0
    assert limiter.frames == frames and limiter.updates == updates
    assert limiter.ratio == pytest.approx(updates_per_frame, rel=0.02)


def test_min_frames_are_not_paid_for():
    limiter = SampleToInsertRatio(0.5, min_frames=100)
    assert limiter.insert(60) == 0
    assert limiter.insert(39) == 0
    assert limiter.insert(11) == 5  # 10 frames past 100 -> 5 updates
    pay(limiter)
    assert limiter.insert(1) == 0  # half an update owed
    assert limiter.insert(1) == 1
    pay(limiter)
    assert limiter.updates == 6 and limiter.ratio == pytest.approx(0.5)


def test_owed_updates_stay_owed_until_made():
    limiter = SampleToInsertRatio(1.0)
    assert limiter.insert(5) == 5
    limiter.made(2)  # the loop stopped after two updates
    assert limiter.owed == 3
    assert limiter.insert(1) == 4
    limiter.made(4)
    assert limiter.owed == 0 and limiter.updates == 6


def test_state_dict_round_trip_continues_exactly():
    a = SampleToInsertRatio(1 / 3, min_frames=10)
    a.insert(25)
    pay(a)
    a.insert(2)  # a fraction of an update is owed now
    b = SampleToInsertRatio(1 / 3, min_frames=10)
    b.load_state_dict(json.loads(json.dumps(a.state_dict())))  # survives plain serialisation
    assert b.state_dict() == a.state_dict() and b.owed == a.owed
    for block in (1, 4, 9, 2):
        assert a.insert(block) == b.insert(block)
        assert pay(a) == pay(b)
    assert a.state_dict() == b.state_dict()


def test_a_non_positive_ratio_is_refused():
    with pytest.raises(ValueError):
        SampleToInsertRatio(0)


@pytest.mark.parametrize("init,end,steps", [(1.0, 0.05, 250_000), (1.0, 0.04, 5000), (0.1, 0.1, 1), (1.0, 0.01, 7),
                                            (0.9, 0.013, 33_333_337)])
def test_epsilon_is_annealed_to_egreedymodules_own_values(init, end, steps):
    """DQN anneals epsilon with ``anneal_epsilon`` (numpy float32) in place of ``EGreedyModule.step``: the
    same float32 value after every block, past the end of the schedule too."""
    import random

    from torchrl.data import Categorical
    from torchrl.modules import EGreedyModule

    from rlpipe.modules.fast.exploration import anneal_epsilon

    stock, ours = (EGreedyModule(Categorical(2), eps_init=init, eps_end=end, annealing_num_steps=steps) for _ in "ab")
    rng, total = random.Random(0), 0
    while total < min(2 * steps + 50, 300_000):
        frames = rng.choice([1, 10, 160, 1000])
        total += frames
        stock.step(frames)
        anneal_epsilon(ours, frames)
        assert ours.eps.item() == stock.eps.item(), total


def test_module_forward_is_the_modules_forward_and_respects_hooks():
    """The collect policies run their MLPs layer by layer (``module_forward``): the module's numbers, and the
    module's own call while it has a forward hook."""
    from torchrl.modules import MLP, NormalParamExtractor

    from rlpipe.modules.fast.tensor_nets import module_forward

    torch.manual_seed(0)
    for net in (MLP(in_features=4, out_features=2, num_cells=[16, 8]),
                torch.nn.Sequential(MLP(in_features=4, out_features=4, num_cells=[16]), NormalParamExtractor())):
        run, x = module_forward(net), torch.randn(5, 4)
        assert run is not net
        expected, got = net(x), run(x)
        for a, b in zip(expected if isinstance(expected, tuple) else (expected,),
                        got if isinstance(got, tuple) else (got,), strict=True):
            assert torch.equal(a, b)
        calls: list[int] = []
        handle = net.register_forward_hook(lambda *args, calls=calls: calls.append(1))
        run(x)
        assert calls == [1]
        handle.remove()
    other = torch.nn.Linear(4, 2)
    assert module_forward(other) is other
