"""Issue 9: does one `--eta auto` run match the best of the swept ratios? And do `ema` / `floor` help?

    python experiments/eta_auto.py --scale cpu --domains maze2 maze3
    python experiments/eta_auto.py --scale cpu --domains peg --normalisers floor --no-sweep
    python experiments/eta_auto.py --scale cpu --domains maze2 --normalisers --no-sweep --fresh-seeds 12
    python experiments/eta_auto.py --scale cpu --domains maze3 --normalisers --no-sweep --raw-sum --fresh-seeds 5

Table I's CSAC grid (`table1.py`, same scale and folder) already holds the
swept ratios and `auto` with the paper's batch normaliser, all on the same
seeds. This script adds CSAC `auto` with the `ema` and `floor` normalisers
(and `none` if asked; one grid call each, same seeds, written beside them as
<domain>/csac_auto_<normaliser>/), then writes eta_auto.md: per domain, final
success and env steps to the first evaluation success of every variant, next
to the best swept ratio.

The best swept ratio is the best of several noisy 3-seed means, so its score
on the seeds it was picked on is biased upwards (the winner's curse).
`--fresh-seeds K` trains it and `auto` again on K new seeds, numbered after the
scale's (<domain>/csac_fresh_seeds/), where neither was picked.

`--raw-sum` adds the objective `auto` stands for without the paper's units:
η* makes the normalised loss a multiple of Q_n + Q_{n+1}, which raw critics
give at η = 0.5 (`--normaliser none --eta 0.5`, <domain>/csac_raw_sum/, and
with `--fresh-seeds` also on the fresh seeds, <domain>/csac_raw_sum_fresh_seeds/).

`--ramp LOW HIGH` adds a per-agent rule read off the independent-ratio grids: the
first agent cooperates most, η rising linearly to HIGH for the last
cooperative agent, η_n = LOW + (HIGH − LOW) n / (N − 2) (N = 2: LOW), in
<domain>/csac_ramp/ (and <domain>/csac_ramp_fresh_seeds/).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal, Optional

import numpy as np

from ccp_jax.eta import AUTO
from common import (DOMAINS, SCALES, Scale, ScaleName, best_swept_eta, cli, eta_label, final_success, mean_and_iqm,
                    merged_summary, read_json, results_folder, run_grid, swept_runs, write_text)
from table1 import run_dir, train_domain

NORMALISERS = ("ema", "floor", "none")  # the variants a table row is looked for
# Trained unless --normalisers says otherwise. Not `none`: on raw critics η* no longer recovers the sum
# Q_n + Q_{n+1} (η = 0.5 does), so `auto` with it is a choice to make on purpose.
DEFAULT_NORMALISERS = ("ema", "floor")


@dataclasses.dataclass
class Args:
    scale: ScaleName = "cpu"
    domains: tuple[str, ...] = ("maze2", "maze3", "maze4", "peg")
    normalisers: tuple[Literal["ema", "floor", "none"], ...] = DEFAULT_NORMALISERS
    """The auto variants to train beside the swept ratios."""
    out: Optional[Path] = None
    """Results folder shared with table1.py (default experiments/results/table1_<scale>)."""
    sweep: bool = True
    """First train the swept ratios that Table I's CSAC grid still lacks (on peg: 75 min per ratio on a CPU)."""
    fresh_seeds: int = 0
    """Also train the best swept ratio and `auto` (and the raw sum) on this many new seeds (see above)."""
    raw_sum: bool = False
    """Also train the raw sum of the two critics, `--normaliser none --eta 0.5` (see above)."""
    ramp: Optional[tuple[float, float]] = None
    """LOW HIGH: also train per-agent ratios rising along the chain (see above), with --fresh-seeds also on those."""
    table_only: bool = False


def firsts(summary: dict) -> dict[tuple, list]:
    by_eta: dict[tuple, list] = {}
    for m in summary["members"]:
        by_eta.setdefault(tuple(m["eta"]), []).append(m["first_success_env_steps"])
    return by_eta


