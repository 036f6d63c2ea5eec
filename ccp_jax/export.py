"""Export a trained chain of stage policies as one StableHLO artefact that runs with jax alone.

    python -m ccp_jax.export RUN_DIR [--member K] [--epoch E] [--out FILE]

writes FILE (default RUN_DIR/policy_member<K>.jaxexport) and FILE's metadata
beside it (.json). The artefact is `jax.export`'s serialisation of

    policy(obs float32[b, obs_size], stage int32[b]) -> action float32[b, action_size]

with every agent's weights inside: the deterministic action (tanh of the
Gaussian mean) of the agent that acts in `stage`. The stage switch U(s) is the
caller's: pass the env's own `state.info["stage"]` (0-based), as the trainer
does; end-to-end SAC has one agent and ignores it. The batch size b is
symbolic, so any batch runs, and the artefact is lowered for CPU and, where
this jax can lower for it, CUDA. To run it, nothing of ccp-jax is needed:

    import jax, numpy as np
    policy = jax.export.deserialize(bytearray(open("policy_member0.jaxexport", "rb").read()))
    action = policy.call(np.zeros((1, obs_size), np.float32), np.zeros((1,), np.int32))

ONNX is not offered: the converters from JAX (jax2onnx, or jax2tf then
tf2onnx) are not in this project's pinned stack, and StableHLO already runs
wherever jax (or an XLA/IREE runtime) does.
"""
from __future__ import annotations

import envs_mjx

if __name__ == "__main__":  # the CLI: MJX's CPU flag and quiet import, before the imports below load brax and MJX
    envs_mjx.configure_cpu()

import argparse
import json
from pathlib import Path
from typing import Optional, Sequence

import jax
import jax.numpy as jnp

from ccp_jax import outputs
from ccp_jax.config import ConfigError
from ccp_jax.policy import chain_policy, load_member

PLATFORMS = ("cpu", "cuda")


def export_chain(run_dir: str | Path, member: int = 0, epoch: Optional[int] = None,
                 platforms: Sequence[str] = PLATFORMS) -> tuple[jax.export.Exported, dict]:
    """The exported stage chain of grid member `member` (latest checkpoint unless `epoch`) and its metadata.

    Lowered for every platform of `platforms` that this jax can lower for (CPU always)."""
    run_dir = Path(run_dir)
    config, actor, params = load_member(run_dir, member, epoch)
    obs_size = params["params"]["MLP_0"]["Dense_0"]["kernel"].shape[-2]
    (b,) = jax.export.symbolic_shape("b")
    args = (jax.ShapeDtypeStruct((b, obs_size), jnp.float32), jax.ShapeDtypeStruct((b,), jnp.int32))
    fn = jax.jit(chain_policy(config, actor, params))
    try:
        exported = jax.export.export(fn, platforms=tuple(platforms))(*args)
    except Exception:  # noqa: BLE001 - a jax that cannot lower for an accelerator here still exports for the CPU
        exported = jax.export.export(fn, platforms=("cpu",))(*args)
    eta, seed = config.members[member]
    meta = dict(run_dir=str(run_dir.resolve()), member=member, epoch="latest" if epoch is None else epoch, seed=seed,
                eta=[outputs.eta_text([e]) for e in eta], algo=config.algo, env=config.task.env,
                num_stages=config.num_stages, num_agents=config.num_agents, obs_size=int(obs_size),
                action_size=int(exported.out_avals[0].shape[-1]), platforms=list(exported.platforms),
                jax_version=jax.__version__,
                signature="policy(obs float32[b, obs_size], stage int32[b]) -> action float32[b, action_size]",
                stage="the env's state.info['stage'], 0-based (end-to-end SAC ignores it)")
    return exported, meta


def write(exported: jax.export.Exported, meta: dict, out: Path) -> None:
    """`out` (the serialised artefact) and `out` with suffix .json (its metadata)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(exported.serialize())
    out.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n")


def main(argv: Optional[Sequence[str]] = None) -> Path:
    parser = argparse.ArgumentParser(prog="python -m ccp_jax.export",
                                     description="Export a trained member's stage chain as one jax.export artefact.")
    parser.add_argument("run_dir", type=Path, metavar="RUN_DIR")
    parser.add_argument("--member", type=int, default=0, help="grid member (see summary.json)")
    parser.add_argument("--epoch", type=int, default=None, help="checkpoint epoch (default: the latest)")
    parser.add_argument("--out", type=Path, default=None,
                        help="artefact path (default RUN_DIR/policy_member<K>.jaxexport); metadata beside it (.json)")
    args = parser.parse_args(argv)
    out = args.out or args.run_dir / f"policy_member{args.member}.jaxexport"
    if out.suffix == ".json":
        parser.error("--out: the metadata takes the .json beside the artefact; give the artefact another suffix")
    try:
        exported, meta = export_chain(args.run_dir, args.member, args.epoch)
    except (ValueError, ConfigError) as err:  # bad member, or no run / no checkpoint in RUN_DIR
        raise SystemExit(f"error: {err}") from None
    write(exported, meta, out)
    print(f"wrote {out} ({out.stat().st_size:,} bytes; platforms {', '.join(meta['platforms'])}) and "
          f"{out.with_suffix('.json').name}")
    return out


if __name__ == "__main__":
    main()
