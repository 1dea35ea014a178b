"""A user's part that breaks its contract is named in one line ([parts]): shapes and dtypes as the program is
traced, values with `ModelEmitter(checks=True)` as it runs."""

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mqd_jax import Config, run_mqd
from mqd_jax.core.checks import PartFailed
from mqd_jax.emitters import presets
from mqd_jax.emitters.acquisition import Budgeted


class Linear:
    """A surrogate that predicts the first d action coordinates (obstacle2d: n = 2 = d) and their sum."""

    def init(self, key, task, capacity):
        return {"w": jnp.zeros(3)}

    def fit(self, key, state, repertoire, task, params):
        return state, jnp.float32(0.0)

    def predict(self, state, actions, task):
        return actions[:, :task.behavior_dim] + state["w"][0], actions.sum(axis=1)


class OneBehavior(Linear):
    def predict(self, state, actions, task):
        return actions[:, :1], actions[:, 0]


class Integers(Linear):
    def predict(self, state, actions, task):
        return (actions[:, :2] * 100).astype(jnp.int32), actions[:, 0]


class Reshaping(Linear):
    def fit(self, key, state, repertoire, task, params):
        return {"w": jnp.zeros(4)}, jnp.float32(0.0)


class NotFinite(Linear):
    def predict(self, state, actions, task):
        return actions[:, :2] * jnp.nan, actions[:, 0]


@dataclasses.dataclass(frozen=True)
class Rule:
    """Budgeted's choice, broken as `how` says."""

    how: str = ""

    def pool_size(self, num):
        return 4 * num

    def select(self, key, state, judged, repertoire, wanted, params, num):
        rule = Budgeted(4)
        rows, rollout, discarded = rule.select(key, state, judged, repertoire, wanted,
                                               params.part(rule.default_params()), num)
        if self.how == "short":
            return rows[:-1], rollout[:-1], discarded
        if self.how == "repeated":
            rows = rows.at[1].set(rows[0])
        if self.how == "outside":
            rows = rows + 10**6
        return rows, rollout, discarded


def _run(surrogate=None, rule=None, checks=False):
    emitter = presets.mqd_paper(budgeted=True, warmup_samples=16)
    emitter = dataclasses.replace(emitter, surrogate=surrogate or Linear(), acquisition=rule or Budgeted(4),
                                  checks=checks)
    cfg = Config.paper_2d(task="obstacle2d", algorithm=emitter, population_size=8, max_generations=4, capacity=64,
                          archive_capacity=16)
    return jax.block_until_ready(run_mqd(jax.random.PRNGKey(0), cfg))


@pytest.mark.parametrize(("surrogate", "rule", "message"), [
    (OneBehavior(), None, r"OneBehavior.predict returned \(float32\[32, 1\], float32\[32\]\) for 32 actions; "
                          r"expected behaviors float\[32, 2\]"),
    (Integers(), None, r"Integers.predict returned \(int32\[32, 2\], float32\[32\]\)"),
    (Reshaping(), None, r"Reshaping.fit returned a state float32\[4\]; expected one of the structure, shapes and "
                        r"dtypes it was given, float32\[3\]"),
    (None, Rule("short"), r"Rule.select returned \(int32\[7\], bool\[7\], int32\[\]\); expected the rows int\[8\]"),
])
def test_a_part_whose_outputs_have_the_wrong_shape_or_dtype_is_named_before_the_run(surrogate, rule, message):
    with pytest.raises(ValueError, match=message):
        _run(surrogate, rule)


@pytest.mark.parametrize(("surrogate", "rule", "message"), [
    (None, Rule("repeated"), "Rule.select returned a row more than once"),
    (None, Rule("outside"), r"Rule.select returned rows outside the pool's \[0, 32\)"),
    (NotFinite(), None, "NotFinite predicted values that are not finite"),
])
def test_with_checks_a_part_whose_values_break_the_contract_stops_the_run_naming_it(surrogate, rule, message,
                                                                                  caplog):
    with pytest.raises(PartFailed) as raised:  # itself, one line: not the runtime's error with a traceback
        _run(surrogate, rule, checks=True)
    assert re.fullmatch(message + ".*", str(raised.value)) and "\n" not in str(raised.value)
    assert "Traceback" not in caplog.text and "callback failed" not in caplog.text  # nor logged with one


