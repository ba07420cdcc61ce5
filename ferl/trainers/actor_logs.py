"""What the actor phase writes to TensorBoard (docs/records.md): run 0's weights, the moving
averages of its episodes and the hidden activations at its probe visits in the projector; and
what it keeps of every probe visit for ``probe.npz``."""

import numpy as np
import torch

from ferl.images import IMAGE_SIDE, matrix_image, tile, weight_images
from ferl.interfaces import ActorViews
from ferl.run.tensorboard import log_embedding, log_weights

EMBEDDED_PROBES = 2000  # run 0's last probe visits in the projector (docs/records.md)


def log_actor(job, step: int) -> None:
    """Run 0's weights: histograms, the state weights as a (state nodes × hidden) image and,
    where the observation is an unprocessed image, its rows as 28 × 28 tiles (the last two
    where the actor shows them, ``ActorViews``)."""
    log_weights(job.writer, "actor", job.actor, step)
    if not isinstance(job.actor, ActorViews):
        return
    W = job.actor.state_weights()
    job.writer.add_image("actor/W_sh_matrix", matrix_image(W[0]), step)
    if job.preprocessor is None and job.env.observation_size == IMAGE_SIDE**2:
        job.writer.add_image("actor/W_sh_images", tile(weight_images(W[:, : IMAGE_SIDE**2])[:, 0]), step)


def log_probes(job, probes: dict, records: dict, rates: list, n_episodes: int) -> None:
    """Run 0's actor hidden activations at its last probe visits in the projector, labelled
    with the episode's labels and outcome (Figs. 4.14–4.19)."""
    visits = np.flatnonzero(probes["run"] == 0)[-EMBEDDED_PROBES:] if "hidden" in probes else np.array([], int)
    if len(visits) == 0:
        return
    episode = probes["episode"][visits]
    log_embedding(
        job.writer,
        "actor/hidden_at_probe",
        probes["hidden"][visits],
        {
            **{key: probes[key][visits] for key in job.env.labels()},
            "episode": episode,
            "steps_to_goal": probes["steps_to_goal"][visits],
            **{key: records[key][0, episode].astype(int) for key in rates},
        },
        n_episodes,
    )


def log_episodes(writer, window: int, rates: list, records: dict, done: int, lr: float, beta: float) -> None:
    """Moving averages over the last ``window`` episodes (``final_window``; 200: Figs. 4.6–4.8,
    4.11–4.13), mean over runs, tagged ``actor/<name>_ma<window>``; ``rates``: the boolean outcomes."""
    recent = slice(max(0, done - window), done)
    for name in ("discounted_return", "steps", "terminal_reward", "td_abs_mean", *rates):
        writer.add_scalar(f"actor/{name}_ma{window}", float(records[name][:, recent].mean()), done)
    writer.add_scalar("schedule/learning_rate", lr, done)
    writer.add_scalar("schedule/beta", beta, done)


def progress_postfix(records: dict, done: int, window: int, rates: list, averages: list) -> dict[str, str]:
    """The progress bar's moving averages over the last ``window`` episodes, mean over runs, each
    named for what it averages: ``disc_return_ma200`` the discounted return the actor learns
    (Σ γ^t r), then every float outcome (a Gymnasium task's undiscounted ``return_ma200``, the
    number its summary reports as ``final_return``) and every rate. A bare ``return`` label for the
    discounted one read as the undiscounted return, about half of it on a CartPole."""
    recent = slice(max(0, done - window), done)
    shown = {f"disc_return_ma{window}": f"{records['discounted_return'][:, recent].mean():.3f}"}
    shown |= {f"{n}_ma{window}": f"{records[n][:, recent].mean():.3f}" for n in averages}
    return shown | {f"{n}_ma{window}": f"{records[n][:, recent].mean():.2f}" for n in rates}


def probe_visits(job, k: int, ep: dict) -> dict | None:
    """Activations at every probe visit of episode k after the action there was selected
    (Figs. 4.14–4.19): memories, the observation's id (from which and the memories the phase
    rebuilds the actor's state at its end, ``ActorEpisodes.visit_states``) and hidden nodes (where
    the actor shows them, ``ActorViews``), with the episode's labels."""
    step, run = ep["probes"].nonzero(as_tuple=True)
    if len(run) == 0:
        return None
    views = isinstance(job.actor, ActorViews)
    return {
        "run": run.cpu(),
        "episode": torch.full_like(run, k).cpu(),
        "step": step.cpu(),
        **{key: v[run].cpu() for key, v in job.env.labels().items()},
        **{f"memory_{name}": memory[step, run].half().cpu() for name, memory in zip(job.predictors, ep["memories"])},
        "observation": ep["obs"][step, run].cpu(),
        **({"hidden": job.actor.hidden(ep["caches"][step, run]).half().cpu()} if views else {}),
    }


def concat_records(parts: list) -> dict:
    """Probe records gathered episode by episode (a list of dicts of tensors) → one dict."""
    return {key: torch.cat([p[key] for p in parts]) for key in parts[0]}
