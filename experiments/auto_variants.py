"""Issue 9's `auto` variants against the best fixed ratios, one success panel per maze, on the same seeds.

    python experiments/auto_variants.py    # -> results/table1_cpu_forward_slide/auto_variants.png

Draws runs already trained (RESULTS.md, "`auto` weighing the next critic κ times" and "`auto`
following where the episodes fail"); each line is the mean ± std over the six seeds of its folders.
"""
from __future__ import annotations

from pathlib import Path

from ccp_jax import plot
from curves import draw_panels

ROOT = Path(__file__).parent / "results" / "table1_cpu_forward_slide"
# Per maze: (legend, folders under ROOT/<maze>, the ratio vector to keep from them or None for all).
VARIANTS = {
    "maze2": [("best swept, η = 0.1", ["csac", "csac_fresh_seeds"], (0.1, 1.0)),
              ("auto, κ = 4", ["csac_auto_k4"], None),
              ("auto, outcomes", ["csac_auto_outcomes"], None),
              ("auto, outcomes down-only", ["csac_auto_outcomes_down"], None)],
    "maze3": [("best swept, η = 0.3", ["csac_fresh_seeds", "csac_ramp_and_0.3_seeds6to8"], (0.3, 0.3, 1.0)),
              ("auto, κ = 4", ["csac_auto_k4_seeds3to8"], None),
              ("auto, outcomes", ["csac_auto_outcomes_seeds3to8"], None),
              ("auto, outcomes down-only", ["csac_auto_outcomes_down_seeds3to8"], None)],
    "maze4": [("best swept, η = 0.5", ["csac_etas_0.5-0.7", "csac_fresh_seeds"], (0.5, 0.5, 0.5, 1.0)),
              ("ramp 0.1, 0.3, 0.5", ["csac_ramp", "csac_ramp_fresh_seeds"], (0.1, 0.3, 0.5, 1.0)),
              ("auto, κ = 4", ["csac_auto_k4"], None),
              ("auto, outcomes down-only", ["csac_auto_outcomes_down"], None)],
}


def panel(maze: str) -> dict:
    """Curve groups of one maze, keyed (task, legend, ratios) so `plot.curves` labels them by legend."""
    groups = {}
    for legend, folders, keep in VARIANTS[maze]:
        for (task, _, eta), series in plot.load_curves([ROOT / maze / f for f in folders]).items():
            if keep is None or eta == keep:
                groups[task, legend, eta] = series
    return groups


def main() -> Path:
    path = draw_panels({maze: panel(maze) for maze in VARIANTS}, ROOT / "auto_variants.png")
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    main()
