"""The joint update's wiring: cross-buffer critic terms, per-agent α and π, masking."""
import sys
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import optax
import numpy as np
import pytest

from ccp_jax import buffer as replay
from ccp_jax import losses
from ccp_jax.buffer import Transition
from ccp_jax.config import make_config
from ccp_jax.learner import init_agents, make_learner, make_networks, train_loops
from ccp_jax.networks import sample_action
from ccp_jax.devices import CPU_INIT_OPTIONS

OBS, ACT, B = 5, 2, 16


def _init_agents(nets, key, num_agents, obs_size, action_size, **kwargs):
    """`init_agents` compiled as the trainer's init is (LLVM O1: the same bits, seconds instead of eager's tens)."""
    init = jax.jit(lambda k: init_agents(nets, k, num_agents, obs_size, action_size, **kwargs),
                   compiler_options=CPU_INIT_OPTIONS)
    return init(key)


def _setup(algo):
    config = make_config("tiny", algo=algo, rooms=2)
    nets = make_networks(config, ACT)
    agents = _init_agents(nets, jax.random.PRNGKey(0), 2, OBS, ACT)
    # Targets apart from the critics and distinct temperatures, so a wrong wiring shows.
    noisy = jax.tree.map(lambda x: x + 0.3 * jax.random.normal(jax.random.PRNGKey(1), x.shape), agents.critic)
    agents = agents.replace(target_critic=noisy, log_alpha=jnp.log(jnp.array([0.5, 2.0])))
    k = jax.random.split(jax.random.PRNGKey(2), 5)
    batch = Transition(obs=jax.random.normal(k[0], (2, B, OBS)), action=jax.random.uniform(k[1], (2, B, ACT), minval=-1),
                       rewards=jax.random.uniform(k[2], (2, B, 2)), next_obs=jax.random.normal(k[3], (2, B, OBS)),
                       terminal=(jax.random.uniform(k[4], (2, B)) < 0.2).astype(jnp.float32),
                       completed=jnp.zeros((2, B, 2)).at[:, :3, 0].set(1.0),
                       next_stage=jnp.zeros((2, B), jnp.int32).at[0, :3].set(1).at[1].set(1))
    return config, nets, agents, batch, jax.jit(make_learner(config, nets, ACT).update)


def _agent(tree, n):
    return jax.tree.map(lambda x: x[n], tree)


@pytest.fixture(scope="module")
def csac():
    return _setup("csac")


def test_critic_terms_use_pi_n_and_alpha_n_for_both_critics(csac):
    config, nets, agents, batch, update = csac
    key = jax.random.PRNGKey(3)
    _, metrics = update(agents, batch, jnp.array([0.3, 1.0]), jnp.array([True, True]), key)
    k_next = jax.random.split(key, (2, 2))[0, 0]
    b0 = jax.tree.map(lambda x: x[0], batch)
    mean, log_std = nets.actor.apply(_agent(agents.actor, 0), b0.next_obs)
    a_next, logp_next = sample_action(mean, log_std, k_next, config.ablations.tanh_log_prob)
    alpha0 = 0.5
    expected = 0.0
    for j in (0, 1):  # j = n and j = n + 1, both with π_0's next action and α_0
        q_next = jnp.min(nets.critic.apply(_agent(agents.target_critic, j), b0.next_obs, a_next), 0)
        y = losses.soft_target(b0.rewards[:, j], q_next, logp_next, alpha0, b0.terminal, b0.completed[:, j],
                               config.sac.gamma, 1.0 / (1.0 - config.sac.gamma))
        expected += losses.twin_q_loss(nets.critic.apply(_agent(agents.critic, j), b0.obs, b0.action), y)
    assert float(metrics.q_loss[0]) == pytest.approx(float(expected), rel=1e-4)
    np.testing.assert_allclose(metrics.alpha, [0.5, 2.0], rtol=1e-6)
    assert float(metrics.eta_star[1]) == 1.0 and 0.0 <= float(metrics.eta_star[0]) <= 1.0


