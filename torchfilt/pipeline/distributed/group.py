"""The group of Ray actors behind a data-parallel fit: one ``torch.distributed`` ``gloo``
process per actor, the driver that waits for them, and the errors of a lost actor."""

from __future__ import annotations

import os
import pickle
import sys
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from torchfilt.exceptions import InputError, MissingDependencyError, TorchfiltError, WorkerError
from torchfilt.optim import FitHooks
from torchfilt.pipeline.distributed.session import _free_address, import_ray, ray_session

__all__ = ["GROUP_TIMEOUT"]


def _shard_sequences(data: Any, rank: int, world: int) -> Any:
    """Recordings ``rank::world`` of a fit's data (any kind a fit's ``y`` accepts: a list of
    recordings, a :class:`~torchfilt.training.data.Sequences`, ...), as a ``Sequences``."""
    from torchfilt.training.data import Sequences

    seqs = _data(data)

    def part(v: Any) -> Any:
        return None if v is None else v[rank::world]

    return Sequences(part(seqs.y), part(seqs.u), seqs.x0, seqs.P0)


#: Seconds a collective of a data-parallel fit waits for the other actors by default.
GROUP_TIMEOUT = 1800.0
#: Seconds the driver waits, after a first actor failed, for the others to report theirs.
_FAILURE_GRACE = 10.0


def _fit_rank(rank: int, world: int, init: str, job: dict[str, Any]) -> dict[str, Any]:
    """One process of a data-parallel fit (``job["kind"]``): its shard, sums over ``gloo``."""
    import datetime

    import torch.distributed as dist

    from torchfilt.training.calibrate import calibrate
    from torchfilt.training.measurement_only import fit_measurement_only

    torch.set_num_threads(1)
    dist.init_process_group(
        "gloo",
        init_method=init,
        rank=rank,
        world_size=world,
        timeout=datetime.timedelta(seconds=float(job["timeout"])),
    )
    try:
        ckpt = job["checkpoint"]
        path = None if ckpt is None else Path(ckpt) / f"rank{rank}.ckpt"
        data = _shard_sequences(job["recordings"], rank, world)
        options = dict(job["options"])
        # each rank its own checkpoint file in the folder
        options["checkpoint"] = None if path is None else replace(options["checkpoint"], path=path)
        hooks = FitHooks(all_reduce=dist.all_reduce)
        if job["kind"] == "calibrate":
            res: Any = calibrate(job["model"], data, hooks=hooks, **options)
        else:
            res = fit_measurement_only(job["model"], data, hooks=hooks, **options)
    finally:
        dist.destroy_process_group()
    return {"result": res if rank == 0 else None}


def _packed(job: dict[str, Any], dumps: Any) -> tuple[list[str], bytes]:
    """A job as the actors receive it: the driver's ``sys.path`` and the job pickled (by
    ``dumps``, Ray's cloudpickle). Unpickling the job imports the modules of the model's
    functions (a recipe's own sensor, ``package.module:function``), which the actors find only
    on their own path: :func:`_unpacked` first adds the driver's folders that exist there."""
    return [p for p in sys.path if p], dumps(job)


def _unpacked(packed: tuple[list[str], bytes]) -> dict[str, Any]:
    """The job of :func:`_packed`, after adding to ``sys.path`` the driver's folders that exist
    on this machine (a local cluster, or a shared file system).

    Raises:
        MissingDependencyError: a module of the job cannot be imported here; the message names
            it and says how to make it importable on the workers.
    """
    paths, blob = packed
    for p in paths:
        if p not in sys.path and os.path.isdir(p):
            sys.path.append(p)
    try:
        job: dict[str, Any] = pickle.loads(blob)
    except ModuleNotFoundError as e:
        raise MissingDependencyError(
            f"the Ray workers cannot import module {e.name!r}, which the model uses (your own "
            "sensor's module?): install it where the workers run, or put its folder on their "
            "PYTHONPATH (for example ray.init(runtime_env={'env_vars': {'PYTHONPATH': ...}}))"
        ) from None
    return job


def _data(recordings: Any) -> Any:
    """A group's data as a :class:`~torchfilt.training.data.Sequences`."""
    from torchfilt.training.data import as_sequences

    return as_sequences(recordings, name="recordings")


