"""Projected wall time of the paper's whole Table I on this machine, from a measured slice (issue 8, item 6).

    python experiments/bench/paper_projection.py                                   # paper scale, every domain
    python experiments/bench/paper_projection.py --domains maze3 --baselines       # one domain, SAC and Naive too
    python experiments/bench/paper_projection.py --scale smoke --out /tmp/p.jsonl  # seconds, on any machine

For each domain it builds the grid trainer exactly as `experiments/table1.py
--scale <scale>` would (same preset, ratios × seeds, env), times `epochs`
warm epochs of it with compile kept apart (`TimedGrid`), and does the same
for one run alone (the first ratio, seed 0). It prints, per domain:

* per-run cost of an epoch in the grid against one run alone (the GPU target
  of issue 8: ≤ 0.1× at the paper's grid of 45+ runs);
* the projected wall time of that domain's CSAC sweep, epochs × s/epoch with
  epochs = total_steps / steps_per_epoch (600 at the paper's 3 M steps), plus
  the setup (building, initialising and compiling the program);
* with `--baselines`, the same for the SAC and Naive grids (one per seed
  count); TP is not projected (its primitives come from Naive, its PPO epochs
  cost differently).

One JSON line per timed program goes to `--out` as soon as it is measured,
so a run cut short keeps what it measured; the table at the end sums the
domains. Domains run in the order given (cheapest first by default: the
mazes, then peg), one program alive at a time.
"""
from __future__ import annotations

import dataclasses
import gc
import json
import sys
import time
from pathlib import Path
from typing import Optional

import jax
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS, SCALES, ScaleName, check_domains  # noqa: E402
from timed import TimedGrid  # noqa: E402

from ccp_jax.config import Config  # noqa: E402
from envs_mjx import configure_cpu  # noqa: E402


@dataclasses.dataclass
class Args:
    scale: ScaleName = "paper"
    """A scale of experiments/common.py."""
    domains: tuple[str, ...] = ("maze2", "maze3", "maze4", "peg")
    epochs: int = 2
    """Warm epochs timed per program (median reported)."""
    baselines: bool = False
    """Also time the SAC and Naive grids of each domain."""
    grid: bool = True
    """Time the CSAC grid (`--no-grid`: one run alone only, e.g. to size a slow domain first)."""
    single: bool = True
    """Also time one CSAC run alone (for the per-run cost ratio)."""
    out: Optional[Path] = None
    """JSON lines, appended, one per timed program (default
    experiments/results/bench/paper_projection_<scale>_<platform>.jsonl)."""


def programs(args: Args, domain: str) -> list[tuple[str, Config]]:
    """(name, config) of each program to time for `domain`, as table1.py builds them."""
    scale = SCALES[args.scale]
    sweep = scale.config(domain, "csac", etas=[(e,) for e in scale.etas])
    out = [("csac grid", sweep)] if args.grid else []
    if args.single:
        out.append(("csac single", scale.config(domain, "csac", etas=[(scale.etas[0],)], seeds=1)))
    if args.baselines:
        out += [(algo, scale.config(domain, algo)) for algo in ("sac", "naive")]
    return out


def peak_gb() -> Optional[float]:
    """The device's peak allocation so far in GB (this process, all programs), where the backend reports it (GPU, TPU)."""
    stats = jax.devices()[0].memory_stats() or {}
    return stats["peak_bytes_in_use"] / 1e9 if "peak_bytes_in_use" in stats else None


def measure(name: str, domain: str, config: Config, epochs: int) -> dict:
    """Build, compile and time `epochs` warm epochs of `config`'s grid trainer."""
    print(f"{time.strftime('%H:%M:%S')} {domain} {name}: G = {config.grid_size}, building and compiling", flush=True)
    t = time.perf_counter()
    timed = TimedGrid(config)
    setup_s = time.perf_counter() - t
    for _ in range(epochs):
        timed.epoch()
    run_epochs = config.budget.total_steps // config.budget.steps_per_epoch
    # Setup = building, initialising, compiling, and the warm-up epochs TimedGrid ran: keep only the overhead.
    overhead_s = setup_s - (2 + bool(timed.retraced)) * timed.median
    row = dict(domain=domain, program=name, algo=config.algo, grid=config.grid_size, agents=config.num_agents,
               hidden=list(config.sac.hidden), buffer=config.sac.buffer_size, epoch_s=timed.median,
               per_run_epoch_s=timed.median / config.grid_size, compile_s=timed.compile_s,
               overhead_s=overhead_s, run_epochs=run_epochs, projected_s=run_epochs * timed.median + overhead_s,
               peak_gb=peak_gb(), device=str(jax.devices()[0].device_kind), platform=jax.devices()[0].platform,
               jax=jax.__version__,
               time=time.strftime("%Y-%m-%d %H:%M:%S"))
    del timed
    gc.collect()
    return row


def report(rows: list[dict]) -> str:
    """The Markdown table of measured programs, per-run ratios and the projected total."""
    lines = ["| domain | program | G | N | s / epoch | s / run-epoch | vs one run alone | setup s | projected h |",
             "|---|---|---|---|---|---|---|---|---|"]
    single = {r["domain"]: r["per_run_epoch_s"] for r in rows if r["program"] == "csac single"}
    for r in rows:
        grid = r["program"] == "csac grid" and r["domain"] in single
        ratio = f"{r['per_run_epoch_s'] / single[r['domain']]:.3f}×" if grid else "–"
        lines.append(f"| {r['domain']} | {r['program']} | {r['grid']} | {r['agents']} | {r['epoch_s']:.2f} | "
                     f"{r['per_run_epoch_s']:.3f} | {ratio} | {r['overhead_s']:.0f} | {r['projected_s'] / 3600:.2f} |")
    sweeps = [r for r in rows if r["program"] != "csac single"]
    total = sum(r["projected_s"] for r in sweeps)
    lines.append(f"\nProjected Table I ({', '.join(sorted({r['program'] for r in sweeps}))}; "
                 f"{len({r['domain'] for r in sweeps})} domains, one program after another): {total / 3600:.2f} h "
                 f"on {rows[0]['device']}." if sweeps else "\nNo sweep measured: nothing to project.")
    return "\n".join(lines)


def main(args: Args) -> None:
    if args.epochs < 1:
        raise SystemExit(f"error: epochs: must be >= 1, got {args.epochs}")
    check_domains(args.domains)
    platform = jax.devices()[0].platform
    out = args.out or RESULTS / "bench" / f"paper_projection_{args.scale}_{platform}.jsonl"
    out.parent.mkdir(parents=True, exist_ok=True)
    print(f"scale {args.scale}, devices {jax.devices()}; {args.epochs} warm epochs per program -> {out}", flush=True)
    rows = []
    for domain in args.domains:
        for name, config in programs(args, domain):
            row = measure(name, domain, config, args.epochs)
            rows.append(row)
            with out.open("a") as f:
                f.write(json.dumps(row) + "\n")
            print(f"{domain} {name}: G = {row['grid']}, {row['epoch_s']:.2f} s/epoch, "
                  f"setup {row['overhead_s']:.0f} s (compile {row['compile_s']:.0f} s)", flush=True)
    print(report(rows))


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    main(tyro.cli(Args))
