"""Whole-loop throughput on peg-insertion (insert) at the paper's settings, against a stock-TorchRL loop.

    python benchmarks/bench_loop.py                  # 2 rounds of 2000 steps per loop, about ten minutes on 2 cores
    python benchmarks/bench_loop.py --steps 600 --rounds 1   # a shorter look
    python benchmarks/bench_loop.py --device cuda    # on a GPU: networks, buffers and env output there

Runs, in the same process, in rounds (each loop once per round, in turn; two rounds by default):

1. **ours**: the training recipe itself (``recipes/train.py``'s ``train``) with the paper's
   settings (400-300 networks, forward batch 64, reset batch 256 + 256 examples, K = 5 classifiers
   with priors, n = 10, one update per environment step, the reset trigger checked at every forward
   step), evaluation and checkpoints pushed past the end of the run.
2. **stock**: the same work assembled only from stock TorchRL / tensordict parts: the forward
   agent is torchrl's ``DDPGLoss`` on an MLP actor and a ``DdpgMlpQNet`` critic (the action joins
   after the first layer, as in ours); the reset classifiers are ``DdpgMlpQNet`` members stacked
   with ``TensorDict.from_modules`` and evaluated with ``torch.vmap``, their randomized priors a
   second stack evaluated separately; the RCE label, classifier and actor losses written as the
   method states them; ``TensorDictReplayBuffer``s; torch's default Adam; the trigger evaluated at
   every forward step; the same horizons, heat-up, success check and manual resets.

3. **stock, same products**: the stock loop again with its updates' matrix products run as the
   recipe's ``speed.matmul_precision=auto`` chose for ours (only when that is not plain float32:
   oneDNN's bf16 path, measured as accurate as float32), so that the ratio is also shown for the
   same arithmetic speed. The target is judged on this stricter ratio when it exists.

Both record the mean wall time of a step of each phase once both agents made 10 updates (env step,
policy, trigger, buffer, update). The loops decide their own episode boundaries, so their forward
shares differ a little; the ratio is therefore given at one common mix (ours' forward share):
``time per step = share * forward step + (1 - share) * reset step``, beside the raw steps/s of each
run. From ours' rate it projects the wall time of a 1.5M-step paper run on this machine. Writes
``benchmarks/results/loop-<date>.json`` and ``.md``.
"""
from __future__ import annotations

import argparse
import contextlib
import tempfile
import time
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictParams
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs.utils import step_mdp
from torchrl.modules import MLP, DdpgMlpQNet, OrnsteinUhlenbeckProcessModule, TanhModule, ValueOperator
from torchrl.objectives import DDPGLoss, SoftUpdate

ROOT = Path(__file__).resolve().parents[1]

try:  # imported from the benchmarks package (the tests)
    from .bench_updates import check_device, describe, machine, paper_config, write_results
except ImportError:  # run as a script: python benchmarks/bench_loop.py
    from bench_updates import check_device, describe, machine, paper_config, write_results
from torchrl_reset import accel  # noqa: E402
from torchrl_reset_envs import make_env  # noqa: E402

TASK = "peg_insertion_insert"
PAPER_STEPS = 1_500_000  # environment steps of one run in the paper


def run_ours(steps: int, heat_up: int, seed: int, device: str = "cpu", hidden_sizes=(400, 300)) -> dict:
    from torchrl_reset_recipes import train

    with tempfile.TemporaryDirectory() as run_dir:
        cfg = paper_config("ours", total_steps=steps, heat_up=heat_up, seed=seed, run_dir=run_dir, progress_bar=False,
                           eval_every=10 * steps, checkpoint_every=10 * steps, log_every=steps, device=device,
                           hidden_sizes=list(hidden_sizes))
        summary = train.train(cfg)
    return {"steps": summary["steps"], "seconds": summary["seconds"], "forward_share": summary["forward_share"],
            "matmul_precision": summary["matmul_precision"],
            "step_seconds": summary["step_seconds"], "manual_resets": summary["manual_resets"],
            "triggered_resets": summary["triggered_resets"]}