def _check_timeout(timeout: float) -> float:
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)):
        raise InputError(f"timeout must be a number of seconds, got {timeout!r}")
    if not (timeout > 0 and timeout < float("inf")):
        raise InputError(f"timeout must be a positive finite number of seconds, got {timeout}")
    return float(timeout)


def _run_group(
    caller: str,
    kind: str,
    model: Any,
    recordings: Any,
    options: dict[str, Any],
    workers: int,
    address: str | None,
    checkpoint: str | Path | None,
    timeout: float,
    callback_on: str = "actors",
) -> Any:
    """Run a data-parallel fit on ``workers`` Ray actors in one ``gloo`` group; actor 0's result.

    The driver waits for the actors one at a time: at the first failure it gives the others a
    few seconds to report theirs (an actor whose peer died fails in its next collective, or after
    ``timeout``), stops them all, and raises: an actor's own
    :class:`~torchfilt.exceptions.TorchfiltError` if one raised one (a bad argument, a
    checkpoint of another fit), else a :class:`~torchfilt.exceptions.WorkerError` naming the
    rank that died, or the one still running when the others had given up waiting for it.

    With ``callback_on="driver"`` the driver also serves rank 0's callback states (a
    :class:`_Relay` actor passes them) by calling ``options["callback"]`` here."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError(f"workers must be a positive integer, got {workers!r}")
    if callback_on not in ("actors", "driver"):
        raise InputError(f"callback_on must be 'actors' or 'driver', got {callback_on!r}")
    timeout = _check_timeout(timeout)
    on_driver = options["callback"] if callback_on == "driver" else None
    count = len(_data(recordings).y)
    if workers > count:
        raise InputError(f"workers: {workers} workers for {count} recordings; use at most {count}")
    if checkpoint is not None:
        Path(checkpoint).mkdir(parents=True, exist_ok=True)
    job = {
        "kind": kind,
        "model": model,
        "recordings": recordings,
        "options": options,
        "checkpoint": None if checkpoint is None else str(Path(checkpoint).resolve()),
        "timeout": timeout,
    }
    with ray_session(address) as ray:
        total = int(ray.cluster_resources().get("CPU", 0))
        if total < workers:
            raise InputError(
                f"workers: {workers} actors must run at once, but the Ray cluster has {total} CPUs"
            )
        actor = ray.remote(num_cpus=1, max_restarts=0, max_task_retries=0)(_Rank)
        ranks = [actor.remote() for _ in range(workers)]
        relay = None
        if on_driver is not None:
            # no CPU of its own: it only passes states, and the actors may take every CPU
            relay = ray.remote(num_cpus=0, max_concurrency=4, max_restarts=0)(_Relay).remote()
            job["options"] = {**options, "callback": _DriverCallback(relay)}
        try:
            init = ray.get(ranks[0].address.remote())
            ref = ray.put(_packed(job, ray.cloudpickle.dumps))
            refs = [a.run.remote(r, workers, init, ref) for r, a in enumerate(ranks)]
            rank_of = {r: i for i, r in enumerate(refs)}
            outs: dict[int, Any] = {}
            errors: dict[int, BaseException] = {}
            pending = list(refs)
            take = None if relay is None else relay.take.remote()
            while pending and not errors:
                ready, _ = ray.wait(pending if take is None else [*pending, take], num_returns=1)
                if take is not None and ready[0] == take:
                    seq, state = ray.get(take)
                    stop = on_driver(state)  # type: ignore[misc]  # an exception stops all
                    relay.answer.remote(seq, bool(stop))  # type: ignore[union-attr]
                    take = relay.take.remote()  # type: ignore[union-attr]
                    continue
                pending = [p for p in pending if p != ready[0]]
                _collect(ray, ready, rank_of, outs, errors)
            if errors and pending:
                ready, pending = ray.wait(
                    pending, num_returns=len(pending), timeout=min(_FAILURE_GRACE, timeout)
                )
                _collect(ray, ready, rank_of, outs, errors)
        finally:
            for a in [*ranks, *([] if relay is None else [relay])]:
                ray.kill(a)
    if errors:
        stuck = sorted(rank_of[r] for r in pending)
        raise _group_error(ray, caller, errors, stuck, workers, job["checkpoint"], timeout)
    return outs[0]["result"]


def _collect(
    ray: Any,
    ready: list[Any],
    rank_of: dict[Any, int],
    outs: dict[int, Any],
    errors: dict[int, BaseException],
) -> None:
    for r in ready:
        try:
            outs[rank_of[r]] = ray.get(r)
        except Exception as e:
            errors[rank_of[r]] = e


def _group_error(
    ray: Any,
    caller: str,
    errors: dict[int, BaseException],
    stuck: list[int],
    world: int,
    checkpoint: str | None,
    timeout: float,
) -> TorchfiltError:
    """The error a failed data-parallel job raises (see :func:`_run_group`): a rank's own
    TorchfiltError, else a WorkerError naming the rank that died, else the one still running
    when the others had failed (it did not reach a collective in time), else the one that
    failed."""
    causes = [getattr(errors[r], "cause", None) for r in sorted(errors)]
    own = [c for c in causes if isinstance(c, TorchfiltError)]
    # a rank's own error before one that only says another rank failed (``peer``)
    own.sort(key=lambda c: bool(getattr(c, "peer", False)))
    if own:
        return own[0]
    died = [r for r in sorted(errors) if isinstance(errors[r], ray.exceptions.RayActorError)]
    if died:
        what = f"rank {died[0]} of {world} was lost (its Ray actor died: process killed or exited)"
    elif stuck:
        first = min(errors)
        what = (
            f"rank {stuck[0]} of {world} did not reach a collective within timeout={timeout:g} s "
            f"(rank {first} stopped waiting: {_cause_line(errors[first])})"
        )
    else:
        rank = min(errors)
        what = f"rank {rank} of {world} failed ({_cause_line(errors[rank])})"
    if checkpoint is None:
        hint = (
            "no checkpoints were kept, so the fit must start again; pass checkpoint=DIR to be "
            "able to resume after a lost worker"
        )
    else:
        hint = (
            "run the same call again with checkpoint=CheckpointOptions(DIR, resume=True) to "
            f"continue from the checkpoints in DIR = {checkpoint} (every rank restarts from the "
            "latest iteration all of them saved)"
        )
    return WorkerError(f"{caller}: {what}; the other ranks were stopped; {hint}")


def _cause_line(e: BaseException) -> str:
    """An actor's exception in one short line: the original one Ray wraps, if any."""
    cause = getattr(e, "cause", None)
    err = cause if isinstance(cause, BaseException) else e
    text = " ".join(str(err).split())
    return f"{type(err).__name__}: {text[:200]}"


