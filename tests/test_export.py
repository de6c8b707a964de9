"""The exported policy: ONNX (data only) beside the .pt2, its history, rlpipe's loader, `rlpipe eval/video`
on it (a crafted .pt2 refused without --trust), the random baseline, and the exported-policy page's snippets run as
written on a CartPole and a Pendulum run."""

from __future__ import annotations

import io
import json
import logging
import re
import shutil
import stat
import subprocess
import sys
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import gymnasium
import numpy as np
import onnx
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.envs import GymEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal

from rlpipe.envs import make_env
from rlpipe.pipelines import dqn, sac, td3
from rlpipe.pipelines.artifacts.export import OnnxExportWarning, available_steps, export_policy, load_policy
from rlpipe.pipelines.config import apply_overrides
from rlpipe.pipelines.errors import InputError

POLICY_PAGE = Path(__file__).resolve().parents[1] / "docs" / "guides" / "exported-policy.md"
RLPIPE = [sys.executable, "-m", "rlpipe.scripts.cli"]
SHORT = ["num_iterations=300", "initial_collect_steps=100", "eval_interval=0", "num_eval_episodes=1",
         "log_interval=100", "checkpoint_interval=300", "policy_save_interval=100", "collector.sync=true"]


def rlpipe(*args, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(RLPIPE + [str(a) for a in args], cwd=cwd, capture_output=True, text=True, timeout=timeout)


def one_line_error(code: int, stderr: str, *words: str) -> None:
    lines = stderr.strip().splitlines()
    assert code == 2, f"exit {code}; stderr:\n{stderr}"
    assert len(lines) == 1 and lines[0].startswith("rlpipe: error:"), stderr
    for word in words:
        assert word in lines[0], f"{word!r} not in {lines[0]!r}"


def in_process(argv: list[str], capfd) -> tuple[int, str, str]:
    from rlpipe.scripts.cli import main

    capfd.readouterr()
    code = main([str(a) for a in argv])
    out, err = capfd.readouterr()
    return code, out, err


def deterministic_actions(policy: nn.Module, observations: torch.Tensor) -> torch.Tensor:
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        return policy(TensorDict(observation=observations, batch_size=observations.shape[:1]))["action"]


@pytest.fixture
def caller_disables_info():
    """A caller that silenced INFO and below, as a test runner or an application may."""
    logging.disable(logging.INFO)
    yield logging.INFO
    logging.disable(logging.NOTSET)


# --- the files an export writes -----------------------------------------------------------------------


def test_export_writes_onnx_pt2_and_json_atomically(tmp_path):
    torch.manual_seed(0)
    folder = tmp_path / "policy"
    export_policy(nn.Linear(3, 2), 3, folder, {"algo": "td3"})
    with (folder / "policy.json").open() as reader:
        export_policy(nn.Linear(3, 2), 3, folder, {"algo": "sac"})
        # policy.json was replaced, not truncated and rewritten under a reader
        assert json.loads(reader.read())["algo"] == "td3"
    info = json.loads((folder / "policy.json").read_text())
    assert info["algo"] == "sac" and info["observation_dim"] == 3
    assert "safe to load from anyone" in info["files"]["policy.onnx"]
    assert "only from a source you trust" in info["files"]["policy.pt2"]
    assert sorted(p.name for p in folder.iterdir()) == ["policy.json", "policy.onnx", "policy.pt2"]
    for name in ("policy.json", "policy.onnx", "policy.pt2"):
        assert stat.S_IMODE((folder / name).stat().st_mode) == 0o644
    onnx.checker.check_model(onnx.load(folder / "policy.onnx"), full_check=True)
    policy, info = load_policy(folder)
    assert info["algo"] == "sac" and policy.path == folder / "policy.onnx"
    assert policy(torch.zeros(3)).shape == (2,)


def test_the_callers_module_keeps_its_gradients(tmp_path):
    module = nn.Linear(3, 2)
    export_policy(module, 3, tmp_path / "policy", {})
    assert all(p.requires_grad for p in module.parameters()), "export must not freeze the policy being trained"


def test_load_policy_keeps_the_callers_logging_disable_level(tmp_path, caller_disables_info):
    folder = tmp_path / "policy"
    export_policy(nn.Linear(3, 2), 3, folder, {})
    (folder / "policy.onnx").unlink()
    load_policy(folder, trust=True)
    assert logging.root.manager.disable == caller_disables_info
    (folder / "policy.pt2").write_bytes(b"PK\x03\x04 not a torch.export archive" * 10)
    with pytest.raises(InputError, match="corrupt or not an exported policy"):
        load_policy(folder, trust=True)
    assert logging.root.manager.disable == caller_disables_info


def test_a_damaged_or_foreign_onnx_file_is_one_clear_error(tmp_path):
    folder = tmp_path / "policy"
    export_policy(nn.Linear(3, 2), 3, folder, {})
    (folder / "policy.onnx").write_bytes(b"\x08\x07 not an onnx model" * 10)
    with pytest.raises(InputError, match=r"policy\.onnx: corrupt or not an exported policy"):
        load_policy(folder)
    export_policy(nn.Linear(5, 2), 5, tmp_path / "other", {})  # a valid ONNX policy, of another env
    shutil.copy(tmp_path / "other" / "policy.onnx", folder / "policy.onnx")
    with pytest.raises(InputError, match=r"policy\.onnx: corrupt or not an exported policy"):
        load_policy(folder)


# --- ONNX gives the trained policy's actions -------------------------------------------------------------


def _users_sac_actor():
    """The README's own SAC actor: a TorchRL ProbabilisticActor, exported through TensorDicts."""
    spec = GymEnv("Pendulum-v1").action_spec
    net = TensorDictModule(nn.Sequential(MLP(in_features=3, out_features=2, num_cells=[16]), NormalParamExtractor()),
                           in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(net, in_keys=["loc", "scale"], spec=spec, distribution_class=TanhNormal,
                              distribution_kwargs={"low": spec.space.low, "high": spec.space.high})


PIPELINES = {
    "sac": lambda: sac.SAC(apply_overrides(sac.SACConfig(env="Pendulum-v1"), SHORT)),
    "td3": lambda: td3.TD3(apply_overrides(td3.TD3Config(env="Pendulum-v1"), SHORT)),
    "dqn": lambda: dqn.DQN(apply_overrides(dqn.DQNConfig(env="CartPole-v1"), SHORT)),
    "sac-users-actor": lambda: sac.SAC(apply_overrides(sac.SACConfig(env="Pendulum-v1"), SHORT), actor=_users_sac_actor()),
}


@pytest.mark.parametrize("name", list(PIPELINES))
def test_onnx_gives_the_deterministic_policys_actions(name, tmp_path):
    """SAC: the TanhNormal's mode; TD3: the actor; DQN: the argmax; a user's TorchRL actor too."""
    pipeline = PIPELINES[name]()
    with torch.no_grad():  # weights away from their initial values, as after training
        for p in pipeline.policy.parameters():
            p.add_(torch.randn_like(p) * 0.3)
    folder = tmp_path / "policy"
    export_policy(pipeline.export_module(), pipeline.observation_dim, folder, pipeline.export_info())
    observations = make_env(pipeline.config.env, seed=3).rollout(50, break_when_any_done=False)["observation"]
    expected = deterministic_actions(pipeline.policy, observations)

    policy, _ = load_policy(folder)
    assert policy.path.name == "policy.onnx"
    actions = policy(observations)
    assert actions.dtype == expected.dtype and actions.shape == expected.shape and not actions.requires_grad
    if name == "dqn":
        assert actions.tolist() == expected.tolist()
    else:
        torch.testing.assert_close(actions, expected, rtol=1e-4, atol=1e-5)
    # one observation, unbatched, as a tensor and as a numpy array
    torch.testing.assert_close(policy(observations[7]), expected[7], rtol=1e-4, atol=1e-5)
    one = policy(observations[7].numpy().astype(np.float64))
    assert isinstance(one, np.ndarray) and one.shape == tuple(expected[7].shape)
    np.testing.assert_allclose(one, expected[7].numpy(), rtol=1e-4, atol=1e-5)


def test_a_policy_trained_on_rescaled_observations_is_exported_on_the_envs_own(tmp_path):
    # rescale_observations=true: the networks read observations mapped from the space's bounds to
    # [-1, 1] (Pendulum-v1's: [-1, -1, -8] to [1, 1, 8]); the exported policy takes the env's own and maps
    # them itself, as gymnasium's RescaleObservation does.
    pipeline = sac.SAC(apply_overrides(sac.SACConfig(env="Pendulum-v1"), [*SHORT, "rescale_observations=true"]))
    with torch.no_grad():
        for p in pipeline.policy.parameters():
            p.add_(torch.randn_like(p) * 0.3)
    raw = make_env("Pendulum-v1", seed=3).rollout(50, break_when_any_done=False)["observation"]
    assert raw[:, 2].abs().max() > 1  # the angular velocity, bounded by 8
    to_unit = gymnasium.wrappers.utils.rescale_box(gymnasium.make("Pendulum-v1").observation_space,
                                                   np.float32(-1), np.float32(1))[1]
    rescaled = torch.from_numpy(to_unit(raw.numpy()))
    seen = pipeline.env.rollout(50, break_when_any_done=False)["observation"]
    assert seen.abs().max() <= 1 and seen[:, 2].abs().max() < 1
    export_policy(pipeline.exported_policy(), pipeline.observation_dim, tmp_path, pipeline.export_info())
    policy, _ = load_policy(tmp_path)
    torch.testing.assert_close(policy(raw), deterministic_actions(pipeline.policy, rescaled), rtol=1e-4, atol=1e-5)
    with pytest.raises(InputError, match="rescale_observations=true: env 'HalfCheetah-v5' has observation bounds "
                                         "that are not finite .*; expected finite low and high"):
        sac.SAC(apply_overrides(sac.SACConfig(env="HalfCheetah-v5"), [*SHORT, "rescale_observations=true"]))
    with pytest.raises(InputError, match="'CartPole-v1' has observation bounds that are not finite [(]2 of 4 entries "
                                         "infinite or wider than 1e[+]06[)]"):  # its velocities: float32's largest
        dqn.DQN(apply_overrides(dqn.DQNConfig(env="CartPole-v1"), [*SHORT, "rescale_observations=true"]))


def test_the_pt2_gives_actions_without_grad(tmp_path):
    folder = tmp_path / "policy"
    export_policy(nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1)), 3, folder, {})
    program = torch.export.load(folder / "policy.pt2").module()
    assert not program(torch.zeros(5, 3)).requires_grad
    actions = program(torch.zeros(5, 3)).numpy()  # the README's old snippet failed here on Pendulum
    assert actions.shape == (5, 1)


