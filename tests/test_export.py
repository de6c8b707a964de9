"""Tests of rlpipe.pipelines.export with a real torch.export program in tmp_path."""

from __future__ import annotations

import json
import logging
import stat

import pytest
import torch
from torch import nn

from rlpipe.pipelines.errors import InputError
from rlpipe.pipelines.export import export_policy, load_policy


@pytest.fixture
def caller_disables_info():
    """A caller that silenced INFO and below, as a test runner or an application may."""
    logging.disable(logging.INFO)
    yield logging.INFO
    logging.disable(logging.NOTSET)


def test_export_writes_both_files_atomically(tmp_path):
    torch.manual_seed(0)
    folder = tmp_path / "policy"
    export_policy(nn.Linear(3, 2), 3, folder, {"algo": "td3"})
    with (folder / "policy.json").open() as reader:
        export_policy(nn.Linear(3, 2), 3, folder, {"algo": "sac"})
        # policy.json was replaced, not truncated and rewritten under a reader
        assert json.loads(reader.read()) == {"observation_dim": 3, "algo": "td3"}
    assert json.loads((folder / "policy.json").read_text()) == {"observation_dim": 3, "algo": "sac"}
    assert sorted(p.name for p in folder.iterdir()) == ["policy.json", "policy.pt2"]
    for name in ("policy.json", "policy.pt2"):
        assert stat.S_IMODE((folder / name).stat().st_mode) == 0o644
    policy, info = load_policy(folder)
    assert info["algo"] == "sac" and policy(torch.zeros(3)).shape == (2,)


def test_load_policy_keeps_the_callers_logging_disable_level(tmp_path, caller_disables_info):
    folder = tmp_path / "policy"
    export_policy(nn.Linear(3, 2), 3, folder, {})
    load_policy(folder)
    assert logging.root.manager.disable == caller_disables_info
    (folder / "policy.pt2").write_bytes(b"PK\x03\x04 not a torch.export archive" * 10)
    with pytest.raises(InputError, match="corrupt or not an exported policy"):
        load_policy(folder)
    assert logging.root.manager.disable == caller_disables_info
