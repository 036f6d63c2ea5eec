"""Table I's maze rows at the paper's budget (3 M env steps) on a CPU, on seeds never used for a choice.

    python experiments/paper_budget.py                         # trains (or resumes) the whole queue in order, then reports
    python experiments/paper_budget.py --cells maze2/sac       # one cell of the queue (or several)
    python experiments/paper_budget.py --seeds-per-grid 3      # split each cell's 5 seeds into grids of 3 and 2
    python experiments/paper_budget.py --cells maze3/naive --seeds 30 31   # two seeds now, the rest later
    python experiments/paper_budget.py --report-only           # table and curves from the runs as they stand

Settings: the paper's epoch (5000 env steps, 1000 updates), 3 M env steps, a
replay buffer of 1e6, the paper's hyperparameters, but [64, 64] networks (the
paper's RLkit [256, 256] costs 4-6x more per update on a CPU). Seeds 30-34:
every ratio below was chosen on seeds 0-14 at the `cpu` scale, never on these.

The queue, most informative first: 2 rooms SAC and Naive (does SAC solve it by
3 M, about 4x after CSAC; does Naive's success decay), CSAC at η = 0.1 (the
paper's best and ours); 3 rooms CSAC at η = 0.3 (ours) and 0.1 (the paper's),
Naive, SAC; 4 rooms CSAC at η = 0.5 (ours), 0.9 (the paper's), the per-agent
ramp (0.1, 0.3, 0.5), Naive, SAC; then 4 rooms CSAC at η = 0.1 (none of seeds 0-2
solved at 400 k, both of pbt_compare's fresh seeds 40-41 did).

Each cell trains as one vmapped grid into OUT/<domain>/<cell>/ (or
<cell>_seeds<a>to<b>/ per chunk of seeds), with a checkpoint every 25 epochs.
A stopped process loses at most 25 epochs: run the same command again and every
unfinished grid resumes from its latest checkpoint (finished ones are skipped).
Checkpoints hold the 1e6-transition buffers (gigabytes) and are deleted once a
grid finishes, after each member's final policy is exported to policies/ (tens
of kB each) and its metrics are compacted (metrics.jsonl.gz); commit the folder.
"""
from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path
from typing import Optional

from ccp_jax.config import make_config
from common import RESULTS, cli, export_policies, run_grid

SEEDS = tuple(range(30, 35))
TOTAL_STEPS = 3_000_000
CHECKPOINT_EVERY = 25
SETTINGS = dict(hidden=(64, 64), buffer_size=1_000_000, total_steps=TOTAL_STEPS)


@dataclasses.dataclass(frozen=True)
class Cell:
    """One method on one maze: its algorithm and ratio vectors (CSAC), trained on every seed."""

    domain: str
    name: str
    algo: str
    etas: tuple[tuple[float, ...], ...] = ((1.0,),)

    @property
    def rooms(self) -> int:
        return int(self.domain.removeprefix("maze"))

    @property
    def key(self) -> str:
        return f"{self.domain}/{self.name}"


QUEUE = (
    Cell("maze2", "sac", "sac"),
    Cell("maze2", "naive", "naive"),
    Cell("maze2", "csac_0.1", "csac", ((0.1,),)),
    Cell("maze3", "csac_0.3", "csac", ((0.3,),)),
    Cell("maze3", "csac_0.1", "csac", ((0.1,),)),
    Cell("maze3", "naive", "naive"),
    Cell("maze3", "sac", "sac"),
    Cell("maze4", "csac_0.5", "csac", ((0.5,),)),
    Cell("maze4", "csac_0.9", "csac", ((0.9,),)),
    Cell("maze4", "csac_ramp", "csac", ((0.1, 0.3, 0.5),)),
    Cell("maze4", "naive", "naive"),
    Cell("maze4", "sac", "sac"),
    # Beyond the cells: on 4 rooms η = 0.1 solved none of seeds 0-2 at 400 k (so 0.5 was picked) but
    # both fresh seeds 40-41 of pbt_compare's first sweep; seeds 30-34 say which holds at 3 M.
    Cell("maze4", "csac_0.1", "csac", ((0.1,),)),
)
CELLS = {cell.key: cell for cell in QUEUE}


