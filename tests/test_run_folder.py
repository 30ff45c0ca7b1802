"""A run folder's files: verifiable checkpoints (a manifest of every file's size and sha256, written last),
resuming from the newest intact one, checkpoints written before manifests, Ctrl-C handling, and the
summary's counts of the reset episodes in the first and last quarter of a run."""
from __future__ import annotations

import csv
import hashlib
import json
import logging
import os
import shutil
import signal
from pathlib import Path

import pytest


from torchrl_reset_recipes import train
from torchrl_reset_recipes.training.hydra_config import compose
from torchrl_reset_recipes.training.config_checks import ConfigError, validate
from torchrl_reset_recipes.training.run_spec import should_resume
from torchrl_reset_recipes.training.checkpoints import Checkpoints, checkpoint_problems, checkpoint_step, identity_differences
from torchrl_reset_recipes.training.run_folder import CsvTable, reset_outcomes_by_quarter, stop_on_signals

TINY = [
    "hidden_sizes=[16,16]", "heat_up=40", "task.forward_horizon=20", "forward.batch_size=16", "reset.batch_size=16",
    "forward.buffer_size=2000", "reset.buffer_size=2000", "eval_every=50", "log_every=50", "checkpoint_every=50",
    "progress_bar=false", "speed.compile=[]", "task=peg_insertion_remove", "algo=ours",
]


def config(run_dir, *overrides):
    return compose([*TINY, f"run_dir={run_dir}", *overrides])


def rows(path, drop=("steps_per_second",)):
    if not Path(path).exists():
        return []
    with open(path, newline="") as f:
        return [{k: v for k, v in r.items() if k not in drop} for r in csv.DictReader(f)]


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def truncate(path: Path, size: int) -> None:
    with open(path, "r+b") as f:
        f.truncate(size)


# ------------------------------------------------------------------ checkpoints on their own (no training)
def write_state(payload: bytes):
    def write(folder: Path) -> None:
        (folder / "state.pt").write_bytes(payload)
        (folder / "reset_buffer").mkdir()
        (folder / "reset_buffer" / "observation.memmap").write_bytes(payload * 3)
    return write


def test_a_checkpoint_lists_every_file_with_its_size_and_sha256_in_a_manifest_written_last(tmp_path):
    folder = Checkpoints(tmp_path).save(100, write_state(b"12345678"), {"frames": 100})
    manifest = json.loads((folder / "manifest.json").read_text())["files"]
    expected = {name: {"size": (folder / name).stat().st_size, "sha256": sha256(folder / name)}
                for name in ("meta.json", "state.pt", "reset_buffer/observation.memmap")}
    assert manifest == expected
    assert expected["state.pt"]["size"] == 8 and expected["reset_buffer/observation.memmap"]["size"] == 24
    assert expected["state.pt"]["sha256"] == hashlib.sha256(b"12345678").hexdigest()
    assert json.loads((folder / "meta.json").read_text()) == {"frames": 100, "manifest": "manifest.json"}
    assert (tmp_path / "latest").read_text() == "step_0000000100"


@pytest.mark.parametrize("damage, problem", [
    (lambda f: truncate(f / "state.pt", 3), "state.pt has 3 bytes, the manifest lists 8"),
    (lambda f: truncate(f / "reset_buffer" / "observation.memmap", 10),
     "reset_buffer/observation.memmap has 10 bytes, the manifest lists 24"),
    (lambda f: (f / "state.pt").write_bytes(b"87654321"), "state.pt differs from the manifest's sha256"),
    (lambda f: (f / "meta.json").unlink(), "meta.json is missing"),
    (lambda f: (f / "manifest.json").write_text('{"files": {"state.pt": '), "manifest.json is unreadable"),
], ids=["truncated-state", "truncated-buffer-file", "changed-state", "missing-meta", "truncated-manifest"])
def test_the_latest_checkpoint_is_the_newest_intact_one_and_damage_is_named(tmp_path, damage, problem):
    checkpoints = Checkpoints(tmp_path)
    checkpoints.save(100, write_state(b"12345678"), {"frames": 100})
    checkpoints.save(200, write_state(b"12345678"), {"frames": 200})
    damage(tmp_path / "step_0000000200")
    latest, damaged = Checkpoints(tmp_path).survey()
    assert latest == tmp_path / "step_0000000100"
    assert [folder.name for folder, _ in damaged] == ["step_0000000200"]
    assert len(damaged[0][1]) == 1 and damaged[0][1][0].startswith(problem)
    assert Checkpoints(tmp_path).latest() == latest


