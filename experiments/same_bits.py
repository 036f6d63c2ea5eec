"""Does a change keep what the trainer computes, bit for bit? Nine short CLI runs, then a comparison.

    python experiments/same_bits.py record OUT            # the runs, with the code as it is now (≈ 1-3 min)
    python experiments/same_bits.py compare REF NEW       # every metrics row and summary field equal, wall times aside

Record once before a refactor (e.g. from a `git worktree` of the old commit, with PYTHONPATH set to it), once
after, then compare. The runs cover CSAC with a shared ratio and `auto`, per-agent ratios on 3 rooms, the
trusted rule, Naive, SAC, the floor normaliser with one temperature, the ema normaliser with RLkit's init and
log π and the acting next action, population-based training (copies in every epoch), and TP on the Naive
run's agents. config.json is not compared (its format may change); metrics.jsonl(.gz) and summary.json are.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

RUNS = {
    "maze2_csac": "--preset small --rooms 2 --eta 0.1 auto --seeds 2 --total-steps 15000",
    "maze3_per_agent": "--preset small --rooms 3 --eta-per-agent 0.3,0.3 0.1,0.5 --seeds 1 --total-steps 10000",
    "trusted": "--preset tiny --rooms 3 --eta auto --eta-auto-rule trusted --seeds 2 --total-steps 2000",
    "naive": "--preset tiny --algo naive --rooms 2 --seeds 2 --total-steps 1000",
    "sac": "--preset tiny --algo sac --seeds 1 --total-steps 1000",
    "floor_own": "--preset tiny --rooms 3 --normaliser floor --coop-scale own --eta 0.3 --total-steps 1000",
    "ema_rlkit": ("--preset tiny --rooms 2 --normaliser ema --network-init rlkit --tanh-log-prob rlkit "
                  "--next-action acting --eta 0.5 --total-steps 1000"),
    "pbt": "--preset small --rooms 2 --eta 0.1 0.9 --seeds 2 --pbt-every 1 --total-steps 20000",
    "tp": "--preset tiny --algo tp --primitives {out}/naive --rooms 2 --seeds 1 --total-steps 1000",
}
WALL = {"epoch_wall_s", "wall_s"}


def record(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, flags in RUNS.items():  # in order: TP's primitives are the Naive run's
        if (out / name / "summary.json").exists():
            continue
        argv = [sys.executable, "-m", "ccp_jax.train", *flags.format(out=out).split(), "--out", str(out / name),
                "--no-progress", "--no-tensorboard", "--no-compile-cache"]
        done = subprocess.run(argv, capture_output=True, text=True)
        print(f"{name}: {'done' if done.returncode == 0 else 'FAILED ' + done.stderr[-500:]}")


def _rows(folder: Path) -> list[dict]:
    from ccp_jax import outputs

    rows = outputs.read_rows(outputs.metrics_file(folder))
    return sorted(({k: v for k, v in r.items() if k not in WALL} for r in rows), key=lambda r: (r["epoch"], r["member"]))


def _summary(folder: Path) -> dict:
    summary = json.loads((folder / "summary.json").read_text())
    return {k: v for k, v in summary.items() if k not in WALL}


def compare(ref: Path, new: Path) -> bool:
    same = True
    for name in RUNS:
        a, b = ref / name, new / name
        if missing := [f for f in (ref, new) if not (f / name / "summary.json").exists()]:
            print(f"{name}: missing in {', '.join(map(str, missing))}")
            same = False
            continue
        ra, rb = _rows(a), _rows(b)
        # Fields only one side has (added or removed by the change) are named, and every shared one compared.
        added = sorted({k for r in rb for k in r} - {k for r in ra for k in r}
                       | {f"summary.{k}" for m in _summary(b).get("members", []) for k in m}
                       - {f"summary.{k}" for m in _summary(a).get("members", []) for k in m})
        removed = sorted({k for r in ra for k in r} - {k for r in rb for k in r})
        shared = {k for r in ra for k in r} & {k for r in rb for k in r}
        ra = [{k: v for k, v in r.items() if k in shared} for r in ra]
        rb = [{k: v for k, v in r.items() if k in shared} for r in rb]
        sa, sb = _summary(a), _summary(b)
        for x, y in zip(sa.get("members", []), sb.get("members", [])):
            for k in set(x) ^ set(y):
                x.pop(k, None), y.pop(k, None)
        if ra == rb and sa == sb and len(ra) == len(rb):
            changes = "".join(f"; {what}: {', '.join(keys)}" for what, keys in (("new", added), ("gone", removed)) if keys)
            print(f"{name}: same ({len(ra)} rows){changes}")
            continue
        same = False
        first = next(((x["epoch"], x["member"], [k for k in x if x[k] != y.get(k)]) for x, y in zip(ra, rb) if x != y),
                     "the summaries or the row counts")
        print(f"{name}: DIFFERS at {first}")
    return same


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "record":
        record(Path(sys.argv[2]))
    elif len(sys.argv) == 4 and sys.argv[1] == "compare":
        sys.exit(0 if compare(Path(sys.argv[2]), Path(sys.argv[3])) else 1)
    else:
        sys.exit(__doc__)
