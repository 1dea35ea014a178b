"""The hexapod's physics, 0.14's servos and step against today's: how the joints move, how hard the feet land,
whether the behaviors depend on the step, whether legs overlap, and what the contact rule counts.

    python experiments/hexapod_fidelity.py [--gaits 32] [--out docs/data/hexapod_fidelity.md]

Two models of the robot, on C MuJoCo: today's (`envs/assets/hexapod.xml`: Dynamixel MX-28 servos, their
torque-speed line, neighbouring legs that collide, a 4 ms step) and 0.14's (today's MJCF without the legs'
collisions, with kp 8, damping 0.1 N m s/rad, a 2 N m limit and a 10 ms step). For each:

* a 0.5 rad step of the front left hip, the robot standing: overshoot and peak speed;
* `--gaits` random gaits of 3 s: the fastest joint against the MX-28's no-load speed, the peak normal force
  on a foot against the robot's weight (median and largest over the gaits), the share of steps with no foot
  on the floor, the share of foot-steps with a contact in MuJoCo's contact list and the share 0.12-0.14's
  rule counted down (the foot's centre within 2 cm of the floor);
* the same gaits at a 4x finer step: how far the final positions move (`hexapod.finer_step_shift`);
* a gait that swings the front legs back onto the middle ones (`hexapod.ONTO_MIDDLE`): the deepest overlap of
  neighbouring legs (`hexapod.leg_overlap`).
"""

from __future__ import annotations

import argparse

import jax.numpy as jnp
import mujoco
import numpy as np
import report

from envs import hexapod

OLD_HEIGHT = 0.02  # m: 0.12-0.14 counted a foot down while its centre was this close to the floor


def old_servos(model: mujoco.MjModel) -> mujoco.MjModel:
    """`model` with 0.14's servos and step."""
    model.dof_damping[6:] = 0.1
    model.actuator_forcerange[:] = (-2.0, 2.0)
    model.opt.timestep = 0.01
    return model


def step_response(model: mujoco.MjModel) -> tuple[float, float]:
    """(overshoot as a share of the step, peak speed rad/s) of a 0.5 rad step of the front left hip."""
    data = hexapod.start_data(model)
    hip = model.joint("front_left_hip")
    angles, speeds = [], []
    for _ in range(round(1.0 / model.opt.timestep)):
        data.ctrl[:] = 0.0
        data.ctrl[model.actuator("front_left_hip").id] = 0.5
        mujoco.mj_step(model, data)
        angles.append(data.qpos[hip.qposadr[0]])
        speeds.append(abs(data.qvel[hip.dofadr[0]]))
    return max(0.0, (max(angles) - 0.5) / 0.5), max(speeds)


def gaits(model: mujoco.MjModel, actions: np.ndarray, seconds: float = hexapod.SECONDS) -> dict[str, np.ndarray]:
    """Per gait: fastest joint (rad/s), peak foot force (N), steps with no foot down, foot-steps with a contact
    and foot-steps within `OLD_HEIGHT`."""
    feet = [model.geom(f"{leg}_foot").id for leg in hexapod.LEGS]
    sites = [model.site(f"{leg}_foot").id for leg in hexapod.LEGS]
    horizon = round(seconds / model.opt.timestep)
    ctrl = np.asarray(hexapod.controls(jnp.asarray(actions), horizon, model.opt.timestep))
    force = np.zeros(6)
    out: dict[str, list] = {k: [] for k in ("speed", "force", "airborne", "contact", "near")}
    for row in ctrl:
        data = hexapod.start_data(model)
        speed = peak = airborne = contact = near = 0.0
        for u in row:
            data.ctrl[:] = u
            mujoco.mj_step(model, data)
            speed = max(speed, np.abs(data.qvel[6:]).max())
            down = set()
            for i in range(data.ncon):
                c = data.contact[i]
                foot = c.geom1 if c.geom1 in feet else c.geom2 if c.geom2 in feet else None
                if foot is not None:
                    down.add(foot)
                    mujoco.mj_contactForce(model, data, i, force)
                    peak = max(peak, force[0])
            airborne += not down
            contact += len(down)
            near += (data.site_xpos[sites, 2] <= OLD_HEIGHT).sum()
        for k, v in (("speed", speed), ("force", peak), ("airborne", airborne / horizon),
                     ("contact", contact / (6 * horizon)), ("near", near / (6 * horizon))):
            out[k].append(v)
    return {k: np.asarray(v) for k, v in out.items()}


