import dataclasses

import pytest

from mqd_jax import Config


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
    ("coverage_resolution", 4), ("neighbour_slack", -1), ("physics_backend", "gpu"), ("pool_factor", 0),
])
def test_invalid_values_name_the_field(field, value):
    with pytest.raises(ValueError, match=f"Config.{field}="):
        Config(**{field: value})
    with pytest.raises(ValueError, match=f"Config.{field}="):
        dataclasses.replace(Config(), **{field: value})


def test_population_larger_than_capacity_is_rejected():
    with pytest.raises(ValueError, match=r"Config.population_size=.*capacity"):
        Config(population_size=200, capacity=100)
