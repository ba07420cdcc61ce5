"""Where a Gymnasium environment keeps its observations (``ferl.envs.gymnasium_vector``): the episodic
phases store observations as ids into a table of vectors (``EpisodicEnvironment``), so each
encoding needs a table that every stored id stays valid in.

* **Distinct codes** (bits: ``onehot``, ``thresholds``, ``minigrid``): one row per distinct code,
  given in order of first sight. Where the encoding's number of codes is known, the table is sized
  to it (``table_rows``), so no run can outgrow it.
* **Rows per step** (``real``, ``StepRows``): real values are rarely seen twice, so every run's
  observation at step t of an episode gets a row of its own,

      id(r, k, t) = ((k mod E) (T_max + 1) + t) R + r,

  for run r of R, episode k, and E the episodes whose ids must stay valid: 1 (the episode being
  played) unless a phase keeps more (``keep_episodes``: the online trainer's replay keeps its last
  K episodes as ids, so E = K + 1). Episode k's rows are written over by episode k + E. The table
  has E (T_max + 1) R rows, whatever the run's length.
"""

import numpy as np
import torch

from ferl.config.params import ConfigError

TABLE_BYTES = 256 * 2**20  # the largest table of observations sized unasked (codes or rows per step)
UNKNOWN_ROWS = 4096  # max_observations: null where the count of codes is not known in advance


def table_rows(env_id: str, codes: int | None, bits: int, asked: int | None) -> int:
    """The rows of a table of distinct codes (module docstring): ``asked`` where it holds every code
    the encoding can give or that count is unknown or too large for a table; null: the count, or
    ``UNKNOWN_ROWS``. ConfigError naming env.max_observations where a run could outgrow it."""
    fits = codes is not None and codes * bits * 4 <= TABLE_BYTES
    if codes is None:
        return asked or UNKNOWN_ROWS
    size = f"{codes} rows of {bits} bits ({codes * bits * 4 / 2**20:.1f} MiB)"
    if asked is None and not fits:
        raise ConfigError(
            f"env.max_observations: the encoding of {env_id!r} can give {codes} distinct observations, "
            f"more than a table sized to them holds ({TABLE_BYTES // 2**20} MiB); use fewer thresholds (or env.bits_per_entry), "
            f"or set env.max_observations to the most a run meets (a run that meets more stops)"
        )
    if asked is not None and fits and asked < codes:
        raise ConfigError(
            f"env.max_observations={asked}: the encoding of {env_id!r} can give {codes} distinct "
            f"observations, so a run could outgrow the table; set it to null (sized to them: {size}) or ≥ {codes}"
        )
    return asked if asked is not None else codes


class StepRows:
    """The table of rows per step (module docstring) of ``n_runs`` runs, episodes of at most
    ``max_steps`` actions, observations of ``size`` values: ``table`` (E (T_max + 1) R, size)."""

    def __init__(self, n_runs: int, max_steps: int, size: int, device: torch.device):
        self.R, self.T, self.size, self.device = n_runs, max_steps, size, device
        self.episodes = 1
        self.table = torch.zeros(self.rows(1), size, device=device)
        self.placed = False  # whether a row was written: from then on the table's size is fixed
        self.runs = torch.arange(n_runs, device=device)  # run r's row within its step: r

    def rows(self, episodes: int) -> int:
        return episodes * (self.T + 1) * self.R

    def keep(self, episodes: int, key: str, env_id: str) -> None:
        """Ids stay valid for ``episodes`` episodes, the one being played included; ``key``, the
        setting that asks for them, is named where the table would exceed ``TABLE_BYTES``."""
        if episodes == self.episodes:
            return
        if self.placed:
            raise RuntimeError("keep_episodes: the table's size is fixed once an observation is in it")
        size = self.rows(episodes) * self.size * 4
        if size > TABLE_BYTES:
            raise ConfigError(
                f"{key}: env.encoding=real keeps a row per step of the last {episodes} episodes of "
                f"{self.R} runs ({self.rows(episodes)} rows of {self.size} values, {size / 2**20:.0f} MiB), "
                f"more than {TABLE_BYTES // 2**20} MiB; keep fewer episodes, or use env.encoding=thresholds"
            )
        self.episodes = episodes
        self.table = torch.zeros(self.rows(episodes), self.size, device=self.device)

    def place(self, values: np.ndarray, episode: int, t: torch.Tensor, runs: torch.Tensor) -> torch.Tensor:
        """Writes the observations ``values`` (R, size) of the runs where ``runs`` (R,) bool is set,
        at step ``t`` (R,) of ``episode``, into their rows; returns every run's id there (R,)."""
        slot = episode % self.episodes
        ids = (slot * (self.T + 1) + t) * self.R + self.runs
        rows = torch.as_tensor(np.asarray(values, np.float32), device=self.device)
        self.table[ids[runs]] = rows[runs]
        self.placed = True
        return ids
