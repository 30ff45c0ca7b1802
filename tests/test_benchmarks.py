"""The benchmark scripts: their FLOP counts against hand counts, and each documented command end to end (tiny runs)."""
import json
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
from benchmarks import bench_loop, bench_updates

# peg-insertion: 14 observations, 7 actions; the paper's 400-300 networks
OBS, ACT, H0, H1 = 14, 7, 400, 300
ACTOR = 2 * (OBS * H0 + H0 * H1 + H1 * ACT)  # one row through the actor, FLOPs
TRUNK = 2 * (OBS * H0 + H0 * H1)  # one row through a critic member's state part
HEAD = 2 * ACT * H1  # the action layer (the one-wide logit layer is a dot product: not a matrix product)


def test_flop_counter_counts_in_place_products():
    a, b, c = torch.randn(2, 3, 5), torch.randn(2, 3, 4), torch.randn(2, 4, 5)
    with bench_updates.CountFlops() as counter:
        a.baddbmm_(b, c)
        torch.randn(6, 5).addmm_(torch.randn(6, 2), torch.randn(2, 5))
    assert counter.total == 2 * (2 * 3 * 4 * 5) + 2 * 6 * 2 * 5


def test_forward_update_flops_match_a_hand_count():
    update = bench_updates.make_update("forward")
    batch = 64
    # forward: critic on the replay pairs, target actor and target critic on s', actor and held critic on s
    forward = 2 * ACTOR + 3 * (TRUNK + HEAD)
    # backward of the value loss: the critic's weight gradients and the gradient into its first hidden layer
    value = HEAD + 2 * H0 * H1 * 2 + 2 * OBS * H0
    # backward of the actor loss: into the action through the held critic's action layer, then the actor
    # (weight gradients everywhere, input gradients except into the observation)
    actor = HEAD + (2 * H1 * ACT * 2 + 2 * H0 * H1 * 2 + 2 * OBS * H0)
    assert bench_updates.count_flops(update) == batch * (forward + value + actor)  # 145,676,800


def test_rce_update_flops_match_a_hand_count():
    torch.manual_seed(0)
    update = bench_updates.make_update("ours")  # K = 5, 256 replay rows + 256 examples, n = 10, priors
    k, b = 5, 256
    labels = 3 * b * ACTOR + 2 * k * 2 * b * (TRUNK + HEAD)  # actor on s', s_n, s*; 2K stacked members on s', s_n
    paired = (b * ACTOR  # actor on s (with gradient)
              + k * 2 * b * TRUNK  # trained state part on examples and replay rows
              + k * b * HEAD + k * 2 * b * HEAD  # trained heads: the policy's actions, then all rows
              + k * b * TRUNK  # the priors' state part of the replay rows (the examples' is kept)
              + 3 * k * b * HEAD)  # prior heads: policy, examples, replay rows
    classifier = k * 2 * b * (HEAD + 2 * H0 * H1 * 2 + 2 * OBS * H0)
    actor = 2 * k * b * HEAD + b * (2 * H1 * ACT * 2 + 2 * H0 * H1 * 2 + 2 * OBS * H0)
    kept = labels + paired + classifier + actor  # 3,972,915,200
    # the first update computes the examples' prior state part (for the whole example batch) and keeps
    # it; once every one of the 100 examples has been drawn, nothing is recomputed
    assert bench_updates.count_flops(update) == kept + k * b * TRUNK
    for _ in range(5):
        update()
    assert bench_updates.count_flops(update) == kept


def test_update_benchmark_command_writes_its_tables(tmp_path):
    report = bench_updates.main(["--repeats", "2", "--rounds", "1", "--warmup", "1", "--warmup-seconds", "0",
                                 "--no-compile", "--scaling-members", "5", "20", "--scaling-batches", "256",
                                 "--out", str(tmp_path)])
    written = sorted(p.suffix for p in tmp_path.iterdir())
    assert written == [".json", ".md"]
    saved = json.loads(next(tmp_path.glob("*.json")).read_text())
    assert saved["targets"] == report["targets"]
    assert [(r["members"], r["batch"]) for r in saved["scaling"]] == [(5, 256), (20, 256)]
    assert any(t["target"].startswith("K = 20 costs") for t in saved["targets"])
    for row in saved["updates"]:
        rate = saved["matmul_gflops"][row["precision"]] * 1e9
        assert row["flop_limit_ms"] == pytest.approx(1000 * row["flops"] / rate)
        assert row["fraction_of_limit"] == pytest.approx(row["flop_limit_ms"] / row["median_ms"])
        assert 0 < row["min_ms"] <= row["median_ms"]
    text = next(tmp_path.glob("*.md")).read_text()
    assert "forward DDPG update" in text and "torch.compile" not in text  # --no-compile leaves its row out
    assert len(saved["updates"]) == 6 + (saved["matmul_precision"] != "ieee")  # the rows without torch.compile