class _NoOnnx(nn.Module):
    """A plug-in actor with an operator ONNX has no equivalent for (``torch.special.i0``)."""

    def __init__(self):
        super().__init__()
        self.net = nn.Linear(3, 1)

    def forward(self, observation):
        return torch.special.i0(self.net(observation))


def test_a_module_onnx_cannot_express_is_exported_as_pt2_only_with_a_warning(tmp_path, capfd):
    folder = tmp_path / "policy"
    export_policy(nn.Linear(3, 1), 3, folder, {}, step=100)  # an earlier export that had ONNX
    capfd.readouterr()
    with pytest.warns(OnnxExportWarning, match="only policy.pt2 is written.*--trust"):
        export_policy(_NoOnnx(), 3, folder, {}, step=200)
    assert "Torch IR graph" not in capfd.readouterr().err, "the exporter's graph dump reached the terminal"
    assert not (folder / "policy.onnx").exists(), "the earlier export's ONNX is not the latest policy"
    assert (folder / "policy.pt2").exists() and (folder / "step_0000200.pt2").exists()
    assert not (folder / "step_0000200.onnx").exists()
    assert "policy.onnx" not in json.loads((folder / "policy.json").read_text())["files"]
    with pytest.raises(InputError, match="--trust"):
        load_policy(folder)
    policy, _ = load_policy(folder, trust=True)
    assert policy.path.name == "policy.pt2" and policy(torch.zeros(3)).shape == (1,)
    assert load_policy(folder, step=100)[0].path.name == "step_0000100.onnx"


