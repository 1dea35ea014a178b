"""mqd_jax.core.batching: the same results as the plain control flow, member by member, with less work under vmap."""

import jax
import jax.numpy as jnp
import numpy as np

from mqd_jax.core import batching


def _recording(calls: list[int]):
    """A true branch that records, through a host callback, that it was evaluated."""
    def true_fn(x):
        jax.debug.callback(lambda: calls.append(1))
        return x + 1.0
    return true_fn


def test_rare_cond_matches_cond_and_skips_the_branch_no_member_needs():
    x = jnp.arange(4.0)
    for preds in ([False, True, False, True], [False] * 4, [True] * 4):
        pred = jnp.asarray(preds)
        calls: list[int] = []
        true_fn = _recording(calls)
        got = jax.jit(jax.vmap(lambda p, v, t=true_fn: batching.rare_cond(p, t, lambda v: v - 1.0, v)))(pred, x)
        want = [jax.lax.cond(p, lambda v: v + 1.0, lambda v: v - 1.0, v) for p, v in zip(pred, x, strict=True)]
        np.testing.assert_array_equal(got, want)
        assert bool(calls) == any(preds)
    # The control: vmap of a plain lax.cond evaluates the true branch even when no member takes it.
    calls = []
    true_fn = _recording(calls)
    jax.jit(jax.vmap(lambda p, v: jax.lax.cond(p, true_fn, lambda v: v - 1.0, v)))(jnp.zeros(4, bool), x)
    assert calls


def test_rare_cond_nested_vmap_and_unbatched_operands():
    pred = jnp.asarray([[False, False], [True, False], [False, False]])
    x = jnp.arange(6.0).reshape(3, 2)
    calls: list[int] = []
    fn = lambda p, v, s: batching.rare_cond(p, lambda v, s: _recording(calls)(v) * s, lambda v, s: v * 0.0, v, s)  # noqa: E731
    got = jax.jit(jax.vmap(jax.vmap(fn, in_axes=(0, 0, None)), in_axes=(0, 0, None)))(pred, x, 3.0)
    np.testing.assert_array_equal(got, np.where(pred, (x + 1.0) * 3.0, 0.0))
    assert calls
    calls.clear()
    jax.jit(jax.vmap(jax.vmap(fn, in_axes=(0, 0, None)), in_axes=(0, 0, None)))(pred & False, x, 3.0)
    assert calls == []


def test_switch_largest_is_switch_alone_and_the_batch_maximum_under_vmap():
    branches = [lambda v, i=i: v * 10.0 + i for i in range(3)]
    call = lambda i, v: batching.switch_largest(i, branches, v)  # noqa: E731
    for i in range(3):
        assert float(jax.jit(call)(jnp.int32(i), jnp.float32(1.0))) == 10.0 + i
    index, x = jnp.asarray([0, 2, 1, 0]), jnp.arange(4.0)
    np.testing.assert_array_equal(jax.jit(jax.vmap(call))(index, x), x * 10.0 + 2)
    # Nested: the maximum over both axes.
    index2 = jnp.asarray([[0, 0], [1, 0]])
    got = jax.jit(jax.vmap(jax.vmap(call)))(index2, jnp.ones((2, 2)))
    np.testing.assert_array_equal(got, np.full((2, 2), 11.0))


def _sum_rows(rows, total, weights):
    return total.at[rows].add(weights[jnp.minimum(rows, weights.shape[0] - 1)], mode="drop")


def test_for_each_chunk_visits_every_set_row_once_per_member():
    rng = np.random.default_rng(0)
    masks = jnp.asarray(rng.random((5, 37)) < np.linspace(0.0, 1.0, 5)[:, None])  # 0 to 37 rows set
    weights = jnp.asarray(rng.random((5, 37)), jnp.float32)

    def loop(mask, w):
        return batching.for_each_chunk(mask, 4, _sum_rows, jnp.zeros(37), w)

    want = np.where(masks, weights, 0.0)
    for m, w, row in zip(masks, weights, want, strict=True):
        np.testing.assert_array_equal(jax.jit(loop)(m, w), row)
    np.testing.assert_array_equal(jax.jit(jax.vmap(loop))(masks, weights), want)
    np.testing.assert_array_equal(jax.jit(jax.vmap(loop, in_axes=(0, None)))(masks, weights[0]),
                                  np.where(masks, weights[0], 0.0))
    np.testing.assert_array_equal(jax.jit(jax.vmap(jax.vmap(loop)))(masks.reshape(5, 1, 37),
                                                                     weights.reshape(5, 1, 37)).reshape(5, 37), want)