def test_acting_rule_bootstraps_with_the_successor_where_s_next_entered_its_stage(csac):
    config, nets, agents, batch, paper_update = csac
    config = config.replace(next_action="acting")
    update = jax.jit(make_learner(config, nets, ACT).update)
    key = jax.random.PRNGKey(3)
    _, metrics = update(agents, batch, jnp.array([0.3, 1.0]), jnp.array([True, True]), key)
    k_next = jax.random.split(key, (2, 2))[0, 0]
    b0 = jax.tree.map(lambda x: x[0], batch)
    own = sample_action(*nets.actor.apply(_agent(agents.actor, 0), b0.next_obs), k_next, config.ablations.tanh_log_prob)
    succ = sample_action(*nets.actor.apply(_agent(agents.actor, 1), b0.next_obs), jax.random.fold_in(k_next, 1),
                         config.ablations.tanh_log_prob)
    crossed = b0.next_stage > 0  # the first 3 transitions of agent 0's batch entered stage 1
    assert crossed.sum() == 3
    a_next = jnp.where(crossed[:, None], succ[0], own[0])
    logp_next = jnp.where(crossed, succ[1], own[1])
    alpha = jnp.where(crossed, 2.0, 0.5)  # α_1 where π_1 acts at s'
    expected = 0.0
    for j in (0, 1):
        q_next = jnp.min(nets.critic.apply(_agent(agents.target_critic, j), b0.next_obs, a_next), 0)
        y = losses.soft_target(b0.rewards[:, j], q_next, logp_next, alpha, b0.terminal, b0.completed[:, j],
                               config.sac.gamma, 1.0 / (1.0 - config.sac.gamma))
        expected += losses.twin_q_loss(nets.critic.apply(_agent(agents.critic, j), b0.obs, b0.action), y)
    assert float(metrics.q_loss[0]) == pytest.approx(float(expected), rel=1e-4)
    # The paper's rule gives a different loss on the same batch.
    _, paper = paper_update(agents, batch, jnp.array([0.3, 1.0]), jnp.array([True, True]), key)
    assert abs(float(paper.q_loss[0]) - float(expected)) > 1e-3 * float(expected)


def _changed(old, new, n):
    return any(not np.array_equal(a[n], b[n]) for a, b in zip(jax.tree.leaves(old), jax.tree.leaves(new)))


def test_under_filled_agent_is_masked_but_its_critic_gets_the_cross_term(csac):
    _, _, agents, batch, update = csac
    new, metrics = update(agents, batch, jnp.array([0.3, 1.0]), jnp.array([True, False]), jax.random.PRNGKey(4))
    assert _changed(agents.actor, new.actor, 0) and not _changed(agents.actor, new.actor, 1)
    assert float(new.log_alpha[1]) == float(agents.log_alpha[1]) and float(new.log_alpha[0]) != float(agents.log_alpha[0])
    assert not _changed(agents.actor_opt, new.actor_opt, 1)
    assert _changed(agents.critic, new.critic, 1)  # agent 0's batch trains critic 1 (Algorithm 2)
    np.testing.assert_array_equal(metrics.updated, [1.0, 0.0])


def test_naive_agents_do_not_touch_the_next_critic():
    _, _, agents, batch, update = _setup("naive")
    new, _ = update(agents, batch, jnp.array([0.3, 1.0]), jnp.array([True, False]), jax.random.PRNGKey(4))
    assert _changed(agents.critic, new.critic, 0) and not _changed(agents.critic, new.critic, 1)


def test_eta_one_is_plain_sac_on_normalised_own_critic_only(csac):
    """With η = 1 the next critic cannot influence agent 0's actor step."""
    _, _, agents, batch, update = csac
    key, ready = jax.random.PRNGKey(5), jnp.array([True, True])
    new_a, _ = update(agents, batch, jnp.array([1.0, 1.0]), ready, key)
    shuffled = agents.replace(critic=jax.tree.map(lambda x: x.at[1].set(-x[1]), agents.critic))
    new_b, _ = update(shuffled, batch, jnp.array([1.0, 1.0]), ready, key)
    for a, b in zip(jax.tree.leaves(new_a.actor), jax.tree.leaves(new_b.actor)):
        np.testing.assert_allclose(a[0], b[0], rtol=1e-5, atol=1e-7)
    new_c, _ = update(shuffled, batch, jnp.array([0.0, 1.0]), ready, key)
    assert _changed(new_a.actor, new_c.actor, 0)


