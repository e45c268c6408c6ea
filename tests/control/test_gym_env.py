"""The Gymnasium environment vcfusion/Highway-v0 (vcfusion.gym) on the co-simulation loop."""

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from scenario_files import SCENARIOS

import vcfusion.gym  # noqa: F401  (registers the id)
from vcfusion.gym.env import DISCRETE_NAMES, KINEMATICS_FEATURES

SHORT = """
extends: {accident}
simulation: {{max_time_s: {max_time}}}
metrics: {{enabled: {metrics}}}
camera: {{width_px: 96, height_px: 64}}
fusion: {{detector: oracle}}
{more}
"""


def scenario_file(tmp_path, max_time: float = 3.0, more: str = "", name: str = "env.yaml", metrics: bool = False):
    path = tmp_path / name
    path.write_text(SHORT.format(accident=(SCENARIOS / "accident.yaml").as_posix(), max_time=max_time, more=more,
                                 metrics=str(metrics).lower()))
    return path


def make(path, **kwargs):
    return gymnasium.make("vcfusion/Highway-v0", scenario=str(path), **kwargs)


def episode(env, seed: int, actions) -> list:
    obs, _ = env.reset(seed=seed)
    seen = [obs]
    for a in actions:
        obs, _, terminated, truncated, _ = env.step(a)
        seen.append(obs)
        if terminated or truncated:
            break
    return seen


@pytest.mark.parametrize("action", ["continuous", "discrete"])
def test_check_env_passes_in_kinematics_mode(tmp_path, action):
    env = make(scenario_file(tmp_path), action=action)
    check_env(env.unwrapped, skip_render_check=True)
    env.close()


@pytest.mark.slow
@pytest.mark.parametrize("observation, camera", [("camera", "rgb"), ("camera", "rgbd"), ("fused", "rgb")])
def test_check_env_passes_in_camera_and_fused_modes(tmp_path, observation, camera):
    env = make(scenario_file(tmp_path), observation=observation, camera=camera)
    check_env(env.unwrapped)
    obs, _ = env.reset(seed=3)
    image = obs["rgb"] if isinstance(obs, dict) and "rgb" in obs else obs
    if observation == "camera":
        assert image.shape[:2] == (64, 96) and image.std() > 0  # a rendered road, not a blank image
    else:  # the overlay's boxes sit on rows of twins that are present
        boxes, rows = obs["boxes"], obs["kinematics"][1:]
        assert (boxes[:, 0] <= rows[:, 0]).all()
        assert boxes[:, 0].sum() >= 1 and (boxes[boxes[:, 0] == 1, 3] > boxes[boxes[:, 0] == 1, 1]).all()
    env.close()


def test_reset_with_a_seed_repeats_the_episode_byte_for_byte(tmp_path):
    env = make(scenario_file(tmp_path, 2.0))
    actions = [np.array([np.sin(k / 3.0), 0.0], np.float32) for k in range(25)]
    first, second = episode(env, 11, actions), episode(env, 11, actions)
    other = episode(env, 12, actions)
    env.close()
    assert len(first) == len(second) > 10
    assert all(a.tobytes() == b.tobytes() for a, b in zip(first, second))
    assert any(a.tobytes() != b.tobytes() for a, b in zip(first, other))


def test_the_kinematics_rows_are_the_nearest_received_twins_with_their_probabilities(tmp_path):
    env = make(scenario_file(tmp_path), vehicles=4)
    obs, info = env.reset(seed=4)
    assert obs.shape == (5, len(KINEMATICS_FEATURES)) and obs.dtype == np.float32
    ego, twins = obs[0], obs[1:]
    assert tuple(ego[[0, 1, 2, 4]]) == (1.0, 0.0, 0.0, 2.0) and ego[3] == pytest.approx(19.0)
    present = twins[twins[:, 0] == 1]
    # in range (150 m) at the start: the three changers; the fourth row is empty
    assert len(present) == 3 and (twins[3] == 0).all()
    assert (np.diff(np.abs(present[:, 1])) >= 0).all()  # nearest first
    assert ((present[:, 5] >= 0) & (present[:, 5] <= 1)).all() and present[:, 5].max() > 0
    # a neighbour in lane 0 is two lane widths to the ego's right
    assert present[present[:, 4] == 0, 2] == pytest.approx(-7.0, abs=0.2)
    env.close()