def one_variant(summary: dict) -> tuple[list, list]:
    """(final success per seed, first-success steps per seed) of a run of one ratio."""
    return next(zip(final_success(summary).values(), firsts(summary).values()))


def first_text(values: list) -> str:
    reached = [v for v in values if v is not None]
    return f"{np.mean(reached):,.0f} ({len(reached)}/{len(values)} seeds)" if reached else f"never (0/{len(values)})"


FRESH = "csac_fresh_seeds"
RAW_SUM, RAW_SUM_FRESH = "csac_raw_sum", "csac_raw_sum_fresh_seeds"
RAW_SUM_CHANGES = dict(etas=[(0.5,)], normaliser="none")
RAMP, RAMP_FRESH = "csac_ramp", "csac_ramp_fresh_seeds"


def ramp_etas(low: float, high: float, domain: str) -> tuple[float, ...]:
    """Per-agent ratios for the N − 1 cooperative agents of `domain`, rising from `low` to `high`."""
    cooperative = DOMAINS[domain][1] - 1
    if not 0.0 <= low <= 1.0 or not 0.0 <= high <= 1.0:
        raise SystemExit(f"error: ramp: both ratios must lie in [0, 1], got {low} {high}")
    return tuple(round(low + (high - low) * n / max(cooperative - 1, 1), 6) for n in range(cooperative))


def fresh_pick(out: Path, domain: str) -> tuple:
    """The best finished swept ratio of `domain`, which `--fresh-seeds` trains again; exits naming the field if none."""
    swept = merged_summary(swept_runs(out, domain))
    best = swept and best_swept_eta(swept)
    if not best:
        raise SystemExit(f"error: fresh_seeds: {domain} has no finished swept ratio in {out / domain} to pick the best "
                         "from; train the sweep first (table1.py)")
    return best


def train_fresh(scale: Scale, out: Path, domain: str, seeds: int, raw_sum: bool,
                ramp: Optional[tuple[float, float]]) -> None:
    """The best swept ratio and `auto` on `seeds` seeds numbered after the scale's, one grid (the raw sum, the
    ramp: one more each)."""
    run_grid(scale.config(domain, "csac", etas=[fresh_pick(out, domain)[:1], (AUTO,)], seeds=seeds,
                          first_seed=scale.seeds),
             run_dir(out, domain, FRESH))
    if raw_sum:
        run_grid(scale.config(domain, "csac", seeds=seeds, first_seed=scale.seeds, **RAW_SUM_CHANGES),
                 run_dir(out, domain, RAW_SUM_FRESH))
    if ramp:
        run_grid(scale.config(domain, "csac", etas=[ramp_etas(*ramp, domain)], seeds=seeds, first_seed=scale.seeds),
                 run_dir(out, domain, RAMP_FRESH))


def seed_span(summary: dict) -> str:
    seeds = sorted({m["seed"] for m in summary["members"]})
    return f"{seeds[0]}–{seeds[-1]}"


def one_variant_rows(out: Path, domain: str, folder: str, label: str) -> list[tuple]:
    """The row of the one-ratio run in <domain>/<folder> (`{seeds}` in `label` becomes its seeds, `{eta}` its
    cooperative agents' ratios); none if unfinished."""
    path = run_dir(out, domain, folder) / "summary.json"
    if not path.exists():
        return []
    s = read_json(path)
    eta = ", ".join(eta_label(e) for e in s["members"][0]["eta"][:-1])
    return [(label.format(seeds=seed_span(s), eta=eta), *one_variant(s))]