# --- history ------------------------------------------------------------------------------------------


def test_each_export_is_kept_by_step_and_the_newest_keep_remain(tmp_path):
    folder = tmp_path / "policy"
    modules = {}
    for step in (100, 200, 300):
        modules[step] = nn.Linear(3, 2)
        export_policy(modules[step], 3, folder, {"algo": "td3"}, step=step, keep=2)
    assert available_steps(folder) == [200, 300]
    assert sorted(p.name for p in folder.iterdir()) == [
        "policy.json", "policy.onnx", "policy.pt2",
        "step_0000200.onnx", "step_0000200.pt2", "step_0000300.onnx", "step_0000300.pt2"]
    assert (folder / "policy.onnx").read_bytes() == (folder / "step_0000300.onnx").read_bytes()
    info = json.loads((folder / "policy.json").read_text())
    assert info["step"] == 300 and info["steps"] == [200, 300]
    observations = torch.randn(4, 3)
    for step in (200, 300):
        policy, _ = load_policy(folder, step=step)
        with torch.no_grad():
            torch.testing.assert_close(policy(observations), modules[step](observations))
    with pytest.raises(InputError, match=r"--step 100: .* expected one of the exported steps: 200, 300$"):
        load_policy(folder, step=100)


def test_keep_0_keeps_every_export(tmp_path):
    for step in (100, 200, 300):
        export_policy(nn.Linear(3, 2), 3, tmp_path, {}, step=step)
    assert available_steps(tmp_path) == [100, 200, 300]


