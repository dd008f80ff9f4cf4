"""The ``torchfilt`` command line: train, filter, evaluate, simulate, info.

Each command is a thin layer over its Python twin in :mod:`torchfilt.pipeline` /
:mod:`torchfilt.training`. Errors in the user's input (bad files, shapes, options, an output that
exists or cannot be written) are ``TorchfiltError`` subclasses: they are reported
in one line on stderr with exit status 2 (``--debug`` shows the traceback). Any other exception is
a bug and keeps its traceback. No command overwrites a file it did not create unless ``--force``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torchfilt.exceptions import InputError, TorchfiltError

__all__ = ["main"]


def _simulate(args: argparse.Namespace) -> int:
    from torchfilt.io.synth import simulate_dataset

    m = simulate_dataset(
        args.system,
        args.out,
        recordings=args.recordings,
        steps=args.steps,
        seed=args.seed,
        missing=args.missing,
        fmt=f".{args.format}",
        force=args.force,
    )
    counts = {s: sum(r.split == s for r in m.recordings) for s in ("train", "validation", "test")}
    print(f"wrote {len(m.recordings)} recordings of {args.system} to {args.out} ({counts})")
    return 0


def _filter(args: argparse.Namespace) -> int:
    import torch

    from torchfilt.pipeline import check_device, filter_recordings

    dtype = torch.float32 if args.float32 else torch.float64
    if args.ray is None:
        if args.workers is not None:
            raise InputError("--workers sets the CPUs of a local Ray instance: use it with --ray")
        device = args.device or "cpu"
        check_device(device)  # before anything is loaded
        summary = filter_recordings(
            args.model,
            args.recordings,
            args.out,
            smooth=args.smooth,
            plot=args.plot,
            device=device,
            dtype=dtype,
            sqrt=args.sqrt,
            force=args.force,
            batch_size=args.batch_size,
        )
    else:
        from torchfilt.pipeline.distributed import filter_recordings_ray
        from torchfilt.settings import RAY_BATCH_SIZE

        summary = filter_recordings_ray(
            args.model,
            args.recordings,
            args.out,
            address=args.ray,
            workers=args.workers,
            batch_size=RAY_BATCH_SIZE if args.batch_size is None else args.batch_size,
            smooth=args.smooth,
            plot=args.plot,
            device=args.device or "auto",
            dtype=dtype,
            sqrt=args.sqrt,
            force=args.force,
        )
        d = summary["distributed"]
        print(
            f"ray: filtered {d['filtered']} recordings in {d['tasks']} tasks; "
            f"{d['complete_before']} were already complete"
        )
    for e in summary["recordings"]:
        met = e.get("filtered_metrics") or {}
        extra = f", NEES {met['nees']:.3g}" if met else ""
        nis = (
            ""
            if e["mean_nis"] is None
            else f", mean NIS {e['mean_nis']:.3g} (dof {e['mean_nis_dof']:.2g})"
        )
        status = "" if e["finite"] else " (diverged: non-finite estimates)"
        print(
            f"{Path(e['recording']).name}: {e['rows']} rows{nis}{extra} -> {e['filtered']}{status}"
        )
    print(f"wrote estimates to {args.out}")
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from torchfilt.pipeline import evaluate_outputs

    res = evaluate_outputs(
        args.dir, which="smoothed" if args.smoothed else "filtered", force=args.force
    )
    pooled = res["pooled"]
    print(f"{res['which']} estimates, {len(res['recordings'])} recordings, {pooled['steps']} steps")
    cov_key = next(k for k in pooled if k.startswith("coverage"))
    for i, s in enumerate(res["states"]):
        print(f"  {s:>20}: RMSE {pooled['rmse'][i]:.4g}, {cov_key} {pooled[cov_key][i]:.1%}")
    print(f"  mean NEES {pooled['nees']:.3g} (consistent: {pooled['nees_expected']})")
    return 0


def _train(args: argparse.Namespace) -> int:
    if args.data_parallel is not None:
        return _train_data_parallel(args)
    if args.ray is None:
        if len(args.recipe) > 1 or args.dataset:
            raise InputError(
                "several recipes or --dataset train several models: add --ray to run them as "
                "parallel tasks"
            )
        if args.workers is not None:
            raise InputError("--workers sets the CPUs of a local Ray instance: use it with --ray")
        from torchfilt.pipeline import train_recipe

        bundle = train_recipe(
            args.recipe[0], args.out, resume=args.resume, force=args.force, progress=not args.quiet
        )
        print(f"model bundle: {bundle}")
        return 0
    from torchfilt.pipeline.distributed import train_recipes_ray

    bundles = train_recipes_ray(
        args.recipe,
        args.out,
        datasets=args.dataset,
        address=args.ray,
        workers=args.workers,
        resume=args.resume,
        force=args.force,
    )
    for name, b in bundles.items():
        print(f"model bundle ({name}): {b}")
    return 0


def _train_data_parallel(args: argparse.Namespace) -> int:
    """``torchfilt train RECIPE --ray [ADDRESS] --data-parallel N``: one recipe, its likelihood
    stages on N Ray actors."""
    n = args.data_parallel
    if n < 1:
        raise InputError(f"--data-parallel must be a positive integer (actors), got {n}")
    if args.ray is None:
        raise InputError(
            "--data-parallel runs the likelihood stages on Ray actors: use it with --ray [ADDRESS]"
        )
    if len(args.recipe) > 1 or args.dataset:
        raise InputError(
            "--data-parallel trains one recipe on its own dataset: give one recipe and no "
            "--dataset (several units train as parallel tasks with --ray alone)"
        )
    from torchfilt.pipeline.distributed import train_recipe_data_parallel

    bundle = train_recipe_data_parallel(
        args.recipe[0],
        args.out,
        workers=n,
        address=args.ray,
        cpus=args.workers,
        resume=args.resume,
        force=args.force,
        progress=not args.quiet,
    )
    print(f"model bundle: {bundle}")
    return 0


def _add_ray(s: argparse.ArgumentParser, what: str) -> None:
    s.add_argument(
        "--ray",
        nargs="?",
        const="local",
        default=None,
        metavar="ADDRESS",
        help=f"{what} as Ray tasks: on a new local Ray instance, or on the cluster at ADDRESS "
        "(auto, host:6379, ray://host:10001); needs pip install 'torchfilt[distributed]'",
    )
    s.add_argument(
        "--workers", type=int, default=None, help="CPUs of the local Ray instance (default: all)"
    )


def _info(args: argparse.Namespace) -> int:
    from torchfilt.pipeline import resolve_model

    spec = resolve_model(args.model)
    print(f"model: {spec.source}")
    print(f"  states:       {', '.join(f'{n} [{u}]' if u else n for n, u in spec.states)}")
    print(f"  measurements: {', '.join(f'{n} [{u}]' if u else n for n, u in spec.measurements)}")
    print(f"  inputs:       {', '.join(n for n, _ in spec.inputs) or '(none)'}")
    print(f"  time column:  {spec.time_column}")
    print(f"  sample time:  {spec.sample_time}")
    print(f"  transition:   {type(spec.model.transition).__name__}")
    print(f"  measurement:  {type(spec.model.measurement).__name__}")
    mo = spec.info.get("measurement_only")
    if isinstance(mo, dict):
        print(
            f"  learned from: measurements alone (method {mo.get('method')}, known channels "
            f"{', '.join(map(str, mo.get('known_channels', [])))}, {mo.get('iterations')} "
            f"iterations, {_stop_words(mo.get('stopped'))}; log-likelihood "
            f"{float(mo.get('initial_log_likelihood', float('nan'))):.6g} -> "
            f"{float(mo.get('log_likelihood', float('nan'))):.6g})"
        )
        chosen = [c for c in mo.get("candidates") or [] if c.get("chosen")]
        if chosen:  # the start the fit kept, of the candidates scored
            c = chosen[0]
            print(
                f"  start:        candidate {c.get('candidate')} of {len(mo['candidates'])}, "
                f"{_start_words(c)}, {c.get('on')} log-likelihood {float(c['score']):.6g}"
            )
        for c in mo.get("compared") or []:  # method = "auto" or "both": both methods' scores
            score = c.get("score")
            what = (
                f"{c.get('basis')} log-likelihood {float(score):.6g}"
                if score is not None
                else f"not fitted ({c.get('error') or c.get('skipped')})"
            )
            print(
                f"  compared:     {c.get('method')}, {what}" + (", kept" if c.get("kept") else "")
            )
        if mo.get("measurement_R") is not None:
            print(f"  sensor noise: R learned with the transition, {mo['measurement_R']}")
    if spec.info:
        print(json.dumps(spec.info, indent=2, default=str))
    return 0


def _start_words(c: dict[str, Any]) -> str:
    """A ``states = "none"`` candidate start for a reader: ``pilot (process noise 10 x the
    default)`` or ``linear EM from N4SID (10 block rows, stabilised)``."""
    if c.get("start") == "pilot":
        return f"pilot (process noise {c.get('process_noise_scale')} x the default)"
    rows = c.get("block_rows")
    how = (
        ""
        if rows is None
        else f" ({rows} block rows" + (", stabilised)" if c.get("stabilised") else ")")
    )
    return f"{c.get('start')} from {c.get('from')}{how}"


def _stop_words(stopped: Any) -> str:
    """A fit's ``stopped`` for a reader: ``"iterations"`` is its budget."""
    return "stopped at its budget, not converged" if stopped == "iterations" else str(stopped)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="torchfilt", description="Cubature Kalman filtering with learned models."
    )
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("train", help="train a model from a recipe (trainers/*.toml)")
    s.add_argument("recipe", type=Path, nargs="+", help="recipe(s); several need --ray")
    s.add_argument(
        "--out",
        type=Path,
        required=True,
        help="run directory (with --ray: the folder of one run directory per unit)",
    )
    s.add_argument(
        "--dataset",
        type=Path,
        action="append",
        default=None,
        help="with --ray and one recipe: train it on this dataset too (repeat; one model each)",
    )
    s.add_argument(
        "--resume", action="store_true", help="continue from the last checkpoint in --out"
    )
    s.add_argument(
        "--force", action="store_true", help="discard the run already in --out and start afresh"
    )
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_ray(s, "train the units")
    s.add_argument(
        "--data-parallel",
        type=int,
        default=None,
        metavar="N",
        help="with --ray and one recipe: run its calibration and measurement-only stages "
        "data-parallel on N Ray actors (the recordings dealt among them)",
    )
    s.set_defaults(fn=_train)

    s = sub.add_parser("filter", help="filter (and smooth) recordings with a model")
    s.add_argument("recordings", nargs="+", type=Path, metavar="REC")
    s.add_argument("--model", required=True, help="model bundle (.pt) or system:NAME")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--smooth", action="store_true", help="also run the RTS smoother")
    s.add_argument("--plot", action="store_true", help="write a PNG report per recording")
    s.add_argument(
        "--device",
        default=None,
        help="torch device, e.g. cuda (default: cpu; with --ray: each task's GPU if it has one)",
    )
    s.add_argument("--sqrt", action="store_true", help="square-root CKF")
    s.add_argument("--float32", action="store_true", help="compute in float32")
    s.add_argument("--force", action="store_true", help="overwrite existing estimate files")
    s.add_argument(
        "--batch-size",
        type=int,
        default=None,
        help="most recordings per batch (default: all of one length; with --ray: "
        "settings.RAY_BATCH_SIZE per task)",
    )
    _add_ray(s, "filter the batches")
    s.set_defaults(fn=_filter)

    s = sub.add_parser(
        "evaluate", help="compare estimates with logged truth (RMSE, NEES, coverage)"
    )
    s.add_argument("dir", type=Path, help="output folder of torchfilt filter")
    s.add_argument("--smoothed", action="store_true", help="evaluate the smoothed estimates")
    s.add_argument("--force", action="store_true", help="overwrite an existing evaluation file")
    s.set_defaults(fn=_evaluate)

    s = sub.add_parser("simulate", help="write synthetic recordings from a built-in system")
    s.add_argument("system", help="reentry, pendulum, ...")
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--recordings", type=int, default=10)
    s.add_argument("--steps", type=int, default=None)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument(
        "--missing", type=float, default=0.0, help="probability a measurement is missing"
    )
    s.add_argument("--format", choices=["csv", "npz"], default="csv")
    s.add_argument("--force", action="store_true", help="replace an existing dataset in --out")
    s.set_defaults(fn=_simulate)

    s = sub.add_parser("info", help="describe a model bundle (or system:NAME)")
    s.add_argument("model")
    s.set_defaults(fn=_info)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``torchfilt`` command."""
    args = _parser().parse_args(argv)
    try:
        return int(args.fn(args))
    except TorchfiltError as e:
        if args.debug:
            raise
        msg = " ".join(str(e).split()) or type(e).__name__
        print(f"torchfilt {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"torchfilt {args.command}: interrupted", file=sys.stderr)
        return 130
