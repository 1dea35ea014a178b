import dataclasses
import json

import plugin_tasks
import pytest

from mqd_jax import Budgeted, Config, IsoLine, ModelEmitter, registry


def test_paper_presets_match_table_ii():
    c = Config.paper_2d()
    assert (c.max_generations, c.population_size, c.k, c.t_dist, c.t_nov, c.t_qua) == (250, 100, 5, 0.02, 0.04, 0.0)
    assert (c.learning_rate, c.batch_size, c.num_batches, c.warmup_samples, c.hidden_size) == (1e-3, 16, 500, 1000, 32)
    assert (c.adaptation_step_size, c.adaptation_steps) == (0.1, 10)
    r = Config.paper_robot(k=7)
    assert (r.max_generations, r.hidden_size, r.k) == (100, 64, 7)
    assert hash(c) == hash(Config.paper_2d()) and c == Config.paper_2d()


@pytest.mark.parametrize("field, value", [
    ("task", "nope"), ("algorithm", "me"), ("max_generations", 0), ("population_size", 2.0),
    ("k", 0), ("t_dist", 0.0), ("t_dist", float("nan")), ("t_nov", -1.0), ("t_qua", "x"),
    ("learning_rate", -1e-3), ("batch_size", 0), ("num_batches", -1), ("warmup_samples", -5),
    ("hidden_size", True), ("capacity", 0), ("archive_capacity", 0), ("iso_sigma", -0.1),
    ("line_sigma", float("inf")), ("adaptation_step_size", 0), ("adaptation_steps", -1),
    ("coverage_resolution", 4), ("neighbour_slack", -1), ("pool_factor", 0), ("steering_share", 1.0),
    ("steering_share", -0.1), ("anchor", "first"), ("parent_weight", -1.0), ("parent_weight", float("nan")),
    ("quality_share", 1.5), ("quality_share", -0.1), ("wide_scale", 0.0), ("wide_scale", float("nan")),
])
def test_invalid_values_name_the_field(field, value):
    with pytest.raises(ValueError, match=f"Config.{field}="):
        Config(**{field: value})
    with pytest.raises(ValueError, match=f"Config.{field}="):
        dataclasses.replace(Config(), **{field: value})


def test_mqd_refuses_a_steering_share_its_pool_cannot_hold():
    # A pool of 1 x 100: steering 25 would leave the rule 75 of its 100 rollouts; 2 x 2 with 0.1 steers no row.
    for kw in (dict(pool_factor=1), dict(pool_factor=2, population_size=2, steering_share=0.1),
               dict(pool_factor=2, steering_share=0.6)):
        with pytest.raises(ValueError, match=r"Config.steering_share=.*leaves population_size unsteered"):
            Config(algorithm="mqd", **kw)
    for kw in (dict(pool_factor=1, steering_share=0.0), dict(pool_factor=2, steering_share=0.5)):
        assert Config(algorithm="mqd", **kw).pool_factor == kw["pool_factor"]
    assert Config(algorithm="qd", pool_factor=1).steering_share == 0.25  # read by "mqd" only


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


def test_configs_of_the_previous_version_still_read():
    old = {**Config(algorithm="mqd").to_dict(), "physics_backend": "auto"}
    assert Config.from_dict(old) == Config(algorithm="mqd")
    with pytest.raises(ValueError, match="unknown fields"):
        Config.from_dict({**old, "filter": "strict"})


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
    with pytest.raises(ValueError, match=r"only presets .* can be rebuilt from a file"):
        Config.from_dict(saved)
    with pytest.raises(ValueError, match="not registered here"):
        Config.from_dict({**saved, "algorithm": "qd"})
    assert Config(task=task, algorithm=ModelEmitter(IsoLine(), Budgeted(2))) == cfg  # emitters compare by value
