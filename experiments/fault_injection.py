"""Faults a long run meets, injected into small CLI runs: does each one survive, get refused with the way out
named, or lose or corrupt data?

    python experiments/fault_injection.py                  # every fault, 4 random kills (about 10 minutes on 2 cores)
    python experiments/fault_injection.py --kills 10 --faults kill corrupt

Each case runs `python -m ccp_jax.train` (the `tiny` preset: 10 epochs of 200 steps, a checkpoint every 2)
in a subprocess, injects the fault, then does what a user would: `--resume` the folder, and where that is
refused, follow the way out the message names, once. The folder's final metrics.jsonl is compared with an
uninterrupted run's, row for row (wall times aside). Verdicts:

  survived         the resumed run's rows equal the uninterrupted run's
  refused          the resume stopped with one line naming the field and the way out, changing nothing;
                   following that way out, the run then survived ("refused -> survived")
  WRONG DATA       a run exited 0 with rows that differ from the uninterrupted run's
  LOST             a run exited 0 with epochs missing
  CRASH            a traceback instead of a message (a run that exits 0 is judged by its rows alone)

Faults: SIGKILL at a random epoch; SIGKILL while a checkpoint is being written; the newest checkpoint's
array bytes overwritten; metrics.jsonl cut inside its last row, short of its last rows, or before the oldest
checkpoint; the disk filling up (a size-limited tmpfs, where this process may mount one).
"""
from __future__ import annotations

import dataclasses
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import tyro

RUN = ["--preset", "tiny", "--total-steps", "2000", "--checkpoint-every", "2", "--no-progress", "--no-tensorboard"]
EPOCHS = 10
FAULTS = ("kill", "kill_in_checkpoint", "corrupt", "truncate", "disk_full")


@dataclasses.dataclass
class Args:
    faults: tuple[str, ...] = FAULTS
    """Which faults to inject (kill, kill_in_checkpoint, corrupt, truncate, disk_full)."""
    kills: int = 4
    """SIGKILLs at random epochs (and as many during checkpoint writes)."""
    seed: int = 0
    """Seed of the random kill times."""
    work: Optional[Path] = None
    """Folder for the runs (default: a fresh temporary folder, deleted at the end)."""


@dataclasses.dataclass
class Outcome:
    code: int
    output: str

    @property
    def refused(self) -> bool:
        """Stopped with one `error: field: ...` line, no traceback."""
        return self.code != 0 and "Traceback" not in self.output and "error: " in self.output

    @property
    def message(self) -> str:
        lines = [line for line in self.output.splitlines() if line.startswith("error: ")]
        return lines[-1] if lines else self.output.strip().splitlines()[-1] if self.output.strip() else ""


def train(args: list[str], wait: bool = True) -> Outcome | subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "ccp_jax.train", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    if not wait:
        return proc
    out = proc.communicate()[0]
    return Outcome(proc.returncode, out)


def rows(run: Path) -> list[dict]:
    path = run / "metrics.jsonl"
    if not path.exists():
        return []
    return [{k: v for k, v in json.loads(line).items() if k != "epoch_wall_s"}
            for line in path.read_text().splitlines() if line.strip()]


def kill_when(proc: subprocess.Popen, ready, timeout: float = 600.0) -> bool:
    """SIGKILLs `proc` as soon as `ready()` holds; False if the process ended first."""
    end = time.time() + timeout
    while time.time() < end and proc.poll() is None:
        if ready():
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            return True
        time.sleep(0.005)
    proc.wait()
    return False


def verdict(run: Path, reference: list[dict], last: Outcome) -> str:
    """What the folder holds after the user's last step (see the module docstring)."""
    if last.code != 0:
        return "refused" if last.refused else "CRASH" if "Traceback" in last.output else f"failed (exit {last.code})"
    got = rows(run)
    if got == reference:
        return "survived"
    if len(got) < len(reference) and got == reference[:len(got)]:
        return f"LOST: {len(got)} of {len(reference)} rows"
    return "WRONG DATA: rows differ from the uninterrupted run"


def resume(run: Path, reference: list[dict], way_out=None) -> tuple[str, str]:
    """Resumes `run`; if refused, applies `way_out(run)` (what the message names) and resumes once more.
    Returns the verdict and the first resume's message (empty if it exited 0)."""
    first = train(["--resume", str(run), "--no-progress"])
    message = first.message if first.code else ""
    if first.refused and way_out is not None:
        way_out(run)
        return "refused -> " + verdict(run, reference, train(["--resume", str(run), "--no-progress"])), message
    return verdict(run, reference, first), message


def newest_checkpoint(run: Path) -> Optional[Path]:
    steps = sorted((int(p.name), p) for p in (run / "checkpoints").iterdir() if p.name.isdigit()) \
        if (run / "checkpoints").is_dir() else []
    return steps[-1][1] if steps else None


