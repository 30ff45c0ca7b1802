"""The six MuJoCo tasks: specs, registration, physics facts, reward bounds, seeding, state and bad input.

Expected numbers come from tasks.md and from hand computation, written next to each assertion.
"""
from __future__ import annotations

import math
import subprocess
import sys

import gymnasium
import mujoco
import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import check_env_specs

from torchrl_reset import DualCollector
from torchrl_reset_envs import (
    TASKS,
    BallInCupEnv,
    CliffCheetahEnv,
    CliffWalkerEnv,
    PegInsertionEnv,
    RenderingUnavailableError,
    make_env,
    make_gym_env,
    task_spec,
    tolerance,
)
from torchrl_reset_envs.peg import INSERT_START_QPOS, PEG_GOAL, PEG_START, REMOVE_START_QPOS

ALL_TASKS = [name for name, spec in TASKS.items() if spec.gym_id is not None]  # the six MuJoCo tasks
# tasks.md: (H_f, p_thresh, observation size, action size)
PAPER_NUMBERS = {
    "cliff_cheetah": (500, 0.05, 18, 6),
    "cliff_walker": (500, 0.05, 18, 6),
    "peg_insertion_insert": (100, 0.1, 14, 7),
    "peg_insertion_remove": (100, 0.1, 14, 7),
    "ball_in_cup_catch": (100, 0.1, 8, 2),
    "ball_in_cup_throw": (100, 0.1, 8, 2),
}
W = math.atanh(math.sqrt(0.95))  # Cond's slope factor times the margin


def random_actions(env, n, seed=0):
    rng = np.random.default_rng(seed)
    low, high = env.action_space.low, env.action_space.high
    return rng.uniform(low, high, size=(n, low.shape[0]))


# ---------------------------------------------------------------------------------------------- API
@pytest.mark.parametrize("task", ALL_TASKS)
def test_make_env_passes_check_env_specs_and_carries_the_paper_numbers(task):
    horizon, p_thresh, obs_dim, act_dim = PAPER_NUMBERS[task]
    env = make_env(task, seed=0)
    check_env_specs(env)
    assert (env.forward_horizon, env.p_thresh) == (horizon, p_thresh)
    assert (env.task_spec.forward_horizon, env.task_spec.p_thresh) == (horizon, p_thresh)
    td = env.reset()
    assert td["observation"].shape == (obs_dim,) and td["observation"].dtype == torch.float32
    assert env.action_spec.shape == (act_dim,)
    for key, dtype in (("reset_success", torch.bool), ("irrecoverable", torch.bool), ("reset_reward", torch.float32)):
        assert td[key].shape == (1,) and td[key].dtype == dtype
    step = env.rand_step(td)
    assert {"reset_success", "reset_reward", "irrecoverable", "reward"} <= set(step["next"].keys())


