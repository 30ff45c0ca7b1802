"""The accelerator against the reference path, and RCELoss on a classifier built from stock parts.

The reference classes (``EnsembleValueOperator``, ``RCELoss``, torchrl's ``DDPGLoss`` and ``SoftUpdate``)
and the accelerator's (``torchrl_reset.accel``) are built from the same seed and trained side by
side on the same batches, in float32 as the recipes run: losses, gradients, parameters and target
parameters must agree after every update. Not bitwise: the accelerator sums the same products in
another order (fused bias, row blocks, dot products for the one-wide layer, one stack of 2K members
without gradients), so results differ by float32 rounding (about 1e-7 relative per product),
which Adam's normalisation can lift to about ``lr`` times that in the parameters.
"""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict, TensorDictParams
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torch.func import functional_call
from torchrl.data import Bounded
from torchrl.modules import MLP, TanhModule
from torchrl.objectives import SoftUpdate

from torchrl_reset import EnsembleValueOperator, RCELoss, accel

OBS, ACT, BATCH, GAMMA, N_STEPS = 4, 2, 64, 0.99, 4
RTOL, ATOL = 2e-5, 2e-6


def actor_of(parts: accel.Components) -> nn.Module:
    net = nn.Sequential(nn.Linear(OBS, 32), nn.ReLU(), nn.Linear(32, ACT))
    from tensordict.nn import TensorDictSequential

    return TensorDictSequential(
        parts.tensor_module(net, "observation", "action_preactivation"),
        TanhModule(["action_preactivation"], ["action"], spec=Bounded(-1.0, 1.0, shape=(ACT,))),
    )


def build(parts: accel.Components, kind: str, seed: int = 0):
    """An agent's loss, optimizer and target updater, as the recipes build them (small networks)."""
    torch.manual_seed(seed)
    actor = actor_of(parts)
    if kind == "rce":
        model = parts.ensemble(OBS, ACT, num_members=3, hidden_sizes=(32, 24), prior_scale=3.0)
        loss = parts.rce_loss(actor, model, gamma=GAMMA, n_steps=N_STEPS)
    else:  # the forward agent's critic (one member) or LNT's Q ensemble (several, one TD target each)
        members = 1 if kind == "ddpg" else 3
        model = parts.ensemble(OBS, ACT, num_members=members, hidden_sizes=(32, 24), prior_scale=0.0,
                               out_keys=["state_action_value"])
        loss = parts.ddpg_loss(actor, model, delay_actor=True, delay_value=True)
        loss.make_value_estimator(gamma=GAMMA)
    params = [p for p in loss.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=1e-3)
    return loss, optimizer, parts.soft_update(loss, tau=0.05)


def batch_for(kind: str, gen: torch.Generator) -> TensorDict:
    state = lambda: TensorDict(observation=torch.randn(BATCH, OBS, generator=gen), batch_size=[BATCH])  # noqa: E731
    batch = TensorDict(observation=torch.randn(BATCH, OBS, generator=gen),
                       action=torch.rand(BATCH, ACT, generator=gen) * 2 - 1, next=state(), batch_size=[BATCH])
    if kind == "rce":
        batch["nstep"], batch["example"] = state(), state()
        pool = torch.randn(10, OBS, generator=gen)
        slots = torch.randint(10, (BATCH,), generator=gen)
        batch["example"] = TensorDict(observation=pool[slots], index=slots, batch_size=[BATCH])
    else:
        columns = 1 if kind == "ddpg" else 3
        nxt = batch["next"]
        nxt["reward"] = torch.randn(BATCH, 1, generator=gen).expand(BATCH, columns).clone()
        done = torch.rand(BATCH, 1, generator=gen) < 0.1
        nxt["done"] = nxt["terminated"] = done.expand(BATCH, columns).clone()
    return batch