def domain_rows(out: Path, domain: str) -> list[str]:
    """Markdown rows: the best swept ratio, auto (batch), auto with each other normaliser, the raw sum, then the
    best ratio and auto on fresh seeds, and the raw sum on them."""
    swept = merged_summary(swept_runs(out, domain))
    if swept is None:
        return []
    name = lambda eta: "auto, batch normaliser" if AUTO in eta else f"best swept η = {eta_label(eta[0])}"
    success, first = final_success(swept), firsts(swept)
    rows = []
    if best := best_swept_eta(swept):
        rows.append((name(best), success[best], first[best]))
    if auto := next((eta for eta in success if AUTO in eta), None):
        rows.append((name(auto), success[auto], first[auto]))
    for normaliser in NORMALISERS:
        label = "auto, no normaliser" if normaliser == "none" else f"auto, {normaliser} normaliser"
        rows += one_variant_rows(out, domain, f"csac_auto_{normaliser}", label)
    rows += one_variant_rows(out, domain, RAW_SUM, "raw sum (no normaliser, η = 0.5)")
    if (path := run_dir(out, domain, FRESH) / "summary.json").exists():
        s = read_json(path)
        fresh_first = firsts(s)
        for eta, values in final_success(s).items():
            rows.append((f"{name(eta)}, fresh seeds {seed_span(s)}", values, fresh_first[eta]))
    rows += one_variant_rows(out, domain, RAW_SUM_FRESH, "raw sum, fresh seeds {seeds}")
    rows += one_variant_rows(out, domain, RAMP, "ramp η = {eta}")
    rows += one_variant_rows(out, domain, RAMP_FRESH, "ramp η = {eta}, fresh seeds {seeds}")
    return [f"| {domain} | {name} | {mean_and_iqm(values)} | {' '.join(f'{v:.2f}' for v in values)} | "
            f"{first_text(f)} |" for name, values, f in rows]


def eta_star_drift(folders: list[Path]) -> dict[tuple, list[tuple[float, float]]]:
    """{trained ratio vector: per cooperative agent, (mean batch η* over the first third of the epochs, over the
    last third)}, pooled over seeds: the ratio the paper's appendix rule reads off the critics each run trained."""
    from ccp_jax import outputs

    rows_by_eta: dict[tuple, list[dict]] = {}
    for folder in folders:
        for row in outputs.read_rows(outputs.metrics_file(folder)):
            if "eta_star" in row:  # not in runs older than the diagnostic
                rows_by_eta.setdefault(tuple(row["eta"]), []).append(row)
    drift = {}
    for eta, rows in rows_by_eta.items():
        last_epoch = max(r["epoch"] for r in rows)
        third = lambda keep: np.mean([r["eta_star"][:-1] for r in rows if keep(r["epoch"])], axis=0)
        early, late = third(lambda e: e <= last_epoch / 3), third(lambda e: e > 2 * last_epoch / 3)
        drift[eta] = list(zip(early.tolist(), late.tolist()))
    return drift


def eta_star_lines(out: Path) -> list[str]:
    """A markdown table of `eta_star_drift` for every domain trained in `out` (empty if none)."""
    from ccp_jax import plot

    lines, late = [], []
    for domain in DOMAINS:
        drift = eta_star_drift(swept_runs(out, domain))
        for eta in sorted(drift, key=lambda e: plot.group_order((domain, "csac", e))):
            agents = " | ".join(f"{a:.2f} → {b:.2f}" for a, b in drift[eta])
            lines.append(f"| {domain} | {', '.join(eta_label(e) for e in eta[:-1])} | {agents} |")
            late += [b for _, b in drift[eta]]
    if not lines:
        return []
    width = max(line.count("|") for line in lines) - 3
    header = "| domain | trained with η | " + " | ".join(f"agent {n + 1}" for n in range(width)) + " |"
    return ["", "## The paper's η* in the runs themselves", "",
            "Per cooperative agent, the batch η* = Ran(Q_n) / (Ran(Q_n) + Ran(Q_n+1)) each swept run logged (`auto` "
            "computes it from running ranges instead, and clips it), mean over the run's seeds and the first third of "
            "its epochs → the last third; a blank cell: a domain with fewer agents. Over the last thirds it lies "
            f"between {min(late):.2f} and {max(late):.2f}.", "",
            header, "|---|---|" + "---|" * width,
            *[line + " |" * (width - line.count("|") + 3) for line in lines]]


