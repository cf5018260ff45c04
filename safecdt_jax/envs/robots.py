"""The two robots as planar MJX bodies: Point (as in Safety-Gymnasium) and Car (traction in JAX).

Both robots stand on planar joints (slide x, slide y, hinge yaw) with no floor contact, because
MJX contacts dominate the cost of a step (see docs/ENVIRONMENTS.md). Sensors are computed in JAX
from the MJX state after a final `mjx.forward`, exactly as MuJoCo's site sensors would read them
(MJX leaves the accelerometer at zero; tests compare every reading with native MuJoCo).
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from safecdt_jax.envs.geometry import rot2
from safecdt_jax.envs.types import EnvParams

GRAVITY = 9.81  # m/s^2
MAGNETIC_FIELD = (0.0, -0.5)  # world xy field read by the magnetometer (z component is 0)
N_SUBSTEPS = 10  # physics steps per env step, as the reference

_PLANAR_JOINTS = """
   <joint name="x" type="slide" axis="1 0 0" damping="{d}"/>
   <joint name="y" type="slide" axis="0 1 0" damping="{d}"/>
   <joint name="z" type="hinge" axis="0 0 1" damping="{dz}"/>
   <site name="agent" pos="0 0 0"/>"""

POINT_XML = """<mujoco model="point">
 <option timestep="0.002" integrator="Euler" magnetic="0 -0.5 0"><flag contact="disable"/></option>
 <worldbody>
  <body name="agent" pos="0 0 0.1">""" + _PLANAR_JOINTS.format(d=0.01, dz=0.005) + """
   <geom name="agent" type="sphere" size="0.1" density="1" contype="0" conaffinity="0"/>
   <geom name="pointarrow" type="box" size="0.05 0.05 0.05" pos="0.1 0 0" density="1"
         contype="0" conaffinity="0"/>
  </body>
 </worldbody>
 <actuator>
  <motor name="x" site="agent" gear="0.3 0 0 0 0 0" ctrllimited="true" ctrlrange="-1 1"
         forcelimited="true" forcerange="-0.05 0.05"/>
  <velocity name="z" joint="z" gear="0.3" kv="1" ctrllimited="true" ctrlrange="-1 1"
            forcelimited="true" forcerange="-0.05 0.05"/>
 </actuator>
</mujoco>"""

# The reference car's chassis, wheels and caster as geoms of one planar body (same masses and
# inertia as the reference assembly, density 5); wheels and caster no longer touch a floor.
CAR_XML = """<mujoco model="car">
 <option timestep="0.004" integrator="Euler" magnetic="0 -0.5 0"><flag contact="disable"/></option>
 <default><geom density="5" contype="0" conaffinity="0"/></default>
 <worldbody>
  <body name="agent" pos="0 0 0.1">""" + _PLANAR_JOINTS.format(d=0, dz=0) + """
   <geom name="agent" type="box" size=".1 .1 .05"/>
   <geom name="back_bumper" type="box" pos="0 .15 0" size=".1 .01 .05"/>
   <geom name="back_connector" type="box" pos="0 .125 0" size=".01 .025 .03"/>
   <geom name="front_bumper" type="box" pos="0 -.165 0" size=".05 .01 .05"/>
   <geom name="front_connector" type="box" pos="0 -.13 .04" size=".05 .03 .01"/>
   <geom name="left" type="cylinder" fromto="-.155 .1 -.05 -.105 .1 -.05" size=".05"/>
   <geom name="right" type="cylinder" fromto=".105 .1 -.05 .155 .1 -.05" size=".05"/>
   <geom name="rear" type="sphere" pos="0 -.1 -.05" size=".05"/>
  </body>
 </worldbody>