@pytest.mark.parametrize("normaliser", ["batch", "floor"])
def test_own_scale_eta_one_is_naive_for_the_first_agent(csac, normaliser):
    """--coop-scale own: C_n in Q_n's units, so at η = 1 agent 0's whole update (actor, critic, α) is Naive's."""
    config, nets, agents, batch, _ = csac
    # Critics with a batch range far from 1, so the paper's Q̂ and Naive's Q differ in scale ...
    widen = lambda t: jax.tree_util.tree_map_with_path(
        lambda path, x: 30.0 * x if "Dense_2" in jax.tree_util.keystr(path) else x, t)
    agents = agents.replace(critic=widen(agents.critic), target_critic=widen(agents.target_critic))
    # ... and plain gradient steps: Adam's first step is ≈ lr · sign(g) and would hide that scale.
    sgd = optax.sgd(1e-3)
    nets = nets._replace(actor_tx=sgd, critic_tx=sgd, alpha_tx=sgd)
    agents = agents.replace(actor_opt=jax.vmap(sgd.init)(agents.actor), critic_opt=jax.vmap(sgd.init)(agents.critic),
                            alpha_opt=jax.vmap(sgd.init)(agents.log_alpha))
    naive_update, paper_update, own_update = (
        jax.jit(make_learner(c, nets, ACT).update)
        for c in (config.replace(algo="naive"), config.replace(normaliser=normaliser, norm_floor=1e-3),
                  config.replace(coop_scale="own", normaliser=normaliser, norm_floor=1e-3)))
    args = (agents, batch, jnp.array([1.0, 1.0]), jnp.array([True, True]), jax.random.PRNGKey(5))
    naive, mine, paper = naive_update(*args)[0], own_update(*args)[0], paper_update(*args)[0]
    for part in ("actor", "critic", "log_alpha"):
        for a, b in zip(jax.tree.leaves(getattr(naive, part)), jax.tree.leaves(getattr(mine, part))):
            np.testing.assert_allclose(a[0], b[0], rtol=1e-5, atol=1e-7, err_msg=part)
    # The paper's units weigh α log π against Q̂ ∈ [0, 1] instead: a clearly different actor step.
    gap = max(float(jnp.max(jnp.abs(a[0] - b[0]))) for a, b in zip(jax.tree.leaves(naive.actor), jax.tree.leaves(paper.actor)))
    assert gap > 1e-4


def _setup_norm(normaliser, flatness=1.0, eta=0.5):
    config, nets, agents, batch, _ = _setup("csac")
    config = config.replace(normaliser=normaliser, norm_floor=1.0, norm_ema_rate=0.1)
    learner = make_learner(config, nets, ACT)
    # Scale the next critic's output layer: flatness → 0 makes Q_1 nearly constant.
    def flatten(path, x):
        last = "Dense_2" in jax.tree_util.keystr(path)
        return x.at[1].multiply(flatness) if last else x
    agents = agents.replace(critic=jax.tree_util.tree_map_with_path(flatten, agents.critic))
    return config, nets, agents, batch, learner, jnp.array([eta, 1.0])


