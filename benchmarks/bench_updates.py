"""Update speed at the paper's sizes, against the FLOP limit of this machine, and how it scales.

    python benchmarks/bench_updates.py                 # paper sizes + scaling, about two minutes on 2 cores
    python benchmarks/bench_updates.py --quick         # fewer repetitions
    python benchmarks/bench_updates.py --no-compile    # without the torch.compile row (half a minute less)
    python benchmarks/bench_updates.py --device cuda   # on a GPU: networks and batches there, timings synchronized

Measures, in one run:
1. the machine's matrix-multiply rate (float32, 1024 x 1024 products, the best of several runs),
   with plain float32 products and, where the recipe's ``speed.matmul_precision=auto`` picks it,
   with oneDNN's bf16 path;
2. in three rounds of all of them in turn (a slow spell of a shared machine then weighs on every
   row alike), one whole update, as the training recipe runs it, with its speed settings (fused Adam, freed
   memory kept, the matrix-product precision ``auto`` chose; the RCE update also with plain
   float32 products): the replay sample from the recipe's buffers (and the success-example sample),
   the loss, backward, the optimizer step and the target update, for the forward DDPG agent
   (batch 64, torchrl's ``DDPGLoss``; eager, the recipe's default, and through ``torch.compile``), the RCE reset agent
   (K = 5, batch 256 + 256 examples, n = 10, priors) and the LNT reset agent (K = 20, batch 256), each
   also on the plain reference path (``speed.accelerate=false``) for the accelerator's gain,
   with the networks of the paper (400-300) on peg-insertion's sizes (14 observations, 7 actions).
   Beside each: its FLOPs (counted with ``torch.utils.flop_counter``'s formulas while it runs),
   the time those FLOPs take at the measured rate, and the fraction of that limit reached;
3. the RCE reset update for K = 1, 5, 10, 20 and batch 64, 256, 1024.

Prints a table and writes ``benchmarks/results/updates-<date>.json`` and ``.md`` with the machine,
the versions and the date. Compares against the targets of the speed issue: reset update <= 35 ms
and <= 2x its FLOP-limit time, forward update <= 3 ms, K = 20 < 4x K = 5.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

import torch
from tensordict import TensorDict
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import flop_registry

ROOT = Path(__file__).resolve().parents[1]

import torchrl  # noqa: E402
from torchrl_reset_recipes.training.hydra_config import compose
from torchrl_reset_recipes.training.agents import make_forward_agent, make_reset_agent
from torchrl_reset_recipes.training.run_spec import run_spec
from torchrl_reset_recipes.training.reset_agents import lnt_batch
from torchrl_reset_recipes.training.buffers import make_buffers
from torchrl_reset_recipes.training.run_folder import processor_name
from torchrl_reset import accel  # noqa: E402

OBS, ACT = 14, 7  # peg-insertion


def paper_config(algo: str, **overrides):
    return compose(["task=peg_insertion_insert", f"algo={algo}", "preset=paper",
                    *[f"{k}={v}" for k, v in overrides.items()]])


def action_spec():
    from torchrl.data import Bounded

    return Bounded(-2.0, 2.0, shape=(ACT,))


def state(batch: int) -> TensorDict:
    return TensorDict(observation=torch.randn(batch, OBS), batch_size=[batch])


def forward_batch(batch: int) -> TensorDict:
    return TensorDict(
        observation=torch.randn(batch, OBS), action=torch.rand(batch, ACT) * 4 - 2,
        next=TensorDict(observation=torch.randn(batch, OBS), reward=torch.rand(batch, 1),
                        done=torch.zeros(batch, 1, dtype=torch.bool), terminated=torch.zeros(batch, 1, dtype=torch.bool),
                        batch_size=[batch]),
        batch_size=[batch],
    )


def filled_buffers(cfg, transitions: int = 5000):
    """The recipe's replay buffers (n-step transform included) and example buffer, filled with random data."""
    from torchrl_reset import InitialStateBuffer

    forward_rb, reset_rb = make_buffers(run_spec(cfg, check=False))
    episode = int(cfg.task.forward_horizon)
    data = forward_batch(transitions)
    data.set(("collector", "traj_ids"), torch.arange(transitions) // episode)
    data.set(("next", "reset_reward"), torch.rand(transitions, 1))
    data.set(("next", "reset_success"), torch.rand(transitions, 1) > 0.5)
    forward_rb.extend(data.clone())
    reset_rb.extend(data)
    examples = InitialStateBuffer()
    for _ in range(100):
        examples.add(state(1)[0])
    return forward_rb, reset_rb, examples


def make_update(kind: str, *, members: int | None = None, batch: int | None = None, compiled: bool | None = None,
                device: str = "cpu", accelerate: bool = True):
    """A closure running one whole update of ``kind`` (forward, ours, lnt) as the recipe runs it.

    Everything one step of that agent costs: the replay sample (and the success-example sample),
    moved to ``device`` as the recipe moves it, the loss, backward, the optimizer step and the
    target update. ``compiled`` overrides the recipe's ``speed.compile`` choice for this agent.
    ``accelerate=False`` builds the agent as ``speed.accelerate=false``
    does: the plain reference classes and torch's default Adam.
    """
    overrides = {"device": device} if members is None else {"algo.num_members": members, "device": device}
    overrides["speed.accelerate"] = accelerate
    for key, size in (("forward.batch_size", batch if kind == "forward" else None),
                      ("reset.batch_size", batch if kind != "forward" else None)):
        if size is not None:
            overrides[key] = size
    cfg = paper_config("ours" if kind == "forward" else kind, **overrides)
    forward_rb, reset_rb, examples = filled_buffers(cfg)
    if kind == "forward":
        agent = make_forward_agent(run_spec(cfg, check=False), OBS, action_spec())
        names = ("loss_actor", "loss_value")
    else:
        agent = make_reset_agent(run_spec(cfg, check=False), OBS, action_spec())
        names = ("loss_actor", "loss_classifier") if kind == "ours" else ("loss_actor", "loss_value")
    agent.loss.to(device)  # as the recipe does
    agent.actor.to(device)  # the loss moves its own copies of the networks' buffers, not theirs (tanh bounds, priors)
    agent.model.to(device)
    agent_name = "forward" if kind == "forward" else "reset"
    use_compile = agent_name in set(cfg.speed.compile) if compiled is None else compiled
    loss = torch.compile(agent.loss) if use_compile else agent.loss

    def sample():
        if kind == "forward":
            return forward_rb.sample().to(device)
        td = reset_rb.sample().to(device)
        if kind == "ours":
            td.set("example", examples.sample(td.shape[0]).to(device))
            return td
        return lnt_batch(td, cfg.algo, cfg.algo.num_members)

    def update():  # one joint step on both losses (update_order=joint); the release's order adds an actor pass
        losses = loss(sample())
        total = sum(losses[n] for n in names)
        agent.optimizer.zero_grad()
        total.backward()
        agent.optimizer.step()
        agent.targets.step()

    return update


# in-place products (``a.addmm_(b, c)``, ``a.baddbmm_(b, c)``) cost what their out-of-place forms
# do; torch's FLOP table lists only the latter
IN_PLACE_PRODUCTS = {torch.ops.aten.addmm_: torch.ops.aten.addmm, torch.ops.aten.baddbmm_: torch.ops.aten.baddbmm}


class CountFlops(TorchDispatchMode):
    """Adds up the FLOPs of every matrix product and convolution run under it (torch's FLOP formulas,
    ``2 m n k`` for an ``[m, k] x [k, n]`` product), in-place products included.

    (torch's ``FlopCounterMode`` also tracks modules, which does not work with tensordict's parameter
    containers; the formulas are the same. Element-wise work is not counted.)
    """

    def __init__(self):
        super().__init__()
        self.total = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        packet = func._overloadpacket
        formula = flop_registry.get(IN_PLACE_PRODUCTS.get(packet, packet))
        if formula is not None:
            self.total += formula(*args, **kwargs, out_val=out)
        return out


def synchronizer(device) -> Callable[[], None]:
    """What waits for ``device``'s queued work: a timed call must include it (nothing on CPU)."""
    device = torch.device(device)
    return (lambda: torch.cuda.synchronize(device)) if device.type == "cuda" else (lambda: None)


def run_timed(update, repeats: int, warmup: int = 20, warmup_seconds: float = 1.0, device="cpu") -> list[float]:
    """Wall times of ``repeats`` calls of ``update`` (each up to the end of its work on ``device``),
    after at least ``warmup`` calls and ``warmup_seconds`` of them (caches, allocator and thread
    pool settled)."""
    sync = synchronizer(device)
    deadline = time.perf_counter() + warmup_seconds
    done = 0
    while done < warmup or time.perf_counter() < deadline:
        update()
        done += 1
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        update()
        sync()
        times.append(time.perf_counter() - start)
    return times


def count_flops(update) -> int:
    with CountFlops() as counter:
        update()
    return counter.total


def summary(times: list[float]) -> dict:
    return {"median_ms": 1000 * statistics.median(times), "min_ms": 1000 * min(times)}


def time_update(update, repeats: int, warmup: int = 5, device="cpu") -> dict:
    """Median and minimum wall time of ``update`` over ``repeats`` calls after ``warmup`` calls, and its FLOPs."""
    result = summary(run_timed(update, repeats, warmup=warmup, warmup_seconds=0.0, device=device))
    result["flops"] = count_flops(update)
    return result


def matmul_rate(seconds: float = 1.0, n: int = 1024, device="cpu") -> float:
    """The best float32 matrix-multiply rate (FLOP/s) of ``n x n`` products on ``device``; on a GPU
    larger products (4096) are used, as 1024 ones leave it mostly idle."""
    sync = synchronizer(device)
    n = 4096 if torch.device(device).type == "cuda" else n
    a, b = torch.randn(n, n, device=device), torch.randn(n, n, device=device)
    for _ in range(3):
        a @ b
    sync()
    best = 0.0
    deadline = time.perf_counter() + seconds
    while time.perf_counter() < deadline:
        start = time.perf_counter()
        for _ in range(5):
            a @ b
        sync()
        best = max(best, 5 * 2 * n**3 / (time.perf_counter() - start))
    return best


def machine(device="cpu") -> dict:
    info = {"cpu": processor_name(), "cores": os.cpu_count(), "torch_threads": torch.get_num_threads(), "python": platform.python_version(),
            "torch": torch.__version__, "torchrl": torchrl.__version__, "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "device": str(device)}
    if torch.device(device).type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def describe(info: dict, threads: int) -> str:
    """The machine line of a results table."""
    where = f"{info['cpu']}, {info['cores']} cores, {threads} torch threads"
    if "gpu" in info:
        where = f"{info['gpu']} ({info['device']}); host {where}"
    return f"Machine: {where}; torch {info['torch']}, torchrl {info['torchrl']}, Python {info['python']}."


def check_device(device: str) -> str:
    """``device`` if this machine has it, else a clear exit."""
    try:
        kind = torch.device(device).type
    except RuntimeError as err:
        raise SystemExit(f"--device {device}: not a device name ({err}).") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"--device {device}: this machine has no CUDA device (torch {torch.__version__}, "
                         f"CUDA build: {torch.version.cuda or 'no'}).")
    if kind not in ("cpu", "cuda"):
        raise SystemExit(f"--device {device}: only cpu and cuda devices are benchmarked.")
    return device


def write_results(folder: Path, name: str, report: dict, text: str) -> None:
    """Prints the markdown table and writes it with the JSON report as ``<name>-<UTC date>.md/.json``."""
    print(text)
    folder.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M")
    (folder / f"{name}-{stamp}.json").write_text(json.dumps(report, indent=2))
    (folder / f"{name}-{stamp}.md").write_text(text)
    print(f"wrote {folder / f'{name}-{stamp}.md'} and .json")


RATE_NAMES = {"ieee": "plain float32", "bf16": "oneDNN bf16 path"}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer repetitions")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per update (default 60, --quick 20)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3, help="rounds of all updates in turn")
    parser.add_argument("--warmup", type=int, default=20, help="untimed calls of an update before its timed ones")
    parser.add_argument("--warmup-seconds", type=float, default=1.0,
                        help="and at least this long of them (caches, allocator and thread pool settled)")
    parser.add_argument("--scaling-members", type=int, nargs="+", default=[1, 5, 10, 20], metavar="K",
                        help="the scaling table's ensemble sizes (default 1 5 10 20)")
    parser.add_argument("--scaling-batches", type=int, nargs="+", default=[64, 256, 1024], metavar="B",
                        help="the scaling table's batch sizes (default 64 256 1024)")
    parser.add_argument("--no-compile", dest="compile", action="store_false",
                        help="leave out the torch.compile row (its compilation takes half a minute)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:N]: where the networks and batches live")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = parser.parse_args(argv)
    device = check_device(args.device)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    accel.retain_freed_memory()  # as the recipe does (speed.retain_memory)
    repeats = args.repeats if args.repeats is not None else (20 if args.quick else 60)
    if repeats < 1 or args.rounds < 1 or args.warmup < 0 or args.warmup_seconds < 0:
        raise SystemExit("--repeats and --rounds must be at least 1, --warmup and --warmup-seconds at least 0.")
    if min(args.scaling_members) < 1 or min(args.scaling_batches) < 1:
        raise SystemExit("--scaling-members and --scaling-batches must be at least 1.")
    warm = {"warmup": args.warmup, "warmup_seconds": args.warmup_seconds}

    # the recipe's speed.matmul_precision (auto: oneDNN's bf16 path only where it measures as accurate
    # as plain float32; a CPU setting); every rate and limit below belongs to the precision its row ran with
    on_cpu = torch.device(device).type == "cpu"
    precision = accel.choose_matmul_precision(paper_config("ours").speed.matmul_precision) if on_cpu else "ieee"
    rates = {}
    for p in dict.fromkeys(("ieee", precision)):
        with accel.matmul_products(p):
            rates[p] = matmul_rate(device=device)
    rows = []
    reset_label = "reset RCE update (K = 5, batch 256 + 256 examples, n = 10)"
    compile_label = "forward DDPG update (batch 64), torch.compile"
    # (label, kind, compiled, products, accelerated); the last three rows are the
    # plain reference path of each update (speed.accelerate=false), for the accelerator's gain
    cases = [
        ("forward DDPG update (batch 64), eager", "forward", False, precision, True),
        (compile_label, "forward", True, precision, True),
        (reset_label, "ours", False, precision, True),
        ("reset LNT update (K = 20, batch 256)", "lnt", False, precision, True),
        ("forward DDPG update (batch 64), reference path", "forward", False, "ieee", False),
        (reset_label + ", reference path", "ours", False, "ieee", False),
        ("reset LNT update (K = 20, batch 256), reference path", "lnt", False, "ieee", False),
    ]
    if precision != "ieee":
        cases.insert(3, (reset_label + ", plain float32 products", "ours", False, "ieee", True))
    if not args.compile:
        cases = [c for c in cases if not c[2]]
    # In rounds: every update is timed a third of its repeats per round, the updates in turn, so that
    # a slow spell of the shared machine weighs on all of them alike rather than on one row.
    updates = [make_update(kind, compiled=compiled, device=device, accelerate=fast)
               for _, kind, compiled, _, fast in cases]
    times = [[] for _ in cases]
    for _ in range(args.rounds):
        for i, case in enumerate(cases):
            with accel.matmul_products(case[3]):  # as the recipe runs its updates
                times[i] += run_timed(updates[i], max(1, repeats // args.rounds), device=device, **warm)
    for i, (label, kind, compiled, p, _) in enumerate(cases):
        result = summary(times[i])
        if kind == "forward" and i > 0:  # the same arithmetic as the first row
            result["flops"] = rows[0]["flops"]
        else:
            with accel.matmul_products(p):
                result["flops"] = count_flops(updates[i])
        limit_ms = 1000 * result["flops"] / rates[p]
        rows.append({"update": label, "precision": p, **result, "flop_limit_ms": limit_ms,
                     "fraction_of_limit": limit_ms / result["median_ms"]})
    scaling = []
    for members in args.scaling_members:
        for batch in args.scaling_batches:
            with accel.matmul_products(precision):
                result = time_update(make_update("ours", members=members, batch=batch, device=device),
                                     max(1, repeats // 4), warmup=2, device=device)
            scaling.append({"members": members, "batch": batch, **result})

    by = {(r["members"], r["batch"]): r["median_ms"] for r in scaling}
    by_label = {c[0]: r for r, c in zip(rows, cases)}
    forward, ours = rows[0], by_label[reset_label]  # the recipe's defaults: both losses eager
    compiled = by_label.get(compile_label)
    lnt = next(r for r, c in zip(rows, cases) if c[1] == "lnt" and c[4])
    reference = {c[1]: r for r, c in zip(rows, cases) if not c[4]}
    gains = {"forward": reference["forward"]["median_ms"] / forward["median_ms"],
             "ours": reference["ours"]["median_ms"] / ours["median_ms"],
             "lnt": reference["lnt"]["median_ms"] / lnt["median_ms"]}
    targets = [
        ("reset RCE update <= 35 ms", ours["median_ms"], ours["median_ms"] <= 35.0),
        ("reset RCE update <= 2x its FLOP-limit time", ours["median_ms"] / ours["flop_limit_ms"],
         ours["median_ms"] <= 2 * ours["flop_limit_ms"]),
        ("forward update <= 3 ms (eager, the recipe's default)", forward["median_ms"], forward["median_ms"] <= 3.0),
        *([("forward update <= 3 ms (torch.compile)", compiled["median_ms"], compiled["median_ms"] <= 3.0)]
          if compiled is not None else []),
    ]
    if (20, 256) in by and (5, 256) in by:
        targets.append(("K = 20 costs < 4x K = 5 (batch 256)", by[(20, 256)] / by[(5, 256)], by[(20, 256)] < 4 * by[(5, 256)]))
    report = {"machine": machine(device), "matmul_precision": precision,
              "matmul_gflops": {p: r / 1e9 for p, r in rates.items()}, "updates": rows, "scaling": scaling,
              "reference_vs_accelerated": gains,
              "targets": [{"target": t, "measured": v, "met": ok} for t, v, ok in targets]}

    lines = [f"# Update speed ({report['machine']['date']})", "",
             describe(report["machine"], args.threads),
             f"Float32 matrix products ({'4096 x 4096' if not on_cpu else '1024 x 1024'}, best of several runs): "
             + "; ".join(f"{RATE_NAMES[p]}: {r / 1e9:.0f} GFLOP/s" for p, r in rates.items()) + ".",
             (f"The recipe's `speed.matmul_precision=auto` chose `{precision}` on this machine; each row's FLOP limit "
              "uses the rate of the precision it ran with." if on_cpu else
              "Products in plain float32 (`speed.matmul_precision` is a CPU setting)."), "",
             "| update | products | median (ms) | min (ms) | GFLOP | FLOP-limit time (ms) | fraction of the limit |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['update']} | {r['precision']} | {r['median_ms']:.2f} | {r['min_ms']:.2f} | {r['flops'] / 1e9:.3f} | "
                     f"{r['flop_limit_ms']:.2f} | {100 * r['fraction_of_limit']:.0f}% |")
    lines += ["", "The plain reference path (`speed.accelerate=false`), in times the accelerated update, medians: "
              + ", ".join(f"{name} {gain:.2f}x" for name, gain in gains.items()) + ".",
              "", f"Reset RCE update ({precision} products), median ms (rows: K; columns: batch):", "",
              "| K | " + " | ".join(str(b) for b in args.scaling_batches) + " |",
              "|---|" + "---|" * len(args.scaling_batches)]
    for members in args.scaling_members:
        lines.append(f"| {members} | " + " | ".join(f"{by[(members, b)]:.1f}" for b in args.scaling_batches) + " |")
    lines += ["", "| target | measured | met |", "|---|---|---|"]
    for t, v, ok in targets:
        lines.append(f"| {t} | {v:.2f} | {'yes' if ok else 'NO'} |")
    write_results(args.out, "updates", report, "\n".join(lines) + "\n")
    return report


if __name__ == "__main__":
    main()