def test_a_resume_reads_each_checkpoint_file_once_and_again_after_any_write(tmp_path, monkeypatch):
    from torchrl_reset_recipes.training import checkpoints as checkpoint_files

    checkpoints = Checkpoints(tmp_path)
    folder = checkpoints.save(100, write_state(b"12345678"), {"frames": 100})
    hour_ago = os.stat(folder / "state.pt").st_mtime_ns - 3600 * 10**9  # written an hour before the resume
    for path in folder.rglob("*"):
        os.utime(path, ns=(hour_ago, hour_ago))
    read = []
    monkeypatch.setattr(checkpoint_files, "_sha256", lambda path: read.append(Path(path).name) or sha256(path))
    for _ in range(3):  # the configuration check, the check under the folder's lock, the load
        assert Checkpoints(tmp_path).survey() == (folder, [])
    assert sorted(read) == ["meta.json", "observation.memmap", "state.pt"]  # each file once
    (folder / "state.pt").write_bytes(b"87654321")  # the same size, written now
    latest, damaged = Checkpoints(tmp_path).survey()
    assert latest is None and damaged[0][1] == ["state.pt differs from the manifest's sha256 (changed after it "
                                                "was written)"]
    assert Checkpoints(tmp_path).survey()[0] is None  # a file written just now is read every time
    assert read.count("state.pt") == 3


def test_a_table_drops_the_rows_after_a_checkpoint_and_says_how_far_they_went(tmp_path):
    table = CsvTable(tmp_path / "progress.csv", ["frames", "value"])
    for frames in (50, 100, 150, 200, 250):
        table.append({"frames": frames, "value": frames / 10})
    assert table.truncate_after(150) == 250  # 200 and 250 logged after a checkpoint at 150
    assert [r["frames"] for r in rows(tmp_path / "progress.csv")] == ["50", "100", "150"]
    assert table.truncate_after(150) is None  # nothing past it any more
    assert CsvTable(tmp_path / "none.csv", ["frames"]).truncate_after(0) is None


def test_a_checkpoint_written_before_manifests_counts_and_resume_auto_agrees_with_latest(tmp_path):
    run_dir = tmp_path / "run"
    old = run_dir / "checkpoints" / "step_0000000300"
    old.mkdir(parents=True)
    (old / "state.pt").write_bytes(b"state")
    (old / "meta.json").write_text(json.dumps({"task": "peg_insertion_remove", "algo": "ours", "seed": 0,
                                               "frames": 300, "arms": None}, indent=2))  # as older code wrote it
    (run_dir / "checkpoints" / "latest").write_text("step_0000000300")
    checkpoints = Checkpoints(run_dir / "checkpoints")
    assert checkpoints.latest() == old and checkpoints.folders() == [old]
    assert should_resume(config(run_dir, "resume=auto"))
    validate(config(run_dir, "resume=auto"))  # resumable
    with pytest.raises(ConfigError, match="already holds a checkpoint"):
        validate(config(run_dir))

    # its only checkpoint damaged: resume=auto still sees a checkpoint, and stops instead of starting over
    (old / "meta.json").write_text('{"task": "peg_in')
    assert checkpoints.latest() is None and checkpoints.folders() == [old]
    assert should_resume(config(run_dir, "resume=auto"))
    for resume in ("auto", "true"):
        with pytest.raises(ConfigError, match=r"no intact checkpoint .*\n  - step_0000000300: meta.json is unreadable"):
            validate(config(run_dir, f"resume={resume}"))