def test_rewards_info_and_the_end_of_an_episode(tmp_path):
    env = make(scenario_file(tmp_path, 30.0), action="discrete")
    env.reset(seed=1)
    _, reward, terminated, truncated, info = env.step(DISCRETE_NAMES.index("idle"))
    assert not (terminated or truncated) and info["end_reason"] is None
    assert info["metrics"]["progress_m"] == pytest.approx(1.9, abs=0.05)  # 19 m/s for 0.1 s
    assert info["terms"]["progress"] == pytest.approx(1.0, abs=0.03) and info["metrics"]["fuel_g"] > 0
    terms = info["terms"]  # the default weights (scenario.RewardConfig)
    assert reward == pytest.approx(terms["progress"] - terms["ttc"] - 0.5 * terms["drac"] - 0.05 * terms["jerk"]
                                   - terms["fuel"] - 100.0 * terms["collision"], abs=1e-12)
    _, _, _, _, info = env.step(DISCRETE_NAMES.index("slower"))
    assert info["metrics"]["jerk_mps3"] == pytest.approx(-30.0)  # 0 -> -3 m/s^2 within one tick
    steps, total = 2, 0.0
    while True:
        _, reward, terminated, truncated, info = env.step(DISCRETE_NAMES.index("idle"))
        steps, total = steps + 1, total + reward
        if terminated or truncated:
            break
    assert terminated and not truncated and info["end_reason"] == "trip_complete"
    with pytest.raises(RuntimeError, match="episode has ended"):
        env.step(0)
    env.close()


def test_a_collision_ends_the_episode_with_its_penalty(tmp_path):
    # full throttle into the car ahead in the ego's lane (it departs 180-230 m ahead at 17 m/s)
    env = make(scenario_file(tmp_path, 40.0, "ego: {trip_distance_m: 600.0}"))
    env.reset(seed=2)
    for _ in range(400):
        _, reward, terminated, truncated, info = env.step(np.array([1.0, 0.0], np.float32))
        if terminated or truncated:
            break
    assert terminated and info["end_reason"] == "collision" and info["metrics"]["collided"]
    assert reward < -90.0
    env.close()


def test_a_time_out_truncates(tmp_path):
    env = make(scenario_file(tmp_path, 1.0))
    env.reset(seed=1)
    for _ in range(20):
        _, _, terminated, truncated, info = env.step(np.zeros(2, np.float32))
        if terminated or truncated:
            break
    assert truncated and not terminated and info["end_reason"] == "max_time"
    env.close()


def test_an_async_vector_env_of_two_processes_steps_and_matches_single_runs(tmp_path):
    path = scenario_file(tmp_path, 2.0)
    vec = gymnasium.vector.AsyncVectorEnv([lambda: make(path), lambda: make(path)])
    try:
        obs, _ = vec.reset(seed=[5, 6])
        for _ in range(5):
            obs, rewards, terminated, truncated, _ = vec.step(np.zeros((2, 2), np.float32))
        assert obs.shape == (2, 9, 6) and np.isfinite(rewards).all() and not terminated.any()
    finally:
        vec.close()
    single = make(path)
    expected = episode(single, 5, [np.zeros(2, np.float32)] * 5)[-1]
    single.close()
    assert obs[0].tobytes() == expected.tobytes() and obs[1].tobytes() != expected.tobytes()


def test_bad_arguments_are_refused_with_what_was_expected(tmp_path):
    path = scenario_file(tmp_path)
    for kwargs, message in [({"observation": "lidar"}, "observation: expected one of"),
                            ({"action": "both"}, "action: expected"), ({"vehicles": 0}, "vehicles: expected"),
                            ({"render_mode": "rgb_array"}, "render_mode 'rgb_array' shows the ego camera")]:
        with pytest.raises(ValueError, match=message):
            make(path, **kwargs)


def test_the_scenario_sets_the_reward_weights(tmp_path):
    weights = "reward: {progress: 0.0, ttc: 0.0, drac: 0.0, jerk: 0.0, fuel: 10.0, collision: 0.0}"
    env = make(scenario_file(tmp_path, more=weights))
    env.reset(seed=1)
    _, reward, _, _, info = env.step(np.array([0.5, 0.0], np.float32))
    assert info["metrics"]["fuel_g"] > 0 and reward == pytest.approx(-10.0 * info["metrics"]["fuel_g"])
    env.close()


def test_with_summary_the_last_step_carries_the_runs_summary_and_metrics(tmp_path):
    path = scenario_file(tmp_path, 30.0, "ego: {trip_distance_m: 600.0}", metrics=True)
    env = make(path, summary=True)
    env.reset(seed=2)
    while True:  # full throttle into the car ahead: the run ends at the collision
        _, _, terminated, truncated, info = env.step(np.array([1.0, 0.0], np.float32))
        if terminated or truncated:
            break
    run = info["run_summary"]
    assert info["end_reason"] == run["end_reason"] == "collision" and run["seed"] == 2
    assert run["metrics"]["ego"]["collisions"] == 1 and run["collisions"] == 1
    assert run["simulated_s"] == pytest.approx(info["time"], abs=0.11)
    env.close()
