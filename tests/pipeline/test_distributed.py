"""Filtering and training as Ray tasks: byte-identical to the local path, fault-tolerant, resumable.

One local Ray instance with 2 CPUs serves the whole module.
"""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from run_support import tiny_dataset, write_recipe

from torchfilt.cli import main
from torchfilt.exceptions import InputError, MissingDependencyError, OutputError, RunError
from torchfilt.io.synth import simulate_dataset
from torchfilt.pipeline import filter_recordings, shard_plan
from torchfilt.pipeline.distributed import (
    DONE_DIR,
    JOB_FILE,
    filter_recordings_ray,
    train_recipes_ray,
)

SYSTEM = "system:pendulum"


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """12 pendulum recordings of two lengths (so batches of both lengths and a partial batch)."""
    root = tmp_path_factory.mktemp("fleet")
    simulate_dataset("pendulum", root / "a", recordings=7, steps=60, seed=1)
    simulate_dataset("pendulum", root / "b", recordings=5, steps=45, seed=2)
    recs = sorted((root / "a").glob("*.csv")) + sorted((root / "b").glob("*.csv"))
    return recs


def _files(folder: Path) -> dict[str, bytes]:
    """Every output file but the Ray job's own bookkeeping, by relative path."""
    return {
        p.relative_to(folder).as_posix(): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and ".torchfilt" not in p.parts
    }


@pytest.fixture(scope="module")
def local_out(recordings, tmp_path_factory):
    out = tmp_path_factory.mktemp("local") / "out"
    filter_recordings(SYSTEM, recordings, out, smooth=True, batch_size=3)
    return out


def test_shard_plan_groups_by_length_in_order():
    assert shard_plan([5, 5, 7, 5, 7, 5], 2) == [[0, 1], [3, 5], [2, 4]]
    assert shard_plan([5, 5, 7], None) == [[0, 1], [2]]
    with pytest.raises(InputError, match="batch_size \\(--batch-size\\)"):
        shard_plan([5], 0)


def test_batch_composition_changes_bits(recordings, tmp_path):
    """Why the plan is shared: the same recording filtered in another batch shape can differ
    in its last bits, so a test of byte-identity must not pass by accident of batching."""
    a = tmp_path / "one"
    filter_recordings(SYSTEM, recordings[:7], a, smooth=True, batch_size=1)
    b = tmp_path / "all"
    filter_recordings(SYSTEM, recordings[:7], b, smooth=True)
    fa, fb = _files(a), _files(b)
    assert fa.keys() == fb.keys()
    assert any(fa[k] != fb[k] for k in fa if k.endswith(".csv")), (
        "batch shape no longer changes any bits; the shared plan is then not needed"
    )


def test_ray_outputs_byte_identical_to_local(ray_local, recordings, local_out, tmp_path):
    out = tmp_path / "ray"
    stream = io.StringIO()
    res = filter_recordings_ray(SYSTEM, recordings, out, smooth=True, batch_size=3, stream=stream)
    assert _files(out) == _files(local_out)
    d = res["distributed"]
    assert d["filtered"] == len(recordings) and d["complete_before"] == 0
    assert d["tasks"] == len(shard_plan([60] * 7 + [45] * 5, 3))
    assert f"{len(recordings)}/{len(recordings)} recordings done" in stream.getvalue()
    # every recording has exactly one marker, and a re-run does nothing
    markers = sorted((out / DONE_DIR).rglob("*.json"))
    assert len(markers) == len(recordings)
    again = filter_recordings_ray(SYSTEM, recordings[::-1], out, smooth=True, batch_size=3)
    assert again["distributed"]["filtered"] == 0 and again["distributed"]["tasks"] == 0
    assert _files(out) == _files(local_out)


def _our_task_pids() -> list[int]:
    """Ray worker processes running a filter task that belong to this test process's Ray
    instance (a descendant of this process), not to any other job on the machine."""
    me = os.getpid()
    pids = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            cmd = Path(f"/proc/{d}/cmdline").read_bytes()
        except OSError:
            continue
        if not cmd.startswith(b"ray::_filter_shard"):
            continue
        pid = int(d)
        for _ in range(6):  # worker -> raylet -> ... -> this process
            try:
                stat = Path(f"/proc/{pid}/stat").read_text()
            except OSError:
                break
            pid = int(stat.rsplit(")", 1)[1].split()[1])
            if pid == me:
                pids.append(int(d))
                break
            if pid <= 1:
                break
    return pids


class _Killer(threading.Thread):
    """Kills (SIGKILL) one worker process in the middle of a job: once ``after`` recordings are
    complete and a filter task is running."""

    def __init__(self, out: Path, after: int) -> None:
        super().__init__(daemon=True)
        self.out, self.after = out, after
        self.killed: int | None = None
        self.done_at_kill = -1
        self.stop = False

    def run(self) -> None:
        while not self.stop and self.killed is None:
            done = len(list((self.out / DONE_DIR).rglob("*.json")))
            if done >= self.after:
                # not at once: the task that wrote the last marker is returning; a little later
                # a running task is most likely filtering, before its writes
                time.sleep(0.03)
                pids = _our_task_pids()
                if pids:
                    os.kill(pids[0], signal.SIGKILL)
                    self.killed, self.done_at_kill = pids[0], done
                    return
            time.sleep(0.002)