def deepest_overlap(model: mujoco.MjModel) -> float:
    """The deepest overlap (m) of neighbouring legs in 1.5 s of `hexapod.ONTO_MIDDLE`."""
    data = hexapod.start_data(model)
    horizon = round(1.5 / model.opt.timestep)
    deepest = 0.0
    for u in np.asarray(hexapod.controls(jnp.asarray(hexapod.ONTO_MIDDLE[None]), horizon, model.opt.timestep))[0]:
        data.ctrl[:] = u
        mujoco.mj_step(model, data)
        deepest = max(deepest, hexapod.leg_overlap(model, data))
    return deepest


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaits", type=int, default=32)
    parser.add_argument("--out", default="docs/data/hexapod_fidelity.md")
    args = parser.parse_args()
    low, high = hexapod._box(len(hexapod.LEGS))
    actions = np.random.default_rng(0).uniform(low, high, (args.gaits, len(low))).astype(np.float32)
    weight = float(hexapod.load().body_subtreemass[1] * -hexapod.load().opt.gravity[2])
    xml = open(hexapod.XML).read()
    free = xml[:xml.index("  <contact>")] + xml[xml.index("  </contact>") + len("  </contact>"):]
    lines = [f"Command: `python experiments/hexapod_fidelity.py --gaits {args.gaits}`", "",
             f"Machine: {report.machine()}; C MuJoCo {mujoco.__version__}", "",
             f"{args.gaits} random gaits of {hexapod.SECONDS:.0f} s. Speeds against the MX-28's no-load speed "
             f"({hexapod.NO_LOAD_SPEED:.2f} rad/s), foot forces against the robot's weight ({weight:.1f} N); the "
             "finer step is 4x finer; overlaps on the gait that swings the front legs onto the middle ones.", "",
             "| model | hip step: overshoot, peak speed | fastest joint / no-load speed (median, max) | peak foot "
             "force / weight (median, max) | steps airborne | foot-steps in contact / counted by 0.14's 2 cm "
             "rule | final position moved by a 4x finer step (median, p90) | deepest leg overlap |",
             "|---|---|---|---|---|---|---|---|"]
    models = {"0.14: no leg collisions, its servos, 10 ms": lambda: old_servos(mujoco.MjModel.from_xml_string(free)),
              "0.15: leg collisions, MX-28 servos, 4 ms": lambda: mujoco.MjModel.from_xml_path(hexapod.XML)}
    for name, make in models.items():
        model = make()
        overshoot, peak_speed = step_response(model)
        coarse = gaits(model, actions)
        moved, _ = hexapod.finer_step_shift(model, actions)
        speed, force = coarse["speed"] / hexapod.NO_LOAD_SPEED, coarse["force"] / weight
        overlap = f"{1000 * deepest_overlap(model):.1f} mm"
        lines.append(f"| {name} | {100 * overshoot:.0f}%, {peak_speed:.1f} rad/s | {np.median(speed):.2f}, "
                     f"{speed.max():.2f} | {np.median(force):.2f}, {force.max():.2f} | "
                     f"{100 * coarse['airborne'].mean():.2f}% | {coarse['contact'].mean():.2f} / "
                     f"{coarse['near'].mean():.2f} | {1000 * np.median(moved):.1f} mm, "
                     f"{1000 * np.percentile(moved, 90):.1f} mm | {overlap} |")
        print(lines[-1], flush=True)
    report.write(lines, args.out)


if __name__ == "__main__":
    main()
