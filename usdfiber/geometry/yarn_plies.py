"""Plies around the yarn centre (Zhao 2016 eq. 1; eqs. Y2 and Y6 of :mod:`usdfiber.geometry.yarn`).

Ply i of N sits at the angle phi_i(s) = 2 pi i / N + 2 pi T_ply s and the distance
d = R_ply / sin(pi / N) from the yarn centre (:func:`usdfiber.spec.yarn.ply_distance`).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from usdfiber.spec.yarn import YarnParams

__all__ = ["ply_angle", "ply_cross_section"]

_TWO_PI = 2.0 * math.pi


def ply_angle(params: YarnParams, ply: Any, s: Any) -> np.ndarray:
    """phi_i(s), eq. Y2."""
    return _TWO_PI * (np.asarray(ply) / params.plies + params.ply_twist * np.asarray(s))


def ply_cross_section(params: YarnParams, phi: np.ndarray, a: np.ndarray, b: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """c_i + Rot(phi) (a, b): yarn cross-section coordinates (eq. Y6)."""
    cp, sp = np.cos(phi), np.sin(phi)
    d = params.ply_distance
    return d * cp + a * cp - b * sp, d * sp + a * sp + b * cp
