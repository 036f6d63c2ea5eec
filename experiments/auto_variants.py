"""Issue 9's `auto` variants against the best fixed ratios, one panel per domain, on the same seeds.

    python experiments/auto_variants.py    # -> results/table1_cpu_forward_slide/auto_variants.png

Draws runs already trained (RESULTS.md, "`auto` weighing the next critic κ times", "`auto`
following where the episodes fail", "`auto` on peg in hole", the gated and trusted rules and, on 4 rooms,
trusted with `--eta-auto-floor-step 0.25`); each
line is the mean ± std over the seeds of its folders (six per maze, three on peg). The maze panels
draw success; the peg panel draws the grasp (the fraction of evaluations reaching stage 2), since no
peg run inserts at this budget.
"""
from __future__ import annotations

from pathlib import Path

from ccp_jax import plot
from curves import STAGE2, draw_panels

RESULTS = Path(__file__).parent / "results"
ROOT = RESULTS / "table1_cpu_forward_slide"
# Per domain: (its runs' folder, the metric drawn, [(legend, folders, the ratio vector to keep or None for all)]).
PANELS = {
    "maze2": (ROOT / "maze2", "success_rate",
              [("best swept, η = 0.1", ["csac", "csac_fresh_seeds"], (0.1, 1.0)),
               ("auto, κ = 4", ["csac_auto_k4"], None),
               ("auto, outcomes", ["csac_auto_outcomes"], None),
               ("auto, outcomes down-only", ["csac_auto_outcomes_down"], None),
               ("auto, gated", ["csac_auto_gated"], None),
               ("auto, trusted", ["csac_auto_trusted"], None)]),
    "maze3": (ROOT / "maze3", "success_rate",
              [("best swept, η = 0.3", ["csac_fresh_seeds", "csac_ramp_and_0.3_seeds6to8"], (0.3, 0.3, 1.0)),
               ("auto, κ = 4", ["csac_auto_k4_seeds3to8"], None),
               ("auto, outcomes", ["csac_auto_outcomes_seeds3to8"], None),
               ("auto, outcomes down-only", ["csac_auto_outcomes_down_seeds3to8"], None),
               ("auto, gated", ["csac_auto_gated_seeds3to8"], None),
               ("auto, trusted", ["csac_auto_trusted_seeds3to8"], None)]),
    "maze4": (ROOT / "maze4", "success_rate",
              [("best swept, η = 0.5", ["csac_etas_0.5-0.7", "csac_fresh_seeds"], (0.5, 0.5, 0.5, 1.0)),
               ("ramp 0.1, 0.3, 0.5", ["csac_ramp", "csac_ramp_fresh_seeds"], (0.1, 0.3, 0.5, 1.0)),
               ("auto, κ = 4", ["csac_auto_k4"], None),
               ("auto, outcomes down-only", ["csac_auto_outcomes_down"], None),
               ("auto, gated", ["csac_auto_gated"], None),
               ("auto, trusted", ["csac_auto_trusted"], None),
               ("auto, trusted, floors 0.05 0.3 0.5", ["csac_auto_floorramp"], None)]),
    # Peg has no robot: its sweep is the one of sessions 10-12 (results/table1_cpu).
    "peg": (RESULTS / "table1_cpu" / "peg", STAGE2,
            [("best swept for the grasp, η = 0.9", ["csac_etas_0.9"], (0.9, 1.0)),
             ("auto (η*)", ["csac_etas_auto"], None),
             ("auto, κ = 4", ["csac_auto_k4"], None),
             ("auto, outcomes down-only", ["csac_auto_outcomes_down"], None),
             ("auto, gated", ["csac_auto_gated"], None),
             ("auto, trusted", ["csac_auto_trusted"], None)]),
}


def panel(domain: str) -> dict:
    """Curve groups of one domain, keyed (task, legend, ratios) so `plot.curves` labels them by legend."""
    folder, metric, variants = PANELS[domain]
    groups = {}
    for legend, folders, keep in variants:
        for (task, _, eta), series in plot.load_curves([folder / f for f in folders], metric).items():
            if keep is None or eta == keep:
                groups[task, legend, eta] = series
    return groups


def main() -> Path:
    path = draw_panels({d: panel(d) for d in PANELS}, ROOT / "auto_variants.png",
                       {d: metric for d, (_, metric, _) in PANELS.items()})
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    main()
