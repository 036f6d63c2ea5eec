"""The paper's independent-ratio study: 3-room maze, a grid over (η1, η2), heatmap of final success.

    python experiments/independent_ratios.py --scale cpu
    python experiments/independent_ratios.py --scale paper     # 10 seeds, η1, η2 ∈ {0.1, …, 1.0}

All (η1, η2) pairs × seeds are one vmapped grid call (`--eta-per-agent`),
written to OUT/maze3/csac_pairs/. The best pair is set beside the best shared
ratio of the same scale, taken from table1.py's 3-room run if it exists
(OUT_TABLE1/maze3/csac/). Writes heatmap.png and independent_ratios.md.
"""
from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import tyro

from ccp_jax import plot
from common import (PAPER_INDEPENDENT, SCALES, final_success, fmt, mean_std, read_json, results_folder, run_grid,
                    write_text)

# Ratio values per axis: the paper's figure spans 0.1 … 1.0; the CPU budget affords three.
AXES = {"paper": tuple(round(0.1 * k, 1) for k in range(1, 11)), "cpu": (0.1, 0.5, 1.0), "smoke": (0.1, 1.0)}
SEEDS = {"paper": 10, "cpu": 3, "smoke": 1}


@dataclasses.dataclass
class Args:
    scale: Literal["cpu", "paper", "smoke"] = "cpu"
    out: Optional[Path] = None
    """Results folder (default experiments/results/independent_ratios_<scale>)."""
    table1_out: Optional[Path] = None
    """Where table1.py's runs of the same scale are (default experiments/results/table1_<scale>)."""
    table_only: bool = False


def pairs_config(scale_name: str):
    axis = AXES[scale_name]
    pairs = [(a, b) for a, b in itertools.product(axis, axis)]
    return SCALES[scale_name].config("maze3", "csac", etas=pairs, seeds=SEEDS[scale_name])


def report(summary: dict, shared: Optional[dict], scale_name: str, out: Path) -> str:
    cells = {eta[:2]: v for eta, v in final_success(summary).items()}
    best_pair = max(sorted(cells), key=lambda p: np.mean(cells[p]))
    lines = [f"# Independent ratios, 3-room maze (scale `{scale_name}`)", "",
             f"{len(next(iter(cells.values())))} seeds per pair, {summary['members'][0]['env_steps']:,} env steps; "
             "final success = mean of the last 10 epochs' evaluation.", "",
             "| | ours | paper (10 seeds, 3M steps) |", "|---|---|---|",
             f"| best pair (η1, η2) | {best_pair}: {mean_std(cells[best_pair])} | "
             f"{PAPER_INDEPENDENT['best_pair']}: {fmt(PAPER_INDEPENDENT['best_pair_success'])} |"]
    if shared is not None:
        by_eta = {eta: v for eta, v in final_success(shared).items() if "auto" not in eta}
        best_shared = max(sorted(by_eta), key=lambda e: np.mean(by_eta[e]))
        lines.append(f"| best shared η (table1.py) | {best_shared[0]:g}: {mean_std(by_eta[best_shared])} | "
                     f"0.1: {fmt(PAPER_INDEPENDENT['best_shared_success'])} |")
    else:
        lines.append("| best shared η | table1.py's 3-room run not found | "
                     f"0.1: {fmt(PAPER_INDEPENDENT['best_shared_success'])} |")
    lines += ["", "All pairs (η1 rows, η2 columns), mean ± std over seeds:", ""]
    axis1, axis2 = sorted({p[0] for p in cells}), sorted({p[1] for p in cells})
    lines.append("| η1 \\ η2 | " + " | ".join(f"{b:g}" for b in axis2) + " |")
    lines.append("|---|" + "---|" * len(axis2))
    for a in axis1:
        lines.append(f"| {a:g} | " + " | ".join(mean_std(cells.get((a, b), [])) for b in axis2) + " |")
    text = "\n".join(lines) + "\n"
    write_text(out / "independent_ratios.md", text)
    return text


def main(args: Args) -> str:
    out = results_folder(args.out, "independent_ratios", args.scale)
    table1_out = results_folder(args.table1_out, "table1", args.scale)
    folder = out / "maze3" / "csac_pairs"
    if not args.table_only:
        run_grid(pairs_config(args.scale), folder)
    summary = read_json(folder / "summary.json")
    eta1, eta2, values = plot.ratio_grid([folder])
    fig = plot.heatmap(values, eta1, eta2, title=f"3-room maze, final success ({args.scale} scale)")
    fig.savefig(out / "heatmap.png")
    shared_path = table1_out / "maze3" / "csac" / "summary.json"
    text = report(summary, read_json(shared_path) if shared_path.exists() else None, args.scale, out)
    print(text)
    print(f"wrote {out / 'heatmap.png'}")
    return text


if __name__ == "__main__":
    main(tyro.cli(Args))