# --- a crafted .pt2 -----------------------------------------------------------------------------------


class _Payload:
    """Unpickled, it creates ``marker`` and hands back a valid weight: the load goes on as normal."""

    def __init__(self, marker: Path, shape: list[int]):
        self.marker, self.shape = str(marker), shape

    def __reduce__(self):
        return (eval, (f"open({self.marker!r}, 'w').close() or __import__('torch').nn.Parameter("
                       f"__import__('torch').zeros({self.shape}), requires_grad=False)",))


def craft_pt2(path: Path, marker: Path) -> None:
    """Turn a real ``.pt2`` into one whose first weight is a pickle that runs code when loaded."""
    with zipfile.ZipFile(path) as archive:
        entries = {info.filename: archive.read(info) for info in archive.infolist()}
    config_name = next(name for name in entries if name.endswith("model_weights_config.json"))
    config = json.loads(entries[config_name])
    meta = next(iter(config["config"].values()))
    meta["use_pickle"] = True
    payload = io.BytesIO()
    torch.save(_Payload(marker, [s["as_int"] for s in meta["tensor_meta"]["sizes"]]), payload)
    entries[config_name] = json.dumps(config).encode()
    entries[f"{config_name.rsplit('/', 1)[0]}/{meta['path_name']}"] = payload.getvalue()
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
        for name, data in entries.items():
            archive.writestr(name, data)


