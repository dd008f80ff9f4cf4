"""Training recipes: TOML files in ``trainers/`` that say what to train on and how.

A recipe names the dataset, the model of each side (a GP with its options, or a built-in analytic
model), the optimiser and iterations, checkpointing, and the seed::

    name = "reentry"
    seed = 0

    [dataset]
    path = "../data/reentry"           # relative to the recipe file

    [transition]                       # GPTransition.fit options
    increment = true
    inputs = ["altitude", "velocity", "ballistic"]
    iterations = 150

    [measurement]                      # GPMeasurement.fit options
    inputs = ["altitude"]              # input selection by channel name
    iterations = 150

    [train]
    checkpoint_every = 25

A side may instead be a built-in model: ``[measurement] model = "system:reentry"``. A GP's
``prior_mean`` is a built-in nominal model: ``prior_mean = {system = "reentry", gamma = 4e-5}``.
Unknown keys are errors (a typo must not silently train a different model).
"""

from __future__ import annotations

import copy
import hashlib
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchfilt.exceptions import RecipeError
from torchfilt.optim import field_docs
from torchfilt.pipeline.entry_point import is_entry_point
from torchfilt.pipeline.recipe_keys import Key, _file, digested
from torchfilt.pipeline.recipe_measurement_only import (
    MEASUREMENT_ONLY_DEFAULTS,
    check_learned_noise,
    complete,
)
from torchfilt.pipeline.recipe_options import OPTION_KEYS, fit_options, option_default

__all__ = [
    "CALIBRATE_DEFAULTS",
    "GP_OPTIONS",
    "MEASUREMENT_ONLY_DEFAULTS",
    "OPTION_KEYS",
    "RECIPE_SCHEMA",
    "Key",
    "Recipe",
    "RecipeError",
    "check_calibrate",
    "check_states",
    "fit_options",
    "load_recipe",
    "recipe_reference",
]

#: Kernels of the GP models (``torchfilt.models.gp.kernels.KERNELS``; a test keeps them equal).
KERNELS = ("rbf", "matern52", "matern32", "matern12")
#: Marks a key without a default (it must be given).
REQUIRED = "(required)"
#: Default ``[train] holdout``: the fraction held out for validation when the dataset has none.
HOLDOUT = 0.2
#: Values of the top-level ``states`` key.
STATES = ("logged", "none")


def _gp_keys(role: str) -> tuple[Key, ...]:
    """A GP side's keys: the keywords of ``GPTransition.fit`` or ``GPMeasurement.fit`` (by
    ``role``) and their defaults (a test keeps them the signatures'); ``lr``: ``optimizer=``'s."""
    keys = (
        Key(
            "model",
            "(a GP)",
            '`"system:NAME"`: use a built-in analytic model instead of a GP; in '
            '`[measurement]` also `"package.module:function"`: your own known sensor (with '
            "`R`); no other key is then allowed",
        ),
        Key(
            "kernel",
            '`"rbf"`',
            '`"rbf"` (ARD), `"matern52"`, `"matern32"` or `"matern12"`',
            kind="choice",
            choices=KERNELS,
        ),
        Key(
            "structure",
            '`"independent"`',
            '`"independent"` (one GP per output, batched), '
            '`"multitask"` (LMC, correlated outputs) or `"sparse"` (SVGP, minibatches)',
            kind="choice",
            choices=("independent", "multitask", "sparse"),
        ),
        Key(
            "increment",
            "`false`",
            "learn `x_{k+1} - x_k` instead of `x_{k+1}`",
            kind="bool",
        ),
        Key(
            "prior_mean",
            "(none)",
            "a built-in nominal model whose residual the GP learns: "
            '`{system = "NAME", parameter = value, ...}`',
        ),
        Key(
            "inputs",
            "(all)",
            "input selection by channel name (states, then inputs for the "
            "transition; states for the measurement), shared by all outputs or one list per "
            "output; integers index the same features",
        ),
        Key("noise", "(learned)", "fix the noise variance (scalar or one per output)"),
        Key(
            "noise_floor",
            '`"auto"`',
            "lower bound of the noise variance: from the data, or a "
            "variance (scalar or one per output)",
        ),
        Key("num_latents", "`1`", "number of latent GPs of a multitask model", kind="posint"),
        Key("task_rank", "`1`", "rank of each latent's task covariance (multitask)", kind="posint"),
        Key("num_inducing", "`256`", "inducing points per output (sparse)", kind="posint"),
        Key(
            "iterations",
            f"`{option_default('gp', 'iterations')}`",
            "Adam iterations",
            kind="posint",
        ),
        Key("lr", f"`{option_default('gp', 'lr')}`", "Adam learning rate", kind="posfloat"),
        Key(
            "natural_lr",
            "`0.1`",
            "natural-gradient step of a sparse model's `q(u)`",
            kind="posfloat",
        ),
        Key(
            "subset",
            "`1000`",
            "hyperparameters of an exact model are trained on at most this "
            "many random rows, then the GP conditions on all rows",
            kind="posint",
        ),
        Key("batch_size", "`1024`", "minibatch size (sparse)", kind="posint"),
        Key(
            "variance",
            '`"auto"`',
            'frozen predictive variance: `"auto"` (smallest low-rank root '
            'within `tol` of exact, else exact), `"exact"` or `"lowrank"`',
            kind="choice",
            choices=("auto", "exact", "lowrank"),
        ),
        Key("rank", "(none)", 'rank of the low-rank root (`variance = "lowrank"`)', kind="posint"),
        Key("tol", "`0.05`", 'relative variance tolerance of `variance = "auto"`', kind="posfloat"),
        Key("chunk_size", "(auto)", "points per kernel chunk in large batches", kind="posint"),
    )
    return tuple(k for k in keys if role == "transition" or k.name != "increment")