def test_gym_ids_work_in_a_fresh_process_without_a_prior_import():
    code = (
        "import sys, gymnasium\n"
        "assert 'torchrl_reset_envs' not in sys.modules\n"
        "ids = " + repr([TASKS[name].gym_id for name in ALL_TASKS]) + "\n"
        "for i in ids:\n"
        "    env = gymnasium.make('torchrl_reset_envs:' + i)\n"
        "    obs, info = env.reset(seed=0)\n"
        "    obs, r, term, trunc, info = env.step(env.action_space.sample())\n"
        "    assert {'reset_success', 'reset_reward', 'irrecoverable'} <= set(info), info\n"
        "from torchrl.envs import GymEnv\n"
        "td = GymEnv('torchrl_reset_envs:' + ids[0]).rollout(3)\n"
        "print('ok', len(ids), tuple(td['next', 'observation'].shape))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    # the first id is ball-in-cup (catch), the paper's first task: 8 observation entries (tasks.md)
    assert out.stdout.strip().splitlines()[-1] == "ok 6 (3, 8)"


def test_ids_are_namespaced():
    assert task_spec("cliff_cheetah").gym_id == "torchrl_reset/CliffCheetah-v0"
    assert task_spec("torchrl_reset/BallInCupThrow-v0").name == "ball_in_cup_throw"
    assert all(TASKS[name].gym_id in gymnasium.registry for name in ALL_TASKS)


# ------------------------------------------------------------------------------- start states, seeding
@pytest.mark.parametrize("task", ALL_TASKS)
def test_every_start_state_passes_reset_success(task):
    env = make_gym_env(task)
    for seed in range(25):
        _, info = env.reset(seed=seed)
        assert info["reset_success"] and not info["irrecoverable"], (seed, info)


@pytest.mark.parametrize("task", ALL_TASKS)
def test_same_seed_and_actions_give_the_same_trajectory(task):
    actions = random_actions(make_gym_env(task), 60, seed=1)

    def trajectory(seed):
        env = make_gym_env(task)
        obs, _ = env.reset(seed=seed)
        return np.stack([obs] + [env.step(a)[0] for a in actions])

    first, second = trajectory(3), trajectory(3)
    np.testing.assert_array_equal(first, second)
    if not task.startswith("peg"):  # the peg tasks start without noise
        assert not np.array_equal(first[0], trajectory(4)[0])


@pytest.mark.parametrize("task", ALL_TASKS)
def test_simulator_state_restores_the_exact_trajectory(task):
    env = make_env(task, seed=0)
    td = env.reset()
    for _ in range(15):
        td = env.rand_step(td)["next"].exclude("reward")
    state = env.get_simulator_state()  # reached through the TransformedEnv and GymWrapper
    actions = torch.as_tensor(random_actions(env, 20, seed=2), dtype=torch.float32)

    def replay():
        out = []
        t = td.clone()
        for a in actions:
            t = env.step(t.set("action", a))["next"].exclude("reward")
            out.append(t["observation"])
        return torch.stack(out)

    first = replay()
    env.reset()  # move somewhere else (and reseed nothing), then restore
    env.set_simulator_state(state)
    torch.testing.assert_close(replay(), first, rtol=0, atol=0)


# ------------------------------------------------------------------------------- rewards over random play
@pytest.mark.parametrize("task", ALL_TASKS)
def test_rewards_stay_in_unit_interval_and_finite_over_10k_random_steps(task):
    env = make_gym_env(task)
    env.reset(seed=0)
    rewards, reset_rewards = [], []
    for action in random_actions(env, 10_000, seed=0):
        obs, reward, terminated, truncated, info = env.step(action)
        assert np.all(np.isfinite(obs)) and not terminated and not truncated
        rewards.append(reward)
        reset_rewards.append(info["reset_reward"])
    rewards, reset_rewards = np.array(rewards), np.array(reset_rewards)
    for values in (rewards, reset_rewards):
        assert np.all(np.isfinite(values)) and values.min() >= 0.0 and values.max() <= 1.0


def test_tolerance_matches_the_hand_computed_values():
    assert tolerance(10.0, 9, 11, 7) == 1.0 and tolerance(9.0, 9, 11, 7) == 1.0
    # distance 7 = margin: 1 - tanh(atanh(sqrt(0.95)))^2 = 1 - 0.95
    assert tolerance(2.0, 9, 11, 7) == pytest.approx(0.05, abs=1e-12)
    # distance 3.5 = margin / 2: 1 - tanh(2.17827 / 2)^2 = 1 - 0.79662^2 = 0.36549
    assert tolerance(5.5, 9, 11, 7) == pytest.approx(0.36549, abs=1e-4)
    assert tolerance(14.5, 9, 11, 7) == pytest.approx(0.36549, abs=1e-4)  # symmetric on the other side
    with pytest.raises(ValueError):
        tolerance(0.0, 0, 1, 0.0)


# ------------------------------------------------------------------------------- cliff tasks
@pytest.mark.parametrize("env_cls, x_start, edge, z_limit", [(CliffCheetahEnv, 14.5, 14.0, -1.0), (CliffWalkerEnv, 6.5, 6.0, 0.0)])
@pytest.mark.parametrize("pattern", ["random", "push_forward", "bang_bang"])
def test_started_past_the_edge_the_robot_falls_and_irrecoverable_stays_set(env_cls, x_start, edge, z_limit, pattern):
    env = env_cls()
    env.reset(seed=0)
    qpos = env.data.qpos.copy()
    qpos[0] = x_start  # past the edge, at the normal standing height above the (missing) floor
    env.set_state(qpos, np.zeros(env.model.nv))
    rng = np.random.default_rng(5)
    fell_at = None
    for t in range(500):  # one forward episode, H_f = 500
        if pattern == "random":
            action = rng.uniform(-1, 1, 6)
        elif pattern == "push_forward":
            action = np.ones(6)
        else:  # full torque, switching sign every ~10 steps: the walker tumbles in the ditch
            action = -np.ones(6) * np.sign(np.sin(0.3 * t) + 1e-9)
        obs, _, _, _, info = env.step(action)
        x, z = obs[0], obs[1]
        in_ditch = x > edge and z < z_limit  # tasks.md's irrecoverable condition, from the observation
        if fell_at is None and in_ditch:
            fell_at = t
        if fell_at is not None:
            assert x > edge, f"back over the floor at step {t}: x={x:.2f}, z={z:.2f}"
            assert info["irrecoverable"]  # latched
            if pattern != "bang_bang" or env_cls is CliffCheetahEnv:
                assert in_ditch, f"left the irrecoverable region at step {t}: x={x:.2f}, z={z:.2f}"
    assert fell_at is not None and fell_at < 100
    for _ in range(100):  # let it come to rest
        obs, *_, info = env.step(np.zeros(6))
    assert obs[0] > edge and obs[1] < z_limit - 0.5 and info["irrecoverable"]  # ends well below the height
    _, info = env.reset(seed=0)  # only a manual reset clears it
    assert not info["irrecoverable"] and not env.irrecoverable


@pytest.mark.parametrize("env_cls, edge, far", [(CliffCheetahEnv, 14.0, 16.0), (CliffWalkerEnv, 6.0, 8.0)])
def test_cliff_terrain_is_the_releases(env_cls, edge, far):
    """docs/release-audit.md: floor top at z = 0.05 over [-2, edge], the ditch's floor top at -1.9 over
    [edge, far], the cliff face a 0.2 m block on x = edge from z = -2 to 0, walls on x = -2 and x = far."""
    model = env_cls().model

    def extent(name):
        g = model.geom(name)
        return g.pos[0] - g.size[0], g.pos[0] + g.size[0], g.pos[2] - g.size[2], g.pos[2] + g.size[2]

    np.testing.assert_allclose(extent("floor"), (-2.0, edge, -0.15, 0.05), atol=1e-12)
    np.testing.assert_allclose(extent("ditch_floor"), (edge, far, -2.1, -1.9), atol=1e-12)
    np.testing.assert_allclose(extent("cliff_face"), (edge - 0.1, edge + 0.1, -2.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(extent("back_wall"), (-2.1, -1.9, 0.0, 2.0), atol=1e-12)
    np.testing.assert_allclose(extent("far_wall"), (far - 0.1, far + 0.1, -2.0, 2.0), atol=1e-12)


def test_walker_feet_frictions_are_the_releases():
    model = CliffWalkerEnv().model
    assert model.geom("foot_geom").friction[0] == pytest.approx(0.9)  # right foot
    assert model.geom("foot_left_geom").friction[0] == pytest.approx(1.9)


@pytest.mark.parametrize("env_cls", [CliffCheetahEnv, CliffWalkerEnv])
def test_cliff_forward_velocity_is_qvel_after_the_step(env_cls):
    env = env_cls()
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(20):
        _, _, _, _, info = env.step(rng.uniform(-1, 1, 6))
        assert info["reward_velocity"] == float(np.clip(env.data.qvel[0], -10, 10))


def test_cliff_rewards_by_hand():
    cheetah = CliffCheetahEnv()
    cheetah.reset(seed=0)
    qpos = cheetah.model.qpos0.copy()
    qpos[0], qpos[2] = 0.3, 0.2  # x = 0.3, pitch = 0.2
    cheetah.set_state(qpos, np.zeros(9))
    info = cheetah.current_info()
    # 0.8 [0.3 < 0.5] + 0.1 (1 - 0.06) + 0.1 Cond(0.2; -0.05, 0.05, 0.1); Cond: d = 0.15, 1 - tanh(1.5 W)^2
    expected = 0.8 + 0.094 + 0.1 * (1 - math.tanh(1.5 * W) ** 2)
    assert info["reset_reward"] == pytest.approx(expected, abs=1e-9) and expected == pytest.approx(0.89458, abs=1e-5)
    assert not info["reset_success"]  # |x| = 0.3 >= 0.1

    walker = CliffWalkerEnv()
    walker.reset(seed=0)
    qpos = walker.model.qpos0.copy()
    qpos[0], qpos[1], qpos[2] = 1.0, 1.3, 0.0  # x = 1, torso height 1.3, upright
    walker.set_state(qpos, np.zeros(9))
    info = walker.current_info()
    # stand = clip(0.325 + 0.25 + 0.5) = 1, upright = 1; 0.8 [1 < 0.5] + 0.2 (1 - 0.2) = 0.16
    assert info["reset_reward"] == pytest.approx(0.16, abs=1e-9)
    assert not info["reset_success"]  # |x| = 1 >= 0.5
    # a forward step with velocity v: reward = clip(v / 2) * stand * upright; start at 1 m/s, standing
    qvel = np.zeros(9)
    qvel[0] = 1.0
    walker.set_state(qpos, qvel)
    _, reward, _, _, info = walker.step(np.zeros(6))
    v = info["reward_velocity"]
    assert 0.8 < v < 1.05  # 1 m/s, slowed by gravity and contacts over 10 ms
    assert reward == pytest.approx(v / 2 * info["reward_stand"] * info["reward_upright"], rel=1e-9)


# ------------------------------------------------------------------------------- peg insertion
def _pd(env, target, steps, kp=20.0, kd=2.0):
    info = None
    for _ in range(steps):
        obs = env._observation()
        q, v = obs[:7], obs[7:]
        *_, info = env.step(np.clip(kp * (target - q) - kd * v, -2.0, 2.0))
    return info


def _ik(env, q, peg_target, iterations=100):
    """Joint positions putting the peg's ends at ``peg_target`` (damped least squares on the two sites)."""
    model, data = env.model, mujoco.MjData(env.model)
    bottom, top = model.site("bottom").id, model.site("top").id
    qadr = [model.joint(n).qposadr[0] for n in ("r_shoulder_pan_joint", "r_shoulder_lift_joint", "r_upper_arm_roll_joint",
                                                "r_elbow_flex_joint", "r_forearm_roll_joint", "r_wrist_flex_joint", "r_wrist_roll_joint")]
    jb, jt = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    q = q.copy()
    for _ in range(iterations):
        data.qpos[qadr] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        error = peg_target - np.concatenate([data.site_xpos[bottom], data.site_xpos[top]])
        mujoco.mj_jacSite(model, data, jb, None, bottom)
        mujoco.mj_jacSite(model, data, jt, None, top)
        jac = np.vstack([jb, jt])[:, qadr]
        q = q + jac.T @ np.linalg.solve(jac @ jac.T + 1e-4 * np.eye(6), error)
    assert np.linalg.norm(error) < 1e-6
    return q


def test_peg_start_states_lie_in_each_others_goal_regions():
    insert, remove = PegInsertionEnv("insert"), PegInsertionEnv("remove")
    insert.reset()
    remove.reset()
    # forward kinematics of the released start joints reproduce the released peg positions
    np.testing.assert_allclose(insert.peg(), PEG_START, atol=2e-3)
    np.testing.assert_allclose(remove.peg(), PEG_GOAL, atol=1e-3)
    # the insert start is in the remove task's goal region (d_start < 0.2) and not in the hole...
    assert insert.d_start() < 0.2 and not insert.in_hole()
    # ... and the remove start is in the hole, the insert task's goal, far from the start
    assert remove.in_hole() and remove.d_start() > 0.2


def test_scripted_joint_space_moves_flip_the_two_checks():
    # remove task: from the hole to the insert start
    env = PegInsertionEnv("remove")
    _, info = env.reset()
    assert info["reset_success"] and env.d_start() > 0.2
    info = _pd(env, INSERT_START_QPOS, 60)
    assert not info["reset_success"] and not env.in_hole() and env.d_start() < 0.2
    # insert task: from above the table down into the hole, through joint targets over the hole
    env = PegInsertionEnv("insert")
    _, info = env.reset()
    assert info["reset_success"] and not env.in_hole()
    q = REMOVE_START_QPOS
    waypoints = []
    for height in (0.25, 0.2, 0.15, 0.1, 0.05, 0.0):
        q = _ik(env, q, PEG_GOAL + np.array([0, 0, height, 0, 0, height]))
        waypoints.append(q)
    _pd(env, waypoints[0], 40)
    for q in waypoints[1:]:
        info = _pd(env, q, 10)
    info = _pd(env, waypoints[-1], 20)
    assert env.in_hole() and not info["reset_success"] and env.d_start() > 0.2


def test_peg_rewards_by_hand():
    remove_start = PegInsertionEnv("insert")
    remove_start.reset()
    remove_start.set_state(REMOVE_START_QPOS, np.zeros(7))
    # in the hole, zero action: insert = 0.5 * 1 + 0.25 * 1 + 0.25 * (1 - d_goal ~ 0) = 1
    assert remove_start.insert_reward(np.zeros(7)) == pytest.approx(1.0, abs=1e-3)
    env = PegInsertionEnv("insert")
    env.reset()
    # at the insert start with a = (1, ..., 1): control = 1 - 0.1 * 7 = 0.3; remove = 0.8 (1 - d_start ~ 0) + 0.2 * 0.3
    info = env.current_info(np.ones(7))
    assert info["reset_reward"] == pytest.approx(0.86, abs=2e-3)
    # a = 2 everywhere (outside the action box, as noise can make it): |a|^2 = 28, control clipped to 0
    assert env.current_info(np.full(7, 2.0))["reset_reward"] == pytest.approx(0.8, abs=2e-3)
    # a = 0.5 everywhere: |a|^2 = 1.75, control = 0.825; remove = 0.8 + 0.2 * 0.825 = 0.965
    assert env.current_info(np.full(7, 0.5))["reset_reward"] == pytest.approx(0.965, abs=2e-3)


def _capsule_volume(radius, length):
    return math.pi * radius**2 * length + 4.0 / 3.0 * math.pi * radius**3


def _sphere_volume(radius):
    return 4.0 / 3.0 * math.pi * radius**3


@pytest.mark.parametrize("forward", ["insert", "remove"])
def test_peg_model_has_the_release_physics(forward):
    """docs/method.md section 9 and docs/release-audit.md: the release's peg-insertion model, read back."""
    model = PegInsertionEnv(forward).model
    assert model.opt.timestep == 0.01
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    np.testing.assert_array_equal(model.opt.gravity, 0.0)
    assert model.opt.iterations == 20
    # shoulder pan, shoulder lift, upper-arm roll, elbow flex, forearm roll, wrist flex, wrist roll
    np.testing.assert_allclose(model.dof_damping, [10.0, 10.0, 0.1, 1.0, 0.1, 0.1, 0.1])
    np.testing.assert_allclose(model.dof_armature, 0.04)
    np.testing.assert_allclose(model.actuator_ctrlrange, [[-2.0, 2.0]] * 7)
    np.testing.assert_allclose(model.actuator_gear[:, 0], 1.0)
    # the peg: a cylinder r = 0.028, 0.3 m long, at 2000 kg/m^3 plus a sphere of r = 0.028 at each end
    # at 1000: 2000 pi 0.028^2 0.3 + 2000 (4/3) pi 0.028^3 = 1.4778 + 0.1839 = 1.6617 kg
    peg = 2000.0 * math.pi * 0.028**2 * 0.3 + 2 * 1000.0 * _sphere_volume(0.028)
    assert model.body_mass[model.body("tool").id] == pytest.approx(peg, rel=1e-6)
    assert peg == pytest.approx(1.66, abs=0.005)
    # the shoulder-pan link: a capsule r = 0.1 from z = -0.4 to 0.2 and spheres of 0.05, 0.05, 0.03, 0.03
    pan = 1000.0 * (_capsule_volume(0.1, 0.6) + 2 * _sphere_volume(0.05) + 2 * _sphere_volume(0.03))
    assert model.body_mass[model.body("r_shoulder_pan_link").id] == pytest.approx(pan, rel=1e-6)
    assert pan == pytest.approx(24.31, abs=0.01)
    # the whole arm and peg: about 47.8 kg (docs/method.md section 9)
    assert model.body_mass.sum() == pytest.approx(47.8, abs=0.1)
    # the arm touches the table (contype 0 / conaffinity 1 against 1 / 1), not itself; the peg touches the table
    table = model.geom("table1").id
    arm = model.geom_bodyid == model.body("r_upper_arm_roll_link").id
    assert (model.geom_contype[arm] == 0).all() and (model.geom_conaffinity[arm] == 1).all()
    assert model.geom_contype[table] == 1 and model.geom_conaffinity[table] == 1
    assert model.geom_contype[model.geom("peg").id] == 2


def test_peg_remove_start_overlaps_the_hole_floor_so_the_peg_is_pushed_out():
    """The release's numbers put the peg's bottom sphere (r = 0.028) with its centre on the hole's floor
    (top at z = -0.5): 2.8 cm inside it. Without torque the contact pushes the peg up, out of the hole."""
    env = PegInsertionEnv("remove")
    env.reset()
    data, model = env.data, env.model
    floor, sphere = model.geom("hole_floor").id, model.geom("peg_bottom").id
    depth = [data.contact[i].dist for i in range(data.ncon) if {data.contact[i].geom1, data.contact[i].geom2} == {floor, sphere}]
    assert depth and min(depth) == pytest.approx(-0.028, abs=1e-3)
    assert env.in_hole()
    for _ in range(8):
        env.step(np.zeros(7))
    assert not env.in_hole()


def test_peg_actions_reach_the_motors_unscaled_and_clamped_at_the_control_range():
    env = PegInsertionEnv("insert")
    env.reset()
    np.testing.assert_array_equal(env.action_space.low, -1.0)
    np.testing.assert_array_equal(env.action_space.high, 1.0)
    # outside the action box [-1, 1] (a noisy action) but inside the motors' range [-2, 2]: sent as it is
    action = np.array([0.3, -0.7, 1.0, -1.0, 0.0, 0.25, 1.7])
    env.step(action)
    np.testing.assert_allclose(env.data.ctrl, action, atol=1e-7)
    # gear 1: the torque on each joint is the control itself (N m)
    np.testing.assert_allclose(env.data.actuator_force, action, atol=1e-7)
    # beyond the motors' range: clamped at +-2, as MuJoCo clamps a limited motor
    env.step(np.array([2.5, -3.0, 0.0, 0.0, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(env.data.actuator_force[:2], [2.0, -2.0], atol=1e-7)
    # the control term sees the action as sent: |a|^2 = 1.5^2 = 2.25, control = 1 - 0.225 = 0.775;
    # remove = 0.8 (1 - d_start ~ 0) + 0.2 * 0.775 = 0.955
    env.reset()
    assert env.current_info(np.array([1.5, 0, 0, 0, 0, 0, 0]))["reset_reward"] == pytest.approx(0.955, abs=2e-3)
# ------------------------------------------------------------------------------- ball in cup
def test_ball_placed_in_the_cup_gives_catch_reward_one():
    env = BallInCupEnv("catch")
    env.reset(seed=0)
    _, reward, *_ = env.step(np.zeros(2))
    assert reward == 0.0  # hanging below the cup
    # cup at the springs' rest (z = 0.6), ball at the target site: 0.6 - 0.05 = 0.55, its slide origin is 0.2
    env.set_state(np.array([0.0, 0.0, 0.0, 0.35]), np.zeros(4))
    _, reward, *_ = env.step(np.zeros(2))
    assert reward == 1.0


def test_settled_hanging_ball_passes_the_catch_check_and_a_swinging_one_fails_at_every_phase():
    env = BallInCupEnv("catch")
    _, info = env.reset(seed=0)
    assert info["reset_success"]
    for _ in range(50):  # 1 s without action
        *_, info = env.step(np.zeros(2))
        assert info["reset_success"]
    # the ball swung out 30 degrees below the cup's string anchor, released from rest
    anchor = env.data.site_xpos[env.model.site("cup").id]
    angle = math.radians(30)
    ball_x, ball_z = anchor[0] + 0.3 * math.sin(angle), anchor[2] - 0.3 * math.cos(angle)
    qpos = env.data.qpos.copy()
    qpos[2], qpos[3] = ball_x, ball_z - 0.2  # slide origin of the ball at (0, 0.2)
    env.set_state(qpos, np.zeros(4))
    # g L (1 - cos 30) = 9.81 * 0.3 * 0.134 = 0.394 J/kg
    assert env.swing_energy() == pytest.approx(0.394, abs=0.01)
    for _ in range(110):  # two pendulum periods (2 pi sqrt(0.3 / 9.81) = 1.1 s each)
        *_, info = env.step(np.zeros(2))
        assert not info["reset_success"]


def test_throw_start_and_distance_reward():
    env = BallInCupEnv("throw")
    _, info = env.reset(seed=0)
    assert info["reset_success"] and env.in_target()
    # ball 0.15 to the side of the target, at its height, cup at the springs' rest: reward 0.15 / 0.3
    # (cup and ball both fall 2 mm in the 20 ms step, so the distance stays 0.15)
    env.set_state(np.array([0.0, 0.0, 0.15, 0.35]), np.zeros(4))
    _, reward, *_, info = env.step(np.zeros(2))
    assert reward == pytest.approx(0.5, abs=0.01)
    assert not info["reset_success"]


def test_ball_in_cup_reset_reward_at_start():
    env = BallInCupEnv("catch")
    _, info = env.reset(seed=0)
    # 0.8 * 1 + 0.2 * (1 - shift / 0.3), |shift| <= 0.01
    assert 0.8 + 0.2 * (1 - 0.01 / 0.3) - 1e-3 <= info["reset_reward"] <= 1.0


# ------------------------------------------------------------------------------- with the collector
def test_dual_collector_runs_on_a_task_made_by_make_env():
    env = make_env("peg_insertion_insert", seed=0)
    zero = TensorDictModule(lambda obs: torch.zeros(*obs.shape[:-1], 7), in_keys=["observation"], out_keys=["action"])
    collector = DualCollector(env, zero, zero, max_forward_steps=5, max_reset_steps=10, min_reset_steps=1, total_frames=30)
    batches = list(collector)
    assert sum(b.numel() for b in batches) == 30
    # zero torque in zero gravity leaves the peg at the start: every reset episode succeeds after min_reset_steps
    assert collector.counters["manual_resets"] == 0 and collector.counters["successful_resets"] == 5


# ------------------------------------------------------------------------------- bad input, rendering
def test_unknown_task_gets_a_clear_error():
    with pytest.raises(ValueError, match="unknown task 'cliff_chetah'.*cliff_cheetah"):
        make_env("cliff_chetah")
    with pytest.raises(TypeError):
        make_env(3)
    with pytest.raises(gymnasium.error.Error, match="Nope"):
        gymnasium.make("torchrl_reset_envs:torchrl_reset/Nope-v0")
    with pytest.raises(ValueError, match="forward must be"):
        PegInsertionEnv("sideways")


@pytest.mark.parametrize("task", ["cliff_cheetah", "ball_in_cup_catch"])
def test_bad_actions_get_clear_errors(task):
    gym_env = make_gym_env(task)
    gym_env.reset(seed=0)
    n = gym_env.action_space.shape[0]
    with pytest.raises(ValueError, match=rf"action of shape \({n},\), got \({n + 1},\)"):
        gym_env.step(np.zeros(n + 1))
    with pytest.raises(ValueError, match="non-finite"):
        gym_env.step(np.full(n, np.nan))
    env = make_env(task, seed=0)
    td = env.reset()
    with pytest.raises(ValueError, match="action of shape"):
        env.step(td.clone().set("action", torch.zeros(2, n)))
    with pytest.raises(ValueError, match="non-finite"):
        env.step(td.clone().set("action", torch.full((n,), float("inf"))))
    env.rand_step(td)  # still usable


@pytest.mark.filterwarnings("ignore::UserWarning")  # GLFW's complaints when no display is available
def test_render_gives_frames_or_a_clear_error_and_the_env_keeps_working():
    env = make_gym_env("ball_in_cup_catch", render_mode="rgb_array", width=64, height=48)
    env.reset(seed=0)
    try:
        frame = env.render()
    except RenderingUnavailableError as err:
        assert "MUJOCO_GL" in str(err)
    else:
        assert frame.shape == (48, 64, 3) and frame.dtype == np.uint8 and frame.std() > 0
        for _ in range(10):  # the cup moves up: the picture changes
            env.step(np.array([0.0, 1.0]))
        assert np.abs(env.render().astype(int) - frame.astype(int)).sum() > 0
    env.step(np.zeros(2))
    env.close()
    with pytest.warns(UserWarning, match="render_mode"):  # no render_mode: gymnasium's convention
        assert make_gym_env("ball_in_cup_catch").render() is None


@pytest.mark.parametrize("task", ALL_TASKS)
def test_the_recipes_task_config_states_the_papers_horizon_and_threshold(task):
    """The recipe's ``task=<name>`` (built from the registry) carries tasks.md's H_f and p_thresh."""
    from torchrl_reset_recipes.training.hydra_config import compose

    horizon, p_thresh, _, _ = PAPER_NUMBERS[task]
    conf = compose([f"task={task}"]).task
    assert conf.name == task
    assert (conf.forward_horizon, conf.p_thresh) == (horizon, p_thresh)
