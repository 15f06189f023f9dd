"""The training loop of `sgde_plugin.nn.train`: arms, loss, steps, evaluation (~10 s)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sgde_plugin.benchmarks.train_effect import load_sequence
from sgde_plugin.nn import DepthNet
from sgde_plugin.nn.train import (
    SELF_SUPERVISED_ARMS,
    SUPERVISED_ARMS,
    PriorWeight,
    Schedule,
    arm_nets,
    evaluate,
    frame_tensors,
    pooled_abs_rel,
    prior_term,
    supervised_loss,
    train_arm,
)


@pytest.fixture(scope="module")
def seq():
    torch.manual_seed(0)
    return load_sequence([0, 1], (32, 56), seed=3, prior="overlap-noise", render_factor=2)


def test_supervised_loss_against_hand_value():
    gt = torch.zeros(1, 1, 4, 4)
    gt[0, 0, 1, 1], gt[0, 0, 2, 3] = 1.0, 4.0
    out = {("depth", 0): torch.full((1, 1, 4, 4), 2.0), ("depth", 1): torch.full((1, 1, 2, 2), 8.0)}
    # scale 0: |log 2 - log 1|, |log 2 - log 4| -> log 2; scale 1 (upsampled constant 8): log 8 and log 2
    expected = (math.log(2) + (math.log(8) + math.log(2)) / 2) / 2
    assert float(supervised_loss(out, gt, (0, 1))) == pytest.approx(expected, rel=1e-6)


def test_log_prior_term_against_hand_value():
    prior = torch.zeros(1, 1, 4, 4)
    prior[0, 0, 0, 0], prior[0, 0, 3, 3], prior[0, 0, 1, 2] = 5.0, 20.0, 7.0
    valid = prior > 0
    valid[0, 0, 1, 2] = False  # an invalid prior pixel is ignored whatever its value
    out = {("depth", 0): torch.full((1, 1, 4, 4), 10.0)}
    # |log 10 - log 5| = |log 10 - log 20| = log 2, times lambda
    assert float(prior_term(out, prior, valid, (0,), 0.3, "log_l1")) == pytest.approx(0.3 * math.log(2), rel=1e-6)
    # the paper's L1 in metres: mean(5, 10) * lambda
    assert float(prior_term(out, prior, valid, (0,), 0.005, "l1")) == pytest.approx(0.005 * 7.5, rel=1e-6)
    with pytest.raises(ValueError):
        prior_term(out, prior, valid, (0,), 0.3, "l2")


def test_schedule_warms_up_and_decays(seq):
    sched = Schedule(lr=1e-3, warmup=10, clip=0.5)
    assert [sched.factor(i, 100) for i in (0, 4, 9, 50, 74, 75, 99)] == pytest.approx(
        [0.1, 0.5, 1.0, 1.0, 1.0, 0.2, 0.2])
    assert Schedule().factor(0, 10) == 1.0 and Schedule().factor(8, 10) == 0.2  # no warm-up: the old steps
    # Adam's first step moves a parameter by at most its learning rate: lr / warmup, x0.2 (one step is its
    # own last quarter)
    torch.manual_seed(0)
    net = DepthNet(use_prior=False, min_depth=0.5, max_depth=100.0, scales=(0,))
    before = [p.detach().clone() for p in net.parameters()]
    train_arm(net, seq, [0], steps=1, seed=0, prior_weight=None, schedule=Schedule(lr=1e-3, warmup=10, clip=1.0))
    moved = max(float((p.detach() - b).abs().max()) for p, b in zip(net.parameters(), before, strict=True))
    assert moved == pytest.approx(1e-3 * 0.1 * 0.2, rel=1e-2)


def test_prior_weight_warm_up_against_hand_values(seq):
    w = PriorWeight(0.05, start=1.0, steps=100)
    # linear from 1.0 at step 0 to 0.05 at step 100, then constant
    assert [w.at(i) for i in (0, 50, 99, 100, 299)] == pytest.approx([1.0, 0.525, 0.0595, 0.05, 0.05])
    assert PriorWeight(0.2).at(0) == 0.2
    rgb = frame_tensors(seq, [0])[0]

    def one_step(weight):  # one training step of the same net; returns its prediction afterwards
        torch.manual_seed(0)
        net = DepthNet(use_prior=True, validity=True, min_depth=0.5, max_depth=100.0, scales=(0,))
        train_arm(net, seq, [0], steps=1, seed=0, prior_weight=weight, lr=1e-3)
        with torch.no_grad():
            return net.predict(rgb, *frame_tensors(seq, [0])[2:])

    # the first step uses the start weight: 1.0 -> 0 behaves as a constant 1.0 and 0 -> 1.0 as no prior loss
    assert torch.equal(one_step(PriorWeight(0.0, start=1.0, steps=10)), one_step(1.0))
    assert torch.equal(one_step(PriorWeight(1.0, start=0.0, steps=10)), one_step(None))
    assert not torch.equal(one_step(1.0), one_step(None))


def test_arm_nets_share_initial_weights_and_are_independent():
    torch.manual_seed(0)
    init = DepthNet(use_prior=False, scales=(0,)).eval()
    nets = arm_nets(init, SELF_SUPERVISED_ARMS, validity=True, prior_max_depth=80.0, prior_encoding="log")
    assert list(nets) == ["baseline", "+ input", "+ L1", "+ input & L1"]
    assert [n.use_prior for n in nets.values()] == [False, True, False, True]
    assert [n.encoding.form for n in nets.values() if n.use_prior] == ["log", "log"]
    rgb = torch.rand(1, 3, 32, 64)
    with torch.no_grad():
        ref = init.predict(rgb)
        for net in nets.values():  # a zero prior leaves every arm computing what the initial net does
            net.eval()
            zero = torch.zeros(1, 1, 32, 64) if net.use_prior else None
            assert (net.predict(rgb, zero) - ref).abs().max() <= 1e-6
    with torch.no_grad():
        nets["baseline"].decoder.heads["0"].bias.add_(1.0)
    assert not torch.equal(nets["+ L1"].decoder.heads["0"].bias, nets["baseline"].decoder.heads["0"].bias)
    assert [a.prior_weight for a in SUPERVISED_ARMS] == [None, None, 0.005]


def test_evaluate_scores_a_known_prediction(seq):
    class Scaled(torch.nn.Module):
        """Predicts the ground truth times `factor`, frame after frame."""

        use_prior = False

        def __init__(self, factor):
            super().__init__()
            self.factor, self.calls = factor, 0

        def predict(self, rgb, prior=None, valid=None):
            k = self.calls
            self.calls += 1
            return torch.from_numpy(seq.depth[k] * self.factor)[:, None]

    exact = evaluate(Scaled(1.0), seq, [0, 1])
    assert exact["abs_rel"] < 1e-9 and exact["a1"] == 1.0
    assert exact["dep_con"] < 0.03  # only the nearest-pixel rounding of the warp remains
    scaled = evaluate(Scaled(0.9), seq, [0, 1])  # 0.9: no prediction reaches the 80 m cap
    assert scaled["abs_rel"] == pytest.approx(0.1, abs=1e-6)
    assert scaled["abs_rel_overlap"] == pytest.approx(0.1, abs=1e-6)
    assert scaled["abs_rel_outside"] == pytest.approx(0.1, abs=1e-6)
    assert pooled_abs_rel([{"abs_rel": 0.1, "n": 3}, {"abs_rel": 0.3, "n": 1}, {"abs_rel": math.nan, "n": 0}]) == \
        pytest.approx(0.15)


def test_train_arm_lowers_the_training_loss(seq):
    torch.manual_seed(0)
    net = DepthNet(use_prior=True, validity=True, min_depth=0.5, max_depth=100.0, scales=(0, 1))
    from sgde_plugin.nn.train import frame_tensors

    rgb, sup, prior, valid = frame_tensors(seq, [0])

    def loss() -> float:
        with torch.no_grad():
            return float(supervised_loss(net(rgb, prior, valid), sup, net.scales))

    before = loss()
    seconds = train_arm(net, seq, [0], steps=25, seed=0, prior_weight=0.005, lr=1e-3)
    after = loss()
    assert seconds > 0
    assert after < 0.5 * before, (before, after)
    assert np.isfinite(after)


@pytest.fixture(scope="module")
def seq_context():
    return load_sequence([0], (48, 80), seed=1, prior="overlap-noise", render_factor=2, context_s=0.1)


@pytest.mark.parametrize("sources", ["temporal", "spatial", "both"])
def test_self_supervision_is_lowest_at_the_true_depth(seq_context, sources):
    from sgde_plugin.nn.photometric import PhotometricConfig
    from sgde_plugin.nn.train import SelfSupervision

    seq = seq_context
    config = PhotometricConfig(temporal=sources != "spatial", spatial=sources != "temporal", smoothness=0.0)
    loss = SelfSupervision(seq, config)
    rgb = frame_tensors(seq, [0])[0]
    gt = torch.from_numpy(np.where(seq.depth[0] > 0, seq.depth[0], 100.0))[:, None]
    value = {f: float(loss({("depth", 0): gt * f}, 0, rgb, (0,))) for f in (0.7, 1.0, 1.4)}
    # the poses (ego trajectory over time, extrinsics across cameras) are right: the truth explains the views best
    assert value[1.0] < 0.8 * value[0.7] and value[1.0] < 0.8 * value[1.4], value
    assert seq.context_images[0].any() and seq.camera_to_world.shape == (1, 6, 4, 4)
