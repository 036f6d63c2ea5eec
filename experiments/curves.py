"""The paper's success-curve figures: per domain, CSAC at its best ratio against SAC and Naive.

    python experiments/curves.py --scale cpu [--domains maze2 maze3] [--with-auto] [--all-etas]

The curves come from the same runs as Table I (`table1.py`, same scale and
folder): missing runs are trained (or resumed) first, so either script can be
run first. The best ratio of a domain is the one with the highest mean final
success over seeds (ties: the smaller η). Writes curves_<domain>.png and one
figure with every domain side by side (curves.png) into the results folder.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

from ccp_jax import plot
from ccp_jax.eta import AUTO
from common import ScaleName, best_swept_eta, cli, merged_summary, results_folder
from table1 import finished_runs, train_domain

TITLES = {"maze2": "2-room maze", "maze3": "3-room maze", "maze4": "4-room maze", "peg": "peg in hole",
          "pusher": "Brax pusher"}


@dataclasses.dataclass
class Args:
    scale: ScaleName = "cpu"
    domains: tuple[str, ...] = ("maze2", "maze3", "maze4", "peg")
    algos: tuple[str, ...] = ("csac", "sac", "naive", "tp")
    with_auto: bool = True
    """Also draw CSAC with η = auto (issue 9) next to the best swept ratio."""
    all_etas: bool = False
    """Draw every swept CSAC ratio, not only the best (into curves_all_<domain>.png, stage2_all_<domain>.png, curves_all.png)."""
    out: Optional[Path] = None
    """Results folder shared with table1.py (default experiments/results/table1_<scale>)."""
    plot_only: bool = False
    """Only draw from the runs already finished; never train."""


STAGE2 = "stage_fraction/1"


def domain_groups(out: Path, domain: str, algos: tuple[str, ...], with_auto: bool,
                  metric: str = "success_rate", all_etas: bool = False) -> dict:
    """Curve groups of `metric` to draw for one domain: the best CSAC ratio (every ratio with `all_etas`;
    and auto), then each baseline."""
    groups = {}
    for algo in algos:
        folders = finished_runs(out, domain, algo)
        if not folders:
            continue
        loaded = plot.load_curves(folders, metric)
        if algo == "csac":
            best = best_swept_eta(merged_summary(folders))
            loaded = {g: s for g, s in loaded.items()
                      if (with_auto and AUTO in g[2]) or (AUTO not in g[2] and (all_etas or g[2] == best))}
        groups.update(loaded)
    return groups


def draw_panels(drawn: dict[str, dict], path: Path, metrics: Optional[dict[str, str]] = None) -> Path:
    """One panel per domain ({domain: curve groups}, in that order), side by side, saved to `path`; each
    draws its domain's metric in `metrics` (default: success)."""
    fig = plot.new_figure(4.2 * len(drawn), 3.4)
    colors = plot.line_colors(drawn.values())  # a variant in several panels is drawn alike in each
    for i, (domain, groups) in enumerate(drawn.items()):
        plot.curves(groups, (metrics or {}).get(domain, "success_rate"),
                    ax=fig.add_subplot(1, len(drawn), i + 1), title=TITLES[domain], colors=colors)
    return plot.save_figure_and_say(fig, path)


def main(args: Args) -> list[Path]:
    out = results_folder(args.out, "table1", args.scale, args.domains)
    if not args.plot_only:
        for domain in args.domains:
            train_domain(args.scale, domain, args.algos, out)
    tag = "_all" if args.all_etas else ""  # the best-ratio figures stay as they are
    drawn = {d: g for d in args.domains if (g := domain_groups(out, d, args.algos, args.with_auto,
                                                             all_etas=args.all_etas))}
    saved = []
    for domain, groups in drawn.items():
        path = out / f"curves{tag}_{domain}.png"
        plot.save_figure_and_say(plot.curves(groups, title=TITLES[domain]), path)
        stage2 = domain_groups(out, domain, args.algos, args.with_auto, STAGE2, all_etas=args.all_etas)
        stage2_path = out / f"stage2{tag}_{domain}.png"
        plot.save_figure_and_say(plot.curves(stage2, STAGE2, title=f"{TITLES[domain]}: episodes reaching stage 2"),
                                 stage2_path)
        saved += [path, stage2_path]
    if drawn:
        saved.append(draw_panels(drawn, out / f"curves{tag}.png"))
    return saved


if __name__ == "__main__":
    cli(main, Args)
