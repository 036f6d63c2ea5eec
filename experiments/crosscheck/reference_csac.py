"""An independent, deliberately plain CSAC, to cross-check ccp_jax's trainer.

Written from docs/design.md#the-method and the paper's Algorithms 1–2 without importing
ccp_jax: a Python loop over agents, one flax MLP per network, lists of
per-agent dicts, one replay buffer per agent, one environment per run. It
shares only the environment (envs_mjx). Two uses:

* `tests/test_reference.py` checks that ccp_jax's joint update (stacked
  agents, critic "slots") equals `Reference.update` step for step under the
  same noise, for 2 and 3 agents, with and without absorbing stages;
* `python experiments/crosscheck/reference_csac.py --seeds 0 1 2 3 4 5`
  trains it on the 2-room yardstick (seeds vmapped), so its learning
  curve can be compared with ours (results: experiments/crosscheck/README.md).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax

from envs_mjx.maze import Maze
from envs_mjx import configure_cpu


@dataclasses.dataclass(frozen=True)
class Settings:
    """The paper's hyperparameters (docs/design.md#hyperparameters) at the yardstick's sizes."""

    etas: tuple[float, ...] = (0.1, 1.0)  # one per agent; the last agent's is unused
    hidden: tuple[int, ...] = (64, 64)
    gamma: float = 0.95
    tau: float = 0.005
    lr: float = 3e-4
    batch: int = 256
    absorbing_stages: bool = True
    tanh_log_prob: str = "rlkit"  # or "exact": see `gaussian_sample`
    capacity: int = 200_000
    steps_per_epoch: int = 5000
    loops_per_epoch: int = 1000
    start_steps: int = 1000
    episode_length: int = 1000
    eval_episodes: int = 10

    @property
    def num_agents(self) -> int:
        return len(self.etas)


class Mlp(nn.Module):
    hidden: tuple[int, ...]
    out: int

    @nn.compact
    def __call__(self, x):
        for h in self.hidden:
            x = nn.relu(nn.Dense(h)(x))
        return nn.Dense(self.out)(x)


def gaussian_sample(mean: jax.Array, log_std: jax.Array, key: jax.Array,
                    tanh_log_prob: str = "rlkit") -> tuple[jax.Array, jax.Array]:
    """Tanh-Gaussian action [..., a] and log π [...].

    The tanh correction is RLkit's log(1 − a² + 1e-6) ("rlkit") or the closed
    form log(1 − tanh(u)²) = 2 (log 2 − u − softplus(−2u)) ("exact").
    """
    std = jnp.exp(log_std)
    u = mean + std * jax.random.normal(key, mean.shape)
    a = jnp.tanh(u)
    if tanh_log_prob == "rlkit":
        correction = jnp.log(1.0 - a**2 + 1e-6)
    else:
        correction = 2.0 * (jnp.log(2.0) - u - jax.nn.softplus(-2.0 * u))
    return a, jax.scipy.stats.norm.logpdf(u, mean, std).sum(-1) - correction.sum(-1)


class Reference:
    """Networks and the update of Algorithm 2, one agent at a time.

    `sample` (mean, log_std, key) -> (action, log π) is replaceable so a test can
    feed both implementations the same noise.
    """

    def __init__(self, s: Settings, obs_size: int, action_size: int, sample: Callable | None = None):
        self.s, self.obs_size, self.action_size = s, obs_size, action_size
        self.sample = sample or (lambda mean, log_std, key: gaussian_sample(mean, log_std, key, s.tanh_log_prob))
        self.pi_net, self.q_net = Mlp(s.hidden, 2 * action_size), Mlp(s.hidden, 1)
        self.opt = optax.adam(s.lr)

    # -- networks
    def pi(self, params, obs, key):
        mean, log_std = jnp.split(self.pi_net.apply(params, obs), 2, -1)
        return self.sample(mean, jnp.clip(log_std, -20.0, 2.0), key)

    def pi_mean(self, params, obs):
        return jnp.tanh(jnp.split(self.pi_net.apply(params, obs), 2, -1)[0])

    def q(self, twin, obs, act):
        x = jnp.concatenate([obs, act], -1)
        return jnp.minimum(self.q_net.apply(twin[0], x)[..., 0], self.q_net.apply(twin[1], x)[..., 0])

    def init_agents(self, key) -> list[dict]:
        obs, x = jnp.zeros((1, self.obs_size)), jnp.zeros((1, self.obs_size + self.action_size))
        agents = []
        for k in jax.random.split(key, self.s.num_agents):
            kp, k1, k2 = jax.random.split(k, 3)
            pi, q = self.pi_net.init(kp, obs), (self.q_net.init(k1, x), self.q_net.init(k2, x))
            la = jnp.zeros(())
            agents.append(dict(pi=pi, q=q, q_target=q, log_alpha=la, pi_opt=self.opt.init(pi),
                               q_opt=self.opt.init(q), alpha_opt=self.opt.init(la)))
        return agents

    # -- Algorithm 2
    def target(self, agents, j: int, n: int, b: dict, key) -> jax.Array:
        """y_j on agent n's batch: r_j + γ(Q̄_j(s', a') − α_n log π_n(a'|s')), a' ~ π_n(s').

        Absorbing: where s' completes channel j (success, or with `absorbing_stages`
        s' past stage j) the bootstrap is 1/(1 − γ); after another termination 0.
        """
        a2, logp2 = self.pi(agents[n]["pi"], b["next_obs"], key)
        soft = self.q(agents[j]["q_target"], b["next_obs"], a2) - jnp.exp(agents[n]["log_alpha"]) * logp2
        absorbed = b["success"] > 0
        if self.s.absorbing_stages:
            absorbed = absorbed | (b["next_stage"] > j)
        boot = jnp.where(absorbed, 1.0 / (1.0 - self.s.gamma), jnp.where(b["terminal"] > 0, 0.0, soft))
        return jax.lax.stop_gradient(b["rewards"][:, j] + self.s.gamma * boot)

    def update(self, agents: list[dict], batches: list[dict], ready: jax.Array, key) -> list[dict]:
        """One training loop: every agent's critic, actor and α step, all from the parameters before it.

        batches[n]: agent n's batch from B_n (obs, action, rewards [B, N], next_obs,
        terminal, success, next_stage); ready: bool[N].
        """
        s, n_agents = self.s, self.s.num_agents
        keys = jax.random.split(key, 2 * n_agents)
        norm = lambda x: (x - jax.lax.stop_gradient(x.min())) / (jax.lax.stop_gradient(x.max() - x.min()) + 1e-6)

        def critic_loss(twin, j):
            total = 0.0
            for n in ([j - 1] if j > 0 else []) + [j]:  # cross term from B_{j−1}, own term from B_j
                b = batches[n]
                y = self.target(agents, j, n, b, keys[n])
                x = jnp.concatenate([b["obs"], b["action"]], -1)
                loss = sum(jnp.mean((self.q_net.apply(t, x)[..., 0] - y) ** 2) for t in twin)
                total = total + ready[n] * loss
            return total

        def actor_loss(pi, n):
            b = batches[n]
            a, logp = self.pi(pi, b["obs"], keys[n_agents + n])
            alpha = jnp.exp(agents[n]["log_alpha"])
            if n < n_agents - 1:
                coop = s.etas[n] * norm(self.q(agents[n]["q"], b["obs"], a)) + (1 - s.etas[n]) * norm(
                    self.q(agents[n + 1]["q"], b["obs"], a))
            else:
                coop = self.q(agents[n]["q"], b["obs"], a)
            return jnp.mean(alpha * logp - coop), logp

        def step(params, grads, opt_state, go):
            updates, new_opt = self.opt.update(grads, opt_state, params)
            new = optax.apply_updates(params, updates)
            return (jax.tree.map(lambda a, b: jnp.where(go, a, b), new, params),
                    jax.tree.map(lambda a, b: jnp.where(go, a, b), new_opt, opt_state))

        new_agents = []
        for n, ag in enumerate(agents):
            g_q = jax.grad(critic_loss)(ag["q"], n)
            g_pi, logp = jax.grad(actor_loss, has_aux=True)(ag["pi"], n)
            target_entropy = -float(self.action_size)
            g_la = jax.grad(lambda la: -jnp.mean(la * jax.lax.stop_gradient(logp + target_entropy)))(ag["log_alpha"])
            q_ready = ready[n] | ready[n - 1] if n > 0 else ready[n]
            q, q_opt = step(ag["q"], g_q, ag["q_opt"], q_ready)
            pi, pi_opt = step(ag["pi"], g_pi, ag["pi_opt"], ready[n])
            la, alpha_opt = step(ag["log_alpha"], g_la, ag["alpha_opt"], ready[n])
            q_target = jax.tree.map(lambda t, c: t + s.tau * (c - t), ag["q_target"], q)
            new_agents.append(dict(pi=pi, q=q, q_target=q_target, log_alpha=la, pi_opt=pi_opt, q_opt=q_opt,
                                   alpha_opt=alpha_opt))
        return new_agents


def make_run(s: Settings, env: Maze):
    """`init(seed) -> state` and `epoch(state) -> (state, metrics)` of one run (Algorithm 1 + 2)."""
    ref = Reference(s, env.observation_size, env.action_size)
    n_agents, cap = s.num_agents, s.capacity
    fields = dict(obs=(env.observation_size,), action=(env.action_size,), rewards=(n_agents,),
                  next_obs=(env.observation_size,), terminal=(), success=(), next_stage=())

    def init(seed):
        k_agents, k_env, key = jax.random.split(jax.random.PRNGKey(seed), 3)
        buffers = [dict({f: jnp.zeros((cap,) + shape, jnp.int32 if f == "next_stage" else jnp.float32)
                         for f, shape in fields.items()}, size=jnp.int32(0), ptr=jnp.int32(0))
                   for _ in range(n_agents)]
        return dict(agents=ref.init_agents(k_agents), buffers=buffers, env=env.reset(k_env), key=key, t=jnp.int32(0))

    def collect(st):
        def one(carry, _):
            es, buffers, key, t = carry
            key, k_act, k_rand, k_reset = jax.random.split(key, 4)
            stage = es.info["stage"]
            policy = jnp.stack([ref.pi(ag["pi"], es.obs, k_act)[0] for ag in st["agents"]])[stage]
            a = jnp.where(t < s.start_steps, jax.random.uniform(k_rand, policy.shape, minval=-1, maxval=1), policy)
            nxt = env.step(es, a)
            tr = dict(obs=es.obs, action=a, rewards=nxt.info["rewards"], next_obs=nxt.obs,
                      terminal=nxt.metrics["success"], success=nxt.metrics["success"], next_stage=nxt.info["stage"])
            new_buffers = []
            for n, b in enumerate(buffers):  # B_{U(s)} gets the transition
                mine = stage == n
                slot = jnp.where(mine, b["ptr"], cap)  # out of range: dropped
                b = dict({f: b[f].at[slot].set(tr[f], mode="drop") for f in fields},
                         size=jnp.where(mine, jnp.minimum(b["size"] + 1, cap), b["size"]),
                         ptr=jnp.where(mine, (b["ptr"] + 1) % cap, b["ptr"]))
                new_buffers.append(b)
            es = jax.tree.map(lambda r, x: jnp.where(nxt.done > 0, r, x), env.reset(k_reset), nxt)
            return (es, new_buffers, key, t + 1), None

        (es, buffers, key, t), _ = jax.lax.scan(one, (st["env"], st["buffers"], st["key"], st["t"]), None,
                                                 s.steps_per_epoch)
        return dict(st, env=es, buffers=buffers, key=key, t=t)

    def train(st, key):
        ready = jnp.stack([b["size"] >= s.batch for b in st["buffers"]])

        def loop(agents, k):
            ks = jax.random.split(k, n_agents + 1)
            batches = []
            for n, b in enumerate(st["buffers"]):
                idx = jax.random.randint(ks[n], (s.batch,), 0, jnp.maximum(b["size"], 1))
                batches.append({f: b[f][idx] for f in fields})
            return ref.update(agents, batches, ready, ks[-1]), None

        agents, _ = jax.lax.scan(loop, st["agents"], jax.random.split(key, s.loops_per_epoch))
        return agents

    def evaluate(agents, key):
        def episode(k):
            def body(c):
                es, i = c
                act = jnp.stack([ref.pi_mean(ag["pi"], es.obs) for ag in agents])[es.info["stage"]]
                nxt = env.step(es, act)
                return jax.tree.map(lambda a, b: jnp.where(es.done > 0, a, b), es, nxt), i + 1

            es, _ = jax.lax.while_loop(lambda c: (c[0].done == 0) & (c[1] < s.episode_length), body,
                                       (env.reset(k), 0))
            return es.metrics["success"], es.info["stage"], es.metrics["pocket"]

        return jax.vmap(episode)(jax.random.split(key, s.eval_episodes))

    def epoch(st):
        st = collect(st)
        key, k_train, k_eval = jax.random.split(st["key"], 3)
        agents = train(st, k_train)
        success, stage, pocket = evaluate(agents, k_eval)
        st = dict(st, agents=agents, key=key)
        return st, dict(success=success.mean(), stage=stage.mean(), pocket=pocket.mean(),
                        buffer_size=jnp.stack([b["size"] for b in st["buffers"]]))

    return init, epoch


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    p.add_argument("--eta", type=float, default=0.1)
    p.add_argument("--rooms", type=int, default=2)
    p.add_argument("--total-steps", type=int, default=200_000)
    p.add_argument("--absorbing-stages", type=lambda x: x.lower() in ("1", "true", "yes"), default=True)
    p.add_argument("--tanh-log-prob", choices=("rlkit", "exact"), default="rlkit")
    p.add_argument("--out", type=Path, required=True, help="a JSON-lines file, one row per seed and epoch")
    args = p.parse_args()
    s = Settings(etas=(args.eta,) * (args.rooms - 1) + (1.0,), absorbing_stages=args.absorbing_stages,
                 tanh_log_prob=args.tanh_log_prob)
    init, epoch = make_run(s, Maze(rooms=args.rooms, episode_length=s.episode_length))
    state = jax.vmap(init)(jnp.asarray(args.seeds))
    step = jax.jit(jax.vmap(epoch))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("w") as f:
        for e in range(1, args.total_steps // s.steps_per_epoch + 1):
            t0 = time.time()
            state, m = step(state)
            m = jax.device_get(m)
            for i, seed in enumerate(args.seeds):
                row = dict(seed=seed, epoch=e, env_steps=e * s.steps_per_epoch, wall_s=round(time.time() - t0, 2),
                           **{k: v[i].tolist() for k, v in m.items()})
                f.write(json.dumps(row) + "\n")
            f.flush()
            print(f"epoch {e}: {time.time() - t0:.1f} s, success {[round(float(x), 2) for x in m['success']]}",
                  flush=True)


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    main()