class _Rank:
    """A Ray actor of :func:`calibrate_ray` and :func:`fit_measurement_only_ray`."""

    def address(self) -> str:
        return _free_address()

    def run(
        self, rank: int, world: int, init: str, packed: tuple[list[str], bytes]
    ) -> dict[str, Any]:
        return _fit_rank(rank, world, init, _unpacked(packed))


class _Relay:
    """A Ray actor (threaded) that passes rank 0's callback states to the driver and the
    driver's answers back (``callback_on="driver"``): rank 0 calls :meth:`put`, which returns
    the driver's answer; the driver calls :meth:`take`, then :meth:`answer`."""

    def __init__(self) -> None:
        self._cv = threading.Condition()
        self._seq = 0
        self._waiting: tuple[int, Any] | None = None
        self._answers: dict[int, bool] = {}

    def put(self, state: Any) -> bool:
        with self._cv:
            self._seq += 1
            seq = self._seq
            self._waiting = (seq, state)
            self._cv.notify_all()
            self._cv.wait_for(lambda: seq in self._answers)
            return self._answers.pop(seq)

    def take(self) -> tuple[int, Any]:
        with self._cv:
            self._cv.wait_for(lambda: self._waiting is not None)
            item, self._waiting = self._waiting, None
            assert item is not None
            return item

    def answer(self, seq: int, stop: bool) -> None:
        with self._cv:
            self._answers[seq] = stop
            self._cv.notify_all()


class _DriverCallback:
    """The callback the actors get with ``callback_on="driver"``: rank 0 sends its state to the
    driver (through the :class:`_Relay`) and returns the driver's answer; the others do
    nothing (rank 0's ``True`` stops them all)."""

    def __init__(self, relay: Any) -> None:
        self.relay = relay

    def __call__(self, state: Any) -> bool | None:
        import torch.distributed as dist

        if dist.get_rank() != 0:
            return None
        return bool(import_ray().get(self.relay.put.remote(state)))