def _option_key(
    fit: str,
    key: str,
    kind: str,
    *,
    none: str = "",
    note: str = "",
    choices: tuple[str, ...] = (),
) -> Key:
    """The schema entry of option key ``key`` of fit ``fit``: its default from
    :data:`~torchfilt.optim.DEFAULTS` (``none``: how a default of ``None`` reads), its meaning
    from the field's docstring (and ``note``)."""
    v = option_default(fit, key)
    shown = none if v is None else (f'`"{v}"`' if isinstance(v, str) else f"`{v}`")
    cls, name = OPTION_KEYS[key]
    return Key(key, shown, field_docs(cls)[name] + note, kind=kind, choices=choices)


#: Every recipe section and key with its default and meaning: the validator's allowed keys and
#: the reference ``docs/recipes.md`` both come from this table (``""`` is the top level). A new
#: section is one more entry (and one more key in the top level).
RECIPE_SCHEMA: dict[str, tuple[Key, ...]] = {
    "": (
        Key("name", "(the file's stem)", "run name, stored in the bundle"),
        Key("description", '`""`', "free text, stored in the bundle"),
        Key(
            "seed",
            "`0`",
            "seed of every random choice (subsets, initial values, minibatches)",
            kind="int",
        ),
        Key(
            "states",
            '`"logged"`',
            '`"logged"`: learn from the recordings\' logged states; `"none"`: learn from the '
            "measurements and inputs alone (the training recordings' state columns are never "
            "read and may be absent or NaN; the transition is set in `[measurement_only]`, the "
            '`[measurement]` side must be a known `model = "system:NAME"` or your own sensor '
            '`"package.module:function"` (the gauge) and the `[filter]` prior `"system:NAME"` or '
            "`mean`/`cov_diag`)",
            kind="choice",
            choices=STATES,
        ),
        Key("dataset", REQUIRED, "table: the training data"),
        Key(
            "transition",
            REQUIRED,
            'table: the transition model `x_{k+1} = f(x_k, u_k)` (with `states = "none"`: '
            "absent or empty)",
        ),
        Key("measurement", REQUIRED, "table: the measurement model `y_k = h(x_k)`"),
        Key(
            "measurement_only",
            "(defaults)",
            'table: with `states = "none"`, the learned transition and how it is fitted',
        ),
        Key("train", "(defaults)", "table: checkpointing, dtype, threads"),
        Key("filter", "(defaults)", "table: the default filter prior stored in the bundle"),
        Key(
            "calibrate",
            "(defaults: on)",
            "table: the calibration stage (variance scales and noise floors fitted by the "
            "filter likelihood)",
        ),
    ),
    "dataset": (
        Key(
            "path",
            REQUIRED,
            "the dataset's `manifest.json` or its folder, relative to the recipe file",
        ),
    ),
    "transition": _gp_keys("transition"),
    "measurement": (
        *_gp_keys("measurement"),
        Key(
            "R",
            "(required with an entry point)",
            'with `model = "package.module:function"` (your sensor `h(x)` or `h(x, u)`, see '
            "`torchfilt.pipeline.entry_point`): its measurement noise, one variance per "
            "channel or the full matrix",
        ),
    ),
    "measurement_only": (
        Key(
            "method",
            '`"auto"`',
            '`"auto"`: EM, and the likelihood method too where EM stops with "no improvement", '
            'the better log-likelihood on the validation recordings kept; `"em"` '
            '(expectation-maximisation with the cubature RTS smoother); `"likelihood"` (the '
            'filter\'s innovation likelihood maximised directly); `"both"`: both from the same '
            "start, the better kept (the two fits' time); with `--ray --data-parallel` each "
            "method runs on the actors; see `torchfilt.fit_measurement_only`",
            kind="choice",
            choices=("em", "likelihood", "auto", "both"),
        ),
        _option_key("measurement_only", "iterations", "posint"),
        Key(
            "inducing",
            "`16`",
            "inducing points `M` of the `InducingTransition` (`0`: the linear part alone), "
            "placed on the states a pilot filter with the nominal (or random-walk) model "
            "estimates on the training recordings",
            kind="nonnegint",
        ),
        Key(
            "known_channels",
            "(all measurement channels)",
            "measurement channel names whose map is known (the gauge)",
        ),
        Key(
            "nominal",
            "(none: a random walk)",
            "a built-in nominal physics model under the learned transition: "
            '`{system = "NAME", parameter = value, ...}`',
        ),
        Key(
            "process_noise",
            "(1e-2 x the prior variances)",
            "initial diagonal of the learned process noise `Q` (scalar or one per state); also "
            "the initial GP output variance",
        ),
        _option_key(
            "measurement_only",
            "window",
            "posint",
            none="(whole recordings)",
            note=' (`"likelihood"` only)',
        ),
        _option_key("measurement_only", "burn_in", "nonnegint", note=' (`"likelihood"` only)'),
        _option_key(
            "measurement_only",
            "optimizer",
            "choice",
            note=' (`"likelihood"` only)',
            choices=("lbfgs", "adam"),
        ),
        _option_key(
            "measurement_only",
            "lr",
            "posfloat",
            none="(the optimiser's default)",
            note=' (`"likelihood"` only)',
        ),
        Key(
            "m_step_iterations",
            "`20`",
            'L-BFGS iterations per M-step (`"em"` only)',
            kind="posint",
        ),
        Key("compile", "`false`", "`torchfilt.fit_measurement_only(compile=...)`", kind="bool"),
        Key("accelerate", "`false`", 'SQUAREM cycles of the M-steps (`"em"` only)', kind="bool"),
        Key(
            "stable",
            "`false`",
            "the plant is known to be stable: the linear-EM start keeps only N4SID estimates "
            "with every pole inside the unit circle (an unstable one stabilised), and a start "
            "whose linear EM leaves the unit circle as it was before the EM (without it, the "
            "estimates as they come and stabilised compete by log-likelihood)",
            kind="bool",
        ),
        Key(
            "learn_measurement_noise",
            "`false`",
            "learn your own sensor's noise `R` with the transition, from its start `[measurement] "
            'R` (`model = "package.module:function"` only); the bundle keeps the learned `R`',
            kind="bool",
        ),
    ),
    "train": (
        Key(
            "checkpoint_every",
            "`25`",
            "iterations between checkpoints (a killed run resumes "
            "from the last one with `--resume`)",
            kind="posint",
        ),
        Key(
            "dtype",
            '`"float64"`',
            'training dtype: `"float64"` or `"float32"`',
            kind="choice",
            choices=("float64", "float32"),
        ),
        Key("threads", "(unchanged)", "torch threads for training", kind="posint"),
        Key(
            "holdout",
            "`0.2`",
            "without validation recordings in the dataset: the fraction held out for validation "
            "(early stopping, model selection, `validation.json`): whole recordings (the last "
            "`ceil(holdout x N)`) when there are at least 4, else the last part of each "
            "recording; the model is not refit on them. `0`: off (early stopping cannot act)",
        ),
    ),
    "filter": (
        Key(
            "prior",
            '`"data"`',
            '`"data"` (mean and covariance of the training recordings\' '
            'initial states) or `"system:NAME"` (a built-in system\'s prior)',
        ),
        Key("mean", "(none)", "explicit prior mean, one value per state (with `cov_diag`)"),
        Key("cov_diag", "(none)", "explicit prior variances, one per state (with `mean`)"),
    ),
    "calibrate": (
        Key(
            "enabled",
            "`true`",
            "after the GPs, fit per-output variance scales and diagonal noise floors of the "
            "learned sides by the filter's innovation likelihood on the training recordings "
            "(`torchfilt.calibrate`); `false` turns the stage off",
            kind="bool",
        ),
        Key(
            "sides",
            '`"learned"`',
            '`"learned"` (the GP sides) or a list of `"transition"` and/or `"measurement"`',
        ),
        _option_key("calibrate", "window", "posint"),
        _option_key("calibrate", "burn_in", "int"),
        _option_key("calibrate", "iterations", "posint"),
        _option_key("calibrate", "lr", "posfloat", note=" (at most 10)"),
        _option_key("calibrate", "optimizer", "choice", choices=("adam", "lbfgs")),
        _option_key("calibrate", "patience", "posint"),
        _option_key("calibrate", "atol", "nonnegfloat"),
        _option_key("calibrate", "per_iteration", "posint"),
        Key(
            "inflate_only",
            "`true`",
            "keep the variance scales >= 1: calibration only adds uncertainty",
            kind="bool",
        ),
        Key(
            "gp",
            '`"none"`',
            '`"none"`, `"noise"` (also refit the GP likelihood noises) or `"all"` (the noises, '
            "lengthscales and outputscales) of the calibrated GP sides by the same likelihood, "
            "through the frozen predictor's differentiable twin; the bundle then holds the "
            "refitted GPs (independent exact GPs only)",
            kind="choice",
            choices=("none", "noise", "all"),
        ),
    ),
}