@pytest.mark.parametrize("kind", ["rce", "ddpg", "lnt"])
def test_accelerator_and_reference_agree_in_losses_gradients_and_parameters_over_updates(kind):
    fast, plain = build(accel.components(True), kind), build(accel.components(False), kind)
    # the RCE loss and every ensemble differ between the paths; the DDPG agents use torchrl's DDPGLoss on both
    assert type(fast[0].value_network if kind != "rce" else fast[0]) is not type(plain[0].value_network if kind != "rce" else plain[0])
    names = ("loss_actor", "loss_classifier") if kind == "rce" else ("loss_actor", "loss_value")
    for (name, a), b in zip(fast[0].named_parameters(), plain[0].parameters()):
        assert torch.equal(a, b), name  # the same start
    gen = torch.Generator().manual_seed(1)
    for _ in range(5):
        batch = batch_for(kind, gen)
        steps = []
        for loss, optimizer, targets in (fast, plain):
            out = loss(batch.clone())
            optimizer.zero_grad()
            sum(out[n] for n in names).backward()
            steps.append((out, [None if p.grad is None else p.grad.clone() for p in loss.parameters()]))
            optimizer.step()
            targets.step()
        (out_fast, grads_fast), (out_plain, grads_plain) = steps
        for n in names:
            torch.testing.assert_close(out_fast[n], out_plain[n], rtol=RTOL, atol=ATOL, msg=n)
        for g_fast, g_plain in zip(grads_fast, grads_plain):
            assert (g_fast is None) == (g_plain is None)
            if g_fast is not None:
                torch.testing.assert_close(g_fast, g_plain, rtol=1e-4, atol=1e-6)
        for (name, a), b in zip(fast[0].named_parameters(), plain[0].parameters()):
            torch.testing.assert_close(a, b, rtol=RTOL, atol=ATOL, msg=name)
        for (name, a), b in zip(fast[0].named_buffers(), plain[0].buffers()):  # target copies and priors
            torch.testing.assert_close(a, b, rtol=RTOL, atol=ATOL, msg=name)


def test_a_checkpoint_of_either_path_loads_into_the_other():
    fast = accel.FastEnsembleValueOperator(OBS, ACT, num_members=3, hidden_sizes=(8, 8))
    plain = EnsembleValueOperator(OBS, ACT, num_members=3, hidden_sizes=(8, 8))
    plain.load_state_dict(fast.state_dict())
    obs, act = torch.randn(5, OBS), torch.rand(5, ACT)
    torch.testing.assert_close(plain.logits(obs, act), fast.logits(obs, act), rtol=1e-5, atol=1e-6)


def test_the_switch_gives_the_reference_or_the_fast_classes():
    on, off = accel.components(True), accel.components(False)
    assert (off.ensemble, off.rce_loss) == (EnsembleValueOperator, RCELoss) and off.soft_update is SoftUpdate
    assert issubclass(on.ensemble, EnsembleValueOperator) and issubclass(on.rce_loss, RCELoss)
    assert isinstance(on.tensor_module(nn.Identity(), "a", "b"), accel.TensorModule)
    assert isinstance(off.tensor_module(nn.Identity(), "a", "b"), TensorDictModule)


# --- RCELoss on a classifier ensemble built from stock torchrl / tensordict parts ----------------------


class StockEnsemble(TensorDictModuleBase):
    """K torchrl MLPs stacked with ``TensorDict.from_modules`` and run with ``torch.vmap``, each plus
    beta times its own frozen prior network; writes ``[B, K]`` logits as RCELoss's contract asks."""

    in_keys, out_keys = ["observation", "action"], ["state_action_logit"]

    def __init__(self, members: int, beta: float = 3.0):
        super().__init__()
        make = lambda: MLP(in_features=OBS + ACT, out_features=1, num_cells=[16, 16])  # noqa: E731
        self.trained = TensorDict.from_modules(*[make() for _ in range(members)], as_module=True)
        self.priors = TensorDictParams(TensorDict.from_modules(*[make() for _ in range(members)]).detach().clone(),
                                       no_convert=True)  # buffers: never trained
        self.__dict__["net"] = make().to("meta")  # the layout only, not a submodule
        self.beta = beta

    def forward(self, td):
        x = torch.cat([td["observation"], td["action"]], -1)

        def member(f, g):
            with f.to_module(self.net):
                out = self.net(x)
            with g.to_module(self.net):
                prior = self.net(x)
            return out + self.beta * prior

        return td.set("state_action_logit", torch.vmap(member)(self.trained, self.priors).squeeze(-1).movedim(0, -1))


