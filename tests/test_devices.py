"""Splitting the CPU into devices: the XLA flag, the devices a grid uses, and the CLI's --cpu-devices."""
import json
import os
import re
import subprocess
import sys
from typing import NamedTuple

import jax
import numpy as np
import pytest

from ccp_jax import devices, load_policy, train
from ccp_jax.config import ConfigError, make_config


def test_cpu_device_flags_adds_a_count_and_keeps_the_users():
    assert devices.cpu_device_flags("", 2) == "--xla_force_host_platform_device_count=2"
    assert devices.cpu_device_flags("--a=1", 3) == "--a=1 --xla_force_host_platform_device_count=3"
    mine = "--xla_force_host_platform_device_count=5 --b"
    assert devices.cpu_device_flags(mine, 2) == mine


class Fake(NamedTuple):
    platform: str
    id: int


def fake(platform: str, n: int) -> list:
    return [Fake(platform, i) for i in range(n)]


@pytest.mark.parametrize("grid, used", [(1, 1), (2, 2), (3, 3), (4, 2), (5, 2), (6, 2), (12, 2)])
def test_a_cpu_grid_uses_the_device_count_that_wastes_least(grid, used):
    """Cost of d devices on 2 cores = ceil(grid / d) · d / min(d, 2), fewer on a tie: 3 members take 3 devices
    (cost 1.5; 2 devices cost 2, a padded copy), 4 take 2 (cost 2, as 4 devices), one run takes one."""
    four = fake("cpu", 4)
    assert devices.grid_devices(grid, four, cores=2) == four[:used]


def test_a_cpu_grid_on_more_cores():
    eight = fake("cpu", 8)
    assert devices.grid_devices(6, eight, cores=4) == eight[:6]  # cost 1.5, against 2 on 3 or 4 devices
    assert devices.grid_devices(16, eight, cores=4) == eight[:4]  # cost 4 from 4 devices on


@pytest.mark.parametrize("grid, used", [(1, 1), (2, 2), (3, 3), (4, 4), (5, 3), (6, 3), (7, 4), (8, 4), (9, 3)])
def test_an_accelerator_grid_uses_the_fewest_devices_with_the_same_share(grid, used):
    """Share per device = ceil(grid / 4); devices = ceil(grid / share): 5 members take 2 + 2 + 1, not 2 + 1 + 1 + 1."""
    four = fake("gpu", 4)
    assert devices.grid_devices(grid, four) == four[:used]


@pytest.mark.parametrize("cores, grid, count", [(2, 1, 1), (2, 2, 2), (2, 3, 3), (2, 4, 2), (2, 6, 2), (2, 12, 2),
                                               (2, 18, 2), (4, 6, 6), (4, 16, 4), (1, 5, 1)])
def test_auto_exposes_the_devices_the_grid_uses(cores, grid, count):
    """"auto" splits the CPU into exactly the devices `grid_devices` will pick, so none sits idle (an idle one
    slowed the others: ccp_jax.devices.split_host_cpu)."""
    assert devices.cpu_devices_for(grid, cores) == count
    offered = fake("cpu", count)
    assert devices.grid_devices(grid, offered, cores=cores) == offered  # picked from the split: all of it
    assert devices.grid_devices(grid, fake("cpu", 2 * cores), cores=cores) == fake("cpu", count)  # = from 2 x cores


def test_cli_splits_the_cpu_for_the_grid_it_was_asked_for(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(train, "split_host_cpu", lambda devices, grid_size: calls.append((devices, grid_size)))
    for argv, planned in ((["--eta", "0.1", "0.5", "auto", "--seeds", "5"], 15), (["--eta-per-agent", "0.1,1"], 1),
                          ([], 1), (["--seeds", "3", "--cpu-devices", "2"], 3), (["--resume", str(tmp_path)], None)):
        with pytest.raises(ConfigError, match="^checkpoint_every"):  # stops right after the split
            train.main(argv + ["--checkpoint-every", "-1"])
        assert calls.pop() == (2 if "--cpu-devices" in argv else "auto", planned)
    (tmp_path / "config.json").write_text(json.dumps(make_config("tiny", seeds=(0, 1), etas=((0.1,), (0.9,))).to_dict()))
    assert train.planned_grid_size(train.Args(resume=tmp_path)) == 4  # a resume: the saved grid's size


def test_split_host_cpu_changes_nothing_once_jax_runs(monkeypatch):
    jax.devices()  # starts the backends
    monkeypatch.setenv("XLA_FLAGS", "--x")
    assert devices.split_host_cpu(2) is False
    assert os.environ["XLA_FLAGS"] == "--x"


def test_cli_trains_a_grid_on_two_cpu_devices(tmp_path):
    """3 members on 2 devices: padded to 4 (2 each), the padding's results dropped."""
    flags = re.sub(r"--xla_force_host_platform_device_count=\d+", "", os.environ.get("XLA_FLAGS", ""))
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "ccp_jax.train", "--preset", "tiny", "--seeds", "3", "--cpu-devices",
                           "2", "--out", str(out), "--no-progress", "--no-tensorboard"],
                          env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "on 2 cpu devices" in done.stdout  # 2 exposed: 3 members cost 2 there, 3 on one
    summary = json.loads((out / "summary.json").read_text())
    assert [m["seed"] for m in summary["members"]] == [0, 1, 2]
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert {r["member"] for r in rows} == {0, 1, 2}
    # Its checkpoint holds 4 slots; on one device the 3 members resume unpadded, from the checkpoint's state.
    done = subprocess.run([sys.executable, "-m", "ccp_jax.train", "--resume", str(out), "--total-steps", "800",
                           "--cpu-devices", "1", "--no-progress", "--no-tensorboard"],
                          env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Resuming 3 run(s)" in done.stdout and "on 1 cpu device " in done.stdout
    resumed = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert resumed[: len(rows)] == rows
    assert [(r["epoch"], r["env_steps"]) for r in resumed if r["member"] == 2] == [(e, 200 * e) for e in (1, 2, 3, 4)]
    assert json.loads((out / "summary.json").read_text())["devices"] == "1 cpu"
    policy = load_policy(out, member=2)  # this process has one device: the policy loads from 4 slots as well
    assert policy(np.zeros((5, 24), np.float32), np.zeros(5, np.int32)).shape == (5, 2)