# --- runs, and the commands on them -------------------------------------------------------------------


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A CartPole (DQN) and a Pendulum (TD3) run, 300 iterations, a policy every 100, the newest 2 kept."""
    root = tmp_path_factory.mktemp("export-runs")
    dqn.DQN(apply_overrides(dqn.preset("dqn"), SHORT + ["policy_keep=2"])).train(root / "cartpole", progress=False)
    td3.TD3(apply_overrides(td3.preset("td3"), SHORT + ["policy_keep=2"])).train(root / "pendulum", progress=False)
    return root


def test_a_run_keeps_its_newest_exports(runs):
    folder = runs / "cartpole" / "policy"
    assert available_steps(folder) == [200, 300]
    info = json.loads((folder / "policy.json").read_text())
    assert info["step"] == 300 and info["env"] == "CartPole-v0"
    assert info["env_recipe"] == {"gymnasium_id": "CartPole-v0", "imports": [],
                                  "make": "import gymnasium; env = gymnasium.make('CartPole-v0')",
                                  "observations": "the env's own, as float32 (no normalisation)"}


def test_minitaurs_recipe_imports_rlpipe_envs_first(tmp_path):
    export_policy(nn.Linear(28, 8), 28, tmp_path, {"env": "MinitaurBulletEnv-v0"})
    recipe = json.loads((tmp_path / "policy.json").read_text())["env_recipe"]
    assert recipe["imports"] == ["rlpipe.envs"] and recipe["gymnasium_id"] == "rlpipe/MinitaurBullet-v0"
    code = f"{recipe['make']}\nprint(env.observation_space.shape)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.strip().splitlines()[-1] == "(28,)", proc.stderr[-2000:]


@pytest.fixture(scope="module")
def commands(runs):
    """Commands in real processes, two at a time: on copies of a run with a crafted .pt2, and a video."""
    run = runs / "cartpole"
    only_pt2 = runs / "only-pt2"  # an exported policy that exists only as a crafted .pt2
    shutil.copytree(run, only_pt2)
    for onnx_file in (only_pt2 / "policy").glob("*.onnx"):
        onnx_file.unlink()
    craft_pt2(only_pt2 / "policy" / "policy.pt2", runs / "pwned-only-pt2")
    beside_onnx = runs / "beside-onnx"  # a crafted .pt2 next to a good policy.onnx
    shutil.copytree(run, beside_onnx)
    craft_pt2(beside_onnx / "policy" / "policy.pt2", runs / "pwned-beside-onnx")
    jobs = {
        "eval-only-pt2": ["eval", only_pt2, "--episodes", "2"],
        "video-only-pt2": ["video", only_pt2, "--episodes", "1"],
        "eval-beside-onnx": ["eval", beside_onnx, "--episodes", "2", "--json"],
        "video-step": ["video", run, "--step", "200", "--episodes", "1"],
    }
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = dict(zip(jobs, pool.map(lambda args: rlpipe(*args, cwd=runs), jobs.values())))
    return runs, results


def test_the_crafted_pt2_runs_code_when_torch_loads_it(runs, commands):
    """The control: the crafted file is a real attack (torch.export.load runs it and goes on as normal)."""
    marker = runs / "pwned-control"
    path = runs / "control.pt2"
    shutil.copy(runs / "cartpole" / "policy" / "policy.pt2", path)
    craft_pt2(path, marker)
    actions = torch.export.load(path).module()(torch.zeros(3, 4))
    assert marker.exists() and actions.shape == (3,)


@pytest.mark.parametrize("command", ["eval", "video"])
def test_eval_and_video_refuse_a_pt2_without_trust_and_no_code_runs(commands, command):
    runs, results = commands
    proc = results[f"{command}-only-pt2"]
    one_line_error(proc.returncode, proc.stderr, "policy.pt2", "--trust", "run code")
    assert not (runs / "pwned-only-pt2").exists(), "the crafted file ran"
    assert not (runs / "only-pt2" / "trained-agent.mp4").exists()


def test_eval_loads_the_onnx_and_never_the_pt2_beside_it(commands):
    runs, results = commands
    proc = results["eval-beside-onnx"]
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1])["policy"].endswith("policy.onnx")
    assert not (runs / "pwned-beside-onnx").exists(), "the crafted file ran"


def test_eval_and_video_of_an_earlier_step(commands, capfd):
    runs, results = commands
    code, out, err = in_process(["eval", runs / "cartpole", "--step", "200", "--episodes", "2", "--json"], capfd)
    assert code == 0, err
    data = json.loads(out.strip().splitlines()[-1])
    assert data["policy"] == str(runs / "cartpole" / "policy" / "step_0000200.onnx")
    assert len(data["returns"]) == 2 and data["AverageEpisodeLength"] == pytest.approx(data["AverageReturn"])
    proc = results["video-step"]
    assert proc.returncode == 0, proc.stderr
    assert (runs / "cartpole" / "trained-agent-step_200.mp4").stat().st_size > 1000
    assert "trained-agent-step_200.mp4" in proc.stdout


def test_random_agent_on_an_env_id(tmp_path, monkeypatch, capfd):
    monkeypatch.chdir(tmp_path)
    code, out, err = in_process(["eval", "--env", "CartPole-v1", "--random", "--episodes", "5", "--json", "--ecdf"], capfd)
    assert code == 0, err
    assert [p.name for p in tmp_path.iterdir()] == ["ecdf-random.png"], "no run directory: the plot lands here"
    data = json.loads(out.strip().splitlines()[-1])
    assert data["ecdf_png"] == str(tmp_path / "ecdf-random.png")
    assert data["policy"] == "random" and data["env"] == "CartPole-v1" and len(data["returns"]) == 5
    # CartPole pays 1 per step; a random agent falls within a few dozen steps
    assert data["AverageEpisodeLength"] == pytest.approx(data["AverageReturn"]) and 8 <= data["AverageReturn"] < 100


def test_random_agent_on_a_runs_env_prints_as_eval_does(runs, capfd):
    code, out, err = in_process(["eval", runs / "pendulum", "--random", "--episodes", "2"], capfd)
    assert code == 0, err
    lines = out.strip().splitlines()
    assert [line.split(" = ")[0] for line in lines] == ["AverageReturn", "AverageEpisodeLength"]
    assert float(lines[1].split(" = ")[1]) == 200.0  # Pendulum's time limit
    assert float(lines[0].split(" = ")[1]) < -200  # a random pendulum does not swing up
    again = in_process(["eval", runs / "pendulum", "--random", "--episodes", "2"], capfd)[1]
    assert again == out, "the same --seed gives the same random agent"


@pytest.mark.parametrize("argv, words", [
    (["eval", "RUN", "--step", "150"], ["--step 150", "200, 300"]),
    (["video", "RUN", "--step", "100"], ["--step 100", "200, 300"]),
    (["eval", "RUN", "--random", "--step", "200"], ["--step", "--random"]),
    (["eval", "--env", "CartPole-v1"], ["--env", "--random"]),
    (["eval", "RUN", "--env", "CartPole-v1", "--random"], ["--env", "one of them"]),
    (["eval"], ["rlpipe eval RUN_DIR", "--env ID --random"]),
    (["eval", "--env", "CartPol-v1", "--random"], ["CartPol-v1", "CartPole-v1"]),
], ids=["eval-unknown-step", "video-unknown-step", "random-and-step", "env-without-random", "run-and-env",
        "nothing-to-evaluate", "random-unknown-env"])
def test_bad_policy_choices_are_one_line(runs, capfd, argv, words):
    before = sorted(p.name for p in (runs / "cartpole").rglob("*"))
    code, out, err = in_process([runs / "cartpole" if a == "RUN" else a for a in argv], capfd)
    one_line_error(code, err, *words)
    assert out == "" and sorted(p.name for p in (runs / "cartpole").rglob("*")) == before


# --- the exported-policy page's snippets, run as written ---------------------------------------------


def page_snippet(name: str) -> str:
    found = re.search(rf"<!-- snippet: {name} -->\n(?:<!-- no-run: .*? -->\n)?```python\n(.*?)```\n<!-- /snippet -->",
                      POLICY_PAGE.read_text(), re.S)
    assert found, f"docs/guides/exported-policy.md has no snippet {name!r}"
    return found.group(1)


@pytest.mark.parametrize("env", ["cartpole", "pendulum"])
def test_the_policy_pages_snippets_run_as_written(runs, env):
    run = runs / env
    code = "\n".join(page_snippet(name).replace("RUN_DIR", str(run)) for name in ("load-policy", "load-policy-standalone"))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=runs)
    assert proc.returncode == 0, proc.stderr[-3000:]
    episode_return, onnx_shape, pt2 = proc.stdout.strip().splitlines()[-3:]

    policy, info = load_policy(run / "policy")  # the same episode, here
    gym_env = gymnasium.make(info["env_recipe"]["gymnasium_id"])
    obs, _ = gym_env.reset(seed=0)
    expected, done = 0.0, False
    while not done:
        obs, reward, terminated, truncated, _ = gym_env.step(policy(obs))
        expected, done = expected + reward, terminated or truncated
    assert float(episode_return) == pytest.approx(expected)
    shape = "(5,)" if env == "cartpole" else "(5, 1)"
    assert onnx_shape == shape and pt2 == f"{shape} False"
