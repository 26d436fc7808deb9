"""Training progress as a stable-baselines3 callback (SB3's own ProgressBarCallback needs rich,
which the train extra does not bring): the `Progress` bar or plain lines over env steps."""

from __future__ import annotations

from stable_baselines3.common.callbacks import BaseCallback

from sim_stub.progress import Progress


class ProgressCallback(BaseCallback):
    """Advances `progress` by the transitions collected since the last call (N per VecEnv
    step), with the episodes ended so far (VecMonitor marks an ended one's info)."""

    def __init__(self, progress: Progress) -> None:
        super().__init__()
        self.progress = progress
        self.episodes = 0

    def _on_step(self) -> bool:
        self.episodes += sum("episode" in info for info in self.locals["infos"])
        self.progress.advance(self.num_timesteps - self.progress.done, episodes=self.episodes)
        return True
