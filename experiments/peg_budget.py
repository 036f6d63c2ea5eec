"""Peg in hole at 1 M env steps on the fast peg, on seeds never used on peg (issue 57).

    python experiments/peg_budget.py                          # trains (or resumes) the queue in order, then reports
    python experiments/peg_budget.py --cells csac_0.9 naive   # some cells, in the queue's order
    python experiments/peg_budget.py --report-only            # table and curves from the runs as they stand

Settings: the hand on C MuJoCo (`--peg-model hand --peg-physics c`, docs/peg.md#c-physics: the arm's task and
scripted outcomes, 13x its env steps/s), the paper's epoch (5000 env steps, 1000 updates), [64, 64] networks
(the paper's are [256, 256]), a replay buffer of 1e6, 1 M env steps (a third of the paper's 3 M), seeds 30-32:
peg's earlier runs used seeds 0-2 and nothing was chosen on these.

The queue: CSAC at η = 0.9 (the paper's best on peg), Naive, SAC, then a short sweep (`SWEEP`: five ratios,
two seeds 40-41, 200 k steps), whose best ratio trains as one more CSAC cell on seeds 30-32. The sweep's
best: the highest mean final success; where no ratio inserts, the highest mean fraction of final evaluations
handing over on the thick section (`grasp_thick`, the grasp that can insert fully); then the hand-over rate.
Last, `HELD`: CSAC η = 0.9 and Naive again with the gripper held closed from the hand-over on (`--peg-grip-held`,
not the paper's task: no regrasp, so the first agent's grasp decides; docs/peg.md#the-grip-held-variant).

Each cell is one vmapped grid in OUT/<cell>/ with a checkpoint every 25 epochs: run the same command again to
resume a stopped one (finished ones are skipped). When a grid finishes, its last checkpoint is evaluated again on
`FINAL_EPISODES` deterministic episodes per member (`ccp_jax.evaluate`, written to final_eval.json; these carry
`hold_thick`, which shows an insertion agent that regrasps), again with training's action noise
(stochastic_eval.json: does exploration ever hand over on the thick section), probed for what its critics say
of the grasp (critic_probe.json, experiments/peg_critic_probe.py, cells with two agents), and each member's final
policy is exported (policies/, `ccp_jax.export`); then the checkpoints (the buffers: gigabytes) are deleted.
Its metrics are compacted (metrics.jsonl.gz) and the folder is what to commit.

The report (OUT/table.md, OUT/curves.png): per cell, final success with mean and IQM and 95 % stratified-bootstrap
intervals; the final hand-over rate (evaluation episodes that reached stage 2) and where those grasps hold the
peg (`grasp_thick`, `grasp_thin`: envs_mjx/peg_in_hole.py); P(CSAC > baseline); the final evaluation per seed;
the three over env steps, each method's mean over seeds with a bootstrap band.
"""
from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path
from typing import Optional

import numpy as np

from ccp_jax import outputs, stats
from ccp_jax.config import make_config
from common import (PAPER_TABLE1, RESULTS, cli, export_policies, improvement, read_json, rows_by_member, run_grid,
                    with_interval, write_text)

SEEDS = (30, 31, 32)
TOTAL_STEPS = 1_000_000
CHECKPOINT_EVERY = 25
SETTINGS = dict(env="peg", peg_model="hand", peg_physics="c", hidden=(64, 64))
# Transitions each agent's buffer holds, or every transition of a shorter run: sampling reads only the filled
# part of a buffer (`ccp_jax.buffer.sample_indices`), so that trains exactly as 1e6 would, in less memory (the
# sweep's 10 members at 1e6 took 19 GB of this machine's 23).
BUFFER_SIZE = 1_000_000
WINDOW = outputs.FINAL_WINDOW  # epochs in a final value (the paper's final success)
FINAL_EPISODES = 50  # per member, in the final evaluation of the last checkpoint
FINAL_EVAL = "final_eval.json"
STOCHASTIC_EVAL = "stochastic_eval.json"  # the same episodes with training's action noise
CRITIC_PROBE = "critic_probe.json"  # experiments/peg_critic_probe.py on the last checkpoint (two-agent cells)
PROBE_STARTS, PROBE_SEED = 8, 200