#: Defaults of the ``[calibrate]`` section (those of its option keys from
#: ``DEFAULTS["calibrate"]``).
CALIBRATE_DEFAULTS: dict[str, Any] = {
    "enabled": True,
    "sides": "learned",
    **{k: option_default("calibrate", k) for k in OPTION_KEYS},
    "inflate_only": True,
    "gp": "none",
}

#: Keys added after recipes were first digested, by table: a run's digest holds them only when a
#: recipe sets them to something else than the default (:func:`~.recipe_keys.digested`).
_LATER_KEYS = {
    "calibrate": ("atol", "per_iteration"),
    "measurement_only": ("compile", "accelerate", "learn_measurement_noise", "stable"),
}


#: The GP options of a recipe: ``GPTransition.fit``'s keywords (``lr``: ``optimizer=``'s field).
GP_OPTIONS = frozenset(k.name for k in RECIPE_SCHEMA["transition"] if k.name != "model")


def _allowed(section: str) -> set[str]:
    return {k.name for k in RECIPE_SCHEMA[section]}


def _check_values(table: dict[str, Any], section: str, path: Path | None) -> None:
    keys = {k.name: k for k in RECIPE_SCHEMA[section]}
    for name, value in table.items():
        keys[name].check(value, section or "top level", path)


def recipe_reference() -> str:
    """The recipe reference (``docs/recipes.md``) as Markdown, from :data:`RECIPE_SCHEMA`."""
    out = [
        "# Recipe reference",
        "",
        "A recipe is a TOML file (see `trainers/`) that `torchfilt train` runs. Unknown keys are",
        "errors, so a typo never trains a different model silently. Channel names (`inputs`) and",
        "the `[filter]` prior are checked against the dataset before any training.",
        "",
        "This page is generated from `RECIPE_SCHEMA` in `torchfilt/pipeline/recipe.py`, the table",
        "the validator uses (`python scripts/make_docs.py` rewrites it; a test checks that the two",
        "agree).",
    ]
    for section, keys in RECIPE_SCHEMA.items():
        out += ["", "## Top level" if not section else f"## `[{section}]`", ""]
        out += ["| key | default | values | meaning |", "|---|---|---|---|"]
        out += [f"| `{k.name}` | {k.default} | {k.allowed} | {k.meaning} |" for k in keys]
    return "\n".join(out) + "\n"


