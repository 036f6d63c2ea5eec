"""The loss terms against hand-derived values (docs/design.md#the-method)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ccp_jax import losses
from ccp_jax.eta import eta_star

EPS = 1e-6


def test_normaliser_per_batch_with_constant_bounds():
    q = jnp.array([1.0, 2.0, 3.0, 5.0])
    np.testing.assert_allclose(losses.normalise(q, EPS), [0.0, 0.25, 0.5, 1.0], atol=1e-6)
    # min and max are constants: d/dq Σ Q̂ = 1 / (max − min + ε) for every element, min and max included.
    grad = jax.grad(lambda x: losses.normalise(x, EPS).sum())(q)
    np.testing.assert_allclose(grad, np.full(4, 1.0 / (4.0 + EPS)), rtol=1e-6)


def _coop(logp, q_own, q_next, eta, alpha):
    """The paper's loss: both critics batch-normalised."""
    return losses.coop_actor_loss(logp, losses.normalise(q_own, EPS), losses.normalise(q_next, EPS), eta, alpha)


def test_normaliser_with_given_bounds():
    q = jnp.array([1.0, 3.0])
    np.testing.assert_allclose(losses.normalise(q, 0.0, lo=jnp.float32(0.0), scale=jnp.float32(4.0)), [0.25, 0.75])
    grad = jax.grad(lambda x: losses.normalise(x, 0.0, lo=x.min(), scale=x.max() * 2).sum())(q)
    np.testing.assert_allclose(grad, [0.25 / 1.5, 0.25 / 1.5])  # bounds are constants even when computed from q


def test_coop_actor_loss_extremes_and_mixture():
    logp = jnp.array([-1.0, -2.0, 0.5])
    q_own = jnp.array([0.0, 10.0, 5.0])  # Q̂_own = [0, 1, 0.5]
    q_next = jnp.array([4.0, 2.0, 3.0])  # Q̂_next = [1, 0, 0.5]
    alpha = 0.2
    entropy = alpha * np.mean([-1.0, -2.0, 0.5])
    own = _coop(logp, q_own, q_next, 1.0, alpha)
    nxt = _coop(logp, q_own, q_next, 0.0, alpha)
    mix = _coop(logp, q_own, q_next, 0.3, alpha)
    assert float(own) == pytest.approx(entropy - 0.5, abs=1e-6)
    assert float(nxt) == pytest.approx(entropy - 0.5, abs=1e-6)
    assert float(mix) == pytest.approx(entropy - np.mean([0.7, 0.3, 0.5]), abs=1e-6)
    # η = 1 ignores the next critic entirely.
    other = _coop(logp, q_own, -q_next * 7, 1.0, alpha)
    assert float(other) == pytest.approx(float(own), abs=1e-6)


def test_coop_actor_loss_in_own_units_is_the_objective_times_the_scale_held_constant():
    logp, q_hat_own, q_hat_next = jnp.array([-1.0, 0.5]), jnp.array([0.0, 1.0]), jnp.array([1.0, 0.5])
    loss = losses.coop_actor_loss(logp, q_hat_own, q_hat_next, 0.3, 0.2, units=10.0)
    # C = [0.7, 0.65] · 10; α log π = [-0.2, 0.1]
    assert float(loss) == pytest.approx(np.mean([-0.2 - 7.0, 0.1 - 6.5]), abs=1e-5)
    grad = jax.grad(lambda u: losses.coop_actor_loss(logp, q_hat_own, q_hat_next, 0.3, 0.2, units=u))(10.0)
    assert float(grad) == 0.0  # a constant, as the normaliser's bounds are


def test_plain_sac_actor_loss():
    logp, q = jnp.array([-1.0, 0.5]), jnp.array([3.0, 1.0])
    assert float(losses.sac_actor_loss(logp, q, 0.5)) == pytest.approx(np.mean([-0.5 - 3.0, 0.25 - 1.0]))


def test_cooperative_gradient_points_to_the_weighted_critic():
    """A toy actor a = θ (same action for every state); Q_n peaks at a = 1, Q_{n+1} at a = −1."""
    s = jnp.linspace(-1, 1, 8)

    def loss(theta, eta):
        a = theta + 0.0 * s
        q_own = -(a - 1.0) ** 2 + s  # state-dependent offsets spread the batch range
        q_next = -(a + 1.0) ** 2 + 2 * s
        return _coop(jnp.zeros_like(s), q_own, q_next, eta, 0.0)

    assert float(jax.grad(loss)(0.0, 1.0)) < 0  # descending moves θ up, toward Q_n's peak
    assert float(jax.grad(loss)(0.0, 0.0)) > 0  # toward Q_{n+1}'s peak
    # Normalised scales: each critic's gradient is divided by its own batch range (2 and 4 here).
    g_own, g_next = jax.grad(loss)(0.0, 1.0), jax.grad(loss)(0.0, 0.0)
    np.testing.assert_allclose([g_own, g_next], [-2.0 / (2.0 + EPS), 2.0 / (4.0 + EPS)], rtol=1e-5)


def test_soft_target_cases():
    r = jnp.array([0.5, 0.5, 0.5, 0.5])
    next_q = jnp.array([10.0, 10.0, 10.0, 10.0])
    logp = jnp.array([-1.0, -1.0, -1.0, -1.0])
    terminal = jnp.array([0.0, 1.0, 1.0, 0.0])
    completed = jnp.array([0.0, 0.0, 1.0, 1.0])
    y = losses.soft_target(r, next_q, logp, 0.2, terminal, completed, 0.95, 20.0)
    soft = 0.5 + 0.95 * (10.0 + 0.2)
    # plain (or truncated: not a termination) | failure termination | success (absorbing) | stage completed
    np.testing.assert_allclose(y, [soft, 0.5, 0.5 + 0.95 * 20.0, 0.5 + 0.95 * 20.0], rtol=1e-6)


def test_twin_q_loss_sums_the_pair_and_stops_target_gradient():
    q = jnp.array([[1.0, 2.0], [0.0, 0.0]])
    target = jnp.array([1.0, 0.0])
    assert float(losses.twin_q_loss(q, target)) == pytest.approx(np.mean([0, 4]) + np.mean([1, 0]))
    assert float(jax.grad(lambda t: losses.twin_q_loss(q, t))(target).sum()) == 0.0


def test_alpha_loss_value_and_gradient():
    logp = jnp.array([-1.0, -3.0])
    value, grad = jax.value_and_grad(losses.alpha_loss)(jnp.float32(0.5), logp, -2.0)  # target entropy −|A| = −2
    assert float(value) == pytest.approx(-0.5 * np.mean([-3.0, -5.0]))
    assert float(grad) == pytest.approx(4.0)  # entropy 2 is above the target −2: descent lowers α


def test_eta_star():
    assert float(eta_star(jnp.float32(3.0), jnp.float32(1.0), EPS)) == pytest.approx(3.0 / 4.0, rel=1e-5)
    # κ = 4 weighs the next critic's range four times: 3 / (3 + 4 · 1)
    assert float(eta_star(jnp.float32(3.0), jnp.float32(1.0), EPS, 4.0)) == pytest.approx(3.0 / 7.0, rel=1e-5)
