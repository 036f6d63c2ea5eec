"""Acting in the environment: data collection with auto-reset, and evaluation.

Each env acts with the policy of its current stage, π_{U(s)} (or the single
agent for end-to-end SAC); every agent's actor runs on the whole env batch and
the stage picks the row, which is cheaper than gathering parameters per env.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State, Wrapper

from ccp_jax.buffer import ReplayBuffer, Transition, add
from ccp_jax.config import Config
from ccp_jax.networks import Actor, deterministic_action, sample_action


class EpisodeStats(NamedTuple):
    """Training episodes that ended during a collection: counts summed over the epoch."""

    episodes: jax.Array  # float32[]
    successes: jax.Array  # float32[]
    stages: jax.Array  # float32[N]: of which reached stage n (see `stage_counts`)


class TracedOnce(Wrapper):
    """`env` whose `reset` and `step` JAX traces once per argument shapes, however many places call them.

    Each is a `jax.jit` of the env's own, whose traced jaxpr JAX keeps and reuses, also under `vmap`
    (it traces at the unbatched shapes). A run's programs call `reset` in init, auto-reset and
    evaluation and `step` in collection and evaluation (TP's: in init, rollouts and evaluation);
    `make_train` and `make_tp_train` wrap their env in it. An MJX env's are slow to trace (peg: ≈ 3 s
    each alone, ≈ 8 s under `vmap`). XLA inlines the calls: on one device results are bit for bit those of the
    unwrapped env; under several devices' shard_map they differ by float rounding.
    """

    def __init__(self, env: Env):
        super().__init__(env)
        self._reset, self._step = jax.jit(env.reset), jax.jit(env.step)

    def reset(self, rng: jax.Array) -> State:
        return self._reset(rng)

    def step(self, state: State, action: jax.Array) -> State:
        return self._step(state, action)


def per_episode(count: jax.Array, episodes: jax.Array) -> jax.Array:
    """A count over ended training episodes as a fraction of them (0 when none ended)."""
    return count / jnp.maximum(episodes, 1.0)


def stage_counts(done: jax.Array, stage: jax.Array, num_stages: int) -> jax.Array:
    """float32[N]: how many of the episodes that ended (done [E]) reached each stage (final stage int32[E]).

    The stochastic training episodes' counterpart of `EvalMetrics.stage_fraction`: a first agent can
    hand over while acting with noise and yet stall under its deterministic mean.
    """
    reached = stage[:, None] >= jnp.arange(num_stages)[None, :]
    return ((done > 0)[:, None] & reached).sum(0).astype(jnp.float32)


def agent_of(config: Config, stage: jax.Array) -> jax.Array:
    """The acting agent for a stage: the stage itself, or 0 for end-to-end SAC."""
    return jnp.zeros_like(stage) if config.num_agents == 1 else stage


def reward_channels(config: Config, rewards: jax.Array) -> jax.Array:
    """Per-agent rewards [..., R] from the env's subtask rewards [..., N]."""
    return rewards.sum(-1, keepdims=True) if config.num_agents == 1 else rewards


def completed_channels(config: Config, next_stage: jax.Array, success: jax.Array) -> jax.Array:
    """float32[..., R]: channels whose reward is 1 forever from s' on (absorbing).

    Success completes every channel (`absorbing_success`); entering stage U(s')
    completes the subtasks before it (`absorbing_stages`; the summed SAC channel
    only completes with the whole task).
    """
    done = jnp.zeros(success.shape + (config.num_agents,), bool)
    if config.ccp.absorbing_success:
        done |= success[..., None] > 0
    if config.ccp.absorbing_stages and config.num_agents > 1:
        done |= next_stage[..., None] > jnp.arange(config.num_agents)
    return done.astype(jnp.float32)


def policy_mean_and_log_std(actor: Actor, params, obs: jax.Array, agent: jax.Array):
    """The acting agent's Gaussian head for each env: obs [E, o], agent int32[E] -> [E, a] ×2."""
    mean, log_std = jax.vmap(actor.apply, in_axes=(0, None))(params, obs)  # [N, E, a]
    pick = lambda x: jnp.take_along_axis(x, agent[None, :, None], axis=0)[0]
    return pick(mean), pick(log_std)


def where_done(done: jax.Array, on_done, otherwise):
    """Per-env select between two batched pytrees (leaves [E, ...])."""
    def sel(a, b):
        return jnp.where(done.reshape(done.shape + (1,) * (a.ndim - 1)) > 0, a, b)
    return jax.tree.map(sel, on_done, otherwise)


def auto_reset(env: Env, nxt: State, key: jax.Array) -> State:
    """`nxt` [E, ...] with every env whose episode ended replaced by a fresh `env.reset`.

    Resetting is an MJX forward pass on peg; the cond skips it on the steps
    where no episode ended (under a vmapped grid it becomes a select and
    costs what an unconditional reset did).
    """
    fresh = lambda: where_done(nxt.done, jax.vmap(env.reset)(jax.random.split(key, nxt.done.shape[0])), nxt)
    return jax.lax.cond(jnp.any(nxt.done > 0), fresh, lambda: nxt)