def _long_recordings(root: Path) -> list[Path]:
    simulate_dataset("reentry", root, recordings=16, steps=300, seed=4)
    return sorted(root.glob("*.csv"))


def test_worker_killed_mid_job_still_completes(ray_local, tmp_path):
    recs = _long_recordings(tmp_path / "data")
    local = tmp_path / "local"
    filter_recordings("system:reentry", recs, local, batch_size=2)
    out = tmp_path / "ray"
    killer = _Killer(out, after=2)
    killer.start()
    try:
        res = filter_recordings_ray(
            "system:reentry", recs, out, batch_size=2, max_retries=3, progress=False
        )
    finally:
        killer.stop = True
        killer.join()
    assert killer.killed is not None, "the job finished before a worker could be killed"
    assert 2 <= killer.done_at_kill < len(recs)
    assert res["distributed"]["filtered"] == len(recs)
    # every output present exactly once (one per recording, no stray temporaries) and equal
    assert _files(out) == _files(local)
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]


def test_rerun_after_interrupted_job_does_only_the_missing(
    ray_local, recordings, local_out, tmp_path
):
    """A job interrupted as a kill leaves it, laid out without timing: a finished job's output
    with the summary gone and only some recordings' markers left (one recording's whole file
    without its marker: a task killed between its writes and its marker; another's file gone).
    The rerun filters exactly the recordings without a marker, rewrites none of the others, and
    ends byte-identical to the local run. (The kill itself: the slow test below.)"""
    out = tmp_path / "ray"
    filter_recordings_ray(SYSTEM, recordings, out, smooth=True, batch_size=3, progress=False)
    (out / "filter_summary.json").unlink()
    done = out / DONE_DIR
    names = sorted(
        p.relative_to(done).as_posix().removesuffix(".json") for p in done.rglob("*.json")
    )
    lost = names[1::3]  # in several batches and both folders, not the first recording
    for name in lost:
        (done / f"{name}.json").unlink()
    (out / f"{lost[0]}.filtered.csv").unlink()
    (out / f"{lost[0]}.smoothed.csv").unlink()
    complete = [name for name in names if name not in lost]
    before = {name: (out / f"{name}.filtered.csv").stat().st_ino for name in complete}
    res = filter_recordings_ray(
        SYSTEM, recordings, out, smooth=True, batch_size=3, progress=False
    )  # fmt: skip
    d = res["distributed"]
    assert d["complete_before"] == len(complete) == len(recordings) - len(lost)
    assert d["filtered"] == len(lost)
    for name in complete:  # not written again (same inode: no replace)
        assert (out / f"{name}.filtered.csv").stat().st_ino == before[name]
    assert (out / "filter_summary.json").is_file()
    assert _files(out) == _files(local_out)


@pytest.mark.slow
def test_rerun_after_a_killed_worker_does_only_the_missing(ray_local, tmp_path):
    """The same after a real SIGKILL of a worker mid-job (slow: whether the kill lands before
    the job ends depends on the machine's load; the deterministic test above covers the rerun)."""
    recs = _long_recordings(tmp_path / "data")
    local = tmp_path / "local"
    filter_recordings("system:reentry", recs, local, batch_size=2)
    out = tmp_path / "ray"
    killer = _Killer(out, after=2)
    killer.start()
    try:
        with pytest.raises(RunError, match="run the same command again"):
            filter_recordings_ray(
                "system:reentry", recs, out, batch_size=2, max_retries=0, progress=False
            )
    finally:
        killer.stop = True
        killer.join()
    assert killer.killed is not None
    assert not (out / "filter_summary.json").exists()
    complete = sorted(p.name for p in (out / DONE_DIR).glob("*.json"))
    assert 2 <= len(complete) < len(recs)
    # a killed task may have left whole files without a marker: they count as not done
    before = {p.name: p.stat().st_ino for p in out.glob("*.filtered.csv")}
    res = filter_recordings_ray("system:reentry", recs, out, batch_size=2, progress=False)
    d = res["distributed"]
    assert d["complete_before"] == len(complete)
    assert d["filtered"] == len(recs) - len(complete)
    # the complete recordings' files were not written again (same inode: no replace)
    for m in complete:
        name = m.removesuffix(".json") + ".filtered.csv"
        assert (out / name).stat().st_ino == before[name]
    assert _files(out) == _files(local)


def test_other_job_in_out_is_refused(ray_local, recordings, tmp_path):
    out = tmp_path / "ray"
    filter_recordings_ray(SYSTEM, recordings[:3], out, batch_size=3, progress=False)
    with pytest.raises(OutputError, match="another filter job"):
        filter_recordings_ray(SYSTEM, recordings[:3], out, batch_size=2, progress=False)
    res = filter_recordings_ray(SYSTEM, recordings[:3], out, batch_size=2, force=True)
    assert res["distributed"]["filtered"] == 3
    # outputs of a local run are not overwritten without force
    loc = tmp_path / "loc"
    filter_recordings(SYSTEM, recordings[:3], loc)
    with pytest.raises(OutputError, match="exists and would be overwritten"):
        filter_recordings_ray(SYSTEM, recordings[:3], loc, progress=False)
    assert not (loc / JOB_FILE).exists()