@dataclass
class Recipe:
    """A parsed, validated recipe.

    Attributes:
        path: the recipe file (``None`` if built in code).
        name: run name.
        seed: random seed for every random choice.
        dataset: path of the dataset (manifest or folder), resolved.
        transition: GP options, or ``{"model": "system:NAME"}``.
        measurement: GP options, or ``{"model": "system:NAME"}``.
        checkpoint_every: iterations between checkpoints.
        dtype: training dtype name (``"float64"`` or ``"float32"``).
        threads: torch threads for training (``None``: leave as is).
        holdout: the fraction of the training data held out for validation when the dataset has
            no validation recordings (``0``: none; see :data:`RECIPE_SCHEMA`).
        filter: default filter prior for the bundle (``prior = "data"`` (default), ``"system:NAME"``,
            or explicit ``mean`` and ``cov_diag``).
        description: free text.
        calibrate: the ``[calibrate]`` section with its defaults filled in (see
            :data:`RECIPE_SCHEMA`).
        states: ``"logged"`` (learn from the logged states) or ``"none"`` (from measurements
            and inputs alone; see :func:`check_states`).
        measurement_only: with ``states = "none"``, the ``[measurement_only]`` section with its
            defaults filled in (:data:`MEASUREMENT_ONLY_DEFAULTS`); empty otherwise.
        given: the keys each section of the recipe file wrote (``None``: a recipe built in
            code); not part of :meth:`resolved`. A ``patience`` the recipe did not write is the
            fit's default (see :func:`fit_options`).
    """

    path: Path | None
    name: str
    seed: int
    dataset: Path
    transition: dict[str, Any]
    measurement: dict[str, Any]
    checkpoint_every: int = 25
    dtype: str = "float64"
    threads: int | None = None
    holdout: float = HOLDOUT
    filter: dict[str, Any] = field(default_factory=dict)
    description: str = ""
    calibrate: dict[str, Any] = field(default_factory=lambda: dict(CALIBRATE_DEFAULTS))
    states: str = "logged"
    measurement_only: dict[str, Any] = field(default_factory=dict)
    given: dict[str, frozenset[str]] | None = field(default=None, compare=False, repr=False)

    def resolved(self) -> dict[str, Any]:
        """The fully resolved configuration (what a run directory records). ``states`` and
        ``measurement_only`` appear only with ``states = "none"``, so the digests of recipes
        written before the option existed stay the same."""
        extra: dict[str, Any] = {}
        if self.states != "logged":
            extra = {
                "states": self.states,
                "measurement_only": digested(
                    self.measurement_only,
                    _LATER_KEYS["measurement_only"],
                    MEASUREMENT_ONLY_DEFAULTS,
                ),
            }
        return {
            **extra,
            "name": self.name,
            "description": self.description,
            "seed": self.seed,
            "dataset": str(self.dataset),
            "transition": copy.deepcopy(self.transition),
            "measurement": copy.deepcopy(self.measurement),
            "train": {
                "checkpoint_every": self.checkpoint_every,
                "dtype": self.dtype,
                "threads": self.threads,
                # only when set otherwise: the digests of earlier recipes stay the same
                **({} if self.holdout == HOLDOUT else {"holdout": self.holdout}),
            },
            "filter": copy.deepcopy(self.filter),
            # keys added later appear only when set otherwise (earlier digests stay the same)
            "calibrate": digested(self.calibrate, _LATER_KEYS["calibrate"], CALIBRATE_DEFAULTS),
        }

    def digest(self) -> str:
        """SHA-256 of the resolved configuration (identifies the recipe in a run directory)."""
        return hashlib.sha256(json.dumps(self.resolved(), sort_keys=True).encode()).hexdigest()