def test_saving_the_state_a_checkpoint_already_holds_writes_nothing_and_keep_counts_intact_steps(tmp_path):
    checkpoints = Checkpoints(tmp_path, keep=2)
    for frames in (100, 200, 300):
        checkpoints.save(frames, write_state(b"%d" % frames), {"frames": frames})
    assert sorted(p.name for p in tmp_path.glob("step_*")) == ["step_0000000200", "step_0000000300"]
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "step_0000000300").rglob("*")}
    checkpoints.save(300, write_state(b"other"), {"frames": 300})  # no step since: the folder stands as it is
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "step_0000000300").rglob("*")} == before
    assert (tmp_path / "step_0000000300" / "state.pt").read_bytes() == b"300"

    # a run that resumed from step 200 (step 300 damaged) and saves step 250: the later one is gone, and two
    # checkpoints up to 250 are kept
    truncate(tmp_path / "step_0000000300" / "state.pt", 1)
    resumed = Checkpoints(tmp_path, keep=2)
    resumed.current = resumed.latest().name
    assert resumed.current == "step_0000000200"
    resumed.save(250, write_state(b"250"), {"frames": 250})
    assert sorted(p.name for p in tmp_path.glob("step_*")) == ["step_0000000200", "step_0000000250"]
    assert resumed.latest().name == "step_0000000250" and (tmp_path / "latest").read_text() == "step_0000000250"


def test_the_agents_state_of_every_kept_step_outlives_its_checkpoint_and_a_lost_continuation_drops_it(tmp_path):
    checkpoints = Checkpoints(tmp_path, keep=2, keep_states_every=200)
    for frames in (100, 200, 300, 400, 500):
        checkpoints.save(frames, write_state(b"%d" % frames), {"frames": frames})
    assert sorted(p.name for p in tmp_path.glob("step_*")) == ["step_0000000400", "step_0000000500"]
    # steps 200 and 400 are multiples of 200: their state.pt stays, without the buffers
    assert [p.name for p in checkpoints.kept()] == ["step_0000000200", "step_0000000400"]
    assert [(p / "state.pt").read_bytes() for p in checkpoints.kept()] == [b"200", b"400"]
    kept200 = tmp_path / "kept" / "step_0000000200"
    # the state without the buffers, with the checkpoint's meta and a manifest of the state alone
    assert sorted(q.name for q in kept200.iterdir()) == ["manifest.json", "meta.json", "state.pt"]
    assert json.loads((kept200 / "meta.json").read_text())["frames"] == 200
    assert json.loads((kept200 / "manifest.json").read_text())["files"] == {
        "state.pt": {"size": 3, "sha256": hashlib.sha256(b"200").hexdigest()}}
    assert checkpoint_problems(kept200) == []
    assert checkpoints.latest().name == "step_0000000500"  # kept states are not checkpoints a resume reads

    # a run that resumed from an older checkpoint (the later ones damaged) and saves step 350: the states
    # kept past 350 belong to a continuation it no longer has; reaching 400 again keeps the new state
    resumed = Checkpoints(tmp_path, keep=2, keep_states_every=200)
    resumed.save(350, write_state(b"350"), {"frames": 350})
    assert [p.name for p in resumed.kept()] == ["step_0000000200"]
    resumed.save(400, write_state(b"400 again"), {"frames": 400})
    assert (tmp_path / "kept" / "step_0000000400" / "state.pt").read_bytes() == b"400 again"


