"""Issue 9's `auto` variants against the best fixed ratios, one panel per domain, on the same seeds.

    python experiments/auto_variants.py    # -> results/table1_cpu_forward_slide/auto_variants.png, trusted_every_seed.png

Draws runs already trained (RESULTS.md, "`auto` weighing the next critic κ times", "`auto`
following where the episodes fail", "`auto` on peg in hole", the gated and trusted rules and, on 4 rooms,
trusted with `--eta-auto-floor-step 0.25`; outcomes, down-only, gated and the floor step are retired rules whose
runs still read, docs/design.md#retired-settings); each
line is the mean ± std over the seeds of its folders (six per maze, three on peg). The maze panels
draw success; the peg panel draws the grasp (the fraction of evaluations reaching stage 2), since no
peg run inserts at this budget. trusted_every_seed.png draws the trusted rule against the best shared
ratio over every seed both ran (2 rooms 12, 3 rooms 21, 4 rooms 12; and the 4-room ramp, which beats both).
"""
from __future__ import annotations

from pathlib import Path

from ccp_jax import plot
from curves import STAGE2, draw_panels
from envs_mjx import configure_cpu

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
    # Peg has no robot: its sweep is the one in results/table1_cpu.
    "peg": (RESULTS / "table1_cpu" / "peg", STAGE2,
            [("best swept for the grasp, η = 0.9", ["csac_etas_0.9"], (0.9, 1.0)),
             ("auto (η*)", ["csac_etas_auto"], None),
             ("auto, κ = 4", ["csac_auto_k4"], None),
             ("auto, outcomes down-only", ["csac_auto_outcomes_down"], None),
             ("auto, gated", ["csac_auto_gated"], None),
             ("auto, trusted", ["csac_auto_trusted"], None)]),
}


# Trusted against the best shared ratio on every seed both have.
EVERY_SEED = {
    "maze2": (ROOT / "maze2", "success_rate",
              [("best swept, η = 0.1", ["csac", "csac_fresh_seeds", "csac_trusted_0.1_seeds6to11"], (0.1, 1.0)),
               ("auto, trusted", ["csac_auto_trusted", "csac_trusted_0.1_seeds6to11"], ("auto", 1.0))]),
    "maze3": (ROOT / "maze3", "success_rate",
              [("best swept, η = 0.3", ["csac", "csac_fresh_seeds", "csac_ramp_and_0.3_seeds6to8",
                                        "csac_trusted_0.3_seeds9to14", "csac_trusted_0.3_seeds21to26"], (0.3, 0.3, 1.0)),
               ("auto, trusted", ["csac_auto_trusted_seeds0to2", "csac_auto_trusted_seeds3to8",
                                  "csac_trusted_0.3_seeds9to14", "csac_trusted_0.3_seeds21to26"],
                ("auto", "auto", 1.0))]),
    "maze4": (ROOT / "maze4", "success_rate",
              [("best swept, η = 0.5", ["csac_etas_0.5-0.7", "csac_fresh_seeds", "csac_ramp_and_0.5_seeds6to8",
                                        "csac_trusted_0.5_ramp_seeds9to11"], (0.5, 0.5, 0.5, 1.0)),
               ("ramp 0.1, 0.3, 0.5", ["csac_ramp", "csac_ramp_fresh_seeds", "csac_ramp_and_0.5_seeds6to8",
                                       "csac_trusted_0.5_ramp_seeds9to11"], (0.1, 0.3, 0.5, 1.0)),
               ("auto, trusted", ["csac_auto_trusted", "csac_auto_trusted_seeds6to8",
                                  "csac_trusted_0.5_ramp_seeds9to11"], ("auto", "auto", "auto", 1.0))]),
}


def panel(domain: str, panels: dict = PANELS) -> dict:
    """Curve groups of one domain, keyed (task, legend, ratios) so `plot.curves` labels them by legend."""
    folder, metric, variants = panels[domain]
    groups = {}
    for legend, folders, keep in variants:
        for (task, _, eta), series in plot.load_curves([folder / f for f in folders], metric).items():
            if keep is None or eta == keep:
                groups[task, legend, eta] = series
    return groups


def main() -> list[Path]:
    paths = [draw_panels({d: panel(d, panels) for d in panels}, ROOT / name,
                         {d: metric for d, (_, metric, _) in panels.items()})
             for panels, name in ((PANELS, "auto_variants.png"), (EVERY_SEED, "trusted_every_seed.png"))]
    return paths


if __name__ == "__main__":
    configure_cpu()  # before anything starts JAX: MJX's XLA flag, as the CLI sets it
    main()
