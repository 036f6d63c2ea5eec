"""Issue 9: does one `--eta auto` run match the best of the swept ratios? And do `ema` / `floor` help?

    python experiments/eta_auto.py --scale cpu --domains maze2 maze3
    python experiments/eta_auto.py --scale cpu --domains peg --normalisers floor --no-sweep

Table I's CSAC grid (`table1.py`, same scale and folder) already holds the
swept ratios and `auto` with the paper's batch normaliser, all on the same
seeds. This script adds CSAC `auto` with the `ema` and the `floor`
normalisers (one grid call each, same seeds, written beside them as
<domain>/csac_auto_<normaliser>/), then writes eta_auto.md: per domain, final
success and env steps to the first evaluation success of every variant, next
to the best swept ratio.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import tyro

from ccp_jax.config import AUTO
from common import (DOMAINS, SCALES, ScaleName, best_swept_eta, eta_label, final_success, mean_std, merged_summary,
                    read_json, results_folder, run_grid, swept_runs, write_text)
from table1 import run_dir, train_domain

NORMALISERS = ("ema", "floor")


@dataclasses.dataclass
class Args:
    scale: ScaleName = "cpu"
    domains: tuple[str, ...] = ("maze2", "maze3", "maze4", "peg")
    normalisers: tuple[Literal["ema", "floor"], ...] = NORMALISERS
    """The auto variants to train beside the swept ratios."""
    out: Optional[Path] = None
    """Results folder shared with table1.py (default experiments/results/table1_<scale>)."""
    sweep: bool = True
    """First train the swept ratios that Table I's CSAC grid still lacks (on peg: 75 min per ratio on a CPU)."""
    table_only: bool = False


def firsts(summary: dict) -> dict[tuple, list]:
    by_eta: dict[tuple, list] = {}
    for m in summary["members"]:
        by_eta.setdefault(tuple(m["eta"]), []).append(m["first_success_env_steps"])
    return by_eta


def first_text(values: list) -> str:
    reached = [v for v in values if v is not None]
    return f"{np.mean(reached):,.0f} ({len(reached)}/{len(values)} seeds)" if reached else f"never (0/{len(values)})"


def domain_rows(out: Path, domain: str) -> list[str]:
    """Markdown rows: the best swept ratio, auto (batch), auto (ema), auto (floor)."""
    swept = merged_summary(swept_runs(out, domain))
    if swept is None:
        return []
    success, first = final_success(swept), firsts(swept)
    rows = []
    if best := best_swept_eta(swept):
        rows.append((f"best swept η = {eta_label(best[0])}", success[best], first[best]))
    if auto := next((eta for eta in success if AUTO in eta), None):
        rows.append(("auto, batch normaliser", success[auto], first[auto]))
    for normaliser in NORMALISERS:
        path = run_dir(out, domain, f"csac_auto_{normaliser}") / "summary.json"
        if path.exists():
            s = read_json(path)
            rows.append((f"auto, {normaliser} normaliser", *next(zip(final_success(s).values(), firsts(s).values()))))
    return [f"| {domain} | {name} | {mean_std(values)} | {' '.join(f'{v:.2f}' for v in values)} | {first_text(f)} |"
            for name, values, f in rows]


def main(args: Args) -> str:
    out = results_folder(args.out, "table1", args.scale, args.domains)
    scale = SCALES[args.scale]
    if not args.table_only:
        for domain in args.domains:
            if args.sweep:
                train_domain(args.scale, domain, ("csac",), out)
            for normaliser in args.normalisers:
                run_grid(scale.config(domain, "csac", etas=[(AUTO,)], normaliser=normaliser),
                         run_dir(out, domain, f"csac_auto_{normaliser}"))
    lines = ["| domain | CSAC variant | final success | per seed | env steps to first success |", "|---|---|---|---|---|"]
    for domain in DOMAINS:  # every domain trained in `out`, not only this call's: earlier rows are kept
        lines += domain_rows(out, domain)
    text = ("\n".join(lines) + f"\n\nScale `{args.scale}` (see experiments/README.md); the same seeds in every row. "
            "Final success: mean of the last 10 epochs' evaluation; first success: mean over the seeds that ever "
            "succeeded.\n")
    write_text(out / "eta_auto.md", text)
    print(text)
    return text


if __name__ == "__main__":
    main(tyro.cli(Args))