# ----------------------------------------------------------------------------------- the stock loop
class StockReset:
    """The RCE reset agent from stock parts: vmapped DdpgMlpQNet members, priors evaluated separately."""

    def __init__(self, cfg, obs_dim: int, action_spec, device: str = "cpu"):
        act_dim = action_spec.shape[-1]
        k, (h0, h1) = int(cfg.algo.num_members), tuple(cfg.hidden_sizes)
        self.gamma, self.n, self.beta = float(cfg.gamma), int(cfg.algo.n_steps), float(cfg.algo.prior_scale)
        self.tau = float(cfg.tau)

        def member():
            return DdpgMlpQNet(
                mlp_net_kwargs_net1={"in_features": obs_dim, "out_features": h0, "activation_class": nn.ReLU},
                mlp_net_kwargs_net2={"in_features": h0 + act_dim, "num_cells": [h1], "activation_class": nn.ReLU},
            )

        self.params = TensorDictParams(TensorDict.from_modules(*[member() for _ in range(k)]).data.to(device).clone())
        self.priors = TensorDict.from_modules(*[member() for _ in range(k)]).data.to(device)  # never trained
        self.target = self.params.data.clone()
        self.base = member().to("meta")
        self.actor = stock_actor(obs_dim, action_spec, cfg.hidden_sizes).to(device)
        self.optimizer = torch.optim.Adam([{"params": list(self.actor.parameters()), "lr": cfg.reset.actor_lr},
                                           {"params": list(self.params.values(True, True)), "lr": cfg.reset.critic_lr}])

        def call(params, obs, act):
            with params.to_module(self.base):
                return self.base(obs, act).squeeze(-1)

        self.vmapped = torch.vmap(call, (0, None, None))

    def logits(self, params, obs, act):
        """[N, K] logits: the members, then their priors in a second, separate evaluation."""
        return (self.vmapped(params, obs, act) + self.beta * self.vmapped(self.priors, obs, act)).transpose(0, 1)

    def act(self, obs):
        return self.actor(TensorDict(observation=obs, batch_size=obs.shape[:1]))["action"]

    def success_probability(self, obs, act):
        with torch.no_grad():
            return torch.exp(self.logits(self.params.data, obs, act).clamp(max=0.0))

    def update(self, batch: TensorDict, examples: torch.Tensor) -> None:
        g, gn = self.gamma, self.gamma**self.n
        s, a = batch["observation"], batch["action"]
        with torch.no_grad():
            s1, sn = batch["next", "observation"], batch["nstep", "observation"]
            w1 = torch.exp(self.logits(self.target, s1, self.act(s1)).clamp(max=0.0))
            wn = torch.exp(self.logits(self.target, sn, self.act(sn)).clamp(max=0.0))
            y = (0.5 * (g * w1 / (1 + g * w1) + gn * wn / (1 + gn * wn))).amin(-1).clamp(max=0.5)
            c = (y / (y + g * (1 - y))).clamp(0.0, 0.5)
            weight = 1 + g * c / (1 - c)
            example_action = self.act(examples)
        example_logits = self.logits(self.params, examples, example_action)
        replay_logits = self.logits(self.params, s, a)
        bce = nn.functional.binary_cross_entropy_with_logits
        loss_classifier = ((1 - g) * bce(example_logits, torch.full_like(example_logits, 0.5), reduction="none").mean(0)
                           + bce(replay_logits, y.unsqueeze(-1).expand_as(replay_logits), weight=weight.unsqueeze(-1),
                                 reduction="none").mean(0)).sum()
        loss_actor = -torch.sigmoid(self.logits(self.params.detach(), s, self.act(s))).amin(-1).mean()
        self.optimizer.zero_grad()
        (loss_classifier + loss_actor).backward()
        self.optimizer.step()
        self.target.lerp_(self.params.data, self.tau)


