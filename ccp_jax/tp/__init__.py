"""Transition Policies (Lee et al., ICLR 2019), the paper's TP baseline: `--algo tp`.

Frozen primitives (the deterministic agents of a finished `--algo naive` run)
solve the subtasks; between primitive k − 1 and primitive k, a transition
policy (PPO) steers from where k − 1 ended to a state from which k succeeds,
rewarded by a learned proximity predictor. Modules, one job each:

  primitives.py  load and check the frozen primitives of a naive run
  networks.py    transition policy, value and proximity networks; running observation normaliser
  proximity.py   proximity targets, success/failure ring buffers, the predictor's loss and update
  ppo.py         GAE over transition steps, the PPO loss and update
  rollout.py     acting (primitive or transition), the epoch's rollout, evaluation, initial success data
  trainer.py     `make_tp_train`: init / train_step (one epoch) like `ccp_jax.trainer`
"""
