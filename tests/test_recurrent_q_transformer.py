"""The recurrent Q-learner's transformer core (``actor.memory=transformer``,
ferl/actors/recurrent_cores.py): its unroll equals torch.nn's own pre-LN encoder layers, no step sees a later input, padding after an episode's end
changes no valid step, the parallel unroll equals stepping one input at a time through the
key/value cache, the loss's gradient through head and core equals central finite differences
(float64, autograd-free), the same seed gives the same actor, and train.py runs it on the passive
T-maze with the context the environment's T_max + 1; a context too short, or the transformer's
keys with another memory, are refused in one line."""

import json

import pytest
import torch

from conftest import run_train
from ferl.actors.recurrent_q import RecurrentQActor
from ferl.config.params import ConfigError, check_arguments
from ferl.schedules import Constant
from test_recurrent_q import NA, R, S, ended, episode, padded_batch
from test_recurrent_q import actor as recurrent_actor
from test_sizes import only_error_line

T = 6  # padded_batch's episodes: at most T actions, T + 1 states
ENTRIES = 8  # entries of each parameter tensor checked by finite differences


def actor(head="linear", layers=2, heads=2, **kwargs) -> RecurrentQActor:
    """test_recurrent_q's actor (R runs, H = 6) with a transformer core of context T + 1."""
    return recurrent_actor(head, "transformer", layers=layers, heads=heads, max_steps=T, **kwargs)


def perturbed(agent: RecurrentQActor, seed=5) -> dict:
    """The actor's parameters in float64, biases and LN parameters moved off their initial 0 and 1
    so that every one of them matters."""
    g = torch.Generator().manual_seed(seed)
    return {
        k: v.double() + 0.3 * torch.randn(v.shape, generator=g, dtype=torch.float64) for k, v in agent.params().items()
    }


