"""What tests read back from a run folder."""
from pathlib import Path

import jax

from ccp_jax import checkpoint
from ccp_jax.config import Config
from ccp_jax.envs import make_env
from ccp_jax.grid import make_grid_train


def latest_state(run_dir: Path, config: Config):
    """(epoch, the grid's TrainState on the host) of the newest checkpoint of a run of `config` in `run_dir`."""
    mngr = checkpoint.manager(run_dir)
    trainer = make_grid_train(config, make_env(config))
    epoch, state = checkpoint.restore(mngr, trainer.abstract_state(config.grid_arrays()[1]))
    mngr.close()
    return epoch, jax.device_get(state)
