"""Watching skills: the frames of a robot skill, a 2D task's behavior path, and `mqd render`."""


import numpy as np
import pytest

from envs import arena2d
from mqd_jax import Config
from mqd_jax.core import registry
from mqd_jax.experiment import cli, folders, manifest


def test_a_2d_action_cut_at_a_time_gives_the_position_at_that_time():
    task = registry.make("obstacle2d")
    action = np.array([1, 1, 10, -1, 1, 7.5, 0, 1, 3], np.float32)
    cuts = arena2d.truncated(action, np.array([0.0, 10.0, 30.0]))
    b, _, _ = task.evaluate(cuts)
    np.testing.assert_allclose(b[0], task.start)  # nothing done yet
    np.testing.assert_allclose(b[1], task.evaluate(action[None, :3])[0][0], atol=1e-6)  # the first sub-action
    np.testing.assert_array_equal(b[2], task.evaluate(action[None])[0][0])  # all of it
    np.testing.assert_array_equal(cuts[1, 3:], [-1, 1, 0, 0, 1, 0])  # later sub-actions take no time yet


def _run_folder(tmp_path, behaviors):
    cfg = Config(task="obstacle2d", max_generations=2)
    folders.write_json(str(tmp_path / "metrics.json"), {"config": cfg.to_dict()})
    actions = np.tile(np.array([0, 1, 2, 0, 0, 0, 0, 0, 0], np.float32), (len(behaviors), 1))
    actions[:, 2] = np.arange(len(behaviors)) + 1.0
    folders.write_npz(str(tmp_path / "repertoire.npz"), actions=actions, behaviors=np.asarray(behaviors, np.float32))
    return actions


def test_mqd_render_writes_the_skill_nearest_to_a_goal(tmp_path, capsys, refused):
    pytest.importorskip("matplotlib", reason="drawing a 2D skill needs the plot extra")
    from PIL import Image

    _run_folder(tmp_path, [[0.1, 0.1], [0.5, 0.9], [0.9, 0.2]])
    out = tmp_path / "nearest.gif"
    cli.main(["render", str(tmp_path), "--goal", "0.6", "0.8", "--out", str(out), "--width", "80", "--height", "80"])
    assert capsys.readouterr().out.startswith("skill 1:")
    with Image.open(out) as gif:
        assert gif.n_frames > 1 and gif.size == (80, 80)  # Pillow merges repeated frames (a still agent)
    refused(["render", str(tmp_path), "--index", "3"], "--index 3: the repertoire holds 3 skills (0 to 2)")
    refused(["render", str(tmp_path / "missing")], "does not exist")
    assert not (tmp_path / "missing").exists()
    refused(["render", str(tmp_path), "--goal", "nan", "nan"], "--goal nan nan is invalid: expected finite numbers")


def test_a_robot_skill_renders_the_arm_moving():
    import mujoco

    try:
        mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 8, 8).close()
    except Exception as e:  # no OpenGL context on this machine
        pytest.skip(f"no OpenGL context for MuJoCo's renderer (set MUJOCO_GL=egl): {e}")
    task = registry.make("push_cube", backend="mujoco")
    frames = task.frames(np.array([0.5, 0.0, 0.0, 30, 0.75, 0.0, 0.0, 50], np.float32), 64, 48, every=50)
    assert frames.shape == (task.horizon // 50, 48, 64, 3) and frames.dtype == np.uint8
    assert frames.mean() > 40  # lit, not a black image
    assert np.abs(frames[0].astype(int) - frames[2].astype(int)).mean() > 0.5  # the arm moved


def test_render_prints_rounded_numbers_counts_one_skill_and_names_a_sweep_folder(tmp_path, capsys, refused,
                                                                                 monkeypatch):
    pytest.importorskip("matplotlib", reason="drawing a 2D skill needs the plot extra")
    _run_folder(tmp_path, [[0.199, 0.3]])  # float32 0.199 is 0.19900000095... in binary
    cli.main(["render", str(tmp_path), "--out", str(tmp_path / "one.gif"), "--width", "40", "--height", "40"])
    out = capsys.readouterr().out
    assert out.startswith("skill 0: behavior [0.199, 0.3], action [0.0, 1.0, 1.0,") and "0000" not in out
    refused(["render", str(tmp_path), "--index", "1"], "the repertoire holds 1 skill (0 to 0)")
    sweep = tmp_path / "sweep"
    sweep.mkdir()
    monkeypatch.setattr(manifest, "kind", lambda folder: "sweep" if folder == str(sweep) else None)
    refused(["render", str(sweep)], "is a folder of `mqd sweep`: `mqd render` takes a folder of `mqd run`")
