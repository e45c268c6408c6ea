"""Train PPO (stable-baselines3) on vcfusion/Highway-v0 in kinematics mode, then evaluate it
against the built-in driver model on held-out seeds with the project's metrics.

Needs the `rl` extra (pip install -e '.[rl]'). Training draws its episodes' seeds from
[0, TRAIN_SEEDS); evaluation uses seeds from EVAL_SEED0 on, which training never sees. Each arm of
an evaluation trip is one run of the same scenario and seed: the policy drives through the
environment (summary=True: the run's summary with its metrics block), the driver model through
`vcfusion run`'s own path (run.build_cosimulation).

    python examples/ppo_highway.py --timesteps 150000 --out renders/ppo   # the full training
    python examples/ppo_highway.py --timesteps 256 --eval-seeds 2         # a smoke run
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import gymnasium
import numpy as np
import pandas as pd

import vcfusion.gym  # noqa: F401  (registers vcfusion/Highway-v0)
from vcfusion.run import build_cosimulation
from vcfusion.scenario import load_scenario

TRAIN_SEEDS = 10_000
EVAL_SEED0 = 100_000
# the ego's figures of the run summary's metrics block (vcfusion.metrics), in the table's order
COLUMNS = ["travel_time_s", "min_ttc_s", "tet_s", "max_drac_mps2", "max_abs_jerk_mps3", "max_decel_mps2",
           "movestar_fuel_g_per_km", "collisions"]


class TrainSeeds(gymnasium.Wrapper):
    """Every episode a seed from [0, TRAIN_SEEDS), drawn from the wrapper's own generator."""

    def __init__(self, env, seed: int):
        super().__init__(env)
        self.rng = np.random.default_rng(seed)

    def reset(self, *, seed=None, options=None):
        return self.env.reset(seed=int(self.rng.integers(TRAIN_SEEDS)), options=options)


def make_env(scenario: Path, rank: int, summary: bool = False):
    def build():
        env = gymnasium.make("vcfusion/Highway-v0", scenario=str(scenario), observation="kinematics",
                             action="continuous", summary=summary)
        return TrainSeeds(env, rank) if not summary else env
    return build


def policy_trip(model, scenario: Path, seed: int) -> dict:
    env = make_env(scenario, 0, summary=True)()
    obs, _ = env.reset(seed=seed)
    while True:
        action, _ = model.predict(obs, deterministic=True)
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    env.close()
    run = info["run_summary"]
    return {"arm": "ppo", "seed": seed, "end_reason": run["end_reason"],
            **{c: run["metrics"]["ego"][c] for c in COLUMNS}}


def driver_trip(scenario: Path, seed: int) -> dict:
    run = build_cosimulation(load_scenario(scenario), seed).run().summary
    return {"arm": "driver model", "seed": seed, "end_reason": run["end_reason"],
            **{c: run["metrics"]["ego"][c] for c in COLUMNS}}


def main() -> int:
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    # one thread for the small policy network: more threads spin and take the environment
    # processes' cores on a 2-core machine
    torch.set_num_threads(1)

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", type=Path, default=Path("accident"),
                        help="scenario file or shipped scenario name")
    parser.add_argument("--timesteps", type=int, default=150_000, help="environment steps (V2C ticks) of training")
    parser.add_argument("--envs", type=int, default=2, help="environment processes (libsumo: one run per process)")
    parser.add_argument("--eval-seeds", type=int, default=20, help="held-out trips per arm")
    parser.add_argument("--seed", type=int, default=0, help="PPO's and the training seeds' generator")
    parser.add_argument("--out", type=Path, default=None, help="folder for the model and the evaluation table")
    args = parser.parse_args()

    fns = [make_env(args.scenario, args.seed * 1000 + k) for k in range(args.envs)]
    venv = SubprocVecEnv(fns) if args.envs > 1 else DummyVecEnv(fns)
    model = PPO("MlpPolicy", venv, n_steps=max(64, min(1024, args.timesteps // args.envs)), batch_size=64,
                seed=args.seed, verbose=0, device="cpu")
    started = time.perf_counter()
    model.learn(total_timesteps=args.timesteps)
    train_s = time.perf_counter() - started
    venv.close()
    print(f"trained {args.timesteps} steps in {train_s / 60:.1f} min ({args.timesteps / train_s:.0f} steps/s)")

    if args.eval_seeds <= 0:
        return 0
    rows = []
    for seed in range(EVAL_SEED0, EVAL_SEED0 + args.eval_seeds):  # held out: training never draws these
        rows += [policy_trip(model, args.scenario, seed), driver_trip(args.scenario, seed)]
    table = pd.DataFrame(rows)
    print(f"held-out seeds {EVAL_SEED0}-{EVAL_SEED0 + args.eval_seeds - 1}, means per arm:")
    print(table.groupby("arm")[COLUMNS].mean().round(3).to_string())
    print("end reasons:", table.groupby(["arm", "end_reason"]).size().to_dict())
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        model.save(args.out / "ppo_highway")
        table.to_csv(args.out / "evaluation.csv", index=False)
        print(f"written: {args.out / 'ppo_highway.zip'}, {args.out / 'evaluation.csv'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