def by_hand(actor, ensemble, target, batch, k):
    """RCE losses member by member with torch.func.functional_call (docs/method.md section 3, the release's label)."""
    def logit(params, i, obs, act):
        x = torch.cat([obs, act], -1)
        f = functional_call(ensemble.net, {".".join(key): v[i] for key, v in params["trained"].items(True, True)}, (x,))
        g = functional_call(ensemble.net, {".".join(key): v[i] for key, v in params["priors"].items(True, True)}, (x,))
        return (f + 3.0 * g).squeeze(-1)

    live = TensorDict.from_module(ensemble)
    s, a = batch["observation"], batch["action"]
    s1, sn, se = batch["next", "observation"], batch["nstep", "observation"], batch["example", "observation"]
    act = lambda obs: actor(TensorDict(observation=obs, batch_size=[len(obs)]))["action"]  # noqa: E731
    with torch.no_grad():
        c1 = torch.stack([torch.sigmoid(logit(target, i, s1, act(s1))) for i in range(k)], -1)
        cn = torch.stack([torch.sigmoid(logit(target, i, sn, act(sn))) for i in range(k)], -1)
        g, gn = GAMMA, GAMMA**N_STEPS
        y = (0.5 * (g * c1 / (1 + (g - 1) * c1) + gn * cn / (1 + (gn - 1) * cn))).min(-1).values.clamp(max=0.5)
        c_y = (y / (y + g * (1 - y))).clamp(0, 0.5)
        weight = 1 + g * c_y / (1 - c_y)
        ae = act(se)
    loss = 0.0
    for i in range(k):
        ce = torch.nn.functional.binary_cross_entropy_with_logits
        loss = loss + (1 - g) * ce(logit(live, i, se, ae), torch.full((BATCH,), 0.5)) \
            + (weight * ce(logit(live, i, s, a), y, reduction="none")).mean()
    pi = act(s)
    actor_loss = -torch.stack([torch.sigmoid(logit(live.detach(), i, s, pi)) for i in range(k)], -1).min(-1).values.mean()
    return loss, actor_loss


def test_rce_loss_trains_a_stock_built_ensemble_with_priors_through_its_keys():
    torch.manual_seed(0)
    actor = TensorDictModule(nn.Sequential(nn.Linear(OBS, ACT), nn.Tanh()), in_keys=["observation"], out_keys=["action"])
    ensemble = StockEnsemble(4)
    loss = RCELoss(actor, ensemble, gamma=GAMMA, n_steps=N_STEPS)
    trained = [p for p in loss.parameters() if p.requires_grad]
    assert len(trained) == 2 + 6  # the actor's weight and bias; three stacked layers of the trained members
    optimizer, updater = torch.optim.Adam(trained, lr=1e-2), SoftUpdate(loss, tau=0.1)
    priors = ensemble.priors.clone()
    gen = torch.Generator().manual_seed(2)
    for _ in range(3):
        batch = batch_for("rce", gen)
        out = loss(batch)
        target = loss.target_classifier_network_params
        expected_classifier, expected_actor = by_hand(actor, ensemble, target, batch, 4)
        torch.testing.assert_close(out["loss_classifier"], expected_classifier, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(out["loss_actor"], expected_actor, rtol=1e-5, atol=1e-6)
        optimizer.zero_grad()
        out["loss_actor"].backward(retain_graph=True)
        # the actor loss reaches only the actor
        assert all(p.grad is None or not p.grad.any() for p in ensemble.trained.values(True, True))
        assert all(p.grad is not None and p.grad.any() for p in actor.parameters())
        out["loss_classifier"].backward()
        optimizer.step()
        updater.step()
    assert (ensemble.priors == priors).all()  # never trained
    assert not (loss.target_classifier_network_params["trained"] == ensemble.trained.data).all()


def test_keys_follow_the_classifier_and_are_never_overwritten_silently():
    actor = TensorDictModule(nn.Linear(OBS, ACT), in_keys=["observation"], out_keys=["action"])
    classifier = EnsembleValueOperator(OBS, ACT, num_members=2, hidden_sizes=(8, 8), out_keys=["logit"])
    loss = RCELoss(actor, classifier)
    assert loss.tensor_keys.state_action_logit == "logit"  # the classifier's one out_key
    with pytest.raises(ValueError, match="classifier writes"):
        loss.set_keys(state_action_logit="state_action_logit")
    with pytest.raises(ValueError, match="actor must write"):
        loss.set_keys(action="other_action")
    assert (loss.tensor_keys.state_action_logit, loss.tensor_keys.action) == ("logit", "action")  # left as they were
    with pytest.raises(TypeError, match="tensordict module"):
        RCELoss(actor, nn.Linear(3, 1))
