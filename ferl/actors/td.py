"""The online TD step (§3.2) that every trainer takes, with any actor (``ferl.interfaces.Actor``).

    observe s' → F(s', ·) for every action → a' by Eq. (3.11) → δ = r − γ F(s', a') + F(s, a)
    → θ ← θ + α δ (−∂F/∂θ) (Eq. 3.10)

F(s', a') and its cache are carried to the next step, so no free energy is computed twice; with
the actor's ``td_fresh`` reading ``learn`` moves them to the parameters its update produced, so
that δ_t takes both free energies at one θ as Eq. (3.2) writes it.
"""
import torch


def pick(x: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Entries of the chosen actions on the online path: x (R, 1, nA, ...) at a (R, 1) → (R, 1, ...)."""
    flat = x.reshape(-1, *x.shape[3:]) if x.dim() > 3 else x.reshape(-1)
    index = a.squeeze(1) + torch.arange(0, flat.shape[0], x.shape[2], device=a.device)
    return flat.index_select(0, index).unsqueeze(1)


def first_action(actor, s: torch.Tensor, beta: float, generator: torch.Generator, uniform=None):
    """a_0 of every run at state s (R, 1, S), its free energy and cache: where a run of TD steps starts."""
    F, cache = actor.evaluate(s)
    a = actor.select(s, F, beta, generator, uniform)
    return a, pick(F, a), pick(cache, a)


def td_step(actor, s, a, F_sa, cache_sa, reward, s_next, lr, beta, generator, uniform, alive,
            terminal=None, active=None):
    """One TD step of every run: select a' at s' (R, 1, S), δ of (s, a) (Eq. 3.2) with the actor's
    TD rule, and the update (Eq. 3.10) of the runs that are ``alive`` (R, 1) (the divergence guard).

    reward (R,); ``terminal`` (R, 1): no bootstrap from s'; ``active`` (R, 1): runs still in an
    episode (others get δ = 0). Returns a' (R, 1), F(s', a') (R, 1), its cache and δ (R, 1).
    """
    F_next, cache_next = actor.evaluate(s_next)
    a_next = actor.select(s_next, F_next, beta, generator, uniform)
    delta = actor.td_error(reward.unsqueeze(1), F_sa, F_next, a_next, beta, terminal)
    if active is not None:
        delta = torch.where(active, delta, 0.0)
    F_sa, cache_sa = actor.learn(s, a, cache_sa, torch.where(alive, delta, 0.0), lr, s_next, a_next,
                                 pick(F_next, a_next), pick(cache_next, a_next))
    return a_next, F_sa, cache_sa, delta
