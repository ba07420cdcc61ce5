"""Sallans & Hinton (2004)'s large-action task: rewards against a brute-force reading of the task,
run views and checkpoints, the experiment end to end, and learning at reduced scale."""

import json

import numpy as np
import torch
from hydra.utils import instantiate

from conftest import compose_config, run_train, train_job
from ferl.bits import to_bits
from ferl.envs.large_action import LargeActionTask


def make_task(R=3, **kw):
    return LargeActionTask(R, torch.Generator().manual_seed(0), seed=11, **kw)


def brute_force_reward(keys, key_actions, s, bits):
    """The task's definition, one run at a time in NumPy: the first key state at the least
    Hamming distance from s, then the action bits that agree with its key action."""
    distances = [int(np.abs(s - k).sum()) for k in keys]
    nearest = distances.index(min(distances))
    return int((bits == key_actions[nearest]).sum())


def test_rewards_follow_the_definition():
    task = make_task(R=3)
    g = torch.Generator().manual_seed(1)
    for _ in range(50):
        s = task.state.clone()
        action = torch.randint(2**40, (3,), generator=g)
        _, reward, terminated, _ = task.step(action)
        assert not terminated.any()
        bits = to_bits(action, 40).numpy()
        for r in range(3):
            want = brute_force_reward(task.keys[r].numpy(), task.key_actions[r].numpy(), s[r].numpy(), bits[r])
            assert reward[r].item() == want


def test_key_actions_earn_the_optimum_and_states_are_uniform():
    task = make_task(R=2)
    keys, key_actions = task.keys, task.key_actions
    index = (key_actions * 2 ** torch.arange(39, -1, -1).double()).sum(-1).long()  # the key actions as indices
    for j in range(keys.shape[1]):
        assert torch.equal(task.reward(keys[:, j], index[:, j]), torch.full((2,), 40.0))
    assert task.optimal(0.0) == {"reward_per_step": 40.0, "random_reward_per_step": 20.0}
    states = torch.cat(task.step_inputs(4000)).view(-1, 12)
    assert abs(states.mean().item() - 0.5) < 0.01
    # each run draws its own keys from seed + r: run 1 of a 2-run batch is run 1 of a 3-run one
    assert torch.equal(make_task(R=3).keys[1], keys[1]) and not torch.equal(keys[0], keys[1])


def test_key_state_reading_draws_only_key_states():
    task = make_task(R=2, states="key_states")
    states = task.step_inputs(200)[0]
    for r in range(2):
        assert (states[:, r].unsqueeze(1) == task.keys[r]).all(-1).any(-1).all()


def test_run_views_and_state_dict():
    task = make_task(R=4)
    part = task.slice_runs(slice(1, 3))
    next_states = task.step_inputs(1)[0][0]
    part.step_with(torch.zeros(2, dtype=torch.long), next_states[1:3])
    assert torch.equal(task.state[1:3], next_states[1:3])  # the view moved the batch
    saved = {k: v.clone() if torch.is_tensor(v) else v for k, v in task.state_dict().items()}
    ahead = task.step_inputs(5)[0]
    task.load_state_dict(saved)
    assert torch.equal(task.step_inputs(5)[0], ahead)