def test_without_checks_a_model_that_predicts_nan_is_a_warning_naming_the_surrogate():
    from mqd_jax.core.diagnostics import RunWarning

    with pytest.warns(RunWarning, match=r"the model's predictions \(NotFinite\) were not finite in 4 of 4 "):
        _run(NotFinite())


def test_the_checkpointed_runner_a_sweep_s_batch_and_ask_raise_a_broken_part_as_one_line(tmp_path):
    from mqd_jax import ask
    from mqd_jax.core.state import init
    from mqd_jax.experiment.checkpoint import run_with_checkpoints
    from mqd_jax.experiment.sweep import run_batch

    emitter = dataclasses.replace(presets.mqd_paper(budgeted=True, warmup_samples=16), surrogate=Linear(),
                                  acquisition=Rule("repeated"), checks=True)
    cfg = Config.paper_2d(task="obstacle2d", algorithm=emitter, population_size=8, max_generations=4, capacity=64,
                          archive_capacity=16)
    with pytest.raises(PartFailed, match=r"^Rule.select returned a row more than once: its rows must be distinct$"):
        run_with_checkpoints(jax.random.PRNGKey(0), cfg, str(tmp_path / "ckpt"), every=2)
    with pytest.raises(PartFailed, match=r"^Rule.select returned a row more than once: its rows must be distinct$"):
        run_batch(cfg, jax.random.split(jax.random.PRNGKey(0), 2))
    # ask raises it itself (the rule runs in warm-up too), not the runtime's error where the candidates are read
    with pytest.raises(PartFailed, match=r"^Rule.select returned a row more than once: its rows must be distinct$"):
        ask(init(jax.random.PRNGKey(0), cfg), cfg)


def test_checks_change_nothing_in_a_run_that_keeps_the_contracts():
    (a, ma), (b, mb) = _run(), _run(checks=True)
    for x, y in zip(jax.tree.leaves((a.repertoire, ma)), jax.tree.leaves((b.repertoire, mb)), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_presets_take_parts_and_keep_their_other_parts():
    """`presets.mqd(surrogate=..., rule=...)` and the same through `Config.algorithm_options`: the part replaced,
    every other field as the preset's own; a part given as text (the command line), with options it would not
    read, or read back from a file is refused in one line."""
    own, rule = Linear(), Budgeted(8)
    default = presets.mqd()
    for emitter, replaced in ((presets.mqd(surrogate=own), {"surrogate": own}),
                              (presets.mqd(rule=rule), {"acquisition": rule}),
                              (presets.mqd_paper(surrogate=own), None)):
        if replaced is None:
            assert emitter == dataclasses.replace(presets.mqd_paper(), surrogate=own)
        else:
            assert emitter == dataclasses.replace(default, **replaced)
    cfg = Config.paper_2d(task="obstacle2d", algorithm="mqd", algorithm_options={"surrogate": own})
    assert cfg.emitter == dataclasses.replace(presets.mqd(k=cfg.k), surrogate=own)
    with pytest.raises(ValueError, match=r"mqd: surrogate=.* replaces the preset's own, which gate=False would set"):
        presets.mqd(surrogate=own, gate=False)
    with pytest.raises(ValueError, match="mqd's surrogate='KNN' is invalid: expected a part object, given in Python"):
        Config.paper_2d(task="obstacle2d", algorithm="mqd", algorithm_options={"surrogate": "KNN"})
    with pytest.raises(ValueError, match="a part object cannot be rebuilt from a file"):
        Config.from_dict(cfg.to_dict())
