"""Each run's last K episodes, a ring: the one episode replay of ferl (DRQN's, ``ferl.actors.drqn``,
and the online trainer's predictors', ``ferl.trainers.online_episodes``).

A replay is a dict of tensors (R, K, …), one per field of an episode (states or observation ids,
actions, rewards, lengths, …), so that checkpoints keep it as plain tensors. Its owner counts the
episodes it has stored; episode c (0-based) goes to slot c mod K, over the oldest. Draws are
uniform with replacement over the episodes stored so far, every run's at once from one generator,
each run indexing its own episodes (runs are a batch dimension: none reads another's).
"""

import torch


def new_replay(episode: dict[str, torch.Tensor], capacity: int) -> dict[str, torch.Tensor]:
    """An empty replay of ``capacity`` episodes per run, shaped and typed as ``episode``'s fields
    (R, …): zeros (R, capacity, …)."""
    return {key: value.new_zeros(value.shape[0], capacity, *value.shape[1:]) for key, value in episode.items()}


def store_episode(replay: dict[str, torch.Tensor], count: int, episode: dict[str, torch.Tensor]) -> None:
    """Every run's episode number ``count`` (its fields (R, …)) into slot count mod K."""
    slot = count % next(iter(replay.values())).shape[1]
    for key, value in episode.items():
        replay[key][:, slot] = value


def draw_episodes(
    replay: dict[str, torch.Tensor], stored: int, n: int, generator: torch.Generator, device: torch.device | None = None
) -> torch.Tensor:
    """(R, n) slots drawn uniformly from the min(stored, K) that hold episodes, on ``device``
    (the generator's)."""
    runs, capacity = next(iter(replay.values())).shape[:2]
    return torch.randint(min(stored, capacity), (runs, n), generator=generator, device=device)


def stored_episodes(replay: dict[str, torch.Tensor], index: torch.Tensor) -> dict[str, torch.Tensor]:
    """Run r's episodes at slots index[r] (R, n): every field (R, n, …)."""
    runs = torch.arange(index.shape[0], device=index.device).unsqueeze(1)
    return {key: value[runs, index] for key, value in replay.items()}


def filled(replay: dict[str, torch.Tensor], stored: int) -> dict[str, torch.Tensor]:
    """What a checkpoint keeps of a replay that has stored ``stored`` episodes per run: its first
    min(stored, K) slots, copied (a view would save the whole storage). The empty slots of a
    large replay are most of it: MiniGrid's (10 runs × 1 000 episodes × 246 steps × 980 bits)
    took 9 GB in each checkpoint after 200 episodes."""
    capacity = next(iter(replay.values())).shape[1]
    return {key: value[:, : min(stored, capacity)].clone() for key, value in replay.items()}


def refilled(saved: dict[str, torch.Tensor], capacity: int) -> dict[str, torch.Tensor]:
    """The replay of ``capacity`` slots that ``filled`` saved, its empty slots zeros again."""
    return {
        key: torch.cat([value, value.new_zeros(value.shape[0], capacity - value.shape[1], *value.shape[2:])], 1)
        for key, value in saved.items()
    }
