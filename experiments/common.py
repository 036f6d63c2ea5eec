"""What the experiment scripts share: budgets per scale, resumable grid runs, the paper's numbers.

Each script trains its grids through `ccp_jax.train.run` into
`OUT/<domain>/<name>/` (the usual config.json, metrics.jsonl, summary.json;
once a run is finished its metrics.jsonl is compacted into metrics.jsonl.gz,
`outputs.compact_metrics`), so any run folder can also be plotted or resumed by hand. A finished folder is
skipped, an interrupted one resumes from its last checkpoint; checkpoints are
deleted once a run is finished (they hold the replay buffers: gigabytes).
"""
from __future__ import annotations

import dataclasses
import json
import math
import shutil
import time
from pathlib import Path
from typing import Any, Callable, Literal, Optional, Sequence

import numpy as np
import tyro

from ccp_jax import checkpoint
from ccp_jax.config import Config, ConfigError, make_config
from ccp_jax.devices import split_host_cpu
from ccp_jax.eta import AUTO
from envs_mjx import configure_cpu

# Domains: (env, rooms); the paper's four, and Brax's pusher (issue 11). Peg and pusher have two fixed stages.
DOMAINS = {"maze2": ("maze", 2), "maze3": ("maze", 3), "maze4": ("maze", 4), "peg": ("peg", 2),
           "pusher": ("pusher", 2)}
# Per-domain settings on top of a scale: pusher episodes are brax's 200 steps (10 s), not the maze's 1000.
DOMAIN_OVERRIDES = {"pusher": dict(max_episode_steps=200)}
PAPER_ETAS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
# How tables name each algorithm (the paper's spelling).
ALGO_NAMES = {"csac": "CSAC", "sac": "SAC", "naive": "Naive", "tp": "TP"}

# The paper's Table I (success, mean of the last 10 epochs, 5 seeds; TP 3 seeds). None: not reported.
PAPER_TABLE1 = {
    "csac": {
        0.1: {"maze2": 1.00, "maze3": 0.62, "maze4": 0.00, "peg": 0.11},
        0.2: {"maze2": 1.00, "maze3": 0.23, "maze4": 0.00, "peg": 0.11},
        0.3: {"maze2": 1.00, "maze3": 0.07, "maze4": 0.00, "peg": 0.11},
        0.4: {"maze2": 0.31, "maze3": 0.00, "maze4": 0.00, "peg": 0.17},
        0.5: {"maze2": 0.05, "maze3": 0.06, "maze4": 0.00, "peg": 0.21},
        0.6: {"maze2": 0.17, "maze3": 0.04, "maze4": 0.00, "peg": 0.34},
        0.7: {"maze2": 0.42, "maze3": 0.40, "maze4": 0.17, "peg": 0.31},
        0.8: {"maze2": 0.51, "maze3": 0.16, "maze4": 0.50, "peg": 0.37},
        0.9: {"maze2": 0.06, "maze3": 0.21, "maze4": 0.79, "peg": 0.40},
    },
    "sac": {"maze2": 1.00, "maze3": 0.00, "maze4": 0.00, "peg": 0.11},
    "naive": {"maze2": 0.54, "maze3": 0.20, "maze4": 0.14, "peg": 0.13},
    "tp": {"maze2": 0.43, "maze3": 0.50, "maze4": 0.40, "peg": None},
}
# The paper's independent-ratio result on 3 rooms (10 seeds).
PAPER_INDEPENDENT = {"best_pair": (0.1, 1.0), "best_pair_success": 0.78, "best_shared_success": 0.54}


@dataclasses.dataclass(frozen=True)
class Scale:
    """A budget: preset, seeds, ratios and env steps per domain."""

    preset: str
    seeds: int
    etas: tuple[float | str, ...]
    total_steps: dict[str, int]
    overrides: dict = dataclasses.field(default_factory=dict)

    def config(self, domain: str, algo: str, etas: Sequence[Sequence[float | str]] = ((0.1,),),
               seeds: Optional[int] = None, first_seed: int = 0, **changes) -> Config:
        """The grid config of one (domain, algo) call at this scale: seeds first_seed, first_seed + 1, ...

        `changes` override any field, the scale's budget (`total_steps`) included."""
        env, rooms = DOMAINS[domain]
        seeds = tuple(range(first_seed, first_seed + (self.seeds if seeds is None else seeds)))
        return make_config(self.preset, env=env, rooms=rooms, algo=algo, etas=tuple(tuple(e) for e in etas),
                           seeds=seeds, **{"total_steps": self.total_steps[domain], **self.overrides,
                                           **DOMAIN_OVERRIDES.get(domain, {}), **changes})