def _check_keys(
    table: Any, allowed: set[str] | frozenset[str], where: str, path: Path | None
) -> dict[str, Any]:
    if not isinstance(table, dict):
        raise RecipeError(f"{_file(path)}[{where}] must be a table")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise RecipeError(
            f"{_file(path)}unknown key(s) {unknown} in [{where}]; allowed: {sorted(allowed)}"
        )
    return dict(table)


def _side(table: Any, where: str, path: Path | None) -> dict[str, Any]:
    if table is None:
        raise RecipeError(f'{path}: missing [{where}] table (GP options, or model = "system:NAME")')
    if isinstance(table, dict) and "model" in table:
        ep = where == "measurement" and is_entry_point(table["model"])
        t = _check_keys(table, {"model", "R"} if ep else {"model"}, where, path)
        if not ep and not str(t["model"]).startswith("system:"):
            raise RecipeError(
                f'{path}: [{where}] model must be "system:NAME"'
                + (' or "package.module:function"' if where == "measurement" else "")
                + f", got {t['model']!r}"
            )
        return t
    if isinstance(table, dict) and "R" in table:
        raise RecipeError(
            f'{_file(path)}[{where}] R: only with model = "package.module:function" (your own '
            "sensor's noise); a GP side learns its noise"
        )
    t = _check_keys(table, _allowed(where) - {"model", "R"}, where, path)
    _check_values(t, where, path)
    pm = t.get("prior_mean")
    if pm is not None and (not isinstance(pm, dict) or "system" not in pm):
        raise RecipeError(
            f"{path}: [{where}] prior_mean must be a table with 'system' (and parameters)"
        )
    return t