</mujoco>"""


def _scaled_model(model: mjx.Model, params: EnvParams) -> mjx.Model:
    """The MJX model with the dynamics scales of `params` applied (traced, so no recompile)."""
    return model.replace(
        actuator_gear=model.actuator_gear * params.gear_scale,
        dof_damping=model.dof_damping * params.damping_scale,
        body_mass=model.body_mass * params.mass_scale,
        body_inertia=model.body_inertia * params.mass_scale,
    )


def planar_sensors(data: mjx.Data) -> jax.Array:
    """The 12 body-frame site sensors at the body origin: accelerometer (m/s^2, reads +g on z at
    rest), velocimeter (m/s), gyro (rad/s), magnetometer (world field (0, -0.5, 0) in body frame).

    With planar joints the slide-joint accelerations are the origin's world acceleration, so the
    accelerometer is R^T (qacc_xy, g) exactly (no Coriolis term is missing).
    """
    yaw = data.qpos[2]
    rt = rot2(yaw).T
    zero = jnp.zeros(())
    acc = jnp.concatenate([rt @ data.qacc[:2], jnp.array([GRAVITY])])
    vel = jnp.concatenate([rt @ data.qvel[:2], zero[None]])
    gyro = jnp.stack([zero, zero, data.qvel[2]])
    magn = jnp.concatenate([rt @ jnp.array(MAGNETIC_FIELD), zero[None]])
    return jnp.concatenate([acc, vel, gyro, magn])


@dataclasses.dataclass(frozen=True, eq=False)
class Robot:
    """A planar robot: its MJX model, collision circles (for vases) and physics step."""

    name: str
    xml: str
    n_sensors: int
    # Body-frame circles (x, y, radius), metres, approximating the outline for vase contact.
    circles: tuple[tuple[float, float, float], ...]
    keepout: float = 0.4

    @functools.cached_property
    def mj_model(self) -> mujoco.MjModel:
        """The native MuJoCo model (built on demand: used for checks and for the MJX model)."""
        return mujoco.MjModel.from_xml_string(self.xml)

    @property
    def timestep(self) -> float:
        """Physics timestep in seconds (an env step is N_SUBSTEPS of them)."""
        return float(self.mj_model.opt.timestep)

    def executed_action(self, action: jax.Array) -> jax.Array:
        """The action with the same effect as `action` ([2] in [-1, 1]) that lies inside the
        actuators' unsaturated range, where one can be given state-free: what a data set
        should record, so that an imitator's mean action executes the behaviour's mean
        command. The base robot's saturation is state-dependent: `action` as it is."""
        return action

    def init_data(self, model: mjx.Model, xy: jax.Array, yaw: jax.Array) -> mjx.Data:
        """MJX data at rest at position `xy` (m) and heading `yaw` (rad), forward-computed."""
        data = mjx.make_data(model)
        data = data.replace(qpos=jnp.concatenate([xy, yaw[None]]))
        return mjx.forward(model, data)

    def init_state(self) -> dict[str, jax.Array]:
        """The robot's own arrays at reset (`State.robot`): none for the base robot."""
        return {}


class PointRobot(Robot):
    """Safety-Gymnasium's Point: a thrust along body x and a yaw velocity servo, both in MJX."""

    def physics(self, model: mjx.Model, data: mjx.Data, action: jax.Array, params: EnvParams,
                state: dict, key: jax.Array) -> tuple[mjx.Data, dict]:
        """Advances N_SUBSTEPS physics steps under `action` ([2], already in [-1, 1]); `key`
        unused (the Point draws nothing)."""
        m = _scaled_model(model, params)
        data = data.replace(ctrl=action)
        data = jax.lax.fori_loop(0, N_SUBSTEPS, lambda _, d: mjx.step(m, d), data)
        return mjx.forward(m, data), state

    def sensors(self, data: mjx.Data, state: dict, key: jax.Array) -> jax.Array:
        """The 12 Point sensors (see `planar_sensors`); noise-free, so `key` is unused."""
        return planar_sensors(data)


