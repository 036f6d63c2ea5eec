"""Figures from run folders (docs/design.md#contracts): learning curves over seeds, ratio-sweep heatmaps and
a PBT run's lineage (docs/pbt.md).

    python -m ccp_jax.plot RUN_DIR [RUN_DIR ...] [--out FILE.png] [--metric success_rate]
    python -m ccp_jax.plot RUN_DIR --lineage

Figures are built on `matplotlib.figure.Figure` with the Agg canvas, never through
pyplot, so plotting is headless and leaves matplotlib's global backend alone.
"""
from __future__ import annotations

import argparse
import hashlib
import json
from collections import defaultdict
from pathlib import Path
from typing import NamedTuple, Optional, Sequence

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter
from PIL import Image

from ccp_jax import outputs
from ccp_jax.config import Config, ConfigError

# Config fields that say which members a run holds and how long it trains, not what it trains.
GRID_FIELDS = ("etas", "seeds", "total_steps")
Group = tuple[str, str, tuple[float | str, ...]]  # (task, algo, eta vector; "auto" for a running η*)
Series = tuple[np.ndarray, np.ndarray]  # (env_steps int64[E], values float64[E]) of one member


def new_figure(width: float = 6.4, height: float = 4.0) -> Figure:
    """A figure on the Agg canvas (inches)."""
    fig = Figure(figsize=(width, height), dpi=120, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


RENDER_KEY = "Render"  # the PNG text field holding the hash of the drawn pixels


def save_figure(fig: Figure, path: str | Path) -> bool:
    """Save `fig` at `path` (its format by its suffix) unless a PNG there already holds the same pixels; True
    if written.

    A PNG carries the SHA-256 of the drawn RGBA pixels in its text field "Render", which a lossy
    re-compression (pngquant) keeps, so a report that re-draws unchanged results leaves committed figures as
    they are instead of rewriting them with new bytes. Other formats are always written."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        fig.savefig(path)
        return True
    fig.canvas.draw()
    digest = hashlib.sha256(np.asarray(fig.canvas.buffer_rgba()).tobytes()).hexdigest()
    if path.is_file():
        try:
            with Image.open(path) as old:
                if getattr(old, "text", {}).get(RENDER_KEY) == digest:
                    return False
        except OSError:  # not an image we can read: replaced
            pass
    fig.savefig(path, metadata={RENDER_KEY: digest})
    return True


def save_figure_and_say(fig: Figure, path: str | Path) -> Path:
    """`save_figure`, then print whether the file was written or left unchanged; returns `path`."""
    print(f"{'wrote' if save_figure(fig, path) else 'unchanged:'} {path}")
    return Path(path)


def _task(config: Config) -> str:
    return f"{config.task.env}-{config.num_stages}" if config.task.env == "maze" else config.task.env


def _value(row: dict, metric: str) -> Optional[float]:
    """The row's `metric`; 'name/k' picks agent k of a per-agent list, 'name/key' an entry of a dict (eval_end's
    env diagnostics: eval_end/pocket, eval_end/grasp_thick). None when undefined (η* of the last agent)."""
    name, _, part = metric.partition("/")
    if name not in row:
        raise ConfigError("metric", f"{name!r} is not in metrics.jsonl; it has {sorted(row)}")
    value = row[name]
    if isinstance(value, list):
        if not (part.isdigit() and int(part) < len(value)):
            raise ConfigError("metric", f"{name!r} is per agent; write {name}/K for agent K "
                                        f"(0..{len(value) - 1}), got {metric!r}")
        value = value[int(part)]
    elif isinstance(value, dict):
        if part not in value:
            raise ConfigError("metric", f"{name!r} holds {sorted(value)}; write {name}/NAME for one of them, "
                                        f"got {metric!r}")
        value = value[part]
    elif part:
        raise ConfigError("metric", f"{name!r} is one number per epoch, not per agent; write {name}, got {metric!r}")
    return None if value is None else float(value)


def refuse_to_pool(first_dir: Path, first: Config, run_dir: Path, settings: Config, member: str, hint: str) -> None:
    """ValueError if two run folders that both hold `member` differ in settings beyond grid and budget
    (`GRID_FIELDS`): they are different experiments, whose seeds must not be pooled."""
    if differ := first.differing(settings, ignore=GRID_FIELDS):
        raise ValueError(f"{first_dir} and {run_dir} both hold {member} but differ in {', '.join(differ)}{hint}")


def load_curves(run_dirs: Sequence[str | Path], metric: str = "success_rate") -> dict[Group, list[Series]]:
    """Per (task, algo, eta vector): one (env_steps int64[E], values float64[E]) series per grid member.

    Members of the same group from several run folders are pooled (e.g. seeds trained in
    separate runs); a (group, seed) found in several runs counts once, from the first run
    listed. Runs whose settings differ beyond the grid and budget (e.g. `--normaliser`) are
    different experiments: a (group, seed) in two of them raises ValueError (draw them
    apart with `main`'s --labels). Rows where the metric is undefined are dropped.
    """
    groups: dict[Group, list[Series]] = defaultdict(list)
    seen: dict[tuple[Group, int], tuple[Path, Config]] = {}
    for run_dir in map(Path, run_dirs):
        settings = outputs.read_config(run_dir)  # a field an older run's file lacks compares as its default
        members: dict[int, list[dict]] = defaultdict(list)
        for row in outputs.read_rows(outputs.metrics_file(run_dir)):
            members[row["member"]].append(row)
        for rows in members.values():
            rows.sort(key=lambda r: r["epoch"])
            points = [(r["env_steps"], v) for r in rows if (v := _value(r, metric)) is not None]
            steps = np.asarray([s for s, _ in points], np.int64)
            values = np.asarray([v for _, v in points], np.float64)
            group, seed = (_task(settings), rows[0]["algo"], tuple(rows[0]["eta"])), rows[0]["seed"]
            if (group, seed) in seen:
                refuse_to_pool(*seen[group, seed], run_dir, settings, f"{group_label(group)} seed {seed}",
                               "; give each run its own label (--labels)")
                continue
            seen[group, seed] = run_dir, settings
            groups[group].append((steps, values))
    return dict(groups)


def group_label(group: Group, show_task: bool = False) -> str:
    """'csac η=0.1' (cooperative agents' ratios; the last agent's is always 1), or the algo alone."""
    task, algo, eta = group
    label = algo
    if algo.startswith("csac"):
        coop = eta[:-1] or eta
        label += " η=" + ",".join(x if isinstance(x, str) else f"{x:g}" for x in coop)
    return f"{task} {label}" if show_task else label


def variant_label(label: str, group: Group, groups: dict[Group, list[Series]]) -> str:
    """A user's name for a set of run folders; with the group's algo and ratio when those folders hold several."""
    return label if len(groups) == 1 else f"{label}, {group_label(group)}"


def _steps_label(x: float, _) -> str:
    """Axis ticks of env steps: 150k, 3M."""
    return f"{x / 1e6:g}M" if x >= 1e6 else f"{x / 1e3:g}k" if x >= 1e3 else f"{x:g}"


def group_order(group: Group) -> tuple:
    """Sort key: task, algo, then numeric ratios before "auto"."""
    task, algo, eta = group
    return task, algo, [(1, 0.0) if isinstance(x, str) else (0, x) for x in eta]


def mean_std(series: Sequence[Series]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(steps[S], mean[S], std[S], count[S]) over members at every env-step value any member logged.

    Members with shorter runs simply stop contributing, so the tail may average fewer seeds.
    """
    by_step: dict[int, list[float]] = defaultdict(list)
    for steps, values in series:
        for s, v in zip(steps.tolist(), values.tolist()):
            by_step[s].append(v)
    steps = np.asarray(sorted(by_step), dtype=np.int64)
    vals = [np.asarray(by_step[s]) for s in steps.tolist()]
    return (steps, np.asarray([v.mean() for v in vals]), np.asarray([v.std() for v in vals]),
            np.asarray([len(v) for v in vals]))


def _metric_label(metric: str) -> str:
    """Axis label: "stage_fraction/k" (metrics of the k-th stage index) reads as stage k + 1 reached."""
    name, _, k = metric.partition("/")
    if name in ("stage_fraction", "train_stage_fraction") and k:
        episodes = "training episodes" if name.startswith("train") else "evaluations"
        return f"fraction of {episodes} reaching stage {int(k) + 1}"
    if name == "eval_end" and k:
        return f"evaluations ending with {k.replace('_', ' ')}"
    return metric.replace("_", " ")


def curves(groups: dict[Group, list[Series]], metric: str = "success_rate",
           ax: Optional[Axes] = None, title: Optional[str] = None,
           colors: Optional[dict[str, str]] = None) -> Figure:
    """Mean ± std over members of each group vs env steps, one line per group (from `load_curves`).

    Draws into `ax` if given (e.g. a subplot of an experiments figure), else a new figure; `colors` maps a
    group's label (`group_label`) to its colour (default: matplotlib's cycle), so that panels side by side
    can draw a variant alike (`line_colors`). Returns the figure drawn into.
    """
    if ax is None:
        ax = new_figure().add_subplot()
    show_task = len({g[0] for g in groups}) > 1
    fraction = metric == "success_rate" or "stage_fraction" in metric  # fractions of episodes
    for group in sorted(groups, key=group_order):
        steps, mean, std, count = mean_std(groups[group])
        label = group_label(group, show_task)
        line, = ax.plot(steps, mean, color=(colors or {}).get(label), label=f"{label} (n={count.max(initial=0)})")
        low, high = (np.clip(mean - std, 0, 1), np.clip(mean + std, 0, 1)) if fraction else (mean - std, mean + std)
        ax.fill_between(steps, low, high, color=line.get_color(), alpha=0.2, linewidth=0)
    ax.set_xlabel("environment steps")
    ax.xaxis.set_major_formatter(FuncFormatter(_steps_label))
    ax.set_ylabel(_metric_label(metric))
    if fraction:
        ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    if title:
        ax.set_title(title)
    return ax.figure


# After matplotlib's 10-colour cycle, for figures with more variants than that.
EXTRA_COLORS = ["black", "gold", "teal", "navy", "lime", "maroon"]


def line_colors(panels: Sequence[dict[Group, list[Series]]]) -> dict[str, str]:
    """One colour of matplotlib's cycle per group label over several panels' groups, in the order the
    panels draw them, for `curves(colors=...)`."""
    labels = dict.fromkeys(group_label(g) for groups in panels for g in sorted(groups, key=group_order))
    palette = [f"C{i}" for i in range(10)] + EXTRA_COLORS
    return {label: palette[i % len(palette)] for i, label in enumerate(labels)}


def ratio_cells(run_dirs: Sequence[str | Path], key: str = "final_success") -> dict[tuple[float, float], list[float]]:
    """{(η1, η2): [`key` per seed]} from the summary.json of runs of a 3-stage task (eta vectors (η1, η2, 1)).

    Members with an "auto" ratio are left out; a (pair, seed) found in several
    runs counts once, from the first run listed.
    """
    cells: dict[tuple[float, float], dict[int, float]] = defaultdict(dict)
    for run_dir in map(Path, run_dirs):
        for m in json.loads((Path(run_dir) / "summary.json").read_text())["members"]:
            if len(m["eta"]) < 3:
                raise ValueError(f"{run_dir}: eta {m['eta']} has no independent (η1, η2) pair")
            pair = tuple(m["eta"][:2])
            if all(isinstance(x, (int, float)) for x in pair):
                cells[pair].setdefault(m["seed"], m[key])
    return {pair: list(by_seed.values()) for pair, by_seed in cells.items()}


def ratio_table(cells: dict[tuple[float, float], list[float]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(eta1[A], eta2[B], values[A, B]) from `ratio_cells`' output: the mean over seeds per (η1, η2); NaN where none."""
    eta1, eta2 = sorted({a for a, _ in cells}), sorted({b for _, b in cells})
    values = np.full((len(eta1), len(eta2)), np.nan)
    for (a, b), v in cells.items():
        values[eta1.index(a), eta2.index(b)] = np.mean(v)
    return np.asarray(eta1), np.asarray(eta2), values


def ratio_grid(run_dirs: Sequence[str | Path], key: str = "final_success") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(eta1[A], eta2[B], values[A, B]): `key` averaged over seeds per (η1, η2) of the runs, see `ratio_cells`."""
    return ratio_table(ratio_cells(run_dirs, key))


def heatmap(values: np.ndarray, eta1: Sequence[float], eta2: Sequence[float], ax: Optional[Axes] = None,
            label: str = "final success", title: Optional[str] = None, vmin: float = 0.0,
            vmax: float = 1.0) -> Figure:
    """values[i, j] at (η1 = eta1[i], η2 = eta2[j]) as annotated cells; η1 on the y axis, η2 on x.

    NaN cells (not trained) stay blank. Returns the figure drawn into.
    """
    values = np.asarray(values, dtype=float)
    if values.shape != (len(eta1), len(eta2)):
        raise ValueError(f"values has shape {values.shape}, expected ({len(eta1)}, {len(eta2)})")
    if ax is None:
        ax = new_figure(1.2 + 0.7 * len(eta2), 1.0 + 0.6 * len(eta1)).add_subplot()
    image = ax.imshow(values, origin="lower", cmap="viridis", vmin=vmin, vmax=vmax, aspect="auto")
    ax.set_xticks(range(len(eta2)), [f"{x:g}" for x in eta2])
    ax.set_yticks(range(len(eta1)), [f"{x:g}" for x in eta1])
    ax.set_xlabel("η2")
    ax.set_ylabel("η1")
    for i, j in zip(*np.nonzero(np.isfinite(values))):
        # Dark text on the bright end of viridis, light text elsewhere.
        bright = (values[i, j] - vmin) / (vmax - vmin) > 0.6
        ax.text(j, i, f"{values[i, j]:.2f}", ha="center", va="center", fontsize="small",
                color="black" if bright else "white")
    ax.figure.colorbar(image, ax=ax, label=label)
    if title:
        ax.set_title(title)
    return ax.figure


class Lineage(NamedTuple):
    """A PBT run's lineage from its metrics rows (`load_lineage`), G members over E epochs."""

    env_steps: np.ndarray  # int64[E]
    eta: np.ndarray  # float64[E, G, N]: the ratios each member holds after each epoch (`pbt_eta`)
    parent: np.ndarray  # int64[E, G]: the member each copied at that epoch, -1 where none
    start: np.ndarray  # float64[G, N]: the ratios each started with

    @property
    def founders(self) -> np.ndarray:
        """int64[E, G]: the starting member whose line each member carries after each epoch (a copy carries its
        donor's founder; donors are never copied at the same epoch, so the order of the copies does not matter)."""
        founder = np.arange(self.parent.shape[1])
        out = []
        for parent in self.parent:
            founder = np.where(parent >= 0, founder[np.maximum(parent, 0)], founder)
            out.append(founder)
        return np.asarray(out).reshape(self.parent.shape)


def load_lineage(run_dir: str | Path) -> Lineage:
    """The `Lineage` of a PBT run folder; ValueError where its rows carry none (not a PBT run)."""
    rows = outputs.read_rows(outputs.metrics_file(run_dir))
    if not rows or "pbt_parent" not in rows[0]:
        raise ValueError(f"{run_dir} is not a PBT run (its metrics have no pbt_parent; train with --pbt-every K)")
    members = 1 + max(r["member"] for r in rows)
    epochs = sorted({r["epoch"] for r in rows if sum(x["epoch"] == r["epoch"] for x in rows) == members})
    by_key = {(r["epoch"], r["member"]): r for r in rows}
    table = [[by_key[e, m] for m in range(members)] for e in epochs]
    return Lineage(env_steps=np.asarray([t[0]["env_steps"] for t in table], np.int64),
                   eta=np.asarray([[r["pbt_eta"] for r in t] for t in table], np.float64),
                   parent=np.asarray([[r["pbt_parent"] for r in t] for t in table], np.int64),
                   start=np.asarray([r["eta"] for r in table[0]], np.float64))


def lineage(data: Lineage, title: Optional[str] = None) -> Figure:
    """A PBT run's ratios and family tree: one panel per cooperative agent with every member's η_n vs env steps
    (a cross where it copied another member and explored), then the family tree: a row per member, coloured by
    the starting member whose line it carries, with an arrow from donor to copy at each copy."""
    steps, (_, members, agents) = data.env_steps, data.eta.shape
    cooperative = max(agents - 1, 1)
    fig = new_figure(7.0, 2.2 * cooperative + 0.25 * members + 1.5)
    axes = fig.subplots(cooperative + 1, 1, sharex=True,
                        gridspec_kw={"height_ratios": [2.2] * cooperative + [0.25 * members + 1.0]})
    palette = [f"C{i}" for i in range(10)] + EXTRA_COLORS
    color = lambda m: palette[m % len(palette)]
    founders = data.founders
    # Each epoch's row holds the ratios from its end on; the first epoch starts one epoch before its row.
    edges = np.concatenate([steps[:1] - (steps[1] - steps[0] if len(steps) > 1 else steps[0]), steps])
    for n, ax in enumerate(axes[:-1]):
        for m in range(members):
            ax.step(edges, np.concatenate([data.start[m, n:n + 1], data.eta[:, m, n]]), where="post",
                    color=color(m), linewidth=1, label=f"member {m}")
            copied = data.parent[:, m] >= 0
            ax.plot(steps[copied], data.eta[copied, m, n], "x", color=color(m))
        ax.set_ylim(-0.02, 1.02)
        ax.set_ylabel(f"η of agent {n + 1}")
        ax.grid(alpha=0.3)
    if members <= 12:
        axes[0].legend(fontsize="x-small", ncol=2)
    tree = axes[-1]
    # During epoch e a member carries the line it held before that epoch's copy.
    carried = np.concatenate([np.arange(members)[None], founders[:-1]])
    for m in range(members):
        for e in range(len(steps)):
            tree.plot(edges[e:e + 2], [m, m], color=color(carried[e, m]), linewidth=4, solid_capstyle="butt")
            if data.parent[e, m] >= 0:
                tree.annotate("", xy=(steps[e], m), xytext=(steps[e], data.parent[e, m]),
                              arrowprops=dict(arrowstyle="->", color=color(founders[e, m]), linewidth=1))
    tree.set_yticks(range(members), [f"{m} ({outputs.eta_text(list(data.start[m]))})" for m in range(members)],
                    fontsize="x-small")
    tree.set_ylabel("member (start η)")
    tree.set_xlabel("environment steps")
    tree.xaxis.set_major_formatter(FuncFormatter(_steps_label))
    tree.invert_yaxis()
    if title:
        axes[0].set_title(title)
    return fig


def main(argv: Optional[Sequence[str]] = None) -> Path:
    parser = argparse.ArgumentParser(prog="python -m ccp_jax.plot", description=(
        "Curves of a metric vs env steps from run folders: mean ± std over seeds, one line per (algo, eta vector)."))
    parser.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR")
    parser.add_argument("--metric", default="success_rate",
                        help="a metrics.jsonl field; NAME/K for agent K of a per-agent field (e.g. q_loss/0), "
                             "eval_end/NAME for an env diagnostic at the evaluations' end (eval_end/pocket)")
    parser.add_argument("--out", type=Path, help="PNG to write (default RUN_DIR/success.png for success_rate, "
                                                  "else RUN_DIR/<metric>.png, in the first RUN_DIR)")
    parser.add_argument("--title")
    parser.add_argument("--lineage", action="store_true",
                        help="draw one PBT run's ratios per agent and family tree instead (default --out "
                             "RUN_DIR/lineage.png)")
    parser.add_argument("--labels", nargs="+", metavar="LABEL",
                        help="one name per RUN_DIR, replacing its algo in the legend (to compare variants of one algo); "
                             "folders with the same label pool their seeds")
    args = parser.parse_args(argv)
    if args.labels and len(args.labels) != len(args.run_dirs):
        parser.exit(2, f"error: labels: {len(args.labels)} given for {len(args.run_dirs)} run folders\n")
    if args.lineage:
        return _main_lineage(parser, args)
    name = ("success" if args.metric == "success_rate" else args.metric.replace("/", "_")
            if args.metric.startswith("eval_end/") else args.metric.replace("/", "_agent"))
    out = args.out or args.run_dirs[0] / f"{name}.png"
    try:
        if args.labels:  # folders given the same label pool their seeds
            by_label = {label: [d for d, l in zip(args.run_dirs, args.labels) if l == label] for label in args.labels}
            groups = {}
            for label, dirs in by_label.items():
                found = load_curves(dirs, args.metric)
                for group, series in found.items():  # a label over several ratios keeps them apart
                    groups[group[0], variant_label(label, group, found), group[2]] = series
        else:
            groups = load_curves(args.run_dirs, args.metric)
    except (FileNotFoundError, KeyError, ValueError) as err:
        parser.exit(2, f"error: {err}\n")
    return save_figure_and_say(curves(groups, args.metric, title=args.title), out)


def _main_lineage(parser: argparse.ArgumentParser, args: argparse.Namespace) -> Path:
    if len(args.run_dirs) != 1:
        parser.exit(2, f"error: lineage: give one run folder, got {len(args.run_dirs)}\n")
    out = args.out or args.run_dirs[0] / "lineage.png"
    try:
        data = load_lineage(args.run_dirs[0])
    except (FileNotFoundError, ValueError) as err:
        parser.exit(2, f"error: {err}\n")
    return save_figure_and_say(lineage(data, title=args.title), out)


if __name__ == "__main__":
    main()
