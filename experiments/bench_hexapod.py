"""The hexapod's cost: a generation of QD and of M-QD against `mujoco.rollout` alone, and the robot's datasheet.

    python experiments/bench_hexapod.py [--tasks hexapod_omni hexapod_uni] [--grow 100]
        [--out docs/data/bench_hexapod.md]

Per task, on C MuJoCo: `mujoco.rollout` alone on one generation's controls (Table II's population of random
actions, their controls computed beforehand, the task's MjData per thread: what the C backend calls), and one
jitted generation of QD and of the default "mqd" from repertoires grown for `--grow` generations
(`generation_ratio.ms_per_generation`), as ratios to the rollouts alone. Also writes the robot's datasheet (its
MJCF, servos, controller and step; `--datasheet`, docs/data/hexapod_datasheet.md, linked from docs/design.md and
docs/extending.md).
"""

from __future__ import annotations

import argparse
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import report
from generation_ratio import ms_per_generation
from mujoco import rollout

from envs import hexapod, physics
from mqd_jax import Config
from mqd_jax.core import registry


def rollout_ms(task_name: str, calls: int) -> float:
    """ms of `mujoco.rollout` on one generation's controls of random actions of `task_name`."""
    task = registry.make(task_name, backend="mujoco")
    population = Config.paper(task_name).population_size
    low, high = np.asarray(task.action_low), np.asarray(task.action_high)
    actions = np.random.default_rng(0).uniform(low, high, (population, len(low))).astype(np.float32)
    ctrl = np.asarray(jax.jit(task.rollout_controls)(jnp.asarray(actions)), np.float64)
    c = task._rollout
    assert isinstance(c, physics.CRollout)
    return report.median_ms(lambda: rollout.rollout(c.model, c.datas, c.initial_state[None], ctrl), calls)


def step_convergence(controllers: int = 64) -> tuple[float, float]:
    """The medians over random controllers (3 s) of how far a 4x finer step moves the final position (m) and the
    feet's contact fractions (`hexapod.finer_step_shift`)."""
    low, high = hexapod._box(len(hexapod.LEGS))
    actions = np.random.default_rng(0).uniform(low, high, (controllers, len(low))).astype(np.float32)
    moved, fractions = hexapod.finer_step_shift(hexapod.load(), actions)
    return float(np.median(moved)), float(np.median(fractions))


