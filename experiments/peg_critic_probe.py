"""What a trained peg grid's critics say about where the first agent grasps, and whether its insertion agent
can use a good grasp.

    python experiments/peg_critic_probe.py RUN_DIR [--epoch E] [--starts 8] [--seed 200] [--out probe.json]

RUN_DIR holds config.json and checkpoints/ (the whole state: critics, normaliser bounds, actors). From `--starts`
start states (PRNGKey(seed + k)) the env's scripted controller (`envs_mjx.peg_in_hole.scripted_action`) grasps
either the thick section (policy 0, the grasp that can insert) or the peg's centre (policy 1, the grasp
reward's greedy choice, on the thin section) until the hand-over. Per grid member and grasp, at the last
grasping step (s, a), the twin-minimum Q_1(s, a) and Q_2(s, a): the two terms of the first agent's cooperative
objective C_1 = η Q̂_1 + (1 − η) Q̂_2 (docs/design.md#the-method), each also divided by the normaliser's running
range of that critic (`norm.hi − norm.lo`, the scale the actor sees); at the hand-over state s', Q_2(s', π_2(s')),
the insertion agent's own value. Then the member's insertion agent (its deterministic policy) acts from s'
to the episode's end: its success from each grasp says whether a thick hand-over is worth more to it.
Last, the decision itself: from the same starts the member's own first agent acts until it first commands the
gripper closed; there, how each term, and C_1 (each term divided by its running range; CSAC only), would change
had it stayed open and moved on toward the thick section.

If Q_2 does not rank the thick grasp above the centre one, the first agent's cooperative term has nothing to
follow; if it does but the first agent still grasps thin, the weight or the exploration is what fails.
"""
from __future__ import annotations

import envs_mjx

if __name__ == "__main__":
    envs_mjx.configure_cpu()

import argparse
from pathlib import Path
from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ccp_jax import checkpoint, outputs
from ccp_jax.envs import make_env
from ccp_jax.grid import make_grid_train
from ccp_jax.networks import deterministic_action
from envs_mjx.peg_in_hole import OBS_SLICES, scripted_action, thick_grasp_x

GRASPS = {"thick": 0, "centre": 1}  # scripted_action's policies


def hand_overs(env, reset, step, starts: int, seed: int) -> dict[str, dict]:
    """Per grasp: the last grasping step's obs and action [K, ...], the hand-over states (brax States, a list)
    and the grip point's x from the peg's centre at the hand-over [K]; starts that never hand over are dropped.
    `reset` and `step` are `env`'s, jitted once by the caller (as in the functions below)."""
    act = jax.jit(scripted_action)
    out = {}
    for name, policy in GRASPS.items():
        obs, acts, states, offsets = [], [], [], []
        for k in range(starts):
            key = jax.random.PRNGKey(seed + k)
            state = reset(key)
            for _ in range(env.episode_length):
                action = act(state, jnp.int32(policy), key)
                nxt = step(state, action)
                if int(nxt.info["stage"]) >= 1:
                    ro = env.readout(nxt.pipeline_state)
                    obs.append(np.asarray(state.obs))
                    acts.append(np.asarray(action))
                    states.append(nxt)
                    offsets.append(float(ro.grip_pos[0] - ro.peg_pos[0]))
                    break
                if float(nxt.done):
                    break
                state = nxt
        out[name] = dict(obs=np.stack(obs), action=np.stack(acts), states=states, offset=np.array(offsets))
    return out


def insert_from(env, step, state, policy, actor_params) -> float:
    """Success of the insertion agent's deterministic policy acting from the hand-over `state` to the end."""
    for _ in range(env.episode_length):
        if float(state.done):
            break
        mean, _ = policy(actor_params, state.obs[None])
        state = step(state, deterministic_action(mean)[0])
    return float(state.metrics["success"])