def test_large_action_experiment_learns_at_reduced_scale(tmp_path):
    """3 runs × 4 000 steps, 20 Gibbs sweeps: every run's reward over the last 10 % of its steps is
    above a random policy's 20 by more than 6 standard errors of that mean (400 steps, s.d. √10)."""
    run_dir = tmp_path / "run"
    result = run_train(
        "experiment=large_action", "n_runs=3", "trainer.steps=4000", "actor.gibbs_sweeps=20", f"hydra.run.dir={run_dir}"
    )
    assert result.returncode == 0, result.stderr[-2000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["task"] == "large_action" and summary["optimal"]["reward_per_step"] == 40.0
    rewards = np.load(run_dir / "records" / "steps.npz")["rewards"]
    assert rewards.shape == (3, 4000)
    last = summary["metrics"]["reward_per_step_last10pct"]
    np.testing.assert_allclose(rewards[:, -400:].mean(1), last, rtol=1e-6)
    assert min(last) > 20 + 6 * np.sqrt(10 / 400)


def numpy_gibbs_bits(W_sh, W_ah, b_h, b_a, s, beta, u, sweeps):
    """Sallans & Hinton's alternating chain written out for one run and one state in NumPy:
    random start bits, then per sweep h_j = [u < σ(β (sᵀW_sh + aᵀW_ah + b_h)_j)] and
    a_k = [u < σ(β (W_ah h + b_a)_k)], each sweep's uniforms H for h then K for a."""
    K, H = W_ah.shape
    bits = (u[:K] < 0.5).astype(float)
    sig = lambda x: 1 / (1 + np.exp(-x))  # noqa: E731
    for i in range(sweeps):
        uh = u[K + i * (H + K) : K + i * (H + K) + H]
        ua = u[K + i * (H + K) + H : K + (i + 1) * (H + K)]
        h = (uh < sig(beta * (s @ W_sh + bits @ W_ah + b_h))).astype(float)
        bits = (ua < sig(beta * (W_ah @ h + b_a))).astype(float)
    return bits


def test_gibbs_selection_follows_its_uniforms_and_draws_them_as_it_would_itself():
    """The factored chain on pre-drawn uniforms equals the NumPy chain on the same numbers (in
    every run and state), and passing no uniforms draws exactly those numbers from the generator."""
    cfg = compose_config(["experiment=large_action", "n_runs=3", "actor.gibbs_sweeps=4", "actor.init_std=1.0"])
    actor = instantiate(cfg.actor, n_runs=3, n_state=12, n_actions=2**40, seed=0).double()
    R, B = 3, 5
    s = torch.randint(0, 2, (R, B, 12), generator=torch.Generator().manual_seed(1)).double()
    assert actor.uniforms_per_action == 40 + 4 * (13 + 40)
    u = torch.rand(R, B, actor.uniforms_per_action, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    a, *_ = actor.act(s, 2.5, torch.Generator(), u)
    got = to_bits(a, 40).numpy()
    for r in range(R):
        W_sh, W_ah, b_h, b_a = (getattr(actor, n)[r].numpy() for n in ("W_sh", "W_ah", "b_h", "b_a"))
        for b in range(B):
            want = numpy_gibbs_bits(W_sh, W_ah, b_h, b_a, s[r, b].numpy(), 2.5, u[r, b].numpy(), 4)
            np.testing.assert_array_equal(got[r, b], want)
    drawn, *_ = actor.act(s, 2.5, torch.Generator().manual_seed(2))
    assert torch.equal(drawn, a)


def test_gibbs_chunks_compiled_equal_eager(tmp_path):
    """The large-action task with its Gibbs chain inside the compiled chunk (one step a chunk):
    compile=true against compile=false, 3 runs × 48 steps, 3 sweeps: the same actions, so the same
    rewards in every step, TD errors and weights within float32 rounding of the generated kernels."""
    tiny = ["experiment=large_action", "n_runs=3", "trainer.steps=48", "trainer.log_every=16"]
    tiny += ["trainer.checkpoint_every=16", "actor.gibbs_sweeps=3"]
    out = {}
    for name in ("false", "true"):
        torch._dynamo.reset()
        summary = train_job(compose_config([*tiny, f"compile={name}"]), tmp_path / name)
        records = tmp_path / name / "records"
        with np.load(records / "steps.npz") as steps, np.load(records / "weights.npz") as weights:
            out[name] = summary, {**steps, "weights": weights["state_weights_after"]}
    assert out["true"][0]["compile_time_s"] > 0 and out["false"][0]["compile_time_s"] == 0
    np.testing.assert_array_equal(out["true"][1]["rewards"], out["false"][1]["rewards"])
    np.testing.assert_allclose(out["true"][1]["td_errors"], out["false"][1]["td_errors"], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(out["true"][1]["weights"], out["false"][1]["weights"], rtol=1e-4, atol=1e-5)
