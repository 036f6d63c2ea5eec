"""Writes the Colab notebooks from the cell sources below (run after editing them).

Each notebook's first code cell is its parameter cell: `CCP_NOTEBOOK_SCALE=tiny`
in the environment (the test suite sets it) shrinks every run to seconds.
"""
from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

REPO = "https://github.com/ccp-jax/ccp-jax"  # where the project's repository is published
INSTALL = f'''# Colab: install ccp-jax from its repository (skipped where it is already installed).
import importlib.util, subprocess, sys
if importlib.util.find_spec("ccp_jax") is None:
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "git+{REPO}"], check=True)'''
PARAMS = '''import os
SCALE = os.environ.get("CCP_NOTEBOOK_SCALE", "full")  # "tiny" runs everything in seconds (tests)
TINY = SCALE == "tiny"'''
# MJX envs (peg, pusher) on a CPU: XLA's fusion emitters off, before the first JAX array (the CLI does the same).
MJX_PARAMS = PARAMS + '''
import ccp_jax
ccp_jax.configure_cpu()'''

QUICKSTART = [
    new_markdown_cell("# ccp-jax quickstart\n\nTrain cooperative agents (CSAC) on the 2-room maze, plot their "
                      "success and watch an episode. On a Colab CPU the full run takes a few minutes."),
    new_code_cell(INSTALL),
    new_code_cell(PARAMS),
    new_code_cell('''from pathlib import Path
import tempfile
from ccp_jax import make_config, run

out = Path(tempfile.mkdtemp()) / "maze2"
config = make_config("tiny" if TINY else "small", rooms=2, algo="csac", etas=((0.1,),), seeds=(0,))
summary = run(config, out, progress=not TINY)
summary["members"][0]["final_success"]'''),
    new_markdown_cell("Success over training (mean ± std over seeds; one seed here):"),
    new_code_cell('''from IPython.display import Image, display
from ccp_jax.plot import main as plot_main
plot_main([str(out)])
display(Image(str(out / "success.png")))'''),
    new_markdown_cell("A deterministic episode of the trained agents (the robot's colour is its stage):"),
    new_code_cell('''from ccp_jax.render import main as render_main
video = out / "episode.gif"
render_main([str(out), "--member", "0", "--episodes", "1", "--out", str(video)])
display(Image(str(video)))'''),
]

SWEEP = [
    new_markdown_cell("# Sweeping the cooperative ratio\n\nOne call trains every (η1, η2) pair × seed of the "
                      "3-room maze as one vmapped program; the heatmap shows final success per pair "
                      "(the paper's independent-ratio study)."),
    new_code_cell(INSTALL),
    new_code_cell(PARAMS),
    new_code_cell('''from pathlib import Path
import itertools, tempfile
import numpy as np
from ccp_jax import make_config, run

ratios = (0.1, 0.9) if TINY else (0.1, 0.3, 0.5, 0.7, 0.9, 1.0)
pairs = tuple(itertools.product(ratios, ratios))
out = Path(tempfile.mkdtemp()) / "sweep"
config = make_config("tiny" if TINY else "small", rooms=3, etas=pairs, seeds=(0,) if TINY else (0, 1, 2),
                     total_steps=400 if TINY else 300_000)
summary = run(config, out, progress=not TINY)'''),
    new_code_cell('''from IPython.display import Image, display
from ccp_jax.plot import heatmap
success = np.zeros((len(ratios), len(ratios)))
for m in summary["members"]:
    i, j = ratios.index(m["eta"][0]), ratios.index(m["eta"][1])
    success[i, j] += m["final_success"] / len(config.grid.seeds)
heatmap(success, ratios, ratios, title="final success over (η1, η2)").savefig(out / "heatmap.png", dpi=100)
display(Image(str(out / "heatmap.png")))
best = np.unravel_index(success.argmax(), success.shape)
print("best pair", ratios[best[0]], ratios[best[1]], "success", success[best])'''),
]

PEG = [
    new_markdown_cell("# Peg in hole (MuJoCo MJX)\n\nA Panda arm must grasp a peg and insert it: two stages. "
                      "The grasp that the grasp reward prefers (the peg's centre) blocks full insertion; "
                      "cooperation lets the grasping agent learn the thick-section grasp. MJX is slow on a "
                      "CPU: use a GPU runtime for real training."),
    new_code_cell(INSTALL),
    new_code_cell(MJX_PARAMS),
    new_code_cell('''from pathlib import Path
import tempfile
from ccp_jax import make_config, run

out = Path(tempfile.mkdtemp()) / "peg"
config = make_config("tiny" if TINY else "small", env="peg", algo="csac", etas=((0.9,),), seeds=(0,),
                     total_steps=400 if TINY else 1_000_000, max_episode_steps=50 if TINY else 200)
summary = run(config, out, progress=not TINY)
summary["members"][0]'''),
    new_code_cell('''from IPython.display import Image, display
from ccp_jax.plot import main as plot_main
plot_main([str(out)])
display(Image(str(out / "success.png")))'''),
]