def load_recipe(path: str | Path) -> Recipe:
    """Read and validate a recipe TOML file.

    Raises:
        RecipeError: a missing, non-TOML or invalid recipe (the message names file and key).
    """
    path = Path(path)
    if not path.is_file():
        raise RecipeError(f"{path}: recipe not found")
    try:
        d = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise RecipeError(f"{path}: not valid TOML ({e})") from None
    d = _check_keys(d, _allowed(""), "top level", path)
    ds = _check_keys(d.get("dataset", {}), _allowed("dataset"), "dataset", path)
    if "path" not in ds:
        raise RecipeError(f"{path}: [dataset] needs 'path'")
    train = _check_keys(d.get("train", {}), _allowed("train"), "train", path)
    filt = _check_keys(d.get("filter", {}), _allowed("filter"), "filter", path)
    _check_values(d, "", path)
    _check_values(train, "train", path)
    dtype = str(train.get("dtype", "float64"))
    every = int(train.get("checkpoint_every", 25))
    threads = None if train.get("threads") is None else int(train["threads"])
    holdout = train.get("holdout", HOLDOUT)
    if isinstance(holdout, bool) or not isinstance(holdout, int | float) or not 0 <= holdout <= 0.5:
        raise RecipeError(f"{path}: [train] holdout must be a number in [0, 0.5], got {holdout!r}")
    seed = int(d.get("seed", 0))
    states = str(d.get("states", "logged"))
    mo = _check_keys(
        d.get("measurement_only", {}), _allowed("measurement_only"), "measurement_only", path
    )
    _check_values(mo, "measurement_only", path)
    if states == "none":
        tr = _check_keys(d.get("transition", {}), _allowed("transition"), "transition", path)
        transition: dict[str, Any] = tr
    else:
        transition = _side(d.get("transition"), "transition", path)
    r = Recipe(
        path=path,
        name=str(d.get("name", path.stem)),
        seed=seed,
        dataset=(path.parent / str(ds["path"])).resolve(),
        transition=transition,
        measurement=_side(d.get("measurement"), "measurement", path),
        checkpoint_every=every,
        dtype=dtype,
        threads=threads,
        holdout=float(holdout),
        filter=filt,
        description=str(d.get("description", "")),
        calibrate=_calibrate(d.get("calibrate", {}), path),
        states=states,
        measurement_only=mo,
        given={
            "calibrate": frozenset(d.get("calibrate", {})),
            "measurement_only": frozenset(mo),
        },
    )
    try:
        check_states(r)
    except RecipeError as e:
        raise RecipeError(f"{path}: {e}") from None
    return r


def check_calibrate(r: Recipe) -> None:
    """Validate a :class:`Recipe`'s ``calibrate`` table and fill in its defaults, in place (for
    a recipe built in code; :func:`load_recipe` does it for a file): a partial table such as
    ``{"iterations": 20}`` gets the other keys' defaults.

    Raises:
        RecipeError: naming the key (without the file; the callers add it).
    """
    out = _calibrate(r.calibrate, None)
    r.calibrate.clear()
    r.calibrate.update(out)


