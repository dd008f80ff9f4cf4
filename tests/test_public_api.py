"""The public API: a small top level, DMC off it, and the names that left it still resolving for
one release with a DeprecationWarning that names their new home."""

import importlib
import subprocess
import sys

import pytest

import torchfilt

#: Every name removed from the top level, with the module it lives in now.
MOVED = sorted(torchfilt._MOVED.items())

#: The top level's ``__all__`` before it was curated (87 names).
OLD_ALL = set(
    (
        "AffineSensor Bounded Box BundleError CKF CalibratedModel CholeskyCovariance "
        "CholeskyJitterWarning ConditionalModel ConstrainedCKF ConstrainedInfo ConvergenceWarning "
        "DMCController DataError DiagonalCovariance DivergenceWarning FOPDT FilterResult FitState "
        "GPMeasurement GPModel GPTransition GaugeError GaussHermiteRule GaussianFilter IPDT "
        "InducingTransition InfeasibleError InputError LMGPredictor LeastSquaresResult "
        "LinearGaussianModel ModelError NotDetectableError NumericsWarning OpenLoopPredictor "
        "ParameterPosterior Positive Prediction RecipeError Recording RunError ScalarCovariance "
        "Sequences ShapeError SmootherResult SolverStatus SphericalRadialRule StateSpaceModel "
        "StepResponseModel TimeVarying TorchfiltError UncertainParameters UnscentedRule WorkerError "
        "__version__ bounded_least_squares calibrate coverage cubature dmc evaluate_outputs "
        "exceptions filter_recordings filters fit_em fit_likelihood fit_measurement_only "
        "load_bundle load_dataset load_model models nees nis numerics parameter_posterior "
        "read_recording rmse rts_smooth settings simulate simulate_dataset solve_dare "
        "steady_state_kalman systems train_recipe write_recording"
    ).split()
)

#: The light import: these are pulled in only by a name that needs them.
NOT_IMPORTED = (
    "torchfilt.dmc",
    "gpytorch",
    "matplotlib",
    "torchfilt.training",
    "torchfilt.pipeline",
)


def test_top_level_is_small():
    assert len(torchfilt.__all__) <= 40
    assert len(set(torchfilt.__all__)) == len(torchfilt.__all__)


@pytest.mark.parametrize("name", torchfilt.__all__)
def test_every_public_name_resolves(name):
    assert getattr(torchfilt, name) is not None


def test_dir_lists_the_curated_names_not_the_deprecated_ones():
    listed = dir(torchfilt)
    assert set(torchfilt.__all__) <= set(listed)
    assert {"models", "filters", "exceptions", "dmc", "training"} <= set(listed)
    assert not set(torchfilt._MOVED) & set(listed)


def test_every_name_of_the_old_top_level_still_resolves():
    """Each of the 87 names of the previous ``__all__`` is public, a sub-package, or deprecated."""
    lost = OLD_ALL - set(torchfilt.__all__) - set(torchfilt._SUBPACKAGES) - set(torchfilt._MOVED)
    assert not lost


def test_moved_names_have_left_the_top_level():
    for name, _ in MOVED:
        assert name not in torchfilt.__all__
        assert name not in vars(torchfilt), f"{name} is still a module global: it would not warn"


@pytest.mark.parametrize(("name", "home"), MOVED)
def test_moved_name_warns_and_returns_the_object_from_its_new_home(name, home):
    new = getattr(importlib.import_module(home), name)
    message = rf"torchfilt\.{name} is deprecated .* next release; use {home}\.{name}$"
    with pytest.warns(DeprecationWarning, match=message):
        old = getattr(torchfilt, name)
    assert old is new


def test_from_import_of_a_moved_name_warns_once():
    with pytest.warns(DeprecationWarning, match="use torchfilt.dmc.FOPDT") as record:
        from torchfilt import FOPDT
    assert FOPDT is importlib.import_module("torchfilt.dmc").FOPDT
    assert len([w for w in record if issubclass(w.category, DeprecationWarning)]) == 1


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'NoSuchName'"):
        torchfilt.NoSuchName  # noqa: B018


def test_import_torchfilt_stays_light():
    code = f"import sys, torchfilt; print([m for m in {NOT_IMPORTED!r} if m in sys.modules])"
    out = subprocess.run(
        [sys.executable, "-W", "error", "-c", code], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_dmc_is_reachable_lazily_and_by_import():
    import torchfilt.dmc

    assert torchfilt.dmc is sys.modules["torchfilt.dmc"]
    assert torchfilt.dmc.DMCController.__name__ == "DMCController"
    code = "import torchfilt; print(torchfilt.dmc.DMCController.__module__)"
    out = subprocess.run(
        [sys.executable, "-W", "error", "-c", code], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip().startswith("torchfilt.dmc")
