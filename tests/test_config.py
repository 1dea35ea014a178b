import dataclasses
import json
import pathlib
import re

import numpy as np
import plugin_tasks
import pytest

from mqd_jax import Budgeted, Config, IsoLine, ModelEmitter, adaptation
from mqd_jax.core import algorithms, registry
from mqd_jax.experiment import files
from mqd_jax.experiment.migrations import config_from

DATA = pathlib.Path(__file__).resolve().parent / "data" / "v0.9.0"


def test_paper_presets_match_table_ii():
    c = Config.paper_2d(algorithm="mqd-paper")
    assert (c.max_generations, c.population_size, c.k, c.t_dist) == (250, 100, 5, 0.02)
    o = c.options
    assert (o["t_nov"], o["t_qua"], o["learning_rate"], o["batch_size"], o["num_batches"], o["warmup_samples"],
            o["hidden_size"]) == (0.04, 0.0, 1e-3, 16, 500, 1000, 32)
    assert c.params().emitter.acquisition.t_nov == np.float32(0.04)  # the traced threshold's default
    assert (adaptation.STEP_SIZE, adaptation.STEPS) == (0.1, 10)
    r = Config.paper_robot(k=7, algorithm="mqd")
    assert (r.max_generations, r.options["hidden_size"], r.k, r.emitter.k) == (100, 64, 7, 7)
    assert Config.paper_robot(algorithm="qd").algorithm_options == ()  # no model, no model settings
    assert hash(c) == hash(Config.paper_2d(algorithm="mqd-paper")) and c == Config.paper_2d(algorithm="mqd-paper")


@pytest.mark.parametrize("field, value", [
    ("task", "nope"), ("algorithm", "me"), ("max_generations", 0), ("population_size", 2.0),
    ("k", 0), ("t_dist", 0.0), ("t_dist", float("nan")), ("capacity", 0), ("archive_capacity", 0),
    ("coverage_resolution", 4), ("neighbour_slack", -1), ("algorithm_options", 3),
])
def test_invalid_values_name_the_field(field, value):
    with pytest.raises(ValueError, match=f"Config.{field}="):
        Config(**{field: value})
    with pytest.raises(ValueError, match=f"Config.{field}="):
        dataclasses.replace(Config(), **{field: value})


@pytest.mark.parametrize("algorithm, option, value, match", [
    ("mqd-paper", "t_nov", -1.0, r"Threshold.t_nov=-1.0"), ("mqd-paper", "t_qua", "x", r"t_qua='x' is invalid: "
                                                                                         "expected a float"),
    ("mqd", "learning_rate", -1e-3, "Surrogate.learning_rate=-0.001"), ("mqd", "batch_size", 0,
                                                                           "Surrogate.batch_size=0"),
    ("mqd", "num_batches", -1, "Surrogate.num_batches=-1"), ("mqd", "warmup_samples", -5,
                                                                "ModelEmitter.warmup_samples=-5"),
    ("mqd", "hidden_size", True, "hidden_size=True is invalid: expected an int"),
    ("qd", "iso_sigma", -0.1, "IsoLine.iso_sigma=-0.1"), ("qd", "line_sigma", float("inf"), "IsoLine.line_sigma=inf"),
    ("mqd", "pool_factor", 0, "Diverse.pool_factor=0"), ("mqd", "steering_share", 1.0, "Steering.share=1.0"),
    ("mqd", "steering_share", -0.1, "Steering.share=-0.1"), ("mqd", "anchor", "first", "Anchoring.anchor='first'"),
    ("mqd", "parent_weight", -1.0, "Diverse.parent_weight=-1.0"), ("mqd", "parent_weight", float("nan"),
                                                                   "Diverse.parent_weight=nan"),
    ("mqd", "quality_share", 1.5, "Diverse.quality_share=1.5"), ("mqd", "wide_scale", 0.0, "IsoLine.scales="),
    ("mqd-paper", "budgeted", 1, "budgeted=1 is invalid: expected a bool"),
    ("qd", "hidden_size", 8, "'qd' takes no option 'hidden_size'; its options: iso_sigma=0.02, line_sigma=0.1"),
    ("mqd", "k", 3, "'k' is the run's own"),
])
def test_invalid_options_name_the_part_that_refuses_them(algorithm, option, value, match):
    with pytest.raises(ValueError, match=re.escape(match) if "(" in match else match):
        Config(algorithm=algorithm, algorithm_options={option: value})