def datasheet() -> list[str]:
    """Markdown: the robot's limits, read from its MjModel and `envs.hexapod`'s controller."""
    model = hexapod.load()
    data = hexapod.start_data(model)
    inertia = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, inertia)
    name = lambda kind, i: mujoco.mj_id2name(model, kind, i)  # noqa: E731
    torso = model.body("torso")
    size = model.geom("torso").size
    hip, knee = model.joint("front_left_hip"), model.joint("front_left_knee")
    hip_act = model.actuator("front_left_hip")
    legs = [name(mujoco.mjtObj.mjOBJ_BODY, b) for b in range(model.nbody) if name(mujoco.mjtObj.mjOBJ_BODY, b)
            in hexapod.LEGS]
    deg = math.degrees
    kp, damping = model.actuator_gainprm[hip_act.id][0], model.dof_damping[hip.dofadr[0]]
    ratio = lambda joint: damping / (2 * math.sqrt(kp * inertia[joint.dofadr[0], joint.dofadr[0]]))  # noqa: E731
    moved, fractions = step_convergence()
    rows = [
        ("mass", f"{model.body_subtreemass[torso.id]:.2f} kg (torso {model.body_mass[torso.id]:.2f} kg)"),
        ("torso", f"{200 * size[0]:.0f} x {200 * size[1]:.0f} x {200 * size[2]:.0f} cm"),
        ("standing height (torso centre)", f"{100 * data.qpos[2]:.1f} cm"),
        ("legs", f"{len(legs)}: {', '.join(legs)}; two joints each: hip (yaw), knee (lift)"),
        ("thigh, shin", f"{200 * model.geom('front_left_thigh').size[1]:.0f} cm, "
                        f"{200 * model.geom('front_left_shin').size[1]:.1f} cm; foot sphere "
                        f"{100 * model.geom('front_left_foot').size[0]:.1f} cm radius"),
        ("hip range", f"{deg(hip.range[0]):.0f} to {deg(hip.range[1]):.0f} deg"),
        ("knee range", f"{deg(knee.range[0]):.0f} to {deg(knee.range[1]):.0f} deg"),
        ("servos", f"{model.nu} position servos modelled on the Robotis Dynamixel MX-28 at 12 V (Cully et al. "
                   f"2015's): stall torque {hexapod.STALL_TORQUE} N m, no-load speed {hexapod.NO_LOAD_SPEED:.2f} "
                   "rad/s (55 rpm)"),
        ("torque-speed line", f"kp {kp:.0f} N m/rad, clamped to +-{model.actuator_forcerange[hip_act.id][1]} N m, "
                              f"minus the back-EMF damping {damping} N m s/rad: the torque falls linearly from the "
                              f"stall torque at rest to 0 at {hexapod.STALL_TORQUE / damping:.2f} rad/s"),
        ("reflected rotor inertia (armature)", f"{model.dof_armature[hip.dofadr[0]]} kg m^2"),
        ("damping ratio (standing)", f"hip {ratio(hip):.2f}, knee {ratio(knee):.2f}"),
        ("leg collisions", f"neighbouring legs (front-middle, middle-rear, each side): {model.npair} pairs of "
                           f"geoms, pushed apart from {1000 * model.pair_margin[0]:.0f} mm"),
        ("foot friction", f"{model.geom('front_left_foot').friction[0]}"),
        ("timestep, integrator", f"{1000 * model.opt.timestep:.0f} ms, implicit-fast"),
        ("step convergence (64 random controllers, 3 s)",
         f"a 4x finer step moves the final position by a median {1000 * moved:.1f} mm (a quarter of hexapod_omni's "
         f"t_dist: {250 * hexapod.Omni.default_t_dist:.1f} mm), the contact fractions by {fractions:.3f} (a quarter "
         f"of hexapod_uni's: {hexapod.Uni.default_t_dist / 4:.4f})"),
        ("controller", f"per leg: swing {hexapod.SWING} rad x s, phase pi x p, lift {hexapod.LIFT} rad x l, "
                       f"offset {hexapod.OFFSET} rad x o; period {hexapod.PERIOD} s, faded in over {hexapod.RAMP} s"),
        ("action", f"{len(hexapod.LEGS) * hexapod.PARAMETERS} numbers: (s, p, l, o) per leg in [-1, 1] x [-1, 1] x "
                   "[0, 1] x [-1, 1]"),
        ("rollout", f"{hexapod.SECONDS:.0f} s ({round(hexapod.SECONDS / model.opt.timestep)} steps)"),
        ("fall (invalid)", f"tilt past {deg(hexapod.FALL_TILT):.0f} deg or torso centre below "
                           f"{100 * hexapod.FALL_HEIGHT:.0f} cm at any step"),
        ("foot contact", "a contact between the foot and the floor in the simulator's contact list (a `contact` "
                         "sensor per foot, C MuJoCo and MJX alike)"),
        ("a robot that stays put (hexapod_omni)", f"within {1000 * hexapod.STILL:.0f} mm of the start the arc's "
                                                  "tangent is the start's heading: quality -abs(yaw) / pi"),
        ("simplified", "12 joints (hip yaw and knee per leg) where Cully et al.'s robot has 18; the servos have "
                       "no current limit, backlash, deadband or firmware PID; rigid links and feet on a flat floor"),
    ]
    return ["| quantity | value |", "|---|---|", *(f"| {k} | {v} |" for k, v in rows)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["hexapod_omni", "hexapod_uni"])
    parser.add_argument("--grow", type=int, default=None, help="default: the task's Table II generations")
    parser.add_argument("--calls", type=int, default=10)
    parser.add_argument("--out", default="docs/data/bench_hexapod.md")
    parser.add_argument("--datasheet", default="docs/data/hexapod_datasheet.md")
    args = parser.parse_args()
    report.write(datasheet(), args.datasheet)
    lines = [f"Command: `python experiments/bench_hexapod.py --tasks {' '.join(args.tasks)}"
             + (f" --grow {args.grow}" if args.grow else "") + "`", "", f"Machine: {report.machine()}", "",
             "ms of `mujoco.rollout` alone on one generation's controls (C MuJoCo, Table II's population; the median "
             f"of {args.calls} calls) and of one jitted generation (C backend) from repertoires grown for the task's "
             "Table II generations (the best of 5 rounds of medians); ratios to the rollouts alone.", "",
             "| task | population | rollout alone ms | QD ms/gen | x rollout | M-QD ms/gen | x rollout |",
             "|---|---|---|---|---|---|---|"]
    for task in args.tasks:
        alone = rollout_ms(task, args.calls)
        ms = ms_per_generation(task, ["mqd"], args.grow, calls=args.calls)
        lines.append(f"| {task} | {Config.paper(task).population_size} | {alone:.0f} | {ms['qd']:.0f} | "
                     f"{ms['qd'] / alone:.2f} | {ms['mqd']:.0f} | {ms['mqd'] / alone:.2f} |")
        print(lines[-1], flush=True)
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