@dataclasses.dataclass
class Args:
    cells: Optional[tuple[str, ...]] = None
    """Train only these cells (domain/name, e.g. maze2/sac), in the queue's order; default every cell."""
    seeds_per_grid: int = len(SEEDS)
    """Split each cell's seeds into grids of at most this many (each finishes sooner; a grid of 5 is fastest)."""
    seeds: tuple[int, ...] = SEEDS
    """The seeds to train (30-34: never used for a choice)."""
    total_steps: int = TOTAL_STEPS
    """Env steps per run (the paper's 3 M; a smaller budget writes into OUT/budget_<steps>/)."""
    out: Optional[Path] = None
    """Results folder (default experiments/results/paper_budget)."""
    report_only: bool = False
    """Never train: table and curves from whatever the folders hold."""

    @property
    def folder(self) -> Path:
        base = self.out or RESULTS / "paper_budget"
        return base if self.total_steps == TOTAL_STEPS else base / f"budget_{self.total_steps}"

    def chosen(self) -> list[Cell]:
        if self.cells and (unknown := sorted(set(self.cells) - set(CELLS))):
            raise SystemExit(f"error: cells: unknown {unknown}; choose from {list(CELLS)}")
        return [cell for cell in QUEUE if not self.cells or cell.key in self.cells]

    def chunks(self) -> list[tuple[int, ...]]:
        if self.seeds_per_grid < 1:
            raise SystemExit(f"error: seeds_per_grid: must be at least 1, got {self.seeds_per_grid}")
        n = self.seeds_per_grid
        return [tuple(self.seeds[i:i + n]) for i in range(0, len(self.seeds), n)]


def grid_folder(out: Path, cell: Cell, seeds: tuple[int, ...]) -> Path:
    """OUT/<domain>/<cell>/ for every seed of SEEDS at once, else <cell>_seeds<first>to<last>/."""
    name = cell.name if seeds == SEEDS else f"{cell.name}_seeds{seeds[0]}to{seeds[-1]}"
    return out / cell.domain / name


def cell_grids(out: Path, cell_name: str) -> list[Path]:
    """The grids of one cell that exist under OUT/<domain>/ (`out` is that folder): <cell>/ and its seed chunks
    <cell>_seeds<a>to<b>/ (`grid_folder`), finished or not, in name order."""
    return sorted(p for p in out.glob(f"{cell_name}*")
                  if p.name == cell_name or p.name.startswith(f"{cell_name}_seeds"))


def train(args: Args) -> None:
    for cell in args.chosen():
        for seeds in args.chunks():
            folder = grid_folder(args.folder, cell, seeds)
            if (folder / "metrics.jsonl.gz").exists():
                print(f"done already: {folder}")
            else:
                config = make_config("small", env="maze", rooms=cell.rooms, algo=cell.algo, etas=cell.etas,
                                     seeds=seeds, **{**SETTINGS, "total_steps": args.total_steps})
                run_grid(config, folder, checkpoint_every=CHECKPOINT_EVERY, keep_checkpoints=True)
            keep_policies(folder)


def keep_policies(folder: Path) -> None:
    """A finished grid's final policies into FOLDER/policies/ (`common.export_policies`), then its checkpoints
    deleted; nothing where they are gone already. Also on a grid found finished, so a process stopped between
    the two steps loses nothing."""
    if (folder / "summary.json").exists() and (folder / "checkpoints").is_dir():
        export_policies(folder)
        shutil.rmtree(folder / "checkpoints")


def largest_grid(args: Args) -> Optional[int]:
    """The largest grid this call trains (`common.cli` splits the CPU for it); None when it trains nothing."""
    if args.report_only:
        return None
    return max(len(cell.etas) for cell in args.chosen()) * max(len(c) for c in args.chunks())


def main(args: Args) -> None:
    if not args.report_only:
        train(args)
    import paper_budget_report  # matplotlib and the statistics: only once the training is done

    paper_budget_report.report(args.folder)


if __name__ == "__main__":
    cli(main, Args, largest_grid=largest_grid)