@dataclasses.dataclass(frozen=True)
class Cell:
    name: str
    algo: str
    etas: tuple[tuple[float, ...], ...] = ((1.0,),)
    seeds: tuple[int, ...] = SEEDS
    total_steps: int = TOTAL_STEPS
    grip_held: bool = False

    def config(self, smoke: bool = False):
        """The cell's grid; `smoke`: the "tiny" preset, 2 epochs of 200 steps, 100-step episodes (seconds)."""
        if smoke:
            return make_config("tiny", algo=self.algo, etas=self.etas, seeds=self.seeds, total_steps=400,
                               steps_per_epoch=200, max_episode_steps=100, env="peg", peg_model="hand",
                               peg_physics="c", peg_grip_held=self.grip_held)
        return make_config("small", algo=self.algo, etas=self.etas, seeds=self.seeds,
                           total_steps=self.total_steps, buffer_size=min(BUFFER_SIZE, self.total_steps),
                           peg_grip_held=self.grip_held, **SETTINGS)


SWEEP = Cell("sweep", "csac", tuple((e,) for e in (0.1, 0.3, 0.5, 0.7, 0.9)), seeds=(40, 41), total_steps=200_000)
QUEUE = (Cell("csac_0.9", "csac", ((0.9,),)), Cell("naive", "naive"), Cell("sac", "sac"), SWEEP)
HELD = (Cell("csac_0.9_held", "csac", ((0.9,),), grip_held=True), Cell("naive_held", "naive", grip_held=True))
HELD_SUFFIX = "_held"


@dataclasses.dataclass
class Args:
    cells: Optional[tuple[str, ...]] = None
    """Train only these cells (csac_0.9, naive, sac, sweep, best: the sweep's best ratio, csac_0.9_held,
    naive_held), in the queue's order."""
    out: Optional[Path] = None
    """Results folder (default experiments/results/peg_budget)."""
    report_only: bool = False
    smoke: bool = False
    """Seconds per cell (`Cell.config`): checks the script end to end."""


# ------------------------------------------------------------------ reading runs
def curves(folder: Path) -> dict[str, np.ndarray]:
    """[members, complete epochs] per metric of a run folder (finished or training): env_steps, success,
    handover (evaluation episodes that reached stage 2), grasp_thick, grasp_thin; plus seed and eta [members]."""
    rows = list(rows_by_member(folder, field="out", complete_epochs=True).values())
    get = lambda f: np.array([[f(r) for r in member] for member in rows], np.float64)
    return dict(env_steps=get(lambda r: r["env_steps"]), success=get(lambda r: r["success_rate"]),
                handover=get(lambda r: r["stage_fraction"][1]),
                grasp_thick=get(lambda r: r["eval_end"].get("grasp_thick", np.nan)),
                grasp_thin=get(lambda r: r["eval_end"].get("grasp_thin", np.nan)),
                seed=np.array([member[0]["seed"] for member in rows]),
                eta=np.array([member[0]["eta"][0] for member in rows]))


def final(c: dict, metric: str) -> np.ndarray:
    return c[metric][:, -WINDOW:].mean(axis=1)


def best_swept_eta(folder: Path) -> Optional[float]:
    """The sweep's best ratio (module doc), None until the sweep has finished."""
    if not (folder / "summary.json").exists():
        return None
    c = curves(folder)
    score = {eta: tuple(final(c, m)[c["eta"] == eta].mean() for m in ("success", "grasp_thick", "handover"))
             for eta in sorted(set(c["eta"].tolist()))}
    return max(score, key=score.get)


def best_cell(out: Path) -> Optional[Cell]:
    eta = best_swept_eta(out / SWEEP.name)
    if eta is None or eta == 0.9:  # 0.9 trains anyway (csac_0.9)
        return None
    return Cell(f"csac_{eta:g}", "csac", ((eta,),))


