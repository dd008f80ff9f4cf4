"""A frozen-predictor cache that is not one is refused with an ``InputError`` (a ``ValueError``)
naming the argument and the entry."""

import pytest

from torchfilt.exceptions import InputError
from torchfilt.models.gp.predictor import CACHE_FORMAT, FrozenGP


def _block(**kw):
    return {
        "class": "independent",
        "kernel": "rbf",
        "form": "exact",
        "rank": None,
        "args": {},
        **kw,
    }


@pytest.mark.parametrize(
    ("cache", "message"),
    [
        ({}, r"cache: not a frozen-predictor cache \(torchfilt\.frozen/1\)"),
        ({"format": "other"}, r"cache: not a frozen-predictor cache"),
        (
            {"format": CACHE_FORMAT, "blocks": [_block(form="dense")]},
            r"cache: blocks\[0\]: unknown variance form 'dense'",
        ),
        (
            {"format": CACHE_FORMAT, "blocks": [_block(form="lowrank", **{"class": "mixed"})]},
            r"cache: blocks\[0\]: unknown block class 'mixed'",
        ),
    ],
)
def test_bad_cache_is_an_input_error(cache, message):
    with pytest.raises(InputError, match=message) as info:
        FrozenGP.from_cache(cache)
    assert isinstance(info.value, ValueError)