def stock_actor(obs_dim: int, action_spec, hidden_sizes) -> TensorDictSequential:
    net = MLP(in_features=obs_dim, out_features=action_spec.shape[-1], num_cells=list(hidden_sizes), activation_class=nn.ReLU)
    return TensorDictSequential(TensorDictModule(net, in_keys=["observation"], out_keys=["param"]),
                                TanhModule(["param"], ["action"], spec=action_spec))


class NStepWriter:
    """Holds transitions until the state n steps later is known, then writes them with it under ``nstep``."""

    def __init__(self, buffer: TensorDictReplayBuffer, n: int):
        self.buffer, self.n, self.pending = buffer, n, []

    def add(self, transition: TensorDict, episode_over: bool) -> None:
        self.pending.append(transition)
        while self.pending and (len(self.pending) >= self.n or episode_over):
            first = self.pending.pop(0)
            last = self.pending[min(self.n - 1, len(self.pending)) - 1] if self.pending and self.n > 1 else first
            first.set("nstep", last.get("next").select("observation"))
            self.buffer.add(first)


def run_stock(steps: int, heat_up: int, seed: int, update_products: str | None = None, device: str = "cpu",
              hidden_sizes=(400, 300)) -> dict:
    """The stock loop; ``update_products`` runs its updates' matrix products as the recipe's
    ``speed.matmul_precision`` does (``accel.matmul_products``), acting left as it is. On
    ``device`` live the networks, the buffers and the environment's output (as in ours)."""
    products = (lambda: accel.matmul_products(update_products)) if update_products else contextlib.nullcontext
    cfg = paper_config("ours", seed=seed, hidden_sizes=list(hidden_sizes))
    torch.manual_seed(seed)
    env = make_env(TASK, seed=seed, device=device)
    obs_dim, spec = env.observation_spec["observation"].shape[-1], env.action_spec
    h_f, h_r = int(cfg.task.forward_horizon), 2 * int(cfg.task.forward_horizon)
    min_reset, threshold = int(cfg.reset.min_steps), float(cfg.task.p_thresh)

    actor = stock_actor(obs_dim, spec, cfg.hidden_sizes).to(device)
    critic = ValueOperator(DdpgMlpQNet(
        mlp_net_kwargs_net1={"in_features": obs_dim, "out_features": cfg.hidden_sizes[0], "activation_class": nn.ReLU},
        mlp_net_kwargs_net2={"in_features": cfg.hidden_sizes[0] + spec.shape[-1], "num_cells": [cfg.hidden_sizes[1]],
                             "activation_class": nn.ReLU}), in_keys=["observation", "action"]).to(device)
    loss = DDPGLoss(actor, critic, delay_actor=True, delay_value=True)
    loss.make_value_estimator(gamma=cfg.gamma)
    optimizer = torch.optim.Adam([{"params": list(loss.actor_network_params.values(True, True)), "lr": cfg.forward.actor_lr},
                                  {"params": list(loss.value_network_params.values(True, True)), "lr": cfg.forward.critic_lr}])
    targets = SoftUpdate(loss, tau=cfg.tau)
    reset = StockReset(cfg, obs_dim, spec, device)

    def explore(policy):
        return TensorDictSequential(policy, OrnsteinUhlenbeckProcessModule(
            spec=spec.clone(), eps_init=1.0, eps_end=1.0, annealing_num_steps=1, theta=cfg.exploration.theta,
            sigma=cfg.exploration.sigma, dt=cfg.exploration.dt))

    forward_policy, reset_policy = explore(actor), explore(reset.actor)
    forward_rb = TensorDictReplayBuffer(storage=LazyTensorStorage(cfg.forward.buffer_size, device=device),
                                        batch_size=cfg.forward.batch_size)
    reset_rb = TensorDictReplayBuffer(storage=LazyTensorStorage(cfg.reset.buffer_size, device=device),
                                      batch_size=cfg.reset.batch_size)
    example_rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100_000, device=device), batch_size=cfg.reset.batch_size)
    nstep = NStepWriter(reset_rb, int(cfg.algo.n_steps))

    td = env.reset()
    example_rb.add(td.select("observation").clone())
    phase, in_phase = "forward", 0
    counters = {"forward": 0, "reset": 0, "manual_resets": 0, "triggered_resets": 0}
    step_time = {"forward": [0.0, 0], "reset": [0.0, 0]}
    frames, start = 0, time.perf_counter()
    last = start
    while frames < steps:
        td.set("is_init", torch.tensor([in_phase == 0], device=td.device))
        if phase == "forward":
            with torch.no_grad():
                td = forward_policy(td)
            if reset.success_probability(td["observation"][None], td["action"][None]).mean() < threshold:
                counters["triggered_resets"] += 1
                phase, in_phase = "reset", 0
                continue
            td = env.step(td)
            forward_rb.add(td.clone())
            counters["forward"] += 1
            if counters["forward"] > heat_up:
                with products():
                    loss_td = loss(forward_rb.sample())
                    optimizer.zero_grad()
                    (loss_td["loss_actor"] + loss_td["loss_value"]).backward()
                    optimizer.step()
                    targets.step()
            in_phase += 1
            ended = in_phase >= h_f
        else:
            with torch.no_grad():
                td = reset_policy(td)
            td = env.step(td)
            in_phase += 1
            success = bool(td["next", "reset_success"]) and in_phase >= min_reset
            ended = success or in_phase >= h_r
            nstep.add(td.clone(), ended)
            counters["reset"] += 1
            if counters["reset"] > heat_up and len(reset_rb):
                with products():
                    reset.update(reset_rb.sample(), example_rb.sample()["observation"])
        frames += 1
        now = time.perf_counter()
        if min(counters["forward"], counters["reset"]) > heat_up + 10:  # as the recipe: once both made 10 updates
            step_time[phase][0] += now - last
            step_time[phase][1] += 1
        last = now
        td = step_mdp(td)
        if ended:
            if phase == "reset":
                if not success:
                    td = env.reset()
                    counters["manual_resets"] += 1
                example_rb.add(td.select("observation").clone())
            phase, in_phase = ("reset" if phase == "forward" else "forward"), 0
    seconds = time.perf_counter() - start
    env.close()
    return {"steps": frames, "seconds": round(seconds, 1), "forward_share": counters["forward"] / frames,
            "step_seconds": {k: (t / n if n else None) for k, (t, n) in step_time.items()},
            "manual_resets": counters["manual_resets"], "triggered_resets": counters["triggered_resets"]}