def final_evaluation(folder: Path, episodes: int = FINAL_EPISODES, probe_starts: int = PROBE_STARTS
                     ) -> Optional[list[dict]]:
    """`ccp_jax.evaluate`'s rows for a finished grid's last checkpoint (start states of seed 1, not the training
    evaluations' 0), kept in FOLDER/final_eval.json; the same with action noise (stochastic_eval.json) and, with
    two agents, `peg_critic_probe.probe` (critic_probe.json); each member's final policy is kept as a
    `ccp_jax.export` artefact (FOLDER/policies/member<K>.jaxexport, for looking at its episodes later); then the
    checkpoints are deleted. None where the grid has not finished, or finished without checkpoints and without
    that file."""
    import peg_critic_probe
    from ccp_jax.evaluate import evaluate_run

    path = folder / FINAL_EVAL
    if path.exists():
        return read_json(path)
    if not (folder / "summary.json").exists() or not (folder / "checkpoints").is_dir():
        return None
    rows = evaluate_run(folder, episodes=episodes, seed=1)
    outputs.write_json(folder / STOCHASTIC_EVAL, evaluate_run(folder, episodes=episodes, stochastic=True, seed=1))
    if outputs.read_config(folder).num_agents == 2:
        outputs.write_json(folder / CRITIC_PROBE, peg_critic_probe.probe(folder, None, probe_starts, PROBE_SEED))
    export_policies(folder)
    outputs.write_json(path, rows)
    shutil.rmtree(folder / "checkpoints")
    return rows


# ------------------------------------------------------------------ the report
def label(cell_name: str) -> str:
    name = cell_name.removesuffix(HELD_SUFFIX)
    held = ", grip held" if name != cell_name else ""
    return {"naive": "Naive", "sac": "SAC"}.get(name, "CSAC η = " + name.removeprefix("csac_")) + held


def row(name: str, c: dict, paper: Optional[float]) -> str:
    success, handover = final(c, "success"), final(c, "handover")
    thick, thin = final(c, "grasp_thick"), final(c, "grasp_thin")
    per_seed = lambda v: " ".join(f"{x:.2f}" for x in v)
    return (f"| {label(name)} | {int(c['env_steps'][:, -1].min()):,} | {len(success)} | "
            f"{with_interval(success, np.mean)} | {with_interval(success, stats.iqm)} | "
            f"{per_seed(success)} | {per_seed(handover)} | {per_seed(thick)} | {per_seed(thin)} | "
            f"{'–' if paper is None else f'{paper:.2f}'} |")


def figure(found: dict[str, dict], path: Path) -> None:
    """Success, hand-over rate and thick-section grasps over env steps: mean over seeds, 95 % bootstrap band."""
    from matplotlib.ticker import FuncFormatter

    from ccp_jax import plot

    fig = plot.new_figure(width=12.0, height=3.6)
    axes = fig.subplots(1, 3, sharey=True)
    panels = (("success", "evaluation success"), ("handover", "hand-over rate (reached stage 2)"),
              ("grasp_thick", "hand-over on the thick section"))
    for ax, (metric, title) in zip(axes, panels):
        for i, (name, c) in enumerate(found.items()):
            values = c[metric]
            if np.isnan(values).all():
                continue
            mean, low, high = stats.curve_band(values)
            steps = c["env_steps"][0]
            ax.plot(steps, mean, color=f"C{i}", label=f"{label(name)} ({len(values)} seeds)")
            ax.fill_between(steps, low, high, color=f"C{i}", alpha=0.2, linewidth=0)
        ax.xaxis.set_major_formatter(FuncFormatter(plot._steps_label))
        ax.set(xlabel="env steps", title=title, ylim=(-0.02, 1.02))
    axes[0].set_ylabel("fraction of evaluation episodes")
    axes[0].legend(fontsize="small")
    plot.save_figure(fig, path)


