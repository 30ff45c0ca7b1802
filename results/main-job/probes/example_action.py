"""Frozen: its question is decided. It last ran at commit 271779f, as results/quick-ball-in-cup/probes/example_action.py; to run it there:
``git worktree add ../frozen 271779f && cd ../frozen && python results/quick-ball-in-cup/probes/example_action.py --help``.

Does Eq. 2's example action, the actor's own pi(s*), teach the classifiers their early slope toward a corner?

    python results/main-job/probes/example_action.py --seeds 1 0 --steps 750 --updates 500

The candidate (README, "What pushes them there"): Eq. 2 labels ``(s*, pi(s*))`` a success with the actor's
current, noiseless action, while every replay row carries a noisy one; so early on "an action like the
policy's own" is what tells the two classes apart, the classifiers' slope in the action points the way the
policy already leans, and the actor, climbing it, leans further. The test changes only that action.

For each seed: the main job's settings (``preset=quick task=ball_in_cup_catch``, one torch thread, the
reference loss ``speed.accelerate=false``) run to ``--steps`` steps and are checkpointed (the reset agent has
made its first updates; its actor has not moved far yet). From that checkpoint, five copies of the reset
agent take ``--updates`` more updates with the recipe's update (``updates.update``, the release's order) on
the same batches (the same sampler stream), differing only in the example term's action (or, in the
last, in the replay term's):

- ``pi(s*)``: the recipe (Eq. 2);
- ``pi(s*) + replay noise``: plus the noise a replay row carries (``a_t - pi(s_t)`` of a random row, drawn
  from a generator of its own), so examples look like replay rows in their action;
- ``uniform``: an action drawn uniformly from the action box;
- ``replay actions shuffled``: the example term as in the recipe, but each replay row's action ``a_t``
  in Eq. 2's replay term taken from another row of its batch (its label, from ``s_{t+1}`` and the
  target classifiers, unchanged): what the classifiers can learn of an action's effect from the replay
  is gone, and what is left comes from the examples and the labels;
- ``uniform and shuffled``: both, so that neither term tells the classifiers anything about the action.

Every ``--every`` updates, on the newest 500 reset states: the actor's noiseless mean action, the share of
action entries beyond 0.9 and of tanh inputs beyond +-3; at the success examples with the actor's action:
the share of action entries where the trained part's slope (ensemble mean of d f_i / d a) points the way the
action leans (``sign(a) * df/da > 0``), and the slope's mean size.
"""
from __future__ import annotations

import argparse
import tempfile
import types
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[3]
from torchrl_reset_recipes import train
from torchrl_reset_recipes.training.run_spec import run_spec
from torchrl_reset_recipes.training.single_run import build_run
from torchrl_reset_recipes.training.updates import update

VARIANTS = ("pi(s*)", "pi(s*) + replay noise", "uniform", "replay actions shuffled", "uniform and shuffled")


def config(seed: int, run_dir: Path, steps: int, *extra: str):
    with initialize_config_dir(config_dir=str(ROOT / "recipes" / "conf"), version_base="1.3"):
        return compose("config", overrides=[
            "preset=quick", "task=ball_in_cup_catch", "algo=ours", f"seed={seed}", "threads=1", "progress_bar=false",
            "speed.accelerate=false", f"total_steps={steps}", f"checkpoint_every={steps}", f"run_dir={run_dir}", *extra])


def patch_example_action(loss, variant: str, replay_noise, generator: torch.Generator) -> None:
    """Makes ``loss`` use ``variant``'s action in Eq. 2's example term (and only there)."""
    if variant == VARIANTS[0]:
        return
    terms = type(loss)._classifier_terms

    def classifier_terms(self, replay, states, action, examples):
        if variant in VARIANTS[3:]:  # each row's a_t from another row of the batch; the labels are untouched
            action = action[torch.randperm(action.shape[0], generator=generator)]
        if variant == VARIANTS[3]:
            return terms(self, replay, states, action, examples)
        act = self._act

        def example_aware(td):
            a = act(td)
            if td is not examples:
                return a
            if variant == VARIANTS[1]:
                rows = torch.randint(len(replay_noise), (a.shape[0],), generator=generator)
                return a + replay_noise[rows].to(a.dtype)
            return torch.rand(a.shape, generator=generator, dtype=a.dtype) * 2 - 1  # uniform (with or without shuffling)

        self._act = example_aware
        try:
            return terms(self, replay, states, action, examples)
        finally:
            del self._act

    loss._classifier_terms = types.MethodType(classifier_terms, loss)


def measure(run) -> dict:
    agent, model = run.reset, run.reset.model
    states = run.reset_rb[:][-500:].select("observation")
    with torch.no_grad():
        acted = agent.actor(states.clone())
    action, pre = acted["action"], acted["action_preactivation"]
    examples = run.collector.example_buffer.states().select("observation")
    with torch.no_grad():
        a_star = agent.actor(examples.clone())["action"]
    a_star = a_star.detach().requires_grad_(True)
    f = model.members_forward(examples["observation"].float(), a_star,
                              *model.layer_tensors(agent.loss.classifier_network_params))  # [K, N]
    slope = torch.autograd.grad(f.mean(0).sum(), a_star)[0]
    leans = (torch.sign(a_star.detach()) * slope) > 0
    return {"mean action": ", ".join(f"{v:+.2f}" for v in action.mean(0).tolist()),
            "|a| > 0.9": f"{100 * (action.abs() > 0.9).float().mean():.0f}%",
            "tanh input beyond 3": f"{100 * (pre.abs() > 3).float().mean():.0f}%",
            "slope with the lean at s*": f"{100 * leans.float().mean():.0f}%",
            "|df/da| at s*": f"{slope.abs().mean():.2f}"}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 0])
    parser.add_argument("--steps", type=int, default=750)
    parser.add_argument("--updates", type=int, default=500)
    parser.add_argument("--every", type=int, default=125)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    for seed in args.seeds:
        folder = Path(tempfile.mkdtemp(prefix=f"example_action_seed{seed}_"))
        train.train(config(seed, folder, args.steps))
        print(f"\nseed {seed}, from its checkpoint at {args.steps} steps, {args.updates} more reset updates\n")
        header = None
        for variant in VARIANTS:
            run = build_run(run_spec(config(seed, folder, args.steps, "resume=true"), check=False), "ieee")
            try:
                rows = run.reset_rb[:]
                with torch.no_grad():
                    noise = rows["action"] - run.reset.actor(rows.select("observation").clone())["action"]
                patch_example_action(run.reset.loss, variant, noise, torch.Generator().manual_seed(seed))
                torch.manual_seed(1000 + seed)  # the same batches for every variant
                for u in range(args.updates + 1):
                    if u % args.every == 0:
                        row = {"variant": variant, "updates": u, **measure(run)}
                        if header is None:
                            header = list(row)
                            print("| " + " | ".join(header) + " |\n|" + "---|" * len(header))
                        print("| " + " | ".join(str(v) for v in row.values()) + " |", flush=True)
                    if u < args.updates:
                        update(run.reset, run.learner.sample("reset"), run.reset.loss, release_order=True)
            finally:
                run.collector.shutdown()
                run.eval_env.close()


if __name__ == "__main__":
    main()
