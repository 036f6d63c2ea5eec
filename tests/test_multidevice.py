"""The grid axis sharded over 4 (simulated CPU) devices gives the single-device results."""
import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import jax, numpy as np
    from ccp_jax.config import make_config
    from ccp_jax.envs import make_env
    from ccp_jax.grid import make_grid_train
    assert jax.device_count() == 4, jax.devices()
    config = make_config("tiny", etas=((0.1,), (0.9,), (0.5,)), seeds=(0, 1))  # 6 members: padded to 8
    eta, seed = config.grid_arrays()
    results = []
    # One device; four, one member at a time each (the CPU default); four, their two members vmapped.
    for devices, at_once in ((jax.devices()[:1], None), (jax.devices(), None), (jax.devices(), 2)):
        trainer = make_grid_train(config, make_env(config), devices, members_at_once=at_once)
        state = trainer.init(seed)
        assert state.env_steps.shape == (trainer.padded_size,)
        for _ in range(2):
            state, metrics = trainer.train_step(state, eta)
        assert metrics.env_steps.shape == (6,)
        if len(devices) == 4:
            assert len(state.agents.log_alpha.sharding.device_set) == 4
        results.append(jax.device_get((state.agents, metrics.train.q_loss)))
    for other in results[1:]:
        for a, b in zip(jax.tree.leaves(results[0][0]), jax.tree.leaves(other[0])):
            np.testing.assert_allclose(a[:6], b[:6], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(results[0][1], other[1], rtol=1e-5)
    print("EQUAL")
""")


def _on_four_devices(script: str) -> None:
    """Runs `script` in a process whose CPU is split into 4 devices; it prints EQUAL when its comparison held."""
    env = dict(os.environ, XLA_FLAGS=os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4",
               JAX_PLATFORMS="cpu")
    result = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "EQUAL" in result.stdout


def test_four_devices_equal_one():
    _on_four_devices(SCRIPT)


PBT_SCRIPT = textwrap.dedent("""
    import jax, numpy as np
    from ccp_jax.config import make_config
    from ccp_jax.envs import make_env
    from ccp_jax.grid import make_grid_train
    assert jax.device_count() == 4, jax.devices()
    # 6 members padded to 8; a ranking after every epoch replaces one (⌊0.25 × 6⌋).
    config = make_config("tiny", etas=((0.1,), (0.9,), (0.5,)), seeds=(0, 1), pbt_every=1, total_steps=600)
    eta, seed = config.grid_arrays()
    results = []
    for devices in (jax.devices()[:1], jax.devices()):
        trainer = make_grid_train(config, make_env(config), devices)
        state = trainer.init(seed)
        records = []
        for _ in range(3):
            state, metrics = trainer.train_step(state, eta)
            records.append(jax.device_get(metrics.pbt))
        if len(devices) == 4:
            assert len(state.pbt.eta.sharding.device_set) == 4
        results.append((jax.device_get(state), records))
    (one, one_records), (four, four_records) = results
    copies = 0
    for a, b in zip(one_records, four_records):
        np.testing.assert_array_equal(a.parent, b.parent)  # the same copies, across devices
        assert a.parent.max() < 6  # padding is never a donor
        copies += (a.parent >= 0).sum()
        np.testing.assert_allclose(a.eta, b.eta, rtol=1e-6)
        np.testing.assert_array_equal(a.fitness, b.fitness)
    assert copies >= 1, "no member was copied: the comparison says nothing about the gather"
    for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(four)):
        np.testing.assert_allclose(a[:6], b[:6], rtol=1e-5, atol=1e-6)
    print("EQUAL")
""")


def test_pbt_on_four_devices_copies_as_on_one():
    _on_four_devices(PBT_SCRIPT)
