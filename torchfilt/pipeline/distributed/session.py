"""The Ray session: importing Ray (an optional extra), opening a local instance or joining a
cluster, and the one-line reports of a failed task."""

from __future__ import annotations

import contextlib
import re
import socket
from collections.abc import Iterator
from typing import Any

from torchfilt.exceptions import InputError, MissingDependencyError, TorchfiltError

__all__ = ["INSTALL_HINT", "import_ray", "ray_session"]

#: How to install the optional dependency.
INSTALL_HINT = "pip install 'torchfilt[distributed]'"


def import_ray() -> Any:
    """The ``ray`` module.

    Raises:
        MissingDependencyError: Ray is not installed (the message says how to install it).
    """
    try:
        import ray
    except ImportError:
        raise MissingDependencyError(
            f"--ray: Ray is not installed; install it with {INSTALL_HINT}"
        ) from None
    return ray


@contextlib.contextmanager
def ray_session(address: str | None = None, *, workers: int | None = None) -> Iterator[Any]:
    """Use Ray inside this block: the session already open in this process if there is one, else
    a new local instance (``address`` ``None`` or ``"local"``, with ``workers`` CPUs: default all)
    or the cluster at ``address`` (``"auto"``, ``"ray://host:10001"``, ``"host:6379"``). A session
    this block opened is shut down at its end.

    Raises:
        MissingDependencyError: Ray is not installed.
        InputError: ``workers`` is not a positive integer, ``workers`` with a cluster address, or
            the cluster at ``address`` cannot be reached.
    """
    ray = import_ray()
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int)):
        raise InputError(f"--workers must be a positive integer, got {workers!r}")
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be a positive integer, got {workers}")
    if ray.is_initialized():
        yield ray
        return
    local = address in (None, "local")
    if not local and workers is not None:
        raise InputError(
            "--workers sets the CPUs of a local Ray instance; a cluster at --ray ADDRESS has its own"
        )
    if not local:
        _check_reachable(str(address))
    try:
        if local:
            ray.init(
                address="local",
                num_cpus=workers,
                include_dashboard=False,
                logging_level="warning",
                log_to_driver=False,
            )
        else:
            ray.init(address=address, logging_level="warning", log_to_driver=False)
    except (ConnectionError, ValueError, RuntimeError) as e:
        raise InputError(f"--ray {address}: cannot connect to a Ray cluster ({e})") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def _check_reachable(address: str) -> None:
    """A ``host:port`` address must accept a connection within a few seconds (Ray itself keeps
    retrying an unreachable one for minutes)."""
    m = re.fullmatch(r"([\w.\-]+):(\d+)", address)
    if m is None:
        return  # "auto", "ray://...": Ray reports these quickly itself
    try:
        with socket.create_connection((m.group(1), int(m.group(2))), timeout=5.0):
            pass
    except OSError as e:
        raise InputError(
            f"--ray {address}: no Ray cluster answers there ({e.strerror or e}); start one with "
            "`ray start --head` or check the address"
        ) from None


# ------------------------------------------------------------------------------------- filtering


def _one_line(e: BaseException) -> str:
    """A task's failure in one line: a TorchfiltError raised in the task by its own message
    (Ray wraps it, with the worker's traceback), anything else by its type and message."""
    cause = getattr(e, "cause", None)
    if isinstance(cause, TorchfiltError):
        return " ".join(str(cause).split())
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text[:300]}"


def _free_address() -> str:
    """``tcp://{this node}:{a free port}``: the rendezvous of a ``gloo`` process group."""
    ray = import_ray()
    with socket.socket() as s:
        s.bind(("", 0))
        port = s.getsockname()[1]
    return f"tcp://{ray.util.get_node_ip_address()}:{port}"