SCALES = {
    # The paper's budget (docs/design.md#hyperparameters): [256, 256] nets, 1e6 buffers, 3M maze steps, 5 seeds.
    "paper": Scale("paper", seeds=5, etas=PAPER_ETAS + (AUTO,),
                   total_steps={"maze2": 3_000_000, "maze3": 3_000_000, "maze4": 3_000_000, "peg": 3_000_000,
                                "pusher": 3_000_000}),
    # What a 2-core CPU affords (measured, see experiments/README.md): the learning yardstick's [64, 64]
    # settings, 3 seeds, five of the nine ratios, budgets where the 2-room maze is learnt.
    "cpu": Scale("small", seeds=3, etas=(0.1, 0.3, 0.5, 0.7, 0.9, AUTO),
                 total_steps={"maze2": 150_000, "maze3": 300_000, "maze4": 400_000, "peg": 100_000,
                              "pusher": 100_000}),
    # Seconds: checks that a script runs end to end (used by the tests).
    "smoke": Scale("tiny", seeds=2, etas=(0.1, AUTO),
                   total_steps={"maze2": 400, "maze3": 400, "maze4": 400, "peg": 200, "pusher": 200}),
}
ScaleName = Literal[tuple(SCALES)]  # the keys of SCALES, as a CLI choice (tyro reads it at run time)
# Where the scripts keep their results by default: this folder's results/, wherever they are run from.
RESULTS = Path(__file__).resolve().parent / "results"


def results_folder(out: Optional[Path], name: str, scale: str, domains: Sequence[str] = ()) -> Path:
    """`out`, or experiments/results/<name>_<scale> (`RESULTS`); exits with a message naming an unknown domain."""
    check_domains(domains)
    return out or RESULTS / f"{name}_{scale}"


def check_domains(domains: Sequence[str]) -> None:
    """Exits with a message naming the field if a domain is unknown."""
    unknown = [d for d in domains if d not in DOMAINS]
    if unknown:
        raise SystemExit(f"error: domains: unknown {unknown}; choose from {tuple(DOMAINS)}")


def run_grid(config: Config, out: Path, checkpoint_every: int = 10, log=print, keep_checkpoints: bool = False) -> dict:
    """Trains `config` in `out`, or resumes it, or returns its summary if it is finished.

    A folder holding a different config is refused (ConfigError naming the field), never overwritten.
    Checkpoints are deleted once the run is finished unless `keep_checkpoints` (TP's primitives need them).
    """
    # heavy (jax): imported when a grid actually runs
    from ccp_jax import outputs, train

    summary_path, config_path = out / "summary.json", out / "config.json"
    if config_path.exists():
        saved = outputs.read_config(out)
        if changed := saved.differing(config):
            name = changed[0]
            raise ConfigError(name, f"{out} holds a run with {saved.flat()[name]!r}, this "
                                    f"experiment needs {config.flat()[name]!r}; use another --out")
        if summary_path.exists():
            log(f"done already: {out}")
            return read_json(summary_path)
    resume = False
    if config_path.exists():
        mngr = checkpoint.manager(out)
        resume = mngr.latest_step() is not None
        mngr.close()
    if not resume:  # nothing to resume from: (re)start the run
        for name in ("config.json", outputs.METRICS, outputs.COMPACTED):
            (out / name).unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    log(f"{'resuming' if resume else 'training'} {config.algo} on {config.task.env}"
        f"{'-' + str(config.task.rooms) if config.task.env == 'maze' else ''} x{config.grid_size} -> {out}")
    train.enable_compile_cache()
    start = time.time()
    summary = train.run(config, out, progress=True, resume=resume, checkpoint_every=checkpoint_every,
                        tensorboard=False)
    if not keep_checkpoints:
        shutil.rmtree(out / "checkpoints", ignore_errors=True)
    before, after = outputs.compact_metrics(out)  # committed results stay small; the CLI's own runs stay raw
    log(f"compacted {outputs.METRICS}: {before:,} -> {after:,} bytes")
    log(f"finished {out} in {time.time() - start:.0f} s")
    return summary


