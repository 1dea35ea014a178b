"""What uniform random actions do on the robot tasks: how many are valid and why not, how often they touch the
object, how often the arm touches the world, whether the joints keep the datasheet's speed limits, how fast the
gripper and the object move, and (Place) how settled the arm is when the cube is let go and how often the cube was
knocked out of the hand before. C MuJoCo backend.

    python experiments/random_actions.py [--actions 2000] [--tasks push_cube push_sphere place] [--out FILE.md]
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import report
from mujoco import rollout

from envs import kuka, manipulation
from mqd_jax.core import registry


def _touched(model: mujoco.MjModel, initial_state: np.ndarray, ctrl: np.ndarray, until: np.ndarray) -> np.ndarray:
    """[R] whether the hand (tool, pads) or the held object touched the table, a shelf or the floor in the first
    until[r] steps of each control sequence ctrl [R, H, nu] (stepped one at a time to read the contacts)."""
    def geoms(*prefixes: str) -> set[int]:
        return {g for g in range(model.ngeom) if (mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or "")
                .startswith(prefixes)}

    hand, surfaces = geoms("tool", "gripper_pad", "object"), geoms("table", "shelf", "floor")
    data, out = mujoco.MjData(model), np.zeros(len(ctrl), bool)
    for r in range(len(ctrl)):
        mujoco.mj_setState(model, data, initial_state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        for t in range(until[r]):
            data.ctrl[:] = ctrl[r, t]
            mujoco.mj_step(model, data)
            pairs = zip(data.contact.geom1[:data.ncon], data.contact.geom2[:data.ncon], strict=True)
            if any((g1 in hand and g2 in surfaces) or (g2 in hand and g1 in surfaces) for g1, g2 in pairs):
                out[r] = True
                break
    return out


def _stats(name: str, num: int) -> dict[str, float]:
    """The statistics of `num` uniform random actions on task `name`."""
    task = registry.make(name, backend="mujoco")
    actions = jnp.asarray(np.random.default_rng(0).uniform(task.action_low, task.action_high,
                                                           (num, task.action_dim)), jnp.float32)
    plan = jax.jit(task.plan)(actions)
    _, _, valid = jax.jit(task.evaluate)(actions, None)
    reached, fits, valid = np.asarray(plan.reached), np.asarray(plan.fits), np.asarray(valid)
    runs = np.flatnonzero(reached & fits)
    c = task._rollout
    model = c.model
    ctrl = np.asarray(plan.ctrl, np.float64)[runs]
    state, sensors = rollout.rollout(c.model, c.datas, c.initial_state[None], ctrl)
    qvel = np.abs(state[:, :, 1 + model.nq:1 + model.nq + 7]).max(axis=1)  # [R, 7] peak joint speeds
    limits = np.radians(kuka.JOINT_SPEED_LIMITS)
    within_limits = np.all(qvel <= limits, axis=1)
    dt = float(model.opt.timestep)
    ee_speed = np.linalg.norm(np.diff(sensors[:, :, :3], axis=1), axis=-1).max(axis=1) / dt
    obj = sensors[:, :, 3:6]
    end_speed = np.linalg.norm(obj[:, -1] - obj[:, -2], axis=-1) / dt
    on_table = np.all((obj[:, -1, :2] >= kuka.TABLE_LOW) & (obj[:, -1, :2] <= kuka.TABLE_HIGH), axis=1)
    out = {"actions": num, "IK reached": reached.mean(), "motion fits": (reached & fits).mean(),
           "valid": valid.mean(), "off the table (of simulated)": 1 - on_table.mean(),
           "still moving at the end (of simulated)": (end_speed > manipulation.REST_SPEED).mean(),
           "joint speeds within limits (of simulated)": within_limits.mean(),
           "worst joint speed / limit": (qvel / limits).max(),
           "arm touched the table, a shelf or the floor (invalid; of simulated)": kuka.arm_touched(sensors).mean(),
           "joint speeds within limits (of valid)": within_limits[valid[runs]].mean(),
           "gripper peak speed median (m/s)": np.median(ee_speed), "gripper peak speed max (m/s)": ee_speed.max()}
    if name.startswith("push"):
        moved = np.linalg.norm(obj[:, -1, :2] - np.asarray(kuka.TABLE_CENTRE), axis=1) > 0.01
        out["touch rate (object moved > 1 cm, of simulated)"] = moved.mean()
        out["touch rate (of all actions)"] = moved.sum() / num
    else:
        release = np.asarray(task.release_step(plan.durations))[runs]
        last = np.asarray(task.via_points(actions)[0])[runs, -1]
        at_release = sensors[np.arange(len(runs)), release - 1, :3]
        lag = np.linalg.norm(at_release - last, axis=1)
        out["gripper to last via-point at release, median (mm)"] = 1e3 * np.median(lag)
        out["gripper to last via-point at release, max (mm)"] = 1e3 * lag.max()
        _, _, held = task.outcome(jnp.asarray(sensors), plan.durations[runs])
        lost = ~np.asarray(held)
        out["cube knocked out of the hand before release (of simulated)"] = lost.mean()
        touched = _touched(model, c.initial_state, ctrl, release)
        out["hand or cube touched a shelf, the table or the floor before release (of simulated)"] = touched.mean()
        out["cube lost without touching one (of simulated)"] = (lost & ~touched).mean()
        out["over a joint speed limit without touching one (of simulated)"] = (~within_limits & ~touched).mean()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actions", type=int, default=2000)
    parser.add_argument("--tasks", nargs="*", default=["push_cube", "push_sphere", "place"])
    parser.add_argument("--out", default="results/random_actions.md")
    args = parser.parse_args()
    stats = {name: _stats(name, args.actions) for name in args.tasks}
    keys = list(dict.fromkeys(k for s in stats.values() for k in s))
    lines = [f"Uniform random actions, C MuJoCo; {report.machine()}.", "",
             "| statistic | " + " | ".join(args.tasks) + " |", "|---|" + "---|" * len(args.tasks)]
    for k in keys:
        cells = [f"{stats[t][k]:.3g}" if k in stats[t] else "" for t in args.tasks]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
