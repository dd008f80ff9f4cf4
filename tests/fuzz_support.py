"""Shared machinery of the hypothesis suites (tests/*/test_fuzz_*.py).

Every case calls a public entry point through :func:`attempt`. The contract it checks:

- the call raises a :class:`~torchfilt.exceptions.TorchfiltError` subclass (a refusal, counted), or
- it returns, and the case then checks the result against an independent reference or an
  invariant (never a silently wrong answer).

Any other exception (a crash inside torch or gpytorch, a bare ``ValueError``) propagates and fails
the test; so does a warning that is not a :class:`~torchfilt.exceptions.TorchfiltWarning`.

Each property runs twice: a short derandomised run in the default suite (a few seconds in all) and a
long one under ``@pytest.mark.slow`` (over 5,000 cases over all files). :data:`STATS` counts the
outcomes per entry point; ``pytest -m slow -s tests/*/test_fuzz_*.py`` prints them.
"""

from __future__ import annotations

import warnings
from collections import Counter, defaultdict
from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchfilt.exceptions import TorchfiltError, TorchfiltWarning

#: outcomes per entry point: "returned", "refused: <ErrorClass>"
STATS: defaultdict[str, Counter[str]] = defaultdict(Counter)


class Refused:
    """What :func:`attempt` returns when the entry point raised a TorchfiltError."""

    def __init__(self, error: TorchfiltError) -> None:
        self.error = error

    def __repr__(self) -> str:
        return f"Refused({type(self.error).__name__}: {self.error})"


def attempt(name: str, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple[Any, list[Any]]:
    """Call ``fn``; return ``(result or Refused, torchfilt warnings emitted)``.

    Raises:
        AssertionError: a warning that is not a TorchfiltWarning was emitted.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            out: Any = fn(*args, **kwargs)
        except TorchfiltError as exc:
            STATS[name][f"refused: {type(exc).__name__}"] += 1
            out = Refused(exc)
        else:
            STATS[name]["returned"] += 1
    foreign = [w for w in caught if not issubclass(w.category, TorchfiltWarning)]
    assert not foreign, (
        f"{name}: non-torchfilt warning {foreign[0].category.__name__}: {foreign[0].message}"
    )
    return out, [w for w in caught if issubclass(w.category, TorchfiltWarning)]


def _settings(examples: int) -> settings:
    return settings(
        max_examples=examples,
        derandomize=True,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
        print_blob=True,
    )


def property_tests(
    check: Callable[[st.DataObject], None], *, short: int, long: int
) -> tuple[Callable[..., None], Callable[..., None]]:
    """A short (default suite) and a long (``slow``) hypothesis test of ``check(data)``."""

    def run_short(data: st.DataObject) -> None:
        check(data)

    def run_long(data: st.DataObject) -> None:
        check(data)

    short_test = _settings(short)(given(st.data())(run_short))
    long_test = pytest.mark.slow(_settings(long)(given(st.data())(run_long)))
    return short_test, long_test


def print_stats() -> None:
    """Print the outcome counts (shown with ``pytest -s``)."""
    total = sum(sum(c.values()) for c in STATS.values())
    print(f"\nfuzz outcomes ({total} entry-point calls):")
    for name in sorted(STATS):
        parts = ", ".join(f"{k} {v}" for k, v in sorted(STATS[name].items()))
        print(f"  {name}: {parts}")