def test_loop_benchmark_command_gives_ratios_and_the_paper_run_projection(tmp_path):
    # two forward episodes (H_f = 100) around a reset episode: both agents update and are timed
    # the smallest networks: the command and its arithmetic are checked, not the paper-size timing
    report = bench_loop.main(["--steps", "330", "--heat-up", "10", "--rounds", "1", "--hidden-sizes", "16", "16",
                              "--out", str(tmp_path)])
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".json", ".md"]
    loops = report["loops"]
    assert {r["steps"] for r in loops.values()} == {330}
    share = report["common_forward_share"]
    rates = {name: 1 / (share * r["step_seconds"]["forward"] + (1 - share) * r["step_seconds"]["reset"])
             for name, r in loops.items()}
    for name, ratio in report["ratios"].items():
        assert ratio == pytest.approx(rates["ours"] / rates[name])
    assert report["projected_paper_run_hours"] == pytest.approx(1_500_000 / rates["ours"] / 3600)
    assert "paper run" in next(tmp_path.glob("*.md")).read_text()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message of a machine without CUDA")
@pytest.mark.parametrize("script", [bench_updates, bench_loop])
def test_a_cuda_run_without_cuda_stops_with_a_clear_message(script, tmp_path):
    with pytest.raises(SystemExit, match="no CUDA device"):
        script.main(["--device", "cuda", "--out", str(tmp_path)])


@pytest.mark.parametrize("argv,message", [(["--device", "gpu0"], "not a device name"),
                                          (["--device", "meta"], "only cpu and cuda"),
                                          (["--repeats", "0"], "at least 1")])
def test_bad_update_benchmark_arguments_stop_with_a_clear_message(argv, message, tmp_path):
    with pytest.raises(SystemExit, match=message):
        bench_updates.main([*argv, "--out", str(tmp_path)])


def test_the_profile_table_splits_a_runs_time_by_hand():
    """profile_run.table on made-up totals: 100 steps in 10 s; acting 2 s of which env 0.5, trigger 0.2, policies
    0.3 (the collector's own 1.0 s is the rest); reset update 6 s, forward update 1 s, one checkpoint 0.5 s; the loop's
    own time is what is left: 10 - 2 - (6 + 1 + 0.5) = 0.5 s. Outside the updates: 1 - 7 / 10 = 30%. Over 1,000 steps
    the per-step parts grow 10x and the checkpoints come at every 500 steps plus the last (3 x 0.5 s)."""
    from benchmarks import profile_run

    result = {"steps": 100, "wall": 10.0, "eval_every": 1000, "checkpoint_every": 500,
              "total": {"acting": 2.0, "acting: env": 0.5, "acting: trigger": 0.2, "acting: policies": 0.3,
                        "reset update": 6.0, "forward update": 1.0, "checkpoints": 0.5},
              "calls": {"checkpoints": 1, "reset update": 60, "forward update": 40}}
    text, derived = profile_run.table(result, projected_steps=1000)
    assert derived["parts"]["acting: collector"] == pytest.approx(1.0)
    assert derived["parts"]["loop"] == pytest.approx(0.5)
    assert derived["outside_updates"] == pytest.approx(0.30)
    assert derived["projected"]["reset update"] == pytest.approx(60.0)
    assert derived["projected"]["checkpoints"] == pytest.approx(1.5)
    # projected: 95 s of per-step parts (10x of 9.5 s) + 1.5 s of checkpoints; the updates 70 s of it
    assert derived["outside_updates_projected"] == pytest.approx(1 - 70.0 / 96.5)
    assert "| reset update | 6.0 | 60.0% | 60.00 | 60 |" in text


def test_the_profile_command_runs_the_recipe_and_accounts_for_every_step(tmp_path, capsys):
    from benchmarks import profile_run

    report = profile_run.main(["--task", "ball_in_cup_catch", "--steps", "120", "--out", str(tmp_path), "--",
                               "preset=quick", "hidden_sizes=[16,16]", "heat_up=20", "reset.batch_size=16",
                               "forward.batch_size=16", "checkpoint_every=60"])
    counters = report["counters"]
    assert counters["forward_steps"] + counters["reset_steps"] == 120
    assert report["calls"]["acting: env"] >= 120 and report["calls"]["checkpoints"] == 3  # 60, 120 and the last
    updates = report["calls"].get("reset update", 0) + report["calls"].get("forward update", 0)
    assert updates == max(0, counters["forward_steps"] - 20) + max(0, counters["reset_steps"] - 20)
    assert list(tmp_path.glob("profile-ball_in_cup_catch-*.md"))