def test_the_first_checkpoint_at_or_past_each_multiple_keeps_its_state(tmp_path):
    # checkpoints that land past the multiples (as where a signal stopped a run): 102, 201, 300, 402
    for every, expected in ((100, [102, 201, 300, 402]), (200, [201, 402])):
        checkpoints = Checkpoints(tmp_path / str(every), keep=1, keep_states_every=every)
        for frames in (102, 201, 300, 402):
            checkpoints.save(frames, write_state(b"%d" % frames), {"frames": frames})
        assert [checkpoint_step(p) for p in checkpoints.kept()] == expected
        assert [(p / "state.pt").read_bytes() for p in checkpoints.kept()] == [b"%d" % f for f in expected]

    # a resume from 300 (the 402 checkpoint damaged) that lands at 401: the lost continuation's 402 goes,
    # 401 is kept in its place; one that lands at 403 after a lost 401 likewise drops 401 and keeps 403
    for lost, again in ((402, 401), (401, 403)):
        root = tmp_path / f"lost{lost}"
        first = Checkpoints(root, keep=2, keep_states_every=200)
        for frames in (201, 300, lost):
            first.save(frames, write_state(b"%d" % frames), {"frames": frames})
        resumed = Checkpoints(root, keep=2, keep_states_every=200)
        resumed.loaded(root / "step_0000000300")
        resumed.save(again, write_state(b"again"), {"frames": again})
        assert [checkpoint_step(p) for p in resumed.kept()] == [201, again]


def test_states_kept_by_another_attempt_are_not_taken_for_this_runs(tmp_path):
    first = Checkpoints(tmp_path, keep=2, keep_states_every=100)
    for frames in (100, 200):
        first.save(frames, write_state(b"old %d" % frames), {"frames": frames})
    for folder in tmp_path.glob("step_*"):  # its checkpoints removed by hand; its kept states left behind
        shutil.rmtree(folder)
    (tmp_path / "latest").unlink()
    # a fresh start there: everything kept before is another attempt's, gone at its first checkpoint
    fresh = Checkpoints(tmp_path, keep=2, keep_states_every=200)
    fresh.started_fresh()
    fresh.save(100, write_state(b"100"), {"frames": 100})
    assert fresh.kept() == []
    fresh.save(200, write_state(b"200"), {"frames": 200})
    assert [(p.name, (p / "state.pt").read_bytes()) for p in fresh.kept()] == [("step_0000000200", b"200")]
    # a writer that knows nothing of how it started still replaces a state kept at the step it saves
    other = Checkpoints(tmp_path, keep=2, keep_states_every=200)
    other.save(200, write_state(b"200 again"), {"frames": 200})
    assert (tmp_path / "kept" / "step_0000000200" / "state.pt").read_bytes() == b"200 again"


def test_a_state_whose_keeping_a_crash_cut_short_is_kept_after_the_resume(tmp_path, monkeypatch):
    checkpoints = Checkpoints(tmp_path, keep=1, keep_states_every=200)
    checkpoints.save(100, write_state(b"100"), {"frames": 100})
    real = Checkpoints._keep_state

    def crash(self, folder):
        raise KeyboardInterrupt("the process ends while keeping")
    monkeypatch.setattr(Checkpoints, "_keep_state", crash)
    with pytest.raises(KeyboardInterrupt):
        checkpoints.save(200, write_state(b"200"), {"frames": 200})
    monkeypatch.setattr(Checkpoints, "_keep_state", real)
    assert checkpoints.kept() == [] and checkpoints.latest().name == "step_0000000200"
    # the resume reads step 200 and runs on to 300; keeping only one checkpoint, 200's folder would go now:
    # its state is kept first
    resumed = Checkpoints(tmp_path, keep=1, keep_states_every=200)
    resumed.loaded(resumed.latest())
    resumed.save(300, write_state(b"300"), {"frames": 300})
    assert sorted(p.name for p in tmp_path.glob("step_*")) == ["step_0000000300"]
    assert [(p.name, (p / "state.pt").read_bytes()) for p in resumed.kept()] == [("step_0000000200", b"200")]