def test_cli_filter_ray(ray_local, recordings, local_out, tmp_path, capsys):
    out = tmp_path / "cli"
    args = ["filter", *map(str, recordings), "--model", SYSTEM, "--out", str(out), "--smooth"]
    assert main([*args, "--ray", "--batch-size", "3"]) == 0
    assert "already complete" in capsys.readouterr().out
    assert _files(out) == _files(local_out)
    assert main([*args, "--batch-size", "0", "--ray"]) == 2
    assert "(--batch-size) must be a positive integer" in capsys.readouterr().err


def test_train_ray_two_recipes(ray_local, tmp_path):
    data = tiny_dataset(tmp_path / "data", recordings=4, steps=20)
    ra = write_recipe(tmp_path / "a.toml", data, iters=2, cal_iters=2)
    rb = write_recipe(tmp_path / "b.toml", data, iters=3, cal_iters=2)
    ra.write_text(ra.read_text().replace('name = "tiny"', 'name = "a"'))
    rb.write_text(rb.read_text().replace('name = "tiny"', 'name = "b"'))
    stream = io.StringIO()
    bundles = train_recipes_ray([ra, rb], tmp_path / "runs", stream=stream)
    assert set(bundles) == {"a", "b"}
    for name, b in bundles.items():
        assert b == (tmp_path / "runs" / name / "model.pt").resolve()
        assert b.is_file() and (b.parent / "config.json").is_file()
    with pytest.raises(RunError, match="already holds a run"):
        train_recipes_ray([ra, rb], tmp_path / "runs", stream=stream)
    # resume of finished runs trains nothing again and returns the same bundles
    again = train_recipes_ray([ra, rb], tmp_path / "runs", resume=True, stream=stream)
    assert again == bundles


def test_train_ray_one_recipe_over_datasets(ray_local, tmp_path, capsys):
    d1 = tiny_dataset(tmp_path / "unit1", recordings=4, steps=20)
    simulate_dataset("reaction", tmp_path / "unit2", recordings=4, steps=20, seed=5)
    recipe = write_recipe(tmp_path / "r.toml", d1, iters=2, cal_iters=2)
    argv = ["train", str(recipe), "--out", str(tmp_path / "runs"), "--ray"]
    argv += ["--dataset", str(d1), "--dataset", str(tmp_path / "unit2")]
    assert main(argv) == 0
    assert "model bundle (unit2)" in capsys.readouterr().out
    for unit in ("unit1", "unit2"):
        assert (tmp_path / "runs" / unit / "model.pt").is_file()
    cfg1 = (tmp_path / "runs" / "unit1" / "dataset.json").read_text()
    cfg2 = (tmp_path / "runs" / "unit2" / "dataset.json").read_text()
    assert cfg1 != cfg2  # each unit trained on its own data
    assert main(["train", str(recipe), str(recipe), "--out", str(tmp_path / "x")]) == 2
    assert "add --ray" in capsys.readouterr().err


def test_import_torchfilt_does_not_import_ray():
    code = "import sys, torchfilt, torchfilt.pipeline; print('ray' in sys.modules)"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == "False"


def test_without_ray_says_how_to_install(tmp_path, recordings, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(MissingDependencyError, match=r"pip install 'torchfilt\[distributed\]'"):
        filter_recordings_ray(SYSTEM, recordings, tmp_path / "o")
    argv = ["filter", str(recordings[0]), "--model", SYSTEM, "--out", str(tmp_path / "o")]
    assert main([*argv, "--ray"]) == 2
    assert "torchfilt[distributed]" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_fleet_example_small(ray_local, tmp_path):
    """The fleet example end to end on 200 units: every unit filtered once, the error grows with
    the unit's distance from the nominal parameter, and a re-run resumes (filters nothing)."""
    import json

    from script_support import load_script

    fleet = load_script("fleet_example")
    argv = ["--units", "200", "--steps", "40", "--batch-size", "64", "--out", str(tmp_path)]
    assert fleet.main(argv) == 0
    s = json.loads((tmp_path / "fleet_summary.json").read_text())
    assert s["ray"]["filtered"] == 200 and s["ray"]["complete_before"] == 0
    assert (tmp_path / "fleet_errors.png").stat().st_size > 10_000
    bins = s["by_k1_deviation"]
    assert sum(b["units"] for b in bins) == 200
    assert bins[0]["nees_median"] < bins[-1]["nees_median"]
    assert fleet.main(argv) == 0
    again = json.loads((tmp_path / "fleet_summary.json").read_text())
    assert again["ray"]["filtered"] == 0 and again["ray"]["complete_before"] == 200
    assert again["fleet"] == s["fleet"]
