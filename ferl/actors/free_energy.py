"""FERL actor: an RBM whose negative free energy approximates Q(s, a) (§3.2).

Visible layer = state nodes s and action nodes a, hidden layer h (Fig. 4.1a).

* Q(s, a) ≈ −F(s, a), F the unit-temperature free energy (Eq. 3.1 and §2.1.5)
* clamped action selection: softmax π(a|s) ∝ exp(−β F(s, a)) over all action codes (Eq. 3.11)
* alternating-Gibbs action sampling (end of §3.2) as an option
* TD errors SARSA(0), Q(0), expected SARSA (§3.2, with Q = −F):
      δ = r − γ F(s', a') + F(s, a)   (``act`` gives F(s', a') and the bootstrap term, ``ferl.actors.td``)
* ``q``: Q as the free energy (default), the scaled free energy or the expected energy
  (``ferl.actors.values``); F stands for −Q throughout
* factored actions (Sallans & Hinton 2004): with ``action_code=binary`` and more than
  ``MAX_ENUMERATED_ACTIONS`` actions, action i is the K = log2 n bits of i, never enumerated; it is
  drawn by alternating Gibbs sampling and only its own F is evaluated (SARSA only)
* online update θ ← θ + α δ (−∂F/∂θ), Eqs. (3.5–3.10)
* ``td_fresh``: F(s_t, a_t) of δ_t at the θ of F(s_{t+1}, a_{t+1}), as Eq. (3.2) writes δ_t(θ),
  obtained from the value before the previous update by that update's rank-one effect (``learn``)

All parameters carry the run dimension first, ``W_sh`` (R, S, H); states are (R, B, S) with
B = 1 in the online step loop and B = many for test images. The cache of ``evaluate`` is the
hidden input x (R, B, nA, H), ĥ = σ(x).
"""

import math
from typing import Literal

import torch

from ferl import rbm
from ferl.actors.softmax import SoftmaxActor, check_schedules, sample_categorical
from ferl.actors.values import FORMS, value_form
from ferl.bits import from_bits, to_bits
from ferl.config.params import ArgumentError, NonNegative, Positive, PositiveInt, checked

# what α is divided by: the square root of the edges or of a hidden node's fan-in, nothing, or
# ‖∂Q(s, a)/∂θ‖² (normalised LMS: α is then the share of δ that one update corrects)
LRNorm = Literal["edges", "fan_in", "none", "gradient"]
ActionCode = Literal["onehot", "binary"]
ActionSelection = Literal["clamp", "gibbs"]
ValueForm = Literal["free_energy", "scaled_free_energy", "expected_energy"]  # ferl.actors.values.FORMS' names
# Up to this many actions every action's F is computed at every step (clamped softmax, Q(0),
# expected SARSA); beyond it actions are factored bit codes drawn by Gibbs sampling.
MAX_ENUMERATED_ACTIONS = 4096


def action_code_table(n_actions: int, code: str) -> torch.Tensor:
    """Rows are the action-node configurations of every admissible action.

    ``onehot``: one node per action (the dissertation's constraint, §3.2 end).
    ``binary``: ⌈log2 n⌉ factored binary nodes, action i ↔ the bits of i.
    """
    if code == "onehot":
        return torch.eye(n_actions)
    return to_bits(torch.arange(n_actions), max(1, math.ceil(math.log2(n_actions))))