def final_table(found: dict[str, list[dict]]) -> list[str]:
    """The final evaluations (`final_evaluation`'s rows per cell) as table lines: per seed, success, hand-over
    and where the pads hold the peg (at the hand-over: thin; at the episode's end: thick)."""
    if not found:
        return []
    episodes = {r["episodes"] for rows in found.values() for r in rows}
    per_seed = lambda rows, f: " ".join(f"{f(r):.2f}" for r in rows)
    lines = ["", f"Final evaluation of the last checkpoint, {', '.join(map(str, sorted(episodes)))} deterministic "
                 "episodes per seed (start states apart from training's): `hold_thick` is the fraction ending with "
                 "the pads on the thick section, which after a thin hand-over means the insertion agent regrasped.",
             "", "| method | seeds | success | hand-over | hand-over on the thin section | pads on the thick section "
                 "at the end (`hold_thick`) |", "|---|---|---|---|---|---|"]
    for name, rows in found.items():
        lines.append(f"| {label(name)} | {' '.join(str(r['seed']) for r in rows)} | "
                     f"{per_seed(rows, lambda r: r['success_rate'])} | {per_seed(rows, lambda r: r['stage_fraction'][1])} | "
                     f"{per_seed(rows, lambda r: r['eval_end']['grasp_thin'])} | "
                     f"{per_seed(rows, lambda r: r['eval_end']['hold_thick'])} |")
    return lines


