"""Compacts the metrics of every finished run folder under a root: metrics.jsonl -> metrics.jsonl.gz.

    python experiments/compact_results.py                      # experiments/results
    python experiments/compact_results.py --root runs/         # any folder of run folders

A run folder is one holding summary.json (finished) and metrics.jsonl or metrics.jsonl.gz.
`ccp_jax.outputs.compact_metrics` writes each float32 metric as its shortest decimal,
marked so that `outputs.read_rows` gives the very same float back, and gzips the rows
(about a seventh of the bytes); it checks every row read back against the original and
only then deletes the raw file. Every reader takes either form. Idempotent: a folder
compacted already is left byte for byte as it is. Folders still training (no
summary.json) are listed and left alone. Prints the bytes before and after, per folder
and in total.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import tyro

from ccp_jax import outputs
from ccp_jax.config import ConfigError

RESULTS = Path(__file__).resolve().parent / "results"


@dataclasses.dataclass
class Args:
    root: Path = RESULTS
    """The folder searched (recursively) for run folders."""


def run_folders(root: Path) -> tuple[list[Path], list[Path]]:
    """(finished run folders, folders still training) under `root`, sorted: those holding metrics, by summary.json."""
    folders = sorted({p.parent for name in (outputs.METRICS, outputs.COMPACTED) for p in Path(root).rglob(name)})
    finished = [f for f in folders if (f / "summary.json").exists()]
    return finished, [f for f in folders if f not in finished]


def main(args: Args) -> tuple[int, int]:
    """Compacts every finished run under `args.root`; returns the metrics' bytes (before, after) over all of them."""
    if not args.root.is_dir():
        raise ConfigError("root", f"{args.root} is not a folder")
    finished, training = run_folders(args.root)
    total_before = total_after = 0
    for folder in finished:
        before, after = outputs.compact_metrics(folder)
        total_before, total_after = total_before + before, total_after + after
        note = "compacted already" if before == after else f"{before:,} -> {after:,} bytes"
        print(f"{folder.relative_to(args.root)}: {note}")
    for folder in training:
        print(f"{folder.relative_to(args.root)}: no summary.json (still training?), left as it is")
    print(f"{len(finished)} finished runs: {total_before:,} -> {total_after:,} bytes of metrics")
    return total_before, total_after


if __name__ == "__main__":
    try:
        main(tyro.cli(Args))
    except ConfigError as err:
        raise SystemExit(f"error: {err}") from None
