"""The paper's benchmark plants: the Shell heavy-oil fractionator (time in minutes).

Control channels ``G^u`` (3 CVs x 3 MVs) and measured-disturbance channels ``G^v`` (3 x 2), spec
section 3 (Xie, Ding & Chen 2016, sec. 3; the model of Li & Ding 2015).
"""

from __future__ import annotations

from torchfilt.dmc.transfer import FOPDT, IPDT, TransferEntry

__all__ = ["integrating_fractionator", "shell_fractionator"]

Matrix = list[list[TransferEntry]]


def shell_fractionator() -> tuple[Matrix, Matrix]:
    """Section 3.1: all CVs stable.

    Returns:
        ``(Gu, Gv)`` as nested lists of :class:`FOPDT` entries.
    """
    Gu: Matrix = [
        [FOPDT(4.05, 50, 27), FOPDT(1.77, 60, 28), FOPDT(5.88, 50, 27)],
        [FOPDT(5.39, 50, 18), FOPDT(5.72, 60, 14), FOPDT(6.90, 40, 15)],
        [FOPDT(4.38, 33, 20), FOPDT(4.42, 44, 22), FOPDT(7.20, 19, 0)],
    ]
    Gv: Matrix = [
        [FOPDT(1.20, 45, 27), FOPDT(1.44, 40, 27)],
        [FOPDT(1.52, 25, 15), FOPDT(1.83, 20, 15)],
        [FOPDT(1.14, 27, 0), FOPDT(1.26, 32, 0)],
    ]
    return Gu, Gv


def integrating_fractionator() -> tuple[Matrix, Matrix]:
    """Section 3.2: CVs 2 and 3 integrating (``K / (s (tau s + 1))``), CV 1 stable.

    Returns:
        ``(Gu, Gv)`` as nested lists of :class:`FOPDT` / :class:`IPDT` entries.
    """
    Gu: Matrix = [
        [FOPDT(4.05, 50, 27), FOPDT(1.77, 60, 28), FOPDT(5.88, 50, 27)],
        [IPDT(0.0539, 50, 18), IPDT(0.0572, 60, 14), IPDT(0.0690, 40, 15)],
        [IPDT(0.0438, 33, 20), IPDT(0.0442, 44, 22), IPDT(0.0720, 19, 0)],
    ]
    Gv: Matrix = [
        [FOPDT(1.20, 45, 27), FOPDT(1.44, 40, 27)],
        [IPDT(0.0152, 25, 15), IPDT(0.0183, 20, 15)],
        [IPDT(0.0114, 27, 0), IPDT(0.0126, 32, 0)],
    ]
    return Gu, Gv