def make_collect(config: Config, env: Env, actor: Actor) -> Callable:
    """`collect(actor_params, env_state, buffer, key, env_steps) -> (env_state, buffer, stats)`.

    Runs `config.collect_iters` vectorised steps over `config.budget.num_envs` envs;
    before `config.budget.start_steps` total env steps, actions are uniform random.
    """
    num_envs = config.budget.num_envs
    v_step = jax.vmap(env.step)

    def one_step(actor_params, carry, _):
        env_state, buffer, key, env_steps, stats = carry
        key, k_act, k_rand, k_reset = jax.random.split(key, 4)
        agent = agent_of(config, env_state.info["stage"])
        mean, log_std = policy_mean_and_log_std(actor, actor_params, env_state.obs, agent)
        policy_action, _ = sample_action(mean, log_std, k_act, config.ablations.tanh_log_prob)
        random_action = jax.random.uniform(k_rand, policy_action.shape, minval=-1.0, maxval=1.0)
        action = jnp.where(env_steps < config.budget.start_steps, random_action, policy_action)

        nxt = v_step(env_state, action)
        success = nxt.metrics["success"]
        tr = Transition(obs=env_state.obs, action=action,
                        rewards=reward_channels(config, nxt.info["rewards"]), next_obs=nxt.obs,
                        terminal=nxt.done * (1.0 - nxt.info["truncation"]),
                        completed=completed_channels(config, nxt.info["stage"], success),
                        next_stage=nxt.info["stage"])
        buffer = add(buffer, tr, agent)
        stats = EpisodeStats(stats.episodes + nxt.done.sum(), stats.successes + (nxt.done * success).sum(),
                             stats.stages + stage_counts(nxt.done, nxt.info["stage"], config.num_stages))
        env_state = auto_reset(env, nxt, k_reset)
        return (env_state, buffer, key, env_steps + num_envs, stats), None

    def collect(actor_params, env_state: State, buffer: ReplayBuffer, key: jax.Array, env_steps: jax.Array):
        zero = jnp.zeros((), jnp.float32)
        stats = EpisodeStats(zero, zero, jnp.zeros((config.num_stages,), jnp.float32))
        carry = (env_state, buffer, key, env_steps, stats)
        (env_state, buffer, _, _, stats), _ = jax.lax.scan(
            lambda c, x: one_step(actor_params, c, x), carry, None, length=config.collect_iters)
        return env_state, buffer, stats

    return collect


class EvalMetrics(NamedTuple):
    success_rate: jax.Array  # float32[]
    eval_return: jax.Array  # float32[]: mean undiscounted Σ_n r_n per episode
    stage_reached_mean: jax.Array  # float32[]: mean 0-based stage at the episode's end
    stage_fraction: jax.Array  # float32[N]: fraction of episodes that reached each stage
    episode_length: jax.Array  # float32[]
    end_metrics: dict  # {name: float32[]}: the env's other state.metrics at the episodes' end, mean over episodes


def episode_metrics(state: State, ret: jax.Array, length: jax.Array, num_stages: int) -> EvalMetrics:
    """EvalMetrics of a batch of finished episodes: their final states [E, ...], returns and lengths float32[E]."""
    stage = state.info["stage"]
    return EvalMetrics(success_rate=state.metrics["success"].mean(), eval_return=ret.mean(),
                       stage_reached_mean=stage.astype(jnp.float32).mean(),
                       stage_fraction=stage_counts(jnp.ones_like(stage), stage, num_stages) / stage.shape[0],
                       episode_length=length.mean(),
                       end_metrics={k: v.mean() for k, v in state.metrics.items() if k != "success"})


def make_evaluate(config: Config, env: Env, actor: Actor, episodes: int | None = None,
                  stochastic: bool = False) -> Callable:
    """`evaluate(actor_params, key) -> EvalMetrics` over `episodes` (default `config.budget.eval_episodes`) episodes.

    Actions are the policies' deterministic means (docs/design.md#hyperparameters), or with `stochastic` sampled as in
    training. Episodes run in parallel until all are done (or the time limit); a finished
    episode is frozen rather than reset.
    """
    episodes = config.budget.eval_episodes if episodes is None else episodes
    num_stages = config.num_stages
    v_step, v_reset = jax.vmap(env.step), jax.vmap(env.reset)

    def evaluate(actor_params, key: jax.Array) -> EvalMetrics:
        state = v_reset(jax.random.split(key, episodes))  # the deterministic evaluation's starts, as before
        key = jax.random.fold_in(key, 1)  # the stochastic actions' stream
        # Sums shaped like the state's reward, and no step counter (a live episode's length is the step):
        # a carry batched like the state, so a grid's vmap batches the body (an MJX step on peg) fewer times.
        zeros = jnp.zeros_like(state.reward)

        def cond(carry):
            state, _, length, _ = carry
            return jnp.any(state.done == 0) & (length.max() < config.task.max_episode_steps)

        def body(carry):
            state, ret, length, key = carry
            agent = agent_of(config, state.info["stage"])
            mean, log_std = policy_mean_and_log_std(actor, actor_params, state.obs, agent)
            if stochastic:
                key, k_act = jax.random.split(key)
                action, _ = sample_action(mean, log_std, k_act, config.ablations.tanh_log_prob)
            else:
                action = deterministic_action(mean)
            nxt = v_step(state, action)
            live = 1.0 - state.done
            return (where_done(state.done, state, nxt), ret + live * nxt.reward, length + live, key)

        state, ret, length, _ = jax.lax.while_loop(cond, body, (state, zeros, zeros, key))
        return episode_metrics(state, ret, length, num_stages)

    return evaluate
