"""The run folder's files (docs/design.md#contracts): config.json, metrics.jsonl, summary.json.

A finished run's metrics.jsonl may be compacted into metrics.jsonl.gz (`compact_metrics`); every reader
goes through `read_rows` / `metrics_file`, which take either form.
"""
from __future__ import annotations

import gzip
import json
import math
import os
from pathlib import Path
from typing import Any, Iterable, Optional

import numpy as np

from ccp_jax import health
from ccp_jax.config import Config, ConfigError
from ccp_jax.health import DIVERGED

METRICS = "metrics.jsonl"
COMPACTED = METRICS + ".gz"
FINAL_WINDOW = 10  # reported success = mean over the last 10 epochs (docs/design.md#hyperparameters)


def strict(x: Any) -> Any:
    """`x` with every non-finite float (NaN, ±inf: a diverged loss or critic) as None, so the files are strict
    JSON (null) that any parser reads; numpy scalars and arrays become Python numbers and lists."""
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return x.item()
    if isinstance(x, np.ndarray):
        return strict(x.tolist())
    if isinstance(x, dict):
        return {k: strict(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [strict(v) for v in x]
    return x


def _dumps(obj: Any, **kwargs) -> str:
    return json.dumps(strict(obj), allow_nan=False, **kwargs)


def write_json(path: Path, obj: Any) -> None:
    """Writes atomically (temp file + rename), so a crash never leaves half a file."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(_dumps(obj, indent=2) + "\n")
    os.replace(tmp, path)


def read_config(run_dir: Path, field: str = "run_dir") -> Config:
    """The Config a run folder's config.json holds; a ConfigError naming `field` (the argument that gave the
    folder) where it holds none or an unreadable one."""
    path = Path(run_dir) / "config.json"
    try:
        return Config.from_dict(json.loads(path.read_text()))
    except (FileNotFoundError, NotADirectoryError):
        raise ConfigError(field, f"{run_dir} holds no run (no config.json)") from None
    except (json.JSONDecodeError, TypeError) as err:
        raise ConfigError(field, f"{path} is unreadable: {err}") from None


def eval_fields(ev, member: int) -> dict:
    """A member's evaluation fields of a metrics row from `EvalMetrics` (numpy, leading grid axis)."""
    fields = {"success_rate": float(ev.success_rate[member]), "eval_return": float(ev.eval_return[member]),
              "stage_reached_mean": float(ev.stage_reached_mean[member]),
              "stage_fraction": [float(v) for v in ev.stage_fraction[member]],
              "eval_episode_length": float(ev.episode_length[member])}
    if ev.end_metrics:  # env diagnostics at the evaluation episodes' end, e.g. the maze's `pocket`
        fields["eval_end"] = {k: float(v[member]) for k, v in ev.end_metrics.items()}
    return fields


def metric_rows(config: Config, epoch: int, metrics, wall_s: float) -> list[dict]:
    """One metrics.jsonl row per grid member from an epoch's metrics (numpy, leading grid axis).

    Every algorithm writes the same evaluation fields; the per-agent training
    fields are SAC's (`EpochMetrics`) or TP's (`TPEpochMetrics`, see `_tp_fields`); a PBT run adds its
    lineage (`pbt_fields`). "eta" is the member's ratios as the config gives them (under PBT: its start).
    """
    rows = []
    for member, (eta, seed) in enumerate(config.members):
        row = {
            "member": member, "seed": seed, "eta": list(eta), "algo": config.algo, "epoch": epoch,
            "env_steps": int(metrics.env_steps[member]),
            **eval_fields(metrics.eval, member),
            "train_success": float(metrics.train_success[member]),
            "train_episodes": int(metrics.train_episodes[member]),
            "train_stage_fraction": [float(v) for v in metrics.train_stage_fraction[member]],
        }
        row.update(_tp_fields(metrics, member) if config.algo == "tp" else _sac_fields(config, metrics, member))
        if getattr(metrics, "pbt", None) is not None:
            row.update(pbt_fields(metrics.pbt, member))
        row["epoch_wall_s"] = wall_s
        rows.append(row)
    return rows


def _sac_fields(config: Config, metrics, member: int) -> dict:
    n_agents = config.num_agents
    has_next = [config.algo == "csac" and n < n_agents - 1 for n in range(n_agents)]
    t = metrics.train
    per_agent = lambda x: [float(v) for v in x[member]]
    return {
        "q_loss": per_agent(t.q_loss), "pi_loss": per_agent(t.pi_loss), "alpha": per_agent(t.alpha),
        "log_prob": per_agent(t.log_prob), "q_min": per_agent(t.q_min), "q_max": per_agent(t.q_max),
        # η* needs a next critic; it is undefined (null) for the last agent.
        "eta_star": [float(v) if h else None for v, h in zip(t.eta_star[member], has_next)],
        "eta_used": per_agent(t.eta_used), "range_own": per_agent(t.range_own),
        "range_next": per_agent(t.range_next),
        "pull_own": per_agent(metrics.pull_own), "pull_next": per_agent(metrics.pull_next),
        "updated": per_agent(t.updated), "frozen": bool(metrics.frozen[member]),
        "buffer_fill": [int(v) / config.sac.buffer_size for v in metrics.buffer_size[member]],
    }


def pbt_fields(record, member: int) -> dict:
    """A member's PBT lineage from a `pbt.PbtRecord` (numpy, leading grid axis): the ratios it holds after the
    epoch's PBT step (those the next epoch trains with; `eta_used` has this epoch's), the member it copied at
    that step (-1: none) and its fitness (`pbt.fitness`, of its training episodes since the last ranking)."""
    return {"pbt_eta": [float(v) for v in record.eta[member]], "pbt_parent": int(record.parent[member]),
            "pbt_fitness": float(record.fitness[member])}


def _tp_fields(metrics, member: int) -> dict:
    """TP's training fields; lists have one entry per transition policy (into primitive 1 .. N−1)."""
    tp = metrics.tp
    per_policy = lambda x: [float(v) for v in x[member]]
    won, lost = tp.rollout.won, tp.rollout.lost
    return {
        "tp_eval_transition_fraction": float(metrics.eval_transition_fraction[member]),
        "tp_init_env_steps": int(metrics.init_env_steps[member]),
        "tp_samples": per_policy(tp.rollout.samples), "tp_handovers": per_policy(tp.rollout.handovers),
        "tp_forced": per_policy(tp.rollout.forced), "tp_won": per_policy(won), "tp_lost": per_policy(lost),
        # Fraction of labelled transitions whose primitive then succeeded (null: none labelled this epoch).
        "tp_handover_success": [float(w / (w + f)) if w + f > 0 else None for w, f in zip(won[member], lost[member])],
        "prox_loss": per_policy(tp.predictor.loss), "prox_success_mean": per_policy(tp.predictor.success_mean),
        "prox_failure_mean": per_policy(tp.predictor.failure_mean),
        "pi_loss": per_policy(tp.ppo.pi_loss), "v_loss": per_policy(tp.ppo.v_loss),
        "entropy": per_policy(tp.ppo.entropy), "approx_kl": per_policy(tp.ppo.approx_kl),
        "clip_frac": per_policy(tp.ppo.clip_frac),
        "tp_success_buffer": [int(v) for v in tp.success_buffer[member]],
        "tp_failure_buffer": [int(v) for v in tp.failure_buffer[member]],
        "tp_permanent_buffer": [int(v) for v in tp.permanent_buffer[member]],
    }


def append_rows(path: Path, rows: Iterable[dict]) -> None:
    with path.open("a") as f:
        for row in rows:
            f.write(_dumps(row) + "\n")
        f.flush()
        os.fsync(f.fileno())


def write_rows(path: Path, rows: Iterable[dict]) -> None:
    """Replaces the file's rows atomically."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text("".join(_dumps(row) + "\n" for row in rows))
    os.replace(tmp, path)


def metrics_file(run_dir: Path) -> Path:
    """A run folder's metrics: metrics.jsonl, or metrics.jsonl.gz where only the compacted form is there."""
    raw = Path(run_dir) / METRICS
    return raw if raw.exists() or not (compacted := raw.with_name(COMPACTED)).exists() else compacted


def _read_float(text: str) -> float:
    """A JSON number of a metrics file: one marked with `E` (which Python's json never writes) is a float32 written
    as its shortest decimal (`compact_metrics`), read back as that float32; any other as it is written."""
    return float(np.float32(float(text))) if "E" in text else float(text)


_ROWS = json.JSONDecoder(parse_float=_read_float)


def read_rows(path: Path, field: str = "run_dir") -> list[dict]:
    """The rows of a jsonl file (or of its gzip, `PATH.gz`, where PATH itself is not there); a last line without its
    newline is a row still being written and is left out.

    A missing file or a damaged complete line is a ConfigError naming `field` (the argument that gave the folder)
    and the file (and the line)."""
    path = Path(path)
    if path.suffix != ".gz" and not path.exists() and (compacted := path.with_name(path.name + ".gz")).exists():
        path = compacted
    if not path.is_file():
        raise ConfigError(field, f"{path.parent} has no {path.name}: not a run folder, or its metrics were deleted "
                                 "(restore them; a run cannot continue without the rows of its earlier epochs)")
    return _parse_rows(_decode(path.read_bytes(), path, field), path, field)


def _decode(data: bytes, path: Path, field: str) -> str:
    """The text of a metrics file's bytes, gunzipped if `path` is a .gz; an unreadable gzip is a ConfigError
    naming `field`."""
    if path.suffix != ".gz":
        return data.decode()
    try:
        return gzip.decompress(data).decode()
    except (OSError, EOFError, UnicodeDecodeError) as err:  # gzip.BadGzipFile is an OSError
        raise ConfigError(field, f"{path} is not a readable gzip file ({err}); repair or restore it") from None


def _parse_rows(text: str, path: Path, field: str) -> list[dict]:
    """The complete rows of a jsonl text (`read_rows`); `path` and `field` name a damaged line's file."""
    rows = []
    for number, line in enumerate(text.split("\n")[:-1], start=1):
        if not line.strip():
            continue
        try:
            rows.append(_ROWS.decode(line))
        except json.JSONDecodeError as err:
            raise ConfigError(field, f"{path} line {number} is not a JSON row ({err}); repair or remove it") from None
    return rows


def _float_text(x: float) -> str:
    """A float as `compact_metrics` writes it: a float32 value (the device's metrics, e.g. 0.30000001192092896) as
    its shortest float32 decimal marked with `E` (0.3E0), which `_read_float` widens back to the same value; a float
    whose decimal is that short already (0.5), or that is no float32 (wall times, ratios from the config), as json
    writes it."""
    if math.isfinite(x):
        with np.errstate(over="ignore"):
            single = np.float32(x)
        if float(single) == x:
            short = repr(float(np.format_float_scientific(single, unique=True)))
            marked = short.replace("e", "E") if "e" in short else short + "E0"
            if float(short) != x and _read_float(marked) == x:
                return marked
    return json.dumps(x)


def _compact_text(x: Any) -> str:
    """`json.dumps(x)` (same separators and escapes), with floats written by `_float_text`."""
    if isinstance(x, float):
        return _float_text(x)
    if isinstance(x, dict):
        return "{" + ", ".join(f"{json.dumps(k)}: {_compact_text(v)}" for k, v in x.items()) + "}"
    if isinstance(x, list):
        return "[" + ", ".join(_compact_text(v) for v in x) + "]"
    return json.dumps(x)


def compact_metrics(run_dir: Path) -> tuple[int, int]:
    """Rewrites a finished run's metrics.jsonl as metrics.jsonl.gz, about a seventh of the bytes; returns the
    metrics' bytes (before, after).

    Float32 values are written as their shortest decimal, marked so that `read_rows` reads back the very same
    float (`_float_text`); the rows read back are checked to be the original ones, value for value, before the
    raw file is deleted. The gzip has no name or time in it, so compacting the same rows again gives the same
    bytes, and an already compacted folder is left as it is (a plain gzip is rewritten compactly). Only a finished
    run (summary.json) is compacted: a running one still appends to metrics.jsonl.
    """
    run_dir = Path(run_dir)
    if not (run_dir / "summary.json").exists():
        raise ConfigError("run_dir", f"{run_dir} has no summary.json: only a finished run's metrics are compacted")
    source = metrics_file(run_dir)
    if not source.exists():
        raise ConfigError("run_dir", f"{run_dir} holds no {METRICS} to compact")
    data = source.read_bytes()
    text = _decode(data, source, "run_dir")
    if text and not text.endswith("\n"):
        raise ConfigError("run_dir", f"{source}'s last row has no newline (cut while written); repair it first")
    rows = _parse_rows(text, source, "run_dir")
    packed = gzip.compress("".join(_compact_text(r) + "\n" for r in rows).encode(), compresslevel=9, mtime=0)
    back = [_ROWS.decode(line) for line in gzip.decompress(packed).decode().splitlines()]
    # json's own text of a value is exact (every float's repr, NaN, int or bool, key order), so equal texts are
    # equal rows.
    if [json.dumps(r) for r in back] != [json.dumps(r) for r in rows]:
        raise RuntimeError(f"{source}: the compacted rows do not read back as the original ones; nothing changed")
    target = run_dir / COMPACTED
    if source != target or packed != data:
        tmp = target.with_name(COMPACTED + ".tmp")
        with tmp.open("wb") as f:  # on disk before the raw file goes
            f.write(packed)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    (run_dir / METRICS).unlink(missing_ok=True)
    return len(data), len(packed)


def complete_epochs(rows: list[dict], grid_size: int) -> int:
    """The last epoch E such that each of the epochs 1..E has a row for every one of the `grid_size` members."""
    members = {}
    for r in rows:
        members.setdefault(r["epoch"], set()).add(r["member"])
    epoch = 0
    while len(members.get(epoch + 1, ())) == grid_size:
        epoch += 1
    return epoch


def summarise(config: Config, rows: list[dict], wall_s: float | None = None) -> dict:
    """Per member: final success (mean of the last `FINAL_WINDOW` epochs), learning milestones, critic peaks; under
    PBT the ratios its last epoch left it with (`pbt_eta`)."""
    members = []
    for member, (eta, seed) in enumerate(config.members):
        mine = sorted((r for r in rows if r["member"] == member), key=lambda r: r["epoch"])
        success = [r["success_rate"] for r in mine]
        last = success[-FINAL_WINDOW:]
        first = next((r["env_steps"] for r in mine if r["success_rate"] > 0), None)
        members.append({
            "member": member, "seed": seed, "eta": list(eta), "algo": config.algo,
            "epochs": len(mine), "env_steps": mine[-1]["env_steps"] if mine else 0,
            "final_success": float(np.mean(last)) if last else math.nan,
            "final_return": float(np.mean([r["eval_return"] for r in mine[-FINAL_WINDOW:]])) if mine else math.nan,
            "best_success": max(success, default=math.nan),
            "first_success_env_steps": first,
            **critic_peaks(mine, DIVERGED * config.value_bound),
            **first_divergence(mine, config.value_bound),
            **({"pbt_eta": mine[-1]["pbt_eta"]} if mine and "pbt_eta" in mine[-1] else {}),
        })
    return {"final_window_epochs": FINAL_WINDOW, "q_bound": config.value_bound, "wall_s": wall_s, "members": members}


def critic_peaks(rows: list[dict], limit: float) -> dict:
    """`q_peak`: per agent, the largest batch maximum of its critic over a member's epochs (`rows`, in order);
    `q_diverged_env_steps`: the env steps of the first epoch where one was above `limit` or not finite.

    Both are None where no critic ever went above `limit` (the second) or the rows carry no critic values (TP's).
    """
    with_critics = [r for r in rows if r.get("q_max")]
    if not with_critics:
        return {"q_peak": None, "q_diverged_env_steps": None}
    q_max = np.array([[np.nan if q is None else q for q in r["q_max"]] for r in with_critics], np.float64)
    return {"q_peak": np.max(q_max, axis=0).tolist(),  # NaN where a critic went NaN (None once written)
            "q_diverged_env_steps": next((r["env_steps"] for r in with_critics
                                          if any(_above(q, limit) for q in r["q_max"])), None)}


def divergence(row: dict, bound: float) -> Optional[str]:
    """Why one epoch's row of a member shows a diverged learner (`health`'s rule, on the written numbers), or None
    for a healthy one. Rows without learner values (TP's) are healthy."""
    limit, loss_limit = health.limits(bound)
    for n, q in enumerate(row.get("q_max") or ()):
        if _above(q, limit):
            return _beyond(f"agent {n}'s critic", q, f"{limit:,.0f} ({DIVERGED:g} x the {bound:g} its rewards allow)")
    for n, loss in enumerate(row.get("q_loss") or ()):
        if _above(loss, loss_limit):
            return _beyond(f"agent {n}'s critic loss", loss, f"{loss_limit:,.0f}")
    for name in ("pi_loss", "alpha", "log_prob"):
        for n, x in enumerate(row.get(name) or ()):
            if x is None or not math.isfinite(x):
                return f"agent {n}'s {name} is not finite"
    return None


def first_divergence(rows: list[dict], bound: float) -> dict:
    """`diverged_env_steps`: the env steps of a member's first epoch (`rows`, in order) that `divergence` flags,
    and `diverged`: its reason (both None for a healthy member); `frozen_epochs`: how many epochs' updates the
    compiled epoch discarded as diverged (`health.diverged`)."""
    found = next(((r["env_steps"], why) for r in rows if (why := divergence(r, bound))), (None, None))
    return {"diverged_env_steps": found[0], "diverged": found[1],
            "frozen_epochs": sum(bool(r.get("frozen")) for r in rows)}


def _beyond(what: str, x: Optional[float], limit: str) -> str:
    """"what reached x, above limit", or "what is not finite" (None: a non-finite value once written)."""
    return f"{what} is not finite" if x is None or not math.isfinite(x) else f"{what} reached {x:.3g}, above {limit}"


def _above(q: float, limit: float) -> bool:
    """Whether a critic value is above `limit`; NaN (None once written) counts as above."""
    return q is None or not q <= limit


def eta_text(eta: list) -> str:
    """A member's per-agent ratios as "0.1,0.5,1" (or "auto,1")."""
    return ",".join(x if isinstance(x, str) else f"{x:g}" for x in eta)


def summary_table(summary: dict) -> str:
    """A plain-text table of the summary, one line per member; then a warning per diverged member."""
    etas = [eta_text(m["eta"]) if m["algo"] == "csac" else "-" for m in summary["members"]]
    # Where PBT moved a member's ratios: its start, then where it ended.
    etas = [e + ("→" + ",".join(f"{x:.3g}" for x in m["pbt_eta"]) if "pbt_eta" in m else "")
            for e, m in zip(etas, summary["members"])]
    width = max([14, *map(len, etas)])
    lines = [f"{'member':>6}  {'algo':<5}  {'eta':<{width}}  {'seed':>4}  {'final success':>13}  "
             f"{'final return':>12}  {'first success at':>16}"]
    for m, eta in zip(summary["members"], etas):
        first = "-" if m["first_success_env_steps"] is None else f"{m['first_success_env_steps']:,}"
        lines.append(f"{m['member']:>6}  {m['algo']:<5}  {eta:<{width}}  {m['seed']:>4}  {m['final_success']:>13.2f}  "
                     f"{m['final_return']:>12.1f}  {first:>16}")
    for m in summary["members"]:
        if m.get("diverged_env_steps") is not None:
            lines.append(diverged_warning(m["member"], m["seed"], m["diverged_env_steps"], m["diverged"]))
        elif m.get("q_diverged_env_steps") is not None:  # a summary written before the loss checks
            limit = DIVERGED * summary["q_bound"]
            peaks = [_beyond(f"agent {n}'s critic", q, f"{limit:,.0f}")
                     for n, q in enumerate(m["q_peak"]) if _above(q, limit)]
            lines.append(diverged_warning(m["member"], m["seed"], m["q_diverged_env_steps"], "; ".join(peaks)))
    return "\n".join(lines)


def diverged_warning(member: int, seed: int, env_steps: int, why: str) -> str:
    """The line that reports a diverged member, during training and under the final table."""
    return (f"warning: member {member} (seed {seed}) diverged at {env_steps:,} env steps: {why}; its diverged "
            "updates are discarded, so it keeps its last healthy parameters while the grid trains on (per epoch: "
            "frozen, q_max, q_loss in metrics.jsonl)")