def export_policies(folder: Path) -> None:
    """Each member's final chain of stage policies as a `ccp_jax.export` artefact, FOLDER/policies/member<K>.jaxexport
    (tens of kB each, committed with the results), so a grid's episodes can be looked at after its checkpoints
    (gigabytes of replay buffers) are deleted."""
    from ccp_jax import export, outputs

    for member in range(outputs.read_config(folder).grid_size):
        exported, meta = export.export_chain(folder, member, platforms=("cpu",))
        export.write(exported, {**meta, "run_dir": folder.name}, folder / "policies" / f"member{member}.jaxexport")


def swept_folder(out: Path, domain: str, etas: Optional[Sequence[float | str]] = None) -> Path:
    """Where table1.py trains a shared-ratio CSAC sweep: csac/ for the scale's ratios, csac_etas_<ratios>/ for `etas`."""
    return out / domain / ("csac" if etas is None else "csac_etas_" + "-".join(eta_label(e) for e in etas))


def swept_runs(out: Path, domain: str) -> list[Path]:
    """The finished shared-ratio CSAC runs of a domain: csac/ first, then every csac_etas_*/ subset, sorted."""
    folders = [out / domain / "csac", *sorted((out / domain).glob("csac_etas_*"))]
    return [f for f in folders if (f / "summary.json").exists()]


def merged_summary(folders: Sequence[Path], in_progress: bool = False) -> Optional[dict]:
    """The members of several runs' summary.json as one summary (None for no folder).

    An (eta vector, seed) found in several runs counts once, from the first folder
    listed; each member carries its run's folder (`run`) and that run's `wall_s`.
    Runs whose settings differ beyond grid and budget are different experiments: a
    member in two of them raises ValueError naming the fields (as `plot.load_curves`).
    With `in_progress`, a folder without summary.json (a run still training) is
    summarised from its metrics.jsonl so far, as the trainer will summarise it
    (`wall_s` None; final success = the mean of the last evaluations logged).
    """
    from ccp_jax import outputs
    from ccp_jax.plot import refuse_to_pool

    if not folders:
        return None
    seen, members = {}, []
    for folder in folders:
        settings = outputs.read_config(folder)
        if in_progress and not (Path(folder) / "summary.json").exists():
            summary = outputs.summarise(settings, outputs.read_rows(outputs.metrics_file(folder)))
        else:
            summary = read_json(Path(folder) / "summary.json")
        for m in summary["members"]:
            key = (tuple(m["eta"]), m["seed"])
            if key in seen:
                refuse_to_pool(*seen[key], folder, settings, f"eta {list(key[0])} seed {key[1]}",
                               ": they are different experiments")
                continue
            seen[key] = folder, settings
            members.append({**m, "run": str(folder), "wall_s": summary.get("wall_s")})
    return {"members": members}


def rows_by_member(folder: Path, field: str = "run_dir", complete_epochs: bool = False) -> dict[int, list[dict]]:
    """{member: its metrics rows in epoch order} of a run folder (finished or training), members in order; with
    `complete_epochs`, every member cut to the epochs all of them have logged. `field` names the argument that gave
    the folder in a read error (`outputs.read_rows`)."""
    from ccp_jax import outputs

    by_member: dict[int, list[dict]] = {}
    for row in outputs.read_rows(outputs.metrics_file(folder), field=field):
        by_member.setdefault(row["member"], []).append(row)
    epochs = min((len(rows) for rows in by_member.values()), default=0) if complete_epochs else None
    return {m: sorted(by_member[m], key=lambda r: r["epoch"])[:epochs] for m in sorted(by_member)}


def final_ends(folder: Path) -> dict[int, tuple[float, Optional[float]]]:
    """{member: (stage, pocket)} of a run, means over the last 10 evaluations (the final success's window): the
    1-based stage the evaluation episodes end in (N: the last, the goal's), and the fraction that end in a maze's
    dead-end pocket (None for runs without that metric). Where a member that never succeeds gets stuck."""
    from ccp_jax import outputs

    ends = {}
    for member, rows in rows_by_member(folder).items():
        last = rows[-outputs.FINAL_WINDOW:]
        pockets = [r["eval_end"]["pocket"] for r in last if "pocket" in r.get("eval_end", {})]
        ends[member] = (1.0 + float(np.mean([r["stage_reached_mean"] for r in last])),
                        float(np.mean(pockets)) if len(pockets) == len(last) else None)
    return ends


