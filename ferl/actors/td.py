"""The online TD step (§3.2) that every trainer takes, with any actor (``ferl.interfaces.Actor``).

    observe s' → F(s', ·) for every action → a' by Eq. (3.11) → δ = r − γ F(s', a') + F(s, a)
    → θ ← θ + α δ (−∂F/∂θ) (Eq. 3.10)

F(s', a') and its cache are carried to the next step, so no free energy is computed twice; with
the actor's ``td_fresh`` reading ``learn`` moves them to the parameters its update produced, so
that δ_t takes both free energies at one θ as Eq. (3.2) writes it.
"""

import torch


def first_action(actor, s: torch.Tensor, beta: float, generator: torch.Generator, uniform=None, choose=None):
    """a_0 of every run at state s (R, 1, S), its free energy and cache: where a run of TD steps
    starts. ``choose``: a directed exploration's choice given the actor's (``Exploration.choose``)."""
    proposal = actor.act(s, beta, generator, uniform)
    a, F_a, cache_a, _ = proposal if choose is None else choose(actor, s, proposal)
    return a, F_a, cache_a


def td_step(
    actor,
    s,
    a,
    F_sa,
    cache_sa,
    reward,
    s_next,
    lr,
    beta,
    generator,
    uniform,
    alive,
    terminal=None,
    active=None,
    choose=None,
):
    """One TD step of every run: select a' at s' (R, 1, S), δ of (s, a) (Eq. 3.2) with the actor's
    TD rule, and the update (Eq. 3.10) of the runs that are ``alive`` (R, 1) (the divergence guard).

    reward (R,); ``terminal`` (R, 1): no bootstrap from s'; ``active`` (R, 1): runs still in an
    episode (others get δ = 0); ``choose``: a directed exploration's choice of a' given the actor's
    (``ferl.exploration.Exploration.choose``). Returns a' (R, 1), F(s', a') (R, 1), its cache and δ (R, 1).
    """
    proposal = actor.act(s_next, beta, generator, uniform)
    a_next, F_next, cache_next, F_boot = proposal if choose is None else choose(actor, s_next, proposal)
    if terminal is not None:
        F_boot = F_boot * (~terminal)
    delta = reward.unsqueeze(1) - actor.gamma * F_boot + F_sa  # δ = r − γ F(s', ·) + F(s, a)
    if active is not None:
        delta = torch.where(active, delta, 0.0)
    F_sa, cache_sa = actor.learn(s, a, cache_sa, torch.where(alive, delta, 0.0), lr, s_next, a_next, F_next, cache_next)
    return a_next, F_sa, cache_sa, delta