def comparison_groups(out: Path, domain: str) -> dict:
    """Success-curve groups of one domain: the best swept ratio, `auto` and the ramp, each pooled over the
    scale's and the fresh seeds (`plot.load_curves`); empty if the domain has no finished sweep."""
    from ccp_jax import plot

    swept = swept_runs(out, domain)
    if not swept:
        return {}
    best = best_swept_eta(merged_summary(swept))
    extra = [f for name in (FRESH, RAMP, RAMP_FRESH) if ((f := run_dir(out, domain, name)) / "summary.json").exists()]
    ramps = {tuple(read_json(f / "summary.json")["members"][0]["eta"]) for f in extra if f.name.startswith(RAMP)}
    return {g: series for g, series in plot.load_curves(swept + extra).items()
            if g[2] == best or AUTO in g[2] or g[2] in ramps}


def draw_comparison(out: Path) -> Optional[Path]:
    """eta_auto.png: one panel per domain trained in `out`, success of `comparison_groups` against env steps."""
    from curves import draw_panels

    drawn = {d: g for d in DOMAINS if (g := comparison_groups(out, d))}
    return draw_panels(drawn, out / "eta_auto.png") if drawn else None


def largest_grid(args: Args) -> Optional[int]:
    """The largest grid this call may train (`common.cli` splits the CPU for it); None when it trains nothing."""
    if args.table_only:
        return None
    scale = SCALES[args.scale]
    sizes = [scale.seeds]  # auto per normaliser, the raw sum
    if args.sweep:
        sizes.append(len(scale.etas) * scale.seeds)
    if args.fresh_seeds:
        sizes.append(2 * args.fresh_seeds)  # the best swept ratio and auto
    return max(sizes)


def main(args: Args) -> str:
    out = results_folder(args.out, "table1", args.scale, args.domains)
    if args.fresh_seeds < 0:
        raise SystemExit(f"error: fresh_seeds: must be >= 0, got {args.fresh_seeds}")
    scale = SCALES[args.scale]
    for domain in args.domains if args.ramp else ():
        ramp_etas(*args.ramp, domain)  # refused before anything trains
    if args.fresh_seeds and not args.sweep and not args.table_only:
        for domain in args.domains:  # before any grid trains: no sweep will run to supply the pick
            fresh_pick(out, domain)
    if not args.table_only:
        for domain in args.domains:
            if args.sweep:
                train_domain(args.scale, domain, ("csac",), out)
            for normaliser in args.normalisers:
                run_grid(scale.config(domain, "csac", etas=[(AUTO,)], normaliser=normaliser),
                         run_dir(out, domain, f"csac_auto_{normaliser}"))
            if args.raw_sum:
                run_grid(scale.config(domain, "csac", **RAW_SUM_CHANGES), run_dir(out, domain, RAW_SUM))
            if args.ramp:
                run_grid(scale.config(domain, "csac", etas=[ramp_etas(*args.ramp, domain)]), run_dir(out, domain, RAMP))
            if args.fresh_seeds:
                train_fresh(scale, out, domain, args.fresh_seeds, args.raw_sum, args.ramp)
    lines = ["| domain | CSAC variant | final success: mean [95 % CI] | IQM [95 % CI] | per seed | "
             "env steps to first success |", "|---|---|---|---|---|---|"]
    for domain in DOMAINS:  # every domain trained in `out`, not only this call's: earlier rows are kept
        lines += domain_rows(out, domain)
    text = ("\n".join(lines) + f"\n\nScale `{args.scale}` (see experiments/README.md); the same seeds in every row "
            "but the fresh-seed ones. Final success: mean of the last 10 epochs' evaluation, aggregated over seeds as "
            "mean and IQM with 95 % stratified-bootstrap intervals (`ccp_jax.stats`; with 3 seeds the IQM is the "
            "mean); first success: mean over the seeds that ever succeeded.\n" + "".join(line + "\n" for line in eta_star_lines(out)))
    write_text(out / "eta_auto.md", text)
    draw_comparison(out)
    print(text)
    return text


if __name__ == "__main__":
    cli(main, Args, largest_grid=largest_grid)
