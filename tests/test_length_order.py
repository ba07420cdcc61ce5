"""Algorithm 1's predictor phase with the lengths in order (``trainer.length_order=by_length``,
docs/readings.md): each epoch's orders hold only the sequences of its stage's length, each one
L_training times (as many SGD steps as a mixed epoch); the stages follow T_min, T_min + 1, … with
N_epoch / L_training epochs each; the default (mixed) is a permutation of every sequence."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from conftest import TINY_ALGORITHM1, compose_config, eager, train_job
from ferl.trainers.predictor_training import TrainPredictors


def job(t_min: int) -> SimpleNamespace:
    return SimpleNamespace(
        generator=torch.Generator().manual_seed(0), device=torch.device("cpu"), env=SimpleNamespace(optimal_steps=t_min)
    )


def phase(order: str, l_training: int, n_epoch: int) -> TrainPredictors:
    return TrainPredictors(l_training, n_epoch, error_every=1, checkpoint_every_epochs=1, length_order=order)


@pytest.mark.parametrize("n_epoch,l_training", [(7, 3), (400, 5), (3, 3)])
def test_by_length_orders_each_epoch_on_its_stages_length(n_epoch, l_training):
    t_min, per_length, R = 3, 4, 2
    # balanced data: every run holds the same lengths in the same places (here interleaved)
    lengths = torch.arange(t_min, t_min + l_training).repeat(per_length).expand(R, -1)
    p, j = phase("by_length", l_training, n_epoch), job(t_min)
    stages = []
    for epoch in range(1, n_epoch + 1):
        orders = p.epoch_orders(j, lengths, 2, epoch)
        assert len(orders) == 2 and all(o.shape == lengths.shape for o in orders)
        (T,) = set(lengths.gather(1, orders[0]).flatten().tolist())
        for o in orders:
            assert (lengths.gather(1, o) == T).all()
            for run in range(R):  # every sequence of length T, each L_training times
                counts = np.bincount(o[run].numpy(), minlength=lengths.shape[1])
                np.testing.assert_array_equal(counts, np.where(lengths[run].numpy() == T, l_training, 0))
        stages.append(T)
    # the lengths in order, each a whole block of epochs, as even as n_epoch allows
    assert stages == sorted(stages) and set(stages) == set(range(t_min, t_min + l_training))
    blocks = np.bincount(np.asarray(stages) - t_min)
    assert blocks.sum() == n_epoch and blocks.max() - blocks.min() <= 1


def test_mixed_orders_are_permutations_of_every_sequence():
    lengths = torch.arange(3, 8).repeat(4).expand(2, -1)
    orders = phase("mixed", 5, 10).epoch_orders(job(3), lengths, 3, 1)
    for o in orders:
        for run in range(2):
            assert sorted(o[run].tolist()) == list(range(20))


def test_a_run_with_the_lengths_in_order_trains_and_lowers_the_error(tmp_path):
    """table4_1_regular at a tiny scale, by_length: the run ends, and the training error at the end
    of each stage is lower at the stage's length than it was before the stage began."""
    cfg = compose_config(
        eager(["experiment=table4_1_regular", "n_runs=2", *TINY_ALGORITHM1, "trainer.n_epoch=10"])
        + ["trainer.length_order=by_length"]
    )
    train_job(cfg, tmp_path / "run")
    with np.load(tmp_path / "run" / "records" / "predictor.npz") as rec:
        name = next(k[: -len("_lengths")] for k in rec.files if k.endswith("_lengths"))
        error = np.nanmean(rec[f"{name}_error_train"], axis=(0, 3))  # (epochs recorded, lengths)
        epochs, lengths = rec[f"{name}_epochs"], rec[f"{name}_lengths"]
    for stage in range(5):  # 2 epochs a stage: epochs 2s + 1, 2s + 2 train length T_min + s
        before, after = list(epochs).index(2 * stage), list(epochs).index(2 * stage + 2)
        T = list(lengths).index(lengths[0] + stage)
        assert error[after, T] < error[before, T], (stage, error[:, T])