def merge_rounds(runs: list[dict]) -> dict:
    """One loop's rounds as one record: steps and seconds added, step times the mean over rounds
    (the loops are seeded, so every round makes the same steps)."""
    merged = dict(runs[0])
    merged["rounds"] = len(runs)
    merged["steps"] = sum(r["steps"] for r in runs)
    merged["seconds"] = round(sum(r["seconds"] for r in runs), 1)
    times = [r["step_seconds"] for r in runs]
    merged["step_seconds"] = {k: (None if any(t[k] is None for t in times) else sum(t[k] for t in times) / len(times))
                              for k in times[0]}
    merged["step_seconds_per_round"] = times
    return merged


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=2000, help="environment steps per loop")
    parser.add_argument("--heat-up", type=int, default=300, help="steps per agent before its updates start")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rounds", type=int, default=2, help="times each loop runs, in turn with the others")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:N]: where networks, buffers and env output live")
    parser.add_argument("--hidden-sizes", type=int, nargs=2, default=[400, 300], metavar=("H0", "H1"),
                        help="both agents' hidden layers (default: the paper's 400 300; smaller for a quick check)")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = parser.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(args.threads)

    on_cpu = torch.device(device).type == "cpu"
    precision = accel.choose_matmul_precision(paper_config("ours").speed.matmul_precision) if on_cpu else "ieee"
    sizes = tuple(args.hidden_sizes)
    loops = {"ours": lambda *a: run_ours(*a, device=device, hidden_sizes=sizes),
             "stock": lambda *a: run_stock(*a, device=device, hidden_sizes=sizes)}
    if precision != "ieee":
        loops[f"stock, {precision} products"] = lambda *a: run_stock(*a, update_products=precision, device=device,
                                                                     hidden_sizes=sizes)
    # rounds of all loops in turn: a slow spell of a shared machine then weighs on every loop alike
    runs = {name: [] for name in loops}
    for round_ in range(args.rounds):
        for name, run in loops.items():
            print(f"round {round_ + 1}/{args.rounds}: {name} ({args.steps} steps)...", flush=True)
            runs[name].append(run(args.steps, args.heat_up, args.seed))
            torch.set_num_threads(args.threads)
    results = {name: merge_rounds(r) for name, r in runs.items()}
    assert results["ours"]["matmul_precision"] == precision
    share = results["ours"]["forward_share"]
    for name, r in results.items():
        if None in r["step_seconds"].values():
            raise SystemExit(f"{name}: too few steps for both agents to make 10 timed updates; raise --steps or lower --heat-up.")

    def per_step(r):
        f, s = r["step_seconds"]["forward"], r["step_seconds"]["reset"]
        return share * f + (1 - share) * s

    for r in results.values():
        r["raw_steps_per_second"] = r["steps"] / r["seconds"]
        r["steps_per_second_at_common_mix"] = 1.0 / per_step(r)
    ours_rate = results["ours"]["steps_per_second_at_common_mix"]
    ratios = {name: ours_rate / r["steps_per_second_at_common_mix"] for name, r in results.items() if name != "ours"}
    judged = list(ratios)[-1]  # the same products where that run exists
    ratio = ratios[judged]
    # a paper run: PAPER_STEPS steps, nearly all of them with their agent updating (its heat-up is
    # 1000 steps per agent), at the measured mean time of an updating step at the common mix
    projected_hours = PAPER_STEPS / ours_rate / 3600
    report = {"machine": machine(device), "task": TASK, "steps": args.steps, "heat_up": args.heat_up,
              "hidden_sizes": list(sizes), "common_forward_share": share,
              "matmul_precision": precision, "loops": results, "ratios": ratios, "ratio": ratio, "judged_against": judged,
              "target": "ratio >= 1.5", "met": ratio >= 1.5, "projected_paper_run_hours": projected_hours}
    if not on_cpu:
        report["gpu_target"] = "projected paper run < 30 minutes"
        report["gpu_target_met"] = projected_hours < 0.5

    lines = [f"# Whole-loop throughput, {TASK}, paper settings ({report['machine']['date']})", "",
             describe(report["machine"], args.threads) + f" {args.steps} steps per loop and round, "
             f"{args.rounds} rounds of all loops in turn, updates after {args.heat_up} steps per agent; step times are "
             "means over the rounds.", "",
             "| loop | raw steps/s | forward share | forward step (ms) | reset step (ms) | steps/s at a common mix |",
             "|---|---|---|---|---|---|"]
    for name, r in results.items():
        lines.append(f"| {name} | {r['raw_steps_per_second']:.1f} | {r['forward_share']:.3f} | "
                     f"{1000 * r['step_seconds']['forward']:.1f} | {1000 * r['step_seconds']['reset']:.1f} | "
                     f"{r['steps_per_second_at_common_mix']:.1f} |")
    lines += ["", f"Common mix: forward share {share:.3f}. Ours' matrix products: {precision}. Ratios: "
              + "; ".join(f"ours / {name}: {r:.2f}x" for name, r in ratios.items())
              + f". Against {judged}: **{ratio:.2f}x** (target >= 1.5x: {'met' if ratio >= 1.5 else 'NOT met'}).",
              "", f"Projected wall time of a {PAPER_STEPS:,}-step paper run with ours on this machine ({device}): "
              f"**{projected_hours:.1f} h** ({PAPER_STEPS:,} steps at {ours_rate:.1f} steps/s, evaluations not counted)"
              + (f"; GPU target < 30 minutes: {'met' if projected_hours < 0.5 else 'NOT met'}." if not on_cpu else ".")]
    write_results(args.out, "loop", report, "\n".join(lines) + "\n")
    return report


if __name__ == "__main__":
    main()
