"""The paper's independent-ratio study: 3-room maze, a grid over (η1, η2), heatmap of final success.

    python experiments/independent_ratios.py --scale cpu
    python experiments/independent_ratios.py --scale paper     # 10 seeds, η1, η2 ∈ {0.1, …, 1.0}
    python experiments/independent_ratios.py --scale cpu --pairs 0.1,1.0 1.0,0.1   # some pairs only

All (η1, η2) pairs × seeds are one vmapped grid call (`--eta-per-agent`),
written to OUT/maze3/csac_pairs/ (a `--pairs` subset to csac_pairs_<pairs>/).
The table and heatmap gather every pairs run in OUT, plus the shared ratios of
table1.py's 3-room run of the same scale (OUT_TABLE1/maze3/csac/) on the
diagonal; the best pair is set beside the best shared ratio. Writes
heatmap.png and independent_ratios.md.
"""
from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ccp_jax import plot
from ccp_jax.config import ConfigError
from ccp_jax.eta import AUTO, parse_eta_vector
from common import (PAPER_INDEPENDENT, SCALES, ScaleName, best_swept_eta, cli, final_success, fmt, mean_and_iqm, mean_std,
                    merged_summary, read_json, results_folder, run_grid, swept_runs, write_text)

# Ratio values per axis: the paper's figure spans 0.1 … 1.0; the CPU budget affords three.
AXES = {"paper": tuple(round(0.1 * k, 1) for k in range(1, 11)), "cpu": (0.1, 0.5, 1.0), "smoke": (0.1, 1.0)}
SEEDS = {"paper": 10, "cpu": 3, "smoke": 1}


@dataclasses.dataclass
class Args:
    scale: ScaleName = "cpu"
    pairs: Optional[tuple[str, ...]] = None
    """(η1,η2) pairs to train instead of the scale's full grid, e.g. --pairs 0.1,1.0 1.0,0.1: a run of its own
    (OUT/maze3/csac_pairs_<pairs>). The table and heatmap gather every pairs run in OUT."""
    out: Optional[Path] = None
    """Results folder (default experiments/results/independent_ratios_<scale>)."""
    table1_out: Optional[Path] = None
    """Where table1.py's runs of the same scale are (default experiments/results/table1_<scale>); its shared
    ratios fill the diagonal (η1 = η2) where no pairs run has them."""
    table_only: bool = False


Pair = tuple[float, float]


def parse_pairs(texts: Optional[Sequence[str]]) -> Optional[list[Pair]]:
    """['0.1,1.0', ...] -> [(0.1, 1.0), ...]; ConfigError naming `pairs` for anything but two numbers."""
    if texts is None:
        return None
    pairs = []
    for text in texts:
        pair = parse_eta_vector(text, "pairs")
        if len(pair) != 2 or AUTO in pair:
            raise ConfigError("pairs", f"a pair is two numbers η1,η2 in [0, 1], got {text!r}")
        pairs.append(pair)
    return pairs


def pairs_config(scale_name: str, pairs: Optional[Sequence[Pair]] = None):
    """The grid of `pairs` (default: every pair of the scale's axis) × the scale's seeds, 3-room maze."""
    axis = AXES[scale_name]
    pairs = list(pairs or itertools.product(axis, axis))
    return SCALES[scale_name].config("maze3", "csac", etas=pairs, seeds=SEEDS[scale_name])


def pairs_folder(out: Path, pairs: Optional[Sequence[Pair]] = None) -> Path:
    name = "csac_pairs" if pairs is None else "csac_pairs_" + "_".join(f"{a:g}-{b:g}" for a, b in pairs)
    return out / "maze3" / name


def report(cells: dict[Pair, list[float]], shared: Optional[dict], scale_name: str, out: Path, env_steps: int) -> str:
    """independent_ratios.md: the best pair next to the best shared ratio and the paper's, then every pair."""
    best_pair = max(sorted(cells), key=lambda p: np.mean(cells[p]))
    seeds = sorted({len(v) for v in cells.values()})
    lines = [f"# Independent ratios, 3-room maze (scale `{scale_name}`)", "",
             f"{'/'.join(map(str, seeds))} seeds per pair, {env_steps:,} env steps; "
             "final success = mean of the last 10 epochs' evaluation.", "",
             "| | ours | mean [95 % CI] | IQM [95 % CI] | paper (10 seeds, 3M steps) |", "|---|---|---|---|---|",
             f"| best pair (η1, η2) | {best_pair} | {mean_and_iqm(cells[best_pair])} | "
             f"{PAPER_INDEPENDENT['best_pair']}: {fmt(PAPER_INDEPENDENT['best_pair_success'])} |"]
    if shared is not None:
        best_shared = best_swept_eta(shared)
        lines.append(f"| best shared η (table1.py) | {best_shared[0]:g} | "
                     f"{mean_and_iqm(final_success(shared)[best_shared])} | "
                     f"0.1: {fmt(PAPER_INDEPENDENT['best_shared_success'])} |")
    else:
        lines.append("| best shared η | table1.py's 3-room run not found | | | "
                     f"0.1: {fmt(PAPER_INDEPENDENT['best_shared_success'])} |")
    lines += ["", "Both picked as the best of their grid on these same seeds (the winner's curse favours them); "
              "intervals: 95 % stratified bootstrap over seeds (`ccp_jax.stats`)."]
    lines += ["", "Every pair trained (η1 rows, η2 columns), mean ± std over seeds; blank: not trained"
              + (" (the diagonal comes from table1.py's shared ratios where no pairs run has it)" if shared else "")
              + ":", ""]
    axis1, axis2 = sorted({p[0] for p in cells}), sorted({p[1] for p in cells})
    lines.append("| η1 \\ η2 | " + " | ".join(f"{b:g}" for b in axis2) + " |")
    lines.append("|---|" + "---|" * len(axis2))
    for a in axis1:
        lines.append(f"| {a:g} | " + " | ".join(mean_std(cells[(a, b)]) if (a, b) in cells else ""
                                                for b in axis2) + " |")
    text = "\n".join(lines) + "\n"
    write_text(out / "independent_ratios.md", text)
    return text


def largest_grid(args: Args) -> Optional[int]:
    """The grid this call trains (`common.cli` splits the CPU for it); None when it trains nothing."""
    return None if args.table_only else pairs_config(args.scale, parse_pairs(args.pairs)).grid_size


def main(args: Args) -> str:
    out = results_folder(args.out, "independent_ratios", args.scale)
    table1_out = results_folder(args.table1_out, "table1", args.scale)
    pairs = parse_pairs(args.pairs)
    if not args.table_only:
        run_grid(pairs_config(args.scale, pairs), pairs_folder(out, pairs))
    runs = sorted((out / "maze3").glob("csac_pairs*/summary.json"))
    if not runs:
        raise SystemExit(f"error: no finished pairs run in {out / 'maze3'}")
    shared_runs = swept_runs(table1_out, "maze3")
    shared = merged_summary(shared_runs)
    folders = [r.parent for r in runs] + shared_runs
    cells = plot.ratio_cells(folders)
    eta1, eta2, values = plot.ratio_table(cells)
    fig = plot.heatmap(values, eta1, eta2, title=f"3-room maze, final success ({args.scale} scale)")
    text = report(cells, shared, args.scale, out, read_json(runs[0])["members"][0]["env_steps"])
    print(text)
    plot.save_figure_and_say(fig, out / "heatmap.png")
    return text


if __name__ == "__main__":
    cli(main, Args, largest_grid=largest_grid)
