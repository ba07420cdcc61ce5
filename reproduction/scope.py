"""Which runs the dissertation's claims speak to, decided on what a run recorded
(``records/run.json``): its own components and algorithm. Baselines, other value forms,
preprocessors, memories and trainers are findings of ours (``beyond``, ``variants``), never
judged by its claims.
"""

from __future__ import annotations

from ferl.analysis.records import Manifest


def dissertation_components(manifest: Manifest) -> bool:
    """The actor is the free-energy one (§3.2) with Q the free energy, a preprocessor, if any,
    the RBM (§5.2), and the observations what the agent sees, without the continuous pixel
    noise of §5.4's Gaussian-visible variant: baselines, other value forms, preprocessors and
    observations are findings of ours, not claims to judge."""
    return (
        manifest.actor.get("kind", "free_energy") == "free_energy"
        and manifest.actor.get("q", "free_energy") == "free_energy"
        and not manifest.env.get("true_state")
        and (manifest.preprocessor is None or manifest.preprocessor.get("kind") == "rbm")
        and not manifest.env.get("pixel_noise_std")
    )


def dissertation_algorithm(manifest: Manifest) -> bool:
    """The dissertation's components, its predictors (Elman memories) trained in their own
    phase before the actor (Algorithms 1–2): only then do chapters 4–5's claims speak to the
    run. The online trainer and other memories (§5.4) are findings of ours."""
    return (
        dissertation_components(manifest)
        and "predictors" in manifest.trainer.get("phases", ())
        and all(facts.get("kind") == "elman" for facts in manifest.predictors.values())
    )