class FERLActor(SoftmaxActor):
    """The dissertation's actor (§3.2): an RBM over state and action nodes whose negative free
    energy is Q, Q(s, a) ≈ −F(s, a) (Eq. 3.1), acting by the softmax of Eq. 3.11 and learning
    online by θ ← θ + α δ (−∂F/∂θ) (Eqs. 3.5–3.10); batched over runs (module docstring)."""

    shared_buffers = ("codes",)
    codes: torch.Tensor  # (nA, bits) the actions' codes, shared by the runs
    W_sh: torch.Tensor  # (R, S, H)
    W_ah: torch.Tensor  # (R, bits, H)
    b_s: torch.Tensor  # (R, S)
    b_a: torch.Tensor  # (R, bits)
    b_h: torch.Tensor  # (R, H)

    @checked
    def __init__(
        self,
        *,
        n_hidden: PositiveInt,
        lr_norm: LRNorm = "edges",
        init_std: NonNegative = 0.01,
        bias_init_std: NonNegative = 0.0,
        action_code: ActionCode = "onehot",
        action_selection: ActionSelection = "clamp",
        gibbs_sweeps: PositiveInt = 20,
        gibbs_anneal_from: Positive | None = None,
        td_fresh: bool = False,
        q: ValueForm = "free_energy",
        q_scale: Positive | None = None,
        **softmax,
    ):
        """``softmax``: the sizes, TD rule, γ, schedules and seed every softmax actor takes
        (``SoftmaxActor``)."""
        super().__init__(**softmax)
        _, n_state, n_actions = self.sizes
        self.td_fresh, self.n_hidden, self.lr_norm = td_fresh, n_hidden, lr_norm
        self.action_selection, self.gibbs_sweeps = action_selection, gibbs_sweeps
        self.gibbs_anneal_from = gibbs_anneal_from
        # Z of the scaled free energy: by default √(state nodes), Elfwing et al. (2013)'s choice
        self.form = value_form(q, q_scale or math.sqrt(n_state))
        self.onehot = action_code == "onehot"
        self.enumerated = n_actions <= MAX_ENUMERATED_ACTIONS
        # factored actions are the bits of their index (ferl.bits); no table of 2^K rows
        codes = (
            action_code_table(n_actions, action_code) if self.enumerated else torch.zeros(0, int(math.log2(n_actions)))
        )
        n_bits = codes.shape[1]
        self.register_buffer("codes", codes)
        # Each run is initialised from its own seed, so run r does not depend on n_runs.
        gens = self.run_generators()
        self.register_buffer(
            "W_sh", torch.stack([torch.randn(n_state, n_hidden, generator=g) for g in gens]) * init_std
        )
        self.register_buffer("W_ah", torch.stack([torch.randn(n_bits, n_hidden, generator=g) for g in gens]) * init_std)
        # biases N(0, bias_init_std²), drawn after the weights so the weights do not depend on it
        biases = [torch.randn(n_state + n_bits + n_hidden, generator=g) for g in gens]
        b_s, b_a, b_h = (torch.stack(biases) * bias_init_std).split([n_state, n_bits, n_hidden], 1)
        self.register_buffer("b_s", b_s.contiguous())
        self.register_buffer("b_a", b_a.contiguous())
        self.register_buffer("b_h", b_h.contiguous())
        # α's divisor (learning_rate), fixed by the network's size: a hidden node's fan-in is its
        # state + action nodes; the edges are those connections of every hidden node (§3.5)
        fan_in = n_state + n_bits
        self.lr_divisor = math.sqrt({"edges": fan_in * n_hidden, "fan_in": fan_in}.get(lr_norm, 1))

    @classmethod
    def check_config(cls, args: dict) -> None:
        """α and β of the schedules at the start and the end of training (both monotone); a value
        form that Gibbs sampling can draw from; factored actions (known once the environment
        gives ``n_actions``) coded in bits, drawn by Gibbs sampling and learnt by SARSA."""
        check_schedules(args)
        if args["action_selection"] == "gibbs" and not FORMS[args["q"]].boltzmann:
            raise ArgumentError(
                "q",
                "free_energy or scaled_free_energy with action_selection=gibbs "
                "(no Gibbs chain samples exp(β Q) of the expected energy)",
            )
        n_actions = args.get("n_actions", 0)
        if n_actions <= MAX_ENUMERATED_ACTIONS:
            return
        actions = f"the environment's {n_actions} actions"
        if n_actions & (n_actions - 1):
            raise ArgumentError("action_code", f"{actions}: factored actions need a power of two")
        if args["action_code"] != "binary":
            raise ArgumentError("action_code", f"binary: {actions} are too many for one node each")
        if args["action_selection"] != "gibbs":
            raise ArgumentError("action_selection", f"gibbs: softmax selection would enumerate {actions}")
        if args["td_rule"] != "sarsa":
            raise ArgumentError("td_rule", f"sarsa: Q(0) and expected SARSA would enumerate {actions}")

    @property
    def n_runs(self) -> int:
        return self.W_sh.shape[0]

    def describe(self) -> dict:
        return {
            "kind": "free_energy",
            "q": self.form.name,
            "n_hidden": self.n_hidden,
            "gamma": self.gamma,
            "td_rule": self.td_rule,
            "action_selection": self.action_selection,
            "td_fresh": self.td_fresh,
            "action_bits": self.W_ah.shape[1],
        }

    @property
    def uniforms_per_action(self) -> int:
        """U(0, 1) numbers one choice takes: 1 for the clamped softmax; a Gibbs chain's every draw
        (``chain_width``), so that a step's random numbers are drawn beforehand and the chain runs
        inside a compiled chunk."""
        return 1 if self.action_selection != "gibbs" else self.chain_width(factored=not self.enumerated)

    def chain_width(self, factored: bool) -> int:
        """The draws of one Gibbs chain: ``gibbs_bits``' K + sweeps (H + K) (``factored``), or
        ``gibbs_actions``' 1 + sweeps (H + 1)."""
        K, H = self.W_ah.shape[1:]
        return K + self.gibbs_sweeps * (H + K) if factored else 1 + self.gibbs_sweeps * (H + 1)

    def state_weights(self) -> torch.Tensor:
        """W_sh (R, S, H): what every state node feeds the hidden nodes (Figs. 3.5, 4.1a)."""
        return self.W_sh

    def hidden(self, x: torch.Tensor) -> torch.Tensor:
        """ĥ = σ(x) of hidden inputs from ``evaluate`` (Eq. 3.1c)."""
        return torch.sigmoid(x)

    def prepare_for_compile(self) -> None:
        """Store W_sh hidden-major (its values unchanged): in a compiled step Wᵀs and the rank-one
        update (Eq. 3.10a) then both run along the contiguous state axis, which inductor
        vectorises and fuses into one pass over W (eager's bmm is faster on the default layout)."""
        self.W_sh = self.W_sh.transpose(1, 2).contiguous().transpose(1, 2)

    def evaluate(self, s: torch.Tensor):
        """Energies F = −Q of every action and the hidden inputs: s (R, B, S) or shared (B, S) →
        F (R, B, nA), x (R, B, nA, H) with ĥ = σ(x) (Eq. 3.1c)."""
        x = rbm.hidden_input(s, self.W_sh, self.b_h).unsqueeze(2) + self.action_input(self.W_ah).unsqueeze(1)
        visible = rbm.visible_term(s, self.b_s).unsqueeze(-1) + self.action_input(self.b_a.unsqueeze(-1)).transpose(
            1, 2
        )
        return self.form.energy(visible, x), x

    def evaluate_actions(self, s: torch.Tensor, a: torch.Tensor):
        """F = −Q and the hidden inputs of the given actions only: s (R, B, S), a (R, B) →
        F (R, B), x (R, B, H)."""
        code = self.code(a)
        x = rbm.hidden_input(s, self.W_sh, self.b_h) + torch.bmm(code, self.W_ah)
        visible = rbm.visible_term(s, self.b_s) + (code * self.b_a.unsqueeze(1)).sum(-1)
        return self.form.energy(visible, x), x

    def state_gradient(self, s: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """∂Q(s, a)/∂s (R, B, S) at states s (R, B, S) and actions a (R, B), written out: with
        Q = κ (sᵀb_s + aᵀb_a + Σ_k φ(x_k)), x = W_shᵀs + W_ahᵀa + b_h (Eq. 3.1c,
        ``ferl.actors.values``), ∂Q/∂s = κ (b_s + W_sh φ'(x)) — for the free energy
        b_s + W_sh σ(x) (Eq. 2.22 differentiated in s). What the online trainer's
        ``td_to_memory`` sends into the predictors' memory (``ferl.trainers.memory_td``)."""
        _, x = self.evaluate_actions(s, a)
        return self.scaled(
            torch.baddbmm(self.b_s.unsqueeze(1), self.form.hidden_gradient(x), self.W_sh.transpose(1, 2))
        )

    def code(self, a: torch.Tensor) -> torch.Tensor:
        """The action nodes' states of actions a (R, B) → (R, B, K)."""
        return self.codes[a] if self.enumerated else to_bits(a, self.W_ah.shape[1]).to(self.W_ah.dtype)

    def action_input(self, weights: torch.Tensor) -> torch.Tensor:
        """codes @ weights, (R, nA, ·): what every admissible action feeds the hidden layer.
        One-hot codes are the identity, so the product is skipped on the hot path."""
        return weights if self.onehot else self.codes @ weights

    def act(self, s: torch.Tensor, beta: float, generator: torch.Generator, uniform: torch.Tensor | None = None):
        """At states s (R, 1, S): an action a (R, 1), its F(s, a) (R, 1) and hidden input
        (R, 1, H), and the F that a TD error bootstraps from at s (§3.2): F(s, a) (SARSA), min_a F
        (Q(0)) or the policy's mean F (expected SARSA). Factored actions are drawn by Gibbs
        sampling and only their own F is computed. ``uniform`` (R, 1, ``uniforms_per_action``):
        the choice's pre-drawn U(0, 1) numbers, or None to draw them from ``generator``."""
        if not self.enumerated:
            a = self.gibbs_bits(s, beta, self.chain_uniforms(s, generator, uniform))
            F_a, x_a = self.evaluate_actions(s, a)
            return a, F_a, x_a, F_a
        return super().act(s, beta, generator, uniform)

    def select(self, s: torch.Tensor, F: torch.Tensor, beta: float, generator: torch.Generator, uniform=None):
        """An action index per (run, state): clamped softmax (Eq. 3.11) or alternating Gibbs.

        ``uniform`` (R, B, ``uniforms_per_action``) may carry the choice's pre-drawn U(0, 1) numbers.
        """
        if self.action_selection == "gibbs":
            return self.gibbs_actions(s, beta, self.chain_uniforms(s, generator, uniform))
        return super().select(s, F, beta, generator, uniform)

    def chain_uniforms(
        self, s: torch.Tensor, generator: torch.Generator, uniform: torch.Tensor | None, factored: bool | None = None
    ) -> torch.Tensor:
        """A Gibbs chain's U(0, 1) numbers (R, B, ``chain_width``) at states s (R, B, S): as given,
        or drawn from ``generator``; ``factored``: for ``gibbs_bits`` (default: as ``act`` chooses)."""
        if uniform is not None:
            return uniform
        width = self.chain_width(not self.enumerated if factored is None else factored)
        return torch.rand(s.shape[:2] + (width,), generator=generator, device=s.device, dtype=s.dtype)

    def gibbs_actions(self, s: torch.Tensor, beta, u: torch.Tensor) -> torch.Tensor:
        """Alternating Gibbs sampling with s clamped (end of §3.2): h ~ P(h|s,a), a ~ P(a|h).

        Both conditionals at inverse temperature β, so the chain's stationary law is
        P(a|s) ∝ exp(−β F_β(s, a)). P(a|h) ∝ exp(β aᵀ(W_ah h + b_a)) over the admissible codes:
        for ``binary`` codes this factorises into independent action nodes; for ``onehot`` it
        is the softmax unit that enforces one active action node. Each sweep runs at its
        ``chain_betas`` value (β / Z for a scaled free energy, annealed with ``gibbs_anneal_from``).
        u (R, B, 1 + sweeps (H + 1)): the start's uniform, then per sweep H for h and 1 for a.
        """
        x_s = rbm.hidden_input(s, self.W_sh, self.b_h)
        H, n_actions = x_s.shape[-1], self.codes.shape[0]
        a = (u[..., 0] * n_actions).long().clamp_(max=n_actions - 1)  # uniformly random start
        for b, u_sweep in zip(self.chain_betas(beta), u[..., 1:].split(H + 1, -1)):
            x = x_s + torch.bmm(self.codes[a], self.W_ah)
            h = (u_sweep[..., :H] < torch.sigmoid(b * x)).to(x_s.dtype)
            action_field = torch.bmm(h, self.W_ah.transpose(1, 2)) + self.b_a.unsqueeze(1)
            a = sample_categorical(torch.softmax(b * action_field @ self.codes.T, -1), u_sweep[..., H:])
        return a

    def gibbs_bits(self, s: torch.Tensor, beta, u: torch.Tensor) -> torch.Tensor:
        """``gibbs_actions`` for factored actions (Sallans & Hinton 2004, §3): the action nodes
        are independent given h, P(a_k = 1 | h) = σ(β (W_ah h + b_a)_k), so the chain never
        enumerates the 2^K actions. Starts from uniformly random bits. With ``gibbs_anneal_from``
        the chain is annealed: its inverse temperature rises geometrically from that value to β
        over the sweeps. u (R, B, K + sweeps (H + K)): the start's K uniforms, then per sweep H
        for h and K for the bits. Returns action indices (R, B)."""
        x_s = rbm.hidden_input(s, self.W_sh, self.b_h)
        H, K = x_s.shape[-1], self.W_ah.shape[1]
        bits = (u[..., :K] < 0.5).to(x_s.dtype)
        W_ha = self.W_ah.transpose(1, 2)
        for b, u_sweep in zip(self.chain_betas(beta), u[..., K:].split(H + K, -1)):
            h = (u_sweep[..., :H] < torch.sigmoid(b * torch.baddbmm(x_s, bits, self.W_ah))).to(x_s.dtype)
            bits = (u_sweep[..., H:] < torch.sigmoid(b * torch.baddbmm(self.b_a.unsqueeze(1), h, W_ha))).to(x_s.dtype)
        return from_bits(bits)

    def chain_betas(self, beta) -> list:
        """The inverse temperature of every Gibbs sweep: β throughout, or annealed geometrically
        from ``gibbs_anneal_from`` to β; at β / Z for a scaled free energy. β is a float, or a
        0-d tensor in a compiled chunk (one graph for every β)."""
        beta = self.form.gibbs_beta(beta)
        n = self.gibbs_sweeps
        if self.gibbs_anneal_from is None or n == 1:
            return [beta] * n
        start = self.form.gibbs_beta(self.gibbs_anneal_from)
        return [start * (beta / start) ** (i / (n - 1)) for i in range(n)]

    def scaled(self, t: torch.Tensor) -> torch.Tensor:
        """κ t for the value form's κ (``ferl.actors.values``); the free energy's κ = 1 is skipped."""
        return t if self.form.scale == 1.0 else t * self.form.scale

    def learn(self, s, a, x_sa, delta, lr, s_next, a_next, F_next, x_next):
        """The online update of (s, a) (``update``, Eq. 3.10), then F (R, B) and hidden input
        x (R, B, H) of the next pair (s', a') for the next TD error: as evaluated before the
        update, or with ``td_fresh`` at the parameters it produced. With Q = κ (c + Σ_k φ(x_k))
        (``ferl.actors.values``; the free energy: κ = 1, φ = softplus) the update adds
        g = κ α δ φ'(x(s, a)) to b_h, sᵀg to W_sh and g to the rows of a's action nodes, κ α δ s
        to b_s and κ α δ a to b_a, so

            x' = x + (s'·s + 1 + a'·a) g,   F' = F − κ² α δ (s'·s + a'·a) − κ Σ_k [φ(x'_k) − φ(x_k)],

        O(S + H) a pair instead of a second pass over W_sh (a'·a: the action codes' overlap).
        """
        if self.lr_norm == "gradient":
            lr = lr / self.gradient_norm(s, a, x_sa)
        g = self.update(s, a, x_sa, delta, lr)
        if not self.td_fresh:
            return F_next, x_next
        overlap = (s_next * s).sum(-1) + self.codes_overlap(a, a_next)
        x_new = x_next + (overlap + 1).unsqueeze(-1) * g
        phi = self.form.hidden_term
        F_new = (
            F_next - self.scaled(self.scaled(lr * delta * overlap)) - self.scaled((phi(x_new) - phi(x_next)).sum(-1))
        )
        return F_new, x_new

    def gradient_norm(self, s: torch.Tensor, a: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """‖∂Q(s, a)/∂θ‖² (R, B) over W_sh, W_ah, b_s, b_a, b_h: κ² (|v|² (1 + Σ_k φ'_k²) + Σ_k φ'_k²),
        v = (s, a). An update α δ ∂Q/∂θ changes Q(s, a) by α δ times this (to first order), so
        an α above 2 / this makes the update overshoot and grow (the LMS stability bound)."""
        v_sq = (s * s).sum(-1) + self.codes_overlap(a, a)
        phi_sq = self.form.hidden_gradient(x).pow(2).sum(-1)
        return self.scaled(self.scaled(v_sq * (1 + phi_sq) + phi_sq))

    def codes_overlap(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Dot products of the action codes of a and b (R, B): 1 or 0 for one-hot codes."""
        if self.onehot:
            return (a == b).to(self.W_ah.dtype)
        return (self.code(a) * self.code(b)).sum(-1)

    @torch.no_grad()
    def update(self, s, a, x_sa, delta, lr) -> torch.Tensor:
        """θ ← θ + α δ ∂Q/∂θ in place (Eq. 3.10a–e for Q = −F), summed over the B axis; returns
        the hidden nodes' share g = κ α δ φ'(x) (R, B, H) (α δ ĥ for the free energy).

        s (R, B, S), a (R, B) action indices, x_sa (R, B, H) hidden inputs at (s, a), delta (R, B);
        lr a float or a 0-d tensor (so a compiled step does not recompile as α decays).
        """
        step = self.scaled(lr * delta)  # κ α δ
        g = step.unsqueeze(-1) * self.form.hidden_gradient(x_sa)  # κ α δ φ'(x)
        if s.shape[1] == 1:  # online step: broadcast outer products beat batched matmuls
            self.W_sh.addcmul_(s.transpose(1, 2), g)
            self.b_s.addcmul_(step, s.squeeze(1))
        else:
            self.W_sh.baddbmm_(s.transpose(1, 2), g)
            self.b_s.add_(torch.bmm(step.unsqueeze(1), s).squeeze(1))
        self.b_h.add_(g.sum(1))
        if self.onehot:  # the action node of a is the only active one: update row a only
            rows = (
                a + torch.arange(0, a.shape[0] * self.W_ah.shape[1], self.W_ah.shape[1], device=a.device).unsqueeze(1)
            ).flatten()
            self.W_ah.view(-1, self.W_ah.shape[2]).index_add_(0, rows, g.flatten(0, 1))
            self.b_a.view(-1).index_add_(0, rows, step.flatten())
        elif s.shape[1] == 1:  # as W_sh's (a compiled chunk's C++ wrapper also fails on this baddbmm_)
            code = self.code(a)
            self.W_ah.addcmul_(code.transpose(1, 2), g)
            self.b_a.addcmul_(step, code.squeeze(1))
        else:
            code = self.code(a)
            self.W_ah.baddbmm_(code.transpose(1, 2), g)
            self.b_a.add_(torch.bmm(step.unsqueeze(1), code).squeeze(1))
        return g