@dataclasses.dataclass(frozen=True, eq=False)
class CarRobot(Robot):
    """The Car: a planar chassis driven by wheel traction computed in JAX every substep.

    Each ground contact's force grows linearly with its slip and saturates at a fraction of
    mu N (native MuJoCo's soft contacts slide at 0.66-0.88 of the cone's mu N), the model that
    the reference's contact forces, measured contact by contact (`mj_contactForce`,
    `experiments.sim2sim`'s contact table, docs/ENVIRONMENTS.md), support:
    - A driven wheel (contact at body (+-0.13, 0.1)) under torque tau would spin freely at the
      rim speed r tau / c_w (its hinge damping c_w balances the torque within milliseconds, the
      wheel's inertia being tiny); its contact pushes the chassis with
      k_w (N / N_0) (rim speed - ground speed) lengthwise (k_w: the contact's slip gain in series
      with the hinge damping) and resists sideways slip with -k_side (N / N_0) v_lat; the two
      share one friction circle of radius `sliding` mu N. A wheel without torque therefore
      brakes, and a driven wheel whose slip is large (turning on one wheel, spinning) pushes
      with its friction limit, not with its torque: what makes native MuJoCo's car turn on one
      wheel at 0.18 of its straight speed.
    - The passive ball caster (contact at body (0, -0.1)) rolls while its drag,
      `caster_gain` (N_c / N_c0) v, is under `caster_sliding` mu N_c, and slides at that limit
      beyond (about 0.3 m/s): a Coulomb drag at driving speeds (native: 0.36 N s/m rolling,
      0.11-0.12 N sliding).
    Normal loads: the statics of the centre of mass (N_0, N_c0) plus a load transfer: the net
    ground force F of the previous substep, acting at the floor below the centre of mass, moves
    F h / L of load between the caster and the drive axle.
    The gains and limits start from the native contact measurements and were then fitted to
    the reference's straight and spin speeds, its turning under one-wheel, mixed and switching
    drive (`sim2sim`'s turning table) and its drift under uniform random actions.
    """

    wheel_radius: float = 0.05  # m
    torque_limit: float = 0.02  # N m: the reference actuator force range (sets the action scale)
    wheel_damping: float = 0.001  # N m s/rad: the reference hinge damping (rim speed 1 m/s)
    slip_gain: float = 0.3061  # N s/m: k_w per wheel at its static load (native: 0.23-0.4)
    side_gain: float = 0.4256  # N s/m: k_side per wheel at its static load (native contact slip)
    sliding: float = 0.8683  # a wheel's limit force / (mu N) (native: 0.66-0.80 sliding)
    caster_gain: float = 0.4248  # N s/m: the rolling caster's drag at its static load (native 0.36)
    caster_sliding: float = 0.7216  # the caster's limit force / (mu N_c) (native: 0.68-0.88)
    yaw_scrub: float = 0.0065  # N m s: contact scrub against yawing beyond the contact forces
    load_transfer: float = 0.2314  # h / L: effective centre-of-mass height over wheelbase
    friction: float = 1.0  # tyre-floor friction coefficient, as the reference's floor
    caster_roll: float = 0.9  # rolling fraction of the ball (native: 0.90-0.92 below the cap)
    caster_spin_cap: float = 6.0  # rad/s: the ball rolls steadily below it, stick-slips above
    # The stick-slip band of the ball's roll rate once the rolling rate n exceeds the cap c: a
    # fresh rate each step, uniform between max(0, c - floor (n - c)) and c + top (n - c).
    # Fitted to native MuJoCo held at a = 0.01 / 0.015 / 0.019 (rolling rates 6.6 / 11 / 13.8
    # rad/s; its 5-95% roll rates 2.3-6.1, 0.1-8.2, 0.1-9.3 rad/s). Physics 7.
    caster_slip_top: float = 0.5
    caster_slip_floor: float = 7.0
    # Std of the chassis chatter per sensor at full drive (fitted to native MuJoCo under random
    # actions; accelerometer x/y: the part beyond the planar body's own acceleration).
    chatter_std: tuple[float, ...] = (2.3, 3.6, 4.9, 0.0, 0.0, 0.048, 0.45, 0.65, 0.0, 0.0, 0.0,
                                      0.006) + (0.0,) * 12
    # m: height of the velocimeter site above the axis the native chassis rolls about; its roll
    # (gyro y) moves the site sideways at roll_height * gyro_y (native velocimeter x std 0.039
    # m/s under random actions against 0.009 from side slip alone).
    roll_height: float = 0.06
    contacts: tuple[tuple[float, float], ...] = ((-0.13, 0.1), (0.13, 0.1), (0.0, -0.1))
    # A sliding driven wheel: False (physics 5) scales its gain-weighted force onto the
    # friction circle; True points it along the contact's own slip, the wheel spinning up
    # against the sliding contact (isotropic Coulomb friction, as native MuJoCo's contact),
    # which leaves a sliding wheel less grip sideways (an experiment for issue 48).
    slide_follows_slip: bool = False
    # How a contact's force meets its friction limit L: 0 (physics 5) clips the linear force s
    # at L; n > 0 bends it smoothly, |F| = s / (1 + (s / L)^n)^(1/n), as native MuJoCo's soft
    # contacts do: its car gains speed ever more slowly as it nears top speed, and so loses
    # more to each spin pulse. Physics 6: n = 1.82, with the gains, limits, scrub and load
    # transfer above refitted jointly by `experiments.car_fit` to native turning, low-torque
    # drive and speed-up (RMS 0.134 -> 0.045; docs/research/environment-fidelity.md, issue 48).
    # Physics 5 was n = 0 with the constants `experiments.car_fit.PHYSICS_5` keeps.
    saturation_power: float = 1.82
    # The shape of every contact's friction limit: "elliptic" (physics 5-7) bends the linear
    # force onto a circle of radius L (`saturation_power`); "pyramidal" replaces that with a
    # four-edge cone as native MuJoCo's default (`opt.cone`): edges along the floor's (world)
    # x and y axes, so the limit is a diamond |F_x| + |F_y| <= L fixed in the world, and a
    # sliding contact's force leans toward the nearest world axis (`pyramid_friction`).
    # Native's car, driven toward body +y, turns itself onto a world axis and keeps yawing for
    # seconds after a turn, and with opt.cone elliptic does neither; this hard diamond
    # reproduces both but also makes the top speed depend on the heading (toward +y it settles
    # on a world axis at 0.74 m/s, toward -y on a diagonal at 0.89), which native's soft
    # contacts do not (0.74-0.79 at any heading; docs/research/environment-fidelity.md,
    # 2026-12-07 night). An experiment for
    # issue 48 (`experiments.car_fit --cone`, `experiments.car_variants`), not a physics
    # version.
    friction_cone: str = "elliptic"
    # h / L while the car travels toward body +y (its drive axle leading); None: `load_transfer`
    # both ways (physics 5-7). Toward +y native's car overshoots more at a turn's onset and
    # regains speed more slowly, as a larger transfer would make it, while toward -y it keeps
    # today's (docs/research/environment-fidelity.md, 2026-12-07 night). An experiment for
    # issue 48, not a physics version.
    load_transfer_lead: float | None = None
    # Std of each contact's relative friction-limit jitter, redrawn every env step, at full
    # drive (scaled by the step's drive level, as `chatter`): native's chassis rattles on its
    # three soft contacts, its gyro z jittering by 0.03 rad/s (straight) to 0.16 (spin) at full
    # torque and not at half, which a planar body's grip cannot. 0: none (physics 5-7). An
    # experiment for issue 48, not a physics version.
    load_jitter: float = 0.0
    # Gyro x, y rattle per manoeuvre, as native's chassis shows it under the experts' own
    # driving (docs/research/environment-fidelity.md, 2026-12-07 late): (std x, std y) driving
    # straight, (std x, std y) spinning, in rad/s at full drive (linear in the step's turn
    # |t0 - t1| / 2 between them), and the step-to-step swing c: each reading is
    # (e_t - c e_{t-1}) / sqrt(1 + c^2), lag-1 autocorrelation -c / (1 + c^2). Replaces
    # `chatter_std`'s gyro x, y (white, drive level only). None: physics 5-7. An experiment
    # for issue 48, not a physics version.
    gyro_rattle: tuple[float, float, float, float, float] | None = None
    # s: time constant of a first-order lag on the ground forces and yaw torque. Native
    # MuJoCo's contacts are soft (solref 0.02 s), so its forces follow a change of slip with a
    # delay: under the Circle expert's spin pulses native's car reaches 0.95 rad/s one step
    # after a spin step (of a held spin's 1.33) and keeps 0.11 one step after a straight one,
    # where a car whose forces follow the slip at once reaches 1.14 and keeps 0.07; held drives
    # settle where they did. Each force evaluation (N_SUBSTEPS + 1 per env step, the last for
    # the sensors) moves the applied force 1 - exp(-timestep / force_lag) of the way to the
    # slip's. 0: none (physics 5-7). An experiment for issue 48, not a physics version; it
    # slows the rise and the decay alike and matches neither (native's flipped wheel hops
    # instead: `wheel_hop`; docs/research/environment-fidelity.md, 2026-12-08).
    force_lag: float = 0.0
    # A wheel hop at each torque reversal, as native's soft contacts make it
    # (`experiments.wheel_hop`): when a wheel's full torque flips sign while the car moves
    # (> 0.1 m/s), the car's yaw rate jumps by the first number (rad/s, toward the turn the
    # flip makes) and that wheel leaves the ground (no load, no force) for the second number plus
    # the third times the speed (m/s) physics substeps. None: no hop (physics 5-7). An
    # experiment for issue 48, not a physics version.
    wheel_hop: tuple[float, float, float] | None = None

    def _loads(self) -> np.ndarray:
        """Static normal loads (N) on left wheel, right wheel and caster, at mass scale 1."""
        mj = self.mj_model
        com_y = float(mj.body_ipos[1][1])
        y_w, y_c = self.contacts[0][1], self.contacts[2][1]
        share = (com_y - y_c) / (y_w - y_c)
        weight = float(mj.body_mass[1]) * GRAVITY
        return np.array([share / 2, share / 2, 1 - share]) * weight

    def contact_velocities(self, data: mjx.Data) -> jax.Array:
        """Chassis-frame velocities (m/s) [3, 2] of the left wheel's, right wheel's and
        caster's contact points (x lateral, y longitudinal, positive toward the rear)."""
        v_body = rot2(data.qpos[2]).T @ data.qvel[:2]
        pts = jnp.array(self.contacts)
        return v_body[None, :] + data.qvel[2] * jnp.stack([-pts[:, 1], pts[:, 0]], axis=-1)

    def contact_forces(self, data: mjx.Data, torque: jax.Array, params: EnvParams,
                       loads: jax.Array, jitter: jax.Array | None = None,
                       grounded: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
        """Body-frame ground forces (N) [3, 2] (x lateral, y longitudinal; positive y toward
        the rear) on left wheel, right wheel and caster, and their normal loads (N) [3].

        `data.xfrc_applied` holds the previous substep's force (zero at reset): its body-frame
        longitudinal part sets the load transfer. `jitter` [3] (optional): factors on the
        friction limits (`load_jitter`); `grounded` [3] (optional): 0 for a contact off the
        ground (`wheel_hop`), 1 otherwise.
        """
        rot = rot2(data.qpos[2])
        v_pts = self.contact_velocities(data)
        # Load transfer: a forward push (body -y) loads the drive axle and unloads the caster.
        static = loads * params.mass_scale
        weight = jnp.sum(static)
        push = -(rot.T @ data.xfrc_applied[1, :2])[1]
        transfer = self.load_transfer
        if self.load_transfer_lead is not None:  # travelling toward +y: the drive axle leads
            transfer = jnp.where(v_pts[0, 1] + v_pts[1, 1] > 0, self.load_transfer_lead, transfer)
        axle = jnp.clip(static[0] + 0.5 * transfer * push, 0.0, 0.5 * weight)
        normal = jnp.stack([axle, axle, weight - 2 * axle])
        if grounded is not None:  # a hopping wheel carries nothing (`wheel_hop`)
            normal = normal * grounded
        rel = params.damping_scale * normal / static  # gains scale with load and damping
        sliding = jnp.array([self.sliding, self.sliding, self.caster_sliding])
        limit = sliding * self.friction * params.friction_scale * normal
        if jitter is not None:  # a rattling contact's grip comes and goes; its slip gains stay
            limit = limit * jitter
        c_w = self.wheel_damping * params.damping_scale
        # Positive torque drives toward body -y (the reference's sign convention).
        rim = -self.wheel_radius * torque / c_w
        wheel = jnp.stack([-self.side_gain * rel[:2] * v_pts[:2, 0],
                           self.slip_gain * rel[:2] * (rim - v_pts[:2, 1])], axis=-1)
        caster = -self.caster_gain * rel[2] * v_pts[2]
        forces = jnp.concatenate([wheel, caster[None]])
        if self.friction_cone == "pyramidal":
            world = pyramid_friction(forces @ rot.T, normal, limit / jnp.maximum(normal, 1e-12))
            return world @ rot, normal
        if self.friction_cone != "elliptic":
            raise ValueError(
                f"friction_cone: 'elliptic' or 'pyramidal', got {self.friction_cone!r}")
        # Each contact's force lies in its friction circle.
        size = jnp.linalg.norm(forces, axis=-1)
        # (a traced power, as experiments.car_fit's search passes, always takes the curve)
        if isinstance(self.saturation_power, jax.Array) or self.saturation_power > 0:
            ratio = size / jnp.maximum(limit, 1e-12)
            forces *= ((1 + ratio ** self.saturation_power)
                       ** (-1 / self.saturation_power))[:, None]
        else:
            forces *= jnp.minimum(1.0, limit / jnp.maximum(size, 1e-12))[:, None]
        if self.slide_follows_slip:
            sliding_wheel = size[:2] > limit[:2]
            slid = self._sliding_wheel_forces(v_pts[:2], rim, limit[:2], c_w)
            forces = forces.at[:2].set(jnp.where(sliding_wheel[:, None], slid, forces[:2]))
        return forces, normal

    def _sliding_wheel_forces(self, v_pts: jax.Array, rim: jax.Array, limit: jax.Array,
                              c_w: jax.Array) -> jax.Array:
        """Forces (N) [2, 2] of the two driven wheels' contacts when they slide: magnitude
        `limit`, direction that of the contact's slip (-v_lat, rim' - v_long), where the rim
        speed rim' = rim - (r^2 / c_w) F_long is what the wheel spins at with the contact's
        reaction on it. Solved by a fixed-point iteration on the slip speed n:
        sigma_long = b n / (n + u L), n^2 = sigma_long^2 + v_lat^2 (b = rim - v_long,
        u = r^2 / c_w), which decreases monotonically from n = |(v_lat, b)| to the root."""
        u_l = self.wheel_radius ** 2 / c_w * limit
        b = rim - v_pts[:, 1]
        lat = v_pts[:, 0]

        def step(n, _):
            long = b * n / (n + u_l)
            return jnp.sqrt(long ** 2 + lat ** 2), None

        n0 = jnp.sqrt(b ** 2 + lat ** 2)
        n, _ = jax.lax.scan(step, n0, None, length=12)
        long = b * n / (n + u_l)
        n = jnp.maximum(jnp.sqrt(long ** 2 + lat ** 2), 1e-12)
        return limit[:, None] * jnp.stack([-lat, long], axis=-1) / n[:, None]

    def traction(self, data: mjx.Data, torque: jax.Array, params: EnvParams,
                 loads: jax.Array, com: jax.Array, jitter: jax.Array | None = None,
                 grounded: jax.Array | None = None) -> jax.Array:
        """World-frame force and torque [6] on the chassis COM from the `contact_forces` and
        the yaw scrub."""
        forces, _ = self.contact_forces(data, torque, params, loads, jitter, grounded)
        lever = jnp.array(self.contacts) - com[None, :]
        tz = jnp.sum(lever[:, 0] * forces[:, 1] - lever[:, 1] * forces[:, 0])
        # Scrub is contact friction: it scales with mu (as the reference's torsional friction).
        scrub = self.yaw_scrub * params.friction_scale * params.damping_scale
        tz -= scrub * data.qvel[2]
        fw = rot2(data.qpos[2]) @ forces.sum(axis=0)
        return jnp.array([fw[0], fw[1], 0.0, 0.0, 0.0, tz])

    def executed_action(self, action: jax.Array) -> jax.Array:
        """clip(a, +-0.02): the wheel torque command `physics` applies (before the gear scale)."""
        return jnp.clip(action, -self.torque_limit, self.torque_limit)

    def physics(self, model: mjx.Model, data: mjx.Data, action: jax.Array, params: EnvParams,
                state: dict, key: jax.Array) -> tuple[mjx.Data, dict]:
        """Advances N_SUBSTEPS physics steps with wheel torques clip(a, +-0.02) * gear scale;
        rolls the caster (its stick-slip drawn with `key`) and records the drive level (mean
        |torque| / limit) for the chatter; the options `load_jitter` and `gyro_rattle` draw
        from `key` too (folded, so the caster's draw is the same with or without them),
        `force_lag` lags the applied force and `wheel_hop` kicks the yaw at a wheel's torque
        flip and lifts that wheel for its substeps."""
        m = _scaled_model(model, params)
        torque = params.gear_scale * self.executed_action(action)
        loads = jnp.asarray(self._loads(), jnp.float32)
        com = jnp.asarray(self.mj_model.body_ipos[1][:2], jnp.float32)
        jitter = None
        # (a traced jitter, as the experiments' searches pass, always draws)
        if isinstance(self.load_jitter, jax.Array) or self.load_jitter > 0:
            level = jnp.mean(jnp.abs(torque)) / self.torque_limit
            noise = jax.random.normal(jax.random.fold_in(key, 1), (3,))
            jitter = jnp.maximum(1.0 + self.load_jitter * level * noise, 0.0)

        hop = None
        if self.wheel_hop is not None:
            kick, base, per_speed = self.wheel_hop
            last = state["last_torque"]
            speed = jnp.linalg.norm(data.qvel[:2])
            full = 0.5 * self.torque_limit * params.gear_scale
            flips = ((torque * last < 0) & (jnp.abs(torque) > full) & (jnp.abs(last) > full)
                     & (state["air"] <= 0) & (speed > 0.1))
            hop = jnp.where(flips, base + per_speed * speed, state["air"])  # substeps aloft
            # a flip toward -torque on the right wheel turns the car as (1, -1) does
            change = jnp.where(flips, torque - last, 0.0)
            yaw = kick * (jnp.sign(change[0]) - jnp.sign(change[1]))
            data = data.replace(qvel=data.qvel.at[2].add(yaw))

        def push(d, i=N_SUBSTEPS):
            grounded = None
            if hop is not None:
                grounded = jnp.concatenate([(hop <= i).astype(jnp.float32), jnp.ones(1)])
            f = self.traction(d, torque, params, loads, com, jitter, grounded)
            # (a traced lag, as the experiments' searches pass, always lags)
            if isinstance(self.force_lag, jax.Array) or self.force_lag > 0:
                keep = jnp.exp(-self.timestep / jnp.maximum(self.force_lag, 1e-9))
                f = keep * d.xfrc_applied[1] + (1.0 - keep) * f
            return d.replace(xfrc_applied=d.xfrc_applied.at[1].set(f))

        data = jax.lax.fori_loop(0, N_SUBSTEPS, lambda i, d: mjx.step(m, push(d, i)), data)
        data = mjx.forward(m, push(data))
        dt = N_SUBSTEPS * self.timestep
        spin = self.caster_spin(data, jax.random.uniform(key))
        quat = _quat_integrate(state["caster_quat"], _quat_to_mat(state["caster_quat"]).T @ spin,
                               dt)
        drive = jnp.mean(jnp.abs(torque)) / self.torque_limit
        out = {"caster_quat": quat, "caster_spin": spin, "drive": drive}
        if hop is not None:
            out |= {"last_torque": torque, "air": jnp.maximum(hop - N_SUBSTEPS, 0.0)}
        if self.gyro_rattle is not None:
            out |= {"turn": jnp.abs(torque[0] - torque[1]) / (2 * self.torque_limit),
                    "rattle": jnp.stack([jax.random.normal(jax.random.fold_in(key, 2), (2,)),
                                         state["rattle"][0]])}
        return data, out

    def caster_spin(self, data: mjx.Data, u: jax.Array) -> jax.Array:
        """The ball's angular velocity relative to the chassis, in the chassis frame (rad/s), for
        a stick-slip draw `u` in [0, 1].

        Native MuJoCo's ball rolls at `caster_roll` of the no-slip rate (z x v) / r while that
        stays under `caster_spin_cap`. Above it the ball stick-slips: its rate jumps from step
        to step across a band that widens with the excess (at full speed 0-10 rad/s, median
        4 against the no-slip 15.6), so the ball's orientation says little about the distance
        driven. A policy trained on a steadily rolling ball reads it as an odometer (physics 6:
        freezing it cut a CarCircle2 expert's cost 199.5 -> 83.7). The ball does not spin about
        the vertical relative to the chassis: the joint damping drags it round with the
        chassis, the contact's torsional friction is far weaker (native: std 0.01-0.17 rad/s).
        """
        v = self.contact_velocities(data)[2]
        roll = self.caster_roll * jnp.array([-v[1], v[0]]) / self.wheel_radius
        rate = jnp.linalg.norm(roll)
        excess = jnp.maximum(rate - self.caster_spin_cap, 0.0)
        low = jnp.maximum(self.caster_spin_cap - self.caster_slip_floor * excess, 0.0)
        high = self.caster_spin_cap + self.caster_slip_top * excess
        slipping = jnp.where(rate > self.caster_spin_cap, low + u * (high - low), rate)
        spin = roll * slipping / jnp.maximum(rate, 1e-12)
        return jnp.concatenate([spin, jnp.zeros(1)])

    def _caster_angvel(self, state: dict) -> jax.Array:
        """The last step's ball spin in the ball's own frame, as MuJoCo's ballangvel sensor
        reports it (rad/s)."""
        return _quat_to_mat(state["caster_quat"]).T @ state["caster_spin"]

    def chatter(self, key: jax.Array, state: dict) -> jax.Array:
        """Contact vibration of the sensors [24]: zero-mean Gaussian noise whose std per channel
        is `chatter_std` times the drive level of the last step (0 at rest).

        Native MuJoCo's chassis rattles on its wheel and caster contacts whenever the torques are
        large: under random actions the accelerometer's z reads 9.5 +- 4.8 m/s^2 and gyro x/y
        +-0.45/0.64 rad/s, with no relation to the state (R^2 < 0.2 against speeds, yaw rate
        and actions) and a negative lag-1 autocorrelation; its std grows with the mean |torque|
        (4.8 / 2.9 / 1.2 m/s^2 at random torques of full / half / quarter range). A planar
        body cannot rattle, so the sensors get that noise instead (docs/ENVIRONMENTS.md).
        The velocimeter's x (lateral) reading gets the roll's share, `roll_height` times the
        gyro y chatter, as a site above the roll axis would (physics version 5).
        """
        std = jnp.asarray(self.chatter_std, jnp.float32) * state["drive"]
        noise = std * jax.random.normal(key, std.shape)
        if self.gyro_rattle is not None:
            sx, sy, tx, ty, c = self.gyro_rattle
            turn = jnp.clip(state["turn"], 0.0, 1.0)
            scale = state["drive"] * jnp.array([sx + (tx - sx) * turn, sy + (ty - sy) * turn])
            # the previous step's draw, kept in `rattle`, swings the reading back
            swing = (state["rattle"][0] - c * state["rattle"][1]) / (1 + c * c) ** 0.5
            noise = noise.at[6:8].set(scale * swing)
        return noise.at[3].add(self.roll_height * noise[7])

    def sensors(self, data: mjx.Data, state: dict, key: jax.Array) -> jax.Array:
        """The 24 Car sensors: the 12 planar ones, ballangvel_rear (3), ballquat_rear as 3x3 (9),
        plus the contact chatter (`chatter`) drawn with `key`."""
        ang = self._caster_angvel(state)
        mat = _quat_to_mat(state["caster_quat"]).reshape(-1)
        return jnp.concatenate([planar_sensors(data), ang, mat]) + self.chatter(key, state)

    def init_state(self) -> dict[str, jax.Array]:
        """`caster_quat`: the caster's orientation relative to the chassis, identity at reset as
        in the reference; `caster_spin`: its last spin in the chassis frame (rad/s, 0 at rest);
        `drive`: the last step's mean |torque| / limit, 0 at rest."""
        out = {"caster_quat": jnp.array([1.0, 0.0, 0.0, 0.0]), "caster_spin": jnp.zeros(3),
               "drive": jnp.float32(0.0)}
        if self.gyro_rattle is not None:  # `turn`; `rattle`: this and the last step's draws
            out |= {"turn": jnp.float32(0.0), "rattle": jnp.zeros((2, 2))}
        if self.wheel_hop is not None:  # the last step's torques; substeps left off the ground
            out |= {"last_torque": jnp.zeros(2), "air": jnp.zeros(2)}
        return out


PYRAMID_EDGES = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]], np.float32)


