"""Step a trained peg policy and print what its grasp does, step by step.

    python experiments/peg_trace.py RUN_DIR --member K [--epoch E]       # from the run's checkpoint
    python experiments/peg_trace.py CELL_DIR --member K --exported       # from CELL_DIR/policies/member<K>.jaxexport
    python experiments/peg_trace.py ... [--episodes 4] [--seed 100]

For each episode (start states from PRNGKey(seed + episode)): a line whenever the stage, the sign of the grip
command or the number of pads touching the peg changes, and every 50 steps: the x-velocity and grip commands,
the grip point's x from the peg's centre (positive: toward the hole, the thin section; the thick section starts
`CENTRE_TO_SHOULDER` behind the centre) and the peg's x. Then the episode's length, success and `hold_thick`.
docs/peg.md#cost-and-results reads seed 31's regrasp this way. `peg_budget.py` exports each finished grid's
final policies (--exported); a run still training has checkpoints.
"""
from __future__ import annotations

import envs_mjx

if __name__ == "__main__":
    envs_mjx.configure_cpu()

import argparse
from pathlib import Path
from typing import Callable, Optional, Sequence

import jax
import numpy as np

from ccp_jax import outputs
from ccp_jax.envs import make_env


def load(folder: Path, member: int, epoch: Optional[int], exported: bool) -> Callable:
    """policy(obs float32[b, obs_size], stage int32[b]) -> action float32[b, action_size] of one member."""
    if not exported:
        from ccp_jax.policy import load_policy

        return load_policy(folder, member, epoch)
    path = folder / "policies" / f"member{member}.jaxexport"
    if not path.exists():
        raise SystemExit(f"error: member: {path} does not exist (peg_budget.py exports a finished grid's members)")
    chain = jax.export.deserialize(bytearray(path.read_bytes()))
    return lambda obs, stage: chain.call(obs, stage)


def trace(env, reset: Callable, step: Callable, policy: Callable, key: jax.Array, log=print) -> dict:
    """One greedy episode from `reset(key)` (`env`'s, jitted once by the caller, as `step`), logged as the module
    says; returns its end (length, success, hold_thick)."""
    state, last = reset(key), None
    for t in range(env.episode_length):
        action = np.asarray(policy(state.obs[None], state.info["stage"][None].astype(np.int32)))[0]
        ro = env.readout(state.pipeline_state)
        stage, touching = int(state.info["stage"]), int(ro.touch[0]) + int(ro.touch[1])
        if (stage, action[1] > 0, touching) != last or t % 50 == 0:
            log(f"  t={t:4d} stage={stage} vx={action[0]:+.2f} grip={action[1]:+.2f} "
                f"grip-from-centre={float(ro.grip_pos[0] - ro.peg_pos[0]):+.4f} m pads={touching} "
                f"peg x={float(ro.peg_pos[0]):.3f}")
        last = (stage, action[1] > 0, touching)
        state = step(state, action)
        if float(state.done):
            break
    return dict(length=t + 1, success=float(state.metrics["success"]), hold_thick=float(state.metrics["hold_thick"]))


def main(argv: Optional[Sequence[str]] = None) -> list[dict]:
    parser = argparse.ArgumentParser(prog="python experiments/peg_trace.py", description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, metavar="RUN_DIR")
    parser.add_argument("--member", type=int, default=0)
    parser.add_argument("--epoch", type=int, help="checkpoint epoch (default: the latest)")
    parser.add_argument("--exported", action="store_true", help="use policies/member<K>.jaxexport")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--seed", type=int, default=100)
    args = parser.parse_args(argv)
    config = outputs.read_config(args.folder)
    if config.task.env != "peg":
        raise SystemExit(f"error: run_dir: {args.folder} trained {config.task.env!r}, not peg")
    env, policy = make_env(config), load(args.folder, args.member, args.epoch, args.exported)
    reset, step = jax.jit(env.reset), jax.jit(env.step)
    ends = []
    for episode in range(args.episodes):
        print(f"episode {episode}:")
        ends.append(trace(env, reset, step, policy, jax.random.PRNGKey(args.seed + episode)))
        print(f"  -> {ends[-1]['length']} steps, success {ends[-1]['success']:.0f}, hold_thick {ends[-1]['hold_thick']:.0f}")
    return ends


if __name__ == "__main__":
    main()