OWN_TASK = [
    new_markdown_cell("# Your own multi-stage task\n\nAny `brax.envs.base.Env` becomes a CCP task with a "
                      "`StageSpec`: how far along each stage is, and when it is done. Here Brax's own `pusher` "
                      "(a 7-joint arm, a puck, a goal) becomes *reach the puck, then push it to the goal*, and "
                      "CSAC trains on it. A reach that touches the puck on the goal's side is greedy and useless "
                      "for the push: the next agent's critic is what tells the reaching agent to come from behind."),
    new_code_cell(INSTALL),
    new_code_cell(MJX_PARAMS),
    new_code_cell('''import ccp_jax  # first: it sets the XLA CPU flag that MuJoCo MJX needs on a CPU
import jax.numpy as jnp
from brax import envs
from envs_mjx.contract import check_env
from envs_mjx.stage_wrapper import StageSpec, StageWrapper

TIP, PUCK, GOAL = slice(14, 17), slice(17, 20), slice(20, 23)  # positions in brax's pusher observation
reach = lambda s: jnp.linalg.norm(s.obs[TIP] - s.obs[PUCK])
to_goal = lambda s: jnp.linalg.norm(s.obs[PUCK][:2] - s.obs[GOAL][:2])

def make_task():
    spec = StageSpec(
        num_stages=2,
        progress=(lambda s: 1 - (reach(s) - 0.12) / 0.5, lambda s: 1 - (to_goal(s) - 0.05) / 0.4),  # clipped to [0, 1]
        completed=(lambda s: reach(s) < 0.12, lambda s: to_goal(s) < 0.05),
    )
    return StageWrapper(envs.get_environment("pusher", backend="mjx"), spec, episode_length=50 if TINY else 200)

check_env(make_task())  # raises, naming every broken rule, if the task does not meet the contract
"the task meets the contract"'''),
    new_markdown_cell("Train it like a built-in env: `env` names the factory as `module:function` (here this "
                      "notebook's own namespace, `__main__`). From a shell it would be "
                      "`python -m ccp_jax.train --env my_module:make_task --eta 0.5 0.9`."),
    new_code_cell('''from pathlib import Path
import tempfile
from ccp_jax import make_config, run

out = Path(tempfile.mkdtemp()) / "pusher"
config = make_config("tiny" if TINY else "small", env="__main__:make_task", rooms=2,  # rooms: the task's stages
                     algo="csac", etas=((0.5,), (0.9,)), seeds=(0,),
                     total_steps=400 if TINY else 300_000, max_episode_steps=50 if TINY else 200)
summary = run(config, out, progress=not TINY)
[(m["eta"], m["final_success"]) for m in summary["members"]]'''),
    new_code_cell('''from IPython.display import Image, display
from ccp_jax.plot import main as plot_main
plot_main([str(out)])
display(Image(str(out / "success.png")))'''),
]


def colab_badge(name: str) -> str:
    """The "Open in Colab" badge of notebook `name`, as Markdown (Colab opens it from the repository's main branch)."""
    url = REPO.replace("https://github.com/", "https://colab.research.google.com/github/") + f"/blob/main/notebooks/{name}"
    return f"[![Open in Colab](https://colab.research.google.com/assets/colab-badge.svg)]({url})"


def with_badge(name: str, cells: list) -> list:
    """`cells` with the Colab badge opening the first (Markdown) cell."""
    return [new_markdown_cell(colab_badge(name) + "\n\n" + cells[0].source), *cells[1:]]


def write(name: str, cells: list) -> None:
    """Writes notebook `name` beside this script, with its Colab badge."""
    nb = new_notebook(cells=with_badge(name, cells), metadata={"kernelspec": {"name": "python3", "display_name": "Python 3"},
                                             "colab": {"provenance": []}})
    nbformat.write(nb, Path(__file__).with_name(name))


if __name__ == "__main__":
    write("quickstart.ipynb", QUICKSTART)
    write("ratio_sweep.ipynb", SWEEP)
    write("peg_in_hole.ipynb", PEG)
    write("own_task.ipynb", OWN_TASK)