def probe_table(found: dict[str, tuple[dict, list[dict]]]) -> list[str]:
    """Per cell (`peg_critic_probe.probe`'s result, the stochastic evaluation's rows), per seed: whether the
    insertion agent inserts from the scripted thick and centre hand-overs, its value after each, where the first
    agent closes, what moving on would do to its objective, and the thick hand-overs of the noisy episodes."""
    if not found:
        return []
    starts = sorted({probe["starts"] for probe, _ in found.values()})
    lines = ["", "What the critics say of the grasp (`experiments/peg_critic_probe.py` on the checkpoint of the epoch "
                 f"shown, scripted hand-overs from {'/'.join(map(str, starts))} start states; "
                 "docs/peg.md#why-the-first-agent-grasps-thin): the insertion agent's success and value Q_2(s', π_2) "
                 "after a thick / centre hand-over; where the first agent first closes the gripper (from the peg's "
                 "centre) and the change in its own critic, and in CSAC's objective C_1, had it moved on toward the "
                 "thick section; thick hand-overs among the stochastic episodes.", "",
             "| method | epoch | seeds | inserts from thick / centre | Q_2 after thick / centre | closes at | "
             "ΔQ_1 of moving on | ΔC_1 of moving on | noisy thick hand-overs |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, (probe, noisy) in found.items():
        members = probe["members"]
        per_seed = lambda f: " ".join(f(m) for m in members)
        pair = lambda key: per_seed(lambda m: f"{m['thick'][key]:.2f}/{m['centre'][key]:.2f}")
        decision = lambda key, fmt: per_seed(lambda m: "–" if m.get("decision", {}).get(key) is None
                                             else format(m["decision"][key], fmt))
        lines.append(f"| {label(name)} | {probe['epoch']} | {per_seed(lambda m: str(m['seed']))} | {pair('inserts')} "
                     f"| {pair('v2_after')} | {decision('grip_from_centre', '+.3f')} | {decision('gain_q1', '+.2f')} | "
                     f"{decision('gain_c', '+.3f')} | "
                     f"{' '.join(format(r['eval_end']['grasp_thick'], '.2f') for r in noisy)} |")
    return lines


def report(out: Path) -> str:
    found = {cell.name: curves(out / cell.name) for cell in QUEUE[:-1] + tuple(filter(None, [best_cell(out)])) + HELD
             if (out / cell.name / "config.json").exists()}
    found = {name: c for name, c in found.items() if c["success"].size > 0}
    if not found:
        raise SystemExit(f"error: out: no runs of peg_budget.py in {out.resolve()}")
    paper = lambda name: (None if name.endswith(HELD_SUFFIX) else PAPER_TABLE1[name]["peg"] if name in ("naive", "sac")
                          else PAPER_TABLE1["csac"].get(float(name.removeprefix("csac_")), {}).get("peg"))
    lines = ["# Peg in hole at 1 M env steps (the hand on C MuJoCo)", "",
             f"Seeds {SEEDS[0]}–{SEEDS[-1]}; [64, 64] networks, buffer 1e6, the paper's epoch. Finals: the mean of "
             f"the last {WINDOW} evaluations (10 deterministic episodes each). Intervals: 95 % stratified bootstrap "
             "over seeds. A cell below 1,000,000 env steps is still training. The paper's values are at 3 M steps.",
             "", "| method | env steps | seeds | success, mean [95 % CI] | IQM [95 % CI] | success per seed | "
             "hand-over per seed | on the thick section | on the thin section | paper (3 M) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    lines += [row(name, c, paper(name)) for name, c in found.items()]
    csac = [n for n in found if n.startswith("csac_")]
    held = lambda name: HELD_SUFFIX if name.endswith(HELD_SUFFIX) else ""  # a held cell against held baselines
    pairs = [(a, b + held(a)) for a in csac for b in ("naive", "sac") if b + held(a) in found]
    if pairs:
        lines += ["", "| CSAC | baseline | P(CSAC > baseline), final success |", "|---|---|---|"]
        lines += [f"| {label(a)} | {label(b)} | {improvement(final(found[a], 'success'), final(found[b], 'success'))} |"
                  for a, b in pairs]
    if (out / SWEEP.name / "summary.json").exists():
        s = curves(out / SWEEP.name)
        lines += ["", f"Sweep ({SWEEP.total_steps:,} steps, seeds {SWEEP.seeds}): per ratio, final success / hand-over "
                      "/ thick-section hand-over, mean over its seeds; best: "
                      f"η = {best_swept_eta(out / SWEEP.name):g}.", "", "| η | success | hand-over | thick |",
                  "|---|---|---|---|"]
        for eta in sorted(set(s["eta"].tolist())):
            pick = s["eta"] == eta
            lines.append(f"| {eta:g} | " + " | ".join(f"{final(s, m)[pick].mean():.2f}"
                                                       for m in ("success", "handover", "grasp_thick")) + " |")
    lines += final_table({name: read_json(out / name / FINAL_EVAL) for name in found
                          if (out / name / FINAL_EVAL).exists()})
    lines += probe_table({name: (read_json(out / name / CRITIC_PROBE), read_json(out / name / STOCHASTIC_EVAL))
                          for name in found if (out / name / CRITIC_PROBE).exists()})
    text = "\n".join(lines) + "\n"
    write_text(out / "table.md", text)
    figure(found, out / "curves.png")
    print(text)
    return text


def main(args: Args) -> None:
    out = args.out or RESULTS / "peg_budget"
    if not args.report_only:
        names = [c.name for c in QUEUE] + ["best"] + [c.name for c in HELD]
        if args.cells and (unknown := sorted(set(args.cells) - set(names))):
            raise SystemExit(f"error: cells: unknown {unknown}; choose from {names}")
        for cell in QUEUE + ("best",) + HELD:
            if args.cells and (cell if cell == "best" else cell.name) not in args.cells:
                continue
            if cell == "best" and (cell := best_cell(out)) is None:
                print("best: the sweep has not finished (or picked 0.9, trained as csac_0.9)")
                continue
            run_grid(cell.config(args.smoke), out / cell.name, checkpoint_every=CHECKPOINT_EVERY,
                     keep_checkpoints=True)
            final_evaluation(out / cell.name, episodes=2 if args.smoke else FINAL_EPISODES)
    report(out)


if __name__ == "__main__":
    cli(main, Args, largest_grid=lambda a: None if a.report_only else 10)
