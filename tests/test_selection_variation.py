import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import selection, variation


def test_probabilities_proportional_to_novelty():
    nov = jnp.asarray([0.0, 1.0, 3.0, 2.0, 5.0])
    valid = jnp.asarray([True, True, True, True, False])
    np.testing.assert_allclose(selection.probabilities(nov, valid), [0, 1 / 6, 3 / 6, 2 / 6, 0], rtol=1e-6)
    # All-zero novelty: uniform over valid skills.
    np.testing.assert_allclose(selection.probabilities(jnp.zeros(4), jnp.asarray([1, 1, 0, 0], bool)),
                               [0.5, 0.5, 0, 0])


def test_sampling_frequencies_follow_novelty():
    nov = jnp.asarray([1.0, 0.0, 2.0, 7.0, 9.0])
    valid = jnp.asarray([True, True, True, True, False])
    idx = np.asarray(selection.sample_parents(jax.random.PRNGKey(0), nov, valid, 200_000))
    freq = np.bincount(idx, minlength=5) / len(idx)
    np.testing.assert_allclose(freq, [0.1, 0.0, 0.2, 0.7, 0.0], atol=0.005)


def test_iso_line_stays_in_bounds_and_follows_the_parents_line():
    low, high = jnp.zeros(3), jnp.asarray([1.0, 2.0, 10.0])
    x1 = jnp.full((1000, 3), 0.5)
    x2 = jnp.full((1000, 3), 0.9)
    child = variation.iso_line(jax.random.PRNGKey(0), x1, x2, 0.0, 0.1, low, high)
    assert bool(((child > low) & (child < high)).all())  # no clipping in this case
    # With no isotropic part, children lie on the line through both parents.
    step = (child - x1) / (x2 - x1)
    np.testing.assert_allclose(step, step[:, :1].repeat(3, 1), atol=1e-5)
    wide = variation.iso_line(jax.random.PRNGKey(1), x1, x2, 5.0, 5.0, low, high)
    assert bool(((wide >= low) & (wide <= high)).all())
