"""DirectoryLock: one writer per directory; a dead holder's lock is taken over (issue 24 item 9)."""

from __future__ import annotations

import os
import signal

import pytest
from lock_support import hold_in_subprocess

from torchfilt.exceptions import RunError, TorchfiltError
from torchfilt.io.lock import LOCK_NAME, DirectoryLock

pytestmark = pytest.mark.skipif(os.name != "posix", reason="fcntl locks are POSIX")


def test_second_lock_in_the_same_process_is_refused(tmp_path) -> None:
    with DirectoryLock(tmp_path):
        assert (tmp_path / LOCK_NAME).read_text().strip() == str(os.getpid())
        with pytest.raises(RunError, match=rf"pid {os.getpid()}\)"):
            DirectoryLock(tmp_path).acquire()
    assert not (tmp_path / LOCK_NAME).exists()
    with DirectoryLock(tmp_path):  # free again
        pass


def test_lock_held_by_another_process_is_refused_naming_dir_and_pid(tmp_path) -> None:
    proc = hold_in_subprocess(tmp_path)
    try:
        with pytest.raises(TorchfiltError) as info:
            DirectoryLock(tmp_path).acquire()
        message = str(info.value)
        assert str(tmp_path) in message and f"pid {proc.pid}" in message
    finally:
        proc.communicate("")  # closing stdin lets it release and exit
    assert proc.returncode == 0
    with DirectoryLock(tmp_path):
        pass


def test_lock_of_a_killed_holder_is_taken_over(tmp_path) -> None:
    proc = hold_in_subprocess(tmp_path)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()  # reaps it and closes its pipes
    assert (tmp_path / LOCK_NAME).read_text().strip() == str(proc.pid)  # stale file left
    with DirectoryLock(tmp_path) as lock:
        assert lock.path.read_text().strip() == str(os.getpid())