def test_running_bounds_and_auto_eta_against_hand_values():
    config, nets, agents, batch, learner, _ = _setup_norm("ema")
    agents = agents.replace(norm=agents.norm.replace(lo=jnp.zeros((2, 2)), hi=jnp.full((2, 2), 20.0)))
    key = jax.random.PRNGKey(7)
    new, metrics = jax.jit(learner.update)(agents, batch, jnp.array([jnp.nan, 1.0]), jnp.array([True, True]), key)
    k_pi = jax.random.split(key, (2, 2))[0, 1]
    b0 = jax.tree.map(lambda x: x[0], batch)
    mean, log_std = nets.actor.apply(_agent(agents.actor, 0), b0.obs)
    act, _ = sample_action(mean, log_std, k_pi, config.ablations.tanh_log_prob)
    q = [jnp.min(nets.critic.apply(_agent(agents.critic, j), b0.obs, act), 0) for j in (0, 1)]
    lo = np.array([0.1 * float(x.min()) for x in q])  # 0 + 0.1 (min − 0)
    hi = np.array([20.0 + 0.1 * (float(x.max()) - 20.0) for x in q])
    np.testing.assert_allclose(new.norm.lo[0], lo, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(new.norm.hi[0], hi, rtol=1e-4)
    ranges = hi - lo
    assert float(metrics.eta_used[0]) == pytest.approx(np.clip(ranges[0] / ranges.sum(), 0.05, 0.95), rel=1e-4)
    assert float(metrics.range_own[0]) == pytest.approx(ranges[0], rel=1e-4)
    # Agent 1 has no next critic and keeps η = 1.
    assert float(metrics.eta_used[1]) == 1.0
    # κ = 4 (--eta-auto-next-weight): the next critic's range counts four times; the logged η* stays the appendix's.
    weighted = make_learner(config.replace(eta_auto_next_weight=4.0), nets, ACT)
    _, w_metrics = jax.jit(weighted.update)(agents, batch, jnp.array([jnp.nan, 1.0]), jnp.array([True, True]), key)
    assert float(w_metrics.eta_used[0]) == pytest.approx(np.clip(ranges[0] / (ranges[0] + 4 * ranges[1]), 0.05, 0.95),
                                                         rel=1e-4)
    assert float(w_metrics.eta_used[0]) < float(metrics.eta_used[0])
    np.testing.assert_allclose(w_metrics.eta_star, metrics.eta_star, rtol=1e-6)


@pytest.mark.parametrize("coop_scale", ["unit", "own"])
def test_no_normaliser_is_the_sac_actor_loss_on_the_cooperative_reward(coop_scale):
    """--normaliser none: agent 0 minimises mean(α_0 log π − η Q_0 − (1 − η) Q_1) on raw critics, in either units."""
    config, nets, agents, batch, _, eta = _setup_norm("none", eta=0.3)
    learner = make_learner(config.replace(coop_scale=coop_scale), nets, ACT)
    key = jax.random.PRNGKey(7)
    _, metrics = jax.jit(learner.update)(agents, batch, eta, jnp.array([True, True]), key)
    b0 = jax.tree.map(lambda x: x[0], batch)
    mean, log_std = nets.actor.apply(_agent(agents.actor, 0), b0.obs)
    act, logp = sample_action(mean, log_std, jax.random.split(key, (2, 2))[0, 1], config.ablations.tanh_log_prob)
    q = [jnp.min(nets.critic.apply(_agent(agents.critic, j), b0.obs, act), 0) for j in (0, 1)]
    alpha = float(jnp.exp(agents.log_alpha[0]))
    hand = float(jnp.mean(alpha * logp - 0.3 * q[0] - 0.7 * q[1]))
    assert float(metrics.pi_loss[0]) == pytest.approx(hand, rel=1e-5)
    assert float(metrics.range_own[0]) == float(metrics.range_next[0]) == 1.0  # nothing divided


@pytest.mark.parametrize("normaliser, shrinks", [("batch", False), ("ema", True), ("floor", True), ("none", True)])
def test_flat_next_critic_pull(normaliser, shrinks):
    """As the next critic flattens 10^4-fold, its pull on the actions should shrink with it;
    the paper's batch normaliser instead rescales the remaining noise to full size."""
    pulls = []
    for flatness in (1.0, 1e-4):
        _, _, agents, batch, learner, eta = _setup_norm(normaliser, flatness)
        pulls.append(float(jax.jit(learner.action_pulls)(agents, batch, eta, jax.random.PRNGKey(8))[1][0]))
    ratio = pulls[1] / pulls[0]
    if shrinks:
        assert ratio < 1e-3, pulls
    else:
        assert ratio > 0.1, pulls


def test_tanh_log_prob_forms_against_hand_values():
    """Both forms agree inside (-1, 1); at saturation RLkit's ε caps the correction at log 1e-6, the exact one grows 2|u|."""
    key = jax.random.PRNGKey(0)
    log_std = jnp.full((1, 1), -20.0)  # u = mean to float precision
    gauss = 0.5 * np.log(2 * np.pi) - 20.0  # −log N(u; u, e^-20)
    for form in ("rlkit", "exact"):
        a, logp = sample_action(jnp.full((1, 1), 0.5), log_std, key, form)
        expected = -gauss - np.log(1 - np.tanh(0.5) ** 2)
        assert float(a[0, 0]) == pytest.approx(np.tanh(0.5))
        assert float(logp[0]) == pytest.approx(expected, abs=1e-3 if form == "rlkit" else 1e-5)
    _, rlkit = sample_action(jnp.full((1, 1), 10.0), log_std, key, "rlkit")
    _, exact = sample_action(jnp.full((1, 1), 10.0), log_std, key, "exact")
    assert float(rlkit[0]) == pytest.approx(-gauss - np.log(1e-6), abs=1e-3)  # tanh(10) == 1 in float32
    assert float(exact[0]) == pytest.approx(-gauss - 2 * (np.log(2) - 10.0), abs=1e-3)


def test_target_entropy_sets_which_way_alpha_moves(csac):
    """α's gradient is −mean(log π + target): above an entropy target that is out of reach α rises, below −|A| it falls."""
    config, nets, agents, batch, _ = csac
    eta, ready, key = jnp.array([0.3, 1.0]), jnp.array([True, True]), jax.random.PRNGKey(3)
    moved = {}
    for target in (None, -50.0, 50.0):
        update = jax.jit(make_learner(config.replace(target_entropy=target), nets, ACT).update)
        new, metrics = update(agents, batch, eta, ready, key)
        moved[target] = np.sign(np.asarray(new.log_alpha - agents.log_alpha))
        entropy = -np.asarray(metrics.log_prob)
    assert np.all(moved[-50.0] == -1) and np.all(moved[50.0] == 1)
    # The default is −|A| = −2: α falls for agents whose batch entropy is above it.
    np.testing.assert_array_equal(moved[None], np.where(entropy > -ACT, -1, 1))


def test_rlkit_network_init_bounds_each_layer_and_starts_every_output_near_zero():
    """RLkit's init: hidden kernels U(±1/√out) (its fanin_init reads the torch weight's first dimension),
    last kernels U(±1e-3) (actor) and U(±3e-3) (critic), biases 0; flax's lecun-normal otherwise."""
    obs = jax.random.uniform(jax.random.PRNGKey(1), (512, 24))
    act = jax.random.uniform(jax.random.PRNGKey(2), (512, 2), minval=-1, maxval=1)
    spread = {}
    for scheme in ("flax", "rlkit"):
        nets = make_networks(make_config("small", network_init=scheme), action_size=2)
        agents = _init_agents(nets, jax.random.PRNGKey(0), 2, obs_size=24, action_size=2)
        actor = jax.tree.map(lambda x: x[0], agents.actor)["params"]["MLP_0"]
        critic = jax.tree.map(lambda x: x[0], agents.critic)["params"]["VmapMLP_0"]
        kernels = [actor[f"Dense_{i}"]["kernel"] for i in range(3)] + [critic[f"Dense_{i}"]["kernel"] for i in range(3)]
        assert [k.shape[-2:] for k in kernels] == [(24, 64), (64, 64), (64, 4), (26, 64), (64, 64), (64, 1)]
        mean, log_std = nets.actor.apply(jax.tree.map(lambda x: x[0], agents.actor), obs)
        q = nets.critic.apply(jax.tree.map(lambda x: x[0], agents.critic), obs, act)
        spread[scheme] = max(float(jnp.abs(x).max()) for x in (mean, log_std, q))
        if scheme == "rlkit":
            for k, bound in zip(kernels, [1 / 8, 1 / 8, 1e-3, 1 / 8, 1 / 8, 3e-3]):
                assert float(jnp.abs(k).max()) <= bound
                np.testing.assert_allclose(float(jnp.std(k)), bound / np.sqrt(3), rtol=0.2)  # uniform, not a corner
            assert spread[scheme] < 0.01
        else:  # lecun normal: std 1/√fan_in
            np.testing.assert_allclose(float(jnp.std(kernels[3])), 1 / np.sqrt(26), rtol=0.15)
    assert spread["flax"] > 0.1  # flax's outputs start state-dependent, RLkit's do not


def test_initial_alpha_sets_every_temperature_before_training():
    config = make_config("tiny", rooms=2)
    nets = make_networks(config, ACT)
    for alpha in (1.0, 0.05):
        agents = _init_agents(nets, jax.random.PRNGKey(0), 2, OBS, ACT, initial_alpha=alpha)
        np.testing.assert_allclose(np.exp(np.asarray(agents.log_alpha)), [alpha, alpha], rtol=1e-6)


@pytest.mark.parametrize("next_action", ["own", "acting"])
def test_draws_hoisted_out_of_a_loop_are_the_draws_inside_it(csac, next_action):
    """The trainer draws every loop's batch indices and noise at once (vmapped over the loop's keys):
    they must be, bit for bit, what each loop would draw from its own key."""
    config, nets, agents, batch, _ = csac
    learner = make_learner(config.replace(next_action=next_action), nets, ACT)
    keys = jax.random.split(jax.random.PRNGKey(5), 7)
    at_once = jax.jit(jax.vmap(lambda k: learner.draw_noise(k, B)))(keys)
    chex.assert_shape([at_once.next, at_once.pi], (7, 2, B, ACT))
    chex.assert_shape(at_once.successor, (7, 1 if next_action == "acting" else 0, B, ACT))
    sizes = jnp.array([40, 3], jnp.int32)
    idx = jax.jit(jax.vmap(lambda k: replay.sample_indices(sizes, k, B)))(keys)
    for i, k in enumerate(keys):
        one = learner.draw_noise(k, B)
        for a, b in zip(at_once, one):
            np.testing.assert_array_equal(a[i], b)
        np.testing.assert_array_equal(idx[i], replay.sample_indices(sizes, k, B))
    assert int(idx[:, 1].max()) == 2 and int(idx[:, 0].max()) > 2  # agent 1 holds 3 transitions
    # The first agent's own and successor draws differ (fold_in), and `update` is `update_with_noise` of its key's draws.
    if next_action == "acting":
        assert not np.array_equal(at_once.next[:, 0], at_once.successor[:, 0])
    eta, ready = jnp.array([0.3, 1.0]), jnp.array([True, True])
    by_key = jax.jit(learner.update)(agents, batch, eta, ready, keys[0])
    by_noise = jax.jit(learner.update_with_noise)(agents, batch, eta, ready, learner.draw_noise(keys[0], B))
    for a, b in zip(jax.tree.leaves(by_key), jax.tree.leaves(by_noise)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)


def test_critic_first_layer_is_a_dense_layer_on_obs_and_action_together():
    """`ConcatDense` keeps nn.Dense's parameters of the concatenated input (checkpoints are unchanged) and
    computes that layer product by product: same values, and ∂Q/∂a the action rows of ∂Q/∂[s, a]."""
    nets = make_networks(make_config("small"), action_size=2)
    obs = jax.random.normal(jax.random.PRNGKey(1), (9, 24))
    act = jax.random.uniform(jax.random.PRNGKey(2), (9, 2), minval=-1, maxval=1)
    params = nets.critic.init(jax.random.PRNGKey(0), obs, act)
    layers = params["params"]["VmapMLP_0"]
    assert sorted(layers) == ["Dense_0", "Dense_1", "Dense_2"]
    chex.assert_shape([layers["Dense_0"]["kernel"], layers["Dense_0"]["bias"]], [(2, 26, 64), (2, 64)])

    def by_hand(x):  # [9, 26] -> [2, 9]
        h = x
        for i in range(3):
            w, b = layers[f"Dense_{i}"]["kernel"], layers[f"Dense_{i}"]["bias"]
            h = jnp.einsum("bi,tio->tbo" if i == 0 else "tbi,tio->tbo", h, w) + b[:, None]
            h = jax.nn.relu(h) if i < 2 else h[..., 0]
        return h

    x = jnp.concatenate([obs, act], -1)
    np.testing.assert_allclose(nets.critic.apply(params, obs, act), by_hand(x), rtol=1e-5, atol=1e-6)
    d_act = jax.grad(lambda a: nets.critic.apply(params, obs, a).sum())(act)
    d_x = jax.grad(lambda x: by_hand(x).sum())(x)
    np.testing.assert_allclose(d_act, d_x[:, 24:], rtol=1e-5, atol=1e-6)


def test_train_loops_are_updates_on_the_batches_drawn_for_them(csac):
    """`train_loops` gathers loop i + 1's batch during loop i: the result must be that of the loop
    where each update gathers its own batch first (same draws), up to XLA's float rounding (≈ 1e-10 here)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments" / "bench"))
    from epoch_versions import gather_before_each_update
    from update_speed import full_of_noise

    config, nets, agents, _, _ = csac
    learner = make_learner(config, nets, ACT)
    empty = replay.init_buffer(replay.zero_transition(OBS, ACT, 2), 2, 64)
    buffer = full_of_noise(empty, jax.random.PRNGKey(7)).replace(size=jnp.array([64, 20], jnp.int32))
    eta, ready, key, loops = jnp.array([0.3, 1.0]), jnp.array([True, True]), jax.random.PRNGKey(8), 4
    run = lambda loops_fn: jax.jit(lambda a: loops_fn(learner, a, buffer, eta, ready, key, loops, B))(agents)
    got, metrics = run(train_loops)
    chex.assert_shape(metrics.q_loss, (loops, 2))
    chex.assert_trees_all_close(got, run(gather_before_each_update)[0], rtol=1e-5, atol=1e-8)