def test_a_kept_state_is_a_link_where_the_file_system_allows_and_a_checked_copy_where_not(tmp_path, monkeypatch):
    linked = Checkpoints(tmp_path / "linked", keep=2, keep_states_every=100)
    linked.save(100, write_state(b"100"), {"frames": 100})
    kept = tmp_path / "linked" / "kept" / "step_0000000100" / "state.pt"
    assert kept.stat().st_ino == (tmp_path / "linked" / "step_0000000100" / "state.pt").stat().st_ino

    def no_links(src, dst):
        raise OSError(1, "Operation not permitted")
    monkeypatch.setattr(os, "link", no_links)
    copied = Checkpoints(tmp_path / "copied", keep=2, keep_states_every=100)
    copied.save(100, write_state(b"100"), {"frames": 100})
    kept = tmp_path / "copied" / "kept" / "step_0000000100"
    assert (kept / "state.pt").read_bytes() == b"100"
    assert (kept / "state.pt").stat().st_ino != (tmp_path / "copied" / "step_0000000100" / "state.pt").stat().st_ino
    assert checkpoint_problems(kept) == []
    (kept / "state.pt").write_bytes(b"101")  # changed after it was kept: the manifest tells
    assert checkpoint_problems(kept) == ["state.pt differs from the manifest's sha256 (changed after it was written)"]


# ------------------------------------------------------------------------------ with training runs
@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """150 steps without a stop."""
    run_dir = tmp_path_factory.mktemp("whole")
    train.train(config(run_dir, "total_steps=150"))
    return run_dir


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    """The same run stopped after 100 steps: checkpoints at 50 and 100."""
    run_dir = tmp_path_factory.mktemp("split") / "run"
    train.train(config(run_dir, "total_steps=100"))
    assert sorted(p.name for p in (run_dir / "checkpoints").glob("step_*")) == ["step_0000000050", "step_0000000100"]
    return run_dir


def assert_same_tables(a: Path, b: Path) -> None:
    for table in ("progress.csv", "eval.csv", "resets.csv"):
        assert rows(a / table) == rows(b / table), table
    assert len(rows(a / "progress.csv")) == 3