def inputs(B=3, N=T + 1, seed=1) -> torch.Tensor:
    return torch.randn(R, B, N, S + NA, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def stepped(agent: RecurrentQActor, p: dict, x: torch.Tensor) -> torch.Tensor:
    """h_0 … h_T (R, B, T+1, H) by ``step``, one input at a time from the zero state."""
    state = x.new_zeros(*x.shape[:2], agent.core.state_size)
    out = []
    for t in range(x.shape[2]):
        state = agent.core.step(p, x[:, :, t], state)
        out.append(agent.core.hidden(state))
    return torch.stack(out, 2)


def torch_reference(agent: RecurrentQActor, p: dict, run: int, x: torch.Tensor) -> torch.Tensor:
    """h_0 … h_T (B, T+1, H) of run ``run`` by torch.nn's pre-LN encoder layers (norm_first, GELU,
    4 H feed-forward, no dropout) under a causal mask, the final LN and tanh: the GPT-2 block the
    core's docstring states, computed by another implementation."""
    P, H, N = {k: v[run] for k, v in p.items()}, agent.n_hidden, x.shape[2]
    angle = torch.arange(N, dtype=torch.float64)[:, None] / 10000.0 ** (torch.arange(0, H, 2) / H)
    z = x[run] @ P["W_in"].T + P["b_in"] + torch.stack([angle.sin(), angle.cos()], -1).flatten(-2)
    for layer in range(agent.core.layers):
        block = torch.nn.TransformerEncoderLayer(
            H, agent.core.attention.heads, 4 * H, dropout=0.0, activation="gelu", norm_first=True, batch_first=True
        ).double()
        with torch.no_grad():
            for target, name in [
                (block.self_attn.in_proj_weight, "W_qkv"),
                (block.self_attn.in_proj_bias, "b_qkv"),
                (block.self_attn.out_proj.weight, "W_o"),
                (block.self_attn.out_proj.bias, "b_o"),
                (block.linear1.weight, "W_1"),
                (block.linear1.bias, "b_1"),
                (block.linear2.weight, "W_2"),
                (block.linear2.bias, "b_2"),
                (block.norm1.weight, "ln1_g"),
                (block.norm1.bias, "ln1_b"),
                (block.norm2.weight, "ln2_g"),
                (block.norm2.bias, "ln2_b"),
            ]:
                target.copy_(P[name][layer])
        block.eval()
        z = block(z, src_mask=torch.nn.Transformer.generate_square_subsequent_mask(N, dtype=torch.float64))
    return torch.tanh(torch.nn.functional.layer_norm(z, (H,), P["lnf_g"], P["lnf_b"]))


def test_the_unroll_equals_torchs_own_transformer_layers():
    agent = actor()
    p = perturbed(agent)
    x = inputs()
    with torch.no_grad():
        h = agent.core.unroll(p, x)
        for run in range(R):
            torch.testing.assert_close(h[run], torch_reference(agent, p, run, x))


def test_no_step_sees_a_later_input():
    """Change x_{t'} (state and previous action): Q at every t < t' stays bit for bit, Q at t' moves."""
    agent = actor()
    p = perturbed(agent)
    x = inputs()
    with torch.no_grad():
        q = agent.core.unroll(p, x, lambda h: agent.head.q(p, h))
        for later in (1, 3, T):
            changed = x.clone()
            changed[:, :, later] += 2.0
            moved = agent.core.unroll(p, changed, lambda h: agent.head.q(p, h))
            assert torch.equal(moved[:, :, :later], q[:, :, :later])
            assert (moved[:, :, later] - q[:, :, later]).abs().amax() > 1e-3


def test_the_parallel_unroll_equals_stepping_one_input_at_a_time():
    """The full cache (T + 1 = context tokens), two layers of two heads, float64."""
    agent = actor()
    assert agent.core.context == T + 1 and agent.core.state_size == 6 + 1 + 2 * 2 * (T + 1) * 6
    p = perturbed(agent)
    x = inputs()
    with torch.no_grad():
        torch.testing.assert_close(agent.core.unroll(p, x), stepped(agent, p, x), rtol=1e-12, atol=1e-12)


def test_padded_episodes_give_the_unpadded_outputs_and_loss():
    """Episodes of 1 … T actions padded with large values: Q at each valid step equals the episode's
    own unroll, and the batched loss equals the per-episode losses weighted by their lengths."""
    agent = actor().double()
    batch = padded_batch(T=T, B=4)
    batch["states"], batch["rewards"] = batch["states"].double(), batch["rewards"].double()
    lengths = batch["lengths"]
    x = torch.cat([batch["states"], inputs(B=4)[..., S:]], -1)
    for r in range(R):
        for b in range(4):
            x[r, b, lengths[r, b] + 1 :] = 50.0
    p = perturbed(agent)
    loss, reference = agent.loss(p, batch), 0.0
    with torch.no_grad():
        q = agent.unroll(p, *x.split([S, NA], -1))
        for r in range(R):
            one, p_r, n = agent.slice_runs(slice(r, r + 1)), {k: v[r : r + 1] for k, v in p.items()}, lengths[r]
            for b in range(4):
                valid = int(n[b]) + 1
                alone = one.unroll(p_r, *x[r : r + 1, b : b + 1, :valid].split([S, NA], -1))
                torch.testing.assert_close(q[r, b, :valid], alone[0, 0], rtol=1e-12, atol=1e-12)
            reference += sum(one.loss(p_r, episode(batch, r, b)) * n[b] for b in range(4)) / n.sum()
    torch.testing.assert_close(loss, reference)


@pytest.mark.parametrize("head", ["linear", "free_energy"])
def test_the_gradient_through_head_and_core_equals_central_differences(head):
    """∂L/∂θ of every trained parameter tensor (core and head; 8 random entries of each) on a padded batch, against
    (L(θ + ε e_i) − L(θ − ε e_i)) / 2ε, ε = 1e−6, float64; the target network differs."""
    agent = actor(head, layers=1, heads=2).double()
    for name in agent.names:
        getattr(agent, f"{name}_target").add_(torch.randn_like(getattr(agent, name)) * 0.1)
    batch = padded_batch(T=T, B=2, seed=3)
    batch["states"] = batch["states"].double()
    batch["rewards"] = batch["rewards"].double()
    p = perturbed(agent)
    trained = {k: v.clone().requires_grad_() for k, v in p.items() if k in agent.names}
    grads = torch.autograd.grad(agent.loss({**p, **trained}, batch), list(trained.values()))
    eps, pick = 1e-6, torch.Generator().manual_seed(0)
    with torch.no_grad():
        for (name, value), grad in zip(trained.items(), grads):
            flat = value.detach().view(-1)
            entries = torch.randperm(flat.numel(), generator=pick)[:ENTRIES]  # of every run, every tensor
            numeric = []
            for i in entries:
                losses = []
                for sign in (1, -1):
                    moved = flat.clone()
                    moved[i] += sign * eps
                    losses.append(agent.loss({**p, name: moved.view_as(value)}, batch))
                numeric.append((losses[0] - losses[1]) / (2 * eps))
            torch.testing.assert_close(grad.reshape(-1)[entries], torch.stack(numeric), rtol=1e-5, atol=1e-7, msg=name)


def trained_actor(seed: int) -> RecurrentQActor:
    """An actor after 4 episodes that act and replay (Adam steps, a target copy)."""
    agent = actor(seed=seed, batch_episodes=3, target_every=2)
    for k in range(4):
        s = torch.rand(R, 1, S, generator=torch.Generator().manual_seed(100 + k))
        agent.act(s, 2.0, torch.Generator().manual_seed(k))
        agent.end_episode(ended(k, T=4), 0.05)
    return agent


def test_the_same_seed_gives_the_same_actor_bit_for_bit():
    one, two, other = trained_actor(7), trained_actor(7), trained_actor(8)
    for name, value in one.state_dict().items():
        if torch.is_tensor(value):
            assert torch.equal(value, two.state_dict()[name]), name
    assert not torch.equal(one.W_qkv, other.W_qkv)


def test_the_transformers_keys_are_checked():
    keys = {"memory": "transformer", "n_hidden": 6, "lr": Constant(0.1), "beta": Constant(1.0), "gamma": 0.9}
    with pytest.raises(ConfigError, match=r"^actor\.context=7 is not allowed: ≥ 8, the environment's T_max \+ 1"):
        check_arguments(RecurrentQActor, {**keys, "context": 7, "max_steps": 7}, "actor.")
    with pytest.raises(ConfigError, match=r"^actor\.heads=4 is not allowed: a divisor of n_hidden=6"):
        check_arguments(RecurrentQActor, {**keys, "heads": 4}, "actor.")
    for key, value in (("context", 20), ("layers", 2), ("heads", 2)):
        with pytest.raises(ConfigError, match=rf"^actor\.{key}={value} is not allowed: only with memory=transformer"):
            check_arguments(RecurrentQActor, {**keys, "memory": "gru", key: value}, "actor.")
    check_arguments(RecurrentQActor, {**keys, "context": 8, "max_steps": 7}, "actor.")
    with pytest.raises(ValueError, match="context is needed"):
        RecurrentQActor(n_runs=1, n_state=S, n_actions=NA, **keys)


PASSIVE = ["experiment=passive_tmaze", "trainer=algorithm1", "actor=recurrent_q", "predictor=none"]
PASSIVE += ["actor.memory=transformer", "env.corridor_length=4"]


def test_a_context_shorter_than_t_max_plus_one_is_one_line_before_any_file(tmp_path):
    """The passive maze of corridor 4 lasts T_max = 5 steps: context 5 < 6 is refused."""
    result = run_train(*PASSIVE, "actor.context=5", f"hydra.run.dir={tmp_path / 'out' / 'run'}")
    assert only_error_line(result) == (
        "ferl: error: actor.context=5 is not allowed: ≥ 6, the environment's T_max + 1 (env.max_steps + 1): "
        "the core attends to every state s_0 … s_T_max of an episode"
    )
    assert not (tmp_path / "out").exists()


def test_train_py_runs_the_transformer_core_on_the_passive_maze(tmp_path):
    """A tiny run composes the real configs and writes summary.json; its context is T_max + 1."""
    run_dir = tmp_path / "run"
    overrides = ["n_runs=2", "trainer.n_episodes=20", "trainer.log_every=10", "trainer.final_window=10"]
    result = run_train(*PASSIVE, *overrides, f"hydra.run.dir={run_dir}")
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert len(summary["metrics"]["final_correct_goal_rate"]) == 2
    described = json.loads((run_dir / "records" / "run.json").read_text())["actor"]
    assert (described["memory"], described["context"], described["layers"], described["heads"]) == (
        "transformer",
        6,
        1,
        1,
    )