def best_swept_eta(summary: dict) -> Optional[tuple]:
    """The numeric ratio vector (auto excluded) with the best mean final success; ties (e.g. all 0.00) go to
    the best mean final return, i.e. the agents that got furthest. None if there is no numeric ratio."""
    by_eta: dict[tuple, list[tuple[float, float]]] = {}
    for m in summary["members"]:
        if AUTO not in m["eta"]:
            by_eta.setdefault(tuple(m["eta"]), []).append((m["final_success"], m["final_return"]))
    return max(sorted(by_eta), key=lambda eta: tuple(np.mean(by_eta[eta], axis=0)), default=None)


def final_success(summary: dict) -> dict[tuple, list[float]]:
    """{eta vector: [final success per seed]} of a summary."""
    by_eta: dict[tuple, list[float]] = {}
    for m in summary["members"]:
        by_eta.setdefault(tuple(m["eta"]), []).append(m["final_success"])
    return by_eta


def success_at(series: Sequence[tuple[np.ndarray, np.ndarray]], steps: int) -> list[float]:
    """The value each member logged at env step `steps` (members that had not reached it are left out)."""
    return [float(v[np.searchsorted(s, steps)]) for s, v in series if steps in s]


def mean_std(values: Sequence[float]) -> str:
    """'0.67 ± 0.47' (population std over seeds), or '–' for no values."""
    if not values:
        return "–"
    return f"{np.mean(values):.2f} ± {np.std(values):.2f}"


def with_interval(values: Sequence[float], aggregate: Callable[[Sequence[float]], float]) -> str:
    """'0.98 [0.95, 1.00]': `aggregate` (e.g. `stats.iqm`) of the seeds' values and its 95 % stratified-bootstrap
    interval."""
    from ccp_jax import stats

    low, high = stats.bootstrap_ci(values, aggregate)
    return f"{aggregate(values):.2f} [{low:.2f}, {high:.2f}]"


def mean_and_iqm(values: Sequence[float]) -> str:
    """Two table cells: the seeds' mean and their IQM, each with its 95 % stratified-bootstrap interval."""
    from ccp_jax import stats

    return f"{with_interval(values, np.mean)} | {with_interval(values, stats.iqm)}"


def improvement(x: Sequence[float], y: Sequence[float]) -> str:
    """'0.62 [0.25, 1.00]': P(a seed of x ends above a seed of y; ties count half) and its 95 % bootstrap interval."""
    from ccp_jax import stats

    low, high = stats.probability_of_improvement_ci(x, y)
    return f"{stats.probability_of_improvement(x, y):.2f} [{low:.2f}, {high:.2f}]"


def eta_label(eta: float | str) -> str:
    return eta if isinstance(eta, str) else f"{eta:g}"


def fmt(x: Optional[float]) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.2f}"


def read_json(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def cli(main: Callable[[Any], Any], args_type: type, errors: tuple[type[Exception], ...] = (ConfigError,),
        largest_grid: Optional[Callable[[Any], Optional[int]]] = None) -> None:
    """Runs a script's `main` on its parsed command line, as `python -m ccp_jax.train` runs: the CPU split
    into several devices (`ccp_jax.devices`), and bad input (`errors`) ending in one line naming the
    field (`error: seeds: ...`), not a traceback.

    One process cannot split the CPU again between grids, so it is split for the largest grid the call may
    train, `largest_grid(args)` (None: the script trains nothing), which takes most of its time: an exposed
    device that grid left idle would slow it (a 2-room grid of 6 on the 2-core CPU, which uses 2 devices:
    8.5 s per epoch with 2 exposed, 10.2–10.3 s with 3 or 4). Smaller grids of the same call then
    share those devices. Without `largest_grid`: twice the cores, for `grid_devices` to choose from."""
    try:
        args = tyro.cli(args_type)
        configure_cpu()  # before anything starts JAX: MJX's XLA flag
        split_host_cpu("auto", largest_grid(args) if largest_grid else None)
        main(args)
    except errors as err:
        raise SystemExit(f"error: {err}") from None