def corrupt(folder: Path) -> str:
    """Overwrites the middle of the largest array file under `folder` with random bytes; names the file."""
    files = sorted((p for p in folder.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    victim = files[-1]
    data = bytearray(victim.read_bytes())
    start, n = len(data) // 3, max(1, len(data) // 3)
    data[start:start + n] = os.urandom(n)
    victim.write_bytes(bytes(data))
    return str(victim.relative_to(folder))


def move_newest_checkpoint_away(run: Path) -> None:
    newest = newest_checkpoint(run)
    shutil.move(str(newest), str(run / f"damaged_checkpoint_{newest.name}"))


def case_kill(work: Path, reference: list[dict], rng: random.Random) -> tuple[str, str, str]:
    epoch = rng.randint(1, EPOCHS - 1)
    run = work / f"kill_{epoch}_{rng.randrange(10 ** 6)}"
    proc = train(RUN + ["--out", str(run)], wait=False)
    killed = kill_when(proc, lambda: len(rows(run)) >= epoch)
    result, message = resume(run, reference)
    return f"SIGKILL after epoch {epoch}'s row" + ("" if killed else " (ended first)"), result, message


def case_kill_in_checkpoint(work: Path, reference: list[dict], rng: random.Random) -> tuple[str, str, str]:
    run = work / f"kill_ckpt_{rng.randrange(10 ** 6)}"
    skip = rng.randint(0, 3)  # which checkpoint write to interrupt
    seen: set[str] = set()

    def writing() -> bool:
        folder = run / "checkpoints"
        tmp = {p.name for p in folder.iterdir() if "tmp" in p.name} if folder.is_dir() else set()
        seen.update(tmp)
        return len(seen) > skip and bool(tmp)

    proc = train(RUN + ["--out", str(run)], wait=False)
    killed = kill_when(proc, writing)
    result, message = resume(run, reference, way_out=move_newest_checkpoint_away)
    return f"SIGKILL while checkpoint {skip + 1} is written" + ("" if killed else " (ended first)"), result, message


def case_corrupt(work: Path, reference: list[dict]) -> tuple[str, str, str]:
    run = work / "corrupt"
    proc = train(RUN + ["--out", str(run)], wait=False)
    kill_when(proc, lambda: len(rows(run)) >= 7)  # checkpoints 4 and 6 kept
    victim = corrupt(newest_checkpoint(run))
    result, message = resume(run, reference, way_out=move_newest_checkpoint_away)
    return f"newest checkpoint's bytes overwritten ({victim})", result, message


def case_truncate(work: Path, reference: list[dict], how: str) -> tuple[str, str, str]:
    run = work / f"truncate_{how}"
    proc = train(RUN + ["--out", str(run)], wait=False)
    kill_when(proc, lambda: len(rows(run)) >= 7)
    path = run / "metrics.jsonl"
    text = path.read_text()
    lines = text.splitlines(keepends=True)
    if how == "inside_last_row":
        path.write_text(text[:-len(lines[-1]) // 2])
        what = "metrics.jsonl cut inside its last row"
    elif how == "last_rows":
        path.write_text("".join(lines[:-2]))
        what = "metrics.jsonl short of its last 2 rows"
    else:
        path.write_text("".join(lines[:2]))
        what = "metrics.jsonl cut before the oldest checkpoint"
    result, message = resume(run, reference)
    return what, result, message


def case_disk_full(work: Path, reference: list[dict]) -> tuple[str, str, str]:
    mount = work / "small_disk"
    mount.mkdir()
    size = "600k"
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mount)],
                      capture_output=True).returncode:
        return "disk full", "skipped: cannot mount a tmpfs here", ""
    try:
        run = mount / "run"
        first = train(RUN + ["--out", str(run)])
        full = first.code != 0
        moved = work / "disk_full_run"
        shutil.copytree(run, moved)  # the user frees space: here, moves the folder to a larger disk
    finally:
        subprocess.run(["umount", str(mount)], capture_output=True)
    if not full:
        return f"disk full ({size})", "not reached: the run fitted", ""
    result, message = resume(moved, reference)
    return f"disk full ({size}): {first.message[:120]}", result, message


def main(args: Args) -> list[tuple[str, str, str]]:
    unknown = sorted(set(args.faults) - set(FAULTS))
    if unknown:
        raise SystemExit(f"error: faults: unknown {unknown}; choose from {FAULTS}")
    work = args.work or Path(tempfile.mkdtemp(prefix="ccp-faults-"))
    work.mkdir(parents=True, exist_ok=True)
    rng = random.Random(args.seed)
    done = train(RUN + ["--out", str(work / "reference")])
    if done.code:
        raise SystemExit(f"the uninterrupted run failed:\n{done.output[-2000:]}")
    reference = rows(work / "reference")
    results = []

    def record(case: tuple[str, str, str]) -> None:
        results.append(case)
        fault_text, result, message = case
        print(f"{fault_text:<60}  {result}" + (f"\n{'':<62}{message}" if message else ""), flush=True)

    try:
        for fault in args.faults:
            if fault == "kill":
                for _ in range(args.kills):
                    record(case_kill(work, reference, rng))
            elif fault == "kill_in_checkpoint":
                for _ in range(args.kills):
                    record(case_kill_in_checkpoint(work, reference, rng))
            elif fault == "corrupt":
                record(case_corrupt(work, reference))
            elif fault == "truncate":
                for how in ("inside_last_row", "last_rows", "before_oldest_checkpoint"):
                    record(case_truncate(work, reference, how))
            else:
                record(case_disk_full(work, reference))
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    print("\n| fault | outcome | message |\n|---|---|---|")
    for fault_text, result, message in results:
        print(f"| {fault_text} | {result} | {message.replace('|', '/')} |")
    return results


if __name__ == "__main__":
    main(tyro.cli(Args))