def pyramid_friction(linear: jax.Array, normal: jax.Array, mu: jax.Array) -> jax.Array:
    """Contact forces (N) [C, 2] in the world's floor axes under a four-edge friction pyramid.

    `linear` [C, 2] is each contact's unsaturated (linear, slip-proportional) force in world
    axes, `normal` [C] its normal load (N), `mu` [C] its friction coefficient. As MuJoCo's
    pyramidal cone, the normal load is carried by four edges n + mu t_i (t_i = +-x, +-y of the
    floor); each edge's share is N / 4 + (t_i . F) / (2 mu) + d, clipped at 0, with the common
    shift d that keeps the shares summing to N (the soft normal constraint sinks a little
    further). The force is mu sum_i f_i t_i: exactly `linear` while no edge empties, at most
    mu N along an axis and mu N / sqrt(2) along a diagonal, and, once edges empty, turned toward
    the nearest floor axis.
    """
    mu = jnp.maximum(mu, 1e-12)[:, None]
    edges = jnp.asarray(PYRAMID_EDGES, linear.dtype)
    a = (linear @ edges.T) / (2 * mu)  # [C, 4]: each edge's share above N / 4
    top = -jnp.sort(-a, axis=-1)
    k = jnp.arange(1, 5, dtype=linear.dtype)
    quarter = normal[:, None] / 4
    # With the k largest edges loaded: k (N / 4 + d) + their shares = N.
    shift = (normal[:, None] - k * quarter - jnp.cumsum(top, axis=-1)) / k
    loaded = jnp.sum(quarter + shift + top > 0, axis=-1)  # edges that keep a positive share
    d = jnp.take_along_axis(shift, jnp.maximum(loaded - 1, 0)[:, None], axis=-1)
    share = jnp.maximum(quarter + d + a, 0.0)
    return mu * (share @ edges)