@pytest.mark.parametrize("damaged_file", ["state.pt", "reset_buffer/storage/observation.memmap"])
def test_a_damaged_latest_checkpoint_is_named_and_the_run_resumes_exactly_from_the_one_before(
        tmp_path, whole, split, damaged_file, caplog):
    run_dir = tmp_path / "run"
    shutil.copytree(split, run_dir)
    broken = run_dir / "checkpoints" / "step_0000000100" / damaged_file
    size = broken.stat().st_size
    truncate(broken, size // 2)  # what a full disk or a copy cut short leaves
    with caplog.at_level(logging.WARNING):
        summary = train.train(config(run_dir, "total_steps=150", "resume=true"))
    said = [r.getMessage() for r in caplog.records if "damaged" in r.getMessage()]
    assert len(said) == 1
    assert "step_0000000100" in said[0]
    assert f"{damaged_file} has {size // 2} bytes, the manifest lists {size}" in said[0]
    assert said[0].endswith("resuming from step_0000000050")
    assert summary["steps"] == 150 and summary["finished"]
    assert_same_tables(whole, run_dir)  # steps 50-100 taken again, exactly as the run that never stopped
    latest, damaged = Checkpoints(run_dir / "checkpoints").survey()  # step 100 written again, intact
    assert latest.name == "step_0000000150" and not damaged
    assert [p.name for p in Checkpoints(run_dir / "checkpoints").folders()] == ["step_0000000150", "step_0000000100"]


def test_a_run_whose_checkpoints_are_all_damaged_stops_with_a_message_naming_them(tmp_path, split):
    run_dir = tmp_path / "run"
    shutil.copytree(split, run_dir)
    truncate(run_dir / "checkpoints" / "step_0000000100" / "state.pt", 100)
    (run_dir / "checkpoints" / "step_0000000050" / "manifest.json").unlink()
    progress = (run_dir / "progress.csv").read_text()
    for resume in ("true", "auto"):
        with pytest.raises(ConfigError) as refused:
            train.train(config(run_dir, "total_steps=150", f"resume={resume}"))
        message = str(refused.value)
        assert message.startswith(f"no intact checkpoint in {run_dir / 'checkpoints'} to resume from")
        assert "step_0000000100: state.pt has 100 bytes, the manifest lists" in message
        assert "step_0000000050: manifest.json is missing" in message
    assert (run_dir / "progress.csv").read_text() == progress  # nothing started over


def test_a_checkpoint_written_before_manifests_still_resumes_with_a_warning(tmp_path, whole, split, caplog):
    run_dir = tmp_path / "run"
    shutil.copytree(split, run_dir)
    for folder in (run_dir / "checkpoints").glob("step_*"):  # as the code before manifests wrote them
        (folder / "manifest.json").unlink()
        meta = json.loads((folder / "meta.json").read_text())
        del meta["manifest"]
        (folder / "meta.json").write_text(json.dumps(meta, indent=2))
    with caplog.at_level(logging.WARNING):
        summary = train.train(config(run_dir, "total_steps=150", "resume=true"))
    said = [r.getMessage() for r in caplog.records if "cannot be verified" in r.getMessage()]
    assert len(said) == 1 and "step_0000000100" in said[0] and "\n" not in said[0]
    assert summary["steps"] == 150
    assert_same_tables(whole, run_dir)
    assert (run_dir / "checkpoints" / "step_0000000150" / "manifest.json").exists()  # new ones have one


def test_resuming_writes_nothing_into_the_checkpoint_it_reads(tmp_path, split):
    run_dir = tmp_path / "run"
    shutil.copytree(split, run_dir)

    def files():
        return {p: (p.stat().st_size, p.stat().st_mtime_ns, sha256(p))
                for p in (run_dir / "checkpoints").rglob("*") if p.is_file()}

    before = files()
    summary = train.train(config(run_dir, "total_steps=100", "resume=true"))  # nothing left to do: it stops at once
    assert summary["steps"] == 100 and summary["finished"]
    assert files() == before


# --------------------------------------------------------------------------------------------- signals
def test_the_first_ctrl_c_asks_for_a_stop_and_the_second_stops_at_once():
    previous = signal.getsignal(signal.SIGINT)
    with stop_on_signals() as requested:
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGINT)
        assert requested == [signal.SIGTERM, signal.SIGINT]  # no KeyboardInterrupt: the step goes on
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):  # the handler runs between two bytecodes of this thread
                pass
    assert signal.getsignal(signal.SIGINT) is previous