def check_states(r: Recipe) -> None:
    """Check the ``states`` option against the rest of a recipe and, with ``states = "none"``,
    validate ``[measurement_only]`` and fill in its defaults (in place; idempotent). Runs when a
    recipe is loaded and again when a :class:`Recipe` built in code is trained.

    With ``states = "none"`` there are no logged states to fit GPs on, so: ``[transition]`` must
    be empty (the transition is the ``InducingTransition`` of ``[measurement_only]``), the
    ``[measurement]`` side must be a known ``model = "system:NAME"`` (the gauge: it pins the state
    coordinates), the ``[filter]`` prior cannot be ``"data"``, and ``[calibrate] gp`` must be
    ``"none"``.

    Raises:
        RecipeError: naming the table and key (without the file; the callers add it).
    """
    if r.states not in STATES:
        raise RecipeError(f'states must be "logged" or "none", got {r.states!r}')
    if r.states == "logged":
        if r.measurement_only:
            raise RecipeError(
                '[measurement_only] applies only with states = "none" (learning from '
                'measurements alone); remove the table or set states = "none"'
            )
        return
    if r.transition:
        raise RecipeError(
            f'[transition] {sorted(r.transition)}: with states = "none" there are no logged '
            "states to fit a GP transition on; the transition is the InducingTransition of "
            "[measurement_only] (method, iterations, inducing, nominal, ...): remove these keys"
        )
    if "model" not in r.measurement:
        raise RecipeError(
            '[measurement]: with states = "none" the measurement model must be known: give '
            '[measurement] model = "system:NAME" or "package.module:function" (your sensor, '
            "with R). A learned measurement GP has no training "
            "targets without logged states, and a known sensor model is the gauge that pins the "
            "state coordinates (without it every change of coordinates x -> T x fits equally well)"
        )
    f = r.filter
    prior = str(f.get("prior", "data"))
    if "mean" not in f and "cov_diag" not in f and not prior.startswith("system:"):
        if prior != "data":
            raise RecipeError(
                f"[filter] prior must be 'data', 'system:NAME' or mean/cov_diag, got "
                f"{f.get('prior')!r}"
            )
        raise RecipeError(
            f'[filter] prior = "{prior}": the prior "data" is the mean and covariance of the '
            'logged initial states, which states = "none" does not have; give prior = '
            '"system:NAME" or an explicit mean and cov_diag'
        )
    if r.calibrate.get("gp", "none") != "none":
        raise RecipeError(
            f'[calibrate] gp = "{r.calibrate["gp"]}" refits the hyperparameters of exact GP '
            'sides; the states = "none" transition is an InducingTransition fitted by '
            '[measurement_only]: use gp = "none"'
        )
    out = _measurement_only_options(r.measurement_only)
    check_learned_noise(out, r.measurement)
    r.measurement_only.clear()
    r.measurement_only.update(out)


def _measurement_only_options(table: dict[str, Any]) -> dict[str, Any]:
    """``[measurement_only]`` checked (keys, values, the options of its method) and completed
    with its defaults; a ``RecipeError`` names the key."""
    mo = _check_keys(table, _allowed("measurement_only"), "measurement_only", None)
    _check_values({k: v for k, v in mo.items() if v is not None}, "measurement_only", None)
    return complete(mo)


def _calibrate(table: Any, path: Path | None) -> dict[str, Any]:
    """Validate ``[calibrate]`` and fill in its defaults."""
    t = _check_keys(table, _allowed("calibrate"), "calibrate", path)
    _check_values(t, "calibrate", path)
    out = {**CALIBRATE_DEFAULTS, **t}
    sides = out["sides"]
    ok_sides = sides == "learned" or (
        isinstance(sides, list) and bool(sides) and set(sides) <= {"transition", "measurement"}
    )
    if not ok_sides:
        raise RecipeError(
            f'{_file(path)}[calibrate] sides must be "learned" or a list of "transition" and/or '
            f'"measurement", got {sides!r}'
        )
    if not 0 <= out["burn_in"] < out["window"]:
        raise RecipeError(
            f"{_file(path)}[calibrate] burn_in must be an integer in [0, window), got {out['burn_in']!r}"
        )
    if float(out["lr"]) > 10:
        raise RecipeError(
            f"{_file(path)}[calibrate] lr must be a number in (0, 10], got {out['lr']!r}"
        )
    out["lr"] = float(out["lr"])
    return out