def decision_points(env, reset, step, policy, actor_params, starts: int, seed: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the member's own first agent (deterministic) first commands the gripper closed, per start that gets
    there: its obs [K, o], its action [K, a], and the other choice there [K, a]: stay open and move toward the
    thick section at full speed."""
    obs, own, other = [], [], []
    for k in range(starts):
        state = reset(jax.random.PRNGKey(seed + k))
        for _ in range(env.episode_length):
            mean, _ = policy(actor_params, state.obs[None])
            action = np.asarray(deterministic_action(mean)[0])
            if action[1] > 0 or int(state.info["stage"]) >= 1 or float(state.done):
                break
            state = step(state, action)
        if action[1] > 0 and int(state.info["stage"]) == 0:
            o = np.asarray(state.obs)
            thick = float(thick_grasp_x(o[OBS_SLICES["peg_pos"]][0]))
            obs.append(o)
            own.append(action)
            other.append(np.array([np.sign(thick - o[OBS_SLICES["grip_pos"]][0]), -1.0], np.float32))
    return np.array(obs), np.array(own), np.array(other)


def probe(run_dir: Path, epoch: Optional[int], starts: int, seed: int) -> dict:
    """The module's measurements on RUN_DIR's checkpoint (the latest unless `epoch`): run, epoch, starts, seed,
    each grasp's hand-over offsets, and per member (seed, eta, the first agent's normaliser ranges) per grasp
    q1, q2 (at the last grasping step), v2_after and inserts, and `decision` (where its first agent closes: closes,
    grip_from_centre, gain_q1, gain_q2, and for CSAC gain_c and balance_eta; absent if it never closes)."""
    config = outputs.read_config(run_dir)
    if config.task.env != "peg" or config.num_agents != 2:
        raise SystemExit("error: run_dir: a CSAC or Naive peg run (two agents) is needed")
    env = make_env(config)
    trainer = make_grid_train(config, env, jax.devices()[:1])
    mngr = checkpoint.manager(run_dir)
    try:
        epoch, state = checkpoint.restore(mngr, trainer.abstract_state(config.grid_arrays()[1]), epoch=epoch,
                                          grid_size=config.grid_size)
    finally:
        mngr.close()
    agents = jax.device_get(state.agents)
    del state  # the buffers
    critic, actor = trainer.networks.critic, trainer.networks.actor
    cooperative = config.algo == "csac"
    q = jax.jit(lambda p, o, a: jnp.min(critic.apply(p, o, a), axis=0))
    policy = jax.jit(actor.apply)
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    grasps = hand_overs(env, reset, step, starts, seed)
    result = dict(run=run_dir.name, epoch=int(epoch), starts=starts, seed=seed,
                  offset={g: grasps[g]["offset"].tolist() for g in GRASPS}, members=[])
    for m, (eta, member_seed) in enumerate(config.members):
        take = lambda tree, n: jax.tree.map(lambda x: x[m, n], tree)
        span = np.asarray(agents.norm.hi[m] - agents.norm.lo[m])  # [N, 2]: agent n's own and next critic
        row = dict(member=m, seed=member_seed, eta=list(eta), norm_range_own=float(span[0, 0]),
                   norm_range_next=float(span[0, 1]))
        for g, data in grasps.items():
            obs, act = jnp.asarray(data["obs"]), jnp.asarray(data["action"])
            after = jnp.stack([s.obs for s in data["states"]])
            mean, _ = policy(take(agents.actor, 1), after)
            row[g] = dict(q1=float(q(take(agents.critic, 0), obs, act).mean()),
                          q2=float(q(take(agents.critic, 1), obs, act).mean()),
                          v2_after=float(q(take(agents.critic, 1), after, deterministic_action(mean)).mean()),
                          inserts=float(np.mean([insert_from(env, step, s, policy, take(agents.actor, 1))
                                                 for s in data["states"]])))
        obs, own, other = decision_points(env, reset, step, policy, take(agents.actor, 0), starts, seed)
        if len(obs):
            grip = obs[:, OBS_SLICES["grip_pos"]][:, 0] - obs[:, OBS_SLICES["peg_pos"]][:, 0]
            gaps = [q(take(agents.critic, n), jnp.asarray(obs), jnp.asarray(other))
                    - q(take(agents.critic, n), jnp.asarray(obs), jnp.asarray(own)) for n in (0, 1)]
            own_term, next_term = float(np.mean(gaps[0] / span[0, 0])), float(np.mean(gaps[1] / span[0, 1]))
            row["decision"] = dict(closes=len(obs), grip_from_centre=float(grip.mean()),
                                   gain_q1=float(gaps[0].mean()), gain_q2=float(gaps[1].mean()),
                                   gain_c=None, balance_eta=None)
            if cooperative:  # Naive's actor maximises plain Q_1 and has no normaliser: ΔQ_1 says it all
                row["decision"].update(gain_c=eta[0] * own_term + (1 - eta[0]) * next_term,
                                       # the ratio at which the two terms cancel: below it, moving on wins
                                       balance_eta=next_term / (next_term - own_term) if next_term > 0 > own_term
                                       else None)
        result["members"].append(row)
    return result


def table(result: dict) -> str:
    lines = [f"{result['run']}, epoch {result['epoch']}, {result['starts']} scripted starts per grasp "
             f"(seed {result['seed']}); grip x from the peg centre at the hand-over: "
             + ", ".join(f"{g} {np.mean(result['offset'][g]):+.3f} m" for g in GRASPS), "",
             "| member | seed | η | grasp | Q_1(s, a) | Q_2(s, a) | Q_2 / range | Q_2(s', π_2) | insertion agent "
             "inserts |", "|---|---|---|---|---|---|---|---|---|"]
    for r in result["members"]:
        for g in GRASPS:
            v = r[g]
            lines.append(f"| {r['member']} | {r['seed']} | {outputs.eta_text(r['eta'])} | {g} | {v['q1']:.2f} | "
                         f"{v['q2']:.2f} | {v['q2'] / max(r['norm_range_next'], 1e-6):.3f} | {v['v2_after']:.2f} | "
                         f"{v['inserts']:.2f} |")
    lines += ["", "Where the member's own first agent first closes the gripper: the change in each term of its "
              "objective if it stayed open and moved on toward the thick section instead (C_1 in the "
              "normaliser's running ranges; negative: closing there is what the objective prefers).", "",
              "| member | seed | starts that close | grip from the centre | ΔQ_1 | ΔQ_2 | ΔC_1 | η below which moving "
              "on wins |", "|---|---|---|---|---|---|---|---|"]
    for r in result["members"]:
        d = r.get("decision")
        maybe = lambda key, fmt: "–" if d is None or d[key] is None else format(d[key], fmt)
        lines.append(f"| {r['member']} | {r['seed']} | " + ("0 | | | | | |" if d is None else
                     f"{d['closes']} | {d['grip_from_centre']:+.3f} m | {d['gain_q1']:+.2f} | {d['gain_q2']:+.2f} | "
                     f"{maybe('gain_c', '+.3f')} | {maybe('balance_eta', '.2f')} |"))
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--epoch", type=int, help="checkpoint epoch (default: the latest)")
    parser.add_argument("--starts", type=int, default=8, help="scripted start states per grasp (default 8)")
    parser.add_argument("--seed", type=int, default=200, help="first start state's seed (default 200)")
    parser.add_argument("--out", type=Path, help="also write the result to FILE.json")
    args = parser.parse_args(argv)
    result = probe(args.run_dir, args.epoch, args.starts, args.seed)
    print(table(result))
    if args.out:
        outputs.write_json(args.out, result)
    return result


if __name__ == "__main__":
    main()
