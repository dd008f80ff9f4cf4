"""A live run directory is detected (issue 24 item 9): a second ``torchfilt train`` into a folder
that another process is writing is refused (one line, exit 2, naming the folder and the pid),
with or without --resume / --force; a run whose process was killed still resumes."""

from __future__ import annotations

import os
import signal

import pytest
from lock_support import hold_in_subprocess
from run_support import tiny_dataset, write_recipe

from torchfilt.cli import main
from torchfilt.exceptions import RunError
from torchfilt.io.lock import LOCK_NAME
from torchfilt.pipeline import train_recipe

pytestmark = pytest.mark.skipif(os.name != "posix", reason="fcntl locks are POSIX")


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny recipe and a finished run of it."""
    root = tmp_path_factory.mktemp("lock")
    recipe = write_recipe(root / "tiny.toml", tiny_dataset(root / "data"), iters=2, cal_iters=2)
    out = root / "run"
    train_recipe(recipe, out, progress=False)
    return recipe, out


@pytest.mark.parametrize("flag", [[], ["--resume"], ["--force"]])
def test_train_into_a_directory_another_process_writes_is_refused(trained, flag, capsys) -> None:
    recipe, out = trained
    before = sorted(p.name for p in out.iterdir())
    proc = hold_in_subprocess(out)
    try:
        capsys.readouterr()
        assert main(["train", str(recipe), "--out", str(out), *flag]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1, err
        assert str(out) in err[0] and f"pid {proc.pid}" in err[0]
        assert "another process" in err[0] and "--resume" not in err[0]
        with pytest.raises(RunError, match=f"pid {proc.pid}"):
            train_recipe(recipe, out, resume=True, progress=False)
    finally:
        proc.communicate("")
    assert sorted(p.name for p in out.iterdir()) == before  # nothing touched, --force included


def test_a_killed_run_still_resumes(trained) -> None:
    """The run's process died holding the lock (SIGKILL: the lock file stays, naming a dead
    pid): --resume takes the lock over and finishes, and releases it."""
    recipe, out = trained
    proc = hold_in_subprocess(out)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()  # reaps it and closes its pipes
    assert (out / LOCK_NAME).exists()
    assert main(["train", str(recipe), "--out", str(out), "--resume"]) == 0
    assert not (out / LOCK_NAME).exists()
    assert (out / "model.pt").is_file()