def test_options_equal_to_the_defaults_are_the_same_config():
    assert Config(algorithm="mqd", algorithm_options={"pool_factor": 8, "optimism": 1}) == Config(algorithm="mqd")
    cfg = Config(algorithm="mqd", algorithm_options={"pool_factor": 16})
    assert cfg.algorithm_options == (("pool_factor", 16),) and cfg.emitter.acquisition.pool_factor == 16
    written = {o: v for o, v in algorithms.options("mqd").items() if v is not None}  # parts at None: not written
    assert cfg.to_dict()["algorithm_options"] == {**written, "pool_factor": 16}  # all written out
    assert Config.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(ValueError, match=r"Config.algorithm_options=.*with an Emitter"):
        Config(algorithm=IsoLine(), algorithm_options={"iso_sigma": 0.1})


def test_mqd_refuses_a_steering_share_its_pool_cannot_hold():
    # A pool of 1 x 100: steering 25 would leave the rule 75 of its 100 rollouts; 2 x 2 with 0.1 steers no row.
    for kw in (dict(pool_factor=1), dict(pool_factor=2, steering_share=0.1), dict(pool_factor=2, steering_share=0.6)):
        with pytest.raises(ValueError, match=r"ModelEmitter: Steering\(.*\) steers \d+ of a pool of \d+: expected at "
                                             r"least 1, leaving the inner emitter"):
            Config(algorithm="mqd", population_size=2 if kw.get("steering_share") == 0.1 else 100,
                   algorithm_options={**kw, "warmup_samples": 0})
    for kw in (dict(pool_factor=1, steering_share=0.0), dict(pool_factor=2, steering_share=0.5)):
        assert Config(algorithm="mqd", algorithm_options=kw).emitter.acquisition.pool_factor == kw["pool_factor"]


def test_warm_up_longer_than_the_run_is_refused():
    with pytest.raises(ValueError, match=r"ModelEmitter.warmup_samples=1000 is invalid for this run: expected fewer "
                                         r"than its population_size x max_generations \(800\)"):
        Config(algorithm="mqd", population_size=8, max_generations=100)


def test_population_larger_than_capacity_is_rejected():
    with pytest.raises(ValueError, match=r"Config.population_size=.*capacity"):
        Config(population_size=200, capacity=100)


def test_a_task_made_with_options_round_trips_through_json():
    task = registry.make("plugin_tasks:make_reach", scale=0.5)
    cfg = Config(task=task, max_generations=3)
    saved = json.loads(json.dumps(cfg.to_dict()))
    assert saved["task"] == "plugin_tasks:make_reach" and saved["task_options"] == {"scale": 0.5}
    assert cfg.task_name == "plugin_tasks:make_reach"
    assert Config.from_dict(saved) == cfg and Config.from_dict(saved).task is task


def test_configs_of_version_0_9_read_with_their_settings_as_algorithm_options():
    """A real file of 0.9.0 (tests/data/v0.9.0): its preset's settings were fields of the config, and its "mqd"
    took neither the task's features nor a gate (0.11's defaults)."""
    old = files.read_json(str(DATA / "run" / "metrics.json"), "")["config"]
    assert old["warmup_samples"] == 8 and "algorithm_options" not in old
    cfg = config_from(old)
    assert cfg == Config(algorithm="mqd", max_generations=3, population_size=8, capacity=32, archive_capacity=16,
                         coverage_resolution=16, algorithm_options=dict(warmup_samples=8, num_batches=2, hidden_size=4,
                                                                        features=False, gate=False))
    assert config_from({**old, "physics_backend": "auto"}) == cfg  # and before 0.2
    with pytest.raises(ValueError, match="unknown fields"):
        config_from({**old, "filter": "strict"})


def test_robot_settings_are_options_of_the_task_not_fields_of_the_core_config():
    with pytest.raises(TypeError, match="physics_backend"):
        Config(task="obstacle2d", physics_backend="mujoco")  # the field is gone
    with pytest.raises(ValueError, match=r"task 'obstacle2d': its factory failed with the options "
                                         r"\{'backend': 'mujoco'\}"):
        registry.make("obstacle2d", backend="mujoco")


def test_composed_emitters_and_unnamed_tasks_are_saved_by_repr_and_refused_on_reading():
    task = plugin_tasks.Reach((-1.0, -1.0), (1.0, 1.0), (0.0, 0.0), (1.0, 1.0))
    emitter = ModelEmitter(IsoLine(), Budgeted(2))
    cfg = Config(task=task, algorithm=emitter)
    saved = cfg.to_dict()
    assert saved["task"] == repr(task) and saved["algorithm"] == repr(emitter)
    assert (cfg.task_name, cfg.algorithm_name) == ("Reach", "ModelEmitter")
    with pytest.raises(ValueError, match=r"only the algorithms .* can be rebuilt from a file"):
        Config.from_dict(saved)
    with pytest.raises(ValueError, match="not registered here"):
        Config.from_dict({**saved, "algorithm": "qd"})
    assert Config(task=task, algorithm=ModelEmitter(IsoLine(), Budgeted(2))) == cfg  # emitters compare by value