# ---------------------------------------------------------------------------- the summary's quarters
def test_the_quarters_count_every_reset_episode_that_ended_in_them(tmp_path):
    # 500 steps logged every 50: the first quarter ends at step 125, between two log rows. Two reset
    # episodes succeed at steps 110 and 120, after the row at step 100, which had none ended yet.
    with open(tmp_path / "resets.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["frames", "outcome", "steps", "distance_to_start", "distance_to_examples"])
        for frames, outcome in ((110, "success"), (120, "success"), (126, "manual"), (300, "success"),
                                (375, "manual"), (376, "manual"), (450, "success"), (500, "terminated")):
            writer.writerow([frames, outcome, 5, 0.0, 0.0])
    quarters = reset_outcomes_by_quarter(tmp_path / "resets.csv", 500, reset_episodes=8)
    assert quarters == {"first": {"from_step": 0, "to_step": 125, "reset_episodes": 2, "successful_resets": 2},
                        "last": {"from_step": 375, "to_step": 500, "reset_episodes": 3, "successful_resets": 1}}
    summary = {"manual_resets": 3, "episodic_resets": 9, "resets_saved": 6, "reset_episodes_by_quarter": quarters}
    assert train._in_words(summary) == (
        "3 manual resets where an episodic agent would have needed 9 (6 saved); 2 of 2 reset episodes succeeded "
        "in the first quarter of the run (steps 0-125, 100%); 1 of 3 reset episodes succeeded in the last "
        "quarter (steps 375-500, 33%).")
    # a table that lacks some of the run's reset episodes (begun before it was written) gives no counts
    partial = reset_outcomes_by_quarter(tmp_path / "resets.csv", 500, reset_episodes=9)
    assert partial["first"]["reset_episodes"] is None and partial["last"]["successful_resets"] is None
    assert "not all in resets.csv" in train._in_words({**summary, "reset_episodes_by_quarter": partial})
    empty = reset_outcomes_by_quarter(tmp_path / "none.csv", 500, reset_episodes=0)
    assert "no reset episode ended in the first quarter of the run (steps 0-125)" in train._in_words(
        {**summary, "reset_episodes_by_quarter": empty})


def test_a_runs_summary_counts_the_quarters_from_its_own_reset_episodes(whole):
    summary = json.loads((whole / "summary.json").read_text())
    ended = [(int(r["frames"]), r["outcome"]) for r in rows(whole / "resets.csv")]
    first = [o for f, o in ended if f <= 37]  # 150 steps: the first quarter is steps 0-37, the last 113-150
    last = [o for f, o in ended if f > 113]
    quarters = summary["reset_episodes_by_quarter"]
    for name, ended_there in (("first", first), ("last", last)):
        counted = quarters[name]
        assert (counted["reset_episodes"], counted["successful_resets"]) == (len(ended_there), ended_there.count("success"))
    assert summary["reset_success_rate_last_quarter"] == (last.count("success") / len(last) if last else None)
    assert len(ended) == summary["reset_episodes"]


def test_a_buffer_loaded_and_saved_again_without_new_rows_is_saved_whole_and_quietly(tmp_path):
    """A resume that checkpoints before a buffer gets a new row (a quick stop after a resume, or a phase
    that did not act): torchrl's storage then has no last write cursor and warns; without save hooks the
    cursor is unused, so the buffer must come back whole, rows and write position, and without that warning."""
    import warnings

    import torch
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    from torchrl_reset_recipes.training.checkpoints import dump_buffer

    def buffer():
        return ReplayBuffer(storage=LazyTensorStorage(8), batch_size=4)

    first = buffer()
    first.extend(TensorDict({"x": torch.arange(11.0)}, batch_size=[11]))  # wrapped round: 8 slots, 11 rows
    dump_buffer(first, tmp_path / "a")
    second = buffer()
    second.loads(tmp_path / "a")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning fails the test
        dump_buffer(second, tmp_path / "b")
    third = buffer()
    third.loads(tmp_path / "b")
    # slots 0-2 hold rows 8-10, slots 3-7 rows 3-7; the next write goes to slot 3
    assert third.storage["x"].tolist() == [8.0, 9.0, 10.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    assert len(third) == 8 and third.writer.state_dict() == first.writer.state_dict()
    third.extend(TensorDict({"x": torch.tensor([11.0])}, batch_size=[1]))
    assert third.storage["x"].tolist() == [8.0, 9.0, 10.0, 11.0, 4.0, 5.0, 6.0, 7.0]


def test_identity_differences_name_each_part_of_a_run_that_differs():
    from omegaconf import OmegaConf

    cfg = OmegaConf.create({"task": {"name": "cliff_cheetah"}, "algo": {"name": "lnt"}, "seed": 2})
    same = {"task": "cliff_cheetah", "algo": "lnt", "seed": 2, "frames": 500}
    assert identity_differences(same, cfg) == {}
    assert identity_differences({"frames": 500}, cfg) == {
        "task": (None, "cliff_cheetah"), "algo": (None, "lnt"), "seed": (None, 2)}
    # older code wrote arms too: null for a run on one environment, as every run is now; a config of older
    # code holds arms: null as well
    assert identity_differences({**same, "arms": None}, cfg) == {}
    assert identity_differences({**same, "arms": None}, OmegaConf.merge(cfg, {"arms": None})) == {}
    # one agent pair over 4 copies of the task (run batching, retired) is another run
    assert identity_differences({**same, "seed": 1, "arms": 4}, cfg) == {"seed": (1, 2), "arms": (4, None)}
