"""The training environment: a gymnasium Env over the lock-stepped simulated robot.

One step is one control cycle of the runtime's `Pipeline` running the SafeMove job, with the
actor's decision supplied from outside between the pipeline's two halves: `begin` (odometry,
world model, health, DWA count-budgeted, the spec's observation) gives the observation, the
agent's action goes to `finish` (the spec's action mapping, the shield, the limits stage), and
the base model executes the command (`LockstepEpisode`). So the policy learns on the pipeline it
will run in, shield included, and its observations are exactly the robot's.

Episodes: each reset draws a scenario from the list and a fresh episode seed from the env's
generator (seeded by `reset(seed=…)`), so a seeded env is reproducible. The world judges from
ground truth: success and collision terminate the episode, the scenario's time limit truncates
it. When odometry says the goal is reached but the world does not (odometry drift), the episode
is truncated as well: the job would stop there.

Reward (`RewardConfig`): progress toward the goal per metre of true distance, a per-second time
cost, a bonus on success, a penalty on collision (any: the crowd may be oblivious, and a
learnt policy should keep away from people even when a contact would not be its fault), and a
penalty each cycle the shield changed the actor's command, so the actor learns to propose what
the shield passes.

Each step's info also gives the DWA baseline's choice in the observation the step acted on
(`TEACHER_KEY`, in SB3's [-1, 1] action box): the replay buffer keeps it as TD3+BC's label.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from runtime.config.settings import LoadedConfig
from runtime.jobs.safemove import SafeMoveJob
from runtime.pipeline import Pipeline, Sensed
from runtime.policy.obs_spec import ObsSpec
from sim_stub.lockstep import LockstepEpisode
from sim_stub.train.replay import TEACHER_KEY
from sim_stub.train.reward import RewardConfig, corridor_yaw_error, step_reward
from sim_stub.world import World

F32 = np.float32


class SafeMoveEnv(gym.Env):
    """Scenarios × seeds of the lock-stepped robot; actions in the spec's output box."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, scenarios: list[str], spec: ObsSpec, loaded: LoadedConfig,
                 reward: RewardConfig | None = None, fps: float = 15.0, noise: bool = True,
                 crowd: str = "scenario", surround_people: bool = False) -> None:
        """crowd: as the scenario says, reactive, oblivious, or "mixed" (each episode draws
        reactive or oblivious); surround_people: the pipeline also sees every person around,
        exactly (sim_stub.surround_people: a what-if, no robot has that sensor)."""
        if not scenarios:
            raise ValueError("SafeMoveEnv needs at least one scenario")
        self.scenarios = list(scenarios)
        self.obs_spec = spec
        self.loaded = loaded
        self.reward_config = reward if reward is not None else RewardConfig()
        self.fps, self.noise, self.crowd = fps, noise, crowd
        self.surround_people = surround_people
        lo, hi = spec.bounds()
        self.observation_space = gym.spaces.Box(lo, hi, dtype=F32)
        a = spec.action
        self.action_space = gym.spaces.Box(np.array(a.output_low, dtype=F32),
                                           np.array(a.output_high, dtype=F32), dtype=F32)
        self._episode: LockstepEpisode | None = None
        self._job: SafeMoveJob | None = None
        self._pipeline: Pipeline | None = None
        self._sensed: Sensed | None = None
        self._distance = 0.0
        self._t = 0.0

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        rng = self.np_random
        scenario = self.scenarios[int(rng.integers(len(self.scenarios)))]
        episode_seed = int(rng.integers(2**31 - 1))
        crowd = self.crowd
        if crowd == "mixed":  # domain randomisation: people who see the robot, or do not
            crowd = ("reactive", "oblivious")[int(rng.integers(2))]
        self._episode = LockstepEpisode(scenario, episode_seed, self.loaded.config,
                                        self.loaded.calibration, self.fps, self.noise, crowd,
                                        surround_people=self.surround_people)
        self._job = SafeMoveJob(self._episode.goal_odom, self.loaded.config, None, None,
                                spec=self.obs_spec)
        self._pipeline = Pipeline(self._episode.config, self.loaded.calibration, self._job)
        self._distance = self._true_distance()
        self._t = 0.0
        obs, outcome = self._advance()
        if obs is None:
            raise RuntimeError(f"{scenario} seed {episode_seed}: the episode ended ({outcome})"
                               " before the first observation")
        return obs, {"scenario": scenario, "seed": episode_seed}

    def step(self, action: np.ndarray
             ) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if (self._episode is None or self._job is None or self._pipeline is None
                or self._sensed is None):
            raise RuntimeError("step() before reset(), or after the episode ended")
        teacher = self._dwa_choice().astype(F32)  # TD3+BC's label for this observation
        out = self._pipeline.finish(self._sensed, np.asarray(action, dtype=F32))
        changed = self._job.shield_changed
        self._episode.send(out.command)
        t_before = self._t
        obs, outcome = self._advance()
        distance = self._true_distance()
        prepared = None if self._sensed is None else self._sensed.prepared
        yaw = 0.0 if prepared is None else corridor_yaw_error(prepared.context.dwa.best_path)
        reward = step_reward(self.reward_config, progress_m=self._distance - distance,
                             dt_s=self._t - t_before, outcome=outcome, shield_changed=changed,
                             yaw_error_rad=yaw)
        self._distance = distance
        terminated = outcome in ("success", "collision")
        truncated = not terminated and obs is None
        if obs is None:  # SB3 keeps the last observation of an ended episode: give one
            obs = np.zeros(self.observation_space.shape, dtype=F32)
        world = self._episode.world
        info = {"outcome": outcome, "shield_changed": changed,
                "at_fault": bool(world.outcome.at_fault), "time_s": self._t,
                TEACHER_KEY: teacher}
        return obs, float(reward), terminated, truncated, info

    @property
    def world(self) -> World | None:
        """The current episode's world (ground truth), for callbacks and analysis."""
        return None if self._episode is None else self._episode.world

    def _advance(self) -> tuple[np.ndarray | None, str]:
        """To the next cycle that needs a decision: (its observation, "running"), or (None,
        the outcome) when the episode ended. Cycles without one (no world yet, holding) run
        the pipeline with no decision: the robot stands still."""
        episode, job, pipeline = self._episode, self._job, self._pipeline
        assert episode is not None and job is not None and pipeline is not None
        self._sensed = None
        while (inp := episode.cycle()) is not None:
            self._t = inp.t
            sensed = pipeline.begin(inp)
            if sensed.observation is not None:
                self._sensed = sensed
                return sensed.observation.astype(F32), "running"
            if job.reached:
                return None, "odometry_reached"
            episode.send(pipeline.finish(sensed).command)
        self._t = episode.world.outcome.t
        return None, episode.world.outcome.status

    def expert_action(self) -> np.ndarray:
        """The DWA baseline's choice for the current observation (its best sample) as an action
        of the spec's box: the demonstrations and behaviour cloning of the training recipe.
        The DWA stage runs every planning cycle whatever the spec, so this exists for `drl`
        too; a reversing DWA sample clips to the box's standstill."""
        unit = self._dwa_choice()
        a = self.obs_spec.action
        lo, hi = np.array(a.output_low), np.array(a.output_high)
        return (lo + (unit + 1.0) * 0.5 * (hi - lo)).astype(F32)

    def _dwa_choice(self) -> np.ndarray:
        """DWA's best (v, ω) for the current observation in the [-1, 1]² action space, computed
        as the `dwa` block's first two features are, so the step's teacher label equals them."""
        if self._sensed is None or self._sensed.prepared is None:
            raise RuntimeError("DWA's choice asked for without a current observation")
        v, omega = self._sensed.prepared.context.dwa.best
        return np.array(self.obs_spec.action.normalise(float(v), float(omega)))

    def _true_distance(self) -> float:
        assert self._episode is not None
        w = self._episode.world
        return float(np.hypot(w.goal[0] - w.robot.x, w.goal[1] - w.robot.y))