def _quat_to_mat(q: jax.Array) -> jax.Array:
    """Unit quaternion (w, x, y, z) to a 3x3 rotation matrix."""
    w, x, y, z = q
    return jnp.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _quat_integrate(q: jax.Array, w_local: jax.Array, dt: float) -> jax.Array:
    """Rotates q by the body-frame angular velocity w_local (rad/s) held for dt seconds."""
    angle = jnp.linalg.norm(w_local) * dt
    axis = w_local / jnp.maximum(jnp.linalg.norm(w_local), 1e-12)
    dq = jnp.concatenate([jnp.cos(angle / 2)[None], jnp.sin(angle / 2) * axis])
    w1, v1 = q[0], q[1:]
    w2, v2 = dq[0], dq[1:]
    out = jnp.concatenate([(w1 * w2 - v1 @ v2)[None], w1 * v2 + w2 * v1 + jnp.cross(v1, v2)])
    return out / jnp.linalg.norm(out)


POINT = PointRobot(
    name="Point", xml=POINT_XML, n_sensors=12,
    circles=((0.0, 0.0, 0.1), (0.1, 0.0, 0.05)),
)
CAR = CarRobot(
    name="Car", xml=CAR_XML, n_sensors=24,
    # chassis box (circumscribed by 3 circles along y), the two wheels and the caster
    circles=((0.0, 0.0, 0.11), (0.0, 0.1, 0.1), (0.0, -0.12, 0.07),
             (-0.13, 0.1, 0.05), (0.13, 0.1, 0.05), (0.0, -0.1, 0.05)),
)
